"""The stepwise σ kernel (all K samples per wavefront, issue 25) against the sample-by-sample
linearised recursion: each sample's slopes drawn by ``_sample_dg`` and integrated by
``_stepwise_linear``, Σ_k δz_k² summed in numpy."""

import numpy as np
import pytest

from pmdsim.evaluation import uncertainty as U
from pmdsim.evaluation.uncertainty_stepwise import stepwise_sampled


def _problem(seed=4, H=23, W=31):
    """A mask with holes (so that wavefronts bend and pixels have one to three upstream
    neighbours), a smooth random geometry and random A = J·diag(σ)."""
    rng = np.random.default_rng(seed)
    S = np.ones((H, W), bool)
    S[5:9, 8:20] = False
    S[14:20, 4:7] = False
    S[12, 15:29] = False
    S[rng.random((H, W)) < 0.04] = False
    sv, su = 11, 10
    S[sv, su] = True
    v, u = np.mgrid[0:H, 0:W].astype(float)
    geo = np.stack([u * 0.5, v * 0.5, 0.01 * np.sin(u / 5), 0.02 * np.cos(v / 7),
                    0.003 * rng.normal(size=(H, W)), 0.003 * rng.normal(size=(H, W)),
                    0.05 * rng.normal(size=(H, W)), 0.05 * rng.normal(size=(H, W))], axis=-1)
    A = np.where(S[..., None, None], 1e-4 * rng.normal(size=(H, W, 2, 2)), 0.0)
    layer = np.empty((H, W), np.int64)
    order = np.empty(H * W, np.int64)
    n = U._bfs(S, sv, su, layer, order)
    lo = layer.reshape(-1)[order[:n]]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(lo)) + 1, [n]]).astype(np.int64)
    pos = np.zeros((H, W), np.int64)
    pos.reshape(-1)[order[:n]] = np.arange(n) - starts[lo]
    return S, np.ascontiguousarray(geo), layer, order, n, starts, pos, np.ascontiguousarray(A)


def _reference(S, geo, layer, order, n, A, seed, K):
    acc = np.zeros(S.shape)
    dg = np.empty(S.shape + (2,))
    dz = np.empty(S.shape)
    for k in range(K):
        U._sample_dg(A, S, seed, k, (K + 31) // 32, dg)
        assert U._stepwise_linear(geo, layer, order, n, dg, dz)
        acc += np.nan_to_num(dz) ** 2
    return acc


@pytest.mark.parametrize("K", [5, 40, 64])
def test_equals_the_sample_by_sample_recursion(K):
    S, geo, layer, order, n, starts, pos, A = _problem()
    reached = layer >= 0
    P = np.pad(layer, 1, constant_values=-9)
    up = sum((P[1 + dv:P.shape[0] - 1 + dv, 1 + du:P.shape[1] - 1 + du] == layer - 1)
             for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)))
    assert up[reached & (layer > 0)].max() >= 3  # bent wavefronts: several upstream neighbours
    seed = 987654321
    acc = np.zeros(S.shape)
    assert stepwise_sampled(geo, layer, order, starts, pos, A, seed, K, acc)
    ref = _reference(S, geo, layer, order, n, A, seed, K)
    assert np.all(acc[~reached] == 0.0)
    assert np.count_nonzero(acc[reached] == 0.0) == 1  # the seed
    np.testing.assert_allclose(acc, ref, rtol=1e-12, atol=0.0)
    again = np.zeros(S.shape)
    stepwise_sampled(geo, layer, order, starts, pos, A, seed, K, again)
    np.testing.assert_array_equal(acc, again)


def test_vanishing_coefficient_is_reported():
    S, geo, layer, order, n, starts, pos, A = _problem()
    geo[..., 2] = 1.0
    geo[..., 3:8] = 0.0
    vb, ub = divmod(int(order[starts[3] + 1]), S.shape[1])
    geo[vb, ub, 6] = 1.0  # J_b = 1 − G_x·1 = 0 on every edge into this pixel
    assert not stepwise_sampled(geo, layer, order, starts, pos, A, 1, 8, np.zeros(S.shape))
