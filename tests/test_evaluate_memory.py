"""Memory of ``pmdsim evaluate`` (issue 25, item 1): the changes that keep fewer full-size maps
alive give the same numbers as the computations they replace.

Truths: numpy expressions of the same formulas (the residuals, the root-sum-square of σ parts,
A zeroed off S by ``np.where``), the sample-by-sample linearised recursion of
tests/test_uncertainty_stepwise.py, and the consistency checks of the same images as integers
(maps computed per stack when used) and as floats (A and RSS of every stack kept for the noise
model); tracemalloc for the peak of the checks.
"""

from __future__ import annotations

import tracemalloc
from types import SimpleNamespace

import numpy as np

from pmdsim.evaluation import uncertainty as U
from pmdsim.evaluation.consistency import check_consistency
from pmdsim.evaluation.phase import decode_screen_coordinates
from pmdsim.evaluation.surface_fit import _residuals
from pmdsim.geometry.kernel_args import readonly

from test_uncertainty_stepwise import _problem, _reference

_FIELDS = ("flags", "fit_residual_ratio", "period_mismatch_ratio", "worst_image", "tested")


def _integer_stacks(rng, h=120, w=150, n=5, ext=(100.0, 80.0), px=(120.0, 12.0, 1.5), py=(90.0, 9.0, 1.5)):
    v, u = np.mgrid[0:h, 0:w].astype(float)
    x = 5 + u * (ext[0] - 10) / (w - 1)
    y = 5 + v * (ext[1] - 10) / (h - 1)

    def stacks(c, periods):
        return [np.clip(np.rint(np.stack([120 + 100 * np.cos(2 * np.pi * c / p - 2 * np.pi * k / n)
                                          + rng.normal(0, 2.0, c.shape) for k in range(n)])), 0, 255).astype(np.uint8)
                for p in periods]

    sx, sy = stacks(x, px), stacks(y, py)
    sx[2][3, 40:60, 30:90] = 0  # a local defect: flagged pixels, a worst image
    return sx, px, sy, py, decode_screen_coordinates(sx, px, sy, py, ext, 255.0, 1.0)


def test_checks_of_integer_and_float_images_agree():
    """uint8 stacks (each stack's maps computed where used, twice) and the same values as
    float64 (A and RSS of all stacks kept until the noise model's pixels are known): the same
    flags, ratios, worst images and noise model, bit for bit."""
    sx, px, sy, py, dec = _integer_stacks(np.random.default_rng(5))
    a = check_consistency(sx, px, sy, py, dec, (100.0, 80.0), 1.0)
    b = check_consistency([s.astype(np.float64) for s in sx], px, [s.astype(np.float64) for s in sy], py, dec,
                          (100.0, 80.0), 1.0)
    assert np.count_nonzero(a.flags) > 100 and (a.worst_image >= 0).any()
    for f in _FIELDS:
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f
    assert a.noise_model == b.noise_model and np.array_equal(a.noise_lines, b.noise_lines)
    assert a.defects == b.defects and a.image_counts == b.image_counts


def test_a_nan_pixel_of_float_images_is_left_out_of_the_noise_model():
    """A NaN in one float stack: that pixel is not tested by the noise model (its RSS is not
    finite), and the model equals the one from the images with that pixel dark (not tested)."""
    sx, px, sy, py, dec = _integer_stacks(np.random.default_rng(6))
    fx = [s.astype(np.float64) for s in sx]
    fx[1][0, 7, 9] = np.nan
    a = check_consistency(fx, px, [s.astype(np.float64) for s in sy], py, dec, (100.0, 80.0), 1.0)
    assert np.isfinite(a.noise_model).all()
    assert a.tested[7, 9]  # photometrically tested, but the noise model skipped it without error


