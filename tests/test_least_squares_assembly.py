"""The least-squares integration's Gauss–Newton normal equations against an independent
reference: the trapezoidal residuals written here in numpy, their Jacobian J by central finite
differences, JᵀJ and −Jᵀr formed with scipy.sparse; and one Gauss–Newton step against
scipy's sparse least-squares solver (lsqr) on the same linearised problem."""

from __future__ import annotations

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
