"""Stereo deflectometry (issue 14): absolute heights without a seed, checked against the
simulated truth (the sample the tracer used), through 8-bit images of binned cameras."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pmdsim.evaluation.integration import ReconstructionError
from pmdsim.evaluation.pipeline import decode_images
from pmdsim.evaluation.stereo import evaluate_stereo_decoded, stereo_residual
from pmdsim.geometry.surface import SplineSurface
from pmdsim.geometry.warpage import FoilWarpage
from pmdsim.setup import default_setup
from pmdsim.setup.model import SampleSetup
from pmdsim.simulation.imaging import decoder_response
from pmdsim.simulation.render import render_images, trace_setup_camera

DS = 12  # 160 × 100 px per camera


def _with_heights(setup, gx, gy, z):
    return replace(setup, sample=SampleSetup(setup.sample.pose, tuple(float(v) for v in gx),
                                             tuple(float(v) for v in gy), tuple(tuple(float(v) for v in r) for r in z)))


def _decode_all(truth):
    dec = {}
    for cam in truth.cameras:
        m = trace_setup_camera(truth, cam)
        images = {}
        for spec, img in render_images(truth, cam, m):
            images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        assert all(i.dtype == np.uint8 for v in images.values() for i in v)  # 8-bit images
        dec[cam] = decode_images(truth, images, response=decoder_response(truth))
    return dec


def _sphere(setup, R=1000.0):
    g = np.linspace(0.0, 400.0, 101)
    r2 = (g[None, :] - 200.0) ** 2 + (g[:, None] - 200.0) ** 2
    return _with_heights(setup, g, g, R - np.sqrt(R * R - r2))


def _foil(setup):
    foil = FoilWarpage()
    gx, gy = foil.grid(4.0)
    return _with_heights(setup, gx, gy, foil.on_grid(gx, gy))


@pytest.fixture(scope="module")
def base():
    return default_setup().binned(DS)


@pytest.fixture(scope="module")
def flat_decoded(base):
    return _decode_all(base)


def _errors_um(truth, res):
    """Per camera: |z − z_true| (µm) at every reconstructed pixel, z_true the truth's sample
    surface under the reconstructed point."""
    out = {}
    for cam, c in res.cameras.items():
        p = c.reconstruction.p_sample_mm
        zt = truth.sample.surface.height(p[..., 0], p[..., 1])
        out[cam] = np.abs(c.height_mm - zt) * 1e3
    return out


def _check_within_1um(truth, res, decoded):
    for cam, e in _errors_um(truth, res).items():
        c = res.cameras[cam]
        assert c.overlap.sum() > 0.5 * c.reconstructed.sum(), f"{cam}: overlap too small"
        eo = e[c.overlap]
        assert np.all(np.isfinite(eo))
        out = e[c.reconstructed & ~c.overlap]
        print(f"{cam}: max |z − z_true| over {eo.size} overlap pixels = {eo.max():.4f} µm; "
              f"outside the overlap ({out.size} pixels) {out.max() if out.size else float('nan'):.4f} µm")
        assert eo.max() <= 1.0, f"{cam}: max error {eo.max():.3f} µm > 1 µm"
        # outside the overlap the camera's own slopes extend the surface: every decoded pixel
        # (4-connected to the anchors) is reconstructed
        assert c.reconstruction.converged
        assert c.reconstructed.sum() >= 0.99 * decoded[cam].valid.sum()


def test_flat_true_setup_within_1um_no_seed(base, flat_decoded):
    _, res = evaluate_stereo_decoded(base, flat_decoded)
    _check_within_1um(base, res, flat_decoded)


def test_api_stereo_results_are_read_only_and_equal_the_evaluation(base, flat_decoded):
    """Issue 23: `pmdsim.evaluate_stereo` returns values — its arrays cannot be written (and
    are the same heights as the evaluation layer's)."""
    import pmdsim

    res = pmdsim.evaluate_stereo(flat_decoded, base)
    _, ref = evaluate_stereo_decoded(base, flat_decoded)
    for name, cam in res.cameras.items():
        np.testing.assert_array_equal(cam.height_mm, ref.cameras[name].height_mm)
        for arr in (cam.height_mm, cam.overlap, cam.normal_disagreement_urad, cam.anchor_pixels,
                    cam.reconstruction.p_sample_mm):
            assert not arr.flags.writeable
        with pytest.raises(ValueError):
            cam.height_mm[0, 0] = 1.0


def test_foil_true_setup_within_1um(base):
    truth = _foil(base)
    dec = _decode_all(truth)
    _, res = evaluate_stereo_decoded(truth, dec)
    _check_within_1um(truth, res, dec)
    # the foil is not flat where it is measured: the check has something to find
    c = res.cameras["left"]
    assert np.ptp(c.height_mm[c.overlap]) > 0.1


def test_sphere_1m_within_1um(base):
    truth = _sphere(base)
    dec = _decode_all(truth)
    _, res = evaluate_stereo_decoded(truth, dec)
    _check_within_1um(truth, res, dec)
    assert np.nanmax(res.cameras["left"].height_mm) > 5.0  # far from the table plane z = 0


def test_bulge_3mm_with_true_screen_within_1um(base):
    truth = base.with_bulge(3.0)
    dec = _decode_all(truth)
    _, res = evaluate_stereo_decoded(truth, dec, screen_model=truth.screen.surface)
    _check_within_1um(truth, res, dec)


def test_bulge_3mm_with_calibrated_free_3x3_screen_within_1um():
    """The instrument's way: holistic calibration (Experiment 2's chain, nominal start values)
    with a free 3 × 3 screen, then stereo with the calibrated cameras and screen. The sample is
    the table plane, the calibrated frame's z = 0: the height is the error. Coarser binning
    (80 × 50 px) keeps the 16-pose calibration fast."""
    from pmdsim.studies.experiment2 import calibrate_and_reconstruct

    truth = default_setup().binned(24).with_bulge(3.0)
    dec = _decode_all(truth)
    errs = {}
    for grid in (3, None):
        e = calibrate_and_reconstruct(truth, screen_grid=grid, start_seed=[0, 3000])
        assert e.result.converged
        _, res = evaluate_stereo_decoded(e.model, dec, screen_model=None if grid is None else e.model.screen.surface)
        errs[grid] = {cam: np.abs(c.height_mm[c.overlap]) * 1e3 for cam, c in res.cameras.items()}
    for cam, err in errs[3].items():
        print(f"{cam}: calibrated free 3×3 screen: max |z| {err.max():.3f} µm; planar calibration: "
              f"{errs[None][cam].max():.3f} µm")
        assert err.size > 1000 and err.max() <= 1.0
        # the planar screen model cannot: its error is the bulge's (Experiment 2's µm scale)
        assert errs[None][cam].max() > 1.0


def test_wrong_calibration_shows_as_disagreement(base, flat_decoded):
    _, good = evaluate_stereo_decoded(base, flat_decoded)
    o = base.cameras["right"].pose.origin_world_mm
    for shift in ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, 0.0, 0.1)):
        wrong = base.with_camera("right", origin_world_mm=tuple(a + b for a, b in zip(o, shift)))
        _, bad = evaluate_stereo_decoded(wrong, flat_decoded)
        for cam in base.cameras:
            g = good.cameras[cam].normal_disagreement_urad
            b = bad.cameras[cam].normal_disagreement_urad
            gd = np.abs(good.cameras[cam].height_discrepancy_um)
            bd = np.abs(bad.cameras[cam].height_discrepancy_um)
            print(f"shift {shift} {cam}: disagreement median {np.nanmedian(b):.1f} µrad (true calibration: median "
                  f"{np.nanmedian(g):.2f}, max {np.nanmax(g):.2f}); height discrepancy median {np.nanmedian(bd):.3f} µm "
                  f"(true: max {np.nanmax(gd):.3f})")
            # the typical pixel of the wrong calibration disagrees more than any pixel of the right one
            assert np.nanmedian(b) > np.nanmax(g)
            assert np.nanmedian(bd) > np.nanmax(gd)
    # the summary carries the same figures
    s = bad.summary()["left"]
    assert s["normal_disagreement_median_urad"] == pytest.approx(np.nanmedian(bad.cameras["left"].normal_disagreement_urad))


