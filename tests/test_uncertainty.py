"""Per-pixel standard uncertainties (issue 22): the slopes' Jacobian against finite differences,
the linearised integration against the nonlinear reconstruction, the sampled estimator against
the exact covariance, a seeded Monte Carlo of noisy decodes, the surface fit's coefficient σ
against a Monte Carlo, and the outputs of ``pmdsim evaluate``."""

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.evaluation import uncertainty as U
from pmdsim.evaluation.integration import normals_from_registration
from pmdsim.evaluation.pipeline import decode_simulated, evaluate_decoded
from pmdsim.evaluation.reconstruction import reconstruct
from pmdsim.evaluation.surface_fit import fit_paraboloid_slopes, with_uncertainty
from pmdsim.setup import default_setup
from pmdsim.simulation.render import noise_generator, trace_setup_camera


@pytest.fixture(scope="module")
def tiny():
    """The Table 1 setup binned 80× (15×24 px) with 2 grey levels of noise, one noisy decode."""
    s = default_setup().binned(80).with_patterns(noise_std=2.0)
    m = trace_setup_camera(s, "left")
    dec = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, "left", stream=1))
    return s, m, dec


def _slopes(o, p, q):
    n = normals_from_registration(p, o, q)
    return -n[..., :2] / n[..., 2:3]


def test_slope_jacobian_against_finite_differences():
    rng = np.random.default_rng(3)
    o = np.array([10.0, -20.0, -900.0])
    p = rng.normal(scale=30.0, size=(5, 7, 3)) * [1, 1, 0.01]
    q = np.array([0.0, 50.0, -700.0]) + rng.normal(scale=100.0, size=(5, 7, 3)) * [1, 1, 0.05]
    # a tilted, curved screen: tangents with a z part
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T = np.stack([R[:, 0] + 0.3 * R[:, 2], R[:, 1] - 0.2 * R[:, 2]], axis=-1)
    J = U.slope_jacobian(o, p, q, T)
    h = 1e-4
    for j in range(2):
        fd = (_slopes(o, p, q + h * T[:, j]) - _slopes(o, p, q - h * T[:, j])) / (2 * h)
        np.testing.assert_allclose(J[..., j], fd, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("method", ["stepwise", "least_squares"])
def test_linearised_integration_and_estimator(tiny, method):
    s, _, dec = tiny
    reg, rec = evaluate_decoded(s, "left", dec, method=method)
    S = rec.reconstructed
    lin = U._LinearisedIntegration(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec)
    R = (s.sample.T_world_sample.inv() @ s.screen.T_world_screen).rotation
    dq = np.broadcast_to(U._screen_tangents(R, None, dec.screen_xy_mm), S.shape + (3, 2))  # a plane: R[:, :2]
    J = U.slope_jacobian(reg.o_ref_mm, rec.p_sample_mm, reg.q_ref_mm, dq)
    # (1) the linear map against the nonlinear reconstruction (directional central differences)
    rng = np.random.default_rng(0)
    z0 = rec.height_mm[rec.seed_pixel]
    for _ in range(2):
        dxy = np.where(S[..., None], rng.normal(size=dec.screen_xy_mm.shape), 0.0)
        h = 1e-4
        z = [reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm + sg * h * np.einsum("hwij,hwj->hwi", dq, dxy),
                         reg.valid, method=method, seed_pixel=rec.seed_pixel, seed_height_mm=z0,
                         **({"tol_mm": 1e-13} if method == "least_squares" else {})).height_mm for sg in (1, -1)]
        fd = (z[0] - z[1]) / (2 * h)
        dg = np.ascontiguousarray(np.where(S[..., None], np.einsum("hwij,hwj->hwi", np.nan_to_num(J), dxy), 0.0))
        lin_dz = lin.apply(dg)
        assert np.max(np.abs(lin_dz[S] - fd[S])) < 1e-4 * np.max(np.abs(fd[S]))
    # (2) the estimator against the exact covariance M Σ Mᵀ (M column by column, densely)
    sig = dec.std_xy_mm
    cols = []
    for v, u in np.argwhere(S):
        for j in range(2):
            dg = np.zeros(S.shape + (2,))
            dg[v, u] = J[v, u, :, j] * sig[v, u, j]
            cols.append(lin.apply(dg)[S])
    exact = np.sqrt(np.sum(np.array(cols) ** 2, axis=0))
    ok = exact > 0
    assert np.count_nonzero(~ok) == 1  # the seed
    for K, rms_max, worst in ((4096, 1.5, 5.0), (64, 1.5, 5.0)):
        est = U.height_std_sampled(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec, J, sig, samples=K)[S]
        rel = est[ok] / exact[ok] - 1.0
        bound = 1.0 / np.sqrt(2 * K)  # relative standard error of a σ from K Gaussian samples
        assert np.sqrt(np.mean(rel**2)) < rms_max * bound and np.max(np.abs(rel)) < worst * bound, (K, rel)
    # reproducible
    a = U.height_std_sampled(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec, J, sig, samples=8, rng_seed=5)
    b = U.height_std_sampled(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec, J, sig, samples=8, rng_seed=5)
    np.testing.assert_array_equal(a, b)


