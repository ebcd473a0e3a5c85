"""Tests of pmdsim.phase against synthetic fringe images with a known coordinate field.

The image generator below is written independently of the module under test, directly from
the fringe model of docs/conventions.md: φ = 2π·c/p, δ_k = 2πk/N, I_k = A + B·cos(φ − δ_k),
quantised by rounding and clipping to the bit depth.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pmdsim.evaluation.phase import (
    PhaseDecodingError,
    PhaseFlag,
    decode_direction,
    decode_screen_coordinates,
    unwrap_hierarchical,
    wrapped_phase,
)

H, W = 120, 160
EXTENT_MM = 700.0


# ---------------------------------------------------------------------------------------------
# Independent synthetic data
# ---------------------------------------------------------------------------------------------


def coordinate_field(lo=0.0, hi=EXTENT_MM, h=H, w=W, transpose=False):
    """Smooth (H, W) screen-coordinate field in mm spanning exactly [lo, hi]."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    t = v / (h - 1) if transpose else u / (w - 1)
    s = u / (w - 1) if transpose else v / (h - 1)
    g = 0.7 * t + 0.3 * s**2 + 0.05 * np.sin(2 * np.pi * t) * np.sin(np.pi * s)
    g = (g - g.min()) / (g.max() - g.min())
    return lo + (hi - lo) * g


def render(coord_mm, period_mm, n, offset, amplitude, quantise=True, max_value=255, noise=None):
    """(N, H, W) images I_k = A + B cos(2πc/p − 2πk/N); uint8 if quantised, else float64."""
    k = np.arange(n).reshape(-1, 1, 1)
    img = offset + amplitude * np.cos(2 * np.pi * coord_mm / period_mm - 2 * np.pi * k / n)
    if noise is not None:
        img = img + noise
    if not quantise:
        return img
    return np.clip(np.rint(img), 0, max_value).astype(np.uint8)


def render_set(coord_mm, periods_mm, shifts, offset=128.0, amplitude=100.0, **kw):
    if np.isscalar(shifts):
        shifts = [shifts] * len(periods_mm)
    return [render(coord_mm, p, n, offset, amplitude, **kw) for p, n in zip(periods_mm, shifts)]


def quantisation_bound_mm(period_mm, amplitude):
    """Worst-case coordinate error of one period caused by rounding to integer grey levels.

    Recorded J_k = I_k + e_k with |e_k| ≤ 1/2. The decoder forms
    (C', S') = (2/N)·Σ J_k (cos δ_k, sin δ_k) = B·(cos φ, sin φ) + d, because the offset term
    (2/N)·A·Σ (cos δ_k, sin δ_k) vanishes for equally spaced δ_k. The error vector is
    d = (2/N)·Σ e_k (cos δ_k, sin δ_k), so |d| ≤ (2/N)·Σ |e_k| ≤ (2/N)·(N/2) = 1 grey level.
    The direction of a vector of length B perturbed by |d| ≤ r < B changes by at most
    asin(r/B) (the tangent to the disc of radius r), hence |δφ| ≤ asin(1/B) — to first order
    the familiar 1/B — and the coordinate error is p·|δφ|/(2π).
    """
    return period_mm * math.asin(1.0 / amplitude) / (2 * math.pi)


def assert_hierarchy_resolvable(periods_mm, amplitude, tol=0.25):
    """Precondition of the round trip: each level's worst-case error is within the tolerance."""
    p = sorted(periods_mm, reverse=True)
    for coarse, fine in zip(p[:-1], p[1:]):
        assert quantisation_bound_mm(coarse, amplitude) < tol * fine


