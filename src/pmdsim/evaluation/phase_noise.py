"""The σ model of decoded coordinates: intensity noise σ_I per pixel and its propagation.

For equally spaced N-step decoding of the finest period p_f with modulation B (docs/conventions.md,
"Fringe patterns")::

    σ_φ = √(2/N_f)·σ_I/B,    σ_c = p_f·σ_φ/(2π),

so ``σ_c = coordinate_std_scale(p_f, N_f) · σ_I / B``; the fused decoding kernel of
:mod:`pmdsim.evaluation.decoding` evaluates the last product per pixel.
"""

from __future__ import annotations

import math

import numpy as np

from .phase_flags import _TWO_PI, PhaseDecodingError

__all__ = ["QUANTISATION_NOISE_STD", "coordinate_std_scale", "sensor_noise_std"]

#: Standard deviation (grey levels) of the rounding error of a uniformly distributed value
#: quantised to integers, 1/√12. Default intensity noise of the σ model.
QUANTISATION_NOISE_STD = 1.0 / math.sqrt(12.0)


def coordinate_std_scale(period_mm: float, n_shifts: int) -> float:
    """p/(2π)·√(2/N): σ_c (mm) per unit σ_I/B of an N-step decode of period p (mm)."""
    return period_mm / _TWO_PI * math.sqrt(2.0 / n_shifts)


def _noise_map(noise_std, shape) -> np.ndarray:
    """σ_I as a C-contiguous float64 array of shape (1|H, 1|W)."""
    sigma = QUANTISATION_NOISE_STD if noise_std is None else noise_std
    arr = np.asarray(sigma, dtype=np.float64)
    try:
        np.broadcast_shapes(arr.shape, shape)
        if arr.ndim > 2 or np.broadcast_shapes(arr.shape, shape) != tuple(shape):
            raise ValueError
    except ValueError:
        raise PhaseDecodingError(
            f"noise_std: expected a scalar or an array broadcastable to {tuple(shape)}, got shape {arr.shape}"
        ) from None
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise PhaseDecodingError("noise_std: intensity noise must be finite and >= 0 (grey levels)")
    return np.ascontiguousarray(arr.reshape((1,) * (2 - arr.ndim) + arr.shape))


def sensor_noise_std(offset, gain_dn_per_e: float = 0.0, const_var_dn2: float = 0.0, dark_dn: float = 0.0,
                     quantisation: bool = True) -> np.ndarray:
    """Intensity noise σ_I (grey levels) of a shot- and read-noise-limited sensor, per pixel.

    For use as ``noise_std`` of :func:`decode_direction` / :func:`decode_screen_coordinates`
    (issue 13; EMVA 1288's linear sensor model): a sample of mean I has variance
    g·(I − dark) + σ_c² (+ 1/12 for rounding), g the conversion gain (DN/e⁻, the shot-noise
    variance per DN of signal) and σ_c² the signal-independent variance (read noise (g·σ_read)²
    and any additive noise, DN²). The shot variance changes with the shift, g·B·cos(φ − δ_k),
    but its contribution to Var(φ) ∝ Σ_k cos(φ − δ_k)·sin²(φ − δ_k) = Σ_k [cos(x_k) − cos(3x_k)]/4
    vanishes for equally spaced N ≥ 4, so σ_φ = √(2/N)·σ_I/B holds exactly with σ_I taken at
    the offset A (for N = 3 it is an approximation).

    Parameters
    ----------
    offset : array_like (H, W)
        Offset A per pixel (grey levels), e.g. the mean of the finest period's images.
    gain_dn_per_e, const_var_dn2, dark_dn : float
        Sensor values (0: no shot noise, no read noise, no dark offset).
    quantisation : bool
        Add the rounding variance 1/12.

    Returns
    -------
    ndarray (H, W), float64
        σ_I; finite and ≥ 0 (non-finite offsets count as dark).
    """
    a = np.asarray(offset, dtype=np.float64)
    signal = np.clip(np.nan_to_num(a - dark_dn, nan=0.0), 0.0, None)
    return np.sqrt(gain_dn_per_e * signal + const_var_dn2 + (1.0 / 12.0 if quantisation else 0.0))
