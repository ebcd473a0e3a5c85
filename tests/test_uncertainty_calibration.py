"""The calibration's covariance carried by a setup and propagated to heights and slopes.

* :class:`CalibrationCovariance` refuses what is not a covariance; the setup TOML round trip
  keeps it (``[calibration_report] covariance_parameters`` / ``covariance``) and refuses bad
  input with one line naming the key;
* the bridge: ``calibrated_setup`` carries the result's covariance (mirror 0 as the table);
  ``perturbed_setup`` moves a setup as ``CalibrationState.updated`` moves the calibration's
  state, checked against the bridge (cameras, table plane, screen heights); binning commutes
  with a step;
* ``calibration_contribution`` against a dense reference computed here, independently: central
  differences per *parameter* (not along principal axes) on every pixel, σ² = diag(J C Jᵀ),
  without and with a height anchor; a zero covariance gives zero.

The Monte Carlo over independent calibrations is ``benchmarks/mc_uncertainty_calibration.py``
(docs/benchmarks.md, "Uncertainty: calibration Monte Carlo").
"""

from __future__ import annotations

import tomllib
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from pmdsim.calibration import calibrate, free_screen_model, nominal_setup, nominal_state
from pmdsim.calibration.setup_bridge import calibrated_setup, perturbed_setup, setup_covariance
from pmdsim.errors import SetupError
from pmdsim.evaluation.anchor import HeightAnchor, reconstruct_anchored, register_model
from pmdsim.evaluation.reconstruction import reconstruct
from pmdsim.evaluation.surface_fit import sample_slopes
from pmdsim.evaluation.uncertainty_calibration import (
    CalibrationUncertaintyError,
    calibration_contribution,
    calibration_parameters,
)
from pmdsim.setup import default_setup, parse_setup
from pmdsim.setup.covariance import CalibrationCovariance, table_plane
from pmdsim.simulation.render import trace_setup_camera
from pmdsim.studies import observe_calibration_poses, trace_calibration_poses
from pmdsim.studies.calibration_data import simulate_decoded

DS = 8  # cameras binned 8 × 8: 240 × 150 px


def _random_matrix(n, seed=0):
    a = np.random.default_rng(seed).normal(size=(n, n))
    return a @ a.T + 0.1 * np.eye(n)


def _random_cov(names, seed=0):
    return CalibrationCovariance(tuple(names), _random_matrix(len(names), seed))