def test_residual_vanishes_at_the_true_height(base):
    """The criterion itself on the tracer's noise-free mapping: r(z) = g_A − g_B is ~0 at the
    true height of a pixel and changes sign across it (a root, not a touching minimum)."""
    from pmdsim.evaluation.phase import ScreenCoordinates

    truth = _foil(base)
    dec, maps = {}, {}
    for cam in truth.cameras:
        m = trace_setup_camera(truth, cam, store_points=True)
        maps[cam] = m
        z = np.zeros(m.valid.shape + (2,))
        dec[cam] = ScreenCoordinates(m.screen_xy_mm, m.valid, np.zeros(m.valid.shape, np.uint8), z, z, z)
    views, _ = evaluate_stereo_decoded(truth, dec)
    v, u = 50, 80
    z_true = maps["left"].p_sample_mm[v, u, 2]
    r0 = stereo_residual(views, "left", "right", (v, u), [z_true])[0]
    rm, rp = stereo_residual(views, "left", "right", (v, u), [z_true - 0.05, z_true + 0.05])
    assert np.hypot(*r0) < 1e-6  # interpolation of the partner's screen points only
    assert np.hypot(*rm) > 10e-6 and np.hypot(*rp) > 10e-6
    k = int(np.argmax(np.abs(rp - rm)))
    assert np.sign(rm[k]) != np.sign(rp[k])


