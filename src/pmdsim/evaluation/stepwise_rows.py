"""The stepwise integration in bands of image rows where the wavefronts are the seed's L1 diamonds
(issue 25).

The wavefront pass (:func:`pmdsim.evaluation.stepwise._expand_kernel`) solves each pixel from its
4-neighbours reconstructed in earlier wavefronts. Where every pixel of the mask except the seed
(sv, su) has a 4-neighbour in the mask one step closer to the seed in the L1 (city-block)
distance |v − sv| + |u − su| (:func:`l1_layered`: a mask without holes that bend the diamonds)
and no step fails, wavefront k is the set of pixels at L1 distance k, and each pixel is solved
from its 4-neighbours at distance one less (its *upstream* neighbours: the row towards the seed's
and the pixel beside it towards the seed's column), in the neighbour order (−1, 0), (1, 0),
(0, −1), (0, 1). Any order that reaches every pixel after its upstream neighbours and before its
downstream ones (distance one more) then gathers the same neighbours and, solving each pixel by
the same functions (:func:`~pmdsim.evaluation.stepwise._gather_wavefront`,
:func:`~pmdsim.evaluation.stepwise._solve_wavefront`, whose per-pixel arithmetic does not depend
on the other pixels of the batch), gives the same bits.

:func:`rows_stepwise_kernel` uses such an order with contiguous reads: the seed's row (from the
seed's column to the right, then to the left), then the rows below it and the rows above it —
two independent halves, in parallel — each in bands of ``band`` rows from the seed's row
outwards. A band is swept right of the seed's column (columns su, su + 1, …) and then left of it
(su − 1, su − 2, …), skewed: at step s its j-th row (counted from the seed's side) is at the
s − j-th column of the sweep, so the band's pixels of one step are never 4-adjacent, each one's
upstream neighbours were solved at an earlier step (or band, or sweep), and they are solved
together in lock-step like a wavefront's (a batch of at most ``band`` pixels, each row read left
to right or right to left). A pixel's downstream neighbours are always solved later: the row
beyond it at a later step or band, the pixel beside it away from the seed's column at the next
step, and the seed's column before the left sweep only from its own row's right sweep.

The pass is optimistic: the mask is checked first (not :func:`l1_layered`: −1, nothing written)
and a failed step (its pixel would stay unreached in its wavefront and be reached later from
another side in the wavefront pass) stops it (−2); the caller then runs the wavefront pass on a
fresh state (:func:`pmdsim.evaluation.stepwise._run_stepwise`).
"""

from __future__ import annotations

import numba
import numpy as np

from .prefetch import prefetch
from .stepwise import _gather_end, _gather_own, _gather_slot, _solve_wavefront

__all__ = ["rows_stepwise_kernel", "l1_layered", "BAND_ROWS"]

#: Columns ahead of each row's pixel whose inputs a sweep prefetches (the band's rows are as many
#: streams: more than the hardware prefetchers follow).
PREFETCH_AHEAD = 8

#: Rows per band of :func:`rows_stepwise_kernel` (the lock-step batch: at most this many pixels).
BAND_ROWS = 128


