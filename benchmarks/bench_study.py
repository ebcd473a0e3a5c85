"""Cases per hour of a study under several worker / thread layouts (issues 15, 23).

Runs the study into fresh temporary directories, once per layout, and prints the wall time of
the cases (the cluster's start, ≈ 3–4 s, is printed apart) and cases per hour:

* ``serial`` — in this process, numba on all cores;
* ``WxT`` — a LocalCluster of W worker processes with T Dask threads each, numba threads by
  pmdsim's rule (:mod:`pmdsim.studies.study_cluster`: cores // (W × T), at least 1);
* ``WxT-all`` — the same, but every case runs numba on all cores (what a ``dask worker`` did
  before the rule: W × T × cores threads on the machine).

The numba kernels are compiled (cached) before timing by one untimed serial case with
``--warm-up`` (or by an earlier run: they are cached). Layouts run in the order given; give
them interleaved (``2x1,1x1,2x1,1x1``) to see the spread.

    python benchmarks/bench_study.py [--study examples/study_bulge_focal.toml] [--layouts serial,1x1,2x1,2x2,2x2-all]
                                     [--warm-up] [--json]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from _common import dump_json
from pmdsim import __version__
from pmdsim.studies import study_cluster
from pmdsim.studies.study import run_case, run_study
from pmdsim.studies.study_file import load_study


def _load() -> list[str]:
    return open("/proc/loadavg").read().split()[:3]


def _run(study, layout: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out")
        if layout == "serial":
            t = time.perf_counter()
            run = run_study(study, out, serial=True)
            return {"start_s": 0.0, "wall_s": time.perf_counter() - t, "numba_threads": os.cpu_count(), "run": run}
        from distributed import Client, LocalCluster

        spec, _, flavour = layout.partition("-")
        w, nt = (int(x) for x in spec.split("x"))
        t = time.perf_counter()
        with LocalCluster(n_workers=w, threads_per_worker=nt, processes=True, dashboard_address=None,
                          host="127.0.0.1") as lc, Client(lc) as client:
            client.wait_for_workers(w)
            start = time.perf_counter() - t
            check = study_cluster.check_workers  # looked up by open_cluster at each call
            if flavour == "all":  # every case runs numba on all cores (the layout before issue 23)
                def check_all(c, timeout_s=30.0):
                    workers, threads = check(c, timeout_s)
                    return workers, {h: os.cpu_count() for h in threads}

                study_cluster.check_workers = check_all
            try:
                t = time.perf_counter()
                run = run_study(study, out, client=client)
                wall = time.perf_counter() - t
            finally:
                study_cluster.check_workers = check
            return {"start_s": start, "wall_s": wall, "cluster": run.cluster, "run": run}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--study", default="examples/study_bulge_focal.toml")
    ap.add_argument("--layouts", default="serial,1x1,2x1,2x2,2x2-all")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--warm-up", action="store_true", help="Run one case untimed first (numba compilation).")
    a = ap.parse_args()
    study = load_study(a.study)
    if a.warm_up:
        run_case(next(study.iter_cases()), study.metrics)  # compile/load the numba kernels untimed
    res = {"pmdsim_version": __version__, "study": a.study, "n_cases": study.n_cases, "cores": os.cpu_count(),
           "runs": []}
    for layout in a.layouts.split(","):
        before = _load()
        r = _run(study, layout)
        run = r.pop("run")
        assert run.n_missing == 0 and run.n_failed == 0, run
        res["runs"].append({"layout": layout, **r, "cases_per_hour": study.n_cases / r["wall_s"] * 3600,
                            "load": before + ["→"] + _load()})
    if a.json:
        dump_json(res)
        return
    print(f"study {a.study}: {study.n_cases} cases on {res['cores']} cores")
    for r in res["runs"]:
        print(f"  {r['layout']:10s} start {r['start_s']:5.1f} s  cases {r['wall_s']:7.1f} s  "
              f"{r['cases_per_hour']:8.0f} cases/h  load {' '.join(r['load'])}  {r.get('cluster', '')}")


if __name__ == "__main__":
    main()
