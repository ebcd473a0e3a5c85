"""The stereo heights' noise σ on a subgrid (issue 22 "Speed", ``--stereo``).

The noise part of a stereo evaluation's height σ (:mod:`pmdsim.evaluation.uncertainty_stereo`)
costs K = 64 solves of each camera's anchored normal equations; at every pixel that is 3–8 times
the stereo evaluation itself. On large images the same estimator runs on every s-th pixel:

* **The subgrid system.** Each camera is taken as the camera of focal length f/s whose pixel
  (i, j) is pixel (o + s·i, o + s·j) (o as the calibration part's subgrid, so that the anchors
  lie on it when s divides the search's stride): its view rays, screen points and heights there
  give the zonal least-squares equations between subgrid neighbours (the same Gauss–Newton
  matrix, :func:`~pmdsim.evaluation.least_squares._assemble_gauss_newton`), and every anchor
  moves to its subgrid pixel (nearest, ties upwards) with its weight w² (several anchors on one
  subgrid pixel add their weights and their w²·δa).
* **The slopes' noise on the subgrid.** Every pixel's slope perturbation δg = J σ ξ (the same
  Rademacher draws ξ as at every pixel) is averaged over the pixels of the subgrid pixel's block
  (the reconstructed pixels whose nearest subgrid pixel it is). For a smooth height mode φ the
  right-hand side's projection Σ δg·∇φ has the same variance from the block means on the
  subgrid as from every pixel (σ²/s² per block mean, blocks s² times larger): the subgrid keeps
  the covariance of every scale it resolves and drops the scales below s pixels.
* **The anchors' noise** is every pixel's: each anchor's δa (its own pixel and its partner's 16,
  :class:`~pmdsim.evaluation.uncertainty_stereo.AnchorNoise`) from the same draws, so the
  correlations between a camera's slopes, its anchors and the partner's data stay propagated.
* **All K samples' draws at once**: one pass over the pixels draws each pixel's random word once
  per 32 samples and adds its δg_k to its block's mean; the anchors' δa_k likewise (bit for bit
  the per-sample draws). Each sample is then one multigrid-CG solve of the subgrid's system. The
  same pass makes each pixel's A = J·diag(σ) and the slopes' σ (:func:`subgrid_noise_std`): the
  (H, W, 2, 2) array of A is never stored (bit for bit the values it would hold).
* **Back to every pixel**: σ of the subgrid, bilinearly interpolated (subgrid pixels that are
  not reconstructed filled from their neighbours first).

The stereo σ is mostly the anchors' weighted mean (σ_a/√n, uniform); what the subgrid changes is
the slopes' shape part below s pixels. Measured against every pixel: docs/benchmarks.md,
"Uncertainty: stereo at the issue's speed"; :func:`default_noise_stride` keeps a subgrid of at
least :data:`MIN_NOISE_SUBGRID_PX` pixels on the shorter side (every pixel below twice that).
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage

from .least_squares import _assemble_gauss_newton
from .multigrid import _CGWork, _Multigrid, _pcg
from .stereo import ANCHOR_WEIGHT, _view_arrays
from .uncertainty import UncertaintyError, _geometry, _ls_rhs, _pixel_jacobian, _tangent_array, _word, _xi
from .uncertainty_calibration import _fill
from .uncertainty_gram import _cell

__all__ = ["MIN_NOISE_SUBGRID_PX", "default_noise_stride", "subgrid_noise_std"]

_RTOL = 1e-4  # relative tolerance of each solve, as the every-pixel σ's (uncertainty_stereo._RTOL)

#: The shortest subgrid side :func:`default_noise_stride` keeps (pixels).
MIN_NOISE_SUBGRID_PX = 75


def default_noise_stride(shape) -> int:
    """The noise σ's default subgrid stride: min(H, W) // :data:`MIN_NOISE_SUBGRID_PX`, at least
    1 (every pixel below 150 px; 4 at 480 × 300, 16 at 1920 × 1200)."""
    return max(1, min(int(shape[0]), int(shape[1])) // MIN_NOISE_SUBGRID_PX)


def _nearest(x, o: int, s: int, n: int) -> np.ndarray:
    """Subgrid index (0 … n − 1) nearest to pixel coordinate(s) x (ties upwards)."""
    return np.clip((np.asarray(x, dtype=np.int64) - o + s // 2) // s, 0, n - 1)


@numba.njit(cache=True, nogil=True, inline="always")
def _add_draws(a, seed, pix, n_chunks, K, t0, t1, row):
    """Add pixel ``pix``'s δg_k = a ξ_k (a (2, 2)) of the K samples to its block's sums row (2K,)
    (x: row[k], y: row[K + k]). The four values ±a₀₀ ± a₀₁ (and ±a₁₀ ± a₁₁) are tabulated and
    each sample adds the one its two bits select (exactly a ξ_k of
    :func:`pmdsim.evaluation.uncertainty._sample_dg`: the same products and sum)."""
    for b in range(4):
        x = 1.0 - 2.0 * (b & 1)
        y = 1.0 - 2.0 * (b >> 1)
        t0[b] = a[0, 0] * x + a[0, 1] * y
        t1[b] = a[1, 0] * x + a[1, 1] * y
    for c in range(n_chunks):
        w = _word(seed, pix, c, n_chunks)
        for kk in range(min(32, K - 32 * c)):
            b = (w >> np.uint64(2 * kk)) & np.uint64(3)
            row[32 * c + kk] += t0[b]
            row[K + 32 * c + kk] += t1[b]


@numba.njit(cache=True, nogil=True, inline="always")
def _block_row_means(acc, cnt, K, i, out):
    """out[k, i, j] = the block sums acc (wc, 2K) over the counts cnt (wc,) (at least 1)."""
    for j in range(acc.shape[0]):
        n = max(cnt[j], 1.0)
        for k in range(K):
            out[k, i, j, 0] = acc[j, k] / n
            out[k, i, j, 1] = acc[j, K + k] / n


@numba.njit(cache=True, nogil=True, parallel=True)
def _block_means(A, S, seed, n_chunks, K, row_block, col_block, hc, wc, out):
    """out (K, hc, wc, 2) = the mean of δg_k = A ξ_k over each subgrid pixel's block of
    reconstructed pixels (row_block[v], col_block[u]: the block of pixel (v, u)), for the K
    samples (ξ of :func:`pmdsim.evaluation.uncertainty._sample_dg`, bit for bit). Blocks are
    disjoint row bands per subgrid row, so threads own their rows."""
    H, W = S.shape
    for i in numba.prange(0, hc):
        cnt = np.zeros(wc)
        acc = np.zeros((wc, 2 * K))
        t0 = np.empty(4)
        t1 = np.empty(4)
        for v in range(H):
            if row_block[v] != i:
                continue
            for u in range(W):
                if not S[v, u]:
                    continue
                j = col_block[u]
                cnt[j] += 1.0
                _add_draws(A[v, u], seed, v * W + u, n_chunks, K, t0, t1, acc[j])
        _block_row_means(acc, cnt, K, i, out)


@numba.njit(cache=True, nogil=True, inline="always")
def _finite(x):
    """numpy's ``nan_to_num`` of one float: NaN → 0, ±inf → ± the largest float."""
    if np.isnan(x):
        return 0.0
    if np.isinf(x):
        return np.finfo(np.float64).max if x > 0 else -np.finfo(np.float64).max
    return x


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _jacobian_block_means(o, p, q, T, S, sig, seed, n_chunks, K, row_block, col_block, hc, wc, out, gstd):
    """:func:`_block_means` of A = J·diag(σ) computed per pixel in the same pass
    (:func:`~pmdsim.evaluation.uncertainty._pixel_jacobian`, NaN-free as ``np.nan_to_num``)
    instead of read from an (H, W, 2, 2) array, and the slopes' σ gstd (H, W, 2) (NaN off S):
    bit for bit ``_jacobian_scaled`` followed by ``_block_means``. T (H, W, 3, 2) or (1, 1, 3, 2)."""
    H, W = S.shape
    per_pixel = 0 if T.shape[0] == 1 else 1
    for i in numba.prange(0, hc):
        cnt = np.zeros(wc)
        acc = np.zeros((wc, 2 * K))
        t0 = np.empty(4)
        t1 = np.empty(4)
        a = np.empty((2, 2))
        for v in range(H):
            if row_block[v] != i:
                continue
            for u in range(W):
                if not S[v, u]:
                    gstd[v, u, 0] = np.nan
                    gstd[v, u, 1] = np.nan
                    continue
                _pixel_jacobian(o, p, q, T, v, u, v * per_pixel, u * per_pixel, sig, a, gstd[v, u])
                for m in range(2):
                    for n in range(2):
                        a[m, n] = _finite(a[m, n])
                j = col_block[u]
                cnt[j] += 1.0
                _add_draws(a, seed, v * W + u, n_chunks, K, t0, t1, acc[j])
        _block_row_means(acc, cnt, K, i, out)


