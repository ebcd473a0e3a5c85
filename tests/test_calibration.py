"""Holistic calibration with a planar mirror (paper §4), against truths the calibration did not make.

The truth is simulated with pmdsim's ray tracer (camera → bounded planar mirror → screen), an
independent forward model: the calibration itself mirrors the screen point across the plane and
projects it. The setup is the paper's Table 1 (cameras binned for speed) with non-zero lens
distortion and slightly different intrinsics per camera, and the paper's 16 mirror poses: on the
table, three lifts, and ±1, ±2, ±3° tilts about the mirror's x and y axes.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from pmdsim.geometry.transform import rotation_angle_rad

from pmdsim.calibration import (
    PARAMETER_UNITS,
    CalibrationDataError,
    CalibrationDegenerateError,
    CalibrationError,
    CalibrationState,
    CameraParams,
    MirrorPlane,
    Observations,
    calibrate,
    nominal_state,
    observations_from_mapping,
    perturbed_state,
    residuals_and_jacobian,
)
from pmdsim.errors import PmdsimError
from pmdsim.setup import CameraSetup, default_setup
from pmdsim.geometry.surface import PlaneSurface, SplineSurface
from pmdsim.simulation.trace import trace_camera
from pmdsim.geometry.transform import RigidTransform

MIRROR = PlaneSurface((0.0, 400.0), (0.0, 400.0))
SCREEN = PlaneSurface((0.0, 708.0), (0.0, 398.0))
MIRROR_CENTRE = np.array([200.0, 200.0, 0.0])  # in the mirror frame; world (0, 0, 0) on the table

# True intrinsics: (fx factor, fy factor, Δppx, Δppy) on Table 1, and distortion, per camera.
TRUE_INTRINSICS = {"left": (1.0, 1.002, 3.0, -2.0), "right": (0.99, 0.995, -4.0, 5.0)}
TRUE_DISTORTION = {
    "left": dict(k1=-0.05, k2=0.02, p1=3e-4, p2=-2e-4),
    "right": dict(k1=-0.04, k2=0.015, p1=-2e-4, p2=1e-4),
}


# ----------------------------------------------------------------------------- truth
def mirror_pose(lift_mm=0.0, angles_deg=(0.0, 0.0, 0.0)) -> RigidTransform:
    """T_world_mirror: the mirror (plane z = 0 of its frame) rotated about its centre, which stays
    at world (0, 0, −lift) under the cameras (world −z points towards the cameras)."""
    r = RigidTransform.from_origin_angles([0.0, 0.0, 0.0], angles_deg).rotation
    return RigidTransform(r, np.array([0.0, 0.0, -lift_mm]) - r @ MIRROR_CENTRE)


def paper_mirror_poses(lifts=(4.0, 8.0, 12.0), tilts=(1.0, 2.0, 3.0)) -> list[RigidTransform]:
    poses = [mirror_pose()]
    poses += [mirror_pose(lift_mm=h) for h in lifts]
    for axis in (0, 1):
        for t in tilts:
            for sign in (1.0, -1.0):
                a = [0.0, 0.0, 0.0]
                a[axis] = sign * t
                poses.append(mirror_pose(angles_deg=a))
    return poses


def truth_setup(binning: int):
    s = default_setup()
    cams = {}
    for name, cs in s.cameras.items():
        fxs, fys, dpx, dpy = TRUE_INTRINSICS[name]
        c = cs.camera
        c = replace(c, fx_px=c.fx_px * fxs, fy_px=c.fy_px * fys, ppx_px=c.ppx_px + dpx,
                    ppy_px=c.ppy_px + dpy, **TRUE_DISTORTION[name])
        cams[name] = CameraSetup(c.binned(binning), cs.pose)
    return replace(s, cameras=cams)


def trace_observations(setup, poses, stride, first_index=0):
    obs = []
    for name, cs in setup.cameras.items():
        rays = cs.camera.sensor_rays()
        for k, T in enumerate(poses):
            m = trace_camera(cs.camera, cs.T_world_cam, T, MIRROR, setup.screen.T_world_screen, SCREEN, rays=rays)
            obs.append(observations_from_mapping(name, first_index + k, m.screen_xy_mm, m.valid, stride=stride))
    return obs


def true_values(setup, poses):
    """Truth computed here (not by the module): T_screen_cam per camera, (n, d) per mirror pose."""
    T_sw = setup.screen.T_world_screen.inv()
    cams = {name: (cs.camera, T_sw @ cs.T_world_cam) for name, cs in setup.cameras.items()}
    planes = []
    for T in poses:
        n = T_sw.rotation @ T.rotation[:, 2]
        planes.append((n, float(n @ T_sw.apply(T.translation))))
    return cams, planes


@pytest.fixture(scope="module")
def exact4():
    """Binned-4 cameras (480 × 300 px), 16 poses, exact correspondences every 4 pixels."""
    setup = truth_setup(4)
    poses = paper_mirror_poses()
    return setup, poses, trace_observations(setup, poses, stride=4)


@pytest.fixture(scope="module")
def exact8():
    """Binned-8 cameras (240 × 150 px), 16 poses, exact correspondences every 4 pixels."""
    setup = truth_setup(8)
    poses = paper_mirror_poses()
    return setup, poses, trace_observations(setup, poses, stride=4)


# ----------------------------------------------------------------------------- model and start
def test_nominal_state_matches_independent_truth(exact8):
    setup, poses, obs = exact8
    state = nominal_state(setup, poses)
    cams, planes = true_values(setup, poses)
    for name, (cam, T) in cams.items():
        assert state.cameras[name].camera == cam
        np.testing.assert_allclose(state.cameras[name].T_screen_cam.as_matrix(), T.as_matrix(), atol=1e-12)
    for mp, (n, d), in zip(state.mirrors, planes):
        s = 1.0 if mp.normal @ n > 0 else -1.0
        np.testing.assert_allclose(mp.normal, s * n, atol=1e-12)
        assert mp.d_mm == pytest.approx(s * d, abs=1e-9)
        # Normals point towards the cameras.
        for cp in state.cameras.values():
            assert mp.normal @ cp.position_mm - mp.d_mm > 0


def test_mirror_model_reproduces_ray_tracer(exact8):
    """At the true parameters the analytic mirror model reproduces the traced pixels."""
    setup, poses, obs = exact8
    r, J, names = residuals_and_jacobian(obs, nominal_state(setup, poses))
    assert np.all(np.isfinite(r))
    assert np.max(np.abs(r)) < 1e-7
    assert J.shape == (r.size, 2 * 14 + 16 * 3) and len(names) == J.shape[1]


def test_perturbed_state_has_the_stated_errors(exact8):
    setup, poses, _ = exact8
    truth = nominal_state(setup, poses)
    p = perturbed_state(truth, np.random.default_rng(3), position_mm=5, angle_deg=2, focal_frac=0.03,
                        pp_px=20, mirror_mm=3, mirror_deg=1)
    for name, cp in truth.cameras.items():
        q = p.cameras[name]
        assert np.linalg.norm(q.position_mm - cp.position_mm) == pytest.approx(5.0)
        ang = rotation_angle_rad(q.T_screen_cam.rotation @ cp.T_screen_cam.rotation.T)
        assert math.degrees(ang) == pytest.approx(2.0)
        assert abs(q.camera.fx_px / cp.camera.fx_px - 1) == pytest.approx(0.03)
        assert abs(q.camera.fy_px / cp.camera.fy_px - 1) == pytest.approx(0.03)
        assert math.hypot(q.camera.ppx_px - cp.camera.ppx_px, q.camera.ppy_px - cp.camera.ppy_px) == pytest.approx(20.0)
        assert (q.camera.k1, q.camera.k2, q.camera.p1, q.camera.p2) == (0.0, 0.0, 0.0, 0.0)
    for a, b in zip(truth.mirrors, p.mirrors):
        assert math.degrees(math.acos(min(1.0, a.normal @ b.normal))) == pytest.approx(1.0)
        assert abs(a.d_mm - b.d_mm) == pytest.approx(3.0)


# ----------------------------------------------------------------------------- Jacobian
FD_STEP = {"fx_px": 1e-3, "fy_px": 1e-3, "ppx_px": 1e-3, "ppy_px": 1e-3, "k1": 1e-6, "k2": 1e-6,
           "p1": 1e-7, "p2": 1e-7, "rotvec_x": 1e-7, "rotvec_y": 1e-7, "rotvec_z": 1e-7,
           "position_x_mm": 1e-4, "position_y_mm": 1e-4, "position_z_mm": 1e-4,
           "tilt_a": 1e-7, "tilt_b": 1e-7, "d_mm": 1e-4}


def test_jacobian_matches_central_differences(exact8):
    setup, poses, obs = exact8
    rng = np.random.default_rng(11)
    small = []
    for o in obs:  # 5 random correspondences per block, with a non-planar screen (random z)
        idx = rng.choice(o.n, size=5, replace=False)
        q = o.q_screen_mm[idx].copy()
        q[:, 2] = rng.uniform(-3.0, 3.0, size=5)
        small.append(Observations(o.camera, o.pose_index, o.uv_px[idx], q))
    truth = nominal_state(setup, poses)
    with_k3 = CalibrationState(
        {n: CameraParams(replace(cp.camera, k3=0.01), cp.T_screen_cam) for n, cp in truth.cameras.items()},
        truth.mirrors)
    states = [
        truth,
        perturbed_state(truth, np.random.default_rng(1), reset_distortion=False),
        perturbed_state(with_k3, np.random.default_rng(2), reset_distortion=False),
        perturbed_state(truth, np.random.default_rng(3), position_mm=20, angle_deg=5, mirror_deg=3),
    ]
    for state in states:
        r, J, names = residuals_and_jacobian(small, state)
        assert names == state.parameter_names()
        assert np.all(np.isfinite(J))
        for j, name in enumerate(names):
            h = FD_STEP[name.split(".")[1]]
            d = np.zeros(len(names))
            d[j] = h
            rp = residuals_and_jacobian(small, state.updated(d))[0]
            rm = residuals_and_jacobian(small, state.updated(-d))[0]
            fd = (rp - rm) / (2 * h)
            err = np.linalg.norm(fd - J[:, j]) / np.linalg.norm(J[:, j])
            assert err < 1e-6, f"{name}: analytic and central-difference columns differ by {err:.2e}"


# ----------------------------------------------------------------------------- exact recovery
def test_exact_data_recovers_truth(exact4):
    setup, poses, obs = exact4
    init = perturbed_state(nominal_state(setup, poses), np.random.default_rng(2024))
    res = calibrate(obs, init)
    assert res.converged, res.reason
    assert res.rms_px < 1e-6
    assert res.n_residuals == 2 * sum(o.n for o in obs)
    assert set(res.rms_px_by_camera_pose) == {(o.camera, o.pose_index) for o in obs}
    assert max(res.rms_px_by_camera_pose.values()) < 1e-6

    cams, planes = true_values(setup, poses)
    for name, (cam, T) in cams.items():
        est, T_est = res.cameras[name]
        for attr in ("fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2"):
            t, e = getattr(cam, attr), getattr(est, attr)
            assert abs(e - t) <= 1e-6 * abs(t), f"{name}.{attr}: {e!r} vs true {t!r}"
        assert est.k3 == 0.0  # held fixed
        assert rotation_angle_rad(T_est.rotation @ T.rotation.T) <= 1e-6
        assert np.max(np.abs(T_est.translation - T.translation)) <= 1e-6 * np.linalg.norm(T.translation)
    for k, (mp, (n, d)) in enumerate(zip(res.mirrors, planes)):
        s = 1.0 if mp.normal @ n > 0 else -1.0
        assert s * mp.normal @ n > 0 and np.linalg.norm(np.cross(mp.normal, n)) <= 1e-6, f"mirror {k} normal"
        assert abs(mp.d_mm - s * d) <= max(1e-6 * abs(d), 1e-6), f"mirror {k} d"

    names = res.parameter_names
    assert len(names) == 2 * 14 + 16 * 3
    assert names[0] == "left.fx_px" and "right.rotvec_z" in names and names[-1] == "mirror15.d_mm"
    assert np.all(res.parameter_std >= 0) and np.all(np.isfinite(res.parameter_std))
    assert 1.0 < res.condition_number < 1e12
    doc = res.to_dict()
    json.dumps(doc)
    assert doc["cameras"]["left"]["fx_px"] == pytest.approx(cams["left"][0].fx_px, rel=1e-6)
    assert doc["parameter_std"]["mirror3.d_mm"] == res.std("mirror3.d_mm")


# ----------------------------------------------------------------------------- uncertainties
def test_reported_std_matches_monte_carlo_spread(exact8):
    """σ = 5 µm Gaussian noise on (x_q, y_q): the reported standard deviations agree with the
    spread of the estimates over 10 noise seeds (deviation from the truth) within 35 %."""
    setup, poses, obs = exact8
    cams, _ = true_values(setup, poses)
    truth = nominal_state(setup, poses)
    checked = [f"{c}.{p}" for c in cams for p in ("fx_px", "fy_px", "position_x_mm", "position_y_mm", "position_z_mm")]
    devs, stds = [], []
    for seed in range(10):
        rng = np.random.default_rng(1000 + seed)
        noisy = []
        for o in obs:
            q = o.q_screen_mm.copy()
            q[:, :2] += rng.normal(scale=0.005, size=(o.n, 2))
            noisy.append(Observations(o.camera, o.pose_index, o.uv_px, q))
        res = calibrate(noisy, perturbed_state(truth, np.random.default_rng(seed)))
        assert res.converged, res.reason
        assert 1e-3 < res.rms_px < 1e-2  # ≈ 5 µm / (1.3 mm screen footprint of a binned pixel)
        row_dev, row_std = [], []
        for name in checked:
            cam, attr = name.split(".")
            est_cam, T_est = res.cameras[cam]
            if attr.startswith("position"):
                axis = "xyz".index(attr[9])
                row_dev.append(T_est.translation[axis] - cams[cam][1].translation[axis])
            else:
                row_dev.append(getattr(est_cam, attr) - getattr(cams[cam][0], attr))
            row_std.append(res.std(name))
        devs.append(row_dev)
        stds.append(row_std)
    observed = np.sqrt(np.mean(np.square(devs), axis=0))
    predicted = np.sqrt(np.mean(np.square(stds), axis=0))
    ratio = observed / predicted
    bad = {n: round(float(r), 3) for n, r in zip(checked, ratio) if not 0.65 <= r <= 1.35}
    assert not bad, f"observed / reported standard deviation outside 1 ± 0.35: {bad}"


# ----------------------------------------------------------------------------- bad data
def test_fewer_than_three_poses_is_rejected(exact8):
    setup, poses, obs = exact8
    state = nominal_state(setup, poses)
    few = [o for o in obs if o.camera == "right" or o.pose_index < 2]
    with pytest.raises(CalibrationDataError, match=r"camera 'left'.* 2 mirror pose\(s\).*at least 3"):
        calibrate(few, state)
    state2 = nominal_state(setup, poses[:2])
    with pytest.raises(CalibrationDataError, match="at least 3"):
        calibrate([o for o in obs if o.pose_index < 2], state2)


def test_pose_whose_reflection_misses_the_screen_is_named(exact8):
    """A mirror tilted by 40° about its y axis: the left camera's reflections almost all miss
    the screen (a handful of valid pixels), the right camera's do not."""
    setup, poses, obs = exact8
    steep = mirror_pose(angles_deg=(0.0, -40.0, 0.0))
    extra = trace_observations(setup, [steep], stride=4, first_index=len(poses))
    n_left = [o.n for o in extra if o.camera == "left"][0]
    assert 0 < n_left < 20 and [o.n for o in extra if o.camera == "right"][0] > 100
    state = nominal_state(setup, list(poses) + [steep])
    with pytest.raises(CalibrationDataError, match=rf"camera 'left', mirror pose 16: only {n_left} valid correspondences.*misses the screen"):
        calibrate(obs + extra, state)


