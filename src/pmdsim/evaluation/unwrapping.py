"""Temporal multi-period (hierarchical) phase unwrapping into a screen coordinate in mm.

The per-pixel steps :func:`_coarse_coord` and :func:`_refine` are numba functions that the fused
decoding kernel of :mod:`pmdsim.evaluation.decoding` calls too, so a coordinate unwrapped here and
one decoded there are the same arithmetic. Fringe model and units: docs/conventions.md
("Fringe patterns").

Contrast reversal (issue 20). A defocused lens multiplies a fringe of period p by the transfer
2·J₁(x)/x, x = 4πσ/p (:mod:`pmdsim.simulation.optics`); beyond its first zero (σ > 0.305·p) the
transfer is negative: the recorded fringe is the displayed one shifted by half a period (a π
phase flip) and weak (|2·J₁(x)/x| ≤ 0.132 in the first negative lobe). A refinement step whose
finer coordinate lies half a period (± :data:`REVERSAL_PHASE_TOLERANCE` periods) from the
coarser one, and whose contrast B/A is at most :data:`REVERSAL_CONTRAST_RATIO` times the
coarser period's, is taken as reversed: its phase is shifted by π and the pixel is marked in
``reversed`` (not a flag: the coordinate is right). A pixel half a period off with a strong
contrast is a real inconsistency and stays UNWRAP_INCONSISTENT; a pixel near a zero of the
transfer has no usable contrast and is LOW_MODULATION.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

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

__all__ = ["REVERSAL_CONTRAST_RATIO", "REVERSAL_PHASE_TOLERANCE", "UnwrapResult", "unwrap_hierarchical"]

#: A finer period is taken as reversed only if its contrast B/A is at most this fraction of the
#: coarser period's (the negative lobes of 2·J₁(x)/x reach 0.132; a coarser period at the same
#: blur has a transfer ≥ 0.5 wherever the finer one has reversed, for period ratios ≥ 2).
REVERSAL_CONTRAST_RATIO = 0.25
#: … and only if its coordinate lies within this many periods of half a period from the coarser
#: one (the π flip; beyond it the pixel is UNWRAP_INCONSISTENT).
REVERSAL_PHASE_TOLERANCE = 0.125


def _zeros_like_flags(obj, shape) -> None:
    """Set a frozen result's ``reversed`` to an all-False array of ``shape`` if it is None."""
    if obj.reversed is None:
        object.__setattr__(obj, "reversed", np.zeros(shape, bool))


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
    reversed : ndarray, shape (H, W), bool
        A period's contrast was reversed and its phase corrected by π (only with ``contrasts``
        given to :func:`unwrap_hierarchical`; else all False).
    """

    coord_mm: np.ndarray
    flags: np.ndarray
    reversed: np.ndarray | None = field(default=None)

    def __post_init__(self):
        _zeros_like_flags(self, self.flags.shape)

    def __iter__(self):
        return iter((self.coord_mm, self.flags))


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _coarse_coord(phi, p0, origin, upper):
    """Coordinate from the coarsest phase, in [origin, origin + p0), wrapped back by −p0 above
    ``upper`` (origin + extent + margin)."""
    r = p0 * (phi / _TWO_PI) - origin
    c = origin + (r - p0 * np.floor(r / p0))
    if c > upper:
        c -= p0
    return c


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _refine(c, phi, p, inv_p, tolerance):
    """Refine coordinate c with the phase of the finer period p (``inv_p`` = 1/p):
    returns (c_k, inconsistent)."""
    fine = p * (phi * _INV_TWO_PI)
    ck = fine + p * np.floor((c - fine) * inv_p + 0.5)
    return ck, abs(c - ck) > tolerance * p


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _refine_reversal(c, phi, p, inv_p, tolerance, contrast, prev_contrast, ratio):
    """:func:`_refine` aware of a reversed contrast (module docstring): returns (c_k,
    inconsistent, reversed). ``contrast``/``prev_contrast``: B/A of this and the coarser
    period; ``ratio`` < 0 turns the correction off."""
    ck, bad = _refine(c, phi, p, inv_p, tolerance)
    if (abs(c - ck) >= (0.5 - REVERSAL_PHASE_TOLERANCE) * p and contrast <= ratio * prev_contrast
            and ratio >= 0.0):
        ck, bad = _refine(c, phi + math.pi, p, inv_p, tolerance)
        return ck, bad, True
    return ck, bad, False


@numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _unwrap_kernel(phases, periods, origin, upper, tolerance, contrasts, ratio, coord, flags, rev):
    """Hierarchical unwrapping; ``periods`` descending. Flags are OR-ed into ``flags``;
    ``contrasts`` (P, H, W) B/A per period (ignored if ``ratio`` < 0).

    Serial: it is not on the hot path (:func:`decode_direction` unwraps inside
    :func:`_decode_kernel`), and a parallel kernel costs seconds of compilation."""
    n_p, h, w = phases.shape
    for v in range(h):
        for u in range(w):
            c = _coarse_coord(phases[0, v, u], periods[0], origin, upper)
            f = np.uint8(0)
            for k in range(1, n_p):
                if ratio >= 0.0:
                    c, bad, r = _refine_reversal(c, phases[k, v, u], periods[k], 1.0 / periods[k], tolerance,
                                                 contrasts[k, v, u], contrasts[k - 1, v, u], ratio)
                    rev[v, u] |= r
                else:
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
    contrasts=None,
) -> UnwrapResult:
    """Temporal multi-period (hierarchical) phase unwrapping into a screen coordinate in mm.

    Periods are processed in descending order p_0 > p_1 > … The coarsest phase gives the
    absolute coordinate c_0 = p_0·φ_0/2π (shifted by ``origin_mm``); a coordinate that lands
    above ``origin_mm + extent_mm + margin_mm`` is taken to be a wrap of a coordinate just
    below the lower end and moved back by −p_0. Each finer period refines::

        c_k = p_k·(φ_k/2π + round((c_{k−1} − p_k·φ_k/2π) / p_k))

    and the pixel is flagged UNWRAP_INCONSISTENT if |c_{k−1} − c_k| > ``tolerance``·p_k.
    With ``contrasts`` a period whose contrast the lens reversed is corrected by π first (module
    docstring).
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
    contrasts : array_like, shape (P, H, W), optional
        Contrast B/A of each period's fringe (as ``phases``). Given: a period half a period off
        with at most :data:`REVERSAL_CONTRAST_RATIO` of the coarser period's contrast is taken
        as reversed and corrected by π (``reversed``). Default None: no correction.

    Returns
    -------
    UnwrapResult
        ``coord_mm`` (H, W) float64 in mm, ``flags`` (H, W) uint8 (UNWRAP_INCONSISTENT,
        NONFINITE) and ``reversed`` (H, W) bool. Unpacks as ``coord_mm, flags``.

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
    if contrasts is not None:
        con = np.asarray(contrasts, dtype=np.float64)
        if con.shape != ph.shape:
            raise PhaseDecodingError(f"contrasts: expected the shape of phases {ph.shape}, got {con.shape}")
        con = np.ascontiguousarray(con[order])
    else:
        con = np.zeros((1, 1, 1))
    if not np.array_equal(order, np.arange(order.size)):
        ph = ph[order]
    ph = np.ascontiguousarray(ph, dtype=np.float64)
    _, h, w = ph.shape
    coord = np.empty((h, w), np.float64)
    flags = np.zeros((h, w), np.uint8)
    rev = np.zeros((h, w), np.bool_)
    ratio = REVERSAL_CONTRAST_RATIO if contrasts is not None else -1.0
    _unwrap_kernel(ph, periods, org, org + ext + margin, tol, con, ratio, coord, flags, rev)
    return UnwrapResult(coord_mm=coord, flags=flags, reversed=rev)
