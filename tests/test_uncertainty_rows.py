"""The stepwise σ in image-row order (``uncertainty_stepwise_rows``, issue 25) on masks whose
wavefronts are the seed's L1 diamonds: equal bit for bit to the wavefront pass
(``uncertainty_stepwise_fused._fused_kernel``), to 1e-12 relative to the sample-by-sample
linearised recursion (``_sample_dg`` + ``_stepwise_linear``, Σ_k δz_k² in numpy in sample
order), the slopes' σ to ``_jacobian_scaled``; a mask with a hole is left to the wavefront pass."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from test_stepwise_wavefront import _scene

from pmdsim.evaluation import uncertainty as U
from pmdsim.evaluation.stepwise import reconstruct_stepwise
from pmdsim.evaluation.uncertainty_stepwise_fused import _fused_kernel, stepwise_noise_sigma
from pmdsim.evaluation.uncertainty_stepwise_rows import l1_layered, rows_kernel
from pmdsim.geometry.kernel_args import readonly


def _bfs_is_l1(S, seed):
    """Every pixel of S reached by a breadth-first search from ``seed`` within S, at its L1
    distance (Python, independent of the kernels)."""
    H, W = S.shape
    dist = np.full((H, W), -1)
    dist[seed] = 0
    todo = deque([seed])
    while todo:
        v, u = todo.popleft()
        for a, b in ((v - 1, u), (v + 1, u), (v, u - 1), (v, u + 1)):
            if 0 <= a < H and 0 <= b < W and S[a, b] and dist[a, b] < 0:
                dist[a, b] = dist[v, u] + 1
                todo.append((a, b))
    v, u = np.mgrid[0:H, 0:W]
    return bool(np.all(dist[S] == (np.abs(v - seed[0]) + np.abs(u - seed[1]))[S]))


def _case(seed, hole=False, per_pixel_tangents=False):
    """A reconstruction over a frame with bites out of its edges and corners (no hole: the
    wavefronts are L1 diamonds), or with a hole beside the seed."""
    o, d, q, _, _ = _scene(H=19, W=24)
    d = d.copy()
    d[..., 2] = -np.abs(d[..., 2])  # no failing steps: the mask is the valid one
    valid = np.ones((19, 24), bool)
    valid[:3, 19:] = False
    valid[16:, :2] = False
    valid[18, 9:14] = False
    valid[7:10, 0] = False
    if hole:
        valid[seed[0] - 3:seed[0] - 1, seed[1] - 1:seed[1] + 2] = False
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.25)
    assert np.array_equal(rec.reconstructed, valid)
    rng = np.random.default_rng(11)
    std = rng.uniform(1e-3, 5e-3, size=valid.shape + (2,))
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    dq = R[:, :2] + 0.01 * rng.normal(size=valid.shape + (3, 2)) if per_pixel_tangents else np.ascontiguousarray(R[:, :2])
    return o, d, q, rec, dq, std


def _kernel_args(o, d, q, rec, dq, std, K, seed):
    S = rec.reconstructed
    acc = np.zeros(S.shape)
    gstd = np.full(S.shape + (2,), np.nan)
    T = U._tangent_array(dq)
    sv, su = (int(x) for x in rec.seed_pixel)
    return (np.asarray(o, float), d, q, rec.height_mm, S, sv, su, rec.p_sample_mm, T, readonly(std), seed, K,
            acc, gstd)


@pytest.mark.parametrize("seed_pixel, K, per_pixel", [((9, 11), 64, False), ((9, 11), 5, True), ((0, 5), 40, False),
                                                      ((17, 23), 64, True), ((3, 22), 33, False)])
def test_row_order_equals_the_wavefront_pass_and_the_sample_by_sample_recursion(seed_pixel, K, per_pixel):
    o, d, q, rec, dq, std = _case(seed_pixel, per_pixel_tangents=per_pixel)
    S = rec.reconstructed
    assert _bfs_is_l1(S, seed_pixel) and l1_layered(S, *seed_pixel)
    rows = _kernel_args(o, d, q, rec, dq, std, K, 777)
    waves = _kernel_args(o, d, q, rec, dq, std, K, 777)
    assert rows_kernel(*rows) == 0
    assert _fused_kernel(*waves) == 0
    h, g = rows[-2], rows[-1]
    assert np.array_equal(h, waves[-2], equal_nan=True) and np.array_equal(np.signbit(h), np.signbit(waves[-2]))
    assert np.array_equal(g, waves[-1], equal_nan=True)
    h2, g2, status = stepwise_noise_sigma(o, d, q, rec, dq, std, K, 777)  # (which takes the row order)
    assert status == 0 and np.array_equal(h2, h, equal_nan=True) and np.array_equal(g2, g, equal_nan=True)
    A, g_ref = U._jacobian_scaled(o, rec.p_sample_mm, q, dq, S, std)
    assert np.array_equal(g, g_ref, equal_nan=True)
    lin = U._LinearisedIntegration(o, d, q, rec)
    acc = np.zeros(S.shape)
    dg = np.empty(S.shape + (2,))
    dz = np.empty(S.shape)
    A[~S] = 0.0
    for k in range(K):  # one δg map per sample; Σ_k δz_k² in sample order
        U._sample_dg(A, S, 777, k, (K + 31) // 32, dg)
        assert U._stepwise_linear(lin.geo, lin.layer, lin.order, lin.n, dg, dz)
        acc += np.nan_to_num(dz) ** 2
    assert np.isnan(h[~S]).all() and h[seed_pixel] == 0.0 and (h[S] > 0).sum() == S.sum() - 1
    np.testing.assert_allclose(h[S], np.sqrt(acc[S] / K), rtol=1e-12, atol=0.0)


def test_a_hole_that_bends_the_wavefronts_is_left_to_the_wavefront_pass():
    o, d, q, rec, dq, std = _case((9, 11), hole=True)
    assert not _bfs_is_l1(rec.reconstructed, (9, 11)) and not l1_layered(rec.reconstructed, 9, 11)
    args = _kernel_args(o, d, q, rec, dq, std, 8, 5)
    assert rows_kernel(*args) == -1
    assert np.all(args[-2] == 0.0) and np.isnan(args[-1]).all()  # nothing written
    waves = _kernel_args(o, d, q, rec, dq, std, 8, 5)
    assert _fused_kernel(*waves) == 0
    h, g, status = stepwise_noise_sigma(o, d, q, rec, dq, std, 8, 5)
    assert status == 0 and np.array_equal(h, waves[-2], equal_nan=True) and np.array_equal(g, waves[-1], equal_nan=True)


def test_a_geometry_that_is_not_finite_is_reported_in_row_order():
    o, d, q, rec, dq, std = _case((9, 11))
    q = q.copy()
    q[14, 5] = rec.p_sample_mm[14, 5]  # the screen point on the surface point: b̂ = 0/0
    with np.errstate(all="ignore"):
        assert rows_kernel(*_kernel_args(o, d, q, rec, dq, std, 8, 1)) == 1
