"""The pattern screen as a light source: response curve, angular emission, pixel structure.

* Response (docs/conventions.md, "Image formation" and "Intensity response"): the commanded
  display level d = A + B·cos(φ − δ_k) becomes the relative radiance
  r(d) = b + (1 − b)·d^γ (:class:`~pmdsim.evaluation.response.IntensityResponse.forward`;
  b the black level = 1/contrast). r(A + B·cos θ) is even and 2π-periodic in θ, so it is the
  cosine series Σ_n c_n·cos(nθ) (:func:`harmonic_coefficients`); each harmonic is then blurred
  analytically with its own transfer (simulation.optics).
* Angular emission: radiance ∝ cos^m θ_v, θ_v the angle between the viewing ray and the screen
  normal (m = 0: a Lambertian emitter).
* Pixel structure: the screen shows the pattern constant over each pixel of pitch P
  (sample-and-hold: the pattern sampled at the pixel centres (j + ½)·P and held, a staircase in
  position; its spectrum is harmonic n of period p at ν = n/p plus aliases at ν = n/p + a/P with
  weight sin(πnP/p)/(π(nP/p + a)), a = 0 giving sinc(n·P/p); the renderer sums it in position,
  simulation.imaging_held: the held values weighted by the footprint kernel over each screen
  pixel) and emits through an aperture of area fraction f (the black
  matrix: a rectangular wave of pitch P and duty √f per axis, whose harmonics survive the blur
  only where the camera resolves the pitch). The mean radiance is normalised to that of a fully
  emitting screen (the exposure refers to the screen's average white).
"""

from __future__ import annotations

import numba
import numpy as np

from ..setup.response import IntensityResponse
from .optics import JINC_TABLE, jinc

__all__ = ["display_response", "quantise_levels", "harmonic_coefficients", "emission_falloff", "black_matrix_factor",
           "HARMONIC_TOLERANCE"]

#: Harmonics of the response with |c_n| below this (relative radiance) are dropped: 1e-5 of full
#: scale is 0.04 DN at 12 bit.
HARMONIC_TOLERANCE = 1e-5


def display_response(gamma: float | None, black_level: float = 0.0) -> IntensityResponse | None:
    """The display's response r(d) = b + (1 − b)·d^γ, or None (linear, b = 0) when ``gamma`` is None
    and ``black_level`` 0."""
    if gamma is None and black_level == 0.0:
        return None
    return IntensityResponse.from_gamma(1.0 if gamma is None else gamma, black_level=black_level, n_levels=1025)


def quantise_levels(d, levels: int | None) -> np.ndarray:
    """Commanded display levels d ∈ [0, 1] rounded to ``levels`` equally spaced levels
    (round(d·(L − 1))/(L − 1), half up; e.g. L = 256 for an 8-bit display); None: unchanged."""
    d = np.asarray(d, dtype=float)
    if levels is None:
        return d
    return np.floor(np.clip(d, 0.0, 1.0) * (levels - 1) + 0.5) / (levels - 1)


def harmonic_coefficients(response: IntensityResponse | None, mean_level: float, amplitude: float, *,
                          n_samples: int = 256, max_harmonics: int = 16, levels: int | None = None) -> np.ndarray:
    """Cosine-series coefficients c_n of r(Q(A + B·cos θ)) = Σ_n c_n cos(nθ), shape (K + 1,).

    Q rounds the commanded level to ``levels`` display levels (:func:`quantise_levels`; None: no
    rounding). Without a response and levels: (A, B) exactly. Trailing harmonics below
    :data:`HARMONIC_TOLERANCE` are dropped (the series of a smooth response converges fast). The
    rounded pattern is a staircase in θ whose harmonics decay slowly: it is sampled on 16384
    points and kept up to harmonic 48 (the remainder, each below ~1/(n·L), is dropped — see
    docs/conventions.md, "Screen pixels").
    """
    if response is None and levels is None:
        return np.array([float(mean_level), float(amplitude)])
    if levels is not None:
        n_samples, max_harmonics = max(n_samples, 16384), max(max_harmonics, 48)
    theta = 2.0 * np.pi * np.arange(n_samples) / n_samples
    d = quantise_levels(mean_level + amplitude * np.cos(theta), levels)
    f = d if response is None else response.forward(d)
    spec = np.fft.rfft(f).real / n_samples  # f even in θ: real cosine coefficients
    c = np.concatenate([[spec[0]], 2.0 * spec[1:max_harmonics + 1]])
    keep = np.nonzero(np.abs(c) >= HARMONIC_TOLERANCE)[0]
    k = max(1, int(keep.max()) if keep.size else 1)
    return c[:k + 1].copy()


