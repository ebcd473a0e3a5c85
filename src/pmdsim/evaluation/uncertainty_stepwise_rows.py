"""The stepwise σ pass in image-row order where the wavefronts are the seed's diamonds (issue 25).

The sampled recursion of :mod:`pmdsim.evaluation.uncertainty_stepwise` gives each pixel δz_b
from the δz of its upstream neighbours (its 4-neighbours in the previous wavefront), so any
order that visits every pixel after its upstream neighbours gives the same values. Where every
pixel of S except the seed (sv, su) has a 4-neighbour in S one step closer to the seed in the
L1 (city-block) distance |v − sv| + |u − su| — a mask without holes that block a straight
path — each pixel's wavefront is its L1 distance (induction on the distance: such a neighbour
is reached one wavefront earlier, and no path is shorter than the L1 distance) and its upstream
neighbours are its 4-neighbours in S at L1 distance one less: the row towards the seed and the
pixel beside it towards the seed column. Then :func:`rows_kernel` visits the rows from the
seed's outwards (the seed's row, then the rows below it and the rows above it: two independent
halves, in parallel), each row from the seed's column outwards (the pixel in the seed's column,
the pixels right of it left to right, then the pixels left of it right to left): it reads the
inputs row by row (contiguous, where the wavefront pass reads each pixel of a diagonal on
another image row) and keeps the samples δz of two rows per half. Each pixel's values are computed by the same functions in the same order as in the
wavefront pass (the geometry and A by :func:`_pixel_inputs`, the edge coefficients by
``_add_edge`` in the neighbour order (−1, 0), (1, 0), (0, −1), (0, 1), the samples by
``_pixel_samples``), so σ is bit-identical to it (tests/test_uncertainty_rows.py). Other masks
are left to the wavefront pass (:func:`rows_kernel` returns −1 before writing anything).
"""

from __future__ import annotations

import numba
import numpy as np

from .least_squares import _point_geometry
from .uncertainty import _pixel_jacobian
from .stepwise_rows import l1_layered
from .uncertainty_stepwise import _add_edge, _draw_word, _pixel_samples, _seed_key

