"""Holistic calibration with a planar mirror (paper §4): parameters, state and observations.

Several cameras observe the pattern screen via a planar front-surface mirror placed in K poses.
Phase decoding gives, per camera c and mirror pose k, correspondences pixel (u, v) ↔ screen
point q (screen frame, mm; q = (x_q, y_q, 0) for the planar screen model, but any (M, 3) points
are accepted so that a non-planar screen model can be plugged in). The calibration estimates jointly

* per camera: the intrinsics fx, fy, ppx, ppy, k1, k2, p1, p2 (k3 is held at its initial value,
  normally 0) and the pose ``T_screen_cam`` (6 DOF);
* per mirror pose k: the mirror plane {x : n·x = d} in the screen frame (3 DOF; a 6-DOF mirror
  pose would be singular, a plane being invariant to in-plane motions).

Gauge
-----
**The screen frame is held fixed**: it is the reference of the calibration (the screen is the
one rigid object seen in every measurement). All camera poses and mirror planes are estimated
in the screen frame; nothing else needs to be fixed: the data then determine every parameter,
provided that the mirror planes are neither all parallel (with lifts only, moving the cameras
along the common normal and every plane by half as much is invisible) nor all through one
common line (with tilts about a single axis and no lifts, rotating the cameras by 2φ and the
planes by φ about that line is invisible); :func:`calibrate` reports both as a
:class:`CalibrationDegenerateError`.


Model (forward, analytic, exact for a planar mirror)
----------------------------------------------------
The screen point is mirrored across the plane, q' = q − 2 (n·q − d) n (the virtual point: the
reflected ray through it passes through the camera centre), transformed to the camera,
p = T_cam_screen(q') = Rᵀ (q' − c) with ``T_screen_cam = (R, c)``, and projected with the
camera model of :mod:`pmdsim.geometry.camera` (eqs. 2–4, OpenCV's distortion). The residual is
predicted − observed pixel (px).

Parameterisation (per Levenberg–Marquardt step, increments around the current state)
------------------------------------------------------------------------------------
camera (14): ``fx_px, fy_px, ppx_px, ppy_px, k1, k2, p1, p2`` additively;
``rotvec_x/y/z`` (rad) a rotation-vector increment of the camera's orientation expressed in the
screen frame, R_screen_cam ← exp([δ]×)·R_screen_cam; ``position_x/y/z_mm`` the camera centre
(the translation of ``T_screen_cam``) additively. mirror (3): ``tilt_a, tilt_b`` (rad)
n ← normalize(n + a·e1 + b·e2) with (e1, e2) = :meth:`MirrorPlane.tangent_basis`, ``d_mm``
additively. screen (F, optional): the free control heights ``screen.h[j,i]_mm`` additively
(row j ↔ y_j, column i ↔ x_i), in the order of ``np.nonzero(free)``, after all mirrors.
Internally every parameter is measured in a unit of typical size
(:data:`PARAMETER_UNITS`: 100 px focal length, 10 px principal point, 0.01 for k1/k2, 0.001 for
p1/p2, 1 mrad, 1 mm; :data:`SCREEN_HEIGHT_UNIT_MM` = 0.1 mm for screen heights) and the normal equations are Jacobi-scaled to unit diagonal (Marquardt's
scaling), so that the damping and the reported :attr:`CalibrationResult.condition_number` do not
depend on units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..errors import SetupError
from ..geometry.camera import Camera
from ..geometry.cover_glass import CoverGlass
from ..geometry.transform import RigidTransform, rotvec_to_matrix
from .errors import CalibrationDataError
from .screen import ScreenModel


# ============================================================================ constants
#: Names of the 14 per-camera parameters (prefixed ``"<camera>."`` in parameter names).
CAMERA_PARAMETERS = (
    "fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2",
    "rotvec_x", "rotvec_y", "rotvec_z", "position_x_mm", "position_y_mm", "position_z_mm",
)
#: Names of the 3 per-mirror-pose parameters (prefixed ``"mirror<k>."``).
MIRROR_PARAMETERS = ("tilt_a", "tilt_b", "d_mm")
#: Internal unit of each parameter (the Jacobian columns are multiplied by these).
PARAMETER_UNITS = {
    "fx_px": 100.0, "fy_px": 100.0, "ppx_px": 10.0, "ppy_px": 10.0,
    "k1": 0.01, "k2": 0.01, "p1": 1e-3, "p2": 1e-3,
    "rotvec_x": 1e-3, "rotvec_y": 1e-3, "rotvec_z": 1e-3,
    "position_x_mm": 1.0, "position_y_mm": 1.0, "position_z_mm": 1.0,
    "tilt_a": 1e-3, "tilt_b": 1e-3, "d_mm": 1.0,
}
_INTRINSICS = CAMERA_PARAMETERS[:8]  # the Camera fields among them, in order
_NC = len(CAMERA_PARAMETERS)
_NM = len(MIRROR_PARAMETERS)
_NB = _NC + _NM  # parameters touched by one residual (besides the screen heights)
_NJ = _NB + 3  # width of the kernel's Jacobian buffer: the 17 block columns, then ∂r/∂q_z, ∂r/∂q_x, ∂r/∂q_y
_CAM_UNITS = np.array([PARAMETER_UNITS[p] for p in CAMERA_PARAMETERS])
_MIR_UNITS = np.array([PARAMETER_UNITS[p] for p in MIRROR_PARAMETERS])

#: Internal unit of the free screen heights ``screen.h[j,i]_mm`` (mm).
SCREEN_HEIGHT_UNIT_MM = 0.1
#: Names of the cover glass's parameters (thickness t, index n), when free.
GLASS_PARAMETERS = ("screen.glass_thickness_mm", "screen.glass_index")
#: Internal units of the glass parameters (0.1 mm, 0.01).
GLASS_UNITS = (0.1, 0.01)
#: A correspondence "sees" a free screen control height (j, i) if its basis weight
#: |w_i(x_q)·w_j(y_q)| is at least this (the weight is 1 at the control point; the not-a-knot
#: basis decays by about 4× per grid interval); :func:`calibrate` needs ``min_correspondences``
#: such correspondences per free height.
SCREEN_WEIGHT_MIN = 0.1
#: Fewest correspondences accepted per (camera, mirror pose) block.
MIN_CORRESPONDENCES = 20
#: Fewest mirror poses per camera.
MIN_POSES = 3
#: Condition number of the Jacobi-scaled normal matrix above which the data are called degenerate.
DEFAULT_CONDITION_LIMIT = 1e12
#: Number of worst-determined parameter combinations kept in :attr:`CalibrationResult.weak_directions`.
WEAK_DIRECTIONS = 3
#: Relative tolerance of the recognition of degenerate mirror-plane configurations (parallel
#: planes, planes through one line) named in a :class:`CalibrationDegenerateError`.
_PLANE_HINT_TOL = 1e-4
_CHUNK = 2048  # correspondences per work item of the kernels


# ============================================================================ observations
def _as_points(a, shape_tail, name: str) -> np.ndarray:
    arr = np.array(a, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != shape_tail:
        raise CalibrationDataError(f"{name} must have shape (M, {shape_tail}), got {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class Observations:
    """Correspondences of one camera in one mirror pose: pixel ``uv_px[i]`` sees screen point
    ``q_screen_mm[i]`` (screen frame, mm) via the mirror.

    Parameters
    ----------
    camera : str
        Camera name (a key of :attr:`CalibrationState.cameras`).
    pose_index : int
        Index k of the mirror pose (into :attr:`CalibrationState.mirrors`).
    uv_px : array_like (M, 2)
        Pixel coordinates (u, v); (0, 0) is the centre of the top-left pixel.
    q_screen_mm : array_like (M, 3) or (M, 2)
        Screen points (x_q, y_q, z) in the screen frame; z = 0 for the planar screen model.
        (M, 2): the decoded pattern coordinates (x_q, y_q) only, stored with z = 0. When
        :func:`calibrate` is given a :class:`ScreenModel`, only (x_q, y_q) are used and z is the
        model's height h(x_q, y_q).
    q_std_mm : array_like (M, 2), optional
        Standard deviations of the decoded (x_q, y_q) (e.g. the decoder's
        :attr:`pmdsim.evaluation.phase.ScreenCoordinates.std_xy_mm`), used by :func:`calibrate` for the
        covariance only (their overall scale is estimated from the residuals: only ratios
        matter). None: the same for all correspondences and both coordinates.

    Raises
    ------
    CalibrationDataError
        On wrong shapes, mismatched lengths, non-finite values or non-positive ``q_std_mm``.
    """

    camera: str
    pose_index: int
    uv_px: np.ndarray
    q_screen_mm: np.ndarray
    q_std_mm: np.ndarray | None = None

    def __post_init__(self) -> None:
        where = f"observations of camera {self.camera!r}, mirror pose {self.pose_index}"
        if int(self.pose_index) != self.pose_index or self.pose_index < 0:
            raise CalibrationDataError(f"{where}: pose_index must be a non-negative integer")
        uv = _as_points(self.uv_px, 2, f"{where}: uv_px")
        q_in = np.asarray(self.q_screen_mm, dtype=float)
        if q_in.ndim == 2 and q_in.shape[1] == 2:
            q_in = np.column_stack([q_in, np.zeros(q_in.shape[0])])
        q = _as_points(q_in, 3, f"{where}: q_screen_mm")
        if uv.shape[0] != q.shape[0]:
            raise CalibrationDataError(
                f"{where}: uv_px has {uv.shape[0]} rows but q_screen_mm has {q.shape[0]}"
            )
        bad = ~(np.isfinite(uv).all(axis=1) & np.isfinite(q).all(axis=1))
        if bad.any():
            raise CalibrationDataError(
                f"{where}: {int(bad.sum())} of {uv.shape[0]} correspondences contain NaN or infinite "
                f"values (first at row {int(np.argmax(bad))}); drop invalid pixels before calibrating "
                f"(observations_from_mapping does this with the valid mask)"
            )
        if self.q_std_mm is not None:
            sd = _as_points(self.q_std_mm, 2, f"{where}: q_std_mm")
            if sd.shape[0] != uv.shape[0]:
                raise CalibrationDataError(f"{where}: q_std_mm has {sd.shape[0]} rows but uv_px has {uv.shape[0]}")
            if not np.all(np.isfinite(sd) & (sd > 0)):
                raise CalibrationDataError(f"{where}: q_std_mm must be positive and finite")
            sd.setflags(write=False)
            object.__setattr__(self, "q_std_mm", sd)
        uv.setflags(write=False)
        q.setflags(write=False)
        object.__setattr__(self, "pose_index", int(self.pose_index))
        object.__setattr__(self, "uv_px", uv)
        object.__setattr__(self, "q_screen_mm", q)

    @property
    def n(self) -> int:
        """Number of correspondences M."""
        return self.uv_px.shape[0]


def observations_from_mapping(
    camera: str,
    pose_index: int,
    screen_xy_mm: np.ndarray,
    valid: np.ndarray,
    stride: int = 8,
    screen_surface=None,
    screen_std_xy_mm: np.ndarray | None = None,
) -> Observations:
    """Correspondences from a decoded pixel → screen mapping, subsampled every ``stride`` pixels.

    Parameters
    ----------
    camera, pose_index
        As in :class:`Observations`.
    screen_xy_mm : ndarray (H, W, 2)
        Pattern coordinates (x_q, y_q) per pixel (e.g. :attr:`pmdsim.simulation.trace.Mapping.screen_xy_mm`
        or decoded phases converted to mm).
    valid : ndarray of bool (H, W)
        Pixels whose pattern coordinates are valid.
    stride : int
        Pixels u, v ≡ 0 (mod stride) are used.
    screen_surface : surface with ``height(x, y)``, optional
        The screen model; q's z is its height at (x_q, y_q). None: the plane z = 0.
    screen_std_xy_mm : ndarray (H, W, 2), optional
        Standard deviations of the pattern coordinates per pixel (e.g. the decoder's
        :attr:`pmdsim.evaluation.phase.ScreenCoordinates.std_xy_mm`): the observations' ``q_std_mm``.

    Raises
    ------
    CalibrationDataError
        On wrong shapes, or if a pixel marked valid has non-finite coordinates.
    """
    where = f"camera {camera!r}, mirror pose {pose_index}"
    xy = np.asarray(screen_xy_mm, dtype=float)
    ok = np.asarray(valid, dtype=bool)
    if xy.ndim != 3 or xy.shape[2] != 2:
        raise CalibrationDataError(f"{where}: screen_xy_mm must have shape (H, W, 2), got {xy.shape}")
    if ok.shape != xy.shape[:2]:
        raise CalibrationDataError(f"{where}: valid must have shape {xy.shape[:2]}, got {ok.shape}")
    s = int(stride)
    if s != stride or s < 1:
        raise CalibrationDataError(f"stride must be a positive integer, got {stride!r}")
    sub_xy = xy[::s, ::s]
    sub_ok = ok[::s, ::s]
    nonfinite = sub_ok & ~np.isfinite(sub_xy).all(axis=-1)
    if nonfinite.any():
        raise CalibrationDataError(
            f"{where}: {int(nonfinite.sum())} pixels marked valid have NaN or infinite screen "
            f"coordinates; mark them invalid"
        )
    vv, uu = np.nonzero(sub_ok)
    uv = np.stack([uu * s, vv * s], axis=-1).astype(float)
    xyq = sub_xy[vv, uu]
    z = np.zeros(len(uv)) if screen_surface is None else np.asarray(
        screen_surface.height(xyq[:, 0], xyq[:, 1]), dtype=float)
    sd = None
    if screen_std_xy_mm is not None:
        sd_map = np.asarray(screen_std_xy_mm, dtype=float)
        if sd_map.shape != xy.shape:
            raise CalibrationDataError(f"{where}: screen_std_xy_mm must have shape {xy.shape}, got {sd_map.shape}")
        sd = sd_map[::s, ::s][vv, uu]
    return Observations(camera, int(pose_index), uv, np.column_stack([xyq, z]), sd)


# ============================================================================ parameters
@dataclass(frozen=True, eq=False)
class CameraParams:
    """One camera's calibration parameters: intrinsics and pose ``T_screen_cam``."""

    camera: Camera
    T_screen_cam: RigidTransform

    @property
    def position_mm(self) -> np.ndarray:
        """Camera centre in the screen frame."""
        return self.T_screen_cam.translation


