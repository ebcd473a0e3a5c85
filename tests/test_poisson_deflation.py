"""The deflated DCT-preconditioned CG (issue 25 item 3) against independent references: its
Galerkin matrix E = WᵀNW against W and N formed explicitly (dense basis, scipy.sparse
operator), its solutions against scipy's sparse direct solver (spsolve) on small grids."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.fft import idctn
from scipy.sparse.linalg import spsolve

from pmdsim.evaluation.poisson_deflation import LowModes, deflated_dct_pcg
from test_poisson import _laplacian, _sparse


def _operator(S, seed, rng):
    """A Gauss–Newton-like operator: edge weights 1 ± 5 %, a small potential, and Robin-type
    terms on the border (the matrix's row sums there)."""
    D, Ex, Ey = _laplacian(S, seed, weights=0.05, rng=rng)
    border = np.zeros(S.shape, bool)
    border[[0, -1], :] = border[:, [0, -1]] = True
    D[1:-1, 1:-1] += np.where(border & S, 5e-3, 0.0)
    D[seed[0] + 1, seed[1] + 1] = 0.0
    D[1:-1, 1:-1][~S] = 0.0
    return D, Ex, Ey


def _problem(rng_seed, H, W, seed, hole):
    """The operator of :func:`_operator` on H×W (``hole``: a region that is not unknowns, or
    None) and its sparse matrix with the unknowns' flat indices."""
    S = np.ones((H, W), bool)
    if hole is not None:
        S[hole] = False
    D, Ex, Ey = _operator(S, seed, np.random.default_rng(rng_seed))
    return (D, Ex, Ey), _sparse(D, Ex, Ey)


@pytest.mark.parametrize("masked", [False, True])
def test_galerkin_matrix_matches_the_explicit_basis(masked):
    H, W, seed = 18, 27, (5, 20)
    (D, Ex, Ey), (A, unk) = _problem(11, H, W, seed, np.s_[9, 3:6] if masked else None)
    modes = LowModes((H, W), seed, modes=(3, 4))
    modes.prepare(D, Ex, Ey, D > 0)
    # the basis written out: the orthonormal DCT-II vectors (scipy's inverse transform of unit
    # spectra) and the Green's function h, on the unknowns
    cols = []
    for r in range(3):
        for s in range(4):
            e = np.zeros((H, W))
            e[r, s] = 1.0
            cols.append(idctn(e, norm="ortho").ravel()[unk])
    cols.append(modes.h[1:-1, 1:-1].ravel()[unk])
    Wm = np.array(cols).T
    E_ref = Wm.T @ (A @ Wm)
    E = np.linalg.pinv(modes.E_inv, hermitian=True)
    assert np.max(np.abs(E - E_ref)) < 1e-11 * np.max(np.abs(E_ref))
    # h is the Laplacian's Green's function at the seed: L h = e_s − 1/n (up to the restriction)
    if not masked:
        g = modes._g.astype(float)
        Lg = 4 * g
        Lg[1:, :] -= g[:-1, :]
        Lg[:-1, :] -= g[1:, :]
        Lg[:, 1:] -= g[:, :-1]
        Lg[:, :-1] -= g[:, 1:]
        Lg[0, :] -= g[0, :]
        Lg[-1, :] -= g[-1, :]
        Lg[:, 0] -= g[:, 0]
        Lg[:, -1] -= g[:, -1]
        e = np.full((H, W), -1.0 / (H * W))
        e[seed] += 1.0
        assert np.max(np.abs(Lg - e)) < 1e-5


@pytest.mark.parametrize("masked", [False, True])
def test_deflated_pcg_matches_spsolve(masked):
    rng = np.random.default_rng(5)
    H, W, seed = 40, 52, (20, 11)
    (D, Ex, Ey), (A, unk) = _problem(5, H, W, seed, np.s_[10:13, 25:29] if masked else None)
    for k in range(2):
        b = np.zeros((H + 2, W + 2))
        b[1:-1, 1:-1] = rng.standard_normal((H, W)) if k == 0 else np.outer(np.linspace(0, 1, H), np.ones(W))
        b[D == 0] = 0.0
        ref = spsolve(A.tocsc(), b[1:-1, 1:-1].ravel()[unk])
        x, its, ok = deflated_dct_pcg(D, Ex, Ey, b, seed, 0.0, 1e-13, 200)
        assert ok and its < 200
        xi = x[1:-1, 1:-1].ravel()
        assert np.max(np.abs(xi[unk] - ref)) < 1e-9 * np.max(np.abs(ref))
        assert np.all(np.delete(xi, unk) == 0.0) and np.all(x[[0, -1], :] == 0) and np.all(x[:, [0, -1]] == 0)
