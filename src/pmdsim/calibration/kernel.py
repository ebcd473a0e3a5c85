"""Numba kernels of the calibration: forward model and analytic Jacobian, JᵀJ/Jᵀr accumulation.

The forward model (mirroring, rigid transform, projection with distortion) and the per-residual
Jacobian are described in :mod:`pmdsim.calibration.model`; the kernels work on packed arrays
prepared by :mod:`pmdsim.calibration.solver`.
"""

from __future__ import annotations

import numba
import numpy as np

from .batch_rows import (
    _BATCH, _batched_normal, _cross, _distorted, _dot3, _finish_normal, _gram_add, _h_matrix, _mirror_terms,
    _virtual_point,
)
from .model import _NB, _NC, _NJ, _NM


# ============================================================================ kernels
@numba.njit(cache=True)
def _model_row(u_obs, v_obs, qx, qy, qz, intr, rot, cen, mir, e1, e2, want_jac, jac):
    """Residual (predicted − observed, px) of one correspondence and, if ``want_jac``, its
    Jacobian (2 × 17) w.r.t. the block's parameters in natural units, written to ``jac[:, :17]``,
    and the derivatives w.r.t. the screen point, ∂r/∂q_z, ∂r/∂q_x, ∂r/∂q_y, written to
    ``jac[:, 17]``, ``jac[:, 18]``, ``jac[:, 19]`` (q's coordinates taken independently).

    intr: (9,) fx, fy, ppx, ppy, k1, k2, p1, p2, k3; rot: (3, 3) R_screen_cam; cen: (3,) camera
    centre in the screen frame; mir: (4,) n, d; e1, e2: tangent basis of n.
    Returns (ru, rv, ok) with ok False if the virtual point is not in front of the camera.
    """
    nx, ny, nz, dd = mir[0], mir[1], mir[2], mir[3]
    # Virtual (mirrored) screen point, p = Rᵀ w.
    s, wx, wy, wz = _virtual_point(qx, qy, qz, nx, ny, nz, dd, cen[0], cen[1], cen[2])
    px = _dot3(rot[0, 0], rot[1, 0], rot[2, 0], wx, wy, wz)
    py = _dot3(rot[0, 1], rot[1, 1], rot[2, 1], wx, wy, wz)
    pz = _dot3(rot[0, 2], rot[1, 2], rot[2, 2], wx, wy, wz)
    if not pz > 0.0:
        return 0.0, 0.0, False
    fx, fy, ppx, ppy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = intr[4], intr[5], intr[6], intr[7], intr[8]
    iz, x, y, r2, radial, xd, yd = _distorted(px, py, pz, k1, k2, p1, p2, k3)
    ru = fx * xd + ppx - u_obs
    rv = fy * yd + ppy - v_obs
    if not want_jac:
        return ru, rv, True
    for i in range(2):
        for j in range(_NJ):
            jac[i, j] = 0.0
    # Intrinsics.
    jac[0, 0] = xd
    jac[1, 1] = yd
    jac[0, 2] = 1.0
    jac[1, 3] = 1.0
    jac[0, 4] = fx * x * r2
    jac[1, 4] = fy * y * r2
    jac[0, 5] = fx * x * r2 * r2
    jac[1, 5] = fy * y * r2 * r2
    jac[0, 6] = fx * 2.0 * x * y
    jac[1, 6] = fy * (r2 + 2.0 * y * y)
    jac[0, 7] = fx * (r2 + 2.0 * x * x)
    jac[1, 7] = fy * 2.0 * x * y
    # H = d(u, v)/d w (screen frame).
    h00, h01, h02, h10, h11, h12 = _h_matrix(x, y, r2, radial, iz, fx, fy, k1, k2, p1, p2, k3, rot[0, 0], rot[0, 1],
                                             rot[0, 2], rot[1, 0], rot[1, 1], rot[1, 2], rot[2, 0], rot[2, 1],
                                             rot[2, 2])
    # Rotation increment R ← exp([δ]×) R: dp/dδ = Rᵀ [w]×, so d(u, v)_i/dδ = H_i × w.
    jac[0, 8], jac[0, 9], jac[0, 10] = _cross(h00, h01, h02, wx, wy, wz)
    jac[1, 8], jac[1, 9], jac[1, 10] = _cross(h10, h11, h12, wx, wy, wz)
    # Camera centre: dp/dc = −Rᵀ.
    jac[0, 11] = -h00
    jac[0, 12] = -h01
    jac[0, 13] = -h02
    jac[1, 11] = -h10
    jac[1, 12] = -h11
    jac[1, 13] = -h12
    # Mirror: dq'/dd = 2n, dq'/da = −2 (s e1 + (e1·q) n), likewise b with e2.
    jac[0, 14], jac[1, 14], jac[0, 15], jac[1, 15], hn0, hn1 = _mirror_terms(
        h00, h01, h02, h10, h11, h12, s, nx, ny, nz, e1[0], e1[1], e1[2], e2[0], e2[1], e2[2], qx, qy, qz)
    jac[0, 16] = 2.0 * hn0
    jac[1, 16] = 2.0 * hn1
    # Screen point: dq'/dq = I − 2 n nᵀ, so d(u, v)/dq_i = H e_i − 2 n_i H n.
    jac[0, _NB] = h02 - 2.0 * nz * hn0
    jac[1, _NB] = h12 - 2.0 * nz * hn1
    jac[0, _NB + 1] = h00 - 2.0 * nx * hn0
    jac[1, _NB + 1] = h10 - 2.0 * nx * hn1
    jac[0, _NB + 2] = h01 - 2.0 * ny * hn0
    jac[1, _NB + 2] = h11 - 2.0 * ny * hn1
    return ru, rv, True


