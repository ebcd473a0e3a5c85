"""Monte Carlo check and cost of the per-pixel σ of stereo evaluations (issue 22, ``--stereo``).

    python benchmarks/bench_uncertainty_stereo.py --binning 16 --sets 100 [--noise-std 2] [--bins 5]
    python benchmarks/bench_uncertainty_stereo.py --sets 0 --time-binning 1 [--compare-strides 8,16]
    python benchmarks/bench_uncertainty_stereo.py --sets 0 --cli IMAGE_DIR --repeat 2
        [--cli-setup SETUP.toml] [--cli-trees /work/main/src,src] [--cli-keep DIR]

Monte Carlo (``--sets`` > 0): Table 1, both cameras binned ``--binning``×, the patterns'
intensity noise ``--noise-std`` grey levels, ``--sets`` seeded noisy image sets of both cameras,
each decoded with :func:`pmdsim.evaluation.pipeline.decode_simulated` (bit for bit what decoding
the rendered noisy images gives, tests/test_synthetic_decode.py; the in-process equivalent of a
``pmdsim study`` over noise seeds) and evaluated as ``pmdsim evaluate --stereo`` does (the
normal-consistency search for anchors, the anchored integration; nothing held fixed). The
observed per-pixel scatter (sample standard deviation over the sets) of the absolute heights
and of the slopes is compared with the σ predicted from the first set (K = 64 and K = 1024),
per camera in bins of distance from the centroid of the anchors: ratio = sqrt(mean observed
variance / mean predicted variance). The anchors' own σ: the scatter of the anchor height at
pixels that are anchors in every set, against the predicted ``anchor_height_std_um``.

Cost (``--time-binning`` B > 0; B = 1 is full resolution, 1920×1200): one noisy set at binning
B; CPU (process) and wall time of the stereo evaluation (search, integration, report) and of its
σ (K = ``--samples``), default numba threads, and the σ's stages; ``--compare-strides``: the
noise σ on those subgrids against every pixel's (same draws). ``--cli IMAGE_DIR``: ``pmdsim
evaluate IMAGE_DIR --stereo`` with σ and with ``--no-uncertainty``, subprocesses, A/B
interleaved, CPU and wall times; ``--cli-setup FILE`` the evaluation's setup (e.g. one carrying
``[calibration_report]``), ``--cli-trees SRC,SRC`` the same for each source tree in turn (the
children's PYTHONPATH; e.g. main's against a branch), ``--cli-keep DIR`` keeps each tree's
evaluation with σ (to compare the arrays).
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from pmdsim.evaluation.pipeline import decode_simulated
from pmdsim.evaluation.stereo import evaluate_stereo_decoded
from pmdsim.evaluation.uncertainty_stereo import stereo_uncertainty
from pmdsim.setup import default_setup
from pmdsim.simulation.render import noise_generator, trace_setup_camera


def _decode(s, maps, k):
    return {c: decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, c, stream=1000 + k))
            for c, m in maps.items()}


def monte_carlo(a) -> None:
    s = default_setup().binned(a.binning).with_patterns(noise_std=a.noise_std)
    maps = {c: trace_setup_camera(s, c) for c in s.cameras}
    acc = {}
    anchors = {}
    pred = {}
    mask = {}
    t_eval = t_sigma = 0.0
    for k in range(a.sets):
        dec = _decode(s, maps, k)
        t0 = time.perf_counter()
        views, st = evaluate_stereo_decoded(s, dec)
        t_eval += time.perf_counter() - t0
        if k == 0:
            for K in (64, 1024):
                t0 = time.perf_counter()
                pred[K] = stereo_uncertainty(s, views, dec, st, samples=K)
                if K == 64:
                    t_sigma = time.perf_counter() - t0
            first = {c: (c_.anchor_pixels.copy(), c_.anchor_height_mm.mean()) for c, c_ in st.cameras.items()}
        for c, sc in st.cameras.items():
            rec = sc.reconstruction
            S = rec.reconstructed
            mask[c] = S.copy() if k == 0 else mask[c] & S
            z = np.where(S, rec.height_mm * 1e3, 0.0)
            g = np.where(S[..., None], -rec.n_sample[..., :2] / rec.n_sample[..., 2:3] * 1e6, 0.0)
            if c not in acc:
                acc[c] = [np.zeros_like(z), np.zeros_like(z), np.zeros_like(g), np.zeros_like(g)]
            acc[c][0] += z
            acc[c][1] += z * z
            acc[c][2] += g
            acc[c][3] += g * g
            for (v, u), h in zip(map(tuple, sc.anchor_pixels), sc.anchor_height_mm):
                anchors.setdefault(c, {}).setdefault((v, u), []).append(h)
    n = a.sets
    print(f"setup Table 1 binned {a.binning}×, noise σ_I {a.noise_std} grey levels, {n} seeded sets of both "
          f"cameras, stereo (nothing held); numba threads {numba.get_num_threads()}; in the loop: stereo evaluation "
          f"{t_eval / n:.2f} s per set, σ (K = 64) of the first set {t_sigma:.2f} s")
    worst = 0.0
    for c in acc:
        z_var = (acc[c][1] - acc[c][0] ** 2 / n) / (n - 1)
        g_var = (acc[c][3] - acc[c][2] ** 2 / n) / (n - 1)
        vu, _ = first[c]
        cv, cu = vu.mean(axis=0)
        vv, uu = np.indices(mask[c].shape)
        dist = np.hypot(vv - cv, uu - cu)
        use = mask[c]
        edges = np.quantile(dist[use], np.linspace(0, 1, a.bins + 1))
        u64, u1k = pred[64][c][0], pred[1024][c][0]
        print(f"camera {c}: {int(use.sum())} pixels reconstructed in every set, {len(vu)} anchors in the first")
        print("  distance from anchors' centroid (px)   ratio height K=64  K=1024   ratio slope x   slope y   "
              "pred. height σ K=1024 (µm)")
        for i in range(a.bins):
            b = use & (dist >= edges[i]) & (dist <= edges[i + 1] if i == a.bins - 1 else dist < edges[i + 1])
            rh = [float(np.sqrt(z_var[b].mean() / (u.height_std_noise_um[b] ** 2).mean())) for u in (u64, u1k)]
            rg = np.sqrt(g_var[b].mean(axis=0) / (u64.slope_std_noise_urad[b] ** 2).mean(axis=0))
            worst = max(worst, *(abs(r - 1) for r in (*rh, *rg)))
            print(f"  {edges[i]:7.1f} – {edges[i + 1]:7.1f}                       {rh[0]:.3f}      {rh[1]:.3f}      "
                  f"{rg[0]:.3f}      {rg[1]:.3f}     {np.sqrt((u1k.height_std_noise_um[b] ** 2).mean()):.4g}")
        # anchors present in every set: observed scatter against the first set's predicted σ
        pred_a = {tuple(p): sd for p, sd in zip(map(tuple, vu), pred[1024][c][1])}
        obs, prd = [], []
        for p, hs in anchors[c].items():
            if len(hs) == n and p in pred_a:
                obs.append(np.std(hs, ddof=1) * 1e3)
                prd.append(pred_a[p])
        obs, prd = np.array(obs), np.array(prd)
        if obs.size:
            r = np.sqrt(np.mean(obs ** 2) / np.mean(prd ** 2))
            print(f"  anchors in every set: {obs.size}; RMS observed σ {np.sqrt(np.mean(obs ** 2)):.3f} µm, predicted "
                  f"{np.sqrt(np.mean(prd ** 2)):.3f} µm, ratio {r:.3f}; per-anchor ratio median "
                  f"{np.median(obs / prd):.3f}")
    print(f"largest |ratio − 1| over the bins: {worst:.3f}")


class _Stages:
    """CPU (process) and wall seconds spent in named functions of the σ's modules (wrapped)."""

    def __init__(self):
        self.cpu = {}
        self.wall = {}
        self._undo = []

    def wrap(self, module, name, label=None):
        f = getattr(module, name)
        label = label or name

        def timed(*args, **kw):
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                return f(*args, **kw)
            finally:
                self.cpu[label] = self.cpu.get(label, 0.0) + time.process_time() - c0
                self.wall[label] = self.wall.get(label, 0.0) + time.perf_counter() - w0

        setattr(module, name, timed)
        self._undo.append((module, name, f))

    def reset(self):
        self.cpu.clear()
        self.wall.clear()

    def line(self):
        return "; ".join(f"{k} {self.cpu[k]:.2f} s CPU ({self.wall[k]:.2f} s wall)" for k in self.cpu)


