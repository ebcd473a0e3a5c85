"""Phase decoding of phase-shifted fringe images (numeric core).

Implements the fringe model of docs/conventions.md ("Fringe patterns"): for a period ``p`` (mm)
the phase of screen coordinate ``c`` (mm) is ``φ = 2π·c/p`` wrapped to [0, 2π); shift ``k`` of
``N`` has ``δ_k = 2πk/N`` and the recorded intensity is ``I_k = A + B·cos(φ − δ_k)``
(``A`` offset, ``B`` modulation, both in grey levels).

The module provides

* :func:`wrapped_phase` — N-step phase, modulation and offset of one image stack, with
  per-pixel validity flags (:class:`PhaseFlag`);
* :func:`unwrap_hierarchical` (:mod:`pmdsim.evaluation.unwrapping`) — temporal multi-period
  unwrapping of wrapped phases into an absolute screen coordinate in mm;
* :func:`decode_direction` — both steps for one fringe direction, with a predicted standard
  deviation of the coordinate from the phase-noise model;
* :func:`decode_screen_coordinates` — both directions: the pixel → screen (x_q, y_q) mapping.

Everything is a pure function of numpy arrays: nothing is read, written or printed. Invalid
input raises :class:`PhaseDecodingError` (a ``ValueError``) naming the problem. The per-pixel
loops are numba kernels; the decoding kernel runs in parallel over image rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numba
import numpy as np

from ..geometry.compact import compact_repr
from ..geometry.kernel_args import readonly
from .phase_flags import (
    _DARK,
    _LOW_MODULATION,
    _NONFINITE,
    _SATURATED,
    _TWO_PI,
    _UNWRAP_INCONSISTENT,
    DEFAULT_DARK_FRACTION,
    DEFAULT_MIN_MODULATION_FRACTION,
    DEFAULT_MIN_MODULATION_RATIO,
    DEFAULT_UNWRAP_TOLERANCE,
    PhaseDecodingError,
)
from .fast_atan import _phase_0_2pi
from .phase_noise import _noise_map, coordinate_std_scale
from .unwrapping import (
    REVERSAL_CONTRAST_RATIO,
    _check_extent,
    _check_periods,
    _coarse_coord,
    _refine_reversal,
    _resolve_margin,
    _zeros_like_flags,
)

__all__ = [
    "PhaseResult",
    "DirectionResult",
    "ScreenCoordinates",
    "equal_shifts",
    "wrapped_phase",
    "decode_direction",
    "decode_screen_coordinates",
]


# --------------------------------------------------------------------------------------------
# Result types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PhaseResult:
    """Result of :func:`wrapped_phase` for one stack of N phase-shifted images.

    Attributes
    ----------
    phase : ndarray, shape (H, W), float64
        Wrapped phase φ in radians, in [0, 2π); NaN where a sample is not finite.
    modulation : ndarray, shape (H, W), float64
        Modulation B in grey levels.
    offset : ndarray, shape (H, W), float64
        Offset A (mean intensity) in grey levels.
    flags : ndarray, shape (H, W), uint8
        :class:`PhaseFlag` bits (DARK, SATURATED, LOW_MODULATION, NONFINITE); 0 is valid.
    """

    phase: np.ndarray
    modulation: np.ndarray
    offset: np.ndarray
    flags: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: ``flags == 0``."""
        return self.flags == 0


@dataclass(frozen=True)
class DirectionResult:
    """Result of :func:`decode_direction`: the screen coordinate along one fringe direction.

    Attributes
    ----------
    coord_mm : ndarray, shape (H, W), float64
        Screen coordinate (x_q for direction "x", y_q for "y") in mm of the screen frame;
        NaN where not :attr:`valid`.
    valid : ndarray, shape (H, W), bool
        ``flags == 0``.
    flags : ndarray, shape (H, W), uint8
        OR of the :class:`PhaseFlag` bits of all periods and of the unwrapping.
    modulation : ndarray, shape (H, W), float64
        Modulation B (grey levels) of the finest period.
    offset : ndarray, shape (H, W), float64
        Offset A (grey levels) of the finest period.
    std_mm : ndarray, shape (H, W), float64
        Predicted standard deviation of ``coord_mm`` in mm (see :func:`decode_direction`);
        NaN where not valid.
    reversed : ndarray, shape (H, W), bool
        A period's contrast was reversed (a lens transfer beyond a zero of 2·J₁(x)/x) and its
        phase corrected by π (:func:`~pmdsim.evaluation.unwrapping.unwrap_hierarchical`).
    """

    coord_mm: np.ndarray
    valid: np.ndarray
    flags: np.ndarray
    modulation: np.ndarray
    offset: np.ndarray
    std_mm: np.ndarray
    reversed: np.ndarray | None = None

    def __post_init__(self):
        _zeros_like_flags(self, self.flags.shape)


