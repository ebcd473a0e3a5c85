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
