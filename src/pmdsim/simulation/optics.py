"""Optics of the camera: defocus of the screen seen via the sample, and pixel-area integration.

Defocus (docs/conventions.md, "Image formation"). The camera is focused on the sample: all rays
from the entrance pupil (diameter D = f/N, in the camera's x–y plane at the pinhole) to a
pixel's sample point P reflect at P with the same normal, so the reflected bundle is the
mirrored incident cone continued a distance s₂ to the screen. To first order in the pupil
offset a (camera frame, |a| ≤ D/2, uniform), the screen point moves by

    δq = s₂ · M · H · δd,   δd = −(I − d dᵀ)·a / s₁,

with d, r the unit incident and reflected directions, s₁ = |P − O|, s₂ = |q − P|,
H = I − 2nnᵀ the reflection at P (n ∥ r − d) and M = I − r e_zᵀ / r_z the projection along r onto
the screen plane (screen frame, normal e_z). The footprint's covariance is therefore

    Σ = (D²/16) · (s₂/s₁)² · M H (I − d dᵀ) P_xy (I − d dᵀ) Hᵀ Mᵀ

(D²/16: the variance of a uniform disc of diameter D per axis; P_xy projects onto the pupil
plane). It is computed from the traced sample and screen points, no extra rays. A curved sample
changes s₂ and r over the image, and with them Σ. The blur is applied to each sinusoidal
harmonic analytically with the Gaussian of this covariance, whose transfer at period p is
exp(−2π²σ²/p²) (σ² the variance along the fringe axis): the modulation shrinks and the phase is
kept.

Pixel-area integration: a pixel integrates the pattern over its 1 × 1 px footprint; with the
local Jacobian J = ∂(x_q, y_q)/∂(u, v) (central differences of the traced mapping) a sinusoid of
period p along axis a is multiplied exactly (for a locally linear mapping) by
sinc(J_a,u/p)·sinc(J_a,v/p), sinc(x) = sin(πx)/(πx).
"""

from __future__ import annotations

import numpy as np

from ..geometry.transform import RigidTransform

__all__ = ["defocus_covariance", "pixel_jacobian", "view_geometry"]


def view_geometry(T_world_cam: RigidTransform, T_world_sample: RigidTransform, T_world_screen: RigidTransform,
                  p_sample_mm: np.ndarray, q_screen_mm: np.ndarray):
    """Incident and reflected unit directions and distances per pixel, in the screen frame.

    Parameters
    ----------
    p_sample_mm : ndarray (H, W, 3)
        Sample points in the sample frame (``Mapping.p_sample_mm``).
    q_screen_mm : ndarray (H, W, 3)
        Screen points in the screen frame (``Mapping.q_screen_mm``).

    Returns
    -------
    d, r : ndarray (H, W, 3)
        Unit directions camera → sample and sample → screen (screen frame).
    s1_mm, s2_mm : ndarray (H, W)
        Distances camera → sample and sample → screen (NaN where not traced).
    """
    T_screen_world = T_world_screen.inv()
    p = (T_screen_world @ T_world_sample).apply(p_sample_mm)
    o = T_screen_world.apply(T_world_cam.translation)
    dv = p - o
    s1 = np.linalg.norm(dv, axis=-1)
    rv = np.asarray(q_screen_mm) - p
    s2 = np.linalg.norm(rv, axis=-1)
    return dv / s1[..., None], rv / s2[..., None], s1, s2


def defocus_covariance(T_world_cam: RigidTransform, T_world_sample: RigidTransform, T_world_screen: RigidTransform,
                       p_sample_mm: np.ndarray, q_screen_mm: np.ndarray, aperture_mm: float) -> np.ndarray:
    """Covariance (mm², screen frame x, y) of the defocus footprint on the screen, (H, W, 2, 2).

    See the module docstring for the model; ``aperture_mm`` is the entrance-pupil diameter
    D = focal length / f-number. NaN where the pixel was not traced.
    """
    d, r, s1, s2 = view_geometry(T_world_cam, T_world_sample, T_world_screen, p_sample_mm, q_screen_mm)
    R_screen_cam = (T_world_screen.inv() @ T_world_cam).rotation
    ex, ey = R_screen_cam[:, 0], R_screen_cam[:, 1]  # the pupil plane's axes (screen frame)
    eye = np.eye(3)
    n = r - d
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    H = eye - 2.0 * n[..., :, None] * n[..., None, :]
    Pd = eye - d[..., :, None] * d[..., None, :]
    M = eye - r[..., :, None] * np.array([0.0, 0.0, 1.0])[None, :] / r[..., 2, None, None]
    A = np.einsum("...ij,...jk,...kl->...il", M, H, Pd)  # δq / s₂ per unit δd
    # Columns: the images of the pupil axes; Σ = c · Σ_axes (A e)(A e)ᵀ.
    ax = A @ ex
    ay = A @ ey
    c = (aperture_mm**2 / 16.0) * (s2 / s1) ** 2
    cov = c[..., None, None] * (ax[..., :2, None] * ax[..., None, :2] + ay[..., :2, None] * ay[..., None, :2])
    return cov


def pixel_jacobian(screen_xy_mm: np.ndarray) -> np.ndarray:
    """∂(x_q, y_q)/∂(u, v) per pixel, (H, W, 2, 2) (rows: x_q, y_q; columns: u, v), mm/px.

    Central differences where both neighbours are traced, one-sided where only one is, 0 where
    none is (no pixel-area attenuation there).
    """
    xy = np.asarray(screen_xy_mm, dtype=float)
    J = np.zeros(xy.shape[:2] + (2, 2))
    for col, axis in ((0, 1), (1, 0)):  # u along columns (axis 1), v along rows (axis 0)
        fwd = np.full(xy.shape, np.nan)
        bwd = np.full(xy.shape, np.nan)
        sl_hi = [slice(None)] * 2
        sl_lo = [slice(None)] * 2
        sl_hi[axis] = slice(1, None)
        sl_lo[axis] = slice(None, -1)
        diff = xy[tuple(sl_hi)] - xy[tuple(sl_lo)]
        fwd[tuple(sl_lo)] = diff
        bwd[tuple(sl_hi)] = diff
        cen = 0.5 * (fwd + bwd)
        g = np.where(np.isfinite(cen), cen, np.where(np.isfinite(fwd), fwd, np.where(np.isfinite(bwd), bwd, 0.0)))
        J[..., :, col] = g
    return J
