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
import threading
from dataclasses import dataclass

import numba
import numpy as np

from ..geometry.camera import Camera
from ..geometry.kernel_args import SERIAL_BELOW_PX, readonly
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


#: Pixels per block of the fused registration: the block's (x, y, h) rows (384 kB) stay in cache
#: between the kernel that writes them and the rotation that reads them, and numpy's matmul of
#: that many rows runs on one OpenBLAS thread (from 65 536 rows on it starts threads, which on
#: a loaded 2-vCPU machine took 0.9–1.1 s instead of 20 ms for 2.3 M rows: docs/benchmarks.md).
_BLOCK_PX = 16_384
#: Threads of the fused registration (blocks dealt out in turn; at most numba's thread count).
_THREADS = 2


@numba.njit(cache=True, error_model="numpy", nogil=True)
def _screen_block(xy, ok, conv, bounds, kind, gx, gy, coef, start, stop, status, q):  # pragma: no cover - compiled
    """Status (``status`` (P,), uint8) and screen points (x, y, h(x, y)) — NaN where the status is
    not VALID — of the flat pixels start … stop − 1 (``xy`` (P, 2), ``ok``, ``conv`` (P,)) into
    ``q[: stop − start]`` ((B, 3)); the status as :func:`register`'s masks set it (NOT_DECODED
    over UNDISTORT_FAILED over OUTSIDE_SCREEN_MODEL)."""
    x0, x1, y0, y1 = bounds[0], bounds[1], bounds[2], bounds[3]
    for k in range(start, stop):
        x = xy[k, 0]
        y = xy[k, 1]
        j = k - start
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
            q[j, 0] = x
            q[j, 1] = y
            q[j, 2] = height_kernel(kind, gx, gy, coef, x, y)
        else:
            q[j, 0] = np.nan
            q[j, 1] = np.nan
            q[j, 2] = np.nan


def _register_blocks(xy, ok, converged, d_cam, screen_model, T_ref_screen, T_ref_cam):
    """Status (H, W), view rays (H, W, 3) and screen points (H, W, 3) in the reference frame of
    :func:`register` without a glass, in blocks of pixels: a compiled pass writes a block's
    (x, y, h) rows, numpy rotates them into the result (``p @ R.T``, then ``+= t``:
    :meth:`RigidTransform.apply`'s operations row for row — the same bits,
    tests/test_registration_fused.py) while they are in cache, and rotates the block's view rays
    (:meth:`RigidTransform.apply_vector`). No (H, W, 3) screen points, masks or heights of the
    whole image are allocated; numpy's matmul runs on blocks of rows as on the whole array,
    except a block of one row (another path, other bits), which the blocks avoid. From
    ``SERIAL_BELOW_PX`` pixels on, every other block runs on a second Python thread (the kernel
    and the matmuls release the GIL; a block's arithmetic does not depend on its thread)."""
    shape = ok.shape
    P = ok.size
    k = screen_model.kernel
    flat_xy = readonly(np.ascontiguousarray(xy, dtype=np.float64).reshape(P, 2))
    flat_ok = readonly(np.ascontiguousarray(ok, dtype=np.bool_).reshape(P))
    flat_cv = readonly(np.ascontiguousarray(converged, dtype=np.bool_).reshape(P))
    flat_d = np.asarray(d_cam, dtype=np.float64).reshape(P, 3)
    bounds = readonly(np.array(screen_model.bounds_mm, dtype=np.float64))
    gx, gy, coef = (readonly(np.ascontiguousarray(a, dtype=np.float64)) for a in (k.grid_x, k.grid_y, k.coef))
    kind = np.int64(k.kind)
    status = np.empty(P, np.uint8)
    q_ref = np.empty((P, 3))
    d_ref = np.empty((P, 3))
    rot_q, t_q, rot_d = T_ref_screen.rotation.T, T_ref_screen.translation, T_ref_cam.rotation.T
    blocks, start = [], 0
    while start < P:
        stop = min(P, start + _BLOCK_PX)
        if P - stop == 1:  # no block of one row
            stop = P
        blocks.append((start, stop))
        start = stop

    failed = []

    def run(mine):
        try:
            _blocks(mine)
        except BaseException as exc:  # (re-raised in the calling thread)
            failed.append(exc)

    def _blocks(mine):
        block = np.empty((min(P, _BLOCK_PX + 1), 3))
        for start, stop in mine:
            q = block[: stop - start]
            _screen_block(flat_xy, flat_ok, flat_cv, bounds, kind, gx, gy, coef, np.int64(start), np.int64(stop),
                          status, q)
            out = q_ref[start:stop]
            np.matmul(q, rot_q, out=out)
            out += t_q
            np.matmul(flat_d[start:stop], rot_d, out=d_ref[start:stop])

    # every other block on a second thread (the kernel and numpy's matmul release the GIL; each
    # block's arithmetic is the same on either thread)
    n_threads = min(_THREADS, numba.get_num_threads()) if P >= SERIAL_BELOW_PX else 1
    helpers = [threading.Thread(target=run, args=(blocks[i::n_threads],)) for i in range(1, n_threads)]
    for t in helpers:
        t.start()
    run(blocks[::n_threads])
    for t in helpers:
        t.join()
    if failed:
        raise failed[0]
    return status.reshape(shape), d_ref.reshape(shape + (3,)), q_ref.reshape(shape + (3,))
