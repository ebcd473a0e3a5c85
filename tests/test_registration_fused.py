"""The fused registration (issue 25, item 1): status, view rays and screen points of
:func:`pmdsim.evaluation.registration.register` without a cover glass against numpy's masks,
heights and transforms written out here (the paper's §2.5 steps, as before the fused pass) — the
status bit for bit; rays and points with the same NaN pattern and within 4 units in the last place of
each array's largest value, for a spline, plane and quadric screen model, and with blocks that end
one row before the image does. On this machine the fused pass reproduces numpy's bits (its rotation
is OpenBLAS's multiply-add order, written as FMAs, docs/benchmarks.md); the test does not demand
that, because OpenBLAS chooses its kernel, and so its rounding order, by processor."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation import registration as R
from pmdsim.evaluation.registration import RegistrationStatus, register
from pmdsim.geometry.shapes import QuadricSurface
from pmdsim.geometry.surface import PlaneSurface, SplineSurface
from pmdsim.geometry.transform import RigidTransform
from pmdsim.setup import default_setup


def _reference(camera, T_world_cam, screen_model, T_world_screen, xy, ok, T_world_ref):
    """The registration in numpy: masks, the screen model's heights on the full grid, stacked
    points, then the transforms (RigidTransform.apply: ``p @ R.T``, ``+= t``)."""
    d_cam, converged = camera.sensor_rays()
    x, y = xy[..., 0], xy[..., 1]
    x0, x1, y0, y1 = screen_model.bounds_mm
    with np.errstate(invalid="ignore"):
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    status = np.zeros(camera.shape, np.uint8)
    status[~inside] = RegistrationStatus.OUTSIDE_SCREEN_MODEL
    status[~converged] = RegistrationStatus.UNDISTORT_FAILED
    status[~ok] = RegistrationStatus.NOT_DECODED
    valid = status == 0
    h = screen_model.height(np.where(valid, x, x0), np.where(valid, y, y0))
    q = np.stack([x, y, h], axis=-1)
    q[~valid] = np.nan
    T_ref_world = T_world_ref.inv()
    T_s = T_ref_world @ T_world_screen
    T_c = T_ref_world @ T_world_cam
    q_ref = q @ T_s.rotation.T
    q_ref += T_s.translation
    return status, d_cam @ T_c.rotation.T, q_ref


def _tilted(T_world_screen):
    """The screen pose turned by a few degrees: a rotation without exact zeros and ones (the
    rounding of every product shows)."""
    return T_world_screen @ RigidTransform.from_rotvec(np.array([0.03, -0.05, 0.07]), np.array([1.0, -2.0, 3.0]))


def _same(a, b):
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True) and np.array_equal(
        np.signbit(a), np.signbit(b))


def _close(a, b):
    """Same shape, dtype and NaN pattern; elsewhere within 4 ulp of ``b``'s largest magnitude (a sum of
    three products rounded in another order differs by at most a few ulp of its largest term)."""
    if a.shape != b.shape or a.dtype != b.dtype or not np.array_equal(np.isnan(a), np.isnan(b)):
        return False
    fin = ~np.isnan(b)
    return bool(np.all(np.abs(a[fin] - b[fin]) <= 4 * np.spacing(np.max(np.abs(b[fin])))))


@pytest.mark.parametrize("model", ["spline_zero", "spline", "plane", "quadric"])
@pytest.mark.parametrize("block", [None, 7])
def test_fused_registration_matches_numpy(model, block, monkeypatch):
    setup = default_setup().binned(48)
    cs = setup.cameras["left"]
    scr = setup.screen
    gx, gy = scr.grid_x_mm, scr.grid_y_mm
    rng = np.random.default_rng(3)
    screen = {"spline_zero": SplineSurface(gx, gy, np.zeros((len(gy), len(gx)))),
              "spline": SplineSurface(gx, gy, rng.normal(0.0, 0.05, (len(gy), len(gx)))),
              "plane": PlaneSurface((gx[0], gx[-1]), (gy[0], gy[-1])),
              "quadric": QuadricSurface.paraboloid(gx, gy, 5000.0, 8000.0)}[model]
    shape = cs.camera.shape
    xy = np.stack([rng.uniform(gx[0] - 20, gx[-1] + 20, shape), rng.uniform(gy[0] - 20, gy[-1] + 20, shape)], -1)
    xy[rng.random(shape) < 0.05] = np.nan
    ok = rng.random(shape) < 0.9
    if block is not None:  # many blocks
        monkeypatch.setattr(R, "_BLOCK_PX", block)
    reg = register(cs.camera, cs.T_world_cam, screen, _tilted(scr.T_world_screen), xy, ok, setup.sample.T_world_sample)
    status, d_ref, q_ref = _reference(cs.camera, cs.T_world_cam, screen, _tilted(scr.T_world_screen), xy, ok,
                                      setup.sample.T_world_sample)
    assert _same(reg.status, status)
    assert _close(reg.d_ref, d_ref)
    assert _close(reg.q_ref_mm, q_ref)
    assert {0, 1, 3} <= set(np.unique(reg.status).tolist())


def test_block_of_one_row_is_avoided(monkeypatch):
    """Blocks of P − 1 pixels: the one pixel left joins the block (numpy rotates one row another way)."""
    setup = default_setup().binned(48)
    cs = setup.cameras["left"]
    monkeypatch.setattr(R, "_BLOCK_PX", cs.camera.shape[0] * cs.camera.shape[1] - 1)
    scr = setup.screen
    screen = SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
    ok = np.ones(cs.camera.shape, bool)
    for seed in range(8):  # a lone row differs in about half the cases: 8 draws
        rng = np.random.default_rng(seed)
        xy = np.stack([rng.uniform(scr.grid_x_mm[0], scr.grid_x_mm[-1], cs.camera.shape),
                       rng.uniform(scr.grid_y_mm[0], scr.grid_y_mm[-1], cs.camera.shape)], -1)
        reg = register(cs.camera, cs.T_world_cam, screen, _tilted(scr.T_world_screen), xy, ok, setup.sample.T_world_sample)
        ref = _reference(cs.camera, cs.T_world_cam, screen, _tilted(scr.T_world_screen), xy, ok, setup.sample.T_world_sample)
        assert _close(reg.q_ref_mm, ref[2])
