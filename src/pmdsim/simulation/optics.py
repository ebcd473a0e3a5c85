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
plane), and to second order the footprint's centroid is offset from the chief ray's screen
point by the curvature of the central projection onto the oblique screen
(:func:`defocus_moments`), a phase bias ∝ D². Both are computed from the traced sample and
screen points, no extra rays. A curved sample
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

__all__ = ["defocus_moments", "defocus_covariance", "pixel_jacobian", "screen_normal", "view_geometry"]


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


def defocus_moments(T_world_cam: RigidTransform, T_world_sample: RigidTransform, T_world_screen: RigidTransform,
                    p_sample_mm: np.ndarray, q_screen_mm: np.ndarray, aperture_mm: float, screen_surface=None):
    """Covariance and centroid offset of the defocus footprint on the screen (screen frame x, y).

    A pupil point a (uniform on the disc of diameter D in the camera's x–y plane) sends its ray
    through the sample point P; its (unnormalised) direction P − O − a is linear in a, so after
    the reflection H the ray is r + ε with ε = −H·a/s₁, and it meets the screen plane (normal
    m, the local screen normal: e_z for a plane) at δq = s₂·(m·r)·[(r + ε)/(m·r + m·ε) − r/(m·r)].
    To second order in ε, with C = Cov(ε) = (D²/16)/s₁² · H (e_x e_xᵀ + e_y e_yᵀ) Hᵀ (e_x, e_y the
    pupil axes):

        Σ = s₂² · M C Mᵀ,                          M = I − r mᵀ / (m·r),
        E[δq] = s₂ · (r · mᵀCm / (m·r)² − C m / (m·r))

    (x, y components: the pattern coordinates on the local tangent plane), plus the lift of a
    curved screen over its tangent plane, ½·tr(KΣ) along the ray (K the height's Hessian).

    The centroid offset E[δq] — the central projection's curvature — is O(D²): it scales with
    1/N², points where the oblique reflected bundle meets the screen farther out, and shifts the
    fringe phase (the footprint is no longer centred on the chief ray).

    Returns
    -------
    cov_mm2 : ndarray (H, W, 2, 2)
    centroid_mm : ndarray (H, W, 2)
        NaN where the pixel was not traced.
    """
    d, r, s1, s2 = view_geometry(T_world_cam, T_world_sample, T_world_screen, p_sample_mm, q_screen_mm)
    R_screen_cam = (T_world_screen.inv() @ T_world_cam).rotation
    ex, ey = R_screen_cam[:, 0], R_screen_cam[:, 1]  # the pupil plane's axes (screen frame)
    eye = np.eye(3)
    n = r - d
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    H = eye - 2.0 * n[..., :, None] * n[..., None, :]
    hx = H @ ex
    hy = H @ ey
    C = ((aperture_mm**2 / 16.0) / s1**2)[..., None, None] * (hx[..., :, None] * hx[..., None, :]
                                                             + hy[..., :, None] * hy[..., None, :])
    mz = screen_normal(q_screen_mm, screen_surface)
    rz = np.sum(r * mz, axis=-1)
    M = eye - r[..., :, None] * mz[..., None, :] / rz[..., None, None]
    cov3 = (s2**2)[..., None, None] * np.einsum("...ij,...jk,...lk->...il", M, C, M)
    Cm = np.einsum("...ij,...j->...i", C, mz)
    mCm = np.sum(mz * Cm, axis=-1)
    centroid = s2[..., None] * (r * (mCm / rz**2)[..., None] - Cm / rz[..., None])
    cov = cov3[..., :2, :2]
    if screen_surface is not None:
        # The screen's curvature K (Hessian of its height) lifts the surface by ½·δqᵀKδq over
        # the tangent plane: the ray meets it λ = ½·δqᵀKδq / (n·r) further on (n = (−h_x, −h_y, 1)).
        K = screen_hessian(q_screen_mm, screen_surface)
        n_un = mz / mz[..., 2:3]
        lam = 0.5 * np.einsum("...ij,...ij->...", K, cov) / np.sum(n_un * r, axis=-1)
        centroid = centroid + lam[..., None] * r
    return cov, centroid[..., :2]


def defocus_covariance(T_world_cam: RigidTransform, T_world_sample: RigidTransform, T_world_screen: RigidTransform,
                       p_sample_mm: np.ndarray, q_screen_mm: np.ndarray, aperture_mm: float,
                       screen_surface=None) -> np.ndarray:
    """Covariance (mm², screen frame x, y) of the defocus footprint on the screen, (H, W, 2, 2)
    (:func:`defocus_moments`); ``aperture_mm`` is D = focal length / f-number."""
    return defocus_moments(T_world_cam, T_world_sample, T_world_screen, p_sample_mm, q_screen_mm, aperture_mm,
                           screen_surface)[0]


def screen_hessian(q_screen_mm: np.ndarray, screen_surface, step_mm: float = 1.0) -> np.ndarray:
    """Hessian of the screen height at the traced points, (H, W, 2, 2) 1/mm (central differences
    of the spline's analytic gradient over ±``step_mm``; 0 where not traced)."""
    q = np.asarray(q_screen_mm, dtype=float)
    out = np.zeros(q.shape[:-1] + (2, 2))
    ok = np.isfinite(q).all(-1)
    x, y = q[ok][:, 0], q[ok][:, 1]
    gx = (screen_surface.gradient(x + step_mm, y) - screen_surface.gradient(x - step_mm, y)) / (2 * step_mm)
    gy = (screen_surface.gradient(x, y + step_mm) - screen_surface.gradient(x, y - step_mm)) / (2 * step_mm)
    K = np.stack([gx, gy], axis=-1)  # K[i, j] = ∂(∂h/∂x_i)/∂x_j
    out[ok] = 0.5 * (K + np.swapaxes(K, -1, -2))
    return out


def screen_normal(q_screen_mm: np.ndarray, screen_surface=None) -> np.ndarray:
    """Unit normal of the screen at the traced points (screen frame), (H, W, 3); e_z for a
    plane (``screen_surface`` None) and where the point is not traced."""
    q = np.asarray(q_screen_mm, dtype=float)
    out = np.zeros(q.shape)
    out[..., 2] = 1.0
    if screen_surface is None:
        return out
    ok = np.isfinite(q).all(-1)
    nrm = np.asarray(screen_surface.normal(q[ok][:, 0], q[ok][:, 1]), dtype=float)
    out[ok] = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)  # (−h_x, −h_y, 1): z > 0
    return out


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
