"""Display levels seen by a sharp camera: the displayed pattern sampled at each pixel's screen point
(issue 20, speed).

Without any camera transfer (no defocus, no pixel area, no screen pixels) a camera pixel records
the displayed radiance at its screen coordinate x exactly:

    mean = g·r(Q(A + B·cos(2π·x/p − δ_k))),

Q the rounding to ``display_levels`` L (:func:`.display.quantise_levels`: index
⌊clip(d, 0, 1)·(L − 1) + ½⌋), r the response tabulated at the L levels (with the LCD's
viewing-angle model the R basis functions at the levels, mixed with the pixel's weights,
:mod:`.display_angle`). This is the harmonic series of :mod:`.imaging_series` summed to infinity:
the series keeps the rounded staircase's first 48 harmonics (each ≲ 1/(n·L)), whose truncation
rings (Gibbs) at the level steps; the two differ by that truncation (docs/benchmarks.md,
"Display levels alone"). Cost: one cosine and one table look-up per pixel and image instead of
48 harmonics.
"""

from __future__ import annotations

import numba
import numpy as np

from .sensor_code import sensor_code

__all__ = ["point_kernel", "render_period_point"]


@numba.njit(cache=True, parallel=True, error_model="numpy")
def point_kernel(coord, valid, period, delta, mean_level, amplitude, lut, pw, use_pw, radiance, scale, dark, clip,
                 shot, const_var, full, noise, use_noise, out, means):
    """All N images of one period: ``lut`` (R, L) the response (functions) at the L display
    levels, mixed per pixel with ``pw`` (H, W, R) when ``use_pw`` (else row 0); ``out`` (N, H, W),
    ``means`` (N, H, W) float64 or empty: the mean grey levels above the dark offset."""
    h, w = valid.shape
    n = delta.shape[0]
    nr, nl = lut.shape
    keep_means = means.shape[0] > 0
    k1 = 2.0 * np.pi / period
    for v in numba.prange(0, h):
        for u in range(w):
            x = coord[v, u]
            if not valid[v, u] or not np.isfinite(x):
                for k in range(n):
                    out[k, v, u] = 0
                    if keep_means:
                        means[k, v, u] = 0.0
                continue
            g = radiance[v, u] * scale
            phi = k1 * x
            for k in range(n):
                d = mean_level + amplitude * np.cos(phi - delta[k])
                d = min(1.0, max(0.0, d))
                i = int(np.floor(d * (nl - 1) + 0.5))
                if use_pw:
                    val = 0.0
                    for r in range(nr):
                        val += pw[v, u, r] * lut[r, i]
                else:
                    val = lut[0, i]
                mean = g * val
                if keep_means:
                    means[k, v, u] = mean
                out[k, v, u] = sensor_code(mean, dark, clip, shot, const_var, full, use_noise,
                                           noise[k, v, u] if use_noise else 0.0)


def render_period_point(coord: np.ndarray, valid: np.ndarray, period_mm: float, n_shifts: int, mean_level: float,
                        amplitude: float, lut: np.ndarray, weights: np.ndarray | None, radiance: np.ndarray, sensor,
                        noise: np.ndarray | None, out: np.ndarray, means: np.ndarray | None = None) -> np.ndarray:
    """Fill ``out`` (N, H, W) with the N images of one period through :func:`point_kernel`.

    ``coord`` (H, W) the screen coordinate along the fringe axis (mm); ``lut`` (R, L) the response
    (functions) at the display's L levels; ``weights`` (H, W, R) or None (R = 1); ``noise``
    (N, H, W) float32 standard-normal draws when the sensor is noisy."""
    delta = 2.0 * np.pi * np.arange(n_shifts) / n_shifts
    use_pw = weights is not None
    pw = np.ascontiguousarray(weights, dtype=float) if use_pw else np.zeros((1, 1, 1))
    nz = noise if sensor.noisy else np.empty((0, 0, 0), dtype=np.float32)
    m_out = np.empty((0, 0, 0)) if means is None else means
    point_kernel(np.ascontiguousarray(coord, dtype=float), np.ascontiguousarray(valid, dtype=bool), float(period_mm),
                 delta, float(mean_level), float(amplitude), np.ascontiguousarray(lut, dtype=float), pw, use_pw,
                 np.ascontiguousarray(radiance, dtype=float), sensor.scale_dn, sensor.dark_dn, sensor.clip_dn,
                 sensor.shot_dn, sensor.const_var_dn2, sensor.full_scale, nz, sensor.noisy, out, m_out)
    return out
