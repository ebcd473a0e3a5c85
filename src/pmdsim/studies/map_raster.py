"""Maps of per-pixel values over their points' x, y, drawn as an image at the resolution of the
axes they are shown in (issue 25 item 1: the figures of ``pmdsim evaluate``).

A camera's map (H, W) of values z at points (x, y) (mm, e.g. the sample frame) lies on a
distorted grid in the x–y plane. It used to be drawn as a quadrilateral mesh of up to 250 000
cells (``pcolormesh``), which cost more than the rest of the figure. Here each value is binned
into the cell of a regular raster over the points' bounding box that it falls in, a cell shows
the mean of its values, cells without a value are masked (transparent), and matplotlib colours
the raster with the figure's colour map and norm (``imshow``). The raster has one cell per
device pixel of the axes (so the drawing is a 1:1 copy), computed when the figure is drawn
(:class:`MapImage`: a notebook's inline display and ``savefig`` each get their own resolution),
but never finer than the points: the cell is at least 1.5 times the mean spacing of
neighbouring points, so that every cell inside the map holds a point; a single empty cell
between two filled ones (a crack where the points are sparser than on average) gets their mean.

Two compiled passes over the points, one signature each (their arguments are declared as
read-only arrays of any layout, so that strided views such as ``p[..., 0]`` and contiguous maps
share the one compiled kernel; this module is imported only when a map is drawn).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, types

__all__ = ["MapPoints", "map_points", "MapImage"]

_R2 = types.Array(types.float64, 2, "A", readonly=True)
_W2 = types.Array(types.float64, 2, "C")


@njit(types.UniTuple(types.float64, 8)(_R2, _R2, _R2), cache=True, nogil=True)
def _extent_kernel(x, y, z):  # pragma: no cover - compiled
    """(x_min, x_max, y_min, y_max, z_min, z_max, number of points with finite x, y, z, mean
    distance between neighbouring such points along u and along v, the larger of the two, from
    every 8th row and column). ``a - a == 0`` is ``isfinite(a)``; one test per point."""
    h, w = x.shape
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    z0 = np.inf
    z1 = -np.inf
    n = 0
    for i in range(0, h):
        for j in range(0, w):
            xi = x[i, j]
            yi = y[i, j]
            zi = z[i, j]
            if (xi - xi) + (yi - yi) + (zi - zi) == 0.0:
                n += 1
                x0 = min(x0, xi)
                x1 = max(x1, xi)
                y0 = min(y0, yi)
                y1 = max(y1, yi)
                z0 = min(z0, zi)
                z1 = max(z1, zi)
    su = 0.0
    nu = 0
    sv = 0.0
    nv = 0
    for i in range(0, h - 1, 8):
        for j in range(0, w - 1, 8):
            xi = x[i, j]
            yi = y[i, j]
            if not (xi - xi) + (yi - yi) + (z[i, j] - z[i, j]) == 0.0:
                continue
            dx = x[i, j + 1] - xi
            dy = y[i, j + 1] - yi
            if (dx - dx) + (dy - dy) + (z[i, j + 1] - z[i, j + 1]) == 0.0:
                su += np.sqrt(dx * dx + dy * dy)
                nu += 1
            dx = x[i + 1, j] - xi
            dy = y[i + 1, j] - yi
            if (dx - dx) + (dy - dy) + (z[i + 1, j] - z[i + 1, j]) == 0.0:
                sv += np.sqrt(dx * dx + dy * dy)
                nv += 1
    if nu + nv == 0:  # no neighbouring pairs on the sampled rows and columns: every row and column
        for i in range(0, h):
            for j in range(0, w):
                xi = x[i, j]
                yi = y[i, j]
                if not (xi - xi) + (yi - yi) + (z[i, j] - z[i, j]) == 0.0:
                    continue
                if j + 1 < w:
                    dx = x[i, j + 1] - xi
                    dy = y[i, j + 1] - yi
                    if (dx - dx) + (dy - dy) + (z[i, j + 1] - z[i, j + 1]) == 0.0:
                        su += np.sqrt(dx * dx + dy * dy)
                        nu += 1
                if i + 1 < h:
                    dx = x[i + 1, j] - xi
                    dy = y[i + 1, j] - yi
                    if (dx - dx) + (dy - dy) + (z[i + 1, j] - z[i + 1, j]) == 0.0:
                        sv += np.sqrt(dx * dx + dy * dy)
                        nv += 1
    spacing = max(su / max(nu, 1), sv / max(nv, 1))
    return x0, x1, y0, y1, z0, z1, float(n), spacing


@njit(types.void(_R2, _R2, _R2, types.int64, types.float64, types.float64, types.float64, types.float64, _W2, _W2),
      cache=True, nogil=True)
def _bin_kernel(x, y, z, stride, x0, y0, inv_dx, inv_dy, total, count):  # pragma: no cover - compiled
    """Sum and count of the finite values of every ``stride``-th row and column per raster
    cell; cell (r, c) holds the points with x0 + c/inv_dx <= x < x0 + (c+1)/inv_dx (the last
    column closed; points outside clamped to the border cells) and likewise y."""
    h, w = x.shape
    ny, nx = total.shape
    for i in range(0, h, stride):
        for j in range(0, w, stride):
            xi = x[i, j]
            yi = y[i, j]
            zi = z[i, j]
            if (xi - xi) + (yi - yi) + (zi - zi) == 0.0:
                c = min(max(int((xi - x0) * inv_dx), 0), nx - 1)
                r = min(max(int((yi - y0) * inv_dy), 0), ny - 1)
                total[r, c] += zi
                count[r, c] += 1.0


def _readonly2(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


@dataclass(frozen=True)
class MapPoints:
    """A map's values over its points, ready to be binned.

    Attributes
    ----------
    x_mm, y_mm, z : ndarray, (H, W)
        Read-only views of the points' coordinates and the values (NaN: no value).
    extent_mm : tuple of float
        (x_min, x_max, y_min, y_max) of the points with finite x, y, z.
    z_range : tuple of float
        (min, max) of the finite values.
    n : int
        Number of points with finite x, y, z.
    spacing_mm : float
        Mean distance between neighbouring points (the larger of the u and v directions).
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    z: np.ndarray
    extent_mm: tuple
    z_range: tuple
    n: int
    spacing_mm: float

    def raster(self, nx: int, ny: int) -> np.ma.MaskedArray:
        """The mean value per cell of an (ny, nx) raster over :attr:`extent_mm`, row 0 at
        y_min (``imshow(..., origin="lower")``), masked where no point falls; ``nx`` and ``ny``
        are reduced so that a cell is at least 1.5 × :attr:`spacing_mm` wide and high. Where a
        cell is wider than that, every s-th row and column of points is binned (s the largest
        stride that keeps 1.5 strided spacings per cell)."""
        x0, x1, y0, y1 = self.extent_mm
        wx, wy = max(x1 - x0, 1e-12), max(y1 - y0, 1e-12)
        cell = 1.5 * self.spacing_mm
        if cell > 0:
            nx = min(nx, max(1, int(wx / cell)))
            ny = min(ny, max(1, int(wy / cell)))
        nx, ny = max(1, int(nx)), max(1, int(ny))
        # every stride-th point when the cells hold many: still >= 1.5 point spacings per cell
        stride = max(1, int(min(wx / nx, wy / ny) / cell)) if cell > 0 else 1
        total = np.zeros((ny, nx))
        count = np.zeros((ny, nx))
        _bin_kernel(self.x_mm, self.y_mm, self.z, stride, x0, y0, nx / wx, ny / wy, total, count)
        _fill_cracks(total, count)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = total / count
        return np.ma.masked_array(mean, mask=count == 0)


