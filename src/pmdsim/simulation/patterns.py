"""Phase-shifted sinusoidal fringe patterns and image rendering.

The pattern is defined on the continuous screen (pattern coordinates in mm, screen frame); the
recorded intensity of a pixel is the pattern's intensity at the pixel's mapped screen point
(paper §2.4). Model and signs: docs/conventions.md, "Fringe patterns":

    φ = 2π·c/p,   δ_k = 2π·k/N,   I_k = A + B·cos(φ − δ_k)

with c the screen x (direction "x") or y (direction "y") coordinate.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.fast_trig import MAX_FAST_PHASE, TIE_GUARD, libm_grey_level, sincos
from ..setup.fringes import DIRECTIONS, FringeSequence, PatternFrame

__all__ = ["PatternFrame", "FringeSequence", "render", "render_period", "render_sequence"]

@numba.njit(cache=True, parallel=True, error_model="numpy")
def _render_kernel(screen_xy, valid, axis, period, shift, mean, amp, full_scale, noise, out):
    h, w = valid.shape
    two_pi_over_p = 2.0 * np.pi / period
    for v in numba.prange(0, h):
        for u in range(w):
            if not valid[v, u]:
                out[v, u] = 0
                continue
            val = full_scale * (mean + amp * np.cos(two_pi_over_p * screen_xy[v, u, axis] - shift))
            if noise.shape[0] > 0:
                val += noise[v, u]
            q = np.floor(val + 0.5)
            if q < 0.0:
                q = 0.0
            elif q > full_scale:
                q = full_scale
            out[v, u] = q


def _check_render_args(screen_xy_mm, valid, bit_depth):
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth!r}")
    xy = np.asarray(screen_xy_mm, dtype=float)
    ok = np.asarray(valid, dtype=bool)
    if xy.ndim != 3 or xy.shape[-1] != 2 or ok.shape != xy.shape[:2]:
        raise ValueError(f"screen_xy_mm must be (H, W, 2) and valid (H, W), got {xy.shape} and {ok.shape}")
    return xy, ok


def render(
    screen_xy_mm: np.ndarray,
    valid: np.ndarray,
    frame: PatternFrame,
    sequence: FringeSequence,
    *,
    bit_depth: int = 8,
    noise_std: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Render one camera image of one pattern frame from a pixel → screen mapping.

    Parameters
    ----------
    screen_xy_mm : ndarray (H, W, 2)
        Pattern coordinates per pixel (screen frame, mm).
    valid : ndarray of bool (H, W)
        Pixels that see the screen; the others are black.
    frame : PatternFrame
    sequence : FringeSequence
        Supplies A and B.
    bit_depth : {8, 16}
    noise_std : float
        Standard deviation of additive Gaussian intensity noise, in grey levels, before
        quantisation (0: none).
    rng : numpy.random.Generator
        Source of the noise (required when noise_std > 0, for reproducibility).

    Returns
    -------
    ndarray (H, W), uint8 or uint16
        Rounded to the nearest grey level and clipped to [0, 2**bit_depth − 1].
    """
    xy, ok = _check_render_args(screen_xy_mm, valid, bit_depth)
    full = float(2**bit_depth - 1)
    if noise_std > 0:
        if rng is None:
            raise ValueError("noise_std > 0 needs a seeded rng for reproducible images")
        noise = rng.normal(0.0, noise_std, size=ok.shape)
    else:
        noise = np.empty((0, 0))
    out = np.empty(ok.shape, dtype=np.uint8 if bit_depth == 8 else np.uint16)
    _render_kernel(xy, ok, frame.axis, frame.period_mm, frame.shift_rad, sequence.mean_level,
                   sequence.amplitude, full, noise, out)
    return out


