"""The calibration's batched normal equations (:mod:`pmdsim.calibration.batch_rows`: model rows
and Jacobian vectorised across correspondences) against the scalar per-correspondence model
:func:`pmdsim.calibration.kernel._model_row` (through ``_rows_kernel``, the rows of
:func:`residuals_and_jacobian`, which test_calibration.py checks against central differences),
bit for bit: the reference gathers the scalar rows into the interleaved batch layout in numpy,
squeezing out the points behind the camera, and adds each batch with the same Gram product.

Synthetic blocks (random distorted cameras and mirror planes, no ray tracing) with chunks of
every length around the batch size, points behind the camera and free screen heights.
"""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.calibration.batch_rows import _BATCH, _gram_add
from pmdsim.calibration.glass_kernel import _dummies
from pmdsim.calibration.kernel import _chunks_kernel, _rows_kernel
from pmdsim.calibration.model import _CAM_UNITS, _MIR_UNITS, _NB, SCREEN_HEIGHT_UNIT_MM
from pmdsim.geometry.transform import rotvec_to_matrix


def _problem(rng, n, n_heights):
    """Two cameras, three mirror planes, ``n`` correspondences with screen points in front of
    and (about one in eight) behind the camera, basis weights of ``n_heights`` free heights."""
    n_cam, n_mir = 2, 3
    intr = np.array([[1500.0 + 100 * c, 1490.0, 640.0, 480.0, -0.2, 0.05, 1e-3, -2e-3, 0.01] for c in range(n_cam)])
    rot = np.array([rotvec_to_matrix(rng.normal(scale=0.2, size=3)) for _ in range(n_cam)])
    cen = rng.normal(scale=50.0, size=(n_cam, 3))
    normals = rng.normal(scale=0.1, size=(n_mir, 3)) + [0.0, 0.0, 1.0]
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    mir = np.c_[normals, rng.uniform(-20.0, 20.0, n_mir)]
    e1 = np.cross(normals, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(normals, e1)
    cam = rng.integers(0, n_cam, n)
    pose = rng.integers(0, n_mir, n)
    # Virtual points p in the camera frame (z mostly > 0), mapped back to screen points q.
    p = np.c_[rng.uniform(-300.0, 300.0, (n, 2)), rng.uniform(400.0, 900.0, n)]
    p[rng.random(n) < 0.125, 2] *= -1.0
    w = np.einsum("nij,nj->ni", rot[cam], p) + cen[cam]
    nrm, d = mir[pose, :3], mir[pose, 3]
    q = w - 2.0 * ((w * nrm).sum(1) - d)[:, None] * nrm
    uv = rng.uniform(0.0, 1000.0, (n, 2))
    wx = rng.uniform(-1.0, 1.0, (n, 4))
    wy = rng.uniform(-1.0, 1.0, (n, 4))
    fi = np.arange(n_heights, dtype=np.int64) % 4
    fj = (np.arange(n_heights, dtype=np.int64) * 3 + 1) % 4
    return cam, pose, uv, q, (intr, rot, cen, mir, e1, e2), wx, wy, fi, fj


def _reference(k_start, k_end, cam, pose, uv, q, arrays, units, wx, wy, fi, fj):
    """[J r]ᵀ[J r] of one chunk from the scalar rows, in the batched layout; (JᵀJ, Jᵀr, SSR, bad)."""
    m = k_end - k_start
    res = np.empty((m, 2))
    jac = np.empty((m, 2, _NB + 3))
    ok = np.empty(m, dtype=np.bool_)
    gl0, *_ = _dummies()
    sl = slice(k_start, k_end)
    _rows_kernel(np.full(m, cam), np.full(m, pose), uv[sl], q[sl], *arrays, res, jac, ok, False, gl0,
                 np.zeros((m, 2, 4)))
    nf = fi.shape[0]
    npar = _NB + nf
    ncol = npar + 1 + ((npar + 1) & 1)
    rows = []
    ssr = 0.0
    for i in np.flatnonzero(ok):
        col = np.zeros((2, ncol))
        col[:, :_NB] = jac[i, :, :_NB] * units
        sf = wy[k_start + i, fj] * wx[k_start + i, fi]
        col[:, _NB:npar] = (jac[i, :, _NB] * SCREEN_HEIGHT_UNIT_MM)[:, None] * sf
        col[:, npar] = res[i]
        ssr += res[i, 0] * res[i, 0] + res[i, 1] * res[i, 1]
        rows.extend(col)
    acc = np.zeros((ncol, ncol))
    for b0 in range(0, len(rows), 2 * _BATCH):
        bt = np.zeros((ncol, 2 * _BATCH))
        part = np.array(rows[b0:b0 + 2 * _BATCH]).T
        bt[:, :part.shape[1]] = part
        _gram_add(bt, part.shape[1], acc)
    upper = np.triu(acc[:npar, :npar])
    return upper + np.triu(upper, 1).T, acc[:npar, npar].copy(), ssr, m - int(ok.sum())


@pytest.mark.parametrize("n_heights", [0, 3])
def test_batched_normal_equations_equal_the_scalar_rows_bit_for_bit(n_heights):
    rng = np.random.default_rng(11 + n_heights)
    lengths = [1, 2, _BATCH - 1, _BATCH, _BATCH + 1, 2 * _BATCH + 7, 517]
    n = sum(lengths)
    cam, pose, uv, q, arrays, wx, wy, fi, fj = _problem(rng, n, n_heights)
    ends = np.cumsum(lengths)
    c_start = np.r_[0, ends[:-1]].astype(np.int64)
    c_end = ends.astype(np.int64)
    c_cam = cam[c_start].astype(np.int64)
    c_pose = pose[c_start].astype(np.int64)
    nch = len(lengths)
    npar = _NB + n_heights
    jtj = np.empty((nch, npar, npar))
    jtr = np.empty((nch, npar))
    ssr = np.empty(nch)
    ssr_w = np.empty(nch)
    nbad = np.empty(nch, dtype=np.int64)
    units = np.concatenate([_CAM_UNITS, _MIR_UNITS])
    gl0, dwx, dwy, gsel, g_units = _dummies()
    _chunks_kernel(c_start, c_end, c_cam, c_pose, uv, q, *arrays, units, wx, wy, fi, fj, SCREEN_HEIGHT_UNIT_MM,
                   True, jtj, jtr, ssr, nbad, False, np.zeros((1, 2)), np.zeros((1, 2)), ssr_w, False, gl0, dwx,
                   dwy, gsel, g_units)
    assert nbad.sum() > 0  # the squeezing of points behind the camera is exercised
    for c in range(nch):
        a, g, s, bad = _reference(c_start[c], c_end[c], c_cam[c], c_pose[c], uv, q, arrays, units, wx, wy, fi, fj)
        assert nbad[c] == bad
        assert ssr[c] == s
        np.testing.assert_array_equal(jtj[c], a)
        np.testing.assert_array_equal(jtr[c], g)
