"""The decode stage of `pmdsim evaluate` alone, on camera "left" of an image set (issue 25, item 1):
reading (``load_camera_stacks`` in the main thread, and with the frames decoded by the background
prefetch of ``pmdsim.io.imageset_prefetch``: the main thread's share) and the fused two-direction
decode (``decode_screen_coordinates``) against its memory floor. Best of 3–7, wall and CPU.

    python benchmarks/bench_imageset_read.py [IMAGE_SET]     # default /tmp/evalx25d/set3
"""
import sys, time, os
import numpy as np
from pmdsim.io.imageset import load_manifest, load_camera_stacks
from pmdsim.evaluation.phase import decode_screen_coordinates
SET = sys.argv[1] if len(sys.argv) > 1 else "/tmp/evalx25d/set3"
m = load_manifest(SET)
def clock(fn, rep=5):
    best = (1e9, 1e9)
    for _ in range(rep):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
    return best, out
(tw, tc), imgs = clock(lambda: load_camera_stacks(m, "left"), 3)
print(f"load_camera_stacks (main thread, Pillow serial): {tw:.3f} s wall {tc:.3f} s CPU")
try:
    from pmdsim.io import imageset_prefetch as pf
    def pre():
        pf.start_prefetch(SET); p = pf._ACTIVE[pf._manifest_key(SET)]
        p.thread.join()  # decoded in the background meanwhile (here: waited for)
        t0, c0 = time.perf_counter(), time.process_time()
        out = load_camera_stacks(m, "left")
        r = time.perf_counter() - t0, time.process_time() - c0
        pf.stop_prefetch()
        return r
    best = min(pre() for _ in range(3))
    print(f"load_camera_stacks with the frames prefetched: {best[0]:.3f} s wall {best[1]:.3f} s CPU (main thread)")
except ImportError:
    pass
args = (list(imgs.x_stacks), list(imgs.x_periods_mm), list(imgs.y_stacks), list(imgs.y_periods_mm), m.screen_size_mm, 255)
decode_screen_coordinates(*args)  # loads/compiles
(tw, tc), dec = clock(lambda: decode_screen_coordinates(*args), 7)
h, w = imgs.shape
n = sum(len(s) for s in imgs.x_stacks + imgs.y_stacks)
traffic = n * h * w * 1 + h * w * (4 * 2 * 8 + 1 + 1 + 2)
print(f"decode_screen_coordinates (fused kernel + argument handling), {n} images {w}x{h}: {tw:.4f} s wall {tc:.4f} s CPU; "
      f"traffic {traffic/1e6:.0f} MB -> floor {traffic/23e9*1e3:.0f}-{traffic/15e9*1e3:.0f} ms at 23-15 GB/s")
