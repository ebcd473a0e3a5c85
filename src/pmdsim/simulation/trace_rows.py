"""Vectorised row kernel of the tracer: one image row, in blocks of pixels, stage by stage.

:func:`pmdsim.simulation.trace._trace_run` traces every image row after the first of a band
here. Such a row's pixels are warm started from the rows above and do not depend on each
other, so the row is traced one stage at a time over a block of up to ``_BLK`` pixels, each
stage a loop without calls that LLVM compiles to SIMD instructions (AVX2/AVX-512 lanes):

1. view ray in the sample frame and its parametrisation by height (paper eqs. 10–16); a
   planar sample is intersected in the same loop (eqs. 9–12);
2. sample intersection of any other surface: a spline surface by one Newton step
   per pixel (:func:`pmdsim.geometry.surface._newton_step`), the pixels of the block grouped
   into runs that use the same bicubic patch, whose 16 coefficients are then loop-invariant
   scalars (no gathers);
3. grazing-incidence test, reflection (eq. 17), reflected ray in the screen frame;
4. screen intersection as in 2, without the gradient;
5. status codes and stores.

Pixels that the vectorised steps do not settle (no warm start, a Newton step not converged by
its error bound, an analytic shape) are traced by the scalar kernels of
:mod:`pmdsim.geometry.surface` (``intersect_kernel`` then ``intersect_solve``), exactly as the
pixel-by-pixel loop does, so the accepted roots, error bounds and status codes are the same.

The arithmetic of stages 1–3 and 5 repeats that of :mod:`.trace`'s pixel loop (ray set-up,
reflection, status) on purpose: there it runs one pixel at a time with a call per stage, here
each stage is a call-free loop over a block (structure of arrays), which is what lets LLVM
vectorise it; merging the two was not tried. ``tests/test_trace.py`` checks the two against each other
(status identical, points within the intersection tolerance) and against closed forms.

All intermediate values live in one scratch vector per band, field ``f`` of pixel ``i`` at
``f·_BLK + i``: with ``_BLK`` a compile-time constant, LLVM sees that the fields of a pixel
never overlap (a constant dependence distance) and vectorises without run-time alias checks.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.surface import (
    _KIND_PLANE, _KIND_SPLINE, _NEEDS_SOLVE, _interval, intersect_kernel, intersect_solve,
)

#: Pixels per block: the scratch of a band holds ``_NF`` fields of ``_BLK`` float64 = 19 kB (the
#: glass-free trace uses 13 kB of it), which stays in a 32–48 kB L1 data cache together with the
#: warm-start rows of the block (4 or, with a cover glass, 14 rows of ``_BLK`` values). With 128
#: (38 kB of scratch and 14 kB of rows) the trace with a glass ran 6–13 ms slower on Table 1, the
#: glass-free one the same (docs/benchmarks.md, "Cover glass (issue 21): blocks of 64 pixels").
#: Results do not depend on it (the pixels of a row are independent).
_BLK = 64

# Scratch fields (float64; codes stored as small integers in float64). The intersection
# stages work on the generic fields _AX … _C (first for the sample, then for the screen).
(_VX, _VY, _VZ, _PX, _PY, _PZ, _SC, _QOX, _QOY, _QOZ, _WX, _WY, _WZ,
 _AX, _AY, _BX, _BY, _INV, _ZG, _Z, _X, _Y, _HX, _HY, _CONV, _C) = range(26)
# With a cover glass (pmdsim.simulation.glass_rows): the foot point, the reflected ray's origin z
# (kept for the scalar path: _QOZ then holds the refracted ray's, the outer-surface height A_z, a
# warm start of the rows below as the plate normal's m_x, m_y), the edge margin (−1: pixel not
# traced through the glass), the refracted ray's origin and direction (for _fixup).
(_UX, _UY, _ROZ, _GMX, _GMY, _GM, _TOX, _TOY, _TOZ, _TDX, _TDY, _TDZ) = range(26, 38)
_NF = 38
# As pmdsim.simulation.trace._trace_run: nothing is allocated (no reference counting), and
# fastmath only fuses a·b + c into FMAs (no assumptions about NaN or infinity).
_JIT = dict(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})

# int64 scratch (``_NI`` fields of ``_BLK``): the patch offset per pixel, and the patch's row index
# while counting.
_PID = 0
_PIY = 1
_NI = 2
#: Grids with at most this many intervals (n_x − 1 + n_y − 1) find each pixel's patch by
#: counting the grid lines below it (vectorised); larger ones by bisection (scalar).
_SMALL_GRID = 16


@numba.njit(**_JIT)
def _patches_small(n, gx, gy, S, P):
    """Patch offsets (:func:`pmdsim.geometry.surface._patch`) of the start points of n pixels,
    by counting grid lines: the same intervals as :func:`~pmdsim.geometry.surface._interval`
    (v ≤ g[1] → 0; g[m] ≤ v < g[m + 1] → m; v ≥ g[−2] → last), with one compare per grid
    line and pixel, without branches."""
    B = _BLK
    nx = gx.shape[0]
    ny = gy.shape[0]
    for i in range(n):
        z = S[_ZG * B + i]
        S[_X * B + i] = S[_AX * B + i] + S[_BX * B + i] * z
        S[_Y * B + i] = S[_AY * B + i] + S[_BY * B + i] * z
        P[_PID * B + i] = 0
        P[_PIY * B + i] = 0
    for m in range(1, nx - 1):
        g = gx[m]
        for i in range(n):
            P[_PID * B + i] += S[_X * B + i] >= g
    for m in range(1, ny - 1):
        g = gy[m]
        for i in range(n):
            P[_PIY * B + i] += S[_Y * B + i] >= g
    if nx > 2:  # v = g[1] exactly belongs to the first interval
        g = gx[1]
        for i in range(n):
            P[_PID * B + i] -= S[_X * B + i] == g
    if ny > 2:
        g = gy[1]
        for i in range(n):
            P[_PIY * B + i] -= S[_Y * B + i] == g
    nx1 = nx - 1
    for i in range(n):
        P[_PID * B + i] = (P[_PIY * B + i] * nx1 + P[_PID * B + i]) * 16

_FAILED = -1.0  # sample code of a pixel whose view ray is not defined (UNDISTORT_FAILED)
_NOT_TRACED = -1.0  # screen code of a pixel that did not reach the screen



@numba.njit(**_JIT, inline="always")
def patch_rows(c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12, c13, c14, c15, sx):
    """The bicubic patch h = Σ_a Σ_b c[4a + b]·s_y^a·s_x^b at s_x = ``sx``: its four polynomials in
    s_x, r_a = Σ_b c[4a + b]·s_x^b, and their derivatives ∂r_a/∂s_x (Horner's scheme; h, ∇h and the
    Hessian follow by Horner's scheme in s_y)."""
    r0 = c0 + sx * (c1 + sx * (c2 + sx * c3))
    r1 = c4 + sx * (c5 + sx * (c6 + sx * c7))
    r2 = c8 + sx * (c9 + sx * (c10 + sx * c11))
    r3 = c12 + sx * (c13 + sx * (c14 + sx * c15))
    e1d0 = c1 + sx * (2.0 * c2 + sx * 3.0 * c3)
    e1d1 = c5 + sx * (2.0 * c6 + sx * 3.0 * c7)
    e1d2 = c9 + sx * (2.0 * c10 + sx * 3.0 * c11)
    e1d3 = c13 + sx * (2.0 * c14 + sx * 3.0 * c15)
    return r0, r1, r2, r3, e1d0, e1d1, e1d2, e1d3


@numba.njit(**_JIT)
def _newton_run(n, c, gxi, gyj, m2c, m3c, tol, gradient, S):
    """One Newton step (:func:`pmdsim.geometry.surface._newton_step`) for the pixels 0 … n − 1
    of ``S`` (a view of the block's scratch from the run's first pixel on), which all evaluate
    on the same bicubic patch (coefficients ``c[0:16]``, origin (gxi, gyj)).

    Reads the ray x = a_x + b_x z, y = a_y + b_y z (fields _AX, _AY, _BX, _BY) and the start
    height (_ZG); writes the new height (_Z), point (_X, _Y), with ``gradient`` the gradient
    carried to it (_HX, _HY), and 1.0 where the step has converged by the error bounds of
    :func:`~pmdsim.geometry.surface._newton_step` (_CONV). ``m2c``, ``m3c``: the surface's
    derivative bounds D₂, D₃ (:attr:`~pmdsim.geometry.surface.KernelSurface.dmax`). The same
    operations in the same order as the scalar kernel.
    """
    c0, c1, c2, c3, c4, c5, c6, c7 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
    c8, c9, c10, c11, c12, c13, c14, c15 = c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15]
    B = _BLK
    for i in range(n):  # from 0: LLVM then knows the indices are not negative (and vectorises)
        ax = S[_AX * B + i]
        ay = S[_AY * B + i]
        bx = S[_BX * B + i]
        by = S[_BY * B + i]
        z = S[_ZG * B + i]
        w2 = (abs(bx) + abs(by)) ** 2
        m2 = m2c * w2
        sx = (ax + bx * z) - gxi
        sy = (ay + by * z) - gyj
        r0, r1, r2, r3, d0, d1, d2, d3 = patch_rows(c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12, c13,
                                                    c14, c15, sx)
        h = r0 + sy * (r1 + sy * (r2 + sy * r3))
        hx = d0 + sy * (d1 + sy * (d2 + sy * d3))
        hy = r1 + sy * (2.0 * r2 + sy * 3.0 * r3)
        hz = hx * bx + hy * by
        fp = 1.0 - hz
        step = (h - z) / fp
        zn = z + step
        sa = abs(step)
        conv = (abs(hz) < 1.0) & (m2 * sa * sa <= tol * fp)
        if gradient:
            m3 = m3c * w2
            e0 = 2.0 * c2 + 6.0 * sx * c3
            e1 = 2.0 * c6 + 6.0 * sx * c7
            e2 = 2.0 * c10 + 6.0 * sx * c11
            e3 = 2.0 * c14 + 6.0 * sx * c15
            hxx = e0 + sy * (e1 + sy * (e2 + sy * e3))
            hxy = d1 + sy * (2.0 * d2 + sy * 3.0 * d3)
            hyy = 2.0 * r2 + 6.0 * sy * r3
            conv = conv & (m3 * sa * sa <= tol)
            S[_HX * B + i] = hx + (hxx * bx + hxy * by) * step
            S[_HY * B + i] = hy + (hxy * bx + hyy * by) * step
        S[_Z * B + i] = zn
        S[_X * B + i] = ax + bx * zn
        S[_Y * B + i] = ay + by * zn
        S[_CONV * B + i] = 1.0 if conv else 0.0


