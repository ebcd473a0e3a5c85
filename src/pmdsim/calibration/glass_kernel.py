"""The cover glass in the calibration's forward model: apparent points and their derivatives.

The decoded correspondence gives the point Q on the *emitting* surface; the light left the glass
at A and travelled, via the mirror, to the camera. The planar-mirror model of :mod:`.model`
takes a screen point whose straight line to the *virtual camera centre* c′ (the camera centre
mirrored across the mirror plane) is the camera ray. With a glass this is the **apparent point**
q: where the straight line c′ → A meets the emitting surface's tangent plane at Q.

Local-plate model
-----------------
At Q the glass is taken as a flat plate of thickness t and index n over the tangent plane of the
emitting surface (unit normal m towards the sample, m = (h_x, h_y, −1)/√(1 + h_x² + h_y²) from
the screen model's slope; (0, 0, −1) for the planar screen). For the air ray direction
w = q − c′, with a = −w·m (its normal part) and w_t = w + a·m (its tangential part, ρ = |w_t|),
the ray meets the plane at q and, refracted, the emitting surface at Q; so

    q = Q + D(q − c′),    D(w) = t·w_t·φ,    φ = 1/a − 1/√(n²a² + (n² − 1)ρ²),

i.e. the plate shift t·(tanθ − tanθ_g) along the tangential direction (θ the angle in air,
θ_g in the glass; its component perpendicular to the ray is the textbook
t·sinθ·(1 − cosθ/√(n² − sin²θ))). q is the fixed point of this map (it contracts by ≈ t/|w|:
four to six iterations reach 1e-12 mm). For a flat screen the model is exact; on a curved one
the plate is the tangent plate at Q (its error grows with t·curvature: ≈ 0.01 mm in t for a
3 mm bulge, docs/conventions.md "Cover glass").

Derivatives (implicit function theorem): with M = ∂D/∂w = t·(φ·P + w_t ⊗ ∇φ) (P = I − m mᵀ,
∇φ = −φ_a·m + 2φ_ρ²·w_t, φ_a = −1/a² + n²a/R³, φ_ρ² = (n² − 1)/(2R³), R² = n²a² + (n² − 1)ρ²),
dq = (I − M)⁻¹·(dQ + ∂D/∂t dt + ∂D/∂n dn + ∂D/∂m dm − M dc′), with ∂D/∂t = w_t·φ,
∂D/∂n = t·w_t·n(a² + ρ²)/R³ and ∂D/∂m = t·(φ·(a I − m wᵀ) + w_t ⊗ (−φ_a·w + 2aφ_ρ²·w_t)).
:func:`glass_points_kernel` stores per correspondence (30 values): (I − M)⁻¹ (9, row-major),
dq/dc′ = −(I − M)⁻¹M (9), dq/dt (3), dq/dn (3), dq/dh_x and dq/dh_y (3 + 3, through m).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["GLASS_COLUMNS", "glass_points_kernel"]

#: Values stored per correspondence by :func:`glass_points_kernel`.
GLASS_COLUMNS = 30
#: Fixed-point tolerance of the apparent point (mm) and iteration limit.
_TOL_MM = 1e-12
_MAX_ITER = 50


@numba.njit(cache=True, inline="always")
def _shift(qx, qy, qz, cx, cy, cz, mx, my, mz, t, n):
    """(D, a, w_t, ρ², R, φ) of the local plate for the apparent point q and virtual centre c′."""
    wx = qx - cx
    wy = qy - cy
    wz = qz - cz
    a = -(wx * mx + wy * my + wz * mz)
    tx = wx + a * mx
    ty = wy + a * my
    tz = wz + a * mz
    rho2 = tx * tx + ty * ty + tz * tz
    r = math.sqrt(n * n * a * a + (n * n - 1.0) * rho2)
    phi = 1.0 / a - 1.0 / r
    return t * phi * tx, t * phi * ty, t * phi * tz, a, tx, ty, tz, rho2, r, phi, wx, wy, wz


@numba.njit(cache=True)
def _glass_row(qx, qy, qz, sx, sy, c, t, n, out_q, out_g, sc, want_g, px, py, pz):
    """Apparent point and (``want_g``) its derivatives for one correspondence (module
    docstring), the fixed point started at (``px``, ``py``, ``pz``); ``sc`` (15, 3) scratch (no
    allocation per correspondence). Returns False where the ray does not meet the plate from the
    sample side (a ≤ 0) or does not converge."""
    g = 1.0 / math.sqrt(1.0 + sx * sx + sy * sy)
    mx = sx * g
    my = sy * g
    mz = -g
    ok = False
    for _ in range(_MAX_ITER):
        dx, dy, dz, a, tx, ty, tz, rho2, r, phi, wx, wy, wz = _shift(px, py, pz, c[0], c[1], c[2], mx, my, mz, t, n)
        if not a > 0.0:
            return False
        nx = qx + dx
        ny = qy + dy
        nz = qz + dz
        moved = abs(nx - px) + abs(ny - py) + abs(nz - pz)
        px, py, pz = nx, ny, nz
        if moved <= _TOL_MM:
            ok = True
            break
    if not ok:
        return False
    dx, dy, dz, a, tx, ty, tz, rho2, r, phi, wx, wy, wz = _shift(px, py, pz, c[0], c[1], c[2], mx, my, mz, t, n)
    out_q[0] = px
    out_q[1] = py
    out_q[2] = pz
    if not want_g:
        return True
    m = (mx, my, mz)
    wt = (tx, ty, tz)
    w = (wx, wy, wz)
    r3 = r * r * r
    phi_a = -1.0 / (a * a) + n * n * a / r3
    phi_r = (n * n - 1.0) / (2.0 * r3)
    grad = sc[0]
    for j in range(3):
        grad[j] = -phi_a * m[j] + 2.0 * phi_r * wt[j]
    # I − M, M = t (φ P + w_t ⊗ ∇φ).
    imm = sc[3:6]
    mm = sc[6:9]
    for i in range(3):
        for j in range(3):
            pij = (1.0 if i == j else 0.0) - m[i] * m[j]
            mm[i, j] = t * (phi * pij + wt[i] * grad[j])
            imm[i, j] = (1.0 if i == j else 0.0) - mm[i, j]
    # (I − M)⁻¹ by the adjugate.
    inv = sc[9:12]
    inv[0, 0] = imm[1, 1] * imm[2, 2] - imm[1, 2] * imm[2, 1]
    inv[0, 1] = imm[0, 2] * imm[2, 1] - imm[0, 1] * imm[2, 2]
    inv[0, 2] = imm[0, 1] * imm[1, 2] - imm[0, 2] * imm[1, 1]
    inv[1, 0] = imm[1, 2] * imm[2, 0] - imm[1, 0] * imm[2, 2]
    inv[1, 1] = imm[0, 0] * imm[2, 2] - imm[0, 2] * imm[2, 0]
    inv[1, 2] = imm[0, 2] * imm[1, 0] - imm[0, 0] * imm[1, 2]
    inv[2, 0] = imm[1, 0] * imm[2, 1] - imm[1, 1] * imm[2, 0]
    inv[2, 1] = imm[0, 1] * imm[2, 0] - imm[0, 0] * imm[2, 1]
    inv[2, 2] = imm[0, 0] * imm[1, 1] - imm[0, 1] * imm[1, 0]
    det = imm[0, 0] * inv[0, 0] + imm[0, 1] * inv[1, 0] + imm[0, 2] * inv[2, 0]
    for i in range(3):
        for j in range(3):
            inv[i, j] /= det
            out_g[3 * i + j] = inv[i, j]
    # dq/dc′ = −(I − M)⁻¹ M.
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += inv[i, k] * mm[k, j]
            out_g[9 + 3 * i + j] = -s
    # ∂D/∂t, ∂D/∂n and ∂D/∂m·∂m/∂h_x, ∂D/∂m·∂m/∂h_y (∂m/∂h_x = e_x·g − m·h_x·g², likewise y).
    dn = t * n * (a * a + rho2) / r3
    dphi_m = sc[1]
    for j in range(3):
        dphi_m[j] = -phi_a * w[j] + 2.0 * a * phi_r * wt[j]
    dmx = (g - mx * sx * g * g, -my * sx * g * g, -mz * sx * g * g)
    dmy = (-mx * sy * g * g, g - my * sy * g * g, -mz * sy * g * g)
    vt = sc[2]
    vn = sc[12]
    vx = sc[13]
    vy = sc[14]
    for i in range(3):
        vt[i] = wt[i] * phi
        vn[i] = wt[i] * dn
        sx_i = 0.0
        sy_i = 0.0
        for j in range(3):
            dij = t * (phi * ((a if i == j else 0.0) - m[i] * w[j]) + wt[i] * dphi_m[j])
            sx_i += dij * dmx[j]
            sy_i += dij * dmy[j]
        vx[i] = sx_i
        vy[i] = sy_i
    for i in range(3):
        st = 0.0
        sn = 0.0
        sxx = 0.0
        syy = 0.0
        for k in range(3):
            st += inv[i, k] * vt[k]
            sn += inv[i, k] * vn[k]
            sxx += inv[i, k] * vx[k]
            syy += inv[i, k] * vy[k]
        out_g[18 + i] = st
        out_g[21 + i] = sn
        out_g[24 + i] = sxx
        out_g[27 + i] = syy
    return True


@numba.njit(cache=True, parallel=True)
def glass_points_kernel(c_start, c_end, c_cam, c_pose, q, slope, cen, mir, t, n, want_g, q_start, out_q, out_g, bad):
    """Per chunk of one (camera, pose) block: the apparent points ``out_q`` (N, 3) of the
    emitting points ``q`` (N, 3) with the screen slopes ``slope`` (N, 2) for the virtual camera
    centre (camera centre ``cen[cam]`` mirrored across ``mir[pose]`` = (n, d)), and, with
    ``want_g``, the derivatives ``out_g`` (N, 30) (module docstring; without, ``out_g`` is not
    written); the fixed point starts at ``q_start`` (N, 3) (``q``, or the apparent points of a
    nearby state). ``bad[k]`` True where no apparent point exists (then ``out_q`` = q and
    ``out_g`` = 0)."""
    for ch in numba.prange(0, c_start.shape[0]):
        cm = cen[c_cam[ch]]
        mp = mir[c_pose[ch]]
        s = mp[0] * cm[0] + mp[1] * cm[1] + mp[2] * cm[2] - mp[3]
        c = np.empty(3)
        for j in range(3):
            c[j] = cm[j] - 2.0 * s * mp[j]
        sc = np.empty((15, 3))
        for k in range(c_start[ch], c_end[ch]):
            good = _glass_row(q[k, 0], q[k, 1], q[k, 2], slope[k, 0], slope[k, 1], c, t, n, out_q[k], out_g[k], sc,
                              want_g, q_start[k, 0], q_start[k, 1], q_start[k, 2])
            bad[k] = not good
            if not good:
                for j in range(3):
                    out_q[k, j] = q[k, j]
                if want_g:
                    for j in range(GLASS_COLUMNS):
                        out_g[k, j] = 0.0


# ============================================================================ solver glue
_NO_GLASS = None


def _dummies():
    global _NO_GLASS
    if _NO_GLASS is None:
        _NO_GLASS = (np.zeros((1, GLASS_COLUMNS)), np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(0, dtype=np.int64),
                     np.zeros(0))
    return _NO_GLASS


def _derivative_weights(data, screen):
    """(dwx (M, n_x), dwy (M, n_y)): the screen basis weights' derivatives at the
    correspondences' (x_q, y_q), computed once per packed data set."""
    cached = getattr(data, "_glass_dw", None)
    if cached is None:
        from ..geometry.surface import cardinal_spline_coefficients
        from .screen import _basis_weights

        gx, gy = screen.grid_x_mm, screen.grid_y_mm
        cached = (np.ascontiguousarray(_basis_weights(gx, cardinal_spline_coefficients(gx), data.q[:, 0], True)),
                  np.ascontiguousarray(_basis_weights(gy, cardinal_spline_coefficients(gy), data.q[:, 1], True)))
        data._glass_dw = cached
    return cached