@numba.njit(cache=True, nogil=True, parallel=True)
def _interpolated_std(sd, S, o, s, out):
    """out (H, W) = sqrt(x²), x the bilinear interpolation of the subgrid's σ sd (h, w) (no NaN;
    node (i, j) is pixel (o + s·i, o + s·j), linear extrapolation beyond the outer nodes), NaN
    off S: what ``np.sqrt(_accumulate(sd[None, ..., None] · (1, 1, 1), o, o, s, H, W)[..., 0])``
    gives there, bit for bit (the same weights and sums; 0 + x² = x²), in one channel and one
    pass."""
    h, w = sd.shape
    H, W = S.shape
    for v in numba.prange(0, H):
        i0, ay = _cell(v, o, s, h)
        i1 = min(i0 + 1, h - 1)
        for u in range(W):
            if not S[v, u]:
                out[v, u] = np.nan
                continue
            j0, ax = _cell(u, o, s, w)
            j1 = min(j0 + 1, w - 1)
            x = ((1 - ay) * (1 - ax) * sd[i0, j0] + (1 - ay) * ax * sd[i0, j1] + ay * (1 - ax) * sd[i1, j0]
                 + ay * ax * sd[i1, j1])
            out[v, u] = np.sqrt(x * x)


@numba.njit(cache=True, nogil=True)
def _anchor_draws(anchor, cam, pix, coef, seeds, K, n_chunks, out):
    """out (K, n): δa of every sample k from the linear terms δa_i = Σ_t coef_t·ξ_k(cam_t, pix_t)
    (what :func:`pmdsim.evaluation.uncertainty_stereo._anchor_draw` gives per sample, in the same
    order of the terms: bit for bit), each term's random word drawn once per 32 samples."""
    out[:] = 0.0
    for t in range(anchor.size):
        i = anchor[t]
        c0 = coef[t, 0]
        c1 = coef[t, 1]
        for c in range(n_chunks):
            w = _word(seeds[cam[t]], pix[t], c, n_chunks)
            for kk in range(min(32, K - 32 * c)):
                out[32 * c + kk, i] += c0 * _xi(w, kk, 0) + c1 * _xi(w, kk, 1)


