"""The least-squares integration's solves: DCT- against multigrid-preconditioned CG, and the
least-squares height σ's K right-hand sides (issue 25 item 3, issue 22 "Speed").

    python benchmarks/bench_poisson.py [--samples 64] [--repeat 2] [--skip-sigma]

Table 1, left camera, 1920×1200, Δh = 3 mm (a full frame: every pixel reconstructed). Prints,
A/B interleaved, ``--repeat`` times, with the 1-minute load average:

1. the least-squares reconstruction with its Gauss–Newton solves preconditioned by multigrid
   and by the DCT (wall and CPU time, the largest height difference);
2. one σ-like right-hand side (the divergence of white slope noise) solved to a relative 1e-6
   and 1e-3 by both (time and iterations per right-hand side);
3. the height σ's K sampled right-hand sides: one by one to 1e-6 with multigrid (the code
   before batching) against the batched solves (uncertainty_solve.py), and the largest
   relative σ difference;
4. a DCT pair (forward + inverse, one 1920×1200 field) in float32 and float64, against its
   floors: bytes moved at 15–23 GB/s and flops at 55–64 GFLOP/s (the machine's measured
   bandwidth and one core's FMA peak; see docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import scipy.fft

from pmdsim.evaluation import least_squares as LS
from pmdsim.evaluation import poisson as P
from pmdsim.evaluation import uncertainty as U
from pmdsim.evaluation import uncertainty_solve as US
from pmdsim.evaluation.multigrid import _CGWork, _Multigrid, _pcg
from pmdsim.evaluation.pipeline import decode_simulated, evaluate_decoded
from pmdsim.setup import default_setup
from pmdsim.simulation.render import noise_generator, trace_setup_camera


def _load() -> str:
    return f"load {os.getloadavg()[0]:.1f}"


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w, time.process_time() - c, out


def _force(kind):
    P.DCT_MIN_FILL = 0.999 if kind == "dct" else 2.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--skip-sigma", action="store_true")
    a = ap.parse_args()
    print(f"{_load()} (before)", flush=True)
    s = default_setup().with_bulge(3.0)
    m = trace_setup_camera(s, "left")
    dec = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, "left", stream=1))
    model = s.with_bulge(0.0)
    seed = (600, 960)
    reg, rec = evaluate_decoded(model, "left", dec, method="least_squares", seed_pixel=seed)
    o, d, q, valid = reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid
    H, W = valid.shape
    print(f"1920×1200 frame: {valid.mean():.4f} of the pixels valid, {rec.reconstructed.mean():.4f} reconstructed")

    # 1. the reconstruction
    z = {}
    for r in range(a.repeat):
        for kind in ("multigrid", "dct"):
            _force(kind)
            w, c, rr = _timed(lambda: LS.reconstruct_least_squares(o, d, q, valid, seed, rec.height_mm[seed]))
            z[kind] = rr.height_mm
            print(f"[1] reconstruction, {kind:9s}: {w:.2f} s wall, {c:.2f} s CPU, {rr.iterations} iterations, "
                  f"{_load()}", flush=True)
    print(f"[1] largest height difference: {np.nanmax(np.abs(z['dct'] - z['multigrid'])):.1e} mm")
    _force("dct")

    # 2. one σ-like right-hand side
    lin = U._LinearisedIntegration(o, d, q, rec)
    rng = np.random.default_rng(1)
    g = rng.standard_normal((2, H, W, 2)) * 1e-4
    B = np.zeros((2, H + 2, W + 2))
    B[:, 1:-1, 1:-1] = g[..., 0] - np.roll(g[..., 0], 1, axis=2) + g[..., 1] - np.roll(g[..., 1], 1, axis=1)
    B[:, lin.D == 0] = 0.0
    mg, cgw = _Multigrid(lin.D, lin.iD, lin.Ex, lin.Ey), _CGWork(lin.D.shape)
    lap = P.DCTLaplacian((H, W), rec.seed_pixel, dtype=np.float32)
    dw, unk = P._DCTWork(2, lin.D.shape), lin.D > 0
    for r in range(a.repeat):
        for rtol in (1e-6, 1e-3):
            w, c, out = _timed(lambda: [_pcg(lin.D, lin.iD, lin.Ex, lin.Ey, b, 0.0, rtol, 500, work=cgw, mg=mg)[1]
                                        for b in B])
            print(f"[2] rtol {rtol:g}, multigrid: {w / 2:.3f} s wall, {c / 2:.3f} s CPU per right-hand side, "
                  f"iterations {out}, {_load()}", flush=True)
            w, c, out = _timed(lambda: P.dct_pcg(lin.D, lin.Ex, lin.Ey, B, rec.seed_pixel, 0.0, rtol, 500, lap=lap,
                                                 work=dw, unknown=unk)[1].tolist())
            print(f"[2] rtol {rtol:g}, DCT      : {w / 2:.3f} s wall, {c / 2:.3f} s CPU per right-hand side, "
                  f"iterations {out}, {_load()}", flush=True)

    # 3. the height σ
    if not a.skip_sigma:
        S = rec.reconstructed
        R = (model.sample.T_world_sample.inv() @ model.screen.T_world_screen).rotation
        dq = U._screen_tangents(R, None, dec.screen_xy_mm)
        A, _ = U._jacobian_scaled(o, rec.p_sample_mm, q, dq, S, np.nan_to_num(dec.std_xy_mm))
        K = a.samples

        def one_by_one():  # the code before batching: K multigrid solves to 1e-6
            A0 = np.ascontiguousarray(np.where(S[..., None, None], A, 0.0))
            dg, acc = np.empty(S.shape + (2,)), np.zeros(S.shape)
            for k in range(K):
                U._sample_dg(A0, S, U.DEFAULT_RNG_SEED, k, (K + 31) // 32, dg)
                acc += np.where(S, lin.apply(dg), 0.0) ** 2
            return np.where(S, np.sqrt(acc / K), np.nan)

        sig = {}
        for r in range(max(1, a.repeat - 1)):
            for label, fn in (("one by one, multigrid, 1e-6", one_by_one),
                              ("batched (uncertainty_solve)", lambda: U._sampled_std(lin, A, K, U.DEFAULT_RNG_SEED))):
                w, c, sig[label] = _timed(fn)
                print(f"[3] σ, K = {K}, {label}: {w:.1f} s wall, {c:.1f} s CPU, {_load()}", flush=True)
        a0, b0 = sig.values()
        ok = S & (a0 > 0)
        print(f"[3] σ difference: max {np.max(np.abs(b0[ok] / a0[ok] - 1)):.2e} relative, "
              f"{np.nanmax(np.abs(b0 - a0)) / np.nanmax(a0):.2e} of max σ; solver {US._SigmaSolver(lin).kind}; "
              f"work arrays of a batch: {US.SIGMA_BATCH * (5 * (H + 2) * (W + 2) * 8 + H * W * 4 + (H + 2) * (W + 2) * 8) / 1e6:.0f} MB")

    # 4. a DCT pair and its floors
    f = np.random.default_rng(0).standard_normal((H, W))
    for dt in (np.float32, np.float64):
        x = f.astype(dt)
        best = np.inf
        for _ in range(5):
            t = time.perf_counter()
            y = scipy.fft.dctn(x, type=2, norm="ortho")
            scipy.fft.idctn(y, type=2, norm="ortho", overwrite_x=True)
            best = min(best, time.perf_counter() - t)
        nbytes = 2 * 2 * 2 * x.nbytes  # 2 transforms × 2 axes × (read + write)
        flops = 2 * 2.5 * H * W * np.log2(H * W)  # ≈ 2.5 N log2 N per real transform
        print(f"[4] DCT pair {np.dtype(dt).name}: {best * 1e3:.1f} ms; floors: bytes {nbytes / 23e9 * 1e3:.1f}–"
              f"{nbytes / 15e9 * 1e3:.1f} ms, flops {flops / 64e9 / (2 if dt == np.float32 else 1) * 1e3:.1f}–"
              f"{flops / 55e9 / (2 if dt == np.float32 else 1) * 1e3:.1f} ms, {_load()}")
    print(f"{_load()} (after)")


if __name__ == "__main__":
    main()
