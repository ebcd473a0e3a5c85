"""The fused two-direction decoder (pmdsim.evaluation.decoding_fused, issue 25 item 3) against an
independent numpy reference of the N-step phase and of hierarchical unwrapping.

The reference is written from docs/conventions.md ("Fringe patterns") and the documented flag
rules (pmdsim.evaluation.phase_flags), with numpy's arctan2 and hypot: nothing of the module under
test. The images are handed over as per-image lists (the path of ``decode_images``, no stacking),
as stacks, and with mixed dtypes.
"""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation.phase import PhaseFlag, decode_screen_coordinates
from pmdsim.evaluation.decoding_fused import ImageList, as_image_list

H, W = 24, 40
SIZE_MM = (300.0, 200.0)
ORIGIN_MM = (5.0, -3.0)


def _images(coord_mm, period_mm, n, offset, amplitude, dtype, full):
    """List of N (H, W) images I_k = A + B cos(2πc/p − 2πk/N), rounded and clipped."""
    out = []
    for k in range(n):
        i_k = offset + amplitude * np.cos(2 * np.pi * coord_mm / period_mm - 2 * np.pi * k / n)
        out.append(np.clip(np.rint(i_k), 0, full).astype(dtype))
    return out


def _reference_direction(stacks, periods, extent, origin, full, noise, tol=0.25):
    """Numpy reference of one direction: (coord, flags, B, A, σ) of the finest period, (H, W)."""
    order = np.argsort(periods)[::-1]
    flags = np.zeros((H, W), np.uint8)
    upper = origin + extent + 0.5 * (periods[order[0]] - extent)
    coord = None
    for level, i in enumerate(order):
        imgs = np.asarray(stacks[i], dtype=np.float64)
        n, p = imgs.shape[0], periods[i]
        delta = 2 * np.pi * np.arange(n) / n
        c = (2 / n) * np.tensordot(np.cos(delta), imgs, 1)
        s = (2 / n) * np.tensordot(np.sin(delta), imgs, 1)
        a = imgs.mean(0)
        b = np.hypot(c, s)
        phi = np.mod(np.arctan2(s, c), 2 * np.pi)
        flags |= np.where(a < 0.02 * full, np.uint8(PhaseFlag.DARK), np.uint8(0))
        flags |= np.where(imgs.max(0) >= full, np.uint8(PhaseFlag.SATURATED), np.uint8(0))
        flags |= np.where((b < 0.01 * full) | (b < 0.05 * a), np.uint8(PhaseFlag.LOW_MODULATION), np.uint8(0))
        fine = p * phi / (2 * np.pi)
        if level == 0:
            coord = origin + np.mod(fine - origin, p)
            coord = np.where(coord > upper, coord - p, coord)
        else:
            new = fine + p * np.floor((coord - fine) / p + 0.5)
            flags |= np.where(np.abs(coord - new) > tol * p, np.uint8(PhaseFlag.UNWRAP_INCONSISTENT), np.uint8(0))
            coord = new
    sigma = periods[order[-1]] / (2 * np.pi) * np.sqrt(2 / n) * noise / b
    return coord, flags, b, a, sigma


def _field(lo, hi, transpose):
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    t = v / (H - 1) if transpose else u / (W - 1)
    s = u / (W - 1) if transpose else v / (H - 1)
    g = 0.8 * t + 0.2 * s**2
    return lo + (hi - lo) * (g - g.min()) / (g.max() - g.min())


def _case(x_dtype, y_dtype, full):
    cx = _field(ORIGIN_MM[0] + 1.0, ORIGIN_MM[0] + SIZE_MM[0] - 1.0, False)
    cy = _field(ORIGIN_MM[1] + 1.0, ORIGIN_MM[1] + SIZE_MM[1] - 1.0, True)
    xp, yp = [320.0, 40.0, 8.0], [12.0, 220.0, 36.0]  # y in display order, not sorted
    a, b = 0.5 * full, 0.38 * full
    xs = [_images(cx, p, 4, a, b, x_dtype, full) for p in xp]
    ys = [_images(cy, p, n, a, b, y_dtype, full) for p, n in zip(yp, (5, 3, 4))]
    for im in xs[1]:
        im[2:5, 3:7] = 0  # DARK in one x period
    xs[2][1][8:10, 10:14] = full  # SATURATED
    for im in ys[2]:
        im[12:15, 20:25] = int(a)  # LOW_MODULATION (constant)
    k = np.arange(4).reshape(-1, 1, 1)
    wrong = a + b * np.cos(2 * np.pi * (cx[16:20, 30:36] + 20.0) / 40.0 - 2 * np.pi * k / 4)  # half a period off
    for i in range(4):
        xs[1][i][16:20, 30:36] = np.rint(wrong[i]).astype(x_dtype)  # UNWRAP_INCONSISTENT at the next level
    return xs, xp, ys, yp


