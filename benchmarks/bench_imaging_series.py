"""Time one case of benchmarks/bench_imaging.py (maps + 24 images, 1920×1200, one camera) in a
process of its own, per period — short jobs that interleave runs of two source trees:

    PYTHONPATH=/path/to/tree/src python benchmarks/bench_imaging_series.py [--case all] [--downsample 1]

Cases: ``all`` (every effect) or one effect of bench_imaging.PER_EFFECT. Prints the load before
timing, the maps time and each period's N images (best of ``--repeat``), and the total.
"""

from __future__ import annotations

import argparse
import os
import time

from bench_imaging import ALL_EFFECTS, PER_EFFECT
from pmdsim.setup import default_setup
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
from pmdsim.simulation.render import render_images, trace_setup_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="all", choices=["all", *PER_EFFECT])
    ap.add_argument("--downsample", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--tolerance", type=float, default=None,
                    help="truncation tolerance of the series, grey levels (trees that have one; default: theirs)")
    args = ap.parse_args()
    import numpy as np

    kw = ALL_EFFECTS if args.case == "all" else PER_EFFECT[args.case]
    setup = default_setup().with_bulge(3.0).with_imaging(**kw)
    small = setup.binned(8)
    ms = trace_setup_camera(small, "left", store_points=True)
    for _ in render_images(small, "left", ms):  # compile / load the kernels
        pass
    if args.downsample > 1:
        setup = setup.binned(args.downsample)
    m = trace_setup_camera(setup, "left", store_points=True)
    load = os.getloadavg()[0]
    t = time.perf_counter()
    maps = imaging_maps(setup, "left", m)
    t_maps = time.perf_counter() - t
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    parts = []
    for d in "xy":
        for p in seq.periods(d):
            best = np.inf
            for _ in range(args.repeat):
                rng = np.random.default_rng(0)
                t = time.perf_counter()
                extra = {} if args.tolerance is None else {"tolerance_dn": args.tolerance}
                render_period_imaging(maps, m.screen_xy_mm, m.valid, d, p, seq, sensor, rng, **extra)
                best = min(best, time.perf_counter() - t)
            parts.append((f"{d} {p:g}", best))
    total = t_maps + sum(b for _, b in parts)
    print(f"case {args.case}, {m.valid.shape[1]}×{m.valid.shape[0]}, load before {load:.2f}, after "
          f"{os.getloadavg()[0]:.2f}: maps {t_maps:.2f} s + images {total - t_maps:.2f} s = {total:.2f} s; "
          + ", ".join(f"{k} mm {b:.2f} s" for k, b in parts))


if __name__ == "__main__":
    main()
