"""Per-pixel standard uncertainties of stereo evaluations (issue 22; stereo: issue 14).

Vocabulary as :mod:`pmdsim.evaluation.uncertainty` (GUM standard uncertainties, k = 1). A
stereo evaluation (:mod:`pmdsim.evaluation.stereo`) fixes its heights by many anchors found by
normal consistency, not by a seed of known height: its σ is **absolute** (nothing is held).

**The anchors' σ.** An anchor height a on camera A's view ray solves r(a) = g_A(a) − g_B(a) = 0
(2-vector, one unknown; g_A from A's screen point q_A at the pixel, g_B from the partner's screen
points interpolated by cubic convolution at the projection of the point, q_B = Σ_ij w_ij q_B,ij
over a 4 × 4 neighbourhood). To first order its Gauss–Newton solution moves by

    δa = −(JᵀJ)⁻¹ Jᵀ δr,   δr = G_A T_A δxy_A − G_B Σ_ij w_ij T_B,ij δxy_B,ij,

with J = ∂r/∂a (central difference along the ray, as the solver's), G = ∂g/∂q the slopes'
exact Jacobian (:func:`~pmdsim.evaluation.uncertainty.slope_jacobian`), T = ∂q/∂(x_s, y_s) the
screen tangents and δxy the decoded screen coordinates' noise (σ ``std_xy_mm``, independent per
pixel and axis). So σ_a² = (JᵀJ)⁻¹ Jᵀ Σ_r J (JᵀJ)⁻¹ with Σ_r the covariance of δr: A's pixel
and the partner's 16 pixels, each with its own σ (the interpolated q_B is less noisy than one
pixel: Σ w_ij² < 1). With several partners, the anchor's partner is the one of smallest |r|
(the search keeps that one).

**The heights' σ.** Each camera's surface solves the anchored least-squares normal equations
(the zonal slope equations plus w·(z_i − a_i) = 0 at its anchors, w = ``ANCHOR_WEIGHT``); to
first order δz = N⁻¹ (−Jᵀ δr_slopes + w² Σ_i e_i δa_i), with N the Gauss–Newton matrix at the
solution (same D, Ex, Ey as the evaluation, the anchor weight on the diagonal), solved by the
multigrid-preconditioned CG. The covariance is estimated as for mono: K right-hand sides from
Rademacher draws ξ (±1) per camera, pixel and axis; the *same* draws give each sample's slope
perturbations δg = J σ ξ of every camera and its anchors' δa, so that the correlations between
a camera's slopes, its anchors and the partner's data are propagated (an anchor shares its
pixel's noise with the slopes there, and the partner's noise with the partner's surface).
σ_z² = mean_k δz_k²; relative standard error of σ at most about 1/√(2K). On images of at least
150 px in the shorter side (the default stride) the same estimator runs on a subgrid
(:mod:`pmdsim.evaluation.uncertainty_stereo_subgrid`: the slopes' draws block-averaged, every
anchor's δa as here), which is what makes the stereo σ affordable at full resolution.

The calibration covariance, when the setup carries one, adds its part
(:mod:`pmdsim.evaluation.uncertainty_stereo_calibration`; without one the noise part only, and
the notes say so). Not covered: the cover glass in the Jacobians, model errors (systematic, not
in σ).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numba
import numpy as np

from .least_squares import _assemble_gauss_newton
from .multigrid import _CGWork, _Multigrid, _pcg
from .stereo import (ANCHOR_WEIGHT, StereoReconstruction, _camera_arrays, _keys, _project, _residual_jacobian,
                     _view_arrays)
from .uncertainty import (DEFAULT_RNG_SEED, DEFAULT_SAMPLES, NO_COVARIANCE_NOTE, SurfaceUncertainty,
                          UncertaintyError, _geometry, _jacobian_scaled, _ls_rhs, _sample_dg, _screen_tangents,
                          _word, _xi, combine, slope_jacobian)
from .uncertainty_stereo_subgrid import default_noise_stride, subgrid_noise_std

__all__ = ["AnchorNoise", "anchor_noise", "stereo_height_std", "stereo_uncertainty", "with_uncertainty",
           "stereo_with_uncertainty"]

_SEED_STRIDE = 0x9E3779B9  # per-camera offset of the estimator's seed
_RTOL = 1e-4  # relative tolerance of each sample's multigrid-CG solve (docs/benchmarks.md, "Uncertainty: stereo")


# ============================================================================ kernels
@numba.njit(cache=True, nogil=True, parallel=True)
def _anchor_kernel(oA, d, q, rows, cols, za, oB, qB, okB, RB, tB, camB, p_out, qB_out, J_out, r_out, idx_out,
                   w_out, ok_out):
    """Per anchor k of A (pixel rows[k], cols[k], height za[k]) with partner B: the point p on
    A's ray, the interpolated q_B, J = ∂r/∂a (the search's own derivative, :func:`~pmdsim.evaluation.stereo._residual_jacobian`), |r|, and
    the 16 flat pixel indices of B and their cubic-convolution weights. ok_out[k] False where B
    does not see the point."""
    n = rows.size
    W = qB.shape[1]
    for k in numba.prange(0, n):
        ok_out[k] = False
        v = rows[k]
        u = cols[k]
        z = za[k]
        buf = np.empty(3)
        r0 = np.empty(6)
        r1 = np.empty(6)
        r2 = np.empty(6)
        dx = d[v, u, 0]
        dy = d[v, u, 1]
        dz = d[v, u, 2]
        qx = q[v, u, 0]
        qy = q[v, u, 1]
        qz = q[v, u, 2]
        ok, jx, jy = _residual_jacobian(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, r0, r1, r2)
        if not ok:
            continue
        J_out[k, 0] = jx
        J_out[k, 1] = jy
        r_out[k] = np.sqrt(r0[0] * r0[0] + r0[1] * r0[1])
        t = (z - oA[2]) / dz
        px = oA[0] + t * dx
        py = oA[1] + t * dy
        p_out[k, 0] = px
        p_out[k, 1] = py
        p_out[k, 2] = z
        for c in range(3):
            qB_out[k, c] = buf[c]
        _, uu, vv = _project(RB, tB, camB, px, py, z)
        iu = int(np.floor(uu))
        iv = int(np.floor(vv))
        wu = _keys(uu - iu)
        wv = _keys(vv - iv)
        for a in range(4):
            for b in range(4):
                idx_out[k, 4 * a + b] = (iv - 1 + a) * W + (iu - 1 + b)
                w_out[k, 4 * a + b] = wv[a] * wu[b]
        ok_out[k] = True


@numba.njit(cache=True, nogil=True)
def _nonfinite_on(x, S):
    """The number of pixels of S (H, W) where x (H, W, c) has a component that is not finite (one
    pass, no masked copy of x)."""
    H, W = S.shape
    n = 0
    for v in range(H):
        for u in range(W):
            if S[v, u]:
                for m in range(x.shape[2]):
                    if not np.isfinite(x[v, u, m]):
                        n += 1
                        break
    return n


@numba.njit(cache=True, nogil=True)
def _anchor_draw(anchor, cam, pix, coef, seeds, k, n_chunks, out):
    """δa of sample k (out, one per anchor) from the linear terms δa_i = Σ_t coef_t·ξ(cam_t, pix_t)."""
    out[:] = 0.0
    c = k // 32
    kk = k % 32
    for t in range(anchor.size):
        w = _word(seeds[cam[t]], pix[t], c, n_chunks)
        out[anchor[t]] += coef[t, 0] * _xi(w, kk, 0) + coef[t, 1] * _xi(w, kk, 1)


# ============================================================================ anchors
@dataclass(frozen=True, eq=False)
class AnchorNoise:
    """The linearised noise of one camera's anchors: δa_i = Σ_t coef[t]·(ξ_x, ξ_y)(camera[t], pixel[t])
    over the terms t of anchor i (its own pixel and the partner's 16), ξ the unit draws of the
    decoded screen coordinates (σ folded into ``coef``).

    Attributes
    ----------
    std_mm : ndarray (n,)
        Standard uncertainty of each anchor height, mm (NaN where the partner no longer sees it).
    partner : tuple of str
        Each anchor's partner camera.
    anchor, camera, pixel : ndarray of int64 (m,)
        Term → anchor index, camera index (in the evaluation's camera order), flat pixel index.
    coef : ndarray (m, 2)
        mm per unit draw of x_s and y_s.
    """

    std_mm: np.ndarray
    partner: tuple
    anchor: np.ndarray
    camera: np.ndarray
    pixel: np.ndarray
    coef: np.ndarray


def _tangents(setup, screen_model, decoded) -> np.ndarray:
    R = np.asarray((setup.sample.T_world_sample.inv() @ setup.screen.T_world_screen).rotation, dtype=float)
    T = _screen_tangents(R, screen_model, decoded.screen_xy_mm)
    H, W = decoded.valid.shape
    return np.broadcast_to(T, (H, W, 3, 2)) if T.ndim == 2 else T


def anchor_noise(views: dict, decoded: dict, tangents: dict, camera: str, anchors_vu, anchors_z, *,
                 arrays: dict | None = None) -> AnchorNoise:
    """The anchors' linearised noise (:class:`AnchorNoise`, module docstring) of ``camera``.

    Parameters
    ----------
    views : dict name → StereoView
        The stereo evaluation's views (registrations in the reconstruction frame).
    decoded : dict name → ScreenCoordinates
        Every camera's decoded coordinates with ``std_xy_mm`` (H, W, 2).
    tangents : dict name → ndarray (H, W, 3, 2)
        ∂q/∂(x_s, y_s) per camera (reconstruction frame).
    camera : str
    anchors_vu : ndarray of int (n, 2)
        The anchors' pixels (row, column) of ``camera``.
    anchors_z : ndarray (n,)
        Their heights, mm.
    arrays : dict name → tuple, optional
        Every camera's ``_view_arrays`` (o, d, q, valid) when the caller has them (each is a
        full-size copy of the screen points; default: made here).
    """
    names = list(views)
    ci = names.index(camera)
    if arrays is None:
        arrays = {c: _view_arrays(views[c]) for c in names}
    o, d, q, _ = arrays[camera]
    rows = np.ascontiguousarray(anchors_vu[:, 0], dtype=np.int64)
    cols = np.ascontiguousarray(anchors_vu[:, 1], dtype=np.int64)
    za = np.ascontiguousarray(anchors_z, dtype=np.float64)
    n = rows.size
    best = None
    for partner in names:
        if partner == camera:
            continue
        oB, _, qB, okB = arrays[partner]
        RB, tB, camB = _camera_arrays(views[partner])
        out = (np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2)), np.full(n, np.inf), np.zeros((n, 16), np.int64),
               np.zeros((n, 16)), np.zeros(n, dtype=np.bool_))
        _anchor_kernel(o, d, q, rows, cols, za, oB, qB, okB, RB, tB, camB, *out)
        r = np.where(out[6], out[3], np.inf)
        if best is None:
            best = [np.array([partner] * n, dtype=object), oB, *[a.copy() for a in out]]
            best_r = r
            continue
        take = r < best_r
        best_r = np.where(take, r, best_r)
        best[0][take] = partner
        for j in range(7):
            best[2 + j][take] = out[j][take]
    partners, _, p, qB_pt, J, _, idx, w, ok = best
    # A's own term: c_A = −(JᵀJ)⁻¹ Jᵀ G_A T_A diag(σ_A)
    sA = np.nan_to_num(np.asarray(decoded[camera].std_xy_mm, dtype=float)[rows, cols])
    GA = slope_jacobian(o, p[:, None], q[rows, cols][:, None], tangents[camera][rows, cols][:, None])[:, 0]
    jj = np.einsum("ni,ni->n", J, J)
    inv = np.where(ok & (jj > 0), 1.0 / np.where(jj > 0, jj, 1.0), 0.0)
    cA = -inv[:, None] * np.einsum("ni,nij->nj", J, np.nan_to_num(GA)) * sA
    terms_a = [np.arange(n)]
    terms_c = [np.full(n, ci)]
    terms_p = [rows * q.shape[1] + cols]
    terms_k = [cA]
    var = np.sum(cA ** 2, axis=1)
    E1 = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    E2 = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    for partner in set(partners[ok]):
        sel = np.flatnonzero(ok & (partners == partner))
        reg_b = views[partner].registration
        oB = np.asarray(reg_b.o_ref_mm, dtype=float)
        GB = np.concatenate([slope_jacobian(oB, p[sel, None], qB_pt[sel, None], E1)[:, 0],
                             slope_jacobian(oB, p[sel, None], qB_pt[sel, None], E2)[:, 0, :, :1]], axis=-1)  # (m, 2, 3)
        HB, WB = decoded[partner].valid.shape
        iB = idx[sel]
        TB = tangents[partner][iB // WB, iB % WB]  # (m, 16, 3, 2); a reshape would copy a broadcast plane's
        sB = np.asarray(decoded[partner].std_xy_mm, dtype=float).reshape(HB * WB, 2)[idx[sel]]
        # an interpolation pixel without σ leaves the anchor without σ (noted), not with a smaller one
        ok[sel[~(np.isfinite(sB).all(axis=-1) | (w[sel] == 0.0)).all(axis=1)]] = False
        sB = np.nan_to_num(sB)
        jG = np.einsum("ni,nik->nk", J[sel], np.nan_to_num(GB))  # (m, 3)
        cB = (inv[sel] [:, None, None] * w[sel][..., None] * np.einsum("nk,nmkj->nmj", jG, TB) * sB)  # (m, 16, 2)
        var[sel] += np.sum(cB ** 2, axis=(1, 2))
        terms_a.append(np.repeat(sel, 16))
        terms_c.append(np.full(sel.size * 16, names.index(partner)))
        terms_p.append(idx[sel].reshape(-1))
        terms_k.append(cB.reshape(-1, 2))
    std = np.where(ok & (jj > 0), np.sqrt(var), np.nan)  # J = 0: the height is not determined
    return AnchorNoise(std, tuple(partners), np.ascontiguousarray(np.concatenate(terms_a), dtype=np.int64),
                       np.ascontiguousarray(np.concatenate(terms_c), dtype=np.int64),
                       np.ascontiguousarray(np.concatenate(terms_p), dtype=np.int64),
                       np.ascontiguousarray(np.concatenate(terms_k), dtype=np.float64))


# ============================================================================ heights
class _AnchoredLinear:
    """One camera's anchored least-squares heights linearised: δz = N⁻¹(−Jᵀ δr + w² Σ e_i δa_i)."""

    def __init__(self, view, rec, anchors_vu):
        o, d, q, _ = _view_arrays(view)
        S = np.ascontiguousarray(rec.reconstructed)
        self.S = S
        z = np.ascontiguousarray(np.where(S, rec.height_mm, 0.0))
        q = np.ascontiguousarray(np.where(S[..., None], q, 0.0))
        H, W = S.shape
        self.geo = np.zeros((H, W, 8))
        _geometry(o, d, q, S, z, self.geo)
        if not np.isfinite(self.geo[S]).all():
            raise UncertaintyError("the slopes' geometry is not finite at some reconstructed pixel; no σ")
        keep = S[anchors_vu[:, 0], anchors_vu[:, 1]]
        self.keep = keep
        self.av = np.ascontiguousarray(anchors_vu[keep, 0] + 1)
        self.au = np.ascontiguousarray(anchors_vu[keep, 1] + 1)
        shape = (H + 2, W + 2)
        self.D, self.iD, self.Ex, self.Ey, self.rhs = (np.zeros(shape) for _ in range(5))
        _assemble_gauss_newton(o, d, q, S, z, -1, -1, self.D, self.iD, self.Ex, self.Ey, self.rhs)
        self.w2 = ANCHOR_WEIGHT ** 2
        np.add.at(self.D, (self.av, self.au), self.w2)
        self.iD[self.av, self.au] = 1.0 / self.D[self.av, self.au]
        if not self.av.size:
            raise UncertaintyError("no anchor lies on the reconstructed pixels; no σ")
        self.mg = _Multigrid(self.D, self.iD, self.Ex, self.Ey)
        self.work = _CGWork(shape)

    def apply(self, dg, da) -> np.ndarray:
        """δz (H, W) for slope perturbations dg (H, W, 2) (0 off S) and anchor perturbations da
        (n,) of all anchors given at construction; NaN off S."""
        _ls_rhs(self.S, -1, -1, self.geo, dg, self.rhs)
        np.add.at(self.rhs, (self.av, self.au), self.w2 * np.asarray(da)[self.keep])
        if float(np.max(np.abs(self.rhs))) == 0.0:
            return np.where(self.S, 0.0, np.nan)
        x, _, ok = _pcg(self.D, self.iD, self.Ex, self.Ey, self.rhs, 0.0, _RTOL, 500, work=self.work, mg=self.mg)
        if not ok or not np.isfinite(x).all():
            raise UncertaintyError("the linearised anchored least-squares system did not converge (singular or "
                                   "ill-conditioned normal equations); no σ")
        return np.where(self.S, x[1:-1, 1:-1], np.nan)


def _seeds(rng_seed: int, n: int) -> np.ndarray:
    return np.array([(int(rng_seed) + i * _SEED_STRIDE) % (1 << 63) for i in range(n)], dtype=np.int64)


def stereo_height_std(lins: dict, A: dict, noise: dict, *, samples: int = DEFAULT_SAMPLES,
                      rng_seed: int = DEFAULT_RNG_SEED) -> dict:
    """σ (H, W) of every camera's heights, mm (module docstring): ``lins`` name → linearised
    anchored integration, ``A`` name → J·diag(σ_xy) (H, W, 2, 2) of every camera (evaluation
    order), ``noise`` name → :class:`AnchorNoise`; K = ``samples`` shared Rademacher draws."""
    names = list(A)
    K = int(samples)
    if K < 2:
        raise UncertaintyError(f"samples must be ≥ 2, got {samples!r}")
    seeds = _seeds(rng_seed, len(names))
    n_chunks = (K + 31) // 32
    Az = {c: np.ascontiguousarray(np.where(lins[c].S[..., None, None], np.nan_to_num(A[c]), 0.0)) for c in lins}
    acc = {c: np.zeros(lins[c].S.shape) for c in lins}
    dg = {c: np.empty(lins[c].S.shape + (2,)) for c in lins}
    da = {c: np.empty(noise[c].std_mm.size) for c in lins}
    for k in range(K):
        for c, lin in lins.items():
            _sample_dg(Az[c], lin.S, int(seeds[names.index(c)]), k, n_chunks, dg[c])
            an = noise[c]
            _anchor_draw(an.anchor, an.camera, an.pixel, an.coef, seeds, k, n_chunks, da[c])
            acc[c] += np.where(lin.S, lin.apply(dg[c], da[c]), 0.0) ** 2
    return {c: np.where(lins[c].S, np.sqrt(acc[c] / K), np.nan) for c in lins}


def stereo_uncertainty(setup, views: dict, decoded: dict, stereo: StereoReconstruction, *, screen_model=None,
                       samples: int = DEFAULT_SAMPLES, rng_seed: int = DEFAULT_RNG_SEED,
                       noise_stride: int | None = None) -> dict:
    """Per camera the :class:`~pmdsim.evaluation.uncertainty.SurfaceUncertainty` of a stereo
    evaluation and its anchors' σ (module docstring).

    Parameters
    ----------
    setup : Setup
        The evaluating setup (reconstruction frame: its sample frame).
    views : dict name → StereoView
    decoded : dict name → ScreenCoordinates
        With ``std_xy_mm``.
    stereo : StereoReconstruction
        The result of :func:`~pmdsim.evaluation.stereo.reconstruct_stereo` for ``views``.
    screen_model : surface, optional
        The evaluation's screen model (None: the plane).
    samples, rng_seed
        K and the seed of the height σ estimator.
    noise_stride : int, optional
        Subgrid stride s of the heights' noise σ (:mod:`pmdsim.evaluation.uncertainty_stereo_subgrid`);
        default :func:`~pmdsim.evaluation.uncertainty_stereo_subgrid.default_noise_stride` (every
        pixel below 150 px in the shorter image side). 1: every pixel.

    Returns
    -------
    dict name → (SurfaceUncertainty, ndarray (n,))
        The σ maps and each anchor's height σ, µm.

    Raises
    ------
    UncertaintyError
        σ cannot be computed (the caller keeps the heights).
    """
    if len(views) < 2:
        raise UncertaintyError(f"stereo σ needs at least two cameras' views, got {len(views)}")
    missing = [c for c in views if c not in stereo.cameras or c not in decoded]
    if missing:
        raise UncertaintyError(f"camera(s) {missing} have a view but no stereo reconstruction or decoded images")
    if int(samples) < 2:
        raise UncertaintyError(f"samples must be ≥ 2, got {samples!r}")
    tangents = {c: _tangents(setup, screen_model, decoded[c]) for c in views}
    arrays = {c: _view_arrays(views[c]) for c in views}  # once per camera (each a full-size copy)
    first = stereo.cameras[next(iter(views))].reconstruction.reconstructed.shape
    s = default_noise_stride(first) if noise_stride is None else int(noise_stride)
    if s < 1:
        raise UncertaintyError(f"noise_stride must be ≥ 1, got {noise_stride!r}")
    jac, noise = {}, {}
    for c, view in views.items():
        rec = stereo.cameras[c].reconstruction
        std = np.asarray(decoded[c].std_xy_mm, dtype=float)
        bad = _nonfinite_on(std, np.asarray(rec.reconstructed, dtype=bool))
        if bad:
            raise UncertaintyError(f"camera {c!r}: the decoder's σ (std_xy_mm) is not finite at {bad} reconstructed "
                                   f"pixel(s); no σ of the surface")
        # the Jacobian reads σ only on the reconstructed pixels, where it is finite: no NaN-free copy
        jac[c] = (view.registration.o_ref_mm, rec.p_sample_mm, view.registration.q_ref_mm, tangents[c], std)
        sc = stereo.cameras[c]
        noise[c] = anchor_noise(views, decoded, tangents, c, sc.anchor_pixels, sc.anchor_height_mm, arrays=arrays)
    if s == 1:
        A, g_noise, lins = {}, {}, {}
        for c, view in views.items():
            rec = stereo.cameras[c].reconstruction
            A[c], g_noise[c] = _jacobian_scaled(*jac[c][:4], rec.reconstructed, jac[c][4])
            lins[c] = _AnchoredLinear(view, rec, stereo.cameras[c].anchor_pixels)
        h = stereo_height_std(lins, A, noise, samples=samples, rng_seed=rng_seed)
    else:  # the slopes' σ and the subgrid's draws in one pass (no (H, W, 2, 2) array)
        h, g_noise = subgrid_noise_std(views, {c: stereo.cameras[c].reconstruction for c in views},
                                       {c: stereo.cameras[c].anchor_pixels for c in views}, jac, noise,
                                       _seeds(rng_seed, len(jac)), samples=int(samples), stride=s,
                                       offset=(int(stereo.stride_px) // 2) % s, arrays=arrays)
    del arrays  # its pages serve the calibration part's arrays (fresh pages cost more than the arithmetic here)
    cov = getattr(setup, "calibration_covariance", None)
    cal = None
    if cov is not None:
        from .uncertainty_calibration import CalibrationUncertaintyError
        from .uncertainty_stereo_calibration import stereo_calibration_contribution

        try:
            cal = stereo_calibration_contribution(setup, decoded, stereo, screen_model=screen_model)
        except CalibrationUncertaintyError as exc:
            raise UncertaintyError(f"stereo: the calibration's contribution cannot be computed: {exc}") from None
    out = {}
    for c in views:
        S = np.asarray(stereo.cameras[c].reconstruction.reconstructed, dtype=bool)
        if _nonfinite_on(h[c][..., None], S):
            raise UncertaintyError(f"camera {c!r}: the height σ is not finite at some reconstructed pixel")
        a_std = noise[c].std_mm
        fin = a_std[np.isfinite(a_std)]
        notes = [f"stereo: absolute heights gauged by {a_std.size} normal-consistency anchors (weight "
                 f"{ANCHOR_WEIGHT:g}), their σ included (median {np.median(fin) * 1e3 if fin.size else float('nan'):.3g} "
                 f"µm)"]
        if s > 1:
            notes.append(f"stereo: the heights' noise σ estimated on a subgrid of every {s}th pixel (slopes' noise "
                         f"block-averaged, every anchor's own σ) and interpolated")
        if fin.size < a_std.size:
            notes.append(f"{a_std.size - fin.size} anchors without σ (the partner does not see them at the height "
                         f"found): their own noise is not included")
        if cal is None:
            notes.append(NO_COVARIANCE_NOTE)
        else:
            notes.append(f"stereo: calibration covariance propagated through the anchors and the anchored integration "
                         f"({len(cal.parameters)} parameters, {cal.n_axes} principal axes)")
            notes.extend(cal.notes)
        if setup.screen.cover_glass is not None and getattr(setup.screen.cover_glass, "present", False):
            notes.append("cover glass: the refraction's effect on the slopes' Jacobian is not included")
        if cal is None:
            g_cal = np.where(S[..., None], 0.0, np.nan) * np.ones(S.shape + (2,))
            h_cal = np.where(S, 0.0, np.nan)
            a_cal = np.zeros(a_std.size)
        else:  # NaN off S already (stereo_calibration_contribution)
            g_cal = cal.cameras[c].slope_std_urad
            h_cal = cal.cameras[c].height_std_um
            a_cal = cal.anchor_height_std_um[c]
        h_um = h[c]  # in place: the arrays are this function's own (the values of h[c] * 1e3)
        h_um *= 1e3
        g_urad = g_noise[c]
        g_urad *= 1e6
        unc = SurfaceUncertainty(slope_std_urad=combine(g_urad, g_cal), height_std_um=combine(h_um, h_cal),
                                 slope_std_noise_urad=g_urad, height_std_noise_um=h_um,
                                 slope_std_calibration_urad=g_cal, height_std_calibration_um=h_cal,
                                 samples=int(samples), notes=tuple(notes))
        out[c] = (unc, combine(a_std * 1e3, a_cal))
    return out


def with_uncertainty(stereo: StereoReconstruction, uncs: dict) -> StereoReconstruction:
    """``stereo`` with each camera's ``uncertainty`` and ``anchor_height_std_um`` set from
    :func:`stereo_uncertainty`'s result (cameras missing from ``uncs`` unchanged)."""
    cams = {c: (replace(sc, uncertainty=uncs[c][0], anchor_height_std_um=uncs[c][1]) if c in uncs else sc)
            for c, sc in stereo.cameras.items()}
    return replace(stereo, cameras=cams)


def stereo_with_uncertainty(setup, views: dict, decoded: dict, stereo: StereoReconstruction, *, screen_model=None,
                            **options) -> tuple[StereoReconstruction, dict, list]:
    """:func:`stereo_uncertainty` attached to ``stereo`` (:func:`with_uncertainty`), or the
    heights without σ and why: the one way the API, ``pmdsim evaluate --stereo`` and the
    experiments compute a stereo evaluation's σ.

    Returns
    -------
    (StereoReconstruction, dict name → SurfaceUncertainty or None, list of str)
        The result (with σ where computed), each camera's σ, and the warnings (empty, or one
        line saying why there is no σ; the heights stand).
    """
    try:
        res = stereo_uncertainty(setup, views, decoded, stereo, screen_model=screen_model, **options)
    except UncertaintyError as exc:
        return stereo, {c: None for c in views}, [f"stereo: no uncertainty (σ datasets omitted, heights written): {exc}"]
    return with_uncertainty(stereo, res), {c: u for c, (u, _) in res.items()}, []
