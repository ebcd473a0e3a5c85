"""The deflated DCT-preconditioned CG (``uncertainty_deflation.deflated_dct_pcg``, the
least-squares σ's solver on full frames) against scipy's sparse direct solver on small grids,
and its deflation space's Galerkin matrix E = WᵀNW against the dense product."""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import spsolve

from test_poisson import _laplacian, _sparse


def _operator(rng, H=40, W=52, seed=(20, 11), potential=1e-3):
    """A weighted full-frame operator as the Gauss–Newton matrix: edge weights 1 ± 5 %, a
    potential on the border pixels (the Robin terms), the seed not an unknown."""
    D, Ex, Ey = _laplacian(np.ones((H, W), bool), seed, weights=0.05, rng=rng)
    border = np.zeros((H + 2, W + 2), bool)
    border[1:-1, 1:-1] = True
    border[2:-2, 2:-2] = False
    D[border & (D > 0)] += potential
    return D, Ex, Ey


def _random_rhs(rng, D):
    """A padded random right-hand side, 0 off the unknowns (D = 0)."""
    b = np.zeros(D.shape)
    b[1:-1, 1:-1] = rng.standard_normal((D.shape[0] - 2, D.shape[1] - 2))
    b[D == 0] = 0.0
    return b


def test_deflated_pcg_matches_spsolve():
    from pmdsim.evaluation.uncertainty_deflation import LowModes, deflated_dct_pcg

    rng = np.random.default_rng(8)
    H, W, seed = 40, 52, (20, 11)
    D, Ex, Ey = _operator(rng, H, W, seed)
    A, unk = _sparse(D, Ex, Ey)
    modes = LowModes((H, W), seed)
    modes.prepare(D, Ex, Ey, D > 0)
    for k in range(3):  # the prepared space reused for several right-hand sides, as by the σ
        b = _random_rhs(rng, D)
        ref = spsolve(A.tocsc(), b[1:-1, 1:-1].ravel()[unk])
        x, its, ok = deflated_dct_pcg(D, Ex, Ey, b, seed, 0.0, 1e-12, 100, modes=modes)
        assert ok and its < 100
        xi = x[1:-1, 1:-1]
        assert np.max(np.abs(xi.ravel()[unk] - ref)) < 1e-9 * np.max(np.abs(ref))
        assert xi[seed] == 0.0
        # the σ's tolerance: one or two iterations, within 1 % of the largest |x|
        x, its, ok = deflated_dct_pcg(D, Ex, Ey, b, seed, 0.0, 3e-2, 100, modes=modes)
        assert ok and its <= 3
        assert np.max(np.abs(x[1:-1, 1:-1].ravel()[unk] - ref)) < 1e-2 * np.max(np.abs(ref))


def test_galerkin_matrix_matches_the_dense_product():
    """E = WᵀNW from the separable sums against W (explicit, restricted to the unknowns) and
    N as a dense matrix."""
    from pmdsim.evaluation.uncertainty_deflation import LowModes

    rng = np.random.default_rng(9)
    H, W, seed = 12, 17, (5, 3)
    D, Ex, Ey = _operator(rng, H, W, seed)
    A, unk = _sparse(D, Ex, Ey)
    modes = LowModes((H, W), seed, modes=(3, 4))
    modes.prepare(D, Ex, Ey, D > 0)
    cols = [np.outer(modes.U[:, r], modes.VT[s]).ravel()[unk] for r in range(3) for s in range(4)]
    cols.append(modes.h[1:-1, 1:-1].ravel()[unk])
    Wm = np.stack(cols, axis=1)
    E = Wm.T @ (A @ Wm)
    E_ref_inv = np.linalg.pinv(E, hermitian=True)
    assert np.allclose(modes.E_inv, E_ref_inv, rtol=1e-8, atol=1e-8 * np.abs(E_ref_inv).max())


def _deflated_z_reference(y, y0, unknown, modes, mu, mu_h):
    """numpy: the padded z − (Σ_rs mu U_r V_s + mu_h h) on the unknowns, z = y − y0 (float32)."""
    Z = np.zeros(unknown.shape)
    Z[1:-1, 1:-1] = (y - y0).astype(np.float64)
    W = modes.U @ mu @ modes.VT
    Zd = np.zeros(unknown.shape)
    Zd[1:-1, 1:-1] = Z[1:-1, 1:-1] - (W + mu_h * modes.h[1:-1, 1:-1].astype(np.float64))
    return np.where(unknown, Zd, 0.0), np.where(unknown, Z, 0.0)