def test_monte_carlo_noisy_decodes():
    """48 seeded noisy decodes of one binned setup: the observed scatter of heights and slopes
    against the predicted σ (pooled over pixels): within 15 % (48 samples: ±10 % standard error
    per pixel, the K = 256 estimator ±4 %)."""
    s = default_setup().binned(40).with_patterns(noise_std=2.0)
    m = trace_setup_camera(s, "left")
    seed = (15, 24)
    zs, gs = [], []
    for k in range(48):
        dec = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, "left", stream=100 + k))
        reg, rec = evaluate_decoded(s, "left", dec, seed_pixel=seed)
        zs.append(rec.height_mm)
        gs.append(-rec.n_sample[..., :2] / rec.n_sample[..., 2:3])
        if k == 0:
            unc = U.surface_uncertainty(s, "left", dec, reg, rec, method="stepwise", samples=256)
            S0 = rec.reconstructed
    z_obs = np.std(zs, axis=0, ddof=1) * 1e3
    g_obs = np.std(gs, axis=0, ddof=1) * 1e6
    far = unc.height_std_noise_um > 0
    r_h = np.sqrt(np.mean(z_obs[far] ** 2) / np.mean(unc.height_std_noise_um[far] ** 2))
    r_g = np.sqrt(np.mean(g_obs[far] ** 2, axis=0) / np.mean(unc.slope_std_noise_urad[far] ** 2, axis=0))
    assert abs(r_h - 1) < 0.15 and np.all(np.abs(r_g - 1) < 0.15), (r_h, r_g)
    assert unc.notes == (U.NO_COVARIANCE_NOTE,)
    np.testing.assert_array_equal(unc.height_std_calibration_um[far], 0.0)
    for cal in (unc.height_std_calibration_um, unc.slope_std_calibration_urad):  # 0 on the reconstruction, NaN off it
        assert cal.shape[:2] == S0.shape and np.all(cal[S0] == 0.0) and np.isnan(cal[~S0]).all()


def test_surface_fit_coefficient_std_monte_carlo():
    """σ of the paraboloid's coefficients and focal lengths against 300 fits of noisy slopes."""
    rng = np.random.default_rng(11)
    n = 3000
    xy = rng.uniform(-50, 50, size=(n, 2)) + [5.0, -3.0]
    a, b, c, d, e = 2e-4, 1e-5, -1e-4, 1e-3, -2e-3
    g0 = np.stack([2 * a * xy[:, 0] + b * xy[:, 1] + d, b * xy[:, 0] + 2 * c * xy[:, 1] + e], axis=-1)
    sig = np.full((n, 2), 5e-5) * (1 + (xy[:, :1] > 0))  # heteroscedastic
    fits = [fit_paraboloid_slopes(xy, g0 + sig * rng.normal(size=(n, 2)), np.ones(n, bool), camera_z_mm=-500.0)
            for _ in range(300)]
    obs = np.std([f.coefficients for f in fits], axis=0, ddof=1)
    obs_f = np.std([[f.focal_length_x_mm, f.focal_length_y_mm] for f in fits], axis=0, ddof=1)
    pred = with_uncertainty(fits[0], np.asfortranarray(xy), sig, -500.0)  # F order, as evaluate's (2, M) rows.T
    np.testing.assert_allclose(obs, pred.coefficients_std, rtol=0.15)
    np.testing.assert_allclose(obs_f, [pred.focal_length_x_std_mm, pred.focal_length_y_std_mm], rtol=0.15)
    js = pred.as_json()
    assert set(js) >= {"focal_length_x_std_mm", "focal_length_y_std_mm", "coefficients", "coefficients_std"}


def _run(args):
    return CliRunner().invoke(main, args)


