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

import numba
import numpy as np

from ..errors import ComputationError
from ..geometry.kernel_args import readonly

__all__ = ["ParaboloidFit", "sample_slopes", "remove_piston_tilt", "fit_paraboloid_slopes", "surface_fit_summary",
           "with_uncertainty"]


def sample_slopes(n_sample) -> np.ndarray:
    """Slopes (H, W, 2) = (−n_x/n_z, −n_y/n_z) of unit normals (H, W, 3); NaN where n is NaN."""
    n = np.asarray(n_sample, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return -n[..., :2] / n[..., 2:3]


def remove_piston_tilt(p_sample_mm, valid) -> tuple[np.ndarray, np.ndarray]:
    """Heights (H, W) with the least-squares plane removed, and the plane's (c₀, c₁, c₂) mm, mm/mm.

    ``p_sample_mm`` (H, W, 3) points in the sample frame; ``valid`` (H, W) the points to use
    (NaN elsewhere in the result). Solved by centred normal equations in two compiled passes
    (the plane z = c₀ + c₁x + c₂y: its 2×2 slope system on centred coordinates is well
    conditioned; equal to lstsq to ~1e-12, tests/test_surface_fit_kernels.py)."""
    p = np.asarray(p_sample_mm, dtype=float)
    shape = p.shape[:-1]
    flat = readonly(np.ascontiguousarray(p.reshape(-1, 3)))  # read-only: one argument type
    okf = readonly(np.ascontiguousarray(np.broadcast_to(np.asarray(valid, dtype=bool), shape).reshape(-1)))
    out = np.empty(okf.size)
    coef = np.empty(3)
    status = _plane_kernel(flat, okf, np.empty(okf.size, np.bool_), out, coef)
    if status == 1:
        raise ComputationError("fewer than 3 reconstructed points: cannot remove piston and tilt")
    if status == 2:
        raise ComputationError("the reconstructed points are collinear: cannot remove piston and tilt")
    return out.reshape(shape), coef


@numba.njit(cache=True, nogil=True, fastmath=False)
def _plane_kernel(p, ok, use, out, coef):
    """Least-squares plane z = c₀ + c₁x + c₂y through the points ``p`` (N, 3) where ``ok`` and
    x, y, z are finite (``use``: those points, written by the first pass); ``out`` the residual
    heights (NaN elsewhere). Returns 0, 1 if fewer than 3 points, 2 if the 2×2 system is
    singular."""
    n = 0
    sx = sy = sz = 0.0
    for i in range(p.shape[0]):
        use[i] = ok[i] and np.isfinite(p[i, 0]) and np.isfinite(p[i, 1]) and np.isfinite(p[i, 2])
        if use[i]:
            n += 1
            sx += p[i, 0]
            sy += p[i, 1]
            sz += p[i, 2]
    if n < 3:
        return 1
    xm, ym, zm = sx / n, sy / n, sz / n
    sxx = sxy = syy = sxz = syz = 0.0
    for i in range(p.shape[0]):
        if use[i]:
            dx = p[i, 0] - xm
            dy = p[i, 1] - ym
            dz = p[i, 2] - zm
            sxx += dx * dx
            sxy += dx * dy
            syy += dy * dy
            sxz += dx * dz
            syz += dy * dz
    det = sxx * syy - sxy * sxy
    if not (det > 1e-14 * sxx * syy):
        return 2
    c1 = (syy * sxz - sxy * syz) / det
    c2 = (sxx * syz - sxy * sxz) / det
    coef[0] = zm - c1 * xm - c2 * ym
    coef[1] = c1
    coef[2] = c2
    for i in range(p.shape[0]):  # a select, not a branch: vectorised
        out[i] = p[i, 2] - zm - c1 * (p[i, 0] - xm) - c2 * (p[i, 1] - ym) if use[i] else np.nan
    return 0


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
    coefficients_std: tuple | None = None
    focal_length_x_std_mm: float | None = None
    focal_length_y_std_mm: float | None = None
    scale: float = 0.0  # the robust fit's last bisquare scale 4.685·MAD/0.6745 of the slope residuals (0: plain)
    centre: tuple = (0.0, 0.0)  # (xc, yc) mm: the origin of the fit's centred coordinates

    def as_json(self) -> dict:
        """Exactly the keys of ``surface_fit.json`` (issue 12); a focal length that is infinite
        (no curvature: a plane) is null. With standard uncertainties (:func:`with_uncertainty`,
        issue 22) also ``focal_length_x_std_mm``, ``focal_length_y_std_mm``, ``coefficients`` and
        ``coefficients_std`` (a … e of the module docstring, mm⁻¹ or 1)."""
        def num(v):
            return float(v) if v is not None and np.isfinite(v) else None

        out = {"focal_length_x_mm": num(self.focal_length_x_mm), "focal_length_y_mm": num(self.focal_length_y_mm),
               "slope_residual_rms_mrad": num(self.slope_residual_rms_mrad)}
        if self.coefficients_std is not None:
            out.update(focal_length_x_std_mm=num(self.focal_length_x_std_mm),
                       focal_length_y_std_mm=num(self.focal_length_y_std_mm),
                       coefficients=dict(zip("abcde", map(num, self.coefficients))),
                       coefficients_std=dict(zip("abcde", map(num, self.coefficients_std))),
                       uncertainty_note=_STD_NOTE)
        return out


_STD_NOTE = ("standard uncertainties (k = 1) from the fit's (robustly weighted) normal equations, sandwich "
             "covariance with the per-pixel slope standard uncertainty of the images' noise (independent between "
             "pixels); the calibration's contribution, correlated over the field, is not included")


@numba.njit(cache=True, nogil=True)
def _centre_kernel(xy, res, sig, ok, start, acc, cnt):  # pragma: no cover - compiled
    """Σx, Σy (``acc``) and their number (``cnt``) over the points i = start, start + 1, … of the
    pixels ``ok`` (P,) (a map's, flat) whose residuals, σ (``sig`` (P, 2), at the pixel) and x, y
    are finite; returns the next i."""
    sx, sy, n = acc[0], acc[1], cnt[0]
    i = start
    for k in range(ok.size):
        if not ok[k]:
            continue
        if np.isfinite(res[i, 0] + res[i, 1] + sig[k, 0] + sig[k, 1] + xy[i, 0] + xy[i, 1]):
            sx += xy[i, 0]
            sy += xy[i, 1]
            n += 1
        i += 1
    acc[0], acc[1], cnt[0] = sx, sy, n
    return i


@numba.njit(cache=True, nogil=True, inline="always")
def _row_terms(acc, w, p, q):
    """``acc`` (9 sums) plus the terms of one design row with nonzero entries (p, q, 1) and weight
    w: (w·p)·p, (w·p)·q, w·p, (w·q)·p, (w·q)·q, w·q, w·p, w·q, w — entries (p, p), (p, q), (p, 1),
    (q, p), (q, q), (q, 1), (1, p), (1, q), (1, 1) of w·AᵢᵀAᵢ as (w·A_a)·A_b (w·1 = w exactly)."""
    tp = w * p
    tq = w * q
    return (acc[0] + tp * p, acc[1] + tp * q, acc[2] + tp, acc[3] + tq * p, acc[4] + tq * q, acc[5] + tq,
            acc[6] + w * p, acc[7] + w * q, acc[8] + w)


@numba.njit(cache=True, nogil=True, inline="always")
def _nine(a, k):
    return (a[k, 0], a[k, 1], a[k, 2], a[k, 3], a[k, 4], a[k, 5], a[k, 6], a[k, 7], a[k, 8])


@numba.njit(cache=True, nogil=True)
def _sandwich_kernel(xy, res, sig, ok, start, xc, yc, scale, acc):  # pragma: no cover - compiled
    """N = Σ w AᵢᵀAᵢ and B = Σ w² σ² AᵢᵀAᵢ over the g_x rows [2x, y, 0, 1, 0] and g_y rows
    [0, x, 2y, 0, 1] (centred x, y), w the bisquare weights of the residuals at ``scale`` (1 if 0),
    continued in ``acc`` (4, 9): the entries (2x, y, 1)² of the g_x rows and (x, 2y, 1)² of the
    g_y rows, of N then of B. The points i = start, start + 1, … are the pixels ``ok`` (P,) (a
    map's, flat), their σ ``sig`` (P, 2) read at the pixel; returns the next i.

    Each entry (a, b) sums (w·A_a)·A_b over the points in order, g_x row before g_y row, in a
    scalar (not a memory round trip per term); the design's zeros are not multiplied (±0 terms
    leave a sum that starts at +0 unchanged): the sums of the entry-by-entry loop bit for bit
    (tests/test_surface_fit_kernels.py)."""
    nx, ny, bx, by = _nine(acc, 0), _nine(acc, 1), _nine(acc, 2), _nine(acc, 3)
    i = start - 1
    for k in range(ok.size):
        if not ok[k]:
            continue
        i += 1
        if not np.isfinite(res[i, 0] + res[i, 1] + sig[k, 0] + sig[k, 1] + xy[i, 0] + xy[i, 1]):
            continue
        x = xy[i, 0] - xc
        y = xy[i, 1] - yc
        w0 = 1.0
        w1 = 1.0
        if scale > 0:
            t = res[i, 0] / scale
            w0 = (1.0 - t * t) ** 2 if abs(t) < 1.0 else 0.0
            t = res[i, 1] / scale
            w1 = (1.0 - t * t) ** 2 if abs(t) < 1.0 else 0.0
        # (1, 1) (the y·y of g_x, then the x·x of g_y) is one sum: slot 4 of the g_x terms, 0 of the g_y terms
        nx = _row_terms(nx, w0, 2 * x, y)
        ny = _row_terms((nx[4],) + ny[1:], w1, x, 2 * y)
        nx = nx[:4] + (ny[0],) + nx[5:]
        bx = _row_terms(bx, (w0 * sig[k, 0]) ** 2, 2 * x, y)
        by = _row_terms((bx[4],) + by[1:], (w1 * sig[k, 1]) ** 2, x, 2 * y)
        bx = bx[:4] + (by[0],) + bx[5:]
    for k, t9 in enumerate((nx, ny, bx, by)):
        for j in range(9):
            acc[k, j] = t9[j]
    return i + 1


def _sandwich_matrices(acc):
    """N, B (5, 5) from the sums of :func:`_sandwich_kernel`."""
    out = (np.zeros((5, 5)), np.zeros((5, 5)))
    for M, tx, ty in ((out[0], acc[0], acc[1]), (out[1], acc[2], acc[3])):
        for k, (a, b) in enumerate(((0, 0), (0, 1), (0, 3), (1, 0), (1, 1), (1, 3), (3, 0), (3, 1), (3, 3))):
            M[a, b] = tx[k]
        for k, (a, b) in enumerate(((1, 1), (1, 2), (1, 4), (2, 1), (2, 2), (2, 4), (4, 1), (4, 2), (4, 4))):
            if k:
                M[a, b] = ty[k]
    return out


def _sandwich_sums(xy, res, sig, xc, yc, scale):
    """N, B of :func:`_sandwich_kernel` over (M, 2) points, residuals and σ."""
    acc = np.zeros((4, 9))
    _sandwich_kernel(_pairs(xy), _pairs(res), readonly(np.ascontiguousarray(sig, dtype=float).reshape(-1, 2)),
                     readonly(np.ones(len(xy), bool)), 0, float(xc), float(yc), float(scale), acc)
    return _sandwich_matrices(acc)


def _pairs(a):
    """(M, 2) float64 read-only, Fortran order — the summary's (2, M) rows transposed, no copy — the
    one argument type of the sandwich kernels (issue 25 item 4: one compile)."""
    return readonly(np.asfortranarray(np.asarray(a, dtype=np.float64).reshape(-1, 2)))


def with_uncertainty(fit: ParaboloidFit, xy, slope_std, camera_z_mm: float, *, masks=None) -> ParaboloidFit:
    """``fit`` with the standard uncertainties of its coefficients and focal lengths.

    The coefficients c = (AᵀWA)⁻¹AᵀW g are linear in the slopes g; with independent slope errors
    of standard uncertainty σ (per point and component) their covariance is the sandwich
    (AᵀWA)⁻¹ Aᵀ W Σ W A (AᵀWA)⁻¹, W the final bisquare weights (recomputed from the residuals with
    the IRLS's last scale, ``fit.scale``; 1 where that is 0). σ of f = 1/(4a') is |f|·σ_a/|a|.

    Parameters
    ----------
    xy : ndarray (M, 2)
        The points the fit used, in its order (``fit.residual_slopes`` is (M, 2)).
    slope_std : ndarray (M, 2), or with ``masks`` a sequence of (H, W, 2) maps
        σ of (g_x, g_y) at those points (rad).
    masks : sequence of (H, W) bool, optional
        The pixels of each map that are the points, maps in order, pixels in C order (what
        :func:`surface_fit_summary` fitted): σ is read in the maps, not gathered (issue 25).
    """
    xy = _pairs(xy)  # the summary's (2, M) rows transposed: no copy
    res = _pairs(fit.residual_slopes)  # the fit's rows: no copy
    if masks is None:
        sigs = [readonly(np.ascontiguousarray(slope_std, dtype=float).reshape(-1, 2))]
        masks = [readonly(np.ones(len(sigs[0]), bool))]
    else:  # flat views of the maps (no copies)
        sigs = [readonly(np.ascontiguousarray(s, dtype=float).reshape(-1, 2)) for s in slope_std]
        masks = [readonly(np.ascontiguousarray(m, dtype=bool).reshape(-1)) for m in masks]
        if (sum(int(np.count_nonzero(m)) for m in masks) != len(xy) or len(res) != len(xy)
                or any(m.size != len(s) for s, m in zip(sigs, masks)) or len(sigs) != len(masks)):
            raise ValueError("with_uncertainty: the masks' pixels are not the fit's points (or σ maps of "
                             "another size)")
    acc, cnt, i = np.zeros(2), np.zeros(1, np.int64), 0
    for s, m in zip(sigs, masks):
        i = _centre_kernel(xy, res, s, m, i, acc, cnt)
    xc, yc = acc[0] / cnt[0], acc[1] / cnt[0]
    sums, i = np.zeros((4, 9)), 0
    for s, m in zip(sigs, masks):
        i = _sandwich_kernel(xy, res, s, m, i, xc, yc, float(fit.scale), sums)
    return with_sandwich(fit, *_sandwich_matrices(sums), (xc, yc))


def with_sandwich(fit: ParaboloidFit, N, B, centre) -> ParaboloidFit:
    """``fit`` with the standard uncertainties of :func:`with_uncertainty` from N = Σ w AᵢᵀAᵢ and
    B = Σ w² σ² AᵢᵀAᵢ ((5, 5) each) of the design rows at coordinates centred on ``centre``."""
    xc, yc = centre
    Ni = np.linalg.inv(N)
    cov = Ni @ B @ Ni
    # back to the uncentred linear terms: d0 = d − 2a xc − b yc, e0 = e − b xc − 2c yc
    T = np.eye(5)
    T[3, :3] = (-2 * xc, -yc, 0.0)
    T[4, :3] = (0.0, -xc, -2 * yc)
    cov = T @ cov @ T.T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    a, c = fit.coefficients[0], fit.coefficients[2]
    fx_std = abs(fit.focal_length_x_mm) * std[0] / abs(a) if a != 0 else float("inf")
    fy_std = abs(fit.focal_length_y_mm) * std[2] / abs(c) if c != 0 else float("inf")
    from dataclasses import replace

    return replace(fit, coefficients_std=tuple(float(v) for v in std), focal_length_x_std_mm=float(fx_std),
                   focal_length_y_std_mm=float(fy_std))


#: Tukey bisquare tuning constant (95 % efficiency at the normal distribution) and MAD → σ.
_TUKEY_C = 4.685
_MAD_TO_SIGMA = 0.6745

# The IRLS below streams over the points: each pass computes the two slope residuals of a point
# on the fly (no (2M, 5) design matrix, no weighted copies of it). One iteration is the median
# of the residuals, the median of their absolute deviations (both exact, by selection within a
# bracket) and the weighted normal equations AᵀWA·c = AᵀWg (5×5, from 18 sums per point thanks
# to the design's zeros), solved after Jacobi equilibration: with centred coordinates the system
# is well conditioned, so the normal equations lose no accuracy that matters against lstsq
# (tests/test_surface_fit_kernels.py: 1e-9 relative, weights included).
# Brackets: a median is 1-Lipschitz in the sup norm, so when the coefficients change by Δc the
# median of the residuals moves by at most δ = max_i |A_i·Δc| and their MAD by at most 2δ; one
# pass then collects the few values in [m − δ, m + δ]. Without a previous value (or when the
# bracket holds too many values) a strided sample gives a bracket, a histogram pass narrows it
# to one bin and a second pass collects that bin; a full selection is the last resort.
_SAMPLE_POINTS = 16_384
_BRACKET_SIGMAS = 6.0
_N_BINS_SELECT = 8192


@numba.njit(cache=True, nogil=True, fastmath=False)
def _sample_values(x, y, gx, gy, xc, yc, coef, mode, centre, stride):
    """The residuals (``mode`` 1: their |r − centre|) of every ``stride``-th point, both rows
    (at x − xc, y − yc: the centred coordinates, here and in the kernels below)."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    k = (x.size + stride - 1) // stride
    out = np.empty(2 * k)
    j = 0
    for i in range(0, x.size, stride):
        r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, mode, centre)
        out[j] = r0
        out[j + 1] = r1
        j += 2
    return out[:j]


@numba.njit(cache=True, nogil=True, fastmath=False, inline="always")
def _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, mode, centre):
    """The two residuals of point i (``mode`` 1: their |r − centre|), at (x − xc, y − yc)."""
    xi = x[i] - xc
    yi = y[i] - yc
    r0 = gx[i] - (a2 * xi + b * yi + d)
    r1 = gy[i] - (b * xi + c2 * yi + e)
    if mode == 1:
        r0 = abs(r0 - centre)
        r1 = abs(r1 - centre)
    return r0, r1


@numba.njit(cache=True, nogil=True, fastmath=False, inline="always")
def _bin(v, lo, inv, nbins):
    """Histogram bin of v ∈ [lo, hi] (clamped; the float is clamped first: no integer overflow)."""
    return int(min(max((v - lo) * inv, 0.0), nbins - 1.0))


@numba.njit(cache=True, nogil=True, fastmath=False, inline="always")
def _take(v, lo, hi, inv, nbins, kb):
    """v in [lo, hi] and in bin kb or kb + 1 — as an integer, without branches (the comparisons
    against lo are unpredictable: a branch per value costs ~10× the pass). One bin (a bracket
    from a sample or the Lipschitz bound): [lo, hi] only (a loop-invariant test: compiled as two
    loops; 26 → 19 ms per pass over 9.2 M values)."""
    if nbins == 1:
        return (v >= lo) * (v <= hi)
    k = _bin(v, lo, inv, nbins)
    return (v >= lo) * (v <= hi) * ((k == kb) + (k == kb + 1))


@numba.njit(cache=True, nogil=True, fastmath=False)
def _collect(x, y, gx, gy, xc, yc, coef, mode, centre, lo, hi, nbins, kb, buf):
    """One pass over the 2M values (residuals, or ``mode`` 1: |r − centre|): the number of
    values < lo, and the values in [lo, hi] whose bin (``nbins`` equal bins over [lo, hi]) is
    ``kb`` or ``kb + 1`` copied to ``buf`` (as many as fit: the last slot takes the values not
    kept). Returns (below, inside); inside ≥ buf.size: the bracket held too many. Blocks are counted without branches and re-read only
    where they hold a value to copy."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    below = 0
    inside = 0
    last = buf.size - 1
    inv = nbins / (hi - lo) if hi > lo else 0.0
    bs = 256
    m = x.size
    for start in range(0, m, bs):
        stop = min(start + bs, m)
        cnt = 0
        for i in range(start, stop):
            r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, mode, centre)
            below += (r0 < lo) + (r1 < lo)
            cnt += _take(r0, lo, hi, inv, nbins, kb) + _take(r1, lo, hi, inv, nbins, kb)
        if cnt:  # each value written to the next free slot, which only a value to keep advances (no branch)
            for i in range(start, stop):
                r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, mode, centre)
                buf[min(inside, last)] = r0
                inside += _take(r0, lo, hi, inv, nbins, kb)
                buf[min(inside, last)] = r1
                inside += _take(r1, lo, hi, inv, nbins, kb)
    return below, inside


