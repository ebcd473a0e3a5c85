"""Shared helpers of the benchmark scripts (run them as `python benchmarks/NAME.py`)."""

from __future__ import annotations

import json
import resource
import sys
import time

import numpy as np


def best_of(fn, repeat):
    """(best wall time in s, last result) of ``repeat`` calls of ``fn``."""
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def best_wall_cpu(fn, repeat):
    """(least wall time, least CPU (process) time) in s of ``repeat`` calls of ``fn``."""
    wall, cpu = [], []
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def rendered_images(setup, camera, mapping):
    """The camera's images as ``decode_images`` takes them: ``{(direction, period_mm): [image per
    shift]}``, rendered from ``mapping`` (``pmdsim.simulation.render_images``)."""
    from pmdsim.simulation import render_images

    images = {}
    for spec, img in render_images(setup, camera, mapping):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    return images


def table1_integration_frame(seed=(600, 960)):
    """The least-squares integration's benchmark frame: Table 1, left camera, Δh = 3 mm,
    1920×1200, its 24 8-bit images rendered, decoded and registered against the flat nominal,
    reconstructed by least squares from ``seed``. Returns (registration, reconstruction, seed)."""
    from pmdsim.evaluation.pipeline import decode_images, evaluate_decoded
    from pmdsim.setup import default_setup
    from pmdsim.simulation import trace_setup_camera

    s = default_setup().with_bulge(3.0)
    m = trace_setup_camera(s, "left", store_points=True)
    dec = decode_images(s, rendered_images(s, "left", m))
    reg, rec = evaluate_decoded(s.with_bulge(0.0), "left", dec, method="least_squares", seed_pixel=seed)
    return reg, rec, seed


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def dump_json(res: dict) -> None:
    json.dump(res, sys.stdout)
    sys.stdout.write("\n")


def captured_inputs_args(description, out_help):
    """The arguments of a kernel benchmark on inputs captured from an evaluation (image_dir,
    --repeat, --save/--load of the inputs, --out/--compare of the result); returns (args, the
    inputs: loaded, or None to capture)."""
    import argparse  # noqa: PLC0415

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("image_dir", nargs="?")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--save")
    ap.add_argument("--load")
    ap.add_argument("--out", help=out_help)
    ap.add_argument("--compare", help="an --out file of another tree: bit-identical?")
    args = ap.parse_args()
    return args, (dict(np.load(args.load)) if args.load else None)