def test_refuses_one_camera_and_a_range_without_the_surface(base, flat_decoded):
    one = base.with_cameras({"left": base.cameras["left"]})
    with pytest.raises(ReconstructionError, match="at least two cameras"):
        evaluate_stereo_decoded(one, {"left": flat_decoded["left"]})
    with pytest.raises(ReconstructionError, match="camera 'left': no pixel has a unique consistent height"):
        evaluate_stereo_decoded(base, flat_decoded, search_range_mm=(5.0, 15.0))
    with pytest.raises(ReconstructionError, match="search_range_mm"):
        evaluate_stereo_decoded(base, flat_decoded, search_range_mm=(1.0, -1.0))
    dark = replace(flat_decoded["right"], valid=np.zeros_like(flat_decoded["right"].valid))
    with pytest.raises(ReconstructionError, match="camera 'right': valid has no True pixel"):
        evaluate_stereo_decoded(base, {"left": flat_decoded["left"], "right": dark})


# ----------------------------------------------------------------------------- foil warpage
def test_warpage_bow_is_reproduced_exactly_by_a_3x3_spline():
    """The bows are quadratics: the not-a-knot spline through 3 × 3 samples is exact."""
    for kind in ("spherical", "cylindrical", "saddle"):
        w = FoilWarpage(n_shrinks=0, bow_kind=kind, bow_mm=3.0, bow_axis_deg=30.0)
        g = (0.0, 200.0, 400.0)
        assert w.interpolation_error_mm(g, g) < 1e-12
        # edge midpoint lift of the spherical bow is b (towards the cameras: −z)
    w = FoilWarpage(n_shrinks=0, bow_mm=2.0)
    assert w.height_mm(200.0, 0.0) == pytest.approx(-2.0)
    assert w.height_mm(200.0, 200.0) == pytest.approx(0.0)


def test_warpage_local_warps_and_grid_convergence():
    w = FoilWarpage(bow_mm=0.0, bow_kind="none", n_shrinks=4, shrink_depth_um=30.0, shrink_width_mm=10.0, seed=3)
    s = w.shrinks
    assert s.shape == (4, 3) and np.allclose(np.abs(s[:, 2]), 0.030)
    assert np.array_equal(s, FoilWarpage(bow_mm=0.0, bow_kind="none", n_shrinks=4, shrink_width_mm=10.0, seed=3).shrinks)
    # each warp's centre has its depth (the others are far enough away not to matter much)
    for cx, cy, a in s:
        assert w.height_mm(cx, cy) == pytest.approx(a, abs=0.003)
    # cubic spline: error ~ h⁴ for a smooth function; halving the spacing divides it by ≈ 16
    # (on a 120 mm foil: a 400 mm one at 2 mm makes a 201 × 201 spline, slow to set up)
    w = FoilWarpage(x_range_mm=(0.0, 120.0), y_range_mm=(0.0, 120.0), bow_mm=0.0, bow_kind="none", n_shrinks=2,
                    shrink_depth_um=30.0, shrink_width_mm=10.0, seed=3)
    e = [w.interpolation_error_mm(*w.grid(h)) for h in (8.0, 4.0, 2.0)]
    print("interpolation error (µm) at 8, 4, 2 mm spacing:", [x * 1e3 for x in e])
    assert 8.0 < e[0] / e[1] < 32.0 and 8.0 < e[1] / e[2] < 32.0
    assert e[1] * 1e3 < 0.1  # the 4 mm grid of the stereo checks: well below the 1 µm target
    pad = FoilWarpage(bow_kind="none", n_shrinks=1, shrink_shape="pad", shrink_width_mm=15.0, pad_edge_mm=3.0)
    cx, cy, a = pad.shrinks[0]
    assert pad.height_mm(cx, cy) == pytest.approx(a, rel=1e-3)  # flat top of the pad
    assert abs(pad.height_mm(cx + 40.0, cy)) < 1e-9
    with pytest.raises(ValueError, match="bow_kind"):
        FoilWarpage(bow_kind="twisted")


# ----------------------------------------------------------------------------- API and CLI
def test_api_evaluate_stereo_matches_the_evaluation_layer(base, flat_decoded):
    import pmdsim

    res = pmdsim.evaluate_stereo(flat_decoded, base)
    _, ref = evaluate_stereo_decoded(base, flat_decoded)
    for cam in base.cameras:
        np.testing.assert_array_equal(res.cameras[cam].height_mm, ref.cameras[cam].height_mm)


