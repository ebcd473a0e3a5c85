"""Evaluation (layer 2): from fringe images to a surface (paper §2.5).

* :mod:`.phase` — N-step phase decoding, masks with a reason per pixel, hierarchical
  (temporal) unwrapping and the decoder's noise model → :class:`~.phase.ScreenCoordinates`;
* :mod:`.registration` — each pixel's view ray and decoded screen point in the reconstruction
  (sample) frame, for any screen model;
* :mod:`.reconstruction` — slope-based integration: stepwise (the paper's §2.5) and least squares
  (Southwell, Gauss–Newton);
* :mod:`.pipeline` — decode → register → reconstruct for one camera of a setup;
* :mod:`.metrics` — the figures of merit of the paper's Tables 2 and 3.

May import: :mod:`pmdsim.errors`, :mod:`pmdsim.geometry`, :mod:`pmdsim.setup`.
"""

import importlib

#: Public name → the submodule defining it, imported on first use (PEP 562), so that importing one
#: submodule (``pmdsim evaluate`` needs the decoder, registration and reconstruction) does not
#: import the others (the pipeline, the metrics and what they import: docs/benchmarks.md, "start-up").
_LAZY = {"surface_error_metrics": "metrics", "PhaseDecodingError": "phase", "PhaseFlag": "phase",
         "ScreenCoordinates": "phase", "decode_screen_coordinates": "phase", "decode_images": "pipeline",
         "evaluate_decoded": "pipeline", "Reconstruction": "reconstruction", "ReconstructionError": "reconstruction",
         "reconstruct": "reconstruction", "Registration": "registration", "RegistrationStatus": "registration",
         "register": "registration"}

__all__ = list(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = globals()[name] = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