@numba.njit(cache=True, inline="always")
def _glass_correct(jac, gk, mir_k, e1, e2, cen_c, ext):
    """Add the cover glass's terms to one correspondence's Jacobian, computed by
    :func:`_model_row` at the apparent point q (:mod:`pmdsim.calibration.glass_kernel`; ``gk``
    its 30 stored derivatives): the camera-centre and mirror columns through the virtual centre
    c′ (dq/dc′, with dc′/dc = I − 2nnᵀ, dc′/dd = 2n, dc′/da = −2(s_c·e1 + (e1·c)·n), likewise b),
    ∂r/∂(q_x, q_y, q_z) ← ∂r/∂q·(I − M)⁻¹ (w.r.t. the emitting point Q), and ``ext[i]`` =
    (∂r/∂h_x, ∂r/∂h_y through the plate normal, ∂r/∂t, ∂r/∂n)."""
    nx, ny, nz, dd = mir_k[0], mir_k[1], mir_k[2], mir_k[3]
    s_c = nx * cen_c[0] + ny * cen_c[1] + nz * cen_c[2] - dd
    e1c = e1[0] * cen_c[0] + e1[1] * cen_c[1] + e1[2] * cen_c[2]
    e2c = e2[0] * cen_c[0] + e2[1] * cen_c[1] + e2[2] * cen_c[2]
    for i in range(2):
        g0 = jac[i, _NB + 1]
        g1 = jac[i, _NB + 2]
        g2 = jac[i, _NB]
        gn0 = g0 * gk[9] + g1 * gk[12] + g2 * gk[15]
        gn1 = g0 * gk[10] + g1 * gk[13] + g2 * gk[16]
        gn2 = g0 * gk[11] + g1 * gk[14] + g2 * gk[17]
        gnn = gn0 * nx + gn1 * ny + gn2 * nz
        jac[i, 11] += gn0 - 2.0 * nx * gnn
        jac[i, 12] += gn1 - 2.0 * ny * gnn
        jac[i, 13] += gn2 - 2.0 * nz * gnn
        gne1 = gn0 * e1[0] + gn1 * e1[1] + gn2 * e1[2]
        gne2 = gn0 * e2[0] + gn1 * e2[1] + gn2 * e2[2]
        jac[i, 14] += -2.0 * (s_c * gne1 + e1c * gnn)
        jac[i, 15] += -2.0 * (s_c * gne2 + e2c * gnn)
        jac[i, 16] += 2.0 * gnn
        jac[i, _NB + 1] = g0 * gk[0] + g1 * gk[3] + g2 * gk[6]
        jac[i, _NB + 2] = g0 * gk[1] + g1 * gk[4] + g2 * gk[7]
        jac[i, _NB] = g0 * gk[2] + g1 * gk[5] + g2 * gk[8]
        ext[i, 0] = g0 * gk[24] + g1 * gk[25] + g2 * gk[26]
        ext[i, 1] = g0 * gk[27] + g1 * gk[28] + g2 * gk[29]
        ext[i, 2] = g0 * gk[18] + g1 * gk[19] + g2 * gk[20]
        ext[i, 3] = g0 * gk[21] + g1 * gk[22] + g2 * gk[23]


