"""Monte Carlo over calibrations: the calibration's predicted σ of heights and slopes against
the observed scatter (issue 22, item 5).

Truth: the paper's Table 1 setup binned ``--downsample`` × ``--downsample`` (``planar``: flat
screen; ``NxN``: the paper's bulge ``--bulge-mm`` calibrated with an N × N free-form screen
model, evaluated with the calibrated screen surface). Each of ``--calibrations`` draws renders
the 16 calibration poses × 2 cameras with independent 8-bit image noise (``--noise`` grey
levels, seed ``--seed0 + i``; every ``--stride``-th pixel, as ``tests/test_calibration_uncertainty.py``)
and calibrates them (the decoder's σ as the correspondences' weights); the calibrated setup
then evaluates *the same* decoded measurement of the planar sample (one fixed noisy image set),
heights relative to the seed pixel (``--anchor none``) or to a height anchor at the image
centre (``--anchor height``). Per camera and pixel the observed standard deviation of heights
and slopes over the calibrations is compared with the predicted
:func:`pmdsim.evaluation.uncertainty_calibration.calibration_contribution` (RMS over the
calibrations of each one's prediction): the ratio of RMS over pixels, overall and in 5 bins of
distance from the seed. The sampling error of one ratio is about 1/√(2(N − 1)).

    python benchmarks/mc_uncertainty_calibration.py [--downsample 8] [--calibrations 60]
        [--models planar,5x5] [--noise 2] [--stride 16] [--anchor none|height] [--json]

``--speed``: instead, the full-resolution cost and subgrid error of one camera's contribution
(a covariance from a strided full-resolution calibration; reference: stride 1, central
differences).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _common import dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.calibration import calibrate, calibrated_setup, free_screen_model, nominal_setup, nominal_state
from pmdsim.evaluation.anchor import HeightAnchor, default_seed_pixel, reconstruct_anchored, register_model
from pmdsim.evaluation.surface_fit import sample_slopes
from pmdsim.evaluation.uncertainty_calibration import calibration_contribution
from pmdsim.setup import default_setup
from pmdsim.simulation.render import trace_setup_camera
from pmdsim.studies import observe_calibration_poses, trace_calibration_poses
from pmdsim.studies.calibration_data import simulate_decoded

MEASUREMENT_SEED = 999_999


def _truth(downsample, grid, bulge_mm):
    s = default_setup().binned(downsample)
    return s.with_bulge(bulge_mm if grid else 0.0)


def _noisy(truth, noise, seed):
    return truth.with_patterns(noise_std=noise, seed=seed)


def run_model(label, args):
    grid = None if label == "planar" else int(label.split("x")[0])
    truth = _truth(args.downsample, grid, args.bulge_mm)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = nominal_state(nominal, poses)
    screen = None if grid is None else free_screen_model(nominal, grid)
    traced = trace_calibration_poses(truth, args.stride)
    meas = _noisy(truth, args.noise, MEASUREMENT_SEED)
    decoded = {c: simulate_decoded(meas, c, trace_setup_camera(truth, c)) for c in truth.cameras}
    anchors, seeds = {}, {}
    for c, dec in decoded.items():
        H, W = dec.valid.shape
        anchors[c] = HeightAnchor((H / 2 + 0.3, W / 2 + 0.4), 0.0) if args.anchor == "height" else None
    obs_f = {c: [] for c in truth.cameras}
    pred_v = {c: [] for c in truth.cameras}
    t_cal = t_pred = 0.0
    for i in range(args.calibrations):
        t = time.perf_counter()
        res = calibrate(observe_calibration_poses(_noisy(truth, args.noise, args.seed0 + i), traced, args.stride),
                        start, screen_model=screen)
        if not res.converged:
            raise SystemExit(f"{label}: calibration {i} did not converge: {res.reason}")
        model = calibrated_setup(nominal, res)
        t_cal += time.perf_counter() - t
        sm = None if grid is None else model.screen.surface
        for c, dec in decoded.items():
            reg = register_model(model, c, dec, screen_model=sm)
            ar = reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=anchors[c],
                                      T_world_ref=model.sample.T_world_sample, method=args.method)
            rec = ar.reconstruction
            seeds.setdefault(c, rec.seed_pixel)
            f = np.concatenate([rec.height_mm[..., None] * 1e3, sample_slopes(rec.n_sample) * 1e6], axis=-1)
            f[~rec.reconstructed] = np.nan
            obs_f[c].append(f)
            t = time.perf_counter()
            cc = calibration_contribution(model, c, dec, anchor=anchors[c], method=args.method, screen_model=sm)
            t_pred += time.perf_counter() - t
            pred_v[c].append(np.concatenate([cc.height_std_um[..., None] ** 2, cc.slope_std_urad ** 2], axis=-1))
    out = {"model": label, "calibrations": args.calibrations, "seconds_calibrate": t_cal,
           "seconds_predict": t_pred, "cameras": {}}
    for c in truth.cameras:
        f = np.stack(obs_f[c])
        obs = np.nanstd(f, axis=0, ddof=1)
        pred = np.sqrt(np.mean(np.stack(pred_v[c]), axis=0))
        ok = np.isfinite(obs).all(axis=-1) & np.isfinite(pred).all(axis=-1) & (pred[..., 0] > 0)
        out["cameras"][c] = ratio_table(obs, pred, ok, seeds[c])
    return out


def ratio_table(obs, pred, ok, centre) -> dict:
    """Observed / predicted σ of height, slope x and slope y (obs, pred (H, W, 3)) over the pixels
    ``ok``: the ratio of RMS, overall and in 5 bins (quantiles) of distance from ``centre`` (v, u)."""
    vv, uu = np.nonzero(ok)
    r = np.hypot(vv - centre[0], uu - centre[1])
    edges = np.quantile(r, np.linspace(0, 1, 6))
    cam = {"pixels": int(ok.sum()), "bin_edges_px": edges.tolist()}
    for k, name in enumerate(("height", "slope_x", "slope_y")):
        o, p = obs[..., k][ok], pred[..., k][ok]
        bins = []
        for b in range(5):
            m = (r >= edges[b]) & (r <= edges[b + 1])
            bins.append(float(np.sqrt(np.mean(o[m] ** 2) / np.mean(p[m] ** 2))))
        cam[name] = {"ratio_rms": float(np.sqrt(np.mean(o ** 2) / np.mean(p ** 2))),
                     "ratio_median": float(np.median(o / p)), "ratio_bins": bins,
                     "predicted_rms": float(np.sqrt(np.mean(p ** 2))), "observed_rms": float(np.sqrt(np.mean(o ** 2)))}
    return cam


def print_ratios(c: str, cam: dict, centre: str) -> None:
    """The lines of :func:`ratio_table`'s result for camera ``c``."""
    for name in ("height", "slope_x", "slope_y"):
        q = cam[name]
        print(f"  {c} {name:8s} RMS pred {q['predicted_rms']:.4g} obs {q['observed_rms']:.4g}  ratio "
              f"{q['ratio_rms']:.3f} (median per pixel {q['ratio_median']:.3f}); by distance from the "
              f"{centre}: " + " ".join(f"{b:.3f}" for b in q["ratio_bins"]))


