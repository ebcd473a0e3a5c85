"""The screen's cover glass in the holistic calibration (issue 21).

The decoded correspondences give points Q on the *emitting* surface; the light reached the camera
from the glass's exit point A, via the mirror. The planar-mirror model of :mod:`.model` takes a
screen point whose straight line to the *virtual camera centre* c′ (the camera centre mirrored
across the mirror plane) is the ray. With a glass that point is the **apparent point**
(:meth:`~pmdsim.geometry.cover_glass.CoverGlass.apparent_points` with P = c′): where the straight
line c′ → A meets the emitting surface. It depends on the camera centre and the mirror plane
(through c′) and on the glass (t, n).

Method (documented approximation of the joint problem):

* **Glass held** (:func:`calibrate_with_glass`): an outer fixed point around :func:`calibrate`:
  compute the apparent points at the current state, calibrate (warm started), repeat until the
  apparent points move by less than ``tol_mm``. Inside one calibration the apparent points are
  held, i.e. their (weak, ≈ t/|c′Q| relative) dependence on the camera and mirror parameters is
  not in the Jacobian; at the fixed point the model is exact, and with noise-free data the
  truth is a zero-residual fixed point. The covariance of the other parameters is that of
  :func:`calibrate` with the glass known.
* **Thickness fitted** (:func:`fit_glass_thickness`): the profile of the cost over t,
  SSR(t) = min over all other parameters (each a :func:`calibrate_with_glass`), minimised by
  Newton steps on central differences; σ_t from the profile's curvature,
  σ_t² = 2·σ̂²/SSR″(t̂) with σ̂² = SSR(t̂)/(2M − p − 1) — for least squares the profile's
  curvature is 2/[(JᵀJ)⁻¹]_tt, so this is the linearised standard deviation of t (residual
  noise model, i.i.d. pixel residuals). The index n is held (it is known for a given glass
  type; fitting it jointly with t is nearly degenerate: both scale the shift alike).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry.cover_glass import CoverGlass
from .model import CalibrationState, Observations
from .solver import calibrate

__all__ = ["glass_observations", "calibrate_with_glass", "GlassFit", "fit_glass_thickness"]


def glass_observations(observations, state: CalibrationState, glass: CoverGlass, surface) -> list[Observations]:
    """The correspondences with their screen points replaced by the apparent points of ``glass``
    for the camera centres and mirror planes of ``state`` (``surface``: the emitting surface
    of the screen model, screen frame). Correspondences whose apparent point fails are dropped."""
    out = []
    for o in observations:
        c = state.cameras[o.camera].position_mm
        cp = state.mirrors[o.pose_index].reflect(c)
        q = np.array(o.q_screen_mm, dtype=float)
        q[:, 2] = surface.height(q[:, 0], q[:, 1])
        qa = glass.apparent_points(surface, cp, q)
        ok = np.isfinite(qa).all(axis=-1)
        std = None if o.q_std_mm is None else np.asarray(o.q_std_mm)[ok]
        out.append(Observations(o.camera, o.pose_index, o.uv_px[ok], qa[ok], std))
    return out


def _surface(state: CalibrationState, planar_surface):
    return planar_surface if state.screen is None else state.screen.surface


def calibrate_with_glass(observations, start: CalibrationState, glass: CoverGlass, planar_surface, *,
                         screen_model=None, max_outer: int = 6, tol_mm: float = 1e-6):
    """Holistic calibration with a known cover glass (module docstring: outer fixed point).

    Parameters
    ----------
    observations : list of Observations
        The decoded correspondences (emitting-surface points).
    start : CalibrationState
        Start values.
    glass : CoverGlass
        The glass (held).
    planar_surface : SplineSurface or PlaneSurface
        The planar screen over the screen's grid (the emitting surface without a screen model).
    screen_model : ScreenModel, optional
        Free-form screen model estimated jointly (as in :func:`calibrate`).

    Returns
    -------
    (CalibrationResult, int)
        The last calibration and the number of outer iterations.
    """
    obs = list(observations)
    if not glass.present:
        return calibrate(obs, start, screen_model=screen_model), 0
    state = start if screen_model is None else CalibrationState(start.cameras, start.mirrors, screen_model)
    prev = None
    result = None
    for it in range(1, max_outer + 1):
        eff = glass_observations(obs, state, glass, _surface(state, planar_surface))
        q = np.concatenate([o.q_screen_mm[:, :2] for o in eff])
        result = calibrate(eff, state, screen_model=state.screen)
        state = result.state
        if prev is not None and prev.shape == q.shape and float(np.abs(q - prev).max()) < tol_mm:
            return result, it
        prev = q
    return result, max_outer


@dataclass(frozen=True, eq=False)
class GlassFit:
    """Result of :func:`fit_glass_thickness`: the calibration at the fitted thickness."""

    result: object  # CalibrationResult
    glass: CoverGlass
    thickness_std_mm: float
    profile: tuple[tuple[float, float], ...]  # (t, SSR) evaluated


def fit_glass_thickness(observations, start: CalibrationState, glass0: CoverGlass, planar_surface, *,
                        screen_model=None, step_mm: float = 0.1, tol_mm: float = 1e-3, max_iter: int = 8) -> GlassFit:
    """Estimate the glass thickness t jointly with the calibration (module docstring: profile).

    ``glass0`` gives the start thickness and the (held) index. Returns the calibration at t̂ and
    σ_t.
    """
    obs = list(observations)
    state = start
    profile = []

    def ssr(t):
        nonlocal state
        r, _ = calibrate_with_glass(obs, state, glass0.with_(thickness_mm=max(t, 0.0)), planar_surface,
                                    screen_model=screen_model if state.screen is None else state.screen)
        state = r.state
        f = float(r.rms_px) ** 2 * r.n_residuals
        profile.append((float(t), f))
        return f, r

    t = glass0.thickness_mm
    h = step_mm
    f0 = fm = fp = curv = None
    for _ in range(max_iter):
        fm, _ = ssr(t - h)
        fp, _ = ssr(t + h)
        f0, r0 = ssr(t)
        curv = (fp - 2.0 * f0 + fm) / (h * h)
        if not curv > 0:
            raise ValueError(f"the cost is not convex in the glass thickness around t = {t:g} mm; "
                             f"the data do not determine it")
        dt = -(fp - fm) / (2.0 * h) / curv  # SSR is nearly quadratic in t: 1–2 steps
        t = max(t + dt, h)
        if abs(dt) < tol_mm:
            break
    f_hat, r_hat = ssr(t)
    dof = max(r_hat.n_residuals - len(r_hat.parameter_names) - 1, 1)
    sigma2 = f_hat / dof
    std = math.sqrt(2.0 * sigma2 / curv)
    return GlassFit(r_hat, glass0.with_(thickness_mm=t), std, tuple(profile))
