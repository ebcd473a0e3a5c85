"""Decoding of simulated fringe images without materialising them (issue 15, per-case cost).

A simulated camera frame of the ideal renderer (:func:`pmdsim.simulation.patterns.render_period`:
``I_k = round(F·(A + B·cos(φ − δ_k)) + noise)`` clipped to [0, F], F = 2^bits − 1, docs/conventions.md
"Fringe patterns") followed by the N-step decoder (:func:`pmdsim.evaluation.phase.decode_screen_coordinates`)
costs, at full resolution, 24 uint8 images written, stacked (copied) and read back per frame. Here
one numba pass per period computes each pixel's N quantised grey levels in registers and feeds
them straight into the decoder's per-row arithmetic (the same ``_finish_row`` of
:mod:`.phase`, the same order of floating-point operations), so the result is **bit for bit** the
result of rendering, quantising and decoding (tests/test_synthetic_decode.py checks every output
array against that two-step path, with and without noise).

The noise (if any) is drawn from the caller's generator exactly as
:func:`~pmdsim.simulation.patterns.render_period` draws it: N fields of shape (H, W) per period,
periods in display order (:meth:`~pmdsim.setup.fringes.FringeSequence.frames`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..geometry.fast_trig import MAX_FAST_PHASE as _MAX_FAST_PHASE
from ..geometry.fast_trig import TIE_GUARD as _TIE_GUARD
from ..geometry.fast_trig import libm_grey_level
from ..geometry.fast_trig import sincos as _sincos_fast
from ..setup.fringes import DIRECTIONS, FringeSequence
from .decoding import _MODE_COARSE, _MODE_REFINE, ScreenCoordinates, _combine_kernel, _finish_row, _shift_weights
from .phase_flags import (
    _TWO_PI,
    DEFAULT_DARK_FRACTION,
    DEFAULT_MIN_MODULATION_FRACTION,
    DEFAULT_MIN_MODULATION_RATIO,
    DEFAULT_UNWRAP_TOLERANCE,
    PhaseDecodingError,
)
from .unwrapping import REVERSAL_CONTRAST_RATIO, _check_extent, _resolve_margin

__all__ = ["decode_rendered_fringes"]


@numba.njit(cache=True, fastmath=False, error_model="numpy")
def _render_accumulate_row(v, screen_xy, valid, axis, two_pi_over_p, cos_d, sin_d, mean, amp, full_scale,
                           noise, w_a, w_c, w_s, tie_guard, sa, sc, ss, mx, cb, sb, redo):
    """Row v: the N quantised grey levels of every pixel (the model and arithmetic of
    ``patterns._render_stack_rows``; 0 where not ``valid``), accumulated as in
    ``decoding._accumulate_row``: sa = Σ w_a I, sc = Σ w_c I, ss = Σ w_s I, mx = max I.

    Vectorised passes over the row (fast sin/cos, then image by image); pixels whose value lies
    within ``tie_guard`` of a rounding boundary, or whose phase is not in the fast range, are
    recomputed with libm's sin and cos. Returns the number of recomputed pixels."""
    w = valid.shape[1]
    n = cos_d.shape[0]
    has_noise = noise.shape[0] > 0
    for u in range(w):  # the strided load in a loop of its own: the next one vectorises
        cb[u] = two_pi_over_p * screen_xy[v, u, axis]
    for u in range(w):
        phi = cb[u]
        fast = abs(phi) <= _MAX_FAST_PHASE  # False for NaN
        s, c = _sincos_fast(phi if fast else 0.0)
        sb[u] = s
        cb[u] = c
        redo[u] = valid[v, u] & (not fast)
        sa[u] = 0.0
        sc[u] = 0.0
        ss[u] = 0.0
        mx[u] = -np.inf
    for k in range(n):
        ca = w_a[k]
        cc = w_c[k]
        cs = w_s[k]
        cdk = cos_d[k]
        sdk = sin_d[k]
        for u in range(w):
            val = full_scale * (mean + amp * (cb[u] * cdk + sb[u] * sdk))
            if has_noise:
                val += noise[k, v, u]
            t = val + 0.5
            q = np.floor(t)
            frac = t - q
            redo[u] = redo[u] | (frac < tie_guard) | (frac > 1.0 - tie_guard)
            q = min(max(q, 0.0), full_scale)
            q = q if valid[v, u] else 0.0
            sa[u] += ca * q
            sc[u] += cc * q
            ss[u] += cs * q
            mx[u] = max(mx[u], q)
    n_redo = 0
    for u in range(w):
        if not redo[u]:
            continue
        n_redo += 1
        a = 0.0
        c_acc = 0.0
        s_acc = 0.0
        m = -np.inf
        if valid[v, u]:
            phi = two_pi_over_p * screen_xy[v, u, axis]
            c = np.cos(phi)
            s = np.sin(phi)
            for k in range(n):
                q = libm_grey_level(c, s, cos_d[k], sin_d[k], mean, amp, full_scale, has_noise,
                                    noise[k, v, u] if has_noise else 0.0)
                a += w_a[k] * q
                c_acc += w_c[k] * q
                s_acc += w_s[k] * q
                m = max(m, q)
        else:  # black pixel: N samples of 0 (the sums of zeros are +0.0, as in decoding._accumulate_row)
            m = 0.0
        sa[u] = a
        sc[u] = c_acc
        ss[u] = s_acc
        mx[u] = m
    return n_redo