def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - np.dot(a, n) * n
    e1 /= math.sqrt(float(e1 @ e1))
    # n × e1, written out (np.cross costs ~20× more, and this runs per mirror and evaluation).
    e2 = np.array([n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2], n[0] * e1[1] - n[1] * e1[0]])
    return e1, e2


@dataclass(frozen=True, eq=False)
class MirrorPlane:
    """A mirror plane {x : n·x = d} in the screen frame (n is normalised on construction)."""

    normal: np.ndarray
    d_mm: float

    def __post_init__(self) -> None:
        n = np.array(self.normal, dtype=float).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not math.isfinite(float(self.d_mm)):
            raise CalibrationDataError(f"MirrorPlane needs a finite normal (3,) and d, got {self.normal!r}, {self.d_mm!r}")
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            raise CalibrationDataError("MirrorPlane normal must not be zero")
        n = n / norm
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "d_mm", float(self.d_mm))

    def tangent_basis(self) -> tuple[np.ndarray, np.ndarray]:
        """(e1, e2): the orthonormal tangent vectors of the tilt increments tilt_a, tilt_b."""
        return _tangent_basis(self.normal)

    def reflect(self, points_mm) -> np.ndarray:
        """Mirror points (..., 3) across the plane: q' = q − 2 (n·q − d) n."""
        q = np.asarray(points_mm, dtype=float)
        s = q @ self.normal - self.d_mm
        return q - 2.0 * s[..., None] * self.normal

    def oriented_towards(self, point_mm) -> "MirrorPlane":
        """The same plane with the normal pointing to the side of ``point_mm``."""
        if float(np.dot(self.normal, point_mm)) - self.d_mm < 0:
            return MirrorPlane(-self.normal, -self.d_mm)
        return self


