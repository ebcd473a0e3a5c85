"""The calibration's contribution to the per-pixel standard uncertainty of heights and slopes.

A calibrated setup carries the covariance C of its calibrated parameters
(:class:`~pmdsim.setup.covariance.CalibrationCovariance`: the camera's intrinsics and pose, the
table plane, the free-form screen heights, the cover glass). An evaluation's heights z and
slopes g are functions f(p) of those parameters; to first order (GUM, law of propagation of
uncertainty) their covariance is J C Jᵀ with J = ∂f/∂p, of which the per-pixel variances are
computed here (docs/conventions.md, "Uncertainty from the calibration"):

1. the parameters that act on the camera's evaluation are kept (its own 14, the table plane,
   the glass, and the screen heights when the evaluation uses the screen surface) — the marginal
   covariance, the sub-block of C;
2. in correlation units, C = D R D with D = diag(σ) and R = U Λ Uᵀ; for every principal axis k
   with λ_k > 1e-12·λ_max the setup is moved by δ_k = ε·√λ_k·D·u_k (:func:`perturbed_setup`,
   ε = :data:`DEFAULT_STEP` = 0.01: a hundredth of a standard deviation), registered and
   reconstructed again as the evaluation does; (f(p + δ_k) − f(p))/ε is then the change of f
   along a 1σ move of that axis, and Var f = Σ_k ((f(p + δ_k) − f(p))/ε)²;
3. the perturbed reconstructions run on a pixel subgrid of stride s (default min(H, W) // 75,
   the subgrid through the reconstruction's seed pixel, i.e. a camera of focal length f/s whose
   pixel (v', u') is pixel (v₀ + s·v', u₀ + s·u')); each axis's change is interpolated
   bilinearly back to every pixel (compiled kernel, nodes not reconstructed on the subgrid filled
   from their neighbours) before it is squared and summed;
4. heights are relative to what fixes them, as the evaluation's: with no anchor the seed pixel
   stays at its height (σ = 0 there); with a :class:`~pmdsim.evaluation.anchor.HeightAnchor` or
   :class:`~pmdsim.evaluation.anchor.DistanceAnchor` the seed height is corrected, to first
   order, so that the perturbed surface still meets the anchor (∂f/∂z₀ from one more
   reconstruction) — the perturbed table, camera and glass move the anchor's ray and frame.

What it does not cover: the images' noise (:mod:`pmdsim.evaluation.uncertainty`), parameters
the calibration did not estimate (held ones, the screen pose — the gauge), and model errors
(e.g. a planar screen model for a bulged screen): a bias, not a scatter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np

from ..errors import PmdsimError
from ..setup.covariance import perturbed_setup
from .anchor import DistanceAnchor, HeightAnchor, _bilinear_point, reconstruct_anchored, register_model
from .integration import ReconstructionError
from .reconstruction import reconstruct
from .registration import register
from .surface_fit import sample_slopes

__all__ = ["CalibrationContribution", "CalibrationUncertaintyError", "calibration_contribution",
           "calibration_parameters", "principal_axes", "DEFAULT_STEP", "default_stride"]

#: Finite-difference step along each principal axis, in standard deviations.
DEFAULT_STEP = 0.01
#: Principal axes with an eigenvalue below this fraction of the largest are skipped.
_NEGLIGIBLE = 1e-12
#: Seed-height step (mm) of the anchor correction's derivative.
_SEED_STEP_MM = 1e-3


class CalibrationUncertaintyError(PmdsimError, ValueError):
    """The calibration's contribution cannot be computed (no covariance, nothing reconstructed)."""


@dataclass(frozen=True, eq=False)
class CalibrationContribution:
    """The calibration's contribution to one camera's standard uncertainties (k = 1).

    Attributes
    ----------
    height_std_um : ndarray (H, W) float64
        Standard uncertainty of the height (µm), relative to what fixes the height (the anchor);
        NaN where not reconstructed.
    slope_std_urad : ndarray (H, W, 2) float64
        Standard uncertainty of the slopes (dz/dx, dz/dy) in the sample frame (µrad); NaN where
        not reconstructed.
    parameters : tuple of str
        The calibrated parameters propagated (the rest do not act on this camera's evaluation).
    n_axes : int
        Principal axes evaluated (perturbed reconstructions).
    stride_px : int
        Pixel stride of the perturbed reconstructions.
    """

    height_std_um: np.ndarray
    slope_std_urad: np.ndarray
    parameters: tuple
    n_axes: int
    stride_px: int


