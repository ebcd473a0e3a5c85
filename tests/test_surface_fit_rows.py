"""The joint surface fit's gathers and scatters (issue 25 item 1) against numpy's boolean-mask
indexing and the slope expression they replace: bit for bit, with NaN normals, unreconstructed
pixels and a zero n_z."""

from __future__ import annotations

import numpy as np

from pmdsim.evaluation.surface_fit_rows import gather_rows, gather_sigma, scatter_residuals, slopes_and_mask


def test_rows_equal_numpy_masks_bit_for_bit():
    rng = np.random.default_rng(2)
    H, W = 23, 31
    n = rng.normal(0, 0.05, (H, W, 3))
    n[..., 2] = -1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[3, 4] = np.nan
    n[5, 6, 2] = 0.0  # slopes ±inf: not fitted
    rec = rng.random((H, W)) > 0.2
    p = rng.normal(0, 50, (H, W, 3))
    sig = rng.random((H, W, 2)) * 1e-6
    g, ok, m = slopes_and_mask(n, rec)
    with np.errstate(invalid="ignore", divide="ignore"):
        g_ref = -n[..., :2] / n[..., 2:3]
    ok_ref = rec & np.isfinite(g_ref[..., 0]) & np.isfinite(g_ref[..., 1])
    np.testing.assert_array_equal(g, g_ref)
    np.testing.assert_array_equal(ok, ok_ref)
    assert m == ok_ref.sum() and not ok[3, 4] and not ok[5, 6]
    # two cameras into one set of rows
    xy, gxy, sg = np.empty((2, 2 * m)), np.empty((2, 2 * m)), np.empty((2 * m, 2))
    j = gather_rows(p, g, ok, 0, xy, gxy)
    assert gather_rows(p[::-1].copy(), g[::-1].copy(), ok[::-1].copy(), j, xy, gxy) == 2 * m
    assert gather_sigma(sig[::-1].copy(), ok[::-1].copy(), gather_sigma(sig, ok, 0, sg), sg) == 2 * m
    np.testing.assert_array_equal(xy[:, :m], p[..., :2][ok].T)
    np.testing.assert_array_equal(xy[:, m:], p[::-1][..., :2][ok[::-1]].T)
    np.testing.assert_array_equal(gxy[:, :m], g[ok].T)
    np.testing.assert_array_equal(sg, np.concatenate([sig[ok], sig[::-1][ok[::-1]]]))
    res = np.asfortranarray(rng.normal(0, 1e-3, (2 * m, 2)))  # F order, as the fit's residual rows: one signature
    out, k = scatter_residuals(res, ok, m)
    ref = np.full((H, W, 2), np.nan)
    ref[ok] = res[m:]
    assert k == 2 * m
    np.testing.assert_array_equal(out, ref)


def test_slopes_and_rows_equal_numpy_masks_bit_for_bit():
    """The fused pass: the slopes and mask of :func:`slopes_and_mask` and the rows of numpy's
    boolean-mask indexing, two cameras into one set of rows; rows too short are refused."""
    import pytest

    from pmdsim.evaluation.surface_fit_rows import slopes_and_rows

    rng = np.random.default_rng(4)
    H, W = 17, 29
    n = rng.normal(0, 0.05, (H, W, 3))
    n[..., 2] = -1.0
    n[2, 3] = np.nan
    n[4, 5, 2] = 0.0
    rec = rng.random((H, W)) > 0.2
    p = rng.normal(0, 50, (H, W, 3))
    rows = np.empty((4, 2 * H * W))
    ext = np.array([np.inf, -np.inf, np.inf, -np.inf, 0.0])
    g, ok, j = slopes_and_rows(n, rec, p, 0, tuple(rows), ext)
    g2, ok2, k = slopes_and_rows(n[::-1], rec[::-1], p[::-1], j, tuple(rows), ext)
    # the extents of the fitted points (both cameras): numpy's min and max
    pts = np.concatenate([p[ok][:, :2], p[::-1][ok2][:, :2]])
    gs = np.concatenate([g[ok], g2[ok2]])
    assert tuple(ext) == (pts[:, 0].min(), pts[:, 0].max(), pts[:, 1].min(), pts[:, 1].max(), np.abs(gs).max())
    g_ref, ok_ref, m = slopes_and_mask(n, rec)
    np.testing.assert_array_equal(g, g_ref)
    np.testing.assert_array_equal(ok, ok_ref)
    assert j == m and k == 2 * m and not ok[2, 3] and not ok[4, 5]
    ref = np.concatenate([np.concatenate([p[..., :2], g_ref], -1)[ok_ref],
                          np.concatenate([p[::-1][..., :2], g_ref[::-1]], -1)[ok_ref[::-1]]]).T
    np.testing.assert_array_equal(rows[:, :k], ref)
    with pytest.raises(ValueError, match="too short"):
        slopes_and_rows(n, rec, p, H * W + 1, tuple(rows))
