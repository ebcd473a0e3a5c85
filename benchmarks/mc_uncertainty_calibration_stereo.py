"""Monte Carlo over calibrations for ``--stereo``: the calibration's predicted σ of the absolute
stereo heights and slopes against the observed scatter (issue 22, item 5).

Truth: the paper's Table 1 setup binned ``--downsample`` × ``--downsample`` (``planar``: flat
screen, planar screen model; ``NxN``: the paper's bulge ``--bulge-mm`` calibrated with an N × N
free-form screen model, evaluated with the calibrated screen surface). Each of
``--calibrations`` draws renders the 16 calibration poses × 2 cameras with independent 8-bit
image noise (``--noise`` grey levels, seed ``--seed0 + i``; every ``--stride``-th pixel) and
calibrates them (the decoder's σ as the correspondences' weights); the calibrated setup then
evaluates *the same* decoded measurement of the planar sample (one fixed noisy image set of both
cameras) as ``pmdsim evaluate --stereo`` does: registration, normal-consistency search, anchored
integration — nothing held, the heights absolute in the calibrated sample frame. Per camera and
pixel the observed standard deviation of the heights and slopes over the calibrations is
compared with the predicted
:func:`pmdsim.evaluation.uncertainty_stereo_calibration.stereo_calibration_contribution` (RMS over
every ``--predict-every``-th calibration's prediction): the ratio of RMS over pixels, overall and
in 5 bins of distance from the anchors' centroid. The sampling error of one ratio is about
1/√(2(N − 1)) (the heights' σ is nearly one number per camera: the bins are correlated).
Also, per draw, the observed deviations against the linearisation's J·(θ_i − θ̄) with each
calibration's own parameters θ_i: this separates the propagation (J) from how well the
reported covariance describes the N calibrations' scatter.

    python benchmarks/mc_uncertainty_calibration_stereo.py [--downsample 16] [--calibrations 60]
        [--models planar,5x5] [--noise 2] [--stride 8] [--predict-every 10] [--json]

``--subgrid 1,2,4``: instead, the error of the calibration part's subgrid option (planar).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _common import dump_json, peak_rss_mb
from mc_uncertainty_calibration import print_ratios, ratio_table
from pmdsim import __version__
from pmdsim.calibration import calibrate, calibrated_setup, free_screen_model, nominal_setup, nominal_state
from pmdsim.evaluation.stereo import evaluate_stereo_decoded
from pmdsim.evaluation.surface_fit import sample_slopes
from pmdsim.evaluation.uncertainty_stereo_calibration import (StereoLinearisation, stereo_calibration_contribution,
                                                              stereo_calibration_parameters)
from pmdsim.setup import default_setup
from pmdsim.simulation.render import trace_setup_camera
from pmdsim.studies import observe_calibration_poses, trace_calibration_poses
from pmdsim.studies.calibration_data import simulate_decoded

MEASUREMENT_SEED = 999_999


def run_model(label, args):
    grid = None if label == "planar" else int(label.split("x")[0])
    truth = default_setup().binned(args.downsample).with_bulge(args.bulge_mm if grid else 0.0)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = nominal_state(nominal, poses)
    screen = None if grid is None else free_screen_model(nominal, grid)
    traced = trace_calibration_poses(truth, args.stride)
    meas = truth.with_patterns(noise_std=args.noise, seed=MEASUREMENT_SEED)
    decoded = {c: simulate_decoded(meas, c, trace_setup_camera(truth, c)) for c in truth.cameras}
    obs_f = {c: [] for c in truth.cameras}
    obs_a = {c: [] for c in truth.cameras}
    pred_v = {c: [] for c in truth.cameras}
    pred_a = {c: [] for c in truth.cameras}
    centroid, anchors0 = {}, {}
    t_cal = t_eval = t_pred = 0.0
    axes = 0
    results, first = [], None
    for i in range(args.calibrations):
        t = time.perf_counter()
        res = calibrate(observe_calibration_poses(truth.with_patterns(noise_std=args.noise, seed=args.seed0 + i),
                                                  traced, args.stride), start, screen_model=screen)
        if not res.converged:
            raise SystemExit(f"{label}: calibration {i} did not converge: {res.reason}")
        model = calibrated_setup(nominal, res)
        t_cal += time.perf_counter() - t
        sm = None if grid is None else model.screen.surface
        t = time.perf_counter()
        _, st = evaluate_stereo_decoded(model, decoded, screen_model=sm)
        t_eval += time.perf_counter() - t
        results.append(res)
        first = first or (model, st, sm)
        for c, sc in st.cameras.items():
            rec = sc.reconstruction
            f = np.concatenate([rec.height_mm[..., None] * 1e3, sample_slopes(rec.n_sample) * 1e6], axis=-1)
            f[~rec.reconstructed] = np.nan
            obs_f[c].append(f)
            centroid.setdefault(c, sc.anchor_pixels.mean(axis=0))
            # the first calibration's anchor pixels: their heights (interpolated in every later one)
            px = anchors0.setdefault(c, sc.anchor_pixels)
            obs_a[c].append(rec.height_mm[px[:, 0], px[:, 1]] * 1e3)
        if i % args.predict_every == 0:
            t = time.perf_counter()
            cc = stereo_calibration_contribution(model, decoded, st, screen_model=sm)
            t_pred += time.perf_counter() - t
            axes = cc.n_axes
            for c, cam in cc.cameras.items():
                pred_v[c].append(np.concatenate([cam.height_std_um[..., None] ** 2, cam.slope_std_urad ** 2], axis=-1))
                px = st.cameras[c].anchor_pixels
                pred_a[c].append(float(np.sqrt(np.mean(cam.height_std_um[px[:, 0], px[:, 1]] ** 2))))
    out = {"model": label, "calibrations": args.calibrations, "predictions": len(pred_v[next(iter(pred_v))]),
           "principal_axes": axes, "seconds_calibrate": t_cal, "seconds_evaluate": t_eval, "seconds_predict": t_pred,
           "cameras": {}}
    linear = _linear_check(first, results, decoded, obs_f)
    out["linear_check"] = linear
    for c in truth.cameras:
        f = np.stack(obs_f[c])
        obs = np.nanstd(f, axis=0, ddof=1)
        n_ok = np.isfinite(f).all(axis=-1).sum(axis=0)
        pred = np.sqrt(np.mean(np.stack(pred_v[c]), axis=0))
        ok = (n_ok == f.shape[0]) & np.isfinite(pred).all(axis=-1) & (pred[..., 0] > 0)
        cam = ratio_table(obs, pred, ok, centroid[c])
        a = np.stack(obs_a[c])
        a_obs = np.nanstd(a, axis=0, ddof=1)
        cam["anchors"] = {"observed_rms_um": float(np.sqrt(np.nanmean(a_obs ** 2))),
                          "predicted_rms_um": float(np.sqrt(np.mean(np.square(pred_a[c]))))}
        out["cameras"][c] = cam
    return out


def _linear_check(first, results, decoded, obs_f) -> dict:
    """Per draw, the observed deviation of heights and slopes from their mean over the draws
    against the linearisation's J·(θ_i − θ̄) (J: one unit step per parameter of the first
    calibration's evaluation, θ_i each calibration's parameters): separates the propagation from
    the sampling of the calibrations' scatter. Ratio sqrt(Σ obs² / Σ pred²) and the residual
    fraction sqrt(Σ (obs − pred)² / Σ obs²) over pixels and draws, per camera and quantity."""
    model, st, sm = first
    names = stereo_calibration_parameters(model, st.cameras, screen_model=sm)
    pn = list(results[0].parameter_names)
    idx = [pn.index("mirror0." + n[6:] if n.startswith("table.") else n) for n in names]
    d = np.array([results[0].state.increment_to(r.state)[idx] for r in results])
    d -= d.mean(axis=0)
    lin = StereoLinearisation(model, decoded, st, names, screen_model=sm)
    sd = model.calibration_covariance.subset(names).std
    J = {c: [] for c in st.cameras}
    for j in range(len(names)):
        delta = np.zeros(len(names))
        delta[j] = 0.01 * sd[j]
        for c, (dz, dg, _) in lin.change(delta).items():
            J[c].append(np.concatenate([dz[..., None] * 1e3, dg * 1e6], axis=-1) / delta[j])
    out = {}
    for c in st.cameras:
        pred = np.einsum("ip,phwk->ihwk", d, np.stack(J[c]))
        f = np.stack(obs_f[c])
        obs = f - np.nanmean(f, axis=0)
        ok = np.isfinite(obs).all(axis=(0, -1)) & np.isfinite(pred).all(axis=(0, -1))
        cam = {}
        for k, name in enumerate(("height", "slope_x", "slope_y")):
            o, p = obs[:, ok, k], pred[:, ok, k]
            cam[name] = {"ratio": float(np.sqrt(np.sum(o ** 2) / np.sum(p ** 2))),
                         "residual_fraction": float(np.sqrt(np.sum((o - p) ** 2) / np.sum(o ** 2)))}
        out[c] = cam
    return out


def subgrid(args) -> dict:
    """The subgrid option's error: one calibration (seed ``--seed0``), its stereo evaluation and
    the contribution at each of ``--subgrid`` strides against the first (1: every pixel)."""
    truth = default_setup().binned(args.downsample)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    traced = trace_calibration_poses(truth, args.stride)
    res = calibrate(observe_calibration_poses(truth.with_patterns(noise_std=args.noise, seed=args.seed0), traced,
                                              args.stride), nominal_state(nominal, poses))
    model = calibrated_setup(nominal, res)
    meas = truth.with_patterns(noise_std=args.noise, seed=MEASUREMENT_SEED)
    dec = {c: simulate_decoded(meas, c, trace_setup_camera(truth, c)) for c in truth.cameras}
    t = time.perf_counter()
    _, st = evaluate_stereo_decoded(model, dec)
    out = {"evaluation_s": time.perf_counter() - t, "strides": {}}
    ref = None
    for s in args.subgrid:
        t = time.perf_counter()
        c = stereo_calibration_contribution(model, dec, st, stride=s)
        row = {"seconds": time.perf_counter() - t}
        ref = ref or c
        for cam, cc in c.cameras.items():
            S = st.cameras[cam].reconstructed
            f = np.concatenate([cc.height_std_um[S][:, None], cc.slope_std_urad[S]], axis=-1)
            r = np.concatenate([ref.cameras[cam].height_std_um[S][:, None], ref.cameras[cam].slope_std_urad[S]], axis=-1)
            rms = np.sqrt(np.mean(r ** 2, axis=0))
            row[cam] = {"rms": np.sqrt(np.mean(f ** 2, axis=0)).tolist(),
                        "max_error_of_rms": (np.max(np.abs(f - r), axis=0) / rms).tolist()}
        out["strides"][s] = row
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=16)
    ap.add_argument("--calibrations", type=int, default=60)
    ap.add_argument("--models", default="planar,5x5")
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--stride", type=int, default=8)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--predict-every", type=int, default=10)
    ap.add_argument("--subgrid", type=lambda v: [int(x) for x in v.split(",")], default=None,
                    help="instead: the subgrid option's error at these strides (the first the reference)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.subgrid:
        res = subgrid(args)
        if args.json:
            dump_json(res)
        else:
            print(f"stereo evaluation {res['evaluation_s']:.1f} s")
            for s, row in res["strides"].items():
                print(f"stride {s}: {row['seconds']:.1f} s; " + "; ".join(
                    f"{c}: RMS σ (height µm, slope x, y µrad) {np.round(v['rms'], 4).tolist()}, largest error / RMS "
                    f"{np.round(v['max_error_of_rms'], 4).tolist()}" for c, v in row.items() if c != "seconds"))
        return
    res = {"pmdsim": __version__, "downsample": args.downsample, "noise_grey": args.noise, "stride": args.stride,
           "models": []}
    for label in args.models.split(","):
        out = run_model(label, args)
        res["models"].append(out)
        if not args.json:
            print(f"{label}: {args.calibrations} calibrations, {out['predictions']} predictions of "
                  f"{out['principal_axes']} principal axes ({out['seconds_calibrate']:.1f} s calibrating, "
                  f"{out['seconds_evaluate']:.1f} s evaluating, {out['seconds_predict']:.1f} s predicting); observed / "
                  f"predicted σ (± {1 / np.sqrt(2 * (args.calibrations - 1)):.2f} sampling error):")
            for c, cam in out["cameras"].items():
                print_ratios(c, cam, "anchors' centroid")
                a = cam["anchors"]
                print(f"  {c} anchors' heights: RMS pred {a['predicted_rms_um']:.4g} obs {a['observed_rms_um']:.4g} µm")
                lc = out["linear_check"][c]
                print(f"  {c} per draw, observed deviation vs J·(θ_i − θ̄): " + "; ".join(
                    f"{n} ratio {lc[n]['ratio']:.3f}, residual {lc[n]['residual_fraction']:.3f}"
                    for n in ("height", "slope_x", "slope_y")))
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)


if __name__ == "__main__":
    main()
