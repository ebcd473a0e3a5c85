"""Benchmark the simulation (issue: simulation framework) on the full Table 1 setup.

Prints, for the 1920×1200 Table 1 setup with a 3 mm screen bulge: view-ray precomputation,
mapping time (best and median of ``--repeat``) and Mrays/s per camera, the 1-minute load
average before timing, rendering time per image, PNG writing time per image,
the 24-image render+write time for one camera, and peak memory.

    python benchmarks/bench_simulate.py            # human-readable
    python benchmarks/bench_simulate.py --json     # one JSON object (mrays_per_s, ...)
    NUMBA_NUM_THREADS=1 python benchmarks/bench_simulate.py   # single thread
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np

from _common import best_of, dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.io import write_png
from pmdsim.setup import default_setup
from pmdsim.simulation import render_images
from pmdsim.simulation.trace import trace_camera



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--repeat", type=int, default=10, help="timed mapping calls (best and median reported)")
    args = ap.parse_args()

    setup = default_setup().with_bulge(args.bulge_mm)
    cam = setup.cameras["left"]
    # View rays (distortion inverted per pixel), computed afresh (sensor_rays() caches them).
    t_rays, rays = best_of(lambda: cam.camera.view_rays(cam.camera.pixel_grid()), 3)
    n = rays[0].shape[0] * rays[0].shape[1]

    def mapping():
        return trace_camera(cam.camera, cam.T_world_cam, setup.sample.T_world_sample, setup.sample.surface,
                            setup.screen.T_world_screen, setup.screen.surface, rays=rays)

    t0 = time.perf_counter()
    m = mapping()  # includes compilation (or loading the cache)
    t_first = time.perf_counter() - t0
    load_before = os.getloadavg()[0]
    times = []
    for _ in range(max(args.repeat, 1)):
        t0 = time.perf_counter()
        m = mapping()
        times.append(time.perf_counter() - t0)
    t_map = min(times)

    # Render the whole sequence (24 images by default) and write it as PNG.
    def render_all():
        return [img for _, img in render_images(setup, "left", m)]

    render_all()
    t_render, imgs = best_of(render_all, 3)
    n_img = len(imgs)
    with tempfile.TemporaryDirectory() as d:
        def write_serial():
            for i, img in enumerate(imgs):
                write_png(Path(d) / f"{i}.png", img)

        t_write, _ = best_of(write_serial, 2)

        def render_and_write():
            with ThreadPoolExecutor(max_workers=2) as pool:
                futs = [pool.submit(write_png, Path(d) / f"{spec.file}", img) for spec, img in render_images(setup, "left", m)]
                for f in futs:
                    f.result()

        t_seq, _ = best_of(render_and_write, 2)

    peak_mb = peak_rss_mb()
    result = {
        "pmdsim_version": __version__,
        "threads": numba.get_num_threads(),
        "image_size_px": [cam.camera.width_px, cam.camera.height_px],
        "bulge_mm": args.bulge_mm,
        "view_rays_s": t_rays,
        "first_mapping_s_incl_compile_or_cache": t_first,
        "mapping_s": t_map,
        "mapping_s_median": float(np.median(times)),
        "mrays_per_s": n / t_map / 1e6,
        "load_avg_1min": load_before,
        "valid_pixels": int(m.valid.sum()),
        "n_images": n_img,
        "render_s_per_image": t_render / n_img,
        "png_write_s_per_image": t_write / n_img,
        "render_and_write_sequence_s": t_seq,
        "peak_rss_mb": peak_mb,
    }
    if args.json:
        dump_json(result)
        return
    print(f"pmdsim {__version__}, {result['threads']} threads, {n} pixels, bulge {args.bulge_mm} mm, "
          f"load average {load_before:.2f} (the cores may be shared: compare back to back)")
    print(f"view rays (once per camera) : {t_rays * 1e3:8.1f} ms")
    print(f"mapping, first call          : {t_first:8.2f} s (compile or load cache)")
    label = f"mapping (best of {len(times)})"
    print(f"{label:<29}: {t_map * 1e3:8.1f} ms  = {result['mrays_per_s']:.1f} Mrays/s"
          f" (median {result['mapping_s_median'] * 1e3:.1f} ms)")
    print(f"render                       : {t_render / n_img * 1e3:8.1f} ms per image")
    print(f"PNG write (serial)           : {t_write / n_img * 1e3:8.1f} ms per image")
    print(f"render + write {n_img} images    : {t_seq:8.2f} s (2 writer threads)")
    print(f"peak memory (RSS)            : {peak_mb:8.0f} MB")


if __name__ == "__main__":
    main()
