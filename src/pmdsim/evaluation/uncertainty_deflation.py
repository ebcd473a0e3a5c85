"""Deflated DCT-preconditioned conjugate gradients for the least-squares integration's normal
equations on a full frame (issue 25 item 3): the solver of the least-squares height σ's sampled
right-hand sides (:mod:`pmdsim.evaluation.uncertainty_solve`), which all share one matrix N,
so that the deflation space's setup is paid once per camera and used K = 64 times.

CG preconditioned by the pinned Laplacian's DCT inverse (:mod:`pmdsim.evaluation.poisson`), with
the lowest DCT modes and the Laplacian's Green's function at the gauge pixel deflated (Saad,
Yeung, Erhel & Guyomarc'h 2000, "A deflated version of the conjugate gradient algorithm", SIAM
J. Sci. Comput. 21, 1909), in the A-DEF2 form (Tang, Nabben, Vuik & Erlangga 2009), which stays
stable to 1e-13 where the plain deflated form drifts.

Why: the Gauss–Newton matrix N differs from the Laplacian L most in its smoothest modes (Robin
terms on the border, the weak dependence of the residuals on the absolute height, which competes
with the one pinned pixel), so the spectrum of L_s⁻¹N spreads over [0.64, 1.84] there (Ritz values
of the Table 1 frame) and CG spends its iterations on them: the error of every iterate of the
plain solve is ≥ 94 % in the lowest 4×6 DCT modes. Deflation solves the problem exactly on the
space W spanned by those modes and the Green's function h (the "level" of the surface against
the pin) and runs CG on the N-orthogonal complement (measured on the σ right-hand sides of the
Table 1 frame: docs/benchmarks.md, "`evaluate --method least_squares` end to end (lsq25h)").
First written as benchmarks/deflation_prototype.py (which times it on one integration).

The basis is separable, W = {U_r(v) V_s(u)} ∪ {h}, U, V the orthonormal DCT-II vectors, all
restricted to the unknowns. Nothing of size N·W is stored: E = WᵀNW is formed from the padded
operator arrays by sums over the basis' pair products (:meth:`LowModes.prepare`), and the
projections Wᵀ(N z − r) that every iteration needs are accumulated in the pass that scatters z
and forms N z (:func:`_scatter_project`), per row (T = y V, then Uᵀ T), and W μ is formed row by
row in the passes that use z − W μ (it is never stored).
"""

from __future__ import annotations

import numba
import numpy as np

from .poisson import DCTLaplacian, _DCTWork, _finish_step, _update_gather

__all__: list[str] = []


#: Row and column DCT modes deflated (the lowest 4 × 6, plus the Green's function at the seed).
DEFLATION_MODES = (4, 6)


def _dct_basis(n: int, m: int) -> np.ndarray:
    """The m lowest orthonormal DCT-II basis vectors of length n, as columns (n, m)."""
    i = np.arange(n)[:, None] + 0.5
    B = np.cos(np.pi * i * np.arange(m)[None, :] / n) * np.sqrt(2.0 / n)
    B[:, 0] = np.sqrt(1.0 / n)
    return B


@numba.njit(cache=True, nogil=True, inline="always")
def _row_sums(y, VT, h, w, T, th, v):
    """T[v, s] = Σ_u y[u] VT[s, u] and th[v] = Σ_u y[u] h[w, u + 1] (y (W,); reassociated in
    the ``fastmath`` callers)."""
    for s in range(VT.shape[0]):
        a = 0.0
        for u in range(y.shape[0]):
            a += y[u] * VT[s, u]
        T[v, s] = a
    a = 0.0
    for u in range(1, y.shape[0] + 1):
        a += y[u - 1] * h[w, u]
    th[v] = a


