"""The consistency checks' noise model reads each stack's offset A and fit residual RSS at its
≤ 60 000 sampled pixels only (issue 25, item 1): computed there, not over the whole image.

:func:`stack_at_pixels` evaluates, at the given pixels of one (N, H, W) stack with equal shifts,
the N-step fit's A and RSS with the arithmetic of ``consistency._stack_kernel`` in the same order
(per pixel: Σ_k I_k, Σ_k I_k cos δ_k, Σ_k I_k sin δ_k in k order; A = ΣI/N, C = 2ΣI cos/N,
S = 2ΣI sin/N; RSS = Σ_k (I_k − A − C cos δ_k − S sin δ_k)² in k order; no fast-math), so the
values are those of the full maps at those pixels bit for bit (tests/test_consistency_kernels.py).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .phase import equal_shifts

__all__ = ["stack_at_pixels"]


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _at_pixels_kernel(images, cos_d, sin_d, idx, a_out, rss_out):
    """A and RSS of the N-step fit at the flat pixel indices ``idx`` (module docstring)."""
    n, h, w = images.shape
    for j in range(idx.size):
        v = idx[j] // w
        u = idx[j] - v * w
        sa = 0.0
        sc = 0.0
        ss = 0.0
        for k in range(n):
            x = np.float64(images[k, v, u])
            sa += x
            sc += x * cos_d[k]
            ss += x * sin_d[k]
        a = sa / n
        c = 2.0 * sc / n
        s = 2.0 * ss / n
        rss = 0.0
        for k in range(n):
            r = np.float64(images[k, v, u]) - a - c * cos_d[k] - s * sin_d[k]
            rss += r * r
        a_out[j] = a
        rss_out[j] = rss


def stack_at_pixels(stack, idx) -> tuple[np.ndarray, np.ndarray]:
    """A and RSS of the N-step fit of one stack at some pixels.

    Parameters
    ----------
    stack : array_like (N, H, W)
        Grey levels of N images with equal shifts δ_k = 2πk/N (integer or float).
    idx : (M,) int64
        Flat pixel indices into (H, W).

    Returns
    -------
    a, rss : (M,) float64
        Offset and residual sum of squares (0 for N ≤ 3: an exact fit), equal bit for bit to
        ``consistency._stack_stats``'s maps at those pixels.
    """
    arr = np.asarray(stack)
    if arr.dtype.kind not in "uif" or not arr.dtype.isnative:
        arr = arr.astype(np.float64)
    arr = np.ascontiguousarray(arr)
    n = arr.shape[0]
    d = equal_shifts(n)
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    a, rss = np.empty(idx.size), np.empty(idx.size)
    _at_pixels_kernel(readonly(arr), np.cos(d), np.sin(d), idx, a, rss)
    if n <= 3:
        rss[:] = 0.0
    return a, rss
