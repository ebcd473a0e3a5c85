"""The cover-glass stage compiled only into the tracer that uses it (issue 25 item 2).

The tracer's band kernel (:func:`pmdsim.simulation.trace._trace_run`) and row kernel
(:func:`pmdsim.simulation.trace_rows.trace_row`) call the glass stage
(:mod:`pmdsim.simulation.glass_rows`) through the two functions here, with a compile-time flag
``with_glass`` (a boolean literal: the tracer's two entry kernels pass the constants ``True`` and
``False``). numba types an ``@overload`` per literal value: with ``True`` the call is the glass
stage itself, with ``False`` a stub that returns nothing useful and is never reached (the tracer
branches on the run-time thickness too). The glass-free tracer therefore neither types nor
compiles the glass stage: measured on a cold cache (`benchmarks/bench_compile.py simulate`,
docs/benchmarks.md "First run: the glass stage compiled only where used"), the glass stage was
half of the tracer's compile.

A non-literal flag (a call from Python, or a caller that lost the literal) gets the glass stage:
correct, only slower to compile.
"""

from __future__ import annotations

import numpy as np
from numba.core import types
from numba.extending import overload

from . import glass_rows

__all__ = ["glass_pixel_if", "glass_block_if"]


def glass_pixel_if(with_glass, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, az_g, mx_g,
                   my_g, zq_g, tol, max_iter):
    """:func:`pmdsim.simulation.glass_rows.glass_pixel` where ``with_glass`` is ``True`` (compiled
    code only; ``with_glass`` a literal). Returns ``(x, y, z, code, A_z, m_x, m_y)``."""
    raise TypeError("glass_pixel_if is called from numba-compiled code only")


def glass_block_if(with_glass, n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, zr, col0, slot, S,
                   P):
    """:func:`pmdsim.simulation.glass_rows.glass_block` where ``with_glass`` is ``True`` (compiled
    code only; ``with_glass`` a literal)."""
    raise TypeError("glass_block_if is called from numba-compiled code only")


def _literal_false(flag) -> bool:
    return isinstance(flag, types.BooleanLiteral) and not flag.literal_value


@overload(glass_pixel_if, prefer_literal=True)
def _ov_glass_pixel_if(with_glass, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, az_g,
                       mx_g, my_g, zq_g, tol, max_iter):
    if _literal_false(with_glass):
        def stub(with_glass, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, az_g, mx_g,
                 my_g, zq_g, tol, max_iter):
            nan = np.nan
            return nan, nan, nan, 3, nan, nan, nan
        return stub

    def impl(with_glass, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, az_g, mx_g, my_g,
             zq_g, tol, max_iter):
        return glass_rows.glass_pixel(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, wx, wy, wz, az_g,
                                      mx_g, my_g, zq_g, tol, max_iter)
    return impl


@overload(glass_block_if, prefer_literal=True)
def _ov_glass_block_if(with_glass, n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, zr, col0, slot,
                       S, P):
    if _literal_false(with_glass):
        def stub(with_glass, n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, zr, col0, slot, S,
                 P):
            return None
        return stub

    def impl(with_glass, n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, zr, col0, slot, S,
             P):
        glass_rows.glass_block(n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, t, n_idx, zr, col0, slot,
                               S, P)
    return impl
