"""The map figures as PNG files (issue 25 item 1): what the file shows, read back with Pillow and
compared with matplotlib's colour map of the values (``matplotlib.colormaps``, independent of the
binning that draws the map)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.colors import CenteredNorm, Normalize
from PIL import Image

from pmdsim.studies.figures import height_map_figure


def _field(H=300, W=400):
    """A slightly rotated, sheared pixel grid (points 0.25 mm apart), a smooth signed field and
    a hole without values."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    x = 0.25 * u + 0.02 * v + 10.0
    y = 0.25 * v - 0.03 * u - 5.0
    z = 40.0 * np.sin(x / 40.0) + 0.3 * (y + 5.0)
    hole = (u - 250) ** 2 + (v - 150) ** 2 < 40 ** 2
    z[hole] = np.nan
    return x, y, z, hole


def _png_at(png, fig, x, y):
    """RGBA of the PNG at data point (x, y) of the first axes (display y upwards, PNG rows down)."""
    X, Y = fig.axes[0].transData.transform(np.array([x, y], dtype=float))
    return png[png.shape[0] - 1 - int(Y), int(X)].astype(int)


@pytest.mark.parametrize("signed", [True, False])
def test_png_shows_the_colour_map_of_the_values(tmp_path, signed):
    x, y, z, hole = _field()
    path = tmp_path / "map.png"
    fig = height_map_figure(x, y, z, title="t: a map", label="height (µm)", path=path, signed=signed)
    img = Image.open(path)
    assert img.format == "PNG" and img.size == (768, 576)  # 6.4 × 4.8 in at 120 dpi
    png = np.asarray(img.convert("RGBA"))
    finite = z[~hole]
    if signed:
        norm, cmap = CenteredNorm(vcenter=0.0, halfrange=np.abs(finite).max()), colormaps["RdBu_r"]
    else:
        norm, cmap = Normalize(finite.min(), finite.max()), colormaps["viridis"]
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(40):  # points well inside the map, away from the hole
        v, u = rng.integers(15, 285), rng.integers(15, 385)
        if (u - 250) ** 2 + (v - 150) ** 2 < 50 ** 2:
            continue
        expect = np.round(np.asarray(cmap(norm(z[v, u]))) * 255).astype(int)
        got = _png_at(png, fig, x[v, u], y[v, u])
        # one cell (≈ 0.6 mm) of the gradient and the 8-bit rounding
        assert np.abs(got - expect).max() <= 6, (v, u, got, expect)
        checked += 1
    assert checked >= 20
    # the hole's centre (no values): the axes' background, white
    assert tuple(_png_at(png, fig, x[150, 250], y[150, 250])) == (255, 255, 255, 255)


def test_no_data_map_is_still_a_figure(tmp_path):
    x, y, z, _ = _field(20, 30)
    path = tmp_path / "empty.png"
    fig = height_map_figure(x, y, np.full_like(z, np.nan), title="empty", label="height (µm)", path=path)
    assert fig.axes[0].get_title().endswith("(no data)")
    assert Image.open(path).size == (768, 576)
