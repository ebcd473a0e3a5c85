"""The stepwise integration's sampled height σ as one compiled pass (issue 25, item 1).

:func:`stepwise_sampled` returns Σ_k δz_k² per pixel for K sampled slope perturbations
δg_k = A ξ_k (ξ the counter-based Rademacher draws of :mod:`pmdsim.evaluation.uncertainty`)
through the linearised stepwise recursion: for each pixel b, in wavefront order from the seed,
from its neighbours a of the previous wavefront,

    δz_b = [Σ_a (½ (A_a ξ_a)·Δxy_ab − J_a δz_a) + Σ_a ½ (A_b ξ_b)·Δxy_ab] / Σ_a J_b.

All K samples are carried together: one wavefront's δz is a (width, K) block, so every pixel's
geometry, Jacobian terms and random words are read once for all samples (rather than once per
32 samples). Per wavefront the kernel first gathers each pixel's coefficients (the pixels of a
wavefront lie on different image rows, so this is a tight loop of independent loads whose cache
misses overlap), then runs the sample loops over contiguous memory, branch-free and vectorised
(the ±1 draws select the sign of a term, ``-x if bit else x``, which equals x·(1 − 2·bit)
exactly), then adds Σ_k δz_k² to the pixels. Every operation and its order per sample are those
of the sample-chunked recursion it replaced, so the result is bit-identical to it; it equals the
sample-by-sample recursion (``_stepwise_linear`` of each ``_sample_dg``) to rounding
(tests/test_uncertainty_stepwise.py).

The wavefronts are serial (each depends on the previous one); the samples are the vector lanes.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["stepwise_sampled"]

@numba.njit(cache=True, nogil=True, inline="always")
def _splitmix64(x):
    """SplitMix64's output function (Steele, Lea & Flood 2014): the draws' counter-based hash."""
    z = x + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, nogil=True, inline="always")
def _seed_key(seed):
    """The hashed seed of a set of draws (:func:`_draw_word`)."""
    return _splitmix64(np.uint64(seed))


@numba.njit(cache=True, nogil=True, inline="always")
def _draw_word(key, pix, chunk, n_chunks):
    """64 random bits of pixel ``pix`` (flat index) for samples 32·chunk … 32·chunk + 31 (bit 2k:
    ξ_x, 2k + 1: ξ_y), ``key`` = :func:`_seed_key` (seed): the one definition of the σ
    estimator's Rademacher draws (the stepwise kernel, the least-squares and stereo paths)."""
    return _splitmix64(key ^ np.uint64(pix * n_chunks + chunk))


@numba.njit(cache=True, nogil=True, inline="always")
def _edge_jac_rows(ga, gb):
    """J_a, J_b and Δx, Δy of the trapezoidal equation of the edge a → b (as least_squares._edge)
    from the two pixels' geometry rows ga, gb (8,) (``uncertainty._geometry``)."""
    Gx = 0.5 * (ga[2] + gb[2])
    Gy = 0.5 * (ga[3] + gb[3])
    dx = gb[0] - ga[0]
    dy = gb[1] - ga[1]
    Ja = -1.0 + (Gx * ga[6] + Gy * ga[7]) - 0.5 * (ga[4] * dx + ga[5] * dy)
    Jb = 1.0 - (Gx * gb[6] + Gy * gb[7]) - 0.5 * (gb[4] * dx + gb[5] * dy)
    return Ja, Jb, dx, dy


@numba.njit(cache=True, nogil=True)
def _edge_jac(geo, va, ua, vb, ub):
    """:func:`_edge_jac_rows` of the edge (va, ua) → (vb, ub) of the geometry map geo (H, W, 8)."""
    return _edge_jac_rows(geo[va, ua], geo[vb, ub])


