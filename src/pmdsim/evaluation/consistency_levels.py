"""The consistency checks' residual and period tests in one parallel pass over image rows
(issue 25, item 1).

:func:`pmdsim.evaluation.consistency.check_consistency` tests each stack (a period of one fringe
direction, coarse → fine): the N-step fit's A, B, φ, RSS and worst image, σ_I²(A), the
coordinate's σ, the contrast B/A, the FIT_RESIDUAL test and the coarse or refined coordinate
with its PERIOD_MISMATCH test. :func:`check_stacks` does all of it for every stack of both
directions in one pass over image rows, as the fused decoder
(:mod:`pmdsim.evaluation.decoding_fused`) decodes them: per row, direction by direction, its
stacks coarse → fine, each step a loop along the row, with the expressions of the per-stack
kernels it replaces in the same order (no fast-math), so the values are the same bit for bit
(tests/test_consistency_levels.py). What a finer stack needs from the coarser one — c, A, B²,
σ_I² — stays in row buffers: no (H, W) map per stack. Each image is read once. Per stack and
pixel the two tests' outcomes are kept as bits of (H, W, ⌈S/8⌉) uint8 maps, for the
whole-stack defect rules of ``check_consistency``.

Divisions and square roots bound the pass. The two test ratios are computed in fewer of them
than their defining expressions (the period ratio without σ and libm's ``hypot``) and used
where they provably decide as those would — the same test outcome, the same update of the
stored maximum, the same float32 (:func:`_same_outcome`); elsewhere the defining expression is
evaluated. Why the decoder's own pass is not shared: docs/benchmarks.md, "`evaluate` end to end:
the checks in one pass over image rows".
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .decoding_fused import common_image_stack
from .fast_atan import _phase_0_2pi
from .phase import PhaseFlag, equal_shifts
from .unwrapping import REVERSAL_CONTRAST_RATIO, _refine_reversal

__all__ = ["stack_array", "stack_images", "fit_row", "StackRows", "check_stacks"]

#: Rows per block of the parallel pass (the row buffers are allocated once per block).
_ROWS_PER_BLOCK = 16


def stack_array(stack) -> np.ndarray:
    """One (N, H, W) stack as the kernels take it: integer or float, native byte order, C order."""
    arr = np.asarray(stack)
    if arr.dtype.kind not in "uif" or not arr.dtype.isnative:
        arr = arr.astype(np.float64)
    return np.ascontiguousarray(arr)


def stack_images(stacks) -> np.ndarray:
    """The images of (N_i, H, W) stacks, one after the other, as one read-only (ΣN_i, H, W) array
    (:func:`stack_array` per stack, then :func:`~pmdsim.evaluation.decoding_fused.common_image_stack`:
    a view where the images already lie one after the other, else one copy; stacks of different
    dtypes promoted to their common type, which holds every grey level exactly)."""
    return common_image_stack([im for st in stacks for im in stack_array(st)])


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")
def _fit4_row(r0, r1, r2, r3, cos_d, sin_d, sa, sc, ss, rss):  # pragma: no cover - compiled
    """:func:`fit_row` of N = 4 rows ``r0`` … ``r3`` with the residual sum of squares, in one loop
    along the row: per pixel the same sums in the same order (from 0.0, shift by shift; x/4 as
    x·0.25, exactly), the same values bit for bit."""
    c0, c1, c2, c3 = cos_d[0], cos_d[1], cos_d[2], cos_d[3]
    s0, s1, s2, s3 = sin_d[0], sin_d[1], sin_d[2], sin_d[3]
    for u in range(sa.shape[0]):
        x0 = np.float64(r0[u])
        x1 = np.float64(r1[u])
        x2 = np.float64(r2[u])
        x3 = np.float64(r3[u])
        a = ((((0.0 + x0) + x1) + x2) + x3) * 0.25
        c = 2.0 * ((((0.0 + x0 * c0) + x1 * c1) + x2 * c2) + x3 * c3) * 0.25
        s = 2.0 * ((((0.0 + x0 * s0) + x1 * s1) + x2 * s2) + x3 * s3) * 0.25
        sa[u] = a
        sc[u] = c
        ss[u] = s
        e0 = x0 - a - c * c0 - s * s0
        e1 = x1 - a - c * c1 - s * s1
        e2 = x2 - a - c * c2 - s * s2
        e3 = x3 - a - c * c3 - s * s3
        rss[u] = (((0.0 + e0 * e0) + e1 * e1) + e2 * e2) + e3 * e3


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")
def fit_row(images, first, n, v, cos_d, sin_d, sa, sc, ss, rss, best, worst, residuals):  # pragma: no cover
    """The N-step fit of row v of the stack ``images[first]`` … ``images[first + n − 1]`` (an
    (N, H, W) array) with equal shifts (``cos_d``, ``sin_d`` (n,)): A, C = B cos φ,
    S = B sin φ into ``sa``, ``sc``, ``ss``; with ``residuals`` ≥ 1 the residual sum of squares
    into ``rss``, with 2 also argmax_k |r_k| into ``worst`` (``best``: scratch) — image by image
    along the row (contiguous, vectorised across pixels; per pixel the sums run over k in
    order)."""
    w = sa.shape[0]
    if n == 4 and residuals == 1:  # the usual case: sums and residuals in one pass over the four rows
        _fit4_row(images[first][v], images[first + 1][v], images[first + 2][v], images[first + 3][v], cos_d, sin_d,
                  sa, sc, ss, rss)
        return
    sa[:] = 0.0
    sc[:] = 0.0
    ss[:] = 0.0
    for k in range(n):
        ck = cos_d[k]
        sk = sin_d[k]
        row = images[first + k][v]
        for u in range(w):
            x = np.float64(row[u])
            sa[u] += x
            sc[u] += x * ck
            ss[u] += x * sk
    if n & (n - 1) == 0:  # N a power of two: x/N = x·(1/N) exactly (no division)
        inv_n = 1.0 / n
        for u in range(w):
            sa[u] = sa[u] * inv_n
            sc[u] = 2.0 * sc[u] * inv_n
            ss[u] = 2.0 * ss[u] * inv_n
    else:
        for u in range(w):
            sa[u] = sa[u] / n
            sc[u] = 2.0 * sc[u] / n
            ss[u] = 2.0 * ss[u] / n
    if residuals == 0:
        return
    rss[:] = 0.0
    if residuals == 2:
        best[:] = -1.0
        worst[:] = 0
    for k in range(n):
        ck = cos_d[k]
        sk = sin_d[k]
        row = images[first + k][v]
        if residuals == 1:
            for u in range(w):
                r = np.float64(row[u]) - sa[u] - sc[u] * ck - ss[u] * sk
                rss[u] += r * r
        else:
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


#: A relative bound on |r − r*| for a test ratio r computed in fewer operations than the
#: defining expression's r* (:func:`_same_outcome`): the ratios below differ by ≤ 25 units in the
#: last place (2^-48.4), so 2^-44 leaves a margin of 20.
_RATIO_EPS = 2.0 ** -44


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")
def _same_outcome(r, cur):  # pragma: no cover - compiled
    """Whether every r* within ``_RATIO_EPS``·r of a test ratio r ≥ 0 has r's outcome: r·(1 ± ε)
    lie on one side of 1 (the test), on one side of ``cur`` (the stored maximum, float32; NaN:
    any) and round to one float32 (the stored value); r zero, or normal and finite."""
    lo = r * (1.0 - _RATIO_EPS)
    hi = r * (1.0 + _RATIO_EPS)
    cu = np.float64(cur)
    return (((r == 0.0) | ((r > 1e-300) & (r < 1e300))) & (np.float32(lo) == np.float32(hi))
            & ((hi < 1.0) | (lo > 1.0)) & (np.isnan(cu) | (cu < lo) | (cu > hi)))


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")
def _fit_ratio_row(rss, s2, thr, cur, out, exact):  # pragma: no cover - compiled
    """RSS/σ_I²/threshold along a row into ``out`` (W,), bit for bit that expression's value
    wherever it decides anything: one division, RSS/(σ_I²·threshold) (within 4 ulp of it), where
    :func:`_same_outcome` holds and σ_I²·threshold is normal and finite; elsewhere the two
    divisions (``exact`` (W,) bool: scratch)."""
    w = out.shape[0]
    n_exact = 0
    for u in range(w):
        d = s2[u] * thr
        r = rss[u] / d
        out[u] = r
        ex = not ((d > 1e-300) & (d < 1e300) & _same_outcome(r, cur[u]))
        exact[u] = ex
        n_exact += ex
    for u in range(w if n_exact else 0):
        if exact[u]:
            out[u] = rss[u] / s2[u] / thr


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")
def _mismatch_ratio_row(c, ck, s2_prev, b2_prev, k_prev, s2, b2, k, z, cur, out, exact):  # pragma: no cover
    """|c − c_k| / (z·hypot(σ_prev, σ)) along a row into ``out`` (W,), σ = k·√σ_I² / √B² of
    each stack (the decoder's σ model; ``b2`` = C² + S²), bit for bit that expression's value
    wherever it decides anything. Without σ and libm's ``hypot`` (one call per pixel): the ratio
    is |c − c_k|·√(B²_prev·B² / (k_prev²·σ²_I,prev·B² + k²·σ_I²·B²_prev)) / z — one square root,
    one division, vectorised, within 25 ulp of the expression's value (glibc's hypot being
    within 1 ulp of the exact one) — where :func:`_same_outcome` holds and no product can under-
    or overflow; elsewhere the expression itself (``exact`` (W,) bool: scratch)."""
    w = out.shape[0]
    kp2 = k_prev * k_prev
    k2 = k * k
    n_exact = 0
    for u in range(w):
        a2 = b2_prev[u]
        bq = b2[u]
        e = s2_prev[u]
        f = s2[u]
        r = abs(c[u] - ck[u]) * math.sqrt(a2 * bq / (kp2 * e * bq + k2 * f * a2)) / z
        out[u] = r
        ex = not ((a2 > 1e-100) & (a2 < 1e100) & (bq > 1e-100) & (bq < 1e100) & (e > 1e-100) & (e < 1e100)
                  & (f > 1e-100) & (f < 1e100) & _same_outcome(r, cur[u]))
        exact[u] = ex
        n_exact += ex
    for u in range(w if n_exact else 0):
        if exact[u]:
            sig_prev = k_prev * math.sqrt(s2_prev[u]) / math.sqrt(b2_prev[u])
            sig = k * math.sqrt(s2[u]) / math.sqrt(b2[u])
            out[u] = abs(c[u] - ck[u]) / (z * math.hypot(sig_prev, sig))


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _stack_row(images, v, s, ax, n_rev, st_img, cos_d, sin_d, st_first, st_n4, st_thr, st_p, st_ksig, st_level, origin,
               upper, lines, given2, tested, rev, z, a_stack, mask, a_offs, a_buf, fit_ratio, worst_image, mis_ratio,
               bits_fit, bits_per, counts, top, c, sa_prev, b2_prev, s2_prev, dir_bad, sa, sc, ss, rss, best, worst,
               b2, ph, s2, tmp, ck, exact):  # pragma: no cover - compiled
    """Stack ``s`` (of direction ``ax``) on row v: the fit, σ_I², σ, B/A, the FIT_RESIDUAL test,
    the coordinate and its PERIOD_MISMATCH test (:func:`_checks_kernel`). Row buffers (W,): ``c``
    (in: the coarser stack's coordinate; out: this one's), ``sa_prev``, ``b2_prev``, ``s2_prev``
    (the coarser stack's A, B² and σ_I²), ``sa``, ``b2``, ``s2`` (out: this stack's), ``dir_bad``
    (PERIOD_MISMATCH at a coarser level of this direction; updated); the others scratch.
    ``n_rev``: the row's pixels with a corrected reversal in this direction. B, σ
    and the contrast B/A are computed only where a test needs them (:func:`_mismatch_ratio_row`,
    the reversal correction)."""
    w = sa.shape[0]
    two_pi = 2.0 * math.pi
    first_img, n = st_img[s], st_img[s + 1] - st_img[s]
    thr, p, ksig, level, first, n_is_4 = st_thr[s], st_p[s], st_ksig[s], st_level[s], st_first[s], st_n4[s]
    byte = s // 8
    bit = np.uint8(1 << (s % 8))
    pm, _ = math.frexp(p)
    p_pow2 = pm == 0.5
    # the residuals only for the FIT_RESIDUAL test (N > 3), the worst image only where it is not
    # every image (N ≠ 4)
    fit_row(images, first_img, n, v, cos_d[first_img:], sin_d[first_img:], sa, sc, ss, rss, best, worst,
            0 if thr <= 0.0 else (1 if n_is_4 else 2))
    for u in range(w):
        b2[u] = sc[u] * sc[u] + ss[u] * ss[u]
        ph[u] = _phase_0_2pi(ss[u], sc[u])
    # σ_I²
    if lines.shape[0] > 0:
        _sigma2_row(sa, lines, tmp, s2)
        for u in range(w):
            g = given2[v, u]
            e = s2[u]
            s2[u] = e if (e > g or np.isnan(e)) else g
    else:
        for u in range(w):
            s2[u] = given2[v, u]
    # the largest tested σ_I² > 0: positive floats order as their bit patterns (an integer
    # maximum, vectorised; NaN and values ≤ 0 never count, as in a running `s2 > t_max`)
    s2_bits = s2.view(np.int64)
    t_bits = np.int64(0)
    for u in range(w):
        t_bits = max(t_bits, s2_bits[u] if (tested[v, u] & (s2[u] > 0.0)) else np.int64(0))
    tmp[0] = 0.0
    tmp.view(np.int64)[0] = t_bits
    t_max = tmp[0]
    if s == a_stack:
        j = a_offs[v]
        for u in range(w):
            if mask[v, u]:
                a_buf[j] = sa[u]
                j += 1
    n_fit = 0
    if thr > 0.0:  # FIT_RESIDUAL: RSS/σ_I²/threshold; the largest ratio and its image kept
        _fit_ratio_row(rss, s2, thr, fit_ratio[v], tmp, exact)
        for u in range(w):
            t = tested[v, u]
            rf = tmp[u]
            cur = fit_ratio[v, u]
            upd = t and (np.isnan(cur) or rf > cur)
            fit_ratio[v, u] = rf if upd else cur
            worst_image[v, u] = first + (n if n_is_4 else worst[u]) if upd else worst_image[v, u]
            bf = t and rf > 1.0
            bits_fit[v, u, byte] |= bit if bf else np.uint8(0)
            n_fit += bf
    n_per = 0
    n_new = 0
    if level == 0:  # the coarsest period's coordinate in [origin, upper] (minus a period above)
        org = origin[ax]
        up = upper[ax]
        for u in range(w):
            rr = p * (ph[u] / two_pi) - org
            cv = org + (rr - p * math.floor(rr / p))
            c[u] = cv - p if cv > up else cv
    else:  # PERIOD_MISMATCH: c_k refined from the coarser c, |c − c_k|/(z·hypot(σ_prev, σ))
        if p_pow2:  # x/p = x·(1/p) exactly
            inv_p = 1.0 / p
            for u in range(w):
                fine = p * ph[u] / two_pi
                ck[u] = fine + p * math.floor((c[u] - fine) * inv_p + 0.5)
        else:
            for u in range(w):
                fine = p * ph[u] / two_pi
                ck[u] = fine + p * math.floor((c[u] - fine) / p + 0.5)
        for u in range(w if n_rev else 0):
            if rev[v, u, ax]:
                ck[u], _, _ = _refine_reversal(c[u], ph[u], p, 1.0 / p, 0.5, math.sqrt(b2[u]) / sa[u],
                                               math.sqrt(b2_prev[u]) / sa_prev[u], REVERSAL_CONTRAST_RATIO)
        _mismatch_ratio_row(c, ck, s2_prev, b2_prev, st_ksig[s - 1], s2, b2, ksig, z, mis_ratio[v], tmp, exact)
        for u in range(w):
            rm = tmp[u]
            c[u] = ck[u]
            t = tested[v, u]
            cur = mis_ratio[v, u]
            mis_ratio[v, u] = rm if (t and not (rm <= cur)) else cur
            bp = t and rm > 1.0
            bits_per[v, u, byte] |= bit if bp else np.uint8(0)
            n_per += bp
            n_new += bp and not dir_bad[u]
            dir_bad[u] |= bp
    counts[s, v, 0] = n_fit
    counts[s, v, 1] = n_per
    counts[s, v, 2] = n_new
    top[s, v] = t_max


@numba.njit(parallel=True, cache=True, nogil=True, fastmath=False, error_model="numpy")
def _checks_kernel(images, st_img, cos_d, sin_d, st_first, st_n4, st_thr, st_p, st_ksig, st_level, dir_st, origin,
                   upper, lo, hi, lines, given2, tested, rev, z, a_stack, mask, a_offs, a_buf, fit_ratio, worst_image,
                   mis_ratio, final, bits_fit, bits_per, geometry, flags, counts, top, n_out):  # pragma: no cover
    """Every stack of both directions, one parallel pass over blocks of image rows (module
    docstring). Stack s: images ``st_img[s]`` … ``st_img[s + 1] − 1`` of the list ``images``,
    per image ``cos_d``/``sin_d`` of its shift; direction d: stacks ``dir_st[d]`` …
    ``dir_st[d + 1] − 1``, coarse → fine. Per row it initialises ``fit_ratio``/``mis_ratio``
    (NaN), ``worst_image`` (−1), the bits (0) and ``flags`` (the bit ``geometry`` where the final coordinate
    of a tested pixel lies outside [``lo[d]``, ``hi[d]``]); ``final`` (H, W, 2) receives the
    finest coordinate per direction; ``counts[s, v]`` = (FIT_RESIDUAL, PERIOD_MISMATCH,
    PERIOD_MISMATCH not at a coarser level), ``top[s, v]`` the row's largest tested σ_I²,
    ``n_out[v, d]`` the row's outside pixels."""
    h, w = tested.shape
    nb = (h + _ROWS_PER_BLOCK - 1) // _ROWS_PER_BLOCK
    for b in numba.prange(0, nb):
        rows = np.empty((14, w))  # the row buffers, one block
        sa_a, sc, ss, rss, best, b2_a, ph, s2_a, tmp, ck, c, sa_b, b2_b, s2_b = (
            rows[0], rows[1], rows[2], rows[3], rows[4], rows[5], rows[6], rows[7], rows[8], rows[9], rows[10],
            rows[11], rows[12], rows[13])
        worst = np.empty(w, np.int64)
        flags_row = np.empty((2, w), np.bool_)
        dir_bad, exact = flags_row[0], flags_row[1]
        for v in range(b * _ROWS_PER_BLOCK, min(h, (b + 1) * _ROWS_PER_BLOCK)):
            for u in range(w):
                fit_ratio[v, u] = np.nan
                mis_ratio[v, u] = np.nan
                worst_image[v, u] = -1
                flags[v, u] = 0
            bits_fit[v] = 0
            bits_per[v] = 0
            for ax in range(2):
                dir_bad[:] = False
                n_rev = 0  # pixels of the row whose contrast reversal the decoder corrected
                for u in range(w):
                    n_rev += rev[v, u, ax]
                sa, sa_prev, b2, b2_prev, s2, s2_prev = sa_a, sa_b, b2_a, b2_b, s2_a, s2_b
                for s in range(dir_st[ax], dir_st[ax + 1]):
                    _stack_row(images, v, s, ax, n_rev, st_img, cos_d, sin_d, st_first, st_n4, st_thr, st_p, st_ksig,
                               st_level, origin, upper, lines, given2, tested, rev, z, a_stack, mask, a_offs, a_buf,
                               fit_ratio, worst_image, mis_ratio, bits_fit, bits_per, counts, top, c, sa_prev, b2_prev,
                               s2_prev, dir_bad, sa, sc, ss, rss, best, worst, b2, ph, s2, tmp, ck, exact)
                    sa_prev, sa = sa, sa_prev
                    b2_prev, b2 = b2, b2_prev
                    s2_prev, s2 = s2, s2_prev
                lo_d = lo[ax]
                hi_d = hi[ax]
                n = 0
                for u in range(w):
                    cu = c[u]
                    final[v, u, ax] = cu
                    out = tested[v, u] and ((cu < lo_d) or (cu > hi_d))
                    flags[v, u] |= geometry if out else np.uint8(0)
                    n += out
                n_out[v, ax] = n


