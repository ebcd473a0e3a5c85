"""The cover glass inside the tracer: warm-started foot-point Newton steps, row by row.

With a cover glass (:mod:`pmdsim.geometry.cover_glass`) the tracer does not intersect the bare
emitting surface at all on its fast path. For every pixel it predicts the outer-surface hit A
from the pixels traced before it — the height A_z and the plate normal m, extrapolated linearly
from the two rows above (the row kernel, :func:`glass_block`) or from the pixels two and three
to the left (the first row of a band, :func:`glass_pixel`) — and takes the foot point
u = A_xy − t·m_xy of that prediction, which lies on the reflected ray's offset line. Then:

1. one Newton step on F(u) = A(u)_xy − (a + b·A(u)_z) (the outer-surface point
   A(u) = (u, h(u)) + t·m(u) on the ray x = a + b·z), with the exact Jacobian (the surface's
   second derivatives: one bicubic evaluation of h, ∇h and the Hessian at u,
   :func:`foot_newton`); the step is accepted by an error bound (below). From the fifth row of a
   band on, the step is skipped where the steps of the two rows above predict the foot point
   provably within the foot tolerance (a bound from the residual alone,
   :mod:`pmdsim.simulation.glass_skip`);
2. the gradient carried to the new foot point by the Hessian, the ray's point on the outer
   surface's tangent plane there, refraction (Snell's law in vector form);
3. the emitting-surface hit of the refracted ray: the tracer's intersection stage
   (one Newton step from the height extrapolated from the rows above, accepted by its error
   bound; the scalar kernels where it is not).

**Error bound of step 1.** With D₂, D₃ bounds of the surface's second and third derivatives
(:attr:`~pmdsim.geometry.surface.KernelSurface.dmax`) and |h_x| + |h_y| ≤ 1 on the step, every
second partial derivative of m (and of g = 1/√(1 + |∇h|²)) is at most K = 3·D₃ + 11·D₂², so
that of F_i is at most M_i = t·K + |b_i|·(D₂ + t·K). After a Newton step s the residual is
≤ ½·M·‖s‖₁², and the foot point is off the root by at most ‖J⁻¹‖_∞·M·‖s‖₁² (a safety factor
2); the step is accepted when that is ≤ 1e-9 mm (the convergence threshold of
:func:`~pmdsim.geometry.cover_glass.through_glass_full`) and the carried gradient's error
D₃·‖s‖₁² is ≤ the intersection tolerance. Since the predicted foot point is within ~1e-6 mm of
the root on smooth screens, one step settles it (its error bound ~1e-15 mm).

**Where the fast path does not apply** — a step not accepted: up to four scalar Newton steps
from the prediction (:func:`glass_pixel_at`; the second row of a band, which has one row above
and no extrapolation, mostly takes them); then, or with no prediction (the first pixels of a
band, next to invalid pixels), the ray not entering the plate from the sample side, the
emitting-surface hit failing or lying within 3·t·(1 + |b_x| + |b_y|) of the grid's edge (where
the glass-free hit, which decides the status there, could lie on the other side of it) — the
pixel is traced exactly as the separate refracting pass did before
(:func:`fallback_trace`: the bare hit, then
:func:`~pmdsim.geometry.cover_glass.through_glass_full` from it), so the status codes are those
of that pass. ``tests/test_cover_glass.py`` compares the two paths pixel by pixel.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..geometry.cover_glass import _FOOT_TOL_MM, through_glass_full
from ..geometry.surface import (
    _KIND_PLANE, _KIND_SPLINE, _NEEDS_SOLVE, _interval, eval2_kernel, intersect_kernel, intersect_solve,
)
from .glass_skip import _in_box, skip_check_run
from .trace_rows import patch_rows
from .trace_rows import (
    _AX, _AY, _BLK, _BX, _BY, _C, _CONV, _GM, _GMX, _GMY, _HX, _HY, _INV, _JIT, _PID, _PIY, _QOX, _QOY, _QOZ,
    _ROZ, _SC, _SMALL_GRID, _TDX, _TDY, _TDZ, _TOX, _TOY, _TOZ, _UX, _UY, _VX, _VY, _VZ, _WX, _WY, _WZ, _X, _Y, _Z,
    _ZG, _fixup, _intersect_block,
)

__all__ = ["foot_newton", "glass_ray", "glass_block", "glass_pixel", "glass_pixel_at", "fallback_trace",
           "glass_band_rows"]

#: Fewest bands (parallel tasks) :func:`glass_band_rows` leaves an image.
_MIN_BANDS = 8


def glass_band_rows(n_rows: int, band_rows: int) -> int:
    """Image rows per band of the tracer with a cover glass, for an image of ``n_rows`` rows
    (``band_rows``: the glass-free tracer's).

    The first row of a band has no rows above: its pixels are traced one by one
    (:func:`glass_pixel`), at 0.2–0.3 µs more per pixel than a row-kernel pixel with glass
    (docs/benchmarks.md "Cover glass (issue 21): where the glass trace's time goes"). So
    with a glass the bands are up to four times as long, as long as the image still gives
    ``_MIN_BANDS`` bands (the threads' tasks). Depends on the image's shape only: the results do
    not depend on the number of threads.
    """
    return max(band_rows, min(4 * band_rows, n_rows // _MIN_BANDS))


# _fixup reads the refracted ray's origin and direction from three consecutive fields each.
assert (_TOY, _TOZ, _TDY, _TDZ) == (_TOX + 1, _TOX + 2, _TDX + 1, _TDX + 2)
# ... and stores the foot-point step's two fields (_VX, _VY) in a loop over both.
assert _VY == _VX + 1

#: Code (field _C) of a pixel left to :func:`fallback_trace`.
_FALLBACK = 6.0
#: Scratch field of :func:`glass_block`: 1.0 where the pixel had the linear prediction (A_z, m of
#: both rows above finite, tested as their extrapolation being finite: the same for values below
#: 1e300), else 0.0 — the view ray's _VZ, unused after the reflection.
_LIN = _VZ


@numba.njit(**_JIT, inline="always")
def foot_newton(h, hx, hy, hxx, hxy, hyy, ux, uy, ax, ay, bx, by, t, d2, d3, tol):
    """One Newton step of the foot point u (module docstring, step 1).

    ``h … hyy``: the emitting surface's height, gradient and second derivatives at u; the ray
    x = a_x + b_x·z, y = a_y + b_y·z (screen frame); ``t``: the glass thickness; ``d2``, ``d3``:
    the surface's derivative bounds; ``tol``: the intersection tolerance (for the carried
    gradient). Returns ``(u_x, u_y, h, h_x, h_y, g, accepted)`` at the new foot point (height,
    gradient and g = 1/√(1 + |∇h|²) carried there by Taylor's theorem: the relative change δ of
    1 + |∇h|² gives g·(1 − δ/2), off by ≤ 3δ²/8 with δ ≤ 5·D₂·‖s‖₁ — accepted only when that is
    below the tolerance).
    """
    q = 1.0 + hx * hx + hy * hy
    g = 1.0 / math.sqrt(q)
    g3 = g * g * g
    azu = h - t * g
    fx = ux + t * (hx * g) - ax - bx * azu
    fy = uy + t * (hy * g) - ay - by * azu
    px = hx * hxx + hy * hxy
    py = hx * hxy + hy * hyy
    daz_x = hx + t * g3 * px
    daz_y = hy + t * g3 * py
    j11 = 1.0 + t * (g * hxx - hx * g3 * px) - bx * daz_x
    j12 = t * (g * hxy - hx * g3 * py) - bx * daz_y
    j21 = t * (g * hxy - hy * g3 * px) - by * daz_x
    j22 = 1.0 + t * (g * hyy - hy * g3 * py) - by * daz_y
    idet = 1.0 / (j11 * j22 - j12 * j21)
    sx = (j12 * fy - j22 * fx) * idet
    sy = (j21 * fx - j11 * fy) * idet
    h2 = h + hx * sx + hy * sy + 0.5 * (hxx * sx * sx + 2.0 * hxy * sx * sy + hyy * sy * sy)
    hx2 = hx + hxx * sx + hxy * sy
    hy2 = hy + hxy * sx + hyy * sy
    dhx = hx2 - hx
    dhy = hy2 - hy
    g2 = g * (1.0 - 0.5 * g * g * (2.0 * (hx * dhx + hy * dhy) + dhx * dhx + dhy * dhy))
    ns = abs(sx) + abs(sy)
    ns2 = ns * ns
    km = 3.0 * d3 + 11.0 * d2 * d2
    jinv = max(abs(j22) + abs(j12), abs(j21) + abs(j11)) * abs(idet)
    mb = t * km + max(abs(bx), abs(by)) * (d2 + t * km)
    ok = (jinv * mb * ns2 <= _FOOT_TOL_MM) & (d3 * ns2 <= tol) & (25.0 * d2 * d2 * ns2 <= tol) & (
        abs(hx) + abs(hy) + 2.0 * d2 * ns <= 1.0)
    return ux + sx, uy + sy, h2, hx2, hy2, g2, ok


@numba.njit(**_JIT, inline="always")
def glass_ray(ux, uy, h, hx, hy, g, ax, ay, bx, by, wx, wy, wz, t, n_idx):
    """Step 2 of the module docstring at the accepted foot point u (height h, gradient h_x, h_y,
    g = 1/√(1 + h_x² + h_y²)).

    Returns ``(A_x, A_y, A_z, r_x, r_y, r_z, m_x, m_y, enters)``: the ray's point A on the outer
    surface's tangent plane at A(u), the refracted direction r (Snell's law in vector form,
    scaled by |w|: no normalisation), the plate normal m and whether the ray (direction w) meets
    the plate from the sample side (w·m < 0).
    """
    mx = hx * g
    my = hy * g
    mz = -g
    pux = ux + t * mx
    puy = uy + t * my
    puz = h + t * mz
    den = bx * mx + by * my + mz
    za = ((pux - ax) * mx + (puy - ay) * my + puz * mz) / den
    a_x = ax + bx * za
    a_y = ay + by * za
    # e = w/|w|, cos_i = −e·m: r·|w| = η·w + (−η·w·m − √(|w|² − η²(|w|² − (w·m)²)))·m.
    wm = wx * mx + wy * my + wz * mz
    ww = wx * wx + wy * wy + wz * wz
    eta = 1.0 / n_idx
    f = -eta * wm - math.sqrt(ww - eta * eta * (ww - wm * wm))
    rx = eta * wx + f * mx
    ry = eta * wy + f * my
    rz = eta * wz + f * mz
    return a_x, a_y, za, rx, ry, rz, mx, my, wm < 0.0


@numba.njit(**_JIT, inline="always")
def _plane_start(ux, uy, h, hx, hy, a_x, a_y, a_z, rx, ry, rz):
    """The height at which the ray A + s·r meets the emitting surface's tangent plane at u."""
    cx = rx / rz
    cy = ry / rz
    return (h + hx * (a_x - cx * a_z - ux) + hy * (a_y - cy * a_z - uy)) / (1.0 - hx * cx - hy * cy)


