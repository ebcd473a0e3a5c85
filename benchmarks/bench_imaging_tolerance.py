"""The series' truncation tolerance (no screen pixels: the renderer's harmonic series) measured:
per tolerance, the largest error of the mean grey levels against the uncut series (every
harmonic), the largest error of the decoded screen coordinate (N-step phase of the noise-free
means, per period, µm) and the CPU time of the 24 images.

    PYTHONPATH=src python benchmarks/bench_imaging_tolerance.py [--downsample 4] [--case all_no_pixels]

Cases: ``all_no_pixels`` (every effect of bench_imaging.ALL_EFFECTS but the screen pixels, which
are rendered in position without a tolerance) and ``display_levels`` (256 levels alone).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench_imaging import ALL_EFFECTS
from pmdsim.setup import default_setup
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
from pmdsim.simulation.render import trace_setup_camera

CASES = {
    "all_no_pixels": {k: v for k, v in ALL_EFFECTS.items() if k not in ("screen_pixel_pitch_mm", "screen_fill_factor")},
    "display_levels": dict(display_levels=256),
    "levels_f8": dict(display_levels=256, display_gamma=2.2, f_number=8.0, focal_length_mm=25.0, pixel_area=True),
}


#: Pixels whose uncut modulation B is below this (grey levels) are left out of the coordinate
#: error: near a zero of the lens transfer any error moves the phase (the decoder flags them).
MIN_MODULATION_DN = 5.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--case", default="all_no_pixels", choices=list(CASES))
    ap.add_argument("--tolerances", default="0,1e-3,1e-2,0.05,0.2")
    args = ap.parse_args()
    setup = default_setup().with_bulge(3.0).with_imaging(**CASES[args.case]).binned(args.downsample)
    m = trace_setup_camera(setup, "left", store_points=True)
    maps = imaging_maps(setup, "left", m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    v = m.valid
    delta = 2 * np.pi * np.arange(seq.n_shifts) / seq.n_shifts
    frames = [(d, p) for d in "xy" for p in seq.periods(d)]
    render_period_imaging(maps, m.screen_xy_mm, v, "x", 2.0, seq, sensor, np.random.default_rng(0))  # compile
    ref = None
    print(f"case {args.case}, {v.shape[1]}×{v.shape[0]}, load {os.getloadavg()[0]:.2f}")
    for tol in (float(t) for t in args.tolerances.split(",")):
        means = np.empty((len(frames), seq.n_shifts) + v.shape)
        c = time.process_time()
        for i, (d, p) in enumerate(frames):
            render_period_imaging(maps, m.screen_xy_mm, v, d, p, seq, sensor, np.random.default_rng(0),
                                  tolerance_dn=tol, means=means[i])
        cpu = time.process_time() - c
        if ref is None:
            ref = means
        err_dn = np.abs(means - ref)[:, :, v].max()
        errs = []
        for i, (d, p) in enumerate(frames):
            z = np.tensordot(np.exp(1j * delta), means[i], 1)
            z0 = np.tensordot(np.exp(1j * delta), ref[i], 1)
            ok = v & (2 / seq.n_shifts * np.abs(z0) >= MIN_MODULATION_DN)
            dphi = np.angle(z / z0)[ok]
            errs.append(np.abs(dphi).max() * p / (2 * np.pi) * 1e3 if dphi.size else np.nan)
        print(f"  tolerance {tol:g} DN: CPU {cpu:.2f} s for {len(frames) * seq.n_shifts} images; max |Δmean| "
              f"{err_dn:.2e} DN; max |Δx| per period where B ≥ 5 DN (µm) " + ", ".join(f"{d}{p:g} {e:.2e}" for (d, p), e in zip(frames, errs)))


if __name__ == "__main__":
    main()
