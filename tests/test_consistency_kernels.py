"""The consistency checks' compiled kernels (issue 25, item 1) against the numpy expressions
they replace: np.gradient/einsum for the orientation test, plane intersections for the nominal
map. Flags must be identical; floats within the stated tolerance."""

from __future__ import annotations

import numpy as np

from pmdsim.evaluation.consistency import _orientation_flipped, nominal_screen_xy
from pmdsim.geometry.camera import Camera
from pmdsim.geometry.transform import RigidTransform


def _numpy_flipped(measured, expected):
    def jac(xy):
        j = np.full(xy.shape[:2] + (2, 2), np.nan)
        if xy.shape[1] >= 2:
            j[..., 0] = np.gradient(xy, axis=1)
        if xy.shape[0] >= 2:
            j[..., 1] = np.gradient(xy, axis=0)
        return j
    j, j0 = jac(measured), jac(expected)
    with np.errstate(invalid="ignore"):
        m = np.linalg.inv(j0) @ j
        return (np.linalg.det(m) < 0) | (np.trace(m, axis1=-2, axis2=-1) < 0)


def test_orientation_kernel_matches_gradient_einsum():
    """A smooth map with a folded patch, a mirrored patch and NaN holes: identical flags."""
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:60, 0:80].astype(float)
    expected = np.stack([2.0 * u + 0.1 * v, -0.05 * u + 1.8 * v], -1)
    measured = expected + 0.3 * np.stack([np.sin(u / 7), np.cos(v / 5)], -1) + rng.normal(0, 0.01, expected.shape)
    measured[10:20, 10:30, 0] *= -1.0  # mirrored in x
    measured[30:40, 40:60] = measured[30:40, 40:60][::-1]  # folded along v
    measured[50, 5:9] = np.nan
    got = _orientation_flipped(measured, expected)
    ref = _numpy_flipped(measured, expected)
    assert got.any() and (~got).any()
    np.testing.assert_array_equal(got, ref)
    one_row = _orientation_flipped(measured[:1], expected[:1])  # an axis of one pixel: untested
    assert not one_row.any()


def test_nominal_map_matches_plane_reflection():
    """Each pixel's ray reflected at the sample plane lands where the numpy plane algebra says
    (1e-9 mm), NaN where the ray does not reach both planes."""
    cam = Camera(width_px=64, height_px=48, fx_px=80.0, fy_px=80.0, ppx_px=31.5, ppy_px=23.5, k1=-0.1, p1=1e-3)
    T_cam = RigidTransform.from_origin_angles([0.0, -300.0, -600.0], [-25.0, 0.0, 0.0])
    T_sample = RigidTransform.from_origin_angles([0.0, 0.0, 0.0], [180.0, 0.0, 0.0])
    T_screen = RigidTransform.from_origin_angles([0.0, 300.0, -600.0], [155.0, 0.0, 0.0])
    got = nominal_screen_xy(cam, T_cam, T_sample, T_screen)
    d_cam, ok = cam.sensor_rays()
    d = d_cam @ T_cam.rotation.T
    n, p0, o = T_sample.rotation[:, 2], T_sample.translation, T_cam.translation
    t = ((p0 - o) @ n) / (d @ n)
    hit = o + t[..., None] * d
    r = d - 2 * (d @ n)[..., None] * n
    m = T_screen.rotation[:, 2]
    t2 = ((T_screen.translation - hit) @ m) / (r @ m)
    q = hit + t2[..., None] * r
    ref = ((q - T_screen.translation) @ T_screen.rotation)[..., :2]
    ref[~(ok & (t > 0) & (t2 > 0))] = np.nan
    assert np.isfinite(ref).any()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_stack_fit_matches_numpy_sums_bit_for_bit():
    """The per-stack fit (A, B, φ, RSS, worst image) against the numpy expressions in the same
    order of operations: A, B, RSS and the worst image identical bit for bit, φ within 1e-15 rad
    of numpy's arctan2 (the kernel uses the decoder's branch-free atan2); uint8, uint16 and float
    stacks, N = 4, 5, 8, with a dropped (black) frame and NaN pixels."""
    from pmdsim.evaluation.consistency import _stack_stats

    rng = np.random.default_rng(11)
    v, u = np.mgrid[0:37, 0:53].astype(float)
    for n, dtype in ((4, np.uint8), (5, np.uint16), (8, np.float64)):
        d = 2 * np.pi * np.arange(n) / n
        phase = 0.3 * u + 0.11 * v
        stack = 120 + 90 * np.cos(phase[None] - d[:, None, None]) + rng.normal(0, 2, (n, 37, 53))
        stack[n - 1, 5:9] = 0.0  # a black frame over a few rows
        if dtype is np.float64:
            stack[2, 20, 30] = np.nan
            stack = stack.astype(dtype)
        else:
            stack = np.clip(np.round(stack), 0, np.iinfo(dtype).max).astype(dtype)
        a_got, b_got, phi_got, rss_got, worst_got = _stack_stats(stack)
        x = stack.astype(np.float64)
        sa = np.zeros(x.shape[1:])
        sc = np.zeros(x.shape[1:])
        ss = np.zeros(x.shape[1:])
        for k in range(n):
            sa += x[k]
            sc += x[k] * np.cos(d[k])
            ss += x[k] * np.sin(d[k])
        a, c, s = sa / n, 2.0 * sc / n, 2.0 * ss / n
        r = np.stack([x[k] - a - c * np.cos(d[k]) - s * np.sin(d[k]) for k in range(n)])
        rss = np.zeros(x.shape[1:])
        for k in range(n):
            rss += r[k] * r[k]
        np.testing.assert_array_equal(a_got, a)
        np.testing.assert_array_equal(b_got, np.sqrt(c * c + s * s))
        np.testing.assert_array_equal(rss_got, rss)
        finite = np.isfinite(rss)
        np.testing.assert_array_equal(worst_got[finite], np.argmax(np.abs(r), axis=0)[finite])
        phi = np.mod(np.arctan2(s, c), 2 * np.pi)
        dphi = np.abs(phi_got - phi)
        dphi = np.minimum(dphi, 2 * np.pi - dphi)  # 0 and 2π are the same phase
        assert np.nanmax(dphi) <= 1e-15
        np.testing.assert_array_equal(np.isnan(phi_got), np.isnan(phi))
        if n > 4:  # (N = 4: every frame has the same |residual|)
            assert worst_got[6, 10] == n - 1  # the black frame is the worst image


