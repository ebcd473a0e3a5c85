"""Reporting for real optics: slopes in the sample frame, heights without piston and tilt, and a
best-fit paraboloid over the slopes (focal lengths, residual slope RMS) — issue 12, item 4.

* Slopes: g = (∂z/∂x, ∂z/∂y) = (−n_x/n_z, −n_y/n_z) of the reconstruction's unit normals, in the
  sample frame (its +z is the height axis).
* Piston and tilt: the least-squares plane z = c₀ + c₁x + c₂y over the reconstructed points is
  subtracted from their heights.
* Paraboloid: z = a x² + b x y + c y² + d x + e y (+ piston), fitted to the slopes
  g_x = 2a x + b y + d, g_y = b x + 2c y + e at the reconstructed points (x, y) — the
  slope-domain fit SOFAST's "parabolic" surface uses — by robust least squares: iteratively
  reweighted with Tukey's bisquare weights w = (1 − (r/(4.685·s))²)² (0 beyond), s = MAD/0.6745
  of the residuals (Holland & Welsch 1977), so that edge defects and outliers do not bend the
  fit (``robust=False``: plain least squares). Focal lengths f_x = 1/(4a'), f_y = 1/(4c')
  with a', c' the curvatures of the height measured **towards the camera** (the sample frame's
  −z when the camera is on its −z side, as in pmdsim's convention): a mirror concave as seen from
  the camera has positive focal lengths. The residual slope RMS is
  √(mean(|g − g_fit|²)) over both components, in mrad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ComputationError

__all__ = ["ParaboloidFit", "sample_slopes", "remove_piston_tilt", "fit_paraboloid_slopes", "surface_fit_summary"]


def sample_slopes(n_sample) -> np.ndarray:
    """Slopes (H, W, 2) = (−n_x/n_z, −n_y/n_z) of unit normals (H, W, 3); NaN where n is NaN."""
    n = np.asarray(n_sample, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return -n[..., :2] / n[..., 2:3]


def remove_piston_tilt(p_sample_mm, valid) -> tuple[np.ndarray, np.ndarray]:
    """Heights (H, W) with the least-squares plane removed, and the plane's (c₀, c₁, c₂) mm, mm/mm.

    ``p_sample_mm`` (H, W, 3) points in the sample frame; ``valid`` (H, W) the points to use
    (NaN elsewhere in the result)."""
    p = np.asarray(p_sample_mm, dtype=float)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(p).all(axis=-1)
    if ok.sum() < 3:
        raise ComputationError("fewer than 3 reconstructed points: cannot remove piston and tilt")
    x, y, z = p[ok, 0], p[ok, 1], p[ok, 2]
    A = np.stack([np.ones_like(x), x, y], axis=-1)
    coef, *_ = np.linalg.lstsq(A, z, rcond=None)
    out = np.full(p.shape[:2], np.nan)
    out[ok] = z - A @ coef
    return out, coef


@dataclass(frozen=True)
class ParaboloidFit:
    """Best-fit paraboloid over slopes (module docstring). Coefficients in the sample frame,
    heights along its +z: z = a x² + b x y + c y² + d x + e y; lengths in mm.

    Attributes
    ----------
    coefficients : (a, b, c, d, e)
    focal_length_x_mm, focal_length_y_mm : float
        1/(4a'), 1/(4c'), a', c' towards the camera (+: concave as seen from the camera).
    slope_residual_rms_mrad : float
    residual_slopes : ndarray (H, W, 2)
        g − g_fit in rad (NaN where not used).
    n_points : int
    """

    coefficients: tuple[float, float, float, float, float]
    focal_length_x_mm: float
    focal_length_y_mm: float
    slope_residual_rms_mrad: float
    residual_slopes: np.ndarray
    n_points: int

    def as_json(self) -> dict:
        """Exactly the keys of ``surface_fit.json`` (issue 12); a focal length that is infinite
        (no curvature: a plane) is null."""
        def num(v):
            return float(v) if np.isfinite(v) else None

        return {"focal_length_x_mm": num(self.focal_length_x_mm), "focal_length_y_mm": num(self.focal_length_y_mm),
                "slope_residual_rms_mrad": num(self.slope_residual_rms_mrad)}


def _design(x, y):
    z0 = np.zeros_like(x)
    one = np.ones_like(x)
    gx = np.stack([2 * x, y, z0, one, z0], axis=-1)
    gy = np.stack([z0, x, 2 * y, z0, one], axis=-1)
    return gx, gy


#: Tukey bisquare tuning constant (95 % efficiency at the normal distribution) and MAD → σ.
_TUKEY_C = 4.685
_MAD_TO_SIGMA = 0.6745


def fit_paraboloid_slopes(p_sample_mm, slopes, valid, *, camera_z_mm: float, robust: bool = True,
                          max_iter: int = 100) -> ParaboloidFit:
    """Least-squares paraboloid over slopes (module docstring).

    Parameters
    ----------
    p_sample_mm : array (H, W, 3) or (M, 3)
        Points (x, y used) in the sample frame, mm.
    slopes : array (..., 2)
        (∂z/∂x, ∂z/∂y) at those points (rad).
    valid : array of bool (...)
    camera_z_mm : float
        The camera centre's z in the sample frame: fixes the direction "towards the camera" of
        the focal lengths' sign.
    robust : bool
        Tukey-bisquare IRLS (default) or plain least squares.
    """
    p = np.asarray(p_sample_mm, dtype=float)
    g = np.asarray(slopes, dtype=float)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(p[..., :2]).all(axis=-1) & np.isfinite(g).all(axis=-1)
    n = int(ok.sum())
    if n < 6:
        raise ComputationError(f"only {n} points with slopes: a paraboloid over slopes needs at least 6")
    x, y = p[ok, 0], p[ok, 1]
    # Centre the coordinates for conditioning; a, b, c do not depend on the origin.
    xc, yc = x.mean(), y.mean()
    Dx, Dy = _design(x - xc, y - yc)
    A = np.concatenate([Dx, Dy])
    rhs = np.concatenate([g[ok, 0], g[ok, 1]])
    coef, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    if robust:
        for _ in range(max_iter):
            r = rhs - A @ coef
            s = np.median(np.abs(r - np.median(r))) / _MAD_TO_SIGMA
            if not s > 0:
                break
            u = r / (_TUKEY_C * s)
            w = np.where(np.abs(u) < 1.0, (1.0 - u**2) ** 2, 0.0)
            sw = np.sqrt(w)
            new, *_ = np.linalg.lstsq(A * sw[:, None], rhs * sw, rcond=None)
            done = np.max(np.abs(new - coef)) <= 1e-12 * max(1.0, np.max(np.abs(coef)))
            coef = new
            if done:
                break
    a, b, c, d, e = coef
    # Back to uncentred linear terms: g_x = 2a(x − xc) + b(y − yc) + d.
    d0 = d - 2 * a * xc - b * yc
    e0 = e - b * xc - 2 * c * yc
    res = np.full(g.shape, np.nan)
    res[ok, 0] = g[ok, 0] - Dx @ coef
    res[ok, 1] = g[ok, 1] - Dy @ coef
    rms = float(np.sqrt(np.mean(res[ok] ** 2)))
    towards = -1.0 if camera_z_mm < 0 else 1.0
    with np.errstate(divide="ignore"):
        fx = float(1.0 / (4.0 * towards * a)) if a != 0 else float("inf")
        fy = float(1.0 / (4.0 * towards * c)) if c != 0 else float("inf")
    return ParaboloidFit((float(a), float(b), float(c), float(d0), float(e0)), fx, fy, rms * 1e3, res, n)


def surface_fit_summary(recs, camera_z_mm) -> tuple[ParaboloidFit, dict]:
    """Joint paraboloid fit over several reconstructions of one sample (same sample frame).

    ``recs`` : list of :class:`~pmdsim.evaluation.integration.Reconstruction`; ``camera_z_mm``
    the (first) camera's z in the sample frame. Returns the fit and per-camera extras
    ``{"slopes": (H, W, 2), "height_detrended_mm": (H, W), "residual_slopes": (H, W, 2)}``.
    """
    pts, gs, oks, extras = [], [], [], []
    for rec in recs:
        g = sample_slopes(rec.n_sample)
        ok = rec.reconstructed & np.isfinite(g).all(axis=-1)
        pts.append(rec.p_sample_mm[ok])
        gs.append(g[ok])
        oks.append(ok)
        extras.append({"slopes": g})
    fit = fit_paraboloid_slopes(np.concatenate(pts), np.concatenate(gs), np.ones(sum(len(p) for p in pts), bool),
                                camera_z_mm=camera_z_mm)
    start = 0
    for rec, ok, ex in zip(recs, oks, extras):
        k = int(ok.sum())
        res = np.full(ok.shape + (2,), np.nan)
        res[ok] = fit.residual_slopes[start:start + k]
        start += k
        ex["residual_slopes"] = res
        ex["height_detrended_mm"] = remove_piston_tilt(rec.p_sample_mm, rec.reconstructed)[0]
    return fit, extras