@numba.njit(cache=True, nogil=True, inline="always", fastmath=True)
def _project_row(F, G, VT, h, matvec, D, Ex, Ey, T, th, v, y):
    """Row v of :func:`_project` (y: a row buffer (W,))."""
    Wp = F.shape[1]
    m2 = VT.shape[0]
    w = v + 1
    if matvec > 0:
        for u in range(1, Wp - 1):
            y[u - 1] = (D[w, u] * F[w, u] - Ex[w, u - 1] * F[w, u - 1] - Ex[w, u] * F[w, u + 1]
                        - Ey[w - 1, u] * F[w - 1, u] - Ey[w, u] * F[w + 1, u])
        if matvec == 2:
            for u in range(1, Wp - 1):
                y[u - 1] -= G[w, u]
    else:
        for u in range(1, Wp - 1):
            y[u - 1] = F[w, u]
    _row_sums(y, VT, h, w, T, th, v)


@numba.njit(cache=True, parallel=True, fastmath=True)
def _project(F, G, VT, h, matvec, D, Ex, Ey, T, th):
    """Per row v of the padded field y (``matvec`` 0: y = F, 1: N F, 2: N F − G; F float64):
    T[v, s] = Σ_u y V[u, s] (VT = Vᵀ, (m2, W)) and th[v] = Σ_u y h (h padded). The row sums
    are reassociated (``fastmath``, vectorised): they only choose the deflation's coefficients,
    whose round-off CG corrects like any other error."""
    for v in numba.prange(0, F.shape[0] - 2):
        _project_row(F, G, VT, h, matvec, D, Ex, Ey, T, th, v, np.empty(F.shape[1] - 2))


@numba.njit(cache=True, nogil=True, inline="always")
def _expansion_row(U, VT, mu, v, c, g):
    """g (W,) = row v of Σ_rs mu[r, s] U_r V_s (U (H, m1), VT (m2, W); c (m2,) work space):
    per column s the row's coefficient c_s = Σ_r U[v, r] mu[r, s], then Σ_s c_s VT[s]."""
    m1 = U.shape[1]
    m2 = VT.shape[0]
    for s in range(m2):
        a = 0.0
        for r in range(m1):
            a += U[v, r] * mu[r, s]
        c[s] = a
    for u in range(g.shape[0]):
        g[u] = 0.0
    for s in range(m2):
        cs = c[s]
        for u in range(g.shape[0]):
            g[u] += cs * VT[s, u]


@numba.njit(cache=True, nogil=True, inline="always")
def _deflated_rows(y, y0, from_y, unknown, U, VT, mu, mu_h, h, w, out, c, g):
    """Rows w − 1, w, w + 1 of the padded field z − (Σ_rs mu[r, s] U_r V_s + mu_h h) on the
    unknowns, 0 elsewhere, into out (3, W + 2) (its padding columns 0); z = y − y0 (single
    precision, y unpadded (H, W)) if ``from_y``, else z = 0. The padding rows give 0."""
    Hp, Wp = unknown.shape
    for k in range(3):
        ww = w - 1 + k
        out[k, 0] = 0.0
        out[k, Wp - 1] = 0.0
        if ww == 0 or ww == Hp - 1:
            for u in range(1, Wp - 1):
                out[k, u] = 0.0
            continue
        _expansion_row(U, VT, mu, ww - 1, c, g)
        # (every term formed, then selected: the loops vectorise)
        if from_y:
            for u in range(1, Wp - 1):
                t = float(y[ww - 1, u - 1] - y0) - (g[u - 1] + mu_h * h[ww, u])
                out[k, u] = t if unknown[ww, u] else 0.0
        else:
            for u in range(1, Wp - 1):
                t = 0.0 - (g[u - 1] + mu_h * h[ww, u])
                out[k, u] = t if unknown[ww, u] else 0.0


@numba.njit(cache=True, nogil=True, fastmath=True)
def _nz_row_sums(F, G, VT, h, D, Ex, Ey, T, th, v, y):
    """Row v of :func:`_project` (``matvec`` 2) for F the rows v, v + 1, v + 2 of the padded
    field (3, W + 2): y = (N F − G) on row v + 1, then T[v] and th[v], the same sums in the
    same (reassociated) form. Not inlined: it keeps ``fastmath`` inside a strict kernel."""
    Wp = F.shape[1]
    m2 = VT.shape[0]
    w = v + 1
    for u in range(1, Wp - 1):
        y[u - 1] = (D[w, u] * F[1, u] - Ex[w, u - 1] * F[1, u - 1] - Ex[w, u] * F[1, u + 1]
                    - Ey[w - 1, u] * F[0, u] - Ey[w, u] * F[2, u])
    for u in range(1, Wp - 1):
        y[u - 1] -= G[w, u]
    _row_sums(y, VT, h, w, T, th, v)


