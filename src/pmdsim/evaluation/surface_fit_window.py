"""The robust paraboloid fit's medians from a window of its points, kept over iterations (issue 25, item 1).

Each IRLS iteration of :func:`pmdsim.evaluation.surface_fit.fit_paraboloid_slopes` needs the
exact median m of the 2M slope residuals r and the exact median of the deviations |r − m|; one
pass over all points per iteration (:func:`~.surface_fit_select.median_and_mad`) costs about as
much as the iteration's weighted sums. Near convergence the coefficients hardly move, so the
points that can decide either median are few and the same from one iteration to the next.

A *window* is taken at coefficients c_k with a median bracket [lo, hi] and a deviation bracket
[dlo, dhi]: one pass copies (x, y, g_x, g_y) of every point with a residual in [lo, hi] or in the
zones [lo − dhi, hi + dhi] \\ (hi − dlo, lo + dlo) (the deviations' candidates, as in
:mod:`.surface_fit_select`), and counts of the other points' residuals those < lo ("below") and
those in (hi − dlo, lo + dlo) ("sure": within dlo of any centre in [lo, hi]). At later
coefficients c_j every residual moves by at most D = max_i |A_i·(c_j − c_k)| (plus the rounding
of both evaluations): a point outside the window that was below lo is below lo + D, one above hi
is above hi − D; with the median m_j in [lo + D, hi − D], a "sure" residual deviates less than
dlo from it and one outside the zones more than dhi. So the medians at c_j are selected among
the window's points alone — their residuals computed as the full pass computes them
(:func:`~.surface_fit._pair`), the counts of the others added — bit for bit the order statistics
of the full pass; where D grew too large or a rank falls outside, :meth:`Window.median_and_mad`
returns None and the caller takes a new window or the full pass.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .surface_fit import _pair, _pick
from .surface_fit_select import split_value

__all__ = ["Window", "WindowedMedians", "take_window"]

_EPS = 2.220446049250313e-16


_BLOCK = 256  # points classified without branches before a block is re-read for the points to copy


@numba.njit(cache=True, nogil=True, fastmath=False, inline="always")
def _classes(r, lo, hi, zlo, zhi, slo, shi):
    """(r < lo, r in (slo, shi), r kept: in [lo, hi] or in [zlo, zhi] outside (slo, shi)) as integers."""
    s = (r > slo) * (r < shi)
    return (r < lo) * 1, s, (r >= lo) * (r <= hi) + (r >= zlo) * (r <= zhi) * (1 - s)


@numba.njit(cache=True, nogil=True, fastmath=False)
def _take(x, y, gx, gy, xc, yc, coef, bounds, xs, ys, gxs, gys):  # pragma: no cover - compiled
    """One pass over the points: those with a residual in [lo, hi] or in [zlo, zhi] \\ (slo, shi)
    (``bounds`` = (lo, hi, zlo, zhi, slo, shi)) copied to ``xs``, ``ys``, ``gxs``, ``gys`` (as
    many as fit; the last slot takes the points not kept); of the other points' residuals the
    number < lo and the number in (slo, shi). Returns (below, sure, n_kept); n_kept ≥ xs.size:
    too many. Blocks of 256 points are
    classified without branches and re-read only where they hold a point to keep."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    lo, hi, zlo, zhi, slo, shi = bounds[0], bounds[1], bounds[2], bounds[3], bounds[4], bounds[5]
    last = xs.size - 1
    below = 0
    sure = 0
    n = 0
    for start in range(0, x.size, _BLOCK):
        stop = min(start + _BLOCK, x.size)
        cnt = 0
        for i in range(start, stop):
            r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, 0, 0.0)
            b0, s0, k0 = _classes(r0, lo, hi, zlo, zhi, slo, shi)
            b1, s1, k1 = _classes(r1, lo, hi, zlo, zhi, slo, shi)
            below += b0 + b1
            sure += s0 + s1
            cnt += k0 + k1
        if cnt:  # the kept points' residuals leave the counts (the window holds them)
            for i in range(start, stop):  # each point to the next free slot, which only a kept one advances
                r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, 0, 0.0)
                b0, s0, k0 = _classes(r0, lo, hi, zlo, zhi, slo, shi)
                b1, s1, k1 = _classes(r1, lo, hi, zlo, zhi, slo, shi)
                j = min(n, last)
                xs[j] = x[i]
                ys[j] = y[i]
                gxs[j] = gx[i]
                gys[j] = gy[i]
                keep = (k0 + k1) > 0
                n += keep
                below -= keep * (b0 + b1)
                sure -= keep * (s0 + s1)
    return below, sure, n


