"""The joint surface fit's last pass over each camera's maps (issue 25, item 1): residuals and σ sums together.

Once :func:`pmdsim.evaluation.surface_fit.surface_fit_summary` has the coefficients, one compiled
pass per camera, over image rows on both numba threads, reads x, y (of the points (H, W, 3)), the
slopes (H, W, 2) and their σ (H, W, 2) at the fitted pixels and

* writes the residuals g − A·c into the (H, W, 2) residual map (NaN elsewhere) and into the fit's
  two (M,) rows (cameras in order, pixels in C order; the row's first index from the counts of the
  rows above) — the arithmetic of :func:`~pmdsim.evaluation.surface_fit._residuals`, no
  contraction: the same bits;
* adds, per image row, the 24 sums Σ w·(x², xy, y², x, y, 1) and Σ (wσ)²·(x², xy, y², x, y, 1) of
  the g_x rows and of the g_y rows — w the bisquare weights of those residuals at the fit's last
  scale (1 if 0) — over the points whose residuals, σ and x, y are finite: N and B of the σ
  sandwich (:func:`~pmdsim.evaluation.surface_fit.with_uncertainty`).

The rows' partial sums are added in row order, cameras in order (no dependence on the number of
threads). The sandwich's sums are those of :func:`~.surface_fit.with_uncertainty` in another order
and centred on the fit's centre instead of the σ points' mean (the same covariance of the
uncentred coefficients): the σ agree to ~1e-13 relative (tests/test_surface_fit_final.py, against
numpy's matmul on the explicit design).

:func:`summary_in_parts`: the summary composed of the general fit, :func:`~.surface_fit.with_uncertainty`
and the scatter, for points whose x or y is not finite (the last pass assumes finite points).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import SERIAL_BELOW_PX, numba_threads, readonly
from .surface_fit_sums import add_rows, moments

__all__ = ["final_pass", "summary_in_parts"]

_NSUM = 24


@numba.njit(cache=True, nogil=True, fastmath=False, parallel=True, error_model="numpy")
def _final_kernel(p, g, sig, ok, offs, xc, yc, coef, scale, use_sig, rx, ry, res, part):  # pragma: no cover - compiled
    """Residual map ``res`` (H, W, 2), residual rows ``rx``, ``ry`` ((M,) each) from index ``offs[v]`` for
    image row v, and ``part[v]`` the row's 24 sums (module docstring; zeros without ``use_sig``)."""
    h, w = ok.shape
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    for v in numba.prange(0, h):
        j = offs[v]
        nx = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        ny = nx
        bx = nx
        by = nx
        for u in range(0, w):
            if not ok[v, u]:
                res[v, u, 0] = np.nan
                res[v, u, 1] = np.nan
                continue
            xi = p[v, u, 0] - xc
            yi = p[v, u, 1] - yc
            r0 = g[v, u, 0] - (a2 * xi + b * yi + d)
            r1 = g[v, u, 1] - (b * xi + c2 * yi + e)
            res[v, u, 0] = r0
            res[v, u, 1] = r1
            rx[j] = r0
            ry[j] = r1
            j += 1
            if not use_sig:
                continue
            s0 = sig[v, u, 0]
            s1 = sig[v, u, 1]
            if not np.isfinite(r0 + r1 + s0 + s1 + p[v, u, 0] + p[v, u, 1]):
                continue
            w0 = 1.0
            w1 = 1.0
            if scale > 0:
                t = r0 / scale
                w0 = (1.0 - t * t) ** 2 if abs(t) < 1.0 else 0.0
                t = r1 / scale
                w1 = (1.0 - t * t) ** 2 if abs(t) < 1.0 else 0.0
            v0 = (w0 * s0) ** 2
            v1 = (w1 * s1) ** 2
            xx = xi * xi
            xy = xi * yi
            yy = yi * yi
            nx = moments(nx, w0, xi, yi, xx, xy, yy)
            ny = moments(ny, w1, xi, yi, xx, xy, yy)
            bx = moments(bx, v0, xi, yi, xx, xy, yy)
            by = moments(by, v1, xi, yi, xx, xy, yy)
        for k in range(6):
            part[v, k] = nx[k]
            part[v, 6 + k] = ny[k]
            part[v, 12 + k] = bx[k]
            part[v, 18 + k] = by[k]