def timing(a) -> None:
    from pmdsim.evaluation import uncertainty_stereo as us

    s = default_setup().binned(a.time_binning).with_patterns(noise_std=a.noise_std)
    t0 = time.perf_counter()
    maps = {c: trace_setup_camera(s, c) for c in s.cameras}
    dec = _decode(s, maps, 0)
    shape = next(iter(dec.values())).valid.shape
    print(f"binning {a.time_binning}: {shape[1]}×{shape[0]} px per camera; trace + decode "
          f"{time.perf_counter() - t0:.1f} s; numba threads {numba.get_num_threads()}; load {os.getloadavg()}")
    del maps
    st_ = _Stages()
    from pmdsim.evaluation import uncertainty_stereo_subgrid as sg

    for name in ("_tangents", "_jacobian_scaled", "anchor_noise", "stereo_height_std", "subgrid_noise_std"):
        st_.wrap(us, name)
    st_.wrap(us._AnchoredLinear, "__init__", "linearisation (every pixel)")
    for name in ("jacobian_block_means", "sum_sq", "to_pixels"):
        st_.wrap(sg._SubgridLinear, name, "subgrid " + name)
    for rep in range(a.repeat):
        st_.reset()
        c0, t0 = time.process_time(), time.perf_counter()
        views, st = evaluate_stereo_decoded(s, dec)
        c1, t1 = time.process_time(), time.perf_counter()
        res = stereo_uncertainty(s, views, dec, st, samples=a.samples, noise_stride=a.noise_stride)
        c2, t2 = time.process_time(), time.perf_counter()
        print(f"run {rep}: stereo evaluation (registration, search, integration, report) {c1 - c0:.2f} s CPU "
              f"({t1 - t0:.2f} s wall); σ (K = {a.samples}, both cameras) {c2 - c1:.2f} s CPU ({t2 - t1:.2f} s wall) "
              f"= +{(c2 - c1) / (c1 - c0):.0%} CPU (+{(t2 - t1) / (t1 - t0):.0%} wall); load {os.getloadavg()}")
        print(f"  σ stages: {st_.line()}")
    if a.compare_strides:
        _compare_strides(a, s, views, dec, st, res)


