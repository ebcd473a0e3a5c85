"""Curved samples: analytic shapes and height maps as setup values (issue 14).

* :class:`SampleShape` — sphere, paraboloid or cylinder. The tracer uses it in closed form
  (:class:`~pmdsim.geometry.shapes.QuadricSurface`); the sample's grid gives only its bounds.
* :class:`HeightMapSource` — where a measured or designed height map comes from (file, dataset,
  units, grid); the file is read by :mod:`pmdsim.io.heightmap` (this layer reads no files) into a
  :class:`HeightMapData`, which :func:`resample_height_map` resamples onto the sample's spline
  grid, with an :class:`InterpolationReport` of what the spline misses.

Conventions (signs, vertex, units): docs/conventions.md, "Curved samples".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from ..errors import SetupError
from ..geometry.shapes import QuadricSurface
from ..geometry.surface import SplineSurface

__all__ = [
    "SHAPES",
    "HEIGHT_MAP_UNITS",
    "SampleShape",
    "InterpolationReport",
    "HeightMapSource",
    "HeightMapData",
    "resample_height_map",
    "spline_report",
]

#: Analytic shapes a ``[sample]`` table may name with ``shape = "…"``.
SHAPES = ("sphere", "paraboloid", "cylinder")
#: Units of height-map files: mm per unit.
HEIGHT_MAP_UNITS = {"mm": 1.0, "um": 1e-3, "m": 1e3}


def _num(key: str, v: Any, *, nonzero: bool = False, allow_inf: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SetupError(f"sample.{key} must be a number, got {v!r}")
    f = float(v)
    if math.isnan(f) or (math.isinf(f) and not allow_inf):
        raise SetupError(f"sample.{key} must be finite, got {v!r}")
    if nonzero and f == 0.0:
        raise SetupError(f"sample.{key} must be non-zero (its sign: + convex as seen from the cameras), got {v!r}")
    return f


@dataclass(frozen=True)
class SampleShape:
    """An analytic sample shape (docs/conventions.md, "Curved samples").

    Attributes
    ----------
    kind : {"sphere", "paraboloid", "cylinder"}
    radius_mm : float or None
        Signed radius of a sphere or cylinder (+: convex as seen from the cameras).
    focal_length_x_mm, focal_length_y_mm : float or None
        Signed focal lengths of a paraboloid, h = x'²/(4 f_x) + y'²/(4 f_y).
    axis_angle_deg : float
        Cylinder: angle of its axis from the sample's x axis, towards +y.
    vertex_xy_mm : (float, float) or None
        The vertex (h = 0, ∇h = 0) in the sample frame; None: the centre of the sample's grid.
    """

    kind: str
    radius_mm: float | None = None
    focal_length_x_mm: float | None = None
    focal_length_y_mm: float | None = None
    axis_angle_deg: float = 0.0
    vertex_xy_mm: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.kind not in SHAPES:
            raise SetupError(f"sample.shape must be one of {list(SHAPES)}, got {self.kind!r}")
        need = {"sphere": ("radius_mm",), "cylinder": ("radius_mm",),
                "paraboloid": ("focal_length_x_mm", "focal_length_y_mm")}[self.kind]
        for name in ("radius_mm", "focal_length_x_mm", "focal_length_y_mm"):
            v = getattr(self, name)
            if name in need:
                if v is None:
                    raise SetupError(f"sample.shape = {self.kind!r} needs sample.{name}")
                object.__setattr__(self, name, _num(name, v, nonzero=True))
            elif v is not None:
                raise SetupError(f"sample.{name} does not apply to sample.shape = {self.kind!r} (it takes {list(need)})")
        object.__setattr__(self, "axis_angle_deg", _num("axis_angle_deg", self.axis_angle_deg))
        if self.axis_angle_deg != 0.0 and self.kind != "cylinder":
            raise SetupError(f"sample.axis_angle_deg applies only to sample.shape = 'cylinder', not {self.kind!r}")
        if self.vertex_xy_mm is not None:
            v = tuple(self.vertex_xy_mm)
            if len(v) != 2:
                raise SetupError(f"sample.vertex_xy_mm must be [x, y], got {self.vertex_xy_mm!r}")
            object.__setattr__(self, "vertex_xy_mm", tuple(_num("vertex_xy_mm", c) for c in v))

    @classmethod
    def sphere(cls, radius_mm: float, vertex_xy_mm=None) -> "SampleShape":
        return cls("sphere", radius_mm=radius_mm, vertex_xy_mm=vertex_xy_mm)

    @classmethod
    def paraboloid(cls, focal_length_x_mm: float, focal_length_y_mm: float, vertex_xy_mm=None) -> "SampleShape":
        return cls("paraboloid", focal_length_x_mm=focal_length_x_mm, focal_length_y_mm=focal_length_y_mm,
                   vertex_xy_mm=vertex_xy_mm)

    @classmethod
    def cylinder(cls, radius_mm: float, axis_angle_deg: float = 0.0, vertex_xy_mm=None) -> "SampleShape":
        return cls("cylinder", radius_mm=radius_mm, axis_angle_deg=axis_angle_deg, vertex_xy_mm=vertex_xy_mm)

    def surface(self, grid_x_mm, grid_y_mm) -> QuadricSurface:
        """The shape over the grid's rectangle, in closed form."""
        try:
            if self.kind == "sphere":
                return QuadricSurface.sphere(grid_x_mm, grid_y_mm, self.radius_mm, self.vertex_xy_mm)
            if self.kind == "cylinder":
                return QuadricSurface.cylinder(grid_x_mm, grid_y_mm, self.radius_mm, self.axis_angle_deg,
                                               self.vertex_xy_mm)
            return QuadricSurface.paraboloid(grid_x_mm, grid_y_mm, self.focal_length_x_mm, self.focal_length_y_mm,
                                             self.vertex_xy_mm)
        except ValueError as e:
            raise SetupError(f"sample.shape = {self.kind!r}: {e}") from None

    def as_dict(self) -> dict[str, Any]:
        """The ``[sample]`` keys of this shape (``shape`` and its parameters)."""
        out: dict[str, Any] = {"shape": self.kind}
        for name in ("radius_mm", "focal_length_x_mm", "focal_length_y_mm"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        if self.kind == "cylinder":
            out["axis_angle_deg"] = self.axis_angle_deg
        if self.vertex_xy_mm is not None:
            out["vertex_xy_mm"] = list(self.vertex_xy_mm)
        return out


@dataclass(frozen=True)
class InterpolationReport:
    """How far the sample's spline is from the shape it was resampled from.

    Attributes
    ----------
    max_error_mm, rms_error_mm : float
        Largest and RMS |spline − truth| over the check points.
    n_points : int
        Number of check points.
    points : str
        Which points: the height map's own grid points inside the sample's grid, or (for an
        analytic shape) the off-node points of a 4× refined grid.
    """

    max_error_mm: float
    rms_error_mm: float
    n_points: int
    points: str = field(default="check points", compare=False)

    def summary(self) -> str:
        return (f"interpolation error max {self.max_error_mm * 1e3:.3g} µm, RMS {self.rms_error_mm * 1e3:.3g} µm "
                f"({self.n_points} {self.points})")

    def as_dict(self) -> dict[str, Any]:
        return {"max_error_mm": self.max_error_mm, "rms_error_mm": self.rms_error_mm, "n_points": self.n_points}


@dataclass(frozen=True)
class HeightMapSource:
    """A height-map file named in a setup (``[sample] height_map = …``; read by pmdsim.io.heightmap).

    Attributes
    ----------
    file : str
        Path as written in the setup (relative paths: to the setup file's directory).
    dataset : str or None
        HDF5 dataset of the heights (default ``"height"``); ignored for NPY and CSV.
    units : {"mm", "um", "m"}
        Unit of the heights in the file.
    grid_units : {"mm", "um", "m"}
        Unit of the grid coordinates in the file (the setup's ``height_map_x_mm`` are mm).
    x_key, y_key : str
        HDF5 datasets of the grid (1-D, strictly increasing; default ``x_mm``, ``y_mm``).
    x_mm, y_mm : tuple of float or None
        The grid given in the setup (NPY and CSV matrices): one value per column / row, or
        [first, last] for an evenly spaced grid.
    max_error_um : float
        Largest interpolation error accepted (``height_map_max_error_um``, default 1 µm): a
        spline grid that misses the map by more is too coarse for its curvature (refused).
    report : InterpolationReport or None
        Set once the map has been resampled onto the sample's spline grid.
    """

    file: str
    dataset: str | None = None
    units: str = "mm"
    grid_units: str = "mm"
    x_key: str = "x_mm"
    y_key: str = "y_mm"
    x_mm: tuple[float, ...] | None = None
    y_mm: tuple[float, ...] | None = None
    max_error_um: float = 1.0
    report: InterpolationReport | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_error_um", _num("height_map_max_error_um", self.max_error_um))
        if not self.max_error_um > 0:
            raise SetupError(f"sample.height_map_max_error_um must be > 0, got {self.max_error_um!r}")
        for name in ("units", "grid_units"):
            if getattr(self, name) not in HEIGHT_MAP_UNITS:
                raise SetupError(f"sample.height_map_{name} must be one of {list(HEIGHT_MAP_UNITS)}, "
                                 f"got {getattr(self, name)!r}")

    def with_report(self, report: InterpolationReport) -> "HeightMapSource":
        return replace(self, report=report)

    def as_dict(self) -> dict[str, Any]:
        """Record written beside the resampled heights (``[sample] height_map_source``): the
        file's keys that differ from the defaults, and the interpolation error."""
        out: dict[str, Any] = {"file": self.file}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name not in ("file", "report") and v != f.default:
                out[f.name] = list(v) if isinstance(v, tuple) else v
        if self.report is not None:
            out.update(self.report.as_dict())
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "HeightMapSource":
        """Inverse of :meth:`as_dict` (the record in a setup that pmdsim wrote)."""
        d = dict(d)
        rep = None
        if "max_error_mm" in d:
            try:
                rep = InterpolationReport(float(d.pop("max_error_mm")), float(d.pop("rms_error_mm")),
                                          int(d.pop("n_points")), "recorded in the setup")
            except (KeyError, TypeError, ValueError):
                raise SetupError("sample.height_map_source: max_error_mm, rms_error_mm and n_points go together "
                                 "(numbers)") from None
        known = {f.name for f in fields(cls)} - {"report"}
        bad = sorted(set(d) - known)
        if bad or "file" not in d:
            raise SetupError(f"sample.height_map_source: expected the keys {sorted(known)} and the error "
                             f"(max_error_mm, rms_error_mm, n_points), got {sorted(d)}")
        for k in ("x_mm", "y_mm"):
            if d.get(k) is not None:
                d[k] = tuple(float(v) for v in d[k])
        return cls(**d, report=rep)


@dataclass(frozen=True, eq=False)
class HeightMapData:
    """Heights on a rectilinear grid, in mm (what a height-map file holds, converted).

    Attributes
    ----------
    x_mm : ndarray (n_x,), y_mm : ndarray (n_y,)
        Strictly increasing grid lines.
    z_mm : ndarray (n_y, n_x)
        ``z_mm[j, i]`` is the height at (x_i, y_j), along the sample's +z.
    source : str
        The file (for messages).
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    source: str = "height map"

    def __post_init__(self) -> None:
        x = np.array(self.x_mm, dtype=float).ravel()
        y = np.array(self.y_mm, dtype=float).ravel()
        z = np.array(self.z_mm, dtype=float)
        src = self.source
        if z.shape != (y.size, x.size):
            raise SetupError(f"height map {src}: heights have shape {z.shape}, expected (len(y), len(x)) = "
                             f"({y.size}, {x.size})")
        for name, g in (("x", x), ("y", y)):
            if g.size < 4:
                raise SetupError(f"height map {src}: {g.size} grid lines in {name}, expected at least 4 "
                                 f"(a cubic spline through them)")
            if not np.all(np.isfinite(g)) or not np.all(np.diff(g) > 0):
                raise SetupError(f"height map {src}: the {name} grid must be finite and strictly increasing")
        bad = ~np.isfinite(z)
        if bad.any():
            j, i = np.argwhere(bad)[0]
            raise SetupError(f"height map {src}: {int(bad.sum())} heights are NaN or infinite (first at "
                             f"x = {x[i]:g} mm, y = {y[j]:g} mm); expected a complete grid of finite heights")
        for a in (x, y, z):
            a.setflags(write=False)
        object.__setattr__(self, "x_mm", x)
        object.__setattr__(self, "y_mm", y)
        object.__setattr__(self, "z_mm", z)


def _not_a_knot(x, y, z):
    """scipy's interpolating bicubic spline (s = 0: knots at x[2:-2], the not-a-knot conditions
    of the paper's eq. 8)."""
    from scipy.interpolate import RectBivariateSpline

    return RectBivariateSpline(y, x, z, kx=3, ky=3, s=0)


def resample_height_map(data: HeightMapData, grid_x_mm, grid_y_mm,
                        max_error_um: float | None = None) -> tuple[np.ndarray, InterpolationReport]:
    """Resample a height map onto the sample's spline grid, with the interpolation error.

    The heights at the spline's nodes come from the not-a-knot bicubic spline through the map
    (scipy ``RectBivariateSpline``, s = 0). The report compares the sample's spline (eq. 8 through
    those nodes) with the map at every grid point of the map inside the sample's grid.

    Raises
    ------
    SetupError
        If the map does not cover the sample's grid, or is coarser than it (its largest spacing
        along x or y exceeds the spline grid's smallest: the spline would interpolate between the
        map's points, not follow them), or if the spline misses the map by more than
        ``max_error_um`` (the spline grid is too coarse for the map's curvature; None: no limit).
    """
    gx = np.asarray(grid_x_mm, dtype=float)
    gy = np.asarray(grid_y_mm, dtype=float)
    src = data.source
    x, y = data.x_mm, data.y_mm
    tol = 1e-9 * max(1.0, float(np.max(np.abs(np.concatenate([gx, gy])))))
    if x[0] > gx[0] + tol or x[-1] < gx[-1] - tol or y[0] > gy[0] + tol or y[-1] < gy[-1] - tol:
        raise SetupError(
            f"height map {src} covers x ∈ [{x[0]:g}, {x[-1]:g}] mm, y ∈ [{y[0]:g}, {y[-1]:g}] mm; expected it to "
            f"cover the sample's grid x ∈ [{gx[0]:g}, {gx[-1]:g}] mm, y ∈ [{gy[0]:g}, {gy[-1]:g}] mm")
    for name, g, d in (("x", gx, x), ("y", gy, y)):
        inside = d[(d >= g[0] - tol) & (d <= g[-1] + tol)]
        step = float(np.max(np.diff(inside))) if inside.size > 1 else math.inf
        if g.size > 1 and step > float(np.min(np.diff(g))) + tol:
            raise SetupError(
                f"height map {src} is too coarse: its {name} spacing is up to {step:g} mm, the sample's spline grid "
                f"(sample.grid_{name}_mm) has {float(np.min(np.diff(g))):g} mm; expected a map at least as fine as "
                f"the spline grid (or a coarser sample.grid_{name}_mm)")
    spl = _not_a_knot(x, y, data.z_mm)
    heights = spl(gy, gx)
    surface = SplineSurface(gx, gy, heights)
    mx = (x >= gx[0] - tol) & (x <= gx[-1] + tol)
    my = (y >= gy[0] - tol) & (y <= gy[-1] + tol)
    X, Y = np.meshgrid(np.clip(x[mx], gx[0], gx[-1]), np.clip(y[my], gy[0], gy[-1]))
    err = surface.height(X, Y) - data.z_mm[np.ix_(my, mx)]
    report = InterpolationReport(float(np.max(np.abs(err))), float(np.sqrt(np.mean(err ** 2))), int(err.size),
                                 f"grid points of {src} inside the sample's grid")
    if max_error_um is not None and report.max_error_mm * 1e3 > max_error_um:
        j, i = np.unravel_index(int(np.argmax(np.abs(err))), err.shape)
        raise SetupError(
            f"the sample's spline grid (spacing {float(np.max(np.diff(gx))):g} × {float(np.max(np.diff(gy))):g} mm) "
            f"is too coarse for height map {src}: it misses the map by up to {report.max_error_mm * 1e3:.3g} µm "
            f"(at x = {X[j, i]:g} mm, y = {Y[j, i]:g} mm), more than sample.height_map_max_error_um = "
            f"{max_error_um:g} µm; expected a finer sample.grid_x_mm/grid_y_mm (or a larger tolerance)")
    return heights, report


def spline_report(shape: SampleShape, grid_x_mm, grid_y_mm) -> tuple[np.ndarray, InterpolationReport]:
    """The shape sampled onto the spline grid, and that spline's error against the closed form.

    The error is measured at the off-node points of the grid refined 4× in both directions
    (every spline patch at 24 interior and edge points). This is what a spline representation
    of the shape would cost; pmdsim's tracer uses the closed form (docs/conventions.md).

    Returns
    -------
    heights_mm : ndarray (n_y, n_x)
    report : InterpolationReport
    """
    gx = np.asarray(grid_x_mm, dtype=float)
    gy = np.asarray(grid_y_mm, dtype=float)
    exact = shape.surface(gx, gy)
    X, Y = np.meshgrid(gx, gy)
    heights = exact.height(X, Y)
    spline = SplineSurface(gx, gy, heights)

    def refine(g):
        f = np.linspace(0.0, 1.0, 5)[:-1]
        return np.concatenate([(g[:-1, None] + f[None, :] * np.diff(g)[:, None]).ravel(), g[-1:]])

    rx, ry = refine(gx), refine(gy)
    RX, RY = np.meshgrid(rx, ry)
    off = ~(np.isin(RX, gx) & np.isin(RY, gy))
    err = (spline.height(RX, RY) - exact.height(RX, RY))[off]
    report = InterpolationReport(float(np.max(np.abs(err))), float(np.sqrt(np.mean(err ** 2))), int(err.size),
                                 "off-node points of the 4× refined grid, against the closed form")
    return heights, report
