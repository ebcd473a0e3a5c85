"""The glass stage's patch of each foot point (``glass_rows._patches_at`` with its one-patch
shortcut ``_in_patch``) against the grid intervals written here with numpy."""

import numpy as np
import pytest

from pmdsim.geometry.kernel_args import readonly
from pmdsim.simulation.glass_rows import _in_patch, _patches_at
from pmdsim.simulation.trace_rows import _BLK, _NF, _NI, _PID, _UX, _UY


def _interval_numpy(grid, v):
    """The spline's interval of v (edge intervals extrapolate; v = grid[1] belongs to the first,
    an inner grid line to the interval above it), with numpy."""
    n = grid.shape[0]
    return np.where(v <= grid[1], 0, np.where(v >= grid[n - 2], n - 2,
                                              np.searchsorted(grid, v, side="right") - 1))


def _block(ux, uy):
    S = np.full(_NF * _BLK, np.nan)
    S[_UX * _BLK:_UX * _BLK + ux.size] = ux
    S[_UY * _BLK:_UY * _BLK + uy.size] = uy
    return S


@pytest.mark.parametrize("nx, ny", [(3, 3), (2, 4), (9, 7), (14, 9)])  # counted (small grids) and bisected
def test_patches_at_and_the_one_patch_shortcut_agree_with_numpy_intervals(nx, ny):
    rng = np.random.default_rng(nx * 100 + ny)
    gx = readonly(np.linspace(0.0, 708.0, nx))  # read-only, as a spline hands its grid over: one signature
    gy = readonly(np.linspace(-5.0, 398.0, ny))
    nx1 = nx - 1
    n_one = 0
    for trial in range(400):
        n = int(rng.integers(1, _BLK + 1))
        kind = trial % 4
        if kind == 0:  # inside one cell (or beyond the grid on its outer side)
            i, j = rng.integers(0, nx - 1), rng.integers(0, ny - 1)
            ux = rng.uniform(gx[i] - (50.0 if i == 0 else 0.0), gx[i + 1] + (50.0 if i == nx - 2 else 0.0), n)
            uy = rng.uniform(gy[j] - (50.0 if j == 0 else 0.0), gy[j + 1] + (50.0 if j == ny - 2 else 0.0), n)
        else:  # anywhere, with points on grid lines and NaN
            ux = rng.uniform(gx[0] - 20.0, gx[-1] + 20.0, n)
            uy = rng.uniform(gy[0] - 20.0, gy[-1] + 20.0, n)
            on_line = rng.random(n) < (0.3 if kind == 2 else 0.0)
            ux[on_line] = rng.choice(gx, on_line.sum())
            uy[on_line & (rng.random(n) < 0.5)] = gy[1]
            if kind == 3:
                ux[rng.integers(0, n)] = np.nan
        S = _block(ux, uy)
        P = np.zeros(_NI * _BLK, dtype=np.int64)
        _patches_at(n, gx, gy, S, P)
        ix = _interval_numpy(gx, ux)
        iy = _interval_numpy(gy, uy)
        finite = np.isfinite(ux) & np.isfinite(uy)
        expected = (iy * nx1 + ix) * 16
        np.testing.assert_array_equal(P[_PID * _BLK:_PID * _BLK + n][finite], expected[finite])
        i0, j0 = _interval_numpy(gx, ux[:1])[0], _interval_numpy(gy, uy[:1])[0]
        one = _in_patch(n, gx, gy, i0, j0, S)
        if one:  # the shortcut is taken only where every pixel is on the first one's patch
            n_one += 1
            assert finite.all() and (ix == i0).all() and (iy == j0).all()
        if kind == 0 and not np.isin(ux, gx).any() and not np.isin(uy, gy).any():
            assert one  # ... and is taken in a cell
    assert n_one >= 100