def test_all_invalid_and_nan_inputs_are_rejected(exact8):
    setup, poses, obs = exact8
    state = nominal_state(setup, poses)
    nan_map = np.full((150, 240, 2), np.nan)
    empty = [observations_from_mapping(o.camera, o.pose_index, nan_map, np.isfinite(nan_map).all(-1))
             for o in obs]
    assert all(o.n == 0 for o in empty)
    with pytest.raises(CalibrationDataError, match="all correspondences are invalid"):
        calibrate(empty, state)
    with pytest.raises(CalibrationDataError, match=r"camera 'left', mirror pose 3: 36000 pixels marked valid have NaN"):
        observations_from_mapping("left", 3, nan_map, np.ones((150, 240), bool), stride=1)
    q = obs[0].q_screen_mm.copy()
    q[5, 0] = np.nan
    with pytest.raises(CalibrationDataError, match=r"camera 'left', mirror pose 0: 1 of .* NaN"):
        Observations("left", 0, obs[0].uv_px, q)


def test_unknown_camera_or_pose_is_rejected(exact8):
    setup, poses, obs = exact8
    state = nominal_state(setup, poses)
    o = obs[0]
    with pytest.raises(CalibrationDataError, match="camera 'middle'.*not in the initial state"):
        calibrate(obs + [Observations("middle", 0, o.uv_px, o.q_screen_mm)], state)
    with pytest.raises(CalibrationDataError, match="mirror pose 16"):
        calibrate(obs + [Observations("left", 16, o.uv_px, o.q_screen_mm)], state)
    with pytest.raises(CalibrationDataError, match=r"mirror pose\(s\) \[16\].*no observations"):
        calibrate(obs, nominal_state(setup, list(poses) + [poses[0]]))


