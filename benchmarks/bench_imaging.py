"""Benchmark realistic image formation (issue 13): a full 1920×1200 24-image sequence of one
camera with every effect on (12-bit sensor noise, gamma 2.2 display with black level, cos²
emission, 0.27 mm screen pixels with 80 % fill, camera pixel-area integration, f/8 defocus).

Prints: the 1-minute load average before timing, the trace time (with the sample and screen
points the defocus needs), the per-camera precomputation (defocus moments, Jacobian, emission,
black matrix: ``imaging_maps``), the 24-image render time (best of ``--repeat``) — the target is
< 5 s on 2 cores for maps + rendering —, and the decoded fraction of the traced pixels.

    python benchmarks/bench_imaging.py [--repeat 3] [--json]
"""

from __future__ import annotations

import argparse
import os
import time

import numba

from _common import best_of, dump_json, peak_rss_mb
from pmdsim.simulation.imaging import decoder_response
from pmdsim.evaluation.pipeline import decode_images
from pmdsim.setup import default_setup
from pmdsim.simulation.imaging import imaging_maps
from pmdsim.simulation.render import render_images, trace_setup_camera

ALL_EFFECTS = dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=16.0, exposure=0.8,
                   display_gamma=2.2, display_black_level=0.001, emission_exponent=2.0,
                   screen_pixel_pitch_mm=0.27, screen_fill_factor=0.8, pixel_area=True,
                   f_number=8.0, focal_length_mm=25.0, display_levels=256)
#: Each effect alone for ``--per-effect`` (issue 20: the lens with its focal plane, the screen's
#: staircase and display levels included).
PER_EFFECT = {
    "sensor": dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=16.0, exposure=0.8),
    "gamma": dict(display_gamma=2.2, display_black_level=0.001),
    "display_levels": dict(display_levels=256),
    "emission": dict(emission_exponent=2.0),
    "screen_pixels": dict(screen_pixel_pitch_mm=0.27, screen_fill_factor=0.8),
    "pixel_area": dict(pixel_area=True),
    "defocus_f8": dict(f_number=8.0, focal_length_mm=25.0),
    "viewing_angle": dict(display_gamma=2.2, display_black_level=0.001, lcd_mode="ips"),
}
#: Every effect and the LCD's viewing-angle response (``--case all_lcd`` of bench_imaging_series).
ALL_EFFECTS_LCD = dict(ALL_EFFECTS, lcd_mode="ips")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--per-effect", action="store_true", help="also time maps + 24 images per single effect")
    ap.add_argument("--profile", action="store_true",
                    help="every effect: time each period's N images and count the series terms per pixel")
    ap.add_argument("--tolerance", type=float, default=None,
                    help="truncation tolerance of the series in grey levels (default: the renderer's)")
    args = ap.parse_args()
    setup = default_setup().with_bulge(3.0).with_imaging(**ALL_EFFECTS)
    cam = "left"
    # Warm-up (numba compilation / cache load) on a binned copy.
    small = setup.binned(8)
    ms = trace_setup_camera(small, cam, store_points=True)
    for _ in render_images(small, cam, ms):
        pass
    load = os.getloadavg()[0]
    t = time.perf_counter()
    m = trace_setup_camera(setup, cam, store_points=True)
    t_trace = time.perf_counter() - t
    t_maps, _ = best_of(lambda: imaging_maps(setup, cam, m), args.repeat)

    if args.tolerance is not None:  # the renderer's default tolerance, replaced for this run
        import pmdsim.simulation.imaging as imaging_module

        imaging_module.TRUNCATION_TOLERANCE_DN = args.tolerance
        imaging_module.render_period_imaging.__kwdefaults__["tolerance_dn"] = args.tolerance

    def run():
        return [img for _, img in render_images(setup, cam, m)]

    t_all, images = best_of(run, args.repeat)
    stacks = {}
    for (spec, _), img in zip(render_images(setup, cam, m), images):
        stacks.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    dec = decode_images(setup, response=decoder_response(setup), images=stacks)
    res = {
        "load_1min": load,
        "threads": numba.get_num_threads(),
        "n_images": len(images),
        "image_size_px": [images[0].shape[1], images[0].shape[0]],
        "dtype": str(images[0].dtype),
        "trace_s": t_trace,
        "maps_s": t_maps,
        "maps_plus_render_24_s": t_all,
        "render_only_24_s": t_all - t_maps,
        "decoded_fraction": float(dec.valid.sum() / max(m.valid.sum(), 1)),
        "peak_rss_mb": peak_rss_mb(),
    }
    if args.json:
        dump_json(res)
        return
    print(f"load (1 min) before timing: {load:.2f}; numba threads: {res['threads']}")
    print(f"trace with points: {t_trace:.2f} s")
    print(f"imaging maps (defocus, Jacobian, emission, black matrix): {t_maps:.2f} s (best of {args.repeat})")
    print(f"24 images 1920×1200, every effect, maps + render: {t_all:.2f} s (best of {args.repeat}; target < 5 s)")
    print(f"decoded: {100 * res['decoded_fraction']:.1f} % of the traced pixels; peak memory {res['peak_rss_mb']:.0f} MB")
    if args.profile:
        _profile(setup, cam, m)
    if args.per_effect:
        base = default_setup().with_bulge(3.0)
        for name, kw in PER_EFFECT.items():
            s = base.with_imaging(**kw)

            def one(s=s):
                return [img for _, img in render_images(s, cam, m)]

            t1, _ = best_of(one, args.repeat)
            print(f"  {name:<15} maps + 24 images: {t1:.2f} s (load {os.getloadavg()[0]:.2f})")


def _profile(setup, cam, m):
    """Per period of the every-effect sequence: the N images' time and the series terms per pixel."""
    import numpy as np

    from pmdsim.setup.sensor import SensorModel
    from pmdsim.simulation.imaging import render_period_imaging

    maps = imaging_maps(setup, cam, m)
    sensor = SensorModel.from_setup(setup)
    seq = setup.patterns.sequence
    rng = np.random.default_rng(0)
    for d in "xy":
        for p in seq.periods(d):
            counts = np.empty(m.valid.shape, dtype=np.int64)
            t = time.perf_counter()
            render_period_imaging(maps, m.screen_xy_mm, m.valid, d, p, seq, sensor, rng, counts=counts)
            dt = time.perf_counter() - t
            c = counts[m.valid]
            print(f"  period {d} {p:g} mm: {seq.n_shifts} images {dt:.2f} s; series terms per pixel "
                  f"median {np.median(c):.0f}, mean {c.mean():.0f}, max {c.max()} (load {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