@numba.njit(cache=True)
def _chunk_run(start, end, cam, pose, uv, q, intr, rot, cen, mir, e1, e2, units, wx, wy, fi, fj, h_unit,
               want_normal, jtj, jtr, sandwich, slope, qstd, glass_on, gl, dwx, dwy, gsel, g_units):
    """Serial work item: correspondences start…end of one block. Accumulates the block's
    (scaled) JᵀJ (full square, the 17 block parameters then the F free screen heights) and Jᵀr
    if ``want_normal``. Returns (SSR, whitened SSR, number behind camera).

    Screen heights (F = ``fi.shape[0]`` may be 0): the column of free height f = (fj[f], fi[f])
    is (∂r/∂q_z)·wy[k, fj[f]]·wx[k, fi[f]].

    Accumulation: the Jacobian rows of :data:`_BATCH` correspondences, with the residuals as a
    last column, are gathered into a transposed buffer and added to [J r]ᵀ[J r] by
    :func:`_gram_add`, which gives JᵀJ and Jᵀr in one pass (upper triangle, mirrored at the end).

    ``sandwich`` (with ``want_normal``): the noise is in the decoded screen point (x_q, y_q),
    standard deviations ``qstd[k]`` (2,), and propagates to the residual by
    B_k = ∂r/∂(x_q, y_q)·diag(qstd[k]) (2 × 2; with the screen's height slope ``slope[k]``
    (∂h/∂x, ∂h/∂y), since q_z = h(x_q, y_q)): Cov(r_k) ∝ B_k B_kᵀ. Then ``jtj`` receives
    Σ_k J_kᵀ B_k B_kᵀ J_k (the middle of the sandwich covariance) instead of JᵀJ, and the
    whitened SSR Σ_k r_kᵀ (B_k B_kᵀ)⁻¹ r_k is returned.

    ``glass_on``: ``q`` holds the apparent points and ``gl`` (N, 30) their derivatives
    (:mod:`pmdsim.calibration.glass_kernel`, :func:`_glass_correct`); the screen-height columns
    gain the plate normal's terms (``dwx``, ``dwy``: the basis weights' derivatives), and the
    G = ``gsel.shape[0]`` free glass parameters (``gsel``: 0 thickness, 1 index; internal units
    ``g_units``) follow the screen heights."""
    if want_normal and not glass_on and not sandwich:
        ssr, nbad = _batched_normal(start, end, uv, q, intr[cam], rot[cam], cen[cam], mir[pose], e1[pose], e2[pose],
                                    units, wx, wy, fi, fj, h_unit, jtj, jtr)
        return ssr, 0.0, nbad
    nf = fi.shape[0]
    ng = gsel.shape[0]
    npar = _NB + nf + ng
    jac = np.zeros((2, _NJ))
    ext = np.zeros((2, 4))
    if want_normal:
        ncol = npar + 1 + ((npar + 1) & 1)  # parameters, residual, padding to an even count
        bt = np.zeros((ncol, 2 * _BATCH))
        acc = np.zeros((ncol, ncol))
    else:
        bt = np.zeros((2, 2))
        acc = np.zeros((2, 2))
    slot = 0
    ssr = 0.0
    ssr_w = 0.0
    nbad = 0
    intr_c = intr[cam]
    rot_c = rot[cam]
    cen_c = cen[cam]
    mir_k = mir[pose]
    e1_k = e1[pose]
    e2_k = e2[pose]
    for k in range(start, end):
        ru, rv, ok = _model_row(uv[k, 0], uv[k, 1], q[k, 0], q[k, 1], q[k, 2], intr_c, rot_c,
                                cen_c, mir_k, e1_k, e2_k, want_normal, jac)
        if not ok:
            nbad += 1
            continue
        ssr += ru * ru + rv * rv
        if want_normal:
            if glass_on:
                _glass_correct(jac, gl[k], mir_k, e1_k, e2_k, cen_c, ext)
            for j in range(_NB):
                jac[0, j] *= units[j]
                jac[1, j] *= units[j]
            if sandwich:
                # B = ∂r/∂(x_q, y_q) with q_z = h(x_q, y_q), times diag(qstd).
                b00 = (jac[0, _NB + 1] + jac[0, _NB] * slope[k, 0]) * qstd[k, 0]
                b10 = (jac[1, _NB + 1] + jac[1, _NB] * slope[k, 0]) * qstd[k, 0]
                b01 = (jac[0, _NB + 2] + jac[0, _NB] * slope[k, 1]) * qstd[k, 1]
                b11 = (jac[1, _NB + 2] + jac[1, _NB] * slope[k, 1]) * qstd[k, 1]
                det = b00 * b11 - b01 * b10
                e0 = (b11 * ru - b01 * rv) / det  # B⁻¹ r: the residual on the screen, in σ
                e1w = (-b10 * ru + b00 * rv) / det
                ssr_w += e0 * e0 + e1w * e1w
                # J ← Bᵀ J (rows), so that the accumulated JᵀJ is Jᵀ B Bᵀ J.
                for j in range(_NB + 1):
                    j0 = jac[0, j]
                    j1 = jac[1, j]
                    jac[0, j] = b00 * j0 + b10 * j1
                    jac[1, j] = b01 * j0 + b11 * j1
                if glass_on:
                    for j in range(4):
                        j0 = ext[0, j]
                        j1 = ext[1, j]
                        ext[0, j] = b00 * j0 + b10 * j1
                        ext[1, j] = b01 * j0 + b11 * j1
            c0 = 2 * slot
            c1 = c0 + 1
            for j in range(_NB):
                bt[j, c0] = jac[0, j]
                bt[j, c1] = jac[1, j]
            if nf > 0:
                dz0 = jac[0, _NB] * h_unit
                dz1 = jac[1, _NB] * h_unit
                for f in range(nf):
                    sf = wy[k, fj[f]] * wx[k, fi[f]]
                    bt[_NB + f, c0] = dz0 * sf
                    bt[_NB + f, c1] = dz1 * sf
                    if glass_on:
                        sx = dwx[k, fi[f]] * wy[k, fj[f]] * h_unit
                        sy = wx[k, fi[f]] * dwy[k, fj[f]] * h_unit
                        bt[_NB + f, c0] += ext[0, 0] * sx + ext[0, 1] * sy
                        bt[_NB + f, c1] += ext[1, 0] * sx + ext[1, 1] * sy
            for g in range(ng):
                bt[_NB + nf + g, c0] = ext[0, 2 + gsel[g]] * g_units[g]
                bt[_NB + nf + g, c1] = ext[1, 2 + gsel[g]] * g_units[g]
            bt[npar, c0] = ru
            bt[npar, c1] = rv
            slot += 1
            if slot == _BATCH:
                _gram_add(bt, 2 * slot, acc)
                slot = 0
    if want_normal:
        if slot > 0:
            _gram_add(bt, 2 * slot, acc)
        _finish_normal(acc, npar, jtj, jtr)
    return ssr, ssr_w, nbad