def internal_units(names) -> np.ndarray:
    return np.array([PARAMETER_UNITS[n.split(".")[1]] for n in names])


def fraction_in_span(mode: np.ndarray, directions: np.ndarray, names) -> float:
    """|projection| / |mode| of a parameter direction (natural units) onto the span of the columns
    of ``directions``, both measured in internal units."""
    u = internal_units(names)
    q, _ = np.linalg.qr(directions / u[:, None])
    m = mode / u
    return float(np.linalg.norm(q.T @ m) / np.linalg.norm(m))


def parallel_planes_mode(names, truth, n_mirrors) -> np.ndarray:
    """The invisible motion of parallel mirror planes (derived here, not by the module): every
    camera centre moves by t along the common normal n (oriented towards the cameras) and every
    plane by t/2 along it — the virtual camera c − 2(n·c − d)n stays where it is."""
    m = np.zeros(len(names))
    n = truth.mirrors[0].normal
    for cam in truth.cameras:
        for ax in range(3):
            m[names.index(f"{cam}.position_{'xyz'[ax]}_mm")] = n[ax]
    for k in range(n_mirrors):
        m[names.index(f"mirror{k}.d_mm")] = 0.5
    return m


@pytest.mark.parametrize("start", ["nominal", "perturbed"])
def test_parallel_mirror_planes_are_reported_as_degenerate(start):
    """Only lifts (all mirror planes parallel): moving both cameras along the normal and every
    plane by half that is invisible. The error names these parameters and the cause, and its
    free direction is that analytic motion; it is not noise."""
    setup = truth_setup(8)
    poses = paper_mirror_poses(tilts=())
    obs = trace_observations(setup, poses, stride=4)
    truth = nominal_state(setup, poses)
    state = truth if start == "nominal" else perturbed_state(truth, np.random.default_rng(7))
    with pytest.raises(CalibrationDegenerateError) as info:
        calibrate(obs, state)
    err = info.value
    msg = str(err)
    assert "condition number" in msg and "all mirror planes are parallel" in msg and "only lifts" in msg
    assert "parallel" in err.cause and err.condition_number > 1e12
    named = msg.split("Badly determined: ")[1].split(". Cause")[0].split(", ")
    assert tuple(named) == err.parameters
    for p in ("left.position_z_mm", "right.position_z_mm", "mirror0.d_mm", "mirror3.d_mm"):
        assert p in named, p
    assert not [p for p in named if p.split(".")[1] in ("fx_px", "fy_px", "k1", "rotvec_x", "tilt_a")]
    names = list(err.parameter_names)
    assert err.directions.shape[0] == len(names) == 2 * 14 + 4 * 3
    assert fraction_in_span(parallel_planes_mode(names, truth, len(poses)), err.directions, names) > 0.99


