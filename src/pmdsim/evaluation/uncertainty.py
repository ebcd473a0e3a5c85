"""Per-pixel standard uncertainties of the reconstructed slopes and heights (issue 22).

Vocabulary (GUM, JCGM 100:2008): every σ here is a *standard uncertainty* (coverage factor
k = 1; multiply by k = 2 for an expanded uncertainty of about 95 % for Gaussian errors).
docs/conventions.md "Uncertainty" states what σ covers and what it does not.

**Noise contribution.** The decoder gives each pixel's standard uncertainty of the decoded
screen coordinates, ``std_xy_mm`` (x and y from independent pattern directions, so
uncorrelated). The slopes g = (−m_x/m_z, −m_y/m_z) of the bisector m = â + b̂ (â towards the
camera, b̂ towards the screen point q; :mod:`pmdsim.evaluation.integration`) depend on q through
b̂ only:

    ∂g/∂q = G_m (I − b̂ b̂ᵀ)/|q − p|,   G_m = [[−1/m_z, 0, m_x/m_z²], [0, −1/m_z, m_y/m_z²]],

and q on the screen coordinates (x_s, y_s) through the screen model, ∂q/∂(x_s, y_s) =
R_ref_screen [e_x + h_x e_z, e_y + h_y e_z] (h the screen model's height). The slope σ is the
linear propagation of ``std_xy_mm`` through J = ∂g/∂(x_s, y_s) (exact for small noise).

The integrated heights are correlated: a height is a sum of slopes along paths from the seed.
They are linear in the slope perturbations (linearised at the reconstruction): the stepwise
integration's recursion (each pixel from its neighbours of the previous wavefront) and the
least-squares integration's normal equations (the Gauss–Newton matrix at convergence, its
sampled right-hand sides solved in batches by DCT- or multigrid-preconditioned CG,
:mod:`pmdsim.evaluation.uncertainty_solve`). The covariance C = M Σ Mᵀ of the heights is estimated by
K sampled right-hand sides: δg = J (σ ∘ ξ) with ξ independent Rademacher (±1) per pixel and axis,
so that E[δg δgᵀ] = J Σ Jᵀ exactly, propagated through the linear map M; σ_z² = mean_k δz_k²
(the mean of δz is 0 by construction). The relative standard error of the estimated σ is at most
about 1/√(2K) (8.8 % at K = 64; Gaussian ξ give exactly that, Rademacher ξ less); measured in
tests/test_uncertainty.py and docs/benchmarks.md. Sampling is seeded (reproducible).

**Relative to what fixes the height.** The seed pixel's height is given, so its noise σ is 0
and σ grows with the distance from it. An anchor with a standard uncertainty of its own (the
distance of a :class:`~pmdsim.evaluation.anchor.DistanceAnchor`, the height of a
:class:`~pmdsim.evaluation.anchor.HeightAnchor`) adds ∂z/∂a · σ_a per pixel, ∂z/∂a from one more
anchored reconstruction with the anchor perturbed (a finite difference).

Not covered by this module: the calibration's covariance (added by
:mod:`pmdsim.evaluation.uncertainty_calibration` when the setup carries one), the cover glass's
refraction in the slope Jacobian (the apparent points are treated as screen points), and model
errors (e.g. a planar screen model of a bulged screen): they are systematic and not in σ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from ..errors import PmdsimError
from ..geometry.compact import compact_repr
from ..geometry.kernel_args import readonly
from .least_squares import _assemble_gauss_newton, _row_geometry
from .multigrid import _CGWork, _Multigrid, _pcg
from .uncertainty_stepwise import _draw_word, _edge_jac, _seed_key, stepwise_sampled

__all__ = ["UncertaintyError", "SurfaceUncertainty", "slope_jacobian", "slope_std", "height_std_sampled",
           "anchor_height_derivative", "surface_uncertainty", "combine", "DEFAULT_SAMPLES", "NO_COVARIANCE_NOTE"]

#: Default number of sampled right-hand sides K of the height σ estimator.
DEFAULT_SAMPLES = 64

#: Default seed of the estimator's random right-hand sides.
DEFAULT_RNG_SEED = 20261127

NO_COVARIANCE_NOTE = "setup carries no calibration covariance: noise part only"

_STEPWISE_SINGULAR = "the linearised stepwise recursion is singular (a step's height coefficient vanishes); no σ"

_GEOMETRY_NOT_FINITE = "the slopes' geometry is not finite at some reconstructed pixel; no σ"


class UncertaintyError(PmdsimError, ArithmeticError):
    """The uncertainty of a reconstruction cannot be computed (e.g. the linearised system is
    singular or its solve does not converge); the heights themselves stand."""


@dataclass(frozen=True, eq=False)
class SurfaceUncertainty:
    """Per-pixel standard uncertainties (k = 1) of one camera's reconstruction.

    Attributes
    ----------
    slope_std_urad : ndarray (H, W, 2)
        Combined standard uncertainty of the slopes (∂z/∂x, ∂z/∂y), µrad (1e-6 of the slope).
    height_std_um : ndarray (H, W)
        Combined standard uncertainty of the height, µm, relative to what fixes the heights.
    slope_std_noise_urad, height_std_noise_um
        The images' noise contribution (decoder σ through registration and integration; the
        anchor's own σ included in the heights).
    slope_std_calibration_urad, height_std_calibration_um
        The calibration covariance's contribution (0 when the setup carries none).
    samples : int
        K of the height σ estimator.
    notes : tuple of str
        What the numbers cover (e.g. :data:`NO_COVARIANCE_NOTE`).

    NaN where not reconstructed. Combined = root-sum-square of the contributions.
    """

    __repr__ = compact_repr

    slope_std_urad: np.ndarray
    height_std_um: np.ndarray
    slope_std_noise_urad: np.ndarray
    height_std_noise_um: np.ndarray
    slope_std_calibration_urad: np.ndarray
    height_std_calibration_um: np.ndarray
    samples: int = DEFAULT_SAMPLES
    notes: tuple = field(default=())

    def dominant(self) -> str:
        """"noise" or "calibration": the contribution with the larger RMS height σ."""
        rn = _rms(self.height_std_noise_um)
        rc = _rms(self.height_std_calibration_um)
        return "calibration" if rc > rn else "noise"

    def describe(self) -> dict:
        """The ``uncertainty`` attribute of evaluation.h5 (JSON-ready)."""
        return {"quantity": "standard uncertainty (GUM, JCGM 100:2008)", "coverage_factor_k": 1,
                "method": "linear propagation of the decoder's std_xy_mm through the reflection law; heights: "
                          "Hutchinson-type estimator, K Rademacher right-hand sides through the linearised "
                          "integration (docs/conventions.md, Uncertainty)",
                "samples_K": int(self.samples),
                "estimator_relative_error": round(1.0 / math.sqrt(2 * self.samples), 4),
                "combined": "root-sum-square of noise and calibration contributions",
                "heights_relative_to": "the seed pixel / anchor (anchor σ included where given)",
                "notes": list(self.notes)}


def _rms(a) -> float:
    a = np.asarray(a)
    f = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(f * f))) if f.size else 0.0


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _pixel_jacobian(o, p, q, T, v, u, tv, tu, sig, a, g):
    """Pixel (v, u): a (2, 2) = J·diag(σ) with J = ∂g/∂(x_s, y_s) (module docstring), σ = sig[v, u]
    (2,), and g (2,) = the slopes' σ sqrt(Σ_j a_ij²); the screen tangents T[tv, tu] (3, 2)."""
    ax = o[0] - p[v, u, 0]
    ay = o[1] - p[v, u, 1]
    az = o[2] - p[v, u, 2]
    la = np.sqrt(ax * ax + ay * ay + az * az)
    bx = q[v, u, 0] - p[v, u, 0]
    by = q[v, u, 1] - p[v, u, 1]
    bz = q[v, u, 2] - p[v, u, 2]
    lb = np.sqrt(bx * bx + by * by + bz * bz)
    bx /= lb
    by /= lb
    bz /= lb
    mx = ax / la + bx
    my = ay / la + by
    mz = az / la + bz
    imz = 1.0 / mz
    for j in range(2):
        tx = T[tv, tu, 0, j]
        ty = T[tv, tu, 1, j]
        tz = T[tv, tu, 2, j]
        bt = bx * tx + by * ty + bz * tz
        # dm = (I − b̂b̂ᵀ) t / |b|; dg_x = (−dm_x + g_x·(−dm_z))/m_z … = −(dm_x − m_x/m_z dm_z)/m_z
        dmx = (tx - bt * bx) / lb
        dmy = (ty - bt * by) / lb
        dmz = (tz - bt * bz) / lb
        a[0, j] = (-dmx + mx * imz * dmz) * imz * sig[v, u, j]
        a[1, j] = (-dmy + my * imz * dmz) * imz * sig[v, u, j]
    for i in range(2):
        g[i] = np.sqrt(a[i, 0] ** 2 + a[i, 1] ** 2)


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _jacobian_kernel(o, p, q, T, S, sig, A, gstd):
    """Per pixel of S: A = J·diag(σ) (2, 2) and the slopes' σ (:func:`_pixel_jacobian`); T
    (H, W, 3, 2) or (1, 1, 3, 2) the screen tangents. NaN off S."""
    H, W = S.shape
    per_pixel = 0 if T.shape[0] == 1 else 1
    for v in numba.prange(0, H):
        for u in range(W):
            if not S[v, u]:
                for i in range(2):
                    gstd[v, u, i] = np.nan
                    for j in range(2):
                        A[v, u, i, j] = np.nan
                continue
            _pixel_jacobian(o, p, q, T, v, u, v * per_pixel, u * per_pixel, sig, A[v, u], gstd[v, u])


