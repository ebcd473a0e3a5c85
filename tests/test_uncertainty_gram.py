"""Σ_k of bilinearly interpolated squares through per-cell Gram matrices
(:mod:`pmdsim.evaluation.uncertainty_gram`) against numpy's direct interpolation of every axis,
and, where nodes are NaN, against the per-axis kernel of
:mod:`pmdsim.evaluation.uncertainty_calibration`."""

from __future__ import annotations

import numpy as np

from pmdsim.evaluation.uncertainty_calibration import _interpolated_squares
from pmdsim.evaluation.uncertainty_gram import interpolated_squares


def _numpy_reference(stack, ov, ou, s, H, W):
    """Σ_k of the bilinear interpolation (linear extrapolation from the outer cells) in numpy."""
    K, h, w, c = stack.shape
    fv, fu = (np.arange(H) - ov) / s, (np.arange(W) - ou) / s
    i0 = np.clip(np.floor(fv).astype(int), 0, h - 2)
    j0 = np.clip(np.floor(fu).astype(int), 0, w - 2)
    ay, ax = (fv - i0)[:, None, None], (fu - j0)[None, :, None]
    out = np.zeros((H, W, c))
    for k in range(K):
        q = stack[k]
        val = ((1 - ay) * (1 - ax) * q[i0][:, j0] + (1 - ay) * ax * q[i0][:, j0 + 1]
               + ay * (1 - ax) * q[i0 + 1][:, j0] + ay * ax * q[i0 + 1][:, j0 + 1])
        out += val ** 2
    return out


def test_gram_squares_equal_numpy_interpolation():
    rng = np.random.default_rng(3)
    stack = rng.normal(size=(7, 9, 12, 3)) + np.linspace(0, 3, 12)[:, None]
    for ov, ou, s, H, W in ((2, 1, 4, 37, 50), (0, 0, 3, 27, 36), (3, 3, 8, 70, 96)):
        got = interpolated_squares(stack, ov, ou, s, H, W)
        ref = _numpy_reference(stack, ov, ou, s, H, W)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14 * ref.max())


def test_nan_nodes_take_the_per_axis_path():
    """A NaN block larger than the fill reaches: its cells renormalise per axis, as before."""
    rng = np.random.default_rng(4)
    stack = rng.normal(size=(5, 30, 40, 3))
    stack[:, 10:22, 15:27, :] = np.nan  # 12 × 12: 4 fill passes leave its 4 × 4 core NaN
    stack[2, 0, 0, :] = np.nan  # one axis's corner node
    got = interpolated_squares(stack, 2, 2, 4, 120, 160)
    ref = _interpolated_squares(stack, 2, 2, 4, 120, 160)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    m = np.isfinite(ref)
    np.testing.assert_allclose(got[m], ref[m], rtol=1e-12, atol=1e-14 * ref[m].max())


def test_std_maps_are_the_square_roots_of_the_gram_squares():
    """σ maps straight from the Gram matrices: numpy's square roots of interpolated_squares
    (heights ×1e3, slopes ×1e6, NaN off S), bit for bit — also at the NaN cells' per-axis path."""
    from pmdsim.evaluation.uncertainty_gram import interpolated_std_maps

    rng = np.random.default_rng(5)
    stack = rng.normal(size=(6, 30, 40, 3))
    stack[:, 10:22, 15:27, :] = np.nan
    S = rng.random((120, 160)) > 0.2
    var = interpolated_squares(stack, 2, 1, 4, 120, 160)
    var[~S] = np.nan
    h, g = interpolated_std_maps(stack, 2, 1, 4, S)
    np.testing.assert_array_equal(h, np.sqrt(var[..., 0]) * 1e3)
    np.testing.assert_array_equal(g, np.sqrt(var[..., 1:]) * 1e6)