def pencil_mode(names, truth, line_point, line_dir) -> np.ndarray:
    """The invisible motion of mirror planes that all contain one line L (derived here): rotate
    the cameras by 2ε and every plane by ε about L. A reflection S across a plane containing L
    reverses rotations about L (S·Rot(ε) = Rot(−ε)·S), so every virtual camera
    Rot(ε)·S·Rot(−ε)·Rot(2ε)·T = S·T stays where it is. In the increments of the calibration:
    rotvec += 2ε·ℓ, centre += 2ε·ℓ × (c − p0); tilt (a, b) = ε·(ℓ × n)·(e1, e2),
    d += ε·(ℓ × n)·p0 (the plane keeps containing p0)."""
    m = np.zeros(len(names))
    for cam, cp in truth.cameras.items():
        dc = 2.0 * np.cross(line_dir, cp.position_mm - line_point)
        for ax in range(3):
            m[names.index(f"{cam}.rotvec_{'xyz'[ax]}")] = 2.0 * line_dir[ax]
            m[names.index(f"{cam}.position_{'xyz'[ax]}_mm")] = dc[ax]
    for k, mp in enumerate(truth.mirrors):
        dn = np.cross(line_dir, mp.normal)
        e1, e2 = mp.tangent_basis()
        m[names.index(f"mirror{k}.tilt_a")] = dn @ e1
        m[names.index(f"mirror{k}.tilt_b")] = dn @ e2
        m[names.index(f"mirror{k}.d_mm")] = dn @ line_point
    return m


