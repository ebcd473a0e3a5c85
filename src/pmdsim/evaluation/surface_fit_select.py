"""The robust paraboloid fit's median and MAD from one pass over the points (issue 25, item 1).

Each IRLS iteration of :func:`pmdsim.evaluation.surface_fit.fit_paraboloid_slopes` needs the
exact median m of the 2M slope residuals r and the exact median of their deviations |r − m|.
From the second iteration on, both are bracketed (the order statistics move by at most δ, the
deviations' by 2δ): m's two middle values lie in [lo, hi], the deviations' in [dlo, dhi].
The deviations' pass needs m exactly, but not to decide most points: for every centre c in
[lo, hi],

* r with hi − dlo < r < lo + dlo has |r − c| < dlo (counted),
* r < lo − dhi or r > hi + dhi has |r − c| > dhi (ignored),

and only the r between (two narrow zones around m ± MAD) are kept. So one pass collects the
residuals in [lo, hi] (the median's selection) and those zones' residuals; once m is selected
from the first, the deviations of the second are formed — abs(r − m), the operation of the
two-pass path, so the same values — counted and selected. The medians are the exact order
statistics either way (bit-identical to the two-pass path); where a bracket holds too many values
or misses a rank, :func:`median_and_mad` returns None and the caller takes the two-pass path.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .surface_fit import _BRACKET_SIGMAS, _pair, _pick

__all__ = ["median_and_mad", "sample_bracket"]

_BLOCK = 256  # points counted before a block is re-read for its values to copy


@numba.njit(cache=True, nogil=True, fastmath=False)
def _collect_both(x, y, gx, gy, xc, yc, coef, lo, hi, dlo, dhi, buf_r, buf_z):
    """One pass over the 2M residuals r: the number < lo and those in [lo, hi] (to ``buf_r``);
    the number with hi − dlo < r < lo + dlo and the others in [lo − dhi, hi + dhi] (to
    ``buf_z``), as many as fit — one less than the buffer's size (the latter two classes' bounds moved inwards, resp. outwards, by
    8 ulps of |lo| + |hi| + dhi: the rounding of r − c and of the bounds cannot misclassify). Returns (below, n_r, sure, n_z); n ≥ buffer size: too many.
    Blocks of 256 points are counted without branches and re-read only where they hold a value
    to copy."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    last_r = buf_r.size - 1
    last_z = buf_z.size - 1
    # the classes' bounds moved by a few ulps towards "collect": r − c and the bounds are rounded
    tol = 8.0 * 2.220446049250313e-16 * (abs(lo) + abs(hi) + dhi)
    zlo = lo - dhi - tol
    zhi = hi + dhi + tol
    slo = hi - dlo + tol
    shi = lo + dlo - tol
    below = n_r = sure = n_z = 0
    for start in range(0, x.size, _BLOCK):
        stop = min(start + _BLOCK, x.size)
        cnt = 0  # values to copy in this block
        for i in range(start, stop):
            r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, 0, 0.0)
            below += (r0 < lo) + (r1 < lo)
            s0 = (r0 > slo) * (r0 < shi)
            s1 = (r1 > slo) * (r1 < shi)
            sure += s0 + s1
            cnt += ((r0 >= lo) * (r0 <= hi) + (r1 >= lo) * (r1 <= hi)
                    + (r0 >= zlo) * (r0 <= zhi) * (1 - s0) + (r1 >= zlo) * (r1 <= zhi) * (1 - s1))
        if cnt:  # each value is written to the next free slot, which only a value to keep advances
            for i in range(start, stop):  # (no branch per value: they are unpredictable)
                for r in _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, 0, 0.0):
                    buf_r[min(n_r, last_r)] = r
                    n_r += (r >= lo) * (r <= hi)
                    buf_z[min(n_z, last_z)] = r
                    n_z += (r >= zlo) * (r <= zhi) * (1 - (r > slo) * (r < shi))
    return below, n_r, sure, n_z


@numba.njit(cache=True, nogil=True, fastmath=False, inline="always")
def split_value(v, lo, hi, out, below, inside):
    """``v`` counted (``below`` + 1) if < lo, written to ``out[inside]`` if in [lo, hi]; returns
    the new (below, inside)."""
    if v < lo:
        return below + 1, inside
    if v <= hi:
        out[inside] = v
        return below, inside + 1
    return below, inside


