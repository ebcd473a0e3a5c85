"""Benchmark the free-form screen calibration (Experiment 3, beyond the paper) at full resolution.

Simulates the 16 calibration poses × 2 cameras once (Table 1 setup, Δh = 3 mm, 8-bit images
decoded in memory), then times one calibration solve for the planar screen model and for each
n × n free-form model from the same nominal start values (after a warm-up solve that compiles
the kernels). Target: the 3×3 model takes < 2× the time of the planar calibration.

    python benchmarks/bench_screen_calibration.py [--json] [--grids 3,5,9] [--bulge-mm 3] [--repeat 2]
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from _common import best_of, dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.calibration import calibrate, nominal_state, perturbed_state
from pmdsim.studies import INITIAL_ERRORS, simulate_calibration_observations
from pmdsim.calibration import free_screen_model, nominal_setup
from pmdsim.setup import default_setup


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--grids", default="3,5,9")
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--repeat", type=int, default=2, help="solves per model; the best time is kept")
    args = ap.parse_args()
    grids = [int(g) for g in args.grids.split(",") if g.strip()]
    res = {"pmdsim_version": __version__, "threads": numba.get_num_threads(), "bulge_mm": args.bulge_mm}

    truth = default_setup().with_bulge(args.bulge_mm)
    nominal = nominal_setup(truth)
    t0 = time.perf_counter()
    obs = simulate_calibration_observations(truth)
    res["simulate_decode_16x2_s"] = time.perf_counter() - t0
    res["correspondences"] = int(sum(o.n for o in obs))
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = perturbed_state(nominal_state(nominal, poses), np.random.default_rng([0, 3000]), **INITIAL_ERRORS)
    calibrate(obs, start, max_iter=2)  # warm-up (compilation)
    calibrate(obs, start, screen_model=free_screen_model(nominal, 3), max_iter=2)
    models = {}
    for g in [None, *grids]:
        label = "planar" if g is None else f"{g}x{g}"
        sm = None if g is None else free_screen_model(nominal, g)
        best, result = best_of(lambda: calibrate(obs, start, screen_model=sm), args.repeat)
        models[label] = {"free_parameters": 0 if sm is None else sm.n_free, "solve_s": best,
                         "iterations": result.iterations, "rms_px": result.rms_px,
                         "converged": result.converged, "parameters": result.state.n_parameters}
    res["models"] = models
    if "3x3" in models:
        res["ratio_3x3_to_planar"] = models["3x3"]["solve_s"] / models["planar"]["solve_s"]
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)
        return
    print(f"pmdsim {__version__}, {res['threads']} threads, 1920×1200 px, 16 poses × 2 cameras, Δh = {args.bulge_mm:g} mm, "
          f"{res['correspondences']} correspondences")
    print(f"simulate + render + decode calibration data: {res['simulate_decode_16x2_s']:.1f} s")
    print(f"{'model':>7s} {'free':>5s} {'params':>6s} {'solve s':>8s} {'iter':>5s} {'RMS px':>9s}")
    for label, m in models.items():
        print(f"{label:>7s} {m['free_parameters']:5d} {m['parameters']:6d} {m['solve_s']:8.2f} {m['iterations']:5d} "
              f"{m['rms_px']:9.5f}")
    if "ratio_3x3_to_planar" in res:
        print(f"3×3 / planar solve time: {res['ratio_3x3_to_planar']:.2f} (target < 2)")
    print(f"peak memory (RSS): {res['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
