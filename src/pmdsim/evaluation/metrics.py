"""Figures of merit of a reconstructed surface (paper Tables 2 and 3).

All metrics are computed over one camera's field of view, i.e. over the reconstructed pixels,
from the height error e = z_reconstructed − z_true at the reconstructed points (sample frame):

* ``max_height_diff_um`` — the peak-to-valley max(e) − min(e) (the paper's "maximum height
  difference"; for a tilted plane this is the height difference across the FOV);
* ``max_dev_plane_um`` — max |e − (a·x + b·y + c)| for the least-squares plane of e over (x, y)
  (the paper's "maximum deviation from best-fit plane");
* ``tilt_urad`` — the tilt angle atan(√(a² + b²)) of that plane (the paper's "best-fit plane
  tilt angle"); ``tilt_x_urad`` / ``tilt_y_urad`` are the signed slopes a and b (µrad), which
  show the direction of the tilt;
* ``rms_um`` — the RMS of e, and ``n_pixels`` the number of pixels.
"""

from __future__ import annotations

import numpy as np

__all__ = ["surface_error_metrics"]


def _plane_fit(x, y, e) -> tuple[float, float, float, float, float]:
    """Least-squares plane e ≈ a·(x − x̄) + b·(y − ȳ) + c from the normal equations.

    With centred coordinates Σ(x − x̄) = Σ(y − ȳ) = 0, so the normal equations of
    [x − x̄, y − ȳ, 1] decouple: c = ē, and (a, b) solve the 2 × 2 system
    [[Sxx, Sxy], [Sxy, Syy]]·(a, b) = (Sxe, Sye) of centred sums. The same solution as
    ``lstsq`` of the (n, 3) design matrix, whose QR/SVD cost dominated the metrics (0.15–0.7 s
    at 2.2 M points, docs/benchmarks.md); centring keeps the
    2 × 2 system as well conditioned as the spread of x and y allows. The sums are numpy's
    pairwise sums (the same result on any number of threads).

    Parameters
    ----------
    x, y, e : ndarray (n,)
        Finite coordinates and values.

    Returns
    -------
    a, b, c, x_mean, y_mean : float
    """
    xm, ym, em = x.mean(), y.mean(), e.mean()
    xc, yc, ec = x - xm, y - ym, e - em
    # numpy's pairwise sums, not BLAS dot products: a multi-threaded BLAS sums in an order that
    # depends on its thread count, and results must not depend on where a case runs.
    sxx, syy, sxy = np.sum(xc * xc), np.sum(yc * yc), np.sum(xc * yc)
    sxe, sye = np.sum(xc * ec), np.sum(yc * ec)
    det = sxx * syy - sxy * sxy
    if not det > 0:
        raise ValueError("surface metrics need points that span a plane (x and y are collinear)")
    a = (syy * sxe - sxy * sye) / det
    b = (sxx * sye - sxy * sxe) / det
    return float(a), float(b), float(em), float(xm), float(ym)


def surface_error_metrics(x_mm, y_mm, error_mm) -> dict[str, float]:
    """Metrics of a height-error field over its points.

    Parameters
    ----------
    x_mm, y_mm, error_mm : array_like, same shape
        Point coordinates and height errors (mm); NaN entries are ignored.

    Returns
    -------
    dict
        ``max_height_diff_um``, ``max_dev_plane_um``, ``tilt_urad``, ``tilt_x_urad``,
        ``tilt_y_urad``, ``rms_um``, ``mean_um``, ``n_pixels`` (see the module docstring).
    """
    x = np.asarray(x_mm, dtype=float).ravel()
    y = np.asarray(y_mm, dtype=float).ravel()
    e = np.asarray(error_mm, dtype=float).ravel()
    m = np.isfinite(x) & np.isfinite(y) & np.isfinite(e)
    if m.sum() < 3:
        raise ValueError(f"surface metrics need at least 3 finite points, got {int(m.sum())}")
    x, y, e = x[m], y[m], e[m]
    a, b, c, xm, ym = _plane_fit(x, y, e)
    resid = e - (a * (x - xm) + b * (y - ym) + c)
    return {
        "max_height_diff_um": float((e.max() - e.min()) * 1e3),
        "max_dev_plane_um": float(np.abs(resid).max() * 1e3),
        "tilt_urad": float(np.arctan(np.hypot(a, b)) * 1e6),
        "tilt_x_urad": float(a * 1e6),
        "tilt_y_urad": float(b * 1e6),
        "rms_um": float(np.sqrt(np.mean(e**2)) * 1e3),
        "mean_um": float(e.mean() * 1e3),
        "n_pixels": int(e.size),
    }