@numba.njit(cache=True, nogil=True, inline="always")
def _add_edge(ga, gb, Aa, Ab, e_c, e_pos, i, m, pa, den, ux, uy):
    """Pixel i's m-th upstream edge a → b (a at ``pa`` in the previous wavefront; ga, gb (8,)
    geometry rows, Aa, Ab (2, 2) J·diag(σ)): e_c[i, m] = ½ (A_a^T Δxy) x, y and J_a, e_pos[i, m] =
    pa; returns den + J_b, ux, uy + ½ (A_b^T Δxy) x, y and m + 1."""
    Ja, Jb, dx, dy = _edge_jac_rows(ga, gb)
    e_c[i, m, 0] = 0.5 * (Aa[0, 0] * dx + Aa[1, 0] * dy)
    e_c[i, m, 1] = 0.5 * (Aa[0, 1] * dx + Aa[1, 1] * dy)
    e_c[i, m, 2] = Ja
    e_pos[i, m] = pa
    return (den + Jb, ux + 0.5 * (Ab[0, 0] * dx + Ab[1, 0] * dy), uy + 0.5 * (Ab[0, 1] * dx + Ab[1, 1] * dy),
            m + 1)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _edge_samples(cur, i, prev, pa, k0, n, w, vx, vy, Ja):
    """cur[i, k0 + k] += ±vx ± vy − J_a·prev[pa, k0 + k], k < n, for the samples of one word
    (signs: its bits 2k, 2k + 1)."""
    z = cur[i, k0:]  # (no bounds or wraparound checks in the loop: it vectorises)
    za = prev[pa, k0:]
    for k in range(n):
        tx = -vx if (w >> np.uint64(2 * k)) & np.uint64(1) else vx
        ty = -vy if (w >> np.uint64(2 * k + 1)) & np.uint64(1) else vy
        z[k] += tx + ty - Ja * za[k]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _own_samples(cur, i, k0, n, w, ux, uy, den):
    """z_k = (z_k ± ux ± uy) / den for the samples k < n of one word, z = cur[i, k0:]."""
    z = cur[i, k0:k0 + n]
    for k in range(n):
        tx = -ux if (w >> np.uint64(2 * k)) & np.uint64(1) else ux
        ty = -uy if (w >> np.uint64(2 * k + 1)) & np.uint64(1) else uy
        z[k] = (z[k] + tx + ty) / den


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _sum_squares(z):
    """Σ_k z_k² of z (K,) on 8 lanes: lane j sums z_k² for k ≡ j (mod 8) in sample order, then
    the lanes are added pairwise, ((0 + 1) + (2 + 3)) + ((4 + 5) + (6 + 7)), and the samples past
    the last group of 8 in order after them. Equal to the in-order sum to K·ε relative (all
    terms ≥ 0); the lanes vectorise where the in-order sum is a chain of K dependent adds."""
    K = z.size
    K8 = K - K % 8
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    for k in range(0, K8, 8):
        s0 += z[k] * z[k]
        s1 += z[k + 1] * z[k + 1]
        s2 += z[k + 2] * z[k + 2]
        s3 += z[k + 3] * z[k + 3]
        s4 += z[k + 4] * z[k + 4]
        s5 += z[k + 5] * z[k + 5]
        s6 += z[k + 6] * z[k + 6]
        s7 += z[k + 7] * z[k + 7]
    s = ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))
    for k in range(K8, K):
        s += z[k] * z[k]
    return s


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _fused_samples(z, za0, za1, n, m, w, ux, uy, den, w0, vx0, vy0, J0, w1, vx1, vy1, J1):
    """The samples k < n of one word of a pixel with m ≤ 2 upstream edges in one pass: z_k = 0, then
    per edge j < m z_k += ±vx_j ± vy_j − J_j·za_j[k] (its word w_j's bits), then z_k = (z_k ± ux
    ± uy) / den (the pixel's word w) — the operations of :func:`_edge_samples` and
    :func:`_own_samples` on z in the same order (the same bits), without storing and reloading
    z between them."""
    for k in range(n):
        b0 = np.uint64(2 * k)
        b1 = np.uint64(2 * k + 1)
        acc = 0.0
        if m > 0:
            tx = -vx0 if (w0 >> b0) & np.uint64(1) else vx0
            ty = -vy0 if (w0 >> b1) & np.uint64(1) else vy0
            acc += tx + ty - J0 * za0[k]
        if m > 1:
            tx = -vx1 if (w1 >> b0) & np.uint64(1) else vx1
            ty = -vy1 if (w1 >> b1) & np.uint64(1) else vy1
            acc += tx + ty - J1 * za1[k]
        tx = -ux if (w >> b0) & np.uint64(1) else ux
        ty = -uy if (w >> b1) & np.uint64(1) else uy
        z[k] = (acc + tx + ty) / den


