"""Stepwise integration (paper §2.5): breadth-first wavefronts from a seed of known height, each
new pixel solved from all its reconstructed 4-neighbours by the trapezoidal rule with a
predictor–corrector iteration. Notation: :mod:`pmdsim.evaluation.reconstruction`.
"""

from __future__ import annotations

import numba
import numpy as np

from .integration import (
    Reconstruction,
    ReconstructionError,
    _bisector_slopes,
    _check_inputs,
    _check_seed,
    _points_and_normals,
)
from .prefetch import prefetch

__all__ = ["reconstruct_stepwise", "step_tolerance_mm", "STEP_TOL_MM", "STEP_TOL_ULPS", "STEP_MAX_ITER"]


#: Convergence tolerance of the corrector iteration of one integration step (|Δz|), in mm.
STEP_TOL_MM = 1e-12


#: The step tolerance is never below this many units in the last place (float64 spacing) of
#: the working distance (the largest coordinate of the camera centre and the screen points):
#: at a 10 m stand-off |Δz| cannot get below ~1e-12 mm, so STEP_TOL_MM alone never converges.
STEP_TOL_ULPS = 16


@numba.njit(cache=True, nogil=True)
def _max_abs_valid(q, valid):
    """max |q[v, u, c]| over the pixels of ``valid`` (H, W) of ``q`` (H, W, 3), NaN skipped
    (−1.0 if there is none), without the (n, 3) copy of ``q[valid]``."""
    H, W = valid.shape
    out = -1.0
    for v in range(H):
        for u in range(W):
            if valid[v, u]:
                for c in range(3):
                    a = abs(q[v, u, c])
                    if a > out:
                        out = a
    return out


def step_tolerance_mm(o, q, valid) -> float:
    """max(:data:`STEP_TOL_MM`, :data:`STEP_TOL_ULPS` · ulp(working distance)), mm: the
    convergence tolerance of one step, relative to what float64 resolves at the coordinates
    involved (the camera centre ``o`` (3,), the valid screen points of ``q`` (H, W, 3))."""
    scale = float(np.max(np.abs(o)))
    qmax = float(_max_abs_valid(np.ascontiguousarray(q, dtype=np.float64), np.ascontiguousarray(valid, dtype=bool)))
    scale = max(scale, qmax)  # (the valid q are finite: _check_inputs)
    return max(STEP_TOL_MM, STEP_TOL_ULPS * float(np.spacing(scale)))


#: Maximum number of corrector iterations of one integration step.
STEP_MAX_ITER = 50


# Neighbour offsets in the order in which the stepwise integration visits them.
_NB_DV = np.array([-1, 1, 0, 0], dtype=np.int64)


_NB_DU = np.array([0, 0, -1, 1], dtype=np.int64)


#: Pixels ahead whose inputs the wavefront gather prefetches (:mod:`pmdsim.evaluation.prefetch`).
_PREFETCH_AHEAD = 8


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gather_wavefront(d, q, state, nxt, n, nb_dv, nb_du, own, nb, m):
    """The inputs of the wavefront ``nxt[:n]``'s steps, as contiguous rows (index i: the
    wavefront's pixel): ``own`` (6, ≥ n) its view ray d and screen point q; ``nb`` (4, 5, ≥ n) per
    slot j < m[i] the j-th reconstructed 4-neighbour a (flag 1 in ``state``, in the order of
    ``nb_dv``, ``nb_du``): t_a·d_a (x, y, z) and g_a (x, y); slots j ≥ m[i] hold zeros."""
    H = state.shape[0]
    W = state.shape[1]
    for i in range(n):
        if i + _PREFETCH_AHEAD < n:  # the inputs of a pixel ahead: its rows and the rows above and below
            k = nxt[i + _PREFETCH_AHEAD]
            prefetch(d, 3 * k)
            prefetch(q, 3 * k)
            prefetch(state, 4 * k)
            if k >= W:
                prefetch(d, 3 * (k - W))
                prefetch(state, 4 * (k - W))
            if k + W < H * W:
                prefetch(d, 3 * (k + W))
                prefetch(state, 4 * (k + W))
        idx = nxt[i]
        vb = idx // W
        ub = idx - vb * W
        _gather_own(d, q, vb, ub, own, i)
        j = 0
        for k in range(4):
            j = _gather_neighbour(d, state, vb + nb_dv[k], ub + nb_du[k], nb, j, i)
        _gather_end(nb, m, j, i)