class _SubgridLinear:
    """One camera's anchored least-squares heights linearised on the subgrid of stride s, offset
    o (module docstring): δz_sub = N_sub⁻¹(−J_subᵀ δr(block means) + Σ w² e δa)."""

    def __init__(self, view, rec, anchors_vu, s: int, o: int, arrays=None):
        o_ref, d, q, _ = _view_arrays(view) if arrays is None else arrays
        S_full = np.asarray(rec.reconstructed, dtype=bool)
        H, W = S_full.shape
        self.shape, self.s, self.o = (H, W), s, o
        S = np.ascontiguousarray(S_full[o::s, o::s])
        h, w = S.shape
        av = _nearest(anchors_vu[:, 0], o, s, h)
        au = _nearest(anchors_vu[:, 1], o, s, w)
        # the subgrid components that hold an anchor (the others have no gauge)
        labels, _ = ndimage.label(S)
        lab = labels[av, au]
        S &= np.isin(labels, np.unique(lab[lab > 0]))
        if not S.any():
            raise UncertaintyError("no anchor lies on the reconstructed pixels of the σ's subgrid; no σ")
        self.S = S
        self.keep = S[av, au]
        self.av = np.ascontiguousarray(av[self.keep] + 1)
        self.au = np.ascontiguousarray(au[self.keep] + 1)
        z = np.ascontiguousarray(np.where(S, np.asarray(rec.height_mm)[o::s, o::s], 0.0))
        d = np.ascontiguousarray(d[o::s, o::s])
        q = np.ascontiguousarray(np.where(S[..., None], q[o::s, o::s], 0.0))
        self.geo = np.zeros((h, w, 8))
        _geometry(o_ref, d, q, S, z, self.geo)
        if not np.isfinite(self.geo[S]).all():
            raise UncertaintyError("the slopes' geometry is not finite at some reconstructed pixel; no σ")
        shape = (h + 2, w + 2)
        self.D, self.iD, self.Ex, self.Ey, self.rhs = (np.zeros(shape) for _ in range(5))
        _assemble_gauss_newton(o_ref, d, q, S, z, -1, -1, self.D, self.iD, self.Ex, self.Ey, self.rhs)
        self.w2 = ANCHOR_WEIGHT ** 2
        np.add.at(self.D, (self.av, self.au), self.w2)
        self.iD[self.av, self.au] = 1.0 / self.D[self.av, self.au]
        self.mg = _Multigrid(self.D, self.iD, self.Ex, self.Ey)
        self.work = _CGWork(shape)
        # each pixel's block: its nearest subgrid pixel
        self.row_block = np.ascontiguousarray(_nearest(np.arange(H), o, s, h))
        self.col_block = np.ascontiguousarray(_nearest(np.arange(W), o, s, w))
        self.S_full = np.ascontiguousarray(S_full)

    def block_means(self, A, seed: int, K: int) -> np.ndarray:
        """(K, h, w, 2) block means of the K samples' slope perturbations (A = J σ, 0 off S)."""
        h, w = self.S.shape
        out = np.empty((K, h, w, 2))
        _block_means(A, self.S_full, np.int64(seed), (K + 31) // 32, K, self.row_block, self.col_block, h, w, out)
        return out

    def jacobian_block_means(self, o, p, q, dq_dxy, sig, seed: int, K: int):
        """:meth:`block_means` of A = J·diag(σ) made per pixel in the same pass (no (H, W, 2, 2)
        array), and the slopes' σ (H, W, 2) (NaN off S): ``_jacobian_scaled(o, p, q, dq_dxy, S,
        sig)`` then :meth:`block_means` of its A (NaN-free), bit for bit. σ ``sig`` (H, W, 2)
        is read on S only."""
        h, w = self.S.shape
        H, W = self.shape
        out = np.empty((K, h, w, 2))
        gstd = np.empty((H, W, 2))
        _jacobian_block_means(np.asarray(o, dtype=float), np.ascontiguousarray(p, dtype=float),
                              np.ascontiguousarray(q, dtype=float), _tangent_array(dq_dxy), self.S_full,
                              np.ascontiguousarray(sig, dtype=float), np.int64(seed), (K + 31) // 32, K,
                              self.row_block, self.col_block, h, w, out, gstd)
        return out, gstd

    def sum_sq(self, means, da) -> np.ndarray:
        """Σ_k δz_k² (h, w) on the subgrid (0 off its S) over the samples' block-mean slope
        perturbations ``means`` (K, h, w, 2) and anchor perturbations ``da`` (K, n) of all
        anchors given at construction, each solved by the multigrid-preconditioned CG."""
        acc = np.zeros(self.S.shape)
        for k in range(means.shape[0]):
            _ls_rhs(self.S, -1, -1, self.geo, means[k], self.rhs)
            np.add.at(self.rhs, (self.av, self.au), self.w2 * da[k][self.keep])
            if float(np.max(np.abs(self.rhs))) == 0.0:
                continue
            x, _, ok = _pcg(self.D, self.iD, self.Ex, self.Ey, self.rhs, 0.0, _RTOL, 500, work=self.work, mg=self.mg)
            if not ok or not np.isfinite(x).all():
                raise UncertaintyError("the linearised anchored least-squares system on the σ's subgrid did not "
                                       "converge (singular or ill-conditioned normal equations); no σ")
            acc += np.where(self.S, x[1:-1, 1:-1], 0.0) ** 2
        return acc

    def to_pixels(self, var_sub) -> np.ndarray:
        """σ (H, W) at every pixel from the subgrid's variances (h, w) (NaN off S): bilinear
        interpolation of σ after filling the subgrid pixels off S from their neighbours."""
        sd = np.where(self.S, np.sqrt(var_sub), np.nan)[..., None]
        h, w = self.S.shape
        filled = _fill(np.ascontiguousarray(sd), h + w)
        if np.isnan(filled).any():
            raise UncertaintyError("the σ's subgrid holds no reconstructed pixel; no σ")
        out = np.empty(self.shape)
        _interpolated_std(np.ascontiguousarray(filled[..., 0]), self.S_full, self.o, self.s, out)
        return out


def subgrid_noise_std(views: dict, recs: dict, anchors_vu: dict, jacobian: dict, noise: dict, seeds, *,
                      samples: int, stride: int, offset: int, arrays: dict | None = None) -> tuple[dict, dict]:
    """σ (H, W) of every camera's heights, mm, on the subgrid of ``stride`` (module docstring),
    and the slopes' σ (H, W, 2) (dimensionless) made in the same pass over the pixels.

    Parameters
    ----------
    views : dict name → StereoView
    recs : dict name → Reconstruction
        Each camera's anchored reconstruction (``reconstructed``, ``height_mm``).
    anchors_vu : dict name → ndarray of int (n, 2)
        Each camera's anchors (pixels), in the order of ``noise[name]``'s anchors.
    jacobian : dict name → tuple (o, p, q, dq_dxy, sig)
        Every camera's slope Jacobian inputs, evaluation order: camera centre (3,), surface
        points and screen points (H, W, 3), mm, screen tangents (H, W, 3, 2) or (3, 2), and the
        decoder's σ (H, W, 2), mm (read on the reconstructed pixels only). A = J·diag(σ) per
        pixel as :func:`~pmdsim.evaluation.uncertainty._jacobian_scaled` (NaN-free), never stored.
    noise : dict name → AnchorNoise
    seeds : ndarray of int64
        The estimator's seed per camera (evaluation order).
    samples, stride, offset
        K, s and o.
    arrays : dict name → tuple, optional
        Each camera's ``_view_arrays`` (o, d, q, valid) when the caller has them.

    Returns
    -------
    (dict name → ndarray (H, W), dict name → ndarray (H, W, 2))
        The heights' noise σ, mm, and the slopes' σ; NaN where not reconstructed.
    """
    names = list(jacobian)
    K = int(samples)
    n_chunks = (K + 31) // 32
    out, g_std = {}, {}
    for c in recs:
        lin = _SubgridLinear(views[c], recs[c], anchors_vu[c], int(stride), int(offset),
                             None if arrays is None else arrays[c])
        means, g_std[c] = lin.jacobian_block_means(*jacobian[c], int(seeds[names.index(c)]), K)
        an = noise[c]
        da = np.empty((K, an.std_mm.size))
        _anchor_draws(an.anchor, an.camera, an.pixel, an.coef, np.ascontiguousarray(seeds, dtype=np.int64), K,
                      n_chunks, da)
        out[c] = lin.to_pixels(lin.sum_sq(means, da) / K)
    return out, g_std
