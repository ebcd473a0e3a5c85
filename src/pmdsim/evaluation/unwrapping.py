"""Temporal multi-period (hierarchical) phase unwrapping into a screen coordinate in mm.

The per-pixel steps :func:`_coarse_coord` and :func:`_refine` are numba functions that the fused
decoding kernel of :mod:`pmdsim.evaluation.decoding` calls too, so a coordinate unwrapped here and
one decoded there are the same arithmetic. Fringe model and units: docs/conventions.md
("Fringe patterns").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .phase_flags import (
    _INV_TWO_PI,
    _NONFINITE,
    _TWO_PI,
    _UNWRAP_INCONSISTENT,
    DEFAULT_UNWRAP_TOLERANCE,
    PhaseDecodingError,
)

__all__ = ["UnwrapResult", "unwrap_hierarchical"]


@dataclass(frozen=True)
class UnwrapResult:
    """Result of :func:`unwrap_hierarchical`. Unpacks as ``coord_mm, flags = result``.

    Attributes
    ----------
    coord_mm : ndarray, shape (H, W), float64
        Absolute screen coordinate in mm (docs/conventions.md), refined by the finest period.
        Not masked: flagged pixels keep their (unreliable) value; NaN only where a phase is NaN.
    flags : ndarray, shape (H, W), uint8
        :class:`PhaseFlag` bits UNWRAP_INCONSISTENT and NONFINITE.
    """

    coord_mm: np.ndarray
    flags: np.ndarray

    def __iter__(self):
        return iter((self.coord_mm, self.flags))


@numba.njit(cache=True, fastmath=False, error_model="numpy")
def _coarse_coord(phi, p0, origin, upper):
    """Coordinate from the coarsest phase, in [origin, origin + p0), wrapped back by −p0 above
    ``upper`` (origin + extent + margin)."""
    r = p0 * (phi / _TWO_PI) - origin
    c = origin + (r - p0 * np.floor(r / p0))
    if c > upper:
        c -= p0
    return c


@numba.njit(cache=True, fastmath=False, error_model="numpy")
def _refine(c, phi, p, inv_p, tolerance):
    """Refine coordinate c with the phase of the finer period p (``inv_p`` = 1/p):
    returns (c_k, inconsistent)."""
    fine = p * (phi * _INV_TWO_PI)
    ck = fine + p * np.floor((c - fine) * inv_p + 0.5)
    return ck, abs(c - ck) > tolerance * p


@numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _unwrap_kernel(phases, periods, origin, upper, tolerance, coord, flags):
    """Hierarchical unwrapping; ``periods`` descending. Flags are OR-ed into ``flags``.

    Serial: it is not on the hot path (:func:`decode_direction` unwraps inside
    :func:`_decode_kernel`), and a parallel kernel costs seconds of compilation."""
    n_p, h, w = phases.shape
    for v in range(h):
        for u in range(w):
            c = _coarse_coord(phases[0, v, u], periods[0], origin, upper)
            f = np.uint8(0)
            for k in range(1, n_p):
                c, bad = _refine(c, phases[k, v, u], periods[k], 1.0 / periods[k], tolerance)
                if bad:
                    f |= _UNWRAP_INCONSISTENT
            if not np.isfinite(c):
                f |= _NONFINITE
            coord[v, u] = c
            flags[v, u] |= f


def _check_periods(periods_mm, n_expected: int | None, name: str = "periods_mm") -> np.ndarray:
    p = np.asarray(periods_mm, dtype=np.float64)
    if p.ndim != 1 or p.size == 0:
        raise PhaseDecodingError(f"{name}: expected a 1-D sequence of periods in mm, got shape {p.shape}")
    if n_expected is not None and p.size != n_expected:
        raise PhaseDecodingError(
            f"{name}: {p.size} periods given but {n_expected} phase maps / image stacks"
        )
    if not np.all(np.isfinite(p)) or np.any(p <= 0):
        raise PhaseDecodingError(f"{name}: periods must be positive and finite (mm), got {p.tolist()}")
    if np.unique(p).size != p.size:
        raise PhaseDecodingError(f"{name}: periods must be distinct, got {p.tolist()}")
    return p


def _check_extent(extent_mm, origin_mm, p_max: float, name: str) -> tuple[float, float]:
    ext = float(extent_mm)
    org = float(origin_mm)
    if not (math.isfinite(ext) and ext > 0):
        raise PhaseDecodingError(f"{name}: the screen extent must be positive and finite (mm), got {extent_mm!r}")
    if not math.isfinite(org):
        raise PhaseDecodingError(f"{name}: the coordinate origin must be finite (mm), got {origin_mm!r}")
    if p_max < ext:
        raise PhaseDecodingError(
            f"{name}: the coarsest period {p_max:g} mm is shorter than the screen extent "
            f"{ext:g} mm, so its phase is ambiguous; the coarsest period must cover the whole "
            "extent (preferably with a margin) for hierarchical unwrapping"
        )
    return ext, org


def _resolve_margin(margin_mm, p0: float, extent: float) -> float:
    if margin_mm is None:
        return 0.5 * (p0 - extent)
    m = float(margin_mm)
    if not (math.isfinite(m) and 0 <= m <= p0 - extent):
        raise PhaseDecodingError(
            f"margin_mm must be in [0, coarsest period − extent] = [0, {p0 - extent:g}] mm, got {margin_mm!r}"
        )
    return m


def unwrap_hierarchical(
    phases,
    periods_mm,
    extent_mm: float,
    *,
    origin_mm: float = 0.0,
    tolerance: float = DEFAULT_UNWRAP_TOLERANCE,
    margin_mm: float | None = None,
) -> UnwrapResult:
    """Temporal multi-period (hierarchical) phase unwrapping into a screen coordinate in mm.

    Periods are processed in descending order p_0 > p_1 > … The coarsest phase gives the
    absolute coordinate c_0 = p_0·φ_0/2π (shifted by ``origin_mm``); a coordinate that lands
    above ``origin_mm + extent_mm + margin_mm`` is taken to be a wrap of a coordinate just
    below the lower end and moved back by −p_0. Each finer period refines::

        c_k = p_k·(φ_k/2π + round((c_{k−1} − p_k·φ_k/2π) / p_k))

    and the pixel is flagged UNWRAP_INCONSISTENT if |c_{k−1} − c_k| > ``tolerance``·p_k.
    Fringe phases follow docs/conventions.md: φ = 2π·c/p wrapped to [0, 2π).

    Parameters
    ----------
    phases : array_like, shape (P, H, W)
        Wrapped phases in radians, ``phases[i]`` belonging to ``periods_mm[i]``. Values outside
        [0, 2π) are accepted (only φ mod 2π matters).
    periods_mm : array_like, shape (P,)
        Distinct positive fringe periods in mm, in any order (sorted descending internally).
    extent_mm : float
        Length of the screen along this direction in mm; coordinates lie in
        [origin_mm, origin_mm + extent_mm]. The coarsest period must be ≥ ``extent_mm``.
    origin_mm : float
        Lowest screen coordinate in mm (default 0).
    tolerance : float
        Consistency tolerance as a fraction of the finer period, in (0, 0.5]. Default 0.25.
        (|c_{k−1} − c_k| ≤ p_k/2 holds by construction, so 0.5 never flags.)
    margin_mm : float, optional
        How far above the extent a coarse coordinate may lie before it is treated as a wrap,
        in [0, p_0 − extent_mm]. Default (p_0 − extent_mm)/2, i.e. the unused part of the
        coarsest period is split evenly between both ends of the screen.

    Returns
    -------
    UnwrapResult
        ``coord_mm`` (H, W) float64 in mm and ``flags`` (H, W) uint8 (UNWRAP_INCONSISTENT,
        NONFINITE). Unpacks as ``coord_mm, flags``.

    Raises
    ------
    PhaseDecodingError
        If shapes do not match, periods are not positive/distinct, the coarsest period is
        shorter than ``extent_mm``, or ``tolerance``/``margin_mm`` are out of range.
    """
    ph = np.asarray(phases)
    if ph.ndim != 3:
        raise PhaseDecodingError(f"phases: expected shape (P, H, W), got shape {ph.shape}")
    if ph.dtype.kind not in "fiu":
        raise PhaseDecodingError(f"phases: expected real phases in radians, got dtype {ph.dtype}")
    periods = _check_periods(periods_mm, ph.shape[0])
    order = np.argsort(-periods, kind="stable")
    periods = np.ascontiguousarray(periods[order])
    ext, org = _check_extent(extent_mm, origin_mm, periods[0], "extent_mm")
    tol = float(tolerance)
    if not (0 < tol <= 0.5):
        raise PhaseDecodingError(f"tolerance must be in (0, 0.5] (fraction of the finer period), got {tolerance!r}")
    margin = _resolve_margin(margin_mm, periods[0], ext)
    if not np.array_equal(order, np.arange(order.size)):
        ph = ph[order]
    ph = np.ascontiguousarray(ph, dtype=np.float64)
    _, h, w = ph.shape
    coord = np.empty((h, w), np.float64)
    flags = np.zeros((h, w), np.uint8)
    _unwrap_kernel(ph, periods, org, org + ext + margin, tol, coord, flags)
    return UnwrapResult(coord_mm=coord, flags=flags)
