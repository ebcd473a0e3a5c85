"""The least-squares integration's Gauss–Newton loop after the coarse-to-fine start
(``least_squares._FIRST_UPDATE_FRAC``, ``_COARSE_ATOL_FRAC``): the first full-grid update is
solved only to tol/5 and never decides convergence, the coarse levels to 3 % of their
tolerance — and the result is still the least-squares minimum to tol/10, checked by solving
the Gauss–Newton system at the result with a sparse direct solver (SuperLU), independently
of the iterative solvers. The assembly of that system is tested against finite differences
in test_least_squares_assembly.py."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.linalg import spsolve
from test_poisson import _sparse
from test_reconstruct import SEED, H, W, plane_scene

import pmdsim.evaluation.least_squares as LS

TOL_MM = 1e-9


@pytest.fixture(scope="module")
def noisy_plane():
    o, d, q, z_true, _ = plane_scene()
    q = q + np.random.default_rng(11).normal(0.0, 0.05, q.shape)  # 50 µm registration noise
    return o, d, q, np.ones((H, W), bool), z_true[SEED]


def _direct_update(o, d, q, S, z):
    """The Gauss–Newton update at the heights z (H, W), solved by SuperLU: (H, W), 0 at the seed."""
    D, iD, Ex, Ey, rhs = (np.zeros((H + 2, W + 2)) for _ in range(5))
    LS._assemble_gauss_newton(o, d, q, S, z, SEED[0], SEED[1], D, iD, Ex, Ey, rhs)
    A, unk = _sparse(D, Ex, Ey)
    delta = np.zeros(H * W)
    delta[unk] = spsolve(A.tocsc(), rhs[1:-1, 1:-1].ravel()[unk])
    return delta.reshape(H, W)


def test_coarse_start_first_update_loose_result_at_the_minimum(monkeypatch, noisy_plane):
    monkeypatch.setattr(LS, "_COARSE_START_MIN_PIXELS", 4000)  # 160×200 → 80×100 → 40×50 (stepwise)
    solves = []  # (grid, atol, cap) of every solve (multigrid-preconditioned at these sizes)
    pcg = LS._pcg

    def spy(D, iD, Ex, Ey, r, atol, rtol, max_iter, **kw):
        solves.append((D.shape[0] - 2, atol, kw["cap"]))
        return pcg(D, iD, Ex, Ey, r, atol, rtol, max_iter, **kw)

    monkeypatch.setattr(LS, "_pcg", spy)
    o, d, q, S, z0 = noisy_plane
    rec = LS.reconstruct_least_squares(o, d, q, S, SEED, z0, tol_mm=TOL_MM)
    fine = [s[1:] for s in solves if s[0] == H]
    coarse = [s[1:] for s in solves if s[0] < H]
    assert rec.converged and rec.final_change_mm < TOL_MM and rec.iterations == len(fine) >= 2
    assert fine[0] == (0.2 * TOL_MM, 0.2 * TOL_MM)  # loose: it cannot decide convergence
    assert all(f == (0.1 * TOL_MM, 0.1 * TOL_MM) for f in fine[1:])
    assert coarse and all(c == (0.03 * 1e-3, 0.1 * 1e-3) for c in coarse)
    # At the result the exact Gauss–Newton update is below tol/10: it is the minimum to that accuracy.
    delta = _direct_update(o, d, q, S, rec.height_mm)
    assert np.abs(delta).max() < 0.1 * TOL_MM


def test_loose_update_never_decides_convergence(noisy_plane):
    o, d, q, S, z0 = noisy_plane
    rec = LS.reconstruct_least_squares(o, d, q, S, SEED, z0, tol_mm=TOL_MM)  # stepwise start: all tight
    assert rec.converged and np.abs(_direct_update(o, d, q, S, rec.height_mm)).max() < 0.1 * TOL_MM
    for first, max_iter, iterations in ((0.2, 5, 2), (0.2, 1, 1), (None, 5, 1)):
        z = rec.height_mm.copy()  # already the solution: the first update is ≈ 0
        it, converged, change = LS._gauss_newton(o, d, q, S, SEED, z, TOL_MM, max_iter, atol_frac=0.1,
                                                 first_frac=first)
        # a loosely solved first update is followed by a tight one (with max_iter 1 it is tight)
        assert (it, converged) == (iterations, True) and change < 0.1 * TOL_MM
        assert np.nanmax(np.abs(z - rec.height_mm)) < 0.1 * TOL_MM


def test_every_second_is_numpys_slice():
    rng = np.random.default_rng(2)
    for shape in ((7, 9, 3), (8, 10, 3), (5, 4, 3)):
        x = rng.standard_normal(shape)
        for a in (0, 1):
            for b in (0, 1):
                for src in (x, np.asfortranarray(x)):
                    r = LS._every_second(src, a, b)
                    assert r.flags.c_contiguous and np.array_equal(r, x[a::2, b::2])