@numba.njit(**_JIT)
def fallback_trace(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, dx, dy, dz, z_start, tol, max_iter):
    """The refracting pass's trace of one reflected ray (origin o, direction d, screen frame):
    the bare emitting-surface hit (from ``z_start``), then
    :func:`~pmdsim.geometry.cover_glass.through_glass_full` from it. Returns ``(x, y, z, code,
    A_z, m_x, m_y)``; ``code`` is the bare hit's :class:`~pmdsim.geometry.surface.IntersectStatus`
    where that fails, else the glass trace's (clipped to 3), 0 for a hit."""
    nan = np.nan
    _t, x, y, z, _hx, _hy, st = intersect_kernel(kind, gx, gy, coef, dmax, ox, oy, oz, dx, dy, dz, tol, z_start, False)
    if st == _NEEDS_SOLVE:
        _t, x, y, z, _hx, _hy, st = intersect_solve(kind, gx, gy, coef, z_min, z_max, dmax, ox, oy, oz, dx, dy, dz, tol,
                                                    max_iter, z)
    if st != 0:
        return nan, nan, nan, st, nan, nan, nan
    x, y, z, st, az, mx, my = through_glass_full(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, dx, dy,
                                                 dz, x, y, z, tol, max_iter)
    return x, y, z, min(st, 3), az, mx, my


