"""The stepwise integration's sampled height σ kernel on a real camera, against its floor (issue 25).

    pmdsim simulate --bulge-mm 3 --out set3
    python benchmarks/bench_uncertainty_stepwise.py set3 [--repeat 3] [--save inputs.npz | --load inputs.npz]

Runs ``pmdsim evaluate``'s path once (in process, without the checks) to capture the kernel's
inputs for the first camera (the linearisation's geometry, wavefronts, A = J·diag(σ), seed, K;
``--save`` keeps them, ``--load`` skips the evaluation), then times the kernel ``--repeat``
times (wall and CPU) and prints its floor on this machine. With ``PYTHONPATH`` pointing at an
older tree the same script times that tree's kernel (``uncertainty._stepwise_sampled``), for an
A/B; ``--compare OTHER.npz`` checks whether two trees' Σ δz² are bit-identical and prints their
largest relative difference (each run writes its result with ``--out``; Σ_k δz_k² is summed on 8
lanes since issue 25's sig25f, ≤ K·ε from the in-order sum of older trees).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import captured_inputs_args

_NAMES = ("geo", "layer", "order", "starts", "pos", "A")


def _kernel():
    from pmdsim.evaluation import uncertainty as U

    try:
        from pmdsim.evaluation.uncertainty_stepwise import stepwise_sampled
        return U, "stepwise_sampled", stepwise_sampled
    except ImportError:  # an older tree
        return U, "_stepwise_sampled", U._stepwise_sampled


def _capture(image_dir) -> dict:
    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import evaluate_image_set

    U, name, fn = _kernel()
    got = {}

    def cap(geo, layer, order, starts, pos, A, seed, K, acc):
        if not got:
            got.update(geo=geo.copy(), layer=layer.copy(), order=order.copy(), starts=starts.copy(), pos=pos.copy(),
                       A=A.copy(), seed=np.int64(seed), K=np.int64(K))
        return fn(geo, layer, order, starts, pos, A, seed, K, acc)

    setattr(U, name, cap)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            evaluate_image_set(image_dir, default_setup(), Path(tmp) / "e", progress=None, consistency=False)
    finally:
        setattr(U, name, fn)
    return got


def main() -> None:
    args, d = captured_inputs_args(__doc__.splitlines()[0], "write Σ δz² (npy) for --compare")
    if d is None:
        d = _capture(args.image_dir)
    if args.save:
        np.savez(args.save, **d)
    _, name, fn = _kernel()
    a = [d[k] for k in _NAMES]
    seed, K = int(d["seed"]), int(d["K"])
    times = []
    acc = None
    for _ in range(args.repeat):
        acc = np.zeros(d["layer"].shape)
        t, c = time.perf_counter(), time.process_time()
        fn(*a, seed, K, acc)
        times.append((time.perf_counter() - t, time.process_time() - c))
    n = int(d["starts"][-1])
    layer = d["layer"]
    P = np.pad(layer, 1, constant_values=-9)
    up = sum((P[1 + dv:P.shape[0] - 1 + dv, 1 + du:P.shape[1] - 1 + du] == layer - 1)
             for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)))
    edges = float(up[layer > 0].mean())
    flops = n * K * (4.0 * edges + 5.0)  # per edge ±vx ± vy − J_a δz_a, +: 4; own: ± ux ± uy, ÷, z², +: 5
    print(f"kernel {name}: {n} pixels, {len(d['starts']) - 1} wavefronts, {edges:.2f} upstream edges per pixel, "
          f"K = {K}; load {os.getloadavg()[0]:.2f}")
    print("  wall / CPU s: " + ", ".join(f"{w:.3f} / {c:.3f}" for w, c in times))
    best = min(c for _, c in times)
    print(f"  floor: {flops / 1e9:.2f} GFLOP at the measured 55–64 GFLOP/s vector peak = "
          f"{flops / 64e9 * 1e3:.0f}–{flops / 55e9 * 1e3:.0f} ms; best CPU {best:.3f} s")
    if args.out:
        np.save(args.out, acc)
    if args.compare:
        other = np.load(args.compare)
        rel = np.abs(acc - other) / np.where(other > 0, other, 1.0)  # Σ δz² on 8 lanes since sig25f: ≤ K·ε apart
        print(f"  bit-identical to {args.compare}: {np.array_equal(other, acc)}; largest relative difference "
              f"{rel.max():.2e}")


if __name__ == "__main__":
    main()
