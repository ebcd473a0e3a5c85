"""OpenCV cameras (issue 12): the full distortion model against cv2, FileStorage files both ways,
rvec/tvec poses, and the camera-model checks (each mistake reproduced, its message asserted).

Everything is compared with OpenCV (cv2.projectPoints, cv2.undistortPoints, cv2.FileStorage,
cv2.Rodrigues, cv2.calibrateCamera, cv2.resize), scipy's Rotation, closed forms or finite
differences — never with pmdsim's own output.
"""

from __future__ import annotations

import math
from dataclasses import replace
import os
import subprocess
import sys
import tomllib
import warnings

import numpy as np
import pytest
import tomli_w

cv2 = pytest.importorskip("cv2")

from scipy.spatial.transform import Rotation  # noqa: E402

from pmdsim.errors import SetupError  # noqa: E402
from pmdsim.geometry.camera import DISTORTION_NAMES, Camera  # noqa: E402
from pmdsim.geometry.camera_checks import CameraModelWarning, fold_over  # noqa: E402
from pmdsim.io.opencv import read_filestorage, read_opencv_camera, write_opencv_camera  # noqa: E402
from pmdsim.setup import default_setup  # noqa: E402
from pmdsim.setup.toml import load_setup, parse_setup  # noqa: E402

W, H = 640, 400
K = np.array([[1400.0, 0.0, 321.3], [0.0, 1410.0, 203.7], [0.0, 0.0, 1.0]])
#: Typical sizes of the coefficients (OpenCV's order k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4).
SCALE = np.array([0.3, 0.1, 2e-3, 2e-3, 0.05, 0.3, 0.1, 0.05, 2e-3, 1e-3, 2e-3, 1e-3])
#: A wide-angle rational model (fx = 600 over 1280 × 800: image corners beyond 70° field angle).
K_WIDE = np.array([[600.0, 0.0, 640.3], [0.0, 601.0, 400.2], [0.0, 0.0, 1.0]])
D_WIDE = np.array([2.5, 1.0, 1e-4, -2e-4, 0.02, 2.9, 1.8, 0.2])


def _coeffs(rng, n):
    """Random OpenCV coefficients of length n (4/5/8/12/14 with τ = 0)."""
    d = np.zeros(14)
    d[:12] = rng.uniform(-1.0, 1.0, 12) * SCALE
    d[min(n, 12):] = 0.0
    return d[:n]


def _points(rng, n=500):
    return np.column_stack([rng.uniform(-60, 60, n), rng.uniform(-40, 40, n), rng.uniform(300, 600, n)])


def _cv_project(p_cam, k, d, rvec=np.zeros(3), tvec=np.zeros(3)):
    uv, _ = cv2.projectPoints(np.asarray(p_cam, float).reshape(-1, 1, 3), rvec, tvec, k, np.asarray(d, float))
    return uv.reshape(-1, 2)


# ============================================================================ projection
@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_projection_matches_cv2_project_points(n):
    rng = np.random.default_rng(100 + n)
    for _ in range(5):
        d = _coeffs(rng, n)
        cam = Camera.from_opencv(K, d, (W, H))
        p = _points(rng)
        np.testing.assert_allclose(cam.project(p), _cv_project(p, K, d), atol=1e-9, rtol=0)


def test_projection_of_wide_angle_rational_model_matches_cv2():
    cam = Camera.from_opencv(K_WIDE, D_WIDE, (1280, 800))
    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(-3, 3, 800), rng.uniform(-2, 2, 800), np.ones(800)]) * 100.0
    np.testing.assert_allclose(cam.project(p), _cv_project(p, K_WIDE, D_WIDE), atol=1e-9, rtol=0)


def test_distortion_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    cam = Camera.from_opencv(K, _coeffs(rng, 12) * 3.0, (W, H))
    xy = rng.uniform(-0.4, 0.4, (200, 2))
    jac = cam.distortion_jacobian(xy)
    h = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (cam.distort(xy + e) - cam.distort(xy - e)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, j], fd, atol=1e-8, rtol=0)


# ============================================================================ undistortion
def _reprojection_of_rays_px(cam, k, d):
    """View rays of every pixel projected back by OpenCV: |error| (H, W) and converged (H, W)."""
    rays, ok = cam.sensor_rays()
    uv = _cv_project(rays.reshape(-1, 3), k, d).reshape(rays.shape[:2] + (2,))
    return np.abs(uv - cam.pixel_grid()).max(axis=-1), ok


@pytest.mark.parametrize("n", [5, 8, 12, 14])
def test_undistortion_round_trip_through_cv2(n):
    rng = np.random.default_rng(200 + n)
    d = _coeffs(rng, n) * 2.0
    cam = Camera.from_opencv(K, d, (W, H)).binned(4)  # 160 × 100 px, the same field
    k, _ = cam.as_opencv()
    err, ok = _reprojection_of_rays_px(cam, k, d)
    assert ok.all()
    assert err.max() < 1e-9


