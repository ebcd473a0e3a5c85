"""Zonal (Southwell-type) least-squares integration of the deflectometric slopes (paper §2.5):
Gauss–Newton iterations over all valid neighbour pairs of the seed's component, each a sparse
solve by multigrid-preconditioned CG (:mod:`pmdsim.evaluation.multigrid`; on large full frames
DCT-preconditioned, :mod:`pmdsim.evaluation.poisson`), started coarse to fine from a stepwise
solution. Notation: :mod:`pmdsim.evaluation.reconstruction`.
"""

from __future__ import annotations

import numba
import numpy as np

from .integration import (
    Reconstruction,
    ReconstructionError,
    _check_inputs,
    _check_seed,
    _points_and_normals,
)
from . import poisson
from .multigrid import _CGWork, _pcg
from .stepwise import STEP_MAX_ITER, _NB_DU, _NB_DV, _fill_kernel, _interpolate_coarse, _run_stepwise

__all__ = ["reconstruct_least_squares"]


#: Relative tolerance (max-norm of the preconditioned residual) of one inner solve.
_INNER_RTOL = 1e-4


_INNER_MAX_ITER = 200


#: Each Gauss–Newton update is solved at least to this fraction of the convergence tolerance.
_INNER_CAP = 0.1


#: The least-squares integration starts coarse to fine (see :func:`_start_heights`) when the
#: seed's component has at least this many pixels; smaller problems start stepwise.
_COARSE_START_MIN_PIXELS = 50_000


#: Convergence tolerance of the Gauss–Newton iteration on the coarse levels of the start, mm.
#: The start need not be more accurate than the coarse and fine solutions agree (about 1e-4 mm
#: for the full-frame benchmark); after an update of at most this size the coarse heights are
#: already far closer to the coarse solution than that (the remaining error is of second
#: order in the update plus the inner solve's error, ≤ 1e-5 mm), so a typical coarse level
#: stops after one iteration. The final convergence test is the one on the full grid.
_COARSE_TOL_MM = 1e-3


#: The updates on the coarse levels of the start are solved to this fraction of
#: :data:`_COARSE_TOL_MM` (3e-5 mm; see :func:`_gauss_newton`): well below the coarse–fine
#: discrepancy that sets the start's error (≈ 1.1e-4 mm on Table 1). 0.01 took one more CG
#: iteration per level for a start only 6 % closer, which saved nothing on the full grid
#: (docs/benchmarks.md, "Full-grid iterations (start25h)").
_COARSE_ATOL_FRAC = 0.03


#: The first full-grid update after the coarse-to-fine start is solved only to this fraction of
#: the convergence tolerance (the later ones to :data:`_INNER_CAP`): it is ≈ 1e-4 mm, far above
#: the tolerance, so it never decides convergence, and the update that follows — solved to
#: ``tol``/10 — removes its error along with the second-order remainder (see
#: :func:`_gauss_newton`). Table 1: 6 instead of 7 CG iterations, the same checking update.
_FIRST_UPDATE_FRAC = 0.2