@numba.njit(cache=True, fastmath=False, error_model="numpy")
def _render_decode_row(v, screen_xy, valid, axis, cos_d, sin_d, mean, amp, full_scale, render_noise,
                       w_a, w_c, w_s, check_saturation, max_value, dark_level, min_modulation, min_ratio,
                       mode, period, origin, upper, tolerance, store, finish, std_scale, noise_sigma,
                       tie_guard, out, flags, modulation, offset, std, contrast, rev, rev_ratio):
    """Row v of one period: render (in registers) and decode; the arguments after
    ``render_noise`` are those of ``decoding._decode_kernel``. Returns the number of pixels
    recomputed with libm's sin and cos (see ``_render_accumulate_row``)."""
    w = valid.shape[1]
    sa = np.empty(w)
    sc = np.empty(w)
    ss = np.empty(w)
    mx = np.empty(w)
    cb = np.empty(w)
    sb = np.empty(w)
    redo = np.empty(w, np.bool_)
    n_redo = _render_accumulate_row(v, screen_xy, valid, axis, 2.0 * np.pi / period, cos_d, sin_d, mean, amp,
                                    full_scale, render_noise, w_a, w_c, w_s, tie_guard, sa, sc, ss, mx, cb, sb, redo)
    _finish_row(v, sa, sc, ss, mx, check_saturation, max_value, dark_level, min_modulation,
                min_ratio, mode, period, 1.0 / period, origin, upper, tolerance, store, finish,
                std_scale, noise_sigma, out, flags, modulation, offset, std, contrast, rev, rev_ratio)
    return n_redo


@numba.njit(parallel=True, cache=True, fastmath=False, error_model="numpy")
def _render_decode_kernel(screen_xy, valid, axis, cos_d, sin_d, mean, amp, full_scale, render_noise,
                          w_a, w_c, w_s, check_saturation, max_value, dark_level, min_modulation, min_ratio,
                          mode, period, origin, upper, tolerance, store, finish, std_scale, noise_sigma,
                          tie_guard, out, flags, modulation, offset, std, contrast, rev, rev_ratio):
    """One period, one parallel pass over image rows (:func:`_render_decode_row`)."""
    h = valid.shape[0]
    n_redo = np.zeros(h, np.int64)
    for v in numba.prange(0, h):
        # the row as int64 (this prange's index reached it as uint64, although it starts at 0): the serial
        # kernel's signature of the row functions and of decoding._finish_row, not a second compile of each
        n_redo[v] = _render_decode_row(np.int64(v), screen_xy, valid, axis, cos_d, sin_d, mean, amp, full_scale,
                                       render_noise, w_a, w_c, w_s, check_saturation, max_value, dark_level,
                                       min_modulation, min_ratio, mode, period, origin, upper, tolerance, store,
                                       finish, std_scale, noise_sigma, tie_guard, out, flags, modulation, offset,
                                       std, contrast, rev, rev_ratio)
    return n_redo.sum()


@numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _render_decode_kernel_serial(screen_xy, valid, axis, cos_d, sin_d, mean, amp, full_scale, render_noise,
                                 w_a, w_c, w_s, check_saturation, max_value, dark_level, min_modulation,
                                 min_ratio, mode, period, origin, upper, tolerance, store, finish, std_scale,
                                 noise_sigma, tie_guard, out, flags, modulation, offset, std, contrast, rev, rev_ratio):
    """:func:`_render_decode_kernel` in the calling thread: for small images (e.g. the
    calibration's strided pixels) a parallel region's wake-up of the other threads can cost
    more than the work on a loaded machine."""
    n_redo = 0
    for v in range(valid.shape[0]):
        n_redo += _render_decode_row(v, screen_xy, valid, axis, cos_d, sin_d, mean, amp, full_scale,
                                     render_noise, w_a, w_c, w_s, check_saturation, max_value, dark_level,
                                     min_modulation, min_ratio, mode, period, origin, upper, tolerance, store,
                                     finish, std_scale, noise_sigma, tie_guard, out, flags, modulation, offset, std,
                                     contrast, rev, rev_ratio)
    return n_redo


