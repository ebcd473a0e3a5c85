"""Multigrid-preconditioned conjugate gradients for the least-squares integration's normal
equations (a 5-point, anisotropically weighted Laplacian-like system on the pixel grid with holes).

Compiled cycle: a V step on the full grid and W cycles below, skewed Gauss–Seidel smoothing,
Galerkin-like coarsening of the edge weights, a dense Cholesky solve on the coarsest level;
the preconditioned CG (:func:`_pcg`) runs fused passes over the grid. Used by
:mod:`pmdsim.evaluation.least_squares`.

Storage. A symmetric positive definite operator N with 4-neighbour couplings is stored on the
pixel grid, padded by one zero pixel on every side (shape (H + 2, W + 2)), as

* ``D``: the diagonal; D == 0 marks a pixel that is not an unknown (inactive);
* ``iD``: 1/D on active pixels, 0 on inactive ones;
* ``Ex``: (N x)[v,u] contains −Ex[v,u]·x[v,u+1], and (N x)[v,u+1] contains −Ex[v,u]·x[v,u];
* ``Ey``: the same for the pixel below, (v+1, u).

Couplings that touch an inactive pixel are 0 and vectors are 0 on inactive pixels, so the
kernels need no branches. Coarse levels aggregate 2×2 pixels; with piecewise-constant
interpolation the Galerkin operator Pᵀ N P is again such a 5-point operator.
"""

from __future__ import annotations

import numba
import numpy as np

from .multigrid_lists import array_list

__all__: list[str] = []


#: Over-correction factors of the multigrid coarse-grid correction (plain aggregation
#: underestimates smooth corrections by about a factor of two): on the finest level, whose
#: correction is a single coarse cycle, and on the coarser levels, whose correction is the sum
#: of two coarse cycles (more accurate, so less over-correction is needed and tolerated).
_MG_TOP_OVERCORRECTION = 2.0


_MG_OVERCORRECTION = 1.5


@numba.njit(cache=True)
def _direction_matvec_dot(D, Ex, Ey, z, p, beta, Ap):
    """The CG direction p = z + βp (p = z for β = 0), then Ap = N p; returns p·Ap. The
    direction is updated one row ahead of the product, which needs the rows above and below."""
    Hp, Wp = D.shape

    def _direction_row(v):
        if beta == 0.0:
            for u in range(1, Wp - 1):
                p[v, u] = z[v, u]
        else:
            for u in range(1, Wp - 1):
                p[v, u] = z[v, u] + beta * p[v, u]

    _direction_row(1)
    s = 0.0
    for v in range(1, Hp - 1):
        if v + 1 < Hp - 1:
            _direction_row(v + 1)
        for u in range(1, Wp - 1):
            y = (D[v, u] * p[v, u] - Ex[v, u - 1] * p[v, u - 1] - Ex[v, u] * p[v, u + 1]
                 - Ey[v - 1, u] * p[v - 1, u] - Ey[v, u] * p[v + 1, u])
            Ap[v, u] = y
            s += p[v, u] * y
    return s


