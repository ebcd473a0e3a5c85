"""View rays (distortion inversion) of a full-resolution camera with OpenCV's distortion models
(issue 12), and their accuracy through OpenCV.

For a 1920 × 1200 camera: a Brown model (5 coefficients), a rational + thin-prism model
(12 coefficients), a wide-angle rational model (1280 × 800, fx = 600 px, corners beyond 70°
field angle) and a strong rational model (1280 × 800, fx = 314 px) for which Newton from the
distorted point alone converges for only 39 % of the pixels and the bracketed fallback inverts
the rest: wall time of ``Camera.view_rays`` of every pixel (best of ``--repeat``), the fraction of
pixels inverted, and the largest distance of ``cv2.projectPoints`` of the rays from the pixel
centres (px). Also the time of the fold-over check (``camera_checks.fold_over``, uncached).

    python benchmarks/bench_camera.py [--repeat 3] [--json]
"""

from __future__ import annotations

import argparse
import os
import warnings

import numpy as np

from _common import best_of, dump_json
from pmdsim.geometry.camera import Camera
from pmdsim.geometry.camera_checks import _fold_over_cached

CASES = {
    "brown_5": ([[4400.0, 0, 955.3], [0, 4410.0, 603.7], [0, 0, 1]], [-0.21, 0.13, 1.2e-3, -0.8e-3, 0.04],
                (1920, 1200)),
    "rational_prism_12": ([[4400.0, 0, 955.3], [0, 4410.0, 603.7], [0, 0, 1]],
                          [-0.21, 0.13, 1.2e-3, -0.8e-3, 0.04, 0.05, 0.01, 0.002, 1e-3, -2e-4, -1e-3, 3e-4],
                          (1920, 1200)),
    "wide_rational_8": ([[600.0, 0, 640.3], [0, 601.0, 400.2], [0, 0, 1]],
                        [2.5, 1.0, 1e-4, -2e-4, 0.02, 2.9, 1.8, 0.2], (1280, 800)),
    "strong_rational_12": ([[314.1, 0, 640.3], [0, 314.1, 400.2], [0, 0, 1]],
                           [0.093, 0.099, -0.004, 0.0, -0.218, -0.174, -0.205, -0.208, 0.003, 0.0, -0.004, -0.001],
                           (1280, 800)),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    import cv2

    res = {"load_average": os.getloadavg()[0]}
    for name, (k, d, size) in CASES.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cam = Camera.from_opencv(k, d, size)
        grid = cam.pixel_grid()
        cam.view_rays(grid[:2, :2])  # compile
        t, (rays, ok) = best_of(lambda: cam.view_rays(grid), args.repeat)
        uv, _ = cv2.projectPoints(rays[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.array(k), np.array(d))
        err = float(np.abs(uv.reshape(-1, 2) - grid[ok]).max())
        t_fold, _ = best_of(lambda: _fold_over_cached.__wrapped__(cam, 72, 250), args.repeat)
        res[name] = {"view_rays_s": t, "inverted_fraction": float(ok.mean()), "max_reprojection_px": err,
                     "fold_check_s": t_fold}
    if args.json:
        dump_json(res)
        return
    print(f"load average {res['load_average']:.1f}")
    for name in CASES:
        r = res[name]
        print(f"{name:19s} view_rays {r['view_rays_s']:.3f} s, inverted {100 * r['inverted_fraction']:.2f} %, "
              f"cv2 reprojection ≤ {r['max_reprojection_px']:.1e} px, fold check {1e3 * r['fold_check_s']:.0f} ms")


if __name__ == "__main__":
    main()
