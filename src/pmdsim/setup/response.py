"""Intensity response of a display–camera pair, and the linearisation of fringe images.

A display does not emit light in proportion to the commanded grey level (an LCD's gamma, a
black level, limited contrast), and a camera adds its own offset and gain. The phase-shift
formula (paper §2.4, docs/conventions.md "Fringe patterns") assumes I_k = A + B·cos(φ − δ_k);
a non-linear response r turns the sinusoid into r(A + B·cos(φ − δ_k)), whose harmonics put a
ripple into the decoded phase (with N shifts the n-th harmonic aliases for n ≡ ±1 mod N: the
(N ± 1)-th harmonics give an N·φ ripple). Applying the inverse response to the recorded images
before decoding (*linearisation*) removes it.

Conventions (docs/conventions.md, "Intensity response"): both axes are fractions of full scale,
so that the response does not depend on bit depths — the *display level* d ∈ [0, 1] (commanded
grey / display full scale) and the *camera level* c ∈ [0, 1] (recorded grey / camera full
scale). :meth:`IntensityResponse.forward` maps d → c (what a simulation records),
:meth:`IntensityResponse.linearise` maps c → d (what an evaluation applies). Between the
measured levels the response is the monotone piecewise-cubic (PCHIP, Fritsch–Carlson)
interpolant of the samples, and :meth:`~IntensityResponse.linearise` is its exact inverse (the
cubic of each segment solved by safeguarded Newton iteration), so that forward and linearise are
inverse to float64 precision everywhere, not only at the samples; outside the measured camera
range :meth:`linearise` reports the samples as out of range (they would be extrapolated).

The response is measured as SOFAST's ``image_calibration.h5`` holds it: a series of uniform
grey levels displayed and the camera's mean recorded value for each
(:meth:`IntensityResponse.from_samples`), or given as a gamma law
(:meth:`IntensityResponse.from_gamma`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import PmdsimError

__all__ = ["ResponseError", "IntensityResponse"]


class ResponseError(PmdsimError, ValueError):
    """An intensity response is invalid (not increasing, too few levels, out of [0, 1], …)."""


def _levels(values, name: str) -> tuple[float, ...]:
    a = np.asarray(values, dtype=float)
    if a.ndim != 1 or a.size < 2:
        raise ResponseError(f"{name} must be a list of at least 2 levels, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ResponseError(f"{name} must be finite")
    return tuple(float(v) for v in a)


@dataclass(frozen=True)
class IntensityResponse:
    """Monotone display → camera response, sampled at increasing display levels.

    Parameters
    ----------
    display_levels : sequence of float, shape (M,)
        Commanded display levels d ∈ [0, 1] (fraction of the display's full scale), strictly
        increasing, M ≥ 2.
    camera_levels : sequence of float, shape (M,)
        Recorded camera levels c ∈ [0, 1] (fraction of the camera's full scale) at those
        display levels, strictly increasing (a response that is not is refused: it cannot be
        inverted, and it usually means saturation or a mis-ordered series).

    Build with :meth:`from_samples` (measured grey-level series) or :meth:`from_gamma`.
    """

    display_levels: tuple[float, ...]
    camera_levels: tuple[float, ...]

    def __post_init__(self) -> None:
        d = _levels(self.display_levels, "display_levels")
        c = _levels(self.camera_levels, "camera_levels")
        if len(d) != len(c):
            raise ResponseError(f"display_levels and camera_levels must have equal lengths, got {len(d)} and {len(c)}")
        for name, v in (("display_levels", d), ("camera_levels", c)):
            if min(v) < 0.0 or max(v) > 1.0:
                raise ResponseError(f"{name} are fractions of full scale and must lie in [0, 1], got "
                                    f"{min(v):g} … {max(v):g}")
            steps = np.diff(v)
            if (steps <= 0).any():
                i = int(np.argmax(steps <= 0))
                raise ResponseError(f"{name} must be strictly increasing, but entry {i + 1} ({v[i + 1]:g}) ≤ entry {i} "
                                    f"({v[i]:g}) — a saturated or mis-ordered grey-level series?")
        object.__setattr__(self, "display_levels", d)
        object.__setattr__(self, "camera_levels", c)

    # ------------------------------------------------------------------ builders
    @classmethod
    def from_samples(cls, display_values, camera_values, *, display_full_scale: float = 255.0,
                     camera_full_scale: float = 255.0) -> "IntensityResponse":
        """From a measured grey-level series: displayed values and the camera's mean recorded
        values, in their own grey units (e.g. SOFAST's ``ImageCalibration/display_values`` 0…255
        and ``camera_values``), with the two full scales (e.g. 255 and 2^bits − 1)."""
        if not (display_full_scale > 0 and camera_full_scale > 0):
            raise ResponseError(f"full scales must be > 0, got {display_full_scale!r}, {camera_full_scale!r}")
        d = np.asarray(display_values, dtype=float) / display_full_scale
        c = np.asarray(camera_values, dtype=float) / camera_full_scale
        return cls(tuple(d), tuple(c))

    @classmethod
    def from_gamma(cls, gamma: float, *, black_level: float = 0.0, white_level: float = 1.0,
                   n_levels: int = 257) -> "IntensityResponse":
        """The law c = b + (w − b)·d^γ (black level b, white level w, fractions of full scale),
        sampled at ``n_levels`` equally spaced display levels."""
        if not (math.isfinite(gamma) and gamma > 0):
            raise ResponseError(f"gamma must be a finite number > 0, got {gamma!r}")
        if not (0.0 <= black_level < white_level <= 1.0):
            raise ResponseError(f"need 0 ≤ black_level < white_level ≤ 1, got {black_level!r}, {white_level!r}")
        if int(n_levels) != n_levels or n_levels < 2:
            raise ResponseError(f"n_levels must be an integer ≥ 2, got {n_levels!r}")
        d = np.linspace(0.0, 1.0, int(n_levels))
        return cls(tuple(d), tuple(black_level + (white_level - black_level) * d**gamma))

    # ------------------------------------------------------------------ readers
    def forward(self, display_level) -> np.ndarray:
        """Camera level c(d) for display levels d (any shape; clipped to the measured range)."""
        from scipy.interpolate import PchipInterpolator  # here: scipy.interpolate is not on evaluate's start-up path

        d = np.clip(np.asarray(display_level, dtype=float), self.display_levels[0], self.display_levels[-1])
        return PchipInterpolator(self.display_levels, self.camera_levels, extrapolate=False)(d)

    def linearise(self, camera_level) -> tuple[np.ndarray, np.ndarray]:
        """Display-equivalent levels d(c) of recorded camera levels (the inverse response).

        Parameters
        ----------
        camera_level : array_like, any shape
            Recorded values as fractions of the camera's full scale.

        Returns
        -------
        display_level : ndarray, float64, same shape
            The linearised values, fractions of the display's full scale; samples outside the
            measured camera range are clipped to its ends.
        out_of_range : ndarray of bool, same shape
            True where the sample lay outside the measured camera range (below the darkest or
            above the brightest level of the series): its linearised value is not measured.
        """
        c = np.asarray(camera_level, dtype=float)
        lo, hi = self.camera_levels[0], self.camera_levels[-1]
        out = (c < lo) | (c > hi) | ~np.isfinite(c)
        # Recorded images hold few distinct values (2^bits at most): invert each once.
        values, index = np.unique(np.clip(np.nan_to_num(c, nan=lo), lo, hi), return_inverse=True)
        return self._inverse(values)[index].reshape(c.shape), out

    def _inverse(self, c: np.ndarray) -> np.ndarray:
        """d(c) for camera levels c (1-D, inside the measured range)."""
        from scipy.interpolate import PchipInterpolator

        pp = PchipInterpolator(self.display_levels, self.camera_levels, extrapolate=False)
        knots_d = np.asarray(self.display_levels)
        knots_c = np.asarray(self.camera_levels)
        seg = np.clip(np.searchsorted(knots_c, c, side="right") - 1, 0, len(knots_c) - 2)
        a0, a1, a2, a3 = pp.c[:, seg]  # f(t) = ((a0 t + a1) t + a2) t + a3, t = d − d_seg
        width = knots_d[seg + 1] - knots_d[seg]
        # Start from the chord, then Newton on the segment's cubic, kept inside the segment
        # (the PCHIP cubic is monotone on it, so the root is unique); 40 steps bound the worst
        # case (a flat start near d = 0), the loop ends as soon as every sample has converged.
        t = (c - knots_c[seg]) / (knots_c[seg + 1] - knots_c[seg]) * width
        lo_t, hi_t = np.zeros_like(t), width.copy()
        for _ in range(60):
            f = ((a0 * t + a1) * t + a2) * t + a3 - c
            lo_t = np.where(f < 0, t, lo_t)
            hi_t = np.where(f > 0, t, hi_t)
            df = (3.0 * a0 * t + 2.0 * a1) * t + a2
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(df > 0, f / df, np.inf)
            t_new = t - step
            bad = ~((t_new > lo_t) & (t_new < hi_t))
            t_new = np.where(bad, 0.5 * (lo_t + hi_t), t_new)  # bisection where Newton leaves the bracket
            done = np.abs(t_new - t) <= 1e-15 * np.maximum(width, 1.0)
            t = t_new
            if done.all():
                break
        return knots_d[seg] + t

    def as_dict(self) -> dict:
        """Plain-data form (manifest / JSON): ``{"display_levels": [...], "camera_levels": [...]}``."""
        return {"display_levels": list(self.display_levels), "camera_levels": list(self.camera_levels)}

    @classmethod
    def from_dict(cls, doc: dict, *, source: str = "response") -> "IntensityResponse":
        """Inverse of :meth:`as_dict`; errors name ``source``."""
        if not isinstance(doc, dict) or set(doc) != {"display_levels", "camera_levels"}:
            raise ResponseError(f"{source} must be a table with exactly display_levels and camera_levels")
        try:
            return cls(tuple(doc["display_levels"]), tuple(doc["camera_levels"]))
        except (TypeError, ValueError) as e:
            raise ResponseError(f"{source}: {e}") from None
