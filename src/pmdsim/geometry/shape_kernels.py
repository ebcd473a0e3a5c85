"""Compiled kernels of the analytic sample shapes: height-field quadrics in closed form.

Sphere, paraboloid and cylinder (docs/conventions.md, "Curved samples") are all height fields
of the form

    F(p') = p'ᵀ Q p' − z = 0,      p' = (x − v_x, y − v_y, z),

with the vertex (v_x, v_y, 0) and a symmetric 3 × 3 matrix Q:

* paraboloid  z = x'²/(4 f_x) + y'²/(4 f_y):   Q = diag(1/(4 f_x), 1/(4 f_y), 0);
* sphere of radius R, centre (v_x, v_y, R):     Q = I / (2R);
* cylinder of radius R, axis through (v_x, v_y, R) along a = (cos θ, sin θ, 0):
  with w = (−sin θ, cos θ, 0),                  Q = (w wᵀ + e_z e_zᵀ) / (2R).

The height field is the branch of F = 0 on which ∂F/∂z = 2 (Q p')_z − 1 < 0 (the cap of the
sphere or cylinder nearer to z = 0; all of the paraboloid). Its height, gradient (implicit
differentiation: h_x = −F_x/F_z) and ray intersection (the quadratic in the ray parameter) are
closed forms. The kernels take the flat coefficient array of
:class:`~pmdsim.geometry.surface.KernelSurface` (kind ``_KIND_QUADRIC``):
``coef = [v_x, v_y, Q_xx, Q_xy, Q_xz, Q_yy, Q_yz, Q_zz]``.

Return conventions and status codes are those of :mod:`pmdsim.geometry.surface`
(0 hit, 1 parallel/behind, 2 outside the grid or missed).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["quadric_height", "quadric_eval2", "quadric_intersect"]

_HIT = 0
_PARALLEL = 1
_OUTSIDE = 2


@numba.njit(cache=True, error_model="numpy", inline="always")
def quadric_height(coef, x, y):
    """Height h(x, y) of the quadric height field (NaN where the branch does not exist)."""
    xp = x - coef[0]
    yp = y - coef[1]
    a = coef[7]
    b = 2.0 * (coef[4] * xp + coef[6] * yp) - 1.0
    c = coef[2] * xp * xp + 2.0 * coef[3] * xp * yp + coef[5] * yp * yp
    disc = b * b - 4.0 * a * c
    den = -b + np.sqrt(disc) if disc >= 0.0 else np.nan
    if not den > 0.0:
        return np.nan
    # The root with b + 2az = −√disc (∂F/∂z < 0), in the cancellation-free form 2c/(−b + √disc).
    return 2.0 * c / den


@numba.njit(cache=True, error_model="numpy", inline="always")
def quadric_eval2(coef, x, y):
    """(h, h_x, h_y, h_xx, h_xy, h_yy) of the quadric height field at (x, y).

    Implicit differentiation of F(x, y, h(x, y)) = 0: h_x = −F_x/F_z, and for the second
    derivatives h_ij = −(F_ij + F_iz h_j + F_jz h_i + F_zz h_i h_j)/F_z.
    """
    z = quadric_height(coef, x, y)
    xp = x - coef[0]
    yp = y - coef[1]
    qxx, qxy, qxz, qyy, qyz, qzz = coef[2], coef[3], coef[4], coef[5], coef[6], coef[7]
    fx = 2.0 * (qxx * xp + qxy * yp + qxz * z)
    fy = 2.0 * (qxy * xp + qyy * yp + qyz * z)
    fz = 2.0 * (qxz * xp + qyz * yp + qzz * z) - 1.0
    hx = -fx / fz
    hy = -fy / fz
    hxx = -(2.0 * qxx + 4.0 * qxz * hx + 2.0 * qzz * hx * hx) / fz
    hxy = -(2.0 * qxy + 2.0 * qxz * hy + 2.0 * qyz * hx + 2.0 * qzz * hx * hy) / fz
    hyy = -(2.0 * qyy + 4.0 * qyz * hy + 2.0 * qzz * hy * hy) / fz
    return z, hx, hy, hxx, hxy, hyy


@numba.njit(cache=True, error_model="numpy", inline="always")
def _root(coef, gx, gy, ox, oy, oz, dx, dy, dz, t):
    """Refine root t of F(o + t d) by one Newton step; (inside, on_branch, t, x, y, z, h_x, h_y)."""
    qxx, qxy, qxz, qyy, qyz, qzz = coef[2], coef[3], coef[4], coef[5], coef[6], coef[7]
    xp = ox - coef[0] + t * dx
    yp = oy - coef[1] + t * dy
    z = oz + t * dz
    gxv = qxx * xp + qxy * yp + qxz * z
    gyv = qxy * xp + qyy * yp + qyz * z
    gzv = qxz * xp + qyz * yp + qzz * z
    f = xp * gxv + yp * gyv + z * gzv - z
    df = 2.0 * (dx * gxv + dy * gyv + dz * gzv) - dz
    if df != 0.0:
        t = t - f / df
        xp = ox - coef[0] + t * dx
        yp = oy - coef[1] + t * dy
        z = oz + t * dz
        gxv = qxx * xp + qxy * yp + qxz * z
        gyv = qxy * xp + qyy * yp + qyz * z
        gzv = qxz * xp + qyz * yp + qzz * z
    fz = 2.0 * gzv - 1.0
    x = xp + coef[0]
    y = yp + coef[1]
    inside = gx[0] <= x <= gx[gx.shape[0] - 1] and gy[0] <= y <= gy[gy.shape[0] - 1]
    return inside, fz < 0.0, t, x, y, z, -2.0 * gxv / fz, -2.0 * gyv / fz


@numba.njit(cache=True, error_model="numpy", inline="always")
def quadric_intersect(coef, gx, gy, ox, oy, oz, dx, dy, dz):
    """First intersection (t > 0) of the ray o + t·d with the quadric height field over the grid.

    F(o + t d) = A t² + B t + C with A = d'ᵀQd, B = 2 o'ᵀQd − d_z, C = o'ᵀQo' − o_z; the roots
    (the numerically stable pair q/A, C/q, q = −(B + sign(B)·√(B² − 4AC))/2) are taken in
    increasing t, each polished by one Newton step on F; the first with t > 0 that lies on
    the height field's branch (∂F/∂z < 0) and inside the grid rectangle is the hit.

    Returns
    -------
    (t, x, y, z, h_x, h_y, status)
        status: 0 hit; 1 (parallel) when the surface lies only behind the ray's origin;
        2 (outside) when the ray meets the height field only outside the grid, or misses it.
    """
    nan = np.nan
    qxx, qxy, qxz, qyy, qyz, qzz = coef[2], coef[3], coef[4], coef[5], coef[6], coef[7]
    oxp = ox - coef[0]
    oyp = oy - coef[1]
    qdx = qxx * dx + qxy * dy + qxz * dz
    qdy = qxy * dx + qyy * dy + qyz * dz
    qdz = qxz * dx + qyz * dy + qzz * dz
    a = dx * qdx + dy * qdy + dz * qdz
    b = 2.0 * (oxp * qdx + oyp * qdy + oz * qdz) - dz
    c = (oxp * (qxx * oxp + qxy * oyp + qxz * oz) + oyp * (qxy * oxp + qyy * oyp + qyz * oz)
         + oz * (qxz * oxp + qyz * oyp + qzz * oz) - oz)
    scale = abs(b) + abs(a) * (abs(oxp) + abs(oyp) + abs(oz) + 1.0)
    if abs(a) <= 1e-15 * scale:  # linear in t (e.g. a vertical ray on a paraboloid)
        if b == 0.0:
            return nan, nan, nan, nan, nan, nan, _PARALLEL
        t1 = -c / b
        t2 = np.inf
    else:
        disc = b * b - 4.0 * a * c
        if not disc >= 0.0:
            return nan, nan, nan, nan, nan, nan, _OUTSIDE  # the ray misses the quadric
        q = -0.5 * (b + np.sqrt(disc)) if b >= 0.0 else -0.5 * (b - np.sqrt(disc))
        if q == 0.0:
            t1 = 0.0
            t2 = 0.0
        else:
            t1 = q / a
            t2 = c / q
        if t2 < t1:
            t1, t2 = t2, t1
    status = _PARALLEL
    if t1 > 0.0:
        inside, branch, t, x, y, z, hx, hy = _root(coef, gx, gy, ox, oy, oz, dx, dy, dz, t1)
        if branch:
            if inside:
                return t, x, y, z, hx, hy, _HIT
            status = _OUTSIDE
    if t2 > 0.0 and t2 < np.inf:
        inside, branch, t, x, y, z, hx, hy = _root(coef, gx, gy, ox, oy, oz, dx, dy, dz, t2)
        if branch:
            if inside:
                return t, x, y, z, hx, hy, _HIT
            status = _OUTSIDE
    if status == _PARALLEL and (t1 > 0.0 or (t2 > 0.0 and t2 < np.inf)):
        status = _OUTSIDE  # roots ahead, but only on the far branch of a sphere or cylinder
    return nan, nan, nan, nan, nan, nan, status


# Out-of-line entry points (issue 25 item 2, docs/benchmarks.md "First run: the tracer's compile
# cut"): the surface kernels call the closed form through these instead of inlining it at every
# call site, so numba types it once per set of flags. Two, because the inlined code took its
# caller's flags: ``intersect_kernel`` is inlined into kernels that contract a·b + c into FMAs,
# ``intersect_solve`` is not (the results stay bit-identical to the inlined code's).
@numba.njit(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})
def quadric_intersect_fma(coef, gx, gy, ox, oy, oz, dx, dy, dz):
    """:func:`quadric_intersect` compiled with FMA contraction (for ``intersect_kernel``)."""
    return quadric_intersect(coef, gx, gy, ox, oy, oz, dx, dy, dz)


@numba.njit(cache=True, error_model="numpy", _nrt=False)
def quadric_intersect_call(coef, gx, gy, ox, oy, oz, dx, dy, dz):
    """:func:`quadric_intersect` compiled without fastmath flags (for ``intersect_solve``)."""
    return quadric_intersect(coef, gx, gy, ox, oy, oz, dx, dy, dz)