@numba.njit(cache=True, parallel=True)
def _chunks_kernel(c_start, c_end, c_cam, c_pose, uv, q, intr, rot, cen, mir, e1, e2, units, wx, wy, fi, fj,
                   h_unit, want_normal, jtj, jtr, ssr, nbad, sandwich, slope, qstd, ssr_w, glass_on, gl, dwx, dwy,
                   gsel, g_units):
    for c in numba.prange(0, c_start.shape[0]):
        s, sw, b = _chunk_run(c_start[c], c_end[c], c_cam[c], c_pose[c], uv, q, intr, rot, cen, mir,
                              e1, e2, units, wx, wy, fi, fj, h_unit, want_normal, jtj[c], jtr[c],
                              sandwich, slope, qstd, glass_on, gl, dwx, dwy, gsel, g_units)
        ssr[c] = s
        ssr_w[c] = sw
        nbad[c] = b


@numba.njit(cache=True)
def _rows_kernel(cam_idx, pose_idx, uv, q, intr, rot, cen, mir, e1, e2, res, jac, ok, glass_on, gl, ext_out):
    """Residuals (N, 2), Jacobian blocks (N, 2, 20) in natural units (17 block columns, then
    ∂r/∂q_z, ∂r/∂q_x, ∂r/∂q_y) and validity, per row; with ``glass_on`` (``q``: the apparent
    points, ``gl`` their derivatives) corrected by :func:`_glass_correct`, whose extra columns
    go to ``ext_out`` (N, 2, 4)."""
    tmp = np.zeros((2, _NJ))
    ext = np.zeros((2, 4))
    for k in range(uv.shape[0]):
        c = cam_idx[k]
        p = pose_idx[k]
        ru, rv, good = _model_row(uv[k, 0], uv[k, 1], q[k, 0], q[k, 1], q[k, 2], intr[c], rot[c],
                                  cen[c], mir[p], e1[p], e2[p], np.bool_(True), tmp)
        if glass_on:
            _glass_correct(tmp, gl[k], mir[p], e1[p], e2[p], cen[c], ext)
            for i in range(2):
                for j in range(4):
                    ext_out[k, i, j] = ext[i, j]
        res[k, 0] = ru
        res[k, 1] = rv
        ok[k] = good
        for i in range(2):
            for j in range(_NJ):
                jac[k, i, j] = tmp[i, j]