# ============================================================================ the covariance
def test_covariance_refuses_what_is_not_a_covariance():
    names = ("left.fx_px", "table.d_mm")
    with pytest.raises(SetupError, match="not symmetric"):
        CalibrationCovariance(names, [[1.0, 0.5], [0.4, 1.0]])
    with pytest.raises(SetupError, match="positive semi-definite"):
        CalibrationCovariance(names, [[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(SetupError, match="negative variance"):
        CalibrationCovariance(names, [[-1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(SetupError, match="unknown parameter"):
        CalibrationCovariance(("left.fx_px", "mirror3.d_mm"), np.eye(2))
    with pytest.raises(SetupError, match="repeated"):
        CalibrationCovariance(("left.fx_px", "left.fx_px"), np.eye(2))
    with pytest.raises(SetupError, match="2 × 2"):
        CalibrationCovariance(names, np.eye(3))
    c = CalibrationCovariance(names, [[1.0, 0.5], [0.5, 1.0]])
    with pytest.raises(ValueError):
        c.matrix[0, 0] = 2.0  # read-only
    with pytest.raises(SetupError, match="no camera 'middle'"):
        default_setup().with_calibration_covariance(CalibrationCovariance(("middle.fx_px",), [[1.0]]))
    with pytest.raises(SetupError, match="screen grid has 3 × 3"):
        default_setup().with_calibration_covariance(CalibrationCovariance(("screen.h[3,1]_mm",), [[1.0]]))


def test_setup_toml_round_trip_and_refusals():
    s = default_setup()
    names = ["left.fx_px", "left.rotvec_y", "right.position_z_mm", "table.tilt_a", "table.d_mm", "screen.h[1,1]_mm"]
    s = s.with_calibration_covariance(_random_cov(names))
    doc = tomllib.loads(s.to_toml())
    assert doc["calibration_report"]["covariance_parameters"] == names
    back = parse_setup(doc)
    assert back == s and np.array_equal(back.calibration_covariance.matrix, s.calibration_covariance.matrix)
    assert parse_setup(tomllib.loads(default_setup().to_toml())).calibration_covariance is None
    bad = tomllib.loads(s.to_toml())
    bad["calibration_report"]["covariance"][0][1] += 1.0
    with pytest.raises(SetupError, match=r"calibration_report\.covariance: .*not symmetric"):
        parse_setup(bad)
    bad = tomllib.loads(s.to_toml())
    bad["calibration_report"]["covariance"] = bad["calibration_report"]["covariance"][:-1]
    with pytest.raises(SetupError, match=r"calibration_report\.covariance must be 6 rows of 6 numbers"):
        parse_setup(bad)
    bad = tomllib.loads(s.to_toml())
    bad["calibration_report"]["covariance"][2][2] = "x"
    with pytest.raises(SetupError, match=r"calibration_report\.covariance\[2\]\[2\] must be a finite number"):
        parse_setup(bad)
    bad = tomllib.loads(s.to_toml())
    del bad["calibration_report"]["covariance"]
    with pytest.raises(SetupError, match=r"missing key calibration_report\.covariance"):
        parse_setup(bad)


# ============================================================================ the bridge
def _result_like(state, cov):
    """What calibrated_setup reads of a CalibrationResult, from a CalibrationState."""
    return SimpleNamespace(cameras={n: (cp.camera, cp.T_screen_cam) for n, cp in state.cameras.items()},
                           mirrors=list(state.mirrors), screen_model=state.screen, covariance=cov,
                           parameter_names=tuple(state.parameter_names()))


@pytest.mark.parametrize("grid", [None, 5])
def test_perturbed_setup_moves_the_setup_as_the_calibration_moves_its_state(grid):
    truth = default_setup().binned(DS)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    state = nominal_state(nominal, poses)
    if grid is not None:
        state = replace(state, screen=free_screen_model(nominal, grid))
    names = state.parameter_names()
    cov = _random_matrix(len(names), seed=1)
    base = calibrated_setup(nominal, _result_like(state, cov))
    # Its covariance: the result's, mirror 0 renamed, the other mirrors dropped.
    sc = base.calibration_covariance
    assert "table.d_mm" in sc.parameters and not any(n.startswith("mirror") for n in sc.parameters)
    assert len(sc.parameters) == 28 + 3 + (0 if grid is None else (grid - 2) ** 2)
    i, j = names.index("mirror0.tilt_b"), names.index("left.ppy_px")
    a, b = sc.parameters.index("table.tilt_b"), sc.parameters.index("left.ppy_px")
    assert sc.matrix[a, b] == cov[i, j]
    assert nominal_setup(base).calibration_covariance is None
    rng = np.random.default_rng(2)
    scale = {"rotvec": 1e-3, "tilt": 1e-3, "k": 1e-3, "p": 1e-4}
    delta = np.array([next((v for k, v in scale.items() if n.split(".")[1].startswith(k)), 0.5) for n in names])
    delta *= rng.normal(size=len(names))
    want = calibrated_setup(nominal, _result_like(state.updated(delta), cov))
    got = perturbed_setup(base, np.array([delta[names.index(n if not n.startswith("table.") else
                                                             "mirror0." + n[6:])] for n in sc.parameters]))
    for cam in truth.cameras:
        g, w = got.cameras[cam], want.cameras[cam]
        for f in ("fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2"):
            assert getattr(g.camera, f) == pytest.approx(getattr(w.camera, f), abs=1e-12)
        np.testing.assert_allclose(g.T_world_cam.as_matrix(), w.T_world_cam.as_matrix(), atol=1e-9)
    (ng, dg), (nw, dw) = table_plane(got), table_plane(want)
    np.testing.assert_allclose(ng, nw, atol=1e-12)
    assert dg == pytest.approx(dw, abs=1e-9)
    np.testing.assert_allclose(got.screen.control_heights(), want.screen.control_heights(), atol=1e-12)
    # and back: the zero step is the identity
    assert perturbed_setup(base, np.zeros(len(sc.parameters))) == base


def test_binning_commutes_with_a_step():
    s = default_setup()
    names = ("left.fx_px", "left.ppx_px", "left.k1", "left.position_x_mm")
    s = s.with_calibration_covariance(_random_cov(names))
    step = np.array([2.0, -3.0, 1e-3, 0.5])
    a = perturbed_setup(s, step).binned(4)
    b = perturbed_setup(s.binned(4), step * np.array([0.25, 0.25, 1.0, 1.0]))
    for f in ("fx_px", "ppx_px", "k1"):
        assert getattr(a.cameras["left"].camera, f) == pytest.approx(getattr(b.cameras["left"].camera, f), rel=1e-12)
    np.testing.assert_allclose(a.cameras["left"].T_world_cam.translation, b.cameras["left"].T_world_cam.translation)
    # the binned covariance: the step's σ scale the same way
    ratio = s.binned(4).calibration_covariance.std / s.calibration_covariance.std
    np.testing.assert_allclose(ratio, [0.25, 0.25, 1.0, 1.0])


# ============================================================================ propagation
@pytest.fixture(scope="module")
def calibrated():
    return calibrated_and_decoded()


def calibrated_and_decoded():
    """A calibration of the 8 × 8-binned Table 1 setup from noisy images (2 grey levels), and a
    decoded measurement of its planar sample."""
    truth = default_setup().binned(DS).with_patterns(noise_std=2.0, seed=7)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    traced = trace_calibration_poses(truth, 16)
    res = calibrate(observe_calibration_poses(truth, traced, 16), nominal_state(nominal, poses))
    assert res.converged
    model = calibrated_setup(nominal, res)
    decoded = simulate_decoded(truth, "left", trace_setup_camera(truth, "left"))
    return model, decoded


def _dense_reference(model, decoded, anchor, seed, rel_step=0.1):
    """σ of heights (µm) and slopes (µrad) per pixel: central differences per parameter on every
    pixel, then diag(J C Jᵀ) — the definition, without principal axes or subgrids."""
    names = calibration_parameters(model, "left")
    cov = model.calibration_covariance.subset(names)
    jac = []
    for j, n in enumerate(names):
        h = rel_step * cov.std[j]
        fields = []
        for sign in (1.0, -1.0):
            e = np.zeros(len(names))
            e[j] = sign * h
            m = perturbed_setup(model, e, names)
            reg = register_model(m, "left", decoded)
            if anchor is None:
                rec = reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, seed_pixel=seed, seed_height_mm=0.0)
            else:
                rec = reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=anchor,
                                           T_world_ref=m.sample.T_world_sample).reconstruction
            fields.append(np.concatenate([rec.height_mm[..., None], sample_slopes(rec.n_sample)], axis=-1))
        jac.append((fields[0] - fields[1]) / (2 * h))
    jac = np.stack(jac, axis=-1)  # (H, W, 3, P)
    var = np.einsum("hwcp,pq,hwcq->hwc", jac, cov.matrix, jac)
    return np.sqrt(var[..., 0]) * 1e3, np.sqrt(var[..., 1:]) * 1e6


@pytest.mark.parametrize("with_anchor", [False, True], ids=["seed", "height_anchor"])
def test_contribution_matches_a_dense_central_difference_reference(calibrated, with_anchor):
    model, decoded = calibrated
    # ×10⁴ in variance (×100 in σ): the reference's differences stay far above the anchor
    # iteration's tolerance; the contribution's step 1e-4 σ is then its default absolute step.
    cov = model.calibration_covariance
    model = model.with_calibration_covariance(CalibrationCovariance(cov.parameters, cov.matrix * 1e4))
    reg = register_model(model, "left", decoded)
    anchor = HeightAnchor((70.3, 121.6), 0.05) if with_anchor else None
    ar = reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=anchor,
                              T_world_ref=model.sample.T_world_sample)
    seed = ar.reconstruction.seed_pixel
    c = calibration_contribution(model, "left", decoded, anchor=anchor, step=1e-4)
    assert c.stride_px == 2 and c.n_axes == 17 and c.height_std_um.dtype == np.float64
    h_ref, g_ref = _dense_reference(model, decoded, anchor, seed)
    mask = ar.reconstruction.reconstructed
    assert np.array_equal(np.isfinite(c.height_std_um), mask)
    assert np.array_equal(np.isfinite(c.slope_std_urad).all(axis=-1), mask)
    # Relative to the field's RMS (σ_h is ~0 near the seed, where a ratio says nothing); measured
    # 0.2 % (heights) and 0.5 % (slopes, at the image corners: extrapolated from the subgrid).
    rms_h = np.sqrt(np.mean(h_ref[mask] ** 2))
    assert np.max(np.abs(c.height_std_um - h_ref)[mask]) < 0.01 * rms_h
    for k in range(2):
        rms_g = np.sqrt(np.mean(g_ref[..., k][mask] ** 2))
        assert np.max(np.abs(c.slope_std_urad[..., k] - g_ref[..., k])[mask]) < 0.01 * rms_g
    if not with_anchor:
        assert c.height_std_um[seed] == 0.0  # heights relative to the seed


def test_zero_covariance_gives_zero_and_none_refuses(calibrated):
    model, decoded = calibrated
    names = model.calibration_covariance.parameters
    zero = model.with_calibration_covariance(CalibrationCovariance(names, np.zeros((len(names), len(names)))))
    c = calibration_contribution(zero, "left", decoded)
    m = np.isfinite(c.height_std_um)
    assert m.sum() > 0.5 * m.size and c.n_axes == 0
    assert np.all(c.height_std_um[m] == 0.0) and np.all(c.slope_std_urad[m] == 0.0)
    with pytest.raises(CalibrationUncertaintyError, match="no calibration covariance"):
        calibration_contribution(model.with_calibration_covariance(None), "left", decoded)