_SERIAL_BELOW_PX = 200_000
_CHUNK_ROWS = 8


def decode_rendered_fringes(
    screen_xy_mm: np.ndarray,
    valid: np.ndarray,
    sequence: FringeSequence,
    screen_size_mm,
    *,
    bit_depth: int = 8,
    noise_std: float = 0.0,
    rng: np.random.Generator | None = None,
    decoder_noise_std: float | None = None,
    tie_guard: float = _TIE_GUARD,
    pixel_stride: int = 1,
) -> ScreenCoordinates:
    """Decode the images the ideal renderer would produce from a pixel → screen mapping.

    Equals, bit for bit, rendering every frame of ``sequence`` with
    :func:`pmdsim.simulation.patterns.render_period` (periods in display order, noise from
    ``rng``) and decoding them with :func:`pmdsim.evaluation.phase.decode_screen_coordinates`
    (default thresholds, ``max_value`` = 2^bits − 1, screen origin (0, 0)), without the images.

    Parameters
    ----------
    screen_xy_mm : ndarray (H, W, 2)
        Pattern coordinates per pixel (screen frame, mm).
    valid : ndarray of bool (H, W)
        Pixels that see the screen; the others are black.
    sequence : FringeSequence
    screen_size_mm : (float, float)
        Screen extent (width, height) in mm.
    bit_depth : {8, 16}
    noise_std : float
        Additive Gaussian intensity noise of the renderer, grey levels (0: none).
    rng : numpy.random.Generator
        Required when ``noise_std`` > 0; consumed as :func:`render_period` would.
    decoder_noise_std : float, optional
        σ_I of the decoder's σ prediction (grey levels); default quantisation noise 1/√12.
    tie_guard : float
        Grey levels: a pixel whose unrounded value lies closer than this to a rounding boundary
        is rendered with libm's sin and cos (see the module notes); 0.5 sends every pixel there.
    pixel_stride : int
        Decode only the pixels (v, u) ≡ (0, 0) mod ``pixel_stride`` (the decoder works per
        pixel, so their values are those of the full decode, noise included: the full noise
        fields are drawn and subsampled); the result has the shape of ``valid[::s, ::s]``.

    Returns
    -------
    ScreenCoordinates
        As :func:`~pmdsim.evaluation.phase.decode_screen_coordinates`.
    """
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth!r}")
    xy = np.asarray(screen_xy_mm, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool)
    if xy.ndim != 3 or xy.shape[-1] != 2 or ok.shape != xy.shape[:2]:
        raise ValueError(f"screen_xy_mm must be (H, W, 2) and valid (H, W), got {xy.shape} and {ok.shape}")
    stride = int(pixel_stride)
    if stride != pixel_stride or stride < 1:
        raise ValueError(f"pixel_stride must be a positive integer, got {pixel_stride!r}")
    full_shape = ok.shape
    xy = np.ascontiguousarray(xy[::stride, ::stride])
    ok = np.ascontiguousarray(ok[::stride, ::stride])
    if not 0.0 <= tie_guard <= 0.5:
        raise ValueError(f"tie_guard must be in [0, 0.5] grey levels, got {tie_guard!r}")
    if noise_std > 0 and rng is None:
        raise ValueError("noise_std > 0 needs a seeded rng for reproducible images")
    size = np.asarray(screen_size_mm, dtype=np.float64)
    if size.shape != (2,):
        raise PhaseDecodingError(f"screen_size_mm: expected (width, height) in mm, got shape {size.shape}")
    h, w = ok.shape
    n = sequence.n_shifts
    full = float(2**bit_depth - 1)
    delta = 2.0 * np.pi * np.arange(n) / n
    cos_d, sin_d = np.cos(delta), np.sin(delta)
    w_a, w_c, w_s = _shift_weights(n, None)
    sigma = np.full((1, 1), 1.0 / math.sqrt(12.0) if decoder_noise_std is None else float(decoder_noise_std))
    if not (np.isfinite(sigma).all() and sigma[0, 0] >= 0):
        raise PhaseDecodingError("decoder_noise_std: intensity noise must be finite and >= 0 (grey levels)")
    noise_source = _NoiseFields(sequence, noise_std, rng, full_shape, stride) if noise_std > 0 else None
    kernel = _render_decode_kernel_serial if h * w < _SERIAL_BELOW_PX else _render_decode_kernel
    # Rows are handed out in chunks of _CHUNK_ROWS (not one static block per thread), so that a
    # thread the OS schedules late (a shared machine) holds up the others by one chunk at most.
    old_chunk = numba.set_parallel_chunksize(_CHUNK_ROWS)
    try:
        per_dir = _decode_directions(kernel, xy, ok, sequence, size, n, full, cos_d, sin_d, w_a, w_c, w_s, sigma,
                                     noise_source, float(tie_guard))
    finally:
        numba.set_parallel_chunksize(old_chunk)
    rx, ry = per_dir
    xy_out = np.empty((h, w, 2))
    std = np.empty((h, w, 2))
    modulation = np.empty((h, w, 2))
    offset = np.empty((h, w, 2))
    flags = np.empty((h, w), np.uint8)
    _combine_kernel(rx["out"], ry["out"], rx["flags"], ry["flags"], rx["std"], ry["std"],
                    rx["modulation"], ry["modulation"], rx["offset"], ry["offset"],
                    xy_out, flags, std, modulation, offset)
    return ScreenCoordinates(screen_xy_mm=xy_out, valid=flags == 0, flags=flags, std_xy_mm=std,
                             modulation=modulation, offset=offset, reversed=np.stack([rx["rev"], ry["rev"]], -1))