def final_pass(p_sample_mm, slopes, slope_std, ok, start: int, centre, coef, scale: float, rows, sums, *,
               out=None):
    """One camera's residual map (H, W, 2) and next row index; its residuals written to
    ``rows[0][start:]``, ``rows[1][start:]`` and, with ``slope_std``, its sandwich sums added to
    ``sums`` (24,).

    Parameters
    ----------
    p_sample_mm : ndarray (H, W, 3)
        The points (x, y used), mm.
    slopes : ndarray (H, W, 2)
        Their slopes, rad.
    slope_std : ndarray (H, W, 2) or None
        The slopes' σ, rad (None: no sums).
    ok : ndarray of bool (H, W)
        The fitted pixels.
    start : int
        The row of this camera's first fitted pixel.
    centre : (xc, yc)
        The fit's centre, mm.
    coef : ndarray (5,)
        The fit's centred (a, b, c, d, e).
    scale : float
        The fit's last bisquare scale (0: weights 1).
    rows : (ndarray (M,), ndarray (M,))
        The fit's residual rows of g_x and g_y (written; C order).
    sums : ndarray (24,)
        Σ w·(x², xy, y², x, y, 1) of the g_x rows, of the g_y rows, then Σ (wσ)²·(…) of each
        (module docstring), continued.
    out : ndarray (H, W, 2), optional
        The residual map to write (every value is written; C order), else a new one.

    Returns
    -------
    (ndarray (H, W, 2), int)
    """
    okr = readonly(np.ascontiguousarray(ok, dtype=np.bool_))
    h, w = okr.shape
    offs = np.empty(h, np.int64)
    offs[0] = start
    np.cumsum(np.count_nonzero(okr, axis=1)[:-1], out=offs[1:])
    offs[1:] += start
    use_sig = slope_std is not None
    sig = readonly(np.ascontiguousarray(slope_std, dtype=np.float64) if use_sig else np.zeros((1, 1, 2)))
    res = np.empty((h, w, 2)) if out is None else out
    if res.shape != (h, w, 2) or res.dtype != np.float64 or not (res.flags.c_contiguous and res.flags.writeable):
        raise ValueError(f"final_pass: out must be a writable C-ordered float64 ({h}, {w}, 2) array")
    part = np.zeros((h, _NSUM))
    with numba_threads(1 if okr.size < SERIAL_BELOW_PX else numba.get_num_threads()):
        _final_kernel(readonly(np.ascontiguousarray(p_sample_mm, dtype=np.float64)),
                      readonly(np.ascontiguousarray(slopes, dtype=np.float64)), sig, okr, offs,
                      float(centre[0]), float(centre[1]), readonly(np.asarray(coef, dtype=np.float64)),
                      float(scale), use_sig, rows[0], rows[1], res, part)
    if use_sig:
        add_rows(part, sums)
    return res, int(start + np.count_nonzero(okr))


def summary_in_parts(recs, camera_z_mm, slope_std, oks, extras, xy, gxy):
    """:func:`~.surface_fit.surface_fit_summary` by :func:`~.surface_fit.fit_paraboloid_slopes`
    (which leaves out points with a non-finite x or y, or raises for fewer than 6) and
    :func:`~.surface_fit.with_uncertainty`: the fit of the rows ``xy``, ``gxy`` ((2, M)), the
    residual maps scattered to the pixels ``oks`` and the detrended heights into ``extras``."""
    from .surface_fit import fit_paraboloid_slopes, remove_piston_tilt, with_uncertainty
    from .surface_fit_rows import scatter_residuals

    fit = fit_paraboloid_slopes(xy.T, gxy.T, np.ones(xy.shape[1], bool), camera_z_mm=camera_z_mm,
                                overwrite_slopes=True)
    if slope_std is not None:  # σ read in the maps at the fitted pixels (no (M, 2) gather)
        fit = with_uncertainty(fit, xy.T, slope_std, camera_z_mm, masks=oks)
    start = 0
    for rec, ok, ex in zip(recs, oks, extras):
        ex["residual_slopes"], start = scatter_residuals(fit.residual_slopes, ok, start)
        ex["height_detrended_mm"] = remove_piston_tilt(rec.p_sample_mm, rec.reconstructed)[0]
    return fit, extras
