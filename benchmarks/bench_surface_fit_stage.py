"""The surface fit and the registration of ``pmdsim evaluate`` alone, per kernel (issue 25, item 1).

Capture the stage's inputs once from a full evaluation (the decoded coordinates of every camera,
the reconstructions and the slopes' σ handed to ``surface_fit_summary``), then time the two
stages on them, as often as wanted, without the rest of the pipeline:

    python benchmarks/bench_surface_fit_stage.py --capture set3 CAPDIR   # evaluates set3 once
    python benchmarks/bench_surface_fit_stage.py --load CAPDIR [--repeat 3]

Prints per repetition the wall and CPU time of ``registration.register`` (all cameras, as
``anchor.register_model`` calls it) and of ``surface_fit_summary``, and the CPU time and calls
of each compiled pass of the summary (``name:calls×ms``), with 4 kB pages as ``evaluate`` runs.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import tempfile
import time
from pathlib import Path


def _capture(image_dir: str, cap: Path) -> None:
    import pmdsim.evaluation.anchor as anchor
    import pmdsim.evaluation.surface_fit as sf
    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import evaluate_image_set

    cap.mkdir(parents=True, exist_ok=True)
    reg, summ = anchor.register_model, sf.surface_fit_summary

    def register_model(model, camera, decoded, **k):
        with open(cap / f"decoded_{camera}.pkl", "wb") as f:
            pickle.dump(decoded, f, protocol=5)
        return reg(model, camera, decoded, **k)

    def surface_fit_summary(recs, camera_z_mm, slope_std=None):
        with open(cap / "summary.pkl", "wb") as f:
            pickle.dump((recs, camera_z_mm, slope_std), f, protocol=5)
        return summ(recs, camera_z_mm, slope_std)

    anchor.register_model, sf.surface_fit_summary = register_model, surface_fit_summary
    with tempfile.TemporaryDirectory() as tmp:
        evaluate_image_set(image_dir, default_setup(), Path(tmp) / "out", progress=None, uncertainty=True)


def _load(cap: Path, repeat: int) -> None:
    import os

    from pmdsim.evaluation import surface_fit as sf
    from pmdsim.evaluation import surface_fit_rows as rows
    from pmdsim.evaluation import surface_fit_select as sel
    from pmdsim.evaluation.anchor import register_model
    from pmdsim.setup import default_setup
    from pmdsim.studies.evaluate_memory import small_pages

    stats: dict = {}

    def wrap(mod, name):
        f = getattr(mod, name, None)
        if f is None:
            return

        def timed(*a, **k):
            t = time.process_time()
            try:
                return f(*a, **k)
            finally:
                s = stats.setdefault(name, [0, 0.0])
                s[0] += 1
                s[1] += time.process_time() - t
        setattr(mod, name, timed)

    for name in ("_collect", "_histogram", "_weighted_sums", "_sample_values", "_max_abs_centred", "_extents", "_sandwich_kernel",
                 "_centre_kernel", "_plane_kernel", "_residual_kernel"):
        wrap(sf, name)
    wrap(sel, "_collect_both")
    for name in ("_slopes_kernel", "_gather_kernel", "_scatter_kernel", "_slopes_rows_kernel"):
        wrap(rows, name)
    for modname, names in (("surface_fit_sums", ("_block_sums",)), ("surface_fit_final", ("_final_kernel",)),
                          ("registration", ("_register_kernel", "_screen_block"))):
        try:  # (not in older trees)
            mod = __import__(f"pmdsim.evaluation.{modname}", fromlist=["_"])
        except ImportError:
            continue
        for name in names:
            wrap(mod, name)
    try:  # (not in older trees)
        from pmdsim.evaluation import surface_fit_window as sw
        wrap(sw, "_take")
        wrap(sw, "_values")
    except ImportError:
        pass
    setup = default_setup()
    decs = {p.stem[len("decoded_"):]: pickle.load(open(p, "rb")) for p in sorted(cap.glob("decoded_*.pkl"))}
    recs, camera_z, slope_std = pickle.load(open(cap / "summary.pkl", "rb"))
    print(f"load {os.getloadavg()[0]:.2f}, {len(decs)} cameras")
    with small_pages():
        for _ in range(repeat):
            t, c = time.perf_counter(), time.process_time()
            regs = [register_model(setup, cam, d) for cam, d in decs.items()]
            tr, cr = time.perf_counter() - t, time.process_time() - c
            del regs
            stats.clear()
            t, c = time.perf_counter(), time.process_time()
            fit, extras = sf.surface_fit_summary(recs, camera_z, slope_std)
            ts, cs = time.perf_counter() - t, time.process_time() - c
            del fit, extras
            print(f"register {tr:.3f} s wall {cr:.3f} CPU | surface_fit_summary {ts:.3f} s wall {cs:.3f} CPU |",
                  " ".join(f"{k}:{v[0]}×{v[1] * 1e3:.0f}" for k, v in sorted(stats.items(), key=lambda kv: -kv[1][1])),
                  flush=True)
    print(f"load {os.getloadavg()[0]:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", nargs=2, metavar=("IMAGE_DIR", "CAPDIR"))
    ap.add_argument("--load", metavar="CAPDIR")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if args.capture:
        _capture(args.capture[0], Path(args.capture[1]))
    elif args.load:
        _load(Path(args.load), args.repeat)
    else:
        ap.error("give --capture IMAGE_DIR CAPDIR or --load CAPDIR")
        sys.exit(2)


if __name__ == "__main__":
    main()
