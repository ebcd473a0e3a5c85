"""Camera model (paper §2.2) against OpenCV (test-only dependency) and round trips."""

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from pmdsim.geometry.camera import Camera

DIST = dict(k1=-0.21, k2=0.13, p1=1.2e-3, p2=-0.8e-3, k3=0.04)


def _camera(**dist):
    return Camera(1920, 1200, 4400.0, 4410.0, 955.3, 603.7, **dist)


@pytest.mark.parametrize("dist", [{}, DIST])
def test_projection_matches_opencv(dist):
    cam = _camera(**dist)
    rng = np.random.default_rng(0)
    p_cam = np.column_stack([rng.uniform(-60, 60, 500), rng.uniform(-40, 40, 500), rng.uniform(300, 600, 500)])
    K, d = cam.as_opencv()
    ref, _ = cv2.projectPoints(p_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d)
    np.testing.assert_allclose(cam.project(p_cam), ref.reshape(-1, 2), atol=1e-9, rtol=0)


def test_undistortion_matches_opencv():
    cam = _camera(**DIST)
    K, d = cam.as_opencv()
    rng = np.random.default_rng(1)
    uv = np.column_stack([rng.uniform(0, 1919, 400), rng.uniform(0, 1199, 400)])
    # OpenCV's undistortPoints iterates a fixed number of times unless asked to converge.
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, d, criteria=crit).reshape(-1, 2)
    xy, ok = cam.pixel_to_normalized(uv)
    assert ok.all()
    # Compare in pixels (scaled by the focal length): 1e-9 px.
    np.testing.assert_allclose(xy * 4400.0, ref * 4400.0, atol=1e-9, rtol=0)


def test_view_rays_round_trip_whole_sensor():
    cam = _camera(**DIST)
    d_cam, ok = cam.sensor_rays()
    assert d_cam.shape == (1200, 1920, 3) and ok.all()
    np.testing.assert_array_equal(d_cam[..., 2], 1.0)
    uv = cam.project(d_cam * 500.0)
    err = np.abs(uv - cam.pixel_grid()).max()
    # Distortion inverted to 1e-12 in normalised coordinates → ≈ 4.4e-9 px at most.
    assert err < 1e-8
    # And the normalised coordinates themselves re-distort to the pixel's to 1e-12.
    xyd = cam.distort(d_cam[..., :2])
    ref = np.stack([(cam.pixel_grid()[..., 0] - cam.ppx_px) / cam.fx_px,
                    (cam.pixel_grid()[..., 1] - cam.ppy_px) / cam.fy_px], axis=-1)
    assert np.abs(xyd - ref).max() <= 1e-12


def test_pixel_origin_is_centre_of_top_left_pixel():
    cam = Camera(4, 3, 10.0, 10.0, 0.0, 0.0)
    # A point on the optical axis lands on (ppx, ppy) = (0, 0): the top-left pixel's centre.
    np.testing.assert_allclose(cam.project([0.0, 0.0, 5.0]), [0.0, 0.0])
    np.testing.assert_allclose(cam.pixel_grid()[0, 0], [0.0, 0.0])
    np.testing.assert_allclose(cam.pixel_grid()[2, 3], [3.0, 2.0])


def test_points_behind_camera_are_nan():
    cam = _camera()
    assert np.isnan(cam.project([0.0, 0.0, -1.0])).all()


def test_non_invertible_distortion_is_reported():
    # Strong barrel distortion folds over beyond some radius: no inverse exists there.
    cam = Camera(1920, 1200, 400.0, 400.0, 960.0, 600.0, k1=-0.5)
    xy, ok = cam.pixel_to_normalized(np.array([[1919.0, 1199.0], [960.0, 600.0]]))
    assert not ok[0] and ok[1]


def test_opencv_round_trip_of_parameters():
    K = np.array([[1000.0, 0, 320.5], [0, 1001.0, 240.25], [0, 0, 1]])
    cam = Camera.from_opencv(K, [0.1, -0.05, 1e-3, 2e-3], (640, 480))
    K2, d2 = cam.as_opencv()
    np.testing.assert_array_equal(K, K2)
    np.testing.assert_array_equal(d2, [0.1, -0.05, 1e-3, 2e-3, 0.0])