# ---------------------------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [3, 4, 8])
@pytest.mark.parametrize("periods", [[720.0, 90.0, 11.25], [720.0, 120.0, 24.0, 6.0]])
def test_round_trip_quantised_within_analytic_bound(n, periods):
    c = coordinate_field()
    amplitude = 100.0  # A ± B = 28…228: no clipping
    assert_hierarchy_resolvable(periods, amplitude)
    res = decode_direction(render_set(c, periods, n, 128.0, amplitude), periods, EXTENT_MM, 255)
    assert res.valid.all()
    assert np.all(res.flags == 0)
    err = np.abs(res.coord_mm - c)
    bound = quantisation_bound_mm(min(periods), amplitude)
    assert err.max() <= bound
    # The field includes c = 0 exactly: a phase just below 2π must have been wrapped back.
    assert np.abs(res.coord_mm[c == 0.0]).max() <= bound


def test_round_trip_unsorted_periods_mixed_shift_counts():
    c = coordinate_field()
    periods = [24.0, 720.0, 6.0, 120.0]
    shifts = [4, 3, 8, 5]
    res = decode_direction(render_set(c, periods, shifts), periods, EXTENT_MM, 255)
    assert res.valid.all()
    assert np.abs(res.coord_mm - c).max() <= quantisation_bound_mm(6.0, 100.0)
    # σ model uses the finest period (6 mm, N = 8) and the quantisation noise 1/√12.
    expected = 6.0 / (2 * np.pi) * np.sqrt(2 / 8) * (1 / np.sqrt(12)) / res.modulation
    np.testing.assert_allclose(res.std_mm, expected, rtol=1e-12)


@pytest.mark.parametrize("n", [3, 4, 8])
def test_round_trip_float_images_exact(n):
    c = coordinate_field()
    periods = [720.0, 90.0, 11.25]
    stacks = render_set(c, periods, n, quantise=False)
    res = decode_direction(stacks, periods, EXTENT_MM, 255)
    assert res.valid.all()
    assert np.abs(res.coord_mm - c).max() < 1e-9
    np.testing.assert_allclose(res.modulation, 100.0, rtol=1e-12)
    np.testing.assert_allclose(res.offset, 128.0, rtol=1e-12)


def test_origin_offset_screen_coordinates():
    c = coordinate_field(lo=-350.0, hi=350.0)
    periods = [720.0, 90.0, 11.25]
    res = decode_direction(render_set(c, periods, 4, quantise=False), periods, EXTENT_MM, 255,
                           origin_mm=-350.0)
    assert res.valid.all()
    assert np.abs(res.coord_mm - c).max() < 1e-9


def test_wrapped_phase_float_and_general_shifts():
    c = coordinate_field()
    p = 37.0
    phi_true = np.mod(2 * np.pi * c / p, 2 * np.pi)
    res = wrapped_phase(render(c, p, 5, 100.0, 60.0, quantise=False), max_value=255)
    d = np.abs(res.phase - phi_true)
    assert np.minimum(d, 2 * np.pi - d).max() < 1e-12
    assert res.phase.min() >= 0.0 and res.phase.max() < 2 * np.pi
    np.testing.assert_allclose(res.modulation, 60.0, rtol=1e-12)
    np.testing.assert_allclose(res.offset, 100.0, rtol=1e-12)
    assert res.valid.all()

    # Unequal shifts: least squares on I_k = A + B cos(φ − δ_k) is exact for noiseless data.
    shifts = np.array([0.0, 1.0, 2.5, 4.0])
    imgs = 100.0 + 60.0 * np.cos(2 * np.pi * c / p - shifts.reshape(-1, 1, 1))
    res = wrapped_phase(imgs, shifts, max_value=255)
    d = np.abs(res.phase - phi_true)
    assert np.minimum(d, 2 * np.pi - d).max() < 1e-12
    np.testing.assert_allclose(res.modulation, 60.0, rtol=1e-12)


