"""The calibration's covariance carried by a setup, and the parameter steps it is defined for.

A calibrated setup (:func:`pmdsim.calibration.calibrated_setup`, ``pmdsim calibrate``) carries
the covariance of the calibrated parameters that the evaluation uses: a
:class:`CalibrationCovariance` (``Setup.calibration_covariance``; in the setup file the keys
``covariance_parameters`` and ``covariance`` of ``[calibration_report]``). Its coordinates are
the calibration's increments (:mod:`pmdsim.calibration.model`, "Parameterisation"), with the
base mirror plane renamed as the table plane of the setup:

* ``<camera>.fx_px``, ``.fy_px``, ``.ppx_px``, ``.ppy_px``, ``.k1``, ``.k2``, ``.p1``, ``.p2``:
  additive; ``<camera>.rotvec_x/y/z`` (rad): a rotation-vector increment of the camera's
  orientation about the *screen* axes, R_screen_cam ← exp([δ]×)·R_screen_cam;
  ``<camera>.position_x/y/z_mm``: the camera centre, screen frame, additively;
* ``table.tilt_a``, ``table.tilt_b`` (rad), ``table.d_mm``: the table plane (the calibration's
  base mirror plane {x : n·x = d}, screen frame, n towards the cameras), n ← normalize(n + a·e1
  + b·e2) with the calibration's tangent basis (e1, e2) of n, d ← d + δd;
* ``screen.h[j,i]_mm``: the screen's control height (row j ↔ y_j, column i ↔ x_i), additively;
* ``screen.glass_thickness_mm``, ``screen.glass_index``: the cover glass, additively.

:func:`perturbed_setup` applies such a step to a setup (the inverse direction of the bridge
:func:`pmdsim.calibration.calibrated_setup`); the evaluation propagates the covariance with it
(:mod:`pmdsim.evaluation.uncertainty_calibration`, docs/conventions.md "Uncertainty from the
calibration").
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace

import numpy as np

from ..errors import SetupError
from ..geometry.transform import RigidTransform, rotvec_to_matrix

__all__ = ["CalibrationCovariance", "CAMERA_PARAMETER_NAMES", "TABLE_PARAMETER_NAMES", "SCREEN_PARAMETER_NAMES",
           "perturbed_setup", "is_setup_parameter", "table_plane", "tangent_basis"]

#: The 14 per-camera parameters (as :data:`pmdsim.calibration.model.CAMERA_PARAMETERS`).
CAMERA_PARAMETER_NAMES = (
    "fx_px", "fy_px", "ppx_px", "ppy_px", "k1", "k2", "p1", "p2",
    "rotvec_x", "rotvec_y", "rotvec_z", "position_x_mm", "position_y_mm", "position_z_mm",
)
#: The table plane's 3 parameters (the calibration's base mirror plane).
TABLE_PARAMETER_NAMES = ("table.tilt_a", "table.tilt_b", "table.d_mm")
#: The cover glass's parameters (added to the screen's when the calibration fits them).
SCREEN_PARAMETER_NAMES = ("screen.glass_thickness_mm", "screen.glass_index")
_SCREEN_HEIGHT = re.compile(r"screen\.h\[(\d+),(\d+)\]_mm\Z")
_CAMERA = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\.(" + "|".join(CAMERA_PARAMETER_NAMES) + r")\Z")
_SYM_TOL = 1e-8  # relative asymmetry accepted (rounding of the sandwich product)
_PSD_TOL = 1e-8  # most negative eigenvalue accepted, relative to the correlation matrix


def is_setup_parameter(name: str) -> bool:
    """True if ``name`` is a parameter a setup's covariance can carry (module docstring)."""
    return bool(name in TABLE_PARAMETER_NAMES or name in SCREEN_PARAMETER_NAMES
                or _SCREEN_HEIGHT.match(name) or (_CAMERA.match(name) and not name.startswith(("table.", "screen."))))


