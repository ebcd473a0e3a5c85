"""Phase decoding of phase-shifted fringe images: the public names in one place.

The numeric core lives in three modules (split from this one, issue 20):

* :mod:`pmdsim.evaluation.decoding` — N-step phase, modulation and offset with per-pixel
  validity flags (:func:`wrapped_phase`), one fringe direction (:func:`decode_direction`) and the
  pixel → screen mapping (:func:`decode_screen_coordinates`);
* :mod:`pmdsim.evaluation.unwrapping` — temporal multi-period (hierarchical) unwrapping
  (:func:`unwrap_hierarchical`);
* :mod:`pmdsim.evaluation.phase_noise` — the σ model (:data:`QUANTISATION_NOISE_STD`,
  :func:`sensor_noise_std`);

with the flags, thresholds and error type in :mod:`pmdsim.evaluation.phase_flags`. This module
re-exports them, so ``from pmdsim.evaluation.phase import …`` keeps working.
"""

from __future__ import annotations

from .decoding import (
    DirectionResult,
    PhaseResult,
    ScreenCoordinates,
    decode_direction,
    decode_screen_coordinates,
    equal_shifts,
    wrapped_phase,
)
from .phase_flags import (
    DEFAULT_DARK_FRACTION,
    DEFAULT_MIN_MODULATION_FRACTION,
    DEFAULT_MIN_MODULATION_RATIO,
    DEFAULT_UNWRAP_TOLERANCE,
    PhaseDecodingError,
    PhaseFlag,
)
from .phase_noise import QUANTISATION_NOISE_STD, sensor_noise_std
from .unwrapping import UnwrapResult, unwrap_hierarchical

__all__ = [
    "PhaseDecodingError",
    "PhaseFlag",
    "PhaseResult",
    "UnwrapResult",
    "DirectionResult",
    "ScreenCoordinates",
    "QUANTISATION_NOISE_STD",
    "DEFAULT_DARK_FRACTION",
    "DEFAULT_MIN_MODULATION_FRACTION",
    "DEFAULT_MIN_MODULATION_RATIO",
    "DEFAULT_UNWRAP_TOLERANCE",
    "equal_shifts",
    "wrapped_phase",
    "unwrap_hierarchical",
    "decode_direction",
    "decode_screen_coordinates",
    "sensor_noise_std",
]
