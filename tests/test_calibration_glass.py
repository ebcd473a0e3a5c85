"""The cover glass as calibration parameters (issue 21), against what the calibration did not make:
the exact refraction trace of :class:`~pmdsim.geometry.cover_glass.CoverGlass` (apparent points),
central finite differences of the residuals (the analytic Jacobian, every column including t and
n, on a curved screen model), the dense Jacobian (the kernel's normal equations), and data traced
through a glass by the simulator (seeded recovery of t and n).
"""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.calibration import Observations, nominal_state, observations_from_mapping, perturbed_state
from pmdsim.calibration import solver as S
from pmdsim.calibration.glass import calibrate_with_glass
from pmdsim.calibration.glass_kernel import glass_points_kernel
from pmdsim.calibration.jacobian import residuals_and_jacobian
from pmdsim.calibration.model import CalibrationState
from pmdsim.calibration.screen import ScreenModel
from pmdsim.geometry.cover_glass import CoverGlass
from pmdsim.setup import default_setup
from pmdsim.studies.calibration_data import trace_calibration_poses


def _state_and_obs(rng, n_per=12, glass=CoverGlass(3.0, 1.52), free=(True, True), screen=None):
    setup = default_setup()
    poses = [T for _, T in setup.calibration.mirror_poses(setup.sample)][:4]
    st = nominal_state(setup, poses)
    st = CalibrationState(st.cameras, st.mirrors, screen, glass, free)
    obs = []
    for cam, cs in setup.cameras.items():
        for k in range(4):
            q = np.column_stack([rng.uniform(150, 550, n_per), rng.uniform(100, 300, n_per), np.zeros(n_per)])
            uv = rng.uniform(300, 1500, (n_per, 2))
            obs.append(Observations(cam, k, uv, q))
    return st, obs


def test_apparent_points_match_the_exact_refraction_trace():
    """Flat screen: the local-plate model is exact, so the kernel's apparent point equals the
    one of CoverGlass.apparent_points (an exact ray trace through the plate, inverted)."""
    from pmdsim.geometry.surface import PlaneSurface

    rng = np.random.default_rng(3)
    glass = CoverGlass(3.0, 1.52)
    c = np.array([120.0, -80.0, -600.0])  # a virtual camera centre (sample side: z < 0)
    q = np.column_stack([rng.uniform(0, 700, 50), rng.uniform(0, 400, 50), np.zeros(50)])
    qa = np.empty_like(q)
    gl = np.empty((50, 30))
    bad = np.empty(50, dtype=bool)
    mir = np.array([[0.0, 0.0, 1.0, 1e6]])  # a plane far away: c' = reflect(cen) is set through cen below
    cen = (c - 2.0 * (c @ mir[0, :3] - mir[0, 3]) * mir[0, :3])[None]  # reflects back to c
    glass_points_kernel(np.array([0]), np.array([50]), np.array([0]), np.array([0]), q, np.zeros((50, 2)), cen, mir,
                        glass.thickness_mm, glass.index, True, q, qa, gl, bad)
    assert not bad.any()
    exact = glass.apparent_points(PlaneSurface((0.0, 708.0), (0.0, 398.0)), c, q)
    np.testing.assert_allclose(qa, exact, atol=1e-8, rtol=0)
    assert np.abs(qa - q).max() > 0.3  # the plate shift is not negligible


def _fd_jacobian(obs, state, h):
    n = state.n_parameters
    cols = []
    for j in range(n):
        d = np.zeros(n)
        d[j] = h[j]
        rp = residuals_and_jacobian(obs, state.updated(d))[0]
        rm = residuals_and_jacobian(obs, state.updated(-d))[0]
        cols.append((rp - rm) / (2 * h[j]))
    return np.column_stack(cols)


def test_jacobian_with_glass_matches_central_differences():
    """Every column — cameras, mirrors, free screen heights of a curved screen (the plate normal
    follows it), glass thickness and index — against central differences of the residuals."""
    rng = np.random.default_rng(5)
    sm = ScreenModel(np.linspace(0, 708, 4), np.linspace(0, 398, 4),
                     np.array([[0, 0, 0, 0], [0, 2.0, 1.5, 0], [0, 1.0, 2.5, 0], [0, 0, 0, 0]], dtype=float),
                     np.array([[0, 0, 0, 0], [0, 1, 1, 0], [0, 1, 1, 0], [0, 0, 0, 0]], dtype=bool))
    state, obs = _state_and_obs(rng, screen=sm)
    r, jac, names = residuals_and_jacobian(obs, state)
    assert np.isfinite(r).all() and names[-2:] == ["screen.glass_thickness_mm", "screen.glass_index"]
    units = S._units(state)
    fd = _fd_jacobian(obs, state, 1e-4 * units)
    scale = np.abs(fd).max(axis=0)
    assert scale.min() > 0
    err = np.abs(jac - fd).max(axis=0) / scale
    assert err.max() < 1e-5, {names[j]: err[j] for j in np.argsort(-err)[:5]}