def test_wrapped_phase_dtypes_and_layouts():
    # (Only uint8 and float64 here: every further dtype costs a numba compilation.)
    c = coordinate_field()
    u8 = render(c, 50.0, 4, 128.0, 127.0)  # reaches 255 somewhere
    res = wrapped_phase(u8)  # max_value from the dtype: 255
    assert np.array_equal(res.flags == PhaseFlag.SATURATED, np.any(u8 == 255, axis=0))
    # Non-native byte order and strided views give the same results as native copies.
    f8 = render(c, 50.0, 4, 128.0, 100.0, quantise=False)
    ref = wrapped_phase(f8, max_value=255)
    np.testing.assert_array_equal(wrapped_phase(f8.astype(">f8"), max_value=255).phase, ref.phase)
    view = u8[:, ::2, 1::3]
    np.testing.assert_array_equal(wrapped_phase(view).phase, wrapped_phase(view.copy()).phase)
    # Boolean images are accepted as 0/1 grey levels.
    assert wrapped_phase(u8 > 128, max_value=1).phase.shape == (H, W)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.phase = None


# ---------------------------------------------------------------------------------------------
# Validity masks
# ---------------------------------------------------------------------------------------------


def test_masks_each_region_gets_its_flag():
    c = coordinate_field()
    periods = [720.0, 90.0, 11.25]
    a = np.full((H, W), 128.0)
    b = np.full((H, W), 100.0)
    regions = {
        "dark": (slice(0, 20), slice(0, 30)),  # black: 0 in all images
        "dim": (slice(0, 20), slice(40, 70)),  # A = 3 < 0.02·255
        "saturated": (slice(30, 50), slice(0, 30)),  # A + B > 255, clipped
        "low_contrast": (slice(30, 50), slice(40, 70)),  # B = 1.5 < 0.01·255
        "constant": (slice(60, 80), slice(0, 30)),  # B = 0
        "low_ratio": (slice(60, 80), slice(40, 70)),  # B/A = 6/200 < 0.05
    }
    values = {"dark": (0, 0), "dim": (3, 2), "saturated": (200, 100), "low_contrast": (128, 1.5),
              "constant": (100, 0), "low_ratio": (200, 6)}
    for name, sl in regions.items():
        a[sl], b[sl] = values[name]
    stacks = render_set(c, periods, 4, a, b)
    assert all(np.all(s[:, regions["dark"][0], regions["dark"][1]] == 0) for s in stacks)
    res = decode_direction(stacks, periods, EXTENT_MM, 255)

    expected = {"dark": PhaseFlag.DARK, "dim": PhaseFlag.DARK, "saturated": PhaseFlag.SATURATED,
                "low_contrast": PhaseFlag.LOW_MODULATION, "constant": PhaseFlag.LOW_MODULATION,
                "low_ratio": PhaseFlag.LOW_MODULATION}
    normal = np.ones((H, W), bool)
    for name, sl in regions.items():
        normal[sl] = False
        assert np.all(res.flags[sl] & expected[name]), name
        assert not res.valid[sl].any(), name
        assert np.isnan(res.coord_mm[sl]).all(), name
        assert np.isnan(res.std_mm[sl]).all(), name
    # Exactly the intended reasons where they are unambiguous.
    assert np.all(res.flags[regions["saturated"]] == PhaseFlag.SATURATED)
    assert np.all(res.flags[regions["low_ratio"]] == PhaseFlag.LOW_MODULATION)
    assert res.valid[normal].all()
    assert np.all(res.flags[normal] == 0)
    assert np.abs(res.coord_mm[normal] - c[normal]).max() <= quantisation_bound_mm(11.25, 100.0)
    assert np.isfinite(res.std_mm[normal]).all()