@numba.njit(cache=True, nogil=True, fastmath=False)
def _histogram(x, y, gx, gy, xc, yc, coef, mode, centre, lo, hi, hist):
    """One pass: the number of values < lo, and the histogram (``hist.size`` bins) of those in [lo, hi]."""
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    nbins = hist.size
    hist[:] = 0
    inv = nbins / (hi - lo)
    below = 0
    for i in range(x.size):
        r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, mode, centre)
        below += (r0 < lo) + (r1 < lo)
        hist[_bin(r0, lo, inv, nbins)] += (r0 >= lo) * (r0 <= hi)
        hist[_bin(r1, lo, inv, nbins)] += (r1 >= lo) * (r1 <= hi)
    return below


@numba.njit(cache=True, nogil=True, fastmath=False)
def _all_values(x, y, gx, gy, xc, yc, coef, mode, centre):
    a2, b, c2, d, e = 2.0 * coef[0], coef[1], 2.0 * coef[2], coef[3], coef[4]
    out = np.empty(2 * x.size)
    for i in range(x.size):
        r0, r1 = _pair(x, y, gx, gy, xc, yc, i, a2, b, c2, d, e, mode, centre)
        out[2 * i] = r0
        out[2 * i + 1] = r1
    return out


def _narrower(a, b):
    """The narrower of two brackets (lo, hi), either None."""
    if a is None or b is None:
        return b if a is None else a
    return a if a[1] - a[0] <= b[1] - b[0] else b


