"""Where the stereo σ's calibration part spends its time (issue 22 "Speed", ``--stereo``).

    python benchmarks/profile_uncertainty_stereo_calibration.py [--binning 4] [--stride S] [--threads N]
    python benchmarks/profile_uncertainty_stereo_calibration.py --binning 8 --compare-threads 3

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
    ap.add_argument("--threads", type=int, default=None, help="the calibration part's numba threads (default: its own)")
    ap.add_argument("--compare-threads", type=int, default=0, metavar="N",
                    help="instead of the profile: N interleaved runs with the default threads and with all numba "
                         "threads (the code before), CPU and wall, and the σ's per-pixel relative difference")
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
    if a.compare_threads:
        _compare_threads(a, s, dec, st, t_eval)
        return
    kw = {} if a.threads is None else {"threads": a.threads}
    stereo_calibration_contribution(s, dec, st, stride=a.stride, **kw)
    pr = cProfile.Profile()
    c0 = time.process_time()
    pr.enable()
    r = stereo_calibration_contribution(s, dec, st, stride=a.stride, **kw)
    pr.disable()
    t_cal = time.process_time() - c0
    shape = st.cameras[next(iter(st.cameras))].reconstructed.shape
    print(f"binning {a.binning} ({shape[1]}×{shape[0]} px): stereo evaluation {t_eval:.2f} s CPU; calibration part "
          f"{t_cal:.2f} s CPU (+{t_cal / t_eval:.0%}; {r.n_axes} axes, subgrid stride {next(iter(r.cameras.values())).stride_px}); load "
          f"{os.getloadavg()}")
    pstats.Stats(pr).sort_stats("tottime").print_stats(a.top)


def _compare_threads(a, s, dec, st, t_eval) -> None:
    """``--compare-threads``: the default (one thread) against all numba threads, interleaved."""
    import numba

    runs = {"default": [], f"{numba.get_num_threads()} threads": []}
    res = {}
    for r in range(a.compare_threads):
        for label, n in zip(runs, (None, numba.get_num_threads())):
            kw = {} if n is None else {"threads": n}
            c0, t0 = time.process_time(), time.perf_counter()
            res[label] = stereo_calibration_contribution(s, dec, st, stride=a.stride, **kw)
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            runs[label].append(cpu)
            print(f"run {r}: calibration part, {label}: {cpu:.2f} s CPU, {wall:.2f} s wall (stereo evaluation "
                  f"{t_eval:.2f} s CPU; load {os.getloadavg()[0]:.2f})", flush=True)
    new, old = (res[k] for k in runs)
    for c in new.cameras:
        for key in ("height_std_um", "slope_std_urad"):
            x, y = getattr(new.cameras[c], key), getattr(old.cameras[c], key)
            m = np.isfinite(y) & (y > 0)
            rel = x[m] / y[m] - 1
            print(f"camera {c} {key}: RMS {np.sqrt(np.mean(x[m] ** 2)):.6g} against {np.sqrt(np.mean(y[m] ** 2)):.6g}; "
                  f"per pixel rel. diff. RMS {np.sqrt(np.mean(rel ** 2)):.2e}, max |·| {np.max(np.abs(rel)):.2e}; "
                  f"bit-identical {np.array_equal(x, y, equal_nan=True)}")
    print(f"medians: default {np.median(runs['default']):.2f} s CPU, all threads {np.median(list(runs.values())[1]):.2f} s CPU")


if __name__ == "__main__":
    main()
