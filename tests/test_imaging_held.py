"""The held screen pattern rendered in position (pmdsim.simulation.imaging_held): its closed forms
against scipy quadrature, the renderer against the harmonic × alias series it replaces (the same
model in the frequency domain) and against the staircase's closed form with exact display levels."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import integrate

from pmdsim.setup import default_setup
from pmdsim.geometry.fast_trig import fast_asin
from pmdsim.setup.fringes import FringeSequence
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.imaging import (HOLD_ALIASES, ImagingMaps, imaging_maps, render_direction_imaging,
                                       render_period_imaging)
from pmdsim.simulation.imaging_held import kernel_cdf, semicircle_cdf, semicircle_g1, semicircle_g2
from pmdsim.simulation.render import render_images, trace_setup_camera

EVERY_EFFECT = dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=16.0, exposure=0.8,
                    display_gamma=2.2, display_black_level=0.001, emission_exponent=2.0,
                    screen_pixel_pitch_mm=0.27, screen_fill_factor=0.8, pixel_area=True,
                    f_number=8.0, focal_length_mm=25.0, display_levels=256)


def test_fast_asin_is_within_two_ulp_of_numpy():
    x = np.concatenate([np.linspace(-1.0, 1.0, 400_001), 1.0 - np.geomspace(1e-16, 1e-3, 2000),
                        np.geomspace(1e-300, 1e-3, 2000)])
    got = np.array([fast_asin(v) for v in x])
    ref = np.arcsin(x)
    assert np.all(np.abs(got - ref) <= 2.0 * np.spacing(np.abs(ref) + 1e-300))


def _semicircle_moment(x, radius, k):
    """E[(x − S)₊^k]/k! for S on the semicircle of ``radius`` — scipy quad after s = R·sin φ (a
    smooth integrand: the density's √ is cos φ)."""
    if x <= -radius:
        return 0.0
    hi = np.arcsin(min(x / radius, 1.0))
    f = lambda ph: (2.0 / np.pi) * np.cos(ph) ** 2 * (x - radius * np.sin(ph)) ** k / (2.0 if k == 2 else 1.0)
    return integrate.quad(f, -np.pi / 2, hi, epsabs=1e-15, epsrel=1e-13, limit=200)[0]


@pytest.mark.parametrize("x", [-2.0, -1.3, -1.2999, -0.7, 0.0, 0.31, 1.0, 1.2999, 1.3, 4.0])
def test_semicircle_cdf_and_its_antiderivatives_match_quadrature(x):
    R = 1.3
    assert semicircle_cdf(x, R) == pytest.approx(_semicircle_moment(x, R, 0), abs=3e-16)
    assert semicircle_g1(x, R) == pytest.approx(_semicircle_moment(x, R, 1), abs=1e-15)
    assert semicircle_g2(x, R) == pytest.approx(_semicircle_moment(x, R, 2), abs=3e-15)


def _trapezoid_cdf(y, a, b):
    """CDF of box(a) ⊛ box(b) (full widths, a ≥ b > 0) at the scalar y: piecewise quadratic."""
    t = abs(y)
    lo, hi = 0.5 * (a - b), 0.5 * (a + b)
    if t <= lo:
        half = t / a
    elif t >= hi:
        half = 0.5
    else:
        d = t - lo
        half = lo / a + d / a - d * d / (2 * a * b)
    return 0.5 + half if y >= 0 else 0.5 - half


@pytest.mark.parametrize("a, b", [(0.18, 3e-3), (0.18, 4e-4), (0.2, 0.15), (0.18, 1e-9), (2.0, 1.0)])
def test_kernel_cdf_matches_the_convolution_by_quadrature(a, b):
    """F of semicircle(R) ⊛ box(a) ⊛ box(b) against ∫ F_trapezoid(e − s)·f_S(s) ds (scipy quad
    over φ, s = R·sin φ, the trapezoid's CDF in closed form); (0.18, 1e-9) takes the merged
    branch. Tolerance: the second difference's rounding, 4 values of G₂ ≤ (R + a)² to a few ulp
    each, divided by a·b (≤ 1.1e-10 of the CDF here; 3e-7 grey levels at 12 bit)."""
    R = 1.3
    tol = 16 * np.finfo(float).eps * (R + a) ** 2 / max(a * b, 1e-7 * (R + a) ** 2) + 1e-14
    for e in np.linspace(-R - a, R + a, 23):
        f = lambda ph: (2.0 / np.pi) * np.cos(ph) ** 2 * _trapezoid_cdf(e - R * np.sin(ph), a, b)
        kinks = [np.arcsin(np.clip((e - c) / R, -1, 1)) for c in (0.5 * (a + b), 0.5 * (a - b), -0.5 * (a - b),
                                                                 -0.5 * (a + b))]
        ref = integrate.quad(f, -np.pi / 2, np.pi / 2, points=sorted(set(kinks)), epsabs=1e-14, limit=400)[0]
        assert kernel_cdf(e, R, a, b) == pytest.approx(ref, abs=tol)


def _means_both(setup, direction):
    m = trace_setup_camera(setup, "left", store_points=True)
    maps = imaging_maps(setup, "left", m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    periods = seq.periods(direction)
    held = np.empty((len(periods), seq.n_shifts) + m.valid.shape)
    render_direction_imaging(dataclasses.replace(maps, display=None), m.screen_xy_mm, m.valid, direction, seq, sensor,
                             np.random.default_rng(0), means=held)
    series = []
    for p in periods:
        mp = np.empty((seq.n_shifts,) + m.valid.shape)
        render_period_imaging(maps, m.screen_xy_mm, m.valid, direction, p, seq, sensor, np.random.default_rng(0),
                              tolerance_dn=0.0, means=mp)
        series.append(mp)
    return m, maps, sensor, held, np.stack(series)


@pytest.mark.parametrize("direction", ["x", "y"])
def test_held_pattern_in_position_equals_the_uncut_alias_series(direction):
    """Every effect at f/8 (binned 16, the real pixel's footprint), the displayed pattern as its
    cosine series: the position-space sum over the screen pixels under the footprint and the
    frequency-domain series (every harmonic × 65 aliases, the uncut series) are one model. Their
    difference is bounded by the series' own approximations: its tabulated J₁ (linear
    interpolation, ≤ 3.0e-8 of each term, docs/conventions.md) summed over the harmonics' alias
    weights Σ_a min(1, 1/(π|r + a|)) ≤ 1 + (2/π)(1 + ln A), and the aliases beyond the cap A = 32
    (each ≤ |c_n|/(π z)·1.66(4πσz/P)^(−3/2)·P/(π|J|z), z ≥ A − r)."""
    setup = default_setup().with_bulge(3.0).with_imaging(**EVERY_EFFECT).binned(16)
    m, maps, sensor, held, series = _means_both(setup, direction)
    v = m.valid
    axis = "xy".index(direction)
    g = (maps.radiance * sensor.scale_dn)[v].max()
    c = np.abs(maps.coefficients[1:])
    A = HOLD_ALIASES
    sig = np.sqrt(maps.var_xy_mm2[..., axis][v]).min()
    jmax = np.abs(maps.jacobian[..., axis, :][v]).max(-1).min()
    P = maps.hold_pitch_mm
    r_max = c.size * P / min(setup.patterns.sequence.periods(direction))
    z = np.arange(A - r_max, 1e5)
    tail = 2 * np.sum(1 / (np.pi * z) * np.minimum(1, 1.66 * (4 * np.pi * sig * z / P) ** -1.5)
                      * np.minimum(1, P / (np.pi * jmax * z)))
    bound = g * (c.sum() * (3.0e-8 * (1 + 2 / np.pi * (1 + np.log(A))) + tail))
    diff = np.abs(held[:, :, v] - series[:, :, v]).max()
    assert diff <= bound, (diff, bound)
    assert bound < 2e-3  # a bound that says something: 1/500 of a grey level (≈ 1.2e-3 DN)


def _row_maps(x, hold, jac_u, jac_v, sigma, display, coefficients=(0.5, 0.45)):
    shape = (1, x.size)
    coord = np.zeros(shape + (2,))
    coord[0, :, 0] = x
    jac = np.zeros(shape + (2, 2))
    jac[..., 0, 0], jac[..., 0, 1] = jac_u, jac_v
    var = np.zeros(shape + (2,))
    var[..., 0] = sigma ** 2
    maps = ImagingMaps(var, jac if (jac_u or jac_v) else None, np.ones(shape), hold, np.asarray(coefficients, float),
                       display=display)
    return coord, maps


def test_display_levels_on_screen_pixels_seen_by_a_box_pixel_closed_form():
    """A sharp camera whose pixel footprint is a box of J = 0.35 mm over 0.27 mm screen pixels
    showing L = 16 display levels through gamma 2.2: each sample is Σ_j overlap_j/J·r(Q(d_j)),
    computed here exactly (overlaps × the rounded, gamma-mapped held values). The renderer's means
    equal it to rounding (1e-9 of full scale)."""
    from pmdsim.simulation.display import display_response

    P, p, J, L, A, B = 0.27, 2.0, 0.35, 16, 0.5, 0.45
    resp = display_response(2.2, 0.0)
    x = np.linspace(10.0, 14.0, 801)
    coord, maps = _row_maps(x, P, J, 0.0, 0.0, (resp, L))
    seq = FringeSequence((p,), (p,), n_shifts=4, mean_level=A, amplitude=B)
    sensor = SensorModel.from_values(None, 16, 0.0)
    means = np.empty((1, 4, 1, x.size))
    render_direction_imaging(maps, coord, np.ones((1, x.size), bool), "x", seq, sensor, None, means=means)
    shifts = 2 * np.pi * np.arange(4) / 4
    lo, hi = x - J / 2, x + J / 2
    ref = np.zeros((4, x.size))
    for j in range(int(np.floor(lo.min() / P)), int(np.floor(hi.max() / P)) + 1):
        overlap = np.clip(np.minimum(hi, (j + 1) * P) - np.maximum(lo, j * P), 0.0, None)
        d = A + B * np.cos(2 * np.pi * (j + 0.5) * P / p - shifts[:, None])
        ref += overlap / J * resp.forward(np.floor(d * (L - 1) + 0.5) / (L - 1))
    np.testing.assert_allclose(means[0, :, 0] / 65535.0, ref, rtol=0, atol=1e-9)


def test_held_images_of_a_noisy_sensor_are_reproducible_and_draw_the_per_period_noise():
    """The sequence renderer draws each period's N noise fields from the stream in display order,
    as the per-period renderer did: a pixel's noise-free mean and its recorded value differ by the
    same draws (checked through a second render with the noise-free means)."""
    setup = default_setup().with_bulge(3.0).with_imaging(**EVERY_EFFECT).binned(16)
    m = trace_setup_camera(setup, "left", store_points=True)
    a = [img for _, img in render_images(setup, "left", m)]
    b = [img for _, img in render_images(setup, "left", m)]
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    maps = imaging_maps(setup, "left", m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    rng = np.random.default_rng([setup.patterns.seed, 0])
    means = np.empty((3, 4) + m.valid.shape)
    render_direction_imaging(maps, m.screen_xy_mm, m.valid, "x", seq, sensor, np.random.default_rng(0), means=means)
    z = rng.standard_normal(size=(4,) + m.valid.shape, dtype=np.float32)  # the first period's draws
    mean = means[0]
    want = np.clip(np.floor(sensor.dark_dn + mean + np.sqrt(sensor.shot_dn * mean + sensor.const_var_dn2) * z + 0.5),
                   0, sensor.full_scale)
    want = np.where(mean >= sensor.clip_dn, sensor.full_scale, want)
    ok = m.valid
    assert np.array_equal(np.stack(a[:4])[:, ok], want[:, ok].astype(a[0].dtype))