@dataclass(frozen=True, eq=False)
class CalibrationState:
    """All calibration parameters: cameras by name (in parameter order), mirror planes by
    pose index (in the screen frame) and, optionally, the screen model whose free control
    heights are estimated (None: the correspondences' q are used as given, e.g. the plane z = 0)
    and the screen's cover glass (None: none) with the flags ``glass_free`` = (thickness free,
    index free) (:mod:`pmdsim.calibration.glass`)."""

    cameras: dict[str, CameraParams]
    mirrors: tuple[MirrorPlane, ...]
    screen: ScreenModel | None = None
    glass: CoverGlass | None = None
    glass_free: tuple[bool, bool] = (False, False)

    def __post_init__(self) -> None:
        cams = dict(self.cameras)
        mirrors = tuple(self.mirrors)
        for name, cp in cams.items():
            if not isinstance(name, str) or not isinstance(cp, CameraParams):
                raise TypeError(f"CalibrationState.cameras must map names (str) to CameraParams, got {name!r}: {type(cp).__name__}")
            if not cp.camera.is_brown:
                raise SetupError(f"camera {name!r} has OpenCV distortion terms beyond Brown's (k4–k6, s1–s4): the "
                                 f"calibration estimates only fx, fy, the principal point and k1, k2, p1, p2, k3 "
                                 f"(paper eq. (3)); set the other terms to 0 to calibrate this camera")
        for k, mp in enumerate(mirrors):
            if not isinstance(mp, MirrorPlane):
                raise TypeError(f"CalibrationState.mirrors[{k}] must be a MirrorPlane, got {type(mp).__name__}")
        if self.screen is not None and not isinstance(self.screen, ScreenModel):
            raise TypeError(f"CalibrationState.screen must be a ScreenModel or None, got {type(self.screen).__name__}")
        if self.glass is not None and not isinstance(self.glass, CoverGlass):
            raise TypeError(f"CalibrationState.glass must be a CoverGlass or None, got {type(self.glass).__name__}")
        free = tuple(bool(f) for f in self.glass_free)
        if len(free) != 2 or (any(free) and self.glass is None):
            raise ValueError(f"CalibrationState.glass_free must be two flags (thickness, index) and needs a glass, "
                             f"got {self.glass_free!r} with glass {self.glass!r}")
        object.__setattr__(self, "glass_free", free)
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "mirrors", mirrors)

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)

    def parameter_names(self) -> list[str]:
        """Names of the parameter vector, e.g. ``left.fx_px``, ``mirror3.d_mm``, then the free
        screen heights ``screen.h[j,i]_mm``."""
        names = [f"{c}.{p}" for c in self.cameras for p in CAMERA_PARAMETERS]
        names += [f"mirror{k}.{p}" for k in range(len(self.mirrors)) for p in MIRROR_PARAMETERS]
        if self.screen is not None:
            names += self.screen.free_names()
        names += [GLASS_PARAMETERS[g] for g in self.glass_index]
        return names

    @property
    def glass_active(self) -> bool:
        """True when the model includes the cover glass (a thickness > 0 or a free parameter)."""
        return self.glass is not None and (self.glass.present or any(self.glass_free))

    @property
    def glass_index(self) -> tuple[int, ...]:
        """Which glass parameters are free: 0 thickness, 1 index (in parameter order)."""
        return tuple(g for g in (0, 1) if self.glass_free[g])

    @property
    def n_glass(self) -> int:
        """Number of free glass parameters (0–2)."""
        return len(self.glass_index)

    @property
    def n_screen(self) -> int:
        """Number of free screen heights (0 without a screen model)."""
        return 0 if self.screen is None else self.screen.n_free

    @property
    def n_parameters(self) -> int:
        return _NC * len(self.cameras) + _NM * len(self.mirrors) + self.n_screen + self.n_glass

    def updated(self, delta) -> "CalibrationState":
        """The state moved by the increment ``delta`` (natural units, in :meth:`parameter_names`
        order; see the module docstring for what each increment means)."""
        delta = np.asarray(delta, dtype=float)
        if delta.shape != (self.n_parameters,):
            raise ValueError(f"delta must have shape ({self.n_parameters},), got {delta.shape}")
        cams = {}
        for i, (name, cp) in enumerate(self.cameras.items()):
            dc = delta[_NC * i : _NC * (i + 1)]
            c = cp.camera
            cam = replace(c, **{f: float(getattr(c, f) + dc[j]) for j, f in enumerate(_INTRINSICS)})
            rot = _orthonormalize(rotvec_to_matrix(dc[8:11]) @ cp.T_screen_cam.rotation)
            cams[name] = CameraParams(cam, RigidTransform(rot, cp.T_screen_cam.translation + dc[11:14]))
        off = _NC * len(self.cameras)
        mirrors = []
        for k, m in enumerate(self.mirrors):
            dm = delta[off + _NM * k : off + _NM * (k + 1)]
            e1, e2 = m.tangent_basis()
            mirrors.append(MirrorPlane(m.normal + dm[0] * e1 + dm[1] * e2, m.d_mm + dm[2]))
        screen = self.screen
        off += _NM * len(self.mirrors)
        if screen is not None and screen.n_free:
            screen = screen.with_free_heights(screen.free_heights_mm + delta[off:off + self.n_screen])
        glass = self.glass
        if self.n_glass:
            dg = dict(zip(self.glass_index, delta[off + self.n_screen:]))
            glass = glass.with_(thickness_mm=glass.thickness_mm + dg.get(0, 0.0), index=glass.index + dg.get(1, 0.0))
        return CalibrationState(cams, tuple(mirrors), screen, glass, self.glass_free)

    def increment_to(self, other: "CalibrationState") -> np.ndarray:
        """The increment δ (n,) with ``self.updated(δ)`` equal to ``other`` (to rounding): the
        inverse of :meth:`updated`, in the coordinates of the reported covariance (e.g. to
        compare two calibrations, or an estimate with the truth, in units of its σ).

        Intrinsics, positions, mirror distances and screen heights: differences; rotations:
        the rotation vector of R_other·R_selfᵀ (about the screen axes); mirror tilts: (a, b)
        with n_other ∝ n_self + a·e1 + b·e2 (tangent basis of ``self``; a mirror whose normal
        points the other way is first flipped, (n, d) → (−n, −d): the same plane).

        Raises
        ------
        ValueError
            If the two states differ in cameras (names or order), number of mirrors or screen
            model (grid and free mask), or two mirror normals are perpendicular.
        """
        if not isinstance(other, CalibrationState):
            raise TypeError(f"other must be a CalibrationState, got {type(other).__name__}")
        if list(self.cameras) != list(other.cameras) or len(self.mirrors) != len(other.mirrors):
            raise ValueError(
                f"the states differ in their parameters: cameras {list(self.cameras)} vs {list(other.cameras)}, "
                f"{len(self.mirrors)} vs {len(other.mirrors)} mirrors")
        if (self.screen is None) != (other.screen is None) or (
                self.screen is not None and not (
                    np.array_equal(self.screen.grid_x_mm, other.screen.grid_x_mm)
                    and np.array_equal(self.screen.grid_y_mm, other.screen.grid_y_mm)
                    and np.array_equal(self.screen.free, other.screen.free))):
            raise ValueError("the states differ in their screen models (grid or free heights)")
        if self.glass_free != other.glass_free:
            raise ValueError("the states differ in their free glass parameters")
        out = []
        for cp, co in zip(self.cameras.values(), other.cameras.values()):
            out += [getattr(co.camera, f) - getattr(cp.camera, f) for f in _INTRINSICS]
            out += list(_matrix_to_rotvec(co.T_screen_cam.rotation @ cp.T_screen_cam.rotation.T))
            out += list(co.T_screen_cam.translation - cp.T_screen_cam.translation)
        for k, (m, mo) in enumerate(zip(self.mirrors, other.mirrors)):
            n_o, d_o = (mo.normal, mo.d_mm) if mo.normal @ m.normal >= 0 else (-mo.normal, -mo.d_mm)
            c = float(n_o @ m.normal)
            if c < 1e-9:
                raise ValueError(f"mirror {k}: the normals of the two states are perpendicular")
            e1, e2 = m.tangent_basis()
            out += [float(n_o @ e1) / c, float(n_o @ e2) / c, d_o - m.d_mm]
        if self.screen is not None:
            out += list(other.screen.free_heights_mm - self.screen.free_heights_mm)
        for g in self.glass_index:
            a, b = (self.glass.thickness_mm, other.glass.thickness_mm) if g == 0 else (self.glass.index, other.glass.index)
            out.append(b - a)
        return np.array(out, dtype=float)

    # kernel arrays ---------------------------------------------------------------------
    def _arrays(self):
        cps = list(self.cameras.values())
        intr = np.array([[cp.camera.fx_px, cp.camera.fy_px, cp.camera.ppx_px, cp.camera.ppy_px,
                          cp.camera.k1, cp.camera.k2, cp.camera.p1, cp.camera.p2, cp.camera.k3]
                         for cp in cps]).reshape(-1, 9)
        rot = np.array([cp.T_screen_cam.rotation for cp in cps]).reshape(-1, 3, 3)
        cen = np.array([cp.T_screen_cam.translation for cp in cps]).reshape(-1, 3)
        mir = np.array([np.r_[m.normal, m.d_mm] for m in self.mirrors]).reshape(-1, 4)
        basis = [m.tangent_basis() for m in self.mirrors]
        e1 = np.array([b[0] for b in basis]).reshape(-1, 3)
        e2 = np.array([b[1] for b in basis]).reshape(-1, 3)
        return intr, rot, cen, mir, e1, e2


