"""The calibration's reported uncertainties against a Monte Carlo over image noise (issue 5).

Truth and chain: the paper's Table 1 setup with cameras binned 8 × 8 (240 × 150 px) and the 16
calibration mirror poses, traced by pmdsim's ray tracer; per draw the fringe images are rendered
with Gaussian image noise (``noise_std`` = 2 grey levels, a seeded, independent stream per
camera and pose), quantised to 8 bits and decoded; the calibration sees pixel ↔ decoded screen
point. Two models, each with a truth it can represent: the planar screen (flat truth, P = 76
parameters) and a free 5 × 5 screen (9 free heights, P = 85; truth: the paper's bulge Δh = 3 mm,
a product of parabolas, which that spline reproduces exactly). 5 × 5 rather than 3 × 3 so that the
screen heights alone carry enough degrees of freedom to be checked. The 5 × 5 calibration gets
the decoder's predicted σ of every correspondence (``q_std_mm``), the planar one does not: both
ways of stating the screen-point noise are checked.

Speed: each (pose, camera) is traced once, and only every ``STRIDE``-th pixel is rendered and
decoded. Rendering is point-sampled and decoding is per pixel, with independent noise per pixel,
so this is the same distribution as rendering every pixel and keeping every ``STRIDE``-th
correspondence (``experiments.simulate_calibration_observations``, which the benchmark
``benchmarks/bench_calibration_mc.py`` uses at larger sizes). Every draw starts at the true
cameras and mirror planes (flat screen): the covariance is a property of the solution.

Noise level: 2 grey levels against the 8-bit quantisation's 1/√12 = 0.29: with noise, the
quantisation error is dithered and adds 2 % to the variance; without noise it is a deterministic
error (checked below to be ≤ 0.3 of the noise's residual). Deviations are taken from the Monte
Carlo mean, so what all draws share (the truth, any deterministic error) is not counted as spread.

Statistics (:func:`pmdsim.calibration.compare_spread`), n draws, d_i = θ_i − θ̄ over a set of
P parameters with reported covariance C (the mean over the draws):

* whitened ratio ρ_w = √(T/((n−1)P)), T = Σ_i d_iᵀ C⁻¹ d_i: pooled z-scores of the decorrelated
  deviations. If C is right (Gaussian, linear regime) T ~ χ²_{(n−1)P}, so ρ_w = 1 with relative
  standard error 1/√(2(n−1)P): 1.9 % for all 76 parameters and n = 20 draws. Computed for all
  parameters and per block (intrinsics 16, camera poses 12, mirror planes 48, screen heights 9
  parameters: 4.1 %, 4.7 %, 2.3 %, 5.4 %), since a wrong σ of a few parameters is diluted in the
  overall ratio. Tolerances: ±15 % overall (8 standard errors), ±20 % per block (≥ 3.7
  standard errors), both tighter than the issue's 30 %; beyond the sampling error they leave
  room for the linearisation and the dithered quantisation (2 % of the variance). The reported
  covariance is the sandwich for noise on the screen points (the plain σ²(JᵀJ)⁻¹ of pixel
  residuals would be off by ≤ 5 % per parameter, ≤ 13 % in the worst direction, here). A
  reported σ scaled by 1.5 or 0.6 fails each of these checks (asserted).
* marginal ratio ρ_z = √(Σ_ij z_ij²/((n−1)P)), z_ij = d_ij/σ_j: the per-parameter reported σ
  pooled without decorrelation. Strongly correlated parameters (intrinsics, poses) make the z_j
  dependent: the effective degrees of freedom are (n−1)P²/Σ_jk r_jk² (r: the reported
  correlations), ≈ 2.4 (n−1) here, a relative standard error of ≈ 10 %. Checked against the
  issue's ±30 % (a consistency check; its power comes from the whitened checks).
"""

from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np
import pytest

from pmdsim.calibration import (
    MirrorPlane,
    Observations,
    SpreadComparison,
    calibrate,
    compare_spread,
    nominal_state,
)
from pmdsim.calibration import free_screen_model, nominal_setup
from pmdsim.studies import observe_calibration_poses, trace_calibration_poses
from pmdsim.setup import default_setup

DS = 8  # cameras binned 8 × 8: 240 × 150 px
STRIDE = 16  # every 16th pixel in u and v: ≈ 150 correspondences per camera and pose
NOISE_GREY = 2.0
DRAWS = 20
WHITENED_TOL = 0.15
BLOCK_TOL = 0.20
MARGINAL_TOL = 0.30


