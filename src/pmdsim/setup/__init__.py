"""The description of an instrument (layer 1, above :mod:`pmdsim.geometry`).

What a measurement *is*, independent of how it is simulated or evaluated: the cameras and their
poses, the pattern screen's shape and pose, the sample, the displayed fringe sequence and the
calibration mirror poses, as immutable value objects (:mod:`.model`), the fringe sequence
(:mod:`.fringes`) and their TOML form (:mod:`.toml`). The paper's Table 1 is
:func:`default_setup`.

May import: :mod:`pmdsim.errors`, :mod:`pmdsim.geometry`.
"""

from .fringes import DIRECTIONS, FringeSequence, PatternFrame
from .model import (
    SETUP_FORMAT,
    CalibrationSetup,
    CameraSetup,
    ImagingSetup,
    PatternSetup,
    Pose,
    SampleSetup,
    ScreenSetup,
    Setup,
    default_setup,
)
from .sample_shape import HeightMapData, HeightMapSource, InterpolationReport, SampleShape
from .toml import load_setup, parse_setup

__all__ = [
    "DIRECTIONS",
    "FringeSequence",
    "PatternFrame",
    "SETUP_FORMAT",
    "CalibrationSetup",
    "CameraSetup",
    "ImagingSetup",
    "PatternSetup",
    "Pose",
    "SampleSetup",
    "SampleShape",
    "HeightMapData",
    "HeightMapSource",
    "InterpolationReport",
    "ScreenSetup",
    "Setup",
    "default_setup",
    "load_setup",
    "parse_setup",
]
