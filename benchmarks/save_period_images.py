"""Save (or compare) the finest-x-period images of one bench_imaging case, for identity checks
between source trees:

    PYTHONPATH=<tree A>/src python save_period_images.py --case display_levels --out a.npz
    PYTHONPATH=<tree B>/src python save_period_images.py --case display_levels --out b.npz
    python save_period_images.py --compare a.npz b.npz

Renders Table 1's left camera (Δh = 3 mm) at ``--downsample`` (default 1: full resolution) with
``imaging_maps`` + ``render_period_imaging`` (the means before noise and rounding kept); the
comparison prints the share of samples that differ and the largest and RMS differences in DN.
"""

from __future__ import annotations

import argparse
import collections

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="display_levels")
    ap.add_argument("--downsample", type=int, default=1)
    ap.add_argument("--out")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    args = ap.parse_args()
    if args.compare:
        a, b = (np.load(f) for f in args.compare)
        v = a["valid"]
        d = a["img"][:, v].astype(int) - b["img"][:, v].astype(int)
        dm = a["means"][:, v] - b["means"][:, v]
        print(f"{d.size} samples: {np.mean(d != 0):.4%} differ, counts {dict(collections.Counter(d.ravel().tolist()))}; "
              f"means: max |Δ| {np.abs(dm).max():.3f} DN, RMS {np.sqrt(np.mean(dm**2)):.3f} DN")
        return
    from bench_imaging import ALL_EFFECTS, PER_EFFECT

    from pmdsim.setup import default_setup
    from pmdsim.setup.sensor import SensorModel
    from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
    from pmdsim.simulation.render import trace_setup_camera

    kw = ALL_EFFECTS if args.case == "all" else PER_EFFECT[args.case]
    s = default_setup().with_bulge(3.0).with_imaging(**kw)
    if args.downsample > 1:
        s = s.binned(args.downsample)
    m = trace_setup_camera(s, "left", store_points=True)
    maps = imaging_maps(s, "left", m)
    seq = s.patterns.sequence
    p = min(seq.periods("x"))
    means = np.empty((seq.n_shifts,) + m.valid.shape)
    img = render_period_imaging(maps, m.screen_xy_mm, m.valid, "x", p, seq, SensorModel.from_setup(s),
                                np.random.default_rng(0), means=means)
    np.savez(args.out, img=img, means=means, valid=m.valid)


if __name__ == "__main__":
    main()