@dataclass(frozen=True)
class ScreenCoordinates:
    """Result of :func:`decode_screen_coordinates`: the pixel → screen mapping.

    Attributes
    ----------
    screen_xy_mm : ndarray, shape (H, W, 2), float64
        Pattern coordinates (x_q, y_q) in mm of the screen frame; NaN (both) where not valid.
    valid : ndarray, shape (H, W), bool
        Both directions valid, i.e. ``flags == 0``.
    flags : ndarray, shape (H, W), uint8
        OR of the :class:`PhaseFlag` bits of both directions.
    std_xy_mm : ndarray, shape (H, W, 2), float64
        Predicted standard deviations of x_q and y_q in mm; NaN where not valid.
    modulation : ndarray, shape (H, W, 2), float64
        Modulation B (grey levels) of the finest x and y period.
    offset : ndarray, shape (H, W, 2), float64
        Offset A (grey levels) of the finest x and y period.
    reversed : ndarray, shape (H, W, 2), bool
        Per direction (x, y): a period's contrast was reversed by the lens and its phase
        corrected by π (:attr:`DirectionResult.reversed`). Default (None): all False.
    """

    __repr__ = compact_repr  # one line: arrays by shape and dtype (issue 23)

    screen_xy_mm: np.ndarray
    valid: np.ndarray
    flags: np.ndarray
    std_xy_mm: np.ndarray
    modulation: np.ndarray
    offset: np.ndarray
    reversed: np.ndarray | None = None

    def __post_init__(self):
        _zeros_like_flags(self, self.flags.shape + (2,))


# --------------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _quality(sa, b, mx, check_saturation, max_value, dark_level, min_modulation, min_ratio):
    f = np.uint8(0)
    if sa < dark_level:
        f |= _DARK
    if check_saturation and mx >= max_value:
        f |= _SATURATED
    if b < min_modulation or b < min_ratio * sa:
        f |= _LOW_MODULATION
    return f


