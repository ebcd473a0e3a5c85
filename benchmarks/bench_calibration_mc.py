"""Monte Carlo over image noise: the calibration's reported σ against the observed spread (issue 5).

Each draw simulates the 16 calibration poses × 2 cameras through the whole image chain
(``--render full``: ``experiments.simulate_calibration_observations``: trace, render 8-bit
fringe images with Gaussian noise of ``--noise`` grey levels from seed ``--seed0 + i``, an
independent stream per camera and pose, decode, keep every ``--stride``-th pixel; or
``--render strided``: trace once, then render and decode only every ``--stride``-th pixel — the
same distribution, since rendering is point-sampled and decoding per pixel, at a fraction of the
cost, for many draws) and calibrates it from the nominal
start values perturbed by ``experiments.INITIAL_ERRORS`` (``--start perturbed``) or from the true
cameras and planes (``--start true``). Models: ``planar`` (flat true screen) and ``NxN`` free
screen grids (true screen: the paper's bulge ``--bulge-mm``, which the 3 × 3 and 5 × 5 splines
represent exactly); the draws of one truth are shared by its models.

Printed per model: per parameter group the RMS reported σ, the observed σ (about the Monte
Carlo mean) and their pooled ratio (z-scores; ± its standard error from the effective degrees
of freedom); per block (intrinsics, camera poses, mirror planes, screen heights) and overall the
whitened ratio √(Σ dᵀC⁻¹d / ((n−1)P)), exact χ² statistics, ± 1/√(2·dof). The issue's
criterion: predicted and observed spreads agree within 30 %.

    python benchmarks/bench_calibration_mc.py [--json] [--downsample 4] [--draws 16]
        [--models planar,3x3] [--noise 2] [--stride 8] [--start perturbed] [--seed0 100]
        [--render full|strided]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

import numba
import numpy as np

from _common import dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.calibration import (calibrate, compare_spread, free_screen_model, nominal_setup, nominal_state,
                                parameter_group, perturbed_state)
from pmdsim.studies import (INITIAL_ERRORS, observe_calibration_poses, simulate_calibration_observations,
                            trace_calibration_poses)
from pmdsim.setup import default_setup


def parse_models(text: str) -> list[tuple[str, int | None]]:
    out = []
    for item in text.split(","):
        item = item.strip().lower()
        if item == "planar":
            out.append(("planar", None))
            continue
        a, sep, b = item.partition("x")
        if not (sep and a.isdigit() and a == b and int(a) >= 3):
            raise SystemExit(f"--models: expected 'planar' or 'NxN' with N ≥ 3, got {item!r}")
        out.append((item, int(a)))
    if not out:
        raise SystemExit("--models: give at least one model")
    return out


def summarise(cmp) -> dict:
    groups = {}
    for g, (ratio, dof, count) in cmp.group_ratios().items():
        idx = [j for j, n in enumerate(cmp.parameter_names) if parameter_group(n) == g]
        groups[g] = {
            "parameters": count,
            "reported_std": float(np.sqrt(np.mean(cmp.reported_std[idx] ** 2))),
            "observed_std": float(np.sqrt(np.mean(cmp.observed_std[idx] ** 2))),
            "ratio": ratio,
            "ratio_se": cmp.ratio_standard_error(dof),
        }
    blocks = {b: {"parameters": count, "whitened_ratio": r, "ratio_se": cmp.ratio_standard_error(dof)}
              for b, (r, dof, count) in cmp.block_ratios().items()}
    return {
        "draws": cmp.n_draws,
        "parameters": len(cmp.parameter_names),
        "whitened_ratio": cmp.whitened_ratio,
        "whitened_ratio_se": cmp.ratio_standard_error(cmp.whitened_dof),
        "marginal_ratio": cmp.marginal_ratio,
        "marginal_ratio_se": cmp.ratio_standard_error(cmp.marginal_dof),
        "blocks": blocks,
        "groups": groups,
    }


def print_table(label: str, s: dict, extra: dict) -> None:
    print(f"\n{label}: {s['draws']} draws, {s['parameters']} parameters, σ₀ = {extra['screen_noise_std']:.4g}, "
          f"rms {extra['rms_px']:.4g} px, {extra['iterations']:.1f} iterations per calibration")
    print(f"{'group':16s} {'n':>3s} {'reported σ':>12s} {'observed σ':>12s} {'obs/rep':>8s} {'± se':>6s}")
    for g, v in s["groups"].items():
        flag = "" if abs(v["ratio"] - 1) <= 0.3 else "  (outside 30 %)"
        print(f"{g:16s} {v['parameters']:3d} {v['reported_std']:12.4g} {v['observed_std']:12.4g} "
              f"{v['ratio']:8.3f} {v['ratio_se']:6.3f}{flag}")
    for b, v in s["blocks"].items():
        print(f"whitened, {b:12s} ({v['parameters']:2d} parameters): {v['whitened_ratio']:.3f} ± {v['ratio_se']:.3f}")
    print(f"whitened, all parameters          : {s['whitened_ratio']:.3f} ± {s['whitened_ratio_se']:.3f}")
    print(f"marginal (pooled z), all          : {s['marginal_ratio']:.3f} ± {s['marginal_ratio_se']:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--downsample", type=int, default=4, help="bin the cameras k × k (default 4: 480 × 300 px)")
    ap.add_argument("--draws", type=int, default=16, help="noise realisations (default 16)")
    ap.add_argument("--models", default="planar,3x3", help="comma-separated: planar, NxN (default planar,3x3)")
    ap.add_argument("--noise", type=float, default=2.0, help="image noise σ in grey levels (default 2)")
    ap.add_argument("--stride", type=int, default=None, help="observation stride in px (default: the setup's, 8)")
    ap.add_argument("--bulge-mm", type=float, default=3.0, help="true bulge for the NxN models (default 3)")
    ap.add_argument("--start", choices=("perturbed", "true"), default="perturbed")
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--render", choices=("full", "strided"), default="full",
                    help="render every pixel (the experiments' chain) or only the strided ones (fast)")
    args = ap.parse_args()
    if args.draws < 2 or args.downsample < 1 or args.noise <= 0 or (args.stride is not None and args.stride < 1):
        raise SystemExit("--draws ≥ 2, --downsample ≥ 1, --noise > 0 and --stride ≥ 1 are required")
    models = parse_models(args.models)

    base = default_setup().binned(args.downsample)
    if args.stride is not None:
        base = replace(base, calibration=replace(base.calibration, observation_stride_px=args.stride))
    truths = {"flat": base.with_bulge(0.0), "bulge": base.with_bulge(args.bulge_mm)}
    by_truth: dict[str, list[tuple[str, int | None]]] = {}
    for label, grid in models:
        by_truth.setdefault("flat" if grid is None else "bulge", []).append((label, grid))

    res = {"pmdsim_version": __version__, "threads": numba.get_num_threads(), "downsample": args.downsample,
           "image_px": [base.cameras["left"].camera.width_px, base.cameras["left"].camera.height_px],
           "stride_px": base.calibration.observation_stride_px, "noise_grey": args.noise, "draws": args.draws,
           "start": args.start, "render": args.render, "models": {}}
    t_all = time.perf_counter()
    t_sim = t_cal = 0.0
    for key, group in by_truth.items():
        truth = truths[key]
        nominal = nominal_setup(truth)
        poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
        true_state = nominal_state(nominal, poses)
        results = {label: [] for label, _ in group}
        stride = truth.calibration.observation_stride_px
        traced = trace_calibration_poses(truth, stride) if args.render == "strided" else None
        for i in range(args.draws):
            t0 = time.perf_counter()
            noisy = replace(truth, patterns=replace(truth.patterns, noise_std=args.noise, seed=args.seed0 + i))
            if traced is None:
                obs = simulate_calibration_observations(noisy)
            else:
                obs = observe_calibration_poses(noisy, traced, stride)
            t_sim += time.perf_counter() - t0
            start = true_state if args.start == "true" else perturbed_state(
                true_state, np.random.default_rng([args.seed0, i]), **INITIAL_ERRORS)
            for label, grid in group:
                t0 = time.perf_counter()
                r = calibrate(obs, start, screen_model=None if grid is None else free_screen_model(nominal, grid))
                t_cal += time.perf_counter() - t0
                if not r.converged:
                    raise SystemExit(f"{label}, draw {i}: the calibration did not converge: {r.reason}")
                results[label].append(r)
            if not args.json:
                print(f"draw {i + 1}/{args.draws} ({key} screen) done, {time.perf_counter() - t_all:.0f} s",
                      file=sys.stderr, flush=True)
        for label, rs in results.items():
            s = summarise(compare_spread(rs))
            s["screen_noise_std"] = float(np.median([r.screen_noise_std for r in rs]))
            s["rms_px"] = float(np.median([r.rms_px for r in rs]))
            s["iterations"] = float(np.mean([r.iterations for r in rs]))
            s["correspondences"] = int(rs[0].n_residuals // 2)
            res["models"][label] = s
    res["simulate_s"] = t_sim
    res["calibrate_s"] = t_cal
    res["total_s"] = time.perf_counter() - t_all
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)
        return
    w, h = res["image_px"]
    print(f"pmdsim {__version__}, {res['threads']} threads; cameras {w}×{h} px (downsample {args.downsample}), "
          f"stride {res['stride_px']} px, noise {args.noise:g} grey levels, {args.draws} draws, start {args.start}, "
          f"render {args.render}")
    for label, s in res["models"].items():
        print_table(f"{label} ({s['correspondences']} correspondences)", s, s)
    print(f"\nsimulate + decode {t_sim:.0f} s, calibrate {t_cal:.0f} s, total {res['total_s']:.0f} s, "
          f"peak memory {res['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