#: Row blocks of :func:`_assemble_gauss_newton` (a constant, so that the result does not
#: depend on the number of threads).
_ASSEMBLY_BLOCKS = 16


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _unit(x, y, z):
    """(x, y, z)/|(x, y, z)| and 1/|(x, y, z)|."""
    i = 1.0 / np.sqrt(x * x + y * y + z * z)
    return x * i, y * i, z * i, i


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _point_geometry(ox, oy, oz, ex, ey, pz, qx, qy, qz):
    """(x, y, g_x, g_y, dg_x/dz, dg_y/dz) of the point at height pz on the view ray through o
    with dp/dz = (ex, ey, 1), seeing the screen point q: its x, y, the slopes g of the
    bisector normal there and their derivative along the view ray."""
    w = pz - oz
    px = ox + w * ex
    py = oy + w * ey
    ax, ay, az, ia = _unit(ox - px, oy - py, oz - pz)  # â, 1/|a|: towards the camera
    bx, by, bz, ib = _unit(qx - px, qy - py, qz - pz)  # b̂, 1/|b|: towards the screen point
    mx = ax + bx
    my = ay + by
    mz = az + bz
    # d(â)/dz = −(e − (â·e) â)/|a|, the same for b̂.
    ae = ax * ex + ay * ey + az
    be = bx * ex + by * ey + bz
    dmx = -(ex - ae * ax) * ia - (ex - be * bx) * ib
    dmy = -(ey - ae * ay) * ia - (ey - be * by) * ib
    dmz = -(1.0 - ae * az) * ia - (1.0 - be * bz) * ib
    imz = 1.0 / mz
    gx = -mx * imz
    gy = -my * imz
    return px, py, gx, gy, -(dmx + gx * dmz) * imz, -(dmy + gy * dmz) * imz  # d(−m_x/m_z)/dz


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_geometry(o, d, q, S, z, v, geo):
    """For every pixel u of S in row v at height z: geo[u] = (x, y, g_x, g_y, dg_x/dz,
    dg_y/dz, d_x/d_z, d_y/d_z) — the point's x, y, the slopes g of the bisector normal there,
    their derivative along the view ray and the ray's dx/dz, dy/dz (geo shape (W, 8))."""
    W = S.shape[1]
    for u in range(W):
        if not S[v, u]:
            continue
        idz = 1.0 / d[v, u, 2]
        ex = d[v, u, 0] * idz  # dp/dz = (ex, ey, 1)
        ey = d[v, u, 1] * idz
        geo[u, 0], geo[u, 1], geo[u, 2], geo[u, 3], geo[u, 4], geo[u, 5] = _point_geometry(
            o[0], o[1], o[2], ex, ey, z[v, u], q[v, u, 0], q[v, u, 1], q[v, u, 2])
        geo[u, 6] = ex
        geo[u, 7] = ey


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_geometry_all(o, d, q, z, v, geo, rays):
    """geo (8, W) = the rows of :func:`_row_geometry` for every pixel of row v (no mask, so
    that the loop vectorises: off the mask the values are unused and may be NaN). The row's d
    and q are first gathered into ``rays`` (6, W) (contiguous rows, which the second loop
    reads)."""
    W = z.shape[1]
    ox = o[0]
    oy = o[1]
    oz = o[2]
    zr = z[v]
    dr = d[v].reshape(3 * W)  # contiguous rows (views)
    qr = q[v].reshape(3 * W)
    d0, d1, d2, q0, q1, q2 = rays[0], rays[1], rays[2], rays[3], rays[4], rays[5]
    for u in range(W):
        d0[u] = dr[3 * u]
        d1[u] = dr[3 * u + 1]
        d2[u] = dr[3 * u + 2]
        q0[u] = qr[3 * u]
        q1[u] = qr[3 * u + 1]
        q2[u] = qr[3 * u + 2]
    g0, g1, g2, g3, g4, g5, g6, g7 = geo[0], geo[1], geo[2], geo[3], geo[4], geo[5], geo[6], geo[7]
    for u in range(W):
        idz = 1.0 / d2[u]
        ex = d0[u] * idz  # dp/dz = (ex, ey, 1)
        ey = d1[u] * idz
        g0[u], g1[u], g2[u], g3[u], g4[u], g5[u] = _point_geometry(ox, oy, oz, ex, ey, zr[u], q0[u], q1[u], q2[u])
        g6[u] = ex
        g7[u] = ey


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _edge(za, zb, ga, ia, gb, ib):
    """Residual of the trapezoidal equation of the edge a → b (heights za, zb; geometry rows
    ga, gb of :func:`_row_geometry` at columns ia, ib) and its derivatives with respect to
    z_a and z_b (xy moves along the rays, dxy/dz = d_xy/d_z; the slopes change by dg/dz).
    Returns (finite, residual, J_a, J_b)."""
    Gx = 0.5 * (ga[ia, 2] + gb[ib, 2])
    Gy = 0.5 * (ga[ia, 3] + gb[ib, 3])
    dx = gb[ib, 0] - ga[ia, 0]
    dy = gb[ib, 1] - ga[ia, 1]
    res = zb - za - (Gx * dx + Gy * dy)
    Ja = -1.0 + (Gx * ga[ia, 6] + Gy * ga[ia, 7]) - 0.5 * (ga[ia, 4] * dx + ga[ia, 5] * dy)
    Jb = 1.0 - (Gx * gb[ib, 6] + Gy * gb[ib, 7]) - 0.5 * (gb[ib, 4] * dx + gb[ib, 5] * dy)
    ok = np.isfinite(res) and np.isfinite(Ja) and np.isfinite(Jb)
    return ok, res, Ja, Jb


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_edges(Sa, Sb, za, zb, ga, gb, off, n, e):
    """The n edges a = u → b = u + off (off = 1: along a row, ga is gb; 0: row a → row b
    below) of rows with masks Sa, Sb, heights za, zb and geometry ga, gb (8, W) of
    :func:`_row_geometry_all`: e[0, u], e[1, u], e[2, u] = residual, J_a, J_b as
    :func:`_edge`, all 0 where an end is off the mask or a value is not finite (no branches:
    the loop vectorises)."""
    res_o, ja_o, jb_o = e[0], e[1], e[2]
    for u in range(n):
        ib = u + off
        Gx = 0.5 * (ga[2, u] + gb[2, ib])
        Gy = 0.5 * (ga[3, u] + gb[3, ib])
        dx = gb[0, ib] - ga[0, u]
        dy = gb[1, ib] - ga[1, u]
        res = zb[ib] - za[u] - (Gx * dx + Gy * dy)
        Ja = -1.0 + (Gx * ga[6, u] + Gy * ga[7, u]) - 0.5 * (ga[4, u] * dx + ga[5, u] * dy)
        Jb = 1.0 - (Gx * gb[6, ib] + Gy * gb[7, ib]) - 0.5 * (gb[4, ib] * dx + gb[5, ib] * dy)
        ok = Sa[u] & Sb[ib] & np.isfinite(res) & np.isfinite(Ja) & np.isfinite(Jb)  # & : no branches
        res_o[u] = res if ok else 0.0
        ja_o[u] = Ja if ok else 0.0
        jb_o[u] = Jb if ok else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_sums(eh, ev, Dr, rr, Dn, rn, Exr, Eyr):
    """Adds row v's edges (eh to the right, ev below, (3, W) of :func:`_row_edges`) to the
    normal equations: Dr, rr (W,) = row v's diagonal and right-hand side (its upper edge's
    terms already in), Dn, rn (W,) = row v + 1's from its upper edges (set), Exr, Eyr (W,) =
    row v's couplings to the right and below. Sums in the order above, left, right, below."""
    W = Dr.shape[0]
    Dr[0] = Dr[0] + eh[1, 0] * eh[1, 0] + ev[1, 0] * ev[1, 0]
    rr[0] = rr[0] - eh[1, 0] * eh[0, 0] - ev[1, 0] * ev[0, 0]
    for u in range(1, W):
        Dr[u] = Dr[u] + eh[2, u - 1] * eh[2, u - 1] + eh[1, u] * eh[1, u] + ev[1, u] * ev[1, u]
        rr[u] = rr[u] - eh[2, u - 1] * eh[0, u - 1] - eh[1, u] * eh[0, u] - ev[1, u] * ev[0, u]
    for u in range(W):
        Dn[u] = ev[2, u] * ev[2, u]
        rn[u] = -(ev[2, u] * ev[0, u])
        Exr[u] = -eh[1, u] * eh[2, u]
        Eyr[u] = -ev[1, u] * ev[2, u]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_diagonal(Dr, rr, iDr):
    """A complete row's diagonal (W,): iDr = 1/Dr where Dr > 0, else Dr, iDr, rr = 0 (not an
    unknown). Without branches (the loop vectorises)."""
    for u in range(Dr.shape[0]):
        dd = Dr[u]
        pos = dd > 0.0
        i = 1.0 / dd
        iDr[u] = i if pos else 0.0
        Dr[u] = dd if pos else 0.0
        rr[u] = rr[u] if pos else 0.0


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _assemble_gauss_newton(o, d, q, S, z, sv, su, D, iD, Ex, Ey, rhs):
    """Gauss–Newton normal equations Jᵀ J δ = −Jᵀ res of the trapezoidal equations
    res = z_b − z_a − ½(g_a + g_b)·(xy_b − xy_a) of all 4-neighbour pairs in S at the heights
    z, written to the padded 5-point arrays (see above). The seed (sv, su) is not an unknown
    (gauge): it gets no row, and the couplings to it are 0 (sv < 0: no seed). Edges whose residual or derivatives are not
    finite are dropped.

    Every edge is evaluated once, from its left or upper pixel. The rows are split into
    :data:`_ASSEMBLY_BLOCKS` blocks processed in parallel, each with a rolling two-row buffer
    of the pixel geometry (:func:`_row_geometry_all`) and the row's edges
    (:func:`_row_edges`), added to the system by :func:`_row_sums`; the contributions of a
    block's last row to the next block's first row go through a buffer that is added
    afterwards. Every sum is formed in the same order whatever the blocks (above, left,
    right, below; a block's first row: left, right, below, above), so the result does not
    depend on the number of threads. A row's diagonal (iD, and the rows that are not
    unknowns cleared, :func:`_row_diagonal`) is formed as soon as the row is complete, while
    it is in cache (a block's first row after the buffer is added)."""
    H, W = S.shape
    nb = min(H, _ASSEMBLY_BLOCKS)
    bD = np.zeros((nb, W))
    brhs = np.zeros((nb, W))
    for blk in numba.prange(0, nb):
        v0 = blk * H // nb
        v1 = (blk + 1) * H // nb
        geo = np.empty((2, 8, W))
        rays = np.empty((6, W))
        eh = np.zeros((3, W))  # the row's edges to the right: residual, J_a, J_b
        ev = np.zeros((3, W))  # and below
        for u in range(W):
            D[v0 + 1, u + 1] = 0.0
            rhs[v0 + 1, u + 1] = 0.0
        _row_geometry_all(o, d, q, z, v0, geo[0], rays)
        for v in range(v0, v1):
            gc = geo[(v - v0) & 1]
            gn = geo[1 - ((v - v0) & 1)]
            _row_edges(S[v], S[v], z[v], z[v], gc, gc, 1, W - 1, eh)
            below = v + 1 < H
            if below:
                _row_geometry_all(o, d, q, z, v + 1, gn, rays)
                _row_edges(S[v], S[v + 1], z[v], z[v + 1], gc, gn, 0, W, ev)
            else:
                ev[:, :] = 0.0
            if v + 1 < v1:
                Dn, rn = D[v + 2, 1:W + 1], rhs[v + 2, 1:W + 1]
            else:  # the next block's first row (or, below the image, unused)
                Dn, rn = bD[blk], brhs[blk]
            Dr, rr = D[v + 1, 1:W + 1], rhs[v + 1, 1:W + 1]
            _row_sums(eh, ev, Dr, rr, Dn, rn, Ex[v + 1, 1:W + 1], Ey[v + 1, 1:W + 1])
            if v > v0 or blk == 0:  # the row is complete: its diagonal while it is in cache
                _row_diagonal(Dr, rr, iD[v + 1, 1:W + 1])
    for blk in range(1, nb):  # the blocks' first rows: the terms of the row above, then the diagonal
        v0 = blk * H // nb
        for u in range(W):
            D[v0 + 1, u + 1] += bD[blk - 1, u]
            rhs[v0 + 1, u + 1] += brhs[blk - 1, u]
        _row_diagonal(D[v0 + 1, 1:W + 1], rhs[v0 + 1, 1:W + 1], iD[v0 + 1, 1:W + 1])
    if sv >= 0:  # the gauge: no row, no couplings
        D[sv + 1, su + 1] = 0.0
        iD[sv + 1, su + 1] = 0.0
        rhs[sv + 1, su + 1] = 0.0
        Ex[sv + 1, su + 1] = 0.0
        Ex[sv + 1, su] = 0.0
        Ey[sv + 1, su + 1] = 0.0
        Ey[sv, su + 1] = 0.0


