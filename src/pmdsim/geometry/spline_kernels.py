"""Compiled kernels of the bicubic patch surfaces alone (issue 25 item 2: the tracer's compile).

:mod:`pmdsim.geometry.surface` evaluates every surface kind through ``height_kernel`` and
``eval2_kernel``, which dispatch on the kind at run time (the plane, the bicubic patches, the
closed-form quadrics of :mod:`pmdsim.geometry.shape_kernels`). The intersection kernels reach
their iterations (the Newton steps, the fixed-point iteration of eq. 13 and its bracketed
fallback) only for the bicubic patches: the plane and the quadrics return in closed form
before. Those iterations call the functions here, so that numba types, lowers and LLVM
optimises the patch arithmetic alone there, not every kind's at each of the many inlined call
sites (measured in docs/benchmarks.md, "First run: the tracer's compile cut"). The operations
are those of the patch branch of ``eval2_kernel``, in the same order: the results are
bit-identical.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["spline_height", "spline_eval2"]


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
def spline_height(gx, gy, coef, x, y):
    """Height h(x, y) of the bicubic patches (``coef``: :attr:`~pmdsim.geometry.surface.KernelSurface.coef`)."""
    b, sx, sy = _patch(gx, gy, x, y)
    r0 = coef[b] + sx * (coef[b + 1] + sx * (coef[b + 2] + sx * coef[b + 3]))
    r1 = coef[b + 4] + sx * (coef[b + 5] + sx * (coef[b + 6] + sx * coef[b + 7]))
    r2 = coef[b + 8] + sx * (coef[b + 9] + sx * (coef[b + 10] + sx * coef[b + 11]))
    r3 = coef[b + 12] + sx * (coef[b + 13] + sx * (coef[b + 14] + sx * coef[b + 15]))
    return r0 + sy * (r1 + sy * (r2 + sy * r3))


@numba.njit(cache=True, error_model="numpy", inline="always")
def spline_eval2(gx, gy, coef, x, y):
    """(h, h_x, h_y, h_xx, h_xy, h_yy) of the bicubic patches at (x, y) (exact derivatives)."""
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


# Out-of-line entry points for the intersection fallbacks (``intersect_solve``'s fixed-point
# iteration and ``_intersect_fallback``, both compiled without fastmath flags, like these):
# called, not inlined at each of their call sites.
@numba.njit(cache=True, error_model="numpy", _nrt=False)
def spline_height_call(gx, gy, coef, x, y):
    """:func:`spline_height`, compiled once."""
    return spline_height(gx, gy, coef, x, y)


@numba.njit(cache=True, error_model="numpy", _nrt=False)
def spline_eval2_call(gx, gy, coef, x, y):
    """:func:`spline_eval2`, compiled once."""
    return spline_eval2(gx, gy, coef, x, y)
