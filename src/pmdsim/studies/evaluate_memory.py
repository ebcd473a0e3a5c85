"""What ``pmdsim evaluate`` keeps of a camera once it is evaluated (issue 25, item 1: memory).

The files (``evaluation.h5``), the joint surface fit and the summary read only part of a
camera's decoding and registration; the rest — the decoder's modulation and offset, the
registration's view rays and screen points, (H, W, 2) and (H, W, 3) float64 maps, 184 MB per
1920×1200 camera — is released as soon as the camera's reconstruction and σ are done, instead of
being held until every camera is evaluated and the files are written.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..evaluation.registration import RegistrationStatus

__all__ = ["KeptDecoding", "KeptRegistration", "kept_for_files"]


@dataclass(frozen=True, eq=False)
class KeptDecoding:
    """The decoding's maps that are written or summarised (``ScreenCoordinates`` field names)."""

    screen_xy_mm: np.ndarray
    valid: np.ndarray
    flags: np.ndarray
    std_xy_mm: np.ndarray
    reversed: np.ndarray | None


@dataclass(frozen=True, eq=False)
class KeptRegistration:
    """The registration's camera centre and status (``Registration`` field names)."""

    o_ref_mm: np.ndarray
    status: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.status == RegistrationStatus.VALID


def kept_for_files(decoded, reg, rec) -> tuple[KeptDecoding, KeptRegistration, object]:
    """``(decoded, reg, rec)`` with only what the files, the surface fit and the summary read
    (the arrays are shared, not copied; ``rec`` as it is)."""
    return (KeptDecoding(decoded.screen_xy_mm, decoded.valid, decoded.flags, decoded.std_xy_mm,
                         getattr(decoded, "reversed", None)),
            KeptRegistration(reg.o_ref_mm, reg.status), rec)