@pytest.mark.parametrize("x_dtype, y_dtype, full", [(np.uint8, np.uint8, 255), (np.uint16, np.uint16, 4095),
                                                    (np.uint8, np.uint16, 255), (np.float32, np.float64, 255)])
def test_fused_decoder_matches_numpy_reference(x_dtype, y_dtype, full):
    xs, xp, ys, yp = _case(x_dtype, y_dtype, full)
    noise = np.linspace(0.3, 0.6, H).reshape(H, 1)
    res = decode_screen_coordinates(xs, xp, ys, yp, SIZE_MM, full, noise_std=noise, screen_origin_mm=ORIGIN_MM)
    ref = [_reference_direction(xs, xp, SIZE_MM[0], ORIGIN_MM[0], full, noise),
           _reference_direction(ys, yp, SIZE_MM[1], ORIGIN_MM[1], full, noise)]
    flags = ref[0][1] | ref[1][1]
    # In the constant patch B ≈ 0: its phase is rounding noise and whether the unwrapping also
    # flags it depends on the last bits of the sums: compare the other bits there.
    const = np.zeros((H, W), bool)
    const[12:15, 20:25] = True
    unwrap = np.uint8(PhaseFlag.UNWRAP_INCONSISTENT)
    np.testing.assert_array_equal(res.flags[~const], flags[~const])
    np.testing.assert_array_equal(res.flags[const] & ~unwrap, flags[const] & ~unwrap)
    flags = res.flags
    np.testing.assert_array_equal(res.valid, flags == 0)
    for bit in (PhaseFlag.DARK, PhaseFlag.SATURATED, PhaseFlag.LOW_MODULATION, PhaseFlag.UNWRAP_INCONSISTENT):
        assert (flags & bit).any(), bit  # every rule is exercised
    ok = flags == 0
    assert not res.reversed[~const].any()  # the constant patch has a tiny contrast: may count as reversed
    for d in range(2):
        coord, _, b, a, sigma = ref[d]
        np.testing.assert_allclose(res.screen_xy_mm[..., d][ok], coord[ok], rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.std_xy_mm[..., d][ok], sigma[ok], rtol=1e-12)
        np.testing.assert_allclose(res.modulation[..., d], b, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(res.offset[..., d], a, rtol=1e-13)
        assert np.isnan(res.screen_xy_mm[..., d][~ok]).all() and np.isnan(res.std_xy_mm[..., d][~ok]).all()
    stacked = decode_screen_coordinates([np.stack(s) for s in xs], xp, [np.stack(s) for s in ys], yp, SIZE_MM, full,
                                        noise_std=noise, screen_origin_mm=ORIGIN_MM)
    for name in ("screen_xy_mm", "std_xy_mm", "modulation", "offset", "flags", "valid", "reversed"):
        assert getattr(stacked, name).tobytes() == getattr(res, name).tobytes(), name


def test_image_list_uses_the_images_in_place():
    imgs = [np.full((3, 4), k, np.uint8) for k in range(4)]
    lst = as_image_list(imgs, "images")
    assert isinstance(lst, ImageList) and lst.shape == (4, 3, 4) and lst.dtype == np.uint8
    assert all(a is b for a, b in zip(lst, imgs))  # no copy
    stack = np.arange(3 * 2 * 5, dtype=np.int16).reshape(3, 2, 5)
    lst = as_image_list(stack, "images")
    assert lst.shape == (3, 2, 5) and all(np.shares_memory(im, stack) for im in lst)
    lst = as_image_list([np.ones((2, 2), bool)] * 3, "images")  # converted as _as_image_stack does
    assert lst.dtype == np.uint8