@numba.njit(**_JIT)
def _intersect_block(n, kind, gx, gy, coef, dmax, tol, gradient, S, P):
    """Intersection stage for the n pixels of the block whose code (_C) is 0 (to be traced).

    On return _C holds the :class:`~pmdsim.geometry.surface.IntersectStatus` code, or
    ``_NEEDS_SOLVE`` where the scalar kernels must take over (no finite warm start, a Newton
    step not converged, a surface kind other than plane and spline); _X, _Y, _Z (and with
    ``gradient`` _HX, _HY) hold the intersection of the settled pixels. The checks of
    :func:`~pmdsim.geometry.surface._finish`: ray parameter t = (z − o_z)/d_z > 0 (o_z in
    _QOZ, 1/d_z in _INV), point within the grid's bounds.
    """
    B = _BLK
    x_lo = gx[0]
    x_hi = gx[gx.shape[0] - 1]
    y_lo = gy[0]
    y_hi = gy[gy.shape[0] - 1]
    if kind == _KIND_PLANE:
        for i in range(n):
            S[_X * B + i] = S[_AX * B + i]
            S[_Y * B + i] = S[_AY * B + i]
            S[_Z * B + i] = 0.0
            S[_CONV * B + i] = 1.0
            S[_HX * B + i] = 0.0
            S[_HY * B + i] = 0.0
    elif kind == _KIND_SPLINE:
        nx1 = gx.shape[0] - 1
        ny1 = gy.shape[0] - 1
        if nx1 + ny1 <= _SMALL_GRID:
            _patches_small(n, gx, gy, S, P)
        else:
            for i in range(n):
                z = S[_ZG * B + i]
                x = S[_AX * B + i] + S[_BX * B + i] * z
                y = S[_AY * B + i] + S[_BY * B + i] * z
                P[_PID * B + i] = (_interval(gy, y) * nx1 + _interval(gx, x)) * 16
        # Runs of pixels on the same patch (usually one per block).
        b0 = P[_PID * B]
        n_other = 0
        for i in range(n):
            n_other += P[_PID * B + i] != b0
        i = 0
        while i < n:
            s = i
            b = P[_PID * B + i]
            i += 1
            if n_other == 0:
                i = n
            while i < n and P[_PID * B + i] == b:
                i += 1
            bi = b // 16
            gxi = gx[bi % nx1]
            gyj = gy[bi // nx1]
            _newton_run(i - s, coef[b:b + 16], gxi, gyj, dmax[0], dmax[1], tol, gradient, S[s:])
    else:
        for i in range(n):
            if S[_C * B + i] == 0.0:
                S[_C * B + i] = _NEEDS_SOLVE
        return
    for i in range(n):
        c = S[_C * B + i]
        # With a finite view ray only (intersect_kernel: d_z = 0 or not finite -> PARALLEL).
        inv = S[_INV * B + i]
        z = S[_Z * B + i]
        x = S[_X * B + i]
        y = S[_Y * B + i]
        t = (z - S[_QOZ * B + i]) * inv
        outside = (x < x_lo) | (x > x_hi) | (y < y_lo) | (y > y_hi)
        code = 1.0 if not t > 0.0 else (2.0 if outside else 0.0)
        code = code if S[_CONV * B + i] != 0.0 else float(_NEEDS_SOLVE)
        S[_C * B + i] = c if c != 0.0 else code


@numba.njit(**_JIT)
def intersect_ray(kind, gx, gy, coef, z_min, z_max, dmax, ox, oy, oz, dx, dy, dz, tol, max_iter, z_start, gradient):
    """One ray's intersection as the pixel-by-pixel tracer computes it: ``intersect_kernel``
    from the warm start ``z_start``, then ``intersect_solve`` from its result where the fast
    path did not settle the pixel. Returns ``(t, x, y, z, h_x, h_y, status)``.

    A function of its own, called (not inlined by numba) from the tracer's pixel loop
    (:func:`pmdsim.simulation.trace._trace_run`, sample and screen) and from :func:`_fixup`,
    with ``gradient`` a run-time value (``np.bool_``): numba types and lowers the scalar
    intersection kernels once instead of at three inlined call sites, each with every surface
    kind's closed form (docs/benchmarks.md, "First run: the tracer's compile cut"). The
    arithmetic is that of the inlined code, with the same fastmath flags (FMA contraction).
    """
    t, x, y, z, hx, hy, st = intersect_kernel(kind, gx, gy, coef, dmax, ox, oy, oz, dx, dy, dz, tol, z_start,
                                              gradient)
    if st == _NEEDS_SOLVE:
        t, x, y, z, hx, hy, st = intersect_solve(kind, gx, gy, coef, z_min, z_max, dmax, ox, oy, oz, dx, dy, dz, tol,
                                                 max_iter, z)
    return t, x, y, z, hx, hy, st


@numba.njit(**_JIT)
def _fixup(n, kind, gx, gy, coef, z_min, z_max, dmax, tol, max_iter, gradient, fo, fd, S):
    """The scalar kernels for the pixels the vectorised stage left (_C == _NEEDS_SOLVE):
    ``intersect_kernel`` from the warm start (_ZG), then ``intersect_solve`` from its result
    (the sequence of the pixel-by-pixel tracer, :func:`intersect_ray`). The ray: origin in the
    fields fo, fo + 1, fo + 2 (_QOX; with a cover glass the refracted ray's, _TOX), direction in
    fd, fd + 1, fd + 2 (_VX: view ray, _WX: reflected ray, _TDX: refracted ray)."""
    B = _BLK
    for i in range(n):
        if S[_C * B + i] == _NEEDS_SOLVE:
            t, x, y, z, hx, hy, st = intersect_ray(kind, gx, gy, coef, z_min, z_max, dmax, S[fo * B + i],
                                                   S[(fo + 1) * B + i], S[(fo + 2) * B + i], S[fd * B + i],
                                                   S[(fd + 1) * B + i], S[(fd + 2) * B + i], tol, max_iter,
                                                   S[_ZG * B + i], gradient)
            S[_X * B + i] = x
            S[_Y * B + i] = y
            S[_Z * B + i] = z
            S[_HX * B + i] = hx
            S[_HY * B + i] = hy
            S[_C * B + i] = st


@numba.njit(**_JIT, inline="always")
def _to_screen(i, sc, vx, vy, vz, px, py, pz, hx, hy, cos2_max, bm, zq1, zq2, S):
    """Grazing-incidence test, reflection (eq. 17) and the reflected ray in the screen frame
    (origin _QOX…, direction _WX…, parametrised by height in _AX … _INV, warm start _ZG from the
    rows above, code _C) for pixel i; writes its sample code (_SC) and point (_PX, _PY, _PZ).
    ``bm``: the screen ← sample rotation (row major) and translation."""
    B = _BLK
    b00, b01, b02, b10, b11, b12, b20, b21, b22, c0, c1, c2 = bm
    # Grazing or back-side incidence: |v·n| ≤ cos(MAX_INCIDENCE_DEG)·|v||n|, n = (−h_x, −h_y, 1),
    # or v·n of the other sign than v_z (pmdsim.simulation.trace, the pixel-by-pixel loop).
    vn = vz - hx * vx - hy * vy
    grazing = not ((vn * vz > 0.0) & (vn * vn > cos2_max * (
        (vx * vx + vy * vy + vz * vz) * (hx * hx + hy * hy + 1.0))))
    if sc == 0.0 and grazing:
        sc = 5.0  # -> SAMPLE_GRAZING
    nx = -hx
    ny = -hy
    f = 2.0 * (vx * nx + vy * ny + vz) / (nx * nx + ny * ny + 1.0)
    rx = vx - f * nx
    ry = vy - f * ny
    rz = vz - f
    qox = b00 * px + b01 * py + b02 * pz + c0
    qoy = b10 * px + b11 * py + b12 * pz + c1
    qoz = b20 * px + b21 * py + b22 * pz + c2
    wx = b00 * rx + b01 * ry + b02 * rz
    wy = b10 * rx + b11 * ry + b12 * rz
    wz = b20 * rx + b21 * ry + b22 * rz
    g = 2.0 * zq1[i] - zq2[i]
    if not np.isfinite(g):
        g = zq1[i]
    inv = 1.0 / wz
    bx = wx * inv
    by = wy * inv
    S[_SC * B + i] = sc
    S[_PX * B + i] = px
    S[_PY * B + i] = py
    S[_PZ * B + i] = pz
    S[_QOX * B + i] = qox
    S[_QOY * B + i] = qoy
    S[_QOZ * B + i] = qoz
    S[_WX * B + i] = wx
    S[_WY * B + i] = wy
    S[_WZ * B + i] = wz
    S[_AX * B + i] = qox - qoz * bx
    S[_AY * B + i] = qoy - qoz * by
    S[_BX * B + i] = bx
    S[_BY * B + i] = by
    S[_INV * B + i] = inv
    S[_ZG * B + i] = g
    code = 1.0 if (wz == 0.0) | (not np.isfinite(wz)) else 0.0  # PARALLEL
    S[_C * B + i] = code if sc == 0.0 else _NOT_TRACED


@numba.njit(**_JIT)
def trace_row(
    kb, m, d_cam, ok, zr, S, P, r_sc, t_sc, r_ps, t_ps, cos2_max,
    s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
    p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
    tol, max_iter, sample_codes, screen_codes,
    screen_xy, status, p_sample, q_screen, store, glass_t, glass_n, with_glass, slot,
):
    """Trace the m pixels kb … kb + m − 1 of one image row, warm started from the rows above.

    The arguments are those of :func:`pmdsim.simulation.trace._trace_run`; ``zr`` (4, m), or
    (14, m) with a cover glass: the sample and screen heights of the two rows above (updated
    here for the next row), then the glass's warm starts in two slots each
    (:func:`.glass_rows.glass_block`, :func:`_glass_rows_update`);
    ``S`` and ``P``: the band's float64 (_NF·_BLK) and int64 (_NI·_BLK) scratch; ``cos2_max``:
    the squared cosine of the largest angle of incidence on the sample; ``glass_t``,
    ``glass_n``: the cover glass's thickness (0: none) and index — with a glass, stage 4 is
    :func:`.glass_rows.glass_block` (the screen point is the emitting-surface point seen
    through the glass); ``with_glass``: a boolean literal, ``False`` in the glass-free tracer,
    which then does not compile the glass stage (:mod:`.glass_switch`); ``slot``: the slot (0, 1)
    of the glass's rows in ``zr`` that this row writes (:func:`_glass_rows_update`: the row's
    index in its band modulo 2).
    """
    B = _BLK
    nan = np.nan
    ox = t_sc[0]
    oy = t_sc[1]
    oz = t_sc[2]
    a00, a01, a02 = r_sc[0, 0], r_sc[0, 1], r_sc[0, 2]
    a10, a11, a12 = r_sc[1, 0], r_sc[1, 1], r_sc[1, 2]
    a20, a21, a22 = r_sc[2, 0], r_sc[2, 1], r_sc[2, 2]
    bm = (r_ps[0, 0], r_ps[0, 1], r_ps[0, 2], r_ps[1, 0], r_ps[1, 1], r_ps[1, 2], r_ps[2, 0], r_ps[2, 1], r_ps[2, 2],
          t_ps[0], t_ps[1], t_ps[2])
    sx_lo = s_gx[0]
    sx_hi = s_gx[s_gx.shape[0] - 1]
    sy_lo = s_gy[0]
    sy_hi = s_gy[s_gy.shape[0] - 1]
    for col0 in range(0, m, B):
        n = min(B, m - col0)
        kc = kb + np.uint64(col0)
        # The heights of the two rows above from this block's first pixel on (1-D views: unit
        # strides and indices from 0, which LLVM vectorises).
        zs1 = zr[0][col0:]
        zs2 = zr[1][col0:]
        zq1 = zr[2][col0:]
        zq2 = zr[3][col0:]
        if s_kind == _KIND_PLANE:
            # 1.–2. The view ray and its intersection with the plane z = 0 (eqs. 9–12): the
            # operations of intersect_kernel's plane path, one loop.
            for i in range(n):
                k = kc + np.uint64(i)
                a = d_cam[k, 0]
                b = d_cam[k, 1]
                c = d_cam[k, 2]
                vx = a00 * a + a01 * b + a02 * c
                vy = a10 * a + a11 * b + a12 * c
                vz = a20 * a + a21 * b + a22 * c
                inv = 1.0 / vz
                x = ox - oz * (vx * inv)
                y = oy - oz * (vy * inv)
                t = (0.0 - oz) * inv
                outside = (x < sx_lo) | (x > sx_hi) | (y < sy_lo) | (y > sy_hi)
                code = 1.0 if not t > 0.0 else (2.0 if outside else 0.0)
                if (vz == 0.0) | (not np.isfinite(vz)):
                    code = 1.0  # PARALLEL
                if not ok[k]:
                    code = _FAILED
                S[_VX * B + i] = vx
                S[_VY * B + i] = vy
                S[_VZ * B + i] = vz
                S[_X * B + i] = x
                S[_Y * B + i] = y
                S[_Z * B + i] = 0.0
                S[_HX * B + i] = 0.0
                S[_HY * B + i] = 0.0
                S[_C * B + i] = code
        else:
            # 1. The view ray in the sample frame, as a function of the height (eqs. 14-16).
            for i in range(n):
                k = kc + np.uint64(i)
                a = d_cam[k, 0]
                b = d_cam[k, 1]
                c = d_cam[k, 2]
                vx = a00 * a + a01 * b + a02 * c
                vy = a10 * a + a11 * b + a12 * c
                vz = a20 * a + a21 * b + a22 * c
                g = 2.0 * zs1[i] - zs2[i]
                if not np.isfinite(g):
                    g = zs1[i]
                inv = 1.0 / vz
                bx = vx * inv
                by = vy * inv
                S[_VX * B + i] = vx
                S[_VY * B + i] = vy
                S[_VZ * B + i] = vz
                S[_QOX * B + i] = ox
                S[_QOY * B + i] = oy
                S[_QOZ * B + i] = oz
                S[_AX * B + i] = ox - oz * bx
                S[_AY * B + i] = oy - oz * by
                S[_BX * B + i] = bx
                S[_BY * B + i] = by
                S[_INV * B + i] = inv
                S[_ZG * B + i] = g
                code = 0.0
                if (vz == 0.0) | (not np.isfinite(vz)):
                    code = 1.0  # PARALLEL
                if not ok[k]:
                    code = _FAILED
                S[_C * B + i] = code
            # 2. The sample intersection.
            _intersect_block(n, s_kind, s_gx, s_gy, s_coef, s_dmax, tol, True, S, P)
            # np.bool_/np.int64: run-time values, not literals, so that numba compiles _fixup once
            # for both calls (a literal specialisation each cost 10–20 s of a cold start).
            _fixup(n, s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax, tol, max_iter, np.bool_(True),
                   np.int64(_QOX), np.int64(_VX), S)
        # 3. Grazing incidence, reflection (eq. 17), the reflected ray in the screen frame.
        for i in range(n):
            _to_screen(i, S[_C * B + i], S[_VX * B + i], S[_VY * B + i], S[_VZ * B + i], S[_X * B + i],
                       S[_Y * B + i], S[_Z * B + i], S[_HX * B + i], S[_HY * B + i], cos2_max, bm, zq1, zq2, S)
        # 4. The screen intersection (through the cover glass, if any).
        if glass_t > 0.0:
            _glass_switch.glass_block_if(with_glass, n, p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax, tol,
                                         max_iter, glass_t, glass_n, zr, col0, slot, S, P)
        else:
            _intersect_block(n, p_kind, p_gx, p_gy, p_coef, p_dmax, tol, False, S, P)
            _fixup(n, p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax, tol, max_iter, np.bool_(False),
                   np.int64(_QOX), np.int64(_WX), S)
        # 5. Status codes and stores (three loops: each vectorises with few alias checks).
        for i in range(n):
            k = kc + np.uint64(i)
            sc = S[_SC * B + i]
            qc = S[_C * B + i]
            valid = (sc == 0.0) & (qc == 0.0)
            st = screen_codes[int(qc)] if sc == 0.0 else (sample_codes[int(sc)] if sc != _FAILED else 1)
            status[k] = st
            screen_xy[k, 0] = S[_X * B + i] if valid else nan
            screen_xy[k, 1] = S[_Y * B + i] if valid else nan
        for i in range(n):
            sc = S[_SC * B + i]
            qc = S[_C * B + i]
            zs2[i] = zs1[i]  # row - 1 becomes row - 2
            zs1[i] = S[_PZ * B + i] if sc == 0.0 else nan
            zq2[i] = zq1[i]
            zq1[i] = S[_Z * B + i] if (sc == 0.0) & (qc == 0.0) else nan
        if glass_t > 0.0:
            _glass_rows_update(n, zr, col0, slot, S)
        if store:
            for i in range(n):
                k = kc + np.uint64(i)
                sc = S[_SC * B + i]
                qc = S[_C * B + i]
                hit = sc == 0.0
                valid = hit & (qc == 0.0)
                p_sample[k, 0] = S[_PX * B + i] if hit else nan
                p_sample[k, 1] = S[_PY * B + i] if hit else nan
                p_sample[k, 2] = S[_PZ * B + i] if hit else nan
                q_screen[k, 0] = S[_X * B + i] if valid else nan
                q_screen[k, 1] = S[_Y * B + i] if valid else nan
                q_screen[k, 2] = S[_Z * B + i] if valid else nan


@numba.njit(**_JIT)
def _glass_rows_update(n, zr, col0, slot, S):
    """The glass's warm starts for the rows below: this row's A_z, m_x, m_y (fields _QOZ, _GMX,
    _GMY; NaN where the pixel is not valid) into slot ``slot`` of ``zr[4:10]`` (from column
    ``col0`` on).

    Each value has two rows, ``zr[4 + 2·f + slot]`` (f = 0, 1, 2: A_z, m_x, m_y), written by the
    rows of a band alternately: the other slot holds row − 1, this one held row − 2, which this
    row's values replace — no copy of row − 1 into row − 2 (which, with the row of each value
    written in one loop, took 2.9 ms of Table 1's trace with a glass: docs/benchmarks.md
    "Cover glass (issue 21): the glass's rows as a ring"). One loop per row: a loop storing into
    several rows is not vectorised."""
    B = _BLK
    nan = np.nan
    for f in range(3):
        r = zr[4 + 2 * f + slot][col0:]
        fs = _QOZ if f == 0 else _GMX + f - 1
        for i in range(n):
            valid = (S[_SC * B + i] == 0.0) & (S[_C * B + i] == 0.0)
            r[i] = S[fs * B + i] if valid else nan


# (glass_rows uses this module's stages and scratch fields: imported last, as a module)
from . import glass_switch as _glass_switch  # noqa: E402