#: A strong rational model whose denominator falls towards a pole beyond the image: Newton's
#: method started at the distorted point (the paper's inversion) converges for only 39 % of the
#: pixels of this camera; the bracketed fallback must find the physical inverse of the others.
K_STRONG = np.array([[314.1, 0.0, 640.3], [0.0, 314.1, 400.2], [0.0, 0.0, 1.0]])
D_STRONG = np.array([0.093, 0.099, -0.004, 0.0, -0.218, -0.174, -0.205, -0.208, 0.003, 0.0, -0.004, -0.001])


@pytest.mark.parametrize("k, d", [(K_WIDE, D_WIDE), (K_STRONG, D_STRONG)], ids=["wide", "strong"])
def test_undistortion_of_strong_rational_models(k, d):
    cam = Camera.from_opencv(k, d, (1280, 800)).binned(8)
    assert fold_over(cam) is None  # the models do not fold inside the image: every pixel has an inverse
    kb, _ = cam.as_opencv()
    err, ok = _reprojection_of_rays_px(cam, kb, d)
    assert ok.all()
    assert err.max() < 1e-9


@pytest.mark.parametrize("n", [5, 8, 12])
def test_undistortion_matches_cv2_undistort_points(n):
    # OpenCV's undistortPoints is a fixed-point iteration: compared where it converges (it is asked
    # to iterate to 1e-15 and its result is checked by projecting it back).
    rng = np.random.default_rng(300 + n)
    d = _coeffs(rng, n)
    cam = Camera.from_opencv(K, d, (W, H))
    uv = np.column_stack([rng.uniform(-0.5, W - 0.5, 400), rng.uniform(-0.5, H - 0.5, 400)])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 5000, 1e-15)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, d, criteria=crit).reshape(-1, 2)
    assert np.abs(_cv_project(np.c_[ref, np.ones(len(ref))], K, d) - uv).max() < 1e-9  # OpenCV converged
    xy, ok = cam.pixel_to_normalized(uv)
    assert ok.all()
    np.testing.assert_allclose(xy * K[0, 0], ref * K[0, 0], atol=1e-9, rtol=0)


def test_fold_detection_agrees_with_the_inversion():
    """Random strong models: without a detected fold every pixel inverts (checked through cv2);
    with a fold inside the image, the pixels beyond it do not."""
    rng = np.random.default_rng(11)
    n_fold = n_clean = 0
    for _ in range(40):
        d = rng.normal(size=12) * SCALE * 3.0
        f = rng.uniform(30.0, 150.0)
        cam = Camera(80, 50, f, f, 40.2, 24.7, *d)
        k, _ = cam.as_opencv()
        err, ok = _reprojection_of_rays_px(cam, k, d)
        if fold_over(cam) is None:
            n_clean += 1
            assert ok.all() and err.max() < 1e-9, (d, f)
        else:
            n_fold += 1
            assert not ok.all(), (d, f)
            assert err[ok].max() < 1e-9
    assert n_fold >= 5 and n_clean >= 5  # both branches exercised


# ============================================================================ checks (item 5)
def test_fold_over_radius_matches_closed_form():
    # Brown with k1 < 0 alone: r_d = r (1 + k1 r²) stops increasing at r = 1/√(−3 k1).
    k1 = -0.5
    cam = Camera(1920, 1200, 400.0, 400.0, 960.0, 600.0, k1=k1)
    f = fold_over(cam)
    r_fold = 1.0 / math.sqrt(-3.0 * k1)
    assert f is not None
    assert 0.0 <= f.radius - r_fold <= f.radius_step  # found within one sampling step after the fold
    # The fold lies at distorted radius (2/3) r_fold from the principal point (px).
    rd_px = math.hypot(f.uv_px[0] - 960.0, f.uv_px[1] - 600.0)
    assert abs(rd_px - 400.0 * 2.0 / 3.0 * r_fold) < 1.0


def test_fold_outside_the_image_is_not_reported():
    # The same lens with a small sensor: the fold (at 2/3·0.816·400 = 218 px) is outside a 200 × 120 image.
    assert fold_over(Camera(200, 120, 400.0, 400.0, 99.5, 59.5, k1=-0.5)) is None


def _write_cv(path, k, d, size, **extra):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if size is not None:
        fs.write("image_width", int(size[0]))
        fs.write("image_height", int(size[1]))
    fs.write("camera_matrix", np.asarray(k, float))
    fs.write("distortion_coefficients", np.asarray(d, float).reshape(-1, 1))
    for key, v in extra.items():
        fs.write(key, v)
    fs.release()
    return path


