"""False-positive rate of the consistency checks on clean simulated images (issue 11).

    nice python benchmarks/bench_consistency.py [--bin 8] [--seeds 10] [--noise 0,1,3]

For each noise level σ (grey levels, Gaussian, on top of 8-bit quantisation) and seed, the
Table 1 setup (cameras binned ×bin, flat mirror) is rendered in memory, decoded and checked;
prints flagged pixels / tested pixels per flag. The decoder is given the default quantisation
noise (as `pmdsim evaluate` without --noise-std): the checks must find the real noise themselves.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pmdsim.evaluation.consistency import check_consistency, nominal_screen_xy
from pmdsim.evaluation.phase import PhaseFlag
from pmdsim.io.imageset import camera_images_from_arrays, decode_camera_images
from pmdsim.setup import default_setup
from pmdsim.simulation.render import render_images, trace_setup_camera


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", type=int, default=8)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--noise", default="0,1,3")
    args = ap.parse_args()
    base = default_setup().binned(args.bin)
    for sigma in [float(s) for s in args.noise.split(",")]:
        totals = {"tested": 0, "FIT_RESIDUAL": 0, "PERIOD_MISMATCH": 0, "GEOMETRY": 0, "any": 0}
        t0 = time.perf_counter()
        for seed in range(args.seeds):
            setup = base.with_patterns(noise_std=sigma, seed=seed)
            for cam, cs in setup.cameras.items():
                m = trace_setup_camera(setup, cam)
                specs, imgs = zip(*render_images(setup, cam, m))
                im = camera_images_from_arrays([s.as_manifest_entry() for s in specs], imgs)
                dec = decode_camera_images(im, setup.screen.size_mm)
                exp = nominal_screen_xy(cs.camera, cs.T_world_cam, setup.sample.T_world_sample,
                                        setup.screen.T_world_screen)
                c = check_consistency(im.x_stacks, im.x_periods_mm, im.y_stacks, im.y_periods_mm, dec,
                                      setup.screen.size_mm, expected_xy_mm=exp)
                totals["tested"] += int(c.tested.sum())
                for f in (PhaseFlag.FIT_RESIDUAL, PhaseFlag.PERIOD_MISMATCH, PhaseFlag.GEOMETRY):
                    totals[f.name] += int(np.count_nonzero(c.flags & f))
                totals["any"] += int(np.count_nonzero(c.flags))
        n = totals["tested"]
        print(f"noise σ = {sigma:g} grey levels, {args.seeds} seeds × {len(base.cameras)} cameras, {n} pixels tested "
              f"({time.perf_counter() - t0:.0f} s): " + ", ".join(
                  f"{k} {v} ({v / n:.2e})" for k, v in totals.items() if k != "tested"))


if __name__ == "__main__":
    main()
