"""Where the time of one Experiment-2 Δh goes (issue 15): CPU and wall time per stage.

Wraps the stage functions of the running tree (works on main's tree too: stages it does not have
are skipped) and runs ``run_experiment2_bulge`` once after a warm-up at downsample 8:
trace (34 camera frames), rendering and decoding (main: ``render_period`` + ``decode_screen_coordinates``;
this branch: the fused ``decode_rendered_fringes``), observations, the calibration solve, the two
registrations + reconstructions, the metrics, and the rest (Python glue, copies).

    PYTHONPATH=<tree>/src nice python benchmarks/bench_experiment2_stages.py [--downsample 1] [--bulge-mm 3]
"""

from __future__ import annotations

import argparse
import collections
import time

import pmdsim.calibration as cal
import pmdsim.evaluation.pipeline as pl
import pmdsim.simulation.render as rd
import pmdsim.simulation.trace as tr
import pmdsim.studies.experiment2 as e2
from pmdsim.setup import default_setup

_ACC = collections.defaultdict(lambda: [0.0, 0.0, 0])


def _wrap(mod, name: str, label: str) -> None:
    if not hasattr(mod, name):
        return
    f = getattr(mod, name)

    def timed(*a, **k):
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            r = _ACC[label]
            r[0] += time.process_time() - c0
            r[1] += time.perf_counter() - w0
            r[2] += 1

    setattr(mod, name, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=1)
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    args = ap.parse_args()
    for mod, name, label in ((tr, "trace_camera", "trace"), (rd, "trace_camera", "trace"),
                             (rd, "render_period", "render (24 images/frame)"),
                             (pl, "decode_screen_coordinates", "decode (24 images/frame)"),
                             (pl, "decode_rendered_fringes", "fused render+decode"),
                             (cal, "observations_from_mapping", "observations"), (cal, "calibrate", "calibrate"),
                             (e2, "evaluate_decoded", "register+reconstruct"),
                             (e2, "surface_error_metrics", "metrics")):
        _wrap(mod, name, label)
    base = default_setup()
    e2.run_experiment2_bulge(args.bulge_mm, base=base, downsample=8)  # warm-up (numba caches)
    _ACC.clear()
    c0, w0 = time.process_time(), time.perf_counter()
    e2.run_experiment2_bulge(args.bulge_mm, base=base, downsample=args.downsample)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    print(f"downsample {args.downsample}, Δh {args.bulge_mm:g} mm: CPU {cpu:.2f} s, wall {wall:.2f} s")
    for label, (c, w, n) in _ACC.items():
        print(f"  {label:26s} calls {n:4d}  CPU {c:7.2f} s  wall {w:7.2f} s")
    c = sum(v[0] for v in _ACC.values())
    w = sum(v[1] for v in _ACC.values())
    print(f"  {'rest (glue, copies)':26s}             CPU {cpu - c:7.2f} s  wall {wall - w:7.2f} s")


if __name__ == "__main__":
    main()
