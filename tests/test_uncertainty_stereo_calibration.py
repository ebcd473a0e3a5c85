"""The calibration's contribution to the σ of stereo evaluations (issue 22, ``--stereo``): the
linearised chain (moved registrations, re-solved anchors, the anchored integration's
Gauss–Newton step) against central differences of the nonlinear chain with the anchors
re-solved by scipy on the public residual; the principal-axes sum against the dense
diag(J C Jᵀ); and a small Monte Carlo over calibrations from independent noisy images
(benchmarks/mc_uncertainty_calibration_stereo.py is the full one)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from scipy.optimize import least_squares

from pmdsim.calibration import calibrate, calibrated_setup, nominal_setup, nominal_state
from pmdsim.evaluation.integration import _points_and_normals
from pmdsim.evaluation.stereo import (_integrate_anchored, _view_arrays, evaluate_stereo_decoded, reconstruct_stereo,
                                      refine_anchors, stereo_residual, stereo_views)
from pmdsim.evaluation.surface_fit import sample_slopes
from pmdsim.evaluation.uncertainty import NO_COVARIANCE_NOTE
from pmdsim.evaluation.uncertainty_calibration import CalibrationUncertaintyError, principal_axes
from pmdsim.evaluation.uncertainty_stereo import stereo_uncertainty
from pmdsim.evaluation.uncertainty_stereo_calibration import (StereoLinearisation, stereo_calibration_contribution,
                                                              stereo_calibration_parameters)
from pmdsim.setup import default_setup
from pmdsim.setup.covariance import perturbed_setup
from pmdsim.simulation.render import trace_setup_camera
from pmdsim.studies import observe_calibration_poses, trace_calibration_poses
from pmdsim.studies.calibration_data import simulate_decoded

DS = 32  # 60 × 37 px per camera
CAL_STRIDE = 4  # calibration correspondences: every 4th pixel (≈ 130 per camera and pose)
ANCHOR_STRIDE = 4  # ≈ 100 anchors per camera
NOISE = 2.0


def _calibrated(truth, traced, seed):
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    res = calibrate(observe_calibration_poses(truth.with_patterns(noise_std=NOISE, seed=seed), traced, CAL_STRIDE),
                    nominal_state(nominal, poses))
    assert res.converged, res.reason
    return calibrated_setup(nominal, res)


@pytest.fixture(scope="module")
def chain():
    """A calibration of the 32×-binned Table 1 setup from noisy images, one noisy decoded
    stereo measurement of its planar sample, and the stereo evaluation with that calibration."""
    truth = default_setup().binned(DS)
    traced = trace_calibration_poses(truth, CAL_STRIDE)
    model = _calibrated(truth, traced, 7)
    meas = truth.with_patterns(noise_std=NOISE, seed=999)
    dec = {c: simulate_decoded(meas, c, trace_setup_camera(truth, c)) for c in truth.cameras}
    _, st = evaluate_stereo_decoded(model, dec, stride_px=ANCHOR_STRIDE)
    return truth, traced, model, dec, st


def _nonlinear(model, dec, st, names, delta, scipy_every=10):
    """Heights (mm), slopes and anchor heights of the stereo chain for ``model`` moved by
    ``delta``: the anchors re-solved from the evaluation's by the search's Gauss–Newton, every
    ``scipy_every``-th also by scipy on the public residual (with the other camera; returned
    separately), then the nonlinear anchored integration with them."""
    m = perturbed_setup(model, delta, names)
    views = stereo_views(m, dec)
    out = {}
    for c, sc in st.cameras.items():
        partner = next(p for p in views if p != c)
        a, _, _ = refine_anchors(views, c, sc.anchor_pixels, sc.anchor_height_mm)
        ks = np.arange(0, a.size, scipy_every)
        a_scipy = np.array([least_squares(lambda z: stereo_residual(views, c, partner, tuple(sc.anchor_pixels[k]), z)[0],
                                          sc.anchor_height_mm[k], xtol=1e-15, ftol=1e-15, gtol=1e-15).x[0] for k in ks])
        o, d, q, valid = _view_arrays(views[c])
        z, S, *_ = _integrate_anchored(o, d, q, valid, sc.anchor_pixels, a, 1e-12, 30)
        z = np.where(sc.reconstructed, z, np.nan)
        out[c] = (z, sample_slopes(_points_and_normals(o, d, q, z)[1]), a, (ks, a_scipy))
    return out


def test_linearised_change_against_the_nonlinear_chain(chain):
    """Single parameters of each kind (intrinsics, a camera's rotation and position, the table
    plane): δz, δg and δa of the linearisation against central differences of the nonlinear
    chain; every 10th anchor's change also against scipy's root of the public residual."""
    _, _, model, dec, st = chain
    names = stereo_calibration_parameters(model, st.cameras)
    assert len(names) == 31  # 2 × 14 per camera + the table plane (planar screen)
    lin = StereoLinearisation(model, dec, st, names)
    sd = model.calibration_covariance.subset(names).std
    errors, scales = {}, {}
    for name in ("left.fx_px", "right.rotvec_x", "left.position_z_mm", "table.tilt_a", "table.d_mm"):
        j = names.index(name)
        delta = np.zeros(len(names))
        delta[j] = sd[j]
        pred = lin.change(delta, central=True)
        plus, minus = _nonlinear(model, dec, st, names, delta), _nonlinear(model, dec, st, names, -delta)
        for c in st.cameras:
            S = st.cameras[c].reconstructed
            ks = plus[c][3][0]
            refs = {"heights": 0.5 * (plus[c][0] - minus[c][0]), "slopes": 0.5 * (plus[c][1] - minus[c][1]),
                    "anchors": 0.5 * (plus[c][2] - minus[c][2]),
                    "anchors (scipy)": 0.5 * (plus[c][3][1] - minus[c][3][1])}
            a_pred = pred[c][2][lin.anchor_node[c]]  # (every pixel: stride 1)
            preds = {"heights": pred[c][0], "slopes": pred[c][1], "anchors": a_pred, "anchors (scipy)": a_pred[ks]}
            for what, ref in refs.items():
                m = S if what in ("heights", "slopes") else np.ones(ref.shape, bool)
                errors[name, c, what] = np.max(np.abs(preds[what][m] - ref[m]))
                scales[c, what] = max(scales.get((c, what), 0.0), np.max(np.abs(ref[m])))
    # each error against the largest change of that quantity over the parameters (a table shift
    # along its normal leaves the slopes unchanged: there the reference is rounding)
    for (name, c, what), err in errors.items():
        assert scales[c, what] > 0
        assert err < 0.01 * scales[c, what], f"{name} {c} {what}: {err / scales[c, what]:.2e} of the largest change"


def test_principal_axes_sum_to_the_dense_reference(chain):
    """The contribution (principal axes, forward differences of 0.01 σ) against the definition:
    per-parameter central differences of the nonlinear chain (anchors re-solved by the search's
    Gauss–Newton, the nonlinear anchored integration), then diag(J C Jᵀ)."""
    _, _, model, dec, st = chain
    names = stereo_calibration_parameters(model, st.cameras)
    cov = model.calibration_covariance.subset(names)
    # the axes reproduce C
    ax = np.array(principal_axes(cov))
    np.testing.assert_allclose(ax.T @ ax, cov.matrix, atol=1e-9 * np.abs(cov.matrix).max())
    got = stereo_calibration_contribution(model, dec, st)
    assert got.n_axes == len(names) and got.parameters == names
    jac = {c: [] for c in st.cameras}
    for j in range(len(names)):
        fields = []
        for sign in (1.0, -1.0):
            delta = np.zeros(len(names))
            delta[j] = sign * 0.1 * cov.std[j]
            m = perturbed_setup(model, delta, names)
            views = stereo_views(m, dec)
            f = {}
            for c, sc in st.cameras.items():
                a, _, _ = refine_anchors(views, c, sc.anchor_pixels, sc.anchor_height_mm)
                o, d, q, valid = _view_arrays(views[c])
                z, *_ = _integrate_anchored(o, d, q, valid, sc.anchor_pixels, a, 1e-12, 30)
                g = sample_slopes(_points_and_normals(o, d, q, z)[1])
                f[c] = np.concatenate([z[..., None], g], axis=-1)
            fields.append(f)
        for c in st.cameras:
            jac[c].append((fields[0][c] - fields[1][c]) / (0.2 * cov.std[j]))
    for c, sc in st.cameras.items():
        J = np.stack(jac[c], axis=-1)
        var = np.einsum("hwkp,pq,hwkq->hwk", J, cov.matrix, J)
        S = sc.reconstructed
        h_ref, g_ref = np.sqrt(var[..., 0]) * 1e3, np.sqrt(var[..., 1:]) * 1e6
        h, g = got.cameras[c].height_std_um, got.cameras[c].slope_std_urad
        assert np.array_equal(np.isfinite(h), S)
        assert np.max(np.abs(h - h_ref)[S]) < 0.01 * np.sqrt(np.mean(h_ref[S] ** 2))
        for k in range(2):
            assert np.max(np.abs(g[..., k] - g_ref[..., k])[S]) < 0.01 * np.sqrt(np.mean(g_ref[..., k][S] ** 2))


def test_threads_do_not_change_the_result_and_are_restored(chain):
    """The calibration part runs on one numba thread by default (speed, docs/benchmarks.md); with
    all the caller's threads it gives the same arrays bit for bit, and the caller's thread
    count is restored after either (also after an error)."""
    _, _, model, dec, st = chain
    before = numba.get_num_threads()
    one = stereo_calibration_contribution(model, dec, st)
    assert numba.get_num_threads() == before
    every = stereo_calibration_contribution(model, dec, st, threads=numba.config.NUMBA_NUM_THREADS)
    assert numba.get_num_threads() == before
    for c in st.cameras:
        for key in ("height_std_um", "slope_std_urad"):
            assert np.array_equal(getattr(one.cameras[c], key), getattr(every.cameras[c], key), equal_nan=True)
        assert np.array_equal(one.anchor_height_std_um[c], every.anchor_height_std_um[c], equal_nan=True)
    with pytest.raises(CalibrationUncertaintyError, match="stride"):
        stereo_calibration_contribution(model, dec, st, stride=0)
    assert numba.get_num_threads() == before


def test_stereo_sigma_carries_the_calibration_part_and_says_so(chain):
    _, _, model, dec, st = chain
    views = stereo_views(model, dec)
    u = stereo_uncertainty(model, views, dec, st, samples=16)
    for c, (unc, a_std) in u.items():
        S = st.cameras[c].reconstructed
        hc, hn = unc.height_std_calibration_um[S], unc.height_std_noise_um[S]
        assert np.all(hc > 0)
        np.testing.assert_allclose(unc.height_std_um[S], np.hypot(hn, hc))
        assert np.all(np.isfinite(a_std)) and any("calibration covariance propagated" in n for n in unc.notes)
    bare = stereo_uncertainty(model.with_calibration_covariance(None), views, dec, st, samples=16)
    for c, (unc, _) in bare.items():
        S = st.cameras[c].reconstructed
        assert np.all(unc.height_std_calibration_um[S] == 0) and NO_COVARIANCE_NOTE in unc.notes
    with pytest.raises(CalibrationUncertaintyError, match="no calibration covariance"):
        stereo_calibration_contribution(model.with_calibration_covariance(None), dec, st)


def test_monte_carlo_over_calibrations(chain):
    """Calibrations from independent noisy calibration images (fixed seeds), each evaluating the
    same stereo measurement with the full chain (search included): the observed scatter of the
    absolute heights and slopes against the predicted σ. N = 24 draws: the sampling error of a
    ratio is 1/√(2·23) = 0.15; the tolerance is three of them (the full Monte Carlo with ≥ 50
    calibrations: docs/benchmarks.md)."""
    truth, traced, model, dec, st = chain
    pred = stereo_calibration_contribution(model, dec, st)
    n = 24
    fields = {c: [] for c in st.cameras}
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # small images: threads would cost more than the work
    try:
        for i in range(n):
            m = _calibrated(truth, traced, 100 + i)
            _, s = evaluate_stereo_decoded(m, dec, stride_px=ANCHOR_STRIDE)
            for c, sc in s.cameras.items():
                z = np.where(sc.reconstructed, sc.height_mm, np.nan)
                fields[c].append(np.concatenate([z[..., None] * 1e3, sample_slopes(sc.reconstruction.n_sample) * 1e6],
                                                axis=-1))
    finally:
        numba.set_num_threads(threads)
    for c in st.cameras:
        obs = np.std(np.stack(fields[c]), axis=0, ddof=1)
        p = np.concatenate([pred.cameras[c].height_std_um[..., None], pred.cameras[c].slope_std_urad], axis=-1)
        ok = np.isfinite(obs).all(axis=-1) & np.isfinite(p).all(axis=-1)
        for k, what in enumerate(("height", "slope x", "slope y")):
            ratio = np.sqrt(np.mean(obs[..., k][ok] ** 2) / np.mean(p[..., k][ok] ** 2))
            print(f"{c} {what}: observed / predicted σ {ratio:.3f}")
            assert abs(ratio - 1) < 3 / np.sqrt(2 * (n - 1)), (c, what, ratio)


def test_std_maps_are_numpys_sqrt_and_scale_bit_for_bit():
    """The calibration part's σ maps from its variances by one compiled pass against numpy's
    ``var[~S] = nan; sqrt(var[..., 0]) * 1e3, sqrt(var[..., 1:]) * 1e6``."""
    from pmdsim.evaluation.uncertainty_stereo_calibration import _std_maps

    rng = np.random.default_rng(3)
    var = rng.lognormal(-8, 3, size=(37, 53, 3))
    var[5, 7, 1] = 0.0
    var[6, 8, 2] = np.nan
    S = rng.random((37, 53)) > 0.2
    h, g = np.empty((37, 53)), np.empty((37, 53, 2))
    _std_maps(var, S, h, g)
    ref = var.copy()
    ref[~S] = np.nan
    np.testing.assert_array_equal(h, np.sqrt(ref[..., 0]) * 1e3)
    np.testing.assert_array_equal(g, np.sqrt(ref[..., 1:]) * 1e6)
