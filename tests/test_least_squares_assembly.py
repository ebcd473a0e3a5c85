"""The least-squares integration's Gauss–Newton normal equations against an independent
reference: the trapezoidal residuals written here in numpy, their Jacobian J by central finite
differences, JᵀJ and −Jᵀr formed with scipy.sparse; and one Gauss–Newton step against
scipy's sparse least-squares solver (lsqr) on the same linearised problem. Bit for bit: the
padded arrays against an element-wise numpy evaluation in the kernel's documented order, on 1
and 2 threads."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import lsqr

from pmdsim.evaluation.least_squares import _assemble_gauss_newton

H, W = 7, 9


def _scene(seed_px, holes):
    """A camera 500 mm above a gently curved surface seen over a tilted screen: o (3,),
    d, q (H, W, 3), heights z (H, W), mask S (H, W)."""
    rng = np.random.default_rng(3)
    o = np.array([1.0, -2.0, 500.0])
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - 4) * 2.0 + 0.1 * rng.normal(size=(H, W)), (v - 3) * 2.0, -np.full((H, W), 500.0)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    z = 0.01 * (u - 4) ** 2 / 16 + 0.005 * v + 1e-3 * rng.normal(size=(H, W))
    q = np.stack([u * 3.0 + 20.0, v * 3.0 - 5.0, np.full((H, W), 300.0)], axis=-1) + rng.normal(size=(H, W, 3))
    S = np.ones((H, W), dtype=bool)
    for h in holes:
        S[h] = False
    S[seed_px] = True
    return o, np.ascontiguousarray(d), np.ascontiguousarray(q), z, S


def _residuals(o, d, q, z, S):
    """Trapezoidal residuals z_b − z_a − ½(g_a + g_b)·(xy_b − xy_a) of every 4-neighbour pair
    in S (right, then below neighbours, each row-major), and the pairs as flat indices (a, b)."""
    t = (z - o[2]) / d[..., 2]
    p = o + t[..., None] * d
    a = o - p
    b = q - p
    m = a / np.linalg.norm(a, axis=-1, keepdims=True) + b / np.linalg.norm(b, axis=-1, keepdims=True)
    g = -m[..., :2] / m[..., 2:]
    idx = np.arange(H * W).reshape(H, W)
    res, pairs = [], []
    for sa, sb in (((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
                   ((slice(0, -1), slice(None)), (slice(1, None), slice(None)))):
        keep = S[sa] & S[sb]
        G = 0.5 * (g[sa] + g[sb])
        dxy = p[sb][..., :2] - p[sa][..., :2]
        r = z[sb] - z[sa] - np.sum(G * dxy, axis=-1)
        res.append(r[keep])
        pairs += list(zip(idx[sa][keep], idx[sb][keep]))
    return np.concatenate(res), pairs


@pytest.mark.parametrize("seed_px,holes", [((3, 4), []), ((0, 0), [(2, 3), (5, 7), (6, 0)]), ((6, 8), [(3, slice(2, 5))])],
                         ids=["full", "holes", "gap"])
def test_normal_equations_match_finite_difference_jacobian(seed_px, holes):
    o, d, q, z, S = _scene(seed_px, holes)
    r0, _ = _residuals(o, d, q, z, S)
    unknown = S.ravel().copy()
    unknown[seed_px[0] * W + seed_px[1]] = False  # the gauge
    cols = np.flatnonzero(unknown)
    J = np.zeros((r0.size, cols.size))
    h = 1e-6
    for j, k in enumerate(cols):
        zp, zm = z.copy(), z.copy()
        zp.flat[k] += h
        zm.flat[k] -= h
        J[:, j] = (_residuals(o, d, q, zp, S)[0] - _residuals(o, d, q, zm, S)[0]) / (2 * h)
    Js = sp.csr_matrix(J)
    N = (Js.T @ Js).toarray()
    g = -(Js.T @ r0)

    D, iD, Ex, Ey, rhs = (np.full((H + 2, W + 2), 7.0) for _ in range(5))
    _assemble_gauss_newton(o, d, q, S, z, seed_px[0], seed_px[1], D, iD, Ex, Ey, rhs)
    pos = {k: j for j, k in enumerate(cols)}
    N_asm = np.zeros_like(N)
    g_asm = np.zeros_like(g)
    for k in cols:
        v, u = divmod(k, W)
        i = pos[k]
        N_asm[i, i] = D[v + 1, u + 1]
        g_asm[i] = rhs[v + 1, u + 1]
        for nb, c in ((k + 1, Ex[v + 1, u + 1]), (k + W, Ey[v + 1, u + 1])):
            if nb in pos and ((nb == k + 1 and u + 1 < W) or nb == k + W):
                N_asm[i, pos[nb]] = N_asm[pos[nb], i] = -c
    assert np.allclose(N_asm, N, rtol=0, atol=1e-7 * np.abs(N).max())
    assert np.allclose(g_asm, g, rtol=0, atol=1e-7 * np.abs(g).max() + 1e-15)
    off = ~S | (np.arange(H * W).reshape(H, W) == seed_px[0] * W + seed_px[1])
    assert np.all(D[1:-1, 1:-1][off] == 0) and np.all(rhs[1:-1, 1:-1][off] == 0)
    assert np.all(iD[1:-1, 1:-1][~off] == 1.0 / D[1:-1, 1:-1][~off])

    # One Gauss–Newton step: the assembled system solved densely against lsqr of J δ = −r.
    step_asm = np.linalg.solve(N_asm, g_asm)
    step_ref = lsqr(Js, -r0, atol=1e-14, btol=1e-14, iter_lim=10_000)[0]
    assert np.allclose(step_asm, step_ref, rtol=0, atol=1e-6 * np.abs(step_ref).max())


def _reference_system(o, d, q, z, S, seed_px):
    """The padded 5-point arrays (D, iD, Ex, Ey, rhs) in numpy, element-wise in the order the
    kernel documents: the geometry of each pixel (point, bisector slopes g, dg/dz, the ray's
    dxy/dz), the trapezoidal edge residuals and derivatives (0 where an end is off S or a value
    not finite), the sums above, left, right, below (a row block's first row: left, right,
    below, above; 16 blocks), the gauge, then 1/D."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return _reference_arrays(o, d, q, z, S, seed_px)