@numba.njit(cache=True, nogil=True)
def _gather_own(d, q, vb, ub, own, i):
    """own[:, i] = pixel (vb, ub)'s view ray d and screen point q (:func:`_gather_wavefront`)."""
    for c in range(3):
        own[c, i] = d[vb, ub, c]
        own[3 + c, i] = q[vb, ub, c]


@numba.njit(cache=True, nogil=True)
def _gather_neighbour(d, state, va, ua, nb, j, i):
    """Slot j of pixel i (:func:`_gather_wavefront`) from pixel (va, ua) if it is in the image and
    reconstructed (flag 1): t_a·d_a and g_a. Returns the next free slot (j + 1, or j)."""
    H = state.shape[0]
    W = state.shape[1]
    if va < 0 or va >= H or ua < 0 or ua >= W:
        return j
    if state[va, ua, 3] != 1.0:
        return j
    _gather_slot(d, va, ua, state[va, ua, 0], state[va, ua, 1], state[va, ua, 2], nb, j, i)
    return j + 1


@numba.njit(cache=True, nogil=True)
def _gather_slot(d, va, ua, ta, gx, gy, nb, j, i):
    """Slot j of pixel i: t_a·d_a of the neighbour (va, ua) with ray parameter ta, and its slopes."""
    nb[j, 0, i] = ta * d[va, ua, 0]
    nb[j, 1, i] = ta * d[va, ua, 1]
    nb[j, 2, i] = ta * d[va, ua, 2]
    nb[j, 3, i] = gx
    nb[j, 4, i] = gy


