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

from .metrics import surface_error_metrics
from .phase import PhaseDecodingError, PhaseFlag, ScreenCoordinates, decode_screen_coordinates
from .pipeline import decode_images, evaluate_decoded
from .reconstruction import Reconstruction, ReconstructionError, reconstruct
from .registration import Registration, RegistrationStatus, register

__all__ = ["surface_error_metrics", "PhaseDecodingError", "PhaseFlag", "ScreenCoordinates",
           "decode_screen_coordinates", "decode_images", "evaluate_decoded", "Reconstruction",
           "ReconstructionError", "reconstruct", "Registration", "RegistrationStatus", "register"]