@numba.njit(**_JIT, inline="always")
def _inside(gx, gy, x, y, margin):
    return (x >= gx[0] + margin) & (x <= gx[gx.shape[0] - 1] - margin) & (y >= gy[0] + margin) & (
        y <= gy[gy.shape[0] - 1] - margin)


#: Foot-point Newton steps of the scalar path (:func:`glass_pixel_at`) before the fallback.
_SCALAR_STEPS = 4


@numba.njit(**_JIT)
def glass_pixel(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, az_g, mx_g, my_g, zq_g,
                tol, max_iter):
    """One pixel of the first row of a band (module docstring), scalar: the predicted outer-surface
    height ``az_g`` and normal (``mx_g``, ``my_g``), the predicted emitting-surface height
    ``zq_g`` (NaN: none). Returns ``(x, y, z, code, A_z, m_x, m_y)`` as :func:`fallback_trace`."""
    if kind == _KIND_PLANE:
        az_g = -t
        mx_g = 0.0
        my_g = 0.0
    ux = np.nan
    uy = np.nan
    if wz != 0.0 and np.isfinite(wz):
        bx = wx / wz
        by = wy / wz
        ux = (ox - oz * bx) + bx * az_g - t * mx_g
        uy = (oy - oz * by) + by * az_g - t * my_g
    return glass_pixel_at(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, ux, uy, zq_g, tol,
                          max_iter)