def _orthonormalize(r: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(r)
    out = u @ vt
    if np.linalg.det(out) < 0:  # cannot happen for a near-rotation; keep it proper regardless
        u[:, -1] *= -1
        out = u @ vt
    return out


def _matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    theta = math.acos(c)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if theta < 1e-8:
        return 0.5 * w
    if theta > math.pi - 1e-6:  # near π: axis from the symmetric part
        b = (r + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(b)))
        axis = b[:, i] / math.sqrt(b[i, i])
        if np.dot(axis, w) < 0:
            axis = -axis
        return theta * axis
    return theta / (2.0 * math.sin(theta)) * w


# ============================================================================ initialisation
def _as_T(pose) -> RigidTransform:
    if isinstance(pose, RigidTransform):
        return pose
    t = getattr(pose, "T_world_x", None)
    if isinstance(t, RigidTransform):
        return t
    raise TypeError(f"mirror poses must be RigidTransform T_world_mirror or setup.Pose, got {type(pose).__name__}")


def mirror_plane_from_pose(T_world_mirror, T_world_screen: RigidTransform) -> MirrorPlane:
    """The plane z = 0 of the mirror frame, in the screen frame (n = mirror +z)."""
    T = _as_T(T_world_mirror)
    T_screen_mirror = T_world_screen.inv() @ T
    n = T_screen_mirror.rotation[:, 2]
    return MirrorPlane(n, float(n @ T_screen_mirror.translation))


