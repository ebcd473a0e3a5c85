"""One pass per stack for the consistency checks' residual and period tests (issue 25, item 1).

:func:`pmdsim.evaluation.consistency.check_consistency` tests each stack (a period of one fringe
direction, coarse → fine) in turn. Per stack it needed the N-step fit's maps A, B, φ, RSS and
the worst image, then σ_I²(A), the coordinate's σ, the contrast B/A and the coarse or refined
coordinate: nine (H, W) arrays made and dropped per stack (≈ 150 MB at 1920×1200), eight passes.
:func:`check_level` does all of it in one row-by-row pass over the stack's images: the fit per
row (the arithmetic of ``consistency._stack_kernel``), then per pixel σ_I², the FIT_RESIDUAL test,
σ, B/A and the PERIOD_MISMATCH test, with the expressions of the kernels it replaces in the same
order (no fast-math): the same values bit for bit (tests/test_consistency_levels.py). What
carries over to the next, finer stack — the coordinate c, σ and B/A — lives in caller-owned
(H, W) buffers reused for every stack.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .fast_atan import _phase_0_2pi
from .phase import equal_shifts
from .unwrapping import REVERSAL_CONTRAST_RATIO, _refine_reversal

__all__ = ["stack_array", "fit_row", "LevelBuffers", "check_level"]


def stack_array(stack) -> np.ndarray:
    """One (N, H, W) stack as the kernels take it: integer or float, native byte order, C order."""
    arr = np.asarray(stack)
    if arr.dtype.kind not in "uif" or not arr.dtype.isnative:
        arr = arr.astype(np.float64)
    return np.ascontiguousarray(arr)


@numba.njit(cache=True, fastmath=False, error_model="numpy", inline="always")
def fit_row(images, v, cos_d, sin_d, sa, sc, ss, rss, best, worst):  # pragma: no cover - compiled
    """The N-step fit of row v of an (N, H, W) stack with equal shifts: A, C = B cos φ,
    S = B sin φ into ``sa``, ``sc``, ``ss``, the residual sum of squares into ``rss`` and
    argmax_k |r_k| into ``worst`` (``best``: scratch) — image by image along the row
    (contiguous, vectorised across pixels; per pixel the sums run over k in order)."""
    n = images.shape[0]
    w = images.shape[2]
    sa[:] = 0.0
    sc[:] = 0.0
    ss[:] = 0.0
    for k in range(n):
        ck = cos_d[k]
        sk = sin_d[k]
        row = images[k, v]
        for u in range(w):
            x = np.float64(row[u])
            sa[u] += x
            sc[u] += x * ck
            ss[u] += x * sk
    for u in range(w):
        sa[u] = sa[u] / n
        sc[u] = 2.0 * sc[u] / n
        ss[u] = 2.0 * ss[u] / n
    rss[:] = 0.0
    best[:] = -1.0
    worst[:] = 0
    for k in range(n):
        ck = cos_d[k]
        sk = sin_d[k]
        row = images[k, v]
        for u in range(w):
            r = np.float64(row[u]) - sa[u] - sc[u] * ck - ss[u] * sk
            rss[u] += r * r
            ar = abs(r)
            gt = ar > best[u]
            best[u] = ar if gt else best[u]
            worst[u] = k if gt else worst[u]


@numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _sigma2_row(a_row, lines, g_row, est):  # pragma: no cover - compiled
    """σ_I²(A) = max(min_s (a_s + b_s·A), σ_given²) along a row, A = clip(nan_to_num(A), 0) (the
    numpy expression of :meth:`ConsistencyResult.noise_std_at`, squared), each line's pass a
    loop of selects over the row (vectorised)."""
    big = np.finfo(np.float64).max
    w = a_row.size
    for u in range(w):
        a = a_row[u]
        a = 0.0 if np.isnan(a) else (big if a > big else (-big if a < -big else a))
        a = 0.0 if a < 0.0 else a
        g_row[u] = a  # the clipped A, until the last pass
        est[u] = lines[0, 0] + lines[0, 1] * a
    for k in range(1, lines.shape[0]):
        l0 = lines[k, 0]
        l1 = lines[k, 1]
        for u in range(w):
            e = l0 + l1 * g_row[u]
            est[u] = e if (e < est[u] or np.isnan(e)) else est[u]


@numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _level_kernel(images, cos_d, sin_d, n_is_4, first, thr, lines, given2, tested, level, p, origin, upper,
                  ksig, z, rev, c, sig_prev, ratio_prev, sig, ratio, fit_ratio, worst_image, mis_ratio, bad_fit,
                  bad_per, mask, a_offs, a_buf, counts, top):  # pragma: no cover - compiled
    """One stack, row by row (module docstring). ``thr`` ≤ 0: no FIT_RESIDUAL test (N ≤ 3);
    ``lines`` with no row: σ_I² = ``given2``; ``level`` 0: the coarse coordinate, else the
    refinement of ``c`` and its test; ``a_buf`` (size > 0): A of the ``mask`` pixels in C order
    from ``a_offs[v]`` per row. ``counts[v]`` = (FIT_RESIDUAL, PERIOD_MISMATCH) pixels of row v,
    ``top[v]`` its largest tested σ_I². Each step a separate loop along the row (the ones
    without a libm call vectorise)."""
    n, h, w = images.shape
    two_pi = 2.0 * math.pi
    has_lines = lines.shape[0] > 0
    write_a = a_buf.size > 0
    sa = np.zeros(w)
    sc = np.zeros(w)
    ss = np.zeros(w)
    rss = np.zeros(w)
    best = np.zeros(w)
    worst = np.zeros(w, np.int64)
    bb = np.zeros(w)
    ph = np.zeros(w)
    s2 = np.zeros(w)
    tmp = np.zeros(w)
    ck = np.zeros(w)
    for v in range(0, h):
        fit_row(images, v, cos_d, sin_d, sa, sc, ss, rss, best, worst)
        for u in range(w):
            bb[u] = math.sqrt(sc[u] * sc[u] + ss[u] * ss[u])
            ph[u] = _phase_0_2pi(ss[u], sc[u])
        # σ_I², the coordinate's σ (the decoder's model) and the contrast B/A
        if has_lines:
            _sigma2_row(sa, lines, tmp, s2)
            for u in range(w):
                g = given2[v, u]
                e = s2[u]
                s2[u] = e if (e > g or np.isnan(e)) else g
        else:
            for u in range(w):
                s2[u] = given2[v, u]
        for u in range(w):
            sig[v, u] = ksig * math.sqrt(s2[u]) / bb[u]
            ratio[v, u] = bb[u] / sa[u]
        t_max = 0.0
        for u in range(w):
            if tested[v, u] and s2[u] > t_max:
                t_max = s2[u]
        if write_a:
            j = a_offs[v]
            for u in range(w):
                if mask[v, u]:
                    a_buf[j] = sa[u]
                    j += 1
        n_fit = 0
        if thr > 0.0:  # FIT_RESIDUAL: RSS/σ_I²/threshold; the largest ratio and its image kept
            for u in range(w):
                t = tested[v, u]
                rf = rss[u] / s2[u] / thr
                cur = fit_ratio[v, u]
                upd = t and (np.isnan(cur) or rf > cur)
                fit_ratio[v, u] = rf if upd else cur
                worst_image[v, u] = first + (n if n_is_4 else worst[u]) if upd else worst_image[v, u]
                bf = t and rf > 1.0
                bad_fit[v, u] = bf
                n_fit += bf
        n_per = 0
        if level == 0:  # the coarsest period's coordinate in [origin, upper] (minus a period above)
            for u in range(w):
                rr = p * (ph[u] / two_pi) - origin
                cv = origin + (rr - p * math.floor(rr / p))
                c[v, u] = cv - p if cv > upper else cv
        else:  # PERIOD_MISMATCH: c_k refined from the coarser c, |c − c_k|/(z·hypot(σ_prev, σ))
            for u in range(w):
                fine = p * ph[u] / two_pi
                ck[u] = fine + p * math.floor((c[v, u] - fine) / p + 0.5)
            for u in range(w):
                if rev[v, u]:
                    ck[u], _, _ = _refine_reversal(c[v, u], ph[u], p, 1.0 / p, 0.5, ratio[v, u], ratio_prev[v, u],
                                                   REVERSAL_CONTRAST_RATIO)
            for u in range(w):
                tmp[u] = math.hypot(sig_prev[v, u], sig[v, u])
            for u in range(w):
                rm = abs(c[v, u] - ck[u]) / (z * tmp[u])
                c[v, u] = ck[u]
                t = tested[v, u]
                cur = mis_ratio[v, u]
                mis_ratio[v, u] = rm if (t and not (rm <= cur)) else cur
                bp = t and rm > 1.0
                bad_per[v, u] = bp
                n_per += bp
        counts[v, 0] = n_fit
        counts[v, 1] = n_per
        top[v] = t_max


class LevelBuffers:
    """The (H, W) maps one direction's stacks hand on, coarse → fine: the coordinate ``c``, σ and
    B/A of the previous and of the current stack (swapped after each), the two tests' pixels."""

    def __init__(self, h: int, w: int):
        self.c = np.empty((h, w))
        self.sig_prev, self.sig = np.empty((h, w)), np.empty((h, w))
        self.ratio_prev, self.ratio = np.empty((h, w)), np.empty((h, w))
        self.bad_fit = np.zeros((h, w), bool)
        self.bad_per = np.zeros((h, w), bool)
        self.counts = np.empty((h, 2), np.int64)
        self.top = np.empty(h)

    def swap(self) -> None:
        self.sig_prev, self.sig = self.sig, self.sig_prev
        self.ratio_prev, self.ratio = self.ratio, self.ratio_prev