@numba.njit(**_JIT)
def glass_pixel_at(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, ux, uy, zq_g, tol,
                   max_iter):
    """:func:`glass_pixel` from a predicted foot point (``ux``, ``uy``; NaN: none), with up to
    ``_SCALAR_STEPS`` foot-point Newton steps until one is accepted (the row kernel's pixels whose
    single vectorised step is not accepted come here too)."""
    nan = np.nan
    if (kind == _KIND_PLANE or kind == _KIND_SPLINE) and wz != 0.0 and np.isfinite(wz) and np.isfinite(ux + uy):
        inv = 1.0 / wz
        bx = wx * inv
        by = wy * inv
        ax = ox - oz * bx
        ay = oy - oz * by
        ok = False
        h = hx = hy = g = nan
        for _ in range(_SCALAR_STEPS):
            h, hx, hy, hxx, hxy, hyy = eval2_kernel(kind, gx, gy, coef, ux, uy)
            ux, uy, h, hx, hy, g, ok = foot_newton(h, hx, hy, hxx, hxy, hyy, ux, uy, ax, ay, bx, by, t, dmax[0],
                                                   dmax[1], tol)
            if ok or not np.isfinite(ux + uy):
                break
        if ok:
            a_x, a_y, a_z, rx, ry, rz, mx, my, enters = glass_ray(ux, uy, h, hx, hy, g, ax, ay, bx, by, wx, wy, wz, t,
                                                                  n_idx)
            if enters:
                zs = zq_g if np.isfinite(zq_g) else _plane_start(ux, uy, h, hx, hy, a_x, a_y, a_z, rx, ry, rz)
                _t, x, y, z, _hx, _hy, st = intersect_kernel(kind, gx, gy, coef, dmax, a_x, a_y, a_z, rx, ry, rz, tol,
                                                             zs, False)
                if st == _NEEDS_SOLVE:
                    _t, x, y, z, _hx, _hy, st = intersect_solve(kind, gx, gy, coef, z_min, z_max, dmax, a_x, a_y, a_z,
                                                                rx, ry, rz, tol, max_iter, z)
                if st == 0 and _inside(gx, gy, x, y, 3.0 * t * (1.0 + abs(bx) + abs(by))):
                    return x, y, z, 0, a_z, mx, my
    zs = zq_g if np.isfinite(zq_g) else nan
    return fallback_trace(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, zs, tol, max_iter)


@numba.njit(**_JIT)
def _in_patch(n, gx, gy, i0, j0, S):
    """Whether the foot points (_UX, _UY) of all n pixels lie strictly inside grid interval i0 of
    ``gx`` and j0 of ``gy`` (the edge intervals open outwards): then each one's patch
    (:func:`_patches_at`, ``_interval``) is that one, and the block is one run of
    :func:`_foot_run`. A point on a grid line, or NaN, answers False (the search per pixel
    decides). One loop without branches (vectorised)."""
    B = _BLK
    x_lo, x_hi, y_lo, y_hi = _patch_box(gx, gy, i0, j0)
    n_in = 0
    for i in range(n):
        n_in += _in_box(S[_UX * B + i], S[_UY * B + i], x_lo, x_hi, y_lo, y_hi)
    return n_in == n


@numba.njit(**_JIT, inline="always")
def _patch_box(gx, gy, i0, j0):
    """The open box (x_lo, x_hi, y_lo, y_hi) of grid interval i0 of ``gx`` and j0 of ``gy``
    where that patch's polynomial is the surface (the edge intervals open outwards)."""
    inf = np.inf
    x_lo = -inf if i0 == 0 else gx[i0]
    x_hi = inf if i0 == gx.shape[0] - 2 else gx[i0 + 1]
    y_lo = -inf if j0 == 0 else gy[j0]
    y_hi = inf if j0 == gy.shape[0] - 2 else gy[j0 + 1]
    return x_lo, x_hi, y_lo, y_hi


