"""The robust paraboloid fit's weighted sums on both numba threads (issue 25, item 1).

Each IRLS iteration of :func:`pmdsim.evaluation.surface_fit.fit_paraboloid_slopes` needs the 18
sums Σ w·(x², xy, y², x, y, 1, g·x, g·y, g) of the g_x rows and of the g_y rows, w the bisquare
weights of the residuals at the current coefficients. The points are cut into fixed blocks of
4096; ``prange`` hands the blocks to the threads, each block's 18 partial sums go to its own row
of a (blocks, 18) array, and one serial pass adds the rows in block order. The blocks and the
order of that addition do not depend on the number of threads: the sums are the same bits with
one thread or two (tests/test_surface_fit_sums.py, in subprocesses).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import SERIAL_BELOW_PX, numba_threads, readonly

__all__ = ["add_rows", "moments", "weighted_sums", "SUM_BLOCK"]

#: Points per block of partial sums (the serial kernel's blocks: the same partial sums).
SUM_BLOCK = 4096


@numba.njit(cache=True, nogil=True, inline="always")
def moments(acc, w, xi, yi, xx, xy, yy):
    """(acc[0] + w·xx, acc[1] + w·xy, acc[2] + w·yy, acc[3] + w·xi, acc[4] + w·yi, acc[5] + w):
    the weighted sums of one design row's (x², xy, y², x, y, 1), continued (``acc`` a 6-tuple
    in every caller: one type)."""
    return (acc[0] + w * xx, acc[1] + w * xy, acc[2] + w * yy, acc[3] + w * xi, acc[4] + w * yi, acc[5] + w)


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"}, parallel=True)
def _block_sums(x, y, gx, gy, xc, yc, coef, scale, robust, part):  # pragma: no cover - compiled
    """Row k of ``part`` (B, 18): the 18 sums of block k (points k·4096 …), at (x − xc, y − yc),
    w the bisquare weights (1 − (r/scale)²)² (0 beyond) at ``coef``, or 1 if not ``robust``.

    r/scale is formed as r·(1/scale) (vector lanes; a partial sum per lane, reassociated); the
    weight as max(1 − u², 0)² (a max instead of a test of |u| and a select: 6 % less CPU, the
    same weights bit for bit)."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    inv = 1.0 / scale
    m = x.size
    for k in numba.prange(0, part.shape[0]):
        start = k * SUM_BLOCK
        stop = min(start + SUM_BLOCK, m)
        sx = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        sy = sx
        for i in range(start, stop):
            xi = x[i] - xc
            yi = y[i] - yc
            gxi = gx[i]
            gyi = gy[i]
            wx = 1.0
            wy = 1.0
            if robust:
                ux = (gxi - (a2 * xi + b * yi + d)) * inv
                uy = (gyi - (b * xi + c2 * yi + e)) * inv
                # (1 − u²)² where |u| < 1, else 0: 1 − u·u (contracted or not) is positive exactly
                # where |u| < 1 (|u| ≤ 1 − 2⁻⁵³ gives u·u ≤ 1 − 2⁻⁵²): the weights of the |u| test
                qx = max(1.0 - ux * ux, 0.0)
                qy = max(1.0 - uy * uy, 0.0)
                wx = qx * qx
                wy = qy * qy
            xx = xi * xi
            xy = xi * yi
            yy = yi * yi
            sx = (moments(sx[:6], wx, xi, yi, xx, xy, yy)
                  + (sx[6] + wx * gxi * xi, sx[7] + wx * gxi * yi, sx[8] + wx * gxi))
            sy = (moments(sy[:6], wy, xi, yi, xx, xy, yy)
                  + (sy[6] + wy * gyi * xi, sy[7] + wy * gyi * yi, sy[8] + wy * gyi))
        for j in range(9):
            part[k, j] = sx[j]
            part[k, 9 + j] = sy[j]


@numba.njit(cache=True, nogil=True, fastmath=False)
def _add_rows(part, out):  # pragma: no cover - compiled
    for k in range(0, part.shape[0]):
        for j in range(0, part.shape[1]):
            out[j] += part[k, j]


def add_rows(part, out) -> None:
    """``out`` (S,) += row 0 + row 1 + … of ``part`` (B, S), in that order (no reassociation):
    partial sums combined independently of the threads that made them."""
    _add_rows(readonly(np.ascontiguousarray(part, dtype=np.float64)), out)


def weighted_sums(x, y, gx, gy, xc, yc, coef, scale, robust) -> np.ndarray:
    """The 18 sums (first 9 of the g_x rows, last 9 of the g_y rows) of the module docstring.

    Parameters
    ----------
    x, y, gx, gy : ndarray (M,) float64, read-only
        Points and slopes.
    xc, yc : float
        The origin the coordinates are taken from.
    coef : ndarray (5,)
        (a, b, c, d, e) of the residuals the weights are formed from.
    scale : float
        The bisquare scale 4.685·MAD/0.6745 (ignored unless ``robust``).
    robust : bool
        Bisquare weights, or all 1.

    Returns
    -------
    ndarray (18,)
    """
    part = np.empty(((x.size + SUM_BLOCK - 1) // SUM_BLOCK, 18))
    # (few points: one thread — the same blocks, the same bits — without the threads' barrier)
    with numba_threads(1 if x.size < SERIAL_BELOW_PX else numba.get_num_threads()):
        _block_sums(x, y, gx, gy, float(xc), float(yc), readonly(np.asarray(coef, dtype=np.float64)), float(scale),
                    bool(robust), part)
    out = np.zeros(18)
    add_rows(part, out)
    return out
