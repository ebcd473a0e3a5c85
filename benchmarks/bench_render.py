"""Time the fringe renderer and the decoder on one full-resolution camera frame (issue 15).

One camera of the Table 1 setup (Δh = 3 mm, 1920×1200), traced once; best of ``--repeat``:
``render_period`` of one period (4 images), ``render_images`` (all 24 images), ``decode_images``
of those images and, where the tree has it, the fused ``decode_simulated`` (no images).

    PYTHONPATH=<tree>/src nice python benchmarks/bench_render.py [--repeat 3] [--threads N]
"""

from __future__ import annotations

import argparse

import numba

from _common import best_wall_cpu
from pmdsim.evaluation import pipeline
from pmdsim.setup import default_setup
from pmdsim.simulation.patterns import render_period
from pmdsim.simulation.render import render_images, trace_setup_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: all)")
    args = ap.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)
    s = default_setup().with_bulge(3.0)
    m = trace_setup_camera(s, "left")
    seq = s.patterns.sequence

    def images():
        out: dict = {}
        for spec, img in render_images(s, "left", m):
            out.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        return out

    imgs = images()
    cases = [("render_period (1 period, 4 images)", lambda: render_period(m.screen_xy_mm, m.valid, "x", 2.0, seq)),
             ("render_images (24 images)", images),
             ("decode_images (24 images)", lambda: pipeline.decode_images(s, imgs))]
    if hasattr(pipeline, "decode_simulated"):
        cases.append(("decode_simulated (fused, no images)", lambda: pipeline.decode_simulated(s, m.screen_xy_mm, m.valid)))
    for label, f in cases:
        f()  # compile / warm up
        w, c = best_wall_cpu(f, args.repeat)
        print(f"{label:38s} best wall {w * 1e3:7.1f} ms, best CPU {c * 1e3:7.1f} ms")


if __name__ == "__main__":
    main()
