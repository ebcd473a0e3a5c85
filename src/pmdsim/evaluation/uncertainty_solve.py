"""The least-squares height σ's sampled right-hand sides, solved in batches (issue 22 "Speed",
issue 25 item 3).

The K right-hand sides of the estimator (:mod:`pmdsim.evaluation.uncertainty`) share one
matrix, the Gauss–Newton matrix N of the reconstruction at convergence. A batch of
:data:`SIGMA_BATCH` of them is built in one parallel pass (:func:`_sampled_rhs`: the draws of
``uncertainty._sample_dg`` and the sums of ``uncertainty._ls_rhs``, bit for bit, without the
(H, W, 2) slope perturbations of each sample and with each edge's Jacobian formed once per
batch: 35 ms for two at 1920×1200 on two threads against 2 × 45 ms, serial in ``_ls_rhs``)
and solved together:

* on a large full frame (:func:`pmdsim.evaluation.poisson.prefers_dct`), by CG
  preconditioned with the pinned Neumann Laplacian's DCT inverse with the lowest DCT modes and
  the seed's Green's function deflated (:func:`pmdsim.evaluation.uncertainty_deflation.deflated_dct_pcg`,
  to :data:`SIGMA_DEFLATED_RTOL`, one right-hand side at a time: the deflation's setup, 0.23 s
  at 1920×1200, is paid once per camera; 1 iteration per right-hand side against 4–5 for
  :func:`pmdsim.evaluation.poisson.dct_pcg` to :data:`SIGMA_RTOL`, still the solver with
  ``SIGMA_DEFLATED_RTOL = None``);
* on masked domains, by the multigrid-preconditioned CG
  (:func:`pmdsim.evaluation.multigrid._pcg`), which needs fewer iterations there (measured:
  docs/benchmarks.md, "Integration: DCT-preconditioned solve").

Each solve stops at the relative tolerance :data:`SIGMA_RTOL` (max-norm of the preconditioned
residual against its initial value). Measured at full resolution, σ then differs from σ
solved to 1e-6 by at most 0.5 % per pixel (0.04 % of the largest σ), against the estimator's
own relative standard error 1/√(2K) = 8.8 % at K = 64.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import SERIAL_BELOW_PX, numba_threads
from .multigrid import _CGWork, _pcg
from . import poisson
from .poisson import DCTLaplacian, _DCTWork, dct_pcg
from .uncertainty import UncertaintyError, _subtract_edge, _xi
from .uncertainty_deflation import LowModes, deflated_dct_pcg
from .uncertainty_stepwise import _draw_word, _edge_jac, _seed_key

__all__: list[str] = []

#: Relative tolerance of one σ right-hand side's solve (module docstring).
SIGMA_RTOL = 1e-3

#: Relative tolerance of one σ right-hand side's deflated solve on a full frame
#: (:mod:`pmdsim.evaluation.uncertainty_deflation`; None: :func:`~pmdsim.evaluation.poisson.dct_pcg`
#: to :data:`SIGMA_RTOL`, :data:`SIGMA_BATCH` at a time). Its stopping test is on the deflated
#: preconditioned residual, whose initial value no longer holds the smooth modes: measured on
#: the Table 1 frame (docs/benchmarks.md, lsq25h), 3e-2 stops after one iteration with a
#: smaller error than ``dct_pcg`` to 1e-3 (4–5 iterations).
SIGMA_DEFLATED_RTOL = 3e-2

#: Iteration limit of one σ right-hand side's solve.
SIGMA_MAX_ITER = 500

#: Right-hand sides solved together: the work arrays are 5 + 1 padded float64 fields and one
#: float32 field per right-hand side (≈ 120 MB each at 1920×1200); stacking more measured no
#: faster per field on this machine (one core's vector units).
SIGMA_BATCH = 2

_NOT_FINITE = "the linearised least-squares system gave non-finite heights; no σ"


@numba.njit(cache=True, parallel=True)
def _accumulate_sq(S, X, acc):
    """acc += X² on S (X padded); returns False if an X on S is not finite."""
    H, W = S.shape
    bad = 0
    for v in numba.prange(0, H):
        for u in range(W):
            if S[v, u]:
                x = X[v + 1, u + 1]
                if not np.isfinite(x):
                    bad += 1
                acc[v, u] += x * x
    return bad == 0


@numba.njit(cache=True, nogil=True, inline="always")
def _row_dg(A, S, key, k0, n, n_chunks, v, dg):
    """dg[u, j] = A ξ_{k0 + j} (2,) for every pixel u of row v in S, j < n (as
    ``uncertainty._sample_dg``: the same products and sum); dg (W, n, 2)."""
    W = S.shape[1]
    for u in range(W):
        if not S[v, u]:
            continue
        a00 = A[v, u, 0, 0]
        a01 = A[v, u, 0, 1]
        a10 = A[v, u, 1, 0]
        a11 = A[v, u, 1, 1]
        w = np.uint64(0)
        for j in range(n):
            k = k0 + j
            if j == 0 or k % 32 == 0:
                w = _draw_word(key, v * W + u, k // 32, n_chunks)
            x = _xi(w, k % 32, 0)
            y = _xi(w, k % 32, 1)
            dg[u, j, 0] = a00 * x + a01 * y
            dg[u, j, 1] = a10 * x + a11 * y


@numba.njit(cache=True, nogil=True, inline="always")
def _row_edges(geo, S, v, E, ok):
    """The edges of row v: E[0:4, u] = J_a, J_b, Δx, Δy of the edge (v, u) → (v, u + 1), E[4:8, u]
    of (v, u) → (v + 1, u) (``uncertainty_stepwise._edge_jac``); ok[0, u], ok[1, u]: the edge
    joins two pixels of S and its J_a, J_b are finite (else ``uncertainty._ls_rhs`` leaves it
    out)."""
    H, W = S.shape
    for u in range(W):
        ok[0, u] = False
        ok[1, u] = False
        if not S[v, u]:
            continue
        if u + 1 < W and S[v, u + 1]:
            Ja, Jb, dx, dy = _edge_jac(geo, v, u, v, u + 1)
            E[0, u], E[1, u], E[2, u], E[3, u] = Ja, Jb, dx, dy
            ok[0, u] = np.isfinite(Ja) and np.isfinite(Jb)
        if v + 1 < H and S[v + 1, u]:
            Ja, Jb, dx, dy = _edge_jac(geo, v, u, v + 1, u)
            E[4, u], E[5, u], E[6, u], E[7, u] = Ja, Jb, dx, dy
            ok[1, u] = np.isfinite(Ja) and np.isfinite(Jb)


@numba.njit(cache=True, nogil=True, parallel=True)
def _edge_coefficients(geo, S, out):
    """Every edge's J_a, J_b, Δx, Δy (:func:`_row_edges`) in single precision, once per camera
    (the σ's right-hand sides read them for every batch): out[v, 0:4, u] of the edge (v, u) →
    (v, u + 1), out[v, 4:8, u] of (v, u) → (v + 1, u) (out (H, 8, W) float32; half the bytes of
    the geometry map they replace); J_a is NaN where ``uncertainty._ls_rhs`` leaves the edge out
    (not joining two pixels of S, or J_a, J_b not finite)."""
    H, W = S.shape
    for v in numba.prange(0, H):
        E = np.zeros((8, W))
        ok = np.empty((2, W), dtype=np.bool_)
        _row_edges(geo, S, v, E, ok)
        for k in range(8):
            for u in range(W):
                out[v, k, u] = E[k, u]
        for u in range(W):
            if not ok[0, u]:
                out[v, 0, u] = np.nan
            if not ok[1, u]:
                out[v, 4, u] = np.nan


@numba.njit(cache=True, nogil=True)
def _ls_rhs_edges(S, sv, su, edges, dg, rhs):
    """``uncertainty._ls_rhs`` from the single-precision edge coefficients of
    :func:`_edge_coefficients` (the same sums in the same order)."""
    H, W = S.shape
    rhs[:, :] = 0.0
    for v in range(H):
        for u in range(W):
            if not S[v, u]:
                continue
            a_free = not (v == sv and u == su)
            for e in range(2):
                vb = v + e
                ub = u + 1 - e
                Ja = edges[v, 4 * e, u]
                if not Ja == Ja:  # NaN: the edge is left out
                    continue
                Jb, dx, dy = edges[v, 4 * e + 1, u], edges[v, 4 * e + 2, u], edges[v, 4 * e + 3, u]
                _subtract_edge(rhs, dg, v, u, vb, ub, float(Ja), float(Jb), float(dx), float(dy), a_free,
                               not (vb == sv and ub == su))


@numba.njit(cache=True, nogil=True, parallel=True)
def _sampled_rhs(A, S, seed, k0, n_chunks, sv, su, edges, B, n_blocks):
    """B[j] = the right-hand side −Jᵀ δr (padded, ``uncertainty._ls_rhs``) of sample k0 + j's
    slope perturbations A ξ (``uncertainty._sample_dg``), j < len(B), in one pass: the rows in
    ``n_blocks`` blocks in parallel, each row's edge Jacobians formed once for the batch (a
    block's first row also forms the edges down from the row above it), each pixel's terms
    subtracted in the order ``_ls_rhs`` adds them (the edges up, left, right, down: bit for bit
    its sums)."""
    H, W = S.shape
    n = B.shape[0]
    key = _seed_key(seed)
    rows = (H + n_blocks - 1) // n_blocks
    for t in numba.prange(0, n_blocks):
        v0 = t * rows
        v1 = min(H, v0 + rows)
        if v0 >= v1:
            continue
        cur = np.empty((W, n, 2))  # δg of row v
        nxt = np.empty((W, n, 2))  # δg of row v + 1
        up = np.zeros((n, W))  # J_b δr of the edge down into row v (0: none)
        _row_dg(A, S, key, k0, n, n_chunks, v0, cur)
        if v0 > 0:  # the edges from the row above the block
            _row_dg(A, S, key, k0, n, n_chunks, v0 - 1, nxt)
            E = edges[v0 - 1]
            for j in range(n):
                for u in range(W):
                    if E[4, u] == E[4, u]:
                        dr = -0.5 * ((nxt[u, j, 0] + cur[u, j, 0]) * E[6, u] + (nxt[u, j, 1] + cur[u, j, 1]) * E[7, u])
                        if np.isfinite(dr):
                            up[j, u] = E[5, u] * dr
        for v in range(v0, v1):
            if v + 1 < H:
                _row_dg(A, S, key, k0, n, n_chunks, v + 1, nxt)
            E = edges[v]  # (J_a NaN: the edge is left out)
            for j in range(n):
                Bv = B[j, v + 1]
                upj = up[j]
                Bv[0] = 0.0
                Bv[W + 1] = 0.0
                left = 0.0
                for u in range(W):
                    if not S[v, u]:
                        Bv[u + 1] = 0.0
                        upj[u] = 0.0
                        left = 0.0
                        continue
                    r = 0.0
                    r -= upj[u]
                    r -= left
                    left = 0.0
                    if E[0, u] == E[0, u]:
                        dr = -0.5 * ((cur[u, j, 0] + cur[u + 1, j, 0]) * E[2, u]
                                     + (cur[u, j, 1] + cur[u + 1, j, 1]) * E[3, u])
                        if np.isfinite(dr):
                            r -= E[0, u] * dr
                            left = E[1, u] * dr
                    upj[u] = 0.0
                    if E[4, u] == E[4, u]:
                        dr = -0.5 * ((cur[u, j, 0] + nxt[u, j, 0]) * E[6, u] + (cur[u, j, 1] + nxt[u, j, 1]) * E[7, u])
                        if np.isfinite(dr):
                            r -= E[4, u] * dr
                            upj[u] = E[5, u] * dr
                    Bv[u + 1] = 0.0 if v == sv and u == su else r
            cur, nxt = nxt, cur
    for j in range(n):  # the padding rows
        B[j, 0, :] = 0.0
        B[j, H + 1, :] = 0.0


class _SigmaSolver:
    """Solves N X = B for stacks of right-hand sides of one linearised least-squares
    integration (module docstring); ``kind`` is "dct" or "multigrid"."""

    def __init__(self, lin):
        self.lin = lin
        unknown = lin.D > 0.0
        self.kind = "dct" if poisson.prefers_dct(np.count_nonzero(unknown), lin.S.shape) else "multigrid"
        if self.kind == "dct":
            self.unknown = unknown
            self.lap = DCTLaplacian(lin.S.shape, lin.seed, dtype=np.float32)
            self.modes = None
            if SIGMA_DEFLATED_RTOL is not None:  # one right-hand side at a time, W E⁻¹ Wᵀ set up once
                self.work = _DCTWork(1, lin.D.shape)
                self.modes = LowModes(lin.S.shape, lin.seed, lap=self.lap)
                self.modes.prepare(lin.D, lin.Ex, lin.Ey, unknown)
            else:
                self.work = _DCTWork(SIGMA_BATCH, lin.D.shape)
        else:
            self.work = _CGWork(lin.D.shape)

    def accumulate(self, B, acc):
        """acc += x² on S (H, W) for the solution x of each right-hand side of B (k, H + 2, W + 2)."""
        lin = self.lin
        fail = ("the linearised least-squares system did not converge (singular or ill-conditioned normal "
                "equations); no σ")
        if self.kind == "dct" and self.modes is not None:  # x² added by the solver's last pass
            for b in B:
                finite, _, ok = deflated_dct_pcg(lin.D, lin.Ex, lin.Ey, b, lin.seed, 0.0, SIGMA_DEFLATED_RTOL,
                                                 SIGMA_MAX_ITER, lap=self.lap, work=self.work, modes=self.modes,
                                                 unknown=self.unknown, acc=acc, on=lin.S)
                if not ok:
                    raise UncertaintyError(fail)
                if not finite:
                    raise UncertaintyError(_NOT_FINITE)
            return
        if self.kind == "dct":
            X, _, ok = dct_pcg(lin.D, lin.Ex, lin.Ey, B, lin.seed, 0.0, SIGMA_RTOL, SIGMA_MAX_ITER, lap=self.lap,
                               work=self.work, unknown=self.unknown)
            if not ok.all():
                raise UncertaintyError(fail)
        for i, b in enumerate(B):
            if self.kind == "dct":
                x = X[i]
            else:
                x, _, ok = _pcg(lin.D, lin.iD, lin.Ex, lin.Ey, b, 0.0, SIGMA_RTOL, SIGMA_MAX_ITER, work=self.work,
                                mg=lin.mg)
                if not ok:
                    raise UncertaintyError(fail)
            if not _accumulate_sq(lin.S, x, acc):
                raise UncertaintyError(_NOT_FINITE)


def least_squares_sum_sq(lin, A, seed: int, K: int) -> np.ndarray:
    """Σ_k δz_k² (H, W) over the K sampled right-hand sides of a least-squares linearised
    integration ``lin`` (``uncertainty._LinearisedIntegration``), from A = J·diag(σ_xy)
    (H, W, 2, 2), 0 off S; the samples' ξ as ``uncertainty._sampled_std``."""
    S = lin.S
    # Small grids on one numba thread (the parallel kernels' barrier dominates: kernel_args).
    with numba_threads(1 if S.size < SERIAL_BELOW_PX else numba.get_num_threads()):
        return _least_squares_sum_sq(lin, S, A, seed, K)


def _least_squares_sum_sq(lin, S, A, seed, K):
    solver = _SigmaSolver(lin)
    acc = np.zeros(S.shape)
    B = np.empty((SIGMA_BATCH,) + lin.D.shape)
    n_chunks = (K + 31) // 32
    n_blocks = 4 * numba.get_num_threads()
    for k0 in range(0, K, SIGMA_BATCH):
        n = min(SIGMA_BATCH, K - k0)
        _sampled_rhs(A, S, seed, k0, n_chunks, lin.seed[0], lin.seed[1], lin.edges, B[:n], n_blocks)
        solver.accumulate(B[:n], acc)
    return acc