@numba.njit(**_JIT)
def _patches_at(n, gx, gy, S, P):
    """Patch offsets of the foot points (_UX, _UY) of n pixels (as ``trace_rows._patches_small``:
    counting grid lines on small grids, bisection otherwise). Where all of them lie inside the
    first one's patch (:func:`_in_patch`: nearly every block), that patch without a search,
    written for the first pixel only, and returns True (else False: every pixel's written)."""
    B = _BLK
    nx = gx.shape[0]
    ny = gy.shape[0]
    nx1 = nx - 1
    i0 = _interval(gx, S[_UX * B])
    j0 = _interval(gy, S[_UY * B])
    if _in_patch(n, gx, gy, i0, j0, S):
        P[_PID * B] = (j0 * nx1 + i0) * 16
        return True
    if nx1 + ny - 1 > _SMALL_GRID:
        for i in range(n):
            P[_PID * B + i] = (_interval(gy, S[_UY * B + i]) * nx1 + _interval(gx, S[_UX * B + i])) * 16
        return False
    for i in range(n):
        P[_PID * B + i] = 0
        P[_PIY * B + i] = 0
    for m in range(1, nx - 1):
        g = gx[m]
        for i in range(n):
            P[_PID * B + i] += S[_UX * B + i] >= g
    for m in range(1, ny - 1):
        g = gy[m]
        for i in range(n):
            P[_PIY * B + i] += S[_UY * B + i] >= g
    if nx > 2:
        g = gx[1]
        for i in range(n):
            P[_PID * B + i] -= S[_UX * B + i] == g
    if ny > 2:
        g = gy[1]
        for i in range(n):
            P[_PIY * B + i] -= S[_UY * B + i] == g
    for i in range(n):
        P[_PID * B + i] = (P[_PIY * B + i] * nx1 + P[_PID * B + i]) * 16
    return False


@numba.njit(**_JIT, inline="always")
def _foot_store(i, ux, uy, h, hx, hy, g, ok, t, n_idx, S):
    """Step 2 for pixel i of the block after its foot step: the refracted ray in the fields of the
    intersection stage (origin _TOX… and its z in _QOZ, direction _TDX…, by height _AX … _INV;
    the start _ZG from the rows above is kept — where there is none the scalar kernels start
    from scratch), the warm-start values (A_z in _QOZ, _GMX, _GMY) and the code (_C: _FALLBACK
    where the step is not accepted or the ray does not enter the plate). The reflected ray's
    origin and direction (_QOX, _QOY, _ROZ, _WX…) stay for the scalar path."""
    B = _BLK
    a_x, a_y, a_z, rx, ry, rz, mx, my, enters = glass_ray(ux, uy, h, hx, hy, g, S[_AX * B + i], S[_AY * B + i],
                                                          S[_BX * B + i], S[_BY * B + i], S[_WX * B + i],
                                                          S[_WY * B + i], S[_WZ * B + i], t, n_idx)
    _refracted_store(i, a_x, a_y, a_z, rx, ry, rz, mx, my, ok & enters & np.isfinite(a_z + rz), S)


@numba.njit(**_JIT, inline="always")
def _refracted_store(i, a_x, a_y, a_z, rx, ry, rz, mx, my, ok, S):
    """The stores of :func:`_foot_store` for pixel i: the refracted ray from A (direction r), its
    parametrisation by height, the warm-start values, and the code (``ok``: 0, else _FALLBACK)."""
    B = _BLK
    inv = 1.0 / rz
    cx = rx * inv
    cy = ry * inv
    S[_TOX * B + i] = a_x
    S[_TOY * B + i] = a_y
    S[_TOZ * B + i] = a_z
    S[_TDX * B + i] = rx
    S[_TDY * B + i] = ry
    S[_TDZ * B + i] = rz
    S[_QOZ * B + i] = a_z
    S[_AX * B + i] = a_x - a_z * cx
    S[_AY * B + i] = a_y - a_z * cy
    S[_BX * B + i] = cx
    S[_BY * B + i] = cy
    S[_INV * B + i] = inv
    S[_GMX * B + i] = mx
    S[_GMY * B + i] = my
    c = S[_C * B + i]
    S[_C * B + i] = c if c != 0.0 else (0.0 if ok else _FALLBACK)