def test_kernel_normal_equations_equal_the_dense_jacobian():
    """The solver's kernel (JᵀJ, Jᵀr in internal units, glass columns included) against the
    dense Jacobian's."""
    rng = np.random.default_rng(6)
    state, obs = _state_and_obs(rng, n_per=30)
    data = S._pack(obs, state, 20)
    cost, _, bad, a, g = S._evaluate(data, state, True)
    # The packed order is block order; the dense one follows obs (the same order here).
    r, jac, _ = residuals_and_jacobian(obs, state)
    ju = jac * S._units(state)
    assert not bad.any()
    np.testing.assert_allclose(cost, r @ r, rtol=1e-12)
    np.testing.assert_allclose(a, ju.T @ ju, rtol=1e-9, atol=1e-9 * np.abs(a).max())
    np.testing.assert_allclose(g, ju.T @ r, rtol=1e-9, atol=1e-9 * np.abs(g).max())


def test_glass_inputs_kept_and_warm_started_equal_a_fresh_computation():
    """The solver's glass inputs are kept for the last state and warm started from it for the
    next: for another state they equal those of freshly packed data (no stale result; the fixed
    point's start moves the apparent points by < 1e-11 mm), the probe call without derivatives
    gives the same apparent points, and a call for the kept state returns them unchanged."""
    from dataclasses import replace

    from pmdsim.calibration.glass_kernel import glass_inputs

    rng = np.random.default_rng(8)
    state, obs = _state_and_obs(rng, n_per=30, free=(True, False))
    other = replace(state, glass=state.glass.with_(thickness_mm=1.7))
    moved = other.updated(1e-3 * rng.standard_normal(other.n_parameters))

    def fresh(st, **kw):
        d = S._pack(obs, st, 20)
        return glass_inputs(d, st, S._screen_q(d.q, d.wx, d.wy, st.screen), **kw)

    data = S._pack(obs, state, 20)
    q = S._screen_q(data.q, data.wx, data.wy, state.screen)
    first = glass_inputs(data, state, q)
    assert glass_inputs(data, state, q) is first  # kept
    for st in (other, moved):
        warm = glass_inputs(data, st, q)
        cold = fresh(st)
        assert np.abs(warm[1] - first[1]).max() > 0.05  # a different state: different points
        np.testing.assert_allclose(warm[1], cold[1], atol=1e-11, rtol=0)
        np.testing.assert_allclose(warm[2], cold[2], atol=1e-9, rtol=1e-9)
        np.testing.assert_array_equal(warm[7], cold[7])
        probe = fresh(st, derivatives=False)
        np.testing.assert_array_equal(probe[1], cold[1])


@pytest.fixture(scope="module")
def traced_glass():
    """Binned-8 Table 1 cameras, 16 mirror poses, a 1.1 mm glass (n = 1.52) traced by the
    simulator (exact refraction), correspondences every 4th binned pixel."""
    truth = default_setup().binned(8).with_cover_glass(1.1, 1.52)
    traced = trace_calibration_poses(truth, stride=4)
    obs = [observations_from_mapping(cam, k, m.screen_xy_mm, m.valid, stride=1) for k, cam, m in traced]
    obs = [Observations(o.camera, o.pose_index, o.uv_px * 4, o.q_screen_mm) for o in obs]
    return truth, obs