def _apply_reference(D, Ex, Ey, F):
    """numpy: N F on the interior of a padded field (0 on the padding)."""
    out = np.zeros_like(F)
    c = (slice(1, -1), slice(1, -1))
    out[c] = (D[c] * F[c] - Ex[1:-1, :-2] * F[1:-1, :-2] - Ex[c] * F[1:-1, 2:] - Ey[:-2, 1:-1] * F[:-2, 1:-1]
              - Ey[c] * F[2:, 1:-1])
    return out


def test_fused_passes_match_numpy_references():
    """The fused passes of the deflated CG (scatter + projection, x₀ + r₀, direction + N p, the
    stopping max, x += z and the σ's accumulation) against numpy on a grid with holes."""
    from pmdsim.evaluation import uncertainty_deflation as ud

    rng = np.random.default_rng(11)
    H, W, seed = 23, 31, (7, 12)
    D, Ex, Ey = _operator(rng, H, W, seed)
    D[5:8, 20:24] = 0.0  # a hole: not unknowns
    unknown = D > 0
    modes = ud.LowModes((H, W), seed, modes=(3, 4))
    modes.prepare(D, Ex, Ey, unknown)
    y = rng.standard_normal((H, W)).astype(np.float32)
    y0 = y[seed]
    R = np.zeros((H + 2, W + 2))
    R[1:-1, 1:-1] = rng.standard_normal((H, W))
    R[~unknown] = 0.0
    mu, mu_h = rng.standard_normal((3, 4)), float(rng.standard_normal())
    Zd, Z = _deflated_z_reference(y, y0, unknown, modes, mu, mu_h)
    tol = 1e-12
    # scatter + projection of N z − R
    rz, zmax = ud._scatter_project(R, y, y0, unknown, D, Ex, Ey, modes.VT, modes.h, modes.T, modes.th)
    assert abs(rz - np.sum(R * Z)) < tol * np.sum(np.abs(R * Z)) and zmax == np.max(np.abs(Z))
    G = (_apply_reference(D, Ex, Ey, Z) - R)[1:-1, 1:-1]
    assert np.allclose(modes.T, G @ modes.VT.T, rtol=0, atol=tol * np.abs(G).sum())
    assert np.allclose(modes.th, (G * modes.h[1:-1, 1:-1]).sum(axis=1), rtol=0, atol=tol * np.abs(G).sum())
    # x₀ = −W μ and r₀ = b − N x₀
    b = _random_rhs(rng, D)
    X, R0, buf = np.zeros_like(R), np.zeros_like(R), np.zeros((H, W), np.float32)
    ud._start(D, Ex, Ey, b, modes.U, modes.VT, mu, mu_h, modes.h, unknown, X, R0, buf, True)
    x0 = _deflated_z_reference(np.zeros((H, W), np.float32), np.float32(0), unknown, modes, mu, mu_h)[0]  # −W μ
    assert np.allclose(X, x0, rtol=0, atol=1e-14) and np.allclose(R0, b - _apply_reference(D, Ex, Ey, x0), atol=1e-13)
    assert np.array_equal(buf, R0[1:-1, 1:-1].astype(np.float32))
    # direction: X += αP, P = Zd + βP, AP = N Zd + β AP; returns P·AP and max |Zd|
    P, AP = rng.standard_normal(R.shape), rng.standard_normal(R.shape)
    X = rng.standard_normal(R.shape)
    alpha, beta = 0.7, 0.3
    P_ref, AP_ref = Zd + beta * P, _apply_reference(D, Ex, Ey, Zd) + beta * AP
    X_ref = X.copy()
    X_ref[1:-1, 1:-1] += alpha * P[1:-1, 1:-1]
    pAp, zdmax = ud._direction_deflated(D, Ex, Ey, y, y0, unknown, modes.U, modes.VT, mu, mu_h, modes.h, P, AP, beta,
                                        X, alpha)
    c = (slice(1, -1), slice(1, -1))
    assert np.allclose(P[c], P_ref[c], atol=1e-14) and np.allclose(AP[c], AP_ref[c], atol=1e-13)
    assert np.allclose(X, X_ref, atol=1e-14) and abs(pAp - np.sum(P_ref[c] * AP_ref[c])) < 1e-12 * np.sum(np.abs(P_ref))
    assert abs(zdmax - np.max(np.abs(Zd))) < 1e-15
    # the stopping max, X = (X + αP) + Zd, acc += x² on S
    S = unknown[1:-1, 1:-1].copy()
    S[seed] = True
    acc = rng.random((H, W))
    m, bad = ud._finish_deflated(X, P, alpha, y, y0, unknown, modes.U, modes.VT, mu, mu_h, modes.h, S, acc, 0, mu, mu_h, False)
    assert abs(m - np.max(np.abs(Zd))) < 1e-15 and bad == 0
    x_ref = X + alpha * P + Zd
    acc_ref = acc + np.where(S, x_ref[c] ** 2, 0.0)
    _, bad = ud._finish_deflated(X, P, alpha, y, y0, unknown, modes.U, modes.VT, mu, mu_h, modes.h, S, acc, 2, mu, mu_h, False)
    assert bad == 0 and np.allclose(acc, acc_ref, rtol=1e-14, atol=0)
    keep, X[3, 4] = X[3, 4], np.nan  # a non-finite x on S is counted
    _, bad = ud._finish_deflated(X, P, alpha, y, y0, unknown, modes.U, modes.VT, mu, mu_h, modes.h, S, acc, 2, mu, mu_h, False)
    assert bad == 1
    X[3, 4] = keep
    ud._finish_deflated(X, P, alpha, y, y0, unknown, modes.U, modes.VT, mu, mu_h, modes.h, S, acc, 1, mu, mu_h, False)
    assert np.allclose(X[c], x_ref[c], atol=1e-14)
    # x₀ not stored (``_start`` without X), formed again in the last pass: the same values
    X2, R2, buf2 = np.full_like(R, 9.0), np.zeros_like(R), np.zeros((H, W), np.float32)
    ud._start(D, Ex, Ey, b, modes.U, modes.VT, mu, mu_h, modes.h, unknown, X2, R2, buf2, False)
    assert (X2 == 9.0).all() and np.array_equal(R2, R0)
    mu1, mu1_h = rng.standard_normal((3, 4)), 0.3
    Zd1 = _deflated_z_reference(y, y0, unknown, modes, mu1, mu1_h)[0]
    acc = rng.random((H, W))  # (the NaN case above left a NaN in acc)
    acc0 = acc.copy()
    _, bad = ud._finish_deflated(X2, P, alpha, y, y0, unknown, modes.U, modes.VT, mu1, mu1_h, modes.h, S, acc, 2, mu,
                                 mu_h, True)
    assert bad == 0 and np.allclose(acc, acc0 + np.where(S, (x0 + alpha * P + Zd1)[c] ** 2, 0.0), rtol=1e-14, atol=0)
    ud._finish_deflated(X2, P, alpha, y, y0, unknown, modes.U, modes.VT, mu1, mu1_h, modes.h, S, acc, 3, mu, mu_h, True)
    assert np.allclose(X2[c], x0[c], rtol=0, atol=1e-14)