def test_masks_wrapped_phase_thresholds_and_nonfinite():
    img = np.full((4, 2, 3), 100.0)
    img[:, 0, 0] = [150, 100, 50, 100]  # B = 50: valid
    img[:, 0, 1] = [104, 100, 96, 100]  # B = 4: above 0.01·255 but B/A = 0.04 < 0.05
    img[:, 0, 2] = np.nan
    res = wrapped_phase(img, max_value=255)
    assert res.flags[0, 0] == 0
    assert res.flags[0, 1] == PhaseFlag.LOW_MODULATION
    assert res.flags[0, 2] & PhaseFlag.NONFINITE and np.isnan(res.phase[0, 2])
    assert wrapped_phase(img, max_value=255, min_modulation_ratio=0.03).flags[0, 1] == 0
    assert wrapped_phase(img, max_value=150).flags[0, 0] == PhaseFlag.SATURATED  # sample 150
    assert wrapped_phase(img, max_value=150.5).flags[0, 0] == 0
    assert wrapped_phase(img, max_value=150, check_saturation=False).flags[0, 0] == 0
    assert np.all(wrapped_phase(img, max_value=255).flags[1] == PhaseFlag.LOW_MODULATION)  # constant
    assert int(PhaseFlag.DARK | PhaseFlag.SATURATED) == 3


