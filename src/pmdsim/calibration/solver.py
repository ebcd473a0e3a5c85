"""Levenberg–Marquardt solver of the holistic calibration (paper §4): packing, evaluation, conditioning.

Solver
------
Levenberg–Marquardt on the dense normal equations (14 parameters per camera + 3 per pose, e.g.
76): a numba kernel accumulates JᵀJ and Jᵀr per (camera, pose) block with the analytic
Jacobian (chain rule through mirror, rigid transform, pinhole and distortion), gathering the
Jacobian rows of 64 correspondences at a time and adding their Gram matrix in vectorised tiles
(no full Jacobian in memory). Each step is the damped Gauss–Newton step (Cholesky factor of the
Jacobi-scaled JᵀJ + λI) with **geodesic acceleration** (Transtrum & Sethna 2012): a second
correction −(JᵀJ + λI)⁻¹Jᵀr_vv/2 from the residuals' second directional derivative r_vv along
the step, by a finite difference. It lets the steps follow the curved valleys of this problem
(rotations of cameras and mirror planes together, nearly invisible to the data) instead of
leaving them: about a third of the accepted steps, almost no rejected ones. The damping follows
Nielsen's update, bounded to a factor of 1/10 per step. Converged when an accepted step changes
the cost by less than ``ftol`` (1e-12) relative, when the Gauss–Newton model predicts less than
that, or when the Gauss–Newton step changes no parameter by more than ``xtol`` relative
(:func:`calibrate`). The conditioning of the Jacobi-scaled JᵀJ is checked at the start and after
every step: a degenerate set of mirror poses raises :class:`CalibrationDegenerateError` naming
the badly determined parameters and, if recognised, the degenerate configuration (all planes
parallel; all planes through one line).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Iterable

import numpy as np
import scipy.linalg

from .errors import CalibrationDataError, CalibrationDegenerateError, CalibrationError
from .screen import ScreenModel, _basis_weights
from .model import (CalibrationState, DEFAULT_CONDITION_LIMIT, GLASS_UNITS, MIN_CORRESPONDENCES, MIN_POSES,
                    Observations, SCREEN_HEIGHT_UNIT_MM, SCREEN_WEIGHT_MIN, WEAK_DIRECTIONS, _CAM_UNITS, _CHUNK, _MIR_UNITS, _NB,
                    _NC, _NJ, _NM, _PLANE_HINT_TOL)
from .kernel import _avv_kernel, _chunks_kernel, _screen_points_kernel
from .glass_kernel import glass_inputs
from .jacobian import residuals_and_jacobian  # noqa: F401  (public here since the beginning)
from .result import CalibrationResult, WeakDirection


# ============================================================================ packed data
class _Data:
    """Observations concatenated in block order, with the chunk table of the kernels."""

    def __init__(self, blocks: list[tuple[int, int, np.ndarray, np.ndarray]], block_keys, screen=None):
        self.block_keys = block_keys  # [(camera name, pose index)]
        self.uv = np.ascontiguousarray(np.concatenate([b[2] for b in blocks]))
        self.q = np.ascontiguousarray(np.concatenate([b[3] for b in blocks]))
        self.wx, self.wy, self.fi, self.fj = _screen_arrays(screen, self.q)
        # Standard deviations of the decoded (x_q, y_q) (relative; isotropic and equal unless
        # the observations give them).
        self.qstd = np.ones((self.q.shape[0], 2))
        starts, ends, cams, poses, cblock = [], [], [], [], []
        off = 0
        self.block_rows = []
        for bi, (ci, k, uv, _) in enumerate(blocks):
            m = uv.shape[0]
            self.block_rows.append((off, off + m))
            for s in range(off, off + m, _CHUNK):
                starts.append(s)
                ends.append(min(s + _CHUNK, off + m))
                cams.append(ci)
                poses.append(k)
                cblock.append(bi)
            off += m
        self.c_start = np.array(starts, dtype=np.int64)
        self.c_end = np.array(ends, dtype=np.int64)
        self.c_cam = np.array(cams, dtype=np.int64)
        self.c_pose = np.array(poses, dtype=np.int64)
        self.c_block = np.array(cblock, dtype=np.int64)
        self.n_rows = off


def _screen_arrays(screen: ScreenModel | None, q: np.ndarray):
    """Per-correspondence 1-D basis weights (wx (M, n_x), wy (M, n_y)) and the (i, j) indices of
    the free heights — computed once, as the correspondences do not move. Dummies without a
    screen model."""
    if screen is None:
        return np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    wx, wy = screen.basis_weights(q[:, 0], q[:, 1])
    fj, fi = screen.free_index
    return (np.ascontiguousarray(wx), np.ascontiguousarray(wy), np.ascontiguousarray(fi, dtype=np.int64),
            np.ascontiguousarray(fj, dtype=np.int64))


def _screen_q(q: np.ndarray, wx: np.ndarray, wy: np.ndarray, screen: ScreenModel | None) -> np.ndarray:
    """The correspondences' screen points with z = h(x_q, y_q) of the screen model (q as given
    without one)."""
    if screen is None:
        return q
    out = np.empty_like(q)
    _screen_points_kernel(q, wx, wy, np.ascontiguousarray(screen.heights_mm, dtype=float), out)
    return out


def _screen_slope(q: np.ndarray, screen: ScreenModel | None) -> np.ndarray:
    """(M, 2) slopes (∂h/∂x, ∂h/∂y) of the screen model at the correspondences' (x_q, y_q)
    (zeros without a screen model: q is used as given)."""
    if screen is None:
        return np.zeros((q.shape[0], 2))
    from ..geometry.surface import cardinal_spline_coefficients

    gx, gy = screen.grid_x_mm, screen.grid_y_mm
    cx, cy = cardinal_spline_coefficients(gx), cardinal_spline_coefficients(gy)
    wx = _basis_weights(gx, cx, q[:, 0])
    wy = _basis_weights(gy, cy, q[:, 1])
    dwx = _basis_weights(gx, cx, q[:, 0], derivative=True)
    dwy = _basis_weights(gy, cy, q[:, 1], derivative=True)
    z = screen.heights_mm
    return np.ascontiguousarray(np.column_stack([np.einsum("mi,mi->m", wy @ z, dwx),
                                                 np.einsum("mi,mi->m", dwy @ z, wx)]))


def _screen_coverage(data: "_Data", screen: ScreenModel, min_correspondences: int) -> None:
    """Raise naming the free heights that no (or too few) correspondences see: fewer than
    ``min_correspondences`` with basis weight |w_i(x_q)·w_j(y_q)| ≥ :data:`SCREEN_WEIGHT_MIN`."""
    if screen is None or screen.n_free == 0:
        return
    problems = []
    for name, i, j in zip(screen.free_names(), data.fi, data.fj):
        count = int(np.count_nonzero(np.abs(data.wy[:, j] * data.wx[:, i]) >= SCREEN_WEIGHT_MIN))
        if count < min_correspondences:
            problems.append(f"{name} at (x, y) = ({screen.grid_x_mm[i]:g}, {screen.grid_y_mm[j]:g}) mm: "
                            f"{count} correspondences")
    if problems:
        raise CalibrationDataError(
            f"the data do not determine {len(problems)} free screen control height(s): fewer than "
            f"{min_correspondences} correspondences have basis weight ≥ {SCREEN_WEIGHT_MIN:g} for "
            + "; ".join(problems)
            + ". The cameras do not see these control points via the mirror: hold them (free=False), "
            f"use a coarser screen grid, or add mirror poses whose reflections reach them")


def _pack(observations: Iterable[Observations], state: CalibrationState, min_correspondences: int) -> _Data:
    obs = list(observations)
    if not obs:
        raise CalibrationDataError("no observations given")
    for o in obs:
        if not isinstance(o, Observations):
            raise CalibrationDataError(f"observations must be Observations objects, got {type(o).__name__}")
    names = state.camera_names
    if not names:
        raise CalibrationDataError("the initial state has no cameras")
    n_m = len(state.mirrors)
    merged: dict[tuple[str, int], list[Observations]] = {}
    for o in obs:
        if o.camera not in state.cameras:
            raise CalibrationDataError(
                f"observations name camera {o.camera!r}, which is not in the initial state (cameras: {names})"
            )
        if o.pose_index >= n_m:
            raise CalibrationDataError(
                f"observations of camera {o.camera!r} name mirror pose {o.pose_index}, but the initial "
                f"state has only {n_m} mirror planes (poses 0…{n_m - 1})"
            )
        merged.setdefault((o.camera, o.pose_index), []).append(o)
    total = sum(o.n for o in obs)
    if total == 0:
        raise CalibrationDataError(
            "all correspondences are invalid: no camera sees the screen via the mirror in any pose "
            "(check the valid masks, the decoding and the mirror poses)"
        )
    problems = []
    for (cam, k), lst in sorted(merged.items(), key=lambda kv: (names.index(kv[0][0]), kv[0][1])):
        m = sum(o.n for o in lst)
        if m < min_correspondences:
            problems.append(
                f"camera {cam!r}, mirror pose {k}: only {m} valid correspondences (need ≥ "
                f"{min_correspondences}); the reflection probably misses the screen or the decoding "
                f"failed — drop this pose for this camera or fix its data"
            )
    if problems:
        raise CalibrationDataError("; ".join(problems))
    for cam in names:
        poses = sorted(k for (c, k) in merged if c == cam)
        if len(poses) < MIN_POSES:
            raise CalibrationDataError(
                f"camera {cam!r} has observations in only {len(poses)} mirror pose(s) {poses}; the "
                f"holistic calibration needs at least {MIN_POSES} per camera (better many, tilted "
                f"about two different axes)"
            )
    seen = {k for (_, k) in merged}
    unseen = [k for k in range(n_m) if k not in seen]
    if unseen:
        raise CalibrationDataError(
            f"mirror pose(s) {unseen} of the initial state have no observations, so their planes "
            f"are undetermined; remove them from the state"
        )
    blocks, keys = [], []
    for (cam, k), lst in sorted(merged.items(), key=lambda kv: (names.index(kv[0][0]), kv[0][1])):
        blocks.append((names.index(cam), k, np.concatenate([o.uv_px for o in lst]),
                       np.concatenate([o.q_screen_mm for o in lst])))
        keys.append((cam, k))
    with_std = [o.q_std_mm is not None for o in obs]
    if any(with_std) and not all(with_std):
        missing = [f"camera {o.camera!r} pose {o.pose_index}" for o in obs if o.q_std_mm is None][:5]
        raise CalibrationDataError(
            "some observations have q_std_mm and others not (" + "; ".join(missing) + "): the noise "
            "model must be the same for all — give q_std_mm for all observations or for none")
    data = _Data(blocks, keys, state.screen)
    if all(with_std):
        data.qstd = np.ascontiguousarray(np.concatenate(
            [np.concatenate([o.q_std_mm for o in merged[key]]) for key in keys]))
    _screen_coverage(data, state.screen, min_correspondences)
    return data


def _units(state: CalibrationState) -> np.ndarray:
    return np.concatenate([np.tile(_CAM_UNITS, len(state.cameras)), np.tile(_MIR_UNITS, len(state.mirrors)),
                           np.full(state.n_screen, SCREEN_HEIGHT_UNIT_MM), [GLASS_UNITS[g] for g in state.glass_index]])


def _block_index(state: CalibrationState, ci: int, k: int) -> np.ndarray:
    nc = _NC * len(state.cameras)
    return np.r_[np.arange(_NC * ci, _NC * (ci + 1)), np.arange(nc + _NM * k, nc + _NM * (k + 1))]


def _evaluate(data: _Data, state: CalibrationState, want_normal: bool, sandwich: bool = False):
    """Cost (SSR), per-block SSR, points behind camera per block and, if wanted, the scaled
    normal equations (A = JᵀJ, g = Jᵀr in internal units).

    ``sandwich``: instead, (whitened SSR Σ_k r_kᵀ(B_k B_kᵀ)⁻¹r_k, per-block SSR, points behind
    camera, M = Σ_k J_kᵀ B_k B_kᵀ J_k in internal units, None) with B_k the propagation of the
    screen-point noise to the residual (see :func:`_chunk_run`)."""
    want_normal = want_normal or sandwich
    intr, rot, cen, mir, e1, e2 = state._arrays()
    nch = data.c_start.shape[0]
    nf = state.n_screen
    if nf != data.fi.shape[0]:
        raise ValueError("the state's screen model does not match the packed data")
    glass_on, q, gl, dwx, dwy, gsel, g_units, gbad = glass_inputs(data, state,
                                                                  _screen_q(data.q, data.wx, data.wy, state.screen))
    nf += state.n_glass  # the glass columns follow the screen heights'
    if want_normal:
        jtj = np.empty((nch, _NB + nf, _NB + nf))
        jtr = np.empty((nch, _NB + nf))
    else:
        jtj = np.empty((nch, 1, 1))
        jtr = np.empty((nch, 1))
    ssr = np.empty(nch)
    ssr_w = np.empty(nch)
    nbad = np.empty(nch, dtype=np.int64)
    units = np.concatenate([_CAM_UNITS, _MIR_UNITS])
    if sandwich:
        slope = _screen_slope(data.q, state.screen)
        qstd = data.qstd
    else:
        slope = qstd = np.zeros((1, 2))
    _chunks_kernel(data.c_start, data.c_end, data.c_cam, data.c_pose, data.uv, q, intr, rot, cen,
                   mir, e1, e2, units, data.wx, data.wy, data.fi, data.fj, SCREEN_HEIGHT_UNIT_MM, want_normal,
                   jtj, jtr, ssr, nbad, sandwich, slope, qstd, ssr_w, glass_on, gl, dwx, dwy, gsel, g_units)
    nblk = len(data.block_keys)
    block_ssr = np.bincount(data.c_block, weights=ssr, minlength=nblk)
    block_bad = np.bincount(data.c_block, weights=nbad, minlength=nblk).astype(int)
    if gbad is not None:  # no apparent point (the ray does not meet the glass from the sample side)
        block_bad += np.add.reduceat(gbad.astype(int), np.r_[0, np.cumsum([e - b for b, e in data.block_rows])[:-1]])
    if not want_normal:
        return float(block_ssr.sum()), block_ssr, block_bad, None, None
    n = state.n_parameters
    a = np.zeros((n, n))
    g = np.zeros(n)
    # Sum the chunks of each (camera, pose) block, then scatter.
    for sel, idx in _block_scatter(data, state):
        blk = jtj[sel].sum(axis=0)
        blk = 0.5 * (blk + blk.T)
        a[np.ix_(idx, idx)] += blk
        g[idx] += jtr[sel].sum(axis=0)
    if sandwich:
        return float(ssr_w.sum()), block_ssr, block_bad, a, None
    return float(block_ssr.sum()), block_ssr, block_bad, a, g


def _block_scatter(data: _Data, state: CalibrationState):
    """Per (camera, pose) block: (boolean chunk selection, parameter indices of the block's
    17 + F columns)."""
    n = state.n_parameters
    names = state.camera_names
    screen_idx = np.arange(n - state.n_screen - state.n_glass, n)  # screen heights, then glass
    for b, (cam, k) in enumerate(data.block_keys):
        yield data.c_block == b, np.r_[_block_index(state, names.index(cam), k), screen_idx]


def _acceleration_gradient(data: _Data, state: CalibrationState, delta: np.ndarray, h: float):
    """Jᵀ·r_vv (n,) in internal units for the geodesic acceleration (Transtrum & Sethna 2012,
    "Improvements to the Levenberg–Marquardt algorithm for nonlinear least-squares
    minimization", eq. 15): r_vv ≈ (2/h)·((r(x + hδ) − r(x))/h − J·δ), the residuals' second
    directional derivative along the step ``delta`` (natural units). None if x + hδ is not a
    valid state or puts a virtual point behind a camera."""
    try:
        probe = state.updated(h * delta)
    except ValueError:
        return None
    nf = state.n_screen
    nc = len(state.cameras)
    ng = state.n_glass
    glass_on, q, gl, dwx, dwy, gsel, g_units, _ = glass_inputs(data, state, _screen_q(data.q, data.wx, data.wy,
                                                                                     state.screen))
    q_t = np.ascontiguousarray(glass_inputs(data, probe, _screen_q(data.q, data.wx, data.wy, probe.screen),
                                            derivatives=False)[1])
    d_cam = np.ascontiguousarray(delta[:_NC * nc].reshape(nc, _NC))
    d_mir = np.ascontiguousarray(delta[_NC * nc:_NC * nc + _NM * len(state.mirrors)].reshape(-1, _NM))
    d_h = np.ascontiguousarray(delta[delta.size - nf - ng:delta.size - ng])
    d_g = np.ascontiguousarray(delta[delta.size - ng:])
    nch = data.c_start.shape[0]
    out = np.empty((nch, _NB + nf + ng))
    nbad = np.empty(nch, dtype=np.int64)
    units = np.concatenate([_CAM_UNITS, _MIR_UNITS])
    _avv_kernel(data.c_start, data.c_end, data.c_cam, data.c_pose, data.uv, q, q_t, *state._arrays(),
                *probe._arrays(), d_cam, d_mir, d_h, units, data.wx, data.wy, data.fi, data.fj,
                SCREEN_HEIGHT_UNIT_MM, float(h), out, nbad, glass_on, gl, dwx, dwy, gsel, g_units, d_g)
    if nbad.any():
        return None
    g2 = np.zeros(state.n_parameters)
    for sel, idx in _block_scatter(data, state):
        g2[idx] += out[sel].sum(axis=0)
    return g2


# ============================================================================ solver
#: Geodesic acceleration (Transtrum & Sethna 2012): finite-difference step h (relative to the
#: velocity step) of the second directional derivative, and the largest accepted ratio
#: 2‖δ_a‖/‖δ_v‖ of acceleration to velocity.
_ACCEL_H = 0.1
_ACCEL_ALPHA = 0.75
#: Nielsen's damping update after an accepted step, λ ← λ·max(_LAMBDA_MIN_FACTOR, 1 − (2ρ − 1)³),
#: bounded to [1/10, 1]; a rejected step multiplies λ by ν = 2, 4, 8, … (Nielsen 1999, "Damping
#: parameter in Marquardt's method", IMM-REP-1999-05; Madsen, Nielsen & Tingleff 2004, §3.1).
_LAMBDA_MIN_FACTOR = 0.1


def _scaled(a: np.ndarray, g: np.ndarray):
    dg = np.sqrt(np.diag(a))
    dg = np.where(dg > 0, dg, 1.0)
    return a / np.outer(dg, dg), g / dg, dg


def _mirror_configuration_hint(state: CalibrationState) -> str | None:
    """The analytically degenerate mirror-pose configurations, recognised from the planes:

    * all planes parallel (only lifts): moving every camera by t along the common normal and
      every plane by t/2 leaves all virtual cameras in place;
    * all planes through one common line L (a pencil: tilts about one axis through a common
      point, no lifts): rotating the cameras by 2φ and every plane by φ about L leaves all
      virtual cameras in place (a reflection across a plane containing L reverses rotations
      about L; cf. Sturm & Bonfort 2006 on mirror-based pose estimation).

    Returns the explanation, or None if the planes are in neither configuration."""
    if len(state.mirrors) < 2:
        return None
    normals = np.array([m.normal for m in state.mirrors])
    ref = normals[0]
    normals = normals * np.sign(normals @ ref)[:, None]
    ds = np.array([m.d_mm for m in state.mirrors]) * np.sign(np.array([m.normal for m in state.mirrors]) @ ref)
    parallel = ("all mirror planes are parallel (only lifts, no tilts): moving the cameras along the common "
                "normal and every plane by half as much is invisible — add mirror poses tilted about the "
                "mirror's x and y axes")
    if np.max(np.linalg.norm(np.cross(normals, ref), axis=1)) < _PLANE_HINT_TOL:
        return parallel
    centres = np.array([cp.T_screen_cam.translation for cp in state.cameras.values()])
    scale = max(float(np.max(np.linalg.norm(centres, axis=1))), 1.0)
    planes = np.column_stack([normals, -ds / scale])  # homogeneous, lengths in units of `scale`
    sv = np.linalg.svd(planes, compute_uv=False)
    if sv[2] < _PLANE_HINT_TOL * sv[0]:
        u, _, _ = np.linalg.svd(normals.T)
        direction = u[:, 2]  # ⟂ to all normals
        direction = direction * np.sign(direction[np.argmax(np.abs(direction))])
        # The point of the line nearest to the screen origin: n_k·p = d_k for all k, p ⟂ direction.
        p0 = np.linalg.lstsq(np.vstack([normals, direction]), np.r_[ds, 0.0], rcond=None)[0]
        if np.linalg.norm(p0 - centres.mean(axis=0)) > 20.0 * scale:
            return parallel  # (nearly) parallel planes: their common line is (nearly) at infinity
        return ("all mirror planes contain one common line (direction "
                + np.array2string(direction, precision=3, separator=", ", suppress_small=True)
                + ", through " + np.array2string(p0, precision=1, separator=", ", suppress_small=True)
                + " mm, screen frame) — mirror poses tilted about one axis only, without lifts: rotating "
                "the cameras by 2φ and every plane by φ about that line is invisible. Add lifts or tilts "
                "about a second axis")
    return None


def _degenerate_error(prefix: str, state: CalibrationState, a_s: np.ndarray, dg: np.ndarray, limit: float,
                      cond: float) -> "CalibrationDegenerateError":
    """The error for a degenerate problem: names the (nearly) free parameter combinations —
    eigenvectors of the Jacobi-scaled JᵀJ whose eigenvalues are below λ_max / limit, with their
    dominant components — and, if recognised, the degenerate mirror-pose configuration."""
    names = state.parameter_names()
    w, v = np.linalg.eigh(a_s)
    small = np.nonzero(w < w[-1] / limit)[0]
    if small.size == 0:
        small = np.array([0])
    combos = []
    undetermined: set[str] = set()
    for i in small[:4]:
        vec = v[:, i]
        big = np.abs(vec) >= 0.15 * np.max(np.abs(vec))
        order = [j for j in np.argsort(-np.abs(vec)) if big[j]][:10]
        combos.append("[" + " ".join(f"{vec[j]:+.2f}·{names[j]}" for j in order) + "]")
        undetermined.update(names[j] for j in np.nonzero(big)[0])
    hint = _mirror_configuration_hint(state)
    screen_free = any(n.startswith("screen.") for n in undetermined)
    if hint is None:
        hint = ("typical causes: all mirror planes parallel (only lifts, no tilts), or all planes through one "
                "common line (tilts about one axis only, no lifts) — add mirror poses tilted about the "
                "mirror's x and y axes, and lifts")
    cause = hint
    if screen_free:
        hint += ("; or free screen control heights (screen.h) that the correspondences cover too sparsely — "
                 "hold them or use a coarser screen grid")
    parameters = tuple(sorted(undetermined, key=names.index))
    msg = (
        prefix + f"the mirror poses do not determine all parameters: the Jacobi-scaled normal matrix JᵀJ has "
        f"condition number {cond:.3g} (limit {limit:.3g}), {small.size} (nearly) free parameter "
        f"combination(s) (eigenvectors, internal units): " + "; ".join(combos)
        + f". Badly determined: {', '.join(parameters)}. Cause: {hint}"
    )
    units = _units(state)
    dirs = v[:, small] * (units / dg)[:, None]  # natural units
    dirs /= np.linalg.norm(dirs / units[:, None], axis=0)  # unit length in internal units
    return CalibrationDegenerateError(msg, parameter_names=tuple(names), parameters=parameters, directions=dirs,
                                      condition_number=cond, cause=cause)


def _weak_directions(names, w: np.ndarray, v: np.ndarray, cov: np.ndarray, scale: np.ndarray,
                     units: np.ndarray, count: int = WEAK_DIRECTIONS) -> tuple["WeakDirection", ...]:
    """The ``count`` worst-determined parameter combinations: eigenvectors of the Jacobi-scaled
    JᵀJ (A_s; eigenvalues ``w`` ascending, eigenvectors ``v``) with the smallest eigenvalues.
    ``cov`` is the covariance (natural units), ``scale`` (n,) maps scaled to natural units (with
    the result's mirror orientation signs), ``units`` natural to internal units."""
    out = []
    cov_int = cov / np.outer(units, units)
    for i in range(min(count, w.size)):
        direction = v[:, i] * scale
        norm = np.linalg.norm(direction / units)
        direction = direction / norm  # natural units, unit length in internal units
        # Variance of the coordinate c = uᵀθ (internal units) along u = direction / units (‖u‖ = 1).
        u = direction / units
        var = float(u @ cov_int @ u)
        big = np.abs(u) >= 0.15 * np.max(np.abs(u))
        order = [j for j in np.argsort(-np.abs(u)) if big[j]][:10]
        comps = tuple((names[j], float(u[j])) for j in order)
        out.append(WeakDirection(float(w[i] / w[-1]), direction, math.sqrt(max(var, 0.0)), comps))
    return tuple(out)


def _condition(a_s: np.ndarray) -> float:
    w = np.linalg.eigvalsh(a_s)
    if w[0] <= 0:
        return math.inf
    return float(w[-1] / w[0])


def _rel_step(delta: np.ndarray, state: CalibrationState) -> float:
    """max |δ_j| / ref_j: focal length for intrinsics in px, 1 for distortion and angles, the
    camera distance for positions and mirror distances."""
    refs = []
    pos = [float(np.linalg.norm(cp.T_screen_cam.translation)) for cp in state.cameras.values()]
    scale_mm = max(max(pos), 1.0)
    for cp in state.cameras.values():
        f = max(cp.camera.fx_px, cp.camera.fy_px)
        refs += [f, f, f, f, 1, 1, 1, 1, 1, 1, 1, scale_mm, scale_mm, scale_mm]
    for _ in state.mirrors:
        refs += [1, 1, scale_mm]
    refs += [1] * (state.n_screen + state.n_glass)  # screen heights, glass thickness: 1 mm; glass index: 1
    return float(np.max(np.abs(delta) / np.array(refs, dtype=float)))


def calibrate(
    observations: Iterable[Observations],
    initial_state: CalibrationState,
    *,
    screen_model: ScreenModel | None = None,
    max_iter: int = 100,
    ftol: float = 1e-12,
    xtol: float = 1e-10,
    min_correspondences: int = MIN_CORRESPONDENCES,
    condition_limit: float = DEFAULT_CONDITION_LIMIT,
    raise_on_failure: bool = False,
) -> CalibrationResult:
    """Holistic calibration with a planar mirror (paper §4) by Levenberg–Marquardt.

    Parameters
    ----------
    observations : iterable of Observations
        Correspondences per (camera, mirror pose); several objects for the same block are merged.
    initial_state : CalibrationState
        Start values (e.g. :func:`nominal_state`); its cameras define the parameter order, its
        mirrors the pose indices. k3 of each camera stays fixed at its initial value.
    screen_model : ScreenModel, optional
        Non-planar screen: the correspondences' z is the model's height h(x_q, y_q) and its
        free control heights are estimated jointly (start values: its ``heights_mm``). Replaces
        ``initial_state.screen``; None keeps that (normally None: q is used as given).
    max_iter : int
        Maximum number of accepted steps.
    ftol : float
        Converged when an accepted step changes the cost (SSR) by less than ``ftol`` relative,
        or when the model predicts less than that.
    xtol : float
        Converged when a step changes every parameter by less than ``xtol`` relative to its
        reference size (the focal length for intrinsics in px, 1 for distortion coefficients and
        angles in rad, the largest camera distance for lengths).
    min_correspondences : int
        Fewest correspondences per (camera, pose) block.
    condition_limit : float
        Largest acceptable condition number of the Jacobi-scaled JᵀJ (checked at the start and at
        the solution); above it the pose set is reported as degenerate.
    raise_on_failure : bool
        Raise :class:`CalibrationError` instead of returning ``converged=False``.

    Returns
    -------
    CalibrationResult
        ``converged`` False (with the ``reason``) if the iteration stopped before a criterion
        was met. Its covariance is for noise in the decoded screen points (module docstring,
        "Uncertainties"; the observations' ``q_std_mm`` if given).

    Raises
    ------
    CalibrationDataError
        Unusable input, with the camera / pose / parameters named: no observations or none
        valid; a camera or pose index not in the state; a (camera, pose) block with fewer than
        ``min_correspondences``; a camera seen in fewer than 3 poses; a mirror of the state
        without observations; correspondences behind a camera at the initial state; free screen
        heights that fewer than ``min_correspondences`` correspondences see with basis weight
        ≥ :data:`SCREEN_WEIGHT_MIN` (named).
    CalibrationDegenerateError
        (a :class:`CalibrationDataError`) A degenerate pose set: condition number above
        ``condition_limit`` at the start, after a step or at the solution. The message names the
        badly determined parameter combinations and, if recognised, the configuration (all
        mirror planes parallel; all through one common line); the exception carries them
        (``parameters``, ``directions``, ``cause``). Weakly determined parameters below the limit
        are reported by the result (:attr:`CalibrationResult.weak_directions`,
        :meth:`CalibrationResult.poorly_determined`).
    CalibrationError
        Not converged and ``raise_on_failure``.
    """
    if int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    state = initial_state
    if screen_model is not None:
        if not isinstance(screen_model, ScreenModel):
            raise TypeError(f"screen_model must be a ScreenModel, got {type(screen_model).__name__}")
        state = replace(state, screen=screen_model)
    data = _pack(observations, state, int(min_correspondences))
    names = state.parameter_names()
    n = len(names)
    m = 2 * data.n_rows
    if m <= n:
        raise CalibrationDataError(f"{m} residuals cannot determine {n} parameters")
    units = _units(state)

    cost, block_ssr, block_bad, a, g = _evaluate(data, state, True)
    if block_bad.any():
        bad = [f"camera {c!r} pose {k}: {b}" for (c, k), b in zip(data.block_keys, block_bad) if b]
        raise CalibrationDataError(
            "the initial state puts the virtual (mirrored) screen points of some correspondences "
            "behind the camera (" + "; ".join(bad) + "); the initial camera poses or mirror planes are "
            "too far off"
        )
    a_s, g_s, dg = _scaled(a, g)
    cond = _condition(a_s)
    if not cond <= condition_limit:
        raise _degenerate_error("at the initial state, ", state, a_s, dg, condition_limit, cond)

    lam = 1e-3
    nu = 2.0
    converged = False
    reason = ""
    iterations = 0
    eye = np.eye(n)
    history = [math.sqrt(cost / m)]
    while True:
        if cost == 0.0:
            converged, reason = True, "zero residuals"
            break
        # Convergence tests on the undamped (Gauss–Newton) step: independent of the damping.
        try:
            step_gn = np.linalg.solve(a_s, -g_s)
        except np.linalg.LinAlgError:
            step_gn = np.linalg.lstsq(a_s, -g_s, rcond=None)[0]
        pred_gn = float(-(g_s @ step_gn))
        rel_gn = _rel_step(step_gn / dg * units, state)
        if rel_gn <= xtol:
            converged, reason = True, (f"step size: the Gauss–Newton step changes no parameter by more "
                                       f"than {rel_gn:.2g} (relative) ≤ xtol = {xtol:g}")
            break
        if pred_gn <= ftol * cost:
            converged, reason = True, (f"relative cost change: the Gauss–Newton model predicts "
                                       f"{pred_gn / cost:.2g} ≤ ftol = {ftol:g}")
            break
        if iterations >= max_iter:
            reason = (f"maximum number of iterations ({max_iter}) reached before convergence; rms "
                      f"{math.sqrt(cost / m):.3g} px, Gauss–Newton step {rel_gn:.2g} (relative), "
                      f"predicted relative cost change {pred_gn / cost:.2g}")
            break
        # Levenberg–Marquardt step (Marquardt scaling: λ·diag(JᵀJ) = λ·I after Jacobi scaling)
        # with geodesic acceleration. The trial state is evaluated with its normal equations:
        # nearly every trial is accepted, and then they are the next iteration's.
        accepted = False
        rel_change = math.nan
        while lam <= 1e20:
            try:
                chol = scipy.linalg.cho_factor(a_s + lam * eye, check_finite=False)
            except np.linalg.LinAlgError:
                lam, nu = max(lam, 1e-12) * nu, nu * 2.0
                continue
            step_v = scipy.linalg.cho_solve(chol, -g_s, check_finite=False)  # velocity δ_v
            # Acceleration δ_a = −(JᵀJ + λI)⁻¹ Jᵀ r_vv (scaled coordinates) with r_vv the
            # residuals' second directional derivative along δ_v; the step is δ_v + δ_a/2.
            g2 = _acceleration_gradient(data, state, step_v / dg * units, _ACCEL_H)
            if g2 is None:  # x + hδ_v invalid or behind a camera: shorten the step
                lam, nu = max(lam, 1e-12) * nu, nu * 2.0
                continue
            step_a = scipy.linalg.cho_solve(chol, -(g2 / dg), check_finite=False)
            if 2.0 * np.linalg.norm(step_a) > _ACCEL_ALPHA * np.linalg.norm(step_v):
                # The step is too long for its curvature: shorten it.
                lam, nu = max(lam, 1e-12) * nu, nu * 2.0
                continue
            step_s = step_v + 0.5 * step_a
            # Predicted reduction of the velocity step by the Gauss–Newton model (the quadratic
            # model does not describe the acceleration; Transtrum & Sethna 2012, §IV).
            pred = -(2.0 * g_s @ step_v + step_v @ a_s @ step_v)
            new_cost = math.inf
            try:
                trial = state.updated(step_s / dg * units)
            except ValueError:  # e.g. a focal length ≤ 0: reject the step
                trial = None
            if trial is not None:
                evaluated = _evaluate(data, trial, True)
                if not evaluated[2].any():  # no virtual point behind a camera
                    new_cost = evaluated[0]
            rho = (cost - new_cost) / pred if pred > 0 else -1.0
            if rho > 1e-4 and new_cost < cost:
                rel_change = (cost - new_cost) / cost
                state = trial
                cost, block_ssr, block_bad, a, g = evaluated
                iterations += 1
                history.append(math.sqrt(cost / m))
                lam = max(lam * min(max(_LAMBDA_MIN_FACTOR, 1.0 - (2.0 * rho - 1.0) ** 3), 1.0), 1e-15)
                nu = 2.0
                accepted = True
                break
            lam = max(lam, 1e-12) * nu
            nu *= 2.0
        if not accepted:
            reason = (f"no step reduces the cost any more (damping λ = {lam:.3g}) although the "
                      f"convergence criteria are not met; rms {math.sqrt(cost / m):.3g} px")
            break
        a_s, g_s, dg = _scaled(a, g)
        cond = _condition(a_s)
        if not cond <= condition_limit:
            raise _degenerate_error(f"after {iterations} iterations, ", state, a_s, dg, condition_limit, cond)
        if rel_change < ftol:
            converged, reason = True, f"relative cost change {rel_change:.2g} < ftol = {ftol:g}"
            break

    eig_w, eig_v = np.linalg.eigh(a_s)
    cond = math.inf if eig_w[0] <= 0 else float(eig_w[-1] / eig_w[0])
    if not cond <= condition_limit:
        raise _degenerate_error("at the solution, ", state, a_s, dg, condition_limit, cond)
    # Covariance. The noise is in the decoded screen points, not in the pixels: r_k ≈ J_k δ + B_k ε_k
    # with ε_k ~ N(0, σ₀² I₂) and B_k = ∂r_k/∂(x_q, y_q)·diag(q_std) (see _chunk_run), so the
    # least-squares estimate has the sandwich covariance
    #   Cov = σ₀² (JᵀJ)⁻¹ (Σ_k J_kᵀ B_k B_kᵀ J_k) (JᵀJ)⁻¹,   σ₀² = Σ_k r_kᵀ (B_k B_kᵀ)⁻¹ r_k / (m − n),
    # which is σ²(JᵀJ)⁻¹, σ² = SSR/(m − n), when all B_k are equal multiples of an orthogonal matrix.
    ssr_w, _, _, meat, _ = _evaluate(data, state, True, sandwich=True)
    sigma0_2 = ssr_w / (m - n)
    a_s_inv = np.linalg.inv(a_s)
    a_s_inv = 0.5 * (a_s_inv + a_s_inv.T)
    cov_s = sigma0_2 * (a_s_inv @ (meat / np.outer(dg, dg)) @ a_s_inv)  # Jacobi-scaled coordinates
    cov_s = 0.5 * (cov_s + cov_s.T)
    scale = units / dg
    # The result's mirror normals point towards the cameras; a plane flipped for that, (n, d) →
    # (−n, −d), has the same e1 and the opposite e2 (tangent_basis), so its increments are
    # (tilt_a, tilt_b, d) → (−tilt_a, tilt_b, −d): flip those rows and columns.
    ref = np.mean([cp.T_screen_cam.translation for cp in state.cameras.values()], axis=0)
    oriented = [mp.oriented_towards(ref) for mp in state.mirrors]
    sign = np.ones(n)
    for k, (mp, mo) in enumerate(zip(state.mirrors, oriented)):
        if mo is not mp:
            off = _NC * len(state.cameras) + _NM * k
            sign[[off, off + 2]] = -1.0
    cov = cov_s * np.outer(scale * sign, scale * sign)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    weak = _weak_directions(names, eig_w, eig_v, cov, scale * sign, units)

    block_n = [e - s for s, e in data.block_rows]
    rms_by = {key: math.sqrt(ssr / (2 * k)) for key, ssr, k in zip(data.block_keys, block_ssr, block_n)}
    result = CalibrationResult(
        cameras={k: (cp.camera, cp.T_screen_cam) for k, cp in state.cameras.items()},
        mirrors=oriented,
        converged=converged,
        reason=reason,
        iterations=iterations,
        rms_px=math.sqrt(cost / m),
        rms_px_by_camera_pose=rms_by,
        n_residuals=m,
        parameter_names=tuple(names),
        parameter_std=std,
        covariance=cov,
        condition_number=cond,
        rms_history_px=tuple(history),
        screen_model=state.screen,
        glass=state.glass,
        glass_free=state.glass_free,
        std_inflation=np.sqrt(np.clip(np.diag(a_s_inv), 0.0, None)),
        weak_directions=weak,
        screen_noise_std=math.sqrt(sigma0_2),
    )
    if raise_on_failure and not converged:
        raise CalibrationError(f"the calibration did not converge: {reason}")
    return result
