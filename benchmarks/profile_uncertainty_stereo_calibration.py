"""Where the stereo σ's calibration part spends its time (issue 22 "Speed", ``--stereo``).

    python benchmarks/profile_uncertainty_stereo_calibration.py [--binning 4] [--stride S]

Table 1 binned ``--binning``×, one noisy decode of both cameras, a diagonal calibration
covariance of both cameras' 14 parameters and the table's 3 (the values do not change the
cost: 31 principal axes), the stereo evaluation, then
:func:`~pmdsim.evaluation.uncertainty_stereo_calibration.stereo_calibration_contribution` once
to warm up and once under cProfile: CPU seconds of both and the profile's top functions.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time

import numpy as np

from pmdsim.evaluation.pipeline import decode_simulated
from pmdsim.evaluation.stereo import evaluate_stereo_decoded
from pmdsim.evaluation.uncertainty_stereo_calibration import stereo_calibration_contribution
from pmdsim.setup import default_setup
from pmdsim.setup.covariance import CAMERA_PARAMETER_NAMES, TABLE_PARAMETER_NAMES, CalibrationCovariance
from pmdsim.simulation.render import noise_generator, trace_setup_camera


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--binning", type=int, default=4)
    ap.add_argument("--top", type=int, default=16)
    ap.add_argument("--stride", type=int, default=None, help="the calibration part's subgrid stride (default: its own)")
    a = ap.parse_args()
    s = default_setup().binned(a.binning).with_patterns(noise_std=2.0)
    names = [f"{c}.{n}" for c in s.cameras for n in CAMERA_PARAMETER_NAMES] + list(TABLE_PARAMETER_NAMES)
    sd = np.array([1e-2 if n.split(".")[1].endswith("_px") else 1e-5 for n in names])
    s = s.with_calibration_covariance(CalibrationCovariance(tuple(names), np.diag(sd ** 2)))
    dec = {c: decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, c, stream=1000))
           for c, m in ((c, trace_setup_camera(s, c)) for c in s.cameras)}
    evaluate_stereo_decoded(s, dec)
    c0 = time.process_time()
    _, st = evaluate_stereo_decoded(s, dec)
    t_eval = time.process_time() - c0
    stereo_calibration_contribution(s, dec, st, stride=a.stride)
    pr = cProfile.Profile()
    c0 = time.process_time()
    pr.enable()
    r = stereo_calibration_contribution(s, dec, st, stride=a.stride)
    pr.disable()
    t_cal = time.process_time() - c0
    shape = st.cameras[next(iter(st.cameras))].reconstructed.shape
    print(f"binning {a.binning} ({shape[1]}×{shape[0]} px): stereo evaluation {t_eval:.2f} s CPU; calibration part "
          f"{t_cal:.2f} s CPU (+{t_cal / t_eval:.0%}; {r.n_axes} axes, subgrid stride {next(iter(r.cameras.values())).stride_px}); load "
          f"{os.getloadavg()}")
    pstats.Stats(pr).sort_stats("tottime").print_stats(a.top)


if __name__ == "__main__":
    main()
