"""Σ_k of bilinearly interpolated squares through per-cell Gram matrices (issue 22 "Speed").

The calibration part of a σ (:mod:`pmdsim.evaluation.uncertainty_stereo_calibration`) has K
changes (one per principal axis) on a subgrid and needs Σ_k (bilinear interpolation of change
k at pixel p)² at every pixel. With the cell's 4 node weights w (4,) and the nodes' changes
q_k (4,), that is Σ_k (wᵀ q_k)² = wᵀ G w with G = Σ_k q_k q_kᵀ, the cell's 4 × 4 Gram matrix:
10 numbers per cell and field, formed once per cell, instead of K × 4 products per pixel.
Cells where a node is NaN for some axis take the per-axis path of
:func:`~pmdsim.evaluation.uncertainty_calibration._accumulate` (weights renormalised over the
finite nodes). Equal to it up to rounding.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .uncertainty_calibration import _accumulate, _fill

__all__ = ["interpolated_squares", "interpolated_std_maps"]


@numba.njit(cache=True, parallel=True)
def _cell_grams(stack):
    """Per cell (i, j) of stack (K, h, w, c): the Gram matrix of its nodes (i, j), (i, j1),
    (i1, j), (i1, j1) over the axes, upper triangle row-major → (hc, wc, c, 10), and whether
    any node is NaN for some axis → (hc, wc) bool."""
    K, h, w, c = stack.shape
    hc = max(h - 1, 1)
    wc = max(w - 1, 1)
    G = np.zeros((hc, wc, c, 10))
    bad = np.zeros((hc, wc), dtype=np.bool_)
    for i in numba.prange(0, hc):
        i1 = min(i + 1, h - 1)
        for j in range(wc):
            j1 = min(j + 1, w - 1)
            for k in range(K):
                for m in range(c):
                    q0 = stack[k, i, j, m]
                    q1 = stack[k, i, j1, m]
                    q2 = stack[k, i1, j, m]
                    q3 = stack[k, i1, j1, m]
                    if np.isnan(q0) or np.isnan(q1) or np.isnan(q2) or np.isnan(q3):
                        bad[i, j] = True
                    g = G[i, j, m]
                    g[0] += q0 * q0
                    g[1] += q0 * q1
                    g[2] += q0 * q2
                    g[3] += q0 * q3
                    g[4] += q1 * q1
                    g[5] += q1 * q2
                    g[6] += q1 * q3
                    g[7] += q2 * q2
                    g[8] += q2 * q3
                    g[9] += q3 * q3
    return G, bad


@numba.njit(cache=True)
def _cell(p, o, s, n):
    """The cell (first node index) of pixel ``p`` along an axis of ``n`` subgrid nodes starting at
    pixel ``o`` with stride ``s``, clamped to the outer cells, and p's fraction in it (< 0 or > 1
    beyond the outer nodes: linear extrapolation; 0 for a single node)."""
    f = (p - o) / s
    i = min(max(int(math.floor(f)), 0), max(n - 2, 0))
    return i, (f - i if n > 1 else 0.0)


@numba.njit(cache=True, inline="always")
def _quadratic(g, ay, ax):
    """wᵀ G w for the cell's Gram matrix g (10,) (upper triangle, row-major) and the bilinear
    weights of the fractions (ay, ax); at least 0 (a sum of squares: rounding may not make it
    negative)."""
    w0 = (1 - ay) * (1 - ax)
    w1 = (1 - ay) * ax
    w2 = ay * (1 - ax)
    w3 = ay * ax
    q = (w0 * (w0 * g[0] + 2.0 * (w1 * g[1] + w2 * g[2] + w3 * g[3]))
         + w1 * (w1 * g[4] + 2.0 * (w2 * g[5] + w3 * g[6]))
         + w2 * (w2 * g[7] + 2.0 * w3 * g[8]) + w3 * w3 * g[9])
    return max(q, 0.0)


@numba.njit(cache=True, parallel=True)
def _gram_squares(G, bad, ov, ou, s, h, w, H, W):
    """wᵀ G w at every pixel (H, W, c) of the cells' Gram matrices G (hc, wc, c, 10); pixels of
    ``bad`` cells are left NaN (the caller fills them)."""
    c = G.shape[2]
    out = np.empty((H, W, c))
    for v in numba.prange(0, H):
        i0, ay = _cell(v, ov, s, h)
        for u in range(W):
            j0, ax = _cell(u, ou, s, w)
            if bad[i0, j0]:
                for m in range(c):
                    out[v, u, m] = np.nan
                continue
            for m in range(c):
                out[v, u, m] = _quadratic(G[i0, j0, m], ay, ax)
    return out


@numba.njit(cache=True, parallel=True)
def _gram_std_maps(G, bad, ov, ou, s, h, w, S, h_um, g_urad):
    """The σ maps of a (height mm, slope x, slope y) field (c = 3) from the cells' Gram matrices:
    h_um (H, W) = sqrt(wᵀ G₀ w)·1e3 and g_urad (H, W, 2) = sqrt(wᵀ G₁,₂ w)·1e6 on S, NaN off S
    and at the pixels of ``bad`` cells (the caller fills those) — the values
    ``np.sqrt(_gram_squares(…)[..., 0]) * 1e3`` etc. give, without the (H, W, 3) variances."""
    H, W = S.shape
    for v in numba.prange(0, H):
        i0, ay = _cell(v, ov, s, h)
        for u in range(W):
            j0, ax = _cell(u, ou, s, w)
            if not S[v, u] or bad[i0, j0]:
                h_um[v, u] = np.nan
                g_urad[v, u, 0] = np.nan
                g_urad[v, u, 1] = np.nan
                continue
            h_um[v, u] = np.sqrt(_quadratic(G[i0, j0, 0], ay, ax)) * 1e3
            g_urad[v, u, 0] = np.sqrt(_quadratic(G[i0, j0, 1], ay, ax)) * 1e6
            g_urad[v, u, 1] = np.sqrt(_quadratic(G[i0, j0, 2], ay, ax)) * 1e6


def _filled_grams(changes):
    filled = np.stack([_fill(np.ascontiguousarray(c), 4) for c in changes])
    G, bad = _cell_grams(filled)
    return filled, G, bad


def _per_axis_box(filled, miss, ov, ou, s):
    """The per-axis path (:func:`~pmdsim.evaluation.uncertainty_calibration._accumulate`) over the
    bounding box of the pixels ``miss`` (H, W): (box slices, variances (h_box, w_box, c))."""
    rows, cols = np.flatnonzero(miss.any(axis=1)), np.flatnonzero(miss.any(axis=0))
    v0, v1, u0, u1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    return (slice(v0, v1), slice(u0, u1)), _accumulate(filled, ov - v0, ou - u0, s, v1 - v0, u1 - u0)


def interpolated_squares(changes: np.ndarray, ov: int, ou: int, s: int, H: int, W: int) -> np.ndarray:
    """Σ_k (changes[k] interpolated bilinearly to every pixel)², the variance (H, W, c).

    Parameters
    ----------
    changes : ndarray (K, h, w, c)
        The K axes' changes on the subgrid; node (i, j) is pixel (ov + s·i, ou + s·j). NaN nodes
        are first filled from their finite neighbours (4 passes), as
        :func:`~pmdsim.evaluation.uncertainty_calibration._interpolated_squares` does.
    ov, ou, s : int
        The subgrid's first row and column and its stride (s ≥ 2; s = 1 needs no interpolation).
    H, W : int
        The image's shape.

    Returns
    -------
    ndarray (H, W, c)
        As :func:`~pmdsim.evaluation.uncertainty_calibration._interpolated_squares` up to rounding.
    """
    filled, G, bad = _filled_grams(changes)
    out = _gram_squares(G, bad, ov, ou, s, filled.shape[1], filled.shape[2], H, W)
    miss = np.isnan(out[..., 0])
    if miss.any():  # pixels of cells with a NaN node: the per-axis path over their bounding box
        box, var = _per_axis_box(filled, miss, ov, ou, s)
        out[box][miss[box]] = var[miss[box]]
    return out


def interpolated_std_maps(changes: np.ndarray, ov: int, ou: int, s: int, S) -> tuple[np.ndarray, np.ndarray]:
    """The standard uncertainties of a (height mm, slope x, slope y) field from its axes' changes:
    sqrt of :func:`interpolated_squares` (heights in µm, slopes in µrad), NaN off S, without the
    (H, W, 3) variances (bit for bit ``np.sqrt(var[..., 0]) * 1e3``, ``np.sqrt(var[..., 1:]) *
    1e6`` of them).

    Parameters
    ----------
    changes : ndarray (K, h, w, 3)
        As :func:`interpolated_squares`, c = 3.
    ov, ou, s
        As :func:`interpolated_squares`.
    S : ndarray of bool (H, W)
        The reconstructed pixels.

    Returns
    -------
    (ndarray (H, W), ndarray (H, W, 2))
        σ of the heights, µm, and of the slopes, µrad.
    """
    S = np.ascontiguousarray(S, dtype=np.bool_)
    filled, G, bad = _filled_grams(changes)
    H, W = S.shape
    h_um, g_urad = np.empty((H, W)), np.empty((H, W, 2))
    _gram_std_maps(G, bad, ov, ou, s, filled.shape[1], filled.shape[2], S, h_um, g_urad)
    miss = S & np.isnan(h_um)
    if miss.any():  # as interpolated_squares: the per-axis path over their bounding box
        box, var = _per_axis_box(filled, miss, ov, ou, s)
        m = miss[box]
        h_um[box][m] = np.sqrt(var[m][:, 0]) * 1e3
        g_urad[box][m] = np.sqrt(var[m][:, 1:]) * 1e6
    return h_um, g_urad