@pytest.mark.parametrize("start", ["nominal", "perturbed"])
def test_mirror_planes_through_one_line_are_reported_as_degenerate(start):
    """Tilts about the mirror's x axis only, no lifts: every plane contains the mirror's x axis
    through its centre (a pencil of planes, known to be degenerate for mirror-based calibration,
    Sturm & Bonfort 2006). Rotating the cameras by 2ε and the planes by ε about that line is
    invisible; the error names the line and the parameters, and its free direction is that motion."""
    setup = truth_setup(8)
    poses = [mirror_pose()] + [mirror_pose(angles_deg=(s * t, 0.0, 0.0)) for t in (1.0, 2.0, 3.0) for s in (1, -1)]
    obs = trace_observations(setup, poses, stride=4)
    truth = nominal_state(setup, poses)
    state = truth if start == "nominal" else perturbed_state(truth, np.random.default_rng(8))
    with pytest.raises(CalibrationDegenerateError) as info:
        calibrate(obs, state)
    err = info.value
    assert "contain one common line" in err.cause and "tilted about one axis only" in str(err)
    # The line: the mirror's x axis through its centre (world origin), in the screen frame.
    T_sw = setup.screen.T_world_screen.inv()
    p0 = T_sw.apply(np.zeros(3))
    ell = T_sw.rotation @ np.array([1.0, 0.0, 0.0])
    for cam in ("left", "right"):
        assert f"{cam}.rotvec_x" in err.parameters
    assert "mirror0.tilt_b" in err.parameters or "mirror0.tilt_a" in err.parameters
    assert not [p for p in err.parameters if p.split(".")[1] in ("fx_px", "fy_px", "k1", "k2", "p1", "p2")]
    names = list(err.parameter_names)
    assert fraction_in_span(pencil_mode(names, truth, p0, ell), err.directions, names) > 0.99
    # The parallel-planes motion is not what is free here.
    assert fraction_in_span(parallel_planes_mode(names, truth, len(poses)), err.directions, names) < 0.5