def test_cli_outputs(tmp_path, small_setup_file):
    sim = tmp_path / "sim"
    assert _run(["simulate", "--setup", str(small_setup_file), "--bulge-mm", "3", "--out", str(sim),
                 "--quiet"]).exit_code == 0
    out = tmp_path / "ev"
    r = _run(["evaluate", str(sim), "--setup", str(small_setup_file), "--out", str(out), "--quiet",
              "--seed-pixel", "30", "48", "--seed-height-mm", "0", "--anchor-distance-std-mm", "0.01"])
    assert r.exit_code == 0, r.output
    assert r.stdout.count("height standard uncertainty (k = 1) RMS") == 2 and "dominated by noise" in r.stdout
    assert (out / "height_std_left.png").stat().st_size > 5000
    with h5py.File(out / "evaluation.h5") as f:
        att = json.loads(f.attrs["uncertainty"])
        assert U.NO_COVARIANCE_NOTE in att["left"]["notes"] and att["left"]["coverage_factor_k"] == 1
        for cam in ("left", "right"):
            g = f[cam]
            units = {n: g[n].attrs["units"] for n in ("height_std_um", "height_std_noise_um",
                                                      "height_std_calibration_um", "slope_std_urad",
                                                      "slope_std_noise_urad", "slope_std_calibration_urad")}
            assert units == {"height_std_um": "um", "height_std_noise_um": "um", "height_std_calibration_um": "um",
                             "slope_std_urad": "urad", "slope_std_noise_urad": "urad",
                             "slope_std_calibration_urad": "urad"}
            h = g["height_std_um"][()]
            assert g["slope_std_urad"].shape == h.shape + (2,)
            # at the seed the images' noise adds nothing and the anchor's σ (10 µm × ∂z/∂z₀ = 1) remains
            # (the anchor's σ is part of the noise contribution: docs/conventions.md "Uncertainty")
            assert h[30, 48] == pytest.approx(10.0, rel=1e-3)
    fit = json.loads((out / "surface_fit.json").read_text())
    assert fit["focal_length_x_std_mm"] > 0 and set(fit["coefficients_std"]) == set("abcde")
    # --no-uncertainty: no σ, no figure, and said so in the attribute
    out2 = tmp_path / "ev2"
    r = _run(["evaluate", str(sim), "--setup", str(small_setup_file), "--out", str(out2), "--quiet",
              "--no-uncertainty"])
    assert r.exit_code == 0 and "standard uncertainty" not in r.output
    assert not (out2 / "height_std_left.png").exists()
    with h5py.File(out2 / "evaluation.h5") as f:
        assert "height_std_um" not in f["left"] and json.loads(f.attrs["uncertainty"])["omitted"]


def test_api_and_anchor_key(tiny):
    """pmdsim.evaluate carries σ by default (read-only), skips it on request; the seed height's
    σ enters at the seed; the manifest anchor key distance_std_mm is read."""
    import pmdsim
    from pmdsim.evaluation.anchor import anchor_from_dict
    from pmdsim.studies.uncertainty_job import anchor_std_mm

    s, _, dec = tiny
    ev = pmdsim.evaluate(dec, s, "left", seed_height_std_mm=0.002)
    sv, su = ev.reconstruction.seed_pixel
    assert ev.height_std_um[sv, su] == pytest.approx(2.0, rel=1e-6)  # ∂z/∂z₀ = 1 at the seed
    assert ev.slope_std_urad.shape == ev.height_mm.shape + (2,) and not ev.height_std_um.flags.writeable
    assert pmdsim.evaluate(dec, s, "left", uncertainty=False).uncertainty is None
    a = anchor_from_dict({"kind": "distance", "pixel_vu": [7, 12], "distance_mm": 600.0,
                          "point_world_mm": [0, 0, 0], "distance_std_mm": 0.05})
    assert a.distance_std_mm == 0.05 and anchor_std_mm(a, None) == 0.05 and anchor_std_mm(a, 0.1) == 0.1


def test_a_decoder_sigma_that_is_not_finite_is_refused_and_the_heights_stand(tiny):
    """NaN σ of the screen coordinates at reconstructed pixels (a decoder or an importer that
    cannot state it) would propagate as σ = 0, i.e. exact heights: surface_uncertainty refuses
    it, naming the camera and the count; pmdsim.evaluate warns and returns the same heights."""
    from dataclasses import replace

    import pmdsim
    from pmdsim.errors import ConsistencyWarning

    s, _, dec = tiny
    holed = replace(dec, std_xy_mm=np.where(dec.valid[..., None], np.nan, dec.std_xy_mm))
    reg, rec = evaluate_decoded(s, "left", holed)
    with pytest.raises(U.UncertaintyError, match=r"'left'.*std_xy_mm.*not finite at \d+ reconstructed"):
        U.surface_uncertainty(s, "left", holed, reg, rec, method="stepwise")
    with pytest.warns(ConsistencyWarning, match="uncertainty"):
        ev = pmdsim.evaluate(holed, s, "left")
    assert ev.uncertainty is None
    np.testing.assert_array_equal(ev.height_mm, pmdsim.evaluate(dec, s, "left", uncertainty=False).height_mm)


def test_combine_is_the_root_sum_square_bit_for_bit():
    """combine's compiled two-array pass against numpy's sqrt(a² + b²) written here: equal bit for
    bit (NaN where either is NaN), for (H, W) and (H, W, 2) maps, strided inputs, huge and tiny
    values; three parts and scalars take the numpy expression."""
    rng = np.random.default_rng(3)
    for shape in [(120, 96), (64, 80, 2)]:
        a = rng.lognormal(0.0, 6.0, shape) * rng.choice([-1.0, 1.0], shape)
        b = rng.lognormal(0.0, 6.0, shape)
        a.flat[::97] = np.nan
        b.flat[5::89] = 0.0
        want = np.sqrt(a * a + b * b)
        got = U.combine(a, b)
        assert got.shape == shape and np.array_equal(got, want, equal_nan=True)
        assert np.array_equal(U.combine(a[::-1], b[::-1]), want[::-1], equal_nan=True)  # strided views
    c = rng.random((70, 70))
    assert np.array_equal(U.combine(c, c, c), np.sqrt(c * c + c * c + c * c))
    assert U.combine(3.0, 4.0) == 5.0
