"""The anchored integration's linear solves on full frames: conjugate gradients preconditioned
by the Neumann Laplacian's DCT inverse plus an exact level (issue 25 item 1; used by
:func:`pmdsim.evaluation.stereo._integrate_anchored`).

The stereo integration's Gauss–Newton matrix M = N + w² Aᵀ A (N the slope equations' normal
matrix of :func:`~pmdsim.evaluation.least_squares._assemble_gauss_newton` without a seed, A the
selection of the anchor pixels, w = :data:`~pmdsim.evaluation.stereo.ANCHOR_WEIGHT`) has no
pinned pixel: its gauge is the anchors' small terms. Every mode but the level is close to the
Neumann Laplacian L's (N's edge weights are 1 + O(1e-3), and w² = 1e-4 per anchor at about one
anchor per 24 × 24 pixels is ≈ 2e-7 per pixel, far below L's smallest non-zero eigenvalue,
(π/W)² ≈ 2.7e-6 at 1920 pixels); the level (the constants 1) is in L's null space, while
1ᵀ M 1 = κ > 0 comes from the anchors and from the slopes' dependence on the heights
(Table 1: 0.32 + 0.24). The preconditioner is therefore

    B r = (I − Π) L⁺ (I − Π) r + (1ᵀ r / κ) 1,     Π = 1 1ᵀ / n,

the pseudo-inverse of L on the mean-free part (the DCT solve of
:class:`~pmdsim.evaluation.poisson.DCTLaplacian` in single precision, the right-hand side made
mean-free so that its pinned pixel's substitution changes nothing, the result's mean removed)
plus the Galerkin solve of the level (a coarse space of one vector): symmetric positive
definite. On a frame with a few masked pixels (the fill that
:func:`~pmdsim.evaluation.poisson.prefers_dct` allows) the same with 1 the indicator of the
unknowns and the result restricted to them. CG runs in float64 over the kernels of
:func:`~pmdsim.evaluation.poisson.dct_pcg` (one right-hand side).
"""

from __future__ import annotations

import numpy as np

from . import poisson

__all__: list[str] = []


class LevelDCT:
    """The preconditioner B of the module docstring for the operator (D, Ex, Ey) (padded 5-point
    arrays, :mod:`pmdsim.evaluation.multigrid`) on an H×W frame; ``lap``: a float32
    :class:`~pmdsim.evaluation.poisson.DCTLaplacian` of (H, W) (any pinned pixel; reused
    between operators of one frame)."""

    def __init__(self, D, Ex, Ey, lap):
        self.lap = lap
        self.unknown = D > 0.0
        self.n = D.shape[0] * D.shape[1] - 2 * (D.shape[0] + D.shape[1]) + 4  # the frame's pixels
        # 1ᵀ M 1 over the unknowns: the couplings to pixels that are not unknowns are 0
        self.kappa = float(D.sum() - 2.0 * Ex.sum() - 2.0 * Ey.sum())
        if not self.kappa > 0.0:
            raise ValueError(f"the level's curvature 1ᵀM1 = {self.kappa!r} is not positive (no anchors?)")

    def apply(self, R, buf, total, Z):
        """Z = B R for the residual R (padded, float64, 0 off the unknowns) whose interior is in
        ``buf`` (H, W) float32 (overwritten) and whose sum is ``total``; returns (R·Z, max |Z|)."""
        sv, su = self.lap.pinned
        buf -= np.float32(total / self.n)  # (I − Π) r: consistent, so the pinned pixel's row changes nothing
        y = self.lap.solve(buf, overwrite=True, totals=-float(buf[sv, su]), pin=False)
        y0 = np.float32(np.mean(y, dtype=np.float64) - total / self.kappa)  # remove L⁺'s mean, add the level
        return poisson._scatter_dot_max(R, y, y0, self.unknown, Z)


def level_dct_pcg(D, Ex, Ey, b, atol, rtol, max_iter, *, cap=np.inf, lap=None, work=None):
    """CG for M x = b (padded (H + 2, W + 2) arrays; D == 0 off the unknowns), preconditioned by
    :class:`LevelDCT`; stops when the max-norm of the preconditioned residual (an estimate of
    the error) is below ``max(atol, min(rtol · its initial value, cap))`` and adds that last
    preconditioned residual (as :func:`~pmdsim.evaluation.multigrid._pcg`). ``work``: a
    :class:`~pmdsim.evaluation.poisson._DCTWork` for one field (created if not given).
    Returns (x, iterations, converged); x is ``work.X[0]``."""
    Hp, Wp = D.shape
    if lap is None:
        lap = poisson.DCTLaplacian((Hp - 2, Wp - 2), (0, 0), dtype=np.float32)
    if work is None:
        work = poisson._DCTWork(1, D.shape)
    pre = LevelDCT(D, Ex, Ey, lap)
    X, R, Z, P, AP, buf = work.X[0], work.R[0], work.Z[0], work.P[0], work.AP[0], work.buf[0]
    poisson._start_fields(X, R, b, buf)
    rz, zmax = pre.apply(R, buf, float(np.sum(R)), Z)
    tol = max(atol, min(rtol * zmax, cap))
    its, beta, alpha = 0, 0.0, 0.0
    while zmax > tol and its < max_iter:
        pAp = poisson._direction_matvec(D, Ex, Ey, Z, P, AP, beta, X, alpha)
        alpha = 0.0
        if not (pAp > 0.0 and rz > 0.0):  # breakdown (round-off at convergence)
            break
        alpha = rz / pAp
        total = poisson._update_gather(R, AP, alpha, buf)
        its += 1
        rz_old = rz
        rz, zmax = pre.apply(R, buf, total, Z)
        beta = rz / rz_old
    converged = bool(zmax <= tol)
    poisson._finish_step(X, P, alpha, Z, converged)
    return X, its, converged