def test_seeded_recovery_of_thickness_and_index(traced_glass):
    """Start 1.0 mm and perturbed cameras and mirrors (seeded): the staged fit recovers t (n
    held at its true 1.52; and t, n jointly from n = 1.5) from data the simulator traced through
    a 1.1 mm, n = 1.52 glass (flat screen: the local-plate model is exact, so to ~1e-6 mm);
    the σ from the covariance is reported. With seeded decoding noise on the screen points the
    error of t is within 4 σ."""
    truth, obs = traced_glass
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = perturbed_state(nominal_state(truth.with_cover_glass(0.0), poses), np.random.default_rng(11))
    r = calibrate_with_glass(obs, start, CoverGlass(1.0, 1.52), fit_thickness=True, fit_index=False)
    assert r.converged
    assert abs(r.glass.thickness_mm - 1.1) < 1e-4, r.glass
    r2 = calibrate_with_glass(obs, r.state, CoverGlass(1.0, 1.5), fit_thickness=True, fit_index=True)
    assert abs(r2.glass.thickness_mm - 1.1) < 2e-3 and abs(r2.glass.index - 1.52) < 2e-3, r2.glass
    # Noise: σ = 0.005 mm on the decoded screen points.
    rng = np.random.default_rng(12)
    noisy = [Observations(o.camera, o.pose_index, o.uv_px,
                          o.q_screen_mm + np.column_stack([rng.normal(0, 0.005, (o.n, 2)), np.zeros(o.n)]))
             for o in obs]
    rn = calibrate_with_glass(noisy, r.state, CoverGlass(1.0, 1.52), fit_thickness=True)
    st, sn = rn.glass_std()
    assert sn is None and 0 < st < np.inf
    assert abs(rn.glass.thickness_mm - 1.1) < 4 * st, (rn.glass, st)
    d = rn.to_dict()["glass"]
    assert d["thickness_std_mm"] == st and d["fit_thickness"] and not d["fit_index"]
    # The calibrated setup carries the fitted glass.
    from pmdsim.calibration.setup_bridge import calibrated_setup, nominal_setup

    assert calibrated_setup(nominal_setup(truth), rn).screen.cover_glass == rn.glass


def test_setups_do_not_leak_the_truths_glass_and_toml_keys():
    """nominal_setup drops the truth's glass (unless the nominal declares one); the
    [calibration] fit_glass_* keys round-trip through TOML and reject non-booleans."""
    from pmdsim.calibration.setup_bridge import nominal_setup
    from pmdsim.errors import SetupError
    from pmdsim.setup import parse_setup

    truth = default_setup().with_cover_glass(3.0, 1.52)
    assert not nominal_setup(truth).screen.cover_glass.present
    assert nominal_setup(truth, CoverGlass(1.0, 1.5)).screen.cover_glass == CoverGlass(1.0, 1.5)
    doc = truth.to_dict()
    doc["calibration"]["fit_glass_thickness"] = True
    s = parse_setup(doc)
    assert s.calibration.fit_glass_thickness and not s.calibration.fit_glass_index
    assert parse_setup(s.to_dict()).calibration == s.calibration
    doc["calibration"]["fit_glass_index"] = 1
    with pytest.raises(SetupError, match="calibration.fit_glass_index must be true or false"):
        parse_setup(doc)


def test_experiment4_glass_rows():
    """Experiment 4's glass rows run (truth with a 1.1 mm glass, 3 × 3 free screen) and fitting
    the glass thickness lowers the error of ignoring it. (At downsample 16 both are near the
    8-bit floor, ≈ 0.01 µm RMS, whose level varies between cases by ≈ 0.005 µm: this checks the
    rows and the direction, not the size.)"""
    from pmdsim.studies.experiment4 import EFFECTS, run_experiment4

    assert EFFECTS["glass_ignored"].glass_mm == EFFECTS["glass_modelled"].glass_mm == 1.1
    records, _ = run_experiment4(default_setup(), ["glass_ignored", "glass_modelled"], downsample=16)
    by = {(r["effect"], r["camera"]): r["rms_um"] for r in records}
    for cam in default_setup().cameras:
        assert by[("glass_modelled", cam)] < by[("glass_ignored", cam)], by


def test_api_calibrate_fits_the_glass_the_setup_declares(traced_glass):
    """pmdsim.calibrate with a nominal setup declaring a 1 mm glass and [calibration]
    fit_glass_thickness = true: the result's glass is the fitted 1.1 mm (exact data)."""
    from dataclasses import replace

    import pmdsim

    truth, obs = traced_glass
    nominal = truth.with_cover_glass(1.0, 1.52)
    nominal = replace(nominal, calibration=replace(nominal.calibration, fit_glass_thickness=True))
    r = pmdsim.calibrate(obs, nominal)
    assert r.converged and r.glass_free == (True, False)
    assert abs(r.glass.thickness_mm - 1.1) < 1e-4, r.glass
