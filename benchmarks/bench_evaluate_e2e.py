"""`pmdsim evaluate` end to end, with a per-stage breakdown and peak memory (issue 25, item 1).

Make a full-resolution image set once (Table 1: two cameras, 1920×1200) and pass its directory:

    pmdsim simulate --bulge-mm 3 --out set3
    python benchmarks/bench_evaluate_e2e.py set3 [--repeat 2] [--no-cli] [--json] [--no-uncertainty] [--trace-memory]

Prints, for ``--repeat`` evaluations in this process (the first one also loads the cached numba
kernels; the best is reported): wall time per stage — decode (reading the images + decoding),
checks (nominal map + consistency checks), registration + reconstruction (with its
``registration.register`` and ``RigidTransform.apply`` shares), surface fit, uncertainty (the
per-pixel σ, with the share of its sampled integration ``_sampled_std``), files (evaluation.h5,
PNG figures — heights, σ maps, slope error —, JSON) — and the rest, each as wall and CPU time (CPU: all threads of the process, less sensitive to the
other jobs on a shared machine; the run's system time, mostly page faults, is printed too); then, unless ``--no-cli``, the wall time and
peak resident memory of one ``pmdsim evaluate IMAGE_DIR --out TMP`` subprocess (what a user
waits for and what it needs, imports and kernel loading included). The load average is printed
before and after. Where ``evaluate`` draws its PNG figures in a background thread
(``studies/evaluate_files``), their time is printed apart ("PNG figures in a background thread",
not part of the sum: it overlaps the stages) and "files" holds the main thread's wait for them;
the stages' CPU times (process-wide) then include the figure thread's CPU while they overlap. Where
``evaluate`` runs the cameras two at a time (``studies/evaluate_cameras``), the wall span of the
cameras' pipelines is one row ("cameras, overlapped"), part of the sum; decode, checks,
registration + reconstruction and uncertainty are then summed over the two camera threads (wall,
and CPU of the thread) and not part of the sum. The setup is Table 1 (the default, planar screen model), as the CLI's default.

Timings on the shared 2-vCPU machine: the two vCPUs share one core's vector units, so two numba
threads are no faster than one.
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
import tracemalloc
from collections import defaultdict
from pathlib import Path

from _common import dump_json, peak_rss_mb

_T = defaultdict(float)
_CPU = defaultdict(float)
_DEPTH = {"n": 0}
_CAMERA_DEPTH = threading.local()  # per camera thread (studies/evaluate_cameras: two cameras at once)
_CAMERAS = "cameras, overlapped (decode → σ, wall span)"
_MEM = {}  # stage → (traced MB alive at entry, traced peak MB inside), with --trace-memory
_TRACE = {"on": False}
_ORDER = ("decode", "checks", "registration+reconstruction", "  of which registration.register",
          "  of which RigidTransform.apply", "  of which Camera.view_rays", "surface fit",
          "  of which fit_paraboloid_slopes", "uncertainty", "  of which _sampled_std",
          "  of which stepwise_noise_sigma", "files",
          "  of which write_evaluation_h5", "  of which PNG figures", "  PNG figures in a background thread",
          "rest")
_BACKGROUND = "  PNG figures in a background thread"  # overlapped with the stages: not part of the sum
_OVERLAPPED = ("decode", "checks", "registration+reconstruction", "uncertainty")  # the camera threads' stages


def _timed(stage, fn, *, nested=False):
    """``fn`` wrapped to add its wall time to ``_T[stage]`` (``nested``: a share of another stage,
    counted also when called inside it)."""
    @functools.wraps(fn)
    def wrapper(*a, **k):
        if threading.current_thread().name.startswith("pmdsim-camera"):  # a camera's pipeline in its thread
            if nested or getattr(_CAMERA_DEPTH, "n", 0):
                return fn(*a, **k)
            _CAMERA_DEPTH.n = 1
            t, c = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                _CAMERA_DEPTH.n = 0
                _T[stage] += time.perf_counter() - t  # summed over the camera threads: they overlap
                _CPU[stage] += time.thread_time() - c
        if threading.current_thread() is not threading.main_thread():  # evaluate's figure thread
            if nested:
                return fn(*a, **k)
            t, c = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                _T[_BACKGROUND] += time.perf_counter() - t
                _CPU[_BACKGROUND] += time.thread_time() - c
        if not nested and _DEPTH["n"]:
            return fn(*a, **k)
        if not nested:
            _DEPTH["n"] += 1
        if _TRACE["on"] and not nested:
            cur, before = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
        t = time.perf_counter()
        c = time.process_time()
        try:
            return fn(*a, **k)
        finally:
            _T[stage] += time.perf_counter() - t
            _CPU[stage] += time.process_time() - c
            if _TRACE["on"] and not nested:
                peak = tracemalloc.get_traced_memory()[1]
                old = _MEM.get(stage, (0.0, 0.0))
                _MEM[stage] = (max(old[0], cur / 2**20), max(old[1], peak / 2**20))
                _MEM["(all)"] = (0.0, max(_MEM.get("(all)", (0.0, 0.0))[1], before / 2**20, peak / 2**20))
            if not nested:
                _DEPTH["n"] -= 1
    return wrapper


def _instrument():
    import pmdsim.evaluation.anchor as anchor
    import pmdsim.evaluation.registration as registration
    import pmdsim.evaluation.surface_fit as surface_fit
    import pmdsim.geometry.camera as camera
    import pmdsim.geometry.transform as transform
    import pmdsim.studies.jobs as jobs
    import pmdsim.evaluation.uncertainty as uncertainty
    import pmdsim.studies.surface_figures as surface_figures
    import pmdsim.studies.uncertainty_job as uncertainty_job

    for name in ("load_camera_stacks", "decode_camera_images"):
        setattr(jobs, name, _timed("decode", getattr(jobs, name)))
    for name in ("nominal_screen_xy", "check_consistency", "with_consistency"):
        setattr(jobs, name, _timed("checks", getattr(jobs, name)))
    for name in ("register_model", "reconstruct_anchored"):
        setattr(anchor, name, _timed("registration+reconstruction", getattr(anchor, name)))
    registration.register = _timed("  of which registration.register", registration.register, nested=True)
    transform.RigidTransform.apply = _timed("  of which RigidTransform.apply", transform.RigidTransform.apply,
                                            nested=True)
    camera.Camera.view_rays = _timed("  of which Camera.view_rays", camera.Camera.view_rays, nested=True)
    surface_fit.surface_fit_summary = _timed("surface fit", surface_fit.surface_fit_summary)
    surface_fit.fit_paraboloid_slopes = _timed("  of which fit_paraboloid_slopes",
                                               surface_fit.fit_paraboloid_slopes, nested=True)
    uncertainty_job.camera_uncertainty = _timed("uncertainty", uncertainty_job.camera_uncertainty)
    uncertainty._sampled_std = _timed("  of which _sampled_std", uncertainty._sampled_std, nested=True)
    try:  # the stepwise σ in one pass (issue 25; not in older trees)
        from pmdsim.evaluation import uncertainty_stepwise_fused as fused
        fused.stepwise_noise_sigma = _timed("  of which stepwise_noise_sigma", fused.stepwise_noise_sigma, nested=True)
    except ImportError:
        pass
    # the figures (PNG files): heights (jobs), σ maps (uncertainty_job), slope error (surface_figures);
    # the names of the tree measured (matplotlib figures before, Pillow-written PNGs after issue 25)
    fig_names = [n for n in ("write_height_map_png", "height_map_figure") if hasattr(jobs, n)][:1]
    slope_name = next(n for n in ("write_slope_error_png", "slope_error_figure") if hasattr(surface_figures, n))
    for mod in (uncertainty_job, jobs):
        for n in fig_names:
            if hasattr(mod, n):
                setattr(mod, n, _timed("  of which PNG figures", getattr(mod, n), nested=True))
    setattr(surface_figures, slope_name, _timed("  of which PNG figures", getattr(surface_figures, slope_name),
                                                nested=True))
    uncertainty_job.height_std_figure = _timed("files", uncertainty_job.height_std_figure)
    for name in ("write_evaluation_h5", "write_consistency_h5", *fig_names, "write_json"):
        if hasattr(jobs, name):  # trees before issue 25 call write_evaluation_h5 from jobs; later ones EvaluationFile
            setattr(jobs, name, _timed("files", getattr(jobs, name)))
    if hasattr(jobs, "write_evaluation_h5"):
        jobs.write_evaluation_h5 = _timed("  of which write_evaluation_h5", jobs.write_evaluation_h5, nested=True)
    setattr(surface_figures, slope_name, _timed("files", getattr(surface_figures, slope_name)))
    try:  # the cameras two at a time (issue 25, studies/evaluate_cameras): the wall span of their pipelines
        from pmdsim.studies import evaluate_cameras

        inner = evaluate_cameras.camera_results

        def camera_results(cameras, work, **kw):
            if not evaluate_cameras.concurrent_cameras(len(cameras)) or kw.get("concurrent") is False:
                yield from inner(cameras, work, **kw)
                return
            t, c = time.perf_counter(), time.process_time()
            try:
                yield from inner(cameras, work, **kw)
            finally:
                _T[_CAMERAS] += time.perf_counter() - t
                _CPU[_CAMERAS] += time.process_time() - c

        evaluate_cameras.camera_results = camera_results
    except ImportError:
        pass
    try:  # the figures written in a background thread (issue 25): the main thread's wait for them
        from pmdsim.studies import evaluate_files
        evaluate_files.BackgroundFiles.wait = _timed("files", evaluate_files.BackgroundFiles.wait)
    except ImportError:
        pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("image_dir")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--no-cli", action="store_true")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-uncertainty", action="store_true", help="evaluate without σ (the CLI's --no-uncertainty)")
    ap.add_argument("--figures-in-main-thread", action="store_true",
                    help="draw evaluate's PNG figures in the main thread, each when submitted (A/B of the figure thread)")
    ap.add_argument("--trace-memory", action="store_true",
                    help="tracemalloc per stage in the last run (numpy buffers: what is alive at the stage's entry "
                         "and its peak; slows the run)")
    args = ap.parse_args()
    if args.trace_memory and args.repeat < 2:
        ap.error("--trace-memory traces the last of the --repeat runs and times the others: give --repeat 2 or more")

    import numba

    from pmdsim import __version__
    from pmdsim.setup import default_setup

    _instrument()
    from pmdsim.studies.jobs import evaluate_image_set

    if args.figures_in_main_thread:
        from pmdsim.studies import evaluate_files

        evaluate_files.BackgroundFiles.submit = lambda self, write, *a, **k: write(*a, **k)

    res = {"pmdsim_version": __version__, "uncertainty": not args.no_uncertainty, "threads": numba.get_num_threads(), "image_dir": args.image_dir,
           "load_avg_1min_before": os.getloadavg()[0]}
    setup = default_setup()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            _T.clear()
            _CPU.clear()
            if args.trace_memory and i == args.repeat - 1:
                _MEM.clear()
                tracemalloc.start()
                _TRACE["on"] = True
            t = time.perf_counter()
            c = time.process_time()
            ru = resource.getrusage(resource.RUSAGE_SELF)
            evaluate_image_set(args.image_dir, setup, Path(tmp) / f"e{i}", progress=None,
                               uncertainty=not args.no_uncertainty)
            total = time.perf_counter() - t
            cpu = time.process_time() - c
            ru2 = resource.getrusage(resource.RUSAGE_SELF)
            sys_s = ru2.ru_stime - ru.ru_stime  # page faults mostly (docs/benchmarks.md, "4 kB pages")
            stages = {k: (_T[k], _CPU[k]) for k in (_CAMERAS, *_ORDER) if k in _T}
            summed = [k for k in stages if not k.startswith(" ") and not (_CAMERAS in stages and k in _OVERLAPPED)]
            stages["rest"] = (total - sum(stages[k][0] for k in summed), cpu - sum(stages[k][1] for k in summed))
            if _TRACE["on"]:
                _MEM["(all)"] = (0.0, max(_MEM.get("(all)", (0.0, 0.0))[1], tracemalloc.get_traced_memory()[1] / 2**20))
                tracemalloc.stop()
                _TRACE["on"] = False
                res["traced_mb_at_entry_and_peak"] = dict(_MEM)
            else:
                runs.append((total, stages, cpu, sys_s))
        res["in_process_peak_rss_mb"] = peak_rss_mb()
        total, stages, cpu, sys_s = min(runs, key=lambda r: r[0])
        res["in_process_s"] = total
        res["in_process_cpu_s"] = cpu
        res["in_process_system_s"] = sys_s
        res["stages_wall_cpu_s"] = stages
        res["in_process_all_s"] = [r[0] for r in runs]
        if not args.no_cli:
            exe = Path(sys.executable).with_name("pmdsim")
            cmd = [str(exe) if exe.exists() else "pmdsim", "evaluate", args.image_dir, "--out",
                   str(Path(tmp) / "cli"), "--quiet"]
            if args.no_uncertainty:
                cmd.append("--no-uncertainty")
            t = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            res["cli_wall_s"] = time.perf_counter() - t
            res["cli_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    res["load_avg_1min_after"] = os.getloadavg()[0]
    if args.json:
        dump_json(res)
        return
    print(f"pmdsim {res['pmdsim_version']}, σ {'on' if res['uncertainty'] else 'off (--no-uncertainty)'}, "
          f"{res['threads']} numba threads (the 2 vCPUs share one core's "
          f"vector units), load {res['load_avg_1min_before']:.2f} → {res['load_avg_1min_after']:.2f}")
    print(f"evaluate in process: best {res['in_process_s']:.2f} s of {['%.2f' % t for t in res['in_process_all_s']]}"
          f" ({res['in_process_cpu_s']:.2f} s CPU, of which {res['in_process_system_s']:.2f} s system), "
          f"peak RSS {res['in_process_peak_rss_mb']:.0f} MB")
    print(f"  {'stage':40s} {'wall s':>7s} {'CPU s':>7s}")
    if _CAMERAS in stages:
        print(f"  (cameras overlapped: the span is in the sum; decode … uncertainty are summed over the two camera "
              f"threads, CPU per thread)")
    for k, (v, c) in stages.items():
        print(f"  {k:40s} {v:7.2f} {c:7.2f}")
    if "traced_mb_at_entry_and_peak" in res:
        print(f"  traced memory of the last run (MB)       {'entry':>7s} {'peak':>7s}")
        for k, (a, b) in res["traced_mb_at_entry_and_peak"].items():
            print(f"  {k:40s} {a:7.0f} {b:7.0f}")
    if "cli_wall_s" in res:
        print(f"pmdsim evaluate (subprocess): {res['cli_wall_s']:.2f} s wall, peak RSS {res['cli_peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