def _pick(vals, below, k1, k2, lo, hi):
    """The values of rank k1 and k2 among all, given ``below`` values < lo and ``vals`` all
    those in [lo, hi]; None if the ranks are not inside the bracket."""
    if not (below <= k1 and k2 < below + vals.size):
        return None
    part = np.partition(vals, (k1 - below, k2 - below))
    return part[k1 - below], part[k2 - below]


def _median(x, y, gx, gy, coef, mode, centre, buf, hist, bracket=None, *, ranks=False, origin=(0.0, 0.0)):
    """Exact median (numpy's: mean of the two middle values for an even count) of the 2M
    residuals (``mode`` 0) or of their absolute deviations from ``centre`` (``mode`` 1).
    ``bracket``: (lo, hi) expected to hold the two middle values (the Lipschitz bound above), or
    None (a wrong bracket costs passes, not exactness). ``ranks``: return (median, lower middle
    value, upper middle value) — what the next iteration's bracket is built from. ``origin``: (xc, yc), the
    residuals at (x − xc, y − yc)."""
    xc, yc = float(origin[0]), float(origin[1])
    x, y, gx, gy = readonly(x), readonly(y), readonly(gx), readonly(gy)  # one argument type of the kernels
    n = 2 * x.size
    k1, k2 = (n - 1) // 2, n // 2
    got = None
    stride = max(1, x.size // _SAMPLE_POINTS)
    s = np.sort(_sample_values(x, y, gx, gy, xc, yc, coef, mode, centre, stride))
    ns = s.size
    if bracket is not None and bracket[0] <= bracket[1]:
        lo, hi = bracket
        # The sample tells how many values the bracket holds: one pass if they fit the buffer.
        expected = (np.searchsorted(s, hi, side="right") - np.searchsorted(s, lo)) / ns * n
        if expected <= 0.5 * buf.size:
            below, inside = _collect(x, y, gx, gy, xc, yc, coef, mode, centre, lo, hi, 1, 0, buf)
            if inside < buf.size:  # (its last slot takes the values not kept)
                got = _pick(buf[:inside], below, k1, k2, lo, hi)
    if got is None:
        pos = k1 / max(n - 1, 1) * (ns - 1)
        half = _BRACKET_SIGMAS * np.sqrt(0.25 * ns) + 2.0
        i_lo, i_hi = int(np.floor(pos - half)), int(np.ceil(pos + half))
        lo = s[i_lo] if i_lo >= 0 else -np.inf
        hi = s[i_hi] if i_hi < ns else np.inf
        if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
            below = _histogram(x, y, gx, gy, xc, yc, coef, mode, centre, lo, hi, hist)
            cum = below + np.cumsum(hist)
            if below <= k1 and k2 < cum[-1]:
                kb = int(np.searchsorted(cum, k1, side="right"))  # the bin holding rank k1
                first = cum[kb - 1] if kb > 0 else below
                _, inside = _collect(x, y, gx, gy, xc, yc, coef, mode, centre, lo, hi, hist.size, kb, buf)
                if inside < buf.size:  # (its last slot takes the values not kept)
                    got = _pick(buf[:inside], first, k1, k2, lo, hi)
    if got is None:  # the sample misled the bracket: select among all values
        vals = np.partition(_all_values(x, y, gx, gy, xc, yc, coef, mode, centre), (k1, k2))
        got = vals[k1], vals[k2]
    v1, v2 = got
    med = float(v1) if n % 2 else float((v1 + v2) / 2.0)
    return (med, float(v1), float(v2)) if ranks else med


def _weighted_sums(x, y, gx, gy, xc, yc, coef, scale, robust):
    """Σ w·(x², xy, y², x, y, 1, g·x, g·y, g) over the g_x rows (first 9) and the g_y rows (last
    9), w the bisquare weights (1 − (r/scale)²)² (0 beyond) of the residuals at ``coef``, or 1
    if not ``robust``; at (x − xc, y − yc): blocks of 4096 points on both threads, their partial
    sums added in block order (:mod:`.surface_fit_sums`: the same bits with any thread count)."""
    from .surface_fit_sums import weighted_sums

    return weighted_sums(x, y, gx, gy, xc, yc, coef, scale, robust)


def normal_matrix(X, Y) -> np.ndarray:
    """Σ w AᵢᵀAᵢ (5, 5) of the g_x rows [2x, y, 0, 1, 0] and the g_y rows [0, x, 2y, 0, 1] from
    their weighted sums ``X``, ``Y`` = Σ w·(x², xy, y², x, y, 1) of each kind of row."""
    xx, xy, yy, x1, y1, w1 = X
    xx2, xy2, yy2, x2, y2, w2 = Y
    return np.array([
        [4 * xx, 2 * xy, 0.0, 2 * x1, 0.0],
        [2 * xy, yy + xx2, 2 * xy2, y1, x2],
        [0.0, 2 * xy2, 4 * yy2, 0.0, 2 * y2],
        [2 * x1, y1, 0.0, w1, 0.0],
        [0.0, x2, 2 * y2, 0.0, w2],
    ])


def _solve_normal(s) -> np.ndarray:
    """(a, b, c, d, e) from the sums of :func:`_weighted_sums`: rows g_x = [2x, y, 0, 1, 0],
    g_y = [0, x, 2y, 0, 1] (module docstring)."""
    M = normal_matrix(s[:6], s[9:15])
    gxx, gxy, g1 = s[6:9]
    gyx, gyy, g2 = s[15:18]
    v = np.array([2 * gxx, gxy + gyx, 2 * gyy, g1, g2])
    dg = np.sqrt(np.diag(M))
    if not np.all(dg > 0):
        raise ComputationError("the slope points do not determine a paraboloid (degenerate point set)")
    return np.linalg.solve(M / dg[:, None] / dg[None, :], v / dg) / dg


@numba.njit(cache=True, nogil=True, fastmath=False)
def _residual_kernel(x, y, gx, gy, xc, yc, a2, b, c2, d, e, rx, ry):
    for i in range(0, x.size):
        xi = x[i] - xc  # read before writing: rx, ry may be x, y or gx, gy (in place)
        yi = y[i] - yc
        gxi = gx[i]
        gyi = gy[i]
        rx[i] = gxi - (a2 * xi + b * yi + d)
        ry[i] = gyi - (b * xi + c2 * yi + e)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _extents(x, y, gx, gy, xc, yc):
    """(max |x − xc|, max |y − yc|, max(|g_x|, |g_y|)) over the points, in one pass (exact in
    any order: fastmath only lets the maxima run on vector lanes; the points are finite)."""
    mx = my = mg = 0.0
    for i in range(0, x.size):
        mx = max(mx, abs(x[i] - xc))
        my = max(my, abs(y[i] - yc))
        mg = max(mg, max(abs(gx[i]), abs(gy[i])))
    return mx, my, mg


def _residuals(x, y, gx, gy, xc, yc, a, b, c, d, e, rx, ry):
    """(g_x − (2a·x + b·y + d), g_y − (b·x + 2c·y + e)) per point at (x − xc, y − yc), written to
    rx, ry (which may be x, y or gx, gy: in place): numpy's expression of the same operations in
    the same order (bit-identical; no FMA without fastmath), in one pass."""
    _residual_kernel(x, y, gx, gy, float(xc), float(yc), float(2.0 * a), float(b), float(2.0 * c), float(d),
                     float(e), rx, ry)
    return rx, ry


def fit_paraboloid_slopes(p_sample_mm, slopes, valid, *, camera_z_mm: float, robust: bool = True,
                          max_iter: int = 100, overwrite_slopes: bool = False) -> ParaboloidFit:
    """Least-squares paraboloid over slopes (module docstring).

    Parameters
    ----------
    p_sample_mm : array (H, W, 3) or (M, 3) (or (…, 2): x, y)
        Points (x, y used) in the sample frame, mm.
    slopes : array (..., 2)
        (∂z/∂x, ∂z/∂y) at those points (rad).
    valid : array of bool (...)
    camera_z_mm : float
        The camera centre's z in the sample frame: fixes the direction "towards the camera" of
        the focal lengths' sign.
    robust : bool
        Tukey-bisquare IRLS (default) or plain least squares.
    overwrite_slopes : bool
        With every point valid and ``slopes`` an (M, 2) view of (2, M) rows (what
        :func:`surface_fit_summary` passes): the residuals are written over ``slopes`` and the
        fit's ``residual_slopes`` is that array (no (2, M) array more; issue 25, memory).

    Notes
    -----
    Streamed (numba, one pass per reduction, no (2M, 5) design matrix): the weighted normal
    equations and exact medians give the coefficients of ``np.linalg.lstsq`` on the reweighted
    design to ~1e-12 relative (tests/test_surface_fit_kernels.py).
    """
    p = np.asarray(p_sample_mm, dtype=float)
    g = np.asarray(slopes, dtype=float)
    ok = (np.asarray(valid, dtype=bool) & np.isfinite(p[..., 0]) & np.isfinite(p[..., 1]) & np.isfinite(g[..., 0])
          & np.isfinite(g[..., 1]))
    n = int(np.count_nonzero(ok))
    if n < 6:
        raise ComputationError(f"only {n} points with slopes: a paraboloid over slopes needs at least 6")
    # Centred coordinates for conditioning (a, b, c do not depend on the origin): every point
    # valid, the kernels centre x − xc, y − yc on the fly (the same numbers as a centred copy,
    # without it), else a centred copy of the valid points (origin 0).
    if n == ok.size:
        xc, yc = float(p[..., 0].mean()), float(p[..., 1].mean())
        x, y = np.ascontiguousarray(p[..., 0]).reshape(-1), np.ascontiguousarray(p[..., 1]).reshape(-1)
        gx, gy = np.ascontiguousarray(g[..., 0]).reshape(-1), np.ascontiguousarray(g[..., 1]).reshape(-1)
        ox, oy = xc, yc
    else:
        x, y, gx, gy = p[..., 0][ok], p[..., 1][ok], g[..., 0][ok], g[..., 1][ok]
        xc, yc = x.mean(), y.mean()
        x -= xc
        y -= yc
        ox = oy = 0.0
    # read-only views for the kernels: one argument type whatever the caller's arrays (the
    # residuals are written through the writable arrays at the end)
    xw, yw, gxw, gyw = x, y, gx, gy
    x, y, gx, gy = readonly(x), readonly(y), readonly(gx), readonly(gy)
    coef, scale = _irls(x, y, gx, gy, (ox, oy), robust, max_iter)
    a, b, c, d, e = coef
    if n == ok.size:
        rows = g.T if (overwrite_slopes and g.ndim == 2 and g.shape[1] == 2 and g.T.flags.c_contiguous
                       and g.flags.writeable and np.may_share_memory(gxw, g)) else np.empty((2, n))
        rx, ry = _residuals(x, y, gx, gy, ox, oy, a, b, c, d, e, rows[0], rows[1])  # g − A·c
        res = rows.T.reshape(g.shape)  # a view of the (2, M) rows rx, ry (or ``slopes`` itself)
    else:
        rx, ry = _residuals(x, y, gx, gy, ox, oy, a, b, c, d, e, xw, yw)  # over the centred copies
        res = np.full(g.shape, np.nan)
        res[ok, 0] = rx
        res[ok, 1] = ry
    return fit_result(coef, (xc, yc), rx, ry, res, camera_z_mm, scale if robust else 0.0)


def _irls(x, y, gx, gy, origin, robust, max_iter, extents=None):
    """The centred coefficients (a, b, c, d, e) ((5,) array) and the last bisquare scale (0 if
    not ``robust``) of the fit of the M points x, y, g (read-only (M,) arrays) at
    (x − xc, y − yc), ``origin`` = (xc, yc) (:func:`fit_paraboloid_slopes`). ``extents``: the
    points' (min x, max x, min y, max y, max |g|), if known (else one pass finds them)."""
    ox, oy = origin
    n = x.size
    scale = 0.0
    coef = _solve_normal(_weighted_sums(x, y, gx, gy, ox, oy, np.zeros(5), 1.0, False))
    if robust:
        from .surface_fit_select import median_and_mad, sample_bracket
        from .surface_fit_window import WindowedMedians

        buf = np.empty(min(2 * n, max(4096, (2 * n) // 12)))  # (a sample's bracket: ~3 % of the values)
        hist = np.empty(_N_BINS_SELECT, np.int64)
        if extents is None:
            ax, ay, g_max = _extents(x, y, gx, gy, ox, oy)
        else:  # max |x − xc| = max(x_max − xc, xc − x_min) exactly (the rounded difference is monotonic)
            ax, ay, g_max = (max(extents[1] - ox, ox - extents[0]), max(extents[3] - oy, oy - extents[2]),
                             float(extents[4]))
        reach = (2.0 * ax, ay, ax, 2.0 * ay)  # |∂r_x/∂(a, b)|, |∂r_y/∂(b, c)|
        med = mad = delta = None
        m1 = m2 = d1 = d2 = 0.0  # the two middle values of the residuals and of their deviations
        buf_z = np.empty(buf.size)
        stride = max(1, n // _SAMPLE_POINTS)
        windowed = WindowedMedians(x, y, gx, gy, reach, g_max, (ox, oy))
        for _ in range(max_iter):
            # Each order statistic moves by at most delta (the deviations by 2·delta): the next
            # brackets hold the two middle values, not only their mean (adjacent order
            # statistics of 9 M values lie ~1e-10 apart, wider than delta near convergence).
            both = sample = None
            if delta is not None:  # both medians from a window of the points (surface_fit_window)
                both = windowed(coef, (m1, m2), (d1, d2), delta)
            if both is None:  # or from one pass (surface_fit_select), if the brackets allow
                sample = np.sort(_sample_values(x, y, gx, gy, ox, oy, coef, 0, 0.0, stride))
            if both is None and delta is not None:
                both = median_and_mad(x, y, gx, gy, coef, (m1 - delta, m2 + delta),
                                      (max(d1 - 2.0 * delta, 0.0), d2 + 2.0 * delta), buf, buf_z, origin=(ox, oy),
                                      sample=sample)
            if both is not None:
                (med, m1, m2), (mad, d1, d2) = both
            else:  # two selections, each in the narrower of the Lipschitz bracket and the sample's
                med, m1, m2 = _median(x, y, gx, gy, coef, 0, 0.0, buf, hist,
                                      _narrower(None if delta is None else (m1 - delta, m2 + delta),
                                                sample_bracket(sample, 2 * n)), ranks=True, origin=(ox, oy))
                mad, d1, d2 = _median(x, y, gx, gy, coef, 1, med, buf, hist,
                                      _narrower(None if delta is None else (max(d1 - 2.0 * delta, 0.0),
                                                                            d2 + 2.0 * delta),
                                                sample_bracket(np.sort(np.abs(sample - med)), 2 * n)),
                                      ranks=True, origin=(ox, oy))
            s = mad / _MAD_TO_SIGMA
            scale = _TUKEY_C * s if s > 0 else 0.0
            if not s > 0:
                break
            new = _solve_normal(_weighted_sums(x, y, gx, gy, ox, oy, coef, _TUKEY_C * s, True))
            dc = np.abs(new - coef)
            done = np.max(dc) <= 1e-12 * max(1.0, np.max(np.abs(coef)))
            # max_i |A_i·Δc| (both rows), widened for rounding: the brackets of the next medians.
            delta = (max(reach[0] * dc[0] + reach[1] * dc[1] + dc[3], reach[2] * dc[1] + reach[3] * dc[2] + dc[4])
                     * (1.0 + 1e-6) + 1e-12 * (abs(med) + mad))
            coef = new
            if done:
                break
    return coef, scale


def fit_result(coef, centre, rx, ry, residual_slopes, camera_z_mm, scale) -> ParaboloidFit:
    """The :class:`ParaboloidFit` of the centred coefficients ``coef`` (a, b, c, d, e) at
    ``centre`` = (xc, yc) and the M residuals ``rx``, ``ry`` ((M,) each): uncentred linear
    terms, focal lengths towards the camera, residual RMS (numpy's dot products)."""
    a, b, c, d, e = coef
    xc, yc = centre
    # Back to uncentred linear terms: g_x = 2a(x − xc) + b(y − yc) + d.
    d0 = d - 2 * a * xc - b * yc
    e0 = e - b * xc - 2 * c * yc
    n = rx.size
    rms = float(np.sqrt((np.dot(rx, rx) + np.dot(ry, ry)) / (2 * n)))
    towards = -1.0 if camera_z_mm < 0 else 1.0
    with np.errstate(divide="ignore"):
        fx = float(1.0 / (4.0 * towards * a)) if a != 0 else float("inf")
        fy = float(1.0 / (4.0 * towards * c)) if c != 0 else float("inf")
    return ParaboloidFit((float(a), float(b), float(c), float(d0), float(e0)), fx, fy, rms * 1e3, residual_slopes, n,
                         scale=float(scale), centre=(float(xc), float(yc)))


def surface_fit_summary(recs, camera_z_mm, slope_std=None) -> tuple[ParaboloidFit, dict]:
    """Joint paraboloid fit over several reconstructions of one sample (same sample frame).

    ``recs`` : list of :class:`~pmdsim.evaluation.integration.Reconstruction`; ``camera_z_mm``
    the (first) camera's z in the sample frame; ``slope_std`` (optional): per reconstruction the
    slopes' standard uncertainty (H, W, 2) in rad, or None for all — the fit then carries the σ
    of its coefficients (:func:`with_uncertainty`). Returns the fit and per-camera extras
    ``{"slopes": (H, W, 2), "height_detrended_mm": (H, W), "residual_slopes": (H, W, 2)}``.

    The fit's residuals (its ``residual_slopes``: (M, 2), cameras in order, pixels in C order),
    the residual maps and the σ sandwich's sums come from one pass per camera over its maps
    (:mod:`.surface_fit_final`).
    """
    from .surface_fit_final import final_pass, summary_in_parts
    from .surface_fit_rows import slopes_and_rows

    heights = [remove_piston_tilt(rec.p_sample_mm, rec.reconstructed)[0] for rec in recs]
    oks, extras = [], []
    use_sig = slope_std is not None and all(s is not None for s in slope_std)
    # x, y and the slopes of the fitted points as (2, M) rows (what the fit reads: no per-camera
    # copies, no column copies in the fit), cameras in order, pixels in C order, written with the
    # slopes (room for every pixel: the pages past the fitted points are never touched)
    room = sum(int(np.asarray(rec.reconstructed).size) for rec in recs)
    xy, gxy = np.empty((2, room)), np.empty((2, room))
    spare = xy.reshape(-1)  # after the IRLS: the cameras' residual maps (2·H·W values each), pages already touched
    m, ext = 0, np.array([np.inf, -np.inf, np.inf, -np.inf, 0.0])
    for rec in recs:
        g, ok, m = slopes_and_rows(rec.n_sample, rec.reconstructed, rec.p_sample_mm, m, (xy[0], xy[1], gxy[0], gxy[1]),
                                   ext)
        oks.append(ok)
        extras.append({"slopes": g})
    xy, gxy = xy[:, :m], gxy[:, :m]
    centre = (float(xy[0].mean()), float(xy[1].mean())) if m >= 6 else (np.nan, np.nan)
    if not (np.isfinite(centre[0]) and np.isfinite(centre[1])):  # too few points, or a non-finite x, y
        return summary_in_parts(recs, camera_z_mm, slope_std if use_sig else None, oks, extras, xy, gxy)
    coef, scale = _irls(readonly(xy[0]), readonly(xy[1]), readonly(gxy[0]), readonly(gxy[1]), centre, True, 100, ext)
    del xy
    sums, start, used = np.zeros(24), 0, 0
    for i, (rec, ok, ex) in enumerate(zip(recs, oks, extras)):  # the residuals written over the slope rows
        out = spare[used:used + 2 * ok.size].reshape(ok.shape + (2,))
        used += 2 * ok.size
        ex["residual_slopes"], start = final_pass(rec.p_sample_mm, ex["slopes"], slope_std[i] if use_sig else None,
                                                  ok, start, centre, coef, scale, (gxy[0], gxy[1]), sums, out=out)
    del spare
    fit = fit_result(coef, centre, gxy[0], gxy[1], gxy.T, camera_z_mm, scale)
    if use_sig:
        fit = with_sandwich(fit, normal_matrix(sums[0:6], sums[6:12]), normal_matrix(sums[12:18], sums[18:24]),
                            centre)
    for rec, ex in zip(recs, extras):
        ex["height_detrended_mm"] = heights.pop(0)
    return fit, extras