@pytest.mark.parametrize("kw", [dict(fx_px=0.0), dict(fy_px=-1.0), dict(width_px=0), dict(ppx_px=np.nan), dict(k1=np.inf)])
def test_invalid_parameters_rejected(kw):
    args = dict(width_px=10, height_px=10, fx_px=10.0, fy_px=10.0, ppx_px=5.0, ppy_px=5.0)
    args.update(kw)
    with pytest.raises(ValueError):
        Camera(**args)


# ---------------------------------------------------------------- OpenCV's full model (issue 12)
def test_brown_camera_computes_eq3_bit_for_bit():
    # The rational/thin-prism terms at 0 must not change a Brown camera by a single bit: the
    # distortion equals eq. (3) written out, operation for operation.
    cam = _camera(**DIST)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-0.3, 0.3, (2, 1000))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (DIST["k1"] + r2 * (DIST["k2"] + r2 * DIST["k3"]))
    xd = x * radial + 2.0 * DIST["p1"] * x * y + DIST["p2"] * (r2 + 2.0 * x * x)
    yd = y * radial + DIST["p1"] * (r2 + 2.0 * y * y) + 2.0 * DIST["p2"] * x * y
    np.testing.assert_array_equal(cam.distort(np.stack([x, y], -1)), np.stack([xd, yd], -1))


def test_opencv_vector_lengths():
    K = np.array([[1000.0, 0, 320.5], [0, 1001.0, 240.25], [0, 0, 1]])
    d12 = np.arange(1, 13) * 1e-3
    cam = Camera.from_opencv(K, d12, (640, 480))
    assert [getattr(cam, n) for n in ("k4", "k5", "k6", "s1", "s2", "s3", "s4")] == d12[5:].tolist()
    np.testing.assert_array_equal(cam.distortion, d12)
    np.testing.assert_array_equal(cam.as_opencv(14)[1], np.r_[d12, 0.0, 0.0])
    with pytest.raises(ValueError, match="8-coefficient .* s1, s2, s3, s4"):
        cam.as_opencv(8)
    cam8 = Camera.from_opencv(K, d12[:8], (640, 480))
    assert cam8.distortion.size == 8 and not cam8.is_brown
    assert Camera.from_opencv(K, d12[:5], (640, 480)).is_brown
    assert Camera.from_opencv(K, [], (640, 480)).distortion.tolist() == [0.0] * 5


@pytest.mark.parametrize("kw", [dict(k4=np.nan), dict(s3=np.inf)])
def test_invalid_new_coefficients_rejected(kw):
    with pytest.raises(ValueError):
        Camera(10, 10, 10.0, 10.0, 5.0, 5.0, **kw)


@pytest.mark.parametrize("dist", [{}, DIST])
def test_sensor_rays_kernel_matches_opencv(dist):
    """The fused ray kernel (issue 25): every pixel of a small sensor against
    cv2.undistortPoints (1e-9 px), and view_rays of arbitrary (…, 2) pixels equal to the sensor
    rays of the same pixels."""
    cam = Camera(96, 64, 80.0, 81.0, 47.2, 31.6, **dist)
    d, ok = cam.sensor_rays()
    assert d.shape == (64, 96, 3) and ok.all() and not d.flags.writeable
    K, dv = cam.as_opencv()
    v, u = np.mgrid[0:64, 0:96]
    uv = np.stack([u, v], -1).astype(float)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dv, criteria=crit).reshape(64, 96, 2)
    np.testing.assert_allclose(d[..., :2] * 80.0, ref * 80.0, atol=1e-9, rtol=0)
    np.testing.assert_array_equal(d[..., 2], 1.0)
    sub = uv[5:9, 10:13]
    d_sub, ok_sub = cam.view_rays(sub)
    assert d_sub.shape == (4, 3, 3) and ok_sub.all()
    np.testing.assert_array_equal(d_sub, d[5:9, 10:13])