@numba.njit(cache=True, parallel=True)
def _scatter_project(R, y, y0, unknown, D, Ex, Ey, VT, h, T, th):
    """The preconditioned residual z = y − y0 on the unknowns (0 elsewhere; y (H, W) and y0
    single precision, the difference formed in single precision) and, in the same pass, the
    deflation's projections of N z − R (T, th as :func:`_project`): returns (R·z, max |z|) as
    ``poisson._scatter_dot_max``, whose field Z is not written (every later pass forms z from
    y again). Each row forms z on its neighbour rows itself (no dependencies between threads)."""
    Hp, Wp = unknown.shape
    s = 0.0
    m = 0.0
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        zb = np.zeros((3, Wp), dtype=np.float32)
        for k in range(3):
            ww = w - 1 + k
            if ww == 0 or ww == Hp - 1:
                continue
            for u in range(1, Wp - 1):
                t = y[ww - 1, u - 1] - y0
                zb[k, u] = t if unknown[ww, u] else np.float32(0.0)
        mr = 0.0
        for u in range(1, Wp - 1):
            z = float(zb[1, u])
            s += R[w, u] * z
            mr = max(mr, abs(z))
        m = max(m, mr)
        _nz_row_sums(zb, R, VT, h, D, Ex, Ey, T, th, v, np.empty(Wp - 2))
    return s, m


@numba.njit(cache=True, parallel=True)
def _start(D, Ex, Ey, b, U, VT, mu, mu_h, h, unknown, X, R, buf, store_x):
    """x₀ = −(Σ_rs mu[r, s] U_r V_s + mu_h h) on the unknowns (0 elsewhere) into X (if
    ``store_x``; else :func:`_finish_deflated` forms it again) and r₀ = b − N x₀ into R and
    (single precision) into buf, in one parallel pass over the interior:
    each row forms x₀ on its neighbour rows itself (:func:`_deflated_rows`, the sums of the
    expansion; the padding of X and R is left as it is, 0)."""
    Hp, Wp = D.shape
    m2 = VT.shape[0]
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        xr = np.empty((3, Wp))
        _deflated_rows(buf, np.float32(0.0), False, unknown, U, VT, mu, mu_h, h, w, xr, np.empty(m2), np.empty(Wp - 2))
        for u in range(1, Wp - 1):
            x = xr[1, u]
            if store_x:
                X[w, u] = x
            r = (b[w, u] - D[w, u] * x + Ex[w, u - 1] * xr[1, u - 1] + Ex[w, u] * xr[1, u + 1]
                 + Ey[w - 1, u] * xr[0, u] + Ey[w, u] * xr[2, u])
            R[w, u] = r
            buf[v, u - 1] = r


@numba.njit(cache=True, parallel=True)
def _direction_deflated(D, Ex, Ey, y, y0, unknown, U, VT, mu, mu_h, h, P, AP, beta, X, alpha):
    """``poisson._direction_matvec`` for Z the deflated preconditioned residual z −
    (Σ_rs mu[r, s] U_r V_s + mu_h h) (z = y − y0 on the unknowns, :func:`_scatter_project`),
    formed row by row (:func:`_deflated_rows`) instead of read: X += αP (α ≠ 0), P = Z + βP,
    AP = N Z + β·AP (β = 0: P and AP not read). Returns (P·AP, max |Z|)."""
    Hp, Wp = D.shape
    m2 = VT.shape[0]
    s = 0.0
    m = 0.0
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        zr = np.empty((3, Wp))
        _deflated_rows(y, y0, True, unknown, U, VT, mu, mu_h, h, w, zr, np.empty(m2), np.empty(Wp - 2))
        mr = 0.0
        for u in range(1, Wp - 1):
            z = zr[1, u]
            mr = max(mr, abs(z))
            t = (D[w, u] * z - Ex[w, u - 1] * zr[1, u - 1] - Ex[w, u] * zr[1, u + 1]
                 - Ey[w - 1, u] * zr[0, u] - Ey[w, u] * zr[2, u])
            if alpha != 0.0:  # loop-invariant (unswitched): no X traffic on a solve's first pass
                X[w, u] += alpha * P[w, u]
            if beta != 0.0:
                p = z + beta * P[w, u]
                a = t + beta * AP[w, u]
            else:
                p = z
                a = t
            P[w, u] = p
            AP[w, u] = a
            s += p * a
        m = max(m, mr)
    return s, m


