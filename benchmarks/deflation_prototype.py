"""Prototype (measured; its core is now pmdsim.evaluation.uncertainty_deflation, used by the
least-squares σ): deflated DCT-preconditioned conjugate gradients for
the least-squares integration's normal equations on a full frame (issue 25 item 3, route (a)),
timed against ``poisson.dct_pcg`` on the first full-grid Gauss–Newton system of the Table 1 frame.

    python benchmarks/deflation_prototype.py [--repeat 5]

The method and its references: :mod:`pmdsim.evaluation.uncertainty_deflation` (the lowest 4 × 6
DCT modes and the Laplacian's Green's function at the seed deflated, A-DEF2 form). On one
integration it takes 3 iterations instead of 7, but its setup and two extra passes per iteration
cost more than the 4 iterations saved (docs/benchmarks.md, "Integration after int25d"); on the
σ's 64 right-hand sides of one matrix the setup is paid once (docs/benchmarks.md, lsq25h).
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from pmdsim.evaluation.poisson import DCTLaplacian, _DCTWork, dct_pcg
from pmdsim.evaluation.uncertainty_deflation import LowModes, deflated_dct_pcg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from _common import rendered_images
    from pmdsim.evaluation import least_squares as LS
    from pmdsim.evaluation.pipeline import decode_images, evaluate_decoded
    from pmdsim.setup import default_setup
    from pmdsim.simulation import trace_setup_camera

    s = default_setup().with_bulge(3.0)
    m = trace_setup_camera(s, "left", store_points=True)
    dec = decode_images(s, rendered_images(s, "left", m))
    seed = (600, 960)
    reg, rec = evaluate_decoded(s.with_bulge(0.0), "left", dec, method="least_squares", seed_pixel=seed)
    o, d, q, S, z0 = reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, float(rec.height_mm[seed])
    numba.set_num_threads(1)
    tol = 1e-9  # reconstruct_least_squares' default: the full grid's solves to tol/10
    z = LS._start_heights(o, d, q, S, seed, z0, tol, 20)
    H, W = S.shape
    D, iD, Ex, Ey, rhs = (np.zeros((H + 2, W + 2)) for _ in range(5))
    LS._assemble_gauss_newton(o, d, q, S, z, seed[0], seed[1], D, iD, Ex, Ey, rhs)
    lap = DCTLaplacian(S.shape, seed, dtype=np.float32)
    work = _DCTWork(1, D.shape)
    times = {"plain": [], "deflated": [], "LowModes": []}
    for _ in range(a.repeat + 1):  # the first: compilation, not counted
        c = time.process_time()
        X, its_p, _ = dct_pcg(D, Ex, Ey, rhs[None], seed, 0.1 * tol, 1e-4, 200, cap=0.1 * tol, lap=lap, work=work)
        times["plain"].append(time.process_time() - c)
        x_plain = X[0].copy()
        c = time.process_time()
        modes = LowModes(S.shape, seed, lap=lap)
        times["LowModes"].append(time.process_time() - c)
        c = time.process_time()
        x, its_d, ok = deflated_dct_pcg(D, Ex, Ey, rhs, seed, 0.1 * tol, 1e-4, 200, cap=0.1 * tol, lap=lap,
                                        work=work, modes=modes)
        times["deflated"].append(time.process_time() - c)
    print(f"UTC {time.strftime('%H:%M:%S', time.gmtime())}, load {os.getloadavg()[0]:.2f}, one thread, CPU time, "
          f"best of {a.repeat}: plain dct_pcg {int(its_p[0])} iterations {min(times['plain'][1:]) * 1e3:.1f} ms; "
          f"deflated {its_d} iterations {min(times['deflated'][1:]) * 1e3:.1f} ms (+ LowModes "
          f"{min(times['LowModes'][1:]) * 1e3:.1f} ms); largest difference of the updates "
          f"{np.max(np.abs(x - x_plain)):.2e} mm (largest update {np.max(np.abs(x_plain)):.2e} mm)")


if __name__ == "__main__":
    main()
