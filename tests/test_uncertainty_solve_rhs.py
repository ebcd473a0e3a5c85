"""The least-squares σ's right-hand sides built in one parallel pass
(``uncertainty_solve._sampled_rhs``) against a numpy reference: −Jᵀ δr of the trapezoidal
equations, every edge's J_a, J_b, Δx, Δy from the geometry map by the formulas of
``least_squares._edge`` written out in numpy, the slope perturbations drawn by
``uncertainty._sample_dg`` (a separate kernel), the terms subtracted per pixel in the same
order (edge up, left, right, down), so that the sums are equal bit for bit. The kernel reads
the edges' coefficients in single precision (``uncertainty_solve._edge_coefficients``, checked
here against the numpy formulas rounded to float32); the reference uses the same rounded values."""

from __future__ import annotations

import numpy as np
import pytest


def _edges_numpy(ga, gb):
    """J_a, J_b, Δx, Δy of the edges a → b from stacked geometry rows ga, gb (..., 8)."""
    Gx = 0.5 * (ga[..., 2] + gb[..., 2])
    Gy = 0.5 * (ga[..., 3] + gb[..., 3])
    dx = gb[..., 0] - ga[..., 0]
    dy = gb[..., 1] - ga[..., 1]
    Ja = -1.0 + (Gx * ga[..., 6] + Gy * ga[..., 7]) - 0.5 * (ga[..., 4] * dx + ga[..., 5] * dy)
    Jb = 1.0 - (Gx * gb[..., 6] + Gy * gb[..., 7]) - 0.5 * (gb[..., 4] * dx + gb[..., 5] * dy)
    return Ja, Jb, dx, dy


def _single(*a):
    """The values rounded to single precision (as float64)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return tuple(np.asarray(x, dtype=np.float32).astype(np.float64) for x in a)


def _rhs_numpy(S, seed_pixel, geo, dg):
    """The padded right-hand side −Jᵀ δr, δr_e = −½(δg_a + δg_b)·Δxy_e (edges with a
    non-finite J or δr left out; the seed pixel is not an unknown), with each edge's J_a, J_b,
    Δx, Δy rounded to single precision (where J is finite in double)."""
    H, W = S.shape
    terms = {}
    for name, sa, sb in (("h", np.s_[:, :-1], np.s_[:, 1:]), ("v", np.s_[:-1, :], np.s_[1:, :])):
        Ja, Jb, dx, dy = _edges_numpy(geo[sa], geo[sb])
        fin = np.isfinite(Ja) & np.isfinite(Jb)
        Ja, Jb, dx, dy = _single(Ja, Jb, dx, dy)
        with np.errstate(invalid="ignore", over="ignore"):
            dr = -0.5 * ((dg[sa][..., 0] + dg[sb][..., 0]) * dx + (dg[sa][..., 1] + dg[sb][..., 1]) * dy)
            ok = S[sa] & S[sb] & fin & np.isfinite(dr)
            terms[name] = (np.where(ok, Ja * dr, 0.0), np.where(ok, Jb * dr, 0.0))
    r = np.zeros((H, W))
    r[1:, :] -= terms["v"][1]   # the edge up (this pixel its b)
    r[:, 1:] -= terms["h"][1]   # the edge left
    r[:, :-1] -= terms["h"][0]  # the edge right (this pixel its a)
    r[:-1, :] -= terms["v"][0]  # the edge down
    r[~S] = 0.0
    if seed_pixel[0] >= 0:
        r[seed_pixel] = 0.0
    out = np.zeros((H + 2, W + 2))
    out[1:-1, 1:-1] = r
    return out


@pytest.mark.parametrize("case", range(4))
def test_sampled_rhs_equals_the_numpy_reference(case):
    from pmdsim.evaluation import uncertainty as U
    from pmdsim.evaluation.uncertainty_solve import _edge_coefficients, _ls_rhs_edges, _sampled_rhs

    rng = np.random.default_rng(40 + case)
    H, W = [(17, 23), (1, 9), (31, 5), (12, 12)][case]
    S = rng.random((H, W)) > (0.0 if case == 0 else 0.25)
    geo = rng.normal(size=(H, W, 8)) * 0.1
    if case == 3:  # a non-finite edge Jacobian: its edges are left out
        geo[4, 5, 2] = np.inf
    A = np.where(S[..., None, None], rng.normal(size=(H, W, 2, 2)), 0.0)
    seed_pixel = (-1, -1) if case == 1 else (int(rng.integers(0, H)), int(rng.integers(0, W)))
    K, seed = 7, 1234 + case
    n_chunks = 1
    dg = np.empty((H, W, 2))
    ref = np.empty((K, H + 2, W + 2))
    for k in range(K):
        U._sample_dg(A, S, seed, k, n_chunks, dg)
        ref[k] = _rhs_numpy(S, seed_pixel, geo, dg)
    assert np.abs(ref).max() > 0
    edges = np.full((H, 8, W), -7.0, dtype=np.float32)
    _edge_coefficients(geo, S, edges)
    for e, sa, sb in ((0, np.s_[:, :-1], np.s_[:, 1:]), (1, np.s_[:-1, :], np.s_[1:, :])):  # against numpy
        Ja, Jb, dx, dy = _edges_numpy(geo[sa], geo[sb])
        used = S[sa] & S[sb] & np.isfinite(Ja) & np.isfinite(Jb)
        got = edges.transpose(0, 2, 1)[sa][..., 4 * e:4 * e + 4]
        assert np.array_equal(np.isnan(got[..., 0]), ~used)
        for i, x in enumerate((Ja, Jb, dx, dy)):
            assert np.array_equal(got[..., i][used], np.float32(x[used]))
    assert np.isnan(edges[:, 0, W - 1]).all() and np.isnan(edges[H - 1, 4, :]).all()  # no edge off the grid
    rhs = np.empty((H + 2, W + 2))
    U._sample_dg(A, S, seed, 0, n_chunks, dg)
    _ls_rhs_edges(S, seed_pixel[0], seed_pixel[1], edges, dg, rhs)
    np.testing.assert_array_equal(rhs, ref[0])  # the one-sample form (``_LinearisedIntegration.apply``)
    for n, n_blocks in ((2, 3), (1, 1), (3, 8)):  # batches of n, the rows in n_blocks blocks
        B = np.full((n, H + 2, W + 2), np.nan)
        for k0 in range(0, K - n + 1, n):
            _sampled_rhs(A, S, seed, k0, n_chunks, seed_pixel[0], seed_pixel[1], edges, B, n_blocks)
            np.testing.assert_array_equal(B, ref[k0:k0 + n])