@numba.njit(cache=True, nogil=True)
def _apply_update(z, delta, D):
    """z += delta on the unknowns (D > 0; delta and D padded by one pixel). Returns the
    largest |delta| there (NaN if any is not finite, 0 if there are no unknowns)."""
    H, W = z.shape
    m = 0.0
    for v in range(H):
        for u in range(W):
            if D[v + 1, u + 1] > 0.0:
                dz = delta[v + 1, u + 1]
                z[v, u] += dz
                if not np.isfinite(dz):
                    m = np.nan
                elif abs(dz) > m:
                    m = abs(dz)
    return m


class _Fields:
    """Zeroed work arrays for the levels of one reconstruction, carved from buffers allocated
    once: the k-th array handed out since :meth:`reset` is a view of the k-th buffer of its
    dtype (sized for the largest level, ``size`` elements, grown if a request is larger).

    Every level of the coarse-to-fine start and the full grid need the same dozen padded
    fields; fresh arrays per level cost a page fault per 4 KB page on first touch (on this
    machine 20–60 % of the full reconstruction's time was system time, varying with the
    other jobs). A view is zeroed where an earlier level may have written it, so it is
    exactly a fresh ``np.zeros`` array. No two levels' arrays are alive at once (a level's
    solve ends before the next level starts)."""

    def __init__(self, size: int):
        self.size = int(size)
        self._bufs: dict = {}  # dtype → [[buffer, elements possibly non-zero], ...]
        self._next: dict = {}

    def reset(self) -> None:
        """Hand out the buffers again from the first (the arrays handed out before are dead)."""
        self._next.clear()

    def zeros(self, shape, dtype=np.float64) -> np.ndarray:
        """A zeroed C-contiguous array of ``shape`` and ``dtype``."""
        dtype = np.dtype(dtype)
        shape = tuple(int(n) for n in np.atleast_1d(shape))
        n = int(np.prod(shape))
        bufs = self._bufs.setdefault(dtype, [])
        k = self._next.get(dtype, 0)
        self._next[dtype] = k + 1
        if k == len(bufs) or bufs[k][0].size < n:
            entry = [np.zeros(max(n, self.size), dtype=dtype), 0]  # calloc: zero until touched
            if k == len(bufs):
                bufs.append(entry)
            else:
                bufs[k] = entry
        buf, dirty = bufs[k]
        buf[:min(dirty, n)] = 0
        bufs[k][1] = max(dirty, n)
        return buf[:n].reshape(shape)


