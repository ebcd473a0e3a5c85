"""Foil warpage: a seeded height field of a printed foil after sintering (paper §1).

The paper's application is a printed foil that "cannot be regarded as planar any more" after a
thermal step: a *global* bow from internal strain of the substrate and *local* warps where
printed structures shrink. :class:`FoilWarpage` is that height field as an analytic function
h(x, y) in the sample frame (mm, along the sample's +z, which points away from the cameras);
:meth:`FoilWarpage.on_grid` samples it on a spline grid (the paper's Z_s, eq. 7) and
:meth:`FoilWarpage.interpolation_error_mm` says how well the not-a-knot spline through those
samples reproduces the analytic function. Conventions and units: docs/conventions.md,
"Foil warpage".

Model (all lengths mm; (x_c, y_c) the centre of the foil, ρ half its smaller side):

* global bow of magnitude b = ``bow_mm`` (the lift of the edge midpoints towards the cameras):

  - ``"spherical"``:   h = −b·(Δx² + Δy²)/ρ²
  - ``"cylindrical"``: h = −b·s²/ρ², s = Δx·cos θ + Δy·sin θ (θ = ``bow_axis_deg``: the
    direction across which the foil bends; the bend axis is perpendicular to it)
  - ``"saddle"``:      h = −b·(s² − t²)/ρ², t = −Δx·sin θ + Δy·cos θ

  (quadratics: a spline grid of ≥ 3 lines reproduces them exactly);
* local shrinkage warps: ``n_shrinks`` structures at seeded uniform positions in the central
  80 % of the foil, each of depth a_k = ±``shrink_depth_um`` (sign seeded; positive = into the
  table, away from the cameras) and size ``shrink_width_mm``:

  - ``"gaussian"``: a_k·exp(−r²/(2w²)), r the distance from the centre, w the width;
  - ``"pad"``: a rectangular printed pad of half-sides w × w·``pad_aspect`` whose edges are
    smoothed by a Gaussian of σ = ``pad_edge_mm``:
    a_k·¼·[erf((Δx + w)/(√2σ)) − erf((Δx − w)/(√2σ))]·[same in y with w·aspect].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf

__all__ = ["FoilWarpage", "BOW_KINDS", "SHRINK_SHAPES"]

BOW_KINDS = ("spherical", "cylindrical", "saddle", "none")
SHRINK_SHAPES = ("gaussian", "pad")


@dataclass(frozen=True)
class FoilWarpage:
    """A warped foil's height field over the rectangle ``x_range_mm`` × ``y_range_mm``.

    Parameters
    ----------
    x_range_mm, y_range_mm : (float, float)
        Extent of the foil in the sample frame (mm).
    bow_mm : float
        Global bow b (mm, |b| up to a few mm): lift of the edge midpoints towards the cameras.
    bow_kind : {"spherical", "cylindrical", "saddle", "none"}
    bow_axis_deg : float
        θ of the cylindrical and saddle bows (deg, from the sample's x axis).
    n_shrinks : int
        Number of local shrinkage warps (≥ 0).
    shrink_depth_um : float
        Their depth magnitude (µm, tens of µm); each sign is seeded.
    shrink_width_mm : float
        Gaussian σ, or the pad's half-side, in mm (> 0).
    shrink_shape : {"gaussian", "pad"}
    pad_aspect : float
        Pad's y half-side / x half-side (> 0).
    pad_edge_mm : float
        Smoothing σ of the pad edges, mm (> 0).
    seed : int
        Seed of positions and signs (``numpy.random.default_rng([seed, 14])``).
    """

    x_range_mm: tuple[float, float] = (0.0, 400.0)
    y_range_mm: tuple[float, float] = (0.0, 400.0)
    bow_mm: float = 2.0
    bow_kind: str = "spherical"
    bow_axis_deg: float = 0.0
    n_shrinks: int = 6
    shrink_depth_um: float = 30.0
    shrink_width_mm: float = 12.0
    shrink_shape: str = "gaussian"
    pad_aspect: float = 1.0
    pad_edge_mm: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        (x0, x1), (y0, y1) = self.x_range_mm, self.y_range_mm
        if not (math.isfinite(x0) and math.isfinite(x1) and x1 > x0 and math.isfinite(y0) and math.isfinite(y1)
                and y1 > y0):
            raise ValueError(f"foil extent must be increasing finite ranges, got x {self.x_range_mm}, "
                             f"y {self.y_range_mm}")
        if self.bow_kind not in BOW_KINDS:
            raise ValueError(f"bow_kind must be one of {BOW_KINDS}, got {self.bow_kind!r}")
        if self.shrink_shape not in SHRINK_SHAPES:
            raise ValueError(f"shrink_shape must be one of {SHRINK_SHAPES}, got {self.shrink_shape!r}")
        for name in ("bow_mm", "bow_axis_deg", "shrink_depth_um"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)!r}")
        for name in ("shrink_width_mm", "pad_aspect", "pad_edge_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if int(self.n_shrinks) != self.n_shrinks or self.n_shrinks < 0:
            raise ValueError(f"n_shrinks must be an integer ≥ 0, got {self.n_shrinks!r}")

    @property
    def shrinks(self) -> np.ndarray:
        """(n_shrinks, 3): centre x, centre y (mm) and signed depth (mm) of every local warp."""
        rng = np.random.default_rng([int(self.seed), 14])
        (x0, x1), (y0, y1) = self.x_range_mm, self.y_range_mm
        n = int(self.n_shrinks)
        cx = x0 + (0.1 + 0.8 * rng.random(n)) * (x1 - x0)
        cy = y0 + (0.1 + 0.8 * rng.random(n)) * (y1 - y0)
        sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
        return np.stack([cx, cy, sign * self.shrink_depth_um * 1e-3], axis=-1)

    def bow_height_mm(self, x_mm, y_mm) -> np.ndarray:
        """The global bow alone (mm), x, y broadcast."""
        x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=float), np.asarray(y_mm, dtype=float))
        (x0, x1), (y0, y1) = self.x_range_mm, self.y_range_mm
        dx, dy = x - 0.5 * (x0 + x1), y - 0.5 * (y0 + y1)
        rho2 = (0.5 * min(x1 - x0, y1 - y0)) ** 2
        th = math.radians(self.bow_axis_deg)
        s = dx * math.cos(th) + dy * math.sin(th)
        t = -dx * math.sin(th) + dy * math.cos(th)
        b = self.bow_mm
        if self.bow_kind == "spherical":
            return -b * (dx * dx + dy * dy) / rho2
        if self.bow_kind == "cylindrical":
            return -b * s * s / rho2
        if self.bow_kind == "saddle":
            return -b * (s * s - t * t) / rho2
        return np.zeros_like(x)

    def height_mm(self, x_mm, y_mm) -> np.ndarray:
        """h(x, y) in mm (bow plus local warps), along the sample's +z; x, y broadcast."""
        x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=float), np.asarray(y_mm, dtype=float))
        h = self.bow_height_mm(x, y)
        w = self.shrink_width_mm
        for cx, cy, a in self.shrinks:
            if self.shrink_shape == "gaussian":
                h = h + a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2.0 * w * w))
            else:
                s = math.sqrt(2.0) * self.pad_edge_mm
                wy = w * self.pad_aspect
                h = h + a * 0.25 * (erf((x - cx + w) / s) - erf((x - cx - w) / s)) * (
                    erf((y - cy + wy) / s) - erf((y - cy - wy) / s))
        return h

    def grid(self, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Spline grid lines (grid_x_mm, grid_y_mm) over the foil, at most ``spacing_mm`` apart."""
        if not (math.isfinite(spacing_mm) and spacing_mm > 0):
            raise ValueError(f"grid spacing must be a positive number of mm, got {spacing_mm!r}")
        (x0, x1), (y0, y1) = self.x_range_mm, self.y_range_mm
        nx = max(3, int(math.ceil((x1 - x0) / spacing_mm)) + 1)
        ny = max(3, int(math.ceil((y1 - y0) / spacing_mm)) + 1)
        return np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)

    def on_grid(self, grid_x_mm, grid_y_mm) -> np.ndarray:
        """Heights (n_y, n_x) at the grid's control points (row j: y = y_j; eq. 7), mm."""
        gx = np.asarray(grid_x_mm, dtype=float)
        gy = np.asarray(grid_y_mm, dtype=float)
        return self.height_mm(gx[None, :], gy[:, None])

    def interpolation_error_mm(self, grid_x_mm, grid_y_mm, *, oversample: int = 4) -> float:
        """Largest |spline − h| (mm) of the not-a-knot spline through :meth:`on_grid`, checked
        at ``oversample`` points per grid interval in x and y (cell centres and between)."""
        from .surface import SplineSurface

        gx = np.asarray(grid_x_mm, dtype=float)
        gy = np.asarray(grid_y_mm, dtype=float)
        surf = SplineSurface(gx, gy, self.on_grid(gx, gy))
        k = int(oversample)
        fx = np.concatenate([gx[:-1, None] + np.diff(gx)[:, None] * (np.arange(k) + 0.5)[None, :] / k]).ravel()
        fy = np.concatenate([gy[:-1, None] + np.diff(gy)[:, None] * (np.arange(k) + 0.5)[None, :] / k]).ravel()
        X, Y = np.meshgrid(fx, fy)
        return float(np.max(np.abs(surf.height(X, Y) - self.height_mm(X, Y))))
