"""Time the cover glass's two costly stages of Experiment 6 for A/B between source trees.

    python benchmarks/bench_glass_stages.py [--downsample K] [--bulge-mm 3] [--glass-mm 3] [--repeat 5]
        [--stage inputs|apparent|calibrate|all] [--save FILE.npz] [--json]
    PYTHONPATH=<other tree>/src python benchmarks/bench_glass_stages.py ... --save other.npz
    python benchmarks/bench_glass_stages.py --compare A.npz B.npz

Stages (Table 1 setup binned by K, Δh, glass t with n = 1.52, left camera):

``inputs``
    the calibration's glass inputs (``calibration.glass_kernel.glass_inputs``: the apparent
    points of every correspondence and their derivatives) of the 16-pose observations, with the
    thickness free, as the solver calls them once per evaluation;
``apparent``
    the registration's apparent points (``CoverGlass.apparent_points``) of every pixel of the
    camera, from its traced sample points and emitting points;
``calibrate``
    the whole staged glass calibration (``calibrate_with_glass``, thickness fitted, planar screen).

Prints the best and median wall time and the CPU time of the best call per stage, the 1-minute
load average before and after. ``--save`` writes the stages' outputs; ``--compare`` prints the
largest differences of two saved runs.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from _common import dump_json


def _compare(a_path: str, b_path: str) -> None:
    a, b = np.load(a_path), np.load(b_path)
    for k in sorted(set(a.files) & set(b.files)):
        x, y = a[k], b[k]
        both = np.isfinite(x) & np.isfinite(y)
        d = np.abs(x[both] - y[both])
        print(f"{k}: finite in both {int(both.sum())} of {x.size}, finite differs "
              f"{int((np.isfinite(x) != np.isfinite(y)).sum())}, max |Δ| = {d.max() if d.size else 0.0:.3g}, "
              f"bitwise equal {int((d == 0).sum())}")


def _timed(fn, repeat):
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    i = int(np.argmin(walls))
    return walls[i], float(np.median(walls)), cpus[i], out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--glass-mm", type=float, default=3.0)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--stage", default="all", choices=["inputs", "apparent", "calibrate", "all"])
    ap.add_argument("--save", default="")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    args = ap.parse_args()
    if args.compare:
        _compare(*args.compare)
        return
    import pmdsim
    from pmdsim.setup import default_setup

    truth = default_setup().binned(args.downsample).with_bulge(args.bulge_mm).with_cover_glass(args.glass_mm, 1.52)
    glass = truth.screen.cover_glass
    res = {"tree": os.path.dirname(pmdsim.__file__), "downsample": args.downsample, "bulge_mm": args.bulge_mm,
           "glass_mm": args.glass_mm, "load_before": os.getloadavg()[0]}
    saved = {}
    stages = ["inputs", "apparent", "calibrate"] if args.stage == "all" else [args.stage]
    if "inputs" in stages or "calibrate" in stages:
        from dataclasses import replace

        from pmdsim.calibration import nominal_state, perturbed_state
        from pmdsim.calibration.setup_bridge import nominal_setup
        from pmdsim.studies.calibration_data import simulate_calibration_observations
        from pmdsim.studies.experiment2 import INITIAL_ERRORS

        obs = simulate_calibration_observations(truth)
        nominal = nominal_setup(truth).with_cover_glass(0.0)
        poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
        start = perturbed_state(nominal_state(nominal, poses), np.random.default_rng([0, 3000]), **INITIAL_ERRORS)
        res["correspondences"] = int(sum(o.uv_px.shape[0] for o in obs))
    if "inputs" in stages:
        from pmdsim.calibration.glass_kernel import glass_inputs
        from pmdsim.calibration.solver import _pack, _screen_q

        state = replace(start, glass=glass.with_(thickness_mm=1.0), glass_free=(True, False))
        data = _pack(obs, state, 1)
        q = _screen_q(data.q, data.wx, data.wy, state.screen)

        def inputs():
            if hasattr(data, "_glass_last"):  # a tree that keeps the last state's: time the computation
                data._glass_last = None
            return glass_inputs(data, state, q)

        glass_inputs(data, state, q)  # compile
        best, med, cpu, out = _timed(inputs, args.repeat)
        res["inputs"] = {"best_s": best, "median_s": med, "cpu_of_best_s": cpu}
        saved["inputs_q"], saved["inputs_g"] = out[1], out[2]
    if "apparent" in stages:
        from pmdsim.simulation.render import trace_setup_camera

        cs = truth.cameras["left"]
        m = trace_setup_camera(truth, "left", store_points=True)
        T_screen_sample = truth.screen.T_world_screen.inv() @ truth.sample.T_world_sample
        p = T_screen_sample.apply(m.p_sample_mm)
        q = m.q_screen_mm
        surface = truth.screen.surface
        glass.apparent_points(surface, p[:2], q[:2])  # compile
        best, med, cpu, out = _timed(lambda: glass.apparent_points(surface, p, q), args.repeat)
        res["apparent"] = {"best_s": best, "median_s": med, "cpu_of_best_s": cpu, "pixels": int(p.size // 3),
                           "camera_px": list(cs.camera.shape)}
        saved["apparent"] = out
    if "calibrate" in stages:
        from pmdsim.calibration.glass import calibrate_with_glass

        def cal():
            return calibrate_with_glass(obs, start, glass.with_(thickness_mm=1.0), fit_thickness=True)

        best, med, cpu, out = _timed(cal, args.repeat)
        res["calibrate"] = {"best_s": best, "median_s": med, "cpu_of_best_s": cpu,
                            "thickness_mm": out.glass.thickness_mm, "thickness_std_mm": float(out.glass_std()[0]),
                            "rms_px": float(out.rms_px), "iterations": int(getattr(out, "iterations", -1))}
        saved["calibrate_t"] = np.array([out.glass.thickness_mm])
    res["load_after"] = os.getloadavg()[0]
    if args.save:
        np.savez(args.save, **saved)
    if args.json:
        dump_json(res)
        return
    print(f"tree {res['tree']}, K = {args.downsample}, Δh = {args.bulge_mm:g} mm, glass {args.glass_mm:g} mm, "
          f"load {res['load_before']:.2f} → {res['load_after']:.2f}")
    for s in stages:
        r = res[s]
        extra = {k: v for k, v in r.items() if k not in ("best_s", "median_s", "cpu_of_best_s")}
        print(f"  {s:10s} best {r['best_s'] * 1e3:9.1f} ms  median {r['median_s'] * 1e3:9.1f} ms  "
              f"CPU of best {r['cpu_of_best_s'] * 1e3:9.1f} ms  {extra}")


if __name__ == "__main__":
    main()