def add_screen_noise(obs, sigma_mm, seed):
    rng = np.random.default_rng(seed)
    out = []
    for o in obs:
        q = o.q_screen_mm.copy()
        q[:, :2] += rng.normal(scale=sigma_mm, size=(o.n, 2))
        out.append(Observations(o.camera, o.pose_index, o.uv_px, q))
    return out


#: Prior standard deviations: the errors of the nominal start values (experiments.INITIAL_ERRORS).
PRIOR_STD = {"*.position_?_mm": 5.0, "*.rotvec_?": math.radians(2.0), "mirror*.d_mm": 3.0,
             "mirror*.tilt_?": math.radians(1.0), "*.ppx_px": 20.0, "*.ppy_px": 20.0}


def test_nearly_parallel_planes_give_a_result_that_says_so(exact8):
    """Lifts and two tilts of only 0.05°: below the condition limit, so a result is returned,
    but the cameras' distance along the normal is hardly determined. With 5 µm noise on (x_q,
    y_q) its reported σ is several mm — not better than the start values' 5 mm prior — and the
    report says so: the weak directions contain the parallel-planes motion (derived here), and
    ``poorly_determined`` names the positions. The paper's 16 poses, same noise: nothing flagged."""
    setup = truth_setup(8)
    poses = paper_mirror_poses(tilts=()) + [mirror_pose(angles_deg=(0.05, 0.0, 0.0)),
                                            mirror_pose(angles_deg=(0.0, 0.05, 0.0))]
    truth = nominal_state(setup, poses)
    obs = add_screen_noise(trace_observations(setup, poses, stride=4), 0.005, seed=1)
    # Started at the truth: even so Levenberg–Marquardt crawls along the weak direction (≈ 90
    # iterations; more from perturbed start values) — what is checked here is the report.
    res = calibrate(obs, truth, max_iter=300)
    assert res.converged, res.reason
    assert 1e10 < res.condition_number < 1e12
    names = list(res.parameter_names)
    assert len(res.weak_directions) == 3
    assert res.weak_directions[0].relative_eigenvalue == pytest.approx(1.0 / res.condition_number, rel=1e-6)
    weak = np.array([wd.direction for wd in res.weak_directions]).T
    assert fraction_in_span(parallel_planes_mode(names, truth, len(poses)), weak, names) > 0.99
    assert res.weak_directions[0].std_internal > 1.0  # > 1 mm / 1 mrad along the worst direction
    assert res.std_inflation.shape == (len(names),) and np.all(res.std_inflation >= 1.0 - 1e-9)
    assert res.std_inflation[names.index("left.position_z_mm")] > 1e4
    bad = res.poorly_determined(PRIOR_STD)
    for cam in ("left", "right"):
        assert f"{cam}.position_z_mm" in bad
        sd, prior = bad[f"{cam}.position_z_mm"]
        assert sd == res.std(f"{cam}.position_z_mm") and prior == 5.0 and sd > 1.5
    assert not [n for n in bad if n.split(".")[1] in ("ppx_px", "ppy_px", "tilt_a", "tilt_b")]
    report = res.determination_report(PRIOR_STD)
    assert "weak direction 1" in report and "poorly determined" in report and "left.position_z_mm" in report
    doc = res.to_dict()
    json.dumps(doc)
    assert len(doc["weak_directions"]) == 3 and doc["std_inflation"]["left.position_z_mm"] > 1e4

    setup8, poses16, obs16 = exact8
    good = calibrate(add_screen_noise(obs16, 0.005, seed=1), nominal_state(setup8, poses16))
    assert good.poorly_determined(PRIOR_STD) == {}
    assert "every parameter with a prior is determined" in good.determination_report(PRIOR_STD)
    assert good.std("left.position_z_mm") < 0.02 * res.std("left.position_z_mm")
    with pytest.raises(ValueError, match="positive"):
        good.poorly_determined({"*.fx_px": 0.0})