def test_folding_camera_warns_on_import(tmp_path):
    path = _write_cv(tmp_path / "wide.yml", [[400.0, 0, 960.0], [0, 400.0, 600.0], [0, 0, 1]], [-0.5, 0, 0, 0, 0],
                     (1920, 1200))
    with pytest.warns(CameraModelWarning, match=r"folds over inside the image at field angle 39\.\d+°"):
        read_opencv_camera(path)


def test_folding_camera_warns_on_setup_load(default_toml):
    doc = tomllib.loads(default_toml)
    # Fold at r = 1/√(−3 k1) = 0.289, i.e. (2/3)·0.289·4400 = 847 px from the principal point.
    doc["cameras"]["left"]["distortion"] = {"k1": -4.0}
    with pytest.warns(CameraModelWarning, match="cameras.left: the distortion model folds over"):
        parse_setup(doc)


def test_mild_camera_does_not_warn(tmp_path):
    path = _write_cv(tmp_path / "mild.yml", K, [-0.21, 0.13, 1.2e-3, -0.8e-3, 0.04], (W, H))
    with warnings.catch_warnings():
        warnings.simplefilter("error", CameraModelWarning)
        read_opencv_camera(path)


@pytest.mark.parametrize("k, expected", [
    (K * 1000.0, ["not normalised", "K[2, 2] = 1000.0", "divide K by K[2, 2]"]),
    (np.array([[1400.0, 0.8, 321.3], [0, 1410.0, 203.7], [0, 0, 1]]), ["skew K[0, 1] = 0.8", "not supported"]),
    (np.array([[1400.0, 0, 321.3], [0, -1410.0, 203.7], [0, 0, 1]]), ["fy = K[1, 1] = -1410.0", "flipped"]),
    (K.T.copy(), ["last row", "transposed"]),
])
def test_bad_camera_matrix_in_a_file_is_refused(tmp_path, k, expected):
    path = _write_cv(tmp_path / "cam.yml", k, [0.1, 0, 0, 0, 0], (W, H))
    with pytest.raises(SetupError) as ei:
        read_opencv_camera(path)
    assert str(path) in str(ei.value)
    for s in expected:
        assert s in str(ei.value)


K_HD = np.array([[4400.0, 0.0, 962.5], [0.0, 4400.0, 597.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("k, size, expected", [
    (K_HD, (1200, 1920), ["implausible image size 1200 × 1920", "near the centre of a 1920 × 1200", "swapped"]),
    (K, (320, 200), ["implausible image size 320 × 200", "another resolution", "2.01 × and 2.04 ×"]),
    (K, (0, 0), ["positive", "0 × 0"]),
    (K, (100000, 400), ["implausible image size 100000 × 400", "65536"]),
])
def test_implausible_image_size_is_refused(tmp_path, k, size, expected):
    path = _write_cv(tmp_path / "cam.xml", k, [0.1, 0, 0, 0, 0], size)
    with pytest.raises(SetupError) as ei:
        read_opencv_camera(path)
    for s in expected:
        assert s in str(ei.value)


def test_off_centre_principal_point_warns(tmp_path):
    k = K.copy()
    k[0, 2] = 0.75 * W  # 25 % of the width right of the centre, inside the image
    path = _write_cv(tmp_path / "cam.yml", k, [0.1, 0, 0, 0, 0], (W, H))
    with pytest.warns(CameraModelWarning, match="principal point .* 25 % of the image size from the centre"):
        read_opencv_camera(path)


def test_missing_image_size_is_refused(tmp_path):
    path = _write_cv(tmp_path / "cam.yml", K, [0.1, 0, 0, 0, 0], None)
    with pytest.raises(SetupError, match="no image size .*image_width and image_height.*nodes found: "
                                         "camera_matrix, distortion_coefficients"):
        read_opencv_camera(path)


def test_tilted_sensor_terms_refused_and_zero_tilt_accepted():
    d = np.r_[_coeffs(np.random.default_rng(1), 12), 0.0, 0.0]
    Camera.from_opencv(K, d, (W, H))
    d[12] = 1e-3
    with pytest.raises(SetupError, match=r"tilted-sensor .*\(τx, τy\) = \(0.001, 0.0\).*not supported"):
        Camera.from_opencv(K, d, (W, H))


@pytest.mark.parametrize("n", [3, 6, 13])
def test_wrong_coefficient_count_refused(n):
    with pytest.raises(SetupError, match=f"4, 5, 8, 12 or 14 entries.*got {n}"):
        Camera.from_opencv(K, np.zeros(n), (W, H))


def test_fisheye_file_refused(tmp_path):
    path = _write_cv(tmp_path / "fish.yml", K, [0.1, 0.01, 0.001, 0.0001], (W, H), fisheye_model=1)
    with pytest.raises(SetupError, match="fisheye camera model"):
        read_opencv_camera(path)


# ============================================================================ FileStorage files
def _rational_camera():
    return Camera.from_opencv(K, _coeffs(np.random.default_rng(42), 12), (W, H))


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".xml", ".json"])
@pytest.mark.parametrize("n", [None, 5, 8, 12, 14])
def test_pmdsim_file_read_by_cv2_filestorage(tmp_path, suffix, n):
    cam = _rational_camera() if n is None or n >= 12 else Camera.from_opencv(K, _coeffs(np.random.default_rng(5), n),
                                                                             (W, H))
    path = tmp_path / f"cam{suffix}"
    write_opencv_camera(path, cam, n_coefficients=n)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    k_ref, d_ref = cam.as_opencv(n)
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), k_ref)  # bit for bit
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(), d_ref)
    assert fs.getNode("image_width").real() == W and fs.getNode("image_height").real() == H
    fs.release()
    assert read_opencv_camera(path) == cam  # and back


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_cv2_file_read_by_pmdsim(tmp_path, suffix):
    rng = np.random.default_rng(9)
    d = _coeffs(rng, 12)
    k = K.copy()
    k[0, 0] = 1400.0 + rng.uniform()  # a value that needs all 17 digits
    path = _write_cv(tmp_path / f"cam{suffix}", k, d, (W, H), avg_reprojection_error=0.123,
                     calibration_time="Wed Nov 25 12:00:00 2026", image_points=np.zeros((3, 4, 2), np.float32))
    cam = read_opencv_camera(path)
    k2, d2 = cam.as_opencv(12)
    np.testing.assert_array_equal(k2, k)
    np.testing.assert_array_equal(d2, d)
    assert (cam.width_px, cam.height_px) == (W, H)
    nodes = read_filestorage(path)
    assert nodes["avg_reprojection_error"] == 0.123
    assert nodes["calibration_time"] == "Wed Nov 25 12:00:00 2026"


