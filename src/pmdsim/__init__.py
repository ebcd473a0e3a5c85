"""pmdsim: simulation and evaluation of phase-measuring deflectometry (PMD).

Founding document: "The effects of pattern screen surface deformation on deflectometric
measurements — a simulation study". Conventions: docs/conventions.md; the package map:
docs/architecture.md; a walk-through: docs/api.md.

The names a notebook needs are available here (imported on first use, so that ``import pmdsim``
and ``pmdsim --version`` stay fast and compile nothing)::

    import pmdsim
    setup = pmdsim.default_setup().with_bulge(3.0).binned(4)
    m = pmdsim.simulate(setup, "left")                 # traced mapping + fringe images
    decoded = pmdsim.decode(m.images, setup)           # screen coordinates per pixel
    ev = pmdsim.evaluate(decoded, setup.with_bulge(0.0), "left", seed_pixel=(150, 240),
                         seed_height_mm=0.0)           # planar-screen evaluation, as the paper's

Setups: :class:`Setup`, :func:`default_setup` (Table 1), :func:`load_setup`, :func:`parse_setup`.
Steps: :func:`simulate`, :func:`decode`, :func:`evaluate`, :func:`reconstruct`,
:func:`calibrate`, :func:`calibrated_setup`. Results: :class:`Measurement`,
:class:`ScreenCoordinates`, :class:`Evaluation`, :class:`Reconstruction`,
:class:`CalibrationResult`. Errors: :class:`PmdsimError` and its subclasses.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    "Setup": "pmdsim.setup",
    "default_setup": "pmdsim.setup",
    "load_setup": "pmdsim.setup",
    "parse_setup": "pmdsim.setup",
    "Measurement": "pmdsim.api",
    "simulate": "pmdsim.api",
    "decode": "pmdsim.api",
    "Evaluation": "pmdsim.api",
    "evaluate": "pmdsim.api",
    "evaluate_stereo": "pmdsim.api",
    "calibrate": "pmdsim.api",
    "calibrated_setup": "pmdsim.api",
    "reconstruct": "pmdsim.api",
    "ScreenCoordinates": "pmdsim.evaluation.phase",
    "Reconstruction": "pmdsim.evaluation.reconstruction",
    "CalibrationResult": "pmdsim.calibration",
    "PmdsimError": "pmdsim.errors",
    "SetupError": "pmdsim.errors",
    "ImageSetError": "pmdsim.errors",
    "ComputationError": "pmdsim.errors",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'pmdsim' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
