"""Benchmark the holistic calibration and Experiment 2 (paper §4) at full resolution.

Prints the time of one calibration solve (16 poses × 2 cameras, stride from the setup, 8-bit
decoded correspondences, planar screen), the time of the whole Experiment 2 (4 bulge heights:
16 poses × 2 cameras simulated, rendered and decoded in memory, calibration, 2 reconstructions
each), and peak memory.

    python benchmarks/bench_calibration.py [--json] [--bulges-mm 0,1,2,3]
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from _common import best_of, dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.calibration import calibrate, nominal_state, perturbed_state
from pmdsim.studies import INITIAL_ERRORS, run_experiment2_bulge, simulate_calibration_observations
from pmdsim.setup import default_setup


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--bulges-mm", default="0,1,2,3")
    args = ap.parse_args()
    res = {"pmdsim_version": __version__, "threads": numba.get_num_threads()}

    truth = default_setup().with_bulge(3.0)
    t0 = time.perf_counter()
    obs = simulate_calibration_observations(truth)
    res["simulate_decode_16x2_s"] = time.perf_counter() - t0
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = perturbed_state(nominal_state(truth.with_bulge(0.0), poses), np.random.default_rng(0), **INITIAL_ERRORS)
    calibrate(obs, start, max_iter=2)  # warm-up (compilation)
    t0 = time.perf_counter()
    result = calibrate(obs, start)
    res["calibration_solve_s"] = time.perf_counter() - t0
    res["calibration_iterations"] = result.iterations
    res["calibration_residuals"] = result.n_residuals
    res["calibration_rms_px"] = result.rms_px

    bulges = [float(b) for b in args.bulges_mm.split(",")]
    t0 = time.perf_counter()
    per = {}
    for dh in bulges:
        e = run_experiment2_bulge(dh)
        per[f"{dh:g}"] = {c.camera: c.metrics["max_height_diff_um"] for c in e.cases}
    res["experiment2_s"] = time.perf_counter() - t0
    res["experiment2_bulges_mm"] = bulges
    res["experiment2_max_height_diff_um"] = per
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)
        return
    print(f"pmdsim {__version__}, {res['threads']} threads, 1920×1200 px, 16 poses × 2 cameras")
    print(f"simulate + render + decode calibration data : {res['simulate_decode_16x2_s']:6.1f} s")
    print(f"one calibration solve                        : {res['calibration_solve_s']:6.1f} s "
          f"({result.iterations} iterations, {result.n_residuals} residuals, RMS {result.rms_px:.4f} px)")
    print(f"Experiment 2 ({len(bulges)} bulge heights)            : {res['experiment2_s']:6.1f} s")
    print(f"peak memory (RSS)                            : {res['peak_rss_mb']:6.0f} MB")


if __name__ == "__main__":
    main()