@numba.njit(cache=True, parallel=True)
def _finish_deflated(X, P, alpha, y, y0, unknown, U, VT, mu, mu_h, h, S, acc, mode, mu0, mu0_h, x_implicit):
    """With Z the deflated preconditioned residual (:func:`_direction_deflated`), formed row by
    row: ``mode`` 0: only max |Z|; 1: X = (X + αP) + Z (rounded as ``poisson._finish_step``
    then X += Z); 2: x = (X + αP) + Z not stored, acc += x² on S (H, W) instead (as
    ``uncertainty_solve._accumulate_sq``); 3: X = x₀ only. With ``x_implicit`` X is not read:
    it is x₀ = −(Σ_rs mu0[r, s] U_r V_s + mu0_h h) (not stored by :func:`_start`), formed again
    with its sums. Returns (max |Z|, the number of non-finite x on S (mode 2))."""
    Hp, Wp = X.shape
    m2 = VT.shape[0]
    m = 0.0
    bad = 0
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        c = np.empty(m2)
        g = np.empty(Wp - 2)
        g0 = np.empty(Wp - 2)
        _expansion_row(U, VT, mu, v, c, g)
        for u in range(1, Wp - 1):  # g = the row of Z (the terms formed, then selected: vectorised)
            t = float(y[v, u - 1] - y0) - (g[u - 1] + mu_h * h[w, u])
            g[u - 1] = t if unknown[w, u] else 0.0
        if x_implicit and mode != 0:  # g0 = the row of x₀
            _expansion_row(U, VT, mu0, v, c, g0)
            for u in range(1, Wp - 1):
                t = 0.0 - (g0[u - 1] + mu0_h * h[w, u])
                g0[u - 1] = t if unknown[w, u] else 0.0
        else:
            for u in range(1, Wp - 1):
                g0[u - 1] = X[w, u]
        mr = 0.0
        br = 0
        if mode == 0:
            for u in range(Wp - 2):
                mr = max(mr, abs(g[u]))
        elif mode == 1:
            for u in range(1, Wp - 1):
                x = g0[u - 1] + alpha * P[w, u]
                x += g[u - 1]
                X[w, u] = x
        elif mode == 3:
            for u in range(1, Wp - 1):
                X[w, u] = g0[u - 1]
        else:
            for u in range(1, Wp - 1):
                x = g0[u - 1] + alpha * P[w, u]
                x += g[u - 1]
                on = S[v, u - 1]
                a = acc[v, u - 1]
                acc[v, u - 1] = a + x * x if on else a
                br += 0 if np.isfinite(x) or not on else 1
        m = max(m, mr)
        bad += br
    return m, bad


@numba.njit(cache=True, parallel=True)
def _masked_padded_kernel(g, unknown, out):
    Hp, Wp = out.shape
    for v in numba.prange(0, Hp):
        for u in range(Wp):
            out[v, u] = g[v - 1, u - 1] if unknown[v, u] else 0.0


def _masked_padded(g, unknown, out=None):
    """g (H, W) (float32) as a padded float32 field, 0 off the unknowns (into ``out`` if it
    fits)."""
    if out is None or out.shape != unknown.shape:
        out = np.empty(unknown.shape, dtype=np.float32)
    _masked_padded_kernel(g, unknown, out)
    return out