@dataclass(frozen=True, eq=False)
class CalibrationCovariance:
    """The covariance of calibrated setup parameters (module docstring for the names and units).

    Parameters
    ----------
    parameters : sequence of str
        P distinct parameter names (:func:`is_setup_parameter`).
    matrix : array_like (P, P)
        Covariance in the parameters' natural units (px, rad, mm, unitless); symmetric (to
        1e-8 relative) and positive semi-definite (eigenvalues of the correlation matrix ≥
        −1e-8); stored symmetrised and read-only.

    Raises
    ------
    SetupError
        Naming the problem (unknown or repeated name, wrong shape, non-finite, asymmetric, not
        positive semi-definite).
    """

    parameters: tuple
    matrix: np.ndarray

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.parameters)
        bad = [n for n in names if not is_setup_parameter(n)]
        if bad:
            raise SetupError(f"calibration covariance: unknown parameter name(s) {bad[:5]} (expected "
                             f"<camera>.<{'|'.join(CAMERA_PARAMETER_NAMES[:4])}|…>, table.tilt_a/tilt_b/d_mm, "
                             f"screen.h[j,i]_mm, screen.glass_thickness_mm, screen.glass_index)")
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise SetupError(f"calibration covariance: parameter name(s) {dup[:5]} repeated")
        c = np.array(self.matrix, dtype=float)
        p = len(names)
        if c.shape != (p, p):
            raise SetupError(f"calibration covariance must be {p} × {p} (one row and column per parameter), "
                             f"got shape {c.shape}")
        if not np.isfinite(c).all():
            raise SetupError("calibration covariance must be finite")
        dg = np.diag(c).copy()
        if (dg < 0).any():
            j = int(np.argmin(dg))
            raise SetupError(f"calibration covariance: negative variance {dg[j]:.3g} of {names[j]}")
        s = np.sqrt(dg)
        scale = np.outer(s, s)
        asym = np.abs(c - c.T)
        if (asym > _SYM_TOL * scale + 1e-300).any():
            i, j = np.unravel_index(int(np.argmax(asym - _SYM_TOL * scale)), asym.shape)
            raise SetupError(f"calibration covariance is not symmetric: [{names[i]}, {names[j]}] = {c[i, j]:.6g} "
                             f"but [{names[j]}, {names[i]}] = {c[j, i]:.6g}")
        c = 0.5 * (c + c.T)
        if p:
            with np.errstate(invalid="ignore", divide="ignore"):
                r = np.where(scale > 0, c / np.where(scale > 0, scale, 1.0), 0.0)
            lo = float(np.linalg.eigvalsh(r)[0])
            if lo < -_PSD_TOL:
                raise SetupError(f"calibration covariance is not positive semi-definite (smallest eigenvalue of the "
                                 f"correlation matrix {lo:.3g})")
        c.setflags(write=False)
        object.__setattr__(self, "parameters", names)
        object.__setattr__(self, "matrix", c)

    def __eq__(self, other) -> bool:
        return (isinstance(other, CalibrationCovariance) and self.parameters == other.parameters
                and np.array_equal(self.matrix, other.matrix))

    def __hash__(self) -> int:
        return hash((self.parameters, self.matrix.tobytes()))

    def __repr__(self) -> str:
        return f"CalibrationCovariance({len(self.parameters)} parameters)"

    @property
    def std(self) -> np.ndarray:
        """(P,) standard deviations √diag."""
        return np.sqrt(np.diag(self.matrix))

    def subset(self, names) -> "CalibrationCovariance":
        """The marginal covariance of ``names`` (a Gaussian's marginal: the sub-block), in that order."""
        idx = [self.parameters.index(n) for n in names]
        return CalibrationCovariance(tuple(names), self.matrix[np.ix_(idx, idx)])

    def binned(self, factor: int) -> "CalibrationCovariance":
        """The covariance for cameras binned ``factor`` × ``factor`` (:meth:`Camera.binned`:
        focal lengths and principal points scale by 1/factor; nothing else changes)."""
        j = np.array([1.0 / factor if n.rsplit(".", 1)[-1] in CAMERA_PARAMETER_NAMES[:4] and not
                      n.startswith(("table.", "screen.")) else 1.0 for n in self.parameters])
        return CalibrationCovariance(self.parameters, self.matrix * np.outer(j, j))

    def check_setup(self, setup) -> None:
        """Raise :class:`SetupError` if a parameter does not exist in ``setup`` (an unknown camera,
        a screen control height outside its grid)."""
        ny, nx = len(setup.screen.grid_y_mm), len(setup.screen.grid_x_mm)
        for n in self.parameters:
            m = _SCREEN_HEIGHT.match(n)
            if m and not (int(m.group(1)) < ny and int(m.group(2)) < nx):
                raise SetupError(f"calibration covariance parameter {n!r}: the screen grid has {ny} × {nx} control "
                                 f"heights")
            m = _CAMERA.match(n)
            if m and not m.group(0).startswith(("table.", "screen.")) and m.group(1) not in setup.cameras:
                raise SetupError(f"calibration covariance parameter {n!r}: no camera {m.group(1)!r} in the setup "
                                 f"(cameras: {', '.join(setup.cameras)})")

    def as_dict(self) -> dict:
        """``{"covariance_parameters": [...], "covariance": [[...], ...]}`` (the TOML keys)."""
        return {"covariance_parameters": list(self.parameters),
                "covariance": [[float(v) for v in row] for row in self.matrix]}


# ============================================================================ steps
def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The calibration's tangent basis (e1, e2) of a unit normal n (its mirror tilts' axes)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - np.dot(a, n) * n
    e1 /= math.sqrt(float(e1 @ e1))
    return e1, np.cross(n, e1)


