"""The stepwise integration's lock-step wavefront kernel (issue 25) against a scalar reference
written here: the paper's pixel-by-pixel predictor–corrector step in plain Python (numpy float64
scalars: IEEE division by zero), wavefront by wavefront from the seed. The heights must be equal
bit for bit, on a mask with holes and with steps that fail (view rays pointing away from the
surface: the ray misses the plane in front of the camera), so that pixels are skipped and
reached again from a later wavefront."""

from __future__ import annotations

import numpy as np

from pmdsim.evaluation.stepwise import _max_abs_valid, reconstruct_stepwise, step_tolerance_mm

NB = ((-1, 0), (1, 0), (0, -1), (0, 1))


def _slopes(px, py, pz, o, q):
    ax, ay, az = o[0] - px, o[1] - py, o[2] - pz
    ia = 1.0 / np.sqrt(ax * ax + ay * ay + az * az)
    bx, by, bz = q[0] - px, q[1] - py, q[2] - pz
    ib = 1.0 / np.sqrt(bx * bx + by * by + bz * bz)
    imz = -1.0 / (az * ia + bz * ib)
    return (ax * ia + bx * ib) * imz, (ay * ia + by * ib) * imz


def _step(o, d, q, t, g, flag, vb, ub, tol, max_iter):
    """One pixel alone: predictor G = g_a, correctors G = ½(g_a + g_b) until |Δz| < tol."""
    H, W = flag.shape
    z_prev, gb, ok, tb, it_used, change = 0.0, None, False, 0.0, 0, np.inf
    for it in range(max_iter + 1):
        num = np.float64(0.0)
        den = np.float64(0.0)
        for dv, du in NB:
            va, ua = vb + dv, ub + du
            if not (0 <= va < H and 0 <= ua < W) or flag[va, ua] != 1:
                continue
            Gx = g[va, ua, 0] if gb is None else 0.5 * (g[va, ua, 0] + gb[0])
            Gy = g[va, ua, 1] if gb is None else 0.5 * (g[va, ua, 1] + gb[1])
            r = t[va, ua] * d[va, ua]
            num += r[2] - (Gx * r[0] + Gy * r[1])
            den += d[vb, ub, 2] - (Gx * d[vb, ub, 0] + Gy * d[vb, ub, 1])
        tb = num / den
        if not (tb > 0.0) or not np.isfinite(tb):
            return False, 0.0, None
        bz = o[2] + tb * d[vb, ub, 2]
        gb = _slopes(o[0] + tb * d[vb, ub, 0], o[1] + tb * d[vb, ub, 1], bz, o, q[vb, ub])
        if not (np.isfinite(gb[0]) and np.isfinite(gb[1])):
            return False, 0.0, None
        ok = True
        if it > 0:
            change = abs(bz - z_prev)
            it_used = it
            if change < tol:
                break
        z_prev = bz
    return ok, tb, gb


def _reference(o, d, q, valid, seed, z0, tol, max_iter=50):
    H, W = valid.shape
    flag = np.where(valid, 0, -1)
    t = np.full((H, W), np.nan)
    g = np.full((H, W, 2), np.nan)
    sv, su = seed
    t[seed] = (z0 - o[2]) / d[sv, su, 2]
    g[seed] = _slopes(o[0] + t[seed] * d[sv, su, 0], o[1] + t[seed] * d[sv, su, 1], z0, o, q[seed])
    flag[seed] = 1
    cur = [seed]
    while cur:
        nxt = []
        for va, ua in cur:
            for dv, du in NB:
                vb, ub = va + dv, ua + du
                if 0 <= vb < H and 0 <= ub < W and flag[vb, ub] == 0:
                    flag[vb, ub] = 2
                    nxt.append((vb, ub))
        solved = []
        for vb, ub in nxt:
            ok, tb, gb = _step(o, d, q, t, g, flag, vb, ub, tol, max_iter)
            if not ok:
                flag[vb, ub] = 0
                continue
            t[vb, ub] = tb
            g[vb, ub] = gb
            solved.append((vb, ub))
        for p in solved:
            flag[p] = 1
        cur = solved
    z = np.where(flag == 1, o[2] + t * d[..., 2], np.nan)
    z[seed] = z0
    return z


def _scene(H=21, W=27, seed=3):
    """A camera 300 mm above a wavy surface, screen points on its mirror rays; a mask with holes
    and a few view rays that point upwards (their steps fail)."""
    rng = np.random.default_rng(seed)
    o = np.array([3.0, -5.0, 300.0])
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - W / 2) * 0.01, (v - H / 2) * 0.01, -np.ones((H, W))], axis=-1)
    d *= rng.uniform(0.5, 2.0, size=(H, W, 1))
    t = (0.3 * np.sin(u / 4) + 0.2 * np.cos(v / 3) - o[2]) / d[..., 2]
    p = o + t[..., None] * d
    q = p + np.stack([0.1 * np.sin(v / 5), 0.2 * np.cos(u / 6), 400.0 + u], axis=-1)
    valid = np.ones((H, W), bool)
    valid[4:8, 10:20] = False
    valid[12:18, 3:5] = False
    valid[rng.random((H, W)) < 0.05] = False
    up = rng.random((H, W)) < 0.03
    d[up, 2] = 0.5  # pointing away from the surface: t_b < 0 from every neighbour
    valid[10, 13] = True
    return o, d, q, valid, (10, 13)


def test_heights_equal_the_pixel_by_pixel_reference_bit_for_bit():
    o, d, q, valid, seed = _scene()
    tol = step_tolerance_mm(o, q, valid)
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.25)
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.25, tol)
    assert np.isnan(ref).sum() > np.count_nonzero(~valid)  # some steps failed
    assert np.isfinite(ref).sum() > 0.8 * valid.size
    assert np.array_equal(rec.height_mm, ref, equal_nan=True)
    assert np.array_equal(rec.reconstructed, np.isfinite(ref))


def test_step_tolerance_ignores_invalid_pixels():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(9, 11, 3)) * 100.0
    valid = rng.random((9, 11)) < 0.6
    q[~valid] = 1e9  # far larger than any valid point: must not count
    assert _max_abs_valid(q, valid) == np.max(np.abs(q[valid]))
    assert _max_abs_valid(q, np.zeros((9, 11), bool)) == -1.0
    o = np.array([0.0, 0.0, 5.0])
    assert step_tolerance_mm(o, q, valid) == max(1e-12, 16 * np.spacing(np.max(np.abs(q[valid]))))
    big = np.array([0.0, 0.0, 1e7])  # a 10 km stand-off: 16 ulps of 1e7 mm
    assert step_tolerance_mm(big, q, valid) == 16 * np.spacing(1e7)
