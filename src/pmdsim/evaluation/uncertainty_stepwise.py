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

@numba.njit(cache=True, inline="always")
def _splitmix64(x):
    """SplitMix64's output function (Steele, Lea & Flood 2014): the draws' counter-based hash."""
    z = x + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, inline="always")
def _seed_key(seed):
    """The hashed seed of a set of draws (:func:`_draw_word`)."""
    return _splitmix64(np.uint64(seed))


@numba.njit(cache=True, inline="always")
def _draw_word(key, pix, chunk, n_chunks):
    """64 random bits of pixel ``pix`` (flat index) for samples 32·chunk … 32·chunk + 31 (bit 2k:
    ξ_x, 2k + 1: ξ_y), ``key`` = :func:`_seed_key` (seed): the one definition of the σ
    estimator's Rademacher draws (the stepwise kernel, the least-squares and stereo paths)."""
    return _splitmix64(key ^ np.uint64(pix * n_chunks + chunk))


@numba.njit(cache=True)
def _edge_jac(geo, va, ua, vb, ub):
    """J_a, J_b and Δx, Δy of the trapezoidal equation of the edge a → b (as least_squares._edge)."""
    Gx = 0.5 * (geo[va, ua, 2] + geo[vb, ub, 2])
    Gy = 0.5 * (geo[va, ua, 3] + geo[vb, ub, 3])
    dx = geo[vb, ub, 0] - geo[va, ua, 0]
    dy = geo[vb, ub, 1] - geo[va, ua, 1]
    Ja = -1.0 + (Gx * geo[va, ua, 6] + Gy * geo[va, ua, 7]) - 0.5 * (geo[va, ua, 4] * dx + geo[va, ua, 5] * dy)
    Jb = 1.0 - (Gx * geo[vb, ub, 6] + Gy * geo[vb, ub, 7]) - 0.5 * (geo[vb, ub, 4] * dx + geo[vb, ub, 5] * dy)
    return Ja, Jb, dx, dy


@numba.njit(cache=True, error_model="numpy")
def _edge_samples(cur, i, prev, pa, k0, n, w, vx, vy, Ja):
    """cur[i, k0 + k] += ±vx ± vy − J_a·prev[pa, k0 + k], k < n, for the samples of one word
    (signs: its bits 2k, 2k + 1)."""
    z = cur[i, k0:]  # (no bounds or wraparound checks in the loop: it vectorises)
    za = prev[pa, k0:]
    for k in range(n):
        tx = -vx if (w >> np.uint64(2 * k)) & np.uint64(1) else vx
        ty = -vy if (w >> np.uint64(2 * k + 1)) & np.uint64(1) else vy
        z[k] += tx + ty - Ja * za[k]


@numba.njit(cache=True, error_model="numpy")
def _own_samples(cur, i, k0, n, w, ux, uy, den):
    """z_k = (z_k ± ux ± uy) / den for the samples k < n of one word, z = cur[i, k0:]; returns
    Σ_k z_k² (in order)."""
    z = cur[i, k0:k0 + n]
    s = 0.0
    for k in range(n):
        tx = -ux if (w >> np.uint64(2 * k)) & np.uint64(1) else ux
        ty = -uy if (w >> np.uint64(2 * k + 1)) & np.uint64(1) else uy
        z[k] = (z[k] + tx + ty) / den
    for k in range(z.size):
        s += z[k] * z[k]
    return s


@numba.njit(cache=True, error_model="numpy")
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
    width = 1
    for L in range(n_layers):
        width = max(width, starts[L + 1] - starts[L])
    n_chunks = (K + 31) // 32
    prev = np.zeros((width, K))
    cur = np.zeros((width, K))
    w_prev = np.zeros((width, n_chunks), dtype=np.uint64)  # the draws' words of the previous wavefront
    w_cur = np.zeros((width, n_chunks), dtype=np.uint64)
    # one wavefront's coefficients, gathered first (the pixels lie on different image rows: a
    # tight loop of independent loads overlaps their cache misses), then used contiguously
    n_in = np.zeros(width, dtype=np.int64)
    e_pos = np.zeros((width, 4), dtype=np.int64)
    e_c = np.zeros((width, 4, 3))  # per incoming edge: ½ (A_a^T Δxy) x, y and J_a
    b_c = np.zeros((width, 3))  # Σ ½ (A_b^T Δxy) x, y and Σ J_b
    s_out = np.zeros(width)
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
                Ja, Jb, dx, dy = _edge_jac(geo, va, ua, vb, ub)
                den += Jb
                ux += 0.5 * (A[vb, ub, 0, 0] * dx + A[vb, ub, 1, 0] * dy)
                uy += 0.5 * (A[vb, ub, 0, 1] * dx + A[vb, ub, 1, 1] * dy)
                e_c[i, m, 0] = 0.5 * (A[va, ua, 0, 0] * dx + A[va, ua, 1, 0] * dy)
                e_c[i, m, 1] = 0.5 * (A[va, ua, 0, 1] * dx + A[va, ua, 1, 1] * dy)
                e_c[i, m, 2] = Ja
                e_pos[i, m] = pos[va, ua]
                m += 1
            n_in[i] = m
            b_c[i, 0] = ux
            b_c[i, 1] = uy
            b_c[i, 2] = den
        for i in range(nL):  # all K samples of each pixel
            kb = order[s0 + i]
            for c in range(n_chunks):
                w_cur[i, c] = _draw_word(key, kb, c, n_chunks)
            z = cur[i]
            for k in range(K):
                z[k] = 0.0
            for j in range(n_in[i]):
                vx = e_c[i, j, 0]
                vy = e_c[i, j, 1]
                Ja = e_c[i, j, 2]
                pa = e_pos[i, j]
                for c in range(n_chunks):
                    _edge_samples(cur, i, prev, pa, 32 * c, min(32, K - 32 * c), w_prev[pa, c], vx, vy, Ja)
            den = b_c[i, 2]
            if den == 0.0:
                ok = False
                for k in range(K):
                    z[k] = 0.0
                s_out[i] = 0.0
                continue
            ux = b_c[i, 0]
            uy = b_c[i, 1]
            s = 0.0
            for c in range(n_chunks):  # Σ_k δz_k² per 32 samples, in order (as the sample-chunked loop)
                s += _own_samples(cur, i, 32 * c, min(32, K - 32 * c), w_cur[i, c], ux, uy, den)
            s_out[i] = s
        for i in range(nL):  # scatter
            kb = order[s0 + i]
            vb = kb // W
            acc[vb, kb - vb * W] += s_out[i]
        prev, cur = cur, prev
        w_prev, w_cur = w_cur, w_prev
    return ok
