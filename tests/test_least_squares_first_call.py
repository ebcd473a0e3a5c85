"""The least-squares integration's work arrays carved from its outputs' memory
(``least_squares._Fields(backing=…)``, rc26): zeroed like fresh arrays, and the result — heights,
points, normals — the same bits as with fresh work arrays; the points and normals those of
``integration._points_and_normals`` at the returned heights."""

from __future__ import annotations

import numpy as np
from test_reconstruct import SEED, H, W, plane_scene

import pmdsim.evaluation.least_squares as LS
import pmdsim.evaluation.poisson as P
from pmdsim.evaluation.integration import _points_and_normals


def test_fields_are_carved_from_the_backing_while_a_buffer_fits():
    a = np.zeros((10, 10, 3))  # 2400 bytes: two 800-byte buffers at 64-byte boundaries (0, 832)
    b = np.zeros(50)  # 400 bytes: no float64 buffer of 100 elements fits
    f = LS._Fields(100, backing=(a, b))
    x, y, z = (f.zeros((10, 10)) for _ in range(3))
    assert np.shares_memory(x, a) and np.shares_memory(y, a) and not np.shares_memory(x, y)
    assert not np.shares_memory(z, a) and not np.shares_memory(z, b)  # fresh
    s = f.zeros((10, 10), np.float32)  # 400 bytes: the rest of a (736 bytes) holds it
    assert np.shares_memory(s, a) and not np.shares_memory(s, y)
    assert [arr.ctypes.data - a.ctypes.data for arr in (x, y, s)] == [0, 832, 1664]  # 64-byte steps
    for arr in (x, y, z, s):
        assert arr.flags.c_contiguous and not arr.any()
        arr[:] = 3.0
    f.reset()
    x2, y2 = f.zeros((5, 20)), f.zeros((4, 4))  # the same buffers, zeroed where written before
    assert np.shares_memory(x2, x) and np.shares_memory(y2, y)
    assert not x2.any() and not y2.any() and x2.shape == (5, 20)
    assert f.zeros((10, 10), np.float32).any() == 0.0


def test_result_is_the_same_with_fresh_work_arrays(monkeypatch):
    # Table-1-like path at test size: coarse-to-fine start (160×200 → 80×100 → 40×50 stepwise,
    # multigrid there) and the DCT-preconditioned solves on the upper levels.
    monkeypatch.setattr(LS, "_COARSE_START_MIN_PIXELS", 4000)
    monkeypatch.setattr(P, "DCT_MIN_PIXELS", 8000)
    o, d, q, z_true, _ = plane_scene()
    q = q + np.random.default_rng(5).normal(0.0, 0.05, q.shape)
    valid = np.ones((H, W), bool)
    rec = LS.reconstruct_least_squares(o, d, q, valid, SEED, z_true[SEED])

    class FreshFields(LS._Fields):  # the work arrays without the outputs' memory
        def __init__(self, size, backing=()):
            super().__init__(size)

    monkeypatch.setattr(LS, "_Fields", FreshFields)
    ref = LS.reconstruct_least_squares(o, d, q, valid, SEED, z_true[SEED])
    assert rec.converged and ref.converged and rec.iterations == ref.iterations >= 2
    assert np.array_equal(rec.height_mm, ref.height_mm)
    pts, nrm = _points_and_normals(o, d, q, rec.height_mm)
    assert np.array_equal(rec.p_sample_mm, pts) and np.array_equal(rec.n_sample, nrm)
    assert np.array_equal(ref.p_sample_mm, pts) and np.array_equal(ref.n_sample, nrm)
    assert np.abs(rec.height_mm - z_true).max() < 0.05  # the plane, to the slope noise