def test_cli_evaluate_stereo_writes_the_report(tmp_path, base, binned12_stereo):
    """`pmdsim simulate` then `pmdsim evaluate --stereo` of the binned setup (run once per session
    in tests/conftest.py, in process): the report and the file; a seed pixel is refused."""
    import h5py
    from click.testing import CliRunner

    from pmdsim.cli import main

    run = binned12_stereo
    assert run.setup == base
    assert "normal disagreement median" in run.stereo_stdout
    with h5py.File(run.stereo / "evaluation.h5") as f:
        assert f.attrs["stereo"] and f.attrs["method"] == "stereo"
        for cam in base.cameras:
            g = f[cam]
            ov = g["overlap"][()]
            h = g["height_mm"][()]
            assert ov.sum() > 0
            # the flat sample is the plane z = 0 of the sample frame: the height is the error
            assert np.nanmax(np.abs(h[ov])) * 1e3 <= 1.0
            assert np.isfinite(g["normal_disagreement_urad"][()][ov]).all()
            assert g["anchor_pixels"].shape[1] == 2
    r = CliRunner().invoke(main, ["evaluate", str(run.images), "--setup", str(run.setup_file), "--out",
                                  str(tmp_path / "ev2"), "--stereo", "--seed-pixel", "5", "5", "--quiet"])
    assert r.exit_code == 2 and "pmdsim: error: --stereo needs no seed" in r.stderr
    assert not (tmp_path / "ev2").exists()


# ----------------------------------------------------------------------------- kernels
def test_projection_kernel_matches_the_camera_model_and_opencv():
    """The search's compiled projection against Camera.project (eqs. 2–4) and OpenCV."""
    from pmdsim.evaluation.stereo import StereoView, _camera_arrays, _project
    from pmdsim.geometry.camera import Camera
    from pmdsim.geometry.transform import RigidTransform

    cam = Camera(640, 480, 800.0, 780.0, 330.0, 250.0, k1=-0.2, k2=0.05, p1=0.001, p2=-0.002, k3=0.01)
    T_ref_cam = RigidTransform.from_origin_angles([10.0, -20.0, -300.0], [40.0, 5.0, -8.0])
    R, t, c = _camera_arrays(StereoView(cam, T_ref_cam, None))
    rng = np.random.default_rng(1)
    p_ref = rng.uniform([-60, -60, -5], [60, 60, 5], size=(50, 3))
    p_cam = T_ref_cam.inv().apply(p_ref)
    expected = cam.project(p_cam)
    got = np.array([_project(R, t, c, *p)[1:] for p in p_ref])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    cv2 = pytest.importorskip("cv2")
    K, dist = cam.as_opencv()
    uv, _ = cv2.projectPoints(p_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(got, uv.reshape(-1, 2), rtol=0, atol=1e-6)


def test_cubic_convolution_is_exact_for_quadratics_and_needs_16_valid_pixels():
    from pmdsim.evaluation.stereo import _interp

    H, W = 12, 15
    v, u = np.mgrid[0:H, 0:W].astype(float)
    f = lambda u, v: 0.3 * u * u - 0.2 * u * v + 0.05 * v * v + 2.0 * u - v + 7.0
    arr = np.ascontiguousarray(np.stack([f(u, v), -f(u, v)], axis=-1))
    ok = np.ones((H, W), dtype=bool)
    out = np.empty(2)
    rng = np.random.default_rng(2)
    for uu, vv in rng.uniform([1.0, 1.0], [W - 2.001, H - 2.001], size=(40, 2)):
        assert _interp(arr, ok, uu, vv, out)
        assert out[0] == pytest.approx(f(uu, vv), abs=1e-9) and out[1] == pytest.approx(-f(uu, vv), abs=1e-9)
    ok[5, 7] = False  # one invalid pixel spoils the 4 × 4 neighbourhoods that contain it
    assert not _interp(arr, ok, 6.5, 4.5, out) and not _interp(arr, ok, 8.9, 6.9, out)
    assert _interp(arr, ok, 9.1, 4.5, out)
    assert not _interp(arr, np.ones((H, W), bool), 0.5, 5.0, out)  # too close to the border


def test_on_reconstruction_hands_over_each_camera_in_order_before_the_report(base, flat_decoded):
    """`evaluate --stereo` writes a camera's maps while the next integrates (studies/evaluate_stereo):
    the callback gets every camera once, in camera order, with the reconstruction the result holds,
    before the agreement report exists."""
    from pmdsim.evaluation import stereo_report
    from pmdsim.evaluation.stereo import reconstruct_stereo, stereo_views

    views = stereo_views(base, flat_decoded)
    seen, report_calls = [], []
    agreement = stereo_report.agreement

    def spy(*a, **k):
        report_calls.append(len(seen))
        return agreement(*a, **k)

    stereo_report.agreement = spy
    try:
        res = reconstruct_stereo(views, on_reconstruction=lambda name, rec: seen.append((name, rec)))
    finally:
        stereo_report.agreement = agreement
    assert [n for n, _ in seen] == list(views) and report_calls == [len(views)]
    assert all(rec is res.cameras[n].reconstruction for n, rec in seen)
