"""Between a :class:`~pmdsim.setup.Setup` and the calibration's parameter state.

:func:`nominal_setup` is what a calibration starts from and assumes; :func:`free_screen_model`
the n × n free-form screen model over a setup's screen; :func:`calibrated_setup` turns a
:class:`~pmdsim.calibration.CalibrationResult` back into a setup (the gauge: the screen at its
nominal pose defines world; the calibrated table plane is the sample frame);
:func:`calibration_deviation` and :func:`calibration_summary` report it.
:func:`setup_covariance` is the part of the calibration's covariance that the calibrated setup
carries (``Setup.calibration_covariance``); :func:`perturbed_setup` (from
:mod:`pmdsim.setup.covariance`) applies a step of those parameters to a setup.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..geometry.transform import RigidTransform, rotation_angle_rad
from ..setup import CameraSetup, Pose, Setup
from ..setup.covariance import CalibrationCovariance, is_setup_parameter, perturbed_setup

__all__ = ["nominal_setup", "free_screen_model", "table_frame_from_plane", "calibrated_setup",
           "calibration_deviation", "calibration_summary", "setup_covariance", "perturbed_setup"]


def nominal_setup(truth: Setup, glass=None) -> Setup:
    """What the calibration starts from and assumes: the truth's design (camera models, poses,
    mirror poses) with a planar screen over the same extent and a planar calibration mirror.
    (Start values are perturbed from it by :func:`calibrate_and_reconstruct`.)

    The truth's cover glass is *not* carried over (a calibration must not know it): the nominal
    screen has the glass ``glass`` (a :class:`~pmdsim.geometry.cover_glass.CoverGlass`: what the
    nominal design declares) or none."""
    t, n = (0.0, None) if glass is None else (glass.thickness_mm, glass.index)
    scr = replace(truth.screen, heights_mm=None, bulge_mm=None, cover_glass_thickness_mm=t, cover_glass_index=n)
    return replace(truth, screen=scr, calibration_covariance=None).with_mirror_sag(0.0)


def free_screen_model(nominal: Setup, screen_grid: int):
    """A flat n × n free-form :class:`~pmdsim.calibration.ScreenModel` spanning the nominal
    screen's grid (border held at 0 = the gauge, (n − 2)² free interior heights)."""
    from .screen import ScreenModel

    if isinstance(screen_grid, bool) or int(screen_grid) != screen_grid or screen_grid < 3:
        raise ValueError(f"screen_grid must be an integer ≥ 3, got {screen_grid!r}")
    scr = nominal.screen
    return ScreenModel.flat(np.linspace(scr.grid_x_mm[0], scr.grid_x_mm[-1], int(screen_grid)),
                            np.linspace(scr.grid_y_mm[0], scr.grid_y_mm[-1], int(screen_grid)))


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


def setup_covariance(result) -> CalibrationCovariance | None:
    """The covariance of the calibrated parameters a setup carries: every camera's 14, the base
    mirror plane's 3 as the table plane (``mirror0.*`` → ``table.*``), the free screen heights
    (and any other setup parameter, :func:`~pmdsim.setup.covariance.is_setup_parameter`); the
    other mirror poses are marginalised out (their rows and columns dropped). None if the result
    has no covariance."""
    cov = getattr(result, "covariance", None)
    if cov is None:
        return None
    keep, names = [], []
    for j, n in enumerate(result.parameter_names):
        head, _, kind = n.partition(".")
        if head.startswith("mirror") and head[6:].isdigit():
            if head != "mirror0":
                continue
            n = f"table.{kind}"
        if is_setup_parameter(n):
            keep.append(j)
            names.append(n)
    return CalibrationCovariance(tuple(names), np.asarray(cov, dtype=float)[np.ix_(keep, keep)])


def calibrated_setup(nominal: Setup, result) -> Setup:
    """The setup as the calibration knows it: estimated cameras (poses in the world frame of the
    screen held at its nominal pose — the gauge), planar screen, and the calibrated table plane
    (mirror pose 0) as the sample frame; the screen's cover glass is the calibration's (fitted
    or held; none if the calibration had none); it carries :func:`setup_covariance`."""
    return _calibrated_setup(nominal, result).with_calibration_covariance(setup_covariance(result))


def _calibrated_setup(nominal: Setup, result) -> Setup:
    from ..setup import Pose

    glass = getattr(result, "glass", None)
    nominal = (nominal.with_cover_glass(0.0) if glass is None
               else nominal.with_cover_glass(glass.thickness_mm, glass.index))
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