@numba.njit(cache=True, nogil=True)
def _wavefront_buffers(width, K):
    """The sampled recursion's per-wavefront buffers for ``width`` pixels: δz of the previous and
    the current wavefront (width, K), their draws' words (width, ⌈K/32⌉), and the coefficients
    gathered first (the pixels lie on different image rows: a tight loop of independent loads
    overlaps their cache misses), then used contiguously: upstream edge counts, their positions
    in the previous wavefront, per edge ½ (A_a^T Δxy) x, y and J_a, per pixel Σ ½ (A_b^T Δxy)
    x, y and Σ J_b, and Σ_k δz_k²."""
    n_chunks = (K + 31) // 32
    return (np.zeros((width, K)), np.zeros((width, K)), np.zeros((width, n_chunks), dtype=np.uint64),
            np.zeros((width, n_chunks), dtype=np.uint64), np.zeros(width, dtype=np.int64),
            np.zeros((width, 4), dtype=np.int64), np.zeros((width, 4, 3)), np.zeros((width, 3)), np.zeros(width))


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _pixel_samples(kb, key, K, m, e_pos, e_c, ux, uy, den, prev, cur, i, w_prev, w_cur):
    """All K samples of pixel kb (flat index) into cur[i] (K,) and its draws into w_cur[i], from
    its m upstream edges (δz in the rows e_pos[:m] of ``prev``, their draws in ``w_prev``; e_c[:m]
    (m, 3) their ½ (A_a^T Δxy) x, y and J_a) and its own ux, uy and Σ J_b = ``den``. Returns
    Σ_k δz_k² (:func:`_sum_squares`), or −1.0 if den = 0 (δz is then 0). ``prev`` may be
    ``cur`` (other rows)."""
    n_chunks = (K + 31) // 32
    for c in range(n_chunks):
        w_cur[i, c] = _draw_word(key, kb, c, n_chunks)
    z = cur[i]
    if m <= 2 and den != 0.0:  # the same operations in one pass per sample (:func:`_fused_samples`)
        p0 = e_pos[0] if m > 0 else 0
        p1 = e_pos[1] if m > 1 else 0
        for c in range(n_chunks):
            _fused_samples(z[32 * c:], prev[p0, 32 * c:], prev[p1, 32 * c:], min(32, K - 32 * c), m, w_cur[i, c],
                           ux, uy, den, w_prev[p0, c], e_c[0, 0], e_c[0, 1], e_c[0, 2], w_prev[p1, c], e_c[1, 0],
                           e_c[1, 1], e_c[1, 2])
        return _sum_squares(z)
    for k in range(K):
        z[k] = 0.0
    for j in range(m):
        vx = e_c[j, 0]
        vy = e_c[j, 1]
        Ja = e_c[j, 2]
        pa = e_pos[j]
        for c in range(n_chunks):
            _edge_samples(cur, i, prev, pa, 32 * c, min(32, K - 32 * c), w_prev[pa, c], vx, vy, Ja)
    if den == 0.0:
        for k in range(K):
            z[k] = 0.0
        return -1.0
    for c in range(n_chunks):
        _own_samples(cur, i, 32 * c, min(32, K - 32 * c), w_cur[i, c], ux, uy, den)
    return _sum_squares(z)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _wavefront_samples(idx, nL, key, K, n_in, e_pos, e_c, b_c, prev, cur, w_prev, w_cur, s_out):
    """All K samples of the wavefront's pixels idx[:nL] (flat indices) from their gathered
    coefficients (n_in, e_pos, e_c, b_c) and the previous wavefront's δz ``prev`` and draws
    ``w_prev``: δz into ``cur``, the draws into ``w_cur``, Σ_k δz_k² into ``s_out``
    (:func:`_pixel_samples`). Returns False if a pixel's coefficient Σ J_b vanishes (its δz is
    then 0)."""
    ok = True
    for i in range(nL):
        s = _pixel_samples(idx[i], key, K, n_in[i], e_pos[i], e_c[i], b_c[i, 0], b_c[i, 1], b_c[i, 2], prev, cur, i,
                           w_prev, w_cur)
        if s < 0.0:
            ok = False
            s = 0.0
        s_out[i] = s
    return ok