def _gauss_newton(o, d, q, S, seed, z, tol, max_iter, atol_frac=0.01, fields=None, first_frac=None):
    """Gauss–Newton iterations of the least-squares integration on the pixels S (H, W),
    updating the heights z (H, W) in place, until the largest update is below ``tol`` (its
    linear solve having converged) or after ``max_iter`` iterations. Returns (iterations,
    converged, largest last update).

    Each update is solved (:func:`_pcg`) until the estimated error of the update is below
    ``max(atol_frac · tol, min(1e-4 · |first estimate|, tol/10))`` (max-norm): to a tenth of
    ``tol``, so that after an update that removes all but a second-order remainder the next
    (checking) update is below ``tol`` — with a good start (see :func:`_start_heights`) one
    full solve and one cheap checking solve suffice —, and relatively to 1e-4 when that is
    finer, but never below ``atol_frac · tol``, the accuracy to which the last update is
    known when it is compared with ``tol``: ``tol`` · :data:`_COARSE_ATOL_FRAC` on the coarse
    levels of the start (whose result must be accurate to start the next level well),
    ``tol/10`` on the full grid
    (:func:`reconstruct_least_squares`: the result is that accurate; the checking update is
    then typically solved in one iteration instead of three). ``fields`` (:class:`_Fields`)
    provides the work arrays (a new one if not given).

    ``first_frac`` (with ``max_iter`` > 1): the first update is solved only until its estimated
    error is below ``first_frac · tol``, and it never decides convergence (if it is below
    ``tol``, one more update follows). The update that follows is linear in that error
    (δ₂ = −e₁ + O(|δ₁|²)), so it removes it with the second-order remainder, and it is solved
    to the usual accuracy: the result is as accurate as with every update solved to
    ``atol_frac · tol``, and the first solve saves its last CG iteration or two. Meant for
    a start whose first update is far above ``tol`` (the coarse-to-fine start: ≈ 1e-4 mm)."""
    H, W = S.shape
    if fields is None:
        fields = _Fields((H + 2) * (W + 2))
    fields.reset()
    D, iD, Ex, Ey, rhs = (fields.zeros((H + 2, W + 2)) for _ in range(5))
    lap = None
    if poisson.prefers_dct(np.count_nonzero(S) - 1, S.shape):  # the seed is not an unknown
        lap = poisson.DCTLaplacian(S.shape, seed, dtype=np.float32)
        work = poisson._DCTWork(1, D.shape, zeros=fields.zeros)
    else:
        work = _CGWork(D.shape, zeros=fields.zeros)
    converged = False
    change = np.inf
    it = 0
    for it in range(1, max_iter + 1):
        _assemble_gauss_newton(o, d, q, S, z, seed[0], seed[1], D, iD, Ex, Ey, rhs)
        loose = first_frac is not None and it == 1 and max_iter > 1
        atol, cap = (first_frac * tol, first_frac * tol) if loose else (atol_frac * tol, _INNER_CAP * tol)
        if lap is not None:  # a full frame: CG preconditioned by the DCT (poisson.py)
            X, _, ok = poisson.dct_pcg(D, Ex, Ey, rhs[None], seed, atol, _INNER_RTOL, _INNER_MAX_ITER,
                                       cap=cap, lap=lap, work=work)
            delta, solved = X[0], bool(ok[0])
        else:
            delta, _, solved = _pcg(D, iD, Ex, Ey, rhs, atol, _INNER_RTOL, _INNER_MAX_ITER, cap=cap, work=work)
        change = _apply_update(z, delta, D)
        if not np.isfinite(change):
            raise ReconstructionError(
                "the least-squares iteration diverged (non-finite heights); check that q and d are "
                "consistent (q must be the screen points seen via the surface along d)")
        if change < tol and solved and not loose:  # a partial or loosely solved update proves nothing
            converged = True
            break
    return it, converged, change


