"""Time one case of benchmarks/bench_imaging.py (maps + the 24-image sequence of one camera) in a
process of its own — short jobs that interleave runs of two source trees:

    PYTHONPATH=/path/to/tree/src python benchmarks/bench_imaging_series.py [--case all] [--downsample 1]

Cases: ``all`` (every effect), ``all_lcd`` (every effect and the LCD's viewing-angle response)
or one effect of bench_imaging.PER_EFFECT. Prints the load before and
after, wall and CPU seconds (``time.process_time``: both threads' CPU, less sensitive to the other
jobs on a shared machine) of the maps, of each direction's images (trees with
``render_direction_imaging``: a direction's periods rendered together; otherwise period by period),
of one frame (``--one-frame``: maps + the finest period of x alone, N images — the least a
phase-shift measurement renders), and the total; best of ``--repeat``.
"""

from __future__ import annotations

import argparse
import os
import time

from bench_imaging import ALL_EFFECTS, PER_EFFECT

try:
    from bench_imaging import ALL_EFFECTS_LCD
except ImportError:  # a tree without the viewing-angle model
    ALL_EFFECTS_LCD = None
from pmdsim.setup import default_setup
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation import imaging
from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
from pmdsim.simulation.render import render_images, trace_setup_camera


def _timed(f, repeat):
    best = (float("inf"), float("inf"))
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        f()
        best = min(best, (time.perf_counter() - w, time.process_time() - c))
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="all", choices=["all", "all_lcd", *PER_EFFECT])
    ap.add_argument("--downsample", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--directions", default="xy", help="the directions to time (e.g. x: half the sequence)")
    ap.add_argument("--one-frame", action="store_true", help="also time maps + one period of x (N images)")
    ap.add_argument("--tolerance", type=float, default=None,
                    help="truncation tolerance of the series, grey levels (trees that have one; default: theirs)")
    args = ap.parse_args()
    import numpy as np

    from pmdsim.setup.fringes import FringeSequence

    kw = ALL_EFFECTS if args.case == "all" else (ALL_EFFECTS_LCD if args.case == "all_lcd" else PER_EFFECT[args.case])
    setup = default_setup().with_bulge(3.0).with_imaging(**kw)
    small = setup.binned(8)
    ms = trace_setup_camera(small, "left", store_points=True)
    for _ in render_images(small, "left", ms):  # compile / load the kernels
        pass
    if args.downsample > 1:
        setup = setup.binned(args.downsample)
    m = trace_setup_camera(setup, "left", store_points=True)
    load = os.getloadavg()[0]
    extra = {} if args.tolerance is None else {"tolerance_dn": args.tolerance}
    maps_t = _timed(lambda: imaging_maps(setup, "left", m), args.repeat)
    maps = imaging_maps(setup, "left", m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    by_direction = hasattr(imaging, "render_direction_imaging")

    def direction(d, sq):
        rng = np.random.default_rng(0)
        if by_direction:
            imaging.render_direction_imaging(maps, m.screen_xy_mm, m.valid, d, sq, sensor, rng, **extra)
        else:
            for p in sq.periods(d):
                render_period_imaging(maps, m.screen_xy_mm, m.valid, d, p, sq, sensor, rng, **extra)

    parts = [(d, _timed(lambda d=d: direction(d, seq), args.repeat)) for d in args.directions]
    wall = maps_t[0] + sum(t[0] for _, t in parts)
    cpu = maps_t[1] + sum(t[1] for _, t in parts)
    n_img = sum(len(seq.periods(d)) for d in args.directions) * seq.n_shifts
    print(f"case {args.case}, {m.valid.shape[1]}×{m.valid.shape[0]}, load before {load:.2f}, after "
          f"{os.getloadavg()[0]:.2f}, {'by direction' if by_direction else 'by period'}: "
          f"maps {maps_t[0]:.2f} s (CPU {maps_t[1]:.2f}) + " +
          " + ".join(f"{d} {t[0]:.2f} s (CPU {t[1]:.2f})" for d, t in parts) +
          f" = {wall:.2f} s (CPU {cpu:.2f}) for {n_img} images, {wall / n_img:.3f} s per image")
    if args.one_frame:
        one = FringeSequence((min(seq.periods("x")),), (min(seq.periods("y")),), n_shifts=seq.n_shifts,
                             mean_level=seq.mean_level, amplitude=seq.amplitude)
        t = _timed(lambda: direction("x", one), args.repeat)
        print(f"one frame (maps + the finest x period, {seq.n_shifts} images): {maps_t[0] + t[0]:.2f} s "
              f"(CPU {maps_t[1] + t[1]:.2f}); load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
