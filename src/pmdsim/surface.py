"""Surfaces: height fields over a rectangle of their own frame (paper §2.3).

A surface knows its ``height``, its ``gradient`` and how to ``intersect`` rays; the ray tracer
(:mod:`pmdsim.trace`) does not know which surface it is: it receives the surface's
:class:`KernelSurface` data and calls the compiled kernels of this module.

Interpolation follows the paper's two-step not-a-knot scheme (eq. 8). Because a 1-D
interpolating spline is linear in its data, the spline through the values s_{x_i}(y_q),
evaluated at x_q, equals Σ_i Σ_j w_i(x_q) w_j(y_q) Z[j, i], where w are the cardinal
not-a-knot basis splines of the two grid axes. pmdsim precomputes that tensor product as one
bicubic polynomial per grid patch, which evaluates eq. (8) and its exact first derivatives
in a few dozen floating-point operations. Grid lines of 2 points are linear, of 3 points the
parabola through them (what not-a-knot reduces to), of ≥ 4 points not-a-knot cubics.

See docs/conventions.md, "Surfaces", for frames and the sign of heights.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

__all__ = [
    "cardinal_spline_coefficients",
    "SplineSurface",
    "PlaneSurface",
    "KernelSurface",
    "IntersectStatus",
    "INTERSECT_TOL_MM",
]

#: Convergence tolerance of the ray–surface intersection: estimated remaining error of the
#: height in the fixed-point iteration of eqs. 13–16, in mm.
INTERSECT_TOL_MM = 1e-11
#: Fixed-point iterations (eqs. 13–16) before the safeguarded Newton fallback takes over.
FIXED_POINT_MAX_ITER = 60
_NEWTON_MAX_ITER = 200

_KIND_PLANE = 0
_KIND_SPLINE = 1


_HIT = 0
_PARALLEL = 1
_OUTSIDE = 2
_NO_CONVERGENCE = 3


class IntersectStatus:
    """Result codes of :func:`intersect_kernel` (0 = hit)."""

    HIT = _HIT
    PARALLEL = _PARALLEL  # ray parallel to the x–y plane, or the surface lies behind the ray origin
    OUTSIDE = _OUTSIDE  # the ray meets the height field outside the grid's bounds
    NO_CONVERGENCE = _NO_CONVERGENCE  # fixed point and fallback both failed


# ----------------------------------------------------------------------------- 1-D splines
def cardinal_spline_coefficients(knots) -> np.ndarray:
    """Piecewise-polynomial coefficients of the cardinal not-a-knot interpolating splines.

    Basis function j interpolates the unit vector e_j at the knots. On interval i,
    ``w_j(x) = Σ_k C[i, k, j] (x − knots[i])**k``.

    Parameters
    ----------
    knots : array_like, shape (n,)
        Strictly increasing knots, n ≥ 2.

    Returns
    -------
    C : ndarray, shape (n − 1, 4, n)

    Notes
    -----
    n = 2: linear interpolation. n = 3: the parabola through the three points (the not-a-knot
    conditions at the only interior knot leave a single quadratic). n ≥ 4: the standard
    not-a-knot conditions (continuous third derivative at the second and second-to-last knot,
    paper §2.3), solved for the second derivatives M.
    """
    x = np.asarray(knots, dtype=float)
    n = x.size
    if x.ndim != 1 or n < 2:
        raise ValueError(f"a spline grid needs at least 2 knots, got shape {x.shape}")
    h = np.diff(x)
    if not np.all(h > 0) or not np.all(np.isfinite(x)):
        raise ValueError("spline knots must be finite and strictly increasing")
    coef = np.zeros((n - 1, 4, n))
    eye = np.eye(n)
    if n == 2:
        coef[0, 0] = eye[0]
        coef[0, 1] = (eye[1] - eye[0]) / h[0]
        return coef
    # Second-derivative formulation: A M = B y.
    a = np.zeros((n, n))
    b = np.zeros((n, n))
    for i in range(1, n - 1):
        a[i, i - 1] = h[i - 1]
        a[i, i] = 2.0 * (h[i - 1] + h[i])
        a[i, i + 1] = h[i]
        b[i] = 6.0 * ((eye[i + 1] - eye[i]) / h[i] - (eye[i] - eye[i - 1]) / h[i - 1])
    if n == 3:
        # Single parabola: constant second derivative.
        a[0, 0], a[0, 1] = 1.0, -1.0
        a[2, 1], a[2, 2] = -1.0, 1.0
    else:
        # Not-a-knot: (M1 − M0)/h0 = (M2 − M1)/h1 and likewise at the other end.
        a[0, 0] = 1.0 / h[0]
        a[0, 1] = -1.0 / h[0] - 1.0 / h[1]
        a[0, 2] = 1.0 / h[1]
        a[-1, -3] = 1.0 / h[-2]
        a[-1, -2] = -1.0 / h[-2] - 1.0 / h[-1]
        a[-1, -1] = 1.0 / h[-1]
    m = np.linalg.solve(a, b)  # (n, n): M as a linear map of the data
    for i in range(n - 1):
        coef[i, 0] = eye[i]
        coef[i, 1] = (eye[i + 1] - eye[i]) / h[i] - h[i] * (2.0 * m[i] + m[i + 1]) / 6.0
        coef[i, 2] = m[i] / 2.0
        coef[i, 3] = (m[i + 1] - m[i]) / (6.0 * h[i])
    return coef


# ----------------------------------------------------------------------------- kernels
class KernelSurface(NamedTuple):
    """The plain-array description of a surface that the compiled kernels take.

    kind : int
        0 = the plane z = 0 (fast path), 1 = bicubic patches.
    grid_x, grid_y : ndarray (n_x,), (n_y,)
        Grid lines; the first and last are the surface's bounds.
    coef : ndarray ((n_y − 1)·(n_x − 1)·16,)
        Flat patch coefficients: on patch (j, i) (offset 16·(j·(n_x − 1) + i)),
        ``h = Σ_a Σ_b c[4a + b] (y − y_j)**a (x − x_i)**b``.
    z_min, z_max : float
        Conservative bounds of the height inside the grid (for the intersection fallback).
    """

    kind: int
    grid_x: np.ndarray
    grid_y: np.ndarray
    coef: np.ndarray
    z_min: float
    z_max: float


@numba.njit(cache=True, error_model="numpy", inline="always")
def _interval(grid, v):
    """Index i of the grid interval [grid[i], grid[i+1]] holding v (edge intervals extrapolate)."""
    n = grid.shape[0]
    if v <= grid[1]:
        return 0
    if v >= grid[n - 2]:
        return n - 2
    lo = 1
    hi = n - 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if grid[mid] <= v:
            lo = mid
        else:
            hi = mid
    return lo


@numba.njit(cache=True, error_model="numpy", inline="always")
def _patch(gx, gy, x, y):
    """(offset of the patch's 16 coefficients in the flat array, x − x_i, y − y_j)."""
    i = _interval(gx, x)
    j = _interval(gy, y)
    # Unsigned offsets: numba then skips negative-index wrap-around checks on every load.
    base = np.uint64((j * (gx.shape[0] - 1) + i) * 16)
    return base, x - gx[i], y - gy[j]


@numba.njit(cache=True, error_model="numpy", inline="always")
def height_kernel(kind, gx, gy, coef, x, y):
    """Height h(x, y) only (the inner step of the fixed-point iteration, eq. 13).

    ``coef`` is the flat array of patch coefficients (:attr:`KernelSurface.coef`).
    """
    if kind == _KIND_PLANE:
        return 0.0
    b, sx, sy = _patch(gx, gy, x, y)
    r0 = coef[b] + sx * (coef[b + 1] + sx * (coef[b + 2] + sx * coef[b + 3]))
    r1 = coef[b + 4] + sx * (coef[b + 5] + sx * (coef[b + 6] + sx * coef[b + 7]))
    r2 = coef[b + 8] + sx * (coef[b + 9] + sx * (coef[b + 10] + sx * coef[b + 11]))
    r3 = coef[b + 12] + sx * (coef[b + 13] + sx * (coef[b + 14] + sx * coef[b + 15]))
    return r0 + sy * (r1 + sy * (r2 + sy * r3))


@numba.njit(cache=True, error_model="numpy", inline="always")
def eval2_kernel(kind, gx, gy, coef, x, y):
    """Height, gradient and second derivatives (h, h_x, h_y, h_xx, h_xy, h_yy) at (x, y)."""
    if kind == _KIND_PLANE:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    b, sx, sy = _patch(gx, gy, x, y)
    r0 = coef[b] + sx * (coef[b + 1] + sx * (coef[b + 2] + sx * coef[b + 3]))
    r1 = coef[b + 4] + sx * (coef[b + 5] + sx * (coef[b + 6] + sx * coef[b + 7]))
    r2 = coef[b + 8] + sx * (coef[b + 9] + sx * (coef[b + 10] + sx * coef[b + 11]))
    r3 = coef[b + 12] + sx * (coef[b + 13] + sx * (coef[b + 14] + sx * coef[b + 15]))
    d0 = coef[b + 1] + sx * (2.0 * coef[b + 2] + sx * 3.0 * coef[b + 3])
    d1 = coef[b + 5] + sx * (2.0 * coef[b + 6] + sx * 3.0 * coef[b + 7])
    d2 = coef[b + 9] + sx * (2.0 * coef[b + 10] + sx * 3.0 * coef[b + 11])
    d3 = coef[b + 13] + sx * (2.0 * coef[b + 14] + sx * 3.0 * coef[b + 15])
    e0 = 2.0 * coef[b + 2] + 6.0 * sx * coef[b + 3]
    e1 = 2.0 * coef[b + 6] + 6.0 * sx * coef[b + 7]
    e2 = 2.0 * coef[b + 10] + 6.0 * sx * coef[b + 11]
    e3 = 2.0 * coef[b + 14] + 6.0 * sx * coef[b + 15]
    h = r0 + sy * (r1 + sy * (r2 + sy * r3))
    hx = d0 + sy * (d1 + sy * (d2 + sy * d3))
    hy = r1 + sy * (2.0 * r2 + sy * 3.0 * r3)
    hxx = e0 + sy * (e1 + sy * (e2 + sy * e3))
    hxy = d1 + sy * (2.0 * d2 + sy * 3.0 * d3)
    hyy = 2.0 * r2 + 6.0 * sy * r3
    return h, hx, hy, hxx, hxy, hyy


@numba.njit(cache=True, error_model="numpy", inline="always")
def eval_kernel(kind, gx, gy, coef, x, y):
    """Height and exact gradient (h, ∂h/∂x, ∂h/∂y) at (x, y) (eq. 8 and its derivatives).

    Outside the grid the edge patches extrapolate; callers check bounds themselves. (The
    second derivatives that :func:`eval2_kernel` also computes are dropped by the compiler.)
    """
    h, hx, hy, _hxx, _hxy, _hyy = eval2_kernel(kind, gx, gy, coef, x, y)
    return h, hx, hy


@numba.njit(cache=True, error_model="numpy")
def _intersect_fallback(kind, gx, gy, coef, z_min, z_max, ox, oy, oz, dx, dy, dz, tol):
    """Fallback of :func:`intersect_kernel` where the fixed point does not converge.

    The root lies where the ray is both inside the surface's height bounds and above the grid
    rectangle: intersect those parameter intervals, march through them to the first sign
    change of f(t) = o_z + t d_z − h(o_xy + t d_xy) (the first hit along the ray), then refine
    by Newton steps kept inside the bracket (bisection where Newton leaves it).

    Returns (ok, x, y, z, h_x, h_y, status).
    """
    nan = np.nan
    inv_dz = 1.0 / dz
    ta = (z_min - oz) * inv_dz
    tb = (z_max - oz) * inv_dz
    if ta > tb:
        ta, tb = tb, ta
    nxg = gx.shape[0]
    nyg = gy.shape[0]
    if dx != 0.0:
        t1 = (gx[0] - ox) / dx
        t2 = (gx[nxg - 1] - ox) / dx
        ta = max(ta, min(t1, t2))
        tb = min(tb, max(t1, t2))
    elif ox < gx[0] or ox > gx[nxg - 1]:
        return False, nan, nan, nan, nan, nan, _OUTSIDE
    if dy != 0.0:
        t1 = (gy[0] - oy) / dy
        t2 = (gy[nyg - 1] - oy) / dy
        ta = max(ta, min(t1, t2))
        tb = min(tb, max(t1, t2))
    elif oy < gy[0] or oy > gy[nyg - 1]:
        return False, nan, nan, nan, nan, nan, _OUTSIDE
    ta = max(ta, 0.0)
    if not ta < tb:
        return False, nan, nan, nan, nan, nan, _OUTSIDE
    fa = oz + ta * dz - height_kernel(kind, gx, gy, coef, ox + ta * dx, oy + ta * dy)
    found = fa == 0.0
    tlo = ta
    thi = ta
    flo = fa
    n_march = 64
    for m in range(1, n_march + 1):
        if found:
            break
        tm = ta + (tb - ta) * m / n_march
        fm = oz + tm * dz - height_kernel(kind, gx, gy, coef, ox + tm * dx, oy + tm * dy)
        if fm == 0.0 or (fm < 0.0) != (flo < 0.0):
            thi = tm
            found = True
            break
        tlo = tm
        flo = fm
    if not found:
        return False, nan, nan, nan, nan, nan, _NO_CONVERGENCE
    t = 0.5 * (tlo + thi) if thi > tlo else tlo
    scale = abs(dx) + abs(dy) + abs(dz)
    converged = False
    for _ in range(_NEWTON_MAX_ITER):
        if not thi > tlo:
            converged = True
            break
        hv, hx, hy = eval_kernel(kind, gx, gy, coef, ox + t * dx, oy + t * dy)
        f = oz + t * dz - hv
        if f == 0.0:
            converged = True
            break
        if (f < 0.0) == (flo < 0.0):
            tlo = t
            flo = f
        else:
            thi = t
        df = dz - hx * dx - hy * dy
        tn = t - f / df if df != 0.0 else 0.5 * (tlo + thi)
        if not (tlo < tn < thi):
            tn = 0.5 * (tlo + thi)
        step = abs(tn - t) * scale
        t = tn
        if step <= tol:
            converged = True
            break
    if not converged:
        return False, nan, nan, nan, nan, nan, _NO_CONVERGENCE
    x = ox + t * dx
    y = oy + t * dy
    z, hx, hy = eval_kernel(kind, gx, gy, coef, x, y)
    return True, x, y, z, hx, hy, _HIT


@numba.njit(cache=True, error_model="numpy", inline="always")
def intersect_kernel(kind, gx, gy, coef, z_min, z_max, ox, oy, oz, dx, dy, dz, tol, max_iter, z_start,
                     hx_hint=np.nan, hy_hint=np.nan):
    """Intersection of the ray o + t·d with the height field z = h(x, y) (paper eqs. 9–16).

    The paper's fixed-point iteration z ← h(x(z), y(z)) (eq. 13, with x(z), y(z) the ray's
    point at height z, eqs. 14–16) starts at ``z_start`` — the x–y plane z = 0 of eq. (9) when
    ``z_start`` is NaN, or a nearby ray's height as a warm start, optionally with that ray's
    surface gradient (``hx_hint``, ``hy_hint``) to estimate the contraction factor — and stops
    when the height
    has converged to ``tol``: with q = |step_n/step_(n−1)| the observed contraction factor
    (q ≈ |∇h·d_xy/d_z|), the error after one more step is ≈ step·q²/(1 − q); once that is
    ≤ ``tol``, the final step is taken with the gradient (and second derivatives, which carry
    the gradient to the returned point) for eq. (17). If it has not converged after ``max_iter`` steps (q ≥ 1: steep surface
    or grazing ray), a fallback takes over: the first sign change of
    f(t) = o_z + t d_z − h(o_xy + t d_xy) within the part of the ray that lies inside the
    surface's height bounds and over its grid rectangle, refined by bracketed Newton steps.

    Returns
    -------
    (t, x, y, z, h_x, h_y, status)
        The ray parameter, the point, the surface gradient there and an
        :class:`IntersectStatus` code.
    """
    nan = np.nan
    if dz == 0.0 or not np.isfinite(dz):
        return nan, nan, nan, nan, nan, nan, _PARALLEL
    # The ray as a function of the height z: x = ax + bx·z, y = ay + by·z (eqs. 10–12 and 14–16
    # with t eliminated), so that one fixed-point step is a height evaluation and two FMAs.
    inv_dz = 1.0 / dz
    bx = dx * inv_dz
    by = dy * inv_dz
    ax = ox - oz * bx
    ay = oy - oz * by
    z = 0.0 if (kind == _KIND_PLANE or not np.isfinite(z_start)) else z_start  # eq. (9)
    x = ax + bx * z
    y = ay + by * z
    hx = 0.0
    hy = 0.0
    converged = kind == _KIND_PLANE
    if not converged:
        step_prev = -1.0  # no previous step yet
        q_hint = 2.0 * abs(hx_hint * bx + hy_hint * by) + 1e-6
        if not (np.isfinite(q_hint) and np.isfinite(z_start)):
            q_hint = 1.0  # no hint: wait for two steps
        for _ in range(max_iter):
            znew = height_kernel(kind, gx, gy, coef, x, y)  # eq. (13)
            x = ax + bx * znew  # eqs. (14)–(16)
            y = ay + by * znew
            step = abs(znew - z)
            z = znew
            if step == 0.0:
                converged = True
                break
            # Linear convergence with factor q: the error now is ≈ step·q/(1 − q), and after
            # the final step below ≈ step·q²/(1 − q). q is estimated from the last two steps,
            # or — after the first step of a warm start — from the neighbouring ray's surface
            # gradient (q = |h_x·d_x/d_z + h_y·d_y/d_z| at the fixed point), with a safety
            # factor of 2.
            if step_prev > 0.0:
                q = step / step_prev
                if q < 0.5 and step * q * q / (1.0 - q) <= tol:
                    converged = True
                    break
            elif q_hint < 0.25 and step * q_hint * q_hint / (1.0 - q_hint) <= tol:
                converged = True
                break
            step_prev = step
        if converged:
            # The final step of eq. (13) also gives the gradient for eq. (17). It is evaluated
            # at the point before that step and carried to the returned point to first order
            # with the second derivatives (the remaining gradient error is second order in a
            # height change that is already ≤ step·q).
            zf, hx, hy, hxx, hxy, hyy = eval2_kernel(kind, gx, gy, coef, x, y)
            ddx = bx * (zf - z)
            ddy = by * (zf - z)
            hx += hxx * ddx + hxy * ddy
            hy += hxy * ddx + hyy * ddy
            z = zf
            x = ax + bx * z
            y = ay + by * z
        if not converged:
            ok, x, y, z, hx, hy, code = _intersect_fallback(kind, gx, gy, coef, z_min, z_max, ox, oy, oz, dx, dy, dz,
                                                            tol)
            if not ok:
                return nan, nan, nan, nan, nan, nan, code
    t = (z - oz) * inv_dz
    if not t > 0.0:
        return t, x, y, z, hx, hy, _PARALLEL
    if x < gx[0] or x > gx[gx.shape[0] - 1] or y < gy[0] or y > gy[gy.shape[0] - 1]:
        return t, x, y, z, hx, hy, _OUTSIDE
    return t, x, y, z, hx, hy, _HIT


# Parallel loops are thin wrappers over chunks that call a serial, compiled function: numba's
# parallel lowering of large inlined bodies is slow to compile, a call per chunk is not.
_CHUNK = 4096


@numba.njit(cache=True, error_model="numpy")
def _eval_range(start, end, kind, gx, gy, coef, x, y, out):
    for k in range(start, end):
        h, hx, hy = eval_kernel(kind, gx, gy, coef, x[k], y[k])
        out[k, 0] = h
        out[k, 1] = hx
        out[k, 2] = hy


@numba.njit(cache=True, parallel=True)
def _eval_many(kind, gx, gy, coef, x, y, out):
    n = x.shape[0]
    for c in numba.prange((n + _CHUNK - 1) // _CHUNK):
        _eval_range(c * _CHUNK, min(n, (c + 1) * _CHUNK), kind, gx, gy, coef, x, y, out)


@numba.njit(cache=True, error_model="numpy")
def _intersect_range(start, end, kind, gx, gy, coef, z_min, z_max, o, d, tol, max_iter, t_out, p_out, status):
    for k in range(start, end):
        t, x, y, z, hx, hy, st = intersect_kernel(
            kind, gx, gy, coef, z_min, z_max, o[k, 0], o[k, 1], o[k, 2], d[k, 0], d[k, 1], d[k, 2],
            tol, max_iter, np.nan,
        )
        t_out[k] = t
        p_out[k, 0] = x
        p_out[k, 1] = y
        p_out[k, 2] = z
        status[k] = st


@numba.njit(cache=True, parallel=True)
def _intersect_many(kind, gx, gy, coef, z_min, z_max, o, d, tol, max_iter, t_out, p_out, status):
    n = o.shape[0]
    for c in numba.prange((n + _CHUNK - 1) // _CHUNK):
        _intersect_range(c * _CHUNK, min(n, (c + 1) * _CHUNK), kind, gx, gy, coef, z_min, z_max, o, d,
                         tol, max_iter, t_out, p_out, status)


# ----------------------------------------------------------------------------- classes
class _SurfaceBase:
    """Shared evaluation and intersection on top of :attr:`kernel`."""

    kernel: KernelSurface

    @property
    def bounds_mm(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the surface in its own frame."""
        k = self.kernel
        return float(k.grid_x[0]), float(k.grid_x[-1]), float(k.grid_y[0]), float(k.grid_y[-1])

    def _eval(self, x, y) -> np.ndarray:
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        shape = x.shape
        out = np.empty((x.size, 3))
        k = self.kernel
        _eval_many(k.kind, k.grid_x, k.grid_y, k.coef, np.ascontiguousarray(x.ravel()),
                   np.ascontiguousarray(y.ravel()), out)
        return out.reshape(shape + (3,))

    def height(self, x_mm, y_mm) -> np.ndarray:
        """h(x, y) in mm (eq. 8); x, y broadcast. Outside the bounds the edge patches extrapolate."""
        return self._eval(x_mm, y_mm)[..., 0]

    def gradient(self, x_mm, y_mm) -> np.ndarray:
        """(∂h/∂x, ∂h/∂y), shape broadcast(x, y).shape + (2,)."""
        return self._eval(x_mm, y_mm)[..., 1:]

    def normal(self, x_mm, y_mm) -> np.ndarray:
        """Unnormalised normal n = (−∂h/∂x, −∂h/∂y, 1) (paper §2.4), shape (..., 3)."""
        e = self._eval(x_mm, y_mm)
        return np.stack([-e[..., 1], -e[..., 2], np.ones_like(e[..., 0])], axis=-1)

    def contains(self, x_mm, y_mm) -> np.ndarray:
        """True where (x, y) lies within the grid bounds."""
        x0, x1, y0, y1 = self.bounds_mm
        x = np.asarray(x_mm)
        y = np.asarray(y_mm)
        return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)

    def intersect(self, origin, direction, tol_mm: float = INTERSECT_TOL_MM):
        """Intersect rays with the surface (eqs. 9–16 with a safeguarded fallback).

        Parameters
        ----------
        origin, direction : array_like, shape (..., 3)
            Ray origins and directions in the surface's frame (broadcast).

        Returns
        -------
        t : ndarray (...)
            Ray parameter of the hit (p = o + t d).
        p : ndarray (..., 3)
            Intersection points in the surface's frame.
        status : ndarray of uint8 (...)
            :class:`IntersectStatus` codes; t and p are NaN or meaningless where status ≠ HIT.
        """
        o, d = np.broadcast_arrays(np.asarray(origin, dtype=float), np.asarray(direction, dtype=float))
        if o.shape[-1] != 3:
            raise ValueError(f"origin/direction must have shape (..., 3), got {o.shape}")
        shape = o.shape[:-1]
        of = np.ascontiguousarray(o.reshape(-1, 3))
        df = np.ascontiguousarray(d.reshape(-1, 3))
        t = np.empty(of.shape[0])
        p = np.empty_like(of)
        st = np.empty(of.shape[0], dtype=np.uint8)
        k = self.kernel
        _intersect_many(k.kind, k.grid_x, k.grid_y, k.coef, k.z_min, k.z_max, of, df, tol_mm,
                        FIXED_POINT_MAX_ITER, t, p, st)
        return t.reshape(shape), p.reshape(shape + (3,)), st.reshape(shape)


def _validate_grid(name: str, g) -> np.ndarray:
    a = np.array(g, dtype=float)
    if a.ndim != 1 or a.size < 2:
        raise ValueError(f"{name} must be a list of at least 2 grid coordinates, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if not np.all(np.diff(a) > 0):
        raise ValueError(f"{name} must be strictly increasing, got {a.tolist()}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SplineSurface(_SurfaceBase):
    """Height field interpolated by not-a-knot cubic splines over a rectilinear grid (paper §2.3).

    Parameters
    ----------
    grid_x_mm : array_like, shape (n_x,)
        X_s, strictly increasing (eq. 5), n_x ≥ 2.
    grid_y_mm : array_like, shape (n_y,)
        Y_s, strictly increasing (eq. 6), n_y ≥ 2.
    heights_mm : array_like, shape (n_y, n_x)
        Z_s (eq. 7): ``heights_mm[j, i]`` is the height at (x_i, y_j).
    """

    grid_x_mm: np.ndarray
    grid_y_mm: np.ndarray
    heights_mm: np.ndarray

    def __post_init__(self) -> None:
        gx = _validate_grid("grid_x_mm", self.grid_x_mm)
        gy = _validate_grid("grid_y_mm", self.grid_y_mm)
        z = np.array(self.heights_mm, dtype=float)
        if z.shape != (gy.size, gx.size):
            raise ValueError(
                f"heights_mm must have shape (len(grid_y_mm), len(grid_x_mm)) = ({gy.size}, {gx.size}), got {z.shape}"
            )
        if not np.all(np.isfinite(z)):
            raise ValueError("heights_mm contains NaN or infinite values")
        z.setflags(write=False)
        object.__setattr__(self, "grid_x_mm", gx)
        object.__setattr__(self, "grid_y_mm", gy)
        object.__setattr__(self, "heights_mm", z)
        cx = cardinal_spline_coefficients(gx)  # (nx-1, 4, nx)
        cy = cardinal_spline_coefficients(gy)  # (ny-1, 4, ny)
        patches = np.einsum("jay,ibx,yx->jiab", cy, cx, z)
        patches = np.ascontiguousarray(patches)
        # Conservative height bounds over each patch.
        lx = np.diff(gx)[None, :, None, None] ** np.arange(4)[None, None, None, :]
        ly = np.diff(gy)[:, None, None, None] ** np.arange(4)[None, None, :, None]
        mag = np.abs(patches) * lx * ly
        spread = mag.sum(axis=(2, 3)) - mag[:, :, 0, 0]
        z_min = float(np.min(patches[:, :, 0, 0] - spread)) - 1e-9
        z_max = float(np.max(patches[:, :, 0, 0] + spread)) + 1e-9
        kind = _KIND_PLANE if not np.any(z) else _KIND_SPLINE
        coef = np.ascontiguousarray(patches.reshape(-1))
        coef.setflags(write=False)
        object.__setattr__(self, "kernel", KernelSurface(kind, gx, gy, coef, z_min, z_max))

    @classmethod
    def from_bulge(cls, grid_x_mm, grid_y_mm, bulge_mm: float) -> "SplineSurface":
        """Grid with all border heights 0 and the central control point at ``bulge_mm`` (paper §2.5).

        Both grids need an odd number of lines so that a central control point exists.
        """
        gx = np.asarray(grid_x_mm, dtype=float)
        gy = np.asarray(grid_y_mm, dtype=float)
        if gx.size % 2 == 0 or gy.size % 2 == 0:
            raise ValueError("a central bulge needs an odd number of grid lines in x and in y")
        z = np.zeros((gy.size, gx.size))
        z[gy.size // 2, gx.size // 2] = bulge_mm
        return cls(gx, gy, z)

    @property
    def is_planar(self) -> bool:
        """True when all control heights are zero (the kernels then use the plane fast path)."""
        return self.kernel.kind == _KIND_PLANE


@dataclass(frozen=True, eq=False)
class PlaneSurface(_SurfaceBase):
    """The plane z = 0 of its frame, bounded by a rectangle: the fast path of the tracer.

    Parameters
    ----------
    x_range_mm, y_range_mm : (float, float)
        (min, max) bounds.
    """

    x_range_mm: tuple[float, float]
    y_range_mm: tuple[float, float]

    def __post_init__(self) -> None:
        gx = _validate_grid("x_range_mm", self.x_range_mm)
        gy = _validate_grid("y_range_mm", self.y_range_mm)
        if gx.size != 2 or gy.size != 2:
            raise ValueError("PlaneSurface ranges must be (min, max) pairs")
        object.__setattr__(self, "x_range_mm", (float(gx[0]), float(gx[1])))
        object.__setattr__(self, "y_range_mm", (float(gy[0]), float(gy[1])))
        object.__setattr__(
            self, "kernel", KernelSurface(_KIND_PLANE, gx, gy, np.zeros(16), -1e-9, 1e-9)
        )

    is_planar = True
