"""The streamed robust paraboloid fit (issue 25, item 1) against an independent computation:
numpy's lstsq on the explicit (2M, 5) design, reweighted with Tukey's bisquare from numpy's
medians — the algorithm as documented in :mod:`pmdsim.evaluation.surface_fit`."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation import surface_fit as sf
from pmdsim.evaluation.surface_fit import fit_paraboloid_slopes
from pmdsim.geometry.kernel_args import readonly


def _lstsq_irls(x, y, gx, gy, robust=True, max_iter=100):
    """Reference: lstsq on the reweighted design, numpy medians (centred coordinates)."""
    xc, yc = x.mean(), y.mean()
    X, Y = x - xc, y - yc
    z0, one = np.zeros_like(X), np.ones_like(X)
    A = np.concatenate([np.stack([2 * X, Y, z0, one, z0], -1), np.stack([z0, X, 2 * Y, z0, one], -1)])
    rhs = np.concatenate([gx, gy])
    coef = np.linalg.lstsq(A, rhs, rcond=None)[0]
    n_iter = 0
    if robust:
        for n_iter in range(1, max_iter + 1):
            r = rhs - A @ coef
            s = np.median(np.abs(r - np.median(r))) / 0.6745
            if not s > 0:
                break
            u = r / (4.685 * s)
            sw = np.sqrt(np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0))
            new = np.linalg.lstsq(A * sw[:, None], rhs * sw, rcond=None)[0]
            done = np.max(np.abs(new - coef)) <= 1e-12 * max(1.0, np.max(np.abs(coef)))
            coef = new
            if done:
                break
    a, b, c, d, e = coef
    return np.array([a, b, c, d - 2 * a * xc - b * yc, e - b * xc - 2 * c * yc]), n_iter


def _slopes(m, seed, outliers=0.05):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-150, 150, m) + 40
    y = rng.uniform(-100, 100, m) - 25
    a, b, c, d, e = 2e-6, -3e-7, 1.5e-6, 1e-3, -2e-3
    gx = 2 * a * x + b * y + d + rng.normal(0, 2e-5, m)
    gy = b * x + 2 * c * y + e + rng.normal(0, 2e-5, m)
    bad = rng.random(m) < outliers
    gx[bad] += rng.normal(0, 1e-3, bad.sum())  # edge defects / outliers the weights must remove
    gy[bad] -= 5e-4
    # read-only, as fit_paraboloid_slopes hands them to the kernels: one compiled signature each
    return readonly(x), readonly(y), readonly(gx), readonly(gy)


@pytest.mark.parametrize("m, robust", [(5000, True), (5000, False), (120_000, True)])
def test_streamed_fit_matches_lstsq_irls(m, robust):
    """Coefficients identical to 1e-9 relative, the robust reweighting included (120 000 points:
    sampled brackets and histogram selection; 5000: one-pass brackets)."""
    x, y, gx, gy = _slopes(m, seed=m)
    ref, n_iter = _lstsq_irls(x, y, gx, gy, robust=robust)
    assert not robust or n_iter > 3  # the reweighting really iterates
    fit = fit_paraboloid_slopes(np.stack([x, y, np.zeros(m)], -1), np.stack([gx, gy], -1), np.ones(m, bool),
                                camera_z_mm=1.0, robust=robust)
    np.testing.assert_allclose(fit.coefficients, ref, rtol=1e-9, atol=0)
    xc, yc = x.mean(), y.mean()
    res = np.stack([gx - (2 * ref[0] * x + ref[1] * y + ref[3]), gy - (ref[1] * x + 2 * ref[2] * y + ref[4])], -1)
    np.testing.assert_allclose(fit.residual_slopes, res, rtol=0, atol=1e-12)
    assert fit.slope_residual_rms_mrad == pytest.approx(np.sqrt(np.mean(res**2)) * 1e3, rel=1e-9)
    assert fit.n_points == m and (xc, yc) != (0.0, 0.0)


def test_masked_points_are_ignored():
    """A (H, W) map with invalid and non-finite pixels fits exactly the valid points."""
    x, y, gx, gy = _slopes(40 * 50, seed=7)
    valid = np.random.default_rng(8).random(x.size) > 0.2
    gx_nan = np.where(np.arange(x.size) % 97 == 0, np.nan, gx)
    ok = valid & np.isfinite(gx_nan)
    ref, _ = _lstsq_irls(x[ok], y[ok], gx[ok], gy[ok])
    p = np.stack([x, y, np.zeros_like(x)], -1).reshape(40, 50, 3)
    g = np.stack([gx_nan, gy], -1).reshape(40, 50, 2)
    fit = fit_paraboloid_slopes(p, g, valid.reshape(40, 50), camera_z_mm=1.0)
    np.testing.assert_allclose(fit.coefficients, ref, rtol=1e-9, atol=0)
    assert np.isnan(fit.residual_slopes.reshape(-1, 2)[~ok]).all() and fit.n_points == ok.sum()


@pytest.mark.parametrize("mode", [0, 1])
def test_exact_median_selection(mode):
    """The streamed median is numpy's median exactly: with a tight, a wrong and no bracket, with
    ties (quantised slopes) and with the sampled-bracket (histogram) path."""
    x, y, gx, gy = _slopes(50_000, seed=11)
    gx = readonly(np.round(gx, 5))  # many equal residuals
    coef = np.array([2e-6, -3e-7, 1.5e-6, 1e-3, -2e-3])
    r = np.concatenate([gx - (2 * coef[0] * x + coef[1] * y + coef[3]), gy - (coef[1] * x + 2 * coef[2] * y + coef[4])])
    centre = float(np.median(r))
    v = np.abs(r - centre) if mode == 1 else r
    expected = np.median(v)
    buf, hist = np.empty(4096), np.empty(sf._N_BINS_SELECT, np.int64)
    for bracket in (None, (expected - 1e-7, expected + 1e-7), (expected + 1.0, expected + 2.0)):
        got = sf._median(x, y, gx, gy, coef, mode, centre, buf, hist, bracket)
        assert got == expected


def test_piston_tilt_matches_lstsq_with_mask():
    """The streamed plane removal against lstsq on [1, x, y]: coefficients to 1e-9 relative,
    heights to 1e-12 mm, NaN off the mask; collinear points fail explicitly."""
    rng = np.random.default_rng(12)
    x = rng.uniform(-100, 100, (30, 40)) + 300.0
    y = rng.uniform(-80, 80, (30, 40)) - 200.0
    z = 5.0 + 2e-3 * x - 1e-3 * y + rng.normal(0, 1e-3, x.shape)
    z[0, 0] = np.nan
    p = np.stack([x, y, z], -1)
    ok = rng.random(x.shape) > 0.2
    use = ok & np.isfinite(z)
    A = np.stack([np.ones(use.sum()), x[use], y[use]], -1)
    ref = np.linalg.lstsq(A, z[use], rcond=None)[0]
    h, coef = sf.remove_piston_tilt(p, ok)
    np.testing.assert_allclose(coef, ref, rtol=1e-9, atol=0)
    np.testing.assert_allclose(h[use], z[use] - A @ ref, rtol=0, atol=1e-12)
    assert np.isnan(h[~use]).all()
    line = np.stack([x, 2 * x, z], -1)
    with pytest.raises(sf.ComputationError, match="collinear"):
        sf.remove_piston_tilt(line, np.ones(x.shape, bool))
    few = p.copy()
    few[..., rng.integers(0, 3)] = np.inf  # x, y or z non-finite: left out as if not valid
    few[5, 6] = few[7, 8] = (1.0, 2.0, 3.0)  # two points left
    with pytest.raises(sf.ComputationError, match="fewer than 3"):
        sf.remove_piston_tilt(few, np.ones(x.shape, bool))


@pytest.mark.parametrize("quantise", [False, True])
def test_one_pass_median_and_mad(quantise):
    """The one-pass median and MAD (surface_fit_select) are numpy's medians exactly, with their
    two middle values: with brackets from a nearby fit's medians (the IRLS's next iteration), with
    ties (quantised slopes); None where a bracket misses a rank or holds too many values."""
    from pmdsim.evaluation.surface_fit_select import median_and_mad

    x, y, gx, gy = _slopes(60_001, seed=21)
    if quantise:
        gx = readonly(np.round(gx, 6))  # many equal residuals
    coef = np.array([2e-6, -3e-7, 1.5e-6, 1e-3, -2e-3])
    r = np.concatenate([gx - (2 * coef[0] * x + coef[1] * y + coef[3]), gy - (coef[1] * x + 2 * coef[2] * y + coef[4])])
    n = r.size
    srt = np.sort(r)
    med = np.median(r)
    dev = np.sort(np.abs(r - med))
    mad = np.median(np.abs(r - med))
    k1, k2 = (n - 1) // 2, n // 2
    buf_r, buf_z = np.empty(8192), np.empty(8192)
    for width in (0.0, 1e-8, 1e-7):
        got = median_and_mad(x, y, gx, gy, coef, (srt[k1] - width, srt[k2] + width),
                             (max(dev[k1] - 2 * width, 0.0), dev[k2] + 2 * width), buf_r, buf_z)
        assert got == ((med, srt[k1], srt[k2]), (mad, dev[k1], dev[k2]))
        ref = tuple(sf._median(x, y, gx, gy, coef, mode, centre, buf_r, np.empty(sf._N_BINS_SELECT, np.int64),
                               ranks=True) for mode, centre in ((0, 0.0), (1, med)))
        assert got == ref
    # a bracket above the median, a deviations' bracket missing the MAD, one holding every value
    assert median_and_mad(x, y, gx, gy, coef, (srt[k2] + 1e-9, srt[k2] + 1e-6), (dev[k1], dev[k2]), buf_r, buf_z) is None
    assert median_and_mad(x, y, gx, gy, coef, (srt[k1], srt[k2]), (dev[k2] + 1e-9, dev[k2] + 1e-8), buf_r, buf_z) is None
    assert median_and_mad(x, y, gx, gy, coef, (srt[0], srt[-1]), (0.0, dev[-1]), buf_r, buf_z) is None


def test_sandwich_sums_match_entry_loop_and_matmul():
    """The σ sandwich's N = Σ w AᵢᵀAᵢ and B = Σ (wσ)² AᵢᵀAᵢ: bit for bit the entry-by-entry sums
    (w·A_a)·A_b over the points in order (plain Python floats), and AᵀWA, AᵀW²Σ²A by numpy matmul
    on the explicit (2M, 5) design to 1e-12 relative; with zero weights (residuals beyond the
    scale), a point at x = 0 exactly and non-finite points skipped."""
    rng = np.random.default_rng(31)
    m = 400
    # (M, 2) in the layout evaluate passes ((2, M) rows transposed, F order): one compiled signature
    xy = np.asfortranarray(np.stack([rng.uniform(-50, 50, m), rng.uniform(-40, 40, m)], -1))
    res = np.asfortranarray(rng.normal(0, 1e-4, (m, 2)))
    res[::17] = 5e-3  # beyond the scale: weight 0
    sig = rng.uniform(1e-6, 3e-6, (m, 2))
    xc, yc = 3.0, -2.0
    xy[5, 0] = xc  # x − xc = 0 exactly
    res[9, 1] = np.nan
    sig[11, 0] = np.inf
    scale = 4.685 * 1e-4
    N, B = sf._sandwich_sums(xy, res, sig, xc, yc, scale)
    Nr, Br = [[0.0] * 5 for _ in range(5)], [[0.0] * 5 for _ in range(5)]
    rows, wts, wbs = [], [], []
    for i in range(m):
        if not np.isfinite(res[i].sum() + sig[i].sum() + xy[i].sum()):
            continue
        x, y = float(xy[i, 0]) - xc, float(xy[i, 1]) - yc
        for comp, row in ((0, [2 * x, y, 0.0, 1.0, 0.0]), (1, [0.0, x, 2 * y, 0.0, 1.0])):
            u = float(res[i, comp]) / scale
            w = (1.0 - u * u) ** 2 if abs(u) < 1.0 else 0.0
            wb = (w * float(sig[i, comp])) ** 2
            rows.append(row), wts.append(w), wbs.append(wb)
            for a in range(5):
                for b in range(5):
                    if w != 0.0 and row[a] != 0.0:
                        Nr[a][b] += w * row[a] * row[b]
                        Br[a][b] += wb * row[a] * row[b]
    assert np.array_equal(N, np.array(Nr)) and np.array_equal(B, np.array(Br))
    assert not np.signbit(N).any() or np.array_equal(np.signbit(N), np.signbit(np.array(Nr)))
    A, w, wb = np.array(rows), np.array(wts), np.array(wbs)
    assert (w == 0).sum() >= 40 and len(rows) == 2 * (m - 2)
    np.testing.assert_allclose(N, A.T @ (w[:, None] * A), rtol=1e-12, atol=1e-12 * np.abs(N).max())
    np.testing.assert_allclose(B, A.T @ (wb[:, None] * A), rtol=1e-12, atol=1e-12 * np.abs(B).max())


def test_overwrite_slopes_gives_the_same_fit():
    """``overwrite_slopes``: the same coefficients and residuals bit for bit (the residuals are
    g − A·c of the lstsq IRLS reference to 1e-12), written over the (2, M) slope rows; without it
    the slopes are left unchanged."""
    x, y, gx, gy = _slopes(20_000, seed=41)
    xy, g_rows = np.stack([x, y]), np.stack([gx, gy])
    keep = g_rows.copy()
    plain = fit_paraboloid_slopes(xy.T, g_rows.T, np.ones(x.size, bool), camera_z_mm=-1.0)
    assert np.array_equal(g_rows, keep)
    over = fit_paraboloid_slopes(xy.T, g_rows.T, np.ones(x.size, bool), camera_z_mm=-1.0, overwrite_slopes=True)
    assert over.coefficients == plain.coefficients and over.scale == plain.scale
    assert np.array_equal(over.residual_slopes, plain.residual_slopes)
    assert np.shares_memory(over.residual_slopes, g_rows) and np.array_equal(g_rows.T, plain.residual_slopes)
    ref, _ = _lstsq_irls(x, y, gx, gy)
    res = np.stack([gx - (2 * ref[0] * x + ref[1] * y + ref[3]), gy - (ref[1] * x + 2 * ref[2] * y + ref[4])], -1)
    np.testing.assert_allclose(over.residual_slopes, res, rtol=0, atol=1e-12)
