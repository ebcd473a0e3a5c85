"""Cost of the consistency checks against the decoding, one camera of the Table 1 setup binned ×4
(480×300 px, 24 images):  nice python benchmarks/bench_consistency_time.py  (the second run of
each is the figure: the first compiles)."""
import time, numpy as np
from pmdsim.evaluation.consistency import check_consistency, nominal_screen_xy
from pmdsim.io.imageset import camera_images_from_arrays, decode_camera_images
from pmdsim.setup import default_setup
from pmdsim.simulation.render import render_images, trace_setup_camera
setup = default_setup().binned(4).with_patterns(noise_std=1.0)
cam = "left"; cs = setup.cameras[cam]
m = trace_setup_camera(setup, cam)
specs, imgs = zip(*render_images(setup, cam, m))
im = camera_images_from_arrays([s.as_manifest_entry() for s in specs], imgs)
for i in range(2):
    t=time.perf_counter(); dec = decode_camera_images(im, setup.screen.size_mm); t1=time.perf_counter()
    exp = nominal_screen_xy(cs.camera, cs.T_world_cam, setup.sample.T_world_sample, setup.screen.T_world_screen); t2=time.perf_counter()
    c = check_consistency(im.x_stacks, im.x_periods_mm, im.y_stacks, im.y_periods_mm, dec, setup.screen.size_mm, expected_xy_mm=exp); t3=time.perf_counter()
    print(f"decode {t1-t:.2f}s nominal {t2-t1:.2f}s check {t3-t2:.2f}s flags {np.count_nonzero(c.flags)}")
