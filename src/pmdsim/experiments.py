"""The paper's experiments, end to end through 8-bit images (experiments layer: no I/O).

Experiment 1 (paper §3, Table 2, Fig. 4): simulate the Table 1 setup with a screen bulge Δh,
render the fringe images, decode them, and reconstruct the planar sample with *perfect setup
knowledge* — the true cameras and poses — but a *planar* screen model, as the paper's
evaluation assumes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Iterable

import numpy as np

from .metrics import surface_error_metrics
from .phase import ScreenCoordinates, decode_screen_coordinates
from .reconstruct import Reconstruction, ReconstructionError, reconstruct
from .registration import Registration, register
from .setup import CameraSetup, Setup, default_setup
from .simulation import render_images, trace_setup_camera
from .surface import SplineSurface
from .transform import RigidTransform, rotation_angle_rad

__all__ = [
    "PAPER_TABLE2",
    "CaseResult",
    "binned_setup",
    "decode_images",
    "evaluate_decoded",
    "run_experiment1_case",
    "experiment1",
    "PAPER_TABLE3",
    "INITIAL_ERRORS",
    "simulate_calibration_observations",
    "trace_calibration_poses",
    "observe_calibration_poses",
    "calibrated_setup",
    "run_experiment2_bulge",
    "calibrate_and_reconstruct",
    "nominal_setup",
    "free_screen_model",
    "SCREEN_DEFORMATIONS",
    "screen_deformation",
    "Experiment3Scenario",
    "experiment3_scenarios",
    "run_experiment3",
]

#: The paper's Table 2 (Experiment 1): (Δh mm, camera) → (max height difference µm,
#: max deviation from best-fit plane µm, best-fit plane tilt µrad).
PAPER_TABLE2 = {
    (0.0, "left"): (0.0, 0.0, 0.0),
    (0.0, "right"): (0.0, 0.0, 0.1),
    (1.0, "left"): (49.7, 14.6, 278.5),
    (1.0, "right"): (57.8, 10.8, 259.8),
    (2.0, "left"): (99.6, 29.1, 557.4),
    (2.0, "right"): (115.8, 21.7, 520.3),
    (3.0, "left"): (149.5, 43.7, 836.6),
    (3.0, "right"): (174.1, 32.6, 781.5),
}

Progress = Callable[[str], None]


def binned_setup(setup: Setup, factor: int) -> Setup:
    """The setup with every camera binned ``factor`` × ``factor`` (same field of view)."""
    if factor == 1:
        return setup
    cams = {n: CameraSetup(cs.camera.binned(factor), cs.pose) for n, cs in setup.cameras.items()}
    return replace(setup, cameras=cams)


def decode_images(setup: Setup, images: dict) -> ScreenCoordinates:
    """Decode one camera's in-memory images ``{(direction, period_mm): [image per shift]}``
    with the setup's fringe sequence (N-step phase + hierarchical unwrapping)."""
    seq = setup.patterns.sequence
    full = float(2**setup.patterns.bit_depth - 1)
    xs = [np.stack(images[("x", p)]) for p in seq.periods_x_mm]
    ys = [np.stack(images[("y", p)]) for p in seq.periods_y_mm]
    noise = np.hypot(setup.patterns.noise_std, 1.0 / np.sqrt(12.0))
    return decode_screen_coordinates(xs, seq.periods_x_mm, ys, seq.periods_y_mm, setup.screen.size_mm, full,
                                     noise_std=noise)


