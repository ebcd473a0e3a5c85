"""Rounding as the only noise: why the decoder's σ underestimates it for an even number of shifts.

For the Table 1 setup (ideal camera, ``noise_std = 0``) binned 8×8, left camera: the decoded
screen coordinates against the traced truth, as the RMS of error/σ over the valid pixels (σ the
decoder's ``std_xy_mm``, which assumes independent rounding errors of 1/√12 grey levels per
image), for N = 3, 4, 8, 16 shifts, two mean levels and with 0.5 grey levels of noise.

    cd benchmarks && PYTHONPATH=../src python3 diag_rounding_correlation.py

With the Table 1 mean level 0.5 the offset A = 0.5·(2^b − 1) lies exactly half-way between two
grey levels. For even N, the images k and k + N/2 show A ± x, which round to levels summing to
2A whenever 2A is an integer (A on or half-way between grey levels): their rounding errors are
equal and opposite, and they enter the phase through the difference I_k − I_{k+N/2}, so the
phase error is √2 larger than for independent errors. An offset a quarter grey level off
(2A = 254.5 at 8 bits) does not make them independent either: the pair's errors are then mostly
equal, they cancel in the difference, and the phase error is ≈ 0.7 of the model's. Only noise of
≳ 0.5 grey levels before the rounding (a real sensor's shot noise; here ``noise_std = 0.5``)
dithers the rounding, and then the model holds (N = 3 has no opposite pairs: ≈ 1 throughout).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import pmdsim
from pmdsim.evaluation.pipeline import decode_images
from pmdsim.simulation.render import render_images, trace_setup_camera


def ratio(setup) -> tuple[float, float]:
    m = trace_setup_camera(setup, "left", store_points=True)
    images: dict = {}
    for spec, img in render_images(setup, "left", m):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    dec = decode_images(setup, images)
    ok = dec.valid & np.asarray(m.valid)
    z = (dec.screen_xy_mm[ok] - np.asarray(m.screen_xy_mm)[ok]) / dec.std_xy_mm[ok]
    return tuple(float(np.sqrt(np.mean(z[:, i] ** 2))) for i in range(2))


def main() -> None:
    base = pmdsim.default_setup().binned(8)
    p = base.patterns
    print(f"{'N':>3s} {'mean level':>15s} {'RMS(err/σ) x':>13s} {'RMS(err/σ) y':>13s}")
    for mean_level, noise, label in ((0.5, 0.0, "0.5 (Table 1)"), (127.25 / 255, 0.0, "127.25/255"),
                                     (0.5, 0.5, "0.5, noise 0.5")):
        for n in (3, 4, 8, 16):
            seq = p.sequence
            s = replace(base, patterns=replace(p, noise_std=noise,
                                               sequence=replace(seq, n_shifts=n, mean_level=mean_level)))
            rx, ry = ratio(s)
            print(f"{n:3d} {label:>15s} {rx:13.3f} {ry:13.3f}")


if __name__ == "__main__":
    main()