@numba.njit(cache=True)
def _residual(D, Ex, Ey, r, x, out):
    """out = r − N x."""
    Hp, Wp = D.shape
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            out[v, u] = (r[v, u] - D[v, u] * x[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * x[v, u + 1]
                         + Ey[v - 1, u] * x[v - 1, u] + Ey[v, u] * x[v + 1, u])


@numba.njit(cache=True)
def _presmooth_restrict(iD, Ex, Ey, r, x, rc):
    """One forward (lexicographic) Gauss–Seidel sweep for N x = r from x = 0, then the residual
    r − N x summed over 2×2 aggregates into rc (padded coarse grid).

    Rows are swept in pairs, the second row one column behind the first (it needs the new
    value above it): the result is that of the row-by-row sweep, but the two rows are two
    independent dependency chains, which the processor overlaps. After a forward sweep from
    zero the residual at a pixel is Ex·x(right) + Ey·x(below) (the equation was satisfied with
    the right and lower neighbours still 0); it is accumulated once the row below is swept."""
    Hp, Wp = iD.shape
    rc[:, :] = 0.0

    def _restrict_row(w):
        V = ((w - 1) >> 1) + 1
        for u in range(1, Wp - 1):
            rc[V, ((u - 1) >> 1) + 1] += Ex[w, u] * x[w, u + 1] + Ey[w, u] * x[w + 1, u]

    v = 1
    while v < Hp - 1:
        if v + 1 < Hp - 1:
            w = v + 1
            x0 = (r[v, 1] + Ey[v - 1, 1] * x[v - 1, 1]) * iD[v, 1]
            x[v, 1] = x0
            x1 = 0.0
            for u in range(2, Wp - 1):
                x0 = (r[v, u] + Ex[v, u - 1] * x0 + Ey[v - 1, u] * x[v - 1, u]) * iD[v, u]
                x[v, u] = x0
                t = u - 1
                x1 = (r[w, t] + Ex[w, t - 1] * x1 + Ey[v, t] * x[v, t]) * iD[w, t]
                x[w, t] = x1
            t = Wp - 2
            x1 = (r[w, t] + Ex[w, t - 1] * x1 + Ey[v, t] * x[v, t]) * iD[w, t]
            x[w, t] = x1
            x[v, Wp - 1] = 0.0
            x[w, Wp - 1] = 0.0
            if v > 1:
                _restrict_row(v - 1)
            _restrict_row(v)
            v += 2
        else:
            x0 = 0.0
            for u in range(1, Wp - 1):
                x0 = (r[v, u] + Ex[v, u - 1] * x0 + Ey[v - 1, u] * x[v - 1, u]) * iD[v, u]
                x[v, u] = x0
            x[v, Wp - 1] = 0.0
            if v > 1:
                _restrict_row(v - 1)
            v += 1
    _restrict_row(Hp - 2)  # the row below it is the zero padding


@numba.njit(cache=True)
def _prolong_postsmooth(iD, Ex, Ey, r, x, xc, alpha):
    """x += alpha·P xc (piecewise-constant interpolation from 2×2 aggregates), then one
    backward Gauss–Seidel sweep for N x = r. Rows are swept in pairs from the bottom, the
    upper row one column behind (as in :func:`_presmooth_restrict`; the result is that of the
    row-by-row sweep); the interpolation is added to a row just before it is needed. Inactive
    pixels receive the interpolation too (no branch), but their couplings are 0 and the sweep
    resets them to 0 (iD = 0). Returns (r·x, max |x|) of the result (for CG)."""
    Hp, Wp = iD.shape
    s = 0.0
    m = 0.0

    def _add_row(w):
        V = ((w - 1) >> 1) + 1
        for u in range(1, Wp - 1):
            x[w, u] += alpha * xc[V, ((u - 1) >> 1) + 1]

    _add_row(Hp - 2)
    v = Hp - 2
    while v >= 1:
        if v - 1 >= 1:
            w = v - 1
            _add_row(w)
            if w > 1:
                _add_row(w - 1)
            t = Wp - 2
            x0 = (r[v, t] + Ex[v, t - 1] * x[v, t - 1] + Ex[v, t] * x[v, t + 1]
                  + Ey[w, t] * x[w, t] + Ey[v, t] * x[v + 1, t]) * iD[v, t]
            x[v, t] = x0
            s += r[v, t] * x0
            m = max(m, abs(x0))
            x1 = x[w, Wp - 1]
            for u in range(Wp - 3, 0, -1):
                x0 = (r[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * x0
                      + Ey[w, u] * x[w, u] + Ey[v, u] * x[v + 1, u]) * iD[v, u]
                x[v, u] = x0
                s += r[v, u] * x0
                m = max(m, abs(x0))
                t = u + 1
                x1 = (r[w, t] + Ex[w, t - 1] * x[w, t - 1] + Ex[w, t] * x1
                      + Ey[w - 1, t] * x[w - 1, t] + Ey[w, t] * x[v, t]) * iD[w, t]
                x[w, t] = x1
                s += r[w, t] * x1
                m = max(m, abs(x1))
            x1 = (r[w, 1] + Ex[w, 0] * x[w, 0] + Ex[w, 1] * x1
                  + Ey[w - 1, 1] * x[w - 1, 1] + Ey[w, 1] * x[v, 1]) * iD[w, 1]
            x[w, 1] = x1
            s += r[w, 1] * x1
            m = max(m, abs(x1))
            v -= 2
        else:
            xr = x[v, Wp - 1]
            for u in range(Wp - 2, 0, -1):
                xr = (r[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * xr
                      + Ey[v - 1, u] * x[v - 1, u] + Ey[v, u] * x[v + 1, u]) * iD[v, u]
                x[v, u] = xr
                s += r[v, u] * xr
                m = max(m, abs(xr))
            v -= 1
    return s, m


@numba.njit(cache=True)
def _coarsen(D, Ex, Ey):
    """Galerkin coarse operator Pᵀ N P for 2×2 aggregation (padded arrays in and out)."""
    Hp, Wp = D.shape
    H = Hp - 2
    W = Wp - 2
    Hc = (H + 1) // 2
    Wc = (W + 1) // 2
    Dc = np.zeros((Hc + 2, Wc + 2))
    Exc = np.zeros((Hc + 2, Wc + 2))
    Eyc = np.zeros((Hc + 2, Wc + 2))
    for v in range(1, Hp - 1):
        V = ((v - 1) >> 1) + 1
        v_internal = ((v - 1) & 1) == 0  # the edge to v + 1 stays inside the aggregate
        for u in range(1, Wp - 1):
            if D[v, u] == 0.0:
                continue
            U = ((u - 1) >> 1) + 1
            Dc[V, U] += D[v, u]
            e = Ex[v, u]
            if ((u - 1) & 1) == 0:
                Dc[V, U] -= 2.0 * e  # both off-diagonal entries fall on the aggregate's diagonal
            else:
                Exc[V, U] += e
            e = Ey[v, u]
            if v_internal:
                Dc[V, U] -= 2.0 * e
            else:
                Eyc[V, U] += e
    iDc = np.zeros((Hc + 2, Wc + 2))
    for V in range(1, Hc + 1):
        for U in range(1, Wc + 1):
            if Dc[V, U] > 0.0:
                iDc[V, U] = 1.0 / Dc[V, U]
            else:  # no active pixel (or round-off): not an unknown
                Dc[V, U] = 0.0
                Exc[V, U] = 0.0
                Eyc[V, U] = 0.0
                Exc[V, U - 1] = 0.0
                Eyc[V - 1, U] = 0.0
    return Dc, iDc, Exc, Eyc


@numba.njit(cache=True)
def _cg_update(x, r, p, Ap, alpha):
    """x += αp, r −= αAp."""
    Hp, Wp = x.shape
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            x[v, u] += alpha * p[v, u]
            r[v, u] -= alpha * Ap[v, u]


@numba.njit(cache=True)
def _dot_maxabs(a, b):
    """Returns (a·b, max|b|)."""
    Hp, Wp = a.shape
    s = 0.0
    m = 0.0
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            s += a[v, u] * b[v, u]
            m = max(m, abs(b[v, u]))
    return s, m


#: The multigrid hierarchy stops coarsening once a level has at most this many cells; that
#: level is solved exactly (dense Cholesky factorisation).
_MG_COARSEST_CELLS = 256


@numba.njit(cache=True)
def _cholesky_inplace(A):
    """Lower Cholesky factor of the SPD matrix A, in place. Returns False if a pivot is not
    positive (A not numerically positive definite)."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        ljj = np.sqrt(s)
        A[j, j] = ljj
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / ljj
    return True


@numba.njit(cache=True)
def _cholesky_solve(L, index, r, x):
    """x[index] = (L Lᵀ)⁻¹ r[index] on flattened padded grids; x is 0 elsewhere."""
    n = L.shape[0]
    rf = r.ravel()
    xf = x.ravel()
    xf[:] = 0.0
    y = np.empty(n)
    for i in range(n):
        s = rf[index[i]]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * y[k]
        y[i] = s / L[i, i]
    for i in range(n):
        xf[index[i]] = y[i]


@numba.njit(cache=True)
def _coarsest_solve(kind, F, index, r, x):
    """x = exact solution on the coarsest level: ``kind`` 0 = Cholesky factor F
    (:func:`_cholesky_solve`), 1 = pseudo-inverse F of the matrix of the cells ``index``,
    2 = no unknowns (x = 0)."""
    if kind == 0:
        _cholesky_solve(F, index, r, x)
        return
    x[:, :] = 0.0
    if kind == 1:
        n = index.size
        rf = r.ravel()
        xf = x.ravel()
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += F[i, j] * rf[index[j]]
            xf[index[i]] = s


@numba.njit(cache=True)
def _mg_cycle(lvl, r, x, Ds, iDs, Exs, Eys, xs, rcs, r2s, accs, kind, F, index, alpha_top, alpha):
    """x = multigrid cycle for N_lvl x = r on level ``lvl`` of the hierarchy (typed lists of
    the padded level arrays, see :class:`_Multigrid`): forward Gauss–Seidel, coarse-grid
    correction, backward Gauss–Seidel; exact on the coarsest level. The coarse-grid
    correction is, on level 0, one cycle on level 1 scaled by ``alpha_top`` (a V-cycle step:
    the finest level is by far the most expensive) and, below, two cycles (the second for the
    residual the first leaves) whose sum is scaled by ``alpha`` (W-cycle). Returns
    (r·x, max |x|) except on the coarsest level (0, 0)."""
    if lvl == len(Ds) - 1:
        _coarsest_solve(kind, F, index, r, x)
        return 0.0, 0.0
    n = lvl + 1
    _presmooth_restrict(iDs[lvl], Exs[lvl], Eys[lvl], r, x, rcs[n])
    _mg_cycle(n, rcs[n], xs[n], Ds, iDs, Exs, Eys, xs, rcs, r2s, accs, kind, F, index, alpha_top, alpha)
    if lvl == 0:
        return _prolong_postsmooth(iDs[lvl], Exs[lvl], Eys[lvl], r, x, xs[n], alpha_top)
    acc = accs[n]
    acc[:, :] = xs[n]
    _residual(Ds[n], Exs[n], Eys[n], rcs[n], acc, r2s[n])
    _mg_cycle(n, r2s[n], xs[n], Ds, iDs, Exs, Eys, xs, rcs, r2s, accs, kind, F, index, alpha_top, alpha)
    acc += xs[n]
    return _prolong_postsmooth(iDs[lvl], Exs[lvl], Eys[lvl], r, x, acc, alpha)


class _Multigrid:
    """Aggregation multigrid preconditioner for a padded 5-point SPD operator (see above).

    Levels aggregate 2×2 pixels, with Galerkin coarse operators, so any mask works; the
    coarsest level (≤ ``_MG_COARSEST_CELLS`` cells) is solved exactly. One application
    (:meth:`apply`) is a cycle (:func:`_mg_cycle`, entirely in compiled code): forward
    Gauss–Seidel before and backward Gauss–Seidel after the coarse-grid correction (a
    symmetric pair), the correction being one coarse cycle on the finest level and two below
    (a V-cycle step on top of W-cycles), over-corrected (plain aggregation underestimates
    smooth corrections)."""

    def __init__(self, D, iD, Ex, Ey):
        levels = [(D, iD, Ex, Ey)]
        while (D.shape[0] - 2) * (D.shape[1] - 2) > _MG_COARSEST_CELLS:
            D, iD, Ex, Ey = _coarsen(D, Ex, Ey)
            levels.append((D, iD, Ex, Ey))
        self.n_levels = len(levels)
        shapes = [lv[0].shape for lv in levels]
        # numba typed lists built by cached compiled code (multigrid_lists: numba.typed.List([...])
        # would compile numba's list helpers, 0.25 s of CPU, in every fresh process)
        self.Ds = array_list([lv[0] for lv in levels])
        self.iDs = array_list([lv[1] for lv in levels])
        self.Exs = array_list([lv[2] for lv in levels])
        self.Eys = array_list([lv[3] for lv in levels])
        # Work arrays per level (level 0's are unused: its input and output are the caller's).
        self.xs = array_list([np.zeros(s) for s in shapes])     # the level's result
        self.rcs = array_list([np.zeros(s) for s in shapes])    # restricted residual (level input)
        self.r2s = array_list([np.zeros(s) for s in shapes])    # residual for the second cycle
        self.accs = array_list([np.zeros(s) for s in shapes])   # sum of the two coarse cycles
        self._factor_coarsest(*levels[-1])

    def _factor_coarsest(self, D, _iD, Ex, Ey):
        Wp = D.shape[1]
        flat = np.flatnonzero(D.ravel() > 0.0)
        self.coarse_index = flat
        n = flat.size
        if n == 0:
            self.coarse_kind, self.coarse_factor = 2, np.zeros((1, 1))
            return
        pos = np.full(D.size, -1, dtype=np.int64)
        pos[flat] = np.arange(n)
        A = np.zeros((n, n))
        A[np.arange(n), np.arange(n)] = D.ravel()[flat]
        for E, step in ((Ex.ravel(), 1), (Ey.ravel(), Wp)):
            src = np.flatnonzero(E != 0.0)
            i = pos[src]
            j = pos[src + step]
            keep = (i >= 0) & (j >= 0)
            A[i[keep], j[keep]] = -E[src[keep]]
            A[j[keep], i[keep]] = -E[src[keep]]
        L = A.copy()
        if _cholesky_inplace(L):
            self.coarse_kind, self.coarse_factor = 0, L
        else:  # numerically semi-definite: pseudo-inverse
            self.coarse_kind, self.coarse_factor = 1, np.ascontiguousarray(np.linalg.pinv(A, hermitian=True))

    def apply(self, r, out, alpha_top, alpha):
        """out = M⁻¹ r (padded level-0 arrays; out's padding must be 0), with the
        over-correction factors ``alpha_top`` (finest level) and ``alpha`` (below). Returns
        (r·out, max |out|)."""
        rz, zmax = _mg_cycle(0, r, out, self.Ds, self.iDs, self.Exs, self.Eys, self.xs, self.rcs,
                             self.r2s, self.accs, self.coarse_kind, self.coarse_factor,
                             self.coarse_index, float(alpha_top), float(alpha))
        if self.n_levels == 1:  # solved exactly, no sweep that could have summed them
            rz, zmax = _dot_maxabs(r, out)
        return rz, zmax


class _CGWork:
    """Work arrays of :func:`_pcg` for padded grids of one shape (zero padding kept), from
    ``zeros(shape, dtype)`` (default ``np.zeros``; a caller may hand out reused buffers)."""

    def __init__(self, shape, zeros=np.zeros):
        self.x, self.r, self.z, self.p, self.Ap = (zeros(shape, np.float64) for _ in range(5))


def _pcg(D, iD, Ex, Ey, b, atol, rtol, max_iter, cap=np.inf, work=None, mg=None):
    """Conjugate gradients for N x = b, preconditioned by :class:`_Multigrid`.

    Stops when the max-norm of the preconditioned residual (an estimate of the error of x) is
    below ``max(atol, min(rtol · its initial value, cap))``; that last preconditioned residual
    is added to x. The over-corrected cycle is not guaranteed to be positive definite; should
    CG break down with it (non-positive curvature or a non-finite residual), CG restarts from
    the current x with the plain cycle (no over-correction), which is a symmetric positive
    definite preconditioner. After ``max_iter`` iterations in all, the current x is returned
    (not converged; the caller's next Gauss–Newton iteration continues from it).
    ``work`` (:class:`_CGWork`) and ``mg`` (the hierarchy of this operator) are created if not
    given. Returns (x, total CG iterations, converged); x is ``work.x``."""
    if work is None:
        work = _CGWork(D.shape)
    if mg is None:
        mg = _Multigrid(D, iD, Ex, Ey)
    x, r, z, p, Ap = work.x, work.r, work.z, work.p, work.Ap
    x[:] = 0.0
    r[:] = b
    total = 0
    tol = None
    for alpha_top, alpha in ((_MG_TOP_OVERCORRECTION, _MG_OVERCORRECTION), (1.0, 1.0)):
        rz, zmax = mg.apply(r, z, alpha_top, alpha)
        if tol is None:
            if zmax <= atol:
                x += z  # the solution is below the tolerance anyway
                return x, total, True
            tol = max(atol, min(rtol * zmax, cap))
        elif zmax <= tol:
            x += z
            return x, total, True
        beta = 0.0
        breakdown = False
        while total < max_iter:
            total += 1
            pAp = _direction_matvec_dot(D, Ex, Ey, z, p, beta, Ap)
            if not (pAp > 0.0 and rz > 0.0):
                breakdown = True  # the preconditioner is not positive definite here
                break
            a = rz / pAp
            _cg_update(x, r, p, Ap, a)
            rz_new, zmax = mg.apply(r, z, alpha_top, alpha)
            if not np.isfinite(rz_new):
                breakdown = True
                break
            if zmax <= tol:
                x += z
                return x, total, True
            beta = rz_new / rz
            rz = rz_new
        if not breakdown:
            return x, total, False
        # Restart with the plain cycle from the last good x (its residual recomputed).
        if not np.all(np.isfinite(x)):
            x[:] = 0.0
        _residual(D, Ex, Ey, b, x, r)
    return x, total, False
