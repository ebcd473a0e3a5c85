"""Stage profile of the least-squares integration (issue 25 item 3): where the full-frame
``reconstruct_least_squares`` spends its time.

    python benchmarks/profile_least_squares.py [--threads 1] [--repeat 3]

Table 1, left camera, Δh = 3 mm, 1920×1200 (the frame ``bench_kernel_floors.py`` times: the
24 8-bit images decoded and registered, seed (600, 960)). Wraps the module's stages — every
assembly of the normal equations, every preconditioned CG solve (with its iterations), every
Gauss–Newton loop and coarse-to-fine start level, the final points and normals — and prints
each call's CPU (process) time for the last of ``--repeat`` runs (the first one warms up),
per grid level, with the run's total and the 1-minute load average.
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from _common import table1_integration_frame


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    from pmdsim.evaluation import least_squares as LS
    from pmdsim.evaluation import poisson as P

    reg, rec, seed = table1_integration_frame()
    args = (reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, seed, float(rec.height_mm[seed]))
    numba.set_num_threads(a.threads)

    log = []

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
            elif name == "_gauss_newton":
                extra = f" Gauss–Newton iterations {out[0]}, last update {out[2]:.2e} mm"
            log.append(f"{name:24s} {str(shape):14s} {dt * 1e3:7.1f} ms{extra}")
            return out

        setattr(mod, name, timed)

    for name in ("_gauss_newton", "_assemble_gauss_newton", "_points_and_normals", "_start_heights",
                 "_fill_kernel", "_run_stepwise", "_interpolate_coarse"):
        wrap(LS, name)
    wrap(P, "dct_pcg")
    for r in range(a.repeat):
        log.clear()
        c, w = time.process_time(), time.perf_counter()
        LS.reconstruct_least_squares(*args)
        cpu, wall = time.process_time() - c, time.perf_counter() - w
    print(f"{P.__file__}, {a.threads} thread(s), UTC {time.strftime('%H:%M:%S', time.gmtime())}, "
          f"load {os.getloadavg()[0]:.2f}: total {cpu * 1e3:.1f} ms CPU, {wall * 1e3:.1f} ms wall "
          "(calls listed as they return; a level's start and Gauss–Newton include the calls above them)")
    print("\n".join(log))


if __name__ == "__main__":
    main()
