"""What the per-pixel uncertainty adds to a full-resolution `pmdsim evaluate` (issue 22).

    pmdsim simulate --bulge-mm 3 --out set3          # Table 1, two 1920×1200 cameras
    python benchmarks/bench_uncertainty_speed.py set3 [--repeat 3] [--method stepwise]

Runs ``pmdsim evaluate IMAGE_DIR --out TMP`` as subprocesses, A/B interleaved (with σ, then with
``--no-uncertainty``, ``--repeat`` times), and prints each wall time, the medians, the ratio
and the load average before and after. Target: at most +50 %.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("image_dir")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--method", default="stepwise", choices=["stepwise", "least_squares"])
    a = ap.parse_args()
    print(f"load before: {os.getloadavg()}")
    times: dict = {"with σ": [], "--no-uncertainty": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.repeat):
            for label, extra in (("with σ", []), ("--no-uncertainty", ["--no-uncertainty"])):
                out = os.path.join(tmp, f"ev{r}{len(extra)}")
                t = time.perf_counter()
                subprocess.run([sys.executable, "-m", "pmdsim", "evaluate", a.image_dir, "--out", out, "--quiet",
                                "--method", a.method], check=True, capture_output=True)
                times[label].append(time.perf_counter() - t)
                print(f"run {r}: {label}: {times[label][-1]:.1f} s (load {os.getloadavg()[0]:.2f})", flush=True)
    w, wo = statistics.median(times["with σ"]), statistics.median(times["--no-uncertainty"])
    print(f"median: with σ {w:.1f} s, without {wo:.1f} s: +{100 * (w / wo - 1):.0f} % (target ≤ +50 %)")
    print(f"load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
