"""The DCT Poisson solver and the DCT-preconditioned CG (issue 25 item 3) against scipy's
sparse direct solver (SuperLU, ``scipy.sparse.linalg.spsolve``) on small grids."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from pmdsim.evaluation.multigrid import _pcg
from pmdsim.evaluation.poisson import DCTLaplacian, dct_pcg


def _sparse(D, Ex, Ey):
    """The padded 5-point operator (pmdsim.evaluation.multigrid storage) as a sparse matrix on
    its unknowns (D > 0), and their flat indices in the (H, W) grid."""
    H, W = D.shape[0] - 2, D.shape[1] - 2
    Dc = D[1:-1, 1:-1].ravel()
    unk = np.flatnonzero(Dc > 0)
    pos = np.full(H * W, -1)
    pos[unk] = np.arange(unk.size)
    rows, cols, vals = [pos[unk]], [pos[unk]], [Dc[unk]]
    for E, step, keep in ((Ex[1:-1, 1:-1].ravel(), 1, np.tile(np.arange(W) < W - 1, H)),
                          (Ey[1:-1, 1:-1].ravel(), W, np.arange(H * W) < (H - 1) * W)):
        a = np.flatnonzero(keep & (E != 0))
        i, j = pos[a], pos[a + step]
        ok = (i >= 0) & (j >= 0)
        rows += [i[ok], j[ok]]
        cols += [j[ok], i[ok]]
        vals += [-E[a[ok]], -E[a[ok]]]
    n = unk.size
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)), unk


def _laplacian(S, seed, weights=None, rng=None):
    """Padded D, Ex, Ey of the Neumann 5-point operator on the pixels S (edge weights 1, or
    1 + weights·U(−1, 1) per edge; the seed is not an unknown, its couplings are 0), plus a
    small non-negative potential when weighted (as the Gauss–Newton matrix's row sums)."""
    H, W = S.shape
    Ex = np.zeros((H + 2, W + 2))
    Ey = np.zeros((H + 2, W + 2))
    ex = (S[:, :-1] & S[:, 1:]).astype(float)
    ey = (S[:-1, :] & S[1:, :]).astype(float)
    if weights:
        ex *= 1 + weights * rng.uniform(-1, 1, ex.shape)
        ey *= 1 + weights * rng.uniform(-1, 1, ey.shape)
    Ex[1:-1, 1:-2] = ex
    Ey[1:-2, 1:-1] = ey
    D = np.zeros((H + 2, W + 2))
    D[1:-1, 1:-1] = (Ex[1:-1, 1:-1] + Ex[1:-1, :-2] + Ey[1:-1, 1:-1] + Ey[:-2, 1:-1])
    if weights:
        D[1:-1, 1:-1] += S * weights * 1e-3 * rng.uniform(0, 1, S.shape)
    sv, su = seed
    D[sv + 1, su + 1] = 0.0
    Ex[sv + 1, su + 1] = Ex[sv + 1, su] = 0.0
    Ey[sv + 1, su + 1] = Ey[sv, su + 1] = 0.0
    D[1:-1, 1:-1][~S] = 0.0
    return D, Ex, Ey


def test_dct_solve_matches_spsolve_on_the_full_rectangle():
    rng = np.random.default_rng(3)
    H, W, seed = 23, 37, (7, 30)
    D, Ex, Ey = _laplacian(np.ones((H, W), bool), seed)
    A, unk = _sparse(D, Ex, Ey)
    b = rng.standard_normal((2, H, W))
    ref = [spsolve(A.tocsc(), bb.ravel()[unk]) for bb in b]
    x = DCTLaplacian((H, W), seed).solve(b)
    assert x.shape == (2, H, W) and x[:, seed[0], seed[1]].tolist() == [0.0, 0.0]
    for k in range(2):
        assert np.max(np.abs(x[k].ravel()[unk] - ref[k])) < 1e-9 * np.max(np.abs(ref[k]))
    # a single field, and single precision (the preconditioner's): ≈ 1e-6 relative
    x32 = DCTLaplacian((H, W), seed, dtype=np.float32).solve(b[0])
    assert x32.dtype == np.float32
    assert np.max(np.abs(x32.ravel()[unk] - ref[0])) < 1e-5 * np.max(np.abs(ref[0]))


@pytest.mark.parametrize("masked", [False, True])
def test_dct_pcg_matches_spsolve(masked):
    """A weighted operator (edge weights 1 ± 5 %) on the full rectangle and on a domain with a
    hole and a cut-out corner: CG preconditioned by the single-precision DCT solve reaches the
    direct solution to 1e-9 (relative), for several right-hand sides at once, and agrees with
    the multigrid-preconditioned CG."""
    rng = np.random.default_rng(5)
    H, W, seed = 40, 52, (20, 11)
    S = np.ones((H, W), bool)
    if masked:
        S[10:18, 25:40] = False  # a hole
        S[:12, :9] = False       # a cut-out corner
    D, Ex, Ey = _laplacian(S, seed, weights=0.05, rng=rng)
    A, unk = _sparse(D, Ex, Ey)
    B = np.zeros((3, H + 2, W + 2))
    B[:, 1:-1, 1:-1] = rng.standard_normal((3, H, W))
    B[:, D == 0] = 0.0
    X, its, conv = dct_pcg(D, Ex, Ey, B, seed, 0.0, 1e-13, 200)
    assert conv.all() and (its < 200).all()
    iD = np.where(D > 0, 1.0 / np.where(D > 0, D, 1.0), 0.0)
    for k in range(3):
        ref = spsolve(A.tocsc(), B[k, 1:-1, 1:-1].ravel()[unk])
        x = X[k, 1:-1, 1:-1]
        assert np.max(np.abs(x.ravel()[unk] - ref)) < 1e-9 * np.max(np.abs(ref))
        assert np.all(x.ravel()[np.setdiff1d(np.arange(H * W), unk)] == 0.0)
        xm, _, ok = _pcg(D, iD, Ex, Ey, B[k], 0.0, 1e-13, 200)
        assert ok and np.max(np.abs(xm[1:-1, 1:-1] - x)) < 1e-9 * np.max(np.abs(ref))


@pytest.mark.parametrize("kind", ["dct", "multigrid"])
def test_sampled_height_std_batched_equals_the_one_by_one_solves(monkeypatch, kind):
    """The least-squares σ estimator with its right-hand sides solved in batches (DCT- or
    multigrid-preconditioned, to SIGMA_RTOL) against the same seeded samples solved one by one
    to 1e-6 (``_LinearisedIntegration.apply``): equal to the solver tolerance."""
    from pmdsim.evaluation import poisson as P
    from pmdsim.evaluation import uncertainty as U
    from pmdsim.evaluation import uncertainty_solve as US
    from pmdsim.evaluation.pipeline import decode_simulated, evaluate_decoded
    from pmdsim.setup import default_setup
    from pmdsim.simulation.render import noise_generator, trace_setup_camera

    s = default_setup().binned(40).with_patterns(noise_std=2.0)
    m = trace_setup_camera(s, "left")
    dec = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, "left", stream=3))
    reg, rec = evaluate_decoded(s, "left", dec, method="least_squares", seed_pixel=(12, 30))
    S = rec.reconstructed
    R = (s.sample.T_world_sample.inv() @ s.screen.T_world_screen).rotation
    dq = U._screen_tangents(R, None, dec.screen_xy_mm)
    A, _ = U._jacobian_scaled(reg.o_ref_mm, rec.p_sample_mm, reg.q_ref_mm, dq, S, np.nan_to_num(dec.std_xy_mm))
    lin = U._LinearisedIntegration(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec)
    monkeypatch.setattr(P, "DCT_MIN_FILL", 0.0 if kind == "dct" else 2.0)
    monkeypatch.setattr(P, "DCT_MIN_PIXELS", 0)
    assert US._SigmaSolver(lin).kind == kind
    K, seed = 9, 17  # an odd K: a last, partial batch
    new = U._sampled_std(lin, A, K, seed)
    A0 = np.ascontiguousarray(np.where(S[..., None, None], A, 0.0))
    dg = np.empty(S.shape + (2,))
    acc = np.zeros(S.shape)
    for k in range(K):
        U._sample_dg(A0, S, seed, k, 1, dg)
        acc += np.where(S, lin.apply(dg), 0.0) ** 2
    old = np.where(S, np.sqrt(acc / K), np.nan)
    assert np.array_equal(np.isnan(new), np.isnan(old)) and np.nanmax(old) > 0
    assert np.nanmax(np.abs(new - old)) < 10 * US.SIGMA_RTOL * np.nanmax(old)