def observe(truth, traced, noise_std, seed, with_std=False):
    """Render (8 bit, noise seeded by ``seed``) and decode the strided pixels; ``with_std``:
    keep the decoder's predicted σ of (x_q, y_q) as ``q_std_mm``. Also returns the median
    predicted σ (mm)."""
    s = replace(truth, patterns=replace(truth.patterns, noise_std=noise_std, seed=seed))
    obs = observe_calibration_poses(s, traced, STRIDE)
    std = float(np.median(np.concatenate([o.q_std_mm for o in obs])))
    if not with_std:
        obs = [Observations(o.camera, o.pose_index, o.uv_px, o.q_screen_mm) for o in obs]
    return obs, std


def monte_carlo(bulge_mm, screen_grid, seed0, with_std):
    truth = default_setup().binned(DS).with_bulge(bulge_mm)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = nominal_state(nominal, poses)  # the true cameras and planes; a flat screen
    model = None if screen_grid is None else free_screen_model(nominal, screen_grid)
    traced = trace_calibration_poses(truth, STRIDE)
    results = []
    for i in range(DRAWS):
        obs, decoder_std = observe(truth, traced, NOISE_GREY, seed0 + i, with_std)
        res = calibrate(obs, start, screen_model=model)
        assert res.converged, res.reason
        results.append(res)
    quantised = calibrate(observe(truth, traced, 0.0, 0, with_std)[0], start, screen_model=model)
    return results, quantised, decoder_std


@pytest.fixture(scope="module", params=[("planar", 0.0, None), ("5x5", 3.0, 5)], ids=lambda p: p[0])
def mc(request):
    """The planar model without, the 5 × 5 model with the decoder's σ of each correspondence."""
    label, bulge, grid = request.param
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # images of 15 × 10 px: starting threads would cost more than the work
    try:
        results, quantised, decoder_std = monte_carlo(bulge, grid, 1000 if grid is None else 2000,
                                                      with_std=grid is not None)
    finally:
        numba.set_num_threads(threads)
    return label, results, quantised, decoder_std, compare_spread(results)


def test_noise_level_and_quantisation(mc):
    """The residuals imply the decoder's predicted screen-point noise (σ₀ in mm without
    ``q_std_mm``, ≈ 1 with the decoder's σ as ``q_std_mm``); without image noise the
    deterministic 8-bit error leaves ≤ 0.3 of the noisy residual: the Monte Carlo measures the
    noise, not the quantisation."""
    label, results, quantised, decoder_std, _ = mc
    sigma0 = np.median([r.screen_noise_std for r in results])
    assert sigma0 == pytest.approx(1.0 if label != "planar" else decoder_std, rel=0.05)
    noisy_rms = np.median([r.rms_px for r in results])
    assert 0.0 < quantised.rms_px < 0.3 * noisy_rms
    # The draws differ (independent noise) and fit to the same level.
    assert len({round(r.rms_px, 12) for r in results}) == len(results)
    assert np.ptp([r.rms_px for r in results]) < 0.05 * noisy_rms


def test_reported_covariance_matches_the_monte_carlo_spread(mc):
    label, results, _, _, cmp = mc
    p = len(results[0].parameter_names)
    assert cmp.n_draws == DRAWS and cmp.whitened_dof == (DRAWS - 1) * p
    assert p == 76 + (0 if label == "planar" else 9)
    se_w = cmp.ratio_standard_error(cmp.whitened_dof)
    se_z = cmp.ratio_standard_error(cmp.marginal_dof)
    blocks = cmp.block_ratios()
    assert set(blocks) == ({"intrinsics", "camera_poses", "mirrors"} | ({"screen"} if label != "planar" else set()))
    groups = {g: round(r, 2) for g, (r, _, _) in cmp.group_ratios().items()}
    info = (f"{label} (observed / reported spread): whitened ρ = {cmp.whitened_ratio:.3f} ± {se_w:.3f}, blocks "
            + ", ".join(f"{b} {r:.3f} ± {cmp.ratio_standard_error(d):.3f}" for b, (r, d, _) in blocks.items())
            + f"; marginal ρ = {cmp.marginal_ratio:.3f} ± {se_z:.3f}; groups (marginal) {groups}")
    # The statistics are precise enough for their tolerances to mean something.
    assert 5 * se_w < WHITENED_TOL and 2 * se_z < MARGINAL_TOL, info
    assert abs(cmp.whitened_ratio - 1.0) <= WHITENED_TOL, info
    assert abs(cmp.marginal_ratio - 1.0) <= MARGINAL_TOL, info
    for b, (r, dof, _) in blocks.items():
        assert 3 * cmp.ratio_standard_error(dof) < BLOCK_TOL, info
        assert abs(r - 1.0) <= BLOCK_TOL, f"block {b}: " + info
    # The checks can fail: a reported σ scaled by 1.5 or 0.6 (ratios scale by 1/1.5, 1/0.6) would.
    for k in (1.5, 0.6):
        assert abs(cmp.whitened_ratio / k - 1.0) > WHITENED_TOL, info
        for b, (r, _, _) in blocks.items():
            assert abs(r / k - 1.0) > BLOCK_TOL, f"block {b}: " + info