def _decode_directions(kernel, xy, ok, sequence, size, n, full, cos_d, sin_d, w_a, w_c, w_s, sigma, noise_source,
                       tie_guard):
    """Both directions, coarse → fine per direction: a list of two dicts of (H, W) arrays."""
    h, w = ok.shape
    no_noise = np.empty((0, 0, 0))
    per_dir = []
    for axis, direction in enumerate(DIRECTIONS):
        periods = np.asarray(sequence.periods(direction), dtype=np.float64)
        order = np.argsort(-periods, kind="stable")
        ext, org = _check_extent(size[axis], 0.0, periods[order[0]], "extent_mm")
        upper = org + ext + _resolve_margin(None, periods[order[0]], ext)
        std_scale = periods[order[-1]] / _TWO_PI * math.sqrt(2.0 / n)
        arrays = dict(out=np.empty((h, w)), flags=np.zeros((h, w), np.uint8),
                      modulation=np.empty((h, w)), offset=np.empty((h, w)), std=np.empty((h, w)),
                      contrast=np.empty((h, w)), rev=np.zeros((h, w), np.bool_))
        for level, i in enumerate(order):
            p = float(periods[i])
            last = level == len(order) - 1
            noise = no_noise if noise_source is None else noise_source.fields(direction, p)
            kernel(
                xy, ok, axis, cos_d, sin_d, sequence.mean_level, sequence.amplitude, full, noise,
                w_a, w_c, w_s, True, full, DEFAULT_DARK_FRACTION * full, DEFAULT_MIN_MODULATION_FRACTION * full,
                DEFAULT_MIN_MODULATION_RATIO, _MODE_COARSE if level == 0 else _MODE_REFINE, p, org, upper,
                DEFAULT_UNWRAP_TOLERANCE, last, last, std_scale, sigma, tie_guard, **arrays,
                rev_ratio=REVERSAL_CONTRAST_RATIO)
        per_dir.append(arrays)
    return per_dir


class _NoiseFields:
    """The renderer's noise fields, drawn in display order (N fields per period, as
    ``render_period`` draws them, full frames, subsampled by ``stride``) and handed out in decoding
    order (coarsest first per direction)."""

    def __init__(self, sequence: FringeSequence, noise_std: float, rng, shape, stride: int = 1):
        self._order = [(d, float(p)) for d in DIRECTIONS for p in sequence.periods(d)]
        self._n = sequence.n_shifts
        self._std = noise_std
        self._rng = rng
        self._shape = shape
        self._stride = stride
        self._drawn: dict = {}
        self._next = 0

    def fields(self, direction: str, period_mm: float) -> np.ndarray:
        key = (direction, float(period_mm))
        while key not in self._drawn:
            k = self._order[self._next]
            self._next += 1
            st = self._stride
            self._drawn[k] = np.stack([self._rng.normal(0.0, self._std, size=self._shape)[::st, ::st]
                                       for _ in range(self._n)])
        return self._drawn.pop(key)