def _tangent_array(dq_dxy) -> np.ndarray:
    """The screen tangents as the Jacobian kernels take them: (H, W, 3, 2), or (1, 1, 3, 2) for one
    for every pixel — a (3, 2) array or a broadcast one (no full-size copy of it)."""
    T = np.asarray(dq_dxy, dtype=float)
    if T.ndim == 2:
        T = T[None, None]
    elif T.strides[0] == 0 and T.strides[1] == 0:
        T = T[:1, :1]
    return readonly(np.ascontiguousarray(T))  # one kernel signature whoever owns the array


def _jacobian_scaled(o, p, q, dq_dxy, S, sig):
    """A = J·diag(σ) (H, W, 2, 2) and the slopes' σ (H, W, 2) (:func:`_jacobian_kernel`); σ is read
    on S only."""
    T = _tangent_array(dq_dxy)
    H, W = S.shape
    A = np.empty((H, W, 2, 2))
    gstd = np.empty((H, W, 2))
    _jacobian_kernel(np.asarray(o, dtype=float), np.ascontiguousarray(p, dtype=float),
                     np.ascontiguousarray(q, dtype=float), T, np.ascontiguousarray(S),
                     np.ascontiguousarray(sig, dtype=float), A, gstd)
    return A, gstd


def slope_jacobian(o, p, q, dq_dxy) -> np.ndarray:
    """∂g/∂(x_s, y_s): the slopes' Jacobian w.r.t. the decoded screen coordinates,
    ∂g/∂q = G_m (I − b̂ b̂ᵀ)/|q − p| times ∂q/∂(x_s, y_s) (module docstring).

    Parameters
    ----------
    o : ndarray (3,)
        Camera centre, mm (reconstruction frame).
    p, q : ndarray (H, W, 3)
        Surface points and screen points, mm.
    dq_dxy : ndarray (H, W, 3, 2) or (3, 2)
        ∂q/∂(x_s, y_s) (the screen model's tangent vectors in the reconstruction frame).

    Returns
    -------
    ndarray (H, W, 2, 2)
        J[..., i, j] = ∂g_i/∂xy_j (slopes dimensionless per mm); NaN where p or q is not finite.
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    S = np.isfinite(p).all(axis=-1) & np.isfinite(q).all(axis=-1)
    return _jacobian_scaled(o, p, q, dq_dxy, S, np.ones(S.shape + (2,)))[0]


def slope_std(J, std_xy_mm) -> np.ndarray:
    """Standard uncertainty (H, W, 2) of the slopes (dimensionless) from J (H, W, 2, 2) and
    uncorrelated screen-coordinate σ (H, W, 2), mm: sqrt(diag(J Σ Jᵀ))."""
    s2 = np.asarray(std_xy_mm, dtype=float) ** 2
    return np.sqrt(J[..., 0] ** 2 * s2[..., None, 0] + J[..., 1] ** 2 * s2[..., None, 1])


def _screen_tangents(reg_T_ref_screen_R, screen_model, xy) -> np.ndarray:
    """∂q_ref/∂(x_s, y_s): R (e_x + h_x e_z, e_y + h_y e_z), (H, W, 3, 2); (3, 2) for a plane."""
    R = np.asarray(reg_T_ref_screen_R, dtype=float)
    if screen_model is None:
        return np.ascontiguousarray(R[:, :2])
    H, W = xy.shape[:2]
    t = np.zeros((H, W, 3, 2))
    t[..., 0, 0] = 1.0
    t[..., 1, 1] = 1.0
    x0, x1, y0, y1 = screen_model.bounds_mm
    ok = np.isfinite(xy).all(axis=-1)
    gx = np.where(ok, np.clip(xy[..., 0], x0, x1), x0)
    gy = np.where(ok, np.clip(xy[..., 1], y0, y1), y0)
    g = np.asarray(screen_model.gradient(gx, gy), dtype=float)
    t[..., 2, 0] = g[..., 0]
    t[..., 2, 1] = g[..., 1]
    return np.einsum("ij,hwjk->hwik", R, t)


@numba.njit(cache=True, nogil=True, inline="always")
def _word(seed, pix, chunk, n_chunks):
    """64 random bits of pixel ``pix`` for samples 32·chunk … 32·chunk + 31 (bit 2k: ξ_x, 2k+1: ξ_y)."""
    return _draw_word(_seed_key(seed), pix, chunk, n_chunks)


@numba.njit(cache=True, nogil=True, inline="always")
def _xi(w, k, axis):
    return 1.0 - 2.0 * float((w >> np.uint64(2 * k + axis)) & np.uint64(1))


@numba.njit(cache=True, nogil=True, parallel=True)
def _sample_dg(A, S, seed, k, n_chunks, dg):
    """dg = A ξ_k (H, W, 2) of sample k (0 off S), ξ the counter-based Rademacher draws."""
    H, W = S.shape
    c = k // 32
    kk = k % 32
    for v in numba.prange(0, H):
        for u in range(W):
            if not S[v, u]:
                dg[v, u, 0] = 0.0
                dg[v, u, 1] = 0.0
                continue
            w = _word(seed, v * W + u, c, n_chunks)
            x = _xi(w, kk, 0)
            y = _xi(w, kk, 1)
            dg[v, u, 0] = A[v, u, 0, 0] * x + A[v, u, 0, 1] * y
            dg[v, u, 1] = A[v, u, 1, 0] * x + A[v, u, 1, 1] * y


@numba.njit(cache=True, nogil=True, parallel=True)
def _geometry(o, d, q, S, z, geo):
    for v in numba.prange(0, S.shape[0]):
        _row_geometry(o, d, q, S, z, v, geo[v])


@numba.njit(cache=True, nogil=True)
def _bfs(S, sv, su, layer, order):
    """Wavefront index (4-connected distance from the seed within S; −1 unreached) and the
    pixels in wavefront order (flat indices). Returns the number of pixels reached."""
    H, W = S.shape
    layer[:, :] = -1
    layer[sv, su] = 0
    order[0] = sv * W + su
    n = 1
    i = 0
    while i < n:
        k = order[i]
        i += 1
        v = k // W
        u = k - v * W
        for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            vv = v + dv
            uu = u + du
            if 0 <= vv < H and 0 <= uu < W and S[vv, uu] and layer[vv, uu] < 0:
                layer[vv, uu] = layer[v, u] + 1
                order[n] = vv * W + uu
                n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _stepwise_linear(geo, layer, order, n, dg, dz):
    """The stepwise recursion linearised: for each pixel b (wavefront order) from its
    neighbours a_i of the previous wavefront, Σ_i [J_a δz_a + J_b δz_b − ½(δg_a + δg_b)·Δxy] = 0.
    Returns False if a pixel's coefficient Σ J_b vanishes."""
    H, W = layer.shape
    dz[:, :] = np.nan
    k0 = order[0]
    dz[k0 // W, k0 - (k0 // W) * W] = 0.0
    for i in range(1, n):
        k = order[i]
        vb = k // W
        ub = k - vb * W
        lb = layer[vb, ub]
        num = 0.0
        den = 0.0
        for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            va = vb + dv
            ua = ub + du
            if not (0 <= va < H and 0 <= ua < W) or layer[va, ua] != lb - 1:
                continue
            Ja, Jb, dx, dy = _edge_jac(geo, va, ua, vb, ub)
            num += 0.5 * ((dg[va, ua, 0] + dg[vb, ub, 0]) * dx + (dg[va, ua, 1] + dg[vb, ub, 1]) * dy) - Ja * dz[va, ua]
            den += Jb
        if den == 0.0 or not np.isfinite(num / den):
            return False
        dz[vb, ub] = num / den
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _subtract_edge(rhs, dg, v, u, vb, ub, Ja, Jb, dx, dy, a_free, b_free):
    """The edge (v, u) → (vb, ub)'s terms of −Jᵀ δr, δr = −½(δg_a + δg_b)·Δxy (left out if
    J_a, J_b or δr is not finite; a pixel not free gets none)."""
    dr = -0.5 * ((dg[v, u, 0] + dg[vb, ub, 0]) * dx + (dg[v, u, 1] + dg[vb, ub, 1]) * dy)
    if np.isfinite(Ja) and np.isfinite(Jb) and np.isfinite(dr):
        if a_free:
            rhs[v + 1, u + 1] -= Ja * dr
        if b_free:
            rhs[vb + 1, ub + 1] -= Jb * dr


@numba.njit(cache=True, nogil=True)
def _ls_rhs(S, sv, su, geo, dg, rhs):
    """−Jᵀ δr of the trapezoidal equations for slope perturbations dg (padded rhs), with
    δr_e = −½(δg_a + δg_b)·Δxy_e; the seed is not an unknown."""
    H, W = S.shape
    rhs[:, :] = 0.0
    for v in range(H):
        for u in range(W):
            if not S[v, u]:
                continue
            a_free = not (v == sv and u == su)
            for dv, du in ((0, 1), (1, 0)):
                vb = v + dv
                ub = u + du
                if vb >= H or ub >= W or not S[vb, ub]:
                    continue
                Ja, Jb, dx, dy = _edge_jac(geo, v, u, vb, ub)
                _subtract_edge(rhs, dg, v, u, vb, ub, Ja, Jb, dx, dy, a_free, not (vb == sv and ub == su))


class _LinearisedIntegration:
    """The reconstruction's height map linearised in the slope perturbations: δz = M δg."""

    def __init__(self, o, d, q, rec):
        S = np.ascontiguousarray(rec.reconstructed)
        self.S = S
        self.seed = tuple(int(x) for x in rec.seed_pixel)
        self.method = rec.method
        self._mg = self._work = None  # least squares: built on first use (:attr:`mg`, :attr:`work`)
        z = np.ascontiguousarray(np.where(S, rec.height_mm, 0.0))
        d = np.ascontiguousarray(d, dtype=float)
        q = np.ascontiguousarray(np.where(S[..., None], q, 0.0))
        o = np.asarray(o, dtype=float)
        H, W = S.shape
        self.geo = np.zeros((H, W, 8))
        _geometry(o, d, q, S, z, self.geo)
        if not np.isfinite(self.geo).all(axis=-1)[S].all():  # (no (n, 8) copy of the geometry)
            raise UncertaintyError(_GEOMETRY_NOT_FINITE)
        if self.method == "stepwise":
            self.layer = np.empty((H, W), dtype=np.int64)
            self.order = np.empty(H * W, dtype=np.int64)
            self.n = _bfs(S, self.seed[0], self.seed[1], self.layer, self.order)
            lo = self.layer.reshape(-1)[self.order[:self.n]]
            self.starts = np.concatenate([[0], np.flatnonzero(np.diff(lo)) + 1, [self.n]]).astype(np.int64)
            self.pos = np.zeros((H, W), dtype=np.int64)
            self.pos.reshape(-1)[self.order[:self.n]] = np.arange(self.n) - self.starts[lo]
        else:
            # Memory (issue 25): the σ's right-hand sides read each edge's coefficients in single
            # precision (uncertainty_solve._edge_coefficients), formed first so that the geometry
            # map (147 MB at 1920×1200) is gone before the operator is assembled; the height and
            # slope copies go after it.
            from .uncertainty_solve import _edge_coefficients  # noqa: PLC0415 (it imports this module)

            self.edges = np.empty((H, 8, W), dtype=np.float32)
            _edge_coefficients(self.geo, S, self.edges)
            del self.geo
            shape = (H + 2, W + 2)
            self.D, iD, self.Ex, self.Ey, rhs = (np.zeros(shape) for _ in range(5))
            _assemble_gauss_newton(o, d, q, S, z, self.seed[0], self.seed[1], self.D, iD, self.Ex, self.Ey, rhs)
            del iD, rhs, q, z
            if not (self.D > 0).any():
                raise UncertaintyError("the least-squares normal equations have no unknown; no σ")
            # iD and the right-hand side's array: only the multigrid CG's (:attr:`iD`, :meth:`apply`);
            # the DCT-preconditioned σ of a full frame never reads them (37 MB at 1920×1200)
            self._iD = self._rhs = None

    @property
    def iD(self):
        """1/D on the unknowns, 0 elsewhere (padded; as the assembly's, built on first use)."""
        if self._iD is None:
            self._iD = np.zeros_like(self.D)
            np.divide(1.0, self.D, out=self._iD, where=self.D > 0.0)
        return self._iD

    @property
    def mg(self):
        """The multigrid preconditioner of N (built on first use: the DCT-preconditioned σ
        solves of a full frame never need it, nor its ≈ 125 MB at 1920×1200)."""
        if self._mg is None:
            self._mg = _Multigrid(self.D, self.iD, self.Ex, self.Ey)
        return self._mg

    @property
    def work(self):
        """The multigrid CG's work arrays (:meth:`apply`; built on first use, 92 MB at 1920×1200)."""
        if self._work is None:
            self._work = _CGWork(self.D.shape)
        return self._work

    def apply(self, dg) -> np.ndarray:
        """δz (H, W) for slope perturbations dg (H, W, 2) (0 where not reconstructed); NaN off S."""
        H, W = self.S.shape
        if self.method == "stepwise":
            dz = np.empty((H, W))
            if not _stepwise_linear(self.geo, self.layer, self.order, self.n, dg, dz):
                raise UncertaintyError(_STEPWISE_SINGULAR)
            return dz
        if self._rhs is None:
            self._rhs = np.zeros_like(self.D)
        from .uncertainty_solve import _ls_rhs_edges  # noqa: PLC0415 (it imports this module)

        _ls_rhs_edges(self.S, self.seed[0], self.seed[1], self.edges, dg, self._rhs)
        scale = float(np.max(np.abs(self._rhs)))
        if scale == 0.0:
            return np.where(self.S, 0.0, np.nan)
        x, _, ok = _pcg(self.D, self.iD, self.Ex, self.Ey, self._rhs, 0.0, 1e-6, 500, work=self.work, mg=self.mg)
        if not ok or not np.isfinite(x).all():
            raise UncertaintyError("the linearised least-squares system did not converge (singular or "
                                   "ill-conditioned normal equations); no σ")
        return np.where(self.S, x[1:-1, 1:-1], np.nan)


def _sampled_std(lin, A, samples: int, rng_seed: int, *, overwrite: bool = False) -> np.ndarray:
    """σ (H, W) of the heights, mm, from A = J·diag(σ_xy) (H, W, 2, 2) with ``samples``
    counter-based Rademacher right-hand sides (reproducible for a seed). ``overwrite``: A (a
    C-contiguous float64 array the caller no longer needs) is zeroed off S in place instead of
    being copied (the same values: 147 MB less at a 1920×1200 camera's σ)."""
    S = lin.S
    if overwrite and A.dtype == np.float64 and A.flags.c_contiguous and A.flags.writeable:
        np.copyto(A, 0.0, where=~S[..., None, None])
    else:
        A = np.ascontiguousarray(np.where(S[..., None, None], A, 0.0))
    seed = int(rng_seed) % (1 << 63)
    K = int(samples)
    acc = np.zeros(S.shape)
    if lin.method == "stepwise":
        if not stepwise_sampled(lin.geo, lin.layer, lin.order, lin.starts, lin.pos, A, seed, K, acc):
            raise UncertaintyError(_STEPWISE_SINGULAR)
    else:  # batched solves (DCT- or multigrid-preconditioned CG)
        from .uncertainty_solve import least_squares_sum_sq  # noqa: PLC0415 (it imports this module)

        acc = least_squares_sum_sq(lin, A, seed, K)
    return np.where(S, np.sqrt(acc / K), np.nan)


def height_std_sampled(o, d, q, rec, J, std_xy_mm, *, samples: int = DEFAULT_SAMPLES,
                       rng_seed: int = DEFAULT_RNG_SEED) -> np.ndarray:
    """Standard uncertainty (H, W) of the heights, mm, from uncorrelated screen-coordinate σ
    (H, W, 2) through the slopes' Jacobian J (H, W, 2, 2) and the reconstruction's linearised
    integration (module docstring), with ``samples`` Rademacher right-hand sides.

    Raises
    ------
    UncertaintyError
        The linearised system is singular or its solve does not converge.
    """
    if int(samples) < 2:
        raise UncertaintyError(f"samples must be ≥ 2, got {samples!r}")
    lin = _LinearisedIntegration(o, d, q, rec)
    sig = np.nan_to_num(np.asarray(std_xy_mm, dtype=float))
    return _sampled_std(lin, np.nan_to_num(J) * sig[..., None, :], samples, rng_seed, overwrite=True)


def anchor_height_derivative(reg, anchor, method, *, T_world_ref, step_mm: float = 1e-3) -> np.ndarray:
    """∂z/∂a (H, W): how the anchored heights change per mm of the anchor's own quantity (the
    distance of a DistanceAnchor, the height of a HeightAnchor), by a central difference of two
    anchored reconstructions. Zero-size anchors ('none'): zeros."""
    from .anchor import DistanceAnchor, HeightAnchor, reconstruct_anchored

    if isinstance(anchor, DistanceAnchor):
        pert = [DistanceAnchor(anchor.pixel_vu, anchor.distance_mm + s, anchor.point_world_mm)
                for s in (step_mm, -step_mm)]
    elif isinstance(anchor, HeightAnchor):
        pert = [HeightAnchor(anchor.pixel_vu, anchor.height_mm + s) for s in (step_mm, -step_mm)]
    else:
        return np.zeros(reg.valid.shape)
    z = [reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=a, T_world_ref=T_world_ref,
                              method=method).reconstruction.height_mm for a in pert]
    return (z[0] - z[1]) / (2 * step_mm)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rss2_kernel(a, b, out):
    # sqrt(a² + b²) element by element: the same IEEE operations in the same order as numpy's
    # ``np.sqrt(0 + a**2 + b**2)`` (x + 0 = x for x = a² ≥ 0; no fused multiply-add without
    # fastmath), in one pass instead of five full-size temporaries.
    for i in range(a.shape[0]):
        out[i] = np.sqrt(a[i] * a[i] + b[i] * b[i])