@numba.njit(**_JIT, inline="always")
def _plane_store(i, t, n_idx, S):
    """:func:`_foot_store` after the foot step on a planar emitting surface (z = 0: the plate
    normal m = (0, 0, −1), the outer surface z = −t) for pixel i, with the products by m's zero
    components left out (``fastmath={"contract"}`` does not fold x·0, which may be NaN): the
    same values for finite rays (the foot point does not enter them on a plane; the step was
    accepted, the surface's derivative bounds being 0, where the ray is finite)."""
    B = _BLK
    ax = S[_AX * B + i]
    ay = S[_AY * B + i]
    bx = S[_BX * B + i]
    by = S[_BY * B + i]
    wx = S[_WX * B + i]
    wy = S[_WY * B + i]
    wz = S[_WZ * B + i]
    a_z = -t
    a_x = ax + bx * a_z
    a_y = ay + by * a_z
    wm = -wz
    ww = wx * wx + wy * wy + wz * wz
    eta = 1.0 / n_idx
    f = -eta * wm - math.sqrt(ww - eta * eta * (ww - wm * wm))
    rx = eta * wx
    ry = eta * wy
    rz = eta * wz - f
    ok = (wm < 0.0) & np.isfinite(a_z + rz + ax + ay + bx + by + wx + wy)
    _refracted_store(i, a_x, a_y, a_z, rx, ry, rz, 0.0, 0.0, ok, S)


@numba.njit(**_JIT)
def _foot_run(n, c, gxi, gyj, x_lo, x_hi, y_lo, y_hi, t, n_idx, d2, d3, tol, s1x, s1y, s2x, s2y, S):
    """Foot-point step and refraction (:func:`foot_newton`, :func:`_foot_store`) for pixels
    0 … n − 1 of ``S`` (a view from the run's first pixel), which all evaluate on one bicubic
    patch (coefficients ``c[0:16]``, origin (gxi, gyj), open interval (x_lo, x_hi) ×
    (y_lo, y_hi)): loop-invariant coefficients, no gathers, one loop that LLVM vectorises.
    Where every pixel's predicted foot point v = u_lin + 2·s₁ − s₂ (``s1x`` … ``s2y``: the
    steps of the two rows above, from the run's first pixel) is provably within the foot
    tolerance (:func:`.glass_skip.skip_check_run`), the Newton step is skipped: refraction at v.
    The step taken (or its estimate) is stored in _VX, _VY."""
    B = _BLK
    if skip_check_run(n, c, gxi, gyj, x_lo, x_hi, y_lo, y_hi, t, d2, s1x, s1y, s2x, s2y, S) == n:
        for i in range(n):  # (the check stored the steps' estimates in _VX, _VY)
            _foot_store(i, S[_X * B + i], S[_Y * B + i], S[_Z * B + i], S[_HX * B + i], S[_HY * B + i],
                        S[_CONV * B + i], True, t, n_idx, S)
        return
    c0, c1, c2, c3, c4, c5, c6, c7 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
    c8, c9, c10, c11, c12, c13, c14, c15 = c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15]
    for i in range(n):
        ux = S[_UX * B + i]
        uy = S[_UY * B + i]
        sx = ux - gxi
        sy = uy - gyj
        r0, r1, r2, r3, e1d0, e1d1, e1d2, e1d3 = patch_rows(c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12,
                                                            c13, c14, c15, sx)
        e0 = 2.0 * c2 + 6.0 * sx * c3
        e1 = 2.0 * c6 + 6.0 * sx * c7
        e2 = 2.0 * c10 + 6.0 * sx * c11
        e3 = 2.0 * c14 + 6.0 * sx * c15
        h = r0 + sy * (r1 + sy * (r2 + sy * r3))
        hx = e1d0 + sy * (e1d1 + sy * (e1d2 + sy * e1d3))
        hy = r1 + sy * (2.0 * r2 + sy * 3.0 * r3)
        hxx = e0 + sy * (e1 + sy * (e2 + sy * e3))
        hxy = e1d1 + sy * (2.0 * e1d2 + sy * 3.0 * e1d3)
        hyy = 2.0 * r2 + 6.0 * sy * r3
        ux, uy, h, hx, hy, g, ok = foot_newton(h, hx, hy, hxx, hxy, hyy, ux, uy, S[_AX * B + i], S[_AY * B + i],
                                               S[_BX * B + i], S[_BY * B + i], t, d2, d3, tol)
        S[_VX * B + i] = ux - S[_UX * B + i]
        S[_VY * B + i] = uy - S[_UY * B + i]
        _foot_store(i, ux, uy, h, hx, hy, g, ok, t, n_idx, S)


