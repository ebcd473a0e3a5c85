"""Contrast reversal (issue 20): a lens transfer 2·J₁(x)/x < 0 flips a fringe by π.

The images are written here from the fringe model of docs/conventions.md, independently of the
decoder: φ = 2π·c/p, δ_k = 2πk/N, I_k = A + T·B·cos(φ − δ_k) with a transfer T = −0.2 (in the
first negative lobe of 2·J₁(x)/x, whose extreme is −0.132… at a single harmonic; −0.2 keeps the
fringe well above the LOW_MODULATION threshold) on a band of columns of the finest period, and
seeded Gaussian intensity noise σ_I. The decoded coordinate is compared with the coordinate the
images were written from, per pixel, against the σ model σ_c = p/(2π)·√(2/N)·σ_I/|T·B|.
"""

from __future__ import annotations

import math

import numpy as np

from pmdsim.evaluation.consistency import check_consistency, with_consistency
from pmdsim.evaluation.phase import (
    PhaseFlag,
    decode_screen_coordinates,
    unwrap_hierarchical,
    wrapped_phase,
)

H, W = 40, 64
SIZE_MM = (300.0, 200.0)
PERIODS_MM = (320.0, 40.0, 8.0, 2.0)
N = 4
A, B = 120.0, 90.0
SIGMA_I = 0.4
BAND = slice(24, 40)  # columns whose finest x fringe is reversed
TRANSFER = -0.2
H_TABLE1, W_TABLE1 = 150, 240  # Table 1's 1920 × 1200 sensor, every 8th pixel


def _coords():
    v, u = np.mgrid[0:H, 0:W].astype(float)
    x = 10.0 + 280.0 * (u + 0.37 * v / H) / W
    y = 10.0 + 180.0 * (v + 0.21 * u / W) / H
    return x, y


def _stack(c, p, transfer, rng):
    d = 2.0 * np.pi * np.arange(N) / N
    phi = 2.0 * np.pi * c / p
    img = A + transfer[None] * B * np.cos(phi[None] - d[:, None, None])
    return img + rng.normal(0.0, SIGMA_I, img.shape)


def _images(transfer_x, seed=1):
    rng = np.random.default_rng(seed)
    x, y = _coords()
    one = np.ones((H, W))
    xs = [_stack(x, p, transfer_x if p == PERIODS_MM[-1] else one, rng) for p in PERIODS_MM]
    ys = [_stack(y, p, one, rng) for p in PERIODS_MM]
    return xs, ys, x, y


def _band_transfer():
    t = np.ones((H, W))
    t[:, BAND] = TRANSFER
    return t


def _decode(xs, ys, **kw):
    return decode_screen_coordinates(xs, PERIODS_MM, ys, PERIODS_MM, SIZE_MM, 255.0, SIGMA_I, **kw)


def test_reversed_band_is_corrected_to_the_sigma_model_and_marked_exactly_there():
    xs, ys, x, y = _images(_band_transfer())
    dec = _decode(xs, ys)
    band = np.zeros((H, W), bool)
    band[:, BAND] = True
    assert dec.valid.all(), PhaseFlag(int(np.bitwise_or.reduce(dec.flags.ravel())))
    np.testing.assert_array_equal(dec.reversed[..., 0], band)
    assert not dec.reversed[..., 1].any()
    sigma_model = PERIODS_MM[-1] / (2 * math.pi) * math.sqrt(2 / N) * SIGMA_I / (abs(TRANSFER) * B)
    z = (dec.screen_xy_mm[..., 0] - x)[band] / sigma_model
    assert np.abs(z).max() < 5.0
    assert 0.8 < np.sqrt(np.mean(z**2)) < 1.25  # 640 samples: ±0.07 at 2.5 σ
    # The decoder's σ prediction uses the reversed fringe's own (weak) modulation, measured with
    # a relative error √(2/N)·σ_I/|T·B| = 1.6 % (1 σ).
    np.testing.assert_allclose(dec.std_xy_mm[..., 0][band], sigma_model, rtol=0.1)
    assert np.abs(dec.screen_xy_mm[..., 1] - y).max() < 5 * sigma_model

    # The same phases through unwrap_hierarchical with their contrasts B/A.
    res = [wrapped_phase(s, max_value=255.0) for s in xs]
    un = unwrap_hierarchical([r.phase for r in res], PERIODS_MM, SIZE_MM[0],
                             contrasts=[r.modulation / r.offset for r in res])
    np.testing.assert_array_equal(un.reversed, band)
    assert np.abs(un.coord_mm - x).max() < 5 * sigma_model
    assert not unwrap_hierarchical([r.phase for r in res], PERIODS_MM, SIZE_MM[0]).reversed.any()

    # Without the correction the band is flagged, never silently wrong.
    off = _decode(xs, ys, correct_reversal=False)
    assert np.all(off.flags[band] & PhaseFlag.UNWRAP_INCONSISTENT)
    assert not off.reversed.any()


def test_consistency_does_not_flag_corrected_pixels_but_flags_a_true_inconsistency():
    xs, ys, x, _ = _images(_band_transfer(), seed=2)
    dec = _decode(xs, ys)
    cons = check_consistency(xs, PERIODS_MM, ys, PERIODS_MM, dec, SIZE_MM, SIGMA_I)
    assert not (cons.flags[:, BAND] & PhaseFlag.PERIOD_MISMATCH).any()
    assert with_consistency(dec, cons).reversed[..., 0][:, BAND].all()


