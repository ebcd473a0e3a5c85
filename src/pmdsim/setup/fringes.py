"""The displayed fringe sequence, as a description (no rendering): directions, periods, shifts.

Model and signs: docs/conventions.md, "Fringe patterns":

    φ = 2π·c/p,   δ_k = 2π·k/N,   I_k = A + B·cos(φ − δ_k)

with c the screen x (direction "x") or y (direction "y") coordinate. Rendering lives in
:mod:`pmdsim.simulation.patterns`, decoding in :mod:`pmdsim.evaluation.phase`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DIRECTIONS", "PatternFrame", "FringeSequence"]

DIRECTIONS = ("x", "y")


@dataclass(frozen=True)
class PatternFrame:
    """One displayed fringe pattern: direction, period (mm), shift index k of N."""

    direction: str
    period_mm: float
    shift_index: int
    n_shifts: int

    @property
    def shift_rad(self) -> float:
        """δ_k = 2π k / N."""
        return 2.0 * np.pi * self.shift_index / self.n_shifts

    @property
    def axis(self) -> int:
        """0 for direction x, 1 for y (index into screen_xy_mm)."""
        return DIRECTIONS.index(self.direction)


@dataclass(frozen=True)
class FringeSequence:
    """A sequence of phase-shifted fringe patterns along screen x and y.

    Parameters
    ----------
    periods_x_mm, periods_y_mm : tuple of float
        Fringe periods in mm for each direction, coarsest first. For temporal (hierarchical)
        unwrapping the coarsest period must be at least the screen's extent in that direction.
    n_shifts : int
        N ≥ 3 phase shifts per period.
    mean_level, amplitude : float
        A and B as fractions of full scale; A − B ≥ 0 and A + B ≤ 1 avoid clipping.
    """

    periods_x_mm: tuple[float, ...]
    periods_y_mm: tuple[float, ...]
    n_shifts: int = 4
    mean_level: float = 0.5
    amplitude: float = 0.45

    def __post_init__(self) -> None:
        object.__setattr__(self, "periods_x_mm", tuple(float(p) for p in self.periods_x_mm))
        object.__setattr__(self, "periods_y_mm", tuple(float(p) for p in self.periods_y_mm))
        if int(self.n_shifts) != self.n_shifts or self.n_shifts < 3:
            raise ValueError(f"n_shifts must be an integer ≥ 3, got {self.n_shifts!r}")
        for name in ("periods_x_mm", "periods_y_mm"):
            ps = getattr(self, name)
            if not ps:
                raise ValueError(f"{name} must list at least one period")
            if not all(np.isfinite(p) and p > 0 for p in ps):
                raise ValueError(f"{name} must be finite and > 0, got {list(ps)}")
        if not (0.0 <= self.mean_level <= 1.0) or not (0.0 < self.amplitude <= 1.0):
            raise ValueError("mean_level must be in [0, 1] and amplitude in (0, 1]")

    def periods(self, direction: str) -> tuple[float, ...]:
        return self.periods_x_mm if direction == "x" else self.periods_y_mm

    def frames(self) -> list[PatternFrame]:
        """All frames in display order: direction x then y, periods coarsest first, shifts 0…N−1."""
        out = []
        for direction in DIRECTIONS:
            for p in self.periods(direction):
                for k in range(self.n_shifts):
                    out.append(PatternFrame(direction, p, k, self.n_shifts))
        return out
