"""The screen's cover glass in the holistic calibration (issue 21).

The decoded correspondences give points Q on the *emitting* surface; the light reached the camera
from the glass's exit point, via the mirror. With a glass in the :class:`CalibrationState`
(``glass``, a :class:`~pmdsim.geometry.cover_glass.CoverGlass`) the forward model projects the
**apparent point** instead of Q: where the straight line from the virtual camera centre through
the exit point meets the emitting surface's tangent plane (local-plate model,
:mod:`pmdsim.calibration.glass_kernel`). Its thickness t and index n can be **free parameters**
of the Levenberg–Marquardt solver (``glass_free``; names ``screen.glass_thickness_mm``,
``screen.glass_index``), with the analytic Jacobian through the implicit apparent point and their
standard deviations from the calibration's covariance, like the free screen heights.

:func:`calibrate_with_glass` is the staged fit: first with the glass held at its start values
(which brings the cameras and mirrors near their solution), then with the chosen glass
parameters free. t alone is well determined by a 16-pose calibration (its effect grows with the
viewing angle, tan θ − tan θ_g, unlike any camera or mirror parameter); t and n together are
strongly correlated (both scale the shift, differently only at large angles), so fit n only with
a good pose set and expect a large σ_n.
"""

from __future__ import annotations

from dataclasses import replace

from ..geometry.cover_glass import CoverGlass
from .model import CalibrationState
from .solver import calibrate

__all__ = ["calibrate_with_glass"]


def calibrate_with_glass(observations, start: CalibrationState, glass: CoverGlass, *, screen_model=None,
                         fit_thickness: bool = True, fit_index: bool = False, **options):
    """Holistic calibration with the screen's cover glass (module docstring: the staged fit).

    Parameters
    ----------
    observations : list of Observations
        The decoded correspondences (points on the emitting surface).
    start : CalibrationState
        Start values of the cameras and mirrors (its glass and screen model are replaced).
    glass : CoverGlass
        The glass's start (or known) thickness and index; a thickness of 0 with nothing to fit is
        the glass-free calibration.
    screen_model : ScreenModel, optional
        Free-form screen model estimated jointly (as in :func:`calibrate`); None keeps
        ``start.screen``.
    fit_thickness, fit_index : bool
        Estimate t, n (second stage); both False: the glass is held (one stage).
    **options
        Passed to :func:`calibrate` (``max_iter``, ``ftol``, …).

    Returns
    -------
    CalibrationResult
        The final stage's result: its ``glass`` is the fitted glass, ``glass_std()`` the σ of
        the free parameters.
    """
    if not isinstance(glass, CoverGlass):
        raise TypeError(f"glass must be a CoverGlass, got {type(glass).__name__}")
    screen = start.screen if screen_model is None else screen_model
    free = (bool(fit_thickness), bool(fit_index))
    use = glass if (glass.present or any(free)) else None
    held = CalibrationState(start.cameras, start.mirrors, screen, use, (False, False))
    first = calibrate(observations, held, **options)
    if not any(free):
        return first
    return calibrate(observations, replace(first.state, glass_free=free), **options)
