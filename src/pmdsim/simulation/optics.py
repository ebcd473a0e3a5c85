"""Optics of the camera: defocus of the screen seen via the sample, and pixel-area integration.

Defocus (docs/conventions.md, "Image formation"; issue 20). A thin lens: the entrance pupil is a
uniform disc of diameter D = f/N in the camera's x–y plane, centred on the pinhole O, and there is
one plane of sharp focus perpendicular to the optical axis at the focus distance z_F. The pixel
whose chief ray has unit direction d meets that plane at F = O + s_F·d, s_F = z_F/(d·e_z) (the
*focus path*). Every pupil ray of the pixel passes through F: its (unnormalised) direction is
s_F·d − a for the pupil offset a. A locally flat sample mirrors the bundle, so after the
reflection H = I − 2nnᵀ at the chief ray's sample point P (n ∥ r − d) the rays leave the mirror
image F' of F (at path length s_F along the reflected chief ray) with direction r + ε,
ε = −H·a/s_F, and meet the screen (normal m) at the lever L = s₁ + s₂ − s_F beyond F'
(s₁ = |P − O|, s₂ = |q − P|):

    δq = L·(m·r)·[(r + ε)/(m·r + m·ε) − r/(m·r)].

To first order δq = −(L/s_F)·M H a with M = I − r mᵀ/(m·r) the projection along r onto the
screen: the footprint is the linear image of the pupil disc, a *uniform ellipse*, with covariance

    Σ = (D²/16)·(L/s_F)²·M H P_xy Hᵀ Mᵀ

(D²/16: the variance of a uniform disc of diameter D per axis; P_xy projects onto the pupil
plane). A pixel focused on its own sample point (s_F = s₁, the model before issue 20) has
L/s_F = s₂/s₁. To second order the centroid of the footprint is offset from the chief ray's screen
point by the curvature of the central projection onto the oblique screen
(:func:`defocus_moments`), a phase bias ∝ D². Both are computed from the traced sample and screen
points, no extra rays.

Transfer of a uniform ellipse. The footprint's marginal along the fringe axis e_a is the
projection of a uniform disc of radius R = D/2 by the linear map's row l_a: a semicircle
(Wigner) density of radius R·|l_a|, whose variance is R²|l_a|²/4 = σ_a² (σ_a² = e_aᵀΣe_a). Its
characteristic function at the spatial frequency k = 2πn/p of harmonic n is

    T_n = 2·J₁(x)/x,    x = k·R·|l_a| = 4π·n·σ_a/p,

(J₁ the Bessel function of the first kind): 1 − x²/8 + … (the Gaussian exp(−2π²σ²/p²) to second
order), first zero at x = 3.8317 (σ_a = 0.305·p), negative beyond it up to x = 7.0156 — a
contrast reversal, i.e. a π phase flip of the recorded fringe — then alternating lobes decaying as
x^(−3/2). The mapping is locally linear where the footprint is small against the curvature of
the sample and screen; the sample's curvature is not in this first-order footprint (a curved
sample adds focusing power and mixes neighbouring slopes off the focal plane): its error against a
pupil-sampled reference is recorded in docs/benchmarks.md.

Pixel-area integration: a pixel integrates the pattern over its 1 × 1 px footprint; with the
local Jacobian J = ∂(x_q, y_q)/∂(u, v) (central differences of the traced mapping) a sinusoid of
period p along axis a is multiplied exactly (for a locally linear mapping) by
sinc(J_a,u/p)·sinc(J_a,v/p), sinc(x) = sin(πx)/(πx).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from ..geometry.surface import eval_kernel
from ..geometry.transform import RigidTransform

__all__ = ["focus_path", "default_focus_distance", "uniform_disc_transfer", "defocus_moments", "defocus_covariance", "pixel_jacobian", "screen_normal", "screen_derivatives", "view_geometry"]


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


def _sample_in_camera(T_world_cam: RigidTransform, T_world_sample: RigidTransform, p_sample_mm) -> np.ndarray:
    return (T_world_cam.inv() @ T_world_sample).apply(np.asarray(p_sample_mm, dtype=float))


def default_focus_distance(T_world_cam: RigidTransform, T_world_sample: RigidTransform, p_sample_mm: np.ndarray,
                           principal_point_px) -> float:
    """The default focus distance (mm): the axial (camera z) distance of the sample point seen by
    the principal point — the traced pixel nearest to ``principal_point_px`` (u, v).

    Raises ``ValueError`` if no pixel is traced.
    """
    z = _sample_in_camera(T_world_cam, T_world_sample, p_sample_mm)[..., 2]
    ok = np.isfinite(z) & (z > 0)
    if not ok.any():
        raise ValueError("no traced sample point to focus on (imaging.focus_distance_mm unset)")
    v, u = np.nonzero(ok)
    i = np.argmin((u - principal_point_px[0]) ** 2 + (v - principal_point_px[1]) ** 2)
    return float(z[v[i], u[i]])


def focus_path(T_world_cam: RigidTransform, T_world_sample: RigidTransform, p_sample_mm: np.ndarray,
               focus_distance_mm: float) -> np.ndarray:
    """Path length s_F (mm) from the pinhole along each pixel's chief ray to the plane of sharp
    focus z_cam = ``focus_distance_mm``: s_F = z_F·s₁/z_P (s₁, z_P the distance and camera-z of
    the pixel's sample point), (H, W); NaN where not traced."""
    p = _sample_in_camera(T_world_cam, T_world_sample, p_sample_mm)
    return focus_distance_mm * np.linalg.norm(p, axis=-1) / p[..., 2]


#: Tabulated 2·J₁(x)/x (scipy.special.j1) on [0, _JINC_X_MAX] with step _JINC_STEP: linear
#: interpolation in the render kernel is accurate to h²/8·max|f''| = 3.0e-8 (|f''| ≤ 1/4); beyond
#: the table the asymptotic form 2·√(2/(πx))·cos(x − 3π/4)/x (error < 1e-5 there).
_JINC_STEP = 1.0 / 1024.0
_JINC_X_MAX = 512.0


def _jinc_table() -> np.ndarray:
    from scipy.special import j1

    x = np.arange(0.0, _JINC_X_MAX + 2 * _JINC_STEP, _JINC_STEP)
    t = np.empty_like(x)
    t[0] = 1.0
    t[1:] = 2.0 * j1(x[1:]) / x[1:]
    return t


JINC_TABLE = _jinc_table()


@numba.njit(cache=True, error_model="numpy")
def jinc(x, table):
    """2·J₁(x)/x for x ≥ 0 from :data:`JINC_TABLE` (linear interpolation; asymptotic beyond)."""
    if x < _JINC_X_MAX:
        f = x * (1.0 / _JINC_STEP)
        i = int(f)
        w = f - i
        return table[i] + w * (table[i + 1] - table[i])
    return 2.0 * np.sqrt(2.0 / (np.pi * x)) * np.cos(x - 0.75 * np.pi) / x


def uniform_disc_transfer(sigma_mm, period_mm, harmonic: int = 1) -> np.ndarray:
    """Transfer 2·J₁(x)/x, x = 4π·n·σ/p, of a uniform-ellipse footprint whose std along the
    fringe axis is ``sigma_mm``, for harmonic ``n`` of period ``period_mm`` (module docstring);
    negative where the contrast is reversed. Exact (scipy.special.j1)."""
    from scipy.special import j1

    x = 4.0 * np.pi * harmonic * np.asarray(sigma_mm, dtype=float) / period_mm
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(x == 0, 1.0, 2.0 * j1(x) / np.where(x == 0, 1.0, x))


def defocus_moments(T_world_cam: RigidTransform, T_world_sample: RigidTransform, T_world_screen: RigidTransform,
                    p_sample_mm: np.ndarray, q_screen_mm: np.ndarray, aperture_mm: float, screen_surface=None,
                    focus_path_mm: np.ndarray | None = None):
    """Covariance and centroid offset of the defocus footprint on the screen (screen frame x, y).

    A pupil point a (uniform on the disc of diameter D in the camera's x–y plane) sends its ray
    through the pixel's point F on the focal plane (path s_F from the pinhole); its
    (unnormalised) direction s_F·d − a is linear in a, so after the reflection H the ray is
    r + ε with ε = −H·a/s_F from the mirror image F' of F, and it meets the screen plane (normal
    m, the local screen normal: e_z for a plane) at δq = L·(m·r)·[(r + ε)/(m·r + m·ε) − r/(m·r)],
    L = s₁ + s₂ − s_F (module docstring). To second order in ε, with
    C = Cov(ε) = (D²/16)/s_F² · H (e_x e_xᵀ + e_y e_yᵀ) Hᵀ (e_x, e_y the pupil axes):

        Σ = L² · M C Mᵀ,                          M = I − r mᵀ / (m·r),
        E[δq] = L · (r · mᵀCm / (m·r)² − C m / (m·r))

    (x, y components: the pattern coordinates on the local tangent plane), plus the lift of a
    curved screen over its tangent plane, ½·tr(KΣ) along the ray (K the height's Hessian).

    The centroid offset E[δq] — the central projection's curvature — is O(D²): it scales with
    1/N², points where the oblique reflected bundle meets the screen farther out, and shifts the
    fringe phase (the footprint is no longer centred on the chief ray).

    ``focus_path_mm`` (H, W): s_F per pixel (:func:`focus_path`); None focuses every pixel on
    its own sample point (s_F = s₁, L = s₂).

    Returns
    -------
    cov_mm2 : ndarray (H, W, 2, 2)
    centroid_mm : ndarray (H, W, 2)
    cos_view : ndarray (H, W)
        Cosine of the angle between the reflected ray and the screen normal (for the angular
        emission; computed in the same pass). All NaN where the pixel was not traced.
    """
    T_screen_world = T_world_screen.inv()
    p = np.ascontiguousarray((T_screen_world @ T_world_sample).apply(p_sample_mm), dtype=float)
    q = np.ascontiguousarray(q_screen_mm, dtype=float)
    o = np.ascontiguousarray(T_screen_world.apply(T_world_cam.translation), dtype=float)
    R_screen_cam = (T_screen_world @ T_world_cam).rotation
    ex = np.ascontiguousarray(R_screen_cam[:, 0])  # the pupil plane's axes (screen frame)
    ey = np.ascontiguousarray(R_screen_cam[:, 1])
    shape = q.shape[:-1]
    grad, hess = screen_derivatives(q, screen_surface)
    cov = np.empty(shape + (2, 2))
    centroid = np.empty(shape + (2,))
    cos_view = np.empty(shape)
    fpath = (np.full(shape, -1.0) if focus_path_mm is None
             else np.ascontiguousarray(np.broadcast_to(np.asarray(focus_path_mm, dtype=float), shape)))
    _moments_kernel(p.reshape(-1, 3), q.reshape(-1, 3), o, ex, ey, grad.reshape(-1, 2), hess.reshape(-1, 3),
                    float(aperture_mm), readonly(fpath.reshape(-1)), cov.reshape(-1, 2, 2), centroid.reshape(-1, 2),
                    cos_view.reshape(-1))
    return cov, centroid, cos_view


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _moments_kernel(p, q, o, ex, ey, grad, hess, aperture, fpath, cov, centroid, cos_view):
    """Per pixel: the footprint covariance and centroid of :func:`defocus_moments` (flat arrays)."""
    c0 = aperture * aperture / 16.0
    for i in numba.prange(0, p.shape[0]):
        dx = p[i, 0] - o[0]
        dy = p[i, 1] - o[1]
        dz = p[i, 2] - o[2]
        s1 = np.sqrt(dx * dx + dy * dy + dz * dz)
        rx = q[i, 0] - p[i, 0]
        ry = q[i, 1] - p[i, 1]
        rz = q[i, 2] - p[i, 2]
        s2 = np.sqrt(rx * rx + ry * ry + rz * rz)
        if not (np.isfinite(s1) and np.isfinite(s2)) or s1 == 0.0 or s2 == 0.0:
            cos_view[i] = np.nan
            for a in range(2):
                centroid[i, a] = np.nan
                for b in range(2):
                    cov[i, a, b] = np.nan
            continue
        dx /= s1
        dy /= s1
        dz /= s1
        rx /= s2
        ry /= s2
        rz /= s2
        # Sample normal ∥ r − d; reflection H = I − 2nnᵀ applied to the pupil axes.
        nx = rx - dx
        ny = ry - dy
        nz = rz - dz
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        nx /= nn
        ny /= nn
        nz /= nn
        hxv = np.empty(3)
        hyv = np.empty(3)
        ax = ex[0] * nx + ex[1] * ny + ex[2] * nz
        ay = ey[0] * nx + ey[1] * ny + ey[2] * nz
        hxv[0] = ex[0] - 2.0 * ax * nx
        hxv[1] = ex[1] - 2.0 * ax * ny
        hxv[2] = ex[2] - 2.0 * ax * nz
        hyv[0] = ey[0] - 2.0 * ay * nx
        hyv[1] = ey[1] - 2.0 * ay * ny
        hyv[2] = ey[2] - 2.0 * ay * nz
        # Focus path s_F (≤ 0: focused on the sample point) and lever L beyond the virtual point F'.
        sf = s1 if fpath[i] <= 0.0 else fpath[i]
        lev = s2 if fpath[i] <= 0.0 else s1 + s2 - sf
        c = c0 / (sf * sf)  # C = c·(hx hxᵀ + hy hyᵀ)
        # Screen normal m ∝ (−h_x, −h_y, 1).
        mx = -grad[i, 0]
        my = -grad[i, 1]
        mz = 1.0
        mr = mx * rx + my * ry + mz * rz
        cos_view[i] = mr / np.sqrt(mx * mx + my * my + 1.0)
        mhx = mx * hxv[0] + my * hxv[1] + mz * hxv[2]
        mhy = mx * hyv[0] + my * hyv[1] + mz * hyv[2]
        # M v = v − r (m·v)/(m·r); Σ = L² c Σ_axes (M h)(M h)ᵀ.
        ux = hxv[0] - rx * mhx / mr
        uy = hxv[1] - ry * mhx / mr
        vx = hyv[0] - rx * mhy / mr
        vy = hyv[1] - ry * mhy / mr
        k = lev * lev * c
        sxx = k * (ux * ux + vx * vx)
        sxy = k * (ux * uy + vx * vy)
        syy = k * (uy * uy + vy * vy)
        cov[i, 0, 0] = sxx
        cov[i, 0, 1] = sxy
        cov[i, 1, 0] = sxy
        cov[i, 1, 1] = syy
        # E[δq] = L (r·mᵀCm/(m·r)² − Cm/(m·r)), Cm = c (hx (hx·m) + hy (hy·m)).
        mcm = c * (mhx * mhx + mhy * mhy)
        # Curved screen: + ½ tr(KΣ)/(m·r) · r (m unnormalised with m_z = 1).
        lam = 0.5 * (hess[i, 0] * sxx + 2.0 * hess[i, 1] * sxy + hess[i, 2] * syy) / mr
        cmx = c * (hxv[0] * mhx + hyv[0] * mhy)
        cmy = c * (hxv[1] * mhx + hyv[1] * mhy)
        centroid[i, 0] = lev * (rx * mcm / (mr * mr) - cmx / mr) + lam * rx
        centroid[i, 1] = lev * (ry * mcm / (mr * mr) - cmy / mr) + lam * ry


def defocus_covariance(T_world_cam: RigidTransform, T_world_sample: RigidTransform, T_world_screen: RigidTransform,
                       p_sample_mm: np.ndarray, q_screen_mm: np.ndarray, aperture_mm: float,
                       screen_surface=None) -> np.ndarray:
    """Covariance (mm², screen frame x, y) of the defocus footprint on the screen, (H, W, 2, 2)
    (:func:`defocus_moments`); ``aperture_mm`` is D = focal length / f-number."""
    return defocus_moments(T_world_cam, T_world_sample, T_world_screen, p_sample_mm, q_screen_mm, aperture_mm,
                           screen_surface)[0]  # noqa: E501


def screen_derivatives(q_screen_mm: np.ndarray, screen_surface=None, step_mm: float = 0.5):
    """Gradient (h_x, h_y) and Hessian (h_xx, h_xy, h_yy) of the screen height at the traced
    points, (H, W, 2) and (H, W, 3) (1/mm); the Hessian by forward differences of the spline's
    analytic gradient over ``step_mm``. 0 for a plane (``screen_surface`` None) and where the
    point is not traced."""
    q = np.asarray(q_screen_mm, dtype=float)
    grad = np.zeros(q.shape[:-1] + (2,))
    hess = np.zeros(q.shape[:-1] + (3,))
    if screen_surface is None:
        return grad, hess
    k = getattr(screen_surface, "kernel", None)
    if k is not None:  # one compiled pass, the same arithmetic (numpy's masking cost ≈ 10× the evaluations)
        _derivatives_kernel(k.kind, readonly(k.grid_x), readonly(k.grid_y), readonly(k.coef),
                            readonly(np.ascontiguousarray(q.reshape(-1, 3))), float(step_mm), grad.reshape(-1, 2),
                            hess.reshape(-1, 3))
        return grad, hess
    ok = np.isfinite(q).all(-1)
    x, y = q[ok][:, 0], q[ok][:, 1]
    g0 = screen_surface.gradient(x, y)
    gx = screen_surface.gradient(x + step_mm, y)
    gy = screen_surface.gradient(x, y + step_mm)
    grad[ok] = g0
    hess[ok] = np.stack([(gx[:, 0] - g0[:, 0]) / step_mm, 0.5 * ((gx[:, 1] - g0[:, 1]) + (gy[:, 0] - g0[:, 0])) / step_mm,
                         (gy[:, 1] - g0[:, 1]) / step_mm], axis=-1)
    return grad, hess


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _derivatives_kernel(kind, gx, gy, coef, q, step, grad, hess):
    """:func:`screen_derivatives` per point (flat arrays): gradient, forward-difference Hessian."""
    for i in numba.prange(0, q.shape[0]):
        x = q[i, 0]
        y = q[i, 1]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(q[i, 2])):
            continue
        _h, hx, hy = eval_kernel(kind, gx, gy, coef, x, y)
        _h, ax, ay = eval_kernel(kind, gx, gy, coef, x + step, y)
        _h, bx, by = eval_kernel(kind, gx, gy, coef, x, y + step)
        grad[i, 0] = hx
        grad[i, 1] = hy
        hess[i, 0] = (ax - hx) / step
        hess[i, 1] = 0.5 * ((ay - hy) + (bx - hx)) / step
        hess[i, 2] = (by - hy) / step


