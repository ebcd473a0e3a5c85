"""Benchmark curved samples (issue 14): a 1 m sphere measured mono through 8-bit images.

Table 1 setup (true cameras, planar screen), sample = sphere of radius 1000 mm (convex as seen
from the cameras, vertex at the sample grid's centre), one camera traced, rendered, decoded and
reconstructed (stepwise and least squares) from a seed at its true height. Prints the P-V and
RMS of the height error against the closed-form sphere (target: P-V < 0.1 µm), the masked
pixels by reason, and the wall time of each step; at full resolution unless --downsample.

    python benchmarks/bench_curved.py [--downsample K] [--camera left] [--json]
    python benchmarks/bench_curved.py --spline-table

``--spline-table`` prints instead what a spline on an n × n grid over the Table 1 sample
(400 × 400 mm) misses of the 1 m sphere: height error (max, RMS) at the off-node points of the
4× refined grid (:func:`pmdsim.setup.sample_shape.spline_report`) and the largest slope error
there — the figure behind the closed-form surfaces in the tracer (docs/conventions.md).
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from _common import dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.evaluation import decode_images, evaluate_decoded
from pmdsim.setup import default_setup
from pmdsim.simulation import render_images, trace_setup_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=1)
    ap.add_argument("--camera", default="left")
    ap.add_argument("--radius-mm", type=float, default=1000.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--spline-table", action="store_true")
    args = ap.parse_args()
    if args.spline_table:
        spline_table(args.radius_mm)
        return
    res = {"pmdsim_version": __version__, "threads": numba.get_num_threads(), "load_before": os.getloadavg()[0],
           "downsample": args.downsample, "radius_mm": args.radius_mm}
    setup = default_setup().binned(args.downsample).with_sample_shape("sphere", radius_mm=args.radius_mm)
    surf = setup.sample.surface
    t = time.perf_counter()
    m = trace_setup_camera(setup, args.camera, store_points=True)
    res["trace_s"] = time.perf_counter() - t
    res["status"] = m.status_counts()
    t = time.perf_counter()
    images = {}
    for spec, img in render_images(setup, args.camera, m):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    res["render_s"] = time.perf_counter() - t
    t = time.perf_counter()
    dec = decode_images(setup, images)
    res["decode_s"] = time.perf_counter() - t
    del images
    cam = setup.cameras[args.camera].camera
    seed = (cam.height_px // 2, cam.width_px // 2)
    seed_h = float(m.p_sample_mm[seed][2])
    for method in ("stepwise", "least_squares"):
        t = time.perf_counter()
        _reg, rec = evaluate_decoded(setup, args.camera, dec, method=method, seed_pixel=seed, seed_height_mm=seed_h)
        res[f"{method}_s"] = time.perf_counter() - t
        ok = rec.reconstructed
        p = rec.p_sample_mm[ok]
        err_um = (rec.height_mm[ok] - surf.height(p[:, 0], p[:, 1])) * 1e3
        res[f"{method}_pv_um"] = float(err_um.max() - err_um.min())
        res[f"{method}_rms_um"] = float(np.sqrt(np.mean(err_um ** 2)))
        res[f"{method}_reconstructed_px"] = int(ok.sum())
        res[f"{method}_finite"] = bool(np.all(np.isfinite(err_um)))
    res["valid_px"] = int(m.valid.sum())
    res["load_after"] = os.getloadavg()[0]
    res["peak_rss_mb"] = peak_rss_mb()
    if args.json:
        dump_json(res)
    else:
        for k, v in res.items():
            print(f"{k:28s} {v}")


def spline_table(radius_mm: float) -> None:
    from pmdsim.geometry.surface import SplineSurface
    from pmdsim.setup import SampleShape
    from pmdsim.setup.sample_shape import spline_report

    shape = SampleShape.sphere(radius_mm)
    print("| grid | spacing (mm) | height error max (mm) | RMS (mm) | slope error max (rad) |")
    print("| --- | --- | --- | --- | --- |")
    for n in (2, 3, 5, 9, 17, 41, 81, 161):
        g = np.linspace(0.0, 400.0, n)
        heights, rep = spline_report(shape, g, g)
        exact = shape.surface(g, g)
        spline = SplineSurface(g, g, heights)
        f = np.linspace(0.0, 400.0, 4 * (n - 1) + 1)
        X, Y = np.meshgrid(f, f)
        slope = float(np.max(np.abs(spline.gradient(X, Y) - exact.gradient(X, Y))))
        print(f"| {n} × {n} | {400 / (n - 1):g} | {rep.max_error_mm:.2e} | {rep.rms_error_mm:.2e} | {slope:.2e} |")


if __name__ == "__main__":
    main()
