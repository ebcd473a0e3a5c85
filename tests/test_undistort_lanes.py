"""The distortion inversion in lock-step blocks (issue 25 item 3, brown25c): the ray and
undistortion kernels, which run Newton's first attempt over ``_LANES`` pixels at once
(``camera._newton_lanes``), give bit for bit what the per-pixel inversion gives.

The reference is a plain per-pixel loop over ``camera._undistort_one`` (Newton from (xd, yd),
then the damped fallback; the code the kernels ran before the blocks, unchanged), compiled here:
full sensors for the Brown camera of the benchmarks and for the rational, thin-prism,
wide-angle and strong models the OpenCV tests use, a folding lens (most pixels without an
inverse: every lane of most blocks takes the fallback), and point lists whose length is not a
multiple of the block width, with NaN and huge inputs mixed into blocks of valid ones. The
comparison with OpenCV's ``undistortPoints`` is in tests/test_camera.py and
tests/test_opencv_camera.py.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from pmdsim.geometry.camera import (
    _LANES,
    _UNDISTORT_MAX_ITER,
    UNDISTORT_TOL,
    Camera,
    _undistort_one,
    _unpack,
)

_K_TABLE = [[4400.0, 0, 955.3], [0, 4410.0, 603.7], [0, 0, 1]]
_K_WIDE = [[600.0, 0, 640.3], [0, 601.0, 400.2], [0, 0, 1]]
_K_STRONG = [[314.1, 0, 640.3], [0, 314.1, 400.2], [0, 0, 1]]
CAMERAS = {
    "brown_5": (_K_TABLE, [-0.21, 0.13, 1.2e-3, -0.8e-3, 0.04], (1920, 1200)),
    "rational_prism_12": (_K_TABLE, [-0.21, 0.13, 1.2e-3, -0.8e-3, 0.04, 0.05, 0.01, 0.002, 1e-3, -2e-4, -1e-3, 3e-4],
                          (1920, 1200)),
    "wide_rational_8": (_K_WIDE, [2.5, 1.0, 1e-4, -2e-4, 0.02, 2.9, 1.8, 0.2], (1280, 800)),
    "strong_rational_12": (_K_STRONG, [0.093, 0.099, -0.004, 0.0, -0.218, -0.174, -0.205, -0.208, 0.003, 0.0, -0.004,
                                       -0.001], (1280, 800)),
    "folding_k1": ([[400.0, 0, 960.0], [0, 400.0, 600.0], [0, 0, 1]], [-0.5, 0, 0, 0, 0], (1920, 1200)),
}


@numba.njit(cache=False)
def _reference(xyd, coeffs, tol, max_iter):
    """Per-pixel ``_undistort_one`` of (N, 2) normalised points, one after the other."""
    c, rational, prism = _unpack(coeffs)
    out = np.empty_like(xyd)
    ok = np.empty(xyd.shape[0], dtype=np.bool_)
    for i in range(xyd.shape[0]):
        x, y, conv = _undistort_one(xyd[i, 0], xyd[i, 1], c, rational, prism, tol, max_iter)
        out[i, 0] = x
        out[i, 1] = y
        ok[i] = conv
    return out, ok


def _normalised(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """(u − ppx)/fx, (v − ppy)/fy as the kernels compute them (same operations, same bits)."""
    return np.stack([(uv[..., 0] - cam.ppx_px) / cam.fx_px, (uv[..., 1] - cam.ppy_px) / cam.fy_px], axis=-1)


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_sensor_rays_bit_identical_to_the_per_pixel_inversion(name):
    k, dist, size = CAMERAS[name]
    cam = Camera.from_opencv(k, dist, size)
    d, ok = cam._rays(None)
    v, u = np.mgrid[0:cam.height_px, 0:cam.width_px]
    uv = np.stack([u, v], axis=-1).astype(float).reshape(-1, 2)
    ref, ref_ok = _reference(_normalised(cam, uv), cam._coefficients(), UNDISTORT_TOL, _UNDISTORT_MAX_ITER)
    np.testing.assert_array_equal(d.reshape(-1, 3)[:, :2], ref)
    np.testing.assert_array_equal(d[..., 2], 1.0)
    np.testing.assert_array_equal(ok.reshape(-1), ref_ok)
    # Independent of any inversion: the model's forward distortion (eq. 3) of each converged
    # ray gives back its pixel's normalised coordinates.
    xy = d.reshape(-1, 3)[:, :2][ref_ok]
    np.testing.assert_allclose(cam.distort(xy), _normalised(cam, uv)[ref_ok], rtol=0, atol=1e-11)  # tol 1e-12
    if name == "folding_k1":
        assert 0.5 < 1.0 - ref_ok.mean() < 1.0  # most blocks: every lane falls back, and fails
    else:
        assert ref_ok.all()


@pytest.mark.parametrize("name", sorted(CAMERAS))
@pytest.mark.parametrize("n", [1, _LANES - 1, _LANES, 3 * _LANES + 5, 2500])
def test_point_lists_bit_identical_to_the_per_pixel_inversion(name, n):
    """``view_rays`` and ``undistort`` of lists that end mid-block, with non-finite and far
    points between valid ones (each lane stops on its own; the others are unaffected)."""
    k, dist, size = CAMERAS[name]
    cam = Camera.from_opencv(k, dist, size)
    rng = np.random.default_rng(n)
    uv = rng.uniform(-80.0, [cam.width_px + 80.0, cam.height_px + 80.0], size=(n, 2))  # some off the sensor
    xyd = rng.normal(0.0, 0.7, size=(n, 2))
    if n > 3:
        uv[1] = np.nan
        uv[2] = [1e12, -3.0]
        xyd[1] = [np.nan, 0.1]
        xyd[2] = [1e300, 0.0]
        xyd[3] = 0.0
    c = cam._coefficients()
    ref, ref_ok = _reference(_normalised(cam, uv), c, UNDISTORT_TOL, _UNDISTORT_MAX_ITER)
    d, ok = cam.view_rays(uv)
    np.testing.assert_array_equal(d[:, :2], ref)
    np.testing.assert_array_equal(ok, ref_ok)
    ref, ref_ok = _reference(xyd, c, 1e-10, _UNDISTORT_MAX_ITER)
    xy, ok = cam.undistort(xyd, tol=1e-10)
    np.testing.assert_array_equal(xy, ref)
    np.testing.assert_array_equal(ok, ref_ok)
    if n > 3:
        assert not ok[1] and not ok[2] and ok[3] and np.all(xy[3] == 0.0)


def test_max_iter_ends_the_block_as_it_ends_each_pixel():
    """With too few iterations allowed, the lanes stop unconverged where the per-pixel loop
    does, with the same last iterate (then the fallback, with the same limit)."""
    from pmdsim.geometry.camera import _undistort_kernel

    cam = Camera.from_opencv(*CAMERAS["brown_5"])
    xyd = np.random.default_rng(3).uniform(-0.6, 0.6, size=(777, 2))
    mixed = 0
    for max_iter in (1, 2, 3, 4):
        ref, ref_ok = _reference(xyd, cam._coefficients(), UNDISTORT_TOL, max_iter)
        out = np.empty_like(xyd)
        ok = np.empty(xyd.shape[0], dtype=np.bool_)
        _undistort_kernel(xyd, cam._coefficients(), UNDISTORT_TOL, max_iter, out, ok)
        np.testing.assert_array_equal(out, ref)
        np.testing.assert_array_equal(ok, ref_ok)
        mixed += 0 < ref_ok.sum() < ref_ok.size
    assert mixed >= 2  # blocks where some lanes converge within the limit and others do not
