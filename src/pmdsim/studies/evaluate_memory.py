"""What ``pmdsim evaluate`` keeps of a camera once it is evaluated (issue 25, item 1: memory).

The files (``evaluation.h5``), the joint surface fit and the summary read only part of a
camera's decoding and registration; the rest — the decoder's modulation and offset, the
registration's view rays and screen points, (H, W, 2) and (H, W, 3) float64 maps, 184 MB per
1920×1200 camera — is released as soon as the camera's reconstruction and σ are done, instead of
being held until every camera is evaluated and the files are written.

:func:`small_pages`: numpy asks the kernel for transparent huge pages for every large array
(``madvise(MADV_HUGEPAGE)``, its default on Linux). On the 2-vCPU VM the first touch of such
memory costs ≈ 2.8 ms/MB of system time (the kernel compacts memory to find 2 MB pages: 1.33 GB
of fresh arrays 3.7 s, 0.42 ms/MB with 4 kB pages), and an evaluation touches ≈ 1.4 GB of
memory its process never had; :func:`small_pages` turns the hint off while it runs.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

from ..evaluation.registration import RegistrationStatus

__all__ = ["KeptDecoding", "KeptRegistration", "kept_for_files", "small_pages"]


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


def _hugepage_switch():
    """numpy's (getter, setter) of its huge-page hint, or None where it has none."""
    try:
        from numpy._core import multiarray as ma
    except ImportError:  # pragma: no cover - numpy < 2
        from numpy.core import multiarray as ma
    get, put = getattr(ma, "_get_madvise_hugepage", None), getattr(ma, "_set_madvise_hugepage", None)
    return (get, put) if get is not None and put is not None else None


@contextlib.contextmanager
def small_pages():
    """numpy's huge-page hint off while the ``with`` block runs (module docstring), the previous
    setting restored afterwards, also on an exception (process-wide: arrays other threads
    allocate meanwhile get 4 kB pages too)."""
    switch = _hugepage_switch()
    if switch is None:  # pragma: no cover - a numpy without the hint
        yield
        return
    before = switch[1](False)  # returns the previous setting
    try:
        yield
    finally:
        switch[1](bool(before))
