"""The calibration's model rows and analytic Jacobian for a batch of correspondences at once.

:func:`pmdsim.calibration.kernel._model_row` computes one correspondence's residual and Jacobian
(≈ 300 flops of dependent scalar code) and :func:`pmdsim.calibration.kernel._chunk_run` gathers
its 2 × 17 values into the transposed batch buffer of the Gram product with strided stores. Here
the same arithmetic runs across up to ``_BATCH`` correspondences in one loop without branches,
so that it vectorises (structure of arrays: each Jacobian column is written for consecutive
correspondences to one row of the buffer). The expressions are those of ``_model_row``, term by
term and in the same order, without fast-math: the buffer, and so JᵀJ and Jᵀr, are bit for bit
the scalar path's. Used by ``_chunk_run`` for the normal equations without the cover glass and
without the sandwich (the Levenberg–Marquardt iterations); the other cases keep the scalar path.
"""

from __future__ import annotations

import numba
import numpy as np

from .model import _NB

#: Correspondences whose Jacobian rows are gathered before they are added to JᵀJ (2 rows each).
_BATCH = 64

# The scratch vector of one work item (float64): _NS fields of _BATCH values, field ``f`` of
# correspondence i at ``f·_BATCH + i``: the inputs copied in, the per-correspondence outputs and,
# from _J0 on, the scaled Jacobian, field _J0 + 2j (u) and _J0 + 2j + 1 (v) for column j (the
# fields of the constant and zero entries of columns 0 … 3 are not used). With _BATCH a
# compile-time constant LLVM sees that the fields never overlap (constant dependence distances,
# as in pmdsim.simulation.trace_rows) and vectorises the model loop without run-time checks. The
# Gram buffer interleaves u and v (columns 2i, 2i + 1): stores with stride 2 would need a
# run-time no-wrap check each (numba's addresses carry no ``inbounds``), more than LLVM accepts
# in one loop, so a short loop per Jacobian column copies the fields into it.
(_U, _V, _QX, _QY, _QZ, _RU, _RV, _DZU, _DZV, _OK) = range(10)
_J0 = 10
_NS = _J0 + 2 * _NB
# No ZeroDivisionError branch in 1/p_z (it would stop the vectoriser); no fast-math: the
# expressions are evaluated exactly as written, as in the scalar _model_row.
_JIT = dict(cache=True, error_model="numpy")



# ---------------------------------------------------------------- the model's terms
# Shared by kernel._model_row (one correspondence) and _batch_rows (a loop over many): inlined
# into both, each expression evaluated in the order written, so that the two give the same bits.
@numba.njit(cache=True, inline="always")
def _dot3(a0, a1, a2, b0, b1, b2):
    """a0·b0 + a1·b1 + a2·b2, summed left to right."""
    return a0 * b0 + a1 * b1 + a2 * b2


@numba.njit(cache=True, inline="always")
def _cross(h0, h1, h2, w0, w1, w2):
    """h × w (3 components)."""
    return h1 * w2 - h2 * w1, h2 * w0 - h0 * w2, h0 * w1 - h1 * w0


@numba.njit(cache=True, inline="always")
def _virtual_point(qx, qy, qz, nx, ny, nz, dd, cx, cy, cz):
    """(s, w): the screen point's signed distance s = n·q − d from the mirror plane and
    w = q − 2sn − c, its mirror image relative to the camera centre c (screen frame, mm)."""
    s = _dot3(nx, ny, nz, qx, qy, qz) - dd
    return s, qx - 2.0 * s * nx - cx, qy - 2.0 * s * ny - cy, qz - 2.0 * s * nz - cz


@numba.njit(cache=True, inline="always")
def _distorted(px, py, pz, k1, k2, p1, p2, k3):
    """(1/z, x, y, r², radial factor, x_d, y_d) of the camera-frame point p: the normalised
    point and its Brown–Conrady distortion."""
    iz = 1.0 / pz
    x = px * iz
    y = py * iz
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return iz, x, y, r2, radial, xd, yd