def nominal_state(setup, mirror_poses: Sequence) -> CalibrationState:
    """Initial state from a setup's nominal cameras and screen and nominal mirror poses.

    Parameters
    ----------
    setup : pmdsim.setup.Setup
        Its cameras (intrinsics and ``T_world_cam``) and screen pose ``T_world_screen``.
    mirror_poses : sequence of RigidTransform (T_world_mirror) or setup.Pose
        The mirror is the plane z = 0 of its frame.

    Returns
    -------
    CalibrationState
        Cameras with T_screen_cam = T_world_screen⁻¹ ∘ T_world_cam; mirror planes in the screen
        frame with normals pointing towards the cameras.
    """
    T_ws = setup.screen.T_world_screen
    T_sw = T_ws.inv()
    cams = {name: CameraParams(cs.camera, T_sw @ cs.T_world_cam) for name, cs in setup.cameras.items()}
    ref = np.mean([cp.T_screen_cam.translation for cp in cams.values()], axis=0)
    mirrors = tuple(mirror_plane_from_pose(p, T_ws).oriented_towards(ref) for p in mirror_poses)
    return CalibrationState(cams, mirrors)


def _random_unit(rng: np.random.Generator, dim: int) -> np.ndarray:
    v = rng.normal(size=dim)
    return v / np.linalg.norm(v)