@numba.njit(**_JIT, inline="always")
def _predict(i, a1, a2, mx1, mx2, my1, my2, t, plane, S):
    """Pixel i of :func:`glass_block`: the outer-surface height A_z and plate normal m extrapolated
    linearly from the two rows above (``a1`` … ``my2``: row − 1, row − 2; where not finite,
    row − 1's; on a plane z = −t and (0, 0, −1)), and the foot point u = a + b·A_z − t·m_xy of the
    reflected ray x = a + b·z. Loads only. Returns ``(u_x, u_y, linear, b_x, b_y)``."""
    B = _BLK
    ax = S[_AX * B + i]
    ay = S[_AY * B + i]
    bx = S[_BX * B + i]
    by = S[_BY * B + i]
    azg = 2.0 * a1[i] - a2[i]
    mxg = 2.0 * mx1[i] - mx2[i]
    myg = 2.0 * my1[i] - my2[i]
    lin = np.isfinite(azg + mxg + myg)
    if not lin:
        azg = a1[i]
        mxg = mx1[i]
        myg = my1[i]
    if plane:
        azg = -t
        mxg = 0.0
        myg = 0.0
    ux = ax + bx * azg - t * mxg
    uy = ay + by * azg - t * myg
    return ux, uy, lin, bx, by


