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
seed's outwards (the seed's row, the rows below it, then the rows above it), each row from the
seed's column outwards (the pixel in the seed's column, the pixels right of it left to right,
then the pixels left of it right to left): it reads the inputs row by row (contiguous, where
the wavefront pass reads each pixel of a diagonal on another image row) and keeps the samples δz
of two rows. Each pixel's values are computed by the same functions in the same order as in the
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
from .uncertainty_stepwise import _add_edge, _draw_word, _pixel_samples, _seed_key

__all__ = ["rows_kernel", "l1_layered"]


@numba.njit(cache=True, inline="always", error_model="numpy")
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


@numba.njit(cache=True)
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


@numba.njit(cache=True, inline="always")
def _row_of(r, sv, H):
    """The r-th row visited: the seed's row, the rows below it, then the rows above it."""
    return sv + r if r < H - sv else sv - (r - (H - sv) + 1)


@numba.njit(cache=True, error_model="numpy")
def rows_kernel(o, d, q, z, S, sv, su, p, T, sig, seed, K, acc, gstd):
    """The heights' σ sqrt(Σ_k δz_k² / K) into ``acc`` (H, W) (NaN off S) and the slopes' σ into
    ``gstd`` (H, W, 2) (left as they are off S) in row order (module docstring); the arguments
    as ``uncertainty_stepwise_fused._fused_kernel``'s. Returns −1 (nothing written) if S is not
    :func:`l1_layered` from the seed, else 0, or 1 if a pixel's geometry is not finite, 2 if a
    pixel's coefficient Σ J_b vanishes."""
    H, W = S.shape
    if not l1_layered(S, sv, su):
        return -1
    n_chunks = (K + 31) // 32
    per_pixel = 0 if T.shape[0] == 1 else 1
    # Two rows of each per-pixel buffer: row v in slots (v % 2)·W + u, the previous row in the others.
    Z = np.empty((2 * W, K))
    WD = np.empty((2 * W, n_chunks), dtype=np.uint64)
    G = np.empty((2 * W, 8))
    AA = np.empty((2 * W, 2, 2))
    Z_s = np.empty((W, K))  # the seed's row, kept for the rows above it
    WD_s = np.empty((W, n_chunks), dtype=np.uint64)
    G_s = np.empty((W, 8))
    AA_s = np.empty((W, 2, 2))
    e_c = np.empty((1, 4, 3))
    e_pos = np.empty((1, 4), dtype=np.int64)
    key = _seed_key(seed)
    status = 0
    s0 = (sv % 2) * W
    for r in range(H):
        v = _row_of(r, sv, H)
        if r == H - sv:  # the first row above the seed's: its previous row is the seed's
            Z[s0:s0 + W] = Z_s
            WD[s0:s0 + W] = WD_s
            G[s0:s0 + W] = G_s
            AA[s0:s0 + W] = AA_s
        cs = (v % 2) * W
        ps = W - cs
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
        if r == 0:
            Z_s[:] = Z[s0:s0 + W]
            WD_s[:] = WD[s0:s0 + W]
            G_s[:] = G[s0:s0 + W]
            AA_s[:] = AA[s0:s0 + W]
    return status
