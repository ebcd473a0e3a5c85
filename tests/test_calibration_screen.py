"""Holistic calibration with a non-planar pattern screen (the founding paper's open question, §5):
the screen's control heights are estimated jointly with the cameras and the mirror planes.

Truths the calibration did not make: the correspondences are traced by pmdsim's ray tracer
(camera → bounded planar mirror → *bulged* spline screen, found by ray–surface intersection),
and the true screen is ``SplineSurface.from_bulge`` (Δh = 3 mm at the centre of a 3 × 3 grid,
border 0). The calibration only sees the pixels and the decoded pattern coordinates (x_q, y_q);
the heights come from its own screen model (tensor-product cardinal basis weights).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from pmdsim.geometry.transform import rotation_angle_rad

from pmdsim.calibration import (
    CalibrationDataError,
    CalibrationDegenerateError,
    CalibrationState,
    Observations,
    ScreenModel,
    calibrate,
    nominal_state,
    observations_from_mapping,
    perturbed_state,
    residuals_and_jacobian,
)
from pmdsim.setup import CameraSetup, default_setup
from pmdsim.geometry.surface import SplineSurface
from pmdsim.simulation.trace import trace_camera

GX3, GY3 = [0.0, 354.0, 708.0], [0.0, 199.0, 398.0]
BULGE_MM = 3.0
TRUE_SCREEN = SplineSurface.from_bulge(GX3, GY3, BULGE_MM)
GX5, GY5 = np.linspace(0.0, 708.0, 5), np.linspace(0.0, 398.0, 5)
GX9, GY9 = np.linspace(0.0, 708.0, 9), np.linspace(0.0, 398.0, 9)


# ----------------------------------------------------------------------------- truth
def binned_setup(binning: int):
    s = default_setup()  # Table 1: true distortion zero
    cams = {n: CameraSetup(cs.camera.binned(binning), cs.pose) for n, cs in s.cameras.items()}
    return replace(s, cameras=cams)


def trace_bulged(setup, stride):
    """Exact (unquantised) correspondences over the bulged screen, all 16 calibration poses."""
    cal = setup.calibration
    mirror = cal.mirror_surface()
    poses = [T for _, T in cal.mirror_poses(setup.sample)]
    obs = []
    for k, T in enumerate(poses):
        for name, cs in setup.cameras.items():
            m = trace_camera(cs.camera, cs.T_world_cam, T, mirror, setup.screen.T_world_screen, TRUE_SCREEN)
            # Planar assumption in the observations (z = 0): the screen model must supply the heights.
            obs.append(observations_from_mapping(name, k, m.screen_xy_mm, m.valid, stride=stride))
    return poses, obs


@pytest.fixture(scope="module")
def bulged():
    """Binned-8 cameras (240 × 150 px), 16 poses, exact correspondences every 2 pixels."""
    setup = binned_setup(8)
    poses, obs = trace_bulged(setup, stride=2)
    truth = nominal_state(setup, poses)  # the simulation's true cameras and planes (screen frame)
    init = perturbed_state(truth, np.random.default_rng(2025))
    return setup, poses, obs, truth, init


@pytest.fixture(scope="module")
def planar_result(bulged):
    _, _, obs, _, init = bulged
    return calibrate(obs, init)


def assert_cameras_match(res, truth, rel=1e-6):
    for name, cp in truth.cameras.items():
        est, T_est = res.cameras[name]
        for attr in ("fx_px", "fy_px", "ppx_px", "ppy_px"):
            t, e = getattr(cp.camera, attr), getattr(est, attr)
            assert abs(e - t) <= rel * abs(t), f"{name}.{attr}: {e!r} vs true {t!r}"
        for attr in ("k1", "k2", "p1", "p2"):  # true value 0
            assert abs(getattr(est, attr)) <= rel, f"{name}.{attr}: {getattr(est, attr)!r} vs true 0"
        T = cp.T_screen_cam
        assert rotation_angle_rad(T_est.rotation @ T.rotation.T) <= rel
        assert np.max(np.abs(T_est.translation - T.translation)) <= rel * np.linalg.norm(T.translation)


# ----------------------------------------------------------------------------- the model
def test_screen_model_free_points_names_and_gauge():
    assert ScreenModel.flat(GX3, GY3).n_free == 1
    assert ScreenModel.flat(GX5, GY5).n_free == 9
    m9 = ScreenModel.flat(GX9, GY9)
    assert m9.n_free == 49
    assert m9.free_names()[0] == "screen.h[1,1]_mm" and m9.free_names()[-1] == "screen.h[7,7]_mm"
    assert ScreenModel.flat(GX3, GY3).free_names() == ["screen.h[1,1]_mm"]
    # A free border point: rejected, named, with the gauge explained.
    free = np.zeros((3, 3), bool)
    free[1, 1] = True
    free[0, 2] = True
    with pytest.raises(CalibrationDataError, match=r"screen\.h\[0,2\]_mm.*piston or tilt.*camera poses and mirror"):
        ScreenModel(GX3, GY3, np.zeros((3, 3)), free)
    with pytest.raises(CalibrationDataError, match="shape"):
        ScreenModel(GX3, GY3, np.zeros((3, 4)), np.zeros((3, 3), bool))
    # The model's height is pmdsim's spline surface (independently implemented in surface.py).
    z = np.random.default_rng(0).normal(size=(5, 5))
    z[[0, -1]] = 0.0
    z[:, [0, -1]] = 0.0
    model = replace(ScreenModel.flat(GX5, GY5), heights_mm=z)
    xy = np.random.default_rng(1).uniform([0, 0], [708, 398], size=(500, 2))
    np.testing.assert_allclose(model.height(xy[:, 0], xy[:, 1]),
                               SplineSurface(GX5, GY5, z).height(xy[:, 0], xy[:, 1]), atol=1e-12)


def test_without_screen_model_nothing_changes(bulged):
    """A screen model with no free heights and zero heights gives the planar residuals and
    Jacobian; decoded (x_q, y_q) only ((M, 2)) are accepted."""
    _, _, obs, truth, init = bulged
    small = [Observations(o.camera, o.pose_index, o.uv_px[:7], o.q_screen_mm[:7, :2]) for o in obs]
    r0, j0, n0 = residuals_and_jacobian(small, init)
    held = ScreenModel(GX3, GY3, np.zeros((3, 3)), np.zeros((3, 3), bool))
    r1, j1, n1 = residuals_and_jacobian(small, replace(init, screen=held))
    assert n0 == n1 and len(n0) == 2 * 14 + 16 * 3
    np.testing.assert_array_equal(r0, r1)
    np.testing.assert_array_equal(j0, j1)


# ----------------------------------------------------------------------------- Jacobian
FD_STEP = {"fx_px": 1e-3, "fy_px": 1e-3, "ppx_px": 1e-3, "ppy_px": 1e-3, "k1": 1e-6, "k2": 1e-6,
           "p1": 1e-7, "p2": 1e-7, "rotvec_x": 1e-7, "rotvec_y": 1e-7, "rotvec_z": 1e-7,
           "position_x_mm": 1e-4, "position_y_mm": 1e-4, "position_z_mm": 1e-4,
           "tilt_a": 1e-7, "tilt_b": 1e-7, "d_mm": 1e-4}
H_STEP_MM = 1e-3


def test_screen_height_jacobian_matches_central_differences(bulged):
    _, _, obs, truth, _ = bulged
    rng = np.random.default_rng(5)
    small = []
    for o in obs:
        idx = rng.choice(o.n, size=4, replace=False)
        small.append(Observations(o.camera, o.pose_index, o.uv_px[idx], o.q_screen_mm[idx]))
    z5 = TRUE_SCREEN.height(*np.meshgrid(GX5, GY5)) + rng.uniform(-1, 1, size=(5, 5)) * ScreenModel.flat(GX5, GY5).free
    states = [
        replace(truth, screen=ScreenModel.flat(GX3, GY3)),
        replace(perturbed_state(truth, np.random.default_rng(1), reset_distortion=False),
                screen=replace(ScreenModel.flat(GX5, GY5), heights_mm=z5)),
        replace(perturbed_state(truth, np.random.default_rng(2), position_mm=20, angle_deg=5, mirror_deg=3),
                screen=replace(ScreenModel.flat(GX9, GY9), heights_mm=0.5 * ScreenModel.flat(GX9, GY9).free)),
    ]
    for state in states:
        r, J, names = residuals_and_jacobian(small, state)
        assert names == state.parameter_names() and len(names) == 76 + state.screen.n_free
        assert np.all(np.isfinite(J))
        for j, name in enumerate(names):
            h = H_STEP_MM if name.startswith("screen.") else FD_STEP[name.split(".")[1]]
            d = np.zeros(len(names))
            d[j] = h
            rp = residuals_and_jacobian(small, state.updated(d))[0]
            rm = residuals_and_jacobian(small, state.updated(-d))[0]
            fd = (rp - rm) / (2 * h)
            err = np.linalg.norm(fd - J[:, j]) / np.linalg.norm(J[:, j])
            assert err < 1e-6, f"{name}: analytic and central-difference columns differ by {err:.2e}"
        # The free heights actually move the residuals.
        screen_cols = [j for j, n in enumerate(names) if n.startswith("screen.")]
        assert np.all(np.linalg.norm(J[:, screen_cols], axis=0) > 0)


# ----------------------------------------------------------------------------- recovery
def test_one_free_height_recovers_the_bulge_and_the_cameras(bulged):
    _, poses, obs, truth, init = bulged
    model = ScreenModel.flat(GX3, GY3)  # central height starts at 0
    res = calibrate(obs, init, screen_model=model)
    assert res.converged, res.reason
    assert res.rms_px < 1e-6
    assert res.screen_model.n_free == 1
    assert abs(res.screen_model.heights_mm[1, 1] - BULGE_MM) < 1e-6
    np.testing.assert_array_equal(res.screen_model.heights_mm[[0, 2]], 0.0)  # border held
    assert_cameras_match(res, truth)
    for mp, tp in zip(res.mirrors, truth.mirrors):
        s = 1.0 if mp.normal @ tp.normal > 0 else -1.0
        assert np.linalg.norm(np.cross(mp.normal, tp.normal)) <= 1e-6
        assert abs(mp.d_mm - s * tp.d_mm) <= 1e-6 * max(1.0, abs(tp.d_mm))
    assert res.parameter_names[-1] == "screen.h[1,1]_mm"
    sd = res.std("screen.h[1,1]_mm")
    assert np.isfinite(sd) and 0 <= sd < 1e-9  # exact data
    assert res.screen_std_mm[1, 1] == sd and res.screen_std_mm[0, 0] == 0
    assert res.state.screen is res.screen_model
    doc = res.to_dict()
    json.dumps(doc)
    assert doc["screen"]["heights_mm"][1][1] == pytest.approx(BULGE_MM, abs=1e-6)


def test_planar_model_leaves_large_residuals(bulged, planar_result):
    """Without the screen model the same data leave a residual orders of magnitude larger (and
    the bulge is absorbed by wrong camera poses)."""
    _, _, obs, truth, init = bulged
    res = planar_result
    assert res.converged, res.reason
    assert res.screen_model is None
    assert res.rms_px > 1e-3  # vs < 1e-6 px with the screen model: ≥ 3 orders of magnitude
    worst = max(np.max(np.abs(res.cameras[n][1].translation - cp.T_screen_cam.translation))
                for n, cp in truth.cameras.items())
    assert worst > 1.0  # mm: the planar model puts the cameras far off


def test_five_by_five_model_reproduces_the_true_screen(bulged):
    """The bulge Δh(1 − u²)(1 − v²) is a product of parabolas, which the 5-point not-a-knot
    spline reproduces exactly: the 9 free heights are the true surface at the grid points."""
    _, _, obs, truth, init = bulged
    res = calibrate(obs, init, screen_model=ScreenModel.flat(GX5, GY5))
    assert res.converged, res.reason
    assert res.rms_px < 1e-6
    expected = TRUE_SCREEN.height(*np.meshgrid(GX5, GY5))
    np.testing.assert_allclose(res.screen_model.heights_mm, expected, atol=1e-6)
    assert res.screen_model.heights_mm[2, 2] == pytest.approx(BULGE_MM, abs=1e-6)
    assert_cameras_match(res, truth)
    assert len(res.parameter_names) == 76 + 9
    assert np.all(np.isfinite(res.parameter_std))


# ----------------------------------------------------------------------------- undetermined heights
def test_unseen_control_heights_are_named(bulged):
    """The left camera only, and only its correspondences on the right part of the screen
    (x_q > 420 mm): the 9 × 9 model's control points at x ≤ 265.5 mm are seen by no
    correspondence — reported by name, not fitted to noise."""
    _, _, obs, _, init = bulged
    cropped = []
    for o in obs:
        keep = o.q_screen_mm[:, 0] > 420.0
        if o.camera == "left":
            cropped.append(Observations(o.camera, o.pose_index, o.uv_px[keep], o.q_screen_mm[keep]))
    left = CalibrationState({"left": init.cameras["left"]}, init.mirrors)
    with pytest.raises(CalibrationDataError) as info:
        calibrate(cropped, left, screen_model=ScreenModel.flat(GX9, GY9))
    msg = str(info.value)
    assert "do not determine" in msg
    for j in range(1, 8):
        for i in (1, 2, 3):
            assert f"screen.h[{j},{i}]_mm" in msg
    for i in (5, 6, 7):
        assert f"screen.h[4,{i}]_mm" not in msg


def test_degenerate_pose_sets_with_a_free_screen_are_reported(bulged):
    """With a free screen the pose set must still determine the cameras: only the base pose
    and the three lifts (all planes parallel, by construction of the poses — not by the code)
    are named as degenerate, with the cause; a single pose is refused before fitting."""
    _, poses, obs, truth, _ = bulged
    labels = [label for label, _ in binned_setup(8).calibration.mirror_poses(binned_setup(8).sample)]
    lifts = [k for k, label in enumerate(labels) if "tilt" not in label]
    assert len(lifts) == 4
    sub = [o for o in obs if o.pose_index in lifts]
    state = CalibrationState(truth.cameras, tuple(truth.mirrors[k] for k in lifts))
    with pytest.raises(CalibrationDegenerateError) as info:
        calibrate(sub, state, screen_model=ScreenModel.flat(GX3, GY3))
    err = info.value
    assert "all mirror planes are parallel" in err.cause
    for cam in ("left", "right"):
        assert f"{cam}.position_z_mm" in err.parameters
    one = [Observations(o.camera, 0, o.uv_px, o.q_screen_mm) for o in obs if o.pose_index == 0]
    with pytest.raises(CalibrationDataError, match=r"only 1 mirror pose\(s\).*at least 3"):
        calibrate(one, CalibrationState(truth.cameras, truth.mirrors[:1]), screen_model=ScreenModel.flat(GX3, GY3))
