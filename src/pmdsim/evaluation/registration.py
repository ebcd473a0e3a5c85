"""Deflectometric registration: pixel → 3-D screen point, view rays, in a reconstruction frame.

Paper §2.5: for a pixel with decoded pattern coordinates (x_p, y_p), the light came from the
screen point p_(p) = (x_p, y_p, h_p(x_p, y_p)) of the *screen model* used by the evaluation.
The paper's evaluation assumes a planar screen (h_p = 0, "It is precisely here, that the
reconstruction algorithm implicitly assumes the x–y-plane of the pattern screen coordinate
system to be the planar light source"); any surface of :mod:`pmdsim.geometry.surface` is accepted, so a
deformed (calibrated) screen model can be used as well.

The result is expressed in a reconstruction frame ``ref`` (usually the sample frame), whose +z
is the height direction of the reconstruction (:mod:`pmdsim.evaluation.reconstruction`).

Cover glass (issue 21, docs/conventions.md "Cover glass"): the decoded point Q is on the
*emitting* surface, but the light left the glass at a point A of its outer surface and was
refracted there, so the straight line from the sample point P to Q is not the reflected ray.
With a ``glass``, :func:`register` solves for A given P (:meth:`CoverGlass.apparent_points`: a
fixed-point iteration on A through the forward trace, to 1e-9 mm; pixels where it does not
converge are :attr:`RegistrationStatus.GLASS_NO_CONVERGENCE`) and returns, instead of Q, the
*apparent point* where the straight line P → A meets the emitting surface, which the
reconstruction then uses like a screen point. P is unknown before the reconstruction: it is taken on the plane z = ``sample_height_mm``
of the reconstruction frame (the view ray's point there), or given as ``sample_points_ref_mm``
(e.g. a first reconstruction: :func:`pmdsim.evaluation.pipeline.evaluate_decoded` registers,
reconstructs, registers again at the reconstructed points and reconstructs again).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ..geometry.camera import Camera
from ..geometry.cover_glass import CoverGlass
from ..geometry.transform import RigidTransform
from ..geometry.compact import compact_repr

__all__ = ["Registration", "RegistrationStatus", "register"]


class RegistrationStatus(enum.IntEnum):
    """Why a pixel has no registration (0 = registered)."""

    VALID = 0
    NOT_DECODED = 1  # the decoder marked the pixel invalid (see pmdsim.evaluation.phase.PhaseFlag)
    UNDISTORT_FAILED = 2  # the view ray could not be computed
    OUTSIDE_SCREEN_MODEL = 3  # decoded pattern coordinates outside the screen model's bounds
    GLASS_NO_CONVERGENCE = 4  # cover glass: the apparent point's fixed point did not converge (1e-9 mm)


@dataclass(frozen=True, eq=False)
class Registration:
    """View rays and screen points of one camera in a reconstruction frame.

    Attributes
    ----------
    o_ref_mm : ndarray (3,)
        Camera centre (pinhole) in the reconstruction frame.
    d_ref : ndarray (H, W, 3)
        View-ray directions in the reconstruction frame (not normalised).
    q_ref_mm : ndarray (H, W, 3)
        Screen points of the screen model, in the reconstruction frame (NaN where not valid).
    status : ndarray of uint8 (H, W)
        :class:`RegistrationStatus` per pixel.
    """

    __repr__ = compact_repr  # one line: arrays by shape and dtype (issue 23)

    o_ref_mm: np.ndarray
    d_ref: np.ndarray
    q_ref_mm: np.ndarray
    status: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.status == RegistrationStatus.VALID


def register(
    camera: Camera,
    T_world_cam: RigidTransform,
    screen_model,
    T_world_screen: RigidTransform,
    screen_xy_mm: np.ndarray,
    decoded: np.ndarray,
    T_world_ref: RigidTransform,
    *,
    rays: tuple[np.ndarray, np.ndarray] | None = None,
    glass: CoverGlass | None = None,
    sample_points_ref_mm: np.ndarray | None = None,
    sample_height_mm: float = 0.0,
) -> Registration:
    """Register decoded pattern coordinates to 3-D screen points (paper §2.5).

    Parameters
    ----------
    camera : Camera
        Intrinsic model (the evaluation's knowledge of the camera).
    T_world_cam, T_world_screen, T_world_ref : RigidTransform
        Poses of camera, screen model and reconstruction frame.
    screen_model : SplineSurface or PlaneSurface
        The screen surface the evaluation assumes (a plane in the paper).
    screen_xy_mm : ndarray (H, W, 2)
        Decoded pattern coordinates (screen frame, mm).
    decoded : ndarray of bool (H, W)
        Pixels the decoder accepted.
    rays : (d_cam, converged), optional
        Precomputed ``camera.sensor_rays()``.
    glass : CoverGlass, optional
        The screen's cover glass; present: ``q_ref_mm`` holds the apparent points (module
        docstring). None or zero thickness: the emitting-surface points, as without glass.
    sample_points_ref_mm : ndarray (H, W, 3), optional
        With a glass: the sample points P in the reconstruction frame (NaN: use the plane).
    sample_height_mm : float
        With a glass: the height of the plane of the reconstruction frame on which P is taken
        where ``sample_points_ref_mm`` gives none.

    Returns
    -------
    Registration
    """
    xy = np.asarray(screen_xy_mm, dtype=float)
    ok = np.asarray(decoded, dtype=bool)
    if xy.shape != camera.shape + (2,):
        raise ValueError(f"screen_xy_mm must have shape {camera.shape + (2,)} for this camera, got {xy.shape}")
    if ok.shape != camera.shape:
        raise ValueError(f"decoded must have shape {camera.shape}, got {ok.shape}")
    d_cam, converged = camera.sensor_rays() if rays is None else rays
    x = xy[..., 0]
    y = xy[..., 1]
    x0, x1, y0, y1 = screen_model.bounds_mm
    with np.errstate(invalid="ignore"):
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)  # False for NaN
    status = np.full(camera.shape, RegistrationStatus.VALID, dtype=np.uint8)
    status[~inside] = RegistrationStatus.OUTSIDE_SCREEN_MODEL
    status[~converged] = RegistrationStatus.UNDISTORT_FAILED
    status[~ok] = RegistrationStatus.NOT_DECODED
    valid = status == RegistrationStatus.VALID

    # Screen points (x_p, y_p, h_p(x_p, y_p)) of the screen model; evaluated on the full grid
    # (invalid pixels at a dummy in-bounds point) and masked afterwards.
    h = screen_model.height(np.where(valid, x, x0), np.where(valid, y, y0))
    q_screen = np.stack([x, y, h], axis=-1)
    q_screen[~valid] = np.nan
    T_ref_world = T_world_ref.inv()
    T_ref_screen = T_ref_world @ T_world_screen
    T_ref_cam = T_ref_world @ T_world_cam
    o_ref = T_ref_cam.translation.copy()
    d_ref = T_ref_cam.apply_vector(d_cam)
    if glass is not None and glass.present:
        with np.errstate(invalid="ignore", divide="ignore"):
            p_ref = o_ref + ((sample_height_mm - o_ref[2]) / d_ref[..., 2])[..., None] * d_ref
        if sample_points_ref_mm is not None:
            given = np.asarray(sample_points_ref_mm, dtype=float)
            p_ref = np.where(np.isfinite(given).all(axis=-1)[..., None], given, p_ref)
        p_screen = T_ref_screen.inv().apply(p_ref)
        q_app, converged = glass.apparent_points(screen_model, np.where(valid[..., None], p_screen, np.nan), q_screen,
                                                 return_converged=True)
        lost = valid & ~np.isfinite(q_app).all(axis=-1)
        status[lost & converged] = RegistrationStatus.OUTSIDE_SCREEN_MODEL
        status[lost & ~converged] = RegistrationStatus.GLASS_NO_CONVERGENCE
        q_screen = q_app
    return Registration(
        o_ref_mm=o_ref,
        d_ref=d_ref,
        q_ref_mm=T_ref_screen.apply(q_screen),
        status=status,
    )