def _fill_cracks(total: np.ndarray, count: np.ndarray) -> None:
    """An empty cell between two filled cells (left and right, else below and above) takes
    their mean (in place: sum and count of the two neighbours' means)."""
    filled = count > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(filled, total / np.maximum(count, 1), 0.0)
    for axis in (1, 0):
        lo = [slice(None)] * 2
        mid = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], mid[axis], hi[axis] = slice(0, -2), slice(1, -1), slice(2, None)
        lo, mid, hi = tuple(lo), tuple(mid), tuple(hi)
        crack = ~filled[mid] & filled[lo] & filled[hi]
        if crack.any():
            t = total[mid]
            c = count[mid]
            t[crack] = 0.5 * (mean[lo] + mean[hi])[crack]
            c[crack] = 1.0
            filled = count > 0


def map_points(x_mm, y_mm, z) -> MapPoints:
    """:class:`MapPoints` of (H, W) maps (any layout; not copied)."""
    x, y, zz = _readonly2(x_mm), _readonly2(y_mm), _readonly2(z)
    if x.ndim != 2 or x.shape != y.shape or x.shape != zz.shape:
        raise ValueError(f"x, y and z must be (H, W) maps of one shape, got {x.shape}, {y.shape}, {zz.shape}")
    x0, x1, y0, y1, z0, z1, n, spacing = _extent_kernel(x, y, zz)
    return MapPoints(x, y, zz, (x0, x1, y0, y1), (z0, z1), int(n), float(spacing))


def _map_image_class() -> type:
    """:class:`MapImage`, defined on first use: it subclasses matplotlib's ``AxesImage``, and
    ``pmdsim evaluate`` (which bins maps here for its Pillow-drawn PNGs) does not import
    matplotlib's image and figure modules (start-up, docs/benchmarks.md)."""
    from matplotlib.image import AxesImage

    class MapImage(AxesImage):
        """An image of :class:`MapPoints` binned, when drawn, at one cell per device pixel of its
        axes (see the module docstring); its norm and colour map are an ``imshow``'s."""

        def __init__(self, ax, points: MapPoints, **kwargs):
            super().__init__(ax, origin="lower", interpolation="nearest", extent=points.extent_mm, **kwargs)
            self._points = points
            self._shape = None
            self.set_data(np.ma.masked_all((1, 1)))

        def _update_raster(self) -> None:
            bb = self.axes.bbox
            shape = (max(1, int(round(bb.height))), max(1, int(round(bb.width))))
            if shape != self._shape:
                self._shape = shape
                self.set_data(self._points.raster(shape[1], shape[0]))

        def draw(self, renderer):
            self._update_raster()
            super().draw(renderer)

    MapImage.__qualname__ = "MapImage"
    return MapImage


def __getattr__(name: str):
    if name == "MapImage":
        cls = globals()["MapImage"] = _map_image_class()
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
