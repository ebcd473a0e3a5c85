"""The calibration solver (geodesic Levenberg–Marquardt, tiled JᵀJ accumulation) against
references it did not make: scipy's MINPACK Levenberg–Marquardt on an independent numpy forward
model, dense Jacobians from :func:`residuals_and_jacobian` (itself checked against central
differences in test_calibration.py), central second differences for the geodesic acceleration,
and the truth of data simulated by pmdsim's ray tracer.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import scipy.optimize

from pmdsim.calibration import Observations, calibrate, nominal_state, perturbed_state, residuals_and_jacobian
from pmdsim.calibration import solver as S
from pmdsim.calibration.model import _CAM_UNITS, _MIR_UNITS, SCREEN_HEIGHT_UNIT_MM
from pmdsim.calibration.screen import ScreenModel
from pmdsim.geometry.surface import SplineSurface
from pmdsim.geometry.transform import rotation_angle_rad

from test_calibration import MIRROR, SCREEN, paper_mirror_poses, trace_camera, true_values, truth_setup
from pmdsim.calibration import observations_from_mapping

# A 3 mm bulge of the screen seen through a planar screen model: a large-residual problem with
# the curved valley (cameras and mirror planes rotating together) that slows plain LM down.
BULGED = SplineSurface.from_bulge(np.linspace(0.0, 708.0, 3), np.linspace(0.0, 398.0, 3), 3.0)


def _observations(setup, poses, screen, stride):
    obs = []
    for name, cs in setup.cameras.items():
        rays = cs.camera.sensor_rays()
        for k, T in enumerate(poses):
            m = trace_camera(cs.camera, cs.T_world_cam, T, MIRROR, setup.screen.T_world_screen, screen, rays=rays)
            obs.append(observations_from_mapping(name, k, m.screen_xy_mm, m.valid, stride=stride))
    return obs


@pytest.fixture(scope="module")
def bulged8():
    """Binned-8 cameras, 16 poses, correspondences every 6 px of a 3 mm-bulged screen taken as
    planar (q_z = 0)."""
    setup = truth_setup(8)
    poses = paper_mirror_poses()
    return setup, poses, _observations(setup, poses, BULGED, stride=6)


def _units(state):
    return np.concatenate([np.tile(_CAM_UNITS, len(state.cameras)), np.tile(_MIR_UNITS, len(state.mirrors)),
                           np.full(state.n_screen, SCREEN_HEIGHT_UNIT_MM)])


def _numpy_residuals(obs, state):
    """Independent forward model: mirror the screen point, transform, project with
    :meth:`Camera.project` (predicted − observed, px), in the order of ``obs``. The points of
    all poses of one camera are projected in one call (the same per-point arithmetic; scipy's
    finite differences call this thousands of times)."""
    p_cam = []
    for o in obs:
        cp = state.cameras[o.camera]
        mp = state.mirrors[o.pose_index]
        q = o.q_screen_mm
        q_virtual = q - 2.0 * (q @ mp.normal - mp.d_mm)[:, None] * mp.normal
        R, c = cp.T_screen_cam.rotation, cp.T_screen_cam.translation
        p_cam.append((q_virtual - c) @ R)
    out = [None] * len(obs)
    for name in dict.fromkeys(o.camera for o in obs):
        idx = [i for i, o in enumerate(obs) if o.camera == name]
        uv = state.cameras[name].camera.project(np.concatenate([p_cam[i] for i in idx]))
        ends = np.cumsum([len(p_cam[i]) for i in idx])
        for i, part in zip(idx, np.split(uv, ends[:-1])):
            out[i] = (part - obs[i].uv_px).ravel()
    return np.concatenate(out)


def test_same_optimum_as_scipy_minpack(bulged8):
    """Same problem, same start: the solver and scipy.optimize.least_squares(method="lm")
    (MINPACK, 3-point finite-difference Jacobian of the numpy model) reach the same optimum.

    Bound: the solver stops when the Gauss–Newton model predicts a decrease gᵀ(JᵀJ)⁻¹g ≤
    ftol·cost, i.e. the Gauss–Newton step, ≈ the way to the optimum, has length
    √(ftol·cost) in the metric ‖J·Δ‖. So the two solutions may differ by ‖J·Δ‖ ≤ √(ftol·cost)
    (MINPACK's own stop is far tighter), and their costs by ≤ ftol·cost."""
    setup, poses, obs = bulged8
    obs = _subset(obs, 8)  # ≈ 1000 correspondences: scipy's finite differences are slow
    start = perturbed_state(nominal_state(setup, poses), np.random.default_rng(7))
    ftol = 1e-12
    res = calibrate(obs, start, ftol=ftol)
    assert res.converged, res.reason
    units = _units(start)

    sp = scipy.optimize.least_squares(lambda x: _numpy_residuals(obs, start.updated(x * units)),
                                      np.zeros(start.n_parameters), method="lm", jac="3-point",
                                      ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=20000)
    assert sp.success, sp.message
    ref_state = start.updated(sp.x * units)
    cost_ref = float(np.sum(_numpy_residuals(obs, ref_state) ** 2))
    cost = float(np.sum(_numpy_residuals(obs, res.state) ** 2))
    assert cost == pytest.approx(res.rms_px ** 2 * res.n_residuals, rel=1e-12)  # the same model
    assert abs(cost - cost_ref) <= ftol * cost_ref
    # The distance between the two solutions in the metric of the data, ‖J·Δ‖.
    delta = res.state.increment_to(ref_state)
    _, jac, _ = residuals_and_jacobian(obs, res.state)
    dist = float(np.linalg.norm(jac @ delta))
    assert dist <= math.sqrt(ftol * cost_ref), (dist, math.sqrt(ftol * cost_ref))
    # And per parameter, in units of the solver's reported standard deviation.
    assert np.max(np.abs(delta) / res.parameter_std) < 1e-3


def test_seeded_recovery_from_far_start():
    """Exact correspondences from the ray tracer, start values 3× the default perturbation:
    the truth is recovered to 1e-7 relative."""
    setup = truth_setup(8)
    poses = paper_mirror_poses()
    from test_calibration import trace_observations

    obs = trace_observations(setup, poses, stride=4)
    start = perturbed_state(nominal_state(setup, poses), np.random.default_rng(99), position_mm=15.0,
                            angle_deg=3.0, focal_frac=0.05, pp_px=30.0, mirror_mm=6.0, mirror_deg=2.0)
    res = calibrate(obs, start)
    assert res.converged, res.reason
    assert res.rms_px < 1e-6
    cams, planes = true_values(setup, poses)
    for name, (cam, T) in cams.items():
        est, T_est = res.cameras[name]
        for attr in ("fx_px", "fy_px", "ppx_px", "ppy_px"):
            assert abs(getattr(est, attr) - getattr(cam, attr)) <= 1e-7 * abs(getattr(cam, attr)), (name, attr)
        for attr in ("k1", "k2", "p1", "p2"):
            assert abs(getattr(est, attr) - getattr(cam, attr)) <= 1e-7, (name, attr)
        assert rotation_angle_rad(T_est.rotation @ T.rotation.T) <= 1e-7
        assert np.max(np.abs(T_est.translation - T.translation)) <= 1e-7 * np.linalg.norm(T.translation)
    for mp, (n, d) in zip(res.mirrors, planes):
        s = 1.0 if mp.normal @ n > 0 else -1.0
        assert np.linalg.norm(np.cross(mp.normal, n)) <= 1e-7
        assert abs(mp.d_mm - s * d) <= 1e-7 * max(abs(d), 1.0)


def _subset(obs, every):
    return [Observations(o.camera, o.pose_index, o.uv_px[::every], o.q_screen_mm[::every]) for o in obs]


@pytest.mark.parametrize("screen_grid", [0, 5])
def test_normal_equations_match_dense_jacobian(bulged8, screen_grid):
    """JᵀJ and Jᵀr accumulated by the tiled kernel equal those of the dense Jacobian of
    :func:`residuals_and_jacobian` (internal units), with and without free screen heights."""
    setup, poses, obs = bulged8
    obs = _subset(obs, 3)
    state = perturbed_state(nominal_state(setup, poses), np.random.default_rng(3))
    if screen_grid:
        gx, gy = SCREEN.kernel.grid_x, SCREEN.kernel.grid_y
        free = np.zeros((screen_grid, screen_grid), dtype=bool)
        free[1:-1, 1:-1] = True
        heights = np.random.default_rng(4).uniform(-1.0, 1.0, (screen_grid, screen_grid)) * free
        screen = ScreenModel(np.linspace(gx[0], gx[-1], screen_grid), np.linspace(gy[0], gy[-1], screen_grid),
                             heights, free)
        state = replace(state, screen=screen)
    data = S._pack(obs, state, 20)
    cost, _, bad, a, g = S._evaluate(data, state, True)
    assert not bad.any()
    r, jac, _ = residuals_and_jacobian(obs, state)
    ji = jac * _units(state)
    np.testing.assert_allclose(cost, r @ r, rtol=1e-12)
    scale = np.sqrt(np.outer(np.diag(ji.T @ ji), np.diag(ji.T @ ji)))
    assert np.max(np.abs(a - ji.T @ ji) / scale) < 1e-12
    assert np.max(np.abs(g - ji.T @ r) / np.sqrt(np.diag(ji.T @ ji) * (r @ r))) < 1e-12


def test_acceleration_matches_central_second_difference(bulged8):
    """Jᵀ·r_vv of the geodesic acceleration kernel against the dense Jacobian times the
    central second difference (r(x + tδ) − 2r(x) + r(x − tδ))/t² of the residuals (numpy model):
    the kernel's one-sided difference with step h agrees to O(h)."""
    setup, poses, obs = bulged8
    obs = _subset(obs, 3)
    state = perturbed_state(nominal_state(setup, poses), np.random.default_rng(5))
    units = _units(state)
    delta = np.random.default_rng(6).normal(size=state.n_parameters) * units
    data = S._pack(obs, state, 20)
    r0, jac, _ = residuals_and_jacobian(obs, state)
    t = 1e-3
    r_vv = (_numpy_residuals(obs, state.updated(t * delta)) - 2.0 * r0
            + _numpy_residuals(obs, state.updated(-t * delta))) / t ** 2
    ref = (jac * units).T @ r_vv
    errs = []
    for h in (0.1, 0.01):
        got = S._acceleration_gradient(data, state, delta, h)
        errs.append(np.linalg.norm(got - ref) / np.linalg.norm(ref))
    assert errs[1] < 0.02 and errs[1] < 0.2 * errs[0], errs  # first order in h