def _coarse_mask(S, seed):
    """The coarse problem of the coarse-to-fine start: pixels (a + 2i, b + 2j) of S with
    (a, b) = seed mod 2, so that the seed is one of them.

    Two coarse 4-neighbours are coupled through the fine pixel between them, which must be
    in S too: a coarse pixel is kept only if the fine pixels to its right and below are in S
    (or outside the image), so every coarse neighbour pair is a path of two fine pairs and
    the coarse problem never bridges a gap of the mask. The seed is always kept (instead its
    right or lower coarse neighbour is dropped). Returns (a, b, coarse mask restricted to the
    seed's 4-connected component, coarse seed)."""
    H, W = S.shape
    a, b = seed[0] % 2, seed[1] % 2
    Sp = np.ones((H + 1, W + 1), dtype=bool)
    Sp[:H, :W] = S
    right = Sp[a:H:2, b + 1:W + 1:2]
    down = Sp[a + 1:H + 1:2, b:W:2]
    Sc = S[a::2, b::2] & right & down
    Hc, Wc = Sc.shape
    sc = (seed[0] // 2, seed[1] // 2)
    Sc[sc] = True
    if sc[1] + 1 < Wc and not right[sc]:
        Sc[sc[0], sc[1] + 1] = False
    if sc[0] + 1 < Hc and not down[sc]:
        Sc[sc[0] + 1, sc[1]] = False
    if Sc.all():  # one component (a full frame): no labelling needed
        return a, b, Sc, sc
    from scipy import ndimage  # here, not at import: not on evaluate's start-up path

    labels, _ = ndimage.label(Sc)  # 4-connectivity
    return a, b, np.ascontiguousarray(labels == labels[sc]), sc


def _every_second(x, a, b):
    """x[a::2, b::2] of x (H, W, 3) as a C-contiguous copy. The pixels are copied as items of
    three elements (numpy copies three strided doubles per pixel ≈ 1.8× slower: 4.6 → 2.6 ms
    for the full frame's view rays); the same bytes."""
    if x.flags.c_contiguous and x.ndim == 3:
        v = x.view(np.dtype((np.void, x.shape[2] * x.itemsize)))[a::2, b::2]
        return np.ascontiguousarray(v).view(x.dtype).reshape(v.shape[0], v.shape[1], x.shape[2])
    return np.ascontiguousarray(x[a::2, b::2])


def _starts_coarse(S) -> bool:
    """Whether the Gauss–Newton iteration on the pixels S (H, W) starts coarse to fine
    (:func:`_start_heights`)."""
    return int(np.count_nonzero(S)) >= _COARSE_START_MIN_PIXELS and min(S.shape) >= 4


def _start_heights(o, d, q, S, seed, z0, tol, max_iter, fields=None):
    """Start of the Gauss–Newton iteration on the pixels S (heights (H, W), NaN outside S).

    Coarse to fine: if S has at least :data:`_COARSE_START_MIN_PIXELS` pixels, the
    least-squares problem of every second row and column (:func:`_coarse_mask`, the same
    equations between pixels two apart) is solved first — recursively started the same way —
    to :data:`_COARSE_TOL_MM`; the pixels between are interpolated (bilinearly in the pixel
    grid, :func:`_interpolate_coarse`), and those without solved pixels on both sides (at
    borders and holes of the mask) are filled by stepwise integration from their neighbours
    (:func:`_fill_kernel`). The coarse solution differs from the fine one only by the
    discretisation and by how the slope noise averages, so the fine iteration starts close to
    its solution (for the full-frame benchmark within about 1e-4 mm). On
    small problems (and should a coarse solve fail) the start is the stepwise solution
    (:func:`reconstruct_stepwise`). Pixels of S that neither reaches start at the seed
    height. ``fields``: as :func:`_gauss_newton` (shared by the levels)."""
    H, W = S.shape
    if fields is None:
        fields = _Fields((H + 2) * (W + 2))
    z = None
    if _starts_coarse(S):
        a, b, Sc, sc = _coarse_mask(S, seed)
        dc = _every_second(d, a, b)
        qc = _every_second(q, a, b)
        tol_c = max(tol, _COARSE_TOL_MM)
        try:
            zc = _start_heights(o, dc, qc, Sc, sc, z0, tol_c, max_iter, fields)
            _gauss_newton(o, dc, qc, Sc, sc, zc, tol_c, max_iter, atol_frac=_COARSE_ATOL_FRAC, fields=fields)
        except ReconstructionError:
            zc = None  # fall back to the stepwise start
        if zc is not None:
            z = np.full((H, W), np.nan)
            z[a::2, b::2] = zc  # NaN off Sc ⊂ S (as returned below; the updates change only unknowns)
            if _interpolate_coarse(S, z, a, b) > 0:
                _fill_kernel(o, d, q, S, z, max(tol, 1e-9), STEP_MAX_ITER, _NB_DV, _NB_DU)
    if z is None:
        # The stepwise solution is only a start: its correctors need not converge far below
        # the final tolerance.
        z, _, _, _, _ = _run_stepwise(o, d, q, S, seed, z0, tol=max(tol, 1e-9))
        z = np.where(S, z, np.nan)  # (the coarse start writes only pixels of S)
    z[S & ~np.isfinite(z)] = z0
    z[seed] = z0
    return z


def reconstruct_least_squares(o, d, q, valid, seed_pixel=None, seed_height_mm=0.0, max_iter=20,
                              tol_mm=1e-9) -> Reconstruction:
    """Zonal least-squares integration of the deflectometric slopes (paper §2.5).

    The unknowns are the heights z of all valid pixels that are 4-connected to the seed pixel
    through valid pixels (the seed's component). Every pair of such 4-neighbours a, b (a left
    of or above b) contributes one equation of the Southwell type,

        z_b − z_a = ½ (g_a + g_b) · (xy_b − xy_a),

    with xy of a pixel the x–y position of its point p = o + t·d, t = (z − o_z)/d_z, and g the
    slopes of the bisector normal at p (:func:`normals_from_registration`). All equations have
    weight 1, and the result minimises the sum of their squared residuals over the heights.
    Because the points, and with them the slopes, depend on the heights, the problem is
    nonlinear and is solved by Gauss–Newton iteration:

    1. points from the current heights (along the fixed view rays), then normals and slopes
       at the points;
    2. linearise every residual in the two heights it involves — the movement of xy along the
       rays and the change of the slopes with the height (both exact derivatives) — and solve
       the sparse normal equations Jᵀ J δ = −Jᵀ res for the update δ (a 5-point operator on
       the pixel grid, like a graph Laplacian);
    3. z ← z + δ; repeat until max |δ| < ``tol_mm``.

    Each residual involves two heights only, so including the slope derivative costs nothing
    and gives fast convergence: the slopes' dependence on the heights couples all pixels
    weakly but coherently (a tilt of the whole surface changes all normals), and freezing it
    would make the iteration converge only linearly.

    **Start.** Small problems (fewer than :data:`_COARSE_START_MIN_PIXELS` pixels) start from
    the stepwise solution (:func:`reconstruct_stepwise`), which already satisfies the
    equations exactly for consistent data. Larger ones start coarse to fine: the same
    least-squares problem on every second row and column (never bridging a gap of the mask)
    is solved first, recursively started the same way, and interpolated (see
    :func:`_start_heights`); the full-grid iteration then starts within the coarse–fine
    discrepancy of its solution (about 1e-4 mm for a full 1920×1200 frame), and typically two
    iterations on the full grid suffice: one full update and one that confirms convergence.
    The start affects only the run time: the result is the minimum of the full-grid
    equations, and convergence is always decided on the full grid.

    **Gauge.** The seed pixel's height is fixed at ``seed_height_mm`` exactly (it is removed
    from the unknowns). **Components.** Valid pixels not 4-connected to the seed are not tied
    to the gauge and are left NaN (as in the stepwise integration). **Solver.** Conjugate
    gradients preconditioned by aggregation multigrid (2×2 aggregates with Galerkin coarse
    operators, symmetric Gauss–Seidel smoothing, over-corrected coarse-grid correction — one
    coarse cycle from the full grid, W-cycles below —, dense Cholesky on the coarsest level),
    which copes with arbitrary masks; on a full frame of at least 100 000 pixels by the DCT
    inverse of the Neumann Laplacian instead (:func:`pmdsim.evaluation.poisson.prefers_dct`;
    the same result, fewer iterations). Each update on the full grid is solved until its
    estimated error is below ``tol_mm``/10 (on the coarse levels of the start: or 1e-4
    relative, if finer, but not below 3 % of their tolerance), so that the update that
    follows, which decides convergence, and the result are accurate to a tenth of ``tol_mm``;
    after the coarse-to-fine start the first full-grid update (≈ 1e-4 mm) is solved only to
    ``tol_mm``/5 and never decides convergence — the checking update removes its error
    (:func:`_gauss_newton`, ``first_frac``).

    Parameters
    ----------
    o : array_like, shape (3,)
        Camera projection centre in the reconstruction frame, mm.
    d : array_like, shape (H, W, 3)
        View-ray direction per pixel (any non-zero length); valid pixels need d_z ≠ 0.
    q : array_like, shape (H, W, 3)
        Screen point per pixel from the deflectometric registration, mm.
    valid : array_like of bool, shape (H, W)
        Pixels that may be reconstructed.
    seed_pixel : tuple of int, optional
        (row, column) of the pixel whose height is given. Default: the valid pixel nearest to
        the centroid of ``valid`` (ties: first in row-major order).
    seed_height_mm : float
        Height of the seed pixel, mm.
    max_iter : int
        Maximum number of outer iterations (≥ 1).
    tol_mm : float
        Convergence tolerance on the largest height update of an outer iteration, mm (> 0).

    Returns
    -------
    Reconstruction
        ``iterations`` is the number of outer iterations on the full grid, ``converged``
        whether the last one changed no height by ``tol_mm`` or more (with its sparse solve
        converged to ``tol_mm``/10: after the coarse-to-fine start the loosely solved first
        update never counts, so such a run has at least 2 iterations if ``max_iter`` > 1).

    Raises
    ------
    ReconstructionError
        As :func:`reconstruct_stepwise`, and for ``max_iter`` < 1 or ``tol_mm`` ≤ 0.
    """
    try:
        ok = not isinstance(max_iter, (bool, np.bool_)) and int(max_iter) == max_iter and max_iter >= 1
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ReconstructionError(f"max_iter must be an integer ≥ 1, got {max_iter!r}")
    max_iter = int(max_iter)
    try:
        ok = bool(np.isfinite(tol_mm) and tol_mm > 0)
    except TypeError:
        ok = False
    if not ok:
        raise ReconstructionError(f"tol_mm must be a positive, finite number of mm, got {tol_mm!r}")
    tol_mm = float(tol_mm)
    o, d, q, valid = _check_inputs(o, d, q, valid)
    seed, z0 = _check_seed(seed_pixel, seed_height_mm, o, d, valid)

    H, W = valid.shape
    if valid.all():  # one component: no labelling needed
        S = np.ones((H, W), dtype=bool)
    else:
        from scipy import ndimage

        labels, _ = ndimage.label(valid)  # 4-connectivity
        S = np.ascontiguousarray(labels == labels[seed])

    fields = _Fields((H + 2) * (W + 2))  # the work arrays of every level
    z = _start_heights(o, d, q, S, seed, z0, tol_mm, max_iter, fields)
    first = _FIRST_UPDATE_FRAC if _starts_coarse(S) else None
    it, converged, change = _gauss_newton(o, d, q, S, seed, z, tol_mm, max_iter, atol_frac=_INNER_CAP, fields=fields,
                                          first_frac=first)
    del fields

    recon = S & np.isfinite(z)
    z[~recon] = np.nan  # z is this call's own array
    pts, nrm = _points_and_normals(o, d, q, z)
    return Reconstruction(
        height_mm=z,
        p_sample_mm=pts,
        n_sample=nrm,
        reconstructed=recon,
        method="least_squares",
        iterations=int(it),
        converged=bool(converged),
        seed_pixel=seed,
        final_change_mm=float(change),
    )
