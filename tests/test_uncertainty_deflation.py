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


def test_deflated_pcg_matches_spsolve():
    from pmdsim.evaluation.uncertainty_deflation import LowModes, deflated_dct_pcg

    rng = np.random.default_rng(8)
    H, W, seed = 40, 52, (20, 11)
    D, Ex, Ey = _operator(rng, H, W, seed)
    A, unk = _sparse(D, Ex, Ey)
    modes = LowModes((H, W), seed)
    modes.prepare(D, Ex, Ey, D > 0)
    for k in range(3):  # the prepared space reused for several right-hand sides, as by the σ
        b = np.zeros((H + 2, W + 2))
        b[1:-1, 1:-1] = rng.standard_normal((H, W))
        b[D == 0] = 0.0
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
