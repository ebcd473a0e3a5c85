"""`pmdsim evaluate --stereo` end to end, with a per-stage breakdown (issue 25, item 1; st25h).

    pmdsim simulate --bulge-mm 3 --out set3          # once: Table 1, two cameras, 1920×1200
    python benchmarks/bench_evaluate_stereo.py set3 [--repeat 2] [--no-cli] [--json]

Per stage of :func:`pmdsim.studies.jobs.evaluate_image_set_stereo`, summed over the calls from
any thread: wall time, CPU time of the calling thread, and — for calls from the main thread —
the process's system time and minor page faults (``resource.getrusage``; first touches of fresh
memory). Stages: decode (reading + decoding), checks (nominal map + consistency checks),
registration (``stereo_views``), the integration's warm-up (a thread during decode, st26), the
stereo search / integration / report
(``StereoReconstruction.timings``), σ (``stereo_uncertainty``), files (``evaluation.h5``, PNGs).
Stages overlapped in threads are summed per thread (so they may add to more than the wall
time); "total" is the wall time of the call. ``--huge-pages``: numpy's huge-page hint left on (A/B of
:func:`pmdsim.studies.evaluate_memory.small_pages`). Then, unless ``--no-cli``, one
``pmdsim evaluate IMAGE_DIR --out TMP --quiet --stereo`` subprocess: wall, user, system, peak RSS.
"""

from __future__ import annotations

import argparse
import functools
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

from _common import dump_json, peak_rss_mb

_T = defaultdict(lambda: [0.0, 0.0, 0.0, 0])  # stage → [wall, thread CPU, system (main thread), minor faults]
_ACTIVE = threading.local()
_STAGE = {"main": "rest"}  # the main thread's current stage (for --rss)
_RSS = defaultdict(float)  # stage → largest resident set sampled while the main thread was in it (MB)


def _sample_rss(stop: threading.Event) -> None:
    """Every 5 ms: the resident set (``/proc/self/statm``) against the main thread's stage."""
    page = os.sysconf("SC_PAGE_SIZE") / 2**20
    while not stop.wait(0.005):
        with open("/proc/self/statm") as f:
            rss = int(f.read().split()[1]) * page
        k = _STAGE["main"]
        _RSS[k] = max(_RSS[k], rss)


def _timed(stage, fn):
    """``fn`` wrapped to add its wall / thread CPU (and, in the main thread, system time and minor
    page faults) to ``_T[stage]``; nested timed calls count only in the outermost stage."""
    @functools.wraps(fn)
    def wrapper(*a, **k):
        if getattr(_ACTIVE, "on", False):
            return fn(*a, **k)
        _ACTIVE.on = True
        main = threading.current_thread() is threading.main_thread()
        ru = resource.getrusage(resource.RUSAGE_SELF) if main else None
        if main:
            _STAGE["main"] = stage
        t, c = time.perf_counter(), time.thread_time()
        try:
            return fn(*a, **k)
        finally:
            _ACTIVE.on = False
            if main:
                _STAGE["main"] = "rest"
            s = _T[stage]
            s[0] += time.perf_counter() - t
            s[1] += time.thread_time() - c
            if main:
                ru2 = resource.getrusage(resource.RUSAGE_SELF)
                s[2] += ru2.ru_stime - ru.ru_stime
                s[3] += ru2.ru_minflt - ru.ru_minflt
    return wrapper


def _labelled(label, fn):
    """``fn`` wrapped to set the main thread's --rss stage label while it runs (inside a stage)."""
    @functools.wraps(fn)
    def wrapper(*a, **k):
        if threading.current_thread() is not threading.main_thread():
            return fn(*a, **k)
        before, _STAGE["main"] = _STAGE["main"], label
        try:
            return fn(*a, **k)
        finally:
            _STAGE["main"] = before
    return wrapper


