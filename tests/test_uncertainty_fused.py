"""The stepwise σ in one pass (``uncertainty_stepwise_fused``, issue 25) against the four
full-size stages it replaces in ``surface_uncertainty`` (the linearisation's geometry and
wavefront maps, A = J·diag(σ), the sampled recursion: bit for bit) and against the
sample-by-sample linearised recursion (``_sample_dg`` + ``_stepwise_linear``, Σ δz² in numpy:
to 1e-12 relative), on a stepwise reconstruction with holes and skipped pixels."""

from __future__ import annotations

import numpy as np
import pytest
from test_stepwise_wavefront import _scene

from pmdsim.evaluation import uncertainty as U
from pmdsim.geometry.kernel_args import readonly
from pmdsim.evaluation.stepwise import reconstruct_stepwise
from pmdsim.evaluation.uncertainty_stepwise_fused import stepwise_noise_sigma


def _case(per_pixel_tangents):
    o, d, q, valid, seed = _scene()
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.25)
    rng = np.random.default_rng(7)
    std = rng.uniform(1e-3, 5e-3, size=valid.shape + (2,))
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    if per_pixel_tangents:
        dq = R[:, :2] + 0.01 * rng.normal(size=valid.shape + (3, 2))
    else:
        dq = np.ascontiguousarray(R[:, :2])
    return o, d, q, rec, dq, std


@pytest.mark.parametrize("per_pixel_tangents", [False, True])
@pytest.mark.parametrize("K", [5, 64])
def test_equals_the_four_stages_and_the_sample_by_sample_recursion(per_pixel_tangents, K):
    o, d, q, rec, dq, std = _case(per_pixel_tangents)
    S = rec.reconstructed
    assert np.count_nonzero(S) < S.size - 80  # holes and skipped pixels
    h, g, status = stepwise_noise_sigma(o, d, q, rec, dq, std, K, 12345)
    assert status == 0
    lin = U._LinearisedIntegration(o, d, q, rec)
    A, g_ref = U._jacobian_scaled(o, rec.p_sample_mm, q, dq, S, std)
    A0 = A.copy()
    h_ref = U._sampled_std(lin, A, K, 12345, overwrite=True)
    assert np.array_equal(h, h_ref, equal_nan=True)
    assert np.array_equal(g, g_ref, equal_nan=True)
    assert np.isnan(h[~S]).all() and np.isfinite(h[S]).all() and (h[S] > 0).sum() == S.sum() - 1
    # the sample-by-sample recursion (one δg map per sample)
    acc = np.zeros(S.shape)
    dg = np.empty(S.shape + (2,))
    dz = np.empty(S.shape)
    A0[~S] = 0.0
    for k in range(K):
        U._sample_dg(A0, S, 12345, k, (K + 31) // 32, dg)
        assert U._stepwise_linear(lin.geo, lin.layer, lin.order, lin.n, dg, dz)
        acc += np.nan_to_num(dz) ** 2
    np.testing.assert_allclose(h[S], np.sqrt(acc[S] / K), rtol=1e-12, atol=0.0)


def test_a_geometry_that_is_not_finite_is_reported():
    o, d, q, rec, dq, std = _case(False)
    q = q.copy()
    v, u = np.argwhere(rec.reconstructed)[40]
    q[v, u] = rec.p_sample_mm[v, u]  # the screen point on the surface point: b̂ = 0/0
    with np.errstate(all="ignore"):
        _, _, status = stepwise_noise_sigma(o, d, q, rec, dq, std, 8, 1)
    assert status == 1


def test_combined_noise_part_is_returned_exactly_when_the_root_sum_square_equals_it():
    """``_combined`` (the check without the array of sums) against numpy's root-sum-square and
    ``np.array_equal``: a zero calibration part (noise returned, the same object), a non-zero one
    and a noise σ whose square underflows (the sums returned, equal to numpy's bit for bit)."""
    rng = np.random.default_rng(3)
    S = rng.random((64, 80)) < 0.9
    noise = np.where(S, rng.uniform(0.1, 5.0, size=S.shape), np.nan)
    zero_cal = np.where(S, 0.0, np.nan)
    assert U._combined(noise, zero_cal) is noise
    cal = np.where(S, rng.uniform(0.0, 1.0, size=S.shape), np.nan)
    tiny = noise.copy()
    tiny[S.nonzero()[0][0], S.nonzero()[1][0]] = 1e-200  # (1e-200)² = 0: sqrt(x²) ≠ x
    for a, b in ((noise, cal), (tiny, zero_cal)):
        out = U._combined(a, b)
        ref = np.sqrt(a**2 + b**2)
        assert out is not a and np.array_equal(out, ref, equal_nan=True)
        assert not np.array_equal(ref, a, equal_nan=True)
    g = np.stack([noise, noise], axis=-1)
    assert U._count_not_finite_on(S, readonly(g)) == 0  # read-only, as the callers pass it: one signature
    g[~S] = np.nan
    g[S.nonzero()[0][5], S.nonzero()[1][5], 1] = np.inf
    assert U._count_not_finite_on(S, readonly(g)) == 1


def _widest_wavefront(S, seed):
    """The largest number of pixels at one 4-connected geodesic distance from ``seed`` within S
    (a breadth-first search in Python, independent of the kernels)."""
    from collections import deque

    H, W = S.shape
    dist = np.full((H, W), -1)
    dist[seed] = 0
    todo = deque([seed])
    count = {}
    while todo:
        v, u = todo.popleft()
        count[dist[v, u]] = count.get(dist[v, u], 0) + 1
        for a, b in ((v - 1, u), (v + 1, u), (v, u - 1), (v, u + 1)):
            if 0 <= a < H and 0 <= b < W and S[a, b] and dist[a, b] < 0:
                dist[a, b] = dist[v, u] + 1
                todo.append((a, b))
    return max(count.values())


def test_a_hole_beside_the_seed_widens_the_wavefront_beyond_the_frames():
    """A 6×6 hole beside the seed makes a wavefront wider than two pixels per row and column (46
    pixels on a 20×32 frame; the pass started with 2·min(H, W) + 2 = 42 and wrote past its
    buffers: a segmentation fault in `pmdsim evaluate` of a set with a flagged patch near the
    seed). The buffers grow; σ equals the four stages' bit for bit."""
    o, d, q, _, _ = _scene(H=20, W=32)
    d = d.copy()
    d[..., 2] = -np.abs(d[..., 2])  # no failing steps: the mask is the hole only
    valid = np.ones((20, 32), bool)
    valid[4:10, 13:19] = False
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=(10, 16), seed_height_mm=0.25)
    S = rec.reconstructed
    assert np.array_equal(S, valid)
    assert _widest_wavefront(S, (10, 16)) > 2 * min(S.shape) + 2
    std = np.random.default_rng(5).uniform(1e-3, 5e-3, size=valid.shape + (2,))
    dq = np.ascontiguousarray(np.linalg.qr(np.random.default_rng(6).normal(size=(3, 3)))[0][:, :2])
    h, g, status = stepwise_noise_sigma(o, d, q, rec, dq, std, 64, 99)
    assert status == 0
    lin = U._LinearisedIntegration(o, d, q, rec)
    A, g_ref = U._jacobian_scaled(o, rec.p_sample_mm, q, dq, S, std)
    assert np.array_equal(h, U._sampled_std(lin, A, 64, 99, overwrite=True), equal_nan=True)
    assert np.array_equal(g, g_ref, equal_nan=True)