@numba.njit(cache=True, nogil=True, error_model="numpy")
def stepwise_sampled(geo, layer, order, starts, pos, A, seed, K, acc):
    """Σ_k δz_k² (added to ``acc`` (H, W)) for K samples through the linearised stepwise
    recursion (module docstring).

    Parameters
    ----------
    geo : (H, W, 8) float64
        The linearisation's per-pixel geometry (``uncertainty._geometry``).
    layer : (H, W) int64
        Wavefront index of each pixel (−1: not reached).
    order : (H·W,) int64
        Flat pixel indices in wavefront order; ``starts`` (n_layers + 1,) their wavefront bounds.
    pos : (H, W) int64
        Each pixel's index within its wavefront.
    A : (H, W, 2, 2) float64
        J·diag(σ_xy): the slopes' perturbation per unit draw (0 off the reconstruction).
    seed, K : int
        The draws' seed and the number of samples.
    acc : (H, W) float64
        Accumulator, updated in place.

    Returns
    -------
    bool
        False if a pixel's coefficient Σ J_b vanishes.
    """
    H, W = layer.shape
    n_layers = starts.size - 1
    width = np.int64(1)  # not a literal: one signature of _wavefront_buffers
    for L in range(n_layers):
        width = max(width, starts[L + 1] - starts[L])
    n_chunks = (K + 31) // 32
    prev, cur, w_prev, w_cur, n_in, e_pos, e_c, b_c, s_out = _wavefront_buffers(width, K)
    key = _seed_key(seed)
    ok = True
    k0 = order[0]
    for c in range(n_chunks):  # the seed: δz = 0, its draws enter its neighbours' equations
        w_prev[0, c] = _draw_word(key, k0, c, n_chunks)
    for L in range(1, n_layers):
        s0 = starts[L]
        nL = starts[L + 1] - s0
        for i in range(nL):  # gather
            kb = order[s0 + i]
            vb = kb // W
            ub = kb - vb * W
            ux = 0.0
            uy = 0.0
            den = 0.0
            m = 0
            for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                va = vb + dv
                ua = ub + du
                if not (0 <= va < H and 0 <= ua < W) or layer[va, ua] != L - 1:
                    continue
                den, ux, uy, m = _add_edge(geo[va, ua], geo[vb, ub], A[va, ua], A[vb, ub], e_c, e_pos, i, m, pos[va, ua],
                                           den, ux, uy)
            n_in[i] = m
            b_c[i, 0] = ux
            b_c[i, 1] = uy
            b_c[i, 2] = den
        if not _wavefront_samples(order[s0:], nL, key, K, n_in, e_pos, e_c, b_c, prev, cur, w_prev, w_cur, s_out):
            ok = False
        for i in range(nL):  # scatter
            kb = order[s0 + i]
            vb = kb // W
            acc[vb, kb - vb * W] += s_out[i]
        prev, cur = cur, prev
        w_prev, w_cur = w_cur, w_prev
    return ok