def speed(args):
    """Full-resolution cost of one camera's contribution and its subgrid error."""
    truth = default_setup().with_patterns(noise_std=args.noise, seed=7)
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    stride = 8 * args.stride
    t = time.perf_counter()
    res = calibrate(observe_calibration_poses(truth, trace_calibration_poses(truth, stride), stride),
                    nominal_state(nominal, poses))
    model = calibrated_setup(nominal, res)
    t_cal = time.perf_counter() - t
    dec = simulate_decoded(truth, "left", trace_setup_camera(truth, "left"))
    reg = register_model(model, "left", dec)
    t = time.perf_counter()
    reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, T_world_ref=model.sample.T_world_sample)
    t_rec = time.perf_counter() - t
    calibration_contribution(model, "left", dec)  # compile
    times = []
    for _ in range(3):
        t = time.perf_counter()
        c = calibration_contribution(model, "left", dec)
        times.append(time.perf_counter() - t)
    out = {"calibration_s": t_cal, "reconstruction_s": t_rec, "contribution_s": min(times),
           "stride_px": c.stride_px, "axes": c.n_axes, "shape": list(c.height_std_um.shape)}
    for ref_stride in args.ref_strides:
        t = time.perf_counter()
        ref = calibration_contribution(model, "left", dec, stride=ref_stride, central=True)
        m = np.isfinite(ref.height_std_um)
        eh = np.abs(c.height_std_um - ref.height_std_um)[m]
        eg = np.abs(c.slope_std_urad - ref.slope_std_urad)[m]
        rh = np.sqrt(np.mean(ref.height_std_um[m] ** 2))
        rg = np.sqrt(np.mean(ref.slope_std_urad[m] ** 2, axis=0))
        out[f"reference_stride{ref_stride}"] = {
            "seconds": time.perf_counter() - t,
            "height_max_err_of_rms": float(eh.max() / rh), "height_p99_err_of_rms": float(np.percentile(eh, 99) / rh),
            "slope_max_err_of_rms": (eg.max(axis=0) / rg).tolist(),
            "slope_p99_err_of_rms": (np.percentile(eg, 99, axis=0) / rg).tolist(),
            "height_rms_um": float(rh), "slope_rms_urad": rg.tolist()}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=8)
    ap.add_argument("--calibrations", type=int, default=60)
    ap.add_argument("--models", default="planar,5x5")
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--stride", type=int, default=16)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--anchor", choices=("none", "height"), default="none")
    ap.add_argument("--method", choices=("stepwise", "least_squares"), default="stepwise")
    ap.add_argument("--speed", action="store_true")
    ap.add_argument("--ref-strides", type=lambda s: [int(x) for x in s.split(",")], default=[4])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.speed:
        res = {"pmdsim": __version__, **speed(args), "peak_rss_mb": peak_rss_mb()}
        if args.json:
            dump_json(res)
        else:
            for k, v in res.items():
                print(f"{k}: {v}")
        return
    res = {"pmdsim": __version__, "downsample": args.downsample, "noise_grey": args.noise, "stride": args.stride,
           "anchor": args.anchor, "method": args.method, "models": []}
    for label in args.models.split(","):
        out = run_model(label, args)
        res["models"].append(out)
        if not args.json:
            print(f"{label}: {args.calibrations} calibrations ({out['seconds_calibrate']:.1f} s calibrating, "
                  f"{out['seconds_predict']:.1f} s predicting); observed / predicted σ (± "
                  f"{1 / np.sqrt(2 * (args.calibrations - 1)):.2f} sampling error):")
            for c, cam in out["cameras"].items():
                print_ratios(c, cam, "seed")
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)


if __name__ == "__main__":
    main()
