"""Maps drawn over their points (issue 23 item 5, issue 25 item 1): masked pixels stay masked
cells (no scatter fallback) of a raster binned at the axes' resolution, signed maps use a
diverging colour map centred on zero, every colour bar names its unit."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.collections import PathCollection

from pmdsim.studies.figures import height_grid_figure, height_map_figure
from pmdsim.studies.map_raster import MapImage


def _map(H=40, W=60):
    v, u = np.mgrid[0:H, 0:W].astype(float)
    x, y = 0.5 * u - 15 + 0.01 * v, 0.5 * v - 10
    z = 3.0 * (x / 15) - 1.0  # signed, both signs
    gap = (u - 30) ** 2 + (v - 20) ** 2 < 36  # a hole without points (NaN x, y, z)
    edge = u < 3  # pixels with points but no value
    x[gap], y[gap], z[gap] = np.nan, np.nan, np.nan
    z[edge] = np.nan
    return x, y, z, gap | edge


def _drawn(fig):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig).draw()
    (im,) = [a for a in fig.axes[0].get_images() if isinstance(a, MapImage)]
    return im


def test_masked_pixels_are_masked_cells_not_a_scatter():
    x, y, z, masked = _map()
    fig = height_map_figure(x, y, z, title="t", label="height error (µm)")
    ax = fig.axes[0]
    assert not [c for c in ax.collections if isinstance(c, PathCollection)]  # no scatter
    im = _drawn(fig)
    arr = im.get_array()
    # the drawn raster: per cell the mean of the values whose points fall in it, masked where
    # none does — the same binning by numpy's histogram2d (bin edges over the points' extent)
    ok = ~masked
    ny, nx = arr.shape
    x0, x1, y0, y1 = im.get_extent()
    assert (x0, x1, y0, y1) == (x[ok].min(), x[ok].max(), y[ok].min(), y[ok].max())
    ex, ey = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    s, _, _ = np.histogram2d(y[ok], x[ok], bins=(ey, ex), weights=z[ok])
    n, _, _ = np.histogram2d(y[ok], x[ok], bins=(ey, ex))
    crack = np.ma.getmaskarray(arr) != (n == 0)  # cells bridged between two filled ones
    assert crack.sum() <= 0.02 * arr.size
    np.testing.assert_allclose(np.asarray(arr)[n > 0], (s / np.maximum(n, 1))[n > 0], rtol=0, atol=1e-12)
    # the hole (no points, 12 px across) stays masked: the cell at its centre is empty
    cx, cy = 0.5 * 30 - 15 + 0.01 * 20, 0.5 * 20 - 10
    assert np.ma.getmaskarray(arr)[int((cy - y0) / (y1 - y0) * ny), int((cx - x0) / (x1 - x0) * nx)]
    # never finer than the points: cells at least 1.5 point spacings (0.5 px) wide
    assert (x1 - x0) / nx >= 1.5 * 0.5 * 0.99
    # centred on zero: symmetric limits covering every value, diverging map
    assert im.norm.vmin == pytest.approx(-im.norm.vmax) and im.norm.vmax >= np.nanmax(np.abs(z)) - 1e-12
    assert im.get_cmap().name == "RdBu_r"
    assert fig.axes[1].get_ylabel() == "height error (µm)"  # the colour bar's label, with its unit


def test_unsigned_maps_and_units_required():
    x, y, z, _ = _map()
    fig = height_map_figure(x, y, np.abs(z), title="t", label="modulation (1)", signed=False)
    im = _drawn(fig)
    assert im.get_cmap().name == "viridis"
    assert (im.norm.vmin, im.norm.vmax) == (np.nanmin(np.abs(z)), np.nanmax(np.abs(z)))
    with pytest.raises(ValueError, match="unit"):
        height_grid_figure([[(x, y, z, "a")]], suptitle="s", label="height error")