def _instrument():
    import pmdsim.evaluation.stereo as stereo
    import pmdsim.io.hdf5 as hdf5
    import pmdsim.studies.jobs as jobs
    import pmdsim.studies.uncertainty_job as uj

    for name in ("load_camera_stacks", "decode_camera_images"):
        setattr(jobs, name, _timed("decode", getattr(jobs, name)))
    for name in ("_expected_screen_xy", "consistency_stacks", "check_consistency", "with_consistency"):
        setattr(jobs, name, _timed("checks", getattr(jobs, name)))
    stereo.stereo_views = _timed("registration", stereo.stereo_views)
    stereo._integrate_anchored = _labelled("  integration", stereo._integrate_anchored)
    if hasattr(stereo, "warm_up"):  # the integration's kernels loaded in a thread while decoding (st26)
        stereo.warm_up = _timed("warm-up (thread, during decode)", stereo.warm_up)
    stereo._points_and_normals = _labelled("  points and normals", stereo._points_and_normals)
    try:  # the report in its own module (st25h)
        import pmdsim.evaluation.stereo_report as sr
        sr.agreement = _labelled("  report", sr.agreement)
    except ImportError:
        stereo._report_kernel = _labelled("  report", stereo._report_kernel)
    recon = _timed("stereo (search + integration + report)", stereo.reconstruct_stereo)

    def reconstruct_stereo(*a, **k):  # with the reconstruction's own stage timings
        st = recon(*a, **k)
        for key in ("search", "integration", "report"):
            if key in (st.timings_s or {}):
                s = _T[f"  of which {key}"]
                s[0] += st.timings_s[key]
                s[1] += st.timings_s.get(f"{key}_cpu", 0.0)
        return st

    stereo.reconstruct_stereo = reconstruct_stereo
    uj.stereo_uncertainty = _timed("uncertainty", uj.stereo_uncertainty)
    uj.stereo_figures = _timed("files: PNG", uj.stereo_figures)
    jobs.write_height_map_png = _timed("files: PNG", jobs.write_height_map_png)
    try:  # the job in its own module (st25h): files written while it computes
        import pmdsim.studies.evaluate_stereo as es
        es.write_height_map_png = _timed("files: PNG", es.write_height_map_png)
        mods = (jobs, hdf5, es)
    except ImportError:
        mods = (jobs, hdf5)
    for mod in mods:
        for name in ("write_evaluation_h5", "write_consistency_h5", "append_stereo_h5"):
            if hasattr(mod, name):
                setattr(mod, name, _timed("files: evaluation.h5", getattr(mod, name)))
    for name in ("add_camera", "add_extras", "finish"):
        setattr(hdf5.EvaluationFile, name, _timed("files: evaluation.h5", getattr(hdf5.EvaluationFile, name)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("image_dir")
    ap.add_argument("--huge-pages", action="store_true",
                    help="keep numpy's huge-page hint on in the job (A/B of studies/evaluate_memory.small_pages)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--no-cli", action="store_true")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--rss", action="store_true",
                    help="sample the resident set every 5 ms: its peak per stage of the main thread (last run)")
    args = ap.parse_args()
    if args.huge_pages:
        import contextlib

        import pmdsim.studies.evaluate_memory as em

        em.small_pages = contextlib.nullcontext

    import numba

    from pmdsim.setup import default_setup

    _instrument()
    from pmdsim.studies.jobs import evaluate_image_set_stereo

    res = {"threads": numba.get_num_threads(), "image_dir": args.image_dir, "load_before": os.getloadavg()[0],
           "huge_pages": bool(args.huge_pages),
           "utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}
    setup = default_setup()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            _T.clear()
            _RSS.clear()
            stop = threading.Event()
            sampler = threading.Thread(target=_sample_rss, args=(stop,), daemon=True) if args.rss else None
            if sampler is not None:
                sampler.start()
            ru = resource.getrusage(resource.RUSAGE_SELF)
            t, c = time.perf_counter(), time.process_time()
            evaluate_image_set_stereo(args.image_dir, setup, Path(tmp) / f"e{i}")
            total, cpu = time.perf_counter() - t, time.process_time() - c
            ru2 = resource.getrusage(resource.RUSAGE_SELF)
            stop.set()
            if sampler is not None:
                sampler.join()
            runs.append({"rss_peak_mb_by_stage": dict(_RSS), "total_s": total, "cpu_s": cpu, "system_s": ru2.ru_stime - ru.ru_stime,
                         "minflt": ru2.ru_minflt - ru.ru_minflt, "stages": {k: list(v) for k, v in _T.items()}})
        res["runs"] = runs
        res["in_process_peak_rss_mb"] = peak_rss_mb()
        if not args.no_cli:
            exe = Path(sys.executable).with_name("pmdsim")
            cmd = [str(exe) if exe.exists() else "pmdsim", "evaluate", args.image_dir, "--out", str(Path(tmp) / "cli"),
                   "--quiet", "--stereo"]
            ru = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            ru2 = resource.getrusage(resource.RUSAGE_CHILDREN)
            res["cli"] = {"wall_s": time.perf_counter() - t, "user_s": ru2.ru_utime - ru.ru_utime,
                          "system_s": ru2.ru_stime - ru.ru_stime, "peak_rss_mb": ru2.ru_maxrss / 1024.0}
    res["load_after"] = os.getloadavg()[0]
    if args.json:
        dump_json(res)
        return
    print(f"{res['utc']} UTC, {res['threads']} numba threads, huge pages {'on' if args.huge_pages else 'as the job sets'}, load {res['load_before']:.2f} → {res['load_after']:.2f}")
    for i, r in enumerate(runs):
        print(f"run {i}: {r['total_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU (of which {r['system_s']:.2f} s system), "
              f"{r['minflt']} minor faults")
    best = min(runs, key=lambda r: r["total_s"])
    print(f"  {'stage (best run)':40s} {'wall s':>7s} {'CPU s':>7s} {'sys s':>7s} {'minflt':>8s}")
    for k, (w, c, s, f) in best["stages"].items():
        print(f"  {k:40s} {w:7.2f} {c:7.2f} {s:7.2f} {f:8d}")
    if runs[-1]["rss_peak_mb_by_stage"]:
        print("  resident set peak while the main thread was in (last run, MB): " + ", ".join(
            f"{k} {v:.0f}" for k, v in runs[-1]["rss_peak_mb_by_stage"].items()))
    print(f"in-process peak RSS {res['in_process_peak_rss_mb']:.0f} MB")
    if "cli" in res:
        c = res["cli"]
        print(f"pmdsim evaluate --stereo (subprocess): {c['wall_s']:.2f} s wall, {c['user_s']:.2f} s user, "
              f"{c['system_s']:.2f} s system, peak RSS {c['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
