"""Tracing with a cover glass against tracing without, in one process, interleaved (Table 1, one camera).

    python benchmarks/bench_glass_bands.py [--bulge-mm 3] [--glass-mm 3] [--rounds 11] [--band-rows 32 128]

Per round, one trace of each case in turn: without glass, then with the glass for every band
height of ``--band-rows`` (the tracer's choice, ``glass_rows.glass_band_rows``, replaced for the
call; "auto": that choice). Prints, per case, the best and median CPU time of the process (all
threads) and the best wall time, the ratio of the best CPU time to the glass-free one, the 1-minute
load average before and after, and for each band height the largest difference of the mapping
against the first one's (mm) and the number of pixels whose status differs.
Run with ``NUMBA_NUM_THREADS=1`` for CPU times that other jobs on a shared machine disturb less.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--glass-mm", type=float, default=3.0)
    ap.add_argument("--camera", default="left")
    ap.add_argument("--rounds", type=int, default=11)
    ap.add_argument("--band-rows", nargs="+", default=["32", "auto"])
    args = ap.parse_args()
    import numba
    from pmdsim.geometry.cover_glass import CoverGlass
    from pmdsim.setup import default_setup
    from pmdsim.simulation import trace

    setup = default_setup().with_bulge(args.bulge_mm)
    cam = setup.cameras[args.camera]
    rays = cam.camera.sensor_rays()
    auto = trace.glass_band_rows

    def run(glass, band_rows):
        trace.glass_band_rows = auto if band_rows == "auto" else (lambda n_rows, b: int(band_rows))
        try:
            return trace.trace_camera(cam.camera, cam.T_world_cam, setup.sample.T_world_sample, setup.sample.surface,
                                      setup.screen.T_world_screen, setup.screen.surface, rays=rays, glass=glass)
        finally:
            trace.glass_band_rows = auto

    glass = CoverGlass(args.glass_mm, 1.52)
    cases = [("no glass", None, "auto")] + [(f"glass, bands of {b} rows", glass, b) for b in args.band_rows]
    maps = {name: run(g, b) for name, g, b in cases}  # compilation or cache load
    load_before = os.getloadavg()[0]
    cpu = {name: [] for name, _, _ in cases}
    wall = {name: [] for name, _, _ in cases}
    for _ in range(args.rounds):
        for name, g, b in cases:
            t0, c0 = time.perf_counter(), time.process_time()
            run(g, b)
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
    print(f"{os.path.dirname(trace.__file__)}: {numba.get_num_threads()} threads, "
          f"{rays[0].shape[0] * rays[0].shape[1]} rays, Δh = {args.bulge_mm:g} mm, glass {args.glass_mm:g} mm, "
          f"auto band rows {auto(rays[0].shape[0], trace._BAND_ROWS)}, load {load_before:.1f} → "
          f"{os.getloadavg()[0]:.1f}")
    ref = min(cpu["no glass"])
    first = maps[cases[1][0]]
    for name, _, _ in cases:
        line = (f"  {name:28s} CPU best {1e3 * min(cpu[name]):7.1f} ms, median {1e3 * np.median(cpu[name]):7.1f} ms; "
                f"wall best {1e3 * min(wall[name]):7.1f} ms; CPU ratio {min(cpu[name]) / ref:.2f}")
        if name != "no glass":
            m = maps[name]
            both = (m.status == 0) & (first.status == 0)
            d = np.abs(m.screen_xy_mm[both] - first.screen_xy_mm[both])
            line += (f"; vs first: max |Δ| {d.max() if d.size else 0.0:.3g} mm, status differs "
                     f"{int((m.status != first.status).sum())}")
        print(line)


if __name__ == "__main__":
    sys.exit(main())