def test_cv2_image_size_node_and_row_vector(tmp_path):
    # cv::Size written as image_size, and calibrateCamera's 1 × N distortion row.
    path = tmp_path / "cam.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([[0.1, -0.05, 1e-3, 2e-3, 0.01, 0.02, 0.003, 0.001]]))
    fs.write("image_size", (W, H))
    fs.release()
    cam = read_opencv_camera(path)
    assert (cam.width_px, cam.height_px) == (W, H) and (cam.k4, cam.k5, cam.k6) == (0.02, 0.003, 0.001)


def test_calibration_sample_layout_from_cv2_calibrate_camera(tmp_path):
    """A rational-model calibration by cv2.calibrateCamera, saved the way OpenCV's calibration
    sample saves it, read by pmdsim: pmdsim's projection equals OpenCV's with those values."""
    true_d = np.array([-0.2, 0.1, 1e-3, -1e-3, 0.01, 0.05, 0.02, 0.001])
    board = np.array([[x, y, 0.0] for y in range(6) for x in range(9)], np.float32) * 20.0
    rng = np.random.default_rng(4)
    obj, img = [], []
    for _ in range(12):
        rvec = rng.uniform(-0.4, 0.4, 3)
        tvec = np.array([-80.0, -50.0, 0.0]) + rng.uniform(-20, 20, 3) + [0, 0, 900.0]
        uv = _cv_project(board, K, true_d, rvec, tvec)
        obj.append(board)
        img.append(uv.astype(np.float32).reshape(-1, 1, 2))
    rms, k, d, rvecs, tvecs = cv2.calibrateCamera(obj, img, (W, H), None, None, flags=cv2.CALIB_RATIONAL_MODEL)
    path = tmp_path / "out_camera_data.yml"
    _write_cv(path, k, d, (W, H), calibration_time="now", nr_of_frames=12, board_width=9, board_height=6,
              square_size=20.0, flags=cv2.CALIB_RATIONAL_MODEL, fisheye_model=0, avg_reprojection_error=rms,
              per_view_reprojection_errors=np.full((12, 1), rms), extrinsic_parameters=np.zeros((12, 6)))
    cam = read_opencv_camera(path)
    p = _points(rng)
    np.testing.assert_allclose(cam.project(p), _cv_project(p, k, d.ravel()), atol=1e-9, rtol=0)


