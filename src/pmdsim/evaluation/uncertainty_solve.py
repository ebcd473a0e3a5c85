"""The least-squares height σ's sampled right-hand sides, solved in batches (issue 22 "Speed",
issue 25 item 3).

The K right-hand sides of the estimator (:mod:`pmdsim.evaluation.uncertainty`) share one
matrix, the Gauss–Newton matrix N of the reconstruction at convergence. They are built as
before (``uncertainty._sample_dg``, ``uncertainty._ls_rhs``: the same seeds give the same
right-hand sides) and solved :data:`SIGMA_BATCH` at a time:

* on a large full frame (:func:`pmdsim.evaluation.poisson.prefers_dct`), by CG
  preconditioned with the pinned Neumann Laplacian's DCT inverse
  (:func:`pmdsim.evaluation.poisson.dct_pcg`, the transforms of a batch stacked);
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
from .uncertainty import UncertaintyError, _ls_rhs, _sample_dg

__all__: list[str] = []

#: Relative tolerance of one σ right-hand side's solve (module docstring).
SIGMA_RTOL = 1e-3

#: Iteration limit of one σ right-hand side's solve.
SIGMA_MAX_ITER = 500

#: Right-hand sides solved together: the work arrays are 5 + 1 padded float64 fields and one
#: float32 field per right-hand side (≈ 120 MB each at 1920×1200); stacking more measured no
#: faster per field on this machine (one core's vector units).
SIGMA_BATCH = 2



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
            self.work = _DCTWork(SIGMA_BATCH, lin.D.shape)
        else:
            self.work = _CGWork(lin.D.shape)

    def solve(self, B):
        """Yields the solution (a padded field) of each right-hand side of B (k, H + 2, W + 2),
        in order; a yielded field is work space, valid until the next one is requested."""
        lin = self.lin
        fail = ("the linearised least-squares system did not converge (singular or ill-conditioned normal "
                "equations); no σ")
        if self.kind == "dct":
            X, _, ok = dct_pcg(lin.D, lin.Ex, lin.Ey, B, lin.seed, 0.0, SIGMA_RTOL, SIGMA_MAX_ITER, lap=self.lap,
                               work=self.work, unknown=self.unknown)
            if not ok.all():
                raise UncertaintyError(fail)
            yield from X
            return
        for b in B:
            x, _, ok = _pcg(lin.D, lin.iD, lin.Ex, lin.Ey, b, 0.0, SIGMA_RTOL, SIGMA_MAX_ITER, work=self.work,
                            mg=lin.mg)
            if not ok:
                raise UncertaintyError(fail)
            yield x


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
    dg = np.empty(S.shape + (2,))
    B = np.zeros((SIGMA_BATCH,) + lin.D.shape)
    n_chunks = (K + 31) // 32
    for k0 in range(0, K, SIGMA_BATCH):
        n = min(SIGMA_BATCH, K - k0)
        for j in range(n):
            _sample_dg(A, S, seed, k0 + j, n_chunks, dg)
            _ls_rhs(S, lin.seed[0], lin.seed[1], lin.geo, dg, B[j])
        for x in solver.solve(B[:n]):
            if not _accumulate_sq(S, x, acc):
                raise UncertaintyError("the linearised least-squares system gave non-finite heights; no σ")
    return acc