@numba.njit(cache=True, nogil=True)
def _gather_end(nb, m, j, i):
    """m[i] = j neighbours gathered; the slots j … 3 of pixel i hold zeros."""
    m[i] = j
    for jj in range(j, 4):
        for c in range(5):
            nb[jj, c, i] = 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def _slot_terms(num, den, present, pred, rx, ry, rz, gx_a, gy_a, gx_b, gy_b, dx, dy, dz):
    """num, den plus one neighbour slot's terms (+0.0 for an absent slot)."""
    Gx = gx_a if pred else 0.5 * (gx_a + gx_b)
    Gy = gy_a if pred else 0.5 * (gy_a + gy_b)
    # (t_b d_z − r_a,z) − G·(t_b d_xy − r_a,xy) = 0 summed over the neighbours.
    tn = rz - (Gx * rx + Gy * ry)
    td = dz - (Gx * dx + Gy * dy)
    return num + (tn if present else 0.0), den + (td if present else 0.0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_wavefront(o, own, nb, m, n, tol, max_iter, res, status):
    """One integration step for every pixel of a gathered wavefront (:func:`_gather_wavefront`),
    all pixels in lock-step (per iteration one branch-free loop over the pixels computes their
    steps, reading 1-d rows and writing four, so that it vectorises: the divisions and square
    roots of neighbouring pixels overlap instead of forming one chain per pixel; a second loop
    keeps the steps of the pixels still iterating):

        Σ_i [z_b − z_ai − G_i·(xy_b − xy_ai)] = 0,  G_i = ½(g_ai + g_b) (trapezoidal rule),

    linear in t_b for fixed G_i; predictor G_i = g_ai, then correctors until |Δz| < ``tol``
    (at most ``max_iter``). Each pixel's arithmetic is that of solving it alone, in the same
    order (an absent neighbour slot adds +0.0, which changes at most the sign of a zero sum, and
    a zero sum fails the step either way; the previous height o_z + t_b·d_z is recomputed from
    the previous t_b, the same operations), and a pixel's values stop changing when it converges
    or fails. ``res`` (7, ≥ n): t_b, g_b,x, g_b,y of the last step, its |Δz| (inf if no
    corrector ran), and workspace; ``status`` (≥ n): the correctors used + 1 for a solved pixel
    (converged or not: the last iterate is kept), −1 for a failed one (the ray misses the plane
    in front of the camera or the normal is unusable)."""
    ox = o[0]
    oy = o[1]
    oz = o[2]
    t_b = res[0, :n]
    gbx = res[1, :n]
    gby = res[2, :n]
    change = res[3, :n]
    st = status[:n]
    d_x, d_y, d_z, q_x, q_y, q_z = own[0, :n], own[1, :n], own[2, :n], own[3, :n], own[4, :n], own[5, :n]
    r0x, r0y, r0z, g0x, g0y = nb[0, 0, :n], nb[0, 1, :n], nb[0, 2, :n], nb[0, 3, :n], nb[0, 4, :n]
    r1x, r1y, r1z, g1x, g1y = nb[1, 0, :n], nb[1, 1, :n], nb[1, 2, :n], nb[1, 3, :n], nb[1, 4, :n]
    r2x, r2y, r2z, g2x, g2y = nb[2, 0, :n], nb[2, 1, :n], nb[2, 2, :n], nb[2, 3, :n], nb[2, 4, :n]
    r3x, r3y, r3z, g3x, g3y = nb[3, 0, :n], nb[3, 1, :n], nb[3, 2, :n], nb[3, 3, :n], nb[3, 4, :n]
    mm = m[:n]
    for i in range(n):
        st[i] = 0
        change[i] = np.inf
        t_b[i] = 0.0
        gbx[i] = 0.0
        gby[i] = 0.0
    t_new = res[4, :n]
    gx_new = res[5, :n]
    gy_new = res[6, :n]
    for it in range(max_iter + 1):
        pred = it == 0
        for i in range(n):  # the step of every pixel (four rows written: this loop vectorises)
            dx = d_x[i]
            dy = d_y[i]
            dz = d_z[i]
            bx = gbx[i]
            by = gby[i]
            mi = mm[i]
            num, den = _slot_terms(0.0, 0.0, mi > 0, pred, r0x[i], r0y[i], r0z[i], g0x[i], g0y[i], bx, by, dx, dy, dz)
            num, den = _slot_terms(num, den, mi > 1, pred, r1x[i], r1y[i], r1z[i], g1x[i], g1y[i], bx, by, dx, dy, dz)
            num, den = _slot_terms(num, den, mi > 2, pred, r2x[i], r2y[i], r2z[i], g2x[i], g2y[i], bx, by, dx, dy, dz)
            num, den = _slot_terms(num, den, mi > 3, pred, r3x[i], r3y[i], r3z[i], g3x[i], g3y[i], bx, by, dx, dy, dz)
            tb = num / den
            gx, gy = _bisector_slopes(ox + tb * dx, oy + tb * dy, oz + tb * dz, ox, oy, oz, q_x[i], q_y[i], q_z[i])
            t_new[i] = tb
            gx_new[i] = gx
            gy_new[i] = gy
        n_active = 0
        for i in range(n):  # which pixels take the step, converge or fail
            tb = t_new[i]
            gx = gx_new[i]
            gy = gy_new[i]
            dz = d_z[i]
            s = st[i]
            t_old = t_b[i]
            active = s == 0
            bad = (not (tb > 0.0)) | (not np.isfinite(tb)) | (not np.isfinite(gx)) | (not np.isfinite(gy))
            step = active & (not bad)
            dzc = abs((oz + tb * dz) - (oz + t_old * dz))
            corr = step & (not pred)
            t_b[i] = tb if step else t_old
            gbx[i] = gx if step else gbx[i]
            gby[i] = gy if step else gby[i]
            change[i] = dzc if corr else change[i]
            s = -1 if (active & bad) else (it + 1 if (corr & (dzc < tol)) else s)
            st[i] = s
            n_active += 1 if s == 0 else 0
        if n_active == 0:
            break
    for i in range(n):
        if st[i] == 0:
            st[i] = max_iter + 1  # the last iterate is kept


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _expand_kernel(o, d, q, state, cur, n_cur, tol, max_iter, nb_dv, nb_du):
    """Layered (wavefront) stepwise integration from the reconstructed pixels ``cur[:n_cur]``.

    ``state`` (H, W, 4) holds per pixel [t, g_x, g_y, flag] with flag −1 = not valid,
    0 = valid and not yet reached, 2 = in the wavefront being solved, 1 = reconstructed
    (t: ray parameter of the point, g: slopes there). ``cur`` (H·W,) int64 lists the flat
    indices v·W + u of the wavefront to start from (flag 1, t and g set); it is used as
    workspace. The wavefront k + 1 is every valid, unreached 4-neighbour of wavefront k; each
    of its pixels is solved from *all* its reconstructed 4-neighbours at once (the pixels of
    one wavefront are never 4-adjacent when the start is a single pixel, as the pixel grid is
    bipartite; in general they are solved from the neighbours reconstructed before the
    wavefront, so the order within a wavefront does not matter): its inputs gathered into
    contiguous rows (:func:`_gather_wavefront`), then solved in lock-step
    (:func:`_solve_wavefront`). Returns (largest corrector count, largest final |Δz|, number of
    pixels that missed ``tol``)."""
    H = state.shape[0]
    W = state.shape[1]
    nxt = np.empty(H * W, dtype=np.int64)
    cap = 0
    own = np.empty((6, 0))
    nb = np.empty((4, 5, 0))
    m = np.empty(0, dtype=np.int64)
    res = np.empty((7, 0))
    status = np.empty(0, dtype=np.int64)
    max_used = 0
    max_change = 0.0
    n_unconverged = 0
    while n_cur > 0:
        # The next wavefront: valid, unreached neighbours of the current one.
        n_nxt = np.int64(0)  # not a literal 0: one signature of the wavefront kernels
        for i in range(n_cur):
            idx = cur[i]
            va = idx // W
            ua = idx - va * W
            for k in range(4):
                vb = va + nb_dv[k]
                ub = ua + nb_du[k]
                if vb < 0 or vb >= H or ub < 0 or ub >= W:
                    continue
                if state[vb, ub, 3] != 0.0:
                    continue
                state[vb, ub, 3] = 2.0
                nxt[n_nxt] = vb * W + ub
                n_nxt += 1
        if n_nxt > cap:  # wavefront buffers, grown as needed
            cap = max(n_nxt, 2 * cap)
            own = np.empty((6, cap))
            nb = np.empty((4, 5, cap))
            m = np.empty(cap, dtype=np.int64)
            res = np.empty((7, cap))
            status = np.empty(cap, dtype=np.int64)
        # Solve each pixel of the wavefront from all its reconstructed neighbours.
        _gather_wavefront(d, q, state, nxt, n_nxt, nb_dv, nb_du, own, nb, m)
        _solve_wavefront(o, own, nb, m, n_nxt, tol, max_iter, res, status)
        n_solved = 0
        for i in range(n_nxt):
            idx = nxt[i]
            vb = idx // W
            ub = idx - vb * W
            if status[i] < 0:
                state[vb, ub, 3] = 0.0  # may be reached again from a later wavefront
                continue
            change = res[3, i]
            used = status[i] - 1
            if change >= tol:
                n_unconverged += 1
            if used > max_used:
                max_used = used
            if change > max_change:
                max_change = change
            state[vb, ub, 0] = res[0, i]
            state[vb, ub, 1] = res[1, i]
            state[vb, ub, 2] = res[2, i]
            cur[n_solved] = idx  # reuse cur as the list of solved pixels of this wavefront
            n_solved += 1
        for i in range(n_solved):
            idx = cur[i]
            vb = idx // W
            ub = idx - vb * W
            state[vb, ub, 3] = 1.0
        n_cur = n_solved
    return max_used, max_change, n_unconverged


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _seed_values(o, d, q, sv, su, z0):
    """The seed (sv, su) at height z0: its ray parameter t and slopes g_x, g_y (NaN slopes if its
    normal is unusable)."""
    t = (z0 - o[2]) / d[sv, su, 2]
    px = o[0] + t * d[sv, su, 0]
    py = o[1] + t * d[sv, su, 1]
    gx, gy = _bisector_slopes(px, py, z0, o[0], o[1], o[2], q[sv, su, 0], q[sv, su, 1], q[sv, su, 2])
    return t, gx, gy


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _seed_state(o, d, q, state, sv, su, z0):
    """The seed (sv, su) at height z0 into ``state`` (t, slopes, flag 1). Returns False (nothing
    written) if its normal is unusable."""
    t, gx, gy = _seed_values(o, d, q, sv, su, z0)
    if not (np.isfinite(gx) and np.isfinite(gy)):
        return False
    state[sv, su, 0] = t
    state[sv, su, 1] = gx
    state[sv, su, 2] = gy
    state[sv, su, 3] = 1.0
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _stepwise_kernel(o, d, q, state, sv, su, z0, tol, max_iter, nb_dv, nb_du):
    """Stepwise integration from the seed (sv, su) at height z0: :func:`_expand_kernel` from
    the seed alone. Returns its statistics; the corrector count is −1 if the seed's normal is
    unusable."""
    H = state.shape[0]
    W = state.shape[1]
    if not _seed_state(o, d, q, state, sv, su, z0):
        return -1, 0.0, 0
    cur = np.empty(H * W, dtype=np.int64)
    cur[0] = sv * W + su
    # n_cur as int64, not the literal 1: one compiled signature with _fill_kernel's call
    return _expand_kernel(o, d, q, state, cur, np.int64(1), tol, max_iter, nb_dv, nb_du)


@numba.njit(cache=True, nogil=True)
def _init_state(valid, state):
    """state (H, W, 4) of :func:`_expand_kernel` before the integration: t, g NaN; flag 0 on
    ``valid``, −1 off it."""
    H, W = valid.shape
    for v in range(H):
        for u in range(W):
            state[v, u, 0] = np.nan
            state[v, u, 1] = np.nan
            state[v, u, 2] = np.nan
            state[v, u, 3] = 0.0 if valid[v, u] else -1.0


@numba.njit(cache=True, nogil=True)
def _heights(oz, d, state, z, done):
    """z (H, W) = o_z + t·d_z where the flag of ``state`` is 1 (reconstructed; ``done``), NaN
    elsewhere."""
    H, W = done.shape
    for v in range(H):
        for u in range(W):
            ok = state[v, u, 3] == 1.0
            done[v, u] = ok
            z[v, u] = oz + state[v, u, 0] * d[v, u, 2] if ok else np.nan


def _run_stepwise(o, d, q, valid, seed, z0, tol=STEP_TOL_MM):
    """Heights (H, W) (NaN where not reached) and the kernel's statistics."""
    H, W = valid.shape
    from .stepwise_rows import BAND_ROWS, rows_stepwise_kernel  # noqa: PLC0415 (it imports this module)

    valid = np.ascontiguousarray(valid, dtype=bool)
    d = np.ascontiguousarray(d, dtype=np.float64)
    z = np.empty((H, W))
    t0, gx0, gy0 = _seed_values(o, d, q, seed[0], seed[1], z0)
    code = -1
    if np.isfinite(gx0) and np.isfinite(gy0):  # first in bands of rows (the same bits), else in wavefronts
        max_used, max_change, n_unconv, code = rows_stepwise_kernel(
            o, d, q, valid, z, seed[0], seed[1], t0, gx0, gy0, tol, STEP_MAX_ITER, BAND_ROWS)
    if code == 0:
        done = valid.copy()
    else:
        state = np.empty((H, W, 4))
        _init_state(valid, state)
        max_used, max_change, n_unconv = _stepwise_kernel(
            o, d, q, state, seed[0], seed[1], z0, tol, STEP_MAX_ITER, _NB_DV, _NB_DU)
        if max_used < 0:
            raise ReconstructionError(
                f"the normal at seed_pixel {seed} is undefined or perpendicular to the height axis "
                f"(camera centre, seed point and q[{seed[0]}, {seed[1]}] = {q[seed].tolist()} are degenerate); "
                "choose another seed_pixel or check q")
        done = np.empty((H, W), dtype=bool)
        _heights(float(o[2]), d, state, z, done)
    z[seed] = z0
    return z, done, max_used, max_change, n_unconv


@numba.njit(cache=True, nogil=True, inline="always")
def _between(z0, z1, z2, z3):
    """Height of a pixel from the heights two apart along a row or column: z1, z2 on either
    side (z0 beyond z1, z3 beyond z2, at distance 3): linear interpolation, or linear
    extrapolation from one side if the other is unknown; NaN if neither works."""
    if np.isfinite(z1) and np.isfinite(z2):
        return 0.5 * (z1 + z2)
    if np.isfinite(z1) and np.isfinite(z0):
        return 1.5 * z1 - 0.5 * z0
    if np.isfinite(z2) and np.isfinite(z3):
        return 1.5 * z2 - 0.5 * z3
    return np.nan


@numba.njit(cache=True, nogil=True)
def _interpolate_coarse(S, z, a, b):
    """Heights z (H, W) known on some pixels (a + 2i, b + 2j) (NaN elsewhere): linear
    interpolation to the pixels of S between, first along the rows, at (a + 2i, b + 2j + 1),
    then along the columns, at (a + 2i + 1, ·) — bilinear between four known pixels —, with
    linear extrapolation from one side where the other side is unknown or outside the image
    (:func:`_between`). Returns the number of pixels of S that are still NaN."""
    H, W = S.shape
    ua = (b + 1) % 2  # first column between known ones (or before the first)
    for i in range((H - a + 1) // 2):
        v = a + 2 * i
        for u in range(ua, W, 2):
            if S[v, u]:
                z[v, u] = _between(z[v, u - 3] if u >= 3 else np.nan, z[v, u - 1] if u >= 1 else np.nan,
                                   z[v, u + 1] if u + 1 < W else np.nan,
                                   z[v, u + 3] if u + 3 < W else np.nan)
    va = (a + 1) % 2
    for i in range((H - va + 1) // 2):
        v = va + 2 * i
        for u in range(W):
            if S[v, u]:
                z[v, u] = _between(z[v - 3, u] if v >= 3 else np.nan, z[v - 1, u] if v >= 1 else np.nan,
                                   z[v + 1, u] if v + 1 < H else np.nan,
                                   z[v + 3, u] if v + 3 < H else np.nan)
    n_left = 0
    for v in range(H):
        for u in range(W):
            if S[v, u] and np.isnan(z[v, u]):
                n_left += 1
    return n_left


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _fill_kernel(o, d, q, S, z, tol, max_iter, nb_dv, nb_du):
    """Complete the heights z (H, W) on the pixels of S by stepwise integration
    (:func:`_expand_kernel`) from all pixels of S whose height is finite. Filled heights are
    written to z; pixels that cannot be reached stay NaN. Returns the number of pixels that
    are still NaN.

    Only the known pixels with an unknown 4-neighbour in S (the frontier) are ever used, so
    only their slopes are computed; a known pixel whose normal is unusable becomes unknown
    (and is solved again from its neighbours). The wavefronts start from the frontier in
    row-major order."""
    H, W = S.shape
    ox = o[0]
    oy = o[1]
    oz = o[2]
    state = np.empty((H, W, 4))
    for v in numba.prange(0, H):
        for u in range(W):
            state[v, u, 1] = np.nan  # slopes not computed
            if not S[v, u]:
                state[v, u, 3] = -1.0
            elif np.isfinite(z[v, u]):
                state[v, u, 3] = 1.0
            else:
                state[v, u, 3] = 0.0
    n_invalidated = 1
    while n_invalidated > 0:  # until no known pixel next to an unknown one is unusable
        n_invalidated = 0
        for v in numba.prange(0, H):
            for u in range(W):
                if state[v, u, 3] != 1.0 or np.isfinite(state[v, u, 1]):
                    continue
                frontier = False
                for k in range(4):
                    va = v + nb_dv[k]
                    ua = u + nb_du[k]
                    if 0 <= va < H and 0 <= ua < W and state[va, ua, 3] == 0.0:
                        frontier = True
                if not frontier:
                    continue
                zz = z[v, u]
                t = (zz - oz) / d[v, u, 2]
                gx, gy = _bisector_slopes(ox + t * d[v, u, 0], oy + t * d[v, u, 1], zz, ox, oy, oz,
                                          q[v, u, 0], q[v, u, 1], q[v, u, 2])
                if np.isfinite(gx) and np.isfinite(gy) and t > 0.0:
                    state[v, u, 0] = t
                    state[v, u, 1] = gx
                    state[v, u, 2] = gy
                else:
                    z[v, u] = np.nan
                    state[v, u, 3] = 0.0
                    n_invalidated += 1
    cur = np.empty(H * W, dtype=np.int64)
    n_cur = np.int64(0)  # not the literal 0: typing would compile _expand_kernel for Literal[int](0) too
    for v in range(H):
        for u in range(W):
            if state[v, u, 3] == 1.0 and np.isfinite(state[v, u, 1]):
                cur[n_cur] = v * W + u
                n_cur += 1
    if n_cur > 0:
        _expand_kernel(o, d, q, state, cur, n_cur, tol, max_iter, nb_dv, nb_du)
    n_missing = 0
    for v in range(H):
        for u in range(W):
            if S[v, u] and not np.isfinite(z[v, u]):
                if state[v, u, 3] == 1.0:
                    z[v, u] = oz + state[v, u, 0] * d[v, u, 2]
                else:
                    n_missing += 1
    return n_missing


def reconstruct_stepwise(o, d, q, valid, seed_pixel=None, seed_height_mm=0.0) -> Reconstruction:
    """Stepwise integration of the surface from an initial point (paper §2.5).

    Starting from the seed pixel, whose height is given, the reconstruction expands over valid
    4-connected neighbours, driven by the normals at the border of the current reconstruction.

    **Expansion order.** In wavefronts from the seed: wavefront k + 1 is every valid,
    not yet reconstructed 4-neighbour of wavefront k (so wavefront k holds the pixels at
    4-connected distance k from the seed). Each pixel of a wavefront is solved from *all* its
    reconstructed 4-neighbours together (one or two for a full grid: those of the previous
    wavefront), so the result does not depend on the order in which neighbours are visited,
    and where the measured slope field is not exactly a gradient (a wrong screen model, noise)
    the errors of the different paths are averaged instead of following one arbitrary path.
    A pixel whose step fails (see below) stays unreconstructed in its wavefront and may be
    reached again from a later one. Where every valid pixel has a valid neighbour one step closer
    to the seed in the L1 distance (wavefront k is then the pixels at L1 distance k) the same
    steps run in bands of image rows instead (:mod:`pmdsim.evaluation.stepwise_rows`: the same
    bits, contiguous reads), handing over to the wavefronts if a step fails.

    **One step.** The height of b solves the trapezoidal rule for its reconstructed
    neighbours a_i, summed:

        Σ_i [ z_b − z_ai − ½ (g_ai + g_b) · (xy_b − xy_ai) ] = 0

    with p_b = o + t_b·d_b on b's view ray and g = (−n_x/n_z, −n_y/n_z) the slopes of the
    bisector normal (see :func:`normals_from_registration`). For fixed mean slopes G_i the
    equation is linear in t_b (for one neighbour: p_b is the intersection of b's ray with the
    plane through p_a of slope G). The predictor uses G_i = g_ai; each corrector recomputes g_b
    at the new p_b and uses G_i = ½(g_ai + g_b), until the height changes by less than
    :func:`step_tolerance_mm` (:data:`STEP_TOL_MM`, or a few float64 ulps of the working
    distance where those are larger; at most :data:`STEP_MAX_ITER` correctors; the last iterate is kept
    either way). The rule is exact for height functions of degree ≤ 2 (planes, paraboloids).
    A step that fails (the ray misses the plane in front of the camera, or the normal is
    undefined or perpendicular to z) is skipped and b may be reached from a later wavefront.

    Parameters
    ----------
    o : array_like, shape (3,)
        Camera projection centre in the reconstruction frame, mm.
    d : array_like, shape (H, W, 3)
        View-ray direction per pixel (any non-zero length), reconstruction frame.
        Valid pixels need d_z ≠ 0.
    q : array_like, shape (H, W, 3)
        Screen point per pixel from the deflectometric registration, reconstruction frame, mm.
    valid : array_like of bool, shape (H, W)
        Pixels that may be reconstructed.
    seed_pixel : tuple of int, optional
        (row, column) of the initial point. Default: the valid pixel nearest (Euclidean, in
        pixels) to the centroid of ``valid``; ties go to the first in row-major order.
    seed_height_mm : float
        Height z of the initial point, mm (the integration constant).

    Returns
    -------
    Reconstruction
        Pixels not 4-connected to the seed through valid pixels stay NaN / not reconstructed.

    Raises
    ------
    ReconstructionError
        Shape mismatches, no valid pixels, a seed pixel out of range or invalid, a seed height
        behind the camera, or valid rays with d_z = 0.
    """
    o, d, q, valid = _check_inputs(o, d, q, valid)
    seed, z0 = _check_seed(seed_pixel, seed_height_mm, o, d, valid)
    z, done, max_used, max_change, n_unconv = _run_stepwise(o, d, q, valid, seed, z0,
                                                            tol=step_tolerance_mm(o, q, valid))
    points, normals = _points_and_normals(o, d, q, z)
    return Reconstruction(
        height_mm=z,
        p_sample_mm=points,
        n_sample=normals,
        reconstructed=done,
        method="stepwise",
        iterations=int(max_used),
        converged=bool(n_unconv == 0),
        seed_pixel=seed,
        final_change_mm=float(max_change),
    )
