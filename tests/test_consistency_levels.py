"""The checks' one-pass stack test (issue 25, item 1, :mod:`pmdsim.evaluation.consistency_levels`)
against numpy written from the module docstring of :mod:`pmdsim.evaluation.consistency`: the
N-step fit by lstsq-free sums, σ_I² = max(min_s(a_s + b_s·A), σ²), RSS/σ_I²/threshold, the
decoder's σ model, the coarse coordinate and its refinement by the finer period (with a reversed
contrast corrected by π). Flags and counts identical; floats to 1e-12 relative (the kernel's
atan2 is within 1e-15 rad of libm's)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pmdsim.evaluation.consistency_levels import LevelBuffers, check_level


def _fit(stack):
    n = stack.shape[0]
    d = 2 * np.pi * np.arange(n) / n
    x = stack.astype(float)
    a = x.mean(0)
    c = 2 * np.tensordot(np.cos(d), x, 1) / n
    s = 2 * np.tensordot(np.sin(d), x, 1) / n
    r = x - a - c * np.cos(d)[:, None, None] - s * np.sin(d)[:, None, None]
    return a, np.hypot(c, s), np.mod(np.arctan2(s, c), 2 * np.pi), (r * r).sum(0), np.abs(r).argmax(0)


def _run(buf, stack, level, p, lines, given2, tested, rev, fit_ratio, worst, mis, mask=None):
    n = stack.shape[0]
    thr = 9.0 if n > 3 else 0.0
    return check_level(buf, stack, first=3, thr=thr, lines=lines, given2=given2, tested=tested, level=level, p=p,
                       origin=0.0, upper=300.0, z=4.9, rev=rev, fit_ratio=fit_ratio, worst_image=worst,
                       mis_ratio=mis, mask=mask)


@pytest.mark.parametrize("n, with_lines, dtype", [(4, True, np.uint8), (5, True, np.uint8), (5, False, np.float64),
                                                  (3, True, np.uint8)])
def test_two_levels_match_numpy(n, with_lines, dtype):
    rng = np.random.default_rng(n)
    h, w = 23, 37
    v, u = np.mgrid[0:h, 0:w]
    coord = 20.0 + 6.0 * u + 0.5 * v  # mm on the screen
    periods = (280.0, 35.0)
    d = 2 * np.pi * np.arange(n) / n
    stacks = []
    for p in periods:
        phi = 2 * np.pi * coord / p
        img = 120 + 80 * np.cos(phi[None] - d[:, None, None]) + rng.normal(0, 2.0, (n, h, w))
        img[:, 3, 4] += 60 * (np.arange(n) == 1)  # a bad frame at one pixel
        if p == periods[1]:  # a reversed, low-contrast pixel (the decoder corrects it by π)
            img[:, 11, 12] = 120 + 15 * np.cos(phi[11, 12] + np.pi - d)
        stacks.append(np.clip(np.round(img), 0, 255).astype(dtype) if dtype != np.float64 else img)
    stacks[1][:, 7, 9] = stacks[1][::-1, 7, 9]  # a pixel whose fine phase disagrees
    lines = np.array([[4.0, 0.01], [3.0, 0.02]]) if with_lines else None
    given2 = np.broadcast_to(np.float64(0.3), (h, w))
    tested = np.ones((h, w), bool)
    tested[0, :5] = False
    rev = np.zeros((h, w), bool)
    rev[11, 12] = True
    fit_ratio = np.full((h, w), np.nan, np.float32)
    mis = np.full((h, w), np.nan, np.float32)
    worst = np.full((h, w), -1, np.int16)
    buf = LevelBuffers(h, w)
    mask = tested & (u % 3 == 0)

    out0 = _run(buf, stacks[0], 0, periods[0], lines, given2, tested, rev, fit_ratio, worst, mis, mask)
    a0, b0, phi0, rss0, k0 = _fit(stacks[0])
    if with_lines:
        ac = np.clip(np.nan_to_num(a0), 0.0, None)
        s2_0 = np.maximum(np.min(lines[:, :1, None] + lines[:, 1:, None] * ac, axis=0), given2)
    else:
        s2_0 = np.array(given2)
    sig0 = periods[0] / (2 * np.pi) * math.sqrt(2.0 / n) * np.sqrt(s2_0) / b0
    c0 = np.mod(periods[0] * phi0 / (2 * np.pi), periods[0])
    c0 = np.where(c0 > 300.0, c0 - periods[0], c0)
    np.testing.assert_allclose(buf.c, c0, rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(buf.sig, sig0, rtol=1e-12)
    np.testing.assert_allclose(buf.ratio, b0 / a0, rtol=1e-12)
    np.testing.assert_array_equal(out0[3], a0[mask])  # the same sums in the same order: bit for bit
    assert out0[2] == pytest.approx(s2_0[tested].max(), rel=1e-15)
    if n > 3:
        rf0 = rss0 / s2_0 / 9.0
        bad = tested & (rf0 > 1.0)
        np.testing.assert_array_equal(buf.bad_fit, bad)
        assert out0[0] == bad.sum() and bad[3, 4]
        np.testing.assert_allclose(fit_ratio[tested], rf0[tested].astype(np.float32), rtol=1e-6)
        assert np.isnan(fit_ratio[~tested]).all()
        k_ref = np.full((h, w), n) if n == 4 else k0
        np.testing.assert_array_equal(worst[tested], 3 + k_ref[tested])
    else:
        assert out0[0] == 0 and np.isnan(fit_ratio).all()
    assert out0[1] == 0
    buf.swap()

    out1 = _run(buf, stacks[1], 1, periods[1], lines, given2, tested, rev, fit_ratio, worst, mis)
    a1, b1, phi1, rss1, _ = _fit(stacks[1])
    if with_lines:
        s2_1 = np.maximum(np.min(lines[:, :1, None] + lines[:, 1:, None] * np.clip(a1, 0, None), axis=0), given2)
    else:
        s2_1 = np.array(given2)
    sig1 = periods[1] / (2 * np.pi) * math.sqrt(2.0 / n) * np.sqrt(s2_1) / b1
    p = periods[1]
    fine = p * phi1 / (2 * np.pi)
    ck = fine + p * np.floor((c0 - fine) / p + 0.5)
    fine_r = p * (phi1 + np.pi) / (2 * np.pi)  # the reversed pixel, corrected by π
    flip = rev & (np.abs(c0 - ck) >= 0.375 * p) & (b1 / a1 <= 0.25 * b0 / a0)
    assert flip[11, 12]
    ck = np.where(flip, fine_r + p * np.floor((c0 - fine_r) / p + 0.5), ck)
    ratio1 = np.abs(c0 - ck) / (4.9 * np.hypot(sig0, sig1))
    np.testing.assert_allclose(buf.c, ck, rtol=1e-12, atol=1e-10)
    bad1 = tested & (ratio1 > 1.0)
    np.testing.assert_array_equal(buf.bad_per, bad1)
    assert out1[1] == bad1.sum() and bad1[7, 9] and not bad1[11, 12]
    np.testing.assert_allclose(mis[tested], ratio1[tested].astype(np.float32), rtol=1e-6, atol=1e-9)
    assert np.isnan(mis[~tested]).all()
    assert out1[3] is None


def test_with_consistency_in_place_equals_the_copy():
    """``in_place``: the flagged pixels' coordinates and σ become NaN in the decoder's own arrays
    — the same maps as numpy's ``where`` copy, and the arrays returned are the inputs."""
    import types

    from pmdsim.evaluation.consistency import with_consistency
    from pmdsim.evaluation.phase import ScreenCoordinates

    rng = np.random.default_rng(3)
    h, w = 9, 11
    flags = np.where(rng.random((h, w)) < 0.2, np.uint8(1), np.uint8(0))
    xy = rng.normal(size=(h, w, 2))
    std = rng.random((h, w, 2))
    extra = np.where(rng.random((h, w)) < 0.2, np.uint8(64), np.uint8(0))
    dec = ScreenCoordinates(screen_xy_mm=xy, valid=flags == 0, flags=flags, std_xy_mm=std,
                            modulation=np.ones((h, w, 2)), offset=np.ones((h, w, 2)),
                            reversed=np.zeros((h, w, 2), bool))
    keep = flags | extra
    ref_xy = np.where((keep == 0)[..., None], xy, np.nan)
    ref_std = np.where((keep == 0)[..., None], std, np.nan)
    got = with_consistency(dec, types.SimpleNamespace(flags=extra), in_place=True)
    assert got.screen_xy_mm is xy and got.std_xy_mm is std
    np.testing.assert_array_equal(got.screen_xy_mm, ref_xy)
    np.testing.assert_array_equal(got.std_xy_mm, ref_std)
    np.testing.assert_array_equal(got.valid, keep == 0)
    ro = xy.copy()
    ro.flags.writeable = False  # read-only input: a copy, the input untouched
    got = with_consistency(dec.__class__(**{**dec.__dict__, "screen_xy_mm": ro}), types.SimpleNamespace(flags=extra),
                           in_place=True)
    assert got.screen_xy_mm is not ro
