"""Calibration result: covariance (sandwich), σ, weak directions and the determination report.

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
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .screen import ScreenModel
from ..geometry.cover_glass import CoverGlass
from .model import GLASS_PARAMETERS, CalibrationState, CameraParams, DEFAULT_CONDITION_LIMIT, _matrix_to_rotvec


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
    glass : CoverGlass or None
        The screen's cover glass of the model (fitted where ``glass_free``; None: none); the
        standard deviations of free ones are the ``screen.glass_thickness_mm`` and
        ``screen.glass_index`` entries of :attr:`parameter_std` (:meth:`glass_std`).
    glass_free : tuple[bool, bool]
        Whether the thickness and the index were estimated.
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
    glass: CoverGlass | None = None
    glass_free: tuple = (False, False)

    def glass_std(self) -> tuple[float | None, float | None]:
        """(σ_t in mm, σ_n) of the fitted glass thickness and index (None where not fitted)."""
        return tuple(self.std(GLASS_PARAMETERS[g]) if self.glass_free[g] else None for g in (0, 1))

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
                                tuple(self.mirrors), self.screen_model, self.glass, self.glass_free)

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
        glass = None
        if self.glass is not None:
            st, sn = self.glass_std()
            glass = {"thickness_mm": self.glass.thickness_mm, "index": self.glass.index,
                     "fit_thickness": bool(self.glass_free[0]), "fit_index": bool(self.glass_free[1]),
                     "thickness_std_mm": st, "index_std": sn}
        return {
            "frame": "screen (held fixed)",
            "screen": screen,
            "glass": glass,
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
