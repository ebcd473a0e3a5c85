"""Surface reconstruction (paper §2.5) against closed forms.

The synthetic measurements are built here, independently of pmdsim: a pinhole camera at
o = (0, 300, −300) mm looks at the origin at 45° incidence; every view ray is intersected
analytically with a plane or a paraboloid, reflected analytically (r = d − 2 (d·n) n), and the
registered screen point is taken somewhere on the reflected ray (q = p + L·r with L varying
between 400 and 600 mm: any point of the ray is a valid registration).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from pmdsim.evaluation.reconstruction import (
    Reconstruction,
    ReconstructionError,
    normals_from_registration,
    reconstruct,
    reconstruct_least_squares,
    reconstruct_stepwise,
)

H, W = 160, 200          # pixels
F_PX = 430.0             # focal length: ≈ 200 mm × 150 mm (perpendicular to the view) at 424 mm
O_MM = np.array([0.0, 300.0, -300.0])
SEED = (80, 100)
TOL_SPEC_MM = 1e-4       # 0.1 µm, the requirement
TOL_EXACT_MM = 1e-8      # the trapezoidal rule is exact for degree ≤ 2: only round-off remains

METHODS = ["stepwise", "least_squares"]


def _run(method, *args, **kwargs) -> Reconstruction:
    fn = reconstruct_stepwise if method == "stepwise" else reconstruct_least_squares
    return fn(*args, **kwargs)


# ------------------------------------------------------------------------------------------
# Synthetic scenes (closed forms)
# ------------------------------------------------------------------------------------------


def _view_rays(o, rng=None):
    """Pinhole rays of an H×W camera at o whose optical axis points at the origin; optionally
    with random positive lengths (the direction's length must not matter)."""
    z_c = -o / np.linalg.norm(o)
    x_c = np.array([1.0, 0.0, 0.0])  # perpendicular to z_c since o_x = 0
    y_c = np.cross(z_c, x_c)
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = ((u - (W - 1) / 2) / F_PX)[..., None] * x_c + ((v - (H - 1) / 2) / F_PX)[..., None] * y_c + z_c
    if rng is not None:
        d = d * rng.uniform(0.5, 2.0, size=(H, W, 1))
    return d


def _reflect_to_screen(p, d, n, rng):
    """Screen points on the analytically reflected rays, at random distances 400…600 mm."""
    dh = d / np.linalg.norm(d, axis=-1, keepdims=True)
    r = dh - 2.0 * np.sum(dh * n, axis=-1, keepdims=True) * n
    L = rng.uniform(400.0, 600.0, size=p.shape[:-1] + (1,))
    return p + L * r


def plane_scene(c0=0.5, a=1e-3, b=-2e-3, seed=0):
    """z = c0 + a·x + b·y. Returns o, d, q, true heights, true unit normals (+z up)."""
    rng = np.random.default_rng(seed)
    o = O_MM.copy()
    d = _view_rays(o, rng)
    t = (c0 + a * o[0] + b * o[1] - o[2]) / (d[..., 2] - a * d[..., 0] - b * d[..., 1])
    p = o + t[..., None] * d
    n = np.array([-a, -b, 1.0]) / np.sqrt(a * a + b * b + 1.0)
    n = np.broadcast_to(n, p.shape)
    q = _reflect_to_screen(p, d, n, rng)
    return o, d, q, p[..., 2], n


def paraboloid_scene(R=5000.0, seed=1):
    """z = (x² + y²)/(2R). Returns o, d, q, true heights, true unit normals (+z up)."""
    rng = np.random.default_rng(seed)
    o = O_MM.copy()
    d = _view_rays(o, rng)
    # (o_z + t d_z) = ((o_x + t d_x)² + (o_y + t d_y)²)/(2R): A t² + B t + C = 0
    A = (d[..., 0] ** 2 + d[..., 1] ** 2) / (2 * R)
    B = (o[0] * d[..., 0] + o[1] * d[..., 1]) / R - d[..., 2]
    C = (o[0] ** 2 + o[1] ** 2) / (2 * R) - o[2]
    disc = np.sqrt(B * B - 4 * A * C)
    qq = -0.5 * (B + np.copysign(disc, B))  # numerically stable roots qq/A and C/qq
    roots = np.stack([qq / A, C / qq], axis=-1)
    roots[roots <= 0] = np.inf
    t = roots.min(axis=-1)  # the first intersection in front of the camera
    p = o + t[..., None] * d
    assert np.allclose(p[..., 2], (p[..., 0] ** 2 + p[..., 1] ** 2) / (2 * R), rtol=0, atol=1e-12)
    n = np.stack([-p[..., 0] / R, -p[..., 1] / R, np.ones_like(t)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    q = _reflect_to_screen(p, d, n, rng)
    return o, d, q, p[..., 2], n


def _flip_z(o, d, q, z, n):
    """The same scene in a frame whose z axis is reversed (camera above the surface)."""
    f = np.array([1.0, 1.0, -1.0])
    return o * f, d * f, q * f, -z, n * f


def _objective(rec_z, o, d, q, mask):
    """Sum of squared trapezoidal residuals z_b − z_a − ½(g_a + g_b)·(xy_b − xy_a) over all
    4-neighbour pairs in mask, with points on the rays and slopes of the bisector normal
    (implemented here, independently of the module)."""
    t = (rec_z - o[2]) / d[..., 2]
    p = o + t[..., None] * d
    a = o - p
    b = q - p
    m = a / np.linalg.norm(a, axis=-1, keepdims=True) + b / np.linalg.norm(b, axis=-1, keepdims=True)
    g = -m[..., :2] / m[..., 2:3]
    total = 0.0
    for sa, sb in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
        e = mask[sa] & mask[sb]
        res = (p[sb][..., 2] - p[sa][..., 2]) - np.sum(0.5 * (g[sa] + g[sb]) * (p[sb][..., :2] - p[sa][..., :2]), axis=-1)
        total += float(np.sum(res[e] ** 2))
    return total


# ------------------------------------------------------------------------------------------
# Normals
# ------------------------------------------------------------------------------------------


def test_normals_from_registration_match_analytic_normals():
    for scene in (plane_scene(), paraboloid_scene()):
        o, d, q, z, n_true = scene
        t = (z - o[2]) / d[..., 2]
        p = o + t[..., None] * d
        n = normals_from_registration(p, o, q)
        assert n.shape == (H, W, 3)
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-14)
        # Oriented towards the camera (which is below the surface here): n = −n_true.
        assert np.all(np.sum(n * (o - p), axis=-1) > 0)
        np.testing.assert_allclose(n, -n_true, atol=1e-12)


def test_normals_broadcast_and_degenerate():
    p = np.zeros(3)
    o = np.array([0.0, -1.0, -1.0])
    q = np.array([[0.0, 1.0, -1.0], [0.0, 0.0, -5.0], [3.0, -2.0, -0.5]])
    n = normals_from_registration(p, o, q)  # (3,), (3,), (3, 3) broadcast
    assert n.shape == (3, 3)
    np.testing.assert_allclose(n[0], [0.0, 0.0, -1.0], atol=1e-15)  # symmetric case
    a = (o - p) / np.linalg.norm(o - p)
    b = (q - p) / np.linalg.norm(q - p, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-15)
    # Law of reflection: equal angles to both directions, in their plane, on their side.
    np.testing.assert_allclose(n @ a, np.sum(n * b, axis=-1), atol=1e-15)
    np.testing.assert_allclose(np.sum(np.cross(a, b) * n, axis=-1), 0.0, atol=1e-15)
    assert np.all(n @ a > 0)
    # p coincides with q: undefined.
    assert np.all(np.isnan(normals_from_registration([1.0, 2, 3], [0.0, 0, 0], [1.0, 2, 3])))
    with pytest.raises(ReconstructionError, match="q"):
        normals_from_registration(p, o, q[:, :2])


# ------------------------------------------------------------------------------------------
# Exact surfaces
# ------------------------------------------------------------------------------------------


def _check_exact(rec, o, d, z_true, n_true, valid, seed, seed_height, method):
    assert isinstance(rec, Reconstruction)
    assert rec.method == method
    assert rec.converged
    assert rec.seed_pixel == seed
    assert rec.reconstructed.shape == (H, W) and rec.reconstructed.dtype == bool
    assert np.array_equal(rec.reconstructed, valid)
    assert rec.height_mm[seed] == seed_height
    err = np.abs(rec.height_mm - z_true)[valid]
    assert err.max() < TOL_SPEC_MM
    assert err.max() < TOL_EXACT_MM, err.max()
    assert np.all(np.isnan(rec.height_mm[~valid]))
    # Points lie on the view rays at the reconstructed heights.
    np.testing.assert_array_equal(rec.p_sample_mm[..., 2][valid], rec.height_mm[valid])
    off_ray = np.cross(rec.p_sample_mm - o, d)[valid]
    assert np.abs(off_ray).max() < 1e-9 * np.abs(d).max()
    np.testing.assert_allclose(np.abs(np.sum(rec.n_sample * n_true, axis=-1))[valid], 1.0, atol=1e-12)
    return err.max()


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scene", [plane_scene, paraboloid_scene], ids=["plane", "paraboloid"])
def test_exact_surface_recovered(method, scene):
    o, d, q, z_true, n_true = scene()
    valid = np.ones((H, W), bool)
    rec = _run(method, o, d, q, valid, seed_pixel=SEED, seed_height_mm=z_true[SEED])
    _check_exact(rec, o, d, z_true, n_true, valid, SEED, z_true[SEED], method)
    if method == "least_squares":
        assert rec.iterations >= 1


@pytest.mark.parametrize("method", METHODS)
def test_camera_above_the_surface(method):
    """The same paraboloid in a frame with reversed z: heights flip sign, nothing else changes."""
    o, d, q, z_true, n_true = _flip_z(*paraboloid_scene())
    assert o[2] > 0
    valid = np.ones((H, W), bool)
    rec = _run(method, o, d, q, valid, seed_pixel=(10, 190), seed_height_mm=z_true[10, 190])
    _check_exact(rec, o, d, z_true, n_true, valid, (10, 190), z_true[10, 190], method)
    assert np.all(np.sum(rec.n_sample * (o - rec.p_sample_mm), axis=-1) > 0)


@pytest.mark.parametrize("method", METHODS)
def test_default_seed_is_valid_pixel_nearest_to_centroid(method):
    o, d, q, z_true, n_true = plane_scene()
    valid = np.ones((H, W), bool)
    # Centroid (79.5, 99.5): four pixels tie; the first in row-major order wins.
    rec = _run(method, o, d, q, valid, seed_height_mm=z_true[79, 99])
    assert rec.seed_pixel == (79, 99)
    _check_exact(rec, o, d, z_true, n_true, valid, (79, 99), z_true[79, 99], method)
    # A mask whose centroid falls into a hole: the nearest valid pixel is used.
    valid2 = valid.copy()
    valid2[70:91, 90:111] = False
    valid2[:, :20] = False  # centroid moves right, to (79.5, 109.5)
    rec2 = reconstruct(o, d, q, valid2, method=method, seed_height_mm=z_true[79, 111])
    assert rec2.seed_pixel == (79, 111)
    assert np.abs(rec2.height_mm - z_true)[valid2].max() < TOL_EXACT_MM


# ------------------------------------------------------------------------------------------
# Irregular masks
# ------------------------------------------------------------------------------------------


def _irregular_mask():
    rng = np.random.default_rng(7)
    v, u = np.mgrid[0:H, 0:W]
    valid = np.ones((H, W), bool)
    valid &= (v - 40) ** 2 + (u - 50) ** 2 > 15 ** 2           # a round hole
    valid[20:140, 140:143] = False                              # a slit, open at both ends
    valid &= rng.random((H, W)) > 0.08                          # 8 % dropouts
    valid[100:150, 20:70] = False                               # a square hole …
    valid[115:135, 35:55] = True                                # … with an island inside
    # A pixel touching the main region only diagonally: not 4-connected.
    valid[4:9, 176:181] = False
    valid[6, 178] = True
    valid[7:10, 179] = True
    valid[SEED] = True
    return valid


@pytest.mark.parametrize("method", METHODS)
def test_irregular_mask(method):
    o, d, q, z_true, n_true = paraboloid_scene()
    valid = _irregular_mask()
    labels, _ = ndimage.label(valid)  # 4-connectivity
    component = labels == labels[SEED]
    assert component.sum() < valid.sum()
    assert not component[6, 178] and valid[6, 178]        # the diagonal-only pixel
    assert not component[115:135, 35:55].any()            # the island
    rec = _run(method, o, d, q, valid, seed_pixel=SEED, seed_height_mm=z_true[SEED])
    assert rec.converged
    assert np.array_equal(rec.reconstructed, component)
    assert np.all(np.isfinite(rec.height_mm[component]))
    assert np.all(np.isnan(rec.height_mm[~component]))
    assert np.all(np.isnan(rec.p_sample_mm[~component])) and np.all(np.isnan(rec.n_sample[~component]))
    err = np.abs(rec.height_mm - z_true)[component].max()
    assert err < TOL_SPEC_MM
    assert err < TOL_EXACT_MM, err


# ------------------------------------------------------------------------------------------
# Noisy registration: what least squares adds
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def noisy():
    o, d, q, z_true, n_true = plane_scene()
    q = q + np.random.default_rng(11).normal(0.0, 0.05, q.shape)  # 50 µm registration noise
    valid = np.ones((H, W), bool)
    st = reconstruct_stepwise(o, d, q, valid, SEED, z_true[SEED])
    ls = reconstruct_least_squares(o, d, q, valid, SEED, z_true[SEED])
    return o, d, q, z_true, valid, st, ls


def test_noisy_least_squares_beats_stepwise(noisy):
    o, d, q, z_true, valid, st, ls = noisy
    assert st.converged and ls.converged
    assert ls.iterations >= 2  # the stepwise start is not the least-squares solution
    assert ls.final_change_mm < 1e-9
    rms_st = np.sqrt(np.mean((st.height_mm - z_true)[valid] ** 2))
    rms_ls = np.sqrt(np.mean((ls.height_mm - z_true)[valid] ** 2))
    # Path integration accumulates the slope noise like a random walk; LS averages it.
    assert rms_ls < 0.3 * rms_st
    assert _objective(ls.height_mm, o, d, q, valid) < 0.5 * _objective(st.height_mm, o, d, q, valid)


def test_noisy_least_squares_is_a_minimum(noisy):
    """Perturbing the LS heights (seed fixed) in any direction increases the sum of squared
    trapezoidal residuals, evaluated by the test's own implementation."""
    o, d, q, z_true, valid, st, ls = noisy
    v, u = np.mgrid[0:H, 0:W].astype(float)
    rng = np.random.default_rng(5)
    directions = [
        (u - SEED[1]) / W,                                               # a tilt about the seed
        np.exp(-((v - 40) ** 2 + (u - 150) ** 2) / (2 * 20.0 ** 2)),     # a bump
        np.cos(np.pi * v / 7) * np.cos(np.pi * u / 9),                   # a ripple
        rng.normal(size=(H, W)),                                         # noise
    ]
    f0 = _objective(ls.height_mm, o, d, q, valid)
    for phi in directions:
        phi = phi - phi[SEED]
        phi = phi / np.abs(phi).max()
        for eps in (1e-4, -1e-4):
            assert _objective(ls.height_mm + eps * phi, o, d, q, valid) > f0
    # The stepwise solution is not a minimum: some of these directions decrease the objective.
    f_st = _objective(st.height_mm, o, d, q, valid)
    assert any(_objective(st.height_mm + s * 1e-4 * (p - p[SEED]) / np.abs(p - p[SEED]).max(), o, d, q, valid) < f_st
               for p in directions for s in (1, -1))


# ------------------------------------------------------------------------------------------
# Coarse-to-fine start of the least-squares integration (used for large images; forced here)
# ------------------------------------------------------------------------------------------


@pytest.fixture
def coarse_start(monkeypatch):
    """Make the least-squares integration start coarse to fine already for these small images
    (160×200 → 80×100 → 40×50; the 40×50 level starts stepwise)."""
    import pmdsim.evaluation.least_squares as rc

    monkeypatch.setattr(rc, "_COARSE_START_MIN_PIXELS", 4000)
    calls = []
    original = rc._coarse_mask

    def spy(S, seed):
        calls.append(S.shape)
        return original(S, seed)

    monkeypatch.setattr(rc, "_coarse_mask", spy)
    return calls


@pytest.mark.parametrize("seed", [SEED, (81, 101), (0, 199), (159, 0)], ids=["even", "odd", "corner_tr", "corner_bl"])
@pytest.mark.parametrize("scene", [plane_scene, paraboloid_scene], ids=["plane", "paraboloid"])
def test_coarse_start_exact_surface(coarse_start, scene, seed):
    """Closed-form surfaces are recovered exactly whatever the seed's parity (the coarse grid
    is aligned with the seed) and however the image border falls on the coarse grid."""
    o, d, q, z_true, n_true = scene()
    valid = np.ones((H, W), bool)
    rec = reconstruct_least_squares(o, d, q, valid, seed_pixel=seed, seed_height_mm=z_true[seed])
    assert coarse_start == [(H, W), (H // 2, W // 2)]
    _check_exact(rec, o, d, z_true, n_true, valid, seed, z_true[seed], "least_squares")


def test_coarse_start_camera_above(coarse_start):
    o, d, q, z_true, n_true = _flip_z(*paraboloid_scene())
    valid = np.ones((H, W), bool)
    rec = reconstruct_least_squares(o, d, q, valid, seed_pixel=(10, 190), seed_height_mm=z_true[10, 190])
    assert coarse_start
    _check_exact(rec, o, d, z_true, n_true, valid, (10, 190), z_true[10, 190], "least_squares")


def test_coarse_start_irregular_mask(coarse_start):
    """Holes, a slit, dropouts and an island: the coarse problem must not bridge gaps of the
    mask, and the pixels next to them are filled stepwise; the result is exact."""
    o, d, q, z_true, n_true = paraboloid_scene()
    valid = _irregular_mask()
    labels, _ = ndimage.label(valid)
    component = labels == labels[SEED]
    rec = reconstruct_least_squares(o, d, q, valid, seed_pixel=SEED, seed_height_mm=z_true[SEED])
    assert coarse_start
    assert rec.converged
    assert np.array_equal(rec.reconstructed, component)
    assert np.all(np.isnan(rec.height_mm[~component]))
    assert np.abs(rec.height_mm - z_true)[component].max() < TOL_EXACT_MM


def test_coarse_start_reaches_the_same_minimum(noisy, coarse_start):
    """With noise the start differs (coarse solution vs stepwise solution), but the minimum of
    the sum of squared trapezoidal residuals is unique: both iterations must end there, to
    within the convergence tolerance."""
    o, d, q, z_true, valid, st, ls = noisy
    ls2 = reconstruct_least_squares(o, d, q, valid, SEED, z_true[SEED])
    assert coarse_start
    assert ls2.converged and ls2.final_change_mm < 1e-9
    assert np.abs(ls2.height_mm - ls.height_mm)[valid].max() < 1e-8
    # … and it is a minimum of the test's own objective.
    f0 = _objective(ls2.height_mm, o, d, q, valid)
    bump = np.exp(-((np.mgrid[0:H, 0:W][0] - 40.0) ** 2 + (np.mgrid[0:H, 0:W][1] - 150.0) ** 2) / (2 * 20.0 ** 2))
    bump -= bump[SEED]
    for eps in (1e-4, -1e-4):
        assert _objective(ls2.height_mm + eps * bump, o, d, q, valid) > f0


# ------------------------------------------------------------------------------------------
# Dispatch, result type, errors
# ------------------------------------------------------------------------------------------


def test_dispatch_and_frozen_result():
    o, d, q, z_true, _ = plane_scene()
    valid = np.ones((H, W), bool)
    a = reconstruct(o, d, q, valid, method="least_squares", seed_pixel=SEED, seed_height_mm=z_true[SEED],
                    max_iter=1, tol_mm=1e-6)
    assert a.method == "least_squares" and a.iterations == 1
    b = reconstruct(o, d, q, valid, seed_pixel=SEED, seed_height_mm=z_true[SEED])
    assert b.method == "stepwise"
    with pytest.raises(dataclasses.FrozenInstanceError):
        b.method = "x"
    with pytest.raises(ReconstructionError, match="method"):
        reconstruct(o, d, q, valid, method="poisson")
    with pytest.raises(ReconstructionError, match="max_iter"):
        reconstruct(o, d, q, valid, method="stepwise", max_iter=3)


def _error_cases():
    o, d, q, z_true, _ = plane_scene()
    valid = np.ones((H, W), bool)
    d_flat = d.copy()
    d_flat[3, 4, 2] = 0.0
    q_nan = q.copy()
    q_nan[5, 6, 1] = np.nan
    invalid_seed = valid.copy()
    invalid_seed[SEED] = False
    return [
        ("o_shape", dict(o=o[:2]), r"\bo\b.*shape \(3,\)"),
        ("d_shape", dict(d=d[..., :2]), r"\bd\b.*shape \(H, W, 3\)"),
        ("q_shape", dict(q=q[1:]), r"\bq\b.*\(160, 200, 3\)"),
        ("valid_shape", dict(valid=valid[:, 1:]), r"\bvalid\b.*\(160, 200\)"),
        ("no_valid", dict(valid=np.zeros((H, W), bool)), r"\bvalid\b"),
        ("d_z_zero", dict(d=d_flat), r"\bd\b.*d_z == 0.*row 3, column 4"),
        ("q_nan", dict(q=q_nan), r"\bq\b.*non-finite.*row 5, column 6"),
        ("seed_out_of_range", dict(seed_pixel=(H, 0)), r"seed_pixel.*outside"),
        ("seed_negative", dict(seed_pixel=(-1, 0)), r"seed_pixel.*outside"),
        ("seed_not_valid", dict(valid=invalid_seed, seed_pixel=SEED), r"seed_pixel.*not a valid pixel"),
        ("seed_not_integer", dict(seed_pixel=(1.5, 2)), r"seed_pixel"),
        ("seed_not_pair", dict(seed_pixel=7), r"seed_pixel"),
        ("seed_behind_camera", dict(seed_height_mm=-1000.0), r"seed_height_mm.*behind the camera"),
    ], (o, d, q, valid)


_CASES, _BASE = _error_cases()


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name,override,pattern", _CASES, ids=[c[0] for c in _CASES])
def test_errors_name_the_argument(method, name, override, pattern):
    o, d, q, valid = _BASE
    kwargs = dict(o=o, d=d, q=q, valid=valid, seed_pixel=SEED, seed_height_mm=0.5)
    kwargs.update(override)
    with pytest.raises(ReconstructionError, match=pattern) as info:
        _run(method, **kwargs)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize("kwargs,pattern", [(dict(max_iter=0), "max_iter"), (dict(max_iter=2.5), "max_iter"),
                                            (dict(max_iter="3"), "max_iter"), (dict(tol_mm=0.0), "tol_mm"),
                                            (dict(tol_mm=float("nan")), "tol_mm"), (dict(tol_mm="1e-9"), "tol_mm")])
def test_least_squares_option_errors(kwargs, pattern):
    o, d, q, valid = _BASE
    with pytest.raises(ReconstructionError, match=pattern):
        reconstruct_least_squares(o, d, q, valid, SEED, 0.5, **kwargs)