def test_least_squares_integration_with_the_dct_preconditioner(monkeypatch):
    """The Gauss–Newton integration with its solves DCT-preconditioned (forced on a small full
    frame) reaches the multigrid-preconditioned result to 1e-9 mm (both converge to tol_mm)."""
    from pmdsim.evaluation import poisson as P
    from pmdsim.evaluation.pipeline import decode_simulated, evaluate_decoded
    from pmdsim.setup import default_setup
    from pmdsim.simulation.render import noise_generator, trace_setup_camera

    s = default_setup().binned(20).with_bulge(3.0).with_patterns(noise_std=2.0)
    m = trace_setup_camera(s, "left")
    dec = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, "left", stream=4))
    model = s.with_bulge(0.0)
    runs = {}
    real, calls = P.dct_pcg, []

    def counted(*a, **k):  # the real solver, counted: the "dct" run must take the DCT branch
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(P, "dct_pcg", counted)
    for kind in ("dct", "multigrid"):
        monkeypatch.setattr(P, "DCT_MIN_PIXELS", 0)
        monkeypatch.setattr(P, "DCT_MIN_FILL", 0.0 if kind == "dct" else 2.0)
        calls.clear()
        _, rec = evaluate_decoded(model, "left", dec, method="least_squares")
        assert rec.converged
        assert (len(calls) > 0) == (kind == "dct"), (kind, len(calls))
        runs[kind] = rec.height_mm
    assert dec.valid.all() and np.isfinite(runs["dct"]).all()
    assert np.max(np.abs(runs["dct"] - runs["multigrid"])) < 1e-9


