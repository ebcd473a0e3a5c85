"""The stereo heights' noise σ on a subgrid (issue 22 "Speed", ``--stereo``): its draws against
the every-pixel estimator's (the same Rademacher draws, block-averaged by numpy; the anchors'
perturbations sample by sample), and the subgrid's σ against every pixel's σ."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pmdsim.evaluation import uncertainty_stereo as US
from pmdsim.evaluation import uncertainty_stereo_subgrid as SG
from pmdsim.evaluation.pipeline import decode_simulated
from pmdsim.evaluation.stereo import evaluate_stereo_decoded
from pmdsim.evaluation import uncertainty as U
from pmdsim.evaluation.uncertainty import _sample_dg
from pmdsim.setup import default_setup
from pmdsim.simulation.render import noise_generator, trace_setup_camera

DS = 16  # 120 × 75 px per camera


@pytest.fixture(scope="module")
def evaluated():
    """Table 1 binned 16×, 2 grey levels of noise: one noisy decode of both cameras and its
    stereo evaluation (as ``pmdsim evaluate --stereo``)."""
    s = default_setup().binned(DS).with_patterns(noise_std=2.0)
    dec = {}
    for c in s.cameras:
        m = trace_setup_camera(s, c)
        dec[c] = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, c, stream=1000))
    views, st = evaluate_stereo_decoded(s, dec)
    return s, dec, views, st


def test_default_stride_keeps_every_pixel_below_twice_the_minimum_subgrid():
    m = SG.MIN_NOISE_SUBGRID_PX
    assert SG.default_noise_stride((2 * m - 1, 480)) == 1
    assert SG.default_noise_stride((2 * m, 480)) == 2
    assert SG.default_noise_stride((1200, 1920)) == 1200 // SG.MIN_NOISE_SUBGRID_PX


def test_draws_are_the_every_pixel_estimators_block_averaged(evaluated):
    s, dec, views, st = evaluated
    cam = "left"
    rec = st.cameras[cam].reconstruction
    S = np.ascontiguousarray(rec.reconstructed)
    rng = np.random.default_rng(5)
    A = np.ascontiguousarray(np.where(S[..., None, None], rng.normal(size=S.shape + (2, 2)), 0.0))
    stride, off, K, seed = 3, 1, 40, 12345
    lin = SG._SubgridLinear(views[cam], rec, st.cameras[cam].anchor_pixels, stride, off)
    got = lin.block_means(A, seed, K)
    h, w = lin.S.shape
    # reference: every pixel's δg_k (the every-pixel estimator's kernel), averaged per nearest subgrid pixel
    vv, uu = np.indices(S.shape)
    bi = np.clip((vv - off + stride // 2) // stride, 0, h - 1)
    bj = np.clip((uu - off + stride // 2) // stride, 0, w - 1)
    flat = (bi * w + bj)[S]
    cnt = np.bincount(flat, minlength=h * w)
    dg = np.empty(S.shape + (2,))
    for k in (0, 17, 31, 32, 39):
        _sample_dg(A, S, seed, k, (K + 31) // 32, dg)
        for a in range(2):
            ref = np.bincount(flat, weights=dg[..., a][S], minlength=h * w) / np.maximum(cnt, 1)
            np.testing.assert_allclose(got[k, ..., a].ravel(), ref, rtol=1e-12, atol=1e-12)
    # the anchors' perturbations: all samples at once equal the per-sample draws bit for bit
    tangents = {c: US._tangents(s, None, dec[c]) for c in views}
    an = US.anchor_noise(views, dec, tangents, cam, st.cameras[cam].anchor_pixels, st.cameras[cam].anchor_height_mm)
    seeds = US._seeds(7, len(views))
    all_k = np.empty((K, an.std_mm.size))
    SG._anchor_draws(an.anchor, an.camera, an.pixel, an.coef, seeds, K, (K + 31) // 32, all_k)
    one = np.empty(an.std_mm.size)
    for k in (0, 31, 32, 39):
        US._anchor_draw(an.anchor, an.camera, an.pixel, an.coef, seeds, k, (K + 31) // 32, one)
        assert np.array_equal(all_k[k], one)


def test_subgrid_sigma_against_every_pixels_sigma(evaluated):
    """Same seed, so both estimators use the same draws: the difference is the subgrid's (the
    slopes' scales below s pixels), not the estimators' sampling error."""
    s, dec, views, st = evaluated
    every = US.stereo_uncertainty(s, views, dec, st, samples=64, noise_stride=1)
    for stride in (2, 4):
        sub = US.stereo_uncertainty(s, views, dec, st, samples=64, noise_stride=stride)
        for c, (u, a_std) in every.items():
            v, b_std = sub[c]
            m = np.asarray(st.cameras[c].reconstructed, dtype=bool)
            h1, h2 = u.height_std_noise_um[m], v.height_std_noise_um[m]
            assert np.isfinite(h2).all() and np.isnan(v.height_std_noise_um[~m]).all()
            rms = np.sqrt(np.mean(h2 ** 2) / np.mean(h1 ** 2))
            assert abs(rms - 1) < 0.01, (stride, c, rms)
            assert np.max(np.abs(h2 / h1 - 1)) < 0.05, (stride, c)
            # the slopes' σ and the anchors' σ are every pixel's in both
            np.testing.assert_array_equal(v.slope_std_noise_urad, u.slope_std_noise_urad)
            np.testing.assert_array_equal(b_std, a_std)
            assert any(f"every {stride}th pixel" in n for n in v.notes)
            assert not any("subgrid" in n for n in u.notes)


def test_jacobian_and_draws_in_one_pass_equal_the_jacobian_then_numpys_block_means(evaluated):
    """The fused pass (A = J·diag(σ) per pixel, never stored) against _jacobian_scaled (checked
    against finite differences in tests/test_uncertainty.py) and numpy's block averaging of
    every pixel's δg_k; a pixel whose Jacobian is NaN (q = p) counts as A = 0 (np.nan_to_num)."""
    s, dec, views, st = evaluated
    cam = "left"
    rec = st.cameras[cam].reconstruction
    S = np.array(rec.reconstructed)
    S[:7] = False  # some pixels off S
    S[20:30, 50:60] = False
    rec = replace(rec, reconstructed=S)
    reg = views[cam].registration
    v0, u0 = np.argwhere(S)[len(np.argwhere(S)) // 2]
    q = np.array(reg.q_ref_mm, dtype=float)
    q[v0, u0] = rec.p_sample_mm[v0, u0]  # |q − p| = 0: a NaN Jacobian on S
    sig = np.where(S[..., None], np.asarray(dec[cam].std_xy_mm), np.nan)  # read on S only
    T = US._tangents(s, None, dec[cam])  # a broadcast plane's tangents
    stride, off, K, seed = 3, 1, 40, 999
    lin = SG._SubgridLinear(views[cam], rec, st.cameras[cam].anchor_pixels, stride, off)
    got, gstd = lin.jacobian_block_means(reg.o_ref_mm, rec.p_sample_mm, q, T, sig, seed, K)
    A, g_ref = U._jacobian_scaled(reg.o_ref_mm, rec.p_sample_mm, q, T, S, sig)
    assert np.isnan(A[v0, u0]).all() and np.isnan(gstd[~S]).all()
    np.testing.assert_array_equal(gstd, g_ref)
    A = np.ascontiguousarray(np.where(S[..., None, None], np.nan_to_num(A), 0.0))
    np.testing.assert_array_equal(got, lin.block_means(A, seed, K))
    h, w = lin.S.shape
    vv, uu = np.indices(S.shape)
    flat = (np.clip((vv - off + stride // 2) // stride, 0, h - 1) * w
            + np.clip((uu - off + stride // 2) // stride, 0, w - 1))[S]
    cnt = np.bincount(flat, minlength=h * w)
    dg = np.empty(S.shape + (2,))
    for k in (0, 33):
        _sample_dg(A, S, seed, k, (K + 31) // 32, dg)
        for a in range(2):
            ref = np.bincount(flat, weights=dg[..., a][S], minlength=h * w) / np.maximum(cnt, 1)
            np.testing.assert_allclose(got[k, ..., a].ravel(), ref, rtol=1e-12, atol=1e-12)


def test_interpolated_std_is_bilinear_interpolation():
    """σ from the subgrid to every pixel: scipy's linear interpolation (with linear extrapolation
    beyond the outer nodes) of the subgrid σ, NaN off S; bit for bit the three-channel
    ``_accumulate`` path it replaces."""
    from scipy.interpolate import RegularGridInterpolator

    from pmdsim.evaluation.uncertainty_calibration import _accumulate

    rng = np.random.default_rng(8)
    h, w, o, s, H, W = 9, 13, 2, 5, 47, 66
    sd = rng.lognormal(size=(h, w))
    S = rng.random((H, W)) > 0.1
    out = np.empty((H, W))
    SG._interpolated_std(sd, S, o, s, out)
    f = RegularGridInterpolator((o + s * np.arange(h), o + s * np.arange(w)), sd, bounds_error=False, fill_value=None)
    vv, uu = np.indices((H, W))
    ref = np.abs(f(np.stack([vv, uu], -1).astype(float)))
    np.testing.assert_allclose(out[S], ref[S], rtol=1e-12)
    assert np.isnan(out[~S]).all()
    old = np.sqrt(_accumulate(np.ascontiguousarray(sd[None, ..., None] * np.ones(3)), o, o, s, H, W)[..., 0])
    np.testing.assert_array_equal(out[S], old[S])
