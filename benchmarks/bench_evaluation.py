"""Benchmark the PMD evaluation (issue: phase decoding, registration, reconstruction, Experiment 1).

Prints: decoding a 1920×1200 × 32-image set (2 directions × 4 periods × 4 shifts), stepwise and
least-squares reconstruction of one full frame (Table 1, Δh = 3 mm, planar screen model) — with
registration (wall time) and without it (wall and CPU time) —, the whole full-resolution
Experiment 1 (8 reconstructions, images in memory), and peak memory. The machine's 1-minute load
average before and after the reconstruction timings is printed too: on a shared machine, wall
times above about 1 + load/cores of their unloaded value are to be expected.

    python benchmarks/bench_evaluation.py [--json] [--skip-experiment]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numba
import numpy as np

from _common import best_of, dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.studies import experiment1
from pmdsim.evaluation import decode_images, evaluate_decoded
from pmdsim.simulation.patterns import FringeSequence
from pmdsim.evaluation.reconstruction import reconstruct
from pmdsim.setup import default_setup
from pmdsim.simulation import render_images, trace_setup_camera



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--skip-experiment", action="store_true")
    args = ap.parse_args()
    res = {"pmdsim_version": __version__, "threads": numba.get_num_threads()}

    # A 32-image set: 4 periods per direction.
    base = default_setup().with_bulge(3.0)
    seq32 = FringeSequence((720.0, 96.0, 12.0, 2.0), (420.0, 56.0, 8.0, 2.0), n_shifts=4)
    s32 = replace(base, patterns=replace(base.patterns, sequence=seq32))
    m = trace_setup_camera(s32, "left")
    images = {}
    for spec, img in render_images(s32, "left", m):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    n_img = sum(len(v) for v in images.values())
    decode_images(s32, images)
    res["decode_32_images_s"], dec32 = best_of(lambda: decode_images(s32, images), 3)
    res["decode_valid_fraction"] = float(dec32.valid.mean())

    # Reconstruction of one full frame with the default 24-image sequence.
    m = trace_setup_camera(base, "left", store_points=True)
    images = {}
    for spec, img in render_images(base, "left", m):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    dec = decode_images(base, images)
    model = base.with_bulge(0.0)
    seed = (600, 960)
    res["load_avg_1min_before"] = os.getloadavg()[0]
    for method in ("stepwise", "least_squares"):
        evaluate_decoded(model, "left", dec, method=method, seed_pixel=seed)
        t, (reg, rec) = best_of(lambda: evaluate_decoded(model, "left", dec, method=method, seed_pixel=seed), 3)
        res[f"{method}_s_incl_registration"] = t
        res[f"{method}_iterations"] = rec.iterations
        # The reconstruction alone, on the registration just computed: wall and CPU time.
        def _rec():
            c = time.process_time()
            reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, method=method, seed_pixel=seed)
            return time.process_time() - c
        t, _ = best_of(_rec, 3)
        res[f"{method}_s"] = t
        res[f"{method}_cpu_s"] = min(_rec() for _ in range(3))
    res["load_avg_1min_after"] = os.getloadavg()[0]

    if not args.skip_experiment:
        t0 = time.perf_counter()
        cases = experiment1()
        res["experiment1_s"] = time.perf_counter() - t0
        res["experiment1_max_height_diff_um"] = {f"{c.bulge_mm:g}_{c.camera}": c.metrics["max_height_diff_um"]
                                                 for c in cases}
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)
        return
    print(f"pmdsim {__version__}, {res['threads']} threads, 1920×1200 px")
    print(f"decode {n_img} images              : {res['decode_32_images_s']:6.2f} s")
    print(f"stepwise (incl. registration)  : {res['stepwise_s_incl_registration']:6.2f} s "
          f"(reconstruction alone {res['stepwise_s']:.2f} s, CPU {res['stepwise_cpu_s']:.2f} s)")
    print(f"least squares (incl. reg.)     : {res['least_squares_s_incl_registration']:6.2f} s "
          f"({res['least_squares_iterations']} Gauss–Newton iterations on the full grid; "
          f"reconstruction alone {res['least_squares_s']:.2f} s, CPU {res['least_squares_cpu_s']:.2f} s)")
    print(f"load average (1 min)           : {res['load_avg_1min_before']:6.2f} before, "
          f"{res['load_avg_1min_after']:.2f} after the reconstructions ({os.cpu_count()} CPUs)")
    if "experiment1_s" in res:
        print(f"Experiment 1 (8 cases)         : {res['experiment1_s']:6.1f} s")
    print(f"peak memory (RSS)              : {res['peak_rss_mb']:6.0f} MB")


if __name__ == "__main__":
    main()
