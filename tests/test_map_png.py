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


@pytest.mark.parametrize("signed", [True, False])
def test_pillow_map_png_shows_the_colour_map_of_the_values(tmp_path, signed):
    """The evaluation's figures (Pillow, :mod:`pmdsim.studies.map_png`): size, colours at the
    points equal matplotlib's colour map of the values, the hole white, the colour bar running
    from the lowest to the highest colour."""
    from pmdsim.studies.figures import write_height_map_png

    x, y, z, hole = _field()
    path = tmp_path / "map.png"
    (lay,) = write_height_map_png(x, y, z, title="t: a map", label="height (µm)", path=path, signed=signed)
    img = Image.open(path)
    assert img.format == "PNG" and img.size == (768, 576)
    png = np.asarray(img.convert("RGB")).astype(int)
    finite = z[~hole]
    if signed:
        norm, cmap = CenteredNorm(vcenter=0.0, halfrange=np.abs(finite).max()), colormaps["RdBu_r"]
        assert (lay.vmin, lay.vmax) == (-np.abs(finite).max(), np.abs(finite).max())
    else:
        norm, cmap = Normalize(finite.min(), finite.max()), colormaps["viridis"]
        assert (lay.vmin, lay.vmax) == (finite.min(), finite.max())
    assert lay.cmap == cmap.name
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(40):
        v, u = rng.integers(15, 285), rng.integers(15, 385)
        if (u - 250) ** 2 + (v - 150) ** 2 < 50 ** 2:
            continue
        expect = np.round(np.asarray(cmap(norm(z[v, u]))[:3]) * 255).astype(int)
        got = png[lay.pixel_of(x[v, u], y[v, u])]
        assert np.abs(got - expect).max() <= 6, (v, u, got, expect)
        checked += 1
    assert checked >= 20
    assert tuple(png[lay.pixel_of(x[150, 250], y[150, 250])]) == (255, 255, 255)
    # the colour bar: right of the axes, its column of colours from cmap(1) at the top to cmap(0)
    l, t, r, b = lay.box_px
    row = png[(t + b) // 2, r:]
    bar_cols = [c for c in range(row.shape[0]) if np.abs(row[c] - np.round(np.asarray(cmap(0.5)[:3]) * 255)).max() <= 6]
    assert bar_cols, "no colour bar right of the map"
    col = r + bar_cols[len(bar_cols) // 2]
    column = png[:, col]
    inside = np.flatnonzero(np.abs(column - 255).max(axis=1) > 0)
    top, bottom = column[inside[1]], column[inside[-2]]  # inside the bar's frame
    np.testing.assert_allclose(top, np.round(np.asarray(cmap(1.0)[:3]) * 255), atol=8)
    np.testing.assert_allclose(bottom, np.round(np.asarray(cmap(0.0)[:3]) * 255), atol=8)


def test_pillow_slope_error_png_has_one_panel_per_camera_and_component(tmp_path):
    from types import SimpleNamespace

    from pmdsim.studies.surface_figures import write_slope_error_png

    x, y, z, _ = _field(60, 80)
    p = np.stack([x, y, np.zeros_like(x)], -1)
    res = np.stack([z, -z], -1) * 1e-3
    fit = SimpleNamespace(focal_length_x_mm=-6.5e4, focal_length_y_mm=-1.2e5, slope_residual_rms_mrad=0.6)
    lays = write_slope_error_png({"left": (p, res), "right": (p, res)}, fit, path=tmp_path / "s.png")
    assert Image.open(tmp_path / "s.png").size == (1100, 924)  # 10 × 8.4 in at 110 dpi, as before
    assert len(lays) == 4 and all(lay is not None for lay in lays)
    assert lays[0].vmax == pytest.approx(np.nanmax(np.abs(z)))  # mrad: res × 1e3
