"""The five kernels of issue 25 item 3 against their floors on this machine (Table 1, 1920×1200).

    python benchmarks/bench_kernel_floors.py [--repeat 5] [--cache OBS.npz] [--json]

Table 1, left camera, Δh = 3 mm, built once (trace, the 24 images, decoding, registration;
the calibration's 16 poses × 2 cameras simulated, or read from ``--cache``, as
``bench_calibration_solve.py`` does). Each kernel is timed alone, best of ``--repeat`` (≥ 5),
wall and CPU (process) time, with 1 and 2 numba threads (the two vCPUs of this machine share
one core's vector units, so the floor is one core's):

1. view rays — ``Camera._rays(None)``, the one-pass kernel behind ``Camera.sensor_rays`` (whose
   result is cached per camera model): the Table 1 camera (no distortion) and a Brown
   5-coefficient 1920×1200 camera (``bench_camera.py``'s ``brown_5``, distortion inverted by
   Newton's method to 1e-12, in lock-step over blocks of 32 pixels, ``camera._newton_lanes``);
2. the tracer — ``trace_camera`` of the Table 1 camera, glass-free (``bench_trace.py``);
3. the decoder — ``decode_images`` of the 24 images (the per-image lists, both directions in one
   pass over image rows), and ``decode_screen_coordinates`` on stacks built beforehand;
4. integration — ``reconstruct_least_squares`` of the registered frame (DCT-preconditioned CG
   on a full frame, coarse-to-fine start), as ``bench_poisson.py`` [1];
5. the calibration's JᵀJ — ``solver._evaluate(..., want_normal=True)``: model rows, analytic
   Jacobian and the [J r]ᵀ[J r] accumulation (``kernel._chunks_kernel``) over all
   correspondences, at the perturbed start state of ``bench_calibration_solve.py``.

The floors are measured in the same process: memory bandwidth (best of a 268 MB ``sum`` and
``copyto``), the vector peak (float64 matrix product, 2n³ flops), and the vector division rate
(the faster of a numba loop of independent divisions and numpy's SIMD ``np.divide``, in L1/L2).
Per kernel the script counts the bytes it must move (inputs read once + outputs written once; no
temporaries), the flops it must do (counted from the kernel's arithmetic, comments per term
below) and its divisions and square roots; the floor is the largest of bytes/bandwidth,
flops/peak and divisions/division rate. It prints one table: kernel, the three floors, the
floor, the times (1 and 2 threads, wall and CPU), the ratio and whether it is within 3×. The
verdict is the best wall time (1 or 2 threads) against the floor at the rates measured by wall
time; beside it, one thread's CPU time against the floor at the rates measured by CPU time
(steadier on a loaded machine, where wall times stretch by the share of the core other jobs
take). The floor is one core's: the two vCPUs share one core's vector units (the matrix product
is no faster on two threads), but a latency-bound kernel gains up to 2× from the second hardware
thread. OpenBLAS runs on one thread (``OPENBLAS_NUM_THREADS=1`` unless set), so the matrix
product is one core's peak.
Takes ≈ 30 s with the calibration observations cached and a warm numba cache, ≈ 1.5 min without.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the peak of one core: set before numpy loads

import argparse
import sys
import time

import numba
import numpy as np

from _common import best_wall_cpu, dump_json, rendered_images
from pmdsim.geometry.camera import UNDISTORT_TOL, _UNDISTORT_MAX_ITER, Camera, _distort, _distort_jac, _unpack
from bench_calibration_solve import _observations
from bench_camera import CASES

SIZE = (1200, 1920)  # (H, W) of Table 1


def _timed(fn, repeat: int, threads: int) -> dict:
    """Best wall and least CPU (process) time of ``repeat`` calls of ``fn`` with ``threads``
    numba threads (one warm-up call first)."""
    numba.set_num_threads(threads)
    fn()
    wall, cpu = best_wall_cpu(fn, repeat)
    return {"wall_s": wall, "cpu_s": cpu}


# ------------------------------------------------------------------ the machine's rates
@numba.njit(cache=True)
def _division_loop(a, b, acc, reps):
    """``acc[i] += a[i] / b[i]``, ``reps`` times: independent divisions (vectorised), in L1."""
    for _ in range(reps):
        for i in range(a.shape[0]):
            acc[i] += a[i] / b[i]


def machine_rates() -> dict:
    """Memory bandwidth (B/s), float64 vector peak (flop/s) and vector division rate (1/s),
    one thread, each the best of several runs by CPU time (on a loaded machine the CPU time is
    the steadier figure; the kernels' ratios use their one-thread CPU time alike), and by wall
    time (``*_wall``)."""
    nbytes = (1 << 25) * 8
    a = np.ones(1 << 25)  # 268 MB: far beyond the caches
    b = np.empty_like(a)
    t_sum = best_wall_cpu(lambda: a.sum(), 5)[::-1]  # (CPU, wall)
    t_copy = best_wall_cpu(lambda: np.copyto(b, a), 5)[::-1]
    del a, b
    n = 2000
    x = np.random.default_rng(0).standard_normal((n, n))
    t_mm = best_wall_cpu(lambda: x @ x, 3)[::-1]
    da, db, acc = np.full(512, 3.0), np.full(512, 7.0), np.zeros(512)
    reps = 20000
    _division_loop(da, db, acc, 1)
    t_div = best_wall_cpu(lambda: _division_loop(da, db, acc, reps), 3)[::-1]
    # numpy's SIMD division (2048 elements, in L1/L2): faster than numba's loop on this machine
    na, nb, nc = np.full(2048, 3.0), np.full(2048, 7.0), np.empty(2048)
    t_np = best_wall_cpu(lambda: [np.divide(na, nb, out=nc) for _ in range(reps // 4)], 3)[::-1]
    out = {}
    for i, key in enumerate(("", "_wall")):  # CPU time, then wall time
        out["read_bw" + key] = nbytes / t_sum[i]
        out["copy_bw" + key] = 2 * nbytes / t_copy[i]  # read + write (streaming stores: no write-allocate read)
        out["bandwidth" + key] = max(out["read_bw" + key], out["copy_bw" + key])
        out["peak_flops" + key] = 2.0 * n ** 3 / t_mm[i]
        out["div_rate" + key] = max(512.0 * reps / t_div[i], 2048.0 * (reps // 4) / t_np[i])
    return out


# ------------------------------------------------------------------ work counts
def view_rays_counts(n_pixels: int, newton_iterations: int) -> dict:
    """Bytes, flops, divisions + square roots of ``Camera._rays(None)`` (``_rays_kernel``).

    Bytes: it reads nothing per pixel (the pixel centre comes from the index) and writes
    d (N, 3) float64 and ok (N,) bool: 25 B per pixel.
    Flops (Brown model, as in camera.py; ``newton_iterations`` summed over the pixels, 0 for a
    camera without distortion; the lock-step blocks of ``camera._newton_lanes`` do 0.13 % more
    lane iterations for the Brown camera, not counted: the floor is the pixels' own work):
      normalise (u − ppx)/fx, (v − ppy)/fy        2 flops + 2 divisions per pixel
      with distortion, per pixel once:
        _distort at the start (r² 3, radial 6, x_d 10, y_d 10) + residual 2      31
        _physical at the end: _distort_jac 44 + det 3, num/den 1 division        47 + 1 div
      per Newton iteration:
        _distort_jac: r² 3, num 6, dnum 6, a 10, b 9, d 10                         44
        det 3, dx 3, dy 3 + 2 divisions, update 2                                  11 + 2 div
        _distort 29, residual 2                                                    31
    """
    distorted = newton_iterations > 0
    flops = 2 * n_pixels + (78 * n_pixels + 86 * newton_iterations if distorted else 0)
    divs = 2 * n_pixels + ((1 * n_pixels + 2 * newton_iterations) if distorted else 0)
    return {"bytes": 25 * n_pixels, "flops": flops, "divs": divs}


def tracer_counts(n_rays: int, n_hit: int) -> dict:
    """Bytes, flops, divisions of the glass-free trace (``trace._trace_run`` / ``trace_rows``)
    with both surfaces bicubic patches (Table 1: sample and screen are SplineSurfaces), one
    warm-started Newton step per surface (the fast path; fallbacks are extra work).

    Bytes: reads d_cam (N, 3) float64 + ok (N,) bool, writes screen_xy (N, 2) float64 +
    status (N,) uint8: 42 B per ray.
    Flops per ray reaching the screen (``n_hit``; the others count only the rotation, 15):
      warm start 2·z₁ − z₂ for sample and screen                                 4
      direction into the sample frame (3 × (3 mul + 2 add))                      15
      intersect_kernel set-up: b_x, b_y 2, a_x, a_y 4, w2 2, m2, c3 2; 1/d_z      10 + 1 div
      spline_eval2 (r₀…r₃ 24, d₀…d₃ 24, e₀…e₃ 16, h, h_x, h_y, h_xx, h_xy 30,
        h_yy 4, s_x, s_y 2)                                                      100
      _newton_step: point 4, h_z 3, 1 − h_z 1, step 1 + 1 div, z 1, test 3,
        new point 4; with the gradient (sample): c3·s² 2, h_x, h_y carried 10    17 (+12) + 1 div
      _finish: t = (z − o_z)/d_z                                                 2
        → sample 141 + 2 div, screen 129 + 2 div
      grazing test: v·n 4, vn·v_z 1, vn² 1, |v|² 5, |n|² 4, products 2           17
      reflection: f = 2(v·n)/(n·n) 9 + 1 div, r 4, negations 2                   15 + 1 div
      into the screen frame: origin 3 × 6, direction 3 × 5                        33
    """
    per_hit = 4 + 15 + 141 + 17 + 15 + 33 + 129
    return {"bytes": 42 * n_rays, "flops": per_hit * n_hit + 15 * (n_rays - n_hit), "divs": 5 * n_hit}


def decoder_counts(n_pixels: int, n_images: int, image_itemsize: int, n_levels: int) -> dict:
    """Bytes, flops, divisions + square roots of decoding ``n_images`` images in ``n_levels``
    periods (both directions; ``decoding_fused._fused_kernel``).

    Bytes: the images read once (n_images × itemsize per pixel) and the outputs written once:
    screen_xy, std_xy, modulation, offset (H, W, 2) float64 (64 B), flags uint8 and valid
    bool (2 B), reversed (H, W, 2) bool (2 B): 68 B per pixel.
    Flops per pixel:
      per image: A, B cos φ, B sin φ (3 multiply-adds) + the maximum                 7
      per level: B = √(c² + s²) 3 + 1 sqrt; _phase_0_2pi: comparisons 2, num/den 2,
        z 1, p 8, q 10, z·p/q 2, t 3, quadrant 2 = 30 + 1 div; quality 1; unwrapping
        (_refine_reversal: fine 2, c_k 5, test 2, reversal test 3) 12; contrast B/A
        1 div                                                                      46 + 3 (div, sqrt)
      last level per direction: σ = scale·σ_I/B 1 + 1 div                            1 + 1 div
    """
    flops = n_pixels * (7 * n_images + 46 * n_levels + 2)
    divs = n_pixels * (3 * n_levels + 2)
    return {"bytes": n_pixels * (n_images * image_itemsize + 68), "flops": flops, "divs": divs}


def integration_counts(n_pixels: int) -> dict:
    """Bytes, flops, divisions + square roots of the least-squares integration's floor: the
    data read once, one Gauss–Newton linearisation, one Poisson solve by a DCT pair (the
    fast solver the issue names), the outputs written once. (The algorithm does more: a
    coarse-to-fine start and ≥ 2 linearisations with several CG iterations each; see the
    docs.)

    Bytes: reads d, q (H, W, 3) float64 (48 B) + valid (1 B); writes height (8 B), p_sample
    and n_sample (H, W, 3) float64 (48 B), reconstructed (1 B): 106 B per pixel.
    Flops per pixel:
      _row_geometry: 1/d_z 1 div, e 2, point 5, a 3, |a| 5 + sqrt + div, â 3, b 3,
        |b| 5 + sqrt + div, b̂ 3, m 3, â·e, b̂·e 8, dm 24, 1/m_z 1 div, g 2, dg/dz 8   74 + 6 (div, sqrt)
      _edge × 2 edges (G 4, Δxy 2, residual 5, J_a 8, J_b 8) + normal equations 8 × 2  70
      DCT pair in float64: 2 transforms × 2.5 log₂N                                   5 log₂N
      points and normals out (_points_normals: point 6, â, b̂ 22 + 2 sqrt + 2 div,
        normal 3 + 5 + sqrt + div)                                                  36 + 6 (div, sqrt)
    """
    flops = n_pixels * (74 + 70 + 36 + 5.0 * np.log2(n_pixels))
    return {"bytes": 106 * n_pixels, "flops": flops, "divs": 12 * n_pixels}


def jtj_counts(n_corr: int, n_columns: int) -> dict:
    """Bytes, flops, divisions of the calibration's JᵀJ and Jᵀr (``kernel._chunk_run`` →
    ``batch_rows._batched_normal``: the rows vectorised across correspondences) over
    ``n_corr`` correspondences with ``n_columns`` parameter columns per block (17 for the
    planar screen: model.py's _NB, 14 camera + 3 mirror parameters).

    Bytes: reads uv (N, 2) and q (N, 3) float64: 40 B per correspondence (the (C, C) block
    sums are negligible).
    Flops per correspondence (_model_row with its Jacobian):
      mirroring s 6, w 12; p = Rᵀw 15; 1/p_z 1 div; x, y 2; r² 3, radial 6,
        x_d, y_d 20; residual 4                                                     68 + 1 div
      Jacobian: intrinsic columns 24, d(x_d, y_d)/d(x, y) 35, G 18, H = G Rᵀ 30,
        rotation 18, mirror 58, screen point 18                                      201
      unit scaling 2 × 17                                                             34
      [J r]ᵀ[J r]: the upper triangle of (C + 1)² entries, 2 rows × 1 multiply-add
        each: 2·2·(C + 1)(C + 2)/2                                                   2(C + 1)(C + 2)
    """
    c = n_columns
    per = 68 + 201 + 34 + 2 * (c + 1) * (c + 2)
    return {"bytes": 40 * n_corr, "flops": per * n_corr, "divs": n_corr}


# ------------------------------------------------------------------ inputs
@numba.njit(cache=True)
def _count_newton(w, h, fx, fy, ppx, ppy, coeffs, tol, max_iter):
    """Sum over the pixels of the iterations of ``camera._newton`` from (x_d, y_d) (the
    undamped first attempt of ``_undistort_one``, the same arithmetic), and the number of
    pixels where it does not converge (they take the damped fallback: more work)."""
    c, rational, prism = _unpack(coeffs)
    total = 0
    failed = 0
    for i in range(w * h):
        xd = (float(i % w) - ppx) / fx
        yd = (float(i // w) - ppy) / fy
        x = xd
        y = yd
        fx_, fy_ = _distort(x, y, c, rational, prism)
        rx = fx_ - xd
        ry = fy_ - yd
        ok = False
        for _ in range(max_iter):
            total += 1
            a, b, cc, d, _n, _d = _distort_jac(x, y, c, rational, prism)
            det = a * d - b * cc
            if det == 0.0 or not np.isfinite(det):
                break
            dx = (d * rx - b * ry) / det
            dy = (-cc * rx + a * ry) / det
            x -= dx
            y -= dy
            if abs(dx) <= tol and abs(dy) <= tol:
                ok = True
                break
            fx_, fy_ = _distort(x, y, c, rational, prism)
            rx = fx_ - xd
            ry = fy_ - yd
        if not ok:
            failed += 1
    return total, failed


def newton_iterations(cam: Camera) -> tuple[int, int]:
    """(total Newton iterations, pixels not converged) of ``cam``'s view rays (0, 0 without
    distortion: the kernel skips the inversion)."""
    if not np.any(cam._coefficients()):
        return 0, 0
    return _count_newton(cam.width_px, cam.height_px, cam.fx_px, cam.fy_px, cam.ppx_px, cam.ppy_px,
                         cam._coefficients(), UNDISTORT_TOL, _UNDISTORT_MAX_ITER)


def build_inputs(cache: str) -> dict:
    """Table 1 (Δh = 3 mm, left camera): cameras, rays, mapping, images, decoded coordinates,
    registration; the calibration's packed data and start state."""
    import warnings

    from pmdsim.calibration import nominal_state, perturbed_state
    from pmdsim.calibration.model import MIN_CORRESPONDENCES
    from pmdsim.calibration.solver import _pack
    from pmdsim.evaluation import decode_images, evaluate_decoded
    from pmdsim.setup import default_setup
    from pmdsim.simulation import trace_setup_camera
    from pmdsim.studies import INITIAL_ERRORS

    s = default_setup().with_bulge(3.0)
    cs = s.cameras["left"]
    k, dist, size = CASES["brown_5"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        brown = Camera.from_opencv(k, dist, size)
    m = trace_setup_camera(s, "left", store_points=True)
    images = rendered_images(s, "left", m)
    dec = decode_images(s, images)
    seed = (600, 960)
    reg, rec = evaluate_decoded(s.with_bulge(0.0), "left", dec, method="least_squares", seed_pixel=seed)
    obs = _observations(cache, 3.0)
    poses = [T for _, T in s.calibration.mirror_poses(s.sample)]
    start = perturbed_state(nominal_state(s.with_bulge(0.0), poses), np.random.default_rng(0), **INITIAL_ERRORS)
    data = _pack(obs, start, MIN_CORRESPONDENCES)
    return {"setup": s, "cs": cs, "brown": brown, "rays": cs.camera.sensor_rays(), "mapping": m,
            "images": images, "decoded": dec, "seed": seed, "reg": reg, "z_seed": float(rec.height_mm[seed]),
            "data": data, "start": start}


# ------------------------------------------------------------------ the kernels
def kernels(inp: dict) -> list[tuple[str, object, dict]]:
    """(name, call, counts) of every kernel timed."""
    from pmdsim.calibration.model import _NB
    from pmdsim.calibration.solver import _evaluate
    from pmdsim.evaluation.decoding import decode_screen_coordinates
    from pmdsim.evaluation.least_squares import reconstruct_least_squares
    from pmdsim.evaluation.pipeline import decode_images
    from pmdsim.simulation.trace import trace_camera

    s, cs, m = inp["setup"], inp["cs"], inp["mapping"]
    n = SIZE[0] * SIZE[1]
    table1 = cs.camera
    brown = inp["brown"]
    it_brown, failed = newton_iterations(brown)
    inp["brown_newton"] = (it_brown, failed)
    seq = s.patterns.sequence
    images = inp["images"]
    n_images = sum(len(v) for v in images.values())
    itemsize = next(iter(images.values()))[0].dtype.itemsize
    xs = [np.stack(images[("x", p)]) for p in seq.periods_x_mm]
    ys = [np.stack(images[("y", p)]) for p in seq.periods_y_mm]
    full = float(2 ** s.patterns.bit_depth - 1)
    noise = np.hypot(s.patterns.noise_std, 1.0 / np.sqrt(12.0))
    reg, seed, z_seed = inp["reg"], inp["seed"], inp["z_seed"]
    rays = inp["rays"]

    def trace():
        return trace_camera(table1, cs.T_world_cam, s.sample.T_world_sample, s.sample.surface,
                            s.screen.T_world_screen, s.screen.surface, rays=rays)

    data, start = inp["data"], inp["start"]
    return [
        ("view rays, Table 1 camera (no distortion)", lambda: table1._rays(None), view_rays_counts(n, 0)),
        (f"view rays, Brown 5-coefficient camera ({it_brown / n:.2f} Newton iterations per pixel)",
         lambda: brown._rays(None), view_rays_counts(n, it_brown)),
        ("tracer (glass-free, both surfaces bicubic)", trace, tracer_counts(n, int(m.valid.sum()))),
        (f"decoder, decode_images ({n_images} images, {itemsize}-byte pixels)", lambda: decode_images(s, images),
         decoder_counts(n, n_images, itemsize, len(xs) + len(ys))),
        ("decoder, decode_screen_coordinates on stacked images",
         lambda: decode_screen_coordinates(xs, seq.periods_x_mm, ys, seq.periods_y_mm, s.screen.size_mm, full,
                                           noise_std=noise),
         decoder_counts(n, n_images, itemsize, len(xs) + len(ys))),
        ("integration, reconstruct_least_squares (full frame)",
         lambda: reconstruct_least_squares(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, seed, z_seed),
         integration_counts(int(reg.valid.sum()))),
        (f"calibration JᵀJ + Jᵀr ({data.n_rows} correspondences, {_NB} columns)",
         lambda: _evaluate(data, start, True), jtj_counts(data.n_rows, _NB)),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--cache", default="", help="calibration observations (.npz), created if missing")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--only", default="", metavar="WORDS",
                    help="time only the kernels whose name contains one of these comma-separated words "
                         "(case-insensitive), e.g. --only decoder or --only 'brown,jᵀj'")
    a = ap.parse_args()
    if a.repeat < 5:
        sys.exit("--repeat must be ≥ 5 (best of at least 5)")
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    utc0 = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())
    rates = machine_rates()
    inp = build_inputs(a.cache)
    t_build = time.perf_counter() - t0
    rows = []
    words = [w.strip().lower() for w in a.only.split(",") if w.strip()]
    for name, fn, counts in kernels(inp):
        if words and not any(w in name.lower() for w in words):
            continue
        timing = {th: _timed(fn, a.repeat, th) for th in (1, 2)}
        best = min(timing[1]["wall_s"], timing[2]["wall_s"])
        counts = {k: float(v) for k, v in counts.items()}  # plain floats for --json
        f_bytes = counts["bytes"] / rates["bandwidth"]
        f_flops = counts["flops"] / rates["peak_flops"]
        f_divs = counts["divs"] / rates["div_rate"]
        floor = max(f_bytes, f_flops, f_divs)
        floor_wall = max(counts["bytes"] / rates["bandwidth_wall"], counts["flops"] / rates["peak_flops_wall"],
                         counts["divs"] / rates["div_rate_wall"])
        # The verdict: the best wall time (1 or 2 threads: what a user waits for) against the floor
        # at the rates measured by wall time; beside it one thread's CPU time against the floor at
        # the rates measured by CPU time (steadier under load, but blind to what the second
        # hardware thread adds to a latency-bound kernel).
        ratio_wall = best / floor_wall
        rows.append({"kernel": name, **counts, "floor_bytes_s": f_bytes, "floor_flops_s": f_flops,
                     "floor_divs_s": f_divs, "floor_s": floor, "floor_wall_s": floor_wall, "t1": timing[1],
                     "t2": timing[2], "best_wall_s": best, "ratio": timing[1]["cpu_s"] / floor,
                     "ratio_wall": ratio_wall, "met": bool(ratio_wall <= 3.0)})
        print(f"  timed {name}: {best * 1e3:.1f} ms wall, {timing[1]['cpu_s'] * 1e3:.1f} ms CPU "
              f"(load {os.getloadavg()[0]:.1f})", file=sys.stderr, flush=True)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    res = {"utc_start": utc0, "utc_end": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
           "load_before": load0, "load_after": os.getloadavg(), "numba_threads_max": numba.config.NUMBA_NUM_THREADS,
           "rates": rates, "brown_newton": inp["brown_newton"], "build_s": t_build,
           "total_s": time.perf_counter() - t0, "rows": rows,
           "pmdsim": os.path.dirname(__import__("pmdsim").__file__)}
    if a.json:
        dump_json(res)
        return
    _print(res)


def _print(res: dict) -> None:
    r = res["rates"]
    print(f"{res['pmdsim']}, UTC {res['utc_start']} – {res['utc_end']}, load (1/5/15 min) "
          f"{'/'.join(f'{x:.1f}' for x in res['load_before'])} before, "
          f"{'/'.join(f'{x:.1f}' for x in res['load_after'])} after; inputs built in {res['build_s']:.1f} s, "
          f"total {res['total_s']:.0f} s")
    for key, label in (("", "CPU time"), ("_wall", "wall time")):
        print(f"measured by {label}, one thread: bandwidth {r['bandwidth' + key] / 1e9:.1f} GB/s (read "
              f"{r['read_bw' + key] / 1e9:.1f}, copy {r['copy_bw' + key] / 1e9:.1f}), vector peak "
              f"{r['peak_flops' + key] / 1e9:.1f} GFLOP/s (float64 matrix product), divisions "
              f"{r['div_rate' + key] / 1e9:.2f} G/s")
    print(f"Brown camera: {res['brown_newton'][0]} Newton iterations, {res['brown_newton'][1]} pixels to the fallback")
    print("ratio = best wall time of 1 and 2 threads / floor at the wall-time rates (the verdict); in brackets one "
          "thread's CPU time / floor at the CPU-time rates (the floor column)")
    print()
    print("| kernel | bytes (floor) | flops (floor) | div + sqrt (floor) | floor | 1 thread wall (CPU) "
          "| 2 threads wall (CPU) | ratio wall (CPU) | within 3× |")
    print("|---|---|---|---|---|---|---|---|---|")
    for w in res["rows"]:
        print(f"| {w['kernel']} | {w['bytes'] / 1e6:.0f} MB ({w['floor_bytes_s'] * 1e3:.1f} ms) "
              f"| {w['flops'] / 1e9:.3f} G ({w['floor_flops_s'] * 1e3:.1f} ms) "
              f"| {w['divs'] / 1e6:.1f} M ({w['floor_divs_s'] * 1e3:.1f} ms) | {w['floor_s'] * 1e3:.1f} ms "
              f"| {w['t1']['wall_s'] * 1e3:.1f} ms ({w['t1']['cpu_s'] * 1e3:.0f}) "
              f"| {w['t2']['wall_s'] * 1e3:.1f} ms ({w['t2']['cpu_s'] * 1e3:.0f}) "
              f"| {w['ratio_wall']:.2f}× ({w['ratio']:.1f}×) | {'MET' if w['met'] else 'NOT MET'} |")


if __name__ == "__main__":
    main()