#: Column blocks of :func:`_galerkin_sums` (a constant: the sums do not depend on the threads).
_GALERKIN_BLOCKS = 16


@numba.njit(cache=True, parallel=True, fastmath=True)
def _galerkin_sums(D, Ex, Ey, PA, PAy, PB, PBx):
    """E's separable sums (m1², m2²): PAᵀ D PB − PAᵀ Ex PBx − PAyᵀ Ey PB over the interior of
    the padded arrays (PA, PAy (H, m1²); PB, PBx (W, m2²)). Each of :data:`_GALERKIN_BLOCKS`
    column blocks accumulates the row products PAᵀ D over its columns (axpys along the
    contiguous rows, no BLAS threads), then multiplies by PB; the blocks are summed in order."""
    Hp, Wp = D.shape
    H, W = Hp - 2, Wp - 2
    ka, kb = PA.shape[1], PB.shape[1]
    nb = min(_GALERKIN_BLOCKS, W)
    part = np.zeros((nb, ka, kb))
    for blk in numba.prange(0, nb):
        u0 = blk * W // nb
        u1 = (blk + 1) * W // nb
        n = u1 - u0
        aD = np.zeros((ka, n))
        aX = np.zeros((ka, n))
        aY = np.zeros((ka, n))
        for v in range(H):
            for k in range(ka):
                pa = PA[v, k]
                py = PAy[v, k]
                for j in range(n):
                    aD[k, j] += pa * D[v + 1, u0 + j + 1]
                    aX[k, j] += pa * Ex[v + 1, u0 + j + 1]
                    aY[k, j] += py * Ey[v + 1, u0 + j + 1]
        for k in range(ka):
            for m in range(kb):
                acc = 0.0
                for j in range(n):
                    acc += (aD[k, j] - aY[k, j]) * PB[u0 + j, m] - aX[k, j] * PBx[u0 + j, m]
                part[blk, k, m] = acc
    out = np.zeros((ka, kb))
    for blk in range(nb):
        out += part[blk]
    return out


