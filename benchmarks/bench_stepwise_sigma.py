"""A stepwise reconstruction's noise σ (heights and slopes) on a real camera, A/B across trees (issue 25).

    pmdsim simulate --bulge-mm 3 --out set3
    python benchmarks/bench_stepwise_sigma.py set3 [--repeat 3] [--save inputs.npz | --load inputs.npz]

Runs ``pmdsim evaluate``'s path once (in process, without the checks) to capture the first
camera's ``surface_uncertainty`` inputs (view rays, screen points, the reconstruction, the
decoder's σ, the screen's rotation; ``--save`` keeps them, ``--load`` skips the evaluation), then
times what ``surface_uncertainty`` does for the noise σ ``--repeat`` times in one process (wall and
CPU; after a warm-up on a 16×16 crop, so the first call touches fresh memory as in ``evaluate``
but loads no kernels): in a tree with
``uncertainty_stepwise_fused`` its one pass, in an older tree the four stages (the
linearisation's geometry and wavefronts, A = J·diag(σ), the sampled recursion). ``--out`` writes
the σ maps, ``--compare OTHER.npz`` checks two trees' maps bit for bit.
"""

from __future__ import annotations

import os
import tempfile
import time
import types
from pathlib import Path

import numpy as np
from _common import captured_inputs_args


def _capture(image_dir) -> dict:
    from pmdsim.evaluation import uncertainty as U
    from pmdsim.setup import default_setup
    from pmdsim.studies import uncertainty_job
    from pmdsim.studies.jobs import evaluate_image_set

    fn = U.surface_uncertainty
    got = {}

    def cap(setup, camera, decoded, reg, rec, **kw):
        if not got and kw.get("screen_model") is None and rec.method == "stepwise":
            T = setup.sample.T_world_sample.inv() @ setup.screen.T_world_screen
            got.update(o=np.asarray(reg.o_ref_mm, float), d=np.asarray(reg.d_ref), q=np.asarray(reg.q_ref_mm),
                       z=np.asarray(rec.height_mm), S=np.asarray(rec.reconstructed), seed=np.asarray(rec.seed_pixel),
                       p=np.asarray(rec.p_sample_mm), std=np.asarray(decoded.std_xy_mm),
                       R=np.asarray(T.rotation, dtype=float), K=np.int64(kw.get("samples", U.DEFAULT_SAMPLES)),
                       rng_seed=np.int64(kw.get("rng_seed", U.DEFAULT_RNG_SEED)))
        return fn(setup, camera, decoded, reg, rec, **kw)

    uncertainty_job.surface_uncertainty = cap
    try:
        with tempfile.TemporaryDirectory() as tmp:
            evaluate_image_set(image_dir, default_setup(), Path(tmp) / "e", progress=None, consistency=False)
    finally:
        uncertainty_job.surface_uncertainty = fn
    return got


def _noise_sigma(d):
    """(h, g) as ``surface_uncertainty`` computes the noise part, in this tree."""
    from pmdsim.evaluation import uncertainty as U

    rec = types.SimpleNamespace(reconstructed=d["S"], seed_pixel=tuple(int(x) for x in d["seed"]), method="stepwise",
                                height_mm=d["z"], p_sample_mm=d["p"])
    dq = np.ascontiguousarray(d["R"][:, :2])
    K, seed = int(d["K"]), int(d["rng_seed"])
    try:
        from pmdsim.evaluation.uncertainty_stepwise_fused import stepwise_noise_sigma
    except ImportError:  # an older tree: the four stages
        lin = U._LinearisedIntegration(d["o"], d["d"], d["q"], rec)
        A, g = U._jacobian_scaled(d["o"], d["p"], d["q"], dq, d["S"], d["std"])
        return U._sampled_std(lin, A, K, seed, overwrite=True), g, "four stages"
    h, g, status = stepwise_noise_sigma(d["o"], d["d"], d["q"], rec, dq, d["std"], K, seed)
    assert status == 0, status
    return h, g, "stepwise_noise_sigma"


def main() -> None:
    args, d = captured_inputs_args(__doc__.splitlines()[0], "write the σ maps (npz) for --compare")
    if d is None:
        d = _capture(args.image_dir)
    if args.save:
        np.savez(args.save, **d)
    sv, su = (int(x) for x in d["seed"])  # warm-up on a 16×16 crop: the kernels loaded from the cache
    crop = {k: (v[sv - 8:sv + 8, su - 8:su + 8] if getattr(v, "ndim", 0) >= 2 and k != "R" else v) for k, v in d.items()}
    _noise_sigma({**crop, "seed": np.array([8, 8])})
    times = []
    h = g = None
    for _ in range(args.repeat):
        t, c = time.perf_counter(), time.process_time()
        h, g, name = _noise_sigma(d)
        times.append((time.perf_counter() - t, time.process_time() - c))
    n = int(np.count_nonzero(d["S"]))
    K = int(d["K"])
    print(f"{name}: {n} pixels, K = {K}; load {os.getloadavg()[0]:.2f}")
    print("  wall / CPU s (first call: fresh memory): " + ", ".join(f"{w:.3f} / {c:.3f}" for w, c in times))
    flops = n * K * 13.0 + n * 120.0  # the recursion (bench_uncertainty_stepwise.py) + geometry and Jacobian
    bytes_ = n * (96 + 32.0)  # d, q, p, z, σ read; σ, slopes' σ, the wavefront index written
    print(f"  floor: {flops / 1e9:.2f} GFLOP at 55–64 GFLOP/s = {flops / 64e9 * 1e3:.0f}–{flops / 55e9 * 1e3:.0f} ms; "
          f"{bytes_ / 1e6:.0f} MB at 15–23 GB/s = {bytes_ / 23e9 * 1e3:.0f}–{bytes_ / 15e9 * 1e3:.0f} ms; the in-order "
          f"Σ_k δz_k² (64 dependent adds per pixel) ≈ {n * K * 4 / 3.0e9 * 1e3:.0f} ms at 3 GHz")
    if args.out:
        np.savez(args.out, h=h, g=g)
    if args.compare:
        other = np.load(args.compare)
        same = np.array_equal(other["h"], h, equal_nan=True) and np.array_equal(other["g"], g, equal_nan=True)
        print(f"  bit-identical to {args.compare}: {same}")


if __name__ == "__main__":
    main()