# ----------------------------------------------------------------------------- non-convergence
def test_non_convergence_is_reported(exact8):
    setup, poses, obs = exact8
    init = perturbed_state(nominal_state(setup, poses), np.random.default_rng(5))
    res = calibrate(obs, init, max_iter=1)
    assert not res.converged
    assert res.iterations == 1
    assert "maximum number of iterations (1)" in res.reason
    assert res.rms_px < res.rms_history_px[0]
    with pytest.raises(CalibrationError, match="did not converge: maximum number of iterations") as info:
        calibrate(obs, init, max_iter=1, raise_on_failure=True)
    assert isinstance(info.value, PmdsimError) and isinstance(info.value, RuntimeError)
    assert issubclass(CalibrationDataError, ValueError) and issubclass(CalibrationDataError, PmdsimError)


# ----------------------------------------------------------------------------- helpers
def test_observations_from_mapping_subsamples_and_uses_the_screen_model():
    h, w = 10, 13
    v, u = np.mgrid[0:h, 0:w]
    xy = np.stack([u * 10.0 + 1.0, v * 20.0 + 2.0], axis=-1)
    valid = np.ones((h, w), bool)
    valid[4, 6] = False
    xy[4, 6] = np.nan
    o = observations_from_mapping("left", 2, xy, valid, stride=2)
    us, vs = np.arange(0, w, 2), np.arange(0, h, 2)
    assert o.n == us.size * vs.size - 1
    assert set(map(tuple, o.uv_px.astype(int))) == {(a, b) for a in us for b in vs} - {(6, 4)}
    np.testing.assert_allclose(o.q_screen_mm[:, 0], o.uv_px[:, 0] * 10 + 1)
    np.testing.assert_allclose(o.q_screen_mm[:, 1], o.uv_px[:, 1] * 20 + 2)
    assert np.all(o.q_screen_mm[:, 2] == 0)
    bulge = SplineSurface.from_bulge((0.0, 75.0, 150.0), (0.0, 100.0, 200.0), 3.0)
    o2 = observations_from_mapping("left", 2, xy, valid, stride=2, screen_surface=bulge)
    np.testing.assert_allclose(o2.q_screen_mm[:, 2], bulge.height(o2.q_screen_mm[:, 0], o2.q_screen_mm[:, 1]))
    assert o2.q_screen_mm[:, 2].max() > 1.0


def test_mirror_plane_value_object():
    mp = MirrorPlane([0.0, 0.0, 2.0], 5.0)
    np.testing.assert_allclose(mp.normal, [0, 0, 1])
    e1, e2 = mp.tangent_basis()
    np.testing.assert_allclose([e1 @ mp.normal, e2 @ mp.normal, e1 @ e2], 0, atol=1e-15)
    np.testing.assert_allclose(mp.reflect([1.0, 2.0, 3.0]), [1.0, 2.0, 7.0])
    flipped = mp.oriented_towards([0.0, 0.0, 0.0])
    np.testing.assert_allclose(flipped.normal, [0, 0, -1])
    assert flipped.d_mm == -5.0
    with pytest.raises(CalibrationDataError):
        MirrorPlane([0.0, 0.0, 0.0], 1.0)