class LowModes:
    """The deflation space W of one grid and gauge pixel (module docstring) and, after
    :meth:`prepare`, E = WᵀNW of one operator."""

    def __init__(self, shape, pinned, modes=DEFLATION_MODES, lap=None):
        H, W = (int(n) for n in shape)
        m1, m2 = min(int(modes[0]), H), min(int(modes[1]), W)
        self.shape = (H, W)
        self.U = _dct_basis(H, m1)
        self.VT = np.ascontiguousarray(_dct_basis(W, m2).T)
        V = self.VT.T
        # pair products of the basis vectors for E's separable sums (rows: pixels)
        Un = np.vstack([self.U[1:], np.zeros((1, m1))])
        Vn = np.vstack([V[1:], np.zeros((1, m2))])
        self._PA = (self.U[:, :, None] * self.U[:, None, :]).reshape(H, m1 * m1)
        self._PAy = (self.U[:, :, None] * Un[:, None, :] + Un[:, :, None] * self.U[:, None, :]).reshape(H, m1 * m1)
        self._PB = (V[:, :, None] * V[:, None, :]).reshape(W, m2 * m2)
        self._PBx = (V[:, :, None] * Vn[:, None, :] + Vn[:, :, None] * V[:, None, :]).reshape(W, m2 * m2)
        # h: the Neumann Laplacian's Green's function at the pin, L⁺(e_s − 1/n) up to a constant
        # (W holds the constants): the pinned solver's y for r = −1/n off the pin (it sets r_s
        # to minus the others' sum, 1 − 1/n).
        if lap is None or tuple(lap.shape) != (H, W) or tuple(lap.pinned) != (int(pinned[0]), int(pinned[1])):
            lap = DCTLaplacian((H, W), pinned, dtype=np.float32)
        self._g = lap.solve(np.full((H, W), -1.0 / (H * W), dtype=lap.dtype), overwrite=True, pin=False)
        self.T = np.zeros((H, m2))
        self.th = np.zeros(H)

    def prepare(self, D, Ex, Ey, unknown):
        """E = WᵀNW for the padded operator (D, Ex, Ey), its unknowns ``unknown`` (padded)."""
        H, W = self.shape
        m1, m2 = self.U.shape[1], self.VT.shape[0]
        self.h = _masked_padded(self._g, unknown, getattr(self, "h", None))
        # Σ D φφ' − Σ_x-edges Ex (φ(u)φ'(u+1) + φ(u+1)φ'(u)) − Σ_y-edges Ey (…): the stored
        # arrays are 0 at and around pixels that are not unknowns, so φ is restricted to them.
        Ecc = _galerkin_sums(D, Ex, Ey, self._PA, self._PAy, self._PB, self._PBx)
        Ecc = Ecc.reshape(m1, m1, m2, m2).transpose(0, 2, 1, 3).reshape(m1 * m2, m1 * m2)
        h64 = self.h.astype(np.float64)  # (h itself is kept in single precision, as computed)
        _project(h64, h64, self.VT, self.h, 1, D, Ex, Ey, self.T, self.th)
        del h64
        Ech = (self.U.T @ self.T).reshape(m1 * m2)
        n = m1 * m2 + 1
        E = np.empty((n, n))
        E[:-1, :-1] = 0.5 * (Ecc + Ecc.T)
        E[:-1, -1] = E[-1, :-1] = Ech
        E[-1, -1] = self.th.sum()
        # The constant lies in both the mode (0, 0) and h's span only through the restriction;
        # a semi-definite E (round-off) is solved by least squares.
        self.E_inv = np.linalg.pinv(E, hermitian=True)

    def coefficients(self, b, D, Ex, Ey):
        """μ = E⁻¹ Wᵀ b for a padded float64 field b: (mu (m1, m2), mu_h)."""
        _project(b, b, self.VT, self.h, 0, D, Ex, Ey, self.T, self.th)
        return self.projected()

    def projected(self):
        """μ = E⁻¹ (Uᵀ T, Σ th) of the projections last written to T, th (:func:`_project`,
        :func:`_scatter_project`): (mu (m1, m2), mu_h)."""
        c = np.append((self.U.T @ self.T).ravel(), self.th.sum())
        mu = self.E_inv @ c
        return np.ascontiguousarray(mu[:-1].reshape(self.U.shape[1], self.VT.shape[0])), float(mu[-1])


