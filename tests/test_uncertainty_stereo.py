"""Per-pixel standard uncertainties of stereo evaluations (issue 22, ``--stereo``): an anchor's σ
against a Monte Carlo of noisy re-solves (scipy's root finder on the public residual), the
heights' σ against a Monte Carlo of the anchored integration with noisy slopes and re-solved
anchors, and the outputs of ``pmdsim evaluate --stereo``."""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace

import h5py
import numba
import numpy as np
import pytest
from scipy.optimize import least_squares

from pmdsim.evaluation import uncertainty_stereo as US
from pmdsim.evaluation.pipeline import decode_simulated
from pmdsim.evaluation.registration import register
from pmdsim.evaluation.stereo import (StereoView, _integrate_anchored, _search_kernel, _camera_arrays, _view_arrays,
                                      evaluate_stereo_decoded, reconstruct_stereo, stereo_residual)
from pmdsim.setup import default_setup
from pmdsim.simulation.render import noise_generator, trace_setup_camera

DS = 48  # 40 × 25 px per camera
STRIDE = 4  # about 50 anchors per camera


@contextmanager
def _one_thread():
    """The many small solves of a Monte Carlo run serially (numba's threads only wait on them)."""
    n = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(n)


def _views(setup, decoded, surface=None):
    """The stereo views of noisy decodes (as evaluate_stereo_decoded registers them; planar
    screen unless ``surface``)."""
    from pmdsim.geometry.surface import SplineSurface

    scr = setup.screen
    plane = surface or SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
    T_world_ref = setup.sample.T_world_sample
    out = {}
    for cam, dec in decoded.items():
        cs = setup.cameras[cam]
        reg = register(cs.camera, cs.T_world_cam, plane, scr.T_world_screen, dec.screen_xy_mm, dec.valid, T_world_ref)
        out[cam] = StereoView(cs.camera, T_world_ref.inv() @ cs.T_world_cam, reg)
    return out


@pytest.fixture(scope="module")
def flat():
    """Table 1 binned 48×, 2 grey levels of noise: the noiseless decoded coordinates with the
    decoder's σ, the stereo result on them and its σ (K = 512)."""
    s = default_setup().binned(DS).with_patterns(noise_std=2.0)
    dec = {}
    for c in s.cameras:
        m = trace_setup_camera(s, c)
        d = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, c, stream=1))
        dec[c] = replace(d, screen_xy_mm=np.where(d.valid[..., None], m.screen_xy_mm, np.nan))
    views = _views(s, dec)
    st = reconstruct_stereo(views, stride_px=STRIDE)
    with _one_thread():
        unc = US.stereo_uncertainty(s, views, dec, st, samples=512)
    return s, dec, views, st, unc


def _noisy(dec, rng):
    return {c: replace(d, screen_xy_mm=d.screen_xy_mm + rng.normal(size=d.screen_xy_mm.shape) * d.std_xy_mm)
            for c, d in dec.items()}


def test_anchor_sigma_against_monte_carlo_of_noisy_re_solves(flat):
    s, dec, views, st, unc = flat
    cam = "left"
    c = st.cameras[cam]
    k = len(c.anchor_height_mm) // 2
    pixel = tuple(int(x) for x in c.anchor_pixels[k])
    a0 = float(c.anchor_height_mm[k])
    predicted = unc[cam][1][k]  # µm
    rng = np.random.default_rng(11)
    roots = []
    with _one_thread():
        for _ in range(200):
            nv = _views(s, _noisy(dec, rng))
            f = lambda z: stereo_residual(nv, cam, "right", pixel, z)[0]
            roots.append(least_squares(f, a0, xtol=1e-14, ftol=1e-15, gtol=1e-15).x[0])
    observed = np.std(roots, ddof=1) * 1e3
    print(f"anchor {pixel}: predicted σ {predicted:.3f} µm, observed {observed:.3f} µm (200 draws)")
    assert abs(observed / predicted - 1) < 0.15
    assert np.all(np.isfinite(unc[cam][1])) and np.all(unc[cam][1] > 0)


