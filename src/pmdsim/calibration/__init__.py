"""Holistic calibration with a planar mirror (layer 2, paper §4) and free-form screen models (§5).

Pixel ↔ decoded screen-point correspondences of several cameras and mirror poses → cameras'
intrinsics and poses, mirror planes and (optionally) the screen's free control heights, with
covariance and a report of how well the data determine them. The modules, from the bottom:
the numba model and Jacobian kernel, the parameter state and observations, the free-form
screen model, the Levenberg–Marquardt solver, uncertainty and determination reports, and
:mod:`.setup_bridge` between a :class:`~pmdsim.setup.Setup` and the parameter state.
Gauge and parameterisation: docs/conventions.md and :mod:`.core`.

May import: :mod:`pmdsim.errors`, :mod:`pmdsim.geometry`, :mod:`pmdsim.setup`.
"""

from .core import (
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
    CalibrationDataError,
    CalibrationDegenerateError,
    CalibrationError,
    CalibrationResult,
    CalibrationState,
    CameraParams,
    MirrorPlane,
    Observations,
    ScreenModel,
    SpreadComparison,
    WeakDirection,
    calibrate,
    compare_spread,
    mirror_plane_from_pose,
    nominal_state,
    observations_from_mapping,
    parameter_block,
    parameter_group,
    perturbed_state,
    residuals_and_jacobian,
)
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
