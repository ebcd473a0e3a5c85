"""Exceptions of the holistic calibration (:mod:`pmdsim.calibration`).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import PmdsimError


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