def _compare_strides(a, s, views, dec, st, res) -> None:
    """The noise σ of the subgrid strides against every pixel's (same draws), per camera: RMS and
    largest relative difference of σ, and of its RMS over the field."""
    from pmdsim.evaluation.uncertainty_stereo import stereo_uncertainty as su

    ref = {}
    for stride in [1] + [int(x) for x in a.compare_strides.split(",") if int(x) != 1]:
        c0 = time.process_time()
        r = su(s, views, dec, st, samples=a.compare_samples, noise_stride=stride)
        cpu = time.process_time() - c0
        for c, (u, _) in r.items():
            h = u.height_std_noise_um
            m = np.isfinite(h)
            if stride == 1:
                ref[c] = h
                print(f"stride 1 (every pixel), K = {a.compare_samples}: camera {c}: σ RMS {np.sqrt(np.mean(h[m] ** 2)):.4g} µm, "
                      f"min {h[m].min():.4g}, max {h[m].max():.4g}; {cpu:.2f} s CPU")
                continue
            rel = h[m] / ref[c][m] - 1
            rms = np.sqrt(np.mean(h[m] ** 2)) / np.sqrt(np.mean(ref[c][m] ** 2)) - 1
            print(f"stride {stride}, K = {a.compare_samples}: camera {c}: σ RMS {np.sqrt(np.mean(h[m] ** 2)):.4g} µm "
                  f"({rms:+.2%} against every pixel); per pixel: RMS rel. diff. {np.sqrt(np.mean(rel ** 2)):.2%}, "
                  f"range {rel.min():+.2%} … {rel.max():+.2%}; {cpu:.2f} s CPU")


