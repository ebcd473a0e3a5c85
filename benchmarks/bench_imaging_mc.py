"""Monte Carlo check of the sensor noise model through the reconstruction (issue 13).

Height and slope scatter from a Monte Carlo over seeds (12-bit sensor: shot and read noise;
render → decode → reconstruct with perfect setup knowledge) against the decoder's predicted σ
propagated through the same reconstruction (Gaussian screen-coordinate errors of the predicted
per-pixel σ added to the true mapping, then reconstructed). Prints the ratio
√(mean variance, images / mean variance, prediction) over the field of view for the heights and
the normals' x and y components, with a bootstrap standard error over the draws.

    python benchmarks/bench_imaging_mc.py [--draws 100] [--downsample 8]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numpy as np

from pmdsim.simulation.imaging import decoder_response
from pmdsim.evaluation.pipeline import decode_images, evaluate_decoded
from pmdsim.setup import default_setup
from pmdsim.simulation.render import render_images, trace_setup_camera

SENSOR = dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=16.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--downsample", type=int, default=8)
    args = ap.parse_args()
    cam = "left"
    s = default_setup().binned(args.downsample).with_bulge(3.0).with_imaging(**SENSOR)
    m = trace_setup_camera(s, cam, store_points=True)
    c = s.cameras[cam].camera
    seed_px = (c.height_px // 2, c.width_px // 2)
    seed_h = float(m.p_sample_mm[seed_px][2])
    load = os.getloadavg()[0]
    t0 = time.perf_counter()

    def reconstruct(dec):
        _, rec = evaluate_decoded(s, cam, dec, screen_model=s.screen.surface, seed_pixel=seed_px, seed_height_mm=seed_h)
        return np.where(rec.reconstructed, rec.height_mm, np.nan), rec.n_sample

    img_h, img_n, dec0 = [], [], None
    for k in range(args.draws):
        sk = s.with_patterns(seed=k)
        stacks = {}
        for spec, im in render_images(sk, cam, m):
            stacks.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(im)
        dec = decode_images(sk, response=decoder_response(sk), images=stacks)
        dec0 = dec if dec0 is None else dec0
        h, n = reconstruct(dec)
        img_h.append(h)
        img_n.append(n)
    rng = np.random.default_rng(12345)
    sig = np.where(np.isfinite(dec0.std_xy_mm), dec0.std_xy_mm, 0.0)
    pred_h, pred_n = [], []
    for k in range(args.draws):
        xy = m.screen_xy_mm + rng.standard_normal(sig.shape) * sig
        h, n = reconstruct(replace(dec0, screen_xy_mm=np.where(dec0.valid[..., None], xy, np.nan)))
        pred_h.append(h)
        pred_n.append(n)
    fields = {"height": (np.array(img_h), np.array(pred_h)),
              "normal_x": (np.array(img_n)[..., 0], np.array(pred_n)[..., 0]),
              "normal_y": (np.array(img_n)[..., 1], np.array(pred_n)[..., 1])}
    print(f"{args.draws} draws each, downsample {args.downsample} ({c.width_px}×{c.height_px} px), camera {cam}; "
          f"load before {load:.2f}; draws took {time.perf_counter() - t0:.0f} s")
    boot = np.random.default_rng(7)
    for name, (a, b) in fields.items():
        ok = np.isfinite(a).all(0) & np.isfinite(b).all(0)
        ok[seed_px] = False

        def ratio(ia, ib):
            return np.sqrt(np.mean(a[ia][:, ok].var(0, ddof=1)) / np.mean(b[ib][:, ok].var(0, ddof=1)))

        r = ratio(slice(None), slice(None))
        bs = [ratio(boot.integers(0, len(a), len(a)), boot.integers(0, len(b), len(b))) for _ in range(200)]
        scale, unit = (1e3, "µm") if name == "height" else (1e6, "µrad")
        rms_img = np.sqrt(np.mean(a[:, ok].var(0, ddof=1))) * scale
        print(f"{name:9s}: scatter RMS {rms_img:.4f} {unit}; images / prediction = {r:.4f} ± {np.std(bs):.4f} "
              f"(bootstrap SE, {ok.sum()} pixels)")


if __name__ == "__main__":
    main()