@numba.njit(cache=True, nogil=True, fastmath=False)
def _deviations(z, centre, dlo, dhi, out):
    """|z − centre| of the collected residuals: the number < dlo, and those in [dlo, dhi]
    written to ``out``; returns (below, inside)."""
    below = 0
    inside = 0
    for i in range(z.size):
        below, inside = split_value(abs(z[i] - centre), dlo, dhi, out, below, inside)
    return below, inside


def median_and_mad(x, y, gx, gy, coef, bracket, dev_bracket, buf_r, buf_z, *, sample=None, origin=(0.0, 0.0)):
    """(median, lower and upper middle values) of the 2M residuals at ``coef`` and the same of
    their absolute deviations from that median — as two calls of
    :func:`pmdsim.evaluation.surface_fit._median` with ``ranks=True`` — from one pass, or None
    where the brackets do not allow it (too many values for the buffers, a rank outside).

    Parameters
    ----------
    x, y, gx, gy : (M,) float64
        Centred coordinates and slopes of the points.
    coef : (5,) float64
        (a, b, c, d, e) of the residuals.
    bracket, dev_bracket : (lo, hi)
        Expected to hold the two middle residuals and the two middle deviations.
    buf_r, buf_z : (K,) float64
        Scratch buffers (the deviations kept are written over ``buf_r``).
    sample : (S,) float64, sorted, optional
        Every k-th residual: a pass expected to overflow a buffer is not started (None returned).
    origin : (xc, yc)
        The residuals are those at (x − xc, y − yc).
    """
    lo, hi = bracket
    dlo, dhi = dev_bracket
    x, y, gx, gy = readonly(x), readonly(y), readonly(gx), readonly(gy)  # one argument type of the kernel
    if not (lo <= hi and 0.0 <= dlo <= dhi):
        return None
    if hi - dlo >= lo + dlo:  # (about) no residual is surely within dlo of every centre: too many to keep
        return None
    if sample is not None:
        ns = sample.size
        n_in = np.searchsorted(sample, hi, side="right") - np.searchsorted(sample, lo)
        n_zone = (np.searchsorted(sample, hi + dhi, side="right") - np.searchsorted(sample, lo - dhi)
                  - (np.searchsorted(sample, lo + dlo) - np.searchsorted(sample, hi - dlo, side="right")))
        if max(n_in / ns * 2 * x.size / buf_r.size, n_zone / ns * 2 * x.size / buf_z.size) > 0.5:
            return None
    n = 2 * x.size
    k1, k2 = (n - 1) // 2, n // 2
    below, n_r, sure, n_z = _collect_both(x, y, gx, gy, float(origin[0]), float(origin[1]), coef, lo, hi, dlo, dhi, buf_r, buf_z)
    # (the last slot of a buffer takes the values not kept: full at size − 1; the deviations are written over buf_r)
    if n_r >= buf_r.size or n_z >= buf_z.size or n_z > buf_r.size:
        return None
    got = _pick(buf_r[:n_r], below, k1, k2, lo, hi)
    if got is None:
        return None
    v1, v2 = got
    med = float(v1) if n % 2 else float((v1 + v2) / 2.0)
    # the deviations of the zones' residuals from the exact median, over the residual buffer
    # (no longer needed): the same abs(r − m) as the two-pass path computes
    below_d, inside = _deviations(buf_z[:n_z], med, dlo, dhi, buf_r)
    got = _pick(buf_r[:inside], sure + below_d, k1, k2, dlo, dhi)
    if got is None:
        return None
    w1, w2 = got
    mad = float(w1) if n % 2 else float((w1 + w2) / 2.0)
    return (med, float(v1), float(v2)), (mad, float(w1), float(w2))



def sample_bracket(sample, n):
    """(lo, hi): the values of the sorted ``sample`` within ±6 binomial standard deviations of
    the rank of the median of ``n`` values — a bracket that holds the two middle values of all
    n unless the sample misleads (then the selection finds the ranks outside and selects
    again) — or None if the sample is too small for it."""
    ns = sample.size
    k1 = (n - 1) // 2
    pos = k1 / max(n - 1, 1) * (ns - 1)
    half = _BRACKET_SIGMAS * np.sqrt(0.25 * ns) + 2.0
    i_lo, i_hi = int(np.floor(pos - half)), int(np.ceil(pos + half))
    if i_lo < 0 or i_hi >= ns or not sample[i_hi] > sample[i_lo]:
        return None
    return float(sample[i_lo]), float(sample[i_hi])