def test_ros_camera_info_yaml(tmp_path):
    # ROS camera_info files hold the same matrices as plain rows/cols/data mappings.
    path = tmp_path / "left.yaml"
    path.write_text("image_width: 640\nimage_height: 400\ncamera_name: left\ncamera_matrix:\n  rows: 3\n"
                    "  cols: 3\n  data: [1400.0, 0.0, 321.3, 0.0, 1410.0, 203.7, 0.0, 0.0, 1.0]\n"
                    "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n"
                    "  data: [-0.21, 0.13, 0.0012, -0.0008, 0.04]\n", encoding="utf-8")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # OpenCV's own YAML parser reads the same values
    def seq(name):
        node = fs.getNode(name).getNode("data")
        return np.array([node.at(i).real() for i in range(node.size())])

    k_cv, d_cv = seq("camera_matrix"), seq("distortion_coefficients")
    fs.release()
    k2, d2 = read_opencv_camera(path).as_opencv()
    np.testing.assert_array_equal(k2.ravel(), k_cv)
    np.testing.assert_array_equal(d2, d_cv)


def test_unreadable_files(tmp_path):
    with pytest.raises(SetupError, match="does not exist"):
        read_opencv_camera(tmp_path / "missing.yml")
    with pytest.raises(SetupError, match=r"expected \.yml, \.yaml, \.xml or \.json"):
        read_opencv_camera(tmp_path / "cam.txt")
    (tmp_path / "bad.xml").write_text("<opencv_storage><camera_matrix>", encoding="utf-8")
    with pytest.raises(SetupError, match="not valid XML"):
        read_opencv_camera(tmp_path / "bad.xml")
    (tmp_path / "stereo.yml").write_text("%YAML:1.0\n---\nM1: !!opencv-matrix\n   rows: 1\n   cols: 1\n   dt: d\n"
                                         "   data: [ 1. ]\n", encoding="utf-8")
    with pytest.raises(SetupError, match="no camera matrix .*nodes found: M1.*stereo"):
        read_opencv_camera(tmp_path / "stereo.yml")