def deflated_dct_pcg(D, Ex, Ey, b, pinned, atol, rtol, max_iter, *, cap=np.inf, lap=None, work=None,
                     modes=None, unknown=None, acc=None, on=None):
    """Deflated CG for N x = b on a full frame (one right-hand side), preconditioned by the
    pinned Laplacian's DCT inverse in single precision (:func:`pmdsim.evaluation.poisson.dct_pcg`),
    the deflation space W of ``modes`` (:class:`LowModes`; created and prepared for N if not
    given, prepared if it was not) solved
    exactly: x₀ = W E⁻¹ Wᵀ b, then CG with directions N-orthogonal to W, their preconditioned
    residuals z deflated, z − W E⁻¹ WᵀN z.

    Stops when the max-norm of the deflated preconditioned residual (the estimate of the error)
    is below ``max(atol, min(rtol · its initial value, cap))`` and adds it to x, as ``dct_pcg``.
    Arguments as :func:`pmdsim.evaluation.poisson.dct_pcg` with b (H + 2, W + 2) and ``work`` a
    :class:`pmdsim.evaluation.poisson._DCTWork` for one field (its X, R, P, AP and buf; created
    if missing). Returns (x, iterations, converged); x is ``work.X[0]``. With ``acc`` (H, W)
    and ``on`` (H, W) bool, a converged x is not stored: x² is added to ``acc`` on ``on`` (the
    σ's sum of squares, :mod:`pmdsim.evaluation.uncertainty_solve`) and the first item returned
    is instead whether every such x was finite.

    The passes (docs/benchmarks.md, lsq26): the deflated residual W-part is never stored — the
    preconditioner's output y is scattered and projected (WᵀN z, Wᵀr) in one pass
    (:func:`_scatter_project`), and z − W μ is formed row by row where it is used (x₀ and r₀:
    :func:`_start`; the direction and N p: :func:`_direction_deflated`; the stopping test and
    the final x += z: :func:`_finish_deflated`), with the sums of the separate passes it
    replaces (the same iterates)."""
    Hp, Wp = D.shape
    if lap is None:
        lap = DCTLaplacian((Hp - 2, Wp - 2), pinned, dtype=np.float32)
    if unknown is None:
        unknown = D > 0.0
    if modes is None:
        modes = LowModes((Hp - 2, Wp - 2), pinned, lap=lap)
    if getattr(modes, "E_inv", None) is None:  # not prepared (a prepared one is for this operator)
        modes.prepare(D, Ex, Ey, unknown)
    if work is None:
        work = _DCTWork(1, D.shape)
    X, R, P, AP, buf = work.X[0], work.R[0], work.P[0], work.AP[0], work.buf[0]
    U, VT, h = modes.U, modes.VT, modes.h
    if acc is None:
        acc, on, mode = np.zeros((1, 1)), np.zeros((1, 1), dtype=np.bool_), 1
    else:
        mode = 2
    # x₀ = W E⁻¹ Wᵀ b, r₀ = b − N x₀ (0 off the unknowns: b is, and N has no couplings there)
    mu, mu_h = modes.coefficients(b, D, Ex, Ey)
    mu0, mu0_h = -mu, -mu_h
    x_implicit = mode == 2  # x₀ formed again where it is read (18 MB less; its pages never touched)
    _start(D, Ex, Ey, b, U, VT, mu0, mu0_h, h, unknown, X, R, buf, not x_implicit)

    def precondition(total):  # y = L_s⁻¹ r; z = y − y_s, rz = r·z; μ of z − W E⁻¹ Wᵀ(N z − r)
        y = lap.solve(buf[None], overwrite=True, totals=np.array([total]), pin=False)[0]
        y0 = y[lap.pinned]
        rz, _ = _scatter_project(R, y, y0, unknown, D, Ex, Ey, VT, h, modes.T, modes.th)
        return (y, y0) + modes.projected() + (rz,)

    y, y0, mu, mu_h, rz = precondition(float(np.sum(R)))
    # the first direction pass is run before the stopping test (it also gives the test's max):
    # with α = 0 it leaves X as it is, and only a zero residual stops before it
    pAp, zmax = _direction_deflated(D, Ex, Ey, y, y0, unknown, U, VT, mu, mu_h, h, P, AP, 0.0, X, 0.0)
    tol = max(atol, min(rtol * zmax, cap))
    beta = 0.0
    alpha = 0.0  # the last step, X += αP, is deferred to the next direction pass or the end
    its = 0
    while True:
        if zmax <= tol:
            _, bad = _finish_deflated(X, P, alpha, y, y0, unknown, U, VT, mu, mu_h, h, on, acc, mode, mu0, mu0_h,
                                      x_implicit)
            return (X if mode == 1 else bad == 0), its, True
        if its >= max_iter:
            _finish_step(X, P, alpha, buf, False)
            return (X if mode == 1 else False), its, False
        if its > 0:  # (applies the last step)
            if x_implicit:  # X = x₀ first
                _finish_deflated(X, P, alpha, y, y0, unknown, U, VT, mu, mu_h, h, on, acc, 3, mu0, mu0_h, True)
                x_implicit = False
            pAp, _ = _direction_deflated(D, Ex, Ey, y, y0, unknown, U, VT, mu, mu_h, h, P, AP, beta, X, alpha)
        if not (pAp > 0.0 and rz > 0.0):  # breakdown (round-off at convergence)
            return (X if mode == 1 else False), its, False
        alpha = rz / pAp
        total = _update_gather(R, AP, alpha, buf)
        its += 1
        rz_old = rz
        y, y0, mu, mu_h, rz = precondition(total)
        beta = rz / rz_old
        zmax, _ = _finish_deflated(X, P, alpha, y, y0, unknown, U, VT, mu, mu_h, h, on, acc, 0, mu0, mu0_h, x_implicit)
