"""The glass stage's skipped foot-point Newton step (``simulation.glass_skip``): both branches of
``glass_rows._foot_run`` forced, each against the independent per-ray refraction trace of
``tests/test_cover_glass.py`` (≤ 1e-9 mm), and the bound's decision against the foot point's
known distance from the root."""

import numpy as np
import pytest
from scipy.optimize import brentq
from test_cover_glass import GX, GY, _independent_glass_hit

from pmdsim.geometry.surface import SplineSurface
from pmdsim.simulation.glass_rows import _foot_run
from pmdsim.simulation.glass_skip import skip_check_run
from pmdsim.simulation.trace_rows import (
    _AX, _AY, _BLK, _BX, _BY, _C, _NF, _QOX, _QOY, _QOZ, _TDX, _TDY, _TDZ, _TOX, _TOY, _TOZ, _UX, _UY, _VX, _VY,
    _WX, _WY, _WZ,
)

T_MM, N_GLASS = 3.0, 1.52


def _rays_through_known_feet(screen, n):
    """n rays (origin o, unit direction d, screen frame) whose foot points u are known by
    construction: u drawn in one patch, the outer-surface point A(u) = (u, h(u)) + t·m(u)
    (m = (h_x, h_y, −1)/√(1 + |∇h|²)), a direction towards the screen, o = A − 60·d."""
    rng = np.random.default_rng(21)
    u = np.stack([rng.uniform(GX[1] + 5.0, GX[2] - 5.0, n), rng.uniform(GY[1] + 5.0, GY[2] - 5.0, n)], axis=-1)
    h = np.asarray(screen.height(u[:, 0], u[:, 1]))
    g = np.asarray(screen.gradient(u[:, 0], u[:, 1]))
    m = np.concatenate([g, -np.ones((n, 1))], axis=-1)
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    a = np.concatenate([u, h[:, None]], axis=-1) + T_MM * m
    d = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), np.ones(n)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return u, a - 60.0 * d, d


def _run(screen, o, d, u_lin):
    """``_foot_run`` on one block (zero steps of the rows above: the prediction v is ``u_lin``);
    returns the number of pixels the skip's check passes, and the emitting-surface hits of the
    refracted rays (brentq along them, written here)."""
    k = screen.kernel
    n = o.shape[0]
    S = np.full(_NF * _BLK, np.nan)
    b = d[:, :2] / d[:, 2:]
    fields = {_AX: o[:, 0] - o[:, 2] * b[:, 0], _AY: o[:, 1] - o[:, 2] * b[:, 1], _BX: b[:, 0], _BY: b[:, 1],
              _QOX: o[:, 0], _QOY: o[:, 1], _QOZ: o[:, 2], _WX: d[:, 0], _WY: d[:, 1], _WZ: d[:, 2],
              _UX: u_lin[:, 0], _UY: u_lin[:, 1], _C: np.zeros(n)}
    for f, v in fields.items():
        S[f * _BLK:f * _BLK + n] = v
    i0, j0 = 1, 1
    c = k.coef[16 * (j0 * (k.grid_x.shape[0] - 1) + i0):][:16]
    args = (c, k.grid_x[i0], k.grid_y[j0], k.grid_x[i0], k.grid_x[i0 + 1], k.grid_y[j0], k.grid_y[j0 + 1])
    zero = np.zeros(n)
    n_ok = skip_check_run(n, *args, T_MM, k.dmax[0], zero, zero, zero, zero, S.copy())
    _foot_run(n, *args, T_MM, N_GLASS, k.dmax[0], k.dmax[1], 1e-9, zero, zero, zero, zero, S)
    assert (S[_C * _BLK:_C * _BLK + n] == 0.0).all()
    q = np.empty((n, 2))
    for i in range(n):
        p = np.array([S[f * _BLK + i] for f in (_TOX, _TOY, _TOZ)])  # the refracted ray
        r = np.array([S[f * _BLK + i] for f in (_TDX, _TDY, _TDZ)])
        assert S[_QOZ * _BLK + i] == p[2]  # its origin's z also where the intersection stage reads it
        r /= np.linalg.norm(r)
        f1 = lambda s: (p + s * r)[2] - float(screen.height(*(p + s * r)[:2]))
        q[i] = (p + brentq(f1, 0.0, 10.0 * T_MM, xtol=1e-14) * r)[:2]
    steps = np.stack([S[_VX * _BLK:_VX * _BLK + n], S[_VY * _BLK:_VY * _BLK + n]], axis=-1)
    return n_ok, q, steps


@pytest.mark.parametrize("off_mm, skipped", [(0.0, True), (1e-11, True), (1e-8, False), (1e-6, False)])
def test_both_branches_against_the_independent_refraction_trace(off_mm, skipped):
    """The prediction off the known foot point by ``off_mm``: within the bound (≤ 1e-9 mm, the
    residual ≈ the offset) the step is skipped, beyond it the Newton step is taken; either way
    the emitting-surface point equals the independent trace's to 1e-9 mm, and the stored step
    (for the rows below) is the root's offset from the prediction."""
    screen = SplineSurface.from_bulge(GX, GY, 3.0)
    n = 40
    u, o, d = _rays_through_known_feet(screen, n)
    off = np.array([off_mm, -off_mm])
    n_ok, q, steps = _run(screen, o, d, u + off)
    assert (n_ok == n) == skipped
    assert skipped or n_ok == 0
    for i in range(n):
        ref = _independent_glass_hit(screen, T_MM, N_GLASS, o[i], d[i])
        np.testing.assert_allclose(q[i], ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(steps, np.broadcast_to(-off, steps.shape), rtol=0, atol=1e-12)
