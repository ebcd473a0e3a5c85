"""The joint surface fit of ``pmdsim evaluate`` (issue 25: built from (2, M) rows without
per-camera copies) equals the fit composed from its parts on the concatenated (M, 2) points —
coefficients, residual maps and detrended heights bit for bit, the σ (its sandwich's sums in
another order, tests/test_surface_fit_final.py) to 1e-12 relative."""

import types

import numpy as np

from pmdsim.evaluation.surface_fit import (
    fit_paraboloid_slopes,
    remove_piston_tilt,
    sample_slopes,
    surface_fit_summary,
    with_uncertainty,
)


def _recs(seed=7):
    rng = np.random.default_rng(seed)
    recs, sig = [], []
    for c in range(2):
        v, u = np.mgrid[0:40, 0:64].astype(float)
        x, y = (u - 32) * 2.0 + 7 * c, (v - 20) * 2.0
        z = x**2 / 4000 + y**2 / 3000 + x * y / 9000
        n = np.stack([-(x / 2000 + y / 9000), -(y / 1500 + x / 9000), np.ones_like(x)], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n[..., :2] += 1e-4 * rng.normal(size=x.shape + (2,))
        n[rng.random(x.shape) < 0.01, 0] += 0.002  # outliers for the robust weights
        rc = rng.random(x.shape) > 0.05
        p = np.stack([x, y, z], -1)
        p[~rc] = np.nan
        n[~rc] = np.nan
        n[3, 5] = np.nan  # reconstructed without a finite slope: left out of the fit
        recs.append(types.SimpleNamespace(p_sample_mm=p, n_sample=n, reconstructed=rc))
        sig.append(np.where(rc[..., None], 1e-6 * (1 + rng.random(x.shape + (2,))), np.nan))
    return recs, sig


def test_summary_equals_the_fit_of_the_concatenated_points():
    recs, sig = _recs()
    fit, extras = surface_fit_summary(recs, -900.0, sig)
    gs = [sample_slopes(r.n_sample) for r in recs]
    oks = [r.reconstructed & np.isfinite(g).all(-1) for r, g in zip(recs, gs)]
    xy = np.concatenate([r.p_sample_mm[..., :2][ok] for r, ok in zip(recs, oks)])
    gxy = np.concatenate([g[ok] for g, ok in zip(gs, oks)])
    ref = fit_paraboloid_slopes(xy, gxy, np.ones(len(xy), bool), camera_z_mm=-900.0)
    # xy (M, 2) in F order, as the summary passes its (2, M) rows transposed: one compiled signature
    ref = with_uncertainty(ref, np.asfortranarray(xy), np.concatenate([s[ok] for s, ok in zip(sig, oks)]), -900.0)
    assert fit.coefficients == ref.coefficients
    np.testing.assert_allclose(fit.coefficients_std, ref.coefficients_std, rtol=1e-12, atol=0)
    np.testing.assert_allclose((fit.focal_length_x_std_mm, fit.focal_length_y_std_mm),
                               (ref.focal_length_x_std_mm, ref.focal_length_y_std_mm), rtol=1e-12, atol=0)
    assert (fit.focal_length_x_mm, fit.focal_length_y_mm, fit.slope_residual_rms_mrad, fit.scale) == (
        ref.focal_length_x_mm, ref.focal_length_y_mm, ref.slope_residual_rms_mrad, ref.scale)
    np.testing.assert_array_equal(fit.residual_slopes, ref.residual_slopes)
    start = 0
    for r, g, ok, ex in zip(recs, gs, oks, extras):
        k = int(ok.sum())
        res = np.full(ok.shape + (2,), np.nan)
        res[ok] = ref.residual_slopes[start:start + k]
        start += k
        np.testing.assert_array_equal(ex["residual_slopes"], res)
        np.testing.assert_array_equal(ex["slopes"], g)
        np.testing.assert_array_equal(ex["height_detrended_mm"], remove_piston_tilt(r.p_sample_mm, r.reconstructed)[0])
    # the paraboloid it found is the one the slopes were made from (outliers down-weighted)
    np.testing.assert_allclose(fit.coefficients[:3], (1 / 4000, 1 / 9000, 1 / 3000), rtol=2e-3, atol=2e-7)
    without = surface_fit_summary(recs, -900.0, None)[0]
    assert without.coefficients == fit.coefficients and without.coefficients_std is None


def test_sigma_maps_must_match_the_fitted_pixels():
    """σ read in the maps (``masks``): masks holding other pixels than the fit's points are refused
    before any is read."""
    import pytest

    recs, sig = _recs()
    fit, _ = surface_fit_summary(recs, -900.0, None)
    gs = [sample_slopes(r.n_sample) for r in recs]
    oks = [r.reconstructed & np.isfinite(g).all(-1) for r, g in zip(recs, gs)]
    xy = np.concatenate([r.p_sample_mm[..., :2][ok] for r, ok in zip(recs, oks)])
    with pytest.raises(ValueError, match="not the fit's points"):
        with_uncertainty(fit, xy, sig, -900.0, masks=[oks[0], oks[1] & (np.arange(64) > 3)])
    with pytest.raises(ValueError, match="not the fit's points"):
        with_uncertainty(fit, xy, [sig[0], sig[1][:, :10]], -900.0, masks=oks)


def test_summary_leaves_out_points_without_finite_coordinates():
    """A reconstructed pixel with a finite slope but a non-finite x: the summary fits the other
    points (the composed path), as the fit of the concatenated finite points."""
    recs, sig = _recs(seed=9)
    recs[1].p_sample_mm[7, 8, 0] = np.nan
    fit, extras = surface_fit_summary(recs, -900.0, sig)
    gs = [sample_slopes(r.n_sample) for r in recs]
    oks = [r.reconstructed & np.isfinite(g).all(-1) & np.isfinite(r.p_sample_mm[..., :2]).all(-1)
           for r, g in zip(recs, gs)]
    xy = np.concatenate([r.p_sample_mm[..., :2][ok] for r, ok in zip(recs, oks)])
    gxy = np.concatenate([g[ok] for g, ok in zip(gs, oks)])
    ref = fit_paraboloid_slopes(xy, gxy, np.ones(len(xy), bool), camera_z_mm=-900.0)
    assert fit.coefficients == ref.coefficients and fit.n_points == len(xy)
    assert np.isnan(extras[1]["residual_slopes"][7, 8]).all() and fit.coefficients_std is not None