@dataclass(frozen=True, eq=False)
class CaseResult:
    """One reconstruction of one camera's data, with its error metrics.

    Only the maps needed for outputs are kept (a full-resolution experiment holds many cases).

    Attributes
    ----------
    height_mm : ndarray (H, W)
        Reconstructed height (sample frame), NaN outside the reconstructed FOV.
    height_error_mm : ndarray (H, W)
        z_reconstructed − z_true at the reconstructed points, NaN outside.
    points_mm : ndarray (H, W, 3), float32
        Reconstructed points (sample frame).
    valid : ndarray (H, W) bool
        Reconstructed pixels.
    """

    bulge_mm: float
    camera: str
    metrics: dict
    method: str
    seed_pixel: tuple[int, int]
    converged: bool
    iterations: int
    height_mm: np.ndarray
    height_error_mm: np.ndarray
    points_mm: np.ndarray
    valid: np.ndarray

    @classmethod
    def from_reconstruction(cls, bulge_mm, camera, rec: Reconstruction, height_error_mm, metrics) -> "CaseResult":
        return cls(float(bulge_mm), camera, metrics, rec.method, tuple(int(v) for v in rec.seed_pixel),
                   bool(rec.converged), int(rec.iterations), rec.height_mm, height_error_mm,
                   rec.points.astype(np.float32), rec.reconstructed)

    def as_record(self) -> dict:
        """The results.json object: the contract keys first, then the rest of the metrics."""
        m = self.metrics
        rec = {
            "bulge_mm": self.bulge_mm,
            "camera": self.camera,
            "max_height_diff_um": m["max_height_diff_um"],
            "max_dev_plane_um": m["max_dev_plane_um"],
            "tilt_urad": m["tilt_urad"],
        }
        rec.update({k: v for k, v in m.items() if k not in rec})
        rec["method"] = self.method
        rec["seed_pixel"] = list(self.seed_pixel)
        rec["converged"] = self.converged
        return rec