def combine(*parts) -> np.ndarray:
    """Root-sum-square of standard uncertainties (uncorrelated contributions).

    Two float arrays of one shape (the σ maps: (H, W) or (H, W, 2)) are combined by one compiled
    pass, bit for bit the numpy expression used otherwise (tests/test_uncertainty.py)."""
    arrs = [np.asarray(p, dtype=float) for p in parts]
    if len(arrs) == 2 and arrs[0].shape == arrs[1].shape and arrs[0].size >= 4096:
        a, b = (np.ascontiguousarray(x).reshape(-1) for x in arrs)
        out = np.empty(arrs[0].shape)
        _rss2_kernel(a, b, out.reshape(-1))
        return out
    return np.sqrt(sum(p ** 2 for p in arrs))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rss_equals_first(a, b):
    """Whether sqrt(a² + b²) (:func:`_rss2_kernel`'s operations) equals a element by element (NaN
    equal to NaN, as ``np.array_equal(..., equal_nan=True)``), without the array of sums."""
    for i in range(a.shape[0]):
        t = np.sqrt(a[i] * a[i] + b[i] * b[i])
        if not (t == a[i] or (np.isnan(t) and np.isnan(a[i]))):
            return False
    return True


def _combined(noise, cal) -> np.ndarray:
    """:func:`combine` of the noise and calibration parts; ``noise`` itself (one array, not two
    equal ones: 55 MB less per 1920×1200 camera) where the sum equals it bit for bit, as it does
    for a zero calibration part (sqrt(x²) = |x| in IEEE arithmetic unless x² underflows); that is
    checked by one compiled pass where :func:`combine` uses its kernel (no array of sums)."""
    noise = np.asarray(noise, dtype=float)
    cal = np.asarray(cal, dtype=float)
    if noise.shape == cal.shape and noise.size >= 4096:
        if _rss_equals_first(np.ascontiguousarray(noise).reshape(-1), np.ascontiguousarray(cal).reshape(-1)):
            return noise
        return combine(noise, cal)
    total = combine(noise, cal)
    return noise if np.array_equal(total, noise, equal_nan=True) else total