def perturbed_state(
    state: CalibrationState,
    rng: np.random.Generator,
    position_mm: float = 5.0,
    angle_deg: float = 2.0,
    focal_frac: float = 0.03,
    pp_px: float = 20.0,
    mirror_mm: float = 3.0,
    mirror_deg: float = 1.0,
    *,
    reset_distortion: bool = True,
) -> CalibrationState:
    """A copy of ``state`` with errors of the given sizes in random directions (for tests and
    experiments: a calibration must not start from the true values).

    Each camera centre moves by ``position_mm`` in a random direction and rotates by
    ``angle_deg`` about a random axis; fx and fy change by ±``focal_frac`` (independent random
    signs); the principal point moves by ``pp_px`` in a random direction; distortion
    coefficients k1, k2, p1, p2 are set to 0 (``reset_distortion``; k3 is kept). Each mirror
    plane moves by ±``mirror_mm`` along its normal and its normal tilts by ``mirror_deg`` in a
    random direction.
    """
    cams = {}
    for name, cp in state.cameras.items():
        c = cp.camera
        sx, sy = rng.choice([-1.0, 1.0], size=2)
        dpp = pp_px * _random_unit(rng, 2)
        kw = dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0) if reset_distortion else {}
        cam = replace(c, fx_px=float(c.fx_px * (1 + sx * focal_frac)), fy_px=float(c.fy_px * (1 + sy * focal_frac)),
                      ppx_px=float(c.ppx_px + dpp[0]), ppy_px=float(c.ppy_px + dpp[1]), **kw)
        rot = rotvec_to_matrix(math.radians(angle_deg) * _random_unit(rng, 3)) @ cp.T_screen_cam.rotation
        pos = cp.T_screen_cam.translation + position_mm * _random_unit(rng, 3)
        cams[name] = CameraParams(cam, RigidTransform(_orthonormalize(rot), pos))
    mirrors = []
    for mp in state.mirrors:
        e1, e2 = mp.tangent_basis()
        phi = rng.uniform(0, 2 * math.pi)
        t = math.tan(math.radians(mirror_deg))
        n = mp.normal + t * (math.cos(phi) * e1 + math.sin(phi) * e2)
        mirrors.append(MirrorPlane(n, mp.d_mm + rng.choice([-1.0, 1.0]) * mirror_mm))
    return CalibrationState(cams, tuple(mirrors))


