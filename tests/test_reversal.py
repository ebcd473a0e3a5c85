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
