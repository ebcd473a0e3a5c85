"""The anchored integration's DCT-preconditioned solve (evaluation/stereo_solve.py, issue 25):
the preconditioner against a dense pseudo-inverse, the solve and the whole anchored integration
against scipy's sparse direct solve, the start's level against the least-squares closed form."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from pmdsim.evaluation import poisson, stereo
from pmdsim.evaluation.least_squares import _assemble_gauss_newton
from pmdsim.evaluation.stereo_solve import LevelDCT, level_dct_pcg
from pmdsim.setup import default_setup
from pmdsim.simulation.render import trace_setup_camera


def _sparse(D, Ex, Ey):
    """The padded 5-point operator (multigrid.py's storage) as a sparse matrix over the frame."""
    H, W = D.shape[0] - 2, D.shape[1] - 2
    idx = np.arange(H * W).reshape(H, W)
    ex, ey = Ex[1:-1, 1:-2], Ey[1:-2, 1:-1]
    rows = [idx.ravel(), idx[:, :-1].ravel(), idx[:, 1:].ravel(), idx[:-1].ravel(), idx[1:].ravel()]
    cols = [idx.ravel(), idx[:, 1:].ravel(), idx[:, :-1].ravel(), idx[1:].ravel(), idx[:-1].ravel()]
    vals = [D[1:-1, 1:-1].ravel(), -ex.ravel(), -ex.ravel(), -ey.ravel(), -ey.ravel()]
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(H * W, H * W))