def evaluate_decoded(model: Setup, camera: str, decoded: ScreenCoordinates, *, screen_model=None,
                     method: str = "stepwise", seed_pixel=None, seed_height_mm: float = 0.0) -> tuple[Registration, Reconstruction]:
    """Registration with the model's camera and screen pose, then reconstruction (paper §2.5).

    Heights are in the model's sample frame. ``screen_model`` defaults to the plane z = 0 of the
    screen frame over the model's screen grid: the paper's planar-screen assumption.
    """
    cs = model.cameras[camera]
    if screen_model is None:
        scr = model.screen
        screen_model = SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
    reg = register(cs.camera, cs.T_world_cam, screen_model, model.screen.T_world_screen,
                   decoded.screen_xy_mm, decoded.valid, model.sample.T_world_sample)
    if seed_pixel is None:
        # The registered pixel nearest to the image centre.
        centre = np.array([cs.camera.height_px // 2, cs.camera.width_px // 2])
        rows, cols = np.nonzero(reg.valid)
        if rows.size == 0:
            raise ReconstructionError(f"camera {camera!r}: no pixel was decoded and registered; nothing to reconstruct")
        k = int(np.argmin((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2))
        seed_pixel = (int(rows[k]), int(cols[k]))
    rec = reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, method=method,
                      seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
    return reg, rec


def run_experiment1_case(bulge_mm: float, camera: str, *, base: Setup | None = None, downsample: int = 1,
                         method: str = "stepwise", image_sink=None) -> CaseResult:
    """One cell of Table 2: simulate with Δh = ``bulge_mm``, decode the 8-bit images and
    reconstruct with the true cameras and a planar screen model.

    The seed (initial point) of the reconstruction is the camera's central pixel with its true
    height (perfect knowledge). ``image_sink(spec, image)`` receives every rendered image.
    """
    base = default_setup() if base is None else base
    truth = binned_setup(base, downsample).with_bulge(bulge_mm)
    mapping = trace_setup_camera(truth, camera, store_points=True)
    images: dict = {}
    for spec, img in render_images(truth, camera, mapping):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        if image_sink is not None:
            image_sink(spec, img)
    decoded = decode_images(truth, images)
    del images
    model = truth.with_bulge(0.0)  # perfect knowledge, except for the screen: a plane
    cam = truth.cameras[camera].camera
    seed = (cam.height_px // 2, cam.width_px // 2)
    seed_height = float(mapping.p_sample_mm[seed][2])
    if not np.isfinite(seed_height):
        raise RuntimeError(f"the central pixel of camera {camera!r} does not see the sample; cannot seed")
    reg, rec = evaluate_decoded(model, camera, decoded, method=method, seed_pixel=seed, seed_height_mm=seed_height)
    p = rec.points
    true_h = truth.sample.surface.height(p[..., 0], p[..., 1])
    err = np.where(rec.reconstructed, rec.height_mm - true_h, np.nan)
    metrics = surface_error_metrics(p[..., 0], p[..., 1], err)
    return CaseResult.from_reconstruction(bulge_mm, camera, rec, err, metrics)


def experiment1(bulges: Iterable[float] = (0.0, 1.0, 2.0, 3.0), cameras: Iterable[str] | None = None, *,
                base: Setup | None = None, downsample: int = 1, method: str = "stepwise",
                progress: Progress | None = None, image_sink=None) -> list[CaseResult]:
    """Experiment 1 (paper §3): every Δh and camera; see :func:`run_experiment1_case`."""
    base = default_setup() if base is None else base
    cams = list(base.cameras) if cameras is None else list(cameras)
    out = []
    for dh in bulges:
        for cam in cams:
            if progress is not None:
                progress(f"Δh = {dh:g} mm, camera {cam}")
            out.append(run_experiment1_case(dh, cam, base=base, downsample=downsample, method=method,
                                            image_sink=image_sink))
    return out


# ============================================================================ Experiment 2
#: The paper's Table 3 (Experiment 2): (Δh mm, camera) → (max height difference µm,
#: max deviation from best-fit plane µm, best-fit plane tilt µrad).
PAPER_TABLE3 = {
    (0.0, "left"): (0.0, 0.0, 0.0),
    (0.0, "right"): (0.0, 0.0, 0.1),
    (1.0, "left"): (2.6, 1.6, 6.3),
    (1.0, "right"): (2.6, 1.6, 6.5),
    (2.0, "left"): (7.6, 4.3, 20.1),
    (2.0, "right"): (7.2, 4.3, 16.7),
    (3.0, "left"): (8.5, 5.3, 10.5),
    (3.0, "right"): (8.6, 5.2, 11.0),
}

#: Errors of the nominal start values of the calibration (never the true values): camera and
#: mirror positions, angles, focal lengths (fraction), principal points.
INITIAL_ERRORS = dict(position_mm=5.0, angle_deg=2.0, focal_frac=0.03, pp_px=20.0, mirror_mm=3.0, mirror_deg=1.0)


def simulate_calibration_observations(truth: Setup, *, image_sink=None, progress: Progress | None = None,
                                      screen_surface=None):
    """Simulate the calibration poses (paper §4) through 8-bit images and decode them.

    For every mirror pose of ``truth.calibration`` and camera: trace with the mirror as the
    sample, render and quantise the fringe images, decode, and keep every
    ``observation_stride_px``-th pixel's correspondence (pixel ↔ decoded screen point, with the
    screen taken as planar unless ``screen_surface`` is given).

    Returns
    -------
    list of :class:`pmdsim.calibration.Observations`
    """
    from .calibration import observations_from_mapping
    from .trace import trace_camera

    cal = truth.calibration
    mirror = cal.mirror_surface()
    obs = []
    for k, (label, T_world_mirror) in enumerate(cal.mirror_poses(truth.sample)):
        for cam, cs in truth.cameras.items():
            if progress is not None:
                progress(f"pose {k} ({label}), camera {cam}")
            m = trace_camera(cs.camera, cs.T_world_cam, T_world_mirror, mirror, truth.screen.T_world_screen,
                             truth.screen.surface)
            images: dict = {}
            # One independent noise stream per pose (stream 0 is left to the sample's images).
            for spec, img in render_images(truth, cam, m, stream=k + 1):
                images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
                if image_sink is not None:
                    image_sink(k, spec, img)
            dec = decode_images(truth, images)
            # The decoder's σ per pixel: the covariance's noise model (calibration, "Uncertainties").
            obs.append(observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=cal.observation_stride_px,
                                                 screen_surface=screen_surface, screen_std_xy_mm=dec.std_xy_mm))
    return obs


def trace_calibration_poses(truth: Setup, stride: int = 1) -> list:
    """Trace every calibration pose of ``truth`` (mirror as the sample) for every camera,
    keeping every ``stride``-th pixel in both directions.

    Returns
    -------
    list of (pose index, camera name, :class:`~pmdsim.trace.Mapping` of the kept pixels)
    """
    from .trace import Mapping, trace_camera

    cal = truth.calibration
    mirror = cal.mirror_surface()
    out = []
    for k, (_, T_world_mirror) in enumerate(cal.mirror_poses(truth.sample)):
        for cam, cs in truth.cameras.items():
            m = trace_camera(cs.camera, cs.T_world_cam, T_world_mirror, mirror, truth.screen.T_world_screen,
                             truth.screen.surface)
            out.append((k, cam, m if stride == 1 else Mapping(m.screen_xy_mm[::stride, ::stride],
                                                               m.status[::stride, ::stride])))
    return out


def observe_calibration_poses(truth: Setup, traced: list, stride: int = 1) -> list:
    """Render (with ``truth``'s bit depth and noise: one independent stream per pose, as in
    :func:`simulate_calibration_observations`) and decode the pixels of
    :func:`trace_calibration_poses`; every decoded pixel becomes a correspondence, in full-image
    pixel coordinates (u, v multiplied by ``stride``), with the decoder's σ as ``q_std_mm``.

    Rendering only the strided pixels gives the same noise *distribution* as rendering the
    full images and subsampling (the decoder works per pixel), not the same noise values: a
    Monte Carlo over many noise draws is then ``stride``² times cheaper.
    """
    from .calibration import Observations, observations_from_mapping

    obs = []
    for k, cam, m in traced:
        images: dict = {}
        for spec, img in render_images(truth, cam, m, stream=k + 1):
            images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        dec = decode_images(truth, images)
        o = observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=1, screen_std_xy_mm=dec.std_xy_mm)
        obs.append(Observations(cam, k, o.uv_px * stride, o.q_screen_mm, o.q_std_mm))
    return obs


def table_frame_from_plane(nominal: Setup, plane_screen) -> RigidTransform:
    """``T_world_table``: the calibrated table plane (the base mirror plane, screen frame) as a
    sample frame in world coordinates, world being defined by the screen at its nominal pose.

    +z is the plane normal oriented like the nominal sample's +z (away from the cameras), the
    origin the nominal sample origin projected onto the plane, +x the nominal sample x axis
    projected onto the plane.
    """
    T_ws = nominal.screen.T_world_screen
    n = T_ws.apply_vector(plane_screen.normal)
    p0 = T_ws.apply(plane_screen.normal * plane_screen.d_mm)  # a point of the plane
    T_nom = nominal.sample.T_world_sample
    z_nom = T_nom.rotation[:, 2]
    z = n if np.dot(n, z_nom) > 0 else -n
    o = T_nom.translation - np.dot(T_nom.translation - p0, z) * z
    x = T_nom.rotation[:, 0] - np.dot(T_nom.rotation[:, 0], z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return RigidTransform(np.column_stack([x, y, z]), o)


def calibrated_setup(nominal: Setup, result) -> Setup:
    """The setup as the calibration knows it: estimated cameras (poses in the world frame of the
    screen held at its nominal pose — the gauge), planar screen, and the calibrated table plane
    (mirror pose 0) as the sample frame."""
    from .setup import Pose

    T_ws = nominal.screen.T_world_screen
    cams = {name: CameraSetup(cam, Pose.from_transform(T_ws @ T_sc)) for name, (cam, T_sc) in result.cameras.items()}
    table = table_frame_from_plane(nominal, result.mirrors[0])
    sample = replace(nominal.sample, pose=Pose.from_transform(table))
    sm = getattr(result, "screen_model", None)
    if sm is None:
        flat = replace(nominal.screen, heights_mm=None, bulge_mm=None)
        return replace(nominal, cameras=cams, sample=sample, screen=flat)
    # A calibrated free-form screen: its grid and estimated control heights.
    screen = replace(nominal.screen, grid_x_mm=tuple(float(v) for v in sm.grid_x_mm),
                     grid_y_mm=tuple(float(v) for v in sm.grid_y_mm),
                     heights_mm=tuple(tuple(float(v) for v in row) for row in np.asarray(sm.heights_mm)),
                     bulge_mm=None)
    return replace(nominal, cameras=cams, sample=sample, screen=screen)


def calibration_deviation(truth: Setup, model: Setup) -> dict:
    """Calibrated minus true parameters per camera, and the calibrated frame's turn."""
    out = {}
    for name, cs in model.cameras.items():
        t, c = truth.cameras[name], cs.camera
        tc = t.camera
        out[name] = {
            "fx_px": c.fx_px - tc.fx_px, "fy_px": c.fy_px - tc.fy_px,
            "ppx_px": c.ppx_px - tc.ppx_px, "ppy_px": c.ppy_px - tc.ppy_px,
            "k1": c.k1 - tc.k1, "k2": c.k2 - tc.k2, "p1": c.p1 - tc.p1, "p2": c.p2 - tc.p2,
            "position_mm": float(np.linalg.norm(cs.T_world_cam.translation - t.T_world_cam.translation)),
            "rotation_deg": float(np.degrees(rotation_angle_rad(cs.T_world_cam.rotation @ t.T_world_cam.rotation.T))),
        }
    z_true = truth.sample.T_world_sample.rotation[:, 2]
    z_cal = model.sample.T_world_sample.rotation[:, 2]
    out["table_turn_deg"] = float(np.degrees(np.arccos(np.clip(np.dot(z_true, z_cal), -1.0, 1.0))))
    return out


def calibration_summary(result, model: Setup) -> dict:
    """Calibrated parameters (per camera) with their standard deviations, and the fit quality."""
    cams = {}
    for name, cs in model.cameras.items():
        c = cs.camera
        p = {k: getattr(c, k) for k in ("fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2")}
        p["std"] = {k: result.std(f"{name}.{k}") for k in ("fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2")}
        p["origin_world_mm"] = list(cs.pose.origin_world_mm)
        p["angles_deg"] = list(cs.pose.angles_deg)
        cams[name] = p
    return {
        "converged": bool(result.converged),
        "reason": result.reason,
        "iterations": int(result.iterations),
        "rms_px": float(result.rms_px),
        "n_residuals": int(result.n_residuals),
        "condition_number": float(result.condition_number),
        "cameras": cams,
    }


@dataclass(frozen=True, eq=False)
class Experiment2Bulge:
    """Experiment 2 at one Δh: the calibration and both cameras' reconstructions."""

    bulge_mm: float
    result: object  # CalibrationResult
    model: Setup
    deviation: dict
    cases: list


def run_experiment2_bulge(bulge_mm: float, *, base: Setup | None = None, downsample: int = 1,
                          method: str = "stepwise", seed: int = 0, progress: Progress | None = None,
                          image_sink=None, screen_grid: int | None = None,
                          observations=None) -> Experiment2Bulge:
    """Experiment 2 (paper §4) at one Δh: simulate the calibration poses → calibrate (planar
    screen model, nominal start values with :data:`INITIAL_ERRORS`) → simulate the planar
    sample → reconstruct with the calibrated parameters, heights relative to the calibrated
    table plane (the base mirror pose), seeded at the central pixel with height 0.

    ``screen_grid`` = n (odd, ≥ 3) calibrates the screen as a free-form n × n spline grid
    (border heights held: the rigid frame's plane is the gauge; interior heights free) and
    reconstructs with the calibrated screen — the paper's future work (§5); None: planar.
    """
    base = default_setup() if base is None else base
    truth = binned_setup(base, downsample).with_bulge(bulge_mm)
    return calibrate_and_reconstruct(truth, bulge_mm=bulge_mm, method=method,
                                     start_seed=[seed, int(round(bulge_mm * 1000))], progress=progress,
                                     image_sink=image_sink, screen_grid=screen_grid, observations=observations)


def nominal_setup(truth: Setup) -> Setup:
    """What the calibration starts from and assumes: the truth's design (camera models, poses,
    mirror poses) with a planar screen over the same extent and a planar calibration mirror.
    (Start values are perturbed from it by :func:`calibrate_and_reconstruct`.)"""
    scr = replace(truth.screen, heights_mm=None, bulge_mm=None)
    return replace(truth, screen=scr).with_mirror_sag(0.0)


def free_screen_model(nominal: Setup, screen_grid: int):
    """A flat n × n free-form :class:`~pmdsim.calibration.ScreenModel` spanning the nominal
    screen's grid (border held at 0 = the gauge, (n − 2)² free interior heights)."""
    from .calibration import ScreenModel

    if isinstance(screen_grid, bool) or int(screen_grid) != screen_grid or screen_grid < 3:
        raise ValueError(f"screen_grid must be an integer ≥ 3, got {screen_grid!r}")
    scr = nominal.screen
    return ScreenModel.flat(np.linspace(scr.grid_x_mm[0], scr.grid_x_mm[-1], int(screen_grid)),
                            np.linspace(scr.grid_y_mm[0], scr.grid_y_mm[-1], int(screen_grid)))


def calibrate_and_reconstruct(truth: Setup, *, bulge_mm: float | None = None, method: str = "stepwise",
                              start_seed=0, progress: Progress | None = None, image_sink=None,
                              screen_grid: int | None = None, observations=None) -> Experiment2Bulge:
    """The Experiment 2 chain for any true setup (deformed screen, sagged mirror, …).

    Simulate the calibration poses of ``truth`` (or take ``observations`` of it) → calibrate
    from nominal start values (:func:`nominal_setup` perturbed by :data:`INITIAL_ERRORS`,
    seeded by ``start_seed``) with a planar (``screen_grid`` None) or n × n free-form screen
    model and planar mirrors → simulate the planar sample of ``truth`` → reconstruct both
    cameras with the calibrated setup, heights relative to the calibrated table plane (its true
    height is 0, so the reconstructed height is the error). ``bulge_mm`` labels the results
    (default: the truth's central screen control height).
    """
    from .calibration import calibrate, nominal_state, perturbed_state

    nominal = nominal_setup(truth)
    if bulge_mm is None:
        z = truth.screen.control_heights()
        bulge_mm = float(z[z.shape[0] // 2, z.shape[1] // 2])
    # ``observations`` lets several screen models share one simulated calibration data set.
    obs = observations if observations is not None else simulate_calibration_observations(
        truth, progress=progress, image_sink=image_sink)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    rng = np.random.default_rng(start_seed)
    start = perturbed_state(nominal_state(nominal, poses), rng, **INITIAL_ERRORS)
    if progress is not None:
        progress(f"Δh = {bulge_mm:g} mm: calibrating")
    screen_model = None if screen_grid is None else free_screen_model(nominal, screen_grid)
    result = calibrate(obs, start, screen_model=screen_model)
    model = calibrated_setup(nominal, result)
    deviation = calibration_deviation(truth, model)
    cases = []
    for cam in truth.cameras:
        if progress is not None:
            progress(f"Δh = {bulge_mm:g} mm: reconstructing, camera {cam}")
        m = trace_setup_camera(truth, cam, store_points=False)
        images: dict = {}
        for spec, img in render_images(truth, cam, m):
            images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        decoded = decode_images(truth, images)
        del images
        c = model.cameras[cam].camera
        seed_px = (c.height_px // 2, c.width_px // 2)
        reg, rec = evaluate_decoded(model, cam, decoded, method=method, seed_pixel=seed_px, seed_height_mm=0.0,
                                    screen_model=None if screen_model is None else model.screen.surface)
        p = rec.points
        # The sample is the plane of the base mirror pose: relative to the calibrated table
        # plane its true height is 0, so the reconstructed height is the error.
        err = np.where(rec.reconstructed, rec.height_mm, np.nan)
        metrics = surface_error_metrics(p[..., 0], p[..., 1], err)
        cases.append(CaseResult.from_reconstruction(bulge_mm, cam, rec, err, metrics))
    return Experiment2Bulge(float(bulge_mm), result, model, deviation, cases)


# ============================================================================ Experiment 3
#: True screen deformations that the centred models cannot all represent (the mismatch case).
SCREEN_DEFORMATIONS = ("offcentre", "random")


def screen_deformation(setup: Setup, kind: str, *, peak_mm: float = 3.0, seed: int = 0) -> Setup:
    """``setup`` with a true screen deformation of the mismatch case (Experiment 3).

    Both hold the screen's border at 0 (a rigid frame, as the paper's bulge does):

    ``"offcentre"``
        A 5 × 5 control grid over the screen with one off-centre control height of ``peak_mm``
        (row 1, column 3: at 3/4 of the width and 1/4 of the height). The 3 × 3 model cannot
        represent it; the 5 × 5 model can exactly, and so can 9 × 9 (its not-a-knot spline
        space contains the 5 × 5 one: the 5-point spline's only interior knot is the centre,
        which is also a knot of the 9-point spline).
    ``"random"``
        A seeded random smooth shape on a 17 × 17 grid: Σ_{m,n=1..4} a_mn·sin(mπu)·sin(nπv),
        u, v ∈ [0, 1] across the screen, a_mn ~ N(0, 1)/(m² + n²), scaled so that the largest
        control height magnitude is ``peak_mm``. No model grid represents it exactly.
    """
    scr = setup.screen
    x0, x1 = scr.grid_x_mm[0], scr.grid_x_mm[-1]
    y0, y1 = scr.grid_y_mm[0], scr.grid_y_mm[-1]
    if kind == "offcentre":
        gx, gy = np.linspace(x0, x1, 5), np.linspace(y0, y1, 5)
        z = np.zeros((5, 5))
        z[1, 3] = peak_mm
    elif kind == "random":
        gx, gy = np.linspace(x0, x1, 17), np.linspace(y0, y1, 17)
        u = (gx - x0) / (x1 - x0)
        v = (gy - y0) / (y1 - y0)
        rng = np.random.default_rng([seed, 17])
        z = np.zeros((17, 17))
        for m in range(1, 5):
            for n in range(1, 5):
                z += rng.normal() / (m * m + n * n) * np.outer(np.sin(n * np.pi * v), np.sin(m * np.pi * u))
        z *= peak_mm / np.abs(z).max()
    else:
        raise ValueError(f"unknown screen deformation {kind!r}; expected one of {SCREEN_DEFORMATIONS}")
    return setup.with_screen_heights(gx, gy, z)


@dataclass(frozen=True, eq=False)
class Experiment3Scenario:
    """One true setup of Experiment 3: the paper's bulge, a mismatch deformation, or a sagged
    calibration mirror (with the paper's bulge ``bulge_mm``)."""

    name: str  # "bulge", "offcentre", "random" or "mirror_sag"
    bulge_mm: float
    mirror_sag_um: float
    truth: Setup

    @property
    def label(self) -> str:
        if self.name == "bulge":
            return f"bulge {self.bulge_mm:g} mm"
        if self.name == "mirror_sag":
            return f"mirror sag {self.mirror_sag_um:g} µm, bulge {self.bulge_mm:g} mm"
        return f"{self.name} deformation"

    @property
    def start_seed(self) -> list[int]:
        """Seed of the calibration's start values: Experiment 2's for the bulge scenarios."""
        if self.name == "bulge":
            return [0, int(round(self.bulge_mm * 1000))]
        kind = {"offcentre": 1, "random": 2, "mirror_sag": 3}[self.name]
        return [0, 1_000_000 * kind + int(round(self.mirror_sag_um * 1000))]


def experiment3_scenarios(base: Setup, *, downsample: int = 1, bulges: Iterable[float] = (0.0, 1.0, 2.0, 3.0),
                          deformations: Iterable[str] = SCREEN_DEFORMATIONS,
                          mirror_sags_um: Iterable[float] = (1.0, 5.0), sag_bulge_mm: float = 3.0,
                          peak_mm: float = 3.0) -> list[Experiment3Scenario]:
    """The true setups of Experiment 3, binned by ``downsample``."""
    b = binned_setup(base, downsample)
    out = [Experiment3Scenario("bulge", float(dh), 0.0, b.with_bulge(dh)) for dh in bulges]
    for kind in deformations:
        t = screen_deformation(b, kind, peak_mm=peak_mm)
        z = t.screen.control_heights()
        out.append(Experiment3Scenario(kind, float(z[z.shape[0] // 2, z.shape[1] // 2]), 0.0, t))
    for s in mirror_sags_um:
        out.append(Experiment3Scenario("mirror_sag", float(sag_bulge_mm), float(s),
                                       b.with_bulge(sag_bulge_mm).with_mirror_sag(s)))
    return out


def screen_shape_error_um(truth: Setup, model: Setup, observations) -> tuple[float, float]:
    """(max, RMS) of calibrated − true screen height (µm) over the screen points the calibration
    observed (the decoded (x_q, y_q) of all ``observations``): how well the model found the
    screen's shape where the data can tell. Both share the gauge (border/frame plane at 0)."""
    q = np.concatenate([o.q_screen_mm[:, :2] for o in observations])
    d = model.screen.surface.height(q[:, 0], q[:, 1]) - truth.screen.surface.height(q[:, 0], q[:, 1])
    d = d[np.isfinite(d)]
    return float(np.abs(d).max() * 1e3), float(np.sqrt(np.mean(d * d)) * 1e3)


def experiment3_records(scenario: Experiment3Scenario, screen_model: str, e: Experiment2Bulge, observations) -> list[dict]:
    """results.json objects of one scenario and screen model: the Experiment 1 keys, then
    ``screen_model`` and ``free_parameters`` (the contract), then diagnostics."""
    sm = e.result.screen_model
    shape_max, shape_rms = screen_shape_error_um(scenario.truth, e.model, observations)
    out = []
    for c in e.cases:
        rec = c.as_record()
        rec = {"bulge_mm": rec.pop("bulge_mm"), "camera": rec.pop("camera"),
               "max_height_diff_um": rec.pop("max_height_diff_um"), "max_dev_plane_um": rec.pop("max_dev_plane_um"),
               "tilt_urad": rec.pop("tilt_urad"),
               "screen_model": screen_model, "free_parameters": 0 if sm is None else int(sm.n_free),
               "scenario": scenario.name, "mirror_sag_um": scenario.mirror_sag_um,
               "calibration_rms_px": float(e.result.rms_px), "calibration_converged": bool(e.result.converged),
               "calibration_condition_number": float(e.result.condition_number),
               "frame_turn_deg": float(e.deviation["table_turn_deg"]),
               "screen_shape_max_error_um": shape_max, "screen_shape_rms_error_um": shape_rms, **rec}
        if sm is not None:
            cx = 0.5 * (sm.grid_x_mm[0] + sm.grid_x_mm[-1])
            cy = 0.5 * (sm.grid_y_mm[0] + sm.grid_y_mm[-1])
            rec["screen_central_height_mm"] = float(np.ravel(sm.height(cx, cy))[0])
        out.append(rec)
    return out


def run_experiment3(scenarios: Iterable[Experiment3Scenario], grids: Iterable[int] = (3, 5, 9), *,
                    method: str = "stepwise", progress: Progress | None = None):
    """Experiment 3 (beyond the paper, §5): for every scenario, simulate the calibration data
    once, then calibrate and reconstruct with the planar model and each n × n free-form model.

    Yields
    ------
    (scenario, screen_model label, Experiment2Bulge, records) per scenario and model, in order.
    Where the calibration data cannot determine a model (e.g. control heights that no mirror
    pose's reflection reaches), the third item is the :class:`~pmdsim.calibration.CalibrationDataError`
    that says which parameters and why, and ``records`` is empty: the other models still run.
    """
    from .calibration import CalibrationDataError

    grids = list(grids)
    for sc in scenarios:
        if progress is not None:
            progress(f"{sc.label}: simulating the calibration poses")
        obs = simulate_calibration_observations(sc.truth)
        for g in [None, *grids]:
            label = "planar" if g is None else f"{g}x{g}"
            if progress is not None:
                progress(f"{sc.label}: {label} screen model")
            try:
                e = calibrate_and_reconstruct(sc.truth, bulge_mm=sc.bulge_mm, method=method,
                                              start_seed=sc.start_seed, screen_grid=g, observations=obs)
            except CalibrationDataError as err:
                yield sc, label, err, []
                continue
            yield sc, label, e, experiment3_records(sc, label, e, obs)