def test_stack_fit_at_sampled_pixels_matches_numpy_sums_bit_for_bit():
    """A and RSS of the per-stack fit at sampled pixels (the noise model's) against the numpy
    sums in the same order at those pixels: identical bit for bit; uint8, uint16 and float
    stacks, N = 3 (RSS 0), 4, 5, 8, with a black frame and a NaN pixel."""
    from pmdsim.evaluation.consistency_sample import stack_at_pixels

    rng = np.random.default_rng(13)
    v, u = np.mgrid[0:41, 0:47].astype(float)
    idx = np.sort(rng.choice(41 * 47, 300, replace=False))
    for n, dtype in ((3, np.uint8), (4, np.uint8), (5, np.uint16), (8, np.float64)):
        d = 2 * np.pi * np.arange(n) / n
        stack = 120 + 90 * np.cos((0.3 * u + 0.11 * v)[None] - d[:, None, None]) + rng.normal(0, 2, (n, 41, 47))
        stack[n - 1, 5:9] = 0.0
        if dtype is np.float64:
            stack[1, idx[7] // 47, idx[7] % 47] = np.nan
        else:
            stack = np.clip(np.round(stack), 0, np.iinfo(dtype).max).astype(dtype)
        a_got, rss_got = stack_at_pixels(stack, idx)
        x = stack.astype(np.float64).reshape(n, -1)[:, idx]
        sa, sc, ss = np.zeros(idx.size), np.zeros(idx.size), np.zeros(idx.size)
        for k in range(n):
            sa += x[k]
            sc += x[k] * np.cos(d[k])
            ss += x[k] * np.sin(d[k])
        a, c, s = sa / n, 2.0 * sc / n, 2.0 * ss / n
        rss = np.zeros(idx.size)
        for k in range(n):
            r = x[k] - a - c * np.cos(d[k]) - s * np.sin(d[k])
            rss += r * r
        np.testing.assert_array_equal(a_got, a)
        np.testing.assert_array_equal(rss_got, rss if n > 3 else np.zeros(idx.size))
        assert (dtype is not np.float64) or np.isnan(a_got[7])