@numba.njit(cache=True, error_model="numpy")
def _render_stack_rows(v0, v1, screen_xy, valid, axis, period, cos_d, sin_d, mean, amp, full_scale, noise, out):
    """Rows v0 … v1 − 1 of all N images: I_k = round(F·(A + B·(cos φ cos δ_k + sin φ sin δ_k)) + noise).

    Row by row in vectorisable passes: the phases, their sine and cosine from the branch-free
    :func:`~pmdsim.geometry.fast_trig.sincos`, then image by image the quantised grey levels.
    A pixel whose unrounded value lies within ``TIE_GUARD`` of a rounding boundary in any image
    (or whose phase is outside the fast range) is rendered again with libm's ``sin`` and ``cos``,
    so the images are those of libm bit for bit (tests/test_render.py)."""
    w = valid.shape[1]
    n = cos_d.shape[0]
    two_pi_over_p = 2.0 * np.pi / period
    has_noise = noise.shape[0] > 0
    cb = np.empty(w)
    sb = np.empty(w)
    redo = np.empty(w, np.bool_)
    for v in range(v0, v1):
        for u in range(w):  # the strided load in a loop of its own: the next one vectorises
            cb[u] = two_pi_over_p * screen_xy[v, u, axis]
        for u in range(w):
            phi = cb[u]
            fast = abs(phi) <= MAX_FAST_PHASE  # False for NaN
            s, c = sincos(phi if fast else 0.0)
            sb[u] = s
            cb[u] = c
            redo[u] = valid[v, u] & (not fast)
        for k in range(n):
            cdk = cos_d[k]
            sdk = sin_d[k]
            for u in range(w):
                # cos(φ − δ_k) = cos φ cos δ_k + sin φ sin δ_k: one sine and cosine per pixel.
                val = full_scale * (mean + amp * (cb[u] * cdk + sb[u] * sdk))
                if has_noise:
                    val += noise[k, v, u]
                t = val + 0.5
                q = np.floor(t)
                frac = t - q
                redo[u] = redo[u] | (valid[v, u] & ((frac < TIE_GUARD) | (frac > 1.0 - TIE_GUARD)))
                q = min(max(q, 0.0), full_scale)
                out[k, v, u] = q if valid[v, u] else 0.0
        for u in range(w):
            if not redo[u]:
                continue
            phi = two_pi_over_p * screen_xy[v, u, axis]
            c = np.cos(phi)
            s = np.sin(phi)
            for k in range(n):
                out[k, v, u] = libm_grey_level(c, s, cos_d[k], sin_d[k], mean, amp, full_scale, has_noise,
                                               noise[k, v, u] if has_noise else 0.0)


@numba.njit(cache=True, parallel=True)
def _render_stack_kernel(screen_xy, valid, axis, period, cos_d, sin_d, mean, amp, full_scale, noise, out):
    h = valid.shape[0]
    rows = 16
    for b in numba.prange(0, (h + rows - 1) // rows):
        _render_stack_rows(b * rows, min(h, (b + 1) * rows), screen_xy, valid, axis, period, cos_d, sin_d, mean,
                           amp, full_scale, noise, out)


def render_period(
    screen_xy_mm: np.ndarray,
    valid: np.ndarray,
    direction: str,
    period_mm: float,
    sequence: FringeSequence,
    *,
    bit_depth: int = 8,
    noise_std: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Render all N phase-shifted images of one direction and period at once: (N, H, W).

    Same model and quantisation as :func:`render` (one sine and cosine per pixel instead of N
    cosines). With noise, the N noise fields are drawn from ``rng`` in shift order.
    """
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be 'x' or 'y', got {direction!r}")
    xy, ok = _check_render_args(screen_xy_mm, valid, bit_depth)
    n = sequence.n_shifts
    delta = 2.0 * np.pi * np.arange(n) / n
    full = float(2**bit_depth - 1)
    if noise_std > 0:
        if rng is None:
            raise ValueError("noise_std > 0 needs a seeded rng for reproducible images")
        noise = np.stack([rng.normal(0.0, noise_std, size=ok.shape) for _ in range(n)])
    else:
        noise = np.empty((0, 0, 0))
    out = np.empty((n,) + ok.shape, dtype=np.uint8 if bit_depth == 8 else np.uint16)
    _render_stack_kernel(xy, ok, DIRECTIONS.index(direction), float(period_mm), np.cos(delta), np.sin(delta),
                         sequence.mean_level, sequence.amplitude, full, noise, out)
    return out


def render_sequence(screen_xy_mm, valid, sequence: FringeSequence, *, bit_depth: int = 8,
                    noise_std: float = 0.0, seed: int | None = None):
    """Yield ``(frame, image)`` for every frame of ``sequence`` (see :func:`render`).

    With noise, the generator is seeded with ``seed`` so the same inputs give the same images.
    """
    rng = np.random.default_rng(seed) if noise_std > 0 else None
    for frame in sequence.frames():
        yield frame, render(screen_xy_mm, valid, frame, sequence, bit_depth=bit_depth,
                            noise_std=noise_std, rng=rng)