@numba.njit(cache=True, inline="always")
def _h_matrix(x, y, r2, radial, iz, fx, fy, k1, k2, p1, p2, k3, r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """H = G Rᵀ = d(u, v)/d w (2 × 3, row-major), with G = d(u, v)/d p from d(x_d, y_d)/d(x, y)
    and dx/dp = (1/z, 0, −x/z), dy/dp = (0, 1/z, −y/z); r_ij: R_screen_cam."""
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # = d(x_d)/dy = d(y_d)/dx
    d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    g00 = fx * a * iz
    g01 = fx * b * iz
    g02 = -fx * (a * x + b * y) * iz
    g10 = fy * b * iz
    g11 = fy * d * iz
    g12 = -fy * (b * x + d * y) * iz
    return (_dot3(g00, g01, g02, r00, r01, r02), _dot3(g00, g01, g02, r10, r11, r12),
            _dot3(g00, g01, g02, r20, r21, r22), _dot3(g10, g11, g12, r00, r01, r02),
            _dot3(g10, g11, g12, r10, r11, r12), _dot3(g10, g11, g12, r20, r21, r22))


@numba.njit(cache=True, inline="always")
def _mirror_terms(h00, h01, h02, h10, h11, h12, s, nx, ny, nz, e10, e11, e12, e20, e21, e22, qx, qy, qz):
    """The mirror's columns through dq'/da = −2 (s e1 + (e1·q) n) and likewise b with e2:
    (∂u/∂a, ∂v/∂a, ∂u/∂b, ∂v/∂b), and H n (2,) (dq'/dd = 2n; dq'/dq = I − 2 n nᵀ)."""
    hn0 = _dot3(h00, h01, h02, nx, ny, nz)
    hn1 = _dot3(h10, h11, h12, nx, ny, nz)
    e1q = _dot3(e10, e11, e12, qx, qy, qz)
    e2q = _dot3(e20, e21, e22, qx, qy, qz)
    return (-2.0 * (s * _dot3(h00, h01, h02, e10, e11, e12) + e1q * hn0),
            -2.0 * (s * _dot3(h10, h11, h12, e10, e11, e12) + e1q * hn1),
            -2.0 * (s * _dot3(h00, h01, h02, e20, e21, e22) + e2q * hn0),
            -2.0 * (s * _dot3(h10, h11, h12, e20, e21, e22) + e2q * hn1), hn0, hn1)


@numba.njit(**_JIT)
def _batch_rows(m, S, intr, rot, cen, mir, e1, e2, units):
    """Residuals and scaled Jacobian rows of the m ≤ _BATCH correspondences whose inputs are in
    the fields _U, _V (observed pixel) and _QX, _QY, _QZ (screen point, mm, screen frame) of the
    scratch ``S``.

    Correspondence i's scaled Jacobian goes to the fields _J0 + 2j (u) and _J0 + 2j + 1 (v) of
    columns j = 4 … 16 and of the non-zero entries of columns 0, 1 (x_d·units[0], y_d·units[1];
    columns 2 and 3 are constant: (units[2], 0) and (0, units[3])); its residuals (px) to _RU, _RV; ∂r/∂q_z (px/mm) to _DZU, _DZV; 1.0
    to _OK if the virtual point is in front of the camera, else 0.0 (and the other values have
    no meaning). ``intr``, ``rot``, ``cen``, ``mir``, ``e1``, ``e2``: (9,), (3, 3), (3,), (4,),
    (3,), (3,) the block's camera (intrinsics, R_screen_cam, centre in the screen frame) and
    mirror (n, d; the tangent basis e1, e2 of n), as for ``kernel._model_row``; ``units`` (17,)
    the internal units the 17 columns are multiplied by."""
    B = _BATCH
    nx, ny, nz, dd = mir[0], mir[1], mir[2], mir[3]
    cx, cy, cz = cen[0], cen[1], cen[2]
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    fx, fy, ppx, ppy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = intr[4], intr[5], intr[6], intr[7], intr[8]
    e10, e11, e12 = e1[0], e1[1], e1[2]
    e20, e21, e22 = e2[0], e2[1], e2[2]
    u0, u1, u2, u3, u4, u5, u6, u7 = units[0], units[1], units[2], units[3], units[4], units[5], units[6], units[7]
    u8, u9, u10, u11, u12, u13 = units[8], units[9], units[10], units[11], units[12], units[13]
    u14, u15, u16 = units[14], units[15], units[16]
    for i in range(m):
        qx = S[_QX * B + i]
        qy = S[_QY * B + i]
        qz = S[_QZ * B + i]
        # The mirrored point, p = Rᵀ w, projection and distortion.
        s, wx, wy, wz = _virtual_point(qx, qy, qz, nx, ny, nz, dd, cx, cy, cz)
        px = _dot3(r00, r10, r20, wx, wy, wz)
        py = _dot3(r01, r11, r21, wx, wy, wz)
        pz = _dot3(r02, r12, r22, wx, wy, wz)
        S[_OK * B + i] = 1.0 if pz > 0.0 else 0.0
        iz, x, y, r2, radial, xd, yd = _distorted(px, py, pz, k1, k2, p1, p2, k3)
        S[_RU * B + i] = fx * xd + ppx - S[_U * B + i]
        S[_RV * B + i] = fy * yd + ppy - S[_V * B + i]
        # Intrinsics (columns 2 and 3 are constant).
        S[_J0 * B + i] = xd * u0
        S[(_J0 + 3) * B + i] = yd * u1
        S[(_J0 + 8) * B + i] = fx * x * r2 * u4
        S[(_J0 + 9) * B + i] = fy * y * r2 * u4
        S[(_J0 + 10) * B + i] = fx * x * r2 * r2 * u5
        S[(_J0 + 11) * B + i] = fy * y * r2 * r2 * u5
        S[(_J0 + 12) * B + i] = fx * 2.0 * x * y * u6
        S[(_J0 + 13) * B + i] = fy * (r2 + 2.0 * y * y) * u6
        S[(_J0 + 14) * B + i] = fx * (r2 + 2.0 * x * x) * u7
        S[(_J0 + 15) * B + i] = fy * 2.0 * x * y * u7
        h00, h01, h02, h10, h11, h12 = _h_matrix(x, y, r2, radial, iz, fx, fy, k1, k2, p1, p2, k3, r00, r01, r02,
                                                 r10, r11, r12, r20, r21, r22)
        # Rotation increment: d(u, v)_i/dδ = H_i × w; camera centre: −H.
        ru8, ru9, ru10 = _cross(h00, h01, h02, wx, wy, wz)
        rv8, rv9, rv10 = _cross(h10, h11, h12, wx, wy, wz)
        S[(_J0 + 16) * B + i] = ru8 * u8
        S[(_J0 + 17) * B + i] = rv8 * u8
        S[(_J0 + 18) * B + i] = ru9 * u9
        S[(_J0 + 19) * B + i] = rv9 * u9
        S[(_J0 + 20) * B + i] = ru10 * u10
        S[(_J0 + 21) * B + i] = rv10 * u10
        S[(_J0 + 22) * B + i] = -h00 * u11
        S[(_J0 + 23) * B + i] = -h10 * u11
        S[(_J0 + 24) * B + i] = -h01 * u12
        S[(_J0 + 25) * B + i] = -h11 * u12
        S[(_J0 + 26) * B + i] = -h02 * u13
        S[(_J0 + 27) * B + i] = -h12 * u13
        # Mirror: tilts a, b and distance d.
        ma0, ma1, mb0, mb1, hn0, hn1 = _mirror_terms(h00, h01, h02, h10, h11, h12, s, nx, ny, nz, e10, e11, e12,
                                                     e20, e21, e22, qx, qy, qz)
        S[(_J0 + 28) * B + i] = ma0 * u14
        S[(_J0 + 29) * B + i] = ma1 * u14
        S[(_J0 + 30) * B + i] = mb0 * u15
        S[(_J0 + 31) * B + i] = mb1 * u15
        S[(_J0 + 32) * B + i] = 2.0 * hn0 * u16
        S[(_J0 + 33) * B + i] = 2.0 * hn1 * u16
        # The screen point's height: dq'/dq = I − 2 n nᵀ.
        S[_DZU * B + i] = h02 - 2.0 * nz * hn0
        S[_DZV * B + i] = h12 - 2.0 * nz * hn1


@numba.njit(**_JIT)
def _interleave(m, S, G):
    """Copy the Jacobian fields of the m correspondences in ``S`` to the flat Gram buffer ``G``
    (from the first free column on, row stride 2·_BATCH): correspondence i's u row to column 2i,
    its v row to 2i + 1 (only the non-zero entries of columns 0 and 1; 2 and 3 are constant)."""
    B = _BATCH
    W = 2 * _BATCH
    for i in range(m):
        G[2 * i] = S[_J0 * B + i]
    for i in range(m):
        G[W + 2 * i + 1] = S[(_J0 + 3) * B + i]
    for j in range(4, _NB):
        gj = G[j * W:]
        su = S[(_J0 + 2 * j) * B:]
        sv = S[(_J0 + 2 * j + 1) * B:]
        for i in range(m):
            gj[2 * i] = su[i]
            gj[2 * i + 1] = sv[i]


@numba.njit(cache=True, fastmath={"reassoc", "contract", "nsz"})
def _gram_add(bt, rows, acc):
    """acc[i, j] += Σ_q bt[i, q]·bt[j, q] over q < ``rows``, for i ≤ j (upper triangle, in 2 × 2
    tiles: ``bt.shape[0]`` must be even).

    ``bt`` (C, R) holds the gathered Jacobian rows as columns (a transposed buffer), so that each
    sum runs over contiguous memory; the 2 × 2 tiles reuse each loaded value twice. This is
    JᵀJ of the batch at several times the speed of a rank-2 update per correspondence: the sums
    vectorise (reassociation is allowed here only; the result depends on the batch layout, which
    is fixed, not on the number of threads)."""
    nc = bt.shape[0]
    for i in range(0, nc, 2):
        for j in range(i, nc, 2):
            s00 = 0.0
            s01 = 0.0
            s10 = 0.0
            s11 = 0.0
            for q in range(rows):
                a0 = bt[i, q]
                a1 = bt[i + 1, q]
                b0 = bt[j, q]
                b1 = bt[j + 1, q]
                s00 += a0 * b0
                s01 += a0 * b1
                s10 += a1 * b0
                s11 += a1 * b1
            acc[i, j] += s00
            acc[i, j + 1] += s01
            acc[i + 1, j] += s10
            acc[i + 1, j + 1] += s11


@numba.njit(cache=True)
def _finish_normal(acc, npar, jtj, jtr):
    """JᵀJ (npar, npar), mirrored from the upper triangle of [J r]ᵀ[J r] in ``acc``, and Jᵀr (npar,)."""
    for i in range(npar):
        jtr[i] = acc[i, npar]
        for j in range(i, npar):
            jtj[i, j] = acc[i, j]
            jtj[j, i] = acc[i, j]


@numba.njit(cache=True)
def _batched_normal(start, end, uv, q, intr_c, rot_c, cen_c, mir_k, e1_k, e2_k, units, wx, wy, fi, fj, h_unit,
                    jtj, jtr):
    """JᵀJ and Jᵀr (scaled) of correspondences start…end of one block (no cover glass, no
    sandwich): :func:`pmdsim.calibration.kernel._chunk_run`'s accumulation with the model rows
    computed by :func:`_batch_rows` for up to ``_BATCH`` correspondences at once, into the Gram
    buffer at the next free slot. Correspondences behind the camera are squeezed out of the
    buffer, so that its batches, and so the sums, are the scalar path's bit for bit.

    ``uv`` (N, 2), ``q`` (N, 3): observed pixels, screen points; ``wx``, ``wy``, ``fi``, ``fj``,
    ``h_unit``: the free screen heights as for ``_chunk_run``; ``jtj`` (17 + F, 17 + F) and
    ``jtr`` (17 + F,) receive the sums. Returns (SSR, number behind camera)."""
    B = _BATCH
    nf = fi.shape[0]
    npar = _NB + nf
    ncol = npar + 1 + ((npar + 1) & 1)  # parameters, residual, padding to an even count
    W = 2 * _BATCH
    S = np.zeros(_NS * B)
    flat = np.zeros(ncol * W)
    bt = flat.reshape((ncol, W))
    for c in range(B):  # the constant columns 2 and 3 (2 is ∂u/∂ppx, 3 ∂v/∂ppy)
        bt[2, 2 * c] = units[2]
        bt[3, 2 * c + 1] = units[3]
    acc = np.zeros((ncol, ncol))
    slot = 0
    ssr = 0.0
    nbad = 0
    k0 = start
    while k0 < end:
        m = min(B - slot, end - k0)
        c0 = 2 * slot
        for i in range(m):
            S[_U * B + i] = uv[k0 + i, 0]
            S[_V * B + i] = uv[k0 + i, 1]
            S[_QX * B + i] = q[k0 + i, 0]
            S[_QY * B + i] = q[k0 + i, 1]
            S[_QZ * B + i] = q[k0 + i, 2]
        _batch_rows(m, S, intr_c, rot_c, cen_c, mir_k, e1_k, e2_k, units)
        _interleave(m, S, flat[c0:])
        for f in range(nf):
            for i in range(m):
                sf = wy[k0 + i, fj[f]] * wx[k0 + i, fi[f]]
                bt[_NB + f, c0 + 2 * i] = S[_DZU * B + i] * h_unit * sf
                bt[_NB + f, c0 + 2 * i + 1] = S[_DZV * B + i] * h_unit * sf
        n_ok = 0
        for i in range(m):
            n_ok += 1 if S[_OK * B + i] != 0.0 else 0  # an integer sum: vectorised
        m_done = 0
        if n_ok == m:  # all in front of the camera: nothing to squeeze out
            for i in range(m):
                ru = S[_RU * B + i]
                rv = S[_RV * B + i]
                ssr += ru * ru + rv * rv
                bt[npar, c0 + 2 * i] = ru
                bt[npar, c0 + 2 * i + 1] = rv
            slot += m
            m_done = m
        for i in range(m_done, m):
            if S[_OK * B + i] == 0.0:
                nbad += 1
                continue
            ru = S[_RU * B + i]
            rv = S[_RV * B + i]
            ssr += ru * ru + rv * rv
            src = c0 + 2 * i
            dst = 2 * slot
            if dst != src:
                for j in range(npar):
                    bt[j, dst] = bt[j, src]
                    bt[j, dst + 1] = bt[j, src + 1]
            bt[npar, dst] = ru
            bt[npar, dst + 1] = rv
            slot += 1
        if slot == B:
            _gram_add(bt, 2 * slot, acc)
            slot = 0
        k0 += m
    if slot > 0:
        _gram_add(bt, 2 * slot, acc)
    _finish_normal(acc, npar, jtj, jtr)
    return ssr, nbad
