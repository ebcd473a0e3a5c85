"""Cases per hour of a study on the dask LocalCluster against one process (issue 15).

Runs the study twice into fresh temporary directories: serially in this process (numba threads
= all cores) and on a LocalCluster (``--workers`` processes, numba threads = cores // workers),
and prints the wall time and cases per hour of each. The numba kernels are compiled (cached)
before timing by one untimed serial case with ``--warm-up`` (or by an earlier run: they are cached).

    python benchmarks/bench_study.py [--study examples/study_calibration_bulge.toml] [--workers 2] [--warm-up] [--json]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from _common import dump_json
from pmdsim import __version__
from pmdsim.studies.study import run_case, run_study
from pmdsim.studies.study_file import load_study


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--study", default="examples/study_calibration_bulge.toml")
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--warm-up", action="store_true", help="Run one case untimed first (numba compilation).")
    a = ap.parse_args()
    study = load_study(a.study)
    if a.warm_up:
        run_case(study.cases()[0], study.metrics)  # compile/load the numba kernels untimed
    res = {"pmdsim_version": __version__, "study": a.study, "n_cases": study.n_cases, "cores": os.cpu_count(),
           "load_before": open("/proc/loadavg").read().split()[:3]}
    for mode in ("serial", "local_cluster"):
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            run = run_study(study, os.path.join(tmp, "out"), serial=mode == "serial", n_workers=a.workers)
            dt = time.perf_counter() - t
        assert run.n_missing == 0 and run.n_failed == 0, run
        res[mode] = {"wall_s": dt, "cases_per_hour": study.n_cases / dt * 3600}
    res["load_after"] = open("/proc/loadavg").read().split()[:3]
    res["speedup"] = res["serial"]["wall_s"] / res["local_cluster"]["wall_s"]
    if a.json:
        dump_json(res)
        return
    print(f"study {a.study}: {study.n_cases} cases on {res['cores']} cores (load {res['load_before']} → "
          f"{res['load_after']})")
    for mode in ("serial", "local_cluster"):
        r = res[mode]
        print(f"  {mode:14s} {r['wall_s']:8.1f} s  {r['cases_per_hour']:8.0f} cases/h")
    print(f"  LocalCluster / one process: {res['speedup']:.2f}×")


if __name__ == "__main__":
    main()
