"""Figures drawn on the pixel grid (issue 23 item 5): masked pixels stay masked cells of a
quadrilateral mesh (no scatter fallback), signed maps use a diverging colour map centred on zero,
every colour bar names its unit."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.collections import PathCollection, QuadMesh

from pmdsim.studies.figures import height_grid_figure, height_map_figure


def _map(H=40, W=60):
    v, u = np.mgrid[0:H, 0:W].astype(float)
    x, y = 0.5 * u - 15 + 0.01 * v, 0.5 * v - 10
    z = 3.0 * (x / 15) - 1.0  # signed, both signs
    gap = (u - 30) ** 2 + (v - 20) ** 2 < 36  # a hole without points (NaN x, y, z)
    edge = u < 3  # pixels with points but no value
    x[gap], y[gap], z[gap] = np.nan, np.nan, np.nan
    z[edge] = np.nan
    return x, y, z, gap | edge


def test_masked_pixels_are_masked_cells_not_a_scatter():
    x, y, z, masked = _map()
    fig = height_map_figure(x, y, z, title="t", label="height error (µm)")
    ax = fig.axes[0]
    assert not [c for c in ax.collections if isinstance(c, PathCollection)]  # no scatter
    (mesh,) = [c for c in ax.collections if isinstance(c, QuadMesh)]
    arr = mesh.get_array()
    assert np.array_equal(np.ma.getmaskarray(arr).reshape(z.shape), masked)  # exactly the pixels without a value
    np.testing.assert_array_equal(np.asarray(arr).reshape(z.shape)[~masked], z[~masked])
    # centred on zero: symmetric limits, diverging map
    assert mesh.norm.vmin == pytest.approx(-mesh.norm.vmax) and mesh.norm.vmax >= np.nanmax(np.abs(z)) - 1e-12
    assert mesh.get_cmap().name == "RdBu_r"
    assert fig.axes[1].get_ylabel() == "height error (µm)"  # the colour bar's label, with its unit
    # the drawn cells are where the points are: centres of the mesh at the valid pixels' x, y
    coords = mesh.get_coordinates()  # (H + 1, W + 1, 2) cell corners
    centre = coords[:-1, :-1].reshape(-1, 2) + coords[1:, 1:].reshape(-1, 2)
    ok = (~masked).ravel()
    np.testing.assert_allclose(centre[ok] / 2, np.stack([x.ravel()[ok], y.ravel()[ok]], -1), atol=0.02)


def test_unsigned_maps_and_units_required():
    x, y, z, _ = _map()
    fig = height_map_figure(x, y, np.abs(z), title="t", label="modulation (1)", signed=False)
    (mesh,) = [c for c in fig.axes[0].collections if isinstance(c, QuadMesh)]
    assert mesh.get_cmap().name == "viridis"
    with pytest.raises(ValueError, match="unit"):
        height_grid_figure([[(x, y, z, "a")]], suptitle="s", label="height error")