def test_half_period_off_with_strong_contrast_or_weak_and_not_half_a_period_stays_flagged():
    xs, ys, x, _ = _images(np.ones((H, W)), seed=3)
    fine = PERIODS_MM[-1]
    # Row 5: the finest x fringe half a period off at full contrast (a wrong frame, not a lens).
    # Row 9: weak (0.2) and 0.3 periods off: beyond the unwrapping tolerance (0.25) but not a π
    # flip (0.5 ± 0.125).
    d = 2.0 * np.pi * np.arange(N) / N
    for row, shift, t in ((5, 0.5, 1.0), (9, 0.3, 0.2)):
        phi = 2.0 * np.pi * (x[row] / fine + shift)
        xs[-1][:, row] = A + t * B * np.cos(phi[None] - d[:, None])
    dec = _decode(xs, ys)
    for row in (5, 9):
        assert np.all(dec.flags[row] & PhaseFlag.UNWRAP_INCONSISTENT), row
        assert not dec.reversed[row].any(), row
    assert dec.valid[[r for r in range(H) if r not in (5, 9)]].all()


def test_near_a_zero_of_the_transfer_the_pixel_is_low_modulation_not_reversed():
    t = np.ones((H, W))
    t[:, BAND] = -0.01  # |T·B| = 0.9 grey levels: no usable contrast
    xs, ys, _, _ = _images(t, seed=4)
    dec = _decode(xs, ys)
    assert np.all(dec.flags[:, BAND] & PhaseFlag.LOW_MODULATION)
    assert not dec.valid[:, BAND].any()


def test_f8_lens_on_table1_matches_a_pupil_sampled_reference_through_the_decoder():
    """Table 1 (left camera, every 8th pixel of the sensor), f/8, the default focal plane, 16-bit
    noiseless images of the renderer, decoded along x. The reference (numpy, its own geometry)
    traces 16 × 48 rays through the uniform pupil disc (Gauss–Legendre in r², equal angles) to
    the pixel's point on the focal plane, reflects them at the sample plane and averages
    exp(2πi·x_q/p) over their screen hits: the complex transfer T of the 2 mm fringe relative to
    the chief ray. Where |T| > 0.07 (clear of LOW_MODULATION's 0.05), the decoder must mark
    ``reversed`` exactly where Re T < 0 and return the reference's coordinate, chief ray +
    p/2π·arg(±T), with the π flip removed — a flagged or half-period-off pixel fails by far."""
    from pmdsim.evaluation.phase import decode_direction
    from pmdsim.setup import default_setup
    from pmdsim.setup.sensor import SensorModel
    from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
    from pmdsim.simulation.render import trace_setup_camera

    s = default_setup().binned(8).with_patterns(bit_depth=16).with_imaging(f_number=8.0)
    m = trace_setup_camera(s, "left", store_points=True)
    maps = imaging_maps(s, "left", m)
    seq = s.patterns.sequence
    xs = [render_period_imaging(maps, m.screen_xy_mm, m.valid, "x", p, seq, SensorModel.from_setup(s), None)
          for p in seq.periods_x_mm]
    dec = decode_direction(xs, seq.periods_x_mm, s.screen.size_mm[0], 65535.0)

    cs = s.cameras["left"]
    R, O = cs.T_world_cam.rotation, cs.T_world_cam.translation
    D = s.imaging.focal_length_mm / s.imaging.f_number
    Ts, Tq = s.sample.T_world_sample, s.screen.T_world_screen
    ns, ps0, nq, pq0 = Ts.rotation[:, 2], Ts.translation, Tq.rotation[:, 2], Tq.translation
    P = Ts.apply(m.p_sample_mm)
    d = (P - O) / np.linalg.norm(P - O, axis=-1, keepdims=True)
    F = O + (maps.focus_distance_mm / (d @ R[:, 2]))[..., None] * d  # the focal plane ⟂ optical axis
    x, w = np.polynomial.legendre.leggauss(16)
    r = np.repeat(np.sqrt((x + 1) / 2) * D / 2, 48)
    ph = np.tile(2 * np.pi * (np.arange(48) + 0.5) / 48, 16)
    wts = np.repeat(w / 2 / 48, 48)
    pupil = O + (r * np.cos(ph))[:, None] * R[:, 0] + (r * np.sin(ph))[:, None] * R[:, 1]
    pix = [(v, u) for v in range(2, H_TABLE1, 5) for u in range(2, W_TABLE1, 5) if m.valid[v, u]]
    vv, uu = np.array(pix).T
    hits = []
    for v, u in pix:
        dirs = F[v, u] - pupil
        X = pupil + (((ps0 - pupil) @ ns) / (dirs @ ns))[:, None] * dirs
        rr = dirs - 2 * (dirs @ ns)[:, None] * ns
        Q = X + (((pq0 - X) @ nq) / (rr @ nq))[:, None] * rr
        hits.append(((Q - pq0) @ Tq.rotation)[:, 0])
    p = min(seq.periods_x_mm)
    chief = m.screen_xy_mm[vv, uu, 0]
    T = np.exp(2j * np.pi * (np.array(hits) - chief[:, None]) / p) @ wts
    rev = T.real < 0
    strong = np.abs(T) > 0.07
    assert rev.mean() > 0.5 and strong.sum() > 300  # the lens reverses most of Table 1's 2 mm fringes
    assert dec.valid[vv, uu][strong].all()
    np.testing.assert_array_equal(dec.reversed[vv, uu][strong], rev[strong])
    c_ref = chief + p / (2 * np.pi) * np.angle(np.where(rev, -T, T))
    # 10 µm = 0.5 % of the period: the uniform-ellipse model's own error against the reference
    # (docs/benchmarks.md, "Lens transfer") is below it; a π flip left in would be 1000 µm.
    assert np.abs(dec.coord_mm[vv, uu] - c_ref)[strong].max() < 10e-3