def _anchored_operator(H, W, rng, masked=(), stride=5, w2=1e-4):
    """An anchored 5-point operator like the integration's: edge weights 1 + O(1e-3), small
    Robin terms on the border, w² on every stride-th pixel; ``masked`` pixels are not unknowns."""
    D, Ex, Ey = (np.zeros((H + 2, W + 2)) for _ in range(3))
    Ex[1:-1, 1:-2] = 1.0 + 1e-3 * rng.standard_normal((H, W - 1))
    Ey[1:-2, 1:-1] = 1.0 + 1e-3 * rng.standard_normal((H - 1, W))
    for v, u in masked:
        Ex[v + 1, u:u + 2] = 0.0
        Ey[v:v + 2, u + 1] = 0.0
    D[1:-1, 1:-1] = Ex[1:-1, 1:-1] + Ex[1:-1, :-2] + Ey[1:-1, 1:-1] + Ey[:-2, 1:-1]
    D[1, 1:-1] += 5e-4 * rng.random(W)
    D[1 + stride // 2:-1:stride, 1 + stride // 2:-1:stride] += w2
    for v, u in masked:
        D[v + 1, u + 1] = 0.0
    return D, Ex, Ey


@pytest.mark.parametrize("masked", [(), ((3, 4), (7, 0))])
def test_preconditioner_is_the_pseudo_inverse_on_the_mean_free_part_plus_the_level(masked):
    H, W = 10, 14
    rng = np.random.default_rng(1)
    D, Ex, Ey = _anchored_operator(H, W, rng, masked)
    unknown = (D[1:-1, 1:-1] > 0).ravel()
    r = np.zeros((H + 2, W + 2))
    r[1:-1, 1:-1] = np.where(unknown.reshape(H, W), rng.standard_normal((H, W)), 0.0)
    pre = LevelDCT(D, Ex, Ey, poisson.DCTLaplacian((H, W), (2, 3), dtype=np.float32))
    Z = np.zeros((H + 2, W + 2), dtype=np.float32)
    rz, zmax = pre.apply(r, r[1:-1, 1:-1].astype(np.float32), float(r.sum()), Z)
    # dense reference: the unit Neumann Laplacian's pseudo-inverse, Π the mean over the frame
    n = H * W
    L = _sparse(*_unit_laplacian(H, W)).toarray()
    C = np.eye(n) - np.full((n, n), 1.0 / n)
    one = unknown.astype(float)
    kappa = one @ _sparse(D, Ex, Ey).toarray() @ one
    rr = r[1:-1, 1:-1].ravel()
    ref = one * (C @ np.linalg.pinv(L) @ C @ rr + rr.sum() / kappa)
    got = Z[1:-1, 1:-1].ravel().astype(float)
    assert np.max(np.abs(got - ref)) <= 1e-5 * np.max(np.abs(ref))
    assert rz == pytest.approx(rr @ ref, rel=1e-5) and zmax == pytest.approx(np.max(np.abs(ref)), rel=1e-5)


def _unit_laplacian(H, W):
    D, Ex, Ey = (np.zeros((H + 2, W + 2)) for _ in range(3))
    Ex[1:-1, 1:-2] = 1.0
    Ey[1:-2, 1:-1] = 1.0
    D[1:-1, 1:-1] = Ex[1:-1, 1:-1] + Ex[1:-1, :-2] + Ey[1:-1, 1:-1] + Ey[:-2, 1:-1]
    return D, Ex, Ey


@pytest.mark.parametrize("masked", [(), ((10, 11), (0, 5), (29, 39))])
def test_solve_matches_scipy_spsolve_of_the_anchored_system(masked):
    H, W = 30, 40
    rng = np.random.default_rng(2)
    D, Ex, Ey = _anchored_operator(H, W, rng, masked)
    b = np.zeros((H + 2, W + 2))
    b[1:-1, 1:-1] = np.where(D[1:-1, 1:-1] > 0, 1e-4 * rng.standard_normal((H, W)) + 3e-4, 0.0)  # a net force: a level
    x, its, ok = level_dct_pcg(D, Ex, Ey, b, 1e-13, 1e-12, 200)
    keep = (D[1:-1, 1:-1] > 0).ravel()
    A = _sparse(D, Ex, Ey)[keep][:, keep]
    ref = np.zeros(H * W)
    ref[keep] = spsolve(A.tocsc(), b[1:-1, 1:-1].ravel()[keep])
    assert ok and its < 60
    assert np.max(np.abs(x[1:-1, 1:-1].ravel() - ref)) <= 1e-10 * np.max(np.abs(ref))
    assert np.all(x[1:-1, 1:-1].ravel()[~keep] == 0.0)


def test_start_level_is_the_least_squares_level_of_the_anchors():
    rng = np.random.default_rng(3)
    z = rng.standard_normal((20, 30))
    vu = np.stack([rng.integers(0, 20, 50), rng.integers(0, 30, 50)], axis=-1)
    a = rng.standard_normal(50) + 2.0
    c_ref = np.linalg.lstsq(np.ones((50, 1)), a - z[vu[:, 0], vu[:, 1]], rcond=None)[0][0]
    assert stereo._anchor_level(z, vu, a) == pytest.approx(c_ref, rel=1e-13)


@pytest.fixture(scope="module")
def table1_binned():
    """One camera of Table 1 binned 12× (160 × 100 px, a full frame) with the other as partner:
    the anchored integration's inputs, from the tracer's exact screen points."""
    s = default_setup().binned(12)
    dec = {}
    for cam in s.cameras:
        m = trace_setup_camera(s, cam)
        dec[cam] = SimpleNamespace(screen_xy_mm=m.screen_xy_mm, valid=m.valid)
    views = stereo.stereo_views(s, dec)
    return views


def test_dct_path_matches_the_multigrid_path_and_scipy(table1_binned, monkeypatch):
    views = table1_binned
    calls = []

    def counted(*a, **k):
        calls.append(1)
        return level_dct_pcg(*a, **k)

    monkeypatch.setattr(stereo, "level_dct_pcg", counted)
    monkeypatch.setattr(poisson, "DCT_MIN_PIXELS", 10**9)  # the multigrid path
    mg = stereo.reconstruct_stereo(views)
    assert not calls
    monkeypatch.setattr(poisson, "DCT_MIN_PIXELS", 1000)  # the DCT path on this small frame
    dct = stereo.reconstruct_stereo(views)
    assert calls
    tol = 1e-9  # reconstruct_stereo's default tol_mm
    for cam in views:
        za, zb = mg.cameras[cam].height_mm, dct.cameras[cam].height_mm
        assert np.array_equal(np.isfinite(za), np.isfinite(zb)) and dct.cameras[cam].reconstruction.converged
        assert np.nanmax(np.abs(za - zb)) <= tol / 10
        # the DCT path's heights are the anchored least-squares solution: a Gauss–Newton step
        # there, solved by scipy, is below the tolerance
        o, d, q, valid = stereo._view_arrays(views[cam])
        c = dct.cameras[cam]
        vu, az = c.anchor_pixels, c.anchor_height_mm
        z = np.where(valid, zb, 0.0)
        H, W = valid.shape
        D, iD, Ex, Ey, rhs = (np.zeros((H + 2, W + 2)) for _ in range(5))
        _assemble_gauss_newton(o, d, q, np.ascontiguousarray(valid), z, -1, -1, D, iD, Ex, Ey, rhs)
        np.add.at(D, (vu[:, 0] + 1, vu[:, 1] + 1), stereo.ANCHOR_WEIGHT ** 2)
        np.add.at(rhs, (vu[:, 0] + 1, vu[:, 1] + 1), stereo.ANCHOR_WEIGHT ** 2 * (az - z[vu[:, 0], vu[:, 1]]))
        keep = (D[1:-1, 1:-1] > 0).ravel()
        step = spsolve(_sparse(D, Ex, Ey)[keep][:, keep].tocsc(), rhs[1:-1, 1:-1].ravel()[keep])
        assert np.max(np.abs(step)) < tol


def test_warm_up_integrates_its_flat_mirror_to_zero():
    # the synthetic screen points are the reflections in the plane z = 0 (closed form): the
    # anchored integration with anchors at 0 must return 0
    z = stereo.warm_up()
    assert z.shape == (320, 320) and np.max(np.abs(z)) < 1e-9
