"""The stepwise integration (`reconstruct_stepwise`) on a real camera, against its floor (issue 25).

    pmdsim simulate --bulge-mm 3 --out set3
    python benchmarks/bench_stepwise.py set3 [--repeat 3] [--save inputs.npz | --load inputs.npz]

Runs ``pmdsim evaluate``'s path once (in process, without the checks) to capture the first
camera's first ``reconstruct_stepwise`` call (o, d, q, valid, seed, seed height; ``--save``
keeps them, ``--load`` skips the evaluation), then times ``reconstruct_stepwise`` and its
integration kernel (``stepwise._stepwise_kernel``) ``--repeat`` times (wall and CPU), and
prints the kernel's work (wavefronts, correctors per pixel) and floor. With ``PYTHONPATH``
pointing at another tree the same script times that tree, for an A/B; ``--out`` writes the
heights, ``--compare OTHER.npy`` checks that two trees' heights are bit-identical (NaN where
not reconstructed).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import captured_inputs_args


def _capture(image_dir) -> dict:
    from pmdsim.evaluation import reconstruction
    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import evaluate_image_set

    fn = reconstruction.reconstruct_stepwise
    got = {}

    def cap(o, d, q, valid, seed_pixel=None, seed_height_mm=0.0):
        if not got:
            got.update(o=np.asarray(o, float).copy(), d=np.asarray(d, float).copy(), q=np.asarray(q, float).copy(),
                       valid=np.asarray(valid).copy(), seed=np.asarray(seed_pixel), z0=np.float64(seed_height_mm))
        return fn(o, d, q, valid, seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)

    reconstruction.reconstruct_stepwise = cap
    try:
        with tempfile.TemporaryDirectory() as tmp:
            evaluate_image_set(image_dir, default_setup(), Path(tmp) / "e", progress=None, consistency=False)
    finally:
        reconstruction.reconstruct_stepwise = fn
    return got


def _timed(fn, *a, **k):
    t, c = time.perf_counter(), time.process_time()
    r = fn(*a, **k)
    return r, time.perf_counter() - t, time.process_time() - c


def main() -> None:
    args, d = captured_inputs_args(__doc__.splitlines()[0], "write the heights (npy) for --compare")
    if d is None:
        d = _capture(args.image_dir)
    if args.save:
        np.savez(args.save, **d)
    from pmdsim.evaluation import stepwise as SW

    seed = tuple(int(x) for x in d["seed"])
    z0 = float(d["z0"])
    o, dd, q, valid = SW._check_inputs(d["o"], d["d"], d["q"], d["valid"])
    tol = SW.step_tolerance_mm(o, q, valid)
    full, kern = [], []
    rec = z = None
    for _ in range(args.repeat):
        rec, w, c = _timed(SW.reconstruct_stepwise, d["o"], d["d"], d["q"], d["valid"], seed_pixel=seed,
                           seed_height_mm=z0)
        full.append((w, c))
        (z, done, used, change, n_unconv), w, c = _timed(SW._run_stepwise, o, dd, q, valid, seed, z0, tol=tol)
        kern.append((w, c))
    n = int(np.count_nonzero(rec.reconstructed))
    print(f"reconstruct_stepwise: {n} pixels reconstructed of {int(valid.sum())} valid, largest corrector count "
          f"{rec.iterations}, converged {rec.converged}; load {os.getloadavg()[0]:.2f}")
    print("  reconstruct_stepwise wall / CPU s: " + ", ".join(f"{w:.3f} / {c:.3f}" for w, c in full))
    print("  _run_stepwise (state, kernel, heights) wall / CPU s: " + ", ".join(f"{w:.3f} / {c:.3f}" for w, c in kern))
    # floor: per pixel and corrector (predictor included) one division for t_b, two 1/sqrt and
    # one division for the slopes: 4 divisions + 2 square roots, ≈ 40 other flops; bytes: d, q
    # read once (48 B), the state (32 B) written once and read by ≤ 4 neighbours.
    print(f"  floor: {n} pixels × (48 + 32) B = {n * 80 / 1e6:.0f} MB at 15–23 GB/s = "
          f"{n * 80 / 23e9 * 1e3:.0f}–{n * 80 / 15e9 * 1e3:.0f} ms")
    z = rec.height_mm
    if args.out:
        np.save(args.out, z)
    if args.compare:
        other = np.load(args.compare)
        print(f"  bit-identical to {args.compare}: {np.array_equal(other, z, equal_nan=True)} "
              f"(max |Δz| {np.nanmax(np.abs(other - z)):.3g} mm)")


if __name__ == "__main__":
    main()
