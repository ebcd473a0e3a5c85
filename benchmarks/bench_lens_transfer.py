"""Error of the defocus transfer against a pupil-sampled reference (issue 20).

Table 1 setup (planar sample and screen), camera binned 8 × 8, f/8, 25 mm, the default focal
plane. At a grid of pixels the reference traces 24 × 64 rays through the uniform pupil disc
(Gauss–Legendre in r², equal angles) to the pixel's point on the focal plane, reflects them at the
sample plane and intersects the screen plane (numpy, its own geometry), and averages
exp(2πi·x_q/p): the complex first-harmonic transfer. Compared with (a) the renderer's noise-free
16-bit images decoded (uniform-ellipse transfer 2·J₁(x)/x at the footprint's centroid) and (b) the
Gaussian exp(−2π²σ²/p²) of the same footprint σ (the model before issue 20).

Run: PYTHONPATH=src python benchmarks/bench_lens_transfer.py [camera]
"""

from __future__ import annotations

import sys

import numpy as np

from pmdsim.evaluation.phase import wrapped_phase
from pmdsim.setup import default_setup
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
from pmdsim.simulation.render import trace_setup_camera


def main(cam: str = "left") -> None:
    s = default_setup().binned(8).with_patterns(bit_depth=16).with_imaging(f_number=8.0)
    m = trace_setup_camera(s, cam, store_points=True)
    maps = imaging_maps(s, cam, m)
    cs = s.cameras[cam]
    R, O = cs.T_world_cam.rotation, cs.T_world_cam.translation
    D = s.imaging.focal_length_mm / s.imaging.f_number
    Ts, Tq = s.sample.T_world_sample, s.screen.T_world_screen
    ns, ps0, nq, pq0 = Ts.rotation[:, 2], Ts.translation, Tq.rotation[:, 2], Tq.translation
    P = Ts.apply(m.p_sample_mm)
    d = (P - O) / np.linalg.norm(P - O, axis=-1, keepdims=True)
    F = O + (maps.focus_distance_mm / (d @ R[:, 2]))[..., None] * d
    nr, nphi = 24, 64
    x, w = np.polynomial.legendre.leggauss(nr)
    r = np.repeat(np.sqrt((x + 1) / 2) * D / 2, nphi)
    ph = np.tile(2 * np.pi * (np.arange(nphi) + 0.5) / nphi, nr)
    wts = np.repeat(w / 2 / nphi, nphi)
    A = O + (r * np.cos(ph))[:, None] * R[:, 0] + (r * np.sin(ph))[:, None] * R[:, 1]
    pix = [(v, u) for v in range(3, m.valid.shape[0], 6) for u in range(3, m.valid.shape[1], 6) if m.valid[v, u]]
    hits = []
    for v, u in pix:
        dirs = F[v, u] - A
        X = A + (((ps0 - A) @ ns) / (dirs @ ns))[:, None] * dirs
        rr = dirs - 2 * ((dirs @ ns) / (ns @ ns))[:, None] * ns
        Q = X + (((pq0 - X) @ nq) / (rr @ nq))[:, None] * rr
        hits.append(((Q - pq0) @ Tq.rotation)[:, 0])
    hits = np.array(hits)
    vv, uu = np.array(pix).T
    sensor, seq = SensorModel.from_setup(s), s.patterns.sequence
    sig = np.sqrt(maps.var_xy_mm2[vv, uu, 0])
    chief = m.screen_xy_mm[vv, uu, 0]
    print(f"camera {cam}, f/8, focus distance {maps.focus_distance_mm:.1f} mm, {len(pix)} pixels, "
          f"footprint σ_x {sig.min():.3f}–{sig.max():.3f} mm")
    for p in (2.0, 4.0, 8.0):
        st = render_period_imaging(maps, m.screen_xy_mm, m.valid, "x", p, seq, sensor, None)
        res = wrapped_phase(st, max_value=65535)
        model = (res.modulation * np.exp(1j * res.phase) / (seq.amplitude * 65535))[vv, uu]
        ref = np.exp(2j * np.pi * hits / p) @ wts
        rot = np.exp(-2j * np.pi * chief / p)
        gauss = np.exp(-2 * np.pi**2 * sig**2 / p**2) * np.exp(2j * np.pi * (chief + maps.centroid_xy_mm[vv, uu, 0]) / p)
        e_new, e_old = np.abs(model - ref), np.abs(gauss - ref)
        rev = (ref * rot).real < 0
        print(f"p = {p:g} mm: |T_ref| median {np.median(np.abs(ref)):.3f}; reversed (Re T_ref < 0) on "
              f"{100 * rev.mean():.0f} % of the pixels; |complex error| J1 model median {np.median(e_new):.1e} "
              f"max {e_new.max():.1e}; Gaussian median {np.median(e_old):.3f} p95 {np.percentile(e_old, 95):.3f} "
              f"max {e_old.max():.3f}")


if __name__ == "__main__":
    main(*sys.argv[1:])
