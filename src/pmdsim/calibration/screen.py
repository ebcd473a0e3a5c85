"""Free-form screen model of the calibration (paper §5).

Non-planar screen (optional, paper §5)
--------------------------------------
With a :class:`ScreenModel` (``calibrate(..., screen_model=...)``) the screen is the pmdsim
not-a-knot spline surface over a control grid, and its free control heights are estimated
jointly: the correspondences' decoded (x_q, y_q) are used and their z is the model's height
h(x_q, y_q) = Σ_ji Z_ji w_j(y_q) w_i(x_q) (w: the cardinal basis splines of the grid axes; the
1-D weights are computed once per correspondence). ∂r/∂Z_ji = (∂r/∂q_z)·w_j(y_q)·w_i(x_q), with
∂r/∂q_z by the chain rule through the mirroring, the rigid transform and the projection.
**Gauge**: the screen frame stays the reference and its x–y plane is the plane of the screen's
rigid frame — the border control heights are held (normally 0) and only interior control points
may be free, since a piston or tilt of the screen cannot be separated from the camera poses and
mirror planes (:class:`ScreenModel` rejects free border points). A free height that fewer than
``min_correspondences`` correspondences see with basis weight ≥ :data:`SCREEN_WEIGHT_MIN` is
reported by name (:class:`CalibrationDataError`), as are combinations the condition check finds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import CalibrationDataError


# ============================================================================ screen model
def _basis_weights(grid: np.ndarray, coef: np.ndarray, v: np.ndarray, derivative: bool = False) -> np.ndarray:
    """Values (M, n) of the n cardinal not-a-knot basis splines of ``grid`` at ``v`` (M,), or
    their derivatives d/dv (``coef`` from :func:`pmdsim.geometry.surface.cardinal_spline_coefficients`;
    the edge intervals extrapolate, as in :func:`pmdsim.geometry.surface._interval`)."""
    n = grid.size
    i = np.clip(np.searchsorted(grid, v, side="right") - 1, 0, n - 2)
    t = v - grid[i]
    c = coef[i]  # (M, 4, n)
    if derivative:
        return c[:, 1] + t[:, None] * (2.0 * c[:, 2] + t[:, None] * (3.0 * c[:, 3]))
    return c[:, 0] + t[:, None] * (c[:, 1] + t[:, None] * (c[:, 2] + t[:, None] * c[:, 3]))


@dataclass(frozen=True, eq=False)
class ScreenModel:
    """A non-planar pattern screen for the calibration: the pmdsim not-a-knot spline surface
    over a control grid (the same surface as ``SplineSurface(grid_x_mm, grid_y_mm, heights_mm)``,
    paper §2.3, eq. 8), with some control heights estimated (paper §5, the open question).

    Parameters
    ----------
    grid_x_mm, grid_y_mm : array_like (n_x,), (n_y,)
        Grid lines of the screen frame, strictly increasing, ≥ 2 each (normally the screen's
        bounds and its control lines, e.g. ``[0, 354, 708]`` × ``[0, 199, 398]``).
    heights_mm : array_like (n_y, n_x)
        Control heights (row j ↔ y_j, column i ↔ x_i): the start values of the free ones, the
        fixed values of the others.
    free : array_like of bool (n_y, n_x)
        The control heights to estimate; only interior points may be free.

    Gauge
    -----
    The screen frame is the calibration's reference and its x–y plane is the plane of the
    screen's rigid frame (its border): **the border control heights are held** at their given
    values (normally 0). A piston or tilt of the screen surface (which the border heights would
    carry) is indistinguishable from moving all camera poses and mirror planes, so a ``free``
    mask with a border point set is rejected (:class:`CalibrationDataError`).

    Raises
    ------
    CalibrationDataError
        On bad grids or shapes, non-finite heights, or free border points (named).
    """

    grid_x_mm: np.ndarray
    grid_y_mm: np.ndarray
    heights_mm: np.ndarray
    free: np.ndarray

    def __post_init__(self) -> None:
        grids = []
        for name in ("grid_x_mm", "grid_y_mm"):
            g = np.array(getattr(self, name), dtype=float).reshape(-1) if np.ndim(getattr(self, name)) <= 1 else None
            if g is None or g.size < 2 or not np.all(np.isfinite(g)) or not np.all(np.diff(g) > 0):
                raise CalibrationDataError(
                    f"ScreenModel.{name} must be a strictly increasing 1-D array of ≥ 2 finite values, "
                    f"got {getattr(self, name)!r}")
            g.setflags(write=False)
            grids.append(g)
        gx, gy = grids
        shape = (gy.size, gx.size)
        z = np.array(self.heights_mm, dtype=float)
        if z.shape != shape:
            raise CalibrationDataError(f"ScreenModel.heights_mm must have shape (n_y, n_x) = {shape}, got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise CalibrationDataError("ScreenModel.heights_mm contains NaN or infinite values")
        free = np.array(self.free)
        if free.shape != shape or free.dtype != bool:
            raise CalibrationDataError(f"ScreenModel.free must be a bool array of shape (n_y, n_x) = {shape}, "
                                       f"got {free.dtype} {free.shape}")
        border = free.copy()
        border[1:-1, 1:-1] = False
        if border.any():
            names = [_screen_name(j, i) for j, i in zip(*np.nonzero(border))]
            raise CalibrationDataError(
                f"ScreenModel: border control heights cannot be estimated ({', '.join(names)} are free): "
                f"the gauge of the calibration is the screen frame, whose x–y plane is the plane of the "
                f"rigid screen frame (the border); a piston or tilt of the screen surface cannot be "
                f"separated from the camera poses and mirror planes. Hold the border heights (free=False) "
                f"and free interior control points only")
        z.setflags(write=False)
        free.setflags(write=False)
        object.__setattr__(self, "grid_x_mm", gx)
        object.__setattr__(self, "grid_y_mm", gy)
        object.__setattr__(self, "heights_mm", z)
        object.__setattr__(self, "free", free)

    @classmethod
    def flat(cls, grid_x_mm, grid_y_mm) -> "ScreenModel":
        """A flat start (all heights 0) with every interior control point free: 3 × 3 → 1 free
        height, 5 × 5 → 9, 9 × 9 → 49."""
        gx = np.asarray(grid_x_mm, dtype=float)
        gy = np.asarray(grid_y_mm, dtype=float)
        free = np.zeros((gy.size, gx.size), dtype=bool)
        free[1:-1, 1:-1] = True
        return cls(gx, gy, np.zeros(free.shape), free)

    @classmethod
    def from_surface(cls, surface, free=None) -> "ScreenModel":
        """From a :class:`pmdsim.geometry.surface.SplineSurface` (e.g. a setup's ``screen.surface``);
        ``free`` defaults to all interior control points."""
        z = np.asarray(surface.heights_mm, dtype=float)
        if free is None:
            free = np.zeros(z.shape, dtype=bool)
            free[1:-1, 1:-1] = True
        return cls(surface.grid_x_mm, surface.grid_y_mm, z, free)

    @property
    def n_free(self) -> int:
        """Number F of estimated control heights."""
        return int(self.free.sum())

    @property
    def free_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(j, i) of the free control heights in parameter order (row-major)."""
        return np.nonzero(self.free)

    def free_names(self) -> list[str]:
        """Parameter names of the free heights, ``screen.h[j,i]_mm`` (row j ↔ y_j, column i ↔ x_i)."""
        return [_screen_name(j, i) for j, i in zip(*self.free_index)]

    @property
    def free_heights_mm(self) -> np.ndarray:
        """The free control heights (F,) in parameter order."""
        return self.heights_mm[self.free]

    def with_free_heights(self, values_mm) -> "ScreenModel":
        """A copy with the free heights replaced by ``values_mm`` (F,)."""
        z = np.array(self.heights_mm)
        z[self.free] = np.asarray(values_mm, dtype=float)
        return ScreenModel(self.grid_x_mm, self.grid_y_mm, z, self.free)

    @property
    def surface(self):
        """The screen surface as a :class:`pmdsim.geometry.surface.SplineSurface` (e.g. for the ray tracer)."""
        from ..geometry.surface import SplineSurface

        return SplineSurface(self.grid_x_mm, self.grid_y_mm, self.heights_mm)

    def basis_weights(self, x_mm, y_mm) -> tuple[np.ndarray, np.ndarray]:
        """The 1-D cardinal basis values (wx (M, n_x), wy (M, n_y)) at the points: the height is
        h(x, y) = Σ_j Σ_i heights_mm[j, i]·wy[:, j]·wx[:, i]. (The not-a-knot cardinal basis
        splines have global support — they decay by about 4× per grid interval — so every
        control height has a nonzero weight everywhere.)"""
        from ..geometry.surface import cardinal_spline_coefficients

        x = np.asarray(x_mm, dtype=float).reshape(-1)
        y = np.asarray(y_mm, dtype=float).reshape(-1)
        wx = _basis_weights(self.grid_x_mm, cardinal_spline_coefficients(self.grid_x_mm), x)
        wy = _basis_weights(self.grid_y_mm, cardinal_spline_coefficients(self.grid_y_mm), y)
        return wx, wy

    def height(self, x_mm, y_mm) -> np.ndarray:
        """h(x, y) (mm) at the points (flattened)."""
        wx, wy = self.basis_weights(x_mm, y_mm)
        return np.einsum("mi,mi->m", wy @ self.heights_mm, wx)


def _screen_name(j: int, i: int) -> str:
    return f"screen.h[{j},{i}]_mm"