def screen_normal(q_screen_mm: np.ndarray, screen_surface=None, grad=None) -> np.ndarray:
    """Unit normal of the screen at the traced points (screen frame), (H, W, 3); e_z for a
    plane (``screen_surface`` None) and where the point is not traced. ``grad`` may pass the
    gradient of :func:`screen_derivatives`."""
    g = screen_derivatives(q_screen_mm, screen_surface)[0] if grad is None else grad
    n = np.concatenate([-g, np.ones(g.shape[:-1] + (1,))], axis=-1)  # (−h_x, −h_y, 1): z > 0
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def pixel_jacobian(screen_xy_mm: np.ndarray) -> np.ndarray:
    """∂(x_q, y_q)/∂(u, v) per pixel, (H, W, 2, 2) (rows: x_q, y_q; columns: u, v), mm/px.

    Central differences where both neighbours are traced, one-sided where only one is, 0 where
    none is (no pixel-area attenuation there).
    """
    xy = np.asarray(screen_xy_mm, dtype=float)
    J = np.zeros(xy.shape[:2] + (2, 2))
    if xy.ndim == 3 and xy.shape[2] == 2:  # one compiled pass, the same arithmetic as below
        _jacobian_kernel(readonly(np.ascontiguousarray(xy)), J)
        return J
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


@numba.njit(cache=True, error_model="numpy", inline="always")
def _pick(fwd, bwd):
    cen = 0.5 * (fwd + bwd)
    if np.isfinite(cen):
        return cen
    if np.isfinite(fwd):
        return fwd
    if np.isfinite(bwd):
        return bwd
    return 0.0


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _jacobian_kernel(xy, J):
    """:func:`pixel_jacobian` per pixel: central differences, one-sided, or 0."""
    h, w = xy.shape[0], xy.shape[1]
    for v in numba.prange(0, h):
        for u in range(w):
            for c in range(2):
                fwd = xy[v, u + 1, c] - xy[v, u, c] if u + 1 < w else np.nan
                bwd = xy[v, u, c] - xy[v, u - 1, c] if u >= 1 else np.nan
                J[v, u, c, 0] = _pick(fwd, bwd)
                fwd = xy[v + 1, u, c] - xy[v, u, c] if v + 1 < h else np.nan
                bwd = xy[v, u, c] - xy[v - 1, u, c] if v >= 1 else np.nan
                J[v, u, c, 1] = _pick(fwd, bwd)
