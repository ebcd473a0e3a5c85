"""Interleaved A/B of the tracer's cover-glass pass in one process: glass-free trace ("none"), the
previous second pass through CoverGlass.trace ("old", trace._refract_through_glass) and the fused kernel
("new", simulation.glass_trace.refract_traced); Table 1 left camera, 3 mm glass, flat and Δh = 3 mm.

    python benchmarks/bench_glass_pass.py
"""
import os, time
import numpy as np
import pmdsim.simulation.glass_trace as gt
from pmdsim.simulation import trace as tr
from pmdsim.geometry.cover_glass import CoverGlass
from pmdsim.setup import default_setup

new = gt.refract_traced
def old(glass, screen, T, p_s, q_p, screen_xy, status, codes, tol):
    tr._refract_through_glass(glass, screen, T, p_s, q_p, screen_xy, status, tol)

for b in (0.0, 3.0):
    s = default_setup().with_bulge(b); cam = s.cameras["left"]; rays = cam.camera.sensor_rays()
    def run(glass):
        return tr.trace_camera(cam.camera, cam.T_world_cam, s.sample.T_world_sample, s.sample.surface,
                               s.screen.T_world_screen, s.screen.surface, rays=rays, glass=glass)
    g = CoverGlass(3.0, 1.52)
    res = {"none": [], "old": [], "new": []}
    for impl in (old, new):
        gt.refract_traced = impl; run(g)
    run(None)
    for _ in range(5):
        for k in ("none", "old", "new"):
            if k != "none":
                gt.refract_traced = old if k == "old" else new
            t0 = time.perf_counter(); run(None if k == "none" else g); res[k].append(time.perf_counter() - t0)
    print(f"bulge {b}: " + ", ".join(f"{k} best {min(v)*1e3:.1f} ms median {np.median(v)*1e3:.1f} ms" for k, v in res.items())
          + f"; load {os.getloadavg()[0]:.1f}")