__all__ = ["rows_kernel", "l1_layered"]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _pixel_inputs(o, d, q, z, p, T, per_pixel, sig, v, u, geo, A, gstd):
    """Pixel (v, u): its geometry row geo (8,) (as ``least_squares._row_geometry``), A (2, 2) and
    the slopes' σ gstd[v, u] (``uncertainty._pixel_jacobian``). Returns False if the geometry is
    not finite."""
    idz = 1.0 / d[v, u, 2]
    ex = d[v, u, 0] * idz  # dp/dz = (ex, ey, 1)
    ey = d[v, u, 1] * idz
    geo[0], geo[1], geo[2], geo[3], geo[4], geo[5] = _point_geometry(
        o[0], o[1], o[2], ex, ey, z[v, u], q[v, u, 0], q[v, u, 1], q[v, u, 2])
    geo[6] = ex
    geo[7] = ey
    _pixel_jacobian(o, p, q, T, v, u, v * per_pixel, u * per_pixel, sig, A, gstd[v, u])
    ok = True
    for c in range(8):
        ok = ok and np.isfinite(geo[c])
    return ok


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row(o, d, q, z, S, sv, su, p, T, per_pixel, sig, key, K, acc, gstd, v, Z, WD, G, AA, e_c, e_pos):
    """Row v of :func:`rows_kernel`: its pixels of S from the seed's column outwards (the seed's
    column, the pixels right of it left to right, then those left of it right to left), their
    geometry, A and samples in the slots (v % 2)·W + u of the two-row buffers Z (2W, K) (δz), WD
    (2W, ⌈K/32⌉) (draws), G (2W, 8) (geometry) and AA (2W, 2, 2), the previous row (towards the
    seed's) in the other slots; σ into acc[v] (NaN off S), the slopes' σ into gstd[v]. Returns 0,
    1 if a pixel's geometry is not finite (at once), 2 if a pixel's Σ J_b vanishes."""
    H, W = S.shape
    n_chunks = (K + 31) // 32
    cs = (v % 2) * W
    ps = W - cs
    status = 0
    for t in range(W):
        u = su + t if t < W - su else su - (t - (W - su) + 1)
        if not S[v, u]:
            acc[v, u] = np.nan
            continue
        slot = cs + u
        if not _pixel_inputs(o, d, q, z, p, T, per_pixel, sig, v, u, G[slot], AA[slot], gstd):
            return 1
        kb = v * W + u
        if v == sv and u == su:  # the seed: δz = 0, its draws enter its neighbours' equations
            for c in range(n_chunks):
                WD[slot, c] = _draw_word(key, kb, c, n_chunks)
            for k in range(K):
                Z[slot, k] = 0.0
            acc[v, u] = 0.0
            continue
        dist = abs(v - sv) + abs(u - su)
        ux = 0.0
        uy = 0.0
        den = 0.0
        m = 0
        for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            va = v + dv
            ua = u + du
            if not (0 <= va < H and 0 <= ua < W) or not S[va, ua] or abs(va - sv) + abs(ua - su) != dist - 1:
                continue
            pa = (cs if va == v else ps) + ua
            den, ux, uy, m = _add_edge(G[pa], G[slot], AA[pa], AA[slot], e_c, e_pos, 0, m, pa, den, ux, uy)
        s = _pixel_samples(kb, key, K, m, e_pos[0], e_c[0], ux, uy, den, Z, Z, slot, WD, WD)
        if s < 0.0:
            status = 2
            s = 0.0
        acc[v, u] = np.sqrt(s / K)  # (the wavefront pass: 0.0 + s, then sqrt(acc / K): the same)
    return status


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def rows_kernel(o, d, q, z, S, sv, su, p, T, sig, seed, K, acc, gstd):
    """The heights' σ sqrt(Σ_k δz_k² / K) into ``acc`` (H, W) (NaN off S) and the slopes' σ into
    ``gstd`` (H, W, 2) (left as they are off S) in row order (module docstring); the arguments
    as ``uncertainty_stepwise_fused._fused_kernel``'s. The seed's row first, then the rows below
    it and the rows above it in parallel (each half from the seed's row outwards, with its own
    two-row buffers: :func:`_row`). Returns −1 (nothing written) if S is not :func:`l1_layered`
    from the seed, else 0, or 1 if a pixel's geometry is not finite, 2 if a pixel's coefficient
    Σ J_b vanishes."""
    H, W = S.shape
    if not l1_layered(S, sv, su):
        return -1
    n_chunks = (K + 31) // 32
    per_pixel = 0 if T.shape[0] == 1 else 1
    Z = np.empty((2, 2 * W, K))  # per half: two rows of each buffer (:func:`_row`)
    WD = np.empty((2, 2 * W, n_chunks), dtype=np.uint64)
    G = np.empty((2, 2 * W, 8))
    AA = np.empty((2, 2 * W, 2, 2))
    e_c = np.empty((2, 1, 4, 3))
    e_pos = np.empty((2, 1, 4), dtype=np.int64)
    key = _seed_key(seed)
    status = _row(o, d, q, z, S, sv, su, p, T, per_pixel, sig, key, K, acc, gstd, sv, Z[0], WD[0], G[0], AA[0], e_c[0],
                  e_pos[0])
    if status == 1:
        return 1
    s0 = (sv % 2) * W  # the seed's row: the previous row of both halves' first rows
    Z[1, s0:s0 + W] = Z[0, s0:s0 + W]
    WD[1, s0:s0 + W] = WD[0, s0:s0 + W]
    G[1, s0:s0 + W] = G[0, s0:s0 + W]
    AA[1, s0:s0 + W] = AA[0, s0:s0 + W]
    half = np.zeros(2, dtype=np.int64)
    for h in numba.prange(0, 2):  # the rows below the seed's, the rows above it
        n_rows = H - 1 - sv if h == 0 else sv
        for r in range(n_rows):
            v = sv + 1 + r if h == 0 else sv - 1 - r
            st = _row(o, d, q, z, S, sv, su, p, T, per_pixel, sig, key, K, acc, gstd, v, Z[h], WD[h], G[h], AA[h],
                      e_c[h], e_pos[h])
            if st == 1:
                half[h] = 1
                break
            if st == 2:
                half[h] = 2
    if half[0] == 1 or half[1] == 1:
        return 1
    if half[0] == 2 or half[1] == 2:
        return 2
    return status