def test_spread_statistics_on_synthetic_draws():
    """compare_spread's statistics on draws from a known Gaussian (no calibration involved):
    with the true covariance the ratios are 1 within their standard errors; with σ reported
    1.5× too large they are 1/1.5."""
    class Fake:  # the attributes compare_spread uses
        def __init__(self, state, cov, names):
            self.state, self.covariance, self.parameter_names = state, cov, names

    # A real state to take increments from: 2 cameras, 3 mirrors (P = 37).
    truth = default_setup().binned(DS)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)][:3]
    state = nominal_state(truth, poses)
    names = tuple(state.parameter_names())
    p = len(names)
    rng = np.random.default_rng(5)
    a = rng.normal(size=(p, 3))
    corr_factor = a @ a.T + 0.1 * np.eye(p)  # strongly correlated: 3 dominant common modes
    scale = np.array([1e-3 if ("rotvec" in n or "tilt" in n) else 0.05 for n in names])
    cov = corr_factor * np.outer(scale, scale)
    chol = np.linalg.cholesky(cov)
    n = 60
    draws = [state.updated(chol @ rng.normal(size=p)) for _ in range(n)]
    cmp = compare_spread([Fake(s, cov, names) for s in draws])
    assert isinstance(cmp, SpreadComparison) and cmp.n_draws == n
    assert abs(cmp.whitened_ratio - 1) < 4 * cmp.ratio_standard_error(cmp.whitened_dof)
    assert abs(cmp.marginal_ratio - 1) < 4 * cmp.ratio_standard_error(cmp.marginal_dof)
    assert cmp.marginal_dof < 0.5 * cmp.whitened_dof  # correlations cost degrees of freedom
    wrong = compare_spread([Fake(s, 1.5**2 * cov, names) for s in draws])
    assert wrong.whitened_ratio == pytest.approx(cmp.whitened_ratio / 1.5, rel=1e-9)
    assert wrong.marginal_ratio == pytest.approx(cmp.marginal_ratio / 1.5, rel=1e-9)
    ratios = cmp.group_ratios()
    assert set(ratios) == {"fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2", "rotvec_x", "rotvec_y",
                           "rotvec_z", "position_x_mm", "position_y_mm", "position_z_mm", "mirror.tilt_a",
                           "mirror.tilt_b", "mirror.d_mm"}
    assert all(cnt == (2 if not g.startswith("mirror") else 3) for g, (_, _, cnt) in ratios.items())
    with pytest.raises(ValueError, match="at least 2"):
        compare_spread(draws[:1])


def test_increment_to_inverts_updated():
    truth = default_setup().binned(DS).with_bulge(3.0)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    state = replace(nominal_state(nominal, poses), screen=free_screen_model(nominal, 5))
    rng = np.random.default_rng(9)
    scale = np.where([("rotvec" in n or "tilt" in n or n.endswith(("k1", "k2", "p1", "p2")))
                      for n in state.parameter_names()], 1e-3, 0.5)
    delta = rng.normal(size=state.n_parameters) * scale
    other = state.updated(delta)
    np.testing.assert_allclose(state.increment_to(other), delta, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(state.increment_to(state), 0.0, atol=1e-12)
    # A mirror given with the opposite normal, (−n, −d), is the same plane.
    flipped = replace(other, mirrors=tuple(MirrorPlane(-m.normal, -m.d_mm) for m in other.mirrors))
    np.testing.assert_allclose(state.increment_to(flipped), delta, rtol=1e-6, atol=1e-12)
    with pytest.raises(ValueError, match="screen models"):
        state.increment_to(replace(other, screen=None))