class StackRows:
    """What :func:`check_stacks` returns for S stacks of two directions on (H, W) images.

    Attributes
    ----------
    fit_ratio, mis_ratio : (H, W) float32
        max over stacks of RSS/σ_I²/threshold and |c_{k−1} − c_k|/(z·σ) (NaN: not tested).
    worst_image : (H, W) int16
        The image of the largest fit ratio (label index), −1 where none was tested.
    final : (H, W, 2) float64
        The finest coordinate per direction.
    flags : (H, W) uint8
        GEOMETRY where a tested pixel's final coordinate lies outside the screen's bounds.
    bits_fit, bits_per : (H, W, ⌈S/8⌉) uint8
        Bit s % 8 of byte s // 8: stack s's FIT_RESIDUAL / PERIOD_MISMATCH test failed.
    n_fit, n_per, n_new : (S,) int
        Per stack: the FIT_RESIDUAL and PERIOD_MISMATCH pixels, the latter not flagged at a
        coarser stack of its direction.
    top : (S,) float
        Per stack the largest tested σ_I² (0 without rows).
    n_outside : (2,) int
        GEOMETRY pixels per direction.
    a_at_mask : (M,) float64 or None
        A of stack ``a_stack`` at the ``mask`` pixels (C order).
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def bad_fit(self, s: int) -> np.ndarray:
        """(H, W) bool: stack s's FIT_RESIDUAL pixels."""
        return (self.bits_fit[..., s // 8] & np.uint8(1 << (s % 8))) != 0

    def bad_per(self, s: int) -> np.ndarray:
        """(H, W) bool: stack s's PERIOD_MISMATCH pixels."""
        return (self.bits_per[..., s // 8] & np.uint8(1 << (s % 8))) != 0

    @staticmethod
    def any_bit(bits: np.ndarray, stacks) -> np.ndarray:
        """(H, W) bool: the test failed in any of ``stacks`` (``bits``: ``bits_fit`` or ``bits_per``)."""
        out = np.zeros(bits.shape[:2], bool)
        for byte in range(bits.shape[2]):
            m = sum(1 << (s % 8) for s in stacks if s // 8 == byte)
            if m:
                out |= (bits[..., byte] & np.uint8(m)) != 0
        return out


def check_stacks(dirs, *, lines, given2, tested, rev, z: float, origin, upper, lo, hi, a_stack: int = -1,
                 mask=None) -> StackRows:
    """Test every stack of both directions (module docstring) in one pass over image rows.

    Parameters
    ----------
    dirs : two sequences (x, y) of dicts
        Per direction its stacks coarse → fine, each ``stack`` (N, H, W) grey levels with equal
        shifts, ``p`` (period, mm), ``first`` (the label index of its first image:
        ``worst_image`` = first + k) and ``thr`` (χ²(N − 3) threshold of FIT_RESIDUAL; ≤ 0 or
        N ≤ 3: not tested).
    lines : (L, 2) float64 or None
        The noise model's (a, b) per line; None: σ_I² = ``given2``.
    given2 : (H, W) float64 (a broadcast view is fine)
    tested : (H, W) bool
    rev : (H, W, 2) bool
        The decoder's reversed-contrast correction per direction.
    z : float
        The normal quantile of the period test.
    origin, upper : (2,) float
        Per direction the coarse coordinate's interval.
    lo, hi : (2,) float
        Per direction the bounds of the outside-screen test.
    a_stack : int
        The stack (index in x then y order) whose A at ``mask`` is returned; −1: none.
    mask : (H, W) bool, optional

    Returns
    -------
    StackRows
    """
    stacks = [it for d in dirs for it in d]
    h, w = tested.shape
    images = stack_images([it["stack"] for it in stacks])
    sizes = np.array([np.shape(it["stack"])[0] for it in stacks], np.int64)
    st_img = np.zeros(len(stacks) + 1, np.int64)
    np.cumsum(sizes, out=st_img[1:])
    d = [equal_shifts(int(n)) for n in sizes]
    cos_d = np.concatenate([np.cos(x) for x in d])
    sin_d = np.concatenate([np.sin(x) for x in d])
    levels = np.concatenate([np.arange(len(dd)) for dd in dirs]).astype(np.int64)
    want_a = a_stack >= 0 and mask is not None
    if want_a:
        offs = np.zeros(h + 1, np.int64)
        np.cumsum(np.count_nonzero(mask, axis=1), out=offs[1:])
        a_buf = np.empty(int(offs[-1]))
    else:
        mask, offs, a_buf = np.zeros((1, 1), bool), np.zeros(h + 1, np.int64), np.empty(0)
    nbytes = max(1, (len(stacks) + 7) // 8)
    out = StackRows(fit_ratio=np.empty((h, w), np.float32), mis_ratio=np.empty((h, w), np.float32),
                    worst_image=np.empty((h, w), np.int16), final=np.empty((h, w, 2)),
                    bits_fit=np.empty((h, w, nbytes), np.uint8), bits_per=np.empty((h, w, nbytes), np.uint8),
                    flags=np.empty((h, w), np.uint8))
    counts = np.zeros((len(stacks), h, 3), np.int64)
    top = np.zeros((len(stacks), h))
    n_out = np.zeros((h, 2), np.int64)
    ln = np.zeros((0, 2)) if lines is None else np.ascontiguousarray(lines, dtype=np.float64)
    f = np.array
    _checks_kernel(
        images, st_img, cos_d, sin_d, f([it["first"] for it in stacks], np.int64), sizes == 4,
        f([float(it["thr"]) if n > 3 else 0.0 for it, n in zip(stacks, sizes)]), f([it["p"] for it in stacks], float),
        f([it["p"] / (2.0 * math.pi) * math.sqrt(2.0 / n) for it, n in zip(stacks, sizes)]), levels,
        f([0, len(dirs[0]), len(stacks)], np.int64), f(origin, float), f(upper, float), f(lo, float), f(hi, float),
        readonly(ln), readonly(np.asarray(given2, dtype=np.float64)), readonly(tested), readonly(rev), float(z),
        np.int64(a_stack if want_a else -1), readonly(mask), offs, a_buf, out.fit_ratio, out.worst_image,
        out.mis_ratio, out.final, out.bits_fit, out.bits_per, np.uint8(PhaseFlag.GEOMETRY), out.flags, counts, top,
        n_out)
    sums = counts.sum(axis=1)
    out.n_fit, out.n_per, out.n_new = (sums[:, i] for i in range(3))
    out.top = top.max(axis=1) if h else np.zeros(len(stacks))
    out.n_outside = n_out.sum(axis=0)
    out.a_at_mask = a_buf if want_a else None
    return out