def emission_falloff(cos_view, exponent: float | None) -> np.ndarray:
    """Relative radiance cos^m θ_v (shape of ``cos_view``); 1 where ``exponent`` is None."""
    c = np.abs(np.asarray(cos_view, dtype=float))
    if exponent is None:
        return np.ones_like(c)
    return c ** float(exponent)


def black_matrix_factor(screen_xy_mm, pitch_mm: float, fill_factor: float, var_xy_mm2, sinc_args=None,
                        n_harmonics: int = 4) -> np.ndarray:
    """Relative radiance seen through the screen's black matrix, normalised to mean 1, shape (H, W).

    Per axis a rectangular wave of pitch P and duty w = √f centred on the pixel centres
    (i + ½)·P: w + Σ_m 2w·sinc(m·w)·cos(2πm(x − P/2)/P), each harmonic attenuated by the
    footprint's uniform-ellipse transfer 2·J₁(x)/x, x = 4πmσ/P (:mod:`.optics`; ``var_xy_mm2``
    (H, W, 2): σ² along x and y)
    and, if given, by the pixel-area transfer (``sinc_args`` (H, W, 2, 2): the Jacobian
    d(screen)/d(pixel), rows x and y).
    """
    xy = np.ascontiguousarray(screen_xy_mm, dtype=float)
    var = np.ascontiguousarray(var_xy_mm2, dtype=float)
    w = float(np.sqrt(fill_factor))
    out = np.ones(xy.shape[:2])
    if w >= 1.0:
        return out
    jac = np.zeros((1, 1, 2, 2)) if sinc_args is None else np.ascontiguousarray(sinc_args, dtype=float)
    _black_matrix_kernel(xy, var, jac, sinc_args is not None, float(pitch_mm), w, int(n_harmonics), JINC_TABLE, out)
    return out


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _black_matrix_kernel(xy, var, jac, use_jac, pitch, w, n_harmonics, table, out):
    # sin(m·x), cos(m·x) of the harmonics m = 1 … M by the Chebyshev recurrences (one sine and
    # cosine per angle and pixel instead of one per harmonic); sinc(m·w) once.
    h, wd = out.shape
    sw = np.empty(n_harmonics + 1)
    for m in range(1, n_harmonics + 1):
        xw = np.pi * m * w
        sw[m] = 2.0 * w * np.sin(xw) / xw
    for v in numba.prange(0, h):
        for u in range(wd):
            f = 1.0
            for a in range(2):
                c = xy[v, u, a]
                if not np.isfinite(c):
                    f = 1.0
                    break
                acc = w
                th = 2.0 * np.pi * (c - 0.5 * pitch) / pitch
                c1, s1 = np.cos(th), np.sin(th)
                x0 = np.pi * jac[v, u, a, 0] / pitch if use_jac else 0.0
                x1 = np.pi * jac[v, u, a, 1] / pitch if use_jac else 0.0
                c0a, s0a = np.cos(x0), np.sin(x0)
                c0b, s0b = np.cos(x1), np.sin(x1)
                cm, sm = 1.0, 0.0  # cos(mθ), sin(mθ)
                ca, sa = 1.0, 0.0  # cos(m·x0), sin(m·x0)
                cb, sb = 1.0, 0.0
                sig = np.sqrt(var[v, u, a])
                for m in range(1, n_harmonics + 1):
                    cm, sm = cm * c1 - sm * s1, sm * c1 + cm * s1
                    ca, sa = ca * c0a - sa * s0a, sa * c0a + ca * s0a
                    cb, sb = cb * c0b - sb * s0b, sb * c0b + cb * s0b
                    t = jinc(4.0 * np.pi * m * sig / pitch, table)
                    if x0 != 0.0:
                        t *= sa / (m * x0)
                    if x1 != 0.0:
                        t *= sb / (m * x1)
                    acc += sw[m] * t * cm
                f *= acc / w
            out[v, u] = f
