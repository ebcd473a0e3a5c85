"""Coverage of the height σ in Experiment 2's 3 mm case (issue 22, item 5: ``coverage_k2``).

Truth: the paper's Table 1 setup binned ``--downsample`` × ``--downsample`` with the screen
bulged by ``--bulge-mm`` (3 mm) and ``--noise`` grey levels of 8-bit image noise (seed s for
both the calibration poses' and the sample's images). For every seed s = ``--seed0`` …
``--seed0 + --seeds − 1``: simulate the 16 calibration poses once, calibrate from the nominal
start values (Experiment 2's chain, start values seeded by s) with each screen model of
``--models`` (``planar``; ``NxN`` free form), reconstruct the planar sample with the calibrated
setup and compute σ as Experiment 2's results.json does (noise part: the decoder's σ through the
linearised integration; calibration part: the calibration's covariance). Per model and camera:
``coverage_k2`` (fraction of reconstructed pixels with |error| ≤ 2σ, error = reconstructed
height with nothing removed, σ relative to the same seed pixel) over the seeds — mean, median,
range — and the pooled diagnostics over all seeds and pixels with σ > 0: the pooled coverage and
z_rms = sqrt(mean (e/σ)²) (1 for a σ that states the error's scatter; the per-seed coverage of a
correlated error field scatters widely even then).

    python benchmarks/coverage_experiment2.py [--downsample 8] [--seeds 20] [--models planar,3x3]
        [--noise 2] [--json]
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from _common import dump_json, peak_rss_mb
from pmdsim import __version__
from pmdsim.setup import default_setup
from pmdsim.studies import calibrate_and_reconstruct, simulate_calibration_observations
from pmdsim.studies.experiment_uncertainty import COVERAGE_GAUSSIAN_K2


def _grid(label):
    return None if label == "planar" else int(label.split("x")[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--downsample", type=int, default=8)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--models", default="planar,3x3")
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--method", default="stepwise")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    models = [m.strip() for m in a.models.split(",") if m.strip()]
    base = default_setup().binned(a.downsample).with_bulge(a.bulge_mm)
    per = {(m, c): [] for m in models for c in base.cameras}
    pooled = {k: {"inside": 0, "n": 0, "z2": 0.0, "n_pos": 0} for k in per}
    stats = {k: [] for k in per}
    t0 = time.perf_counter()
    load0 = os.getloadavg()[0]
    for s in range(a.seed0, a.seed0 + a.seeds):
        truth = base.with_patterns(noise_std=a.noise, seed=s)
        obs = simulate_calibration_observations(truth)
        for m in models:
            e = calibrate_and_reconstruct(truth, bulge_mm=a.bulge_mm, method=a.method, start_seed=[s, 3000],
                                          screen_grid=_grid(m), observations=obs, uncertainty=True)
            for c in e.cases:
                rec = c.as_record()
                per[(m, c.camera)].append(rec["coverage_k2"])
                stats[(m, c.camera)].append(rec["height_std_um"])
                p = pooled[(m, c.camera)]
                p["ignores"] = rec["height_std_ignores"]
                if c.height_std_um is not None:  # pooled diagnostics from the maps themselves
                    err_um = c.height_error_mm * 1e3
                    ok = np.isfinite(err_um) & np.isfinite(c.height_std_um)
                    p["inside"] += int(np.sum(np.abs(err_um[ok]) <= 2 * c.height_std_um[ok]))
                    p["n"] += int(ok.sum())
                    pos = ok & (c.height_std_um > 0)
                    p["z2"] += float(np.sum((err_um[pos] / c.height_std_um[pos]) ** 2))
                    p["n_pos"] += int(pos.sum())
        if not a.json:
            line = "; ".join(f"{m} {c}: {per[(m, c)][-1]:.3f}" for (m, c) in per)
            print(f"seed {s}: coverage_k2 {line}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    wall = time.perf_counter() - t0
    out = {"version": __version__, "downsample": a.downsample, "seeds": a.seeds, "seed0": a.seed0,
           "noise_std": a.noise, "bulge_mm": a.bulge_mm, "method": a.method, "wall_s": wall,
           "load_start": load0, "load_end": os.getloadavg()[0], "peak_rss_mb": peak_rss_mb(),
           "gaussian_expectation": COVERAGE_GAUSSIAN_K2, "results": []}
    for (m, c), cov in per.items():
        v = np.array([x for x in cov if x is not None], dtype=float)
        hs = stats[(m, c)]
        out["results"].append({
            "model": m, "camera": c, "coverage_k2": cov,
            "mean": float(v.mean()), "median": float(np.median(v)), "min": float(v.min()), "max": float(v.max()),
            "height_std_rms_um_median": float(np.median([h["rms"] for h in hs])),
            "noise_rms_um_median": float(np.median([h["noise_rms"] for h in hs])),
            "calibration_rms_um_median": float(np.median([h["calibration_rms"] for h in hs])),
            "pooled_coverage_k2": pooled[(m, c)]["inside"] / max(pooled[(m, c)]["n"], 1),
            "pooled_z_rms": math.sqrt(pooled[(m, c)]["z2"] / max(pooled[(m, c)]["n_pos"], 1)),
            "height_std_ignores": pooled[(m, c)].get("ignores", [])})
    if a.json:
        dump_json(out)
        return
    print(f"\nExperiment 2, Δh = {a.bulge_mm:g} mm, Table 1 binned {a.downsample}×, noise {a.noise:g} grey levels, "
          f"{a.seeds} seeds, {a.method}; {wall:.0f} s wall, load {load0:.1f} → {os.getloadavg()[0]:.1f}; "
          f"Gaussian expectation {COVERAGE_GAUSSIAN_K2:.4f}")
    print(f"{'model':8s} {'camera':6s} {'mean':>6s} {'median':>6s} {'min':>6s} {'max':>6s} "
          f"{'pooled':>6s} {'z_rms':>7s} {'σ rms µm':>9s} {'noise':>7s} {'calib':>7s}  ignores")
    for r in out["results"]:
        print(f"{r['model']:8s} {r['camera']:6s} {r['mean']:6.3f} {r['median']:6.3f} {r['min']:6.3f} {r['max']:6.3f} "
              f"{r['pooled_coverage_k2']:6.3f} {r['pooled_z_rms']:7.3g} {r['height_std_rms_um_median']:9.4f} {r['noise_rms_um_median']:7.4f} "
              f"{r['calibration_rms_um_median']:7.4f}  {', '.join(r['height_std_ignores']) or '-'}")


if __name__ == "__main__":
    main()