@numba.njit(cache=True)
def _avv_run(start, end, cam, pose, uv, q, q_t, intr, rot, cen, mir, e1, e2, intr_t, rot_t, cen_t, mir_t, e1_t,
             e2_t, d_cam, d_mir, d_h, units, wx, wy, fi, fj, h_unit, h, out, glass_on, gl, dwx, dwy, gsel, g_units,
             d_g):
    """Serial work item of :func:`_avv_kernel`: adds J_kᵀ·r_vv,k (internal units) of the
    correspondences start…end of one block to ``out`` (17 + F,). Returns the number of
    correspondences skipped because a virtual point lies behind the camera at x or at x + hδ."""
    nf = fi.shape[0]
    ng = gsel.shape[0]
    jac = np.zeros((2, _NJ))
    ext = np.zeros((2, 4))
    dummy = np.zeros((2, _NJ))
    acc = np.zeros(_NB + nf + ng)
    nbad = 0
    dc = d_cam[cam]
    dm = d_mir[pose]
    intr_c, rot_c, cen_c, mir_k, e1_k, e2_k = intr[cam], rot[cam], cen[cam], mir[pose], e1[pose], e2[pose]
    intr_tc, rot_tc, cen_tc = intr_t[cam], rot_t[cam], cen_t[cam]
    mir_tk, e1_tk, e2_tk = mir_t[pose], e1_t[pose], e2_t[pose]
    inv_h = 1.0 / h
    for k in range(start, end):
        # np.bool_: a run-time flag, not a literal, so that _model_row compiles once for all its
        # callers (each literal is a compile of its own on a cold cache).
        ru, rv, ok = _model_row(uv[k, 0], uv[k, 1], q[k, 0], q[k, 1], q[k, 2], intr_c, rot_c, cen_c, mir_k, e1_k,
                                e2_k, np.bool_(True), jac)
        rut, rvt, ok_t = _model_row(uv[k, 0], uv[k, 1], q_t[k, 0], q_t[k, 1], q_t[k, 2], intr_tc, rot_tc, cen_tc,
                                    mir_tk, e1_tk, e2_tk, np.bool_(False), dummy)
        if not (ok and ok_t):
            nbad += 1
            continue
        if glass_on:
            _glass_correct(jac, gl[k], mir_k, e1_k, e2_k, cen_c, ext)
        # J·δ (natural units).
        jd0 = 0.0
        jd1 = 0.0
        for j in range(_NC):
            jd0 += jac[0, j] * dc[j]
            jd1 += jac[1, j] * dc[j]
        for j in range(_NM):
            jd0 += jac[0, _NC + j] * dm[j]
            jd1 += jac[1, _NC + j] * dm[j]
        dz_h = 0.0
        for f in range(nf):
            dz_h += wy[k, fj[f]] * wx[k, fi[f]] * d_h[f]
        jd0 += jac[0, _NB] * dz_h
        jd1 += jac[1, _NB] * dz_h
        if glass_on:
            dsx = 0.0
            dsy = 0.0
            for f in range(nf):
                dsx += dwx[k, fi[f]] * wy[k, fj[f]] * d_h[f]
                dsy += wx[k, fi[f]] * dwy[k, fj[f]] * d_h[f]
            jd0 += ext[0, 0] * dsx + ext[0, 1] * dsy
            jd1 += ext[1, 0] * dsx + ext[1, 1] * dsy
            for g in range(ng):
                jd0 += ext[0, 2 + gsel[g]] * d_g[g]
                jd1 += ext[1, 2 + gsel[g]] * d_g[g]
        # Second directional derivative by a finite difference along δ.
        a0 = 2.0 * inv_h * ((rut - ru) * inv_h - jd0)
        a1 = 2.0 * inv_h * ((rvt - rv) * inv_h - jd1)
        for j in range(_NB):
            acc[j] += jac[0, j] * a0 + jac[1, j] * a1
        if nf > 0:
            gz = (jac[0, _NB] * a0 + jac[1, _NB] * a1) * h_unit
            for f in range(nf):
                acc[_NB + f] += gz * wy[k, fj[f]] * wx[k, fi[f]]
                if glass_on:
                    gx_ = (ext[0, 0] * a0 + ext[1, 0] * a1) * h_unit
                    gy_ = (ext[0, 1] * a0 + ext[1, 1] * a1) * h_unit
                    acc[_NB + f] += gx_ * dwx[k, fi[f]] * wy[k, fj[f]] + gy_ * wx[k, fi[f]] * dwy[k, fj[f]]
        for g in range(ng):
            acc[_NB + nf + g] += (ext[0, 2 + gsel[g]] * a0 + ext[1, 2 + gsel[g]] * a1) * g_units[g]
    for j in range(_NB):
        out[j] = acc[j] * units[j]
    for f in range(nf + ng):
        out[_NB + f] = acc[_NB + f]
    return nbad