def test_deflated_pcg_accumulates_the_squares_of_the_solution():
    """With ``acc``/``on`` the solver adds x² (of the spsolve solution) on ``on`` instead of
    returning x."""
    from pmdsim.evaluation.uncertainty_deflation import LowModes, deflated_dct_pcg

    rng = np.random.default_rng(12)
    H, W, seed = 30, 41, (9, 17)
    D, Ex, Ey = _operator(rng, H, W, seed)
    A, unk = _sparse(D, Ex, Ey)
    modes = LowModes((H, W), seed)
    modes.prepare(D, Ex, Ey, D > 0)
    b = _random_rhs(rng, D)
    ref = np.zeros(H * W)
    ref[unk] = spsolve(A.tocsc(), b[1:-1, 1:-1].ravel()[unk])
    on = np.ones((H, W), bool)
    on[0, :5] = False
    acc = np.full((H, W), 0.5)
    finite, its, ok = deflated_dct_pcg(D, Ex, Ey, b, seed, 0.0, 1e-12, 100, modes=modes, acc=acc, on=on)
    assert ok and finite and its < 100
    want = 0.5 + np.where(on, ref.reshape(H, W) ** 2, 0.0)
    assert np.allclose(acc, want, rtol=0, atol=1e-9 * np.max(ref ** 2))
