"""Stage profile of the least-squares integration (issue 25 item 3): where the full-frame
``reconstruct_least_squares`` spends its time.

    python benchmarks/profile_least_squares.py [--threads 1] [--repeat 3]

Table 1, left camera, Δh = 3 mm, 1920×1200 (the frame ``bench_kernel_floors.py`` times: the
24 8-bit images decoded and registered, seed (600, 960)). Wraps the module's stages — every
assembly of the normal equations, every preconditioned CG solve (with its iterations), every
Gauss–Newton loop and coarse-to-fine start level, the final points and normals — and prints
each call's CPU (process) time for the last of ``--repeat`` runs (the first one warms up),
per grid level, with the run's total and the 1-minute load average, and the error of the
full grid's coarse-to-fine start against the result (max and median |z_start − z|, mm: what the
full-grid Gauss–Newton iterations have to remove). With ``--cg-kernels``, each
``dct_pcg`` line is followed by its passes' CPU time and call counts (the transforms
``scipy.fft.dct``/``idct``, the column substitutions, the scatter, direction/product, update
and start passes, the final step; the rest is Python glue).

    python benchmarks/profile_least_squares.py --save-frame FRAME.npz
    python benchmarks/profile_least_squares.py --first-call --frame FRAME.npz [--threads 2] [--calls 3]

``--save-frame`` stores the frame's inputs (o, d, q, valid, seed, seed height); ``--first-call``
reads them and times ``--calls`` calls in this fresh process (the first one loads the kernels
from numba's cache, imports scipy.fft and touches fresh memory): per call and per stage wall,
CPU (process), system time and minor page faults (``resource.getrusage``), and the first call's
numba cache loads (count, time, the slowest). Run it in a fresh process per measurement.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time

import numba
import numpy as np

from _common import table1_integration_frame


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cg-kernels", action="store_true", help="per dct_pcg call, its passes' CPU time")
    ap.add_argument("--save-frame", help="store the frame's inputs (.npz) and stop")
    ap.add_argument("--first-call", action="store_true", help="stages of the first calls in this process")
    ap.add_argument("--frame", help="the inputs stored by --save-frame (needed by --first-call)")
    ap.add_argument("--calls", type=int, default=3)
    a = ap.parse_args()
    if a.first_call:
        if not a.frame:
            ap.error("--first-call needs --frame (the frame made here would call the integration first)")
        first_calls(a.frame, a.threads, a.calls)
        return
    from pmdsim.evaluation import least_squares as LS
    from pmdsim.evaluation import poisson as P

    reg, rec, seed = table1_integration_frame()
    args = (reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, seed, float(rec.height_mm[seed]))
    if a.save_frame:
        np.savez(a.save_frame, o=args[0], d=args[1], q=args[2], valid=args[3], seed=np.array(seed), z0=args[5])
        return
    numba.set_num_threads(a.threads)

    log = []
    starts = {}  # the start heights per grid shape (the last run's)
    passes: dict = {}  # name → [CPU s, calls] within the current dct_pcg call

    def wrap_pass(owner, name):
        fn = getattr(owner, name)

        def timed(*args, **kw):
            c = time.process_time()
            out = fn(*args, **kw)
            acc = passes.setdefault(name, [0.0, 0])
            acc[0] += time.process_time() - c
            acc[1] += 1
            return out

        setattr(owner, name, timed)

    def wrap(mod, name):
        fn = getattr(mod, name)

        def timed(*args, **kw):
            c = time.process_time()
            out = fn(*args, **kw)
            dt = time.process_time() - c
            shape = next((x.shape[:2] for x in args if isinstance(x, np.ndarray) and x.ndim >= 2), None)
            extra = ""
            if name == "dct_pcg":
                extra = f" CG iterations {int(out[1][0])}"
            elif name == "_start_heights":
                starts[shape] = out.copy()
            elif name == "_gauss_newton":
                extra = f" Gauss–Newton iterations {out[0]}, last update {out[2]:.2e} mm"
            log.append(f"{name:24s} {str(shape):14s} {dt * 1e3:7.1f} ms{extra}")
            if name == "dct_pcg" and passes:
                log.extend(f"    {k:22s} {v[0] * 1e3:7.1f} ms in {v[1]} calls"
                           for k, v in sorted(passes.items(), key=lambda kv: -kv[1][0]))
                log.append(f"    {'(rest: np.sum, D > 0, glue)':22s} {(dt - sum(v[0] for v in passes.values())) * 1e3:7.1f} ms")
            passes.clear()
            return out

        setattr(mod, name, timed)

    for name in ("_gauss_newton", "_assemble_gauss_newton", "_points_normals", "_points_and_normals",
                 "_start_heights", "_fill_kernel", "_run_stepwise", "_interpolate_coarse"):
        if hasattr(LS, name):  # (an older tree has other names)
            wrap(LS, name)
    if a.cg_kernels:
        import scipy.fft

        for name in ("dct", "idct"):
            wrap_pass(scipy.fft, name)
        for name in ("_start_fields", "_scatter_dot_max", "_direction_matvec", "_update_gather", "_finish_step",
                     "_column_substitution"):  # the kernels dct_pcg calls from Python (not nested ones)
            if hasattr(P, name):  # (an older tree may lack one)
                wrap_pass(P, name)
    wrap(P, "dct_pcg")
    for r in range(a.repeat):
        log.clear()
        c, w = time.process_time(), time.perf_counter()
        rec = LS.reconstruct_least_squares(*args)
        cpu, wall = time.process_time() - c, time.perf_counter() - w
    print(f"{P.__file__}, {a.threads} thread(s), UTC {time.strftime('%H:%M:%S', time.gmtime())}, "
          f"load {os.getloadavg()[0]:.2f}: total {cpu * 1e3:.1f} ms CPU, {wall * 1e3:.1f} ms wall "
          "(calls listed as they return; a level's start and Gauss–Newton include the calls above them)")
    print("\n".join(log))
    err = np.abs(starts[rec.height_mm.shape] - rec.height_mm)[rec.reconstructed]
    print(f"start error of the full grid: max {err.max():.2e} mm, median {np.median(err):.2e} mm; result: "
          f"{rec.iterations} Gauss–Newton iterations, converged {rec.converged}, last update "
          f"{rec.final_change_mm:.2e} mm")


def _usage():
    """(wall s, CPU s, system s, minor page faults) of this process so far."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), r.ru_utime + r.ru_stime, r.ru_stime, r.ru_minflt


