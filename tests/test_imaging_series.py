"""Truncation of the image-formation series (docs/conventions.md, "Image formation: truncation of
the series"): the envelope it rests on, checked against scipy's Bessel function, and rendered
images with the cut against the uncut series (every harmonic, every alias up to the cap)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import j1

from pmdsim.setup import default_setup
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.imaging import HOLD_ALIASES, TRUNCATION_TOLERANCE_DN, imaging_maps, render_period_imaging
from pmdsim.simulation.imaging_series import JINC_ENVELOPE
from pmdsim.simulation.optics import JINC_TABLE, jinc
from pmdsim.simulation.render import trace_setup_camera

#: Every effect of benchmarks/bench_imaging.py (12-bit sensor, gamma, 8-bit display levels,
#: emission, 0.27 mm screen pixels, pixel area, f/8).
EVERY_EFFECT = dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=16.0, exposure=0.8,
                    display_gamma=2.2, display_black_level=0.001, emission_exponent=2.0,
                    screen_pixel_pitch_mm=0.27, screen_fill_factor=0.8, pixel_area=True,
                    f_number=8.0, focal_length_mm=25.0, display_levels=256)


def test_jinc_envelope_bounds_the_bessel_transfer_and_the_renderers_table():
    """x^(3/2)·|2·J₁(x)/x| ≤ 1.6501 (scipy.special.j1 on [10⁻³, 10⁵], 4.2·10⁶ points; the maximum
    is in the main lobe, x ≈ 2.17; far out the lobes approach the asymptotic amplitude 2·√(2/π)
    from above), and the renderer's interpolated table stays below min(1, C·x^(−3/2)) with the
    kernel's C."""
    x = np.concatenate([np.geomspace(1e-3, 10.0, 200_000), np.linspace(10.0, 1e5, 4_000_000)])
    ratio = np.abs(2.0 * j1(x) / x) * x**1.5
    assert 1.65 < ratio.max() <= 1.6501
    assert 1.5 < abs(x[ratio.argmax()]) < 3.0
    far = ratio[x > 5e4].max()
    assert 2.0 * np.sqrt(2.0 / np.pi) <= far < 1.001 * 2.0 * np.sqrt(2.0 / np.pi)
    assert 1.6501 * (1.0 - 1.0 / 1398.0) ** -1.5 < JINC_ENVELOPE
    xs = np.linspace(0.0, 600.0, 2_000_003)[1::3]
    got = np.array([jinc(v, JINC_TABLE) for v in xs])
    env = np.minimum(1.0, JINC_ENVELOPE / xs**1.5)
    assert np.all(np.abs(got) <= env)