def default_stride(shape) -> int:
    """The subgrid stride of the perturbed reconstructions: min(H, W) // 75, at least 1."""
    return max(1, min(int(shape[0]), int(shape[1])) // 75)


def calibration_parameters(setup, camera: str, *, screen_model=None) -> tuple:
    """The parameters of ``setup``'s covariance that act on ``camera``'s evaluation: its own, the
    table plane's, the glass's, and the screen heights' when ``screen_model`` is not None."""
    cov = setup.calibration_covariance
    if cov is None:
        return ()
    out = []
    for n in cov.parameters:
        head = n.partition(".")[0]
        if head == camera or head == "table" or n.startswith("screen.glass_") or (
                screen_model is not None and n.startswith("screen.h[")):
            out.append(n)
    return tuple(out)


def principal_axes(sub) -> list:
    """The 1σ steps δ_k = √λ_k·D·u_k (natural units, in ``sub.parameters``' order) along the
    principal axes of a :class:`~pmdsim.setup.covariance.CalibrationCovariance` in correlation
    units (C = D U Λ Uᵀ D), those with λ_k > 1e-12·λ_max; Σ_k δ_k δ_kᵀ = C."""
    sd = sub.std
    used = sd > 0
    axes = []
    if used.any():
        sdu = sd[used]
        r = sub.matrix[np.ix_(used, used)] / np.outer(sdu, sdu)
        lam, u = np.linalg.eigh(0.5 * (r + r.T))
        for k in np.nonzero(lam > _NEGLIGIBLE * lam.max())[0]:
            delta = np.zeros(len(sd))
            delta[used] = math.sqrt(lam[k]) * sdu * u[:, k]
            axes.append(delta)
    return axes


def _strided(setup, camera: str, s: int, ov: int, ou: int, shape):
    """The camera sampling every s-th pixel from (ov, ou): pixel (v', u') is (ov + s·v', ou + s·u')."""
    c = setup.cameras[camera].camera
    h, w = shape
    return replace(c, width_px=w, height_px=h, fx_px=c.fx_px / s, fy_px=c.fy_px / s,
                   ppx_px=(c.ppx_px - ou) / s, ppy_px=(c.ppy_px - ov) / s)


class _Grid:
    """Registration and reconstruction of one camera on the subgrid, as the evaluation does."""

    def __init__(self, camera, xy, decoded, s, ov, ou, screen_model, anchor, method, seed_c, z_seed, pix_c):
        self.camera, self.xy, self.decoded = camera, xy, decoded
        self.s, self.ov, self.ou = s, ov, ou
        self.screen_model, self.anchor, self.method = screen_model, anchor, method
        self.seed_c, self.z_seed, self.pix_c = seed_c, z_seed, pix_c

    def fields(self, setup, valid, dz0: float = 0.0):
        """(F (h, w, 3) = height mm and slopes, miss at the anchor, registration valid)."""
        cs = setup.cameras[self.camera]
        cam = _strided(setup, self.camera, self.s, self.ov, self.ou, self.xy.shape[:2])
        surf = None if self.screen_model is None else setup.screen.surface
        if surf is None:
            scr = setup.screen
            from ..geometry.surface import SplineSurface
            surf = SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
        reg = register(cam, cs.T_world_cam, surf, setup.screen.T_world_screen, self.xy, self.decoded,
                       setup.sample.T_world_sample, glass=setup.screen.cover_glass)
        ok = valid & reg.valid
        if not ok[self.seed_c]:
            raise CalibrationUncertaintyError(f"camera {self.camera!r}: the seed pixel is lost when the setup moves "
                                              f"by a hundredth of a standard deviation")
        try:
            rec = reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, ok, method=self.method, seed_pixel=self.seed_c,
                              seed_height_mm=self.z_seed + dz0)
        except ReconstructionError as exc:  # the covariance moves the setup where no surface is seen
            raise CalibrationUncertaintyError(f"camera {self.camera!r}: the surface cannot be reconstructed when the "
                                              f"setup moves by a hundredth of a standard deviation ({exc})") from None
        f = np.empty(ok.shape + (3,))
        f[..., 0] = rec.height_mm
        f[..., 1:] = sample_slopes(rec.n_sample)
        f[~rec.reconstructed] = np.nan
        return f, self._miss(setup, reg, rec), reg.valid

    def _miss(self, setup, reg, rec) -> float:
        """How far the surface misses the anchor (0 without one: the seed is held)."""
        if self.anchor is None:
            return 0.0
        o, d = reg.o_ref_mm, reg.d_ref
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (rec.height_mm - o[2]) / d[..., 2]
        p = _bilinear_point(o, d, t, self.pix_c)
        if p is None:
            raise CalibrationUncertaintyError(f"camera {self.camera!r}: the subgrid reconstruction does not reach "
                                              f"the anchor pixel")
        if isinstance(self.anchor, DistanceAnchor):
            s_ref = setup.sample.T_world_sample.inv().apply(np.asarray(self.anchor.point_world_mm, dtype=float))
            return float(np.linalg.norm(p - s_ref) - self.anchor.distance_mm)
        return float(p[2] - self.anchor.height_mm)


