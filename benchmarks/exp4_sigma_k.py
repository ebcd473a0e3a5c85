"""Experiment 4's noise rows against the σ model at several ``--downsample K`` (issue 20 item 4).

For each K of ``--ks`` the budget's chain of one effect (default ``sensor``; the same truth,
seeds and calibration as ``pmdsim experiment 4``) is run with the uncertainty propagation on
(``calibrate_and_reconstruct(..., uncertainty=True)``): the σ model's height standard deviation
(noise part, calibration part, combined; RMS over the pixels) is printed beside the measured
height RMS and its RMS after the best-fit plane, so that the measured change with K can be
read against what the σ model predicts for that sampling.

    python benchmarks/exp4_sigma_k.py --effect sensor --ks 8,4
"""

from __future__ import annotations

import argparse
import json
import time

from pmdsim.setup import default_setup
from pmdsim.studies.experiment2 import calibrate_and_reconstruct
from pmdsim.studies.experiment4 import BULGE_MM, _plane_removed_rms_um, effect_truth


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--effect", default="sensor")
    ap.add_argument("--ks", default="8,4")
    a = ap.parse_args()
    base = default_setup()
    for k in (int(v) for v in a.ks.split(",")):
        t0 = time.perf_counter()
        e2 = calibrate_and_reconstruct(effect_truth(base, a.effect, k), bulge_mm=BULGE_MM, method="stepwise",
                                       start_seed=[0, 3000], screen_grid=3, uncertainty=True)
        sec = time.perf_counter() - t0
        for c in e2.cases:
            s = (c.uncertainty or {}).get("height_std_um") or {}
            print(json.dumps({"K": k, "camera": c.camera, "seconds": round(sec, 1),
                              "measured_rms_um": round(c.metrics["rms_um"], 5),
                              "measured_rms_plane_removed_um": round(_plane_removed_rms_um(c.p_sample_mm, c.height_error_mm), 5),
                              "sigma_rms_um": s.get("rms"), "sigma_noise_rms_um": s.get("noise_rms"),
                              "sigma_calibration_rms_um": s.get("calibration_rms"),
                              "coverage_k2": (c.uncertainty or {}).get("coverage_k2")}), flush=True)


if __name__ == "__main__":
    main()