def _means(setup, tol):
    m = trace_setup_camera(setup, "left", store_points=True)
    maps = imaging_maps(setup, "left", m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    out = []
    for d, p in (("x", 48.0), ("x", 2.0), ("y", 2.0)):
        means = np.empty((seq.n_shifts,) + m.valid.shape)
        counts = np.empty(m.valid.shape, dtype=np.int64)
        render_period_imaging(maps, m.screen_xy_mm, m.valid, d, p, seq, sensor, np.random.default_rng(0), tolerance_dn=tol,
                              means=means, counts=counts)
        out.append((means[:, m.valid], counts[m.valid]))
    return out


@pytest.mark.parametrize("lens, tolerances", [("sharp", (TRUNCATION_TOLERANCE_DN, 0.3)),
                                               ("f8", (TRUNCATION_TOLERANCE_DN, 0.03))])
def test_truncated_series_within_its_tolerance_of_the_uncut_series(lens, tolerances):
    """Every effect, downsampled 16× (the real camera's pixel footprint): the mean grey levels with
    the cut differ from the uncut series (every one of the 48 harmonics × 65 aliases) by at most
    the tolerance on the 48 mm and both 2 mm periods. 'f8': the f/8 lens, whose J₁ envelope and
    the pixel area bound the aliases — the default 1e-3 DN already leaves most terms out. 'sharp':
    no defocus; the pixel area alone (one sinc, a z⁻² tail) bounds the staircase's aliases, too
    weakly to leave any term out at 1e-3 DN (the images equal the uncut ones), so 0.3 DN exercises
    the cut there."""
    kw = dict(EVERY_EFFECT)
    if lens == "sharp":
        del kw["f_number"], kw["focal_length_mm"]
    setup = default_setup().with_bulge(3.0).with_imaging(**kw).binned(16)
    uncut = _means(setup, 0.0)
    for (_, counts) in uncut:
        assert np.all(counts == (2 * HOLD_ALIASES + 1) * 48)
    for tol in tolerances:
        cut = _means(setup, tol)
        for (ref, _), (got, _) in zip(uncut, cut):
            assert np.abs(got - ref).max() <= tol
        kept = sum(n.sum() for _, n in cut) / sum(n.sum() for _, n in uncut)
        if lens == "f8":
            assert kept < 0.5
        elif tol > 0.1:
            assert kept < 0.95


def _period_means(setup, periods, tol):
    m = trace_setup_camera(setup, "left", store_points=True)
    maps = imaging_maps(setup, "left", m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    out = []
    for p in periods:
        means = np.empty((seq.n_shifts,) + m.valid.shape)
        counts = np.empty(m.valid.shape, dtype=np.int64)
        render_period_imaging(maps, m.screen_xy_mm, m.valid, "x", p, seq, sensor, np.random.default_rng(0),
                              tolerance_dn=tol, means=means, counts=counts)
        out.append((means[:, m.valid], counts[m.valid]))
    return out


@pytest.mark.parametrize("k", [2, 3])
def test_a_period_of_whole_screen_pixels_renders_as_its_limit(k):
    """A fringe period of exactly k screen pixels puts aliases at frequency zero (r + a = 0 up to
    rounding). The images are continuous in the period: at p = k·P they equal those at
    p = k·P·(1 + 1e-10), where r + a is 1e-10·r away from 0 and the weight sin(πr)/(π(r + a)) is
    well conditioned. (The weight evaluated from rounding noise at p = k·P was off by up to 2 for
    harmonics 15–30 of the 256-level display; its mean grey level by ≈ 0.1–0.5 DN.) Uncut series,
    sharp camera (the staircase resolved), every other effect on."""
    kw = dict(EVERY_EFFECT)
    del kw["f_number"], kw["focal_length_mm"]
    setup = default_setup().with_imaging(**kw).binned(16)
    pitch = setup.imaging.screen_pixel_pitch_mm
    exact, near = _period_means(setup, (k * pitch, k * pitch * (1.0 + 1e-10)), 0.0)
    # the phase moves by 2π·(x/p)·1e-10 ≤ 2e-7 rad at |x| ≤ 300 mm: ≤ 1e-3 DN of a 4095-DN fringe
    assert np.abs(exact[0] - near[0]).max() < 2e-3


def test_harmonics_without_screen_pixels_are_cut_by_the_transfer_envelope():
    """No screen pixels, f/8 and 256 display levels: harmonic n's terms are bounded by
    S_n·E(n/p) (the lens's J₁ envelope), so at 1e-3 DN the harmonic series of the 2 mm period is
    cut short (28.6 of the 48 harmonics kept on average at binning 16; all 48 before the envelope
    was applied), and the means stay within the tolerance of the uncut series."""
    kw = {k: v for k, v in EVERY_EFFECT.items() if k not in ("screen_pixel_pitch_mm", "screen_fill_factor")}
    setup = default_setup().with_imaging(**kw).binned(16)
    uncut = _period_means(setup, (2.0, 48.0), 0.0)
    cut = _period_means(setup, (2.0, 48.0), TRUNCATION_TOLERANCE_DN)
    for (ref, n_ref), (got, n_got) in zip(uncut, cut):
        assert np.all(n_ref == 48)
        assert np.abs(got - ref).max() <= TRUNCATION_TOLERANCE_DN
    assert cut[0][1].mean() < 0.9 * 48  # 2 mm at f/8: the envelope leaves harmonics out


@pytest.mark.parametrize("tol", [float("nan"), -1e-3, float("inf")])
def test_a_tolerance_that_is_not_a_finite_non_negative_number_is_refused(tol):
    setup = default_setup().binned(16)
    m = trace_setup_camera(setup, "left", store_points=True)
    maps = imaging_maps(setup, "left", m)
    with pytest.raises(ValueError, match="tolerance_dn"):
        render_period_imaging(maps, m.screen_xy_mm, m.valid, "x", 2.0, setup.patterns.sequence,
                              SensorModel.from_setup(setup), np.random.default_rng(0), tolerance_dn=tol)
