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

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from ..geometry.camera import Camera
from ..geometry.kernel_args import SERIAL_BELOW_PX, numba_threads, readonly
from ..geometry.surface import height_kernel
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
    T_ref_world = T_world_ref.inv()
    T_ref_screen = T_ref_world @ T_world_screen
    T_ref_cam = T_ref_world @ T_world_cam
    o_ref = T_ref_cam.translation.copy()
    if (glass is None or not glass.present) and getattr(screen_model, "kernel", None) is not None:
        status, d_ref, q_ref = _register_blocks(xy, ok, converged, d_cam, screen_model, T_ref_screen, T_ref_cam)
        return Registration(o_ref_mm=o_ref, d_ref=d_ref, q_ref_mm=q_ref, status=status)
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


#: Pixels per block of the fused registration's parallel loop (the blocks are dealt to the threads).
_BLOCK_PX = 16_384


@intrinsic
def _fma(typingctx, a, b, c):
    """a·b + c with one rounding (LLVM's fma: the processor's instruction)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d]))
        return builder.call(fn, args)

    return sig, codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _rotated(a0, a1, a2, rot, j):  # pragma: no cover - compiled
    """Component j of rot·a: fma(a₂, R_j2, fma(a₁, R_j1, a₀·R_j0)) — the operations of numpy's
    ``a @ rot.T`` (OpenBLAS's dgemm on this machine), so the same bits
    (tests/test_registration_fused.py compares with numpy)."""
    return _fma(a2, rot[j, 2], _fma(a1, rot[j, 1], a0 * rot[j, 0]))


@numba.njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _register_kernel(xy, ok, conv, bounds, kind, gx, gy, coef, d_cam, rot_q, t_q, rot_d, block, status, q_ref,
                     d_ref):  # pragma: no cover - compiled
    """Status (``status`` (P,), uint8), screen points rot_q·(x, y, h(x, y)) + t_q (``q_ref``
    (P, 3); NaN where the status is not VALID) and view rays rot_d·d (``d_ref`` (P, 3)) of the
    flat pixels (``xy`` (P, 2), ``ok``, ``conv`` (P,), ``d_cam`` (P, 3)), in blocks of ``block``
    pixels on the threads; the status as :func:`register`'s masks set it (NOT_DECODED over
    UNDISTORT_FAILED over OUTSIDE_SCREEN_MODEL)."""
    x0, x1, y0, y1 = bounds[0], bounds[1], bounds[2], bounds[3]
    n = ok.size
    for b in numba.prange(0, (n + block - 1) // block):
        for k in range(b * block, min(n, (b + 1) * block)):
            x = xy[k, 0]
            y = xy[k, 1]
            if not ok[k]:
                st = 1
            elif not conv[k]:
                st = 2
            elif not (x >= x0 and x <= x1 and y >= y0 and y <= y1):  # False for NaN
                st = 3
            else:
                st = 0
            status[k] = st
            if st == 0:
                h = height_kernel(kind, gx, gy, coef, x, y)
            else:
                x = y = h = np.nan
            for j in range(3):
                q_ref[k, j] = _rotated(x, y, h, rot_q, j) + t_q[j]
                d_ref[k, j] = _rotated(d_cam[k, 0], d_cam[k, 1], d_cam[k, 2], rot_d, j)


def _register_blocks(xy, ok, converged, d_cam, screen_model, T_ref_screen, T_ref_cam):
    """Status (H, W), view rays (H, W, 3) and screen points (H, W, 3) in the reference frame of
    :func:`register` without a glass, in one compiled pass on the threads: per pixel the status,
    the screen point (x, y, h) and both rotations (the operations of
    :meth:`RigidTransform.apply` — ``p @ R.T`` by OpenBLAS, then ``+= t`` — and of
    :meth:`RigidTransform.apply_vector`: the same bits, tests/test_registration_fused.py). No
    (H, W, 3) screen points, masks or heights of the whole image are allocated."""
    shape = ok.shape
    P = ok.size
    k = screen_model.kernel
    flat_xy = readonly(np.ascontiguousarray(xy, dtype=np.float64).reshape(P, 2))
    flat_ok = readonly(np.ascontiguousarray(ok, dtype=np.bool_).reshape(P))
    flat_cv = readonly(np.ascontiguousarray(converged, dtype=np.bool_).reshape(P))
    flat_d = readonly(np.ascontiguousarray(d_cam, dtype=np.float64).reshape(P, 3))
    bounds = readonly(np.array(screen_model.bounds_mm, dtype=np.float64))
    gx, gy, coef = (readonly(np.ascontiguousarray(a, dtype=np.float64)) for a in (k.grid_x, k.grid_y, k.coef))
    rot_q, t_q, rot_d = (readonly(np.ascontiguousarray(a, dtype=np.float64)) for a in
                         (T_ref_screen.rotation, T_ref_screen.translation, T_ref_cam.rotation))
    status = np.empty(P, np.uint8)
    q_ref = np.empty((P, 3))
    d_ref = np.empty((P, 3))
    with numba_threads(1 if P < SERIAL_BELOW_PX else numba.get_num_threads()):
        _register_kernel(flat_xy, flat_ok, flat_cv, bounds, np.int64(k.kind), gx, gy, coef, flat_d, rot_q, t_q, rot_d,
                         np.int64(_BLOCK_PX), status, q_ref, d_ref)
    return status.reshape(shape), d_ref.reshape(shape + (3,)), q_ref.reshape(shape + (3,))