@numba.njit(**_JIT)
def glass_block(n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, zr, col0, slot, S, P):
    """The glass stage of the row kernel for the n pixels of a block (replaces the glass-free
    screen stage; module docstring). On entry the fields of ``trace_rows._to_screen`` (reflected
    ray, code _C, start _ZG from the rows above); ``zr[4:10]``: A_z, m_x, m_y of the two rows above,
    ``zr[10:14]``: their foot-point steps (x, y), from column ``col0`` on, each value in two slots
    (``trace_rows._glass_rows_update``): row − 1 in slot 1 − ``slot``, row − 2 in slot ``slot``,
    which this row's steps replace. On return _X, _Y, _Z hold the emitting-surface point, _C the
    screen code (0 … 3), _QOZ, _GMX, _GMY the warm-start values A_z, m_x, m_y (for the rows
    below)."""
    B = _BLK
    other = 1 - slot
    a1 = zr[4 + other][col0:]
    a2 = zr[4 + slot][col0:]
    mx1 = zr[6 + other][col0:]
    mx2 = zr[6 + slot][col0:]
    my1 = zr[8 + other][col0:]
    my2 = zr[8 + slot][col0:]
    s1x = zr[10 + 2 * other][col0:]
    s1y = zr[11 + 2 * other][col0:]
    s2x = zr[10 + 2 * slot][col0:]
    s2y = zr[11 + 2 * slot][col0:]
    nan = np.nan
    plane = kind == _KIND_PLANE
    # Each pixel's foot point predicted from the rows above (the first pixel's first: the loop
    # also checks every foot point against its patch, which then is the block's one run — what
    # _patches_at would find — without a pass of its own). The reflected ray (origin _QOX…,
    # direction _WX…) stays for the scalar path: the refracted ray goes to _TOX … _TDZ, except
    # its origin's z (A_z), which the intersection stage reads from _QOZ — the reflected one is
    # kept in _ROZ (it was a copy of the six fields, ≈ 2 ms of Table 1's trace:
    # docs/benchmarks.md "Cover glass (issue 21): the glass's rows as a ring").
    i0 = j0 = 0
    x_lo = x_hi = y_lo = y_hi = nan
    if kind == _KIND_SPLINE:
        ux, uy, _lin, _bx, _by = _predict(0, a1, a2, mx1, mx2, my1, my2, t, plane, S)
        i0 = _interval(gx, ux)
        j0 = _interval(gy, uy)
        x_lo, x_hi, y_lo, y_hi = _patch_box(gx, gy, i0, j0)
    n_in = 0
    for i in range(n):
        ux, uy, lin, bx, by = _predict(i, a1, a2, mx1, mx2, my1, my2, t, plane, S)
        n_in += _in_box(ux, uy, x_lo, x_hi, y_lo, y_hi)
        S[_UX * B + i] = ux
        S[_UY * B + i] = uy
        c = S[_C * B + i]
        S[_GM * B + i] = 3.0 * t * (1.0 + abs(bx) + abs(by)) if c == 0.0 else -1.0
        S[_C * B + i] = c if (c != 0.0) | np.isfinite(ux + uy) else _FALLBACK
        S[_LIN * B + i] = 1.0 if lin else 0.0
        S[_ROZ * B + i] = S[_QOZ * B + i]
    d2 = dmax[0]
    d3 = dmax[1]
    if plane:
        for i in range(n):
            _plane_store(i, t, n_idx, S)
    elif kind == _KIND_SPLINE:
        nx1 = gx.shape[0] - 1
        if n_in == n:
            P[_PID * B] = (j0 * nx1 + i0) * 16
            one = True
        else:
            one = _patches_at(n, gx, gy, S, P)
        b0 = P[_PID * B]
        n_other = 0
        if not one:
            for i in range(n):
                n_other += P[_PID * B + i] != b0
        i = 0
        while i < n:
            s = i
            b = P[_PID * B + i]
            i += 1
            if n_other == 0:
                i = n
            while i < n and P[_PID * B + i] == b:
                i += 1
            bi = b // 16
            i0 = bi % nx1
            j0 = bi // nx1
            x_lo, x_hi, y_lo, y_hi = _patch_box(gx, gy, i0, j0)
            _foot_run(i - s, coef[b:b + 16], gx[i0], gy[j0], x_lo, x_hi, y_lo, y_hi, t, n_idx, d2, d3, tol,
                      s1x[s:], s1y[s:], s2x[s:], s2y[s:], S[s:])
    else:
        for i in range(n):
            if S[_C * B + i] == 0.0:
                S[_C * B + i] = _FALLBACK
    # The emitting-surface hit of the refracted rays (the tracer's intersection stage).
    _intersect_block(n, kind, gx, gy, coef, dmax, tol, False, S, P)
    _fixup(n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, np.bool_(False), np.int64(_TOX), np.int64(_TDX),
           S)
    # Pixels the fast path did not settle: more foot-point steps (scalar), else the refracting
    # pass's trace. Counted first in a loop without calls (vectorised): most blocks have none.
    n_left = 0
    for i in range(n):
        mg = S[_GM * B + i]
        settled = (S[_C * B + i] == 0.0) & _inside(gx, gy, S[_X * B + i], S[_Y * B + i], mg)
        n_left += (mg >= 0.0) & (not settled)
    if n_left > 0:
        _scalar_left(n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, S)
    # The foot-point steps of this row, for the skip's prediction in the rows below (glass_skip):
    # where the pixel is valid and had the linear prediction (both rows above valid), into this
    # row's slot (over row − 2's). One loop per row: a loop storing into both is not vectorised.
    if kind != _KIND_SPLINE:
        return
    for f in range(2):
        s_new = zr[10 + 2 * slot + f][col0:]
        for i in range(n):
            valid = (S[_SC * B + i] == 0.0) & (S[_C * B + i] == 0.0) & (S[_LIN * B + i] != 0.0)
            s_new[i] = S[(_VX + f) * B + i] if valid else nan


@numba.njit(**_JIT)
def _scalar_left(n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, S):
    """The pixels of the block that the fast path of :func:`glass_block` did not settle: more
    foot-point steps (scalar), else the refracting pass's trace; their step for the skip's
    prediction (_VX, _VY) is NaN."""
    B = _BLK
    for i in range(n):
        mg = S[_GM * B + i]
        if mg < 0.0:
            continue
        if S[_C * B + i] == 0.0 and _inside(gx, gy, S[_X * B + i], S[_Y * B + i], mg):
            continue
        x, y, z, st, az, mx, my = glass_pixel_at(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, S[_QOX * B + i],
                                                 S[_QOY * B + i], S[_ROZ * B + i], S[_WX * B + i], S[_WY * B + i],
                                                 S[_WZ * B + i], S[_UX * B + i], S[_UY * B + i], S[_ZG * B + i], tol,
                                                 max_iter)
        S[_X * B + i] = x
        S[_Y * B + i] = y
        S[_Z * B + i] = z
        S[_C * B + i] = float(st)
        S[_QOZ * B + i] = az
        S[_GMX * B + i] = mx
        S[_GMY * B + i] = my
        S[_VX * B + i] = np.nan
        S[_VY * B + i] = np.nan