@numba.njit(cache=True, parallel=True)
def _avv_kernel(c_start, c_end, c_cam, c_pose, uv, q, q_t, intr, rot, cen, mir, e1, e2, intr_t, rot_t, cen_t, mir_t,
                e1_t, e2_t, d_cam, d_mir, d_h, units, wx, wy, fi, fj, h_unit, h, out, nbad, glass_on, gl, dwx, dwy, gsel,
                g_units, d_g):
    """Jᵀ·r_vv per chunk for the geodesic acceleration of Levenberg–Marquardt (Transtrum &
    Sethna 2012): r_vv ≈ (2/h)·((r(x + hδ) − r(x))/h − J·δ), the second directional derivative
    of the residuals along the step δ, by a finite difference.

    The state x is given by (intr … e2), the state x + hδ by (intr_t … e2_t) with ``q_t`` its
    screen points; δ in natural units per block: ``d_cam`` (C, 14), ``d_mir`` (K, 3), ``d_h``
    (F,). ``out`` (chunks, 17 + F) receives Jᵀ·r_vv in internal units (block parameters, then
    the free screen heights, then the free glass parameters), ``nbad`` (chunks,) the skipped
    correspondences. With ``glass_on``, ``q`` and ``q_t`` are the apparent points at x and
    x + hδ, ``gl`` the derivatives at x and ``d_g`` the glass part of δ."""
    for c in numba.prange(0, c_start.shape[0]):
        nbad[c] = _avv_run(c_start[c], c_end[c], c_cam[c], c_pose[c], uv, q, q_t, intr, rot, cen, mir, e1, e2,
                           intr_t, rot_t, cen_t, mir_t, e1_t, e2_t, d_cam, d_mir, d_h, units, wx, wy, fi, fj, h_unit,
                           h, out[c], glass_on, gl, dwx, dwy, gsel, g_units, d_g)


@numba.njit(cache=True, parallel=True)
def _screen_points_kernel(q, wx, wy, heights, out):
    """out[m] = (q[m, 0], q[m, 1], Σ_j Σ_i wy[m, j]·heights[j, i]·wx[m, i]): the correspondences'
    screen points with z = h(x_q, y_q) of the screen model (1-D basis weights per correspondence)."""
    ny, nx = heights.shape
    for m in numba.prange(0, q.shape[0]):
        z = 0.0
        for j in range(ny):
            s = 0.0
            for i in range(nx):
                s += heights[j, i] * wx[m, i]
            z += wy[m, j] * s
        out[m, 0] = q[m, 0]
        out[m, 1] = q[m, 1]
        out[m, 2] = z