def cli(a) -> None:
    """``pmdsim evaluate IMAGE_DIR --stereo`` as subprocesses, A/B interleaved: with σ (the
    default), then ``--no-uncertainty``; CPU (the child's user + system) and wall seconds."""
    import resource
    import statistics
    import subprocess
    import sys
    import tempfile

    trees = [p for p in a.cli_trees.split(",") if p] or [os.environ.get("PYTHONPATH", "")]
    times = {(t, k): [] for t in trees for k in ("with σ", "--no-uncertainty")}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.repeat):
            for i, tree in enumerate(trees):
                for label, extra in (("with σ", []), ("--no-uncertainty", ["--no-uncertainty"])):
                    out = os.path.join(tmp, f"ev{r}{i}{len(extra)}")
                    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                    t = time.perf_counter()
                    mode = ([] if a.mono else ["--stereo"]) + (["--setup", a.cli_setup] if a.cli_setup else [])
                    subprocess.run([sys.executable, "-m", "pmdsim", "evaluate", a.cli, *mode, "--out", out, "--quiet",
                                    *extra], check=True, capture_output=True, env={**os.environ, "PYTHONPATH": tree})
                    wall = time.perf_counter() - t
                    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                    cpu = ru1.ru_utime - ru0.ru_utime + ru1.ru_stime - ru0.ru_stime
                    times[tree, label].append(cpu)
                    print(f"run {r}: [{tree}] evaluate{'' if a.mono else ' --stereo'} {label}: {cpu:.1f} s CPU, {wall:.1f} s "
                          f"wall (load {os.getloadavg()[0]:.2f}, {time.strftime('%H:%M:%S', time.gmtime())} UTC)", flush=True)
                    if a.cli_keep and label == "with σ":
                        import shutil
                        shutil.copytree(out, os.path.join(a.cli_keep, f"tree{i}_run{r}"), dirs_exist_ok=True)
    for tree in trees:
        w, wo = statistics.median(times[tree, "with σ"]), statistics.median(times[tree, "--no-uncertainty"])
        print(f"[{tree}] median CPU: with σ {w:.1f} s, without {wo:.1f} s: {100 * (w / wo - 1):+.0f} % (target ≤ +50 %)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--binning", type=int, default=16)
    ap.add_argument("--sets", type=int, default=100)
    ap.add_argument("--noise-std", type=float, default=2.0)
    ap.add_argument("--bins", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="numba threads of the Monte Carlo loop")
    ap.add_argument("--time-binning", type=int, default=0, help="> 0: time the stereo σ at this binning")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--samples", type=int, default=64, help="K of the timed σ")
    ap.add_argument("--noise-stride", type=int, default=None, help="subgrid stride of the timed noise σ (default: "
                    "the library's)")
    ap.add_argument("--compare-strides", default="", help="e.g. 2,4: the noise σ on these subgrids against every "
                    "pixel's (after the timing)")
    ap.add_argument("--compare-samples", type=int, default=64, help="K of --compare-strides")
    ap.add_argument("--cli-setup", default="", metavar="FILE", help="--cli: the evaluation's setup file (default: "
                    "Table 1)")
    ap.add_argument("--cli-trees", default="", metavar="SRC,SRC",
                    help="--cli: A/B source trees (PYTHONPATH of each child, interleaved per run; default: this one)")
    ap.add_argument("--cli-keep", default="", metavar="DIR", help="--cli: keep each tree's evaluations with σ in DIR")
    ap.add_argument("--mono", action="store_true", help="--cli: the mono evaluation (no --stereo)")
    ap.add_argument("--cli", default="", metavar="IMAGE_DIR", help="time `pmdsim evaluate IMAGE_DIR --stereo` with σ "
                    "and with --no-uncertainty (subprocesses, A/B interleaved, --repeat times)")
    a = ap.parse_args()
    print(f"load before: {os.getloadavg()}")
    t0 = time.perf_counter()
    if a.sets > 0:
        n = numba.get_num_threads()
        numba.set_num_threads(min(a.threads, n))
        monte_carlo(a)
        numba.set_num_threads(n)
    if a.time_binning > 0:
        timing(a)
    if a.cli:
        cli(a)
    print(f"{time.perf_counter() - t0:.0f} s; load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