def test_dct_pivots_converged_tail_and_parallel_transforms():
    """The inverse pivots per column converge to a limit that ``pivot_tail`` holds: right of
    ``pivot_cut[v]`` every stored value equals it (the substitution reads only the tail
    there), the limit is most of the array on a large grid, and the solve with the
    transforms split between two scipy.fft workers equals the one-worker solve bit for bit
    (the default follows numba's thread count)."""
    rng = np.random.default_rng(7)
    for H, W in ((1, 6), (2, 5), (240, 384)):
        for dtype in (np.float32, np.float64):
            lap = DCTLaplacian((H, W), (0, 0), dtype=dtype)
            im, tail, cut = lap.inv_pivots, lap.pivot_tail, lap.pivot_cut
            assert cut[-1] == W and np.array_equal(tail, im[max(H - 2, 0)])
            assert all(np.array_equal(im[v, cut[v]:], tail[cut[v]:]) for v in range(H))
    assert cut.sum() < 0.2 * H * W  # (240, 384), float64: the stored part is small
    b = rng.standard_normal((240, 384))
    one = DCTLaplacian((240, 384), (100, 200), dtype=np.float32, workers=1).solve(b)
    two = DCTLaplacian((240, 384), (100, 200), dtype=np.float32, workers=2).solve(b)
    assert np.array_equal(one, two)


def test_dct_pcg_stopped_by_max_iter_keeps_its_last_step():
    """With ``max_iter`` = 1 (not converged) X is CG's first step α z, z = M⁻¹ b the
    preconditioned right-hand side and α = (b·z)/(z·N z), N the sparse operator: the step
    X += αP deferred to the next pass over P is applied when the solve stops (without it X
    would be 0). z here is the double-precision DCT solve, the solver's single-precision
    one agrees to ≈ 1e-7 (relative)."""
    rng = np.random.default_rng(9)
    H, W, seed = 30, 44, (12, 5)
    D, Ex, Ey = _laplacian(np.ones((H, W), bool), seed, weights=0.05, rng=rng)
    A, unk = _sparse(D, Ex, Ey)
    B = np.zeros((1, H + 2, W + 2))
    B[0, 1:-1, 1:-1] = rng.standard_normal((H, W))
    B[0, D == 0] = 0.0
    X, its, conv = dct_pcg(D, Ex, Ey, B, seed, 0.0, 1e-13, 1)
    assert its[0] == 1 and not conv[0]
    z = DCTLaplacian((H, W), seed).solve(B[0, 1:-1, 1:-1]).ravel()[unk]
    b = B[0, 1:-1, 1:-1].ravel()[unk]
    ref = (b @ z) / (z @ (A @ z)) * z
    assert np.max(np.abs(X[0, 1:-1, 1:-1].ravel()[unk] - ref)) < 1e-6 * np.max(np.abs(ref))