# Modes of _decode_kernel: what ``out`` receives.
_MODE_PHASE = 0  # the wrapped phase (wrapped_phase)
_MODE_COARSE = 1  # the coordinate from the coarsest period (first unwrapping level)
_MODE_REFINE = 2  # ``out`` holds the coordinate of the previous level and is refined


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _accumulate_row(images, v, w_a, w_c, w_s, sa, sc, ss, mx):
    """Row v: sa = Σ w_a I, sc = Σ w_c I, ss = Σ w_s I, mx = max I (image by image along the
    row: contiguous and vectorisable). The only part that depends on the image dtype."""
    _clear_row_sums(sa, sc, ss, mx)
    for k in range(images.shape[0]):
        _add_image_row(images[k, v], w_a[k], w_c[k], w_s[k], sa, sc, ss, mx)


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _clear_row_sums(sa, sc, ss, mx):
    """The row sums before the first image: 0, 0, 0 and −∞ (the maximum), each (W,)."""
    for u in range(sa.shape[0]):
        sa[u] = 0.0
        sc[u] = 0.0
        ss[u] = 0.0
        mx[u] = -np.inf


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _add_image_row(row, ca, cc, cs, sa, sc, ss, mx):
    """One image's row (W,) into the row sums: sa += ca·I, sc += cc·I, ss += cs·I, mx = max."""
    for u in range(sa.shape[0]):
        x = np.float64(row[u])
        sa[u] += ca * x
        sc[u] += cc * x
        ss[u] += cs * x
        mx[u] = max(mx[u], x)


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _modulation_phase_row(sc, ss):
    """Modulation B = √(c² + s²) and phase φ ∈ [0, 2π) in place of the row's B cos φ (``sc``)
    and B sin φ (``ss``), each (W,): a branch-free, vectorised loop."""
    for u in range(sc.shape[0]):
        bc = sc[u]
        bs = ss[u]
        sc[u] = math.sqrt(bc * bc + bs * bs)
        ss[u] = _phase_0_2pi(bs, bc)


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _finish_row(v, sa, sc, ss, mx, check_saturation, max_value, dark_level, min_modulation,
                min_ratio, mode, period, inv_period, origin, upper, tolerance, store, finish,
                std_scale, noise, out, flags, modulation, offset, std, contrast, rev, rev_ratio):
    """Row v of :func:`_decode_kernel` from the accumulated sums. ``contrast`` holds the
    coarser level's B/A and receives this level's; ``rev`` is set where this level's contrast
    was reversed and corrected (``rev_ratio``: :data:`REVERSAL_CONTRAST_RATIO`, < 0: off)."""
    sv = 1 if noise.shape[0] > 1 else 0  # broadcasting strides of the noise map
    su = 1 if noise.shape[1] > 1 else 0
    w = sa.shape[0]
    _modulation_phase_row(sc, ss)
    for u in range(w):
        a = sa[u]
        b = sc[u]
        phi = ss[u]
        if np.isfinite(a) and np.isfinite(b):  # b is not finite if B cos φ or B sin φ is not
            f = _quality(a, b, mx[u], check_saturation, max_value, dark_level,
                         min_modulation, min_ratio)
        else:
            a = np.nan
            b = np.nan
            phi = np.nan
            f = _NONFINITE
        if mode == _MODE_PHASE:
            val = phi
        elif mode == _MODE_COARSE:
            val = _coarse_coord(phi, period, origin, upper)
        else:
            val, bad, r = _refine_reversal(out[v, u], phi, period, inv_period, tolerance, b / a,
                                           contrast[v, u], rev_ratio)
            if bad:
                f |= _UNWRAP_INCONSISTENT
            if r:
                rev[v, u] = True
        if mode != _MODE_PHASE:
            contrast[v, u] = b / a
        f |= flags[v, u]
        flags[v, u] = f
        if store:
            modulation[v, u] = b
            offset[v, u] = a
        if finish:
            if f == 0:
                out[v, u] = val
                std[v, u] = std_scale * noise[v * sv, u * su] / b
            else:
                out[v, u] = np.nan
                std[v, u] = np.nan
        else:
            out[v, u] = val


@numba.njit(parallel=True, cache=True, nogil=True, fastmath=False, error_model="numpy")
def _decode_kernel(images, w_a, w_c, w_s, check_saturation, max_value, dark_level,
                   min_modulation, min_ratio, mode, period, origin, upper, tolerance,
                   store, finish, std_scale, noise, out, flags, modulation, offset, std,
                   contrast, rev, rev_ratio):
    """Decode one image stack; one parallel pass over image rows.

    Per pixel A = Σ w_a I, B cos φ = Σ w_c I, B sin φ = Σ w_s I, max sample; quality flags are
    OR-ed into ``flags``. ``mode`` selects what goes into ``out`` (phase, coarse coordinate or
    refined coordinate, see _MODE_*). ``store``: write ``modulation`` and ``offset``.
    ``finish`` (last level): set ``out`` to NaN where ``flags`` != 0 and write
    ``std = std_scale · σ_I / B`` (NaN where invalid); ``noise`` is (1|H, 1|W). ``contrast``,
    ``rev``, ``rev_ratio``: the contrast reversal (:func:`_finish_row`).
    """
    h = images.shape[1]
    w = images.shape[2]
    inv_period = 1.0 / period
    for v in numba.prange(0, h):
        sa = np.empty(w)
        sc = np.empty(w)
        ss = np.empty(w)
        mx = np.empty(w)
        _accumulate_row(images, v, w_a, w_c, w_s, sa, sc, ss, mx)
        _finish_row(v, sa, sc, ss, mx, check_saturation, max_value, dark_level, min_modulation,
                    min_ratio, mode, period, inv_period, origin, upper, tolerance, store, finish,
                    std_scale, noise, out, flags, modulation, offset, std, contrast, rev, rev_ratio)


@numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _combine_kernel(x_coord, y_coord, x_flags, y_flags, x_std, y_std, x_mod, y_mod, x_off,
                    y_off, xy, flags, std, modulation, offset):
    """Interleave both directions into (H, W, 2) maps; NaN both coordinates/stds where either
    direction is flagged."""
    h, w = flags.shape
    for v in range(h):
        for u in range(w):
            f = x_flags[v, u] | y_flags[v, u]
            flags[v, u] = f
            modulation[v, u, 0] = x_mod[v, u]
            modulation[v, u, 1] = y_mod[v, u]
            offset[v, u, 0] = x_off[v, u]
            offset[v, u, 1] = y_off[v, u]
            if f == 0:
                xy[v, u, 0] = x_coord[v, u]
                xy[v, u, 1] = y_coord[v, u]
                std[v, u, 0] = x_std[v, u]
                std[v, u, 1] = y_std[v, u]
            else:
                xy[v, u, 0] = np.nan
                xy[v, u, 1] = np.nan
                std[v, u, 0] = np.nan
                std[v, u, 1] = np.nan


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------

_KERNEL_DTYPES = frozenset(np.dtype(t) for t in (
    np.uint8, np.uint16, np.uint32, np.uint64, np.int8, np.int16, np.int32, np.int64,
    np.float32, np.float64,
))


def _as_image_stack(images, name: str) -> np.ndarray:
    """(N, H, W) array with a dtype the kernel handles, C-contiguous, native byte order."""
    try:
        arr = np.asarray(images)
    except (ValueError, TypeError) as exc:
        raise PhaseDecodingError(
            f"{name}: cannot be converted to an (N, H, W) array; do all images have the same "
            f"size? ({exc})"
        ) from exc
    if arr.ndim != 3:
        raise PhaseDecodingError(
            f"{name}: expected an image stack of shape (N, H, W), got shape {arr.shape}"
        )
    n, h, w = arr.shape
    if n < 3:
        raise PhaseDecodingError(
            f"{name}: N-step phase shifting needs N >= 3 phase-shifted images, got N = {n}"
        )
    if h == 0 or w == 0:
        raise PhaseDecodingError(f"{name}: images are empty (shape {arr.shape})")
    if arr.dtype.kind == "b":
        arr = arr.astype(np.uint8)
    elif arr.dtype.kind not in "uif":
        raise PhaseDecodingError(
            f"{name}: expected integer or floating-point grey levels, got dtype {arr.dtype}"
        )
    if arr.dtype.newbyteorder("=") not in _KERNEL_DTYPES:
        arr = arr.astype(np.float64)  # float16, longdouble: rare, convert
    elif not arr.dtype.isnative:
        arr = arr.astype(arr.dtype.newbyteorder("="))
    return np.ascontiguousarray(arr)


def _resolve_max_value(max_value, dtype: np.dtype, name: str) -> float:
    if max_value is None:
        if dtype.kind in "ui":
            return float(np.iinfo(dtype).max)
        raise PhaseDecodingError(
            f"{name}: max_value must be given for floating-point images "
            "(the full-scale grey level of the bit depth, e.g. 255 or 65535)"
        )
    mv = float(max_value)
    if not (math.isfinite(mv) and mv > 0):
        raise PhaseDecodingError(f"max_value must be a positive finite grey level, got {max_value!r}")
    return mv


def _check_fraction(value, name: str, upper: float | None = None) -> float:
    val = float(value)
    if not math.isfinite(val) or val < 0 or (upper is not None and val > upper):
        rng = f"[0, {upper}]" if upper is not None else "[0, inf)"
        raise PhaseDecodingError(f"{name} must be a finite number in {rng}, got {value!r}")
    return val


def equal_shifts(n: int) -> np.ndarray:
    """Phase shifts δ_k = 2πk/N in radians (docs/conventions.md), shape (N,)."""
    return _TWO_PI * np.arange(n, dtype=np.float64) / n


