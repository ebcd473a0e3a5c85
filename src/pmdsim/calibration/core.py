"""Holistic calibration with a planar mirror (paper §4): the numeric core.

Several cameras observe the pattern screen via a planar front-surface mirror placed in K poses.
Phase decoding gives, per camera c and mirror pose k, correspondences pixel (u, v) ↔ screen
point q (screen frame, mm; q = (x_q, y_q, 0) for the planar screen model, but any (M, 3) points
are accepted so that a non-planar screen model can be plugged in). This module estimates jointly

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

Non-planar screen (optional, paper §5)
--------------------------------------
With a :class:`ScreenModel` (``calibrate(..., screen_model=...)``) the screen is the pmdsim
not-a-knot spline surface over a control grid, and its free control heights are estimated
jointly: the correspondences' decoded (x_q, y_q) are used and their z is the model's height
h(x_q, y_q) = Σ_ji Z_ji w_j(y_q) w_i(x_q) (w: the cardinal basis splines of the grid axes; the
1-D weights are computed once per correspondence). ∂r/∂Z_ji = (∂r/∂q_z)·w_j(y_q)·w_i(x_q), with
∂r/∂q_z by the chain rule through the mirroring, the rigid transform and the projection.
**Gauge**: the screen frame stays the reference and its x–y plane is the plane of the screen's
rigid frame — the border control heights are held (normally 0) and only interior control points
may be free, since a piston or tilt of the screen cannot be separated from the camera poses and
mirror planes (:class:`ScreenModel` rejects free border points). A free height that fewer than
``min_correspondences`` correspondences see with basis weight ≥ :data:`SCREEN_WEIGHT_MIN` is
reported by name (:class:`CalibrationDataError`), as are combinations the condition check finds.

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

Solver
------
Levenberg–Marquardt on the dense normal equations (14 parameters per camera + 3 per pose, e.g.
76): a numba kernel accumulates JᵀJ and Jᵀr per (camera, pose) block with the analytic
Jacobian (chain rule through mirror, rigid transform, pinhole and distortion). Converged when
an accepted step changes the cost by less than ``ftol`` (1e-12) relative, when the Gauss–Newton
model predicts less than that, or when the Gauss–Newton step changes no parameter by more than
``xtol`` relative (:func:`calibrate`). The conditioning of the Jacobi-scaled JᵀJ is checked at
the start and after every step: a degenerate set of mirror poses raises
:class:`CalibrationDegenerateError` naming the badly determined parameters and, if recognised,
the degenerate configuration (all planes parallel; all planes through one line).

Uncertainties
-------------
The pixels are exact (pixel centres); the noise is in the decoded screen points (x_q, y_q)
(phase noise), isotropic and equal for all correspondences unless the observations give
``q_std_mm``. It reaches the pixel residual through B_k = ∂r_k/∂(x_q, y_q)·diag(q_std) (the
mirroring and the projection; with a screen model also through q_z = h(x_q, y_q)), which varies
over the image and is not isotropic there. The estimate is ordinary least squares in pixels, so
its covariance is the sandwich

    Cov = σ₀² (JᵀJ)⁻¹ (Σ_k J_kᵀ B_k B_kᵀ J_k) (JᵀJ)⁻¹,   σ₀² = Σ_k r_kᵀ (B_k B_kᵀ)⁻¹ r_k / (m − n)

(σ₀: :attr:`CalibrationResult.screen_noise_std`, the screen-point noise the residuals imply), in
natural units (px, mm, rad, unitless for distortion coefficients), for the increments above —
i.e. the rotation standard deviations are about the screen axes, the tilt standard deviations
are rotations of the mirror normal along e1 and e2. (For the paper's geometry it differs from
σ²(JᵀJ)⁻¹, σ² = SSR/(m − n), by ≤ 5 % per parameter; the Monte Carlo over image noise in
``tests/test_calibration_uncertainty.py`` checks it.) Parameters the data hardly determine are
reported: :attr:`CalibrationResult.weak_directions`, :attr:`CalibrationResult.std_inflation`,
:meth:`CalibrationResult.poorly_determined` (σ against a prior) and
:meth:`CalibrationResult.determination_report`; (nearly) free combinations raise
:class:`CalibrationDegenerateError`.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, replace
from typing import Iterable, Mapping, Sequence

import numba
import numpy as np

from ..geometry.camera import Camera
from ..errors import PmdsimError
from ..geometry.transform import RigidTransform, rotvec_to_matrix

__all__ = [
    "CalibrationError",
    "CalibrationDataError",
    "CalibrationDegenerateError",
    "Observations",
    "ScreenModel",
    "observations_from_mapping",
    "CameraParams",
    "MirrorPlane",
    "CalibrationState",
    "CalibrationResult",
    "WeakDirection",
    "calibrate",
    "residuals_and_jacobian",
    "nominal_state",
    "perturbed_state",
    "mirror_plane_from_pose",
    "CAMERA_PARAMETERS",
    "MIRROR_PARAMETERS",
    "PARAMETER_UNITS",
    "SCREEN_HEIGHT_UNIT_MM",
    "SCREEN_WEIGHT_MIN",
    "MIN_CORRESPONDENCES",
    "MIN_POSES",
    "DEFAULT_CONDITION_LIMIT",
    "WEAK_DIRECTIONS",
    "SpreadComparison",
    "compare_spread",
    "parameter_group",
    "parameter_block",
    "PARAMETER_BLOCKS",
]


# ============================================================================ errors
class CalibrationError(PmdsimError, RuntimeError):
    """The calibration did not converge (raised by ``calibrate(..., raise_on_failure=True)``)."""


class CalibrationDataError(PmdsimError, ValueError):
    """Calibration input that cannot give a calibration: too few poses or correspondences,
    NaN values, unknown cameras or poses, or a degenerate set of mirror poses. The message
    names the camera, the pose or the badly determined parameters."""


class CalibrationDegenerateError(CalibrationDataError):
    """The data do not determine some parameter combinations: the Jacobi-scaled normal matrix
    JᵀJ has a condition number above the limit (a rank deficiency, up to rounding). Raised by
    :func:`calibrate`; the message names the combinations and, if recognised, the degenerate
    mirror-pose configuration (all planes parallel, or all through one common line).

    Attributes
    ----------
    parameter_names : tuple[str, ...]
        All parameter names (the rows of ``directions``).
    parameters : tuple[str, ...]
        The badly determined parameters: those with a large component in a free combination.
    directions : ndarray (n, k)
        The k (nearly) free combinations in natural units (the parameterisation of
        :meth:`CalibrationState.updated`), each of unit length in internal units
        (:data:`PARAMETER_UNITS`): moving the parameters along a column changes the residuals
        by (almost) nothing.
    condition_number : float
    cause : str
        The recognised mirror-pose configuration, or the typical causes.
    """

    def __init__(self, message: str, *, parameter_names=(), parameters=(), directions=None,
                 condition_number: float = math.inf, cause: str = "") -> None:
        super().__init__(message)
        self.parameter_names = tuple(parameter_names)
        self.parameters = tuple(parameters)
        self.directions = np.zeros((len(self.parameter_names), 0)) if directions is None else np.asarray(directions)
        self.condition_number = float(condition_number)
        self.cause = cause


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


# ============================================================================ kernels
@numba.njit(cache=True)
def _model_row(u_obs, v_obs, qx, qy, qz, intr, rot, cen, mir, e1, e2, want_jac, jac):
    """Residual (predicted − observed, px) of one correspondence and, if ``want_jac``, its
    Jacobian (2 × 17) w.r.t. the block's parameters in natural units, written to ``jac[:, :17]``,
    and the derivatives w.r.t. the screen point, ∂r/∂q_z, ∂r/∂q_x, ∂r/∂q_y, written to
    ``jac[:, 17]``, ``jac[:, 18]``, ``jac[:, 19]`` (q's coordinates taken independently).

    intr: (9,) fx, fy, ppx, ppy, k1, k2, p1, p2, k3; rot: (3, 3) R_screen_cam; cen: (3,) camera
    centre in the screen frame; mir: (4,) n, d; e1, e2: tangent basis of n.
    Returns (ru, rv, ok) with ok False if the virtual point is not in front of the camera.
    """
    nx, ny, nz, dd = mir[0], mir[1], mir[2], mir[3]
    s = nx * qx + ny * qy + nz * qz - dd
    # Virtual (mirrored) screen point.
    wx = qx - 2.0 * s * nx - cen[0]
    wy = qy - 2.0 * s * ny - cen[1]
    wz = qz - 2.0 * s * nz - cen[2]
    # p = Rᵀ w.
    px = rot[0, 0] * wx + rot[1, 0] * wy + rot[2, 0] * wz
    py = rot[0, 1] * wx + rot[1, 1] * wy + rot[2, 1] * wz
    pz = rot[0, 2] * wx + rot[1, 2] * wy + rot[2, 2] * wz
    if not pz > 0.0:
        return 0.0, 0.0, False
    fx, fy, ppx, ppy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = intr[4], intr[5], intr[6], intr[7], intr[8]
    iz = 1.0 / pz
    x = px * iz
    y = py * iz
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    ru = fx * xd + ppx - u_obs
    rv = fy * yd + ppy - v_obs
    if not want_jac:
        return ru, rv, True
    for i in range(2):
        for j in range(_NJ):
            jac[i, j] = 0.0
    # Intrinsics.
    jac[0, 0] = xd
    jac[1, 1] = yd
    jac[0, 2] = 1.0
    jac[1, 3] = 1.0
    jac[0, 4] = fx * x * r2
    jac[1, 4] = fy * y * r2
    jac[0, 5] = fx * x * r2 * r2
    jac[1, 5] = fy * y * r2 * r2
    jac[0, 6] = fx * 2.0 * x * y
    jac[1, 6] = fy * (r2 + 2.0 * y * y)
    jac[0, 7] = fx * (r2 + 2.0 * x * x)
    jac[1, 7] = fy * 2.0 * x * y
    # d(xd, yd)/d(x, y).
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    c = b
    d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    # G = d(u, v)/d p (2 × 3); dx/dp = (1/z, 0, −x/z), dy/dp = (0, 1/z, −y/z).
    g00 = fx * a * iz
    g01 = fx * b * iz
    g02 = -fx * (a * x + b * y) * iz
    g10 = fy * c * iz
    g11 = fy * d * iz
    g12 = -fy * (c * x + d * y) * iz
    # H = G Rᵀ = d(u, v)/d w (screen frame): H[i, k] = Σ_j G[i, j] R[k, j].
    h00 = g00 * rot[0, 0] + g01 * rot[0, 1] + g02 * rot[0, 2]
    h01 = g00 * rot[1, 0] + g01 * rot[1, 1] + g02 * rot[1, 2]
    h02 = g00 * rot[2, 0] + g01 * rot[2, 1] + g02 * rot[2, 2]
    h10 = g10 * rot[0, 0] + g11 * rot[0, 1] + g12 * rot[0, 2]
    h11 = g10 * rot[1, 0] + g11 * rot[1, 1] + g12 * rot[1, 2]
    h12 = g10 * rot[2, 0] + g11 * rot[2, 1] + g12 * rot[2, 2]
    # Rotation increment R ← exp([δ]×) R: dp/dδ = Rᵀ [w]×, so d(u, v)_i/dδ = H_i × w.
    jac[0, 8] = h01 * wz - h02 * wy
    jac[0, 9] = h02 * wx - h00 * wz
    jac[0, 10] = h00 * wy - h01 * wx
    jac[1, 8] = h11 * wz - h12 * wy
    jac[1, 9] = h12 * wx - h10 * wz
    jac[1, 10] = h10 * wy - h11 * wx
    # Camera centre: dp/dc = −Rᵀ.
    jac[0, 11] = -h00
    jac[0, 12] = -h01
    jac[0, 13] = -h02
    jac[1, 11] = -h10
    jac[1, 12] = -h11
    jac[1, 13] = -h12
    # Mirror: dq'/dd = 2n, dq'/da = −2 (s e1 + (e1·q) n), likewise b with e2.
    hn0 = h00 * nx + h01 * ny + h02 * nz
    hn1 = h10 * nx + h11 * ny + h12 * nz
    he10 = h00 * e1[0] + h01 * e1[1] + h02 * e1[2]
    he11 = h10 * e1[0] + h11 * e1[1] + h12 * e1[2]
    he20 = h00 * e2[0] + h01 * e2[1] + h02 * e2[2]
    he21 = h10 * e2[0] + h11 * e2[1] + h12 * e2[2]
    e1q = e1[0] * qx + e1[1] * qy + e1[2] * qz
    e2q = e2[0] * qx + e2[1] * qy + e2[2] * qz
    jac[0, 14] = -2.0 * (s * he10 + e1q * hn0)
    jac[1, 14] = -2.0 * (s * he11 + e1q * hn1)
    jac[0, 15] = -2.0 * (s * he20 + e2q * hn0)
    jac[1, 15] = -2.0 * (s * he21 + e2q * hn1)
    jac[0, 16] = 2.0 * hn0
    jac[1, 16] = 2.0 * hn1
    # Screen point: dq'/dq = I − 2 n nᵀ, so d(u, v)/dq_i = H e_i − 2 n_i H n.
    jac[0, _NB] = h02 - 2.0 * nz * hn0
    jac[1, _NB] = h12 - 2.0 * nz * hn1
    jac[0, _NB + 1] = h00 - 2.0 * nx * hn0
    jac[1, _NB + 1] = h10 - 2.0 * nx * hn1
    jac[0, _NB + 2] = h01 - 2.0 * ny * hn0
    jac[1, _NB + 2] = h11 - 2.0 * ny * hn1
    return ru, rv, True


@numba.njit(cache=True)
def _chunk_run(start, end, cam, pose, uv, q, intr, rot, cen, mir, e1, e2, units, wx, wy, fi, fj, h_unit,
               want_normal, jtj, jtr, sandwich, slope, qstd):
    """Serial work item: correspondences start…end of one block. Accumulates the block's
    (scaled) JᵀJ (full square, the 17 block parameters then the F free screen heights) and Jᵀr
    if ``want_normal``. Returns (SSR, whitened SSR, number behind camera).

    Screen heights (F = ``fi.shape[0]`` may be 0): the column of free height f = (fj[f], fi[f])
    is (∂r/∂q_z)·wy[k, fj[f]]·wx[k, fi[f]] — rank one per correspondence, which the
    accumulation exploits.

    ``sandwich`` (with ``want_normal``): the noise is in the decoded screen point (x_q, y_q),
    standard deviations ``qstd[k]`` (2,), and propagates to the residual by
    B_k = ∂r/∂(x_q, y_q)·diag(qstd[k]) (2 × 2; with the screen's height slope ``slope[k]``
    (∂h/∂x, ∂h/∂y), since q_z = h(x_q, y_q)): Cov(r_k) ∝ B_k B_kᵀ. Then ``jtj`` receives
    Σ_k J_kᵀ B_k B_kᵀ J_k (the middle of the sandwich covariance) instead of JᵀJ, and the
    whitened SSR Σ_k r_kᵀ (B_k B_kᵀ)⁻¹ r_k is returned."""
    nf = fi.shape[0]
    npar = _NB + nf
    jac = np.zeros((2, _NJ))
    acc = np.zeros((npar, npar))
    accr = np.zeros(npar)
    sw = np.zeros(nf)
    jd = np.zeros(_NB)
    ssr = 0.0
    ssr_w = 0.0
    nbad = 0
    intr_c = intr[cam]
    rot_c = rot[cam]
    cen_c = cen[cam]
    mir_k = mir[pose]
    e1_k = e1[pose]
    e2_k = e2[pose]
    for k in range(start, end):
        ru, rv, ok = _model_row(uv[k, 0], uv[k, 1], q[k, 0], q[k, 1], q[k, 2], intr_c, rot_c,
                                cen_c, mir_k, e1_k, e2_k, want_normal, jac)
        if not ok:
            nbad += 1
            continue
        ssr += ru * ru + rv * rv
        if want_normal:
            for j in range(_NB):
                jac[0, j] *= units[j]
                jac[1, j] *= units[j]
            if sandwich:
                # B = ∂r/∂(x_q, y_q) with q_z = h(x_q, y_q), times diag(qstd).
                b00 = (jac[0, _NB + 1] + jac[0, _NB] * slope[k, 0]) * qstd[k, 0]
                b10 = (jac[1, _NB + 1] + jac[1, _NB] * slope[k, 0]) * qstd[k, 0]
                b01 = (jac[0, _NB + 2] + jac[0, _NB] * slope[k, 1]) * qstd[k, 1]
                b11 = (jac[1, _NB + 2] + jac[1, _NB] * slope[k, 1]) * qstd[k, 1]
                det = b00 * b11 - b01 * b10
                e0 = (b11 * ru - b01 * rv) / det  # B⁻¹ r: the residual on the screen, in σ
                e1w = (-b10 * ru + b00 * rv) / det
                ssr_w += e0 * e0 + e1w * e1w
                # J ← Bᵀ J (rows), so that the accumulated JᵀJ is Jᵀ B Bᵀ J.
                for j in range(_NB + 1):
                    j0 = jac[0, j]
                    j1 = jac[1, j]
                    jac[0, j] = b00 * j0 + b10 * j1
                    jac[1, j] = b01 * j0 + b11 * j1
            for i in range(_NB):
                a0 = jac[0, i]
                a1 = jac[1, i]
                accr[i] += a0 * ru + a1 * rv
                for j in range(_NB):  # full square: contiguous, vectorises better than a triangle
                    acc[i, j] += a0 * jac[0, j] + a1 * jac[1, j]
            if nf > 0:
                dz0 = jac[0, _NB] * h_unit
                dz1 = jac[1, _NB] * h_unit
                for f in range(nf):
                    sw[f] = wy[k, fj[f]] * wx[k, fi[f]]
                gz = dz0 * ru + dz1 * rv
                cz = dz0 * dz0 + dz1 * dz1
                for i in range(_NB):
                    jd[i] = jac[0, i] * dz0 + jac[1, i] * dz1
                for f in range(nf):
                    sf = sw[f]
                    accr[_NB + f] += gz * sf
                    for i in range(_NB):
                        acc[i, _NB + f] += jd[i] * sf
                    csf = cz * sf
                    for g in range(nf):
                        acc[_NB + f, _NB + g] += csf * sw[g]
    if want_normal:
        for f in range(nf):
            for i in range(_NB):
                acc[_NB + f, i] = acc[i, _NB + f]
        for i in range(npar):
            jtr[i] = accr[i]
            for j in range(npar):
                jtj[i, j] = acc[i, j]
    return ssr, ssr_w, nbad


@numba.njit(cache=True, parallel=True)
def _chunks_kernel(c_start, c_end, c_cam, c_pose, uv, q, intr, rot, cen, mir, e1, e2, units, wx, wy, fi, fj,
                   h_unit, want_normal, jtj, jtr, ssr, nbad, sandwich, slope, qstd, ssr_w):
    for c in numba.prange(c_start.shape[0]):
        s, sw, b = _chunk_run(c_start[c], c_end[c], c_cam[c], c_pose[c], uv, q, intr, rot, cen, mir,
                              e1, e2, units, wx, wy, fi, fj, h_unit, want_normal, jtj[c], jtr[c],
                              sandwich, slope, qstd)
        ssr[c] = s
        ssr_w[c] = sw
        nbad[c] = b


@numba.njit(cache=True)
def _rows_kernel(cam_idx, pose_idx, uv, q, intr, rot, cen, mir, e1, e2, res, jac, ok):
    """Residuals (N, 2), Jacobian blocks (N, 2, 18) in natural units (17 block columns, then
    ∂r/∂q_z) and validity, per row."""
    tmp = np.zeros((2, _NJ))
    for k in range(uv.shape[0]):
        c = cam_idx[k]
        p = pose_idx[k]
        ru, rv, good = _model_row(uv[k, 0], uv[k, 1], q[k, 0], q[k, 1], q[k, 2], intr[c], rot[c],
                                  cen[c], mir[p], e1[p], e2[p], True, tmp)
        res[k, 0] = ru
        res[k, 1] = rv
        ok[k] = good
        for i in range(2):
            for j in range(_NJ):
                jac[k, i, j] = tmp[i, j]


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


# ============================================================================ screen model
def _basis_weights(grid: np.ndarray, coef: np.ndarray, v: np.ndarray, derivative: bool = False) -> np.ndarray:
    """Values (M, n) of the n cardinal not-a-knot basis splines of ``grid`` at ``v`` (M,), or
    their derivatives d/dv (``coef`` from :func:`pmdsim.geometry.surface.cardinal_spline_coefficients`;
    the edge intervals extrapolate, as in :func:`pmdsim.geometry.surface._interval`)."""
    n = grid.size
    i = np.clip(np.searchsorted(grid, v, side="right") - 1, 0, n - 2)
    t = v - grid[i]
    c = coef[i]  # (M, 4, n)
    if derivative:
        return c[:, 1] + t[:, None] * (2.0 * c[:, 2] + t[:, None] * (3.0 * c[:, 3]))
    return c[:, 0] + t[:, None] * (c[:, 1] + t[:, None] * (c[:, 2] + t[:, None] * c[:, 3]))


@dataclass(frozen=True, eq=False)
class ScreenModel:
    """A non-planar pattern screen for the calibration: the pmdsim not-a-knot spline surface
    over a control grid (the same surface as ``SplineSurface(grid_x_mm, grid_y_mm, heights_mm)``,
    paper §2.3, eq. 8), with some control heights estimated (paper §5, the open question).

    Parameters
    ----------
    grid_x_mm, grid_y_mm : array_like (n_x,), (n_y,)
        Grid lines of the screen frame, strictly increasing, ≥ 2 each (normally the screen's
        bounds and its control lines, e.g. ``[0, 354, 708]`` × ``[0, 199, 398]``).
    heights_mm : array_like (n_y, n_x)
        Control heights (row j ↔ y_j, column i ↔ x_i): the start values of the free ones, the
        fixed values of the others.
    free : array_like of bool (n_y, n_x)
        The control heights to estimate; only interior points may be free.

    Gauge
    -----
    The screen frame is the calibration's reference and its x–y plane is the plane of the
    screen's rigid frame (its border): **the border control heights are held** at their given
    values (normally 0). A piston or tilt of the screen surface (which the border heights would
    carry) is indistinguishable from moving all camera poses and mirror planes, so a ``free``
    mask with a border point set is rejected (:class:`CalibrationDataError`).

    Raises
    ------
    CalibrationDataError
        On bad grids or shapes, non-finite heights, or free border points (named).
    """

    grid_x_mm: np.ndarray
    grid_y_mm: np.ndarray
    heights_mm: np.ndarray
    free: np.ndarray

    def __post_init__(self) -> None:
        grids = []
        for name in ("grid_x_mm", "grid_y_mm"):
            g = np.array(getattr(self, name), dtype=float).reshape(-1) if np.ndim(getattr(self, name)) <= 1 else None
            if g is None or g.size < 2 or not np.all(np.isfinite(g)) or not np.all(np.diff(g) > 0):
                raise CalibrationDataError(
                    f"ScreenModel.{name} must be a strictly increasing 1-D array of ≥ 2 finite values, "
                    f"got {getattr(self, name)!r}")
            g.setflags(write=False)
            grids.append(g)
        gx, gy = grids
        shape = (gy.size, gx.size)
        z = np.array(self.heights_mm, dtype=float)
        if z.shape != shape:
            raise CalibrationDataError(f"ScreenModel.heights_mm must have shape (n_y, n_x) = {shape}, got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise CalibrationDataError("ScreenModel.heights_mm contains NaN or infinite values")
        free = np.array(self.free)
        if free.shape != shape or free.dtype != bool:
            raise CalibrationDataError(f"ScreenModel.free must be a bool array of shape (n_y, n_x) = {shape}, "
                                       f"got {free.dtype} {free.shape}")
        border = free.copy()
        border[1:-1, 1:-1] = False
        if border.any():
            names = [_screen_name(j, i) for j, i in zip(*np.nonzero(border))]
            raise CalibrationDataError(
                f"ScreenModel: border control heights cannot be estimated ({', '.join(names)} are free): "
                f"the gauge of the calibration is the screen frame, whose x–y plane is the plane of the "
                f"rigid screen frame (the border); a piston or tilt of the screen surface cannot be "
                f"separated from the camera poses and mirror planes. Hold the border heights (free=False) "
                f"and free interior control points only")
        z.setflags(write=False)
        free.setflags(write=False)
        object.__setattr__(self, "grid_x_mm", gx)
        object.__setattr__(self, "grid_y_mm", gy)
        object.__setattr__(self, "heights_mm", z)
        object.__setattr__(self, "free", free)

    @classmethod
    def flat(cls, grid_x_mm, grid_y_mm) -> "ScreenModel":
        """A flat start (all heights 0) with every interior control point free: 3 × 3 → 1 free
        height, 5 × 5 → 9, 9 × 9 → 49."""
        gx = np.asarray(grid_x_mm, dtype=float)
        gy = np.asarray(grid_y_mm, dtype=float)
        free = np.zeros((gy.size, gx.size), dtype=bool)
        free[1:-1, 1:-1] = True
        return cls(gx, gy, np.zeros(free.shape), free)

    @classmethod
    def from_surface(cls, surface, free=None) -> "ScreenModel":
        """From a :class:`pmdsim.geometry.surface.SplineSurface` (e.g. a setup's ``screen.surface``);
        ``free`` defaults to all interior control points."""
        z = np.asarray(surface.heights_mm, dtype=float)
        if free is None:
            free = np.zeros(z.shape, dtype=bool)
            free[1:-1, 1:-1] = True
        return cls(surface.grid_x_mm, surface.grid_y_mm, z, free)

    @property
    def n_free(self) -> int:
        """Number F of estimated control heights."""
        return int(self.free.sum())

    @property
    def free_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(j, i) of the free control heights in parameter order (row-major)."""
        return np.nonzero(self.free)

    def free_names(self) -> list[str]:
        """Parameter names of the free heights, ``screen.h[j,i]_mm`` (row j ↔ y_j, column i ↔ x_i)."""
        return [_screen_name(j, i) for j, i in zip(*self.free_index)]

    @property
    def free_heights_mm(self) -> np.ndarray:
        """The free control heights (F,) in parameter order."""
        return self.heights_mm[self.free]

    def with_free_heights(self, values_mm) -> "ScreenModel":
        """A copy with the free heights replaced by ``values_mm`` (F,)."""
        z = np.array(self.heights_mm)
        z[self.free] = np.asarray(values_mm, dtype=float)
        return ScreenModel(self.grid_x_mm, self.grid_y_mm, z, self.free)

    @property
    def surface(self):
        """The screen surface as a :class:`pmdsim.geometry.surface.SplineSurface` (e.g. for the ray tracer)."""
        from ..geometry.surface import SplineSurface

        return SplineSurface(self.grid_x_mm, self.grid_y_mm, self.heights_mm)

    def basis_weights(self, x_mm, y_mm) -> tuple[np.ndarray, np.ndarray]:
        """The 1-D cardinal basis values (wx (M, n_x), wy (M, n_y)) at the points: the height is
        h(x, y) = Σ_j Σ_i heights_mm[j, i]·wy[:, j]·wx[:, i]. (The not-a-knot cardinal basis
        splines have global support — they decay by about 4× per grid interval — so every
        control height has a nonzero weight everywhere.)"""
        from ..geometry.surface import cardinal_spline_coefficients

        x = np.asarray(x_mm, dtype=float).reshape(-1)
        y = np.asarray(y_mm, dtype=float).reshape(-1)
        wx = _basis_weights(self.grid_x_mm, cardinal_spline_coefficients(self.grid_x_mm), x)
        wy = _basis_weights(self.grid_y_mm, cardinal_spline_coefficients(self.grid_y_mm), y)
        return wx, wy

    def height(self, x_mm, y_mm) -> np.ndarray:
        """h(x, y) (mm) at the points (flattened)."""
        wx, wy = self.basis_weights(x_mm, y_mm)
        return np.einsum("mi,mi->m", wy @ self.heights_mm, wx)


def _screen_name(j: int, i: int) -> str:
    return f"screen.h[{j},{i}]_mm"


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
    heights are estimated (None: the correspondences' q are used as given, e.g. the plane z = 0)."""

    cameras: dict[str, CameraParams]
    mirrors: tuple[MirrorPlane, ...]
    screen: ScreenModel | None = None

    def __post_init__(self) -> None:
        cams = dict(self.cameras)
        mirrors = tuple(self.mirrors)
        for name, cp in cams.items():
            if not isinstance(name, str) or not isinstance(cp, CameraParams):
                raise TypeError(f"CalibrationState.cameras must map names (str) to CameraParams, got {name!r}: {type(cp).__name__}")
        for k, mp in enumerate(mirrors):
            if not isinstance(mp, MirrorPlane):
                raise TypeError(f"CalibrationState.mirrors[{k}] must be a MirrorPlane, got {type(mp).__name__}")
        if self.screen is not None and not isinstance(self.screen, ScreenModel):
            raise TypeError(f"CalibrationState.screen must be a ScreenModel or None, got {type(self.screen).__name__}")
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
        return names

    @property
    def n_screen(self) -> int:
        """Number of free screen heights (0 without a screen model)."""
        return 0 if self.screen is None else self.screen.n_free

    @property
    def n_parameters(self) -> int:
        return _NC * len(self.cameras) + _NM * len(self.mirrors) + self.n_screen

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
        if screen is not None and screen.n_free:
            off += _NM * len(self.mirrors)
            screen = screen.with_free_heights(screen.free_heights_mm + delta[off:])
        return CalibrationState(cams, tuple(mirrors), screen)

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


# ============================================================================ packed data
class _Data:
    """Observations concatenated in block order, with the chunk table of the kernels."""

    def __init__(self, blocks: list[tuple[int, int, np.ndarray, np.ndarray]], block_keys, screen=None):
        self.block_keys = block_keys  # [(camera name, pose index)]
        self.uv = np.ascontiguousarray(np.concatenate([b[2] for b in blocks]))
        self.q = np.ascontiguousarray(np.concatenate([b[3] for b in blocks]))
        self.wx, self.wy, self.fi, self.fj = _screen_arrays(screen, self.q)
        # Standard deviations of the decoded (x_q, y_q) (relative; isotropic and equal unless
        # the observations give them).
        self.qstd = np.ones((self.q.shape[0], 2))
        starts, ends, cams, poses, cblock = [], [], [], [], []
        off = 0
        self.block_rows = []
        for bi, (ci, k, uv, _) in enumerate(blocks):
            m = uv.shape[0]
            self.block_rows.append((off, off + m))
            for s in range(off, off + m, _CHUNK):
                starts.append(s)
                ends.append(min(s + _CHUNK, off + m))
                cams.append(ci)
                poses.append(k)
                cblock.append(bi)
            off += m
        self.c_start = np.array(starts, dtype=np.int64)
        self.c_end = np.array(ends, dtype=np.int64)
        self.c_cam = np.array(cams, dtype=np.int64)
        self.c_pose = np.array(poses, dtype=np.int64)
        self.c_block = np.array(cblock, dtype=np.int64)
        self.n_rows = off


def _screen_arrays(screen: ScreenModel | None, q: np.ndarray):
    """Per-correspondence 1-D basis weights (wx (M, n_x), wy (M, n_y)) and the (i, j) indices of
    the free heights — computed once, as the correspondences do not move. Dummies without a
    screen model."""
    if screen is None:
        return np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    wx, wy = screen.basis_weights(q[:, 0], q[:, 1])
    fj, fi = screen.free_index
    return (np.ascontiguousarray(wx), np.ascontiguousarray(wy), np.ascontiguousarray(fi, dtype=np.int64),
            np.ascontiguousarray(fj, dtype=np.int64))


def _screen_q(q: np.ndarray, wx: np.ndarray, wy: np.ndarray, screen: ScreenModel | None) -> np.ndarray:
    """The correspondences' screen points with z = h(x_q, y_q) of the screen model (q as given
    without one)."""
    if screen is None:
        return q
    out = np.array(q)
    out[:, 2] = np.einsum("mi,mi->m", wy @ screen.heights_mm, wx)
    return out


def _screen_slope(q: np.ndarray, screen: ScreenModel | None) -> np.ndarray:
    """(M, 2) slopes (∂h/∂x, ∂h/∂y) of the screen model at the correspondences' (x_q, y_q)
    (zeros without a screen model: q is used as given)."""
    if screen is None:
        return np.zeros((q.shape[0], 2))
    from ..geometry.surface import cardinal_spline_coefficients

    gx, gy = screen.grid_x_mm, screen.grid_y_mm
    cx, cy = cardinal_spline_coefficients(gx), cardinal_spline_coefficients(gy)
    wx = _basis_weights(gx, cx, q[:, 0])
    wy = _basis_weights(gy, cy, q[:, 1])
    dwx = _basis_weights(gx, cx, q[:, 0], derivative=True)
    dwy = _basis_weights(gy, cy, q[:, 1], derivative=True)
    z = screen.heights_mm
    return np.ascontiguousarray(np.column_stack([np.einsum("mi,mi->m", wy @ z, dwx),
                                                 np.einsum("mi,mi->m", dwy @ z, wx)]))


def _screen_coverage(data: "_Data", screen: ScreenModel, min_correspondences: int) -> None:
    """Raise naming the free heights that no (or too few) correspondences see: fewer than
    ``min_correspondences`` with basis weight |w_i(x_q)·w_j(y_q)| ≥ :data:`SCREEN_WEIGHT_MIN`."""
    if screen is None or screen.n_free == 0:
        return
    problems = []
    for name, i, j in zip(screen.free_names(), data.fi, data.fj):
        count = int(np.count_nonzero(np.abs(data.wy[:, j] * data.wx[:, i]) >= SCREEN_WEIGHT_MIN))
        if count < min_correspondences:
            problems.append(f"{name} at (x, y) = ({screen.grid_x_mm[i]:g}, {screen.grid_y_mm[j]:g}) mm: "
                            f"{count} correspondences")
    if problems:
        raise CalibrationDataError(
            f"the data do not determine {len(problems)} free screen control height(s): fewer than "
            f"{min_correspondences} correspondences have basis weight ≥ {SCREEN_WEIGHT_MIN:g} for "
            + "; ".join(problems)
            + ". The cameras do not see these control points via the mirror: hold them (free=False), "
            f"use a coarser screen grid, or add mirror poses whose reflections reach them")


def _pack(observations: Iterable[Observations], state: CalibrationState, min_correspondences: int) -> _Data:
    obs = list(observations)
    if not obs:
        raise CalibrationDataError("no observations given")
    for o in obs:
        if not isinstance(o, Observations):
            raise CalibrationDataError(f"observations must be Observations objects, got {type(o).__name__}")
    names = state.camera_names
    if not names:
        raise CalibrationDataError("the initial state has no cameras")
    n_m = len(state.mirrors)
    merged: dict[tuple[str, int], list[Observations]] = {}
    for o in obs:
        if o.camera not in state.cameras:
            raise CalibrationDataError(
                f"observations name camera {o.camera!r}, which is not in the initial state (cameras: {names})"
            )
        if o.pose_index >= n_m:
            raise CalibrationDataError(
                f"observations of camera {o.camera!r} name mirror pose {o.pose_index}, but the initial "
                f"state has only {n_m} mirror planes (poses 0…{n_m - 1})"
            )
        merged.setdefault((o.camera, o.pose_index), []).append(o)
    total = sum(o.n for o in obs)
    if total == 0:
        raise CalibrationDataError(
            "all correspondences are invalid: no camera sees the screen via the mirror in any pose "
            "(check the valid masks, the decoding and the mirror poses)"
        )
    problems = []
    for (cam, k), lst in sorted(merged.items(), key=lambda kv: (names.index(kv[0][0]), kv[0][1])):
        m = sum(o.n for o in lst)
        if m < min_correspondences:
            problems.append(
                f"camera {cam!r}, mirror pose {k}: only {m} valid correspondences (need ≥ "
                f"{min_correspondences}); the reflection probably misses the screen or the decoding "
                f"failed — drop this pose for this camera or fix its data"
            )
    if problems:
        raise CalibrationDataError("; ".join(problems))
    for cam in names:
        poses = sorted(k for (c, k) in merged if c == cam)
        if len(poses) < MIN_POSES:
            raise CalibrationDataError(
                f"camera {cam!r} has observations in only {len(poses)} mirror pose(s) {poses}; the "
                f"holistic calibration needs at least {MIN_POSES} per camera (better many, tilted "
                f"about two different axes)"
            )
    seen = {k for (_, k) in merged}
    unseen = [k for k in range(n_m) if k not in seen]
    if unseen:
        raise CalibrationDataError(
            f"mirror pose(s) {unseen} of the initial state have no observations, so their planes "
            f"are undetermined; remove them from the state"
        )
    blocks, keys = [], []
    for (cam, k), lst in sorted(merged.items(), key=lambda kv: (names.index(kv[0][0]), kv[0][1])):
        blocks.append((names.index(cam), k, np.concatenate([o.uv_px for o in lst]),
                       np.concatenate([o.q_screen_mm for o in lst])))
        keys.append((cam, k))
    with_std = [o.q_std_mm is not None for o in obs]
    if any(with_std) and not all(with_std):
        missing = [f"camera {o.camera!r} pose {o.pose_index}" for o in obs if o.q_std_mm is None][:5]
        raise CalibrationDataError(
            "some observations have q_std_mm and others not (" + "; ".join(missing) + "): the noise "
            "model must be the same for all — give q_std_mm for all observations or for none")
    data = _Data(blocks, keys, state.screen)
    if all(with_std):
        data.qstd = np.ascontiguousarray(np.concatenate(
            [np.concatenate([o.q_std_mm for o in merged[key]]) for key in keys]))
    _screen_coverage(data, state.screen, min_correspondences)
    return data


def _units(state: CalibrationState) -> np.ndarray:
    return np.concatenate([np.tile(_CAM_UNITS, len(state.cameras)), np.tile(_MIR_UNITS, len(state.mirrors)),
                           np.full(state.n_screen, SCREEN_HEIGHT_UNIT_MM)])


def _block_index(state: CalibrationState, ci: int, k: int) -> np.ndarray:
    nc = _NC * len(state.cameras)
    return np.r_[np.arange(_NC * ci, _NC * (ci + 1)), np.arange(nc + _NM * k, nc + _NM * (k + 1))]


def _evaluate(data: _Data, state: CalibrationState, want_normal: bool, sandwich: bool = False):
    """Cost (SSR), per-block SSR, points behind camera per block and, if wanted, the scaled
    normal equations (A = JᵀJ, g = Jᵀr in internal units).

    ``sandwich``: instead, (whitened SSR Σ_k r_kᵀ(B_k B_kᵀ)⁻¹r_k, per-block SSR, points behind
    camera, M = Σ_k J_kᵀ B_k B_kᵀ J_k in internal units, None) with B_k the propagation of the
    screen-point noise to the residual (see :func:`_chunk_run`)."""
    want_normal = want_normal or sandwich
    intr, rot, cen, mir, e1, e2 = state._arrays()
    nch = data.c_start.shape[0]
    nf = state.n_screen
    if nf != data.fi.shape[0]:
        raise ValueError("the state's screen model does not match the packed data")
    q = _screen_q(data.q, data.wx, data.wy, state.screen)
    if want_normal:
        jtj = np.empty((nch, _NB + nf, _NB + nf))
        jtr = np.empty((nch, _NB + nf))
    else:
        jtj = np.empty((nch, 1, 1))
        jtr = np.empty((nch, 1))
    ssr = np.empty(nch)
    ssr_w = np.empty(nch)
    nbad = np.empty(nch, dtype=np.int64)
    units = np.concatenate([_CAM_UNITS, _MIR_UNITS])
    if sandwich:
        slope = _screen_slope(data.q, state.screen)
        qstd = data.qstd
    else:
        slope = qstd = np.zeros((1, 2))
    _chunks_kernel(data.c_start, data.c_end, data.c_cam, data.c_pose, data.uv, q, intr, rot, cen,
                   mir, e1, e2, units, data.wx, data.wy, data.fi, data.fj, SCREEN_HEIGHT_UNIT_MM, want_normal,
                   jtj, jtr, ssr, nbad, sandwich, slope, qstd, ssr_w)
    nblk = len(data.block_keys)
    block_ssr = np.bincount(data.c_block, weights=ssr, minlength=nblk)
    block_bad = np.bincount(data.c_block, weights=nbad, minlength=nblk).astype(int)
    if not want_normal:
        return float(block_ssr.sum()), block_ssr, block_bad, None, None
    n = state.n_parameters
    a = np.zeros((n, n))
    g = np.zeros(n)
    names = state.camera_names
    screen_idx = np.arange(n - nf, n)
    # Sum the chunks of each (camera, pose) block, then scatter.
    for b, (cam, k) in enumerate(data.block_keys):
        sel = data.c_block == b
        blk = jtj[sel].sum(axis=0)
        blk = 0.5 * (blk + blk.T)
        idx = np.r_[_block_index(state, names.index(cam), k), screen_idx]
        a[np.ix_(idx, idx)] += blk
        g[idx] += jtr[sel].sum(axis=0)
    if sandwich:
        return float(ssr_w.sum()), block_ssr, block_bad, a, None
    return float(block_ssr.sum()), block_ssr, block_bad, a, g


def residuals_and_jacobian(observations: Iterable[Observations], state: CalibrationState):
    """Residuals and the dense analytic Jacobian (for small observation sets and tests).

    Returns
    -------
    r : ndarray (2M,)
        Residuals (predicted − observed, px), ordered (u₀, v₀, u₁, v₁, …) over the
        observations in the given order.
    J : ndarray (2M, n)
        dr/dΔ for the increments of :meth:`CalibrationState.updated` (natural units).
    names : list[str]
        Parameter names (columns of J).

    Rows whose virtual point lies behind the camera are NaN.
    """
    obs = list(observations)
    names = state.camera_names
    cam_idx, pose_idx, uv, q = [], [], [], []
    for o in obs:
        if o.camera not in state.cameras:
            raise CalibrationDataError(f"camera {o.camera!r} is not in the state (cameras: {names})")
        if o.pose_index >= len(state.mirrors):
            raise CalibrationDataError(f"mirror pose {o.pose_index} is not in the state ({len(state.mirrors)} mirrors)")
        cam_idx.append(np.full(o.n, names.index(o.camera), dtype=np.int64))
        pose_idx.append(np.full(o.n, o.pose_index, dtype=np.int64))
        uv.append(o.uv_px)
        q.append(o.q_screen_mm)
    cam_idx = np.concatenate(cam_idx) if obs else np.zeros(0, dtype=np.int64)
    pose_idx = np.concatenate(pose_idx) if obs else np.zeros(0, dtype=np.int64)
    uv = np.ascontiguousarray(np.concatenate(uv)) if obs else np.zeros((0, 2))
    q = np.ascontiguousarray(np.concatenate(q)) if obs else np.zeros((0, 3))
    m = uv.shape[0]
    wx, wy, fi, fj = _screen_arrays(state.screen, q)
    q = np.ascontiguousarray(_screen_q(q, wx, wy, state.screen))
    res = np.empty((m, 2))
    jb = np.empty((m, 2, _NJ))
    ok = np.empty(m, dtype=np.bool_)
    _rows_kernel(cam_idx, pose_idx, uv, q, *state._arrays(), res, jb, ok)
    n = state.n_parameters
    jac = np.zeros((m, 2, n))
    nc = _NC * len(state.cameras)
    rows = np.arange(m)
    for j in range(_NC):
        jac[rows, :, _NC * cam_idx + j] = jb[:, :, j]
    for j in range(_NM):
        jac[rows, :, nc + _NM * pose_idx + j] = jb[:, :, _NC + j]
    # Free screen heights: ∂r/∂Z_ji = (∂r/∂q_z)·w_j(y_q)·w_i(x_q).
    off = n - state.n_screen
    for f, (i, j) in enumerate(zip(fi, fj)):
        jac[:, :, off + f] = jb[:, :, _NB] * (wy[:, j] * wx[:, i])[:, None]
    res[~ok] = np.nan
    jac[~ok] = np.nan
    return res.reshape(-1), jac.reshape(2 * m, n), state.parameter_names()


# ============================================================================ result
@dataclass(frozen=True, eq=False)
class WeakDirection:
    """One of the worst-determined parameter combinations of a calibration: an eigenvector of
    the Jacobi-scaled normal matrix JᵀJ with one of the smallest eigenvalues.

    Attributes
    ----------
    relative_eigenvalue : float
        Its eigenvalue over the largest (1 / condition number for the worst direction): how much
        less the residuals constrain this combination than the best-determined one.
    direction : ndarray (n,)
        The combination in natural units (the parameterisation of
        :meth:`CalibrationState.updated`), of unit length in internal units
        (:data:`PARAMETER_UNITS`, :data:`SCREEN_HEIGHT_UNIT_MM`).
    std_internal : float
        Standard deviation of the estimate along ``direction`` (internal units: a 1σ move changes
        the parameters by ``std_internal · direction``). 0 for exact data.
    components : tuple[tuple[str, float], ...]
        The dominant (name, component) pairs of the direction in internal units (components
        ≥ 0.15 × the largest, at most 10), largest first.
    """

    relative_eigenvalue: float
    direction: np.ndarray
    std_internal: float
    components: tuple

    def describe(self) -> str:
        """One line: the eigenvalue ratio, the 1σ size and the dominant components."""
        comps = " ".join(f"{c:+.3g}·{name}" for name, c in self.components)
        return f"λ/λ_max = {self.relative_eigenvalue:.3g}, σ = {self.std_internal:.3g} (internal units) along [{comps}]"


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Outcome of :func:`calibrate`.

    Attributes
    ----------
    cameras : dict[str, tuple[Camera, RigidTransform]]
        Estimated intrinsics and ``T_screen_cam`` per camera.
    mirrors : list[MirrorPlane]
        Estimated mirror plane per pose (screen frame; normals point towards the cameras).
    converged : bool
    reason : str
        Which convergence criterion was met, or why the calibration failed.
    iterations : int
        Accepted Levenberg–Marquardt steps (Jacobian evaluations after the first).
    rms_px : float
        RMS of all residual components (px).
    rms_px_by_camera_pose : dict[(str, int), float]
        RMS per (camera, mirror pose) block.
    n_residuals : int
        Number of residual components m (2 per correspondence).
    parameter_names : tuple[str, ...]
    parameter_std : ndarray (n,)
        Standard deviations (natural units): √diag(covariance).
    covariance : ndarray (n, n)
        The covariance matrix (natural units) for noise in the decoded screen points: the
        sandwich σ₀²(JᵀJ)⁻¹(Σ_k J_kᵀB_kB_kᵀJ_k)(JᵀJ)⁻¹ with B_k = ∂r_k/∂(x_q, y_q)·diag(q_std)
        (see the module docstring, "Uncertainties").
    condition_number : float
        Condition number of the Jacobi-scaled JᵀJ at the solution.
    rms_history_px : tuple[float, ...]
        RMS residual at the start and after every accepted step.
    screen_model : ScreenModel or None
        The screen model with the estimated free control heights (None if the calibration had
        none); their standard deviations are the ``screen.h[j,i]_mm`` entries of
        :attr:`parameter_std` (or :attr:`screen_std_mm`).
    std_inflation : ndarray (n,) or None
        Per parameter √(A_s⁻¹)_jj of the Jacobi-scaled JᵀJ (A_s, unit diagonal): how many times
        larger its standard deviation is than if all other parameters were known (≥ 1; 1 for a
        parameter uncorrelated with all others). Independent of the noise level, so it also
        flags weakly determined parameters of exact data, whose σ is 0.
    weak_directions : tuple[WeakDirection, ...]
        The :data:`WEAK_DIRECTIONS` worst-determined parameter combinations, worst first (see
        :meth:`determination_report`).
    screen_noise_std : float
        σ₀: the standard deviation of the decoded screen coordinates (x_q, y_q) that the
        residuals imply — in mm when the observations carry no ``q_std_mm`` (an estimate of the
        decoding noise, comparable with the decoder's predicted σ), otherwise the factor by
        which their ``q_std_mm`` are too small (> 1) or too large (< 1).
    """

    cameras: dict
    mirrors: list
    converged: bool
    reason: str
    iterations: int
    rms_px: float
    rms_px_by_camera_pose: dict
    n_residuals: int
    parameter_names: tuple
    parameter_std: np.ndarray
    covariance: np.ndarray
    condition_number: float
    rms_history_px: tuple = ()
    screen_model: ScreenModel | None = None
    std_inflation: np.ndarray | None = None
    weak_directions: tuple = ()
    screen_noise_std: float = math.nan

    def poorly_determined(self, prior_std: Mapping[str, float], fraction: float = 0.5) -> dict[str, tuple[float, float]]:
        """The parameters that the data determine hardly better than was known before.

        Parameters
        ----------
        prior_std : mapping of str to float
            Prior standard deviation (natural units) by parameter-name pattern
            (:func:`fnmatch.fnmatchcase`, e.g. ``"*.position_?_mm": 5.0``, ``"screen.*": 1.0``,
            ``"left.fx_px": 100.0``); the first matching pattern applies, parameters matching none
            are not checked.
        fraction : float
            A parameter is poorly determined if its standard deviation is at least ``fraction``
            times its prior standard deviation (0.5: the data at most halve the uncertainty).

        Returns
        -------
        dict[str, tuple[float, float]]
            name → (σ, prior σ) of the poorly determined parameters, in parameter order; empty if
            every checked parameter is determined.

        Raises
        ------
        ValueError
            If a prior standard deviation is not positive and finite, or ``fraction`` is not positive.
        """
        if not (fraction > 0 and math.isfinite(fraction)):
            raise ValueError(f"fraction must be positive and finite, got {fraction!r}")
        patterns = []
        for pat, v in dict(prior_std).items():
            v = float(v)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"prior_std[{pat!r}] must be positive and finite, got {v!r}")
            patterns.append((str(pat), v))
        out = {}
        for name, sd in zip(self.parameter_names, self.parameter_std):
            prior = next((v for pat, v in patterns if fnmatch.fnmatchcase(name, pat)), None)
            if prior is not None and sd >= fraction * prior:
                out[name] = (float(sd), prior)
        return out

    def determination_report(self, prior_std: Mapping[str, float] | None = None, fraction: float = 0.5,
                             n_inflated: int = 5) -> str:
        """How well the data determine the parameters, as text (for logs and reports): the
        condition number, the worst-determined combinations (:attr:`weak_directions`), the
        parameters with the largest :attr:`std_inflation` and, given ``prior_std``, the
        parameters the data hardly improve on (:meth:`poorly_determined`)."""
        lines = [f"condition number of the Jacobi-scaled JᵀJ: {self.condition_number:.3g} "
                 f"(calibrate's limit {DEFAULT_CONDITION_LIMIT:.0e} by default)"]
        for i, wd in enumerate(self.weak_directions):
            lines.append(f"weak direction {i + 1}: {wd.describe()}")
        if self.std_inflation is not None and n_inflated > 0:
            order = np.argsort(-self.std_inflation)[:n_inflated]
            lines.append("largest σ inflation by correlation: " + ", ".join(
                f"{self.parameter_names[j]} ×{self.std_inflation[j]:.3g}" for j in order))
        if prior_std is not None:
            bad = self.poorly_determined(prior_std, fraction)
            if bad:
                lines.append(f"poorly determined (σ ≥ {fraction:g} × prior σ): " + ", ".join(
                    f"{name} σ = {sd:.3g} (prior {prior:.3g})" for name, (sd, prior) in bad.items()))
            else:
                lines.append(f"every parameter with a prior is determined (σ < {fraction:g} × prior σ)")
        return "\n".join(lines)

    @property
    def state(self) -> CalibrationState:
        """The estimate as a :class:`CalibrationState` (e.g. to restart from it)."""
        return CalibrationState({k: CameraParams(c, t) for k, (c, t) in self.cameras.items()},
                                tuple(self.mirrors), self.screen_model)

    @property
    def screen_std_mm(self) -> np.ndarray | None:
        """(n_y, n_x) standard deviations of the screen control heights (0 where held); None
        without a screen model."""
        if self.screen_model is None:
            return None
        out = np.zeros(self.screen_model.heights_mm.shape)
        for name, (j, i) in zip(self.screen_model.free_names(), zip(*self.screen_model.free_index)):
            out[j, i] = self.std(name)
        return out

    def std(self, name: str) -> float:
        """Standard deviation of one parameter by name (e.g. ``"left.fx_px"``)."""
        return float(self.parameter_std[self.parameter_names.index(name)])

    def to_dict(self) -> dict:
        """Plain data (dicts, lists, floats, strings): JSON-serialisable."""
        cams = {}
        for name, (c, t) in self.cameras.items():
            origin, angles = t.as_origin_angles()
            rv = _matrix_to_rotvec(t.rotation)
            cams[name] = {
                "image_size_px": [c.width_px, c.height_px],
                "fx_px": c.fx_px, "fy_px": c.fy_px, "ppx_px": c.ppx_px, "ppy_px": c.ppy_px,
                "k1": c.k1, "k2": c.k2, "p1": c.p1, "p2": c.p2, "k3": c.k3,
                "T_screen_cam": {
                    "origin_mm": origin.tolist(),
                    "angles_deg": angles.tolist(),
                    "rotvec_rad": rv.tolist(),
                    "matrix": t.as_matrix().tolist(),
                },
            }
        rms = {}
        for (cam, k), v in self.rms_px_by_camera_pose.items():
            rms.setdefault(cam, {})[str(k)] = float(v)
        screen = None
        if self.screen_model is not None:
            sm = self.screen_model
            screen = {"grid_x_mm": sm.grid_x_mm.tolist(), "grid_y_mm": sm.grid_y_mm.tolist(),
                      "heights_mm": sm.heights_mm.tolist(), "free": sm.free.tolist(),
                      "heights_std_mm": self.screen_std_mm.tolist()}
        return {
            "frame": "screen (held fixed)",
            "screen": screen,
            "cameras": cams,
            "mirrors": [{"normal": m.normal.tolist(), "d_mm": m.d_mm} for m in self.mirrors],
            "converged": bool(self.converged),
            "reason": self.reason,
            "iterations": int(self.iterations),
            "rms_px": float(self.rms_px),
            "rms_px_by_camera_pose": rms,
            "n_residuals": int(self.n_residuals),
            "n_parameters": len(self.parameter_names),
            "parameter_std": {n: float(s) for n, s in zip(self.parameter_names, self.parameter_std)},
            "condition_number": float(self.condition_number),
            "screen_noise_std": float(self.screen_noise_std),
            "std_inflation": None if self.std_inflation is None else {
                n: float(v) for n, v in zip(self.parameter_names, self.std_inflation)},
            "weak_directions": [
                {"relative_eigenvalue": wd.relative_eigenvalue, "std_internal": wd.std_internal,
                 "components": {name: c for name, c in wd.components}}
                for wd in self.weak_directions],
        }


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


# ============================================================================ solver
def _scaled(a: np.ndarray, g: np.ndarray):
    dg = np.sqrt(np.diag(a))
    dg = np.where(dg > 0, dg, 1.0)
    return a / np.outer(dg, dg), g / dg, dg


def _mirror_configuration_hint(state: CalibrationState) -> str | None:
    """The analytically degenerate mirror-pose configurations, recognised from the planes:

    * all planes parallel (only lifts): moving every camera by t along the common normal and
      every plane by t/2 leaves all virtual cameras in place;
    * all planes through one common line L (a pencil: tilts about one axis through a common
      point, no lifts): rotating the cameras by 2φ and every plane by φ about L leaves all
      virtual cameras in place (a reflection across a plane containing L reverses rotations
      about L; cf. Sturm & Bonfort 2006 on mirror-based pose estimation).

    Returns the explanation, or None if the planes are in neither configuration."""
    if len(state.mirrors) < 2:
        return None
    normals = np.array([m.normal for m in state.mirrors])
    ref = normals[0]
    normals = normals * np.sign(normals @ ref)[:, None]
    ds = np.array([m.d_mm for m in state.mirrors]) * np.sign(np.array([m.normal for m in state.mirrors]) @ ref)
    parallel = ("all mirror planes are parallel (only lifts, no tilts): moving the cameras along the common "
                "normal and every plane by half as much is invisible — add mirror poses tilted about the "
                "mirror's x and y axes")
    if np.max(np.linalg.norm(np.cross(normals, ref), axis=1)) < _PLANE_HINT_TOL:
        return parallel
    centres = np.array([cp.T_screen_cam.translation for cp in state.cameras.values()])
    scale = max(float(np.max(np.linalg.norm(centres, axis=1))), 1.0)
    planes = np.column_stack([normals, -ds / scale])  # homogeneous, lengths in units of `scale`
    sv = np.linalg.svd(planes, compute_uv=False)
    if sv[2] < _PLANE_HINT_TOL * sv[0]:
        u, _, _ = np.linalg.svd(normals.T)
        direction = u[:, 2]  # ⟂ to all normals
        direction = direction * np.sign(direction[np.argmax(np.abs(direction))])
        # The point of the line nearest to the screen origin: n_k·p = d_k for all k, p ⟂ direction.
        p0 = np.linalg.lstsq(np.vstack([normals, direction]), np.r_[ds, 0.0], rcond=None)[0]
        if np.linalg.norm(p0 - centres.mean(axis=0)) > 20.0 * scale:
            return parallel  # (nearly) parallel planes: their common line is (nearly) at infinity
        return ("all mirror planes contain one common line (direction "
                + np.array2string(direction, precision=3, separator=", ", suppress_small=True)
                + ", through " + np.array2string(p0, precision=1, separator=", ", suppress_small=True)
                + " mm, screen frame) — mirror poses tilted about one axis only, without lifts: rotating "
                "the cameras by 2φ and every plane by φ about that line is invisible. Add lifts or tilts "
                "about a second axis")
    return None


def _degenerate_error(prefix: str, state: CalibrationState, a_s: np.ndarray, dg: np.ndarray, limit: float,
                      cond: float) -> "CalibrationDegenerateError":
    """The error for a degenerate problem: names the (nearly) free parameter combinations —
    eigenvectors of the Jacobi-scaled JᵀJ whose eigenvalues are below λ_max / limit, with their
    dominant components — and, if recognised, the degenerate mirror-pose configuration."""
    names = state.parameter_names()
    w, v = np.linalg.eigh(a_s)
    small = np.nonzero(w < w[-1] / limit)[0]
    if small.size == 0:
        small = np.array([0])
    combos = []
    undetermined: set[str] = set()
    for i in small[:4]:
        vec = v[:, i]
        big = np.abs(vec) >= 0.15 * np.max(np.abs(vec))
        order = [j for j in np.argsort(-np.abs(vec)) if big[j]][:10]
        combos.append("[" + " ".join(f"{vec[j]:+.2f}·{names[j]}" for j in order) + "]")
        undetermined.update(names[j] for j in np.nonzero(big)[0])
    hint = _mirror_configuration_hint(state)
    screen_free = any(n.startswith("screen.") for n in undetermined)
    if hint is None:
        hint = ("typical causes: all mirror planes parallel (only lifts, no tilts), or all planes through one "
                "common line (tilts about one axis only, no lifts) — add mirror poses tilted about the "
                "mirror's x and y axes, and lifts")
    cause = hint
    if screen_free:
        hint += ("; or free screen control heights (screen.h) that the correspondences cover too sparsely — "
                 "hold them or use a coarser screen grid")
    parameters = tuple(sorted(undetermined, key=names.index))
    msg = (
        prefix + f"the mirror poses do not determine all parameters: the Jacobi-scaled normal matrix JᵀJ has "
        f"condition number {cond:.3g} (limit {limit:.3g}), {small.size} (nearly) free parameter "
        f"combination(s) (eigenvectors, internal units): " + "; ".join(combos)
        + f". Badly determined: {', '.join(parameters)}. Cause: {hint}"
    )
    units = _units(state)
    dirs = v[:, small] * (units / dg)[:, None]  # natural units
    dirs /= np.linalg.norm(dirs / units[:, None], axis=0)  # unit length in internal units
    return CalibrationDegenerateError(msg, parameter_names=tuple(names), parameters=parameters, directions=dirs,
                                      condition_number=cond, cause=cause)


def _weak_directions(names, w: np.ndarray, v: np.ndarray, cov: np.ndarray, scale: np.ndarray,
                     units: np.ndarray, count: int = WEAK_DIRECTIONS) -> tuple["WeakDirection", ...]:
    """The ``count`` worst-determined parameter combinations: eigenvectors of the Jacobi-scaled
    JᵀJ (A_s; eigenvalues ``w`` ascending, eigenvectors ``v``) with the smallest eigenvalues.
    ``cov`` is the covariance (natural units), ``scale`` (n,) maps scaled to natural units (with
    the result's mirror orientation signs), ``units`` natural to internal units."""
    out = []
    cov_int = cov / np.outer(units, units)
    for i in range(min(count, w.size)):
        direction = v[:, i] * scale
        norm = np.linalg.norm(direction / units)
        direction = direction / norm  # natural units, unit length in internal units
        # Variance of the coordinate c = uᵀθ (internal units) along u = direction / units (‖u‖ = 1).
        u = direction / units
        var = float(u @ cov_int @ u)
        big = np.abs(u) >= 0.15 * np.max(np.abs(u))
        order = [j for j in np.argsort(-np.abs(u)) if big[j]][:10]
        comps = tuple((names[j], float(u[j])) for j in order)
        out.append(WeakDirection(float(w[i] / w[-1]), direction, math.sqrt(max(var, 0.0)), comps))
    return tuple(out)


def _condition(a_s: np.ndarray) -> float:
    w = np.linalg.eigvalsh(a_s)
    if w[0] <= 0:
        return math.inf
    return float(w[-1] / w[0])


def _rel_step(delta: np.ndarray, state: CalibrationState) -> float:
    """max |δ_j| / ref_j: focal length for intrinsics in px, 1 for distortion and angles, the
    camera distance for positions and mirror distances."""
    refs = []
    pos = [float(np.linalg.norm(cp.T_screen_cam.translation)) for cp in state.cameras.values()]
    scale_mm = max(max(pos), 1.0)
    for cp in state.cameras.values():
        f = max(cp.camera.fx_px, cp.camera.fy_px)
        refs += [f, f, f, f, 1, 1, 1, 1, 1, 1, 1, scale_mm, scale_mm, scale_mm]
    for _ in state.mirrors:
        refs += [1, 1, scale_mm]
    refs += [1] * state.n_screen  # screen heights: 1 mm
    return float(np.max(np.abs(delta) / np.array(refs, dtype=float)))


def calibrate(
    observations: Iterable[Observations],
    initial_state: CalibrationState,
    *,
    screen_model: ScreenModel | None = None,
    max_iter: int = 100,
    ftol: float = 1e-12,
    xtol: float = 1e-10,
    min_correspondences: int = MIN_CORRESPONDENCES,
    condition_limit: float = DEFAULT_CONDITION_LIMIT,
    raise_on_failure: bool = False,
) -> CalibrationResult:
    """Holistic calibration with a planar mirror (paper §4) by Levenberg–Marquardt.

    Parameters
    ----------
    observations : iterable of Observations
        Correspondences per (camera, mirror pose); several objects for the same block are merged.
    initial_state : CalibrationState
        Start values (e.g. :func:`nominal_state`); its cameras define the parameter order, its
        mirrors the pose indices. k3 of each camera stays fixed at its initial value.
    screen_model : ScreenModel, optional
        Non-planar screen: the correspondences' z is the model's height h(x_q, y_q) and its
        free control heights are estimated jointly (start values: its ``heights_mm``). Replaces
        ``initial_state.screen``; None keeps that (normally None: q is used as given).
    max_iter : int
        Maximum number of accepted steps.
    ftol : float
        Converged when an accepted step changes the cost (SSR) by less than ``ftol`` relative,
        or when the model predicts less than that.
    xtol : float
        Converged when a step changes every parameter by less than ``xtol`` relative to its
        reference size (the focal length for intrinsics in px, 1 for distortion coefficients and
        angles in rad, the largest camera distance for lengths).
    min_correspondences : int
        Fewest correspondences per (camera, pose) block.
    condition_limit : float
        Largest acceptable condition number of the Jacobi-scaled JᵀJ (checked at the start and at
        the solution); above it the pose set is reported as degenerate.
    raise_on_failure : bool
        Raise :class:`CalibrationError` instead of returning ``converged=False``.

    Returns
    -------
    CalibrationResult
        ``converged`` False (with the ``reason``) if the iteration stopped before a criterion
        was met. Its covariance is for noise in the decoded screen points (module docstring,
        "Uncertainties"; the observations' ``q_std_mm`` if given).

    Raises
    ------
    CalibrationDataError
        Unusable input, with the camera / pose / parameters named: no observations or none
        valid; a camera or pose index not in the state; a (camera, pose) block with fewer than
        ``min_correspondences``; a camera seen in fewer than 3 poses; a mirror of the state
        without observations; correspondences behind a camera at the initial state; free screen
        heights that fewer than ``min_correspondences`` correspondences see with basis weight
        ≥ :data:`SCREEN_WEIGHT_MIN` (named).
    CalibrationDegenerateError
        (a :class:`CalibrationDataError`) A degenerate pose set: condition number above
        ``condition_limit`` at the start, after a step or at the solution. The message names the
        badly determined parameter combinations and, if recognised, the configuration (all
        mirror planes parallel; all through one common line); the exception carries them
        (``parameters``, ``directions``, ``cause``). Weakly determined parameters below the limit
        are reported by the result (:attr:`CalibrationResult.weak_directions`,
        :meth:`CalibrationResult.poorly_determined`).
    CalibrationError
        Not converged and ``raise_on_failure``.
    """
    if int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    state = initial_state
    if screen_model is not None:
        if not isinstance(screen_model, ScreenModel):
            raise TypeError(f"screen_model must be a ScreenModel, got {type(screen_model).__name__}")
        state = replace(state, screen=screen_model)
    data = _pack(observations, state, int(min_correspondences))
    names = state.parameter_names()
    n = len(names)
    m = 2 * data.n_rows
    if m <= n:
        raise CalibrationDataError(f"{m} residuals cannot determine {n} parameters")
    units = _units(state)

    cost, block_ssr, block_bad, a, g = _evaluate(data, state, True)
    if block_bad.any():
        bad = [f"camera {c!r} pose {k}: {b}" for (c, k), b in zip(data.block_keys, block_bad) if b]
        raise CalibrationDataError(
            "the initial state puts the virtual (mirrored) screen points of some correspondences "
            "behind the camera (" + "; ".join(bad) + "); the initial camera poses or mirror planes are "
            "too far off"
        )
    a_s, g_s, dg = _scaled(a, g)
    cond = _condition(a_s)
    if not cond <= condition_limit:
        raise _degenerate_error("at the initial state, ", state, a_s, dg, condition_limit, cond)

    lam = 1e-3
    nu = 2.0
    converged = False
    reason = ""
    iterations = 0
    eye = np.eye(n)
    history = [math.sqrt(cost / m)]
    while True:
        if cost == 0.0:
            converged, reason = True, "zero residuals"
            break
        # Convergence tests on the undamped (Gauss–Newton) step: independent of the damping.
        try:
            step_gn = np.linalg.solve(a_s, -g_s)
        except np.linalg.LinAlgError:
            step_gn = np.linalg.lstsq(a_s, -g_s, rcond=None)[0]
        pred_gn = float(-(g_s @ step_gn))
        rel_gn = _rel_step(step_gn / dg * units, state)
        if rel_gn <= xtol:
            converged, reason = True, (f"step size: the Gauss–Newton step changes no parameter by more "
                                       f"than {rel_gn:.2g} (relative) ≤ xtol = {xtol:g}")
            break
        if pred_gn <= ftol * cost:
            converged, reason = True, (f"relative cost change: the Gauss–Newton model predicts "
                                       f"{pred_gn / cost:.2g} ≤ ftol = {ftol:g}")
            break
        if iterations >= max_iter:
            reason = (f"maximum number of iterations ({max_iter}) reached before convergence; rms "
                      f"{math.sqrt(cost / m):.3g} px, Gauss–Newton step {rel_gn:.2g} (relative), "
                      f"predicted relative cost change {pred_gn / cost:.2g}")
            break
        # Levenberg–Marquardt step (Marquardt scaling: λ·diag(JᵀJ) = λ·I after Jacobi scaling).
        accepted = False
        rel_change = math.nan
        while lam <= 1e20:
            try:
                chol = np.linalg.cholesky(a_s + lam * eye)
            except np.linalg.LinAlgError:
                lam = max(lam, 1e-12) * nu
                nu *= 2.0
                continue
            step_s = np.linalg.solve(chol.T, np.linalg.solve(chol, -g_s))
            pred = -(2.0 * g_s @ step_s + step_s @ a_s @ step_s)
            new_cost = math.inf
            try:
                trial = state.updated(step_s / dg * units)
            except ValueError:  # e.g. a focal length ≤ 0: reject the step
                trial = None
            if trial is not None:
                c_new, _, bad_new, _, _ = _evaluate(data, trial, False)
                if not bad_new.any():  # no virtual point behind a camera
                    new_cost = c_new
            rho = (cost - new_cost) / pred if pred > 0 else -1.0
            if rho > 1e-4 and new_cost < cost:
                rel_change = (cost - new_cost) / cost
                state, cost = trial, new_cost
                iterations += 1
                history.append(math.sqrt(cost / m))
                lam = max(lam * (0.1 if rho > 0.25 else 0.5), 1e-15)
                nu = 2.0
                accepted = True
                break
            lam = max(lam, 1e-12) * nu
            nu *= 2.0
        if not accepted:
            reason = (f"no step reduces the cost any more (damping λ = {lam:.3g}) although the "
                      f"convergence criteria are not met; rms {math.sqrt(cost / m):.3g} px")
            break
        cost, block_ssr, block_bad, a, g = _evaluate(data, state, True)
        a_s, g_s, dg = _scaled(a, g)
        cond = _condition(a_s)
        if not cond <= condition_limit:
            raise _degenerate_error(f"after {iterations} iterations, ", state, a_s, dg, condition_limit, cond)
        if rel_change < ftol:
            converged, reason = True, f"relative cost change {rel_change:.2g} < ftol = {ftol:g}"
            break

    eig_w, eig_v = np.linalg.eigh(a_s)
    cond = math.inf if eig_w[0] <= 0 else float(eig_w[-1] / eig_w[0])
    if not cond <= condition_limit:
        raise _degenerate_error("at the solution, ", state, a_s, dg, condition_limit, cond)
    # Covariance. The noise is in the decoded screen points, not in the pixels: r_k ≈ J_k δ + B_k ε_k
    # with ε_k ~ N(0, σ₀² I₂) and B_k = ∂r_k/∂(x_q, y_q)·diag(q_std) (see _chunk_run), so the
    # least-squares estimate has the sandwich covariance
    #   Cov = σ₀² (JᵀJ)⁻¹ (Σ_k J_kᵀ B_k B_kᵀ J_k) (JᵀJ)⁻¹,   σ₀² = Σ_k r_kᵀ (B_k B_kᵀ)⁻¹ r_k / (m − n),
    # which is σ²(JᵀJ)⁻¹, σ² = SSR/(m − n), when all B_k are equal multiples of an orthogonal matrix.
    ssr_w, _, _, meat, _ = _evaluate(data, state, True, sandwich=True)
    sigma0_2 = ssr_w / (m - n)
    a_s_inv = np.linalg.inv(a_s)
    a_s_inv = 0.5 * (a_s_inv + a_s_inv.T)
    cov_s = sigma0_2 * (a_s_inv @ (meat / np.outer(dg, dg)) @ a_s_inv)  # Jacobi-scaled coordinates
    cov_s = 0.5 * (cov_s + cov_s.T)
    scale = units / dg
    # The result's mirror normals point towards the cameras; a plane flipped for that, (n, d) →
    # (−n, −d), has the same e1 and the opposite e2 (tangent_basis), so its increments are
    # (tilt_a, tilt_b, d) → (−tilt_a, tilt_b, −d): flip those rows and columns.
    ref = np.mean([cp.T_screen_cam.translation for cp in state.cameras.values()], axis=0)
    oriented = [mp.oriented_towards(ref) for mp in state.mirrors]
    sign = np.ones(n)
    for k, (mp, mo) in enumerate(zip(state.mirrors, oriented)):
        if mo is not mp:
            off = _NC * len(state.cameras) + _NM * k
            sign[[off, off + 2]] = -1.0
    cov = cov_s * np.outer(scale * sign, scale * sign)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    weak = _weak_directions(names, eig_w, eig_v, cov, scale * sign, units)

    block_n = [e - s for s, e in data.block_rows]
    rms_by = {key: math.sqrt(ssr / (2 * k)) for key, ssr, k in zip(data.block_keys, block_ssr, block_n)}
    result = CalibrationResult(
        cameras={k: (cp.camera, cp.T_screen_cam) for k, cp in state.cameras.items()},
        mirrors=oriented,
        converged=converged,
        reason=reason,
        iterations=iterations,
        rms_px=math.sqrt(cost / m),
        rms_px_by_camera_pose=rms_by,
        n_residuals=m,
        parameter_names=tuple(names),
        parameter_std=std,
        covariance=cov,
        condition_number=cond,
        rms_history_px=tuple(history),
        screen_model=state.screen,
        std_inflation=np.sqrt(np.clip(np.diag(a_s_inv), 0.0, None)),
        weak_directions=weak,
        screen_noise_std=math.sqrt(sigma0_2),
    )
    if raise_on_failure and not converged:
        raise CalibrationError(f"the calibration did not converge: {reason}")
    return result


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
    (rotvec, position), ``"mirrors"`` (tilts, d) or ``"screen"`` (free heights)."""
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
    if head == "screen":
        return "screen.h_mm"
    if head.startswith("mirror") and head[6:].isdigit():
        return f"mirror.{kind}"
    return kind


@dataclass(frozen=True, eq=False)
class SpreadComparison:
    """Reported against observed uncertainty over a Monte Carlo of calibrations (see
    :func:`compare_spread`). P parameters, n draws.

    Attributes
    ----------
    parameter_names : tuple[str, ...]
    deviations : ndarray (n, P)
        Each draw's estimate minus the Monte Carlo mean (natural units, increments of
        :meth:`CalibrationState.increment_to` from the first draw's estimate).
    covariance : ndarray (P, P)
        The mean of the draws' reported covariances.
    observed_std : ndarray (P,)
        Sample standard deviation of the estimates (about their mean, n − 1 degrees of freedom).
    reported_std : ndarray (P,)
        √diag(covariance).
    whitened_ratio : float
        √(T / ((n − 1) P)), T = Σ_i d_iᵀ C⁻¹ d_i: observed over reported spread pooled over all
        directions of parameter space (1 if the covariance is right).
    whitened_dof : int
        (n − 1) P: T ~ χ² with this many degrees of freedom if the covariance is right, so the
        ratio's relative standard error is 1/√(2·dof).
    marginal_ratio : float
        √(Σ_ij z_ij² / ((n − 1) P)), z_ij = d_ij / σ_j: the per-parameter reported σ_j pooled.
    marginal_dof : float
        Its effective degrees of freedom (n − 1) P² / Σ_jk r_jk² (r: the reported correlation
        matrix; correlated z_j carry less information than independent ones); relative standard
        error 1/√(2·dof).
    """

    parameter_names: tuple
    deviations: np.ndarray
    covariance: np.ndarray
    observed_std: np.ndarray
    reported_std: np.ndarray
    whitened_ratio: float
    whitened_dof: int
    marginal_ratio: float
    marginal_dof: float

    @property
    def n_draws(self) -> int:
        return int(self.deviations.shape[0])

    def ratio_standard_error(self, dof: float) -> float:
        """Relative standard error 1/√(2·dof) of a pooled ratio with ``dof`` degrees of freedom."""
        return 1.0 / math.sqrt(2.0 * dof)

    def pooled_ratio(self, indices) -> tuple[float, float]:
        """(observed / reported spread pooled over the parameters ``indices`` (their z-scores),
        effective degrees of freedom) — as :attr:`marginal_ratio` for a subset."""
        idx = np.asarray(indices, dtype=int)
        sd = self.reported_std[idx]
        z = self.deviations[:, idx] / sd
        dof = self.n_draws - 1
        corr = self.covariance[np.ix_(idx, idx)] / np.outer(sd, sd)
        ratio = math.sqrt(float(np.sum(z * z)) / (dof * idx.size))
        return ratio, dof * idx.size ** 2 / float(np.sum(corr * corr))

    def whitened_ratio_of(self, indices) -> tuple[float, int]:
        """(whitened ratio, degrees of freedom) of the parameters ``indices`` alone: the
        deviations of that sub-vector whitened with its own block of the covariance (its
        marginal distribution), T ~ χ²_{(n−1)·len(indices)} if the block is right."""
        idx = np.asarray(indices, dtype=int)
        chol = np.linalg.cholesky(self.covariance[np.ix_(idx, idx)])
        w = np.linalg.solve(chol, self.deviations[:, idx].T)
        dof = (self.n_draws - 1) * idx.size
        return math.sqrt(float(np.sum(w * w)) / dof), dof

    def block_ratios(self) -> dict[str, tuple[float, int, int]]:
        """Per :func:`parameter_block` present: (whitened ratio of the block, degrees of
        freedom, number of parameters). Unlike the overall whitened ratio, in which a wrong σ of
        a few parameters is diluted by all others, these check each kind of parameter."""
        blocks: dict[str, list[int]] = {}
        for j, name in enumerate(self.parameter_names):
            blocks.setdefault(parameter_block(name), []).append(j)
        return {b: (*self.whitened_ratio_of(blocks[b]), len(blocks[b])) for b in PARAMETER_BLOCKS if b in blocks}

    def group_ratios(self) -> dict[str, tuple[float, float, int]]:
        """Per :func:`parameter_group`: (pooled ratio, effective degrees of freedom, number of
        parameters), in parameter order."""
        groups: dict[str, list[int]] = {}
        for j, name in enumerate(self.parameter_names):
            groups.setdefault(parameter_group(name), []).append(j)
        return {g: (*self.pooled_ratio(idx), len(idx)) for g, idx in groups.items()}


def compare_spread(results: Sequence["CalibrationResult"]) -> SpreadComparison:
    """Compare the reported covariances of calibrations of independent noise realisations of the
    same setup with the observed spread of their estimates (a Monte Carlo check).

    Deviations are taken from the Monte Carlo mean, so that what all draws share (the truth and
    any deterministic error, e.g. of the 8-bit quantisation without noise) does not count as
    spread. Statistics (Gaussian, linear regime): with d_i = θ_i − θ̄ and C the reported
    covariance, T = Σ_i d_iᵀ C⁻¹ d_i ~ χ²_{(n−1)P} — the whitened ratio √(T/((n−1)P)) has relative
    standard error 1/√(2(n−1)P) (e.g. 2.6 % for n = 10 draws of P = 76 parameters) and checks the
    whole covariance including correlations; the marginal ratio pools the per-parameter z-scores
    d_ij/σ_j, whose correlations leave (n−1)P²/Σ_jk r_jk² effective degrees of freedom.

    Parameters
    ----------
    results : sequence of CalibrationResult
        n ≥ 2 calibrations with the same parameters (same cameras, mirror poses, screen model).

    Returns
    -------
    SpreadComparison

    Raises
    ------
    ValueError
        Fewer than 2 results, different parameters, or a reported covariance that is not
        positive definite (e.g. exact data: σ = 0).
    """
    res = list(results)
    if len(res) < 2:
        raise ValueError(f"need at least 2 calibrations to compare spreads, got {len(res)}")
    names = res[0].parameter_names
    for r in res[1:]:
        if r.parameter_names != names:
            raise ValueError("the calibrations have different parameters (cameras, mirror poses or screen model)")
    ref = res[0].state
    x = np.array([ref.increment_to(r.state) for r in res])
    dev = x - x.mean(axis=0)
    cov = np.mean([r.covariance for r in res], axis=0)
    cov = 0.5 * (cov + cov.T)
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise ValueError("the mean reported covariance is not positive definite (exact data?)") from None
    n, p = x.shape
    w = np.linalg.solve(chol, dev.T)
    dof = (n - 1) * p
    sd = np.sqrt(np.diag(cov))
    z = dev / sd
    corr = cov / np.outer(sd, sd)
    return SpreadComparison(
        parameter_names=tuple(names),
        deviations=dev,
        covariance=cov,
        observed_std=np.sqrt(np.sum(dev * dev, axis=0) / (n - 1)),
        reported_std=sd,
        whitened_ratio=math.sqrt(float(np.sum(w * w)) / dof),
        whitened_dof=dof,
        marginal_ratio=math.sqrt(float(np.sum(z * z)) / dof),
        marginal_dof=(n - 1) * p * p / float(np.sum(corr * corr)),
    )