@numba.njit(cache=True, nogil=True)
def _count_not_finite_on(S, a):
    """Number of pixels of S (H, W) where a (H, W, C) has a non-finite component."""
    H, W = S.shape
    n = 0
    for v in range(H):
        for u in range(W):
            if S[v, u]:
                for c in range(a.shape[2]):
                    if not np.isfinite(a[v, u, c]):
                        n += 1
                        break
    return n


def surface_uncertainty(setup, camera: str, decoded, reg, rec, *, method: str, screen_model=None, anchor=None,
                        anchor_std_mm: float = 0.0, samples: int = DEFAULT_SAMPLES,
                        rng_seed: int = DEFAULT_RNG_SEED) -> SurfaceUncertainty:
    """Per-pixel standard uncertainties of one camera's reconstruction (module docstring).

    Parameters
    ----------
    setup : Setup
        The evaluating setup (its ``calibration_covariance``, if any, adds the calibration part).
    camera : str
    decoded : ScreenCoordinates
        With ``std_xy_mm`` (H, W, 2).
    reg : Registration
    rec : Reconstruction
        The (anchored) reconstruction in the sample frame.
    method : {"stepwise", "least_squares"}
    screen_model : surface, optional
        The evaluation's screen model (None: the plane).
    anchor : HeightAnchor or DistanceAnchor, optional
        What fixed the heights; with ``anchor_std_mm`` > 0 its own σ is added.
    anchor_std_mm : float
        Standard uncertainty of the anchor's distance (or height), mm.
    samples, rng_seed
        K and the seed of the height σ estimator.

    Raises
    ------
    UncertaintyError
        σ cannot be computed (the caller keeps the heights).
    """
    notes = []
    S = rec.reconstructed
    T_ref_screen = setup.sample.T_world_sample.inv() @ setup.screen.T_world_screen
    R = np.asarray(T_ref_screen.rotation, dtype=float)
    dq = _screen_tangents(R, screen_model, decoded.screen_xy_mm)
    std = np.asarray(decoded.std_xy_mm, dtype=float)
    S = np.ascontiguousarray(S, dtype=bool)
    bad = int(_count_not_finite_on(S, readonly(np.ascontiguousarray(std))))  # (no copy of std[S])
    if bad:
        raise UncertaintyError(f"camera {camera!r}: the decoder's σ (std_xy_mm) is not finite at {bad} reconstructed "
                               f"pixel(s); no σ of the surface")
    if int(samples) < 2:
        raise UncertaintyError(f"samples must be ≥ 2, got {samples!r}")
    if rec.method == "stepwise":  # geometry, A and σ in one pass (no full-size maps: issue 25)
        from .uncertainty_stepwise_fused import stepwise_noise_sigma  # noqa: PLC0415 (it imports this module)

        h_noise, g_noise, status = stepwise_noise_sigma(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec, dq, std, samples,
                                                        rng_seed)
        if status == 1:
            raise UncertaintyError(_GEOMETRY_NOT_FINITE)
        if status == 2:
            raise UncertaintyError(_STEPWISE_SINGULAR)
    else:
        # Memory (issue 25): the linearisation first (its temporaries are gone before A exists), A
        # zeroed off S in place (no copy).
        lin = _LinearisedIntegration(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, rec)
        # the kernel reads σ only on S, where it is finite (checked above): no NaN-free copy
        A, g_noise = _jacobian_scaled(reg.o_ref_mm, rec.p_sample_mm, reg.q_ref_mm, dq, S, std)
        h_noise = _sampled_std(lin, A, samples, rng_seed, overwrite=True)
        del lin, A
    if setup.screen.cover_glass is not None and getattr(setup.screen.cover_glass, "present", False):
        notes.append("cover glass: the refraction's effect on the slopes' Jacobian is not included")
    if anchor_std_mm and anchor is not None:
        dz_da = anchor_height_derivative(reg, anchor, method, T_world_ref=setup.sample.T_world_sample)
        h_noise = combine(h_noise, dz_da * float(anchor_std_mm))
        notes.append(f"anchor standard uncertainty {float(anchor_std_mm):g} mm included")
    if _count_not_finite_on(S, readonly(np.ascontiguousarray(h_noise)[..., None])):
        raise UncertaintyError("the height σ is not finite at some reconstructed pixel")
    cov = getattr(setup, "calibration_covariance", None)
    if cov is not None:
        from .uncertainty_calibration import (  # noqa: PLC0415 (optional part)
            CalibrationUncertaintyError, calibration_contribution)

        try:
            cal = calibration_contribution(setup, camera, decoded, anchor=anchor, method=method,
                                           screen_model=screen_model)
        except CalibrationUncertaintyError as exc:  # as stereo does: the caller keeps the heights
            raise UncertaintyError(f"the calibration's contribution cannot be computed: {exc}") from None
        h_cal = np.where(S, np.asarray(cal.height_std_um, dtype=float), np.nan)
        g_cal = np.where(S[..., None], np.asarray(cal.slope_std_urad, dtype=float), np.nan)
    else:
        h_cal = np.where(S, 0.0, np.nan)
        g_cal = np.empty(S.shape + (2,))
        g_cal[...] = h_cal[..., None]  # 0 on S, NaN elsewhere: a copy (13 ms), not a mask assignment (51 ms)
        notes.append(NO_COVARIANCE_NOTE)
    # the σ maps computed above are this function's own arrays: scaled in place (the same values)
    h_noise_um = np.multiply(h_noise, 1e3, out=h_noise)
    g_noise_urad = np.multiply(g_noise, 1e6, out=g_noise)
    return SurfaceUncertainty(slope_std_urad=_combined(g_noise_urad, g_cal), height_std_um=_combined(h_noise_um, h_cal),
                              slope_std_noise_urad=g_noise_urad, height_std_noise_um=h_noise_um,
                              slope_std_calibration_urad=g_cal, height_std_calibration_um=h_cal,
                              samples=int(samples), notes=tuple(notes))