# ---------------------------------------------------------------------------------------------
# Noise model
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [3, 4])
def test_predicted_std_matches_observed(n):
    rng = np.random.default_rng(12345)
    sigma_i = 2.0
    c = coordinate_field()
    periods = [720.0, 90.0, 11.25]
    b = np.where(np.arange(W) < W // 2, 40.0, 100.0) * np.ones((H, 1))
    stacks = [render(c, p, n, 128.0, b, quantise=False, noise=rng.normal(0.0, sigma_i, (n, H, W)))
              for p in periods]
    res = decode_direction(stacks, periods, EXTENT_MM, 255, noise_std=sigma_i)
    assert res.valid.all()
    err = res.coord_mm - c
    for region in (b == 40.0, b == 100.0):
        observed = np.sqrt(np.mean(err[region] ** 2))
        predicted = np.sqrt(np.mean(res.std_mm[region] ** 2))
        assert abs(observed / predicted - 1) < 0.10
    # Independent of the module: σ_c = p·√(2/N)·σ_I/(2πB) with the true B.
    np.testing.assert_allclose(np.median(res.std_mm[b == 100.0]),
                               11.25 * np.sqrt(2 / n) * sigma_i / (2 * np.pi * 100.0), rtol=0.01)


# ---------------------------------------------------------------------------------------------
# Unwrapping
# ---------------------------------------------------------------------------------------------


def true_phases(c, periods):
    return np.stack([np.mod(2 * np.pi * c / p, 2 * np.pi) for p in periods])


def test_unwrap_exact_phases_any_order():
    c = coordinate_field()
    periods = [11.25, 720.0, 90.0]
    coord, flags = unwrap_hierarchical(true_phases(c, periods), periods, EXTENT_MM)
    assert np.abs(coord - c).max() < 1e-9
    assert np.all(flags == 0)


def test_unwrap_wrap_near_zero_and_far_end():
    c = np.array([[-0.3, 0.0, 700.3, 709.0, 350.0]])
    res = unwrap_hierarchical(true_phases(c, [720.0, 90.0]), [720.0, 90.0], EXTENT_MM)
    np.testing.assert_allclose(res.coord_mm, c, atol=1e-9)
    # 712 mm lies above extent + default margin (10 mm): read as the wrap of −8 mm.
    res = unwrap_hierarchical(true_phases(np.array([[712.0]]), [720.0]), [720.0], EXTENT_MM)
    np.testing.assert_allclose(res.coord_mm, -8.0, atol=1e-9)
    res = unwrap_hierarchical(true_phases(np.array([[712.0]]), [720.0]), [720.0], EXTENT_MM,
                              margin_mm=20.0)
    np.testing.assert_allclose(res.coord_mm, 712.0, atol=1e-9)


def test_unwrap_coarsest_period_shorter_than_extent_raises():
    c = coordinate_field()
    with pytest.raises(PhaseDecodingError, match="coarsest period 600 mm is shorter than the screen extent 700"):
        unwrap_hierarchical(true_phases(c, [600.0, 90.0]), [600.0, 90.0], EXTENT_MM)
    stacks = render_set(c, [600.0, 90.0], 4)
    with pytest.raises(PhaseDecodingError, match="coarsest period"):
        decode_direction(stacks, [600.0, 90.0], EXTENT_MM, 255)


def test_unwrap_corrupted_phases_flagged():
    c = coordinate_field()
    periods = [720.0, 90.0, 11.25]
    phases = true_phases(c, periods)
    bad_coarse = (np.array([5, 17, 60, 99, 110]), np.array([3, 80, 41, 150, 7]))
    bad_mid = (np.array([8, 33, 70, 101, 119]), np.array([120, 9, 66, 12, 159]))
    # Coarse coordinate off by 40 mm (> 0.25·90) at a few pixels ...
    phases[0][bad_coarse] += 2 * np.pi * 40.0 / 720.0
    # ... and the 90 mm level off by 5 mm (> 0.25·11.25) at others.
    phases[1][bad_mid] += 2 * np.pi * 5.0 / 90.0
    coord, flags = unwrap_hierarchical(phases, periods, EXTENT_MM)
    expected = np.zeros((H, W), bool)
    expected[bad_coarse] = True
    expected[bad_mid] = True
    np.testing.assert_array_equal(flags != 0, expected)
    assert np.all(flags[expected] == PhaseFlag.UNWRAP_INCONSISTENT)
    # Both errors were below half the next period, so the coordinate is still recovered.
    assert np.abs(coord - c).max() < 1e-9

    # Through decode_direction: a corrupted coarse image makes the pixel invalid.
    stacks = render_set(c, periods, 4, quantise=False)
    stacks[0][:, 50, 50] = render(np.array([[c[50, 50] + 40.0]]), 720.0, 4, 128.0, 100.0,
                                  quantise=False)[:, 0, 0]
    res = decode_direction(stacks, periods, EXTENT_MM, 255)
    assert res.flags[50, 50] == PhaseFlag.UNWRAP_INCONSISTENT
    assert np.isnan(res.coord_mm[50, 50]) and res.valid.sum() == H * W - 1


def test_unwrap_nan_phase_and_bad_arguments():
    phases = np.zeros((2, 1, 2))
    phases[1, 0, 1] = np.nan
    res = unwrap_hierarchical(phases, [720.0, 90.0], EXTENT_MM)
    assert res.flags[0, 1] == PhaseFlag.NONFINITE and np.isnan(res.coord_mm[0, 1])
    with pytest.raises(PhaseDecodingError, match="tolerance"):
        unwrap_hierarchical(phases, [720.0, 90.0], EXTENT_MM, tolerance=0.6)
    with pytest.raises(PhaseDecodingError, match="margin_mm"):
        unwrap_hierarchical(phases, [720.0, 90.0], EXTENT_MM, margin_mm=30.0)
    with pytest.raises(PhaseDecodingError, match="2 phase maps"):
        unwrap_hierarchical(phases, [720.0, 90.0, 10.0], EXTENT_MM)
    with pytest.raises(PhaseDecodingError, match="distinct"):
        unwrap_hierarchical(phases, [720.0, 720.0], EXTENT_MM)
    with pytest.raises(PhaseDecodingError, match="positive"):
        unwrap_hierarchical(phases, [720.0, -90.0], EXTENT_MM)
    with pytest.raises(PhaseDecodingError, match=r"shape \(P, H, W\)"):
        unwrap_hierarchical(phases[0], [720.0], EXTENT_MM)


# ---------------------------------------------------------------------------------------------
# Both directions
# ---------------------------------------------------------------------------------------------


def test_decode_screen_coordinates():
    cx = coordinate_field()
    cy = coordinate_field(hi=400.0, transpose=True)
    xp = [720.0, 90.0, 11.25]
    yp = [420.0, 60.0, 10.0]
    xs = render_set(cx, xp, 4)
    ys = render_set(cy, yp, 3)
    ys[1][:, 10:20, 10:20] = 0  # black in one y period only
    res = decode_screen_coordinates(xs, xp, ys, yp, (EXTENT_MM, 400.0), 255)
    assert res.screen_xy_mm.shape == (H, W, 2)
    assert res.std_xy_mm.shape == (H, W, 2) and res.modulation.shape == (H, W, 2)
    bad = np.zeros((H, W), bool)
    bad[10:20, 10:20] = True
    np.testing.assert_array_equal(res.valid, ~bad)
    assert np.all(res.flags[bad] & PhaseFlag.DARK)
    assert np.isnan(res.screen_xy_mm[bad]).all() and np.isnan(res.std_xy_mm[bad]).all()
    ok = ~bad
    assert np.abs(res.screen_xy_mm[..., 0] - cx)[ok].max() <= quantisation_bound_mm(11.25, 100.0)
    assert np.abs(res.screen_xy_mm[..., 1] - cy)[ok].max() <= quantisation_bound_mm(10.0, 100.0)
    sx = 11.25 / (2 * np.pi) * np.sqrt(2 / 4) / np.sqrt(12) / res.modulation[..., 0]
    np.testing.assert_allclose(res.std_xy_mm[..., 0][ok], sx[ok], rtol=1e-12)
    with pytest.raises(PhaseDecodingError, match="direction 'y'"):
        decode_screen_coordinates(xs, xp, ys, yp[:2], (EXTENT_MM, 400.0), 255)
    with pytest.raises(PhaseDecodingError, match="differ in image size"):
        decode_screen_coordinates(xs, xp, [s[:, :, :-1] for s in ys], yp, (EXTENT_MM, 400.0), 255)
    with pytest.raises(PhaseDecodingError, match="screen_size_mm"):
        decode_screen_coordinates(xs, xp, ys, yp, 700.0, 255)


# ---------------------------------------------------------------------------------------------
# Input errors
# ---------------------------------------------------------------------------------------------


def test_input_errors_name_the_problem():
    img = np.zeros((4, 5, 6), np.uint8)
    with pytest.raises(PhaseDecodingError, match=r"N >= 3 .* got N = 2"):
        wrapped_phase(img[:2])
    with pytest.raises(PhaseDecodingError, match=r"shape \(N, H, W\)"):
        wrapped_phase(img[0])
    with pytest.raises(PhaseDecodingError, match="same size"):
        wrapped_phase([img[0], img[1], img[2, :4]])
    with pytest.raises(PhaseDecodingError, match=r"shifts: .* shape \(4,\)"):
        wrapped_phase(img, [0.0, 1.0, 2.0])
    with pytest.raises(PhaseDecodingError, match="3 distinct values"):
        wrapped_phase(img, [0.0, 1.0, 0.0, 1.0])
    with pytest.raises(PhaseDecodingError, match="max_value must be given for floating-point"):
        wrapped_phase(img.astype(np.float32))
    with pytest.raises(PhaseDecodingError, match=r"images_by_period\[1\]: image size"):
        decode_direction([img, img[:, :4]], [720.0, 90.0], EXTENT_MM, 255)
    with pytest.raises(PhaseDecodingError, match=r"images_by_period\[1\]: N-step .* got N = 2"):
        decode_direction([img, img[:2]], [720.0, 90.0], EXTENT_MM, 255)
    with pytest.raises(PhaseDecodingError, match="3 periods given but 2"):
        decode_direction([img, img], [720.0, 90.0, 10.0], EXTENT_MM, 255)
    with pytest.raises(PhaseDecodingError, match="sequence of"):
        decode_direction(img, [720.0], EXTENT_MM, 255)
    with pytest.raises(PhaseDecodingError, match="noise_std"):
        decode_direction([img], [720.0], EXTENT_MM, 255, noise_std=np.ones(7))
    assert issubclass(PhaseDecodingError, ValueError)