# ============================================================================ pixel origin
def test_pixel_centres_are_integer_coordinates_as_in_cv2_resize():
    """OpenCV's pixel (0, 0) is the centre of the top-left pixel, as pmdsim's: a blob rendered at a
    camera's projection, area-downsampled by cv2.resize, has its centroid where the binned camera
    (pp' = (pp − (k − 1)/2)/k) projects the same point."""
    cam = Camera(96, 64, 200.0, 200.0, 47.3, 31.8, k1=-0.1)
    p = np.array([3.1, -2.2, 100.0])
    u0, v0 = cam.project(p)
    vv, uu = np.mgrid[0:64, 0:96].astype(float)  # pmdsim's pixel centres
    img = np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * 3.0**2))
    for k in (2, 4):
        small = cv2.resize(img, (96 // k, 64 // k), interpolation=cv2.INTER_AREA)
        v_s, u_s = np.mgrid[0:small.shape[0], 0:small.shape[1]].astype(float)
        centroid = np.array([(small * u_s).sum(), (small * v_s).sum()]) / small.sum()
        np.testing.assert_allclose(cam.binned(k).project(p), centroid, atol=1e-6)
        # The same with OpenCV's convention written out: centre of pixel i at i, so x → (x + 0.5)/k − 0.5.
        np.testing.assert_allclose(centroid, (np.array([u0, v0]) + 0.5) / k - 0.5, atol=1e-6)


def test_cv2_remap_samples_pixel_centres_at_integers():
    # Sampling an image at pmdsim's pixel coordinate of a pixel centre returns that pixel's value.
    img = np.arange(12 * 10, dtype=np.float32).reshape(10, 12)
    cam = Camera(12, 10, 10.0, 10.0, 5.5, 4.5)
    grid = cam.pixel_grid().astype(np.float32)
    out = cv2.remap(img, grid[..., 0], grid[..., 1], interpolation=cv2.INTER_LINEAR)
    np.testing.assert_array_equal(out, img)


# ============================================================================ poses in setups
def _doc_with_pose(default_toml, **pose):
    doc = tomllib.loads(default_toml)
    cam = doc["cameras"]["left"]
    for k in ("origin_world_mm", "angles_deg"):
        cam.pop(k)
    cam.update(pose)
    return doc


def test_rvec_tvec_pose_projects_as_cv2(default_toml):
    rng = np.random.default_rng(21)
    rvec = rng.uniform(-0.5, 0.5, 3)
    tvec = np.array([10.0, -20.0, 300.0])
    setup = parse_setup(_doc_with_pose(default_toml, rvec=rvec.tolist(), tvec=tvec.tolist()))
    cs = setup.cameras["left"]
    p_world = rng.uniform(-50, 50, (300, 3)) + [0, 0, 0]
    uv = cs.camera.project(cs.T_world_cam.inv().apply(p_world))
    k, d = cs.camera.as_opencv()
    np.testing.assert_allclose(uv, _cv_project(p_world, k, d, rvec, tvec), atol=1e-9, rtol=0)
    # OpenCV's rvec/tvec are world → camera: the camera centre is −Rᵀ t.
    r_cv, _ = cv2.Rodrigues(rvec)
    np.testing.assert_allclose(cs.pose.origin_world_mm, -r_cv.T @ tvec, atol=1e-9)
    np.testing.assert_allclose(cs.T_world_cam.rotation, r_cv.T, atol=1e-12)


def test_rotvec_deg_pose_matches_scipy(default_toml):
    rotvec = [12.0, -30.0, 75.0]
    origin = [5.0, 6.0, -295.0]
    setup = parse_setup(_doc_with_pose(default_toml, rotvec_deg=rotvec, origin_world_mm=origin))
    cs = setup.cameras["left"]
    np.testing.assert_allclose(cs.T_world_cam.rotation, Rotation.from_rotvec(rotvec, degrees=True).as_matrix(),
                               atol=1e-12)
    np.testing.assert_allclose(cs.T_world_cam.rotation, cv2.Rodrigues(np.radians(rotvec))[0], atol=1e-12)
    np.testing.assert_array_equal(cs.pose.origin_world_mm, origin)


@pytest.mark.parametrize("pose, expected", [
    (dict(origin_world_mm=[0, 0, 0], angles_deg=[0, 0, 0], rvec=[0, 0, 0], tvec=[0, 0, 0]),
     ["orientation once", "cameras.left.angles_deg and cameras.left.rvec"]),
    (dict(origin_world_mm=[0, 0, 0]), ["orientation once", "found none"]),
    (dict(origin_world_mm=[0, 0, 0], rotvec_deg=[0, 0, 0], tvec=[0, 0, 0]), ["cameras.left.tvec belongs with"]),
    (dict(origin_world_mm=[0, 0, 0], rvec=[0, 0, 0], tvec=[0, 0, 0]), ["remove cameras.left.origin_world_mm"]),
    (dict(rvec=[0, 0, 0]), ["missing key cameras.left.tvec"]),
    (dict(rvec=[0, 0], tvec=[0, 0, 0]), ["cameras.left.rvec must have 3 entries"]),
    # R = Rz(20°)·Ry(90°)·Rx(30°): at the Givens angles' singularity β = 90°.
    (dict(origin_world_mm=[0, 0, 0],
          rotvec_deg=Rotation.from_euler("ZYX", [20, 90, 30], degrees=True).as_rotvec(degrees=True).tolist()),
     ["singularity β = ±90°", "cannot be stored as angles_deg"]),
])
def test_bad_camera_poses_refused(default_toml, pose, expected):
    with pytest.raises(SetupError) as ei:
        parse_setup(_doc_with_pose(default_toml, **pose))
    for s in expected:
        assert s in str(ei.value)


def test_rational_camera_survives_the_setup_file():
    cam = _rational_camera()
    setup = default_setup().with_cameras({"left": default_setup().cameras["left"]})
    setup = setup.with_camera("left", **{f.name: getattr(cam, f.name) for f in cam.__dataclass_fields__.values()})
    doc = tomllib.loads(setup.to_toml())
    assert set(doc["cameras"]["left"]["distortion"]) == {"k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                                                         "s1", "s2", "s3", "s4"}
    assert parse_setup(doc).cameras["left"].camera == cam


# ============================================================================ setups referencing OpenCV files
def _setup_with_opencv_camera(tmp_path, default_toml, camera_file="calib/left.yml", **pose):
    doc = tomllib.loads(default_toml)
    left = doc["cameras"]["left"]
    for k in ("image_size_px", "focal_length_px", "principal_point_px", "distortion", "origin_world_mm",
              "angles_deg"):
        left.pop(k)
    left["opencv"] = camera_file
    left.update(pose)
    (tmp_path / "setup.toml").write_bytes(tomli_w.dumps(doc).encode("utf-8"))
    return tmp_path / "setup.toml"


def test_setup_references_opencv_file_relative_to_itself(tmp_path, default_toml, monkeypatch):
    (tmp_path / "calib").mkdir()
    d = np.array([-0.21, 0.13, 1.2e-3, -0.8e-3, 0.04, 0.01, 0.002, 0.0005])
    k = np.array([[4400.5, 0.0, 961.25], [0.0, 4401.0, 598.75], [0.0, 0.0, 1.0]])
    _write_cv(tmp_path / "calib" / "left.yml", k, d, (1920, 1200))
    rvec, tvec = np.array([0.02, -0.25, 0.01]), np.array([-70.0, 5.0, 300.0])
    path = _setup_with_opencv_camera(tmp_path, default_toml, rvec=rvec.tolist(), tvec=tvec.tolist())
    monkeypatch.chdir(tmp_path / "calib")  # not the setup's directory
    setup = load_setup(path)
    cs = setup.cameras["left"]
    p_world = np.random.default_rng(2).uniform(-60, 60, (200, 3))
    uv = cs.camera.project(cs.T_world_cam.inv().apply(p_world))
    np.testing.assert_allclose(uv, _cv_project(p_world, k, d, rvec, tvec), atol=1e-9, rtol=0)
    # The setup written back is self-contained (the intrinsics inline) and reads to the same camera.
    assert parse_setup(tomllib.loads(setup.to_toml())).cameras["left"].camera == cs.camera


def test_setup_opencv_file_errors(tmp_path, default_toml):
    path = _setup_with_opencv_camera(tmp_path, default_toml, "missing.yml", origin_world_mm=[0, 0, 0],
                                     angles_deg=[0, 0, 0])
    with pytest.raises(SetupError, match=r"cameras\.left\.opencv: .*missing\.yml' does not exist"):
        load_setup(path)
    _write_cv(tmp_path / "left.xml", K * 2.0, [0.1, 0, 0, 0, 0], (W, H))
    path = _setup_with_opencv_camera(tmp_path, default_toml, "left.xml", origin_world_mm=[0, 0, 0],
                                     angles_deg=[0, 0, 0])
    with pytest.raises(SetupError, match=r"cameras\.left\.opencv: .*left\.xml: the camera matrix is not normalised"):
        load_setup(path)
    _write_cv(tmp_path / "left.yml", K, [0.1, 0, 0, 0, 0], (W, H))
    path = _setup_with_opencv_camera(tmp_path, default_toml, "left.yml", origin_world_mm=[0, 0, 0],
                                     angles_deg=[0, 0, 0], focal_length_px=[10.0, 10.0])
    with pytest.raises(SetupError, match=r"cameras\.left\.focal_length_px: the intrinsics come from "
                                         r"cameras\.left\.opencv = 'left\.yml'; give them in one place only"):
        load_setup(path)


def test_cli_shows_setup_with_opencv_camera(tmp_path, default_toml):
    _write_cv(tmp_path / "left.yml", K, [0.1, -0.05, 1e-3, 2e-3, 0.0, 0.01, 0.0, 0.0], (W, H))
    path = _setup_with_opencv_camera(tmp_path, default_toml, "left.yml", rotvec_deg=[0.0, 10.0, 0.0],
                                     origin_world_mm=[-70.0, 0.0, -295.0])
    out = subprocess.run([sys.executable, "-m", "pmdsim.cli", "setup", "--setup", str(path), "--show"],
                         capture_output=True, text=True, cwd=tmp_path.parent)
    assert out.returncode == 0, out.stderr
    left = tomllib.loads(out.stdout)["cameras"]["left"]
    assert left["image_size_px"] == [W, H] and left["focal_length_px"] == [K[0, 0], K[1, 1]]
    assert left["distortion"]["k4"] == 0.01
    np.testing.assert_allclose(left["angles_deg"], [0.0, 10.0, 0.0], atol=1e-12)
    bad = _setup_with_opencv_camera(tmp_path, default_toml, "nope.yml", rotvec_deg=[0.0, 10.0, 0.0],
                                    origin_world_mm=[-70.0, 0.0, -295.0])
    out = subprocess.run([sys.executable, "-m", "pmdsim.cli", "setup", "--setup", str(bad)],
                         capture_output=True, text=True)
    assert out.returncode == 2 and "pmdsim: error:" in out.stderr and "cameras.left.opencv" in out.stderr


@pytest.mark.parametrize("size, pp, expected", [
    ([1200, 1920], [962.5, 597.5], ["cameras.left.image_size_px", "implausible image size 1200 × 1920", "swapped"]),
    ([1920, 1200], [1920.0, 1200.0], ["cameras.left.image_size_px", "does not contain the principal point"]),
])
def test_setup_camera_with_implausible_image_size(default_toml, size, pp, expected):
    doc = tomllib.loads(default_toml)
    doc["cameras"]["left"].update(image_size_px=size, principal_point_px=pp)
    with pytest.raises(SetupError) as ei:
        parse_setup(doc)
    for s in expected:
        assert s in str(ei.value)


def test_tracer_uses_the_full_model():
    """The ray tracer's sample points of a 12-coefficient camera, projected by cv2.projectPoints
    through the camera's pose, land on the pixel centres they were traced from."""
    from pmdsim.simulation.render import trace_setup_camera

    setup = default_setup().binned(16)  # 120 × 75 px
    base = setup.cameras["left"].camera
    d = _coeffs(np.random.default_rng(77), 12) * 2.0
    k = np.array([[base.fx_px, 0, base.ppx_px], [0, base.fy_px, base.ppy_px], [0, 0, 1.0]])
    setup = setup.with_camera("left", distortion=dict(zip(DISTORTION_NAMES, d.tolist())))
    cs = setup.cameras["left"]
    m = trace_setup_camera(setup, "left", store_points=True)
    valid = m.valid
    assert valid.mean() > 0.9
    p_world = setup.sample.T_world_sample.apply(m.p_sample_mm[valid])
    T_cam_world = cs.T_world_cam.inv()
    rvec, _ = cv2.Rodrigues(T_cam_world.rotation)
    uv = _cv_project(p_world, k, d, rvec.ravel(), T_cam_world.translation)
    assert np.abs(uv - cs.camera.pixel_grid()[valid]).max() < 1e-9


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_cv2_structures_beside_the_camera(tmp_path, suffix):
    # Other nodes OpenCV may write beside a camera (sequences of maps, flow maps, sequences of
    # numbers and strings) are read as cv2 wrote them and do not disturb the camera.
    path = tmp_path / f"cam{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.startWriteStruct("views", cv2.FileNode_SEQ)
    for i in range(2):
        fs.startWriteStruct("", cv2.FileNode_MAP)
        fs.write("id", i)
        fs.write("name", f"view {i}")
        fs.write("R", np.eye(3) * (i + 1))
        fs.endWriteStruct()
    fs.endWriteStruct()
    fs.startWriteStruct("flowmap", cv2.FileNode_MAP | cv2.FileNode_FLOW)
    fs.write("a", 1)
    fs.write("b", 2.5)
    fs.endWriteStruct()
    fs.write("strs", ["a b", "c"])
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([0.1, -0.05, 1e-3, 2e-3, 0.01]))  # 1-D: an opencv-nd-matrix
    fs.write("cube", np.arange(8.0).reshape(2, 2, 2))  # a 2 × 2 matrix of 2 channels
    fs.release()
    nodes = read_filestorage(path)
    np.testing.assert_array_equal(nodes["cube"], np.arange(8.0).reshape(2, 2, 2))
    assert [v["id"] for v in nodes["views"]] == [0, 1] and nodes["views"][1]["name"] == "view 1"
    np.testing.assert_array_equal(nodes["views"][1]["R"], 2 * np.eye(3))
    assert nodes["flowmap"] == {"a": 1, "b": 2.5} and nodes["strs"] == ["a b", "c"]
    k2, d2 = read_opencv_camera(path).as_opencv()
    np.testing.assert_array_equal(k2, K)
    np.testing.assert_array_equal(d2, [0.1, -0.05, 1e-3, 2e-3, 0.01])


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="file permissions do not apply (root)")
def test_unreadable_file_permissions(tmp_path):
    path = _write_cv(tmp_path / "cam.yml", K, [0.1, 0, 0, 0, 0], (W, H))
    path.chmod(0)
    try:
        with pytest.raises(SetupError, match="cannot read OpenCV camera file .*cam.yml"):
            read_opencv_camera(path)
    finally:
        path.chmod(0o644)


def test_directory_instead_of_file(tmp_path):
    (tmp_path / "cam.yml").mkdir()
    with pytest.raises(SetupError, match="cannot read OpenCV camera file .*cam.yml"):
        read_opencv_camera(tmp_path / "cam.yml")


def test_byte_order_mark_and_crlf(tmp_path):
    # Files saved by Windows editors: a UTF-8 byte-order mark and CRLF line ends.
    src = _write_cv(tmp_path / "cam.yml", K, [0.1, -0.05, 1e-3, 2e-3, 0.01], (W, H))
    bom = tmp_path / "bom.yml"
    bom.write_bytes(b"\xef\xbb\xbf" + src.read_bytes().replace(b"\n", b"\r\n"))
    assert read_opencv_camera(bom) == read_opencv_camera(src)


def test_calibration_refuses_terms_it_does_not_estimate():
    """The calibration fits only Brown's terms (paper eq. (3)); a camera with OpenCV's rational or
    thin-prism terms is refused by name instead of being calibrated as if they were 0."""
    from pmdsim.calibration.model import CalibrationState, CameraParams
    from pmdsim.errors import SetupError
    from pmdsim.geometry.camera import Camera
    from pmdsim.geometry.transform import RigidTransform

    brown = Camera(fx_px=1000.0, fy_px=1000.0, ppx_px=320.0, ppy_px=240.0, width_px=640, height_px=480, k1=-0.1)
    CalibrationState({"left": CameraParams(brown, RigidTransform(np.eye(3), [0.0, 0.0, 500.0]))}, ())
    rational = replace(brown, k4=0.01)
    with pytest.raises(SetupError, match="'left'.*k4"):
        CalibrationState({"left": CameraParams(rational, RigidTransform(np.eye(3), [0.0, 0.0, 500.0]))}, ())
