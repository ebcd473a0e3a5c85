"""The integrators' final pass, points on the view rays and their bisector normals
(``integration._points_and_normals``), against numpy: the same per-pixel formula evaluated
element-wise (IEEE operations in the same order, so equal bit for bit), the normals also
against :func:`normals_from_registration`; NaN heights give NaN points and normals; the
result does not depend on the number of threads."""

from __future__ import annotations

import numba
import numpy as np

from pmdsim.evaluation.integration import _points_and_normals, normals_from_registration


def _scene(H=9, W=37):
    """Camera 400 mm above a wavy surface over a tilted screen, with NaN heights; W odd so that
    vectorised loops have a remainder."""
    rng = np.random.default_rng(11)
    o = np.array([2.0, -3.0, 400.0])
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - W / 2) * 1.5 + rng.normal(size=(H, W)), (v - H / 2) * 1.5, -np.full((H, W), 400.0)], axis=-1)
    d *= rng.uniform(0.5, 2.0, size=(H, W, 1))  # any length
    z = 0.3 * np.sin(u / 5) + 0.01 * v + 1e-3 * rng.normal(size=(H, W))
    z[2, 5] = z[4, :3] = z[8, W - 1] = np.nan
    q = np.stack([u * 4.0 - 50.0, v * 4.0 + 10.0, 250.0 + 0.1 * u], axis=-1) + rng.normal(size=(H, W, 3))
    return o, np.ascontiguousarray(d), np.ascontiguousarray(q), z


def _reference(o, d, q, z):
    """p = o + t d with t = (z − o_z)/d_z, n = (a/|a| + b/|b|)/|…| (a = o − p, b = q − p), in
    numpy, term by term in the kernel's order."""
    t = (z - o[2]) / d[..., 2]
    px = o[0] + t * d[..., 0]
    py = o[1] + t * d[..., 1]
    a = [o[0] - px, o[1] - py, o[2] - z]
    b = [q[..., 0] - px, q[..., 1] - py, q[..., 2] - z]
    la = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    lb = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    n = [a[k] / la + b[k] / lb for k in range(3)]
    ln = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    return np.stack([px, py, z], axis=-1), np.stack([n[k] / ln for k in range(3)], axis=-1)


def test_points_normals_equal_numpy_reference_bit_for_bit():
    o, d, q, z = _scene()
    p_ref, n_ref = _reference(o, d, q, z)
    nan = np.isnan(z)
    threads = numba.get_num_threads()
    try:
        for th in sorted({1, threads}):
            numba.set_num_threads(th)
            p, n = _points_and_normals(o, d, q, z)
            assert p.shape == n.shape == d.shape
            assert np.array_equal(p, p_ref, equal_nan=True) and np.array_equal(n, n_ref, equal_nan=True)
            assert np.all(np.isnan(p[nan])) and np.all(np.isnan(n[nan]))
            assert np.all(np.isfinite(p[~nan])) and np.all(np.isfinite(n[~nan]))
    finally:
        numba.set_num_threads(threads)
    # The points lie on the view rays, the normals are the law of reflection's bisectors.
    ok = ~nan
    p_ray = o + ((z - o[2]) / d[..., 2])[..., None] * d
    assert np.allclose(p[ok], p_ray[ok], rtol=0, atol=1e-12)
    assert np.allclose(n[ok], normals_from_registration(p, o, q)[ok], rtol=0, atol=1e-15)
    assert np.allclose(np.linalg.norm(n[ok], axis=-1), 1.0, rtol=0, atol=1e-15)