def _reference_arrays(o, d, q, z, S, seed_px):
    Hs, Ws = S.shape
    idz = 1.0 / d[..., 2]
    ex, ey = d[..., 0] * idz, d[..., 1] * idz
    w = z - o[2]
    px, py = o[0] + w * ex, o[1] + w * ey
    unit = []
    for c in ((o[0] - px, o[1] - py, o[2] - z), (q[..., 0] - px, q[..., 1] - py, q[..., 2] - z)):
        i = 1.0 / np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
        unit.append((c[0] * i, c[1] * i, c[2] * i, i))
    (ax, ay, az, ia), (bx, by, bz, ib) = unit
    ae, be = ax * ex + ay * ey + az, bx * ex + by * ey + bz
    dmx = -(ex - ae * ax) * ia - (ex - be * bx) * ib
    dmy = -(ey - ae * ay) * ia - (ey - be * by) * ib
    dmz = -(1.0 - ae * az) * ia - (1.0 - be * bz) * ib
    imz = 1.0 / (az + bz)
    gx, gy = -(ax + bx) * imz, -(ay + by) * imz
    geo = np.stack([px, py, gx, gy, -(dmx + gx * dmz) * imz, -(dmy + gy * dmz) * imz, ex, ey])

    def edges(a, b):  # index tuples of the ends a, b
        ga, gb = geo[(slice(None),) + a], geo[(slice(None),) + b]
        Gx, Gy = 0.5 * (ga[2] + gb[2]), 0.5 * (ga[3] + gb[3])
        dx, dy = gb[0] - ga[0], gb[1] - ga[1]
        res = z[b] - z[a] - (Gx * dx + Gy * dy)
        Ja = -1.0 + (Gx * ga[6] + Gy * ga[7]) - 0.5 * (ga[4] * dx + ga[5] * dy)
        Jb = 1.0 - (Gx * gb[6] + Gy * gb[7]) - 0.5 * (gb[4] * dx + gb[5] * dy)
        ok = S[a] & S[b] & np.isfinite(res) & np.isfinite(Ja) & np.isfinite(Jb)
        return [np.where(ok, x, 0.0) for x in (res, Ja, Jb)]

    R, B = np.zeros((3, Hs, Ws)), np.zeros((3, Hs, Ws))  # the edge to the right, below: res, J_a, J_b
    R[:, :, :-1] = edges((slice(None), slice(0, -1)), (slice(None), slice(1, None)))
    B[:, :-1, :] = edges((slice(0, -1), slice(None)), (slice(1, None), slice(None)))
    L = np.zeros((3, Hs, Ws))  # the edge from the left (none in column 0)
    L[:, :, 1:] = R[:, :, :-1]
    A = np.zeros((3, Hs, Ws))  # the edge from above
    A[:, 1:, :] = B[:, :-1, :]
    nb = min(Hs, 16)
    first = np.zeros(Hs, dtype=bool)
    first[[k * Hs // nb for k in range(1, nb)]] = True
    f = first[:, None]
    D0 = np.where(f, 0.0, A[2] * A[2])
    r0 = np.where(f, 0.0, -(A[2] * A[0]))
    D = D0 + L[2] * L[2] + R[1] * R[1] + B[1] * B[1]
    rhs = r0 - L[2] * L[0] - R[1] * R[0] - B[1] * B[0]
    D = np.where(f, D + A[2] * A[2], D)
    rhs = np.where(f, rhs + -(A[2] * A[0]), rhs)
    Ex, Ey = -R[1] * R[2], -B[1] * B[2]
    sv, su = seed_px
    D[sv, su] = 0.0
    Ex[sv, su] = Ey[sv, su] = 0.0
    if su > 0:
        Ex[sv, su - 1] = 0.0
    if sv > 0:
        Ey[sv - 1, su] = 0.0
    pos = D > 0.0
    iD = np.where(pos, 1.0 / D, 0.0)
    out = []
    for a in (np.where(pos, D, 0.0), iD, Ex, Ey, np.where(pos, rhs, 0.0)):
        p = np.zeros((Hs + 2, Ws + 2))
        p[1:-1, 1:-1] = a
        out.append(p)
    return out


def test_assembly_equals_numpy_reference_bit_for_bit_any_threads():
    """Bit for bit (values and signs of zeros) against the element-wise numpy reference, on a
    34-row image (16 row blocks of 2–3 rows) with holes, NaN and infinite heights and the
    seed on and off a block's first row, on 1 and 2 threads."""
    rng = np.random.default_rng(8)
    Hs, Ws = 34, 23
    o = np.array([1.0, -2.0, 500.0])
    v, u = np.mgrid[0:Hs, 0:Ws].astype(float)
    d = np.ascontiguousarray(np.stack([(u - 11) * 2.0 + 0.1 * rng.normal(size=(Hs, Ws)), (v - 17) * 2.0,
                                       -np.full((Hs, Ws), 500.0)], axis=-1))
    q = np.ascontiguousarray(np.stack([u * 3.0 + 20.0, v * 3.0 - 5.0, np.full((Hs, Ws), 300.0)], axis=-1)
                             + rng.normal(size=(Hs, Ws, 3)))
    z = 0.01 * (u - 11) ** 2 / 16 + 0.005 * v + 1e-3 * rng.normal(size=(Hs, Ws))
    z[4, 6], z[20, 0], z[33, 22] = np.nan, np.inf, np.nan
    S = rng.random((Hs, Ws)) > 0.1
    S[:, 5] = True

    threads = numba.get_num_threads()
    try:
        for seed_px in ((2, 5), (10, 5)):  # row 2 is a block's first row (34 // 16 = 2), row 10 not
            ref = _reference_system(o, d, q, z, S, seed_px)
            for th in sorted({1, threads}):
                numba.set_num_threads(th)
                got = [np.zeros((Hs + 2, Ws + 2)) for _ in range(5)]
                _assemble_gauss_newton(o, d, q, S, z, seed_px[0], seed_px[1], *got)
                for name, a, b in zip(("D", "iD", "Ex", "Ey", "rhs"), got, ref):
                    assert np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b)), (name, seed_px, th)
    finally:
        numba.set_num_threads(threads)
