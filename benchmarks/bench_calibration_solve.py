"""Time one full-resolution calibration solve on cached observations (A/B between source trees).

The 16 poses × 2 cameras of the Table 1 setup (Δh = 3 mm by default) are simulated, rendered
(8-bit) and decoded once and cached in an ``.npz`` file, so that the solve of two source trees
can be timed alternately on identical data:

    python benchmarks/bench_calibration_solve.py --cache /tmp/obs3.npz [--repeat 3] [--grid 0] [--json]
    PYTHONPATH=<other tree>/src python benchmarks/bench_calibration_solve.py --cache /tmp/obs3.npz --json

``--grid N`` (N ≥ 3) solves with the free-form N × N screen model of Experiment 3 instead of
the planar one. ``--save-params FILE`` writes the solution's parameter vector (natural units)
and covariance, for comparing two trees.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numba
import numpy as np

from _common import dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.calibration import Observations, calibrate, free_screen_model, nominal_setup, nominal_state, perturbed_state
from pmdsim.setup import default_setup
from pmdsim.studies import INITIAL_ERRORS, simulate_calibration_observations


def _observations(path: str, bulge_mm: float) -> list:
    if path and os.path.exists(path):
        z = np.load(path)
        return [Observations(str(z[f"cam{i}"]), int(z[f"pose{i}"]), z[f"uv{i}"], z[f"q{i}"], z[f"std{i}"])
                for i in range(int(z["n"]))]
    obs = simulate_calibration_observations(default_setup().with_bulge(bulge_mm))
    if path:
        arrays = {"n": len(obs)}
        for i, o in enumerate(obs):
            arrays.update({f"cam{i}": o.camera, f"pose{i}": o.pose_index, f"uv{i}": o.uv_px,
                           f"q{i}": o.q_screen_mm, f"std{i}": o.q_std_mm})
        np.savez(path, **arrays)
    return obs


def _load_avg() -> float:
    return os.getloadavg()[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="", help="observations cache (.npz), created if missing")
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--grid", type=int, default=0, help="free-form screen model N×N (0: planar)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--save-params", default="")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    truth = default_setup().with_bulge(args.bulge_mm)
    obs = _observations(args.cache, args.bulge_mm)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    nominal = nominal_setup(truth)
    if args.grid:
        start = perturbed_state(nominal_state(nominal, poses), np.random.default_rng([0, 3000]), **INITIAL_ERRORS)
        sm = free_screen_model(nominal, args.grid)
    else:
        start = perturbed_state(nominal_state(truth.with_bulge(0.0), poses), np.random.default_rng(0),
                                **INITIAL_ERRORS)
        sm = None
    calibrate(obs, start, screen_model=sm, max_iter=2)  # warm-up (compilation, caches)
    times, cpus, loads = [], [], []
    for _ in range(args.repeat):
        loads.append(_load_avg())
        t0, c0 = time.perf_counter(), time.process_time()
        result = calibrate(obs, start, screen_model=sm)
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    loads.append(_load_avg())
    res = {"pmdsim": os.path.dirname(__import__("pmdsim").__file__), "pmdsim_version": __version__,
           "threads": numba.get_num_threads(), "grid": args.grid, "solve_s": times, "solve_min_s": min(times),
           "solve_median_s": float(np.median(times)), "solve_cpu_s": cpus, "load_1min": loads, "iterations": result.iterations,
           "residuals": result.n_residuals, "parameters": len(result.parameter_names), "rms_px": result.rms_px,
           "converged": result.converged, "reason": result.reason, "peak_rss_mb": peak_rss_mb()}
    if args.save_params:
        np.savez(args.save_params, params=(start if sm is None else replace(start, screen=sm)).increment_to(result.state), std=result.parameter_std, cov=result.covariance, rms=result.rms_px,
                 names=np.array(result.parameter_names))
    if args.json:
        dump_json(res)
        return
    print(f"{res['pmdsim']}: {res['threads']} threads, {res['residuals']} residuals, {res['parameters']} parameters")
    print(f"solve: min {res['solve_min_s']:.2f} s, median {res['solve_median_s']:.2f} s "
          f"({', '.join(f'{t:.2f}' for t in times)}; CPU {', '.join(f'{t:.2f}' for t in cpus)}), {result.iterations} iterations, RMS {result.rms_px:.6f} px, "
          f"load {', '.join(f'{x:.1f}' for x in loads)}")


if __name__ == "__main__":
    main()
