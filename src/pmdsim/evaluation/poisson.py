"""DCT Poisson solver and DCT-preconditioned conjugate gradients for the least-squares
integration's normal equations (issue 25 item 3).

On the full H×W rectangle, the unit-weight 5-point Neumann Laplacian L (the normal equations of
the forward-difference least-squares integration with all weights 1) is diagonalised by the
orthonormal 2-D DCT-II (Strang 1999, "The discrete cosine transform", SIAM Rev. 41, 135):

    L = Cᵀ diag(λ) C,   λ_jk = (2 − 2 cos(π j / H)) + (2 − 2 cos(π k / W)),

with the constants as its null space (λ_00 = 0). The gauge of the integration fixes one pixel
(the seed s, which is not an unknown); :class:`DCTLaplacian` solves the Laplacian with that
pixel removed, L_s x = r, exactly: y = L⁺ (r − (Σ r) e_s) (a consistent right-hand side),
x = y − y_s (see :meth:`DCTLaplacian.solve`). It transforms along the rows only (the DCT
along the contiguous axis, the faster one) and solves the remaining tridiagonal systems
(L_H + μ_k I) y_k = f_k along the columns, one per row frequency k (μ_k = 2 − 2 cos(π k / W),
L_H the 1-D Neumann Laplacian), by forward and back substitution with pivots computed once
(:func:`_column_pivots`): the same L⁺ up to a constant (removed by the gauge), at 0.8× the
time of the 2-D transform pair.

The Gauss–Newton matrix N = Jᵀ J that the integration actually assembles
(:func:`pmdsim.evaluation.least_squares._assemble_gauss_newton`) is not L: its edge weights
−J_a J_b are 1 + O(slope · ray obliquity) (≤ 6e-4 off for Table 1) and its row sums are not 0
(Robin-type terms ≈ 5e-4 on the border from the slopes' dependence on the heights). Per pixel
the difference is small, but for the smoothest modes it is of the order of L itself, so L_s⁻¹
is used as the preconditioner of CG for N (:func:`dct_pcg`), never as its solution; on a
masked domain (pixels with D = 0 are not unknowns) the preconditioner is P L_s⁻¹ P with P the
restriction to the unknowns (symmetric positive definite there).

Storage of N: the padded 5-point arrays of :mod:`pmdsim.evaluation.multigrid` (D, Ex, Ey of
shape (H + 2, W + 2)); vectors are padded the same way, stacked as (k, H + 2, W + 2) for k
right-hand sides solved together (:func:`dct_pcg`).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["DCTLaplacian", "dct_pcg", "prefers_dct"]


#: The DCT preconditioner is chosen when at least this fraction of the frame are unknowns and
#: the frame has at least :data:`DCT_MIN_PIXELS` pixels: on masked domains the multigrid
#: preconditioner needs fewer iterations, and on small grids the compiled multigrid CG's lower
#: overhead per iteration wins (measured: docs/benchmarks.md, "Integration:
#: DCT-preconditioned solve").
DCT_MIN_FILL = 0.999

DCT_MIN_PIXELS = 100_000


def prefers_dct(unknowns: int, shape) -> bool:
    """Whether CG on ``unknowns`` of an H×W frame is preconditioned by the DCT (see
    :data:`DCT_MIN_FILL`) rather than by multigrid."""
    n = int(shape[0]) * int(shape[1])
    return n >= DCT_MIN_PIXELS and unknowns >= DCT_MIN_FILL * n


class DCTLaplacian:
    """Exact solver of the unit-weight Neumann 5-point Laplacian on an H×W grid with one pixel
    pinned at 0 (L_s⁻¹, module docstring), for one field (H, W) or a stack (k, H, W).

    Parameters
    ----------
    shape : tuple (H, W)
    pinned : tuple of int
        (row, column) of the pixel that is not an unknown (the seed).
    dtype : numpy float dtype
        float64 (relative error ≈ 2e-11 at 1920×1200, from the substitutions' recurrences) or
        float32 (the transforms and substitutions in single precision: about 2× faster,
        relative error ≈ 4e-7, as the 2-D transforms in single precision; for
        preconditioning).
    workers : int, optional
        scipy.fft workers; default: numba's thread count at each :meth:`solve`
        (``numba.get_num_threads()``; the rows' transforms split between the threads give the
        same values as on one).
    """

    def __init__(self, shape, pinned, dtype=np.float64, workers=None):
        H, W = (int(n) for n in shape)
        self.shape = (H, W)
        self.pinned = (int(pinned[0]), int(pinned[1]))
        self.dtype = np.dtype(dtype)
        self.workers = None if workers is None else int(workers)
        self.inv_pivots = np.empty((H, W), dtype=self.dtype)
        self.pivot_tail = np.empty(W, dtype=self.dtype)
        self.pivot_cut = np.empty(H, dtype=np.int64)
        _column_pivots(self.inv_pivots, self.pivot_tail, self.pivot_cut)

    def solve(self, r, overwrite: bool = False, totals=None, pin: bool = True) -> np.ndarray:
        """x = L_s⁻¹ r for r (H, W) or (k, H, W) (r at the pinned pixel is ignored; x is 0
        there). Returns an array of ``dtype``. ``overwrite`` lets it use r (of ``dtype``) as
        work space; ``totals`` (scalar or (k,)): Σ r over the other pixels, if known; ``pin``
        False: y, of which x = y − y_s (the caller subtracts y_s, in ``dtype``)."""
        sv, su = self.pinned
        # overwrite: r itself when it is already of ``dtype`` (else a converted copy, as numpy ≥ 2 requires)
        x = np.asarray(r, dtype=self.dtype) if overwrite else np.array(r, dtype=self.dtype)
        if totals is None:
            x[..., sv, su] = 0.0
            totals = x.sum(axis=(-2, -1), dtype=np.float64)
        x[..., sv, su] = -np.asarray(totals)  # a consistent right-hand side: Σ = 0
        import scipy.fft  # here, not at import: not on evaluate's start-up path

        threads = numba.get_num_threads()
        workers = threads if self.workers is None else self.workers
        f = np.ascontiguousarray(scipy.fft.dct(x, type=2, norm="ortho", axis=-1, workers=workers, overwrite_x=True))
        _column_substitution(f.reshape((-1,) + self.shape), self.inv_pivots, self.pivot_tail, self.pivot_cut, threads)
        y = scipy.fft.idct(f, type=2, norm="ortho", axis=-1, workers=workers, overwrite_x=True)
        if pin:
            y -= y[..., sv, su][..., None, None]
        return y


@numba.njit(cache=True)
def _column_pivots(im, tail, cut):
    """1/m (H, W), m the pivots of the LU factorisation of L_H + μ_k I per row frequency k
    (column k): m_0 = 1 + μ_k, m_v = 2 + μ_k − 1/m_{v−1}, the last row 1 + μ_k − 1/m_{H−2}
    (Neumann ends; H = 1: μ_k). For k = 0 the last pivot is 0 (L_H is singular, its null space
    the constants): 1/m is set to 0 there, which picks the solution with y_{H−1} = 0 of the
    consistent system. Written to ``im`` (H, W) (float32 or float64; computed in float64).

    The recurrence converges to its fixed point within a few rows except for the smallest
    frequencies (at 1920×1200 in float32, 1.6 % of the values differ from their column's
    limit): ``tail`` (W,) receives row H − 2 (row 0 if H = 1), and ``cut`` (H,) the column
    bound per row: in row v < H − 1, every column u ≥ cut[v] holds tail[u] exactly (as
    stored); cut[H − 1] = W (:func:`_column_substitution` reads ``im`` only left of it)."""
    H, W = im.shape
    mu = 2.0 - 2.0 * np.cos(np.pi * np.arange(W) / W)
    prev = np.zeros(W)
    last = np.zeros(W, dtype=np.int64)  # per column: the first row of the run equal to row H − 2
    for v in range(H):  # rows outer: the columns' recurrences are independent (vectorised)
        c = 0.0 if H == 1 else (1.0 if v == 0 or v == H - 1 else 2.0)
        for u in range(W):
            m = mu[u] + c - prev[u]
            prev[u] = 1.0 / m if m != 0.0 else 0.0
            im[v, u] = prev[u]
            if 0 < v < H - 1 and im[v, u] != im[v - 1, u]:
                last[u] = v
    im[H - 1, 0] = 0.0
    tail[:] = im[max(H - 2, 0)]
    cut[:] = 0
    for u in range(W):  # cut[v] = 1 + the largest u with last[u] > v
        if last[u] > 0:
            cut[last[u] - 1] = u + 1
    for v in range(H - 2, -1, -1):
        cut[v] = max(cut[v], cut[v + 1])
    cut[H - 1] = W


@numba.njit(cache=True, parallel=True)
def _column_substitution(f, im, tail, cut, n_chunks):
    """In place, f (k, H, W) → y with (L_H + μ_j I) y[:, :, j] = f[:, :, j] for every column
    j (pivots of :func:`_column_pivots`; :func:`_substitute_columns`); the columns split into
    ``n_chunks`` blocks per field run in parallel."""
    K, H, W = f.shape
    cw = (W + n_chunks - 1) // n_chunks
    for t in numba.prange(0, K * n_chunks):
        u0 = (t % n_chunks) * cw
        _substitute_columns(f[t // n_chunks], im, tail, cut, u0, min(W, u0 + cw))


@numba.njit(cache=True)
def _substitute_columns(x, im, tail, cut, u0, u1):
    """Columns u0 ≤ u < u1 of x (H, W), in place: forward, g_v = (f_v + g_{v−1})/m_v, then
    back, y_v = g_v + y_{v+1}/m_v, row by row, the inverse pivots 1/m read as im[v, u] left of
    cut[v] and as tail[u] (the same value) right of it: ``im`` is read only where the
    recurrence has not converged. The loops run over row slices from 0 (outside a parallel
    loop's body, with indices known to be non-negative, they vectorise: 5× faster than the
    same loops indexed from u0 in the body of the prange)."""
    H = x.shape[0]
    for v in range(H):
        c = min(max(cut[v], u0), u1)
        xa, ia, xb, tb = x[v, u0:c], im[v, u0:c], x[v, c:u1], tail[c:u1]
        if v == 0:
            for j in range(0, xa.size):
                xa[j] = xa[j] * ia[j]
            for j in range(0, xb.size):
                xb[j] = xb[j] * tb[j]
        else:
            ga, gb = x[v - 1, u0:c], x[v - 1, c:u1]
            for j in range(0, xa.size):
                xa[j] = (xa[j] + ga[j]) * ia[j]
            for j in range(0, xb.size):
                xb[j] = (xb[j] + gb[j]) * tb[j]
    for v in range(H - 2, -1, -1):
        c = min(max(cut[v], u0), u1)
        xa, ia, ya, xb, tb, yb = x[v, u0:c], im[v, u0:c], x[v + 1, u0:c], x[v, c:u1], tail[c:u1], x[v + 1, c:u1]
        for j in range(0, xa.size):
            xa[j] = xa[j] + ya[j] * ia[j]
        for j in range(0, xb.size):
            xb[j] = xb[j] + yb[j] * tb[j]


@numba.njit(cache=True, parallel=True)
def _direction_matvec(D, Ex, Ey, Z, P, AP, beta, X, alpha):
    """X += αP (the previous iteration's step, deferred to this pass, which reads P anyway;
    skipped for α = 0, the first pass, as adding 0·P leaves X unchanged), then P = Z + βP and AP = N P as N Z + β·AP (N P_old is AP already: one pass, no row
    dependencies between threads); returns P·AP. Padded (H + 2, W + 2) fields."""
    Hp, Wp = D.shape
    s = 0.0
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        for u in range(1, Wp - 1):
            y = (D[w, u] * Z[w, u] - Ex[w, u - 1] * Z[w, u - 1] - Ex[w, u] * Z[w, u + 1]
                 - Ey[w - 1, u] * Z[w - 1, u] - Ey[w, u] * Z[w + 1, u])
            q = P[w, u]
            if alpha != 0.0:  # loop-invariant (unswitched): no X traffic on a solve's first pass
                X[w, u] += alpha * q
            p = Z[w, u] + beta * q
            a = y + beta * AP[w, u]
            P[w, u] = p
            AP[w, u] = a
            s += p * a
    return s


@numba.njit(cache=True, parallel=True)
def _update_gather(R, AP, alpha, buf):
    """R −= αAP and buf = R's interior (single precision, for the transforms); returns Σ R
    (X += αP is deferred to the next :func:`_direction_matvec` or :func:`_finish_step`)."""
    Hp, Wp = R.shape
    s = 0.0
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        for u in range(1, Wp - 1):
            r = R[w, u] - alpha * AP[w, u]
            R[w, u] = r
            buf[v, u - 1] = r
            s += r
    return s


@numba.njit(cache=True, parallel=True)
def _finish_step(X, P, alpha, Z, add_z):
    """X += αP (the deferred last step), then X += Z if ``add_z`` (the last preconditioned
    residual of a converged solve), in one pass over the interior, rounded as the two
    separate updates."""
    Hp, Wp = X.shape
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        for u in range(1, Wp - 1):
            x = X[w, u] + alpha * P[w, u]
            if add_z:
                x += Z[w, u]
            X[w, u] = x


@numba.njit(cache=True, parallel=True)
def _start_fields(X, R, B, buf):
    """X = 0, R = B and buf = B's interior (single precision), in one pass."""
    Hp, Wp = X.shape
    for v in numba.prange(0, Hp):
        for u in range(Wp):
            X[v, u] = 0.0
            R[v, u] = B[v, u]
        if 0 < v < Hp - 1:
            for u in range(1, Wp - 1):
                buf[v - 1, u - 1] = B[v, u]


@numba.njit(cache=True, parallel=True)
def _scatter_dot_max(R, y, y0, unknown, Z):
    """Z = (y − y0) on the unknowns (0 elsewhere; y unpadded and y0 single precision, the
    difference formed in single precision, Z float32 or float64); returns (R·Z, max |Z|)."""
    Hp, Wp = Z.shape
    s = 0.0
    m = 0.0
    for v in numba.prange(0, Hp - 2):
        w = v + 1
        mr = 0.0
        for u in range(1, Wp - 1):
            z = float(y[v, u - 1] - y0) if unknown[w, u] else 0.0
            Z[w, u] = z
            s += R[w, u] * z
            mr = max(mr, abs(z))
        m = max(m, mr)
    return s, m


class _DCTWork:
    """Work arrays of :func:`dct_pcg` for k padded fields of one shape and the single-precision
    transform buffer, from ``zeros(shape, dtype)`` (default ``np.zeros``): X, R, P, AP in
    float64; the preconditioned residual Z in float32 (its values are differences formed in
    single precision, :func:`_scatter_dot_max`, so float32 holds them exactly and CG's float64
    arithmetic is unchanged, with half the bytes)."""

    def __init__(self, k, shape, zeros=np.zeros):
        # zeros(shape, dtype): zeroed arrays (a caller may hand out reused buffers instead)
        self.k = int(k)
        shape = (self.k,) + tuple(shape)
        self.X, self.R, self.P, self.AP = (zeros(shape, np.float64) for _ in range(4))
        self.Z = zeros(shape, np.float32)
        self.buf = zeros((self.k, shape[1] - 2, shape[2] - 2), np.float32)


def dct_pcg(D, Ex, Ey, B, pinned, atol, rtol, max_iter, *, cap=np.inf, lap=None, work=None, unknown=None):
    """Conjugate gradients for N X_i = B_i (k right-hand sides together), preconditioned by
    the pinned Neumann Laplacian's DCT inverse in single precision (module docstring; CG
    itself runs in float64).

    Stops each right-hand side when the max-norm of its preconditioned residual (an estimate
    of its error) is below ``max(atol, min(rtol · its initial value, cap))``, and adds that
    last preconditioned residual to it (as :func:`pmdsim.evaluation.multigrid._pcg`).

    Parameters
    ----------
    D, Ex, Ey : ndarray (H + 2, W + 2)
        The padded operator (:mod:`pmdsim.evaluation.multigrid`); D == 0 marks pixels that are
        not unknowns (``pinned`` must be one of them).
    B : ndarray (k, H + 2, W + 2)
        Right-hand sides (0 off the unknowns).
    pinned : tuple of int
        (row, column) of the gauge pixel, unpadded.
    atol, rtol, max_iter, cap
        As :func:`~pmdsim.evaluation.multigrid._pcg` (``max_iter`` per right-hand side).
    lap : DCTLaplacian, optional
        The preconditioner (float32; created if not given).
    work : _DCTWork, optional
        Work arrays for k fields (created if not given); X is ``work.X``.
    unknown : ndarray of bool (H + 2, W + 2), optional
        D > 0 (computed if not given).

    Returns
    -------
    X : ndarray (k, H + 2, W + 2)
    iterations : ndarray of int (k,)
    converged : ndarray of bool (k,)
    """
    k = B.shape[0]
    Hp, Wp = D.shape
    sv, su = int(pinned[0]), int(pinned[1])
    if lap is None:
        lap = DCTLaplacian((Hp - 2, Wp - 2), pinned, dtype=np.float32)
    if work is None or work.k < k or work.X.shape[1:] != D.shape:
        work = _DCTWork(k, D.shape)
    if unknown is None:
        unknown = D > 0.0
    X, R, Z, P, AP, buf = work.X[:k], work.R[:k], work.Z[:k], work.P[:k], work.AP[:k], work.buf[:k]
    rz = np.zeros(k)
    zmax = np.zeros(k)
    its = np.zeros(k, dtype=np.int64)
    converged = np.zeros(k, dtype=np.bool_)
    active = np.ones(k, dtype=np.bool_)
    sums = np.zeros(k)
    for i in range(k):
        _start_fields(X[i], R[i], B[i], buf[i])
        sums[i] = float(np.sum(R[i]))

    def precondition(idx):
        # L_s⁻¹ on the stacked residuals of idx (buf[idx] holds them, sums their totals).
        b = buf[idx] if idx.size < k else buf
        y = lap.solve(b, overwrite=True, totals=sums[idx], pin=False)  # the pin's y_s: subtracted below
        for j, i in enumerate(idx):
            rz[i], zmax[i] = _scatter_dot_max(R[i], y[j], y[j][lap.pinned], unknown, Z[i])

    precondition(np.arange(k))
    tol = np.maximum(atol, np.minimum(rtol * zmax, cap))
    beta = np.zeros(k)
    pAp = np.zeros(k)
    alpha = np.zeros(k)  # the step X += αP not yet applied (deferred to the next pass over P)
    while True:
        done = active & (zmax <= tol)
        converged |= done
        leaving = active & ~(~done & (its < max_iter))
        active &= ~done & (its < max_iter)
        for i in np.flatnonzero(leaving):
            _finish_step(X[i], P[i], alpha[i], Z[i], bool(done[i]))
            alpha[i] = 0.0
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        for i in idx:
            pAp[i] = _direction_matvec(D, Ex, Ey, Z[i], P[i], AP[i], beta[i], X[i], alpha[i])
            alpha[i] = 0.0
            if not (pAp[i] > 0.0 and rz[i] > 0.0):  # breakdown (round-off at convergence)
                active[i] = False
                continue
            alpha[i] = rz[i] / pAp[i]
            sums[i] = _update_gather(R[i], AP[i], alpha[i], buf[i])
            its[i] += 1
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        rz_old = rz.copy()
        precondition(idx)
        beta[idx] = rz[idx] / rz_old[idx]
    return X, its, converged