@numba.njit(cache=True, nogil=True)
def l1_layered(S, sv, su):
    """True if every pixel of S (H, W) bool except the seed (sv, su) has a 4-neighbour in S one
    step closer to the seed in the L1 distance (then each pixel's wavefront is its L1 distance:
    module docstring)."""
    H, W = S.shape
    if not S[sv, su]:
        return False
    for v in range(H):
        for u in range(W):
            if not S[v, u] or (v == sv and u == su):
                continue
            if not ((v > sv and S[v - 1, u]) or (v < sv and S[v + 1, u]) or (u > su and S[v, u - 1])
                    or (u < su and S[v, u + 1])):
                return False
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gather_step(d, q, valid, tz, gb, gcol, sv, su, nv, nu, n, dv, du, own, nb, m):
    """:func:`~pmdsim.evaluation.stepwise._gather_wavefront` for a sweep's step (the same rows
    ``own``, ``nb``, ``m``) without its search of the four neighbours: a pixel's reconstructed
    4-neighbours are its upstream ones in the mask, the row towards the seed's (v − ``dv``, in slot
    order first: offset (∓1, 0)) and the pixel towards the seed's column (u − ``du``: (0, ±1)), t
    from ``tz`` (H, W) and the slopes from the two-row buffer ``gb`` (2, W, 2) (row v in gb[v % 2]),
    those in the seed's column from ``gcol`` (H, 2) (the left sweep reads them after the right
    sweep of the band's later rows has reused gb)."""
    H = valid.shape[0]
    for i in range(n):
        vb = nv[i]
        ub = nu[i]
        _gather_own(d, q, vb, ub, own, i)
        j = 0
        va = vb - dv
        if vb != sv and 0 <= va < H and valid[va, ub]:
            _gather_slot(d, va, ub, tz[va, ub], gb[va % 2, ub, 0], gb[va % 2, ub, 1], nb, j, i)
            j += 1
        ua = ub - du
        if abs(ua - su) < abs(ub - su) and valid[vb, ua]:
            if ua == su:
                _gather_slot(d, vb, ua, tz[vb, ua], gcol[vb, 0], gcol[vb, 1], nb, j, i)
            else:
                _gather_slot(d, vb, ua, tz[vb, ua], gb[vb % 2, ua, 0], gb[vb % 2, ua, 1], nb, j, i)
            j += 1
        _gather_end(nb, m, j, i)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sweep(o, d, q, valid, tz, gb, gcol, sv, su, tol, max_iter, v0, dv, n_rows, right, nv, nu, own, nb, m, res,
           status, stats):
    """One skewed sweep of the rows v0, v0 + dv, …, (``n_rows`` of them) right of the seed's column
    (``right``: columns su, su + 1, …) or left of it (su − 1, su − 2, …): at step s, row j's pixel
    at the sweep's column s − j, if it is valid and not the seed, joins the step's batch, solved as
    a wavefront (module docstring): t into ``tz``, the slopes into ``gb`` (:func:`_gather_step`).
    ``stats`` (3,) float: the largest corrector count, the largest final |Δz| and the number of
    pixels that missed ``tol``, updated. Returns False (at once) if a step failed."""
    H, W = valid.shape
    n_cols = W - su if right else su
    c0 = su if right else su - 1
    du = 1 if right else -1
    for s in range(n_cols + n_rows - 1):
        n = np.int64(0)
        for j in range(max(0, s - n_cols + 1), min(n_rows, s + 1)):
            v = v0 + j * dv
            u = c0 + (s - j) * du
            ua = u + PREFETCH_AHEAD * du  # this row's and the upstream row's inputs a few steps ahead
            if 0 <= ua < W:
                ka = v * W + ua
                prefetch(d, 3 * ka)
                prefetch(q, 3 * ka)
                if 0 <= v - dv < H:
                    prefetch(d, 3 * (ka - dv * W))
                    prefetch(tz, ka - dv * W)
            if valid[v, u] and not (v == sv and u == su):
                nv[n] = v
                nu[n] = u
                n += 1
        if n == 0:
            continue
        _gather_step(d, q, valid, tz, gb, gcol, sv, su, nv, nu, n, dv, du, own, nb, m)
        _solve_wavefront(o, own, nb, m, n, tol, max_iter, res, status)
        for i in range(n):
            if status[i] < 0:
                return False
            vb = nv[i]
            ub = nu[i]
            change = res[3, i]
            used = status[i] - 1
            if change >= tol:
                stats[2] += 1.0
            if used > stats[0]:
                stats[0] = used
            if change > stats[1]:
                stats[1] = change
            tz[vb, ub] = res[0, i]
            gb[vb % 2, ub, 0] = res[1, i]
            gb[vb % 2, ub, 1] = res[2, i]
            if ub == su:
                gcol[vb, 0] = res[1, i]
                gcol[vb, 1] = res[2, i]
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _half(o, d, q, valid, tz, gb, gcol, sv, su, tol, max_iter, v0, dv, n_rows, band, stats):
    """The rows v0, v0 + dv, … (``n_rows``) in bands of ``band`` rows (:func:`_sweep` right, then
    left, per band), with their own batch buffers and slopes' rows ``gb``. Returns 1 at a failed
    step, else 0."""
    nv = np.empty(band, dtype=np.int64)  # the step's pixels: rows, columns
    nu = np.empty(band, dtype=np.int64)
    own = np.empty((6, band))
    nb = np.empty((4, 5, band))
    m = np.empty(band, dtype=np.int64)
    res = np.empty((7, band))
    status = np.empty(band, dtype=np.int64)
    for b0 in range(0, n_rows, band):
        nr = min(band, n_rows - b0)
        vb = v0 + b0 * dv
        for right in (True, False):
            if not _sweep(o, d, q, valid, tz, gb, gcol, sv, su, tol, max_iter, vb, dv, nr, right, nv, nu, own, nb, m,
                          res, status, stats):
                return 1
    return 0


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def rows_stepwise_kernel(o, d, q, valid, z, sv, su, t0, gx0, gy0, tol, max_iter, band):
    """The stepwise integration from the seed (sv, su) (ray parameter t0, slopes gx0, gy0) over
    ``valid`` (H, W) in bands of image rows (module docstring); the other arguments as
    :func:`pmdsim.evaluation.stepwise._expand_kernel`'s. Writes the heights o_z + t·d_z into ``z``
    (H, W) (NaN off ``valid``; the seed's as well: the caller sets it) and returns (largest
    corrector count, largest final |Δz|, number of pixels that missed ``tol``, code): code 0
    when done (the wavefront pass's values, every valid pixel reached), −1 if ``valid`` is not
    :func:`l1_layered` from the seed (nothing written), −2 if a step failed (``z`` partly
    written: the caller runs the wavefront pass). No (H, W, 4) state: t is kept in ``z`` until
    the heights replace it, the slopes in two rows per part."""
    H, W = valid.shape
    if not l1_layered(valid, sv, su):
        return 0, 0.0, 0, -1
    stats = np.zeros((3, 3))  # per part (seed row, below, above): max corrector count, max |Δz|, unconverged
    gb = np.empty((3, 2, W, 2))
    gcol = np.empty((H, 2))  # the seed's column (each row written by one part)
    z[sv, su] = t0
    gcol[sv, 0] = gx0
    gcol[sv, 1] = gy0
    gb[0, sv % 2, su, 0] = gx0
    gb[0, sv % 2, su, 1] = gy0
    if _half(o, d, q, valid, z, gb[0], gcol, sv, su, tol, max_iter, sv, 1, 1, np.int64(1), stats[0]) != 0:
        return 0, 0.0, 0, -2
    gb[1, sv % 2] = gb[0, sv % 2]  # the seed's row: the upstream row of both halves' first rows
    gb[2, sv % 2] = gb[0, sv % 2]
    fail = np.zeros(2, dtype=np.int64)
    for h in numba.prange(0, 2):  # the rows below the seed's, the rows above it
        n_rows = H - 1 - sv if h == 0 else sv
        fail[h] = _half(o, d, q, valid, z, gb[1 + h], gcol, sv, su, tol, max_iter, sv + 1 - 2 * h, 1 - 2 * h, n_rows,
                        band, stats[1 + h])
    if fail[0] != 0 or fail[1] != 0:
        return 0, 0.0, 0, -2
    oz = o[2]
    for v in numba.prange(0, H):  # t → heights (as stepwise._heights)
        for u in range(W):
            z[v, u] = oz + z[v, u] * d[v, u, 2] if valid[v, u] else np.nan
    max_used = 0
    max_change = 0.0
    n_unconv = 0
    for k in range(3):
        max_used = max(max_used, int(stats[k, 0]))
        max_change = max(max_change, stats[k, 1])
        n_unconv += int(stats[k, 2])
    return max_used, max_change, n_unconv, 0
