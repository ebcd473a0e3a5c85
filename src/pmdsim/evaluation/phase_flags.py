"""Per-pixel validity flags, thresholds and the error type of fringe decoding.

Shared by :mod:`pmdsim.evaluation.decoding` (N-step phase, masks),
:mod:`pmdsim.evaluation.unwrapping` (hierarchical unwrapping) and
:mod:`pmdsim.evaluation.phase_noise` (the σ model); :mod:`pmdsim.evaluation.phase` re-exports
them all.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from ..errors import PmdsimError

__all__ = [
    "PhaseDecodingError",
    "PhaseFlag",
    "DEFAULT_DARK_FRACTION",
    "DEFAULT_MIN_MODULATION_FRACTION",
    "DEFAULT_MIN_MODULATION_RATIO",
    "DEFAULT_UNWRAP_TOLERANCE",
]

_TWO_PI = 2.0 * math.pi
_INV_TWO_PI = 1.0 / _TWO_PI

#: Default ``dark_fraction``: offset A below 2 % of full scale (5.1 grey levels at 8 bit) is DARK.
DEFAULT_DARK_FRACTION = 0.02
#: Default ``min_modulation_fraction``: modulation B below 1 % of full scale (2.55 grey levels
#: at 8 bit) is LOW_MODULATION.
DEFAULT_MIN_MODULATION_FRACTION = 0.01
#: Default ``min_modulation_ratio``: contrast B/A below 0.05 is LOW_MODULATION.
DEFAULT_MIN_MODULATION_RATIO = 0.05
#: Default ``tolerance`` of hierarchical unwrapping, as a fraction of the finer period.
DEFAULT_UNWRAP_TOLERANCE = 0.25


class PhaseDecodingError(PmdsimError, ValueError):
    """Fringe images, phases or decoding parameters are invalid.

    The message names the offending argument (for example ``images_by_period[2]`` or
    ``periods_mm``) and what was expected.
    """


class PhaseFlag(enum.IntFlag):
    """Reasons why a pixel's decoded phase or coordinate is invalid (bits of a ``uint8`` map).

    A pixel is valid if and only if its flag value is 0 (:attr:`VALID`). Several bits may be set.

    ==========================  =====  ======================================================
    name                        value  meaning
    ==========================  =====  ======================================================
    ``VALID``                   0      no problem found
    ``DARK``                    1      offset A below ``dark_fraction · max_value`` (includes
                                       black pixels, which the simulator writes for invalid
                                       pixels)
    ``SATURATED``               2      at least one sample at or above ``max_value``
    ``LOW_MODULATION``          4      modulation B below ``min_modulation_fraction ·
                                       max_value`` or contrast B/A below
                                       ``min_modulation_ratio`` (includes constant pixels)
    ``UNWRAP_INCONSISTENT``     8      in a hierarchical unwrapping step the coarser
                                       coordinate disagrees with the finer one by more than
                                       ``tolerance ·`` (finer period). A period whose
                                       contrast the lens reversed (a π flip: half a period
                                       off, weak contrast) is corrected instead and marked
                                       in the results' ``reversed`` map
                                       (:mod:`pmdsim.evaluation.unwrapping`)
    ``NONFINITE``               16     a sample or phase is NaN or infinite
    ``FIT_RESIDUAL``            32     an image deviates from the sinusoid fitted to its
                                       period's N images by more than the noise allows
                                       (a dropped, duplicated or foreign frame; set by
                                       :mod:`pmdsim.evaluation.consistency`)
    ``PERIOD_MISMATCH``         64     a period's coordinate disagrees with the next coarser
                                       one by more than the predicted noise of both (a wrong
                                       period, misregistered images, a missing shift; set
                                       by :mod:`pmdsim.evaluation.consistency`)
    ``GEOMETRY``                128    the decoded coordinate lies outside the screen, or the
                                       local orientation of the pixel → screen mapping is
                                       flipped against the nominal sample's (a reversed shift
                                       order or swapped directions; set by
                                       :mod:`pmdsim.evaluation.consistency`)
    ==========================  =====  ======================================================

    The decoder itself (:func:`decode_screen_coordinates`) sets bits 1–16; the consistency
    bits 32–128 are OR-ed in by :func:`pmdsim.evaluation.consistency.check_consistency`.
    """

    VALID = 0
    DARK = 1
    SATURATED = 2
    LOW_MODULATION = 4
    UNWRAP_INCONSISTENT = 8
    NONFINITE = 16
    FIT_RESIDUAL = 32
    PERIOD_MISMATCH = 64
    GEOMETRY = 128


_DARK = np.uint8(PhaseFlag.DARK)
_SATURATED = np.uint8(PhaseFlag.SATURATED)
_LOW_MODULATION = np.uint8(PhaseFlag.LOW_MODULATION)
_UNWRAP_INCONSISTENT = np.uint8(PhaseFlag.UNWRAP_INCONSISTENT)
_NONFINITE = np.uint8(PhaseFlag.NONFINITE)