def table_plane(setup) -> tuple[np.ndarray, float]:
    """The setup's table plane (its sample frame's x–y plane) as the calibration's mirror plane
    in the screen frame: (n (3,), d) with n·x = d, n towards the cameras (−z of the sample)."""
    T_screen_sample = setup.screen.T_world_screen.inv() @ setup.sample.T_world_sample
    n = -T_screen_sample.rotation[:, 2]
    return n, float(n @ T_screen_sample.translation)


def _table_frame(setup, n_screen: np.ndarray, d_mm: float) -> RigidTransform:
    """``T_world_sample`` on the plane (n, d) (screen frame): +z = −n, origin and +x the current
    sample frame's projected onto the plane (as the bridge's ``table_frame_from_plane``)."""
    T_ws = setup.screen.T_world_screen
    T_cur = setup.sample.T_world_sample
    z = -T_ws.apply_vector(n_screen)
    p0 = T_ws.apply(n_screen * d_mm)
    o = T_cur.translation - np.dot(T_cur.translation - p0, z) * z
    x = T_cur.rotation[:, 0] - np.dot(T_cur.rotation[:, 0], z) * z
    x /= np.linalg.norm(x)
    return RigidTransform(np.column_stack([x, np.cross(z, x), z]), o)


def perturbed_setup(setup, delta, names=None):
    """The setup moved by a step ``delta`` of its calibration parameters (module docstring).

    Parameters
    ----------
    setup : Setup
    delta : array_like (P,)
        The step, natural units, in the order of ``names``.
    names : sequence of str, optional
        The parameters of ``delta``; default the setup's ``calibration_covariance.parameters``.

    Returns
    -------
    Setup
        Cameras, table frame (sample pose), screen heights and glass changed; the covariance kept.

    Raises
    ------
    SetupError
        For a name that is not a setup parameter or not in this setup, or a wrong length.
    """
    from .model import CameraSetup, Pose

    if names is None:
        if setup.calibration_covariance is None:
            raise SetupError("perturbed_setup: the setup carries no calibration covariance; give the names")
        names = setup.calibration_covariance.parameters
    names = tuple(names)
    delta = np.asarray(delta, dtype=float).reshape(-1)
    if delta.shape != (len(names),):
        raise SetupError(f"perturbed_setup: delta has {delta.size} entries for {len(names)} parameters")
    CalibrationCovariance(names, np.zeros((len(names), len(names)))).check_setup(setup)
    step = dict(zip(names, delta))
    T_ws = setup.screen.T_world_screen
    cams = {}
    for cam, cs in setup.cameras.items():
        g = {p: step.get(f"{cam}.{p}", 0.0) for p in CAMERA_PARAMETER_NAMES}
        if not any(g.values()):
            cams[cam] = cs
            continue
        c = cs.camera
        camera = replace(c, **{p: float(getattr(c, p) + g[p]) for p in CAMERA_PARAMETER_NAMES[:8]})
        # Screen-frame increments: R_sc ← exp(δ)·R_sc, c_s ← c_s + δ; in world R_ws·exp(δ)·R_wsᵀ.
        rv = np.array([g["rotvec_x"], g["rotvec_y"], g["rotvec_z"]])
        dp = np.array([g["position_x_mm"], g["position_y_mm"], g["position_z_mm"]])
        T = cs.T_world_cam
        R = T_ws.rotation @ rotvec_to_matrix(rv) @ T_ws.rotation.T @ T.rotation
        cams[cam] = CameraSetup(camera, Pose.from_transform(RigidTransform(R, T.translation + T_ws.apply_vector(dp))))
    out = replace(setup, cameras=cams)
    a, b, dd = (step.get(n, 0.0) for n in TABLE_PARAMETER_NAMES)
    if a or b or dd:
        n, d = table_plane(setup)
        e1, e2 = tangent_basis(n)
        n2 = n + a * e1 + b * e2
        n2 /= np.linalg.norm(n2)
        out = replace(out, sample=replace(out.sample, pose=Pose.from_transform(_table_frame(setup, n2, d + dd))))
    scr = out.screen
    hs = [(n, v) for n, v in step.items() if _SCREEN_HEIGHT.match(n) and v]
    if hs:
        z = scr.control_heights()
        for n, v in hs:
            m = _SCREEN_HEIGHT.match(n)
            z[int(m.group(1)), int(m.group(2))] += v
        scr = replace(scr, heights_mm=tuple(tuple(float(v) for v in row) for row in z), bulge_mm=None)
    dt, dn = step.get("screen.glass_thickness_mm", 0.0), step.get("screen.glass_index", 0.0)
    if dt or dn:
        scr = replace(scr, cover_glass_thickness_mm=float(scr.cover_glass_thickness_mm + dt),
                      cover_glass_index=float(scr.cover_glass.index + dn))
    return replace(out, screen=scr) if scr is not out.screen else out
