"""Holistic calibration with a planar mirror (layer 2, paper §4) and free-form screen models (§5).

Pixel ↔ decoded screen-point correspondences of several cameras and mirror poses → cameras'
intrinsics and poses, mirror planes and (optionally) the screen's free control heights, with
covariance and a report of how well the data determine them. The modules, from the bottom:
:mod:`.errors` (exceptions), :mod:`.screen` (free-form screen model, §5), :mod:`.model`
(parameter names/units/blocks, state, observations; gauge, forward model and parameterisation),
:mod:`.kernel` (numba model and Jacobian kernels), :mod:`.result` (covariance, σ, weak
directions, determination report), :mod:`.solver` (Levenberg–Marquardt, conditioning and
degeneracy checks), :mod:`.spread` (Monte Carlo spread comparison), and :mod:`.setup_bridge`
between a :class:`~pmdsim.setup.Setup` and the parameter state.
Gauge and parameterisation: docs/conventions.md and :mod:`.model`.

May import: :mod:`pmdsim.errors`, :mod:`pmdsim.geometry`, :mod:`pmdsim.setup`.
"""

from .errors import CalibrationDataError, CalibrationDegenerateError, CalibrationError
from .screen import ScreenModel
from .model import (
    CAMERA_PARAMETERS,
    DEFAULT_CONDITION_LIMIT,
    MIN_CORRESPONDENCES,
    MIN_POSES,
    MIRROR_PARAMETERS,
    PARAMETER_BLOCKS,
    PARAMETER_UNITS,
    SCREEN_HEIGHT_UNIT_MM,
    SCREEN_WEIGHT_MIN,
    WEAK_DIRECTIONS,
    CalibrationState,
    CameraParams,
    MirrorPlane,
    Observations,
    mirror_plane_from_pose,
    nominal_state,
    observations_from_mapping,
    parameter_block,
    parameter_group,
    perturbed_state,
)
from .result import CalibrationResult, WeakDirection
from .solver import calibrate, residuals_and_jacobian
from .spread import SpreadComparison, compare_spread
from .setup_bridge import (
    calibrated_setup,
    calibration_deviation,
    calibration_summary,
    free_screen_model,
    nominal_setup,
    table_frame_from_plane,
)

__all__ = [
    "CalibrationError", "CalibrationDataError", "CalibrationDegenerateError", "Observations", "ScreenModel",
    "observations_from_mapping", "CameraParams", "MirrorPlane", "CalibrationState", "CalibrationResult",
    "WeakDirection", "calibrate", "residuals_and_jacobian", "nominal_state", "perturbed_state",
    "mirror_plane_from_pose", "CAMERA_PARAMETERS", "MIRROR_PARAMETERS", "PARAMETER_UNITS",
    "SCREEN_HEIGHT_UNIT_MM", "SCREEN_WEIGHT_MIN", "MIN_CORRESPONDENCES", "MIN_POSES",
    "DEFAULT_CONDITION_LIMIT", "WEAK_DIRECTIONS", "SpreadComparison", "compare_spread", "parameter_group",
    "parameter_block", "PARAMETER_BLOCKS",
    "calibrated_setup", "calibration_deviation", "calibration_summary", "free_screen_model", "nominal_setup",
    "table_frame_from_plane",
]