# ============================================================================ uncertainty check
#: The parameter blocks of :meth:`SpreadComparison.block_ratios`.
PARAMETER_BLOCKS = ("intrinsics", "camera_poses", "mirrors", "screen")


def parameter_block(name: str) -> str:
    """The block of a parameter: ``"intrinsics"`` (fx … p2 of any camera), ``"camera_poses"``
    (rotvec, position), ``"mirrors"`` (tilts, d) or ``"screen"`` (free heights, cover glass)."""
    head, _, kind = name.partition(".")
    if head == "screen":
        return "screen"
    if head.startswith("mirror") and head[6:].isdigit():
        return "mirrors"
    return "intrinsics" if kind in _INTRINSICS else "camera_poses"


def parameter_group(name: str) -> str:
    """The group of a parameter for pooled statistics: the camera parameter's kind
    (``"left.fx_px"`` → ``"fx_px"``), ``"mirror.<kind>"`` for mirror parameters
    (``"mirror3.d_mm"`` → ``"mirror.d_mm"``), ``"screen.h_mm"`` for free screen heights."""
    head, _, kind = name.partition(".")
    if name in GLASS_PARAMETERS:
        return name
    if head == "screen":
        return "screen.h_mm"
    if head.startswith("mirror") and head[6:].isdigit():
        return f"mirror.{kind}"
    return kind