def _anchor_fd_check(s, surf, cam):
    """δa = Σ coef·ξ of ``cam``'s anchors against central differences of anchors re-solved by
    scipy (on the public residual, with each anchor's partner) on re-registered coordinates."""
    dec = {c: decode_simulated(s, (m := trace_setup_camera(s, c)).screen_xy_mm, m.valid,
                               rng=noise_generator(s, c, stream=1)) for c in s.cameras}
    views = _views(s, dec, surf)
    st = reconstruct_stereo(views, stride_px=STRIDE)
    tang = {c: US._tangents(s, surf, dec[c]) for c in views}
    sc = st.cameras[cam]
    an = US.anchor_noise(views, dec, tang, cam, sc.anchor_pixels, sc.anchor_height_mm)
    rng = np.random.default_rng(4)
    xi = {c: rng.choice([-1.0, 1.0], size=dec[c].screen_xy_mm.shape) for c in views}
    names = list(views)
    pred = np.zeros(len(sc.anchor_height_mm))
    for t in range(an.anchor.size):
        pred[an.anchor[t]] += an.coef[t] @ xi[names[an.camera[t]]].reshape(-1, 2)[an.pixel[t]]
    ks = np.arange(0, len(pred), max(1, len(pred) // 8))
    h = 0.1
    roots = []
    for sg in (1, -1):
        nv = _views(s, {c: replace(d, screen_xy_mm=d.screen_xy_mm + sg * h * xi[c] * np.nan_to_num(d.std_xy_mm))
                        for c, d in dec.items()}, surf)
        roots.append([least_squares(lambda z: stereo_residual(nv, cam, an.partner[k], tuple(sc.anchor_pixels[k]), z)[0],
                                    sc.anchor_height_mm[k], xtol=1e-15, ftol=1e-15, gtol=1e-15).x[0] for k in ks])
    fd = (np.array(roots[0]) - np.array(roots[1])) / (2 * h)
    np.testing.assert_allclose(fd, pred[ks], rtol=1e-3, atol=1e-3 * np.max(np.abs(pred[ks])))
    return views, dec, st, tang, an


def test_anchor_linearisation_on_a_bulged_screen_model_against_re_solves():
    """On a free-form screen model (per-pixel tangents with a z part; their effect on δa is
    small, ~1e-4 relative, as b̂ nearly projects it out)."""
    s = default_setup().with_bulge(3.0).binned(DS).with_patterns(noise_std=2.0)
    _, dec, _, tang, _ = _anchor_fd_check(s, s.screen.surface, "left")
    assert np.ptp(tang["left"][..., 2, :][dec["left"].valid]) > 1e-3  # the bulge tilts the tangents


def test_three_cameras_each_anchor_with_its_partner():
    """A third camera between the two: every anchor keeps the partner the search kept (smallest
    |r|), its σ linearised with that partner's pixels; the heights' σ is finite everywhere."""
    from pmdsim.setup.model import CameraSetup, Pose

    s = default_setup().binned(DS).with_patterns(noise_std=2.0)
    mid = CameraSetup(s.cameras["left"].camera, Pose((0.0, 295.0, -295.0), (45.0, 0.0, 0.0)))
    s = s.with_cameras({**s.cameras, "mid": mid})
    views, dec, st, _, an = _anchor_fd_check(s, None, "mid")
    assert set(an.partner) == {"left", "right"}  # both partners used by the middle camera's anchors
    unc = US.stereo_uncertainty(s, views, dec, st, samples=16)
    for c in views:
        S = st.cameras[c].reconstructed
        assert np.isfinite(unc[c][0].height_std_um[S]).all() and np.isfinite(unc[c][1]).all()


def test_linearised_anchored_integration_against_the_nonlinear_one(flat):
    """δz of the linear map (slopes and anchors perturbed together) against central differences
    of the anchored least-squares integration itself."""
    s, dec, views, st, unc = flat
    from pmdsim.evaluation import uncertainty as U

    rng = np.random.default_rng(2)
    for cam in views:
        sc = st.cameras[cam]
        rec = sc.reconstruction
        S = rec.reconstructed
        lin = US._AnchoredLinear(views[cam], rec, sc.anchor_pixels)
        o, d, q, valid = _view_arrays(views[cam])
        T = US._tangents(s, None, dec[cam])
        J = np.nan_to_num(U.slope_jacobian(views[cam].registration.o_ref_mm, rec.p_sample_mm, q, T))
        dxy = np.where(valid[..., None], rng.normal(size=S.shape + (2,)), 0.0) * 1e-3
        da = rng.normal(size=len(sc.anchor_height_mm)) * 1e-3
        dz = lin.apply(np.ascontiguousarray(np.where(S[..., None], np.einsum("hwij,hwj->hwi", J, dxy), 0.0)), da)
        h = 1.0
        dq = np.einsum("hwij,hwj->hwi", T, dxy)
        z = [_integrate_anchored(o, d, np.ascontiguousarray(q + sg * h * dq), valid, sc.anchor_pixels,
                                 sc.anchor_height_mm + sg * h * da, 1e-13, 30)[0] for sg in (1, -1)]
        fd = (z[0] - z[1]) / (2 * h)
        assert np.max(np.abs(dz[S] - fd[S])) < 1e-4 * np.max(np.abs(fd[S]))


def test_height_sigma_against_monte_carlo_of_the_anchored_integration(flat):
    """200 seeded noisy decodes of both cameras: anchors re-solved by the evaluation's search,
    heights by the anchored integration; the observed per-pixel scatter against the predicted
    σ in four bins of distance from the anchors' centroid. (For the planar screen the screen
    point is linear in the decoded coordinates: q + T δxy is the re-registration.)"""
    s, dec, views, st, unc = flat
    n_draws = 200
    rng = np.random.default_rng(1)
    lo, hi = st.search_range_mm
    n_steps = int(np.floor((hi - lo) / st.search_step_mm)) + 1
    base = {c: _view_arrays(v) for c, v in views.items()}
    tang = {c: US._tangents(s, None, dec[c]) for c in views}
    zs = {c: [] for c in views}
    with _one_thread():
        for _ in range(n_draws):
            nq = {}
            for c, (o, d, q, valid) in base.items():
                dxy = rng.normal(size=valid.shape + (2,)) * np.nan_to_num(dec[c].std_xy_mm)
                nq[c] = np.ascontiguousarray(np.where(valid[..., None], q + np.einsum("hwij,hwj->hwi", tang[c], dxy),
                                                      0.0))
            for cam, (o, d, q, valid) in base.items():
                partner = next(p for p in base if p != cam)
                oB, _, _, okB = base[partner]
                RB, tB, camB = _camera_arrays(views[partner])
                vu = st.cameras[cam].anchor_pixels
                n = len(vu)
                z, r, cnt = np.empty(n), np.empty(n), np.empty(n, dtype=np.int64)
                _search_kernel(o, d, nq[cam], vu[:, 0].astype(np.int64), vu[:, 1].astype(np.int64), oB, nq[partner],
                               okB, RB, tB, camB, lo, st.search_step_mm, n_steps, z, r, cnt)
                assert np.isfinite(z).all()
                zs[cam].append(_integrate_anchored(o, d, nq[cam], valid, vu, z, 1e-11, 20)[0])
    for cam in views:
        obs = np.std(np.array(zs[cam]), axis=0, ddof=1) * 1e3
        pred = unc[cam][0].height_std_um
        S = st.cameras[cam].reconstructed
        assert np.isfinite(obs[S]).all() and np.isfinite(pred[S]).all()
        vv, uu = np.nonzero(S)
        cv, cu = st.cameras[cam].anchor_pixels.mean(axis=0)
        dist = np.hypot(vv - cv, uu - cu)
        edges = np.quantile(dist, [0, 0.25, 0.5, 0.75, 1.0])
        for b in range(4):
            sel = (dist >= edges[b]) & (dist <= edges[b + 1])
            ro = np.sqrt(np.mean(obs[vv[sel], uu[sel]] ** 2))
            rp = np.sqrt(np.mean(pred[vv[sel], uu[sel]] ** 2))
            print(f"{cam} bin {b} ({edges[b]:.0f}–{edges[b + 1]:.0f} px): predicted {rp:.4f} µm, observed {ro:.4f} µm")
            assert abs(ro / rp - 1) < 0.15, f"{cam} bin {b}: ratio {ro / rp:.3f}"


def test_cli_evaluate_stereo_writes_the_uncertainty(tmp_path):
    import json

    from click.testing import CliRunner

    from pmdsim.cli import main

    base = default_setup().binned(DS)
    setup_file = tmp_path / "setup.toml"
    setup_file.write_text(base.to_toml(), encoding="utf-8")
    runner = CliRunner()
    run = lambda *a: runner.invoke(main, [str(x) for x in a])
    r = run("simulate", "--setup", setup_file, "--out", tmp_path / "img", "--quiet")
    assert r.exit_code == 0, r.output
    r = run("evaluate", tmp_path / "img", "--setup", setup_file, "--out", tmp_path / "ev", "--stereo", "--quiet")
    assert r.exit_code == 0, r.output
    assert "height standard uncertainty (k = 1) RMS" in r.output
    names = ("slope_std_urad", "height_std_um", "height_std_noise_um", "height_std_calibration_um",
             "slope_std_noise_urad", "slope_std_calibration_urad")
    with h5py.File(tmp_path / "ev" / "evaluation.h5") as f:
        doc = json.loads(f.attrs["uncertainty"])
        for cam in base.cameras:
            g = f[cam]
            rec = g["reconstructed"][()]
            for n in names:
                assert n in g, n
            h = g["height_std_um"][()]
            assert np.isfinite(h[rec]).all() and (h[rec] > 0).all()  # absolute: no pixel is held
            assert g["anchor_height_std_um"].shape == g["anchor_height_mm"].shape
            assert g["anchor_height_std_um"].attrs["units"] == "um"  # self-describing, as anchor_height_mm
            assert g["anchor_height_std_um"].dims[0].keys() == g["anchor_height_mm"].dims[0].keys()
            assert doc[cam]["samples_K"] == 64 and doc[cam]["heights_relative_to"].startswith("nothing: absolute")
            assert (tmp_path / "ev" / f"height_std_{cam}.png").exists()
    r = run("evaluate", tmp_path / "img", "--setup", setup_file, "--out", tmp_path / "ev2", "--stereo",
            "--no-uncertainty", "--quiet")
    assert r.exit_code == 0, r.output
    assert "height standard uncertainty" not in r.output
    with h5py.File(tmp_path / "ev2" / "evaluation.h5") as f:
        assert "height_std_um" not in f["left"]
        assert json.loads(f.attrs["uncertainty"])["omitted"]


def test_api_evaluate_stereo_carries_the_uncertainty(flat):
    import pmdsim

    s, dec, views, st, unc = flat
    res = pmdsim.evaluate_stereo(dec, s, stride_px=STRIDE)
    for cam, c in res.cameras.items():
        u = c.uncertainty
        S = c.reconstructed
        assert np.isfinite(u.height_std_um[S]).all() and not u.height_std_um.flags.writeable
        assert c.anchor_height_std_um.shape == c.anchor_height_mm.shape
        np.testing.assert_allclose(c.anchor_height_std_um, unc[cam][1])  # the same anchors, the same σ
    assert all(c.uncertainty is None for c in pmdsim.evaluate_stereo(dec, s, uncertainty=False).cameras.values())


def test_what_stereo_sigma_cannot_use_is_refused_and_the_heights_stand(flat):
    """One camera is no stereo; a decoder σ that is NaN at reconstructed pixels would give σ = 0
    (exact heights) if taken as it is: both are refused with the reason, and the API keeps the
    heights and warns."""
    import pmdsim
    from pmdsim.errors import ConsistencyWarning
    from pmdsim.evaluation.uncertainty import UncertaintyError

    s, dec, views, st, _ = flat
    with pytest.raises(UncertaintyError, match="at least two cameras"):
        US.stereo_uncertainty(s, {"left": views["left"]}, dec, st)
    holed = dict(dec)
    d = dec["left"]
    holed["left"] = replace(d, std_xy_mm=np.where(d.valid[..., None], np.nan, d.std_xy_mm))
    with pytest.raises(UncertaintyError, match=r"'left'.*std_xy_mm.*not finite at \d+ reconstructed"):
        US.stereo_uncertainty(s, views, holed, st)
    with pytest.warns(ConsistencyWarning, match="no uncertainty"):
        res = pmdsim.evaluate_stereo(holed, s, stride_px=STRIDE)
    ref = pmdsim.evaluate_stereo(dec, s, stride_px=STRIDE, uncertainty=False)
    for cam, c in res.cameras.items():
        assert c.uncertainty is None
        np.testing.assert_array_equal(c.reconstruction.p_sample_mm, ref.cameras[cam].reconstruction.p_sample_mm)


def test_nonfinite_on_counts_what_numpy_counts():
    rng = np.random.default_rng(11)
    x = rng.normal(size=(23, 31, 2))
    x[rng.random((23, 31)) < 0.1, 0] = np.nan
    x[rng.random((23, 31)) < 0.1, 1] = np.inf
    S = rng.random((23, 31)) > 0.3
    assert US._nonfinite_on(x, S) == np.count_nonzero(~np.isfinite(x[S]).all(axis=-1)) > 0
    assert US._nonfinite_on(np.ones((23, 31, 1)), S) == 0
