"""The stepwise integration's noise σ in one pass from the reconstruction (issue 25, item 1).

:func:`stepwise_noise_sigma` gives what :func:`~pmdsim.evaluation.uncertainty.surface_uncertainty`
computed for a stepwise reconstruction in four full-size stages — the linearisation's geometry
(H, W, 8), the wavefront maps (layer, order, position), A = J·diag(σ_xy) (H, W, 2, 2), then the
sampled recursion (:func:`~pmdsim.evaluation.uncertainty_stepwise.stepwise_sampled`) — in one
pass over the wavefronts from the seed: each pixel's geometry row and A are computed when its
wavefront is reached and kept only in that wavefront's buffer (its downstream neighbours, all in
the next wavefront, read them there), the slopes' σ written on the way. Per 1920×1200 camera
that is ≈ 0.45 GB of maps less to allocate and touch for the first time (≈ 1.4–3 ms per MB on the
project's VM), and the neighbours' coefficients come from the previous wavefront's contiguous
buffer instead of image rows.

Wavefronts: breadth-first from the seed within S; wavefront L + 1 is every pixel of S not yet
reached next to one of wavefront L, in the order of ``uncertainty._bfs``. On the 4-connected
grid two pixels at the same distance from one seed are never adjacent (the grid is bipartite),
so when wavefront L + 1 is gathered, its pixels' reached neighbours are exactly their
neighbours in wavefront L: one (H, W) int32 map of each reached pixel's index within its
wavefront replaces the layer, order and position maps. Every value is computed by the same
functions in the same order as in the four stages (the geometry as ``_row_geometry``, A and the
slopes' σ by ``_pixel_jacobian``, the coefficients by ``_add_edge``, the samples by
``_wavefront_samples``), so σ is bit-identical to theirs (tests/test_uncertainty_fused.py).
Where the wavefronts are the seed's L1 diamonds (a mask without holes that bend them),
:func:`stepwise_noise_sigma` runs the same computation in image-row order instead
(:mod:`pmdsim.evaluation.uncertainty_stepwise_rows`: contiguous reads, the same values).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .prefetch import prefetch as _prefetch
from .uncertainty import _tangent_array
from .uncertainty_stepwise import _draw_word, _add_edge, _seed_key, _wavefront_buffers, _wavefront_samples
from .uncertainty_stepwise_rows import _pixel_inputs, rows_kernel

__all__ = ["stepwise_noise_sigma"]

#: Pixels ahead whose inputs the wavefront pass prefetches (their cache lines lie on different
#: image rows: without it each pixel waits for its own misses behind the previous pixel's work).
PREFETCH_AHEAD = 6


@numba.njit(cache=True, nogil=True, inline="always")
def _prefetch_pixel(d, q, z, p, sig, k):
    """Prefetch the inputs of flat pixel k (its d, q, z, p and σ)."""
    _prefetch(d, 3 * k)
    _prefetch(q, 3 * k)
    _prefetch(z, k)
    _prefetch(p, 3 * k)
    _prefetch(sig, 2 * k)


@numba.njit(cache=True, nogil=True)
def _doubled(b):
    """``b`` (n,) uint8 with n zero bytes after its own: one signature for every buffer's growth
    (:func:`_grown`)."""
    return np.concatenate((b, np.zeros_like(b)))


@numba.njit(cache=True, nogil=True, inline="always")
def _grown(a):
    """``a`` (n, ...) (C-contiguous, any dtype) with n more rows of zeros after its own (a
    wavefront buffer widened): :func:`_doubled` of its bytes, viewed as ``a``'s dtype and shape."""
    return _doubled(a.reshape(-1).view(np.uint8)).view(a.dtype).reshape((2 * a.shape[0],) + a.shape[1:])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fused_kernel(o, d, q, z, S, sv, su, p, T, sig, seed, K, acc, gstd):
    """The heights' σ sqrt(Σ_k δz_k² / K) into ``acc`` (H, W) (zeros on entry; NaN off S) and the
    slopes' σ into ``gstd`` (H, W, 2) for the pixels reached from the seed (sv, su) within S
    (module docstring). Returns 0, or 1 if a reached pixel's geometry is not finite, 2 if a
    pixel's coefficient Σ J_b vanishes."""
    H, W = S.shape
    cap = 2 * min(H, W) + 2  # the unobstructed frame's widest wavefront; grown where holes widen it
    n_chunks = (K + 31) // 32
    per_pixel = 0 if T.shape[0] == 1 else 1
    pos = np.full((H, W), -1, dtype=np.int32)  # index within its wavefront; −1: not reached
    cur_idx = np.empty(cap, dtype=np.int64)
    nxt_idx = np.empty(cap, dtype=np.int64)
    geo_p = np.empty((cap, 8))
    geo_c = np.empty((cap, 8))
    A_p = np.empty((cap, 2, 2))
    A_c = np.empty((cap, 2, 2))
    prev, cur, w_prev, w_cur, n_in, e_pos, e_c, b_c, s_out = _wavefront_buffers(cap, K)
    key = _seed_key(seed)
    pos[sv, su] = 0
    cur_idx[0] = sv * W + su
    n_cur = 1
    if not _pixel_inputs(o, d, q, z, p, T, per_pixel, sig, sv, su, geo_p[0], A_p[0], gstd):
        return 1
    for c in range(n_chunks):  # the seed: δz = 0, its draws enter its neighbours' equations
        w_prev[0, c] = _draw_word(key, sv * W + su, c, n_chunks)
    status = 0
    while True:
        n_nxt = np.int64(0)  # the next wavefront (not a literal 0: one signature of _wavefront_samples)
        for i in range(n_cur):
            k = cur_idx[i]
            v = k // W
            u = k - v * W
            for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                vv = v + dv
                uu = u + du
                if 0 <= vv < H and 0 <= uu < W and S[vv, uu] and pos[vv, uu] < 0:
                    if n_nxt == nxt_idx.shape[0]:  # a mask with holes: the wavefront is wider
                        nxt_idx = _grown(nxt_idx)
                    pos[vv, uu] = n_nxt
                    nxt_idx[n_nxt] = vv * W + uu
                    n_nxt += 1
        if n_nxt == 0:
            break
        while geo_c.shape[0] < n_nxt:  # every per-wavefront buffer as wide (the previous one's kept)
            cur_idx = _grown(cur_idx)
            geo_p = _grown(geo_p)
            geo_c = _grown(geo_c)
            A_p = _grown(A_p)
            A_c = _grown(A_c)
            prev = _grown(prev)
            cur = _grown(cur)
            w_prev = _grown(w_prev)
            w_cur = _grown(w_cur)
            n_in = _grown(n_in)
            e_pos = _grown(e_pos)
            e_c = _grown(e_c)
            b_c = _grown(b_c)
            s_out = _grown(s_out)
        while nxt_idx.shape[0] < geo_c.shape[0]:  # the index buffers swap: keep them as wide
            nxt_idx = _grown(nxt_idx)
        for i in range(n_nxt):  # its pixels' inputs and coefficients
            if i + PREFETCH_AHEAD < n_nxt:
                _prefetch_pixel(d, q, z, p, sig, nxt_idx[i + PREFETCH_AHEAD])
            kb = nxt_idx[i]
            vb = kb // W
            ub = kb - vb * W
            gb = geo_c[i]
            Ab = A_c[i]
            if not _pixel_inputs(o, d, q, z, p, T, per_pixel, sig, vb, ub, gb, Ab, gstd):
                return 1
            ux = 0.0
            uy = 0.0
            den = 0.0
            m = 0
            for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                va = vb + dv
                ua = ub + du
                if not (0 <= va < H and 0 <= ua < W):
                    continue
                pa = pos[va, ua]
                if pa < 0:  # not reached; reached neighbours are in the previous wavefront
                    continue
                den, ux, uy, m = _add_edge(geo_p[pa], gb, A_p[pa], Ab, e_c, e_pos, i, m, pa, den, ux, uy)
            n_in[i] = m
            b_c[i, 0] = ux
            b_c[i, 1] = uy
            b_c[i, 2] = den
        if not _wavefront_samples(nxt_idx, n_nxt, key, K, n_in, e_pos, e_c, b_c, prev, cur, w_prev, w_cur, s_out):
            status = 2
        for i in range(n_nxt):  # scatter
            kb = nxt_idx[i]
            vb = kb // W
            acc[vb, kb - vb * W] += s_out[i]
        prev, cur = cur, prev
        w_prev, w_cur = w_cur, w_prev
        geo_p, geo_c = geo_c, geo_p
        A_p, A_c = A_c, A_p
        cur_idx, nxt_idx = nxt_idx, cur_idx
        n_cur = n_nxt
    for v in range(H):  # σ = sqrt(Σ_k δz_k² / K) on S (as numpy's sqrt(acc / K)), NaN elsewhere
        for u in range(W):
            acc[v, u] = np.sqrt(acc[v, u] / K) if S[v, u] else np.nan
    return status


