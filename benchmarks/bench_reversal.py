"""Cost of the decoder's contrast-reversal correction (issue 20) at full resolution.

Table 1's periods (x 720/48/2 mm, y 420/28/2 mm, N = 4) on a 1920 × 1200 camera, 8-bit images
written from the fringe model (I_k = A + T·B·cos(φ − δ_k), rounded) with the finest x and y
fringes reversed (T = −0.1) on the left half of the image, as a defocused f/8 lens does on
most of Table 1's pixels. :func:`decode_screen_coordinates` is timed with and without
``correct_reversal`` (best of ``repeat``); the corrected and flagged pixel counts are printed.

Run: PYTHONPATH=src python benchmarks/bench_reversal.py [repeat]
"""

from __future__ import annotations

import sys

import numpy as np

from _common import best_of, dump_json
from pmdsim.evaluation.phase import decode_screen_coordinates
from pmdsim.setup import default_setup


def _stacks(coord, periods, n, reversed_mask, rng):
    d = 2.0 * np.pi * np.arange(n) / n
    out = []
    for p in periods:
        t = np.where(reversed_mask, -0.1, 1.0) if p == min(periods) else np.ones(coord.shape)
        phi = 2.0 * np.pi * coord / p
        img = 128.0 + 100.0 * t[None] * np.cos(phi[None] - d[:, None, None]) + rng.normal(0, 0.5, (n, *coord.shape))
        out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return out


def main(repeat: int = 3) -> None:
    s = default_setup()
    seq = s.patterns.sequence
    cam = next(iter(s.cameras.values())).camera
    h, w = cam.height_px, cam.width_px
    size = s.screen.size_mm
    v, u = np.mgrid[0:h, 0:w].astype(float)
    x = 50.0 + 600.0 * u / w + 3.0 * v / h
    y = 40.0 + 320.0 * v / h + 2.0 * u / w
    rev = u < w / 2
    rng = np.random.default_rng(0)
    xs = _stacks(x, seq.periods_x_mm, seq.n_shifts, rev, rng)
    ys = _stacks(y, seq.periods_y_mm, seq.n_shifts, rev, rng)
    res = {"image_px": [w, h], "repeat": repeat}
    for on in (False, True):
        def run():
            return decode_screen_coordinates(xs, seq.periods_x_mm, ys, seq.periods_y_mm, size, 255.0,
                                             correct_reversal=on)
        run()  # compile
        t, dec = best_of(run, repeat)
        key = "on" if on else "off"
        res[f"decode_s_{key}"] = round(t, 3)
        res[f"valid_fraction_{key}"] = round(float(dec.valid.mean()), 4)
        res[f"reversed_fraction_{key}"] = round(float(dec.reversed.any(-1).mean()), 4)
        if on:
            ok = dec.valid & rev
            err_mm = np.nanmax(np.abs(dec.screen_xy_mm[ok][:, 0] - x[ok]))
            res["max_abs_error_um_corrected"] = round(float(err_mm) * 1e3, 2)
    res["extra_s"] = round(res["decode_s_on"] - res["decode_s_off"], 3)
    dump_json(res)


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:2]))