@numba.njit(cache=True, nogil=True, fastmath=False)
def _values(xs, ys, gxs, gys, xc, yc, coef, mode, centre, lo, hi, out):  # pragma: no cover - compiled
    """The window's residuals (``mode`` 1: |r − centre|): the number < lo, and those in [lo, hi]
    written to ``out``. Returns (below, inside)."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    below = 0
    inside = 0
    for i in range(0, xs.size):
        r0, r1 = _pair(xs, ys, gxs, gys, xc, yc, i, a2, b, c2, d, e, mode, centre)
        below, inside = split_value(r0, lo, hi, out, below, inside)
        below, inside = split_value(r1, lo, hi, out, below, inside)
    return below, inside


class Window:
    """The points of a window (module docstring) and the counts of the others.

    Attributes
    ----------
    coef : ndarray (5,)
        The coefficients the window was taken at.
    bounds : (lo, hi, dlo, dhi)
        Its median and deviation brackets.
    xs, ys, gxs, gys : ndarray (K,)
        The kept points (raw x, y and slopes).
    below, sure : int
        Of the other points' residuals: the number < lo, and in (hi − dlo, lo + dlo) shrunk by tol.
    rounding : float
        A bound of the rounding of one residual at the window's coefficients.
    """

    def __init__(self, coef, bounds, xs, ys, gxs, gys, below, sure, g_max, reach, origin, n_total):
        self.coef = np.array(coef, dtype=float)
        self.bounds = bounds
        self.xs, self.ys, self.gxs, self.gys = xs, ys, gxs, gys
        self.below, self.sure = int(below), int(sure)
        self.g_max = float(g_max)
        self.reach = reach
        self.origin = (float(origin[0]), float(origin[1]))
        self.n_total = int(n_total)
        self.buf = np.empty(2 * xs.size)

    def _rounding(self, coef) -> float:
        """A bound of the rounding error of one residual g − (2a·x + b·y + d) at ``coef``
        (each of its four operations rounds by ≤ ε of a partial sum ≤ |g| + Σ|terms|: 8ε of it)."""
        ax2, ay, ax, ay2 = self.reach
        t = max(abs(coef[0]) * ax2 + abs(coef[1]) * ay + abs(coef[3]),
                abs(coef[1]) * ax + abs(coef[2]) * ay2 + abs(coef[4]))
        return 8.0 * _EPS * (self.g_max + t)

    def drift(self, coef) -> float:
        """max_i |r_i(coef) − r_i(self.coef)| as computed (both roundings included)."""
        dc = np.abs(np.asarray(coef, dtype=float) - self.coef)
        ax2, ay, ax, ay2 = self.reach
        d = max(ax2 * dc[0] + ay * dc[1] + dc[3], ax * dc[1] + ay2 * dc[2] + dc[4])
        lo, hi = self.bounds[0], self.bounds[1]
        # (+ the rounding of lo + drift and hi − drift)
        return d * (1.0 + 1e-6) + self._rounding(coef) + self._rounding(self.coef) + 4.0 * _EPS * (abs(lo) + abs(hi))

    def median_and_mad(self, coef, narrow=None):
        """((median, lower, upper middle value), (MAD, lower, upper)) of the 2M residuals at
        ``coef`` and of their deviations from that median — those of a full pass — or None
        (the coefficients moved too far from the window's, or a rank outside its brackets).

        ``narrow`` = (lo, hi, dlo, dhi): brackets expected to hold the middle values (the
        Lipschitz bounds from the last iteration's), used where they are inside the window's:
        any sub-bracket counts the points outside the window alike, and fewer values are
        selected among. A rank outside them: the window's own brackets are used."""
        got = None
        if narrow is not None:
            got = self._select(coef, narrow)
        return self._select(coef, None) if got is None else got

    def _select(self, coef, narrow):
        lo, hi, dlo, dhi = self.bounds
        drift = self.drift(coef)
        lo2, hi2 = lo + drift, hi - drift
        if narrow is not None:
            lo2, hi2 = max(lo2, narrow[0]), min(hi2, narrow[1])
            dlo, dhi = max(dlo, narrow[2]), min(dhi, narrow[3])
            if not dlo <= dhi:
                return None
        if not lo2 <= hi2:
            return None
        n = 2 * self.n_total
        k1, k2 = (n - 1) // 2, n // 2
        xc, yc = self.origin
        c = np.asarray(coef, dtype=float)
        below, inside = _values(self.xs, self.ys, self.gxs, self.gys, xc, yc, c, 0, 0.0, lo2, hi2, self.buf)
        got = _pick(self.buf[:inside], self.below + below, k1, k2, lo2, hi2)
        if got is None:
            return None
        v1, v2 = got
        med = float(v1) if n % 2 else float((v1 + v2) / 2.0)
        below, inside = _values(self.xs, self.ys, self.gxs, self.gys, xc, yc, c, 1, med, dlo, dhi, self.buf)
        got = _pick(self.buf[:inside], self.sure + below, k1, k2, dlo, dhi)
        if got is None:
            return None
        w1, w2 = got
        mad = float(w1) if n % 2 else float((w1 + w2) / 2.0)
        return (med, float(v1), float(v2)), (mad, float(w1), float(w2))


def take_window(x, y, gx, gy, coef, bracket, dev_bracket, capacity, reach, g_max, *, origin=(0.0, 0.0)):
    """A :class:`Window` at ``coef`` with the median bracket ``bracket`` = (lo, hi) and the
    deviation bracket ``dev_bracket`` = (dlo, dhi), or None if more than ``capacity`` points fall
    in it or the brackets are unusable. ``reach`` = (max 2|x|, max |y|, max |x|, max 2|y|) of the
    centred points (the residuals' sensitivities to a, b, c), ``g_max`` max |g| (the rounding
    of the residuals)."""
    lo, hi = bracket
    dlo, dhi = dev_bracket
    if not (lo <= hi and 0.0 <= dlo <= dhi):
        return None
    tol = 8.0 * _EPS * (abs(lo) + abs(hi) + dhi)
    bounds = np.array([lo, hi, lo - dhi - tol, hi + dhi + tol, hi - dlo + tol, lo + dlo - tol])
    if not bounds[4] < bounds[5]:
        return None
    xs, ys, gxs, gys = (np.empty(capacity + 1) for _ in range(4))
    x, y, gx, gy = readonly(x), readonly(y), readonly(gx), readonly(gy)  # one argument type of the kernel
    below, sure, n = _take(x, y, gx, gy, float(origin[0]), float(origin[1]), np.asarray(coef, dtype=float),
                                  bounds, xs, ys, gxs, gys)
    if n > capacity:
        return None
    return Window(coef, (lo, hi, dlo, dhi), xs[:n], ys[:n], gxs[:n], gys[:n], below, sure, g_max, reach, origin,
                  x.size)


#: A window is taken for a drift of up to this many times the last step's bound δ (the
#: coefficients converge linearly: the steps after one sum to a few of it).
_WIDTH_STEPS = 4.0


class WindowedMedians:
    """The IRLS's medians from windows (module docstring): the one in use while the coefficients
    stay within its reach, else a new one when the sample says it fits.

    Parameters
    ----------
    x, y, gx, gy : ndarray (M,)
        The points (read-only arrays of the fit).
    reach : (max 2|x|, max |y|, max |x|, max 2|y|)
        Of the centred points.
    g_max : float
        max |g| of the slopes.
    origin : (xc, yc)
        The residuals are those at (x − xc, y − yc).
    """

    def __init__(self, x, y, gx, gy, reach, g_max, origin):
        self.points = (x, y, gx, gy)
        self.g_max = g_max
        self.reach = reach
        self.origin = origin
        self.capacity = max(4096, x.size // 16)
        self.stride = max(1, x.size // 16_384)
        self.window = None

    def __call__(self, coef, ranks, dev_ranks, delta):
        """((median, m1, m2), (MAD, d1, d2)) at ``coef`` — the last iteration's middle values
        ``ranks`` = (m1, m2), ``dev_ranks`` = (d1, d2) and the bound δ of the residuals' change
        since — or None (no window fits: the caller makes a full pass)."""
        (m1, m2), (d1, d2) = ranks, dev_ranks
        if self.window is not None:
            got = self.window.median_and_mad(coef, (m1 - delta, m2 + delta, max(d1 - 2.0 * delta, 0.0),
                                                    d2 + 2.0 * delta))
            if got is not None:
                return got
            self.window = None
        from .surface_fit import _sample_values

        w = _WIDTH_STEPS * delta
        lo, hi = m1 - delta - 2.0 * w, m2 + delta + 2.0 * w
        dlo, dhi = max(d1 - 2.0 * delta - 2.0 * w, 0.0), d2 + 2.0 * delta + 2.0 * w
        if not hi - dlo < lo + dlo:
            return None
        x, y, gx, gy = self.points
        s = np.sort(_sample_values(x, y, gx, gy, float(self.origin[0]), float(self.origin[1]), coef, 0, 0.0,
                                   self.stride))
        kept = (np.searchsorted(s, hi + dhi, side="right") - np.searchsorted(s, lo - dhi)
                - (np.searchsorted(s, lo + dlo) - np.searchsorted(s, hi - dlo, side="right"))
                + np.searchsorted(s, hi, side="right") - np.searchsorted(s, lo))
        if kept / s.size * 2 * x.size > 0.5 * self.capacity:  # (residuals: at most that many points)
            return None
        self.window = take_window(x, y, gx, gy, coef, (lo, hi), (dlo, dhi), self.capacity, self.reach, self.g_max,
                                  origin=self.origin)
        return None if self.window is None else self.window.median_and_mad(coef)