def stepwise_noise_sigma(o, d, q, rec, dq_dxy, std_xy_mm, samples: int, rng_seed: int):
    """The noise part of a stepwise reconstruction's σ in one pass (module docstring).

    Parameters
    ----------
    o : ndarray (3,)
        Camera centre, mm (reconstruction frame).
    d, q : ndarray (H, W, 3)
        View rays and screen points (reconstruction frame, mm).
    rec : Reconstruction
        A stepwise reconstruction (its heights, points, mask and seed).
    dq_dxy : ndarray (H, W, 3, 2) or (3, 2)
        The screen tangents ∂q/∂(x_s, y_s).
    std_xy_mm : ndarray (H, W, 2)
        The decoder's σ of the screen coordinates (finite on the reconstruction), mm.
    samples, rng_seed : int
        K and the seed of the estimator.

    Returns
    -------
    h : ndarray (H, W)
        The heights' σ, mm (NaN off the reconstruction).
    g : ndarray (H, W, 2)
        The slopes' σ (dimensionless; NaN off the reconstruction).
    status : int
        0, 1 (a geometry that is not finite) or 2 (a vanishing step coefficient): the caller
        raises.
    """
    S = np.ascontiguousarray(rec.reconstructed, dtype=bool)
    H, W = S.shape
    K = int(samples)
    acc = np.zeros((H, W))
    gstd = np.full((H, W, 2), np.nan)
    sv, su = (int(x) for x in rec.seed_pixel)
    args = (np.asarray(o, dtype=float), np.ascontiguousarray(d, dtype=float), np.ascontiguousarray(q, dtype=float),
            np.ascontiguousarray(rec.height_mm, dtype=float), S, sv, su,
            np.ascontiguousarray(rec.p_sample_mm, dtype=float), _tangent_array(dq_dxy),
            readonly(np.ascontiguousarray(std_xy_mm, dtype=float)), int(rng_seed) % (1 << 63), K, acc, gstd)
    status = rows_kernel(*args)  # the same values in image-row order where the wavefronts are diamonds
    if status < 0:
        status = _fused_kernel(*args)
    return acc, gstd, int(status)