def test_checks_keep_one_stack_of_maps_at_a_time():
    """Six stacks of 5 uint8 images: the traced peak of the checks stays below what the six
    stacks' A, B, φ, RSS (float64) and worst-image (int16) maps alone took (34 bytes per pixel
    and stack, 204 in all), i.e. they are not alive at once."""
    h, w = 400, 500
    sx, px, sy, py, dec = _integer_stacks(np.random.default_rng(8), h=h, w=w)
    check_consistency(sx, px, sy, py, dec, (100.0, 80.0), 1.0)  # warm (compiled kernels, imports)
    tracemalloc.start()
    try:
        check_consistency(sx, px, sy, py, dec, (100.0, 80.0), 1.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 204 * h * w, peak / (h * w)


def test_sampled_std_zeroes_a_in_place_as_the_copy_did():
    """``overwrite=True`` (A zeroed off S in place) gives the σ of the sample-by-sample recursion
    with A zeroed by ``np.where`` — and ``overwrite=False`` leaves the caller's A as it was."""
    S, geo, layer, order, n, starts, pos, A = _problem()
    A_nan = np.where(S[..., None, None], A, np.nan)  # as the Jacobian kernel leaves it off S
    lin = SimpleNamespace(S=S, method="stepwise", geo=geo, layer=layer, order=order, starts=starts, pos=pos)
    K, seed = 16, 123
    ref = np.where(S, np.sqrt(_reference(S, geo, layer, order, n, np.where(S[..., None, None], A_nan, 0.0), seed, K)
                              / K), np.nan)
    own = A_nan.copy()
    got = U._sampled_std(lin, own, K, seed, overwrite=True)
    np.testing.assert_allclose(got[S], ref[S], rtol=1e-12)
    assert np.isnan(got[~S]).all() and (own[~S] == 0.0).all()
    kept = A_nan.copy()
    again = U._sampled_std(lin, kept, K, seed)
    assert np.array_equal(again, got, equal_nan=True)
    assert np.array_equal(kept, A_nan, equal_nan=True)


def test_combined_sigma_shares_the_noise_map_only_when_equal():
    """The total σ is numpy's sqrt(noise² + cal²): with a zero calibration part it is the noise
    map itself (bit for bit equal, so one array), otherwise a new array."""
    rng = np.random.default_rng(2)
    S = rng.random((40, 50)) < 0.8
    noise = np.where(S, rng.uniform(1e-4, 1e3, S.shape), np.nan)
    zero = np.where(S, 0.0, np.nan)
    assert np.array_equal(np.sqrt(noise ** 2 + zero ** 2), noise, equal_nan=True)
    assert U._combined(noise, zero) is noise
    cal = np.where(S, rng.uniform(0.0, 5.0, S.shape), np.nan)
    total = U._combined(noise, cal)
    assert total is not noise
    assert np.array_equal(total, np.sqrt(noise ** 2 + cal ** 2), equal_nan=True)


def test_residuals_in_place_equal_numpy():
    """The paraboloid's final residuals written over the centred coordinates (origin 0), or over
    the slopes with the coordinates centred on the fly (origin xc, yc), equal numpy's
    g_x − (2a·x + b·y + d), g_y − (b·x + 2c·y + e) at the centred x, y bit for bit."""
    rng = np.random.default_rng(3)
    x, y, gx, gy = (rng.normal(size=10_001) for _ in range(4))
    a, b, c, d, e = 1.7e-3, -2.1e-4, 9.3e-4, 3.1e-2, -4.4e-3
    rx_ref = gx - (2.0 * a * x + b * y + d)
    ry_ref = gy - (b * x + 2.0 * c * y + e)
    xw, yw = x.copy(), y.copy()
    # inputs read-only views (of the outputs' memory here), as fit_paraboloid_slopes passes them: one signature
    rx, ry = _residuals(readonly(xw), readonly(yw), readonly(gx), readonly(gy), 0.0, 0.0, a, b, c, d, e, xw, yw)
    assert rx is xw and ry is yw
    assert np.array_equal(rx, rx_ref) and np.array_equal(ry, ry_ref)
    xc, yc = 12.5, -7.25
    xu, yu = x + 12.5, y - 7.25
    cx, cy = xu - xc, yu - yc
    rx_ref = gx - (2.0 * a * cx + b * cy + d)
    ry_ref = gy - (b * cx + 2.0 * c * cy + e)
    gxw, gyw = gx.copy(), gy.copy()
    rx, ry = _residuals(readonly(xu), readonly(yu), readonly(gxw), readonly(gyw), xc, yc, a, b, c, d, e, gxw, gyw)
    assert rx is gxw and ry is gyw
    assert np.array_equal(rx, rx_ref) and np.array_equal(ry, ry_ref)


def test_small_pages_turns_the_hint_off_and_restores_it():
    """numpy's huge-page hint is off inside ``with small_pages()`` and back to what it was
    afterwards, also when the block raises."""
    import pytest

    from pmdsim.studies.evaluate_memory import _hugepage_switch, small_pages

    get, put = _hugepage_switch()
    seen = []

    def job(fail=False):
        with small_pages():
            seen.append(get())
            if fail:
                raise ValueError("boom")
            return np.ones(3).sum()

    old = put(True)
    try:
        assert job() == 3.0 and seen == [False] and get() is True
        with pytest.raises(ValueError):
            job(fail=True)
        assert seen == [False, False] and get() is True
        put(False)
        job()
        assert get() is False
    finally:
        put(bool(old))
