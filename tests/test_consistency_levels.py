"""The checks' one-pass test of every stack (issue 25, item 1,
:mod:`pmdsim.evaluation.consistency_levels`) against numpy written from the module docstring of
:mod:`pmdsim.evaluation.consistency`: the N-step fit by lstsq-free sums, σ_I² = max(min_s(a_s +
b_s·A), σ²), RSS/σ_I²/threshold, the decoder's σ model, the coarse coordinate and its refinement
by the finer period (with a reversed contrast corrected by π), for both directions in one pass.
Flags and counts identical; floats to 1e-12 relative (the kernel's atan2 is within 1e-15 rad of
libm's). The test ratios computed in fewer operations decide as the defining expressions (numpy's
``hypot`` and divisions) bit for bit, also at the boundaries where they could not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pmdsim.evaluation.consistency_levels import _fit_ratio_row, _mismatch_ratio_row, check_stacks


def _fit(stack):
    n = stack.shape[0]
    d = 2 * np.pi * np.arange(n) / n
    x = stack.astype(float)
    a = x.mean(0)
    c = 2 * np.tensordot(np.cos(d), x, 1) / n
    s = 2 * np.tensordot(np.sin(d), x, 1) / n
    r = x - a - c * np.cos(d)[:, None, None] - s * np.sin(d)[:, None, None]
    return a, np.hypot(c, s), np.mod(np.arctan2(s, c), 2 * np.pi), (r * r).sum(0), np.abs(r).argmax(0)


def _direction(rng, n, dtype, coord, periods, bad_px, rev_px, odd_px):
    """Two stacks (coarse, fine) of one direction with a bad frame at ``bad_px``, a reversed
    low-contrast pixel in the finer stack at ``rev_px`` and a disagreeing fine phase at ``odd_px``."""
    h, w = coord.shape
    d = 2 * np.pi * np.arange(n) / n
    stacks = []
    for p in periods:
        phi = 2 * np.pi * coord / p
        img = 120 + 80 * np.cos(phi[None] - d[:, None, None]) + rng.normal(0, 2.0, (n, h, w))
        img[(slice(None), *bad_px)] += 60 * (np.arange(n) == 1)
        if p == periods[1]:  # the decoder corrects it by π
            img[(slice(None), *rev_px)] = 120 + 15 * np.cos(phi[rev_px] + np.pi - d)
        stacks.append(np.clip(np.round(img), 0, 255).astype(dtype) if dtype != np.float64 else img)
    stacks[1][(slice(None), *odd_px)] = stacks[1][(slice(None, None, -1), *odd_px)]
    return stacks


@pytest.mark.parametrize("n, with_lines, dtype", [(4, True, np.uint8), (5, True, np.uint8), (5, False, np.float64),
                                                  (3, True, np.uint8)])
def test_both_directions_match_numpy(n, with_lines, dtype):
    rng = np.random.default_rng(n)
    h, w = 23, 37
    v, u = np.mgrid[0:h, 0:w]
    coords = (20.0 + 6.0 * u + 0.5 * v, 10.0 + 0.3 * u + 7.0 * v)  # mm on the screen, x and y
    periods = ((280.0, 35.0), (200.0, 32.0))  # the finer y period a power of two: the other division
    rev_px = ((11, 12), (15, 20))
    odd_px = ((7, 9), (17, 4))
    stacks = [_direction(rng, n, dtype, coords[0], periods[0], (3, 4), rev_px[0], odd_px[0]),
              _direction(rng, n, dtype, coords[1], periods[1], (5, 30), rev_px[1], odd_px[1])]
    lines = np.array([[4.0, 0.01], [3.0, 0.02]]) if with_lines else None
    given2 = np.broadcast_to(np.float64(0.3), (h, w))
    tested = np.ones((h, w), bool)
    tested[0, :5] = False
    rev = np.zeros((h, w, 2), bool)
    rev[rev_px[0] + (0,)] = rev[rev_px[1] + (1,)] = True
    mask = tested & (u % 3 == 0)
    thr = 9.0 if n > 3 else 0.0
    dirs = [[dict(stack=st, p=p, first=3 + 10 * (2 * ax + k), thr=thr)
             for k, (st, p) in enumerate(zip(stacks[ax], periods[ax]))] for ax in range(2)]
    origin, upper, z = (0.0, 0.0), (300.0, 250.0), 4.9
    lo, hi = (15.0, 9.0), (200.0, 150.0)
    out = check_stacks(dirs, lines=lines, given2=given2, tested=tested, rev=rev, z=z, origin=origin, upper=upper,
                       lo=lo, hi=hi, a_stack=0, mask=mask)

    fit_ref = np.full((h, w), np.nan, np.float32)  # the maxima as stored: float32
    worst_ref = np.full((h, w), -1)
    mis_ref = np.full((h, w), np.nan, np.float32)
    flags_ref = np.zeros((h, w), np.uint8)
    s = 0
    for ax in range(2):
        sig_prev = ab_prev = None
        dir_bad = np.zeros((h, w), bool)
        for level, it in enumerate(dirs[ax]):
            p = it["p"]
            a, b, phi, rss, k = _fit(it["stack"])
            if with_lines:
                ac = np.clip(np.nan_to_num(a), 0.0, None)
                s2 = np.maximum(np.min(lines[:, :1, None] + lines[:, 1:, None] * ac, axis=0), given2)
            else:
                s2 = np.array(given2)
            sig = p / (2 * np.pi) * math.sqrt(2.0 / n) * np.sqrt(s2) / b
            if s == 0:
                np.testing.assert_array_equal(out.a_at_mask, a[mask])  # the same sums in the same order
            assert out.top[s] == pytest.approx(s2[tested].max(), rel=1e-15)
            if n > 3:
                rf = rss / s2 / 9.0
                bad = tested & (rf > 1.0)
                np.testing.assert_array_equal(out.bad_fit(s), bad)
                assert out.n_fit[s] == bad.sum() and bad[(3, 4) if ax == 0 else (5, 30)]
                upd = tested & (np.isnan(fit_ref) | (rf > fit_ref))
                fit_ref = np.where(upd, rf, fit_ref).astype(np.float32)
                worst_ref = np.where(upd, it["first"] + (np.full((h, w), n) if n == 4 else k), worst_ref)
            else:
                assert out.n_fit[s] == 0 and not out.bad_fit(s).any()
            if level == 0:
                c = np.mod(origin[ax] + p * phi / (2 * np.pi) - origin[ax], p)
                c = np.where(c > upper[ax], c - p, c)
                assert out.n_per[s] == 0 and not out.bad_per(s).any()
            else:
                fine = p * phi / (2 * np.pi)
                ck = fine + p * np.floor((c - fine) / p + 0.5)
                fine_r = p * (phi + np.pi) / (2 * np.pi)  # the reversed pixel, corrected by π
                flip = rev[..., ax] & (np.abs(c - ck) >= 0.375 * p) & (b / a <= 0.25 * ab_prev)
                assert flip[rev_px[ax]]
                ck = np.where(flip, fine_r + p * np.floor((c - fine_r) / p + 0.5), ck)
                ratio = np.abs(c - ck) / (z * np.hypot(sig_prev, sig))
                bad = tested & (ratio > 1.0)
                np.testing.assert_array_equal(out.bad_per(s), bad)
                assert out.n_per[s] == bad.sum() and bad[odd_px[ax]] and not bad[rev_px[ax]]
                assert out.n_new[s] == np.count_nonzero(bad & ~dir_bad)
                dir_bad |= bad
                mis_ref = np.where(tested & ~(ratio <= mis_ref), ratio, mis_ref).astype(np.float32)
                c = ck
            sig_prev, ab_prev = sig, b / a
            s += 1
        np.testing.assert_allclose(out.final[..., ax], c, rtol=1e-12, atol=1e-10)
        outside = tested & ((c < lo[ax]) | (c > hi[ax]))
        assert outside.any() and out.n_outside[ax] == outside.sum()
        flags_ref[outside] |= 128
    np.testing.assert_array_equal(out.flags, flags_ref)
    np.testing.assert_array_equal(np.isnan(out.fit_ratio), np.isnan(fit_ref))
    np.testing.assert_allclose(out.fit_ratio[tested], fit_ref[tested], rtol=1e-6)
    np.testing.assert_array_equal(out.worst_image, worst_ref)
    assert np.isnan(out.mis_ratio[~tested]).all()
    np.testing.assert_allclose(out.mis_ratio[tested], mis_ref[tested], rtol=1e-6, atol=1e-9)
    assert out.any_bit(out.bits_per, [1, 3]).sum() == np.count_nonzero(out.bad_per(1) | out.bad_per(3))


def _outcomes(r, cur):
    """What a test ratio decides: the test, the update of the stored maximum, the stored value."""
    return r > 1.0, ~(r <= cur), r.astype(np.float32)


def _boundary_cases(r_exact, rng):
    """Stored maxima ``cur`` (float32) at, near and far from the exact ratios, NaN among them."""
    cur = r_exact.astype(np.float32)
    sel = rng.random(r_exact.size)
    cur[sel < 0.3] = np.nextafter(cur[sel < 0.3], np.float32(np.inf))
    cur[sel > 0.8] = np.nan
    return cur


def test_fast_ratios_decide_as_the_defining_expressions():
    """``_mismatch_ratio_row`` and ``_fit_ratio_row`` against |c − c_k|/(z·hypot(σ_prev, σ))
    and RSS/σ_I²/threshold in numpy (libm's hypot, two divisions): the same test outcome, the same
    update of the stored maximum and the same float32 value at every pixel — on random values,
    on ratios within an ulp of 1 and of float32 rounding boundaries, at stored maxima equal to
    the ratio, and for zero, subnormal, huge, infinite and NaN inputs."""
    rng = np.random.default_rng(5)
    m = 40_000
    s2p, s2 = rng.uniform(0.1, 30.0, m), rng.uniform(0.1, 30.0, m)
    b2p, b2 = rng.uniform(1.0, 1e4, m), rng.uniform(1.0, 1e4, m)
    kp, k, z = 0.9, 0.07, 4.9
    sig_p = kp * np.sqrt(s2p) / np.sqrt(b2p)
    sig = k * np.sqrt(s2) / np.sqrt(b2)
    c = rng.uniform(0.0, 700.0, m)
    d = rng.uniform(0.0, 3.0, m) * z * np.hypot(sig_p, sig)
    d[: m // 4] = z * np.hypot(sig_p, sig)[: m // 4]  # ratios at 1 (up to rounding)
    mid = (np.float32(0.75).astype(np.float64) + np.nextafter(np.float32(0.75), np.float32(1)).astype(np.float64)) / 2
    d[m // 4: m // 2] = mid * z * np.hypot(sig_p, sig)[m // 4: m // 2]  # at a float32 midpoint
    ck = c - d
    odd = rng.choice(m, 60, replace=False)  # zero, tiny, huge, non-finite inputs
    for j, (arr, val) in enumerate([(s2p, 0.0), (b2, 1e-320), (s2, 1e300), (b2p, np.inf), (s2, np.nan), (ck, np.nan)]):
        arr[odd[10 * j: 10 * j + 10]] = val
    ck[odd[:5]] = c[odd[:5]]  # |c − c_k| = 0
    with np.errstate(all="ignore"):
        sig_p = kp * np.sqrt(s2p) / np.sqrt(b2p)
        sig = k * np.sqrt(s2) / np.sqrt(b2)
        r_exact = np.abs(c - ck) / (z * np.hypot(sig_p, sig))
    cur = _boundary_cases(r_exact, rng)
    got, exact = np.empty(m), np.empty(m, bool)
    _mismatch_ratio_row(c, ck, s2p, b2p, kp, s2, b2, k, z, cur, got, exact)
    for g, e in zip(_outcomes(got, cur), _outcomes(r_exact, cur)):
        np.testing.assert_array_equal(g, e)
    assert 0 < exact.sum() < m // 2  # the boundary cases took the exact expression, the others not

    rss = rng.uniform(0.0, 300.0, m)
    rss[: m // 4] = (s2 * 9.21)[: m // 4]
    rss[odd[:10]] = 0.0
    with np.errstate(all="ignore"):
        r_exact = rss / s2 / 9.21
    cur = _boundary_cases(r_exact, rng)
    _fit_ratio_row(rss, s2, 9.21, cur, got, exact)
    for g, e in zip(_outcomes(got, cur), _outcomes(r_exact, cur)):
        np.testing.assert_array_equal(g, e)
    assert 0 < exact.sum() < m // 2


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


def test_four_step_row_fit_matches_numpy_sums_bit_for_bit():
    """N = 4 (the one-pass fit of the four rows) and N = 5 (the general loops): A, C, S and RSS of
    a row against the numpy sums in the same order — from 0.0, shift by shift — bit for bit, for
    uint8 and float images (−0.0 and a NaN sample included)."""
    from pmdsim.evaluation.consistency_levels import fit_row, stack_images

    rng = np.random.default_rng(17)
    for n, dtype in ((4, np.uint8), (4, np.float64), (5, np.uint8)):
        d = 2 * np.pi * np.arange(n) / n
        stack = 120 + 90 * np.cos(rng.uniform(0, 6, (1, 3, 41)) - d[:, None, None]) + rng.normal(0, 2, (n, 3, 41))
        stack = stack.astype(dtype) if dtype is np.uint8 else stack
        if dtype is np.float64:
            stack[:, 1, 3] = -0.0
            stack[2, 1, 7] = np.nan
        x = stack[:, 1].astype(np.float64)
        sa, sc, ss = np.zeros(41), np.zeros(41), np.zeros(41)
        for k in range(n):
            sa, sc, ss = sa + x[k], sc + x[k] * np.cos(d[k]), ss + x[k] * np.sin(d[k])
        a, c, s = sa / n, 2.0 * sc / n, 2.0 * ss / n
        rss = np.zeros(41)
        for k in range(n):
            r = x[k] - a - c * np.cos(d[k]) - s * np.sin(d[k])
            rss = rss + r * r
        got = [np.empty(41) for _ in range(5)]
        fit_row(stack_images([stack]), 0, n, 1, np.cos(d), np.sin(d), *got, np.empty(41, np.int64), 1)
        for g, e in zip(got, (a, c, s, rss)):
            np.testing.assert_array_equal(g, e)
            np.testing.assert_array_equal(np.signbit(g), np.signbit(e))
