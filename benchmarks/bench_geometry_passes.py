"""The least-squares integration's per-pixel geometry passes on the Table 1 frame (issue 25
item 3): ``least_squares._assemble_gauss_newton`` (one Gauss–Newton linearisation) and
``integration._points_normals`` (the final points and normals, also on ``evaluate``'s stepwise
path), each on 1 and 2 numba threads, with the assembly's stages on one thread.

    python benchmarks/bench_geometry_passes.py [--repeat 7] [--save frame.npz]

Inputs as ``profile_least_squares.py`` (Table 1, left camera, Δh = 3 mm, 1920×1200, seed
(600, 960)) at the reconstructed heights. The assembly's work arrays are allocated once and
reused (as ``_gauss_newton`` does: no page faults); the points and normals are timed with fresh
output arrays (as ``_points_and_normals`` returns them: their first touch is part of the cost)
and into preallocated ones. Stages of the assembly, one thread, each over every row: the
geometry pass (``_row_geometry_all``: gathering the rays, then the arithmetic), the two edge
passes (``_row_edges``), the sums and the diagonal (``_row_sums``, ``_row_diagonal``). Best of
``--repeat`` runs, CPU (process) and wall time; the load average and UTC are printed.
``--save`` also writes the frame (o, d, q, valid, seed, z0: the input of
``bench_stepwise_rows.py``).
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from _common import table1_integration_frame


def _best(fn, repeat):
    fn()
    bc = bw = np.inf
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        fn()
        bc, bw = min(bc, time.process_time() - c), min(bw, time.perf_counter() - w)
    return bc, bw


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--save", default="", help="write the frame (o, d, q, valid, seed, z0) to this .npz")
    a = ap.parse_args()
    from pmdsim.evaluation import integration as I
    from pmdsim.evaluation import least_squares as LS

    reg, rec, seed = table1_integration_frame()
    o, d, q, S, z = reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, rec.height_mm
    H, W = S.shape
    if a.save:
        np.savez(a.save, o=o, d=d, q=q, valid=S, seed=np.array(seed), z0=float(z[seed]))
    fields = [np.zeros((H + 2, W + 2)) for _ in range(5)]
    P, N = np.empty(d.shape), np.empty(d.shape)

    @numba.njit(error_model="numpy")
    def geometry(o, d, q, z):
        geo, rays = np.empty((8, W)), np.empty((6, W))
        for v in range(H):
            LS._row_geometry_all(o, d, q, z, v, geo, rays)

    geo = np.stack([np.empty((8, W)), np.empty((8, W))])
    geo[0] = geo[1] = np.random.default_rng(1).random((8, W))

    @numba.njit(error_model="numpy")
    def edges(S, z, geo):
        eh, ev = np.zeros((3, W)), np.zeros((3, W))
        for v in range(H - 1):
            LS._row_edges(S[v], S[v], z[v], z[v], geo[0], geo[0], 1, W - 1, eh)
            LS._row_edges(S[v], S[v + 1], z[v], z[v + 1], geo[0], geo[1], 0, W, ev)

    eh, ev = np.random.default_rng(2).random((2, 3, W))

    @numba.njit(error_model="numpy")
    def sums(eh, ev, D, iD, Ex, Ey, rhs):  # compiled only if called
        for v in range(H - 1):
            Dr, rr = D[v + 1, 1:W + 1], rhs[v + 1, 1:W + 1]
            LS._row_sums(eh, ev, Dr, rr, D[v + 2, 1:W + 1], rhs[v + 2, 1:W + 1], Ex[v + 1, 1:W + 1], Ey[v + 1, 1:W + 1])
            LS._row_diagonal(Dr, rr, iD[v + 1, 1:W + 1])

    rows = []
    for th in (1, 2):
        numba.set_num_threads(th)
        rows.append((f"_assemble_gauss_newton, {th} thread(s)", _best(
            lambda: LS._assemble_gauss_newton(o, d, q, S, z, seed[0], seed[1], *fields), a.repeat)))
        rows.append((f"_points_and_normals (fresh outputs), {th} thread(s)", _best(
            lambda: I._points_and_normals(o, d, q, z), a.repeat)))
        rows.append((f"_points_normals (preallocated outputs), {th} thread(s)", _best(
            lambda: I._points_normals(o, d, q, z, P, N), a.repeat)))
    numba.set_num_threads(1)
    if not hasattr(LS, "_row_sums"):  # a tree before gn25h: the kernels only
        sums = None
    rows.append(("assembly stage: geometry pass (_row_geometry_all), 1 thread", _best(lambda: geometry(o, d, q, z), a.repeat)))
    rows.append(("assembly stage: edge passes (_row_edges ×2), 1 thread", _best(lambda: edges(S, z, geo), a.repeat)))
    if sums is not None:
        rows.append(("assembly stage: sums + diagonal (_row_sums, _row_diagonal), 1 thread",
                     _best(lambda: sums(eh, ev, *fields), a.repeat)))
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    print(f"{os.path.dirname(LS.__file__)}, UTC {time.strftime('%H:%M:%S', time.gmtime())}, load "
          f"{os.getloadavg()[0]:.2f}, {H}×{W} pixels, best of {a.repeat}")
    for name, (cpu, wall) in rows:
        print(f"  {name:72s} {cpu * 1e3:7.1f} ms CPU {wall * 1e3:7.1f} ms wall")


if __name__ == "__main__":
    main()
