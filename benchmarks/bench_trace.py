"""Time the mapping (trace one camera, 1920×1200 px, Table 1 setup) for A/B between source trees.

    python benchmarks/bench_trace.py [--bulge-mm 3] [--glass-mm T] [--repeat 10] [--save FILE.npz] [--json]
    PYTHONPATH=<other tree>/src python benchmarks/bench_trace.py --save other.npz --json

Prints best and median wall time, Mrays/s, the CPU time of the best call, the 1-minute load
average before and after. ``--save`` writes the mapping (screen_xy_mm, status) to compare two
trees (``--compare A.npz B.npz`` prints the largest difference of the valid pixels in mm and the
number of pixels whose status differs).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from _common import dump_json


def _compare(a_path: str, b_path: str) -> None:
    a, b = np.load(a_path), np.load(b_path)
    both = (a["status"] == 0) & (b["status"] == 0)
    d = np.abs(a["screen_xy_mm"][both] - b["screen_xy_mm"][both])
    print(f"valid in both: {int(both.sum())}; status differs: {int((a['status'] != b['status']).sum())}; "
          f"max |Δ(x_q, y_q)| = {d.max() if d.size else 0.0:.3g} mm; bitwise equal: "
          f"{int((d == 0).all(axis=1).sum())} of {int(both.sum())}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--camera", default="left")
    ap.add_argument("--glass-mm", type=float, default=0.0, help="cover glass thickness (n = 1.52); 0: none")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--save", default="")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    args = ap.parse_args()
    if args.compare:
        _compare(*args.compare)
        return
    import numba
    import pmdsim
    from pmdsim.setup import default_setup
    from pmdsim.simulation.trace import trace_camera

    setup = default_setup().with_bulge(args.bulge_mm)
    cam = setup.cameras[args.camera]
    rays = cam.camera.sensor_rays()
    n = rays[0].shape[0] * rays[0].shape[1]
    extra = {}
    if args.glass_mm > 0:  # (a tree without cover glass runs the script without --glass-mm)
        from pmdsim.geometry.cover_glass import CoverGlass
        extra["glass"] = CoverGlass(args.glass_mm, 1.52)

    def mapping():
        return trace_camera(cam.camera, cam.T_world_cam, setup.sample.T_world_sample, setup.sample.surface,
                            setup.screen.T_world_screen, setup.screen.surface, rays=rays, **extra)

    m = mapping()  # compilation or cache load
    load_before = os.getloadavg()[0]
    times, cpus = [], []
    for _ in range(max(args.repeat, 1)):
        t0, c0 = time.perf_counter(), time.process_time()
        m = mapping()
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    best = int(np.argmin(times))
    res = {"pmdsim": os.path.dirname(pmdsim.__file__), "threads": numba.get_num_threads(), "rays": n,
           "best_s": times[best], "median_s": float(np.median(times)), "cpu_of_best_s": cpus[best],
           "mrays_per_s_best": n / times[best] / 1e6, "mrays_per_s_median": n / float(np.median(times)) / 1e6,
           "load_before": load_before, "load_after": os.getloadavg()[0],
           "valid": int((m.status == 0).sum())}
    if args.save:
        np.savez(args.save, screen_xy_mm=m.screen_xy_mm, status=m.status)
    if args.json:
        dump_json(res)
        return
    print(f"{res['pmdsim']}: {res['threads']} threads, {n} rays, best {res['best_s'] * 1e3:.1f} ms "
          f"({res['mrays_per_s_best']:.1f} Mrays/s, CPU {res['cpu_of_best_s'] * 1e3:.0f} ms), median "
          f"{res['median_s'] * 1e3:.1f} ms ({res['mrays_per_s_median']:.1f} Mrays/s), load {load_before:.1f} → "
          f"{res['load_after']:.1f}")


if __name__ == "__main__":
    sys.exit(main())