def _shift_weights(n: int, shifts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights (w_a, w_c, w_s), each (N,), with A = Σ w_a I, B cos φ = Σ w_c I, B sin φ = Σ w_s I."""
    if shifts is None:
        d = equal_shifts(n)
        return np.full(n, 1.0 / n), (2.0 / n) * np.cos(d), (2.0 / n) * np.sin(d)
    d = np.asarray(shifts, dtype=np.float64)
    if d.shape != (n,):
        raise PhaseDecodingError(
            f"shifts: expected one phase shift per image, shape ({n},), got shape {d.shape}"
        )
    if not np.all(np.isfinite(d)):
        raise PhaseDecodingError("shifts: all phase shifts must be finite (radians)")
    # I_k = A + (B cos φ) cos δ_k + (B sin φ) sin δ_k: least squares via the pseudo-inverse.
    design = np.stack([np.ones(n), np.cos(d), np.sin(d)], axis=1)
    sv = np.linalg.svd(design, compute_uv=False)
    if sv[-1] < 1e-6 * sv[0]:
        raise PhaseDecodingError(
            "shifts: the phase shifts do not determine offset, modulation and phase "
            "(they need at least 3 distinct values modulo 2π)"
        )
    w = np.linalg.pinv(design)
    return (np.ascontiguousarray(w[0]), np.ascontiguousarray(w[1]), np.ascontiguousarray(w[2]))


_NO_NOISE = np.zeros((1, 1))
_DUMMY_2D = np.empty((1, 1))
_DUMMY_BOOL = np.zeros((1, 1), np.bool_)


def _phase_into(stack, shifts, max_value, dark_fraction, min_modulation_fraction,
                min_modulation_ratio, check_saturation, phase, modulation, offset, flags):
    w_a, w_c, w_s = _shift_weights(stack.shape[0], shifts)
    _decode_kernel(
        readonly(stack), w_a, w_c, w_s, bool(check_saturation), float(max_value),
        dark_fraction * max_value, min_modulation_fraction * max_value, min_modulation_ratio,
        _MODE_PHASE, 1.0, 0.0, 0.0, 0.25, True, False, 1.0, _NO_NOISE,
        phase, flags, modulation, offset, _DUMMY_2D, _DUMMY_2D, _DUMMY_BOOL, -1.0,
    )


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------


def wrapped_phase(
    images,
    shifts=None,
    *,
    max_value: float | None = None,
    dark_fraction: float = DEFAULT_DARK_FRACTION,
    min_modulation_fraction: float = DEFAULT_MIN_MODULATION_FRACTION,
    min_modulation_ratio: float = DEFAULT_MIN_MODULATION_RATIO,
    check_saturation: bool = True,
) -> PhaseResult:
    """Wrapped phase, modulation and offset of N phase-shifted fringe images.

    With the default equally spaced shifts δ_k = 2πk/N this is the N-step formula of
    docs/conventions.md ("Fringe patterns")::

        S = Σ I_k sin δ_k,  C = Σ I_k cos δ_k,
        φ = atan2(S, C) mod 2π,  B = (2/N)·√(S² + C²),  A = (1/N)·Σ I_k.

    Parameters
    ----------
    images : array_like, shape (N, H, W)
        N ≥ 3 images I_k in grey levels, any integer or floating-point dtype (not converted to
        float64 as a whole). Image k was displayed with shift δ_k.
    shifts : array_like, shape (N,), optional
        Phase shifts δ_k in radians. Default (``None``) 2πk/N. Other shifts are decoded by
        least squares on I_k = A + B·cos(φ − δ_k); they must contain ≥ 3 distinct values
        modulo 2π.
    max_value : float, optional
        Full-scale grey level of the bit depth (255 for 8 bit, 65535 for 16 bit). Default: the
        maximum of the integer dtype; required for floating-point images.
    dark_fraction : float
        DARK where A < ``dark_fraction · max_value``. Default 0.02 (5.1 grey levels at 8 bit).
    min_modulation_fraction : float
        LOW_MODULATION where B < ``min_modulation_fraction · max_value``. Default 0.01
        (2.55 grey levels at 8 bit).
    min_modulation_ratio : float
        LOW_MODULATION where B/A < ``min_modulation_ratio``. Default 0.05.
    check_saturation : bool
        Flag SATURATED where any sample is ≥ ``max_value``. Default True.

    Returns
    -------
    PhaseResult
        ``phase`` (H, W) in [0, 2π) rad, ``modulation`` B and ``offset`` A (H, W) in grey
        levels, ``flags`` (H, W) uint8 :class:`PhaseFlag` bits.

    Raises
    ------
    PhaseDecodingError
        If ``images`` is not (N, H, W) with N ≥ 3, ``shifts`` does not match N, ``max_value``
        is missing for float images, or a threshold is out of range.
    """
    stack = _as_image_stack(images, "images")
    mv = _resolve_max_value(max_value, stack.dtype, "images")
    dark = _check_fraction(dark_fraction, "dark_fraction")
    min_mod = _check_fraction(min_modulation_fraction, "min_modulation_fraction")
    ratio = _check_fraction(min_modulation_ratio, "min_modulation_ratio")
    _, h, w = stack.shape
    phase = np.empty((h, w), np.float64)
    modulation = np.empty((h, w), np.float64)
    offset = np.empty((h, w), np.float64)
    flags = np.zeros((h, w), np.uint8)
    _phase_into(stack, shifts, mv, dark, min_mod, ratio, check_saturation,
                phase, modulation, offset, flags)
    return PhaseResult(phase=phase, modulation=modulation, offset=offset, flags=flags)


def decode_direction(
    images_by_period: Sequence,
    periods_mm,
    extent_mm: float,
    max_value: float,
    noise_std=None,
    *,
    origin_mm: float = 0.0,
    dark_fraction: float = DEFAULT_DARK_FRACTION,
    min_modulation_fraction: float = DEFAULT_MIN_MODULATION_FRACTION,
    min_modulation_ratio: float = DEFAULT_MIN_MODULATION_RATIO,
    tolerance: float = DEFAULT_UNWRAP_TOLERANCE,
    margin_mm: float | None = None,
    check_saturation: bool = True,
    correct_reversal: bool = True,
) -> DirectionResult:
    """Decode the screen coordinate along one fringe direction from multi-period image stacks.

    Each stack is decoded with the N-step formula (:func:`wrapped_phase`, equally spaced
    shifts δ_k = 2πk/N), the phases are unwrapped hierarchically
    (:func:`unwrap_hierarchical`), and the standard deviation of the coordinate is predicted
    from the phase-noise model of the finest period p_f with N_f shifts and modulation B::

        σ_φ = √(2/N_f)·σ_I/B,    σ_c = p_f·σ_φ/(2π).

    Conventions (units, fringe model) are those of docs/conventions.md.

    Parameters
    ----------
    images_by_period : sequence of array_like, each shape (N_i, H, W)
        One stack of N_i ≥ 3 phase-shifted images per period (N_i may differ), grey levels,
        any integer or float dtype; all with the same H, W.
    periods_mm : array_like, shape (P,)
        Fringe period of each stack in mm, distinct, in any order.
    extent_mm : float
        Screen length along this direction in mm (≤ the coarsest period).
    max_value : float
        Full-scale grey level (255 for 8 bit, 65535 for 16 bit); the saturation level and the
        reference of the fractional thresholds.
    noise_std : float or array_like broadcastable to (H, W), optional
        Intensity noise σ_I in grey levels for the σ prediction. Default: quantisation noise
        1/√12 ≈ 0.289.
    origin_mm : float
        Lowest screen coordinate in mm (default 0): coordinates lie in
        [origin_mm, origin_mm + extent_mm].
    dark_fraction, min_modulation_fraction, min_modulation_ratio, check_saturation
        Validity thresholds of :func:`wrapped_phase`, applied to every period.
    tolerance, margin_mm
        Unwrapping parameters of :func:`unwrap_hierarchical`.
    correct_reversal : bool
        Correct a period whose contrast the lens reversed by π and mark it in ``reversed``
        (:func:`unwrap_hierarchical`, ``contrasts``); False: such pixels are
        UNWRAP_INCONSISTENT. Default True.

    Returns
    -------
    DirectionResult
        ``coord_mm`` (H, W) mm (NaN where invalid), ``valid`` (H, W) bool, ``flags`` (H, W)
        uint8 (OR over all periods and the unwrapping), ``modulation`` and ``offset`` (H, W)
        grey levels of the finest period, ``std_mm`` (H, W) mm (NaN where invalid),
        ``reversed`` (H, W) bool.

    Raises
    ------
    PhaseDecodingError
        For mismatched shapes or counts, N < 3, invalid periods, a coarsest period shorter than
        the extent, or out-of-range parameters.
    """
    prep = _prepare_direction(
        images_by_period, periods_mm, extent_mm, max_value, noise_std, origin_mm,
        dark_fraction, min_modulation_fraction, min_modulation_ratio, tolerance, margin_mm,
        correct_reversal,
    )
    h, w = prep.shape
    coord = np.empty((h, w), np.float64)
    flags = np.zeros((h, w), np.uint8)
    modulation = np.empty((h, w), np.float64)
    offset = np.empty((h, w), np.float64)
    std = np.empty((h, w), np.float64)
    rev = np.zeros((h, w), np.bool_)
    _decode_direction_into(prep, check_saturation, coord, flags, modulation, offset, std, rev)
    return DirectionResult(coord_mm=coord, valid=flags == 0, flags=flags,
                           modulation=modulation, offset=offset, std_mm=std, reversed=rev)


@dataclass(frozen=True)
class _DirectionInput:
    """Validated arguments of :func:`decode_direction` (periods sorted descending)."""

    stacks: list
    periods: np.ndarray
    origin: float
    upper: float
    max_value: float
    dark_level: float
    min_modulation: float
    min_ratio: float
    tolerance: float
    noise: np.ndarray  # (1|H, 1|W) float64, C-contiguous
    rev_ratio: float  # REVERSAL_CONTRAST_RATIO, or −1 (reversal correction off)

    @property
    def shape(self) -> tuple[int, int]:
        return self.stacks[0].shape[1:]


def _prepare_direction(images_by_period, periods_mm, extent_mm, max_value, noise_std, origin_mm,
                       dark_fraction, min_modulation_fraction, min_modulation_ratio, tolerance,
                       margin_mm, correct_reversal=True, convert=_as_image_stack) -> _DirectionInput:
    if isinstance(images_by_period, np.ndarray) and images_by_period.ndim == 3:
        raise PhaseDecodingError(
            "images_by_period: expected a sequence of (N, H, W) stacks, one per period, "
            f"got a single array of shape {images_by_period.shape}"
        )
    stacks = [convert(s, f"images_by_period[{i}]") for i, s in enumerate(images_by_period)]
    if not stacks:
        raise PhaseDecodingError("images_by_period: no image stacks given")
    periods = _check_periods(periods_mm, len(stacks))
    hw = stacks[0].shape[1:]
    for i, s in enumerate(stacks):
        if s.shape[1:] != hw:
            raise PhaseDecodingError(
                f"images_by_period[{i}]: image size (H, W) = {s.shape[1:]} differs from "
                f"images_by_period[0]'s {hw}"
            )
    order = np.argsort(-periods, kind="stable")
    periods = np.ascontiguousarray(periods[order])
    stacks = [stacks[i] for i in order]
    ext, org = _check_extent(extent_mm, origin_mm, periods[0], "extent_mm")
    if max_value is None:
        raise PhaseDecodingError("max_value must be given (e.g. 255 for 8-bit, 65535 for 16-bit images)")
    mv = _resolve_max_value(max_value, stacks[0].dtype, "images_by_period")
    dark = _check_fraction(dark_fraction, "dark_fraction")
    min_mod = _check_fraction(min_modulation_fraction, "min_modulation_fraction")
    ratio = _check_fraction(min_modulation_ratio, "min_modulation_ratio")
    tol = float(tolerance)
    if not (0 < tol <= 0.5):
        raise PhaseDecodingError(f"tolerance must be in (0, 0.5] (fraction of the finer period), got {tolerance!r}")
    margin = _resolve_margin(margin_mm, periods[0], ext)
    return _DirectionInput(
        stacks=stacks, periods=periods, origin=org, upper=org + ext + margin, max_value=mv,
        dark_level=dark * mv, min_modulation=min_mod * mv, min_ratio=ratio, tolerance=tol,
        noise=_noise_map(noise_std, hw), rev_ratio=REVERSAL_CONTRAST_RATIO if correct_reversal else -1.0,
    )


def _decode_direction_into(d: _DirectionInput, check_saturation, coord, flags, modulation, offset, std, rev):
    """Decode coarse → fine, one fused kernel pass per period. ``flags`` and ``rev`` must be 0
    on entry."""
    n_p = len(d.stacks)
    contrast = np.empty(coord.shape)
    n_f = d.stacks[-1].shape[0]
    std_scale = coordinate_std_scale(d.periods[-1], n_f)
    for level, stack in enumerate(d.stacks):
        w_a, w_c, w_s = _shift_weights(stack.shape[0], None)
        last = level == n_p - 1
        _decode_kernel(
            readonly(stack), w_a, w_c, w_s, bool(check_saturation), d.max_value, d.dark_level,
            d.min_modulation, d.min_ratio, _MODE_COARSE if level == 0 else _MODE_REFINE,
            float(d.periods[level]), d.origin, d.upper, d.tolerance, last, last, std_scale,
            d.noise, coord, flags, modulation, offset, std, contrast, rev, d.rev_ratio,
        )


def decode_screen_coordinates(
    x_stacks: Sequence,
    x_periods_mm,
    y_stacks: Sequence,
    y_periods_mm,
    screen_size_mm,
    max_value: float,
    noise_std=None,
    *,
    screen_origin_mm=(0.0, 0.0),
    dark_fraction: float = DEFAULT_DARK_FRACTION,
    min_modulation_fraction: float = DEFAULT_MIN_MODULATION_FRACTION,
    min_modulation_ratio: float = DEFAULT_MIN_MODULATION_RATIO,
    tolerance: float = DEFAULT_UNWRAP_TOLERANCE,
    margin_mm: float | None = None,
    check_saturation: bool = True,
    correct_reversal: bool = True,
) -> ScreenCoordinates:
    """Decode the pixel → screen mapping (x_q, y_q) from x- and y-fringe image stacks.

    The values of :func:`decode_direction` for direction "x" (fringes encoding the screen's x_q)
    and "y" (y_q), combined (docs/conventions.md, "Fringe patterns"); both directions are decoded
    in one parallel pass over image rows (:mod:`pmdsim.evaluation.decoding_fused`).

    Parameters
    ----------
    x_stacks, y_stacks : sequence of array_like, each shape (N_i, H, W)
        Image stacks per period for the x and y direction (grey levels); all with equal H, W.
        A stack may be a list of N_i (H, W) images. The kernel reads all stacks as one (N, H, W)
        array: a view where they are consecutive slices of one array (the stacks of
        :func:`pmdsim.io.imageset.load_camera_stacks`), else one copy of them.
    x_periods_mm, y_periods_mm : array_like, shape (P_x,), (P_y,)
        Fringe periods in mm of the stacks.
    screen_size_mm : (float, float)
        Screen extent (width along x_q, height along y_q) in mm.
    max_value : float
        Full-scale grey level (255 for 8 bit, 65535 for 16 bit).
    noise_std : float or array_like broadcastable to (H, W), optional
        Intensity noise σ_I in grey levels; default quantisation noise 1/√12.
    screen_origin_mm : (float, float)
        Lowest (x_q, y_q) on the screen in mm; default (0, 0), i.e. the screen covers
        [0, width] × [0, height].
    dark_fraction, min_modulation_fraction, min_modulation_ratio, tolerance, margin_mm
    check_saturation, correct_reversal
        As in :func:`decode_direction`, applied to both directions (``margin_mm`` None means
        half the unused part of each direction's coarsest period).

    Returns
    -------
    ScreenCoordinates
        ``screen_xy_mm`` (H, W, 2) mm, NaN where invalid; ``valid`` (H, W) bool; ``flags``
        (H, W) uint8, OR of both directions; ``std_xy_mm`` (H, W, 2) mm; ``modulation`` and
        ``offset`` (H, W, 2) grey levels of the finest x and y period; ``reversed`` (H, W, 2).

    Raises
    ------
    PhaseDecodingError
        As :func:`decode_direction` (the message names the direction), or if
        ``screen_size_mm``/``screen_origin_mm`` are not pairs, or the x and y images differ in
        size.
    """
    size = np.asarray(screen_size_mm, dtype=np.float64)
    origin = np.asarray(screen_origin_mm, dtype=np.float64)
    if size.shape != (2,):
        raise PhaseDecodingError(f"screen_size_mm: expected (width, height) in mm, got shape {size.shape}")
    if origin.shape != (2,):
        raise PhaseDecodingError(f"screen_origin_mm: expected (x, y) in mm, got shape {origin.shape}")
    from .decoding_fused import as_image_list, decode_both_directions  # imports this module

    preps = []
    for i, (axis, stacks, periods) in enumerate((("x", x_stacks, x_periods_mm), ("y", y_stacks, y_periods_mm))):
        try:
            preps.append(_prepare_direction(
                stacks, periods, size[i], max_value, noise_std, origin[i], dark_fraction,
                min_modulation_fraction, min_modulation_ratio, tolerance, margin_mm, correct_reversal,
                as_image_list,
            ))
        except PhaseDecodingError as exc:
            raise PhaseDecodingError(f"direction {axis!r}: {exc}") from exc
    if preps[0].shape != preps[1].shape:
        raise PhaseDecodingError(
            f"x and y image stacks differ in image size (H, W): {preps[0].shape} vs {preps[1].shape}"
        )
    return decode_both_directions(preps, check_saturation)