def first_calls(frame: str, threads: int, calls: int) -> None:
    """The stages of the first ``calls`` calls of reconstruct_least_squares in this process."""
    from numba.core import caching

    loads = []  # (s, function) of every numba cache load
    load_overload = caching.Cache.load_overload

    def timed_load(self, sig, target_context):
        t = time.perf_counter()
        out = load_overload(self, sig, target_context)
        loads.append((time.perf_counter() - t, getattr(getattr(self, "_py_func", None), "__name__", self._name)))
        return out

    caching.Cache.load_overload = timed_load
    t0 = _usage()
    from pmdsim.evaluation import least_squares as LS, poisson as P
    from pmdsim.evaluation.integration import _scan_inputs

    print(f"import pmdsim.evaluation.least_squares: {(_usage()[0] - t0[0]) * 1e3:.0f} ms wall")
    fr = np.load(frame)
    args = (fr["o"], fr["d"], fr["q"], fr["valid"], tuple(int(x) for x in fr["seed"]), float(fr["z0"]))
    numba.set_num_threads(threads)
    # numba's first cache load in a process imports its array registries (≈ 0.3 s, scipy.linalg):
    # paid by an earlier kernel in `pmdsim evaluate` (decoding); paid here, outside the calls.
    _scan_inputs(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), np.ones((1, 1), dtype=bool))
    loads.clear()
    log = []

    def wrap(mod, name):
        fn = getattr(mod, name)

        def timed(*args, **kw):
            s = _usage()
            try:
                return fn(*args, **kw)
            finally:
                e = _usage()
                shape = next((x.shape[:2] for x in args if isinstance(x, np.ndarray) and x.ndim >= 2), "")
                log.append((s[0], f"{name} {shape}", *(y - x for x, y in zip(s, e))))

        setattr(mod, name, timed)

    for name in ("_start_heights", "_gauss_newton", "_assemble_gauss_newton", "_every_second", "_run_stepwise",
                 "_points_normals", "_points_and_normals", "_pcg", "Multigrid"):
        if hasattr(LS, name):  # (an older tree has other names)
            wrap(LS, name)
    wrap(P, "dct_pcg")
    wrap(P, "DCTLaplacian")
    print(f"scipy.fft imported before call 1: {'scipy.fft' in sys.modules}")
    for call in range(1, calls + 1):
        log.clear()
        s = _usage()
        LS.reconstruct_least_squares(*args[:4], seed_pixel=args[4], seed_height_mm=args[5])
        e = _usage()
        print(f"call {call}: wall {(e[0] - s[0]) * 1e3:.0f} ms, CPU {(e[1] - s[1]) * 1e3:.0f} ms, system "
              f"{(e[2] - s[2]) * 1e3:.0f} ms, {e[3] - s[3]} minor faults ({threads} threads, UTC "
              f"{time.strftime('%H:%M:%S', time.gmtime())}, load {os.getloadavg()[0]:.2f})")
        for t, name, wall, cpu, sys_s, faults in sorted(log):
            print(f"    {name:40s} wall {wall * 1e3:7.1f}  CPU {cpu * 1e3:7.1f}  sys {sys_s * 1e3:6.1f}  faults {faults:6d}")
        if call == 1:
            print(f"  numba cache loads in call 1: {len(loads)}, {sum(x for x, _ in loads) * 1e3:.0f} ms; slowest: "
                  + ", ".join(f"{n} {x * 1e3:.1f}" for x, n in sorted(loads, reverse=True)[:4]))
    caching.Cache.load_overload = load_overload


if __name__ == "__main__":
    main()