def check_level(buf: LevelBuffers, stack, *, first: int, thr: float, lines, given2, tested, level: int,
                p: float, origin: float, upper: float, z: float, rev, fit_ratio, worst_image, mis_ratio,
                mask=None) -> tuple[int, int, float, np.ndarray | None]:
    """Test one stack (module docstring) and hand its c, σ, B/A on in ``buf``.

    Parameters
    ----------
    stack : array_like (N, H, W)
        Grey levels, equal shifts.
    first : int
        The label index of the stack's first image (``worst_image`` = first + k).
    thr : float
        χ²(N − 3) threshold of FIT_RESIDUAL; ≤ 0 (N ≤ 3): not tested.
    lines : (S, 2) float64 or None
        The noise model's (a, b) per stack; None: σ_I² = ``given2``.
    given2 : (H, W) float64 (a broadcast view is fine)
    tested, rev : (H, W) bool
    level : int
        0 for the coarsest stack of a direction (its coordinate), else the refinement of ``buf.c``.
    p, origin, upper, z : float
        Period (mm), the coarse coordinate's interval, the normal quantile of the period test.
    fit_ratio, mis_ratio : (H, W) float32;  worst_image : (H, W) int16
        Updated in place (the largest ratio over stacks, its image).
    mask : (H, W) bool, optional
        Also return A at these pixels (C order).

    Returns
    -------
    (FIT_RESIDUAL count, PERIOD_MISMATCH count, largest tested σ_I², A at ``mask`` or None);
    ``buf.bad_fit`` / ``buf.bad_per`` hold the tests' pixels, ``buf.sig``/``buf.ratio`` this
    stack's σ and B/A until :meth:`LevelBuffers.swap`.
    """
    arr = stack_array(stack)
    n, h, w = arr.shape
    d = equal_shifts(n)
    want_a = mask is not None
    if want_a:
        offs = np.zeros(h + 1, np.int64)
        np.cumsum(np.count_nonzero(mask, axis=1), out=offs[1:])
        a_buf = np.empty(int(offs[-1]))
    else:
        mask, offs, a_buf = np.zeros((1, 1), bool), np.zeros(h + 1, np.int64), np.empty(0)
    ln = np.zeros((0, 2)) if lines is None else np.ascontiguousarray(lines, dtype=np.float64)
    _level_kernel(readonly(arr), np.cos(d), np.sin(d), n == 4, int(first), float(thr) if n > 3 else 0.0,
                  readonly(ln), readonly(np.asarray(given2, dtype=np.float64)), readonly(tested), int(level), float(p),
                  float(origin), float(upper), float(p / (2.0 * math.pi) * math.sqrt(2.0 / n)), float(z), readonly(rev),
                  buf.c, readonly(buf.sig_prev), readonly(buf.ratio_prev), buf.sig, buf.ratio, fit_ratio, worst_image,
                  mis_ratio, buf.bad_fit, buf.bad_per, readonly(mask), offs, a_buf, buf.counts, buf.top)
    return (int(buf.counts[:, 0].sum()), int(buf.counts[:, 1].sum()), float(buf.top.max()) if h else 0.0,
            a_buf if want_a else None)