def glass_inputs(data, state, q, *, derivatives: bool = True):
    """The glass arguments of the calibration kernels for ``state`` (the solver's packed
    ``data``; ``q`` (N, 3) the emitting points, z from the screen model of ``state``):
    ``(glass_on, q_apparent, gl, dwx, dwy, gsel, g_units, bad)``; without a glass, ``glass_on``
    False, ``q`` unchanged and dummies. ``derivatives`` False: ``gl`` is not computed (only the
    apparent points are needed, e.g. at the acceleration's probe state).

    The result for the last state is kept on ``data`` (the solver evaluates a state, then its
    acceleration at the same state): a call for the same ``state`` object returns it; for
    another state, its apparent points start the fixed point (the states of one solve are near
    each other: two or three iterations instead of five; the result moves by < 1e-12 mm).
    """
    from .model import GLASS_UNITS

    gl0, dwx, dwy, gsel, g_units = _dummies()
    if not state.glass_active:
        return False, q, gl0, dwx, dwy, gsel, g_units, None
    cached = getattr(data, "_glass_last", None)
    if cached is not None and cached[0] is state and (cached[1] or not derivatives):
        return cached[2]
    if state.screen is not None:
        dwx, dwy = _derivative_weights(data, state.screen)
        z = np.asarray(state.screen.heights_mm, dtype=float)
        slope = np.column_stack([np.einsum("mi,mi->m", data.wy @ z, dwx), np.einsum("mi,mi->m", dwy @ z, data.wx)])
    else:
        slope = np.zeros((q.shape[0], 2))
    intr, rot, cen, mir, e1, e2 = state._arrays()
    q = np.ascontiguousarray(q)
    q_start = q if cached is None or cached[2][1].shape != q.shape else cached[2][1]
    qa = np.empty_like(q)
    gl = np.empty((q.shape[0], GLASS_COLUMNS))
    bad = np.empty(q.shape[0], dtype=np.bool_)
    glass_points_kernel(data.c_start, data.c_end, data.c_cam, data.c_pose, q, np.ascontiguousarray(slope), cen, mir,
                        float(state.glass.thickness_mm), float(state.glass.index), bool(derivatives), q_start, qa,
                        gl, bad)
    gsel = np.array(state.glass_index, dtype=np.int64)
    g_units = np.array([GLASS_UNITS[g] for g in state.glass_index], dtype=float)
    out = (True, qa, gl, dwx, dwy, gsel, g_units, bad)
    data._glass_last = (state, bool(derivatives), out)
    return out
