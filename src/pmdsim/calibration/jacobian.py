"""The calibration's residuals and dense analytic Jacobian (for small observation sets and tests).

The solver (:mod:`.solver`) never forms the Jacobian: its kernels accumulate JᵀJ and Jᵀr. This
module gives the same model row by row, from the same per-correspondence kernel
(:func:`pmdsim.calibration.kernel._rows_kernel`), e.g. to check it against finite differences.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Iterable

import numpy as np

from .errors import CalibrationDataError
from .glass_kernel import glass_inputs
from .kernel import _rows_kernel
from .model import _NB, _NC, _NJ, _NM, CalibrationState, Observations

__all__ = ["residuals_and_jacobian"]


def residuals_and_jacobian(observations: Iterable[Observations], state: CalibrationState):
    """Residuals and the dense analytic Jacobian (for small observation sets and tests).

    Returns
    -------
    r : ndarray (2M,)
        Residuals (predicted − observed, px), ordered (u₀, v₀, u₁, v₁, …) over the
        observations in the given order.
    J : ndarray (2M, n)
        dr/dΔ for the increments of :meth:`CalibrationState.updated` (natural units), including
        the free screen heights and the free cover-glass parameters.
    names : list[str]
        Parameter names (columns of J).

    Rows whose virtual point lies behind the camera (or, with a glass, that have no apparent
    point) are NaN.
    """
    from .solver import _screen_arrays, _screen_q

    obs = list(observations)
    names = state.camera_names
    cam_idx, pose_idx, uv, q = [], [], [], []
    for o in obs:
        if o.camera not in state.cameras:
            raise CalibrationDataError(f"camera {o.camera!r} is not in the state (cameras: {names})")
        if o.pose_index >= len(state.mirrors):
            raise CalibrationDataError(f"mirror pose {o.pose_index} is not in the state ({len(state.mirrors)} mirrors)")
        cam_idx.append(np.full(o.n, names.index(o.camera), dtype=np.int64))
        pose_idx.append(np.full(o.n, o.pose_index, dtype=np.int64))
        uv.append(o.uv_px)
        q.append(o.q_screen_mm)
    cam_idx = np.concatenate(cam_idx) if obs else np.zeros(0, dtype=np.int64)
    pose_idx = np.concatenate(pose_idx) if obs else np.zeros(0, dtype=np.int64)
    uv = np.ascontiguousarray(np.concatenate(uv)) if obs else np.zeros((0, 2))
    q = np.ascontiguousarray(np.concatenate(q)) if obs else np.zeros((0, 3))
    m = uv.shape[0]
    wx, wy, fi, fj = _screen_arrays(state.screen, q)
    rows = np.arange(m)
    # One "chunk" per row for the glass kernel (it needs each row's camera and mirror).
    data = SimpleNamespace(q=q, wx=wx, wy=wy, c_start=rows, c_end=rows + 1, c_cam=cam_idx, c_pose=pose_idx)
    glass_on, q, gl, dwx, dwy, gsel, _, gbad = glass_inputs(data, state, _screen_q(q, wx, wy, state.screen))
    q = np.ascontiguousarray(q)
    res = np.empty((m, 2))
    jb = np.empty((m, 2, _NJ))
    ext = np.zeros((m, 2, 4))
    ok = np.empty(m, dtype=np.bool_)
    _rows_kernel(cam_idx, pose_idx, uv, q, *state._arrays(), res, jb, ok, glass_on, gl, ext)
    n = state.n_parameters
    jac = np.zeros((m, 2, n))
    nc = _NC * len(state.cameras)
    for j in range(_NC):
        jac[rows, :, _NC * cam_idx + j] = jb[:, :, j]
    for j in range(_NM):
        jac[rows, :, nc + _NM * pose_idx + j] = jb[:, :, _NC + j]
    # Free screen heights: ∂r/∂Z_ji = (∂r/∂q_z)·w_j(y_q)·w_i(x_q) (+ the glass plate normal's
    # terms through the slopes ∂h/∂x = Σ Z_ji w_j w_i′, ∂h/∂y = Σ Z_ji w_j′ w_i).
    off = n - state.n_screen - state.n_glass
    for f, (i, j) in enumerate(zip(fi, fj)):
        jac[:, :, off + f] = jb[:, :, _NB] * (wy[:, j] * wx[:, i])[:, None]
        if glass_on:
            jac[:, :, off + f] += (ext[:, :, 0] * (dwx[:, i] * wy[:, j])[:, None]
                                   + ext[:, :, 1] * (wx[:, i] * dwy[:, j])[:, None])
    for c, g in enumerate(gsel):
        jac[:, :, off + state.n_screen + c] = ext[:, :, 2 + g]
    if gbad is not None:
        ok &= ~gbad
    res[~ok] = np.nan
    jac[~ok] = np.nan
    return res.reshape(-1), jac.reshape(2 * m, n), state.parameter_names()
