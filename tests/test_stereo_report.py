"""The stereo agreement report (evaluation/stereo_report.py, issue 25 st25h): the valid-window
masks against a brute-force scan, the window interpolation against the closed form of a
quadratic and the 16-test interpolation, and the report kernel against a per-pixel reference
composed in Python from the residual, projection and interpolation primitives (the residual's
own projection, then one projection per step of the intersection, as the report's definition
reads) and numpy's cross and dot products."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation.stereo import _REPORT_MAX_ITER, _REPORT_TOL_MM, _interp, _project, _residual
from pmdsim.evaluation.stereo_report import _interp_window, _report_kernel, agreement, ok_windows


@pytest.mark.parametrize("shape", [(9, 13), (4, 4), (3, 7), (6, 2)])
def test_ok_windows_equal_a_brute_force_scan(shape):
    rng = np.random.default_rng(sum(shape))
    ok = rng.random(shape) > 0.08
    H, W = shape
    expected = np.zeros(shape, dtype=bool)
    for j in range(1, H - 2):
        for i in range(1, W - 2):
            expected[j, i] = ok[j - 1:j + 3, i - 1:i + 3].all()
    np.testing.assert_array_equal(ok_windows(ok), expected)
    assert not ok_windows(np.ones(shape, bool))[0].any()  # the border rows never hold a full window


def test_window_interpolation_is_exact_for_quadratics_and_equals_the_16_tests():
    H, W = 12, 15
    v, u = np.mgrid[0:H, 0:W].astype(float)
    f = lambda u, v: 0.3 * u * u - 0.2 * u * v + 0.05 * v * v + 2.0 * u - v + 7.0  # noqa: E731
    arr = np.ascontiguousarray(f(u, v)[..., None])
    rng = np.random.default_rng(3)
    ok = rng.random((H, W)) > 0.05
    win = ok_windows(ok)
    a, b = np.empty(1), np.empty(1)
    hits = 0
    for uu, vv in rng.uniform([-0.5, -0.5], [W + 0.5, H + 0.5], size=(400, 2)):
        got = _interp_window(arr, win, uu, vv, a)
        assert got == _interp(arr, ok, uu, vv, b)
        if got:
            hits += 1
            assert a[0] == b[0]
            assert a[0] == pytest.approx(f(uu, vv), abs=1e-9)
    assert hits > 50


def _scene(H=30, W=40):
    """Camera A's rays and screen points, B's model (pinhole with distortion, T_cam_ref a small
    rotation), B's screen points and heights (smooth, with holes), and A's heights."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    oA = np.array([2.0, -1.0, 0.0])
    d = np.stack([(u - W / 2) * 0.004, (v - H / 2) * 0.004, np.ones_like(u)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    q = np.ascontiguousarray(np.stack([u * 0.5 - 10.0, v * 0.5 - 7.0, 300.0 + 0.01 * u], axis=-1))
    zA = 100.0 + 0.02 * u - 0.01 * v + 0.001 * u * v
    zA[3, 5] = np.nan
    a = 0.01
    RB = np.ascontiguousarray([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    tB = np.array([-0.5, 0.3, 0.0])
    camB = np.array([300.0, 310.0, W / 2, H / 2, -0.02, 0.001, 0.0, 0.0005, -0.0003])
    oB = -RB.T @ tB
    qB = np.ascontiguousarray(np.stack([u * 0.45 - 9.0, v * 0.55 - 8.0, 300.0 - 0.02 * v], axis=-1))
    okB = np.ones((H, W), bool)
    okB[10:13, 20:22] = False
    zB = 100.3 + 0.015 * u - 0.012 * v
    zB[20, 8:12] = np.nan
    return oA, d, q, zA, oB, qB, okB, zB, RB, tB, camB


def _reference(oA, d, q, zA, oB, qB, okB, zB, RB, tB, camB):
    """The report's definition per pixel, in Python: the residual's normals at A's height, then
    z ← z_B(projection of A's point at z) until the change is below the tolerance."""
    H, W = zA.shape
    okz = np.isfinite(zB)
    zpad = np.ascontiguousarray(np.nan_to_num(zB)[..., None])
    ang = np.full((H, W), np.nan)
    dz = np.full((H, W), np.nan)
    buf, r, hb = np.empty(3), np.empty(6), np.empty(1)
    for v in range(H):
        for u in range(W):
            z = zA[v, u]
            if not np.isfinite(z) or not _residual(oA, *d[v, u], *q[v, u], z, oB, qB, okB, RB, tB, camB, buf, r):
                continue
            na = np.array([-r[2], -r[3], 1.0])
            nb = np.array([-r[4], -r[5], 1.0])
            ang[v, u] = np.arctan2(np.linalg.norm(np.cross(na, nb)), na @ nb)
            zz = z
            for _ in range(_REPORT_MAX_ITER):
                t = (zz - oA[2]) / d[v, u, 2]
                ok, uu, vv = _project(RB, tB, camB, oA[0] + t * d[v, u, 0], oA[1] + t * d[v, u, 1], zz)
                if not ok or not _interp(zpad, okz, uu, vv, hb):
                    zz = np.nan
                    break
                change, zz = hb[0] - zz, hb[0]
                if abs(change) < _REPORT_TOL_MM:
                    break
            dz[v, u] = z - zz
    return ang, dz


def test_report_kernel_equals_the_per_pixel_definition():
    oA, d, q, zA, oB, qB, okB, zB, RB, tB, camB = _scene()
    ang_ref, dz_ref = _reference(oA, d, q, zA, oB, qB, okB, zB, RB, tB, camB)
    ang, dz = np.empty(zA.shape), np.empty(zA.shape)
    _report_kernel(oA, d, q, zA, oB, qB, ok_windows(okB), np.ascontiguousarray(np.nan_to_num(zB)[..., None]),
                   ok_windows(np.isfinite(zB)), RB, tB, camB, ang, dz)
    # NaN where B does not see the point; the angle from numpy's cross and dot products (to rounding),
    # the discrepancy by the same steps (the same bits)
    np.testing.assert_array_equal(np.isnan(ang), np.isnan(ang_ref))
    np.testing.assert_allclose(ang, ang_ref, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(dz, dz_ref)
    n = zA.size
    assert 0.5 * n < np.isfinite(ang).sum() < n and 0.5 * n < np.isfinite(dz).sum() < np.isfinite(ang).sum()
    # the discrepancy is that of the two height maps where they meet along A's ray (|dz| of order 0.3 mm)
    assert 0.1 < np.nanmedian(np.abs(dz)) < 0.6


def test_agreement_of_two_cameras_takes_each_as_the_others_partner():
    oA, d, q, zA, oB, qB, okB, zB, RB, tB, camB = _scene()
    arrays = {"a": (oA, d, q, np.ones(zA.shape, bool)), "b": (oB, d, qB, okB)}
    eye = (np.eye(3), np.zeros(3), camB)
    cams = {"a": eye, "b": (RB, tB, camB)}
    rep = agreement(arrays, cams, {"a": zA, "b": zB})
    ang_ref, dz_ref = _reference(oA, d, q, zA, oB, qB, okB, zB, RB, tB, camB)
    ang_b, dz_b = _reference(oB, d, qB, zB, oA, q, np.ones(zA.shape, bool), zA, *eye)
    for (ang, dz), (ra, rd) in ((rep["a"], (ang_ref, dz_ref)), (rep["b"], (ang_b, dz_b))):
        np.testing.assert_allclose(ang, ra, rtol=0, atol=1e-15)  # NaN where the reference has NaN
        np.testing.assert_array_equal(dz, rd)
    assert np.isfinite(rep["b"][1]).sum() > 0.2 * zA.size