def calibration_contribution(setup, camera: str, decoded, *, anchor=None, method: str = "stepwise",
                             screen_model=None, stride: int | None = None, step: float = DEFAULT_STEP,
                             central: bool = False) -> CalibrationContribution:
    """Per-pixel standard uncertainty of ``camera``'s heights and slopes from the calibration's
    covariance (module docstring).

    Parameters
    ----------
    setup : Setup
        The evaluation's (calibrated) setup; must carry ``calibration_covariance``.
    camera : str
    decoded : ScreenCoordinates
        The camera's decoded screen coordinates (``screen_xy_mm`` (H, W, 2), ``valid`` (H, W)).
    anchor : HeightAnchor, DistanceAnchor or None
        What fixes the height, as given to :func:`~pmdsim.evaluation.anchor.reconstruct_anchored`.
    method : {"stepwise", "least_squares"}
    screen_model : surface or None
        None: the planar screen model; otherwise the setup's screen surface (the perturbed
        setups' surfaces are then used, and the screen heights' covariance acts).
    stride : int, optional
        Pixel stride of the perturbed reconstructions (default :func:`default_stride`; 1: every pixel).
    step : float
        Finite-difference step along each principal axis, in standard deviations.
    central : bool
        Central instead of forward differences (twice the reconstructions; for checks).

    Returns
    -------
    CalibrationContribution

    Raises
    ------
    CalibrationUncertaintyError
        The setup carries no covariance, or nothing is reconstructed.
    """
    cov = setup.calibration_covariance
    if cov is None:
        raise CalibrationUncertaintyError("the setup carries no calibration covariance (calibrate it with "
                                          "`pmdsim calibrate`, or give [calibration_report] covariance)")
    if camera not in setup.cameras:
        raise CalibrationUncertaintyError(f"no camera {camera!r} in the setup (cameras: {', '.join(setup.cameras)})")
    if not (step > 0 and math.isfinite(step)):
        raise CalibrationUncertaintyError(f"step must be positive and finite, got {step!r}")
    if isinstance(anchor, tuple):
        raise CalibrationUncertaintyError("anchor must be a HeightAnchor, a DistanceAnchor or None")
    xy = np.asarray(decoded.screen_xy_mm, dtype=float)
    H, W = xy.shape[:2]
    # The evaluation's own reconstruction: the pixels, the seed and its height.
    reg = register_model(setup, camera, decoded, screen_model=screen_model)
    if not reg.valid.any():
        raise CalibrationUncertaintyError(f"camera {camera!r}: no pixel was decoded and registered")
    ar = reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=anchor,
                              T_world_ref=setup.sample.T_world_sample, method=method)
    rec = ar.reconstruction
    mask = rec.reconstructed
    seed = rec.seed_pixel
    names = calibration_parameters(setup, camera, screen_model=screen_model)
    s = int(default_stride((H, W)) if stride is None else stride)
    if s < 1:
        raise CalibrationUncertaintyError(f"stride must be ≥ 1, got {stride!r}")
    axes = principal_axes(cov.subset(names))
    h_out = np.where(mask, 0.0, np.nan)
    g_out = np.where(mask[..., None], np.zeros(mask.shape + (2,)), np.nan)  # (H, W, 2)
    if not axes:
        return CalibrationContribution(h_out, g_out, names, 0, s)
    ov, ou = seed[0] % s, seed[1] % s
    xy_c = np.ascontiguousarray(xy[ov::s, ou::s])
    dec_c = np.ascontiguousarray(np.asarray(decoded.valid, dtype=bool)[ov::s, ou::s])
    valid_c = mask[ov::s, ou::s]
    seed_c = ((seed[0] - ov) // s, (seed[1] - ou) // s)
    pix_c = None if anchor is None else ((anchor.pixel_vu[0] - ov) / s, (anchor.pixel_vu[1] - ou) / s)
    grid = _Grid(camera, xy_c, dec_c, s, ov, ou, screen_model, anchor, method, seed_c,
                 float(rec.height_mm[seed]), pix_c)
    f0, m0, reg_ok = grid.fields(setup, valid_c)
    valid_c = valid_c & reg_ok
    if anchor is not None:  # ∂f/∂z₀ and ∂miss/∂z₀: the first-order seed-height correction
        fz, mz, _ = grid.fields(setup, valid_c, _SEED_STEP_MM)
        df_dz0 = (fz - f0) / _SEED_STEP_MM
        dm_dz0 = (mz - m0) / _SEED_STEP_MM
        if not (dm_dz0 != 0 and math.isfinite(dm_dz0)):
            raise CalibrationUncertaintyError(f"camera {camera!r}: the anchor does not depend on the seed height")

    def moved(sign: float, delta):
        f, m, _ = grid.fields(perturbed_setup(setup, sign * step * delta, names), valid_c)
        if anchor is not None:
            f = f - ((m - m0) / dm_dz0) * df_dz0
        return f

    changes = np.empty((len(axes),) + f0.shape)
    for k, delta in enumerate(axes):
        fp = moved(1.0, delta)
        changes[k] = (fp - moved(-1.0, delta)) / (2 * step) if central else (fp - f0) / step
    var = _interpolated_squares(changes, ov, ou, s, H, W)
    var[~mask] = np.nan
    return CalibrationContribution(np.sqrt(var[..., 0]) * 1e3, np.sqrt(var[..., 1:]) * 1e6, names, len(axes), s)


# ============================================================================ kernels
@numba.njit(cache=True)
def _fill(a, passes):
    """NaN nodes of a (h, w, c) field filled with the mean of their finite 8-neighbours, ``passes`` times."""
    h, w, c = a.shape
    for _ in range(passes):
        b = a.copy()
        changed = False
        for i in range(h):
            for j in range(w):
                if not np.isnan(a[i, j, 0]):
                    continue
                acc = np.zeros(c)
                n = 0
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        ii, jj = i + di, j + dj
                        if 0 <= ii < h and 0 <= jj < w and not np.isnan(a[ii, jj, 0]):
                            for k in range(c):
                                acc[k] += a[ii, jj, k]
                            n += 1
                if n:
                    for k in range(c):
                        b[i, j, k] = acc[k] / n
                    changed = True
        a = b
        if not changed:
            break
    return a


@numba.njit(cache=True, parallel=True)
def _accumulate(stack, ov, ou, s, H, W):
    """Σ_k (bilinear interpolation of stack[k] at every pixel)² → (H, W, 3); node (i, j) of
    stack (K, h, w, 3) is pixel (ov + s·i, ou + s·j). Pixels beyond the outer nodes are
    extrapolated linearly from the last cell; where one of a cell's 4 nodes is NaN the others'
    weights (clamped to the cell) are renormalised."""
    K, h, w, _ = stack.shape
    out = np.zeros((H, W, 3))
    for v in numba.prange(0, H):
        fv = (v - ov) / s
        i0 = min(max(int(math.floor(fv)), 0), max(h - 2, 0))
        ay = fv - i0 if h > 1 else 0.0
        for u in range(W):
            fu = (u - ou) / s
            j0 = min(max(int(math.floor(fu)), 0), max(w - 2, 0))
            ax = fu - j0 if w > 1 else 0.0
            i1 = min(i0 + 1, h - 1)
            j1 = min(j0 + 1, w - 1)
            for k in range(K):
                q00 = stack[k, i0, j0]
                q01 = stack[k, i0, j1]
                q10 = stack[k, i1, j0]
                q11 = stack[k, i1, j1]
                if not (np.isnan(q00[0]) or np.isnan(q01[0]) or np.isnan(q10[0]) or np.isnan(q11[0])):
                    w00, w01, w10, w11 = (1 - ay) * (1 - ax), (1 - ay) * ax, ay * (1 - ax), ay * ax
                    for m in range(3):
                        val = w00 * q00[m] + w01 * q01[m] + w10 * q10[m] + w11 * q11[m]
                        out[v, u, m] += val * val
                    continue
                cy = min(max(ay, 0.0), 1.0)
                cx = min(max(ax, 0.0), 1.0)
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                wsum = 0.0
                for di in range(2):
                    for dj in range(2):
                        q = stack[k, i1 if di else i0, j1 if dj else j0]
                        wt = (cy if di else 1.0 - cy) * (cx if dj else 1.0 - cx)
                        if wt <= 0.0 or np.isnan(q[0]):
                            continue
                        a0 += wt * q[0]
                        a1 += wt * q[1]
                        a2 += wt * q[2]
                        wsum += wt
                if wsum > 0.0:
                    out[v, u, 0] += (a0 / wsum) ** 2
                    out[v, u, 1] += (a1 / wsum) ** 2
                    out[v, u, 2] += (a2 / wsum) ** 2
                else:
                    out[v, u, 0] = np.nan
                    out[v, u, 1] = np.nan
                    out[v, u, 2] = np.nan
    return out


def _interpolated_squares(changes: np.ndarray, ov: int, ou: int, s: int, H: int, W: int) -> np.ndarray:
    """Σ_k (changes[k] interpolated to every pixel)²: the variance (H, W, c)."""
    filled = np.stack([_fill(np.ascontiguousarray(c), 4) for c in changes])
    if s == 1:
        return np.nansum(filled ** 2, axis=0) + np.where(np.isnan(filled).any(axis=0), np.nan, 0.0)
    return _accumulate(filled, ov, ou, s, H, W)
