"""Pinhole camera with lens distortion (paper §2.2, eqs. 2–4), OpenCV's distortion model.

Conventions (docs/conventions.md): camera frame x right, y down, z forward; pixel (0, 0) is the
centre of the top-left pixel (as in OpenCV); per-pixel arrays are indexed ``[v, u]``. The
distortion model is OpenCV's (``cv::projectPoints``, docs of ``calib3d``): radial rational
(k1, k2, k3 over k4, k5, k6), tangential (p1, p2) and thin prism (s1–s4); the paper's Brown
eq. (3) is the case k3 = k4 = k5 = k6 = s1 = … = s4 = 0. OpenCV's tilted-sensor terms
(τx, τy) are not modelled (refused when non-zero).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields, replace

import numba
import numpy as np

from ..errors import SetupError
from .camera_checks import check_camera_matrix, check_image_size, warn_if_folds_over

__all__ = ["Camera", "UNDISTORT_TOL", "DISTORTION_NAMES", "OPENCV_LENGTHS"]

#: Convergence tolerance of the distortion inversion, in normalised image coordinates.
UNDISTORT_TOL = 1e-12
_UNDISTORT_MAX_ITER = 100


#: OpenCV's distortion coefficients in its order, as held by :class:`Camera` (the tilted-sensor
#: terms τx, τy of OpenCV's 14-coefficient vector are not supported).
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")
#: Lengths of OpenCV distortion vectors that :meth:`Camera.from_opencv` accepts.
OPENCV_LENGTHS = (4, 5, 8, 12, 14)


@numba.njit(cache=True, nogil=True)
def _unpack(c):
    """The kernels' coefficients: a 12-tuple (k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4) from
    the array, and whether the rational (k4–k6) and thin-prism (s1–s4) terms are present. (A tuple
    keeps the coefficients in registers: with the array the inversion ran 2× slower.)"""
    t = (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10], c[11])
    rational = t[5] != 0.0 or t[6] != 0.0 or t[7] != 0.0
    prism = t[8] != 0.0 or t[9] != 0.0 or t[10] != 0.0 or t[11] != 0.0
    return t, rational, prism


@numba.njit(cache=True, nogil=True)
def _distort(x, y, c, rational, prism):
    """OpenCV's distortion of normalised (x, y); c = (k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4).

    Without the rational or thin-prism terms (flags) they are skipped: the arithmetic of a Brown
    camera is exactly eq. (3).
    """
    k1, k2, p1, p2, k3 = c[0], c[1], c[2], c[3], c[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if rational:
        radial = radial / (1.0 + r2 * (c[5] + r2 * (c[6] + r2 * c[7])))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    if prism:
        xd += r2 * (c[8] + r2 * c[9])
        yd += r2 * (c[10] + r2 * c[11])
    return xd, yd


@numba.njit(cache=True, nogil=True)
def _distort_jac(x, y, c, rational, prism):
    """Jacobian of the distortion with respect to (x, y): (dxd/dx, dxd/dy, dyd/dx, dyd/dy),
    and the rational model's numerator and denominator (num, den)."""
    k1, k2, p1, p2, k3 = c[0], c[1], c[2], c[3], c[4]
    r2 = x * x + y * y
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d num / d r2
    den = 1.0
    radial = num
    dradial = dnum  # d radial / d r2
    if rational:
        den = 1.0 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
        dden = c[5] + r2 * (2.0 * c[6] + 3.0 * c[7] * r2)  # d den / d r2
        radial = num / den
        dradial = (dnum * den - num * dden) / (den * den)
    a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    cc = b
    d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    if prism:
        sx = 2.0 * (c[8] + 2.0 * c[9] * r2)  # d(r2 (s1 + s2 r2)) / d r2, times 2 (dr2/dx = 2x)
        sy = 2.0 * (c[10] + 2.0 * c[11] * r2)
        a += x * sx
        b += y * sx
        cc += x * sy
        d += y * sy
    return a, b, cc, d, num, den


@numba.njit(cache=True, nogil=True)
def _physical(x, y, c, rational, prism):
    """True if (x, y) lies where the distortion is a valid, orientation-preserving map: the
    rational model's denominator and the radial factor positive, det J > 0."""
    a, b, cc, d, num, den = _distort_jac(x, y, c, rational, prism)
    return den > 0.0 and num / den > 0.0 and (a * d - b * cc) > 0.0


@numba.njit(cache=True, nogil=True)
def _newton(xd, yd, x, y, c, rational, prism, tol, max_iter, damped):
    """Newton's method for distort(x, y) = (xd, yd) from (x, y). With ``damped`` a step that
    does not reduce the residual is halved (up to 40 times). Returns (x, y, converged)."""
    fx, fy = _distort(x, y, c, rational, prism)
    rx = fx - xd
    ry = fy - yd
    for _ in range(max_iter):
        a, b, cc, d, num, den = _distort_jac(x, y, c, rational, prism)
        det = a * d - b * cc
        if det == 0.0 or not np.isfinite(det):
            return x, y, False
        dx = (d * rx - b * ry) / det
        dy = (-cc * rx + a * ry) / det
        if damped:
            res0 = rx * rx + ry * ry
            t = 1.0
            for _h in range(40):
                fx, fy = _distort(x - t * dx, y - t * dy, c, rational, prism)
                if (fx - xd) ** 2 + (fy - yd) ** 2 < res0 or res0 == 0.0:
                    break
                t *= 0.5
            dx *= t
            dy *= t
        x -= dx
        y -= dy
        if abs(dx) <= tol and abs(dy) <= tol:
            fx, fy = _distort(x, y, c, rational, prism)
            ok = abs(fx - xd) <= tol and abs(fy - yd) <= tol
            return x, y, ok
        fx, fy = _distort(x, y, c, rational, prism)
        rx = fx - xd
        ry = fy - yd
    return x, y, False


@numba.njit(cache=True, nogil=True)
def _radial_start(xd, yd, c):
    """Initial guess on the identity's branch for strong distortion: the radius r with
    r·R(r²) = |(xd, yd)| of the radial part alone, bracketed by marching out from r = 0 while
    r·R(r²) increases (steps halved near a fold or a pole, so none is crossed), then bisected.
    Returns (x, y, found)."""
    rho = math.sqrt(xd * xd + yd * yd)
    if rho == 0.0:
        return 0.0, 0.0, True
    k1, k2, k3 = c[0], c[1], c[4]
    step = rho / 32.0
    lo = 0.0
    g_lo = 0.0
    hi = -1.0
    while lo < 64.0 * rho:
        r = lo + step
        r2 = r * r
        den = 1.0 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
        g = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / den
        if not den > 0.0 or not g > g_lo:
            # A fold or a pole within this step: refine the step; a fold before rho remains one.
            step *= 0.5
            if step <= 1e-12 * rho:
                return xd, yd, False
            continue
        if g >= rho:
            hi = r
            break
        lo = r
        g_lo = g
    if hi < 0.0:
        return xd, yd, False
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        r2 = mid * mid
        g = mid * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (c[5] + r2 * (c[6] + r2 * c[7])))
        if g < rho:
            lo = mid
        else:
            hi = mid
    r = 0.5 * (lo + hi)
    return xd * r / rho, yd * r / rho, True


@numba.njit(cache=True, nogil=True)
def _undistort_fallback(xd, yd, x, y, c, rational, prism, tol, max_iter):
    """The second attempt of :func:`_undistort_one` where Newton from (xd, yd) ended at (x, y)
    without a physical inverse: damped Newton from :func:`_radial_start`. Returns (x, y,
    converged), the first attempt's (x, y) where this one fails too."""
    x0, y0, found = _radial_start(xd, yd, c)
    if not found:
        return x, y, False
    x1, y1, ok1 = _newton(xd, yd, x0, y0, c, rational, prism, tol, max_iter, True)
    if ok1 and _physical(x1, y1, c, rational, prism):
        return x1, y1, True
    return x, y, False


@numba.njit(cache=True, nogil=True)
def _undistort_one(xd, yd, c, rational, prism, tol, max_iter):
    """Invert the distortion. Returns (x, y, converged).

    Newton's method from (x, y) = (xd, yd) first (the paper's inversion of eq. 3; for mild
    distortion it converges in a few steps). Where that fails or ends on a non-physical branch
    (strong rational or wide-angle distortion, where Newton from (xd, yd) can jump past a fold
    or a pole), a damped Newton from the radial-only inverse (:func:`_radial_start`) follows.
    A physical inverse lies on the branch of the identity: the distortion must be
    orientation-preserving there (det J > 0), the radial factor and the rational model's
    denominator positive; beyond a fold-over there is no such inverse and the pixel is reported
    as not converged.

    The kernels run the first attempt in lock-step over blocks of pixels
    (:func:`_newton_lanes`), with the same arithmetic per pixel: this per-pixel form is its
    definition (the tests compare the kernels with it bit for bit).
    """
    x, y, ok = _newton(xd, yd, xd, yd, c, rational, prism, tol, max_iter, False)
    if ok and _physical(x, y, c, rational, prism):
        return x, y, True
    return _undistort_fallback(xd, yd, x, y, c, rational, prism, tol, max_iter)


#: Pixels inverted in lock-step (:func:`_newton_lanes`): wide enough that the vector units carry
#: several independent Newton chains at once (32 measured fastest of 4, 8, 16, 32;
#: docs/benchmarks.md, "view rays after brown25c").
_LANES = 32
#: Pixels per parallel chunk of :func:`_undistort_kernel` and of :func:`_rays_kernel`'s pixel
#: list (a sensor's rays go by rows).
_CHUNK = 32 * _LANES
# Rows of the lanes' work array w (7 × _LANES): inputs xd, yd; iterate x, y; residual rx, ry;
# state (0 iterating / not converged, 1 converged, 2 stopped; after the run 1 = physical inverse).
_XD, _YD, _X, _Y, _RX, _RY, _ST = (j * _LANES for j in range(7))

# The distortion and its Jacobian inlined into the lanes' loops (numba IR), so that the loops
# vectorise: called, they stay scalar calls. The same source, hence the same arithmetic.
_distort_inline = numba.njit(inline="always")(_distort.py_func)
_distort_jac_inline = numba.njit(inline="always")(_distort_jac.py_func)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _newton_lanes(w, c, rational, prism, tol, max_iter):
    """Newton's first attempt of :func:`_undistort_one` for ``_LANES`` pixels in lock-step.

    ``w`` (7 × _LANES,) holds the inputs xd, yd at ``_XD``, ``_YD``; on return x, y at ``_X``,
    ``_Y`` and at ``_ST`` 1.0 where the attempt converged to a physical inverse, else 0.0 (those
    pixels need :func:`_undistort_fallback` from x, y). Every pixel does exactly the arithmetic
    of :func:`_newton` (undamped) and :func:`_physical`: all lanes compute every iteration, and
    a lane that has stopped (converged, or a zero or non-finite determinant) keeps its values
    through selects, so the results are bit-identical and the loops branch-free (they
    vectorise). The iteration ends when no lane is iterating, or after ``max_iter``.
    """
    for k in range(_LANES):
        fx, fy = _distort_inline(w[_XD + k], w[_YD + k], c, rational, prism)
        w[_X + k] = w[_XD + k]
        w[_Y + k] = w[_YD + k]
        w[_RX + k] = fx - w[_XD + k]
        w[_RY + k] = fy - w[_YD + k]
        w[_ST + k] = 0.0
    for _ in range(max_iter):
        iterating = 0
        for k in range(_LANES):
            x = w[_X + k]
            y = w[_Y + k]
            rx = w[_RX + k]
            ry = w[_RY + k]
            a, b, cc, d, _num, _den = _distort_jac_inline(x, y, c, rational, prism)
            det = a * d - b * cc
            dx = (d * rx - b * ry) / det
            dy = (-cc * rx + a * ry) / det
            xn = x - dx
            yn = y - dy
            fx, fy = _distort_inline(xn, yn, c, rational, prism)
            rxn = fx - w[_XD + k]
            ryn = fy - w[_YD + k]
            state = w[_ST + k]
            live = state == 0.0
            bad = (det == 0.0) | (not (abs(det) < np.inf))  # det == 0 or not finite
            step = live & (not bad)
            small = (abs(dx) <= tol) & (abs(dy) <= tol)
            ok = (abs(rxn) <= tol) & (abs(ryn) <= tol)
            w[_X + k] = xn if step else x
            w[_Y + k] = yn if step else y
            w[_RX + k] = rxn if step else rx
            w[_RY + k] = ryn if step else ry
            state = 2.0 if live & bad else state
            state = (1.0 if ok else 2.0) if step & small else state
            w[_ST + k] = state
            iterating += 1 if step & (not small) else 0
        if iterating == 0:
            break
    for k in range(_LANES):
        a, b, cc, d, num, den = _distort_jac_inline(w[_X + k], w[_Y + k], c, rational, prism)
        good = (w[_ST + k] == 1.0) & (den > 0.0) & (num / den > 0.0) & ((a * d - b * cc) > 0.0)
        w[_ST + k] = 1.0 if good else 0.0


@numba.njit(cache=True, nogil=True)
def _lane_result(w, k, c, rational, prism, tol, max_iter):
    """Lane ``k``'s inverse after :func:`_newton_lanes`, with :func:`_undistort_fallback` where
    the first attempt failed: (x, y, converged) as :func:`_undistort_one` returns them."""
    if w[_ST + k] == 1.0:
        return w[_X + k], w[_Y + k], True
    return _undistort_fallback(w[_XD + k], w[_YD + k], w[_X + k], w[_Y + k], c, rational, prism, tol, max_iter)


@numba.njit(cache=True, nogil=True, parallel=True)
def _undistort_kernel(xyd, coeffs, tol, max_iter, out, ok):
    """:func:`_undistort_one` of the points ``xyd`` (N, 2) into ``out`` (N, 2) and ``ok`` (N,),
    ``_LANES`` at a time (:func:`_newton_lanes`)."""
    c, rational, prism = _unpack(coeffs)
    n = xyd.shape[0]
    for ch in numba.prange(0, (n + _CHUNK - 1) // _CHUNK):
        w = np.empty(7 * _LANES)
        hi = min(ch * _CHUNK + _CHUNK, n)
        for s in range(ch * _CHUNK, hi, _LANES):
            m = min(_LANES, hi - s)
            for k in range(_LANES):
                i = s + k if k < m else s  # lanes past the end repeat the block's first point
                w[_XD + k] = xyd[i, 0]
                w[_YD + k] = xyd[i, 1]
            _newton_lanes(w, c, rational, prism, tol, max_iter)
            for k in range(m):
                x, y, conv = _lane_result(w, k, c, rational, prism, tol, max_iter)
                out[s + k, 0] = x
                out[s + k, 1] = y
                ok[s + k] = conv


@numba.njit(cache=True, nogil=True, parallel=True)
def _rays_kernel(uv, grid_w, fx, fy, ppx, ppy, coeffs, distorted, tol, max_iter, d, ok):
    """View rays (x, y, 1) of pixels: ``uv`` (N, 2), or with ``grid_w`` > 0 the pixel centres
    of a sensor ``grid_w`` wide (u = i mod w, v = i div w; ``uv`` unused) — one pass, no
    pixel grid, normalised-coordinate or concatenated temporaries. Same arithmetic as
    :meth:`Camera.pixel_to_normalized` + :func:`_undistort_one`; with distortion the pixels
    are inverted ``_LANES`` at a time (:func:`_newton_lanes`), a sensor by rows."""
    c, rational, prism = _unpack(coeffs)
    n = d.shape[0]
    if not distorted:
        for i in numba.prange(0, n):
            if grid_w > 0:
                u = float(i % grid_w)
                v = float(i // grid_w)
            else:
                u = uv[i, 0]
                v = uv[i, 1]
            d[i, 0] = (u - ppx) / fx
            d[i, 1] = (v - ppy) / fy
            d[i, 2] = 1.0
            ok[i] = True
        return
    chunk = grid_w if grid_w > 0 else _CHUNK
    for ch in numba.prange(0, (n + chunk - 1) // chunk):
        w = np.empty(7 * _LANES)
        lo = ch * chunk
        hi = min(lo + chunk, n)
        for s in range(lo, hi, _LANES):
            m = min(_LANES, hi - s)
            for k in range(_LANES):
                i = s + k if k < m else s  # lanes past the end repeat the block's first pixel
                if grid_w > 0:
                    u = float(i - lo)
                    v = float(ch)
                else:
                    u = uv[i, 0]
                    v = uv[i, 1]
                w[_XD + k] = (u - ppx) / fx
                w[_YD + k] = (v - ppy) / fy
            _newton_lanes(w, c, rational, prism, tol, max_iter)
            for k in range(m):
                x, y, conv = _lane_result(w, k, c, rational, prism, tol, max_iter)
                d[s + k, 0] = x
                d[s + k, 1] = y
                d[s + k, 2] = 1.0
                ok[s + k] = conv


@numba.njit(cache=True, nogil=True)
def _jacobian_kernel(xy, coeffs, out):
    c, rational, prism = _unpack(coeffs)
    for i in range(xy.shape[0]):
        a, b, cc, d, _, _ = _distort_jac(xy[i, 0], xy[i, 1], c, rational, prism)
        out[i, 0, 0] = a
        out[i, 0, 1] = b
        out[i, 1, 0] = cc
        out[i, 1, 1] = d


@functools.lru_cache(maxsize=4)
def _sensor_rays_cached(camera: "Camera") -> tuple[np.ndarray, np.ndarray]:
    d, ok = camera._rays(None)
    d.setflags(write=False)
    ok.setflags(write=False)
    return d, ok


@dataclass(frozen=True)
class Camera:
    """Intrinsic model of one camera: pinhole + OpenCV lens distortion (paper §2.2).

    The camera's pose is not part of this object; a setup stores it as ``T_world_cam``.

    Parameters
    ----------
    width_px, height_px : int
        Image size in pixels (> 0).
    fx_px, fy_px : float
        Focal lengths in pixels (> 0), eq. (4).
    ppx_px, ppy_px : float
        Principal point in pixels, eq. (4); pixel (0, 0) is the centre of the top-left pixel.
    k1, k2, p1, p2, k3 : float
        Brown distortion coefficients of eq. (3) (k3 beyond the paper, OpenCV's fifth coefficient).
    k4, k5, k6 : float
        Denominator of OpenCV's rational radial model,
        (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶).
    s1, s2, s3, s4 : float
        OpenCV's thin-prism coefficients: x' += s1 r² + s2 r⁴, y' += s3 r² + s4 r⁴.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    ppx_px: float
    ppy_px: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0
    s4: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not np.isfinite(v):
                raise ValueError(f"Camera.{f.name} must be finite, got {v!r}")
        if int(self.width_px) != self.width_px or self.width_px <= 0:
            raise ValueError(f"Camera.width_px must be a positive integer, got {self.width_px!r}")
        if int(self.height_px) != self.height_px or self.height_px <= 0:
            raise ValueError(f"Camera.height_px must be a positive integer, got {self.height_px!r}")
        if self.fx_px <= 0 or self.fy_px <= 0:
            raise ValueError(f"Camera focal lengths must be > 0, got fx={self.fx_px}, fy={self.fy_px}")
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))

    # ------------------------------------------------------------------ builders / readers
    @classmethod
    def from_opencv(cls, camera_matrix, dist_coeffs, image_size_px, *, source: str = "camera") -> "Camera":
        """From OpenCV's camera matrix K (3, 3), distortion vector and image size (W, H).

        Parameters
        ----------
        camera_matrix : array_like, shape (3, 3)
            [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels; checked by
            :func:`pmdsim.geometry.camera_checks.check_camera_matrix` (normalised, no skew,
            positive focal lengths).
        dist_coeffs : array_like, 4, 5, 8, 12 or 14 entries (or empty)
            OpenCV's order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, τx, τy]]]]);
            the tilted-sensor terms τx, τy must be 0.
        image_size_px : (int, int)
            (width, height); checked by :func:`~pmdsim.geometry.camera_checks.check_image_size`.
        source : str
            What the values are called in error messages (a file name or key).

        Pixel coordinates need no conversion: OpenCV's pixel (0, 0) is the centre of the
        top-left pixel, as pmdsim's. A distortion that folds over inside the image warns
        (:class:`~pmdsim.geometry.camera_checks.CameraModelWarning`).
        """
        k = check_camera_matrix(camera_matrix, source=source)
        dc = np.asarray(dist_coeffs, dtype=float).ravel()
        if dc.size not in (0,) + OPENCV_LENGTHS:
            raise SetupError(f"{source}: distortion coefficients must have 4, 5, 8, 12 or 14 entries "
                             f"(OpenCV's (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, τx, τy]]]])), "
                             f"got {dc.size}")
        if not np.isfinite(dc).all():
            raise SetupError(f"{source}: distortion coefficients must be finite, got {dc.tolist()}")
        if dc.size == 14 and (dc[12] != 0.0 or dc[13] != 0.0):
            raise SetupError(f"{source}: the tilted-sensor distortion terms (τx, τy) = ({float(dc[12])!r}, "
                             f"{float(dc[13])!r}) "
                             f"are not supported by pmdsim's camera model; only τx = τy = 0 (coefficients 13 "
                             f"and 14 of 14) can be imported")
        d = np.zeros(len(DISTORTION_NAMES))
        n = min(dc.size, len(DISTORTION_NAMES))
        d[:n] = dc[:n]
        w, h = check_image_size(image_size_px, (k[0, 2], k[1, 2]), source=source)
        cam = cls(w, h, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                  **{name: float(v) for name, v in zip(DISTORTION_NAMES, d)})
        warn_if_folds_over(cam, source=source)
        return cam

    def as_opencv(self, n_coefficients: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(camera_matrix (3, 3), dist_coeffs) in OpenCV's layout.

        ``dist_coeffs`` has ``n_coefficients`` entries (4, 5, 8, 12 or 14), by default the
        shortest of 5, 8, 12 that holds every non-zero coefficient (see :attr:`distortion`).
        Asking for fewer than that raises ValueError.
        """
        k = np.array([[self.fx_px, 0.0, self.ppx_px], [0.0, self.fy_px, self.ppy_px], [0.0, 0.0, 1.0]])
        if n_coefficients is None:
            return k, self.distortion
        n = int(n_coefficients)
        if n not in OPENCV_LENGTHS:
            raise ValueError(f"n_coefficients must be one of {OPENCV_LENGTHS}, got {n_coefficients!r}")
        full = self._coefficients()
        if n < len(DISTORTION_NAMES) and np.any(full[n:] != 0.0):
            names = [DISTORTION_NAMES[i] for i in np.flatnonzero(full[n:] != 0.0) + n]
            raise ValueError(f"a {n}-coefficient OpenCV vector cannot hold the non-zero {', '.join(names)}")
        return k, np.concatenate([full, np.zeros(2)])[:n]

    def binned(self, factor: int) -> "Camera":
        """The same camera with ``factor`` × ``factor`` pixels binned into one.

        Same field of view and distortion: W' = W // factor, H' = H // factor,
        f' = f / factor, and since binned pixel u' covers original pixels
        factor·u' … factor·u' + factor − 1 (centre factor·u' + (factor − 1)/2),
        pp' = (pp − (factor − 1)/2) / factor.
        """
        k = int(factor)
        if k != factor or k < 1:
            raise ValueError(f"binning factor must be a positive integer, got {factor!r}")
        if self.width_px // k < 1 or self.height_px // k < 1:
            raise ValueError(f"binning factor {k} leaves no pixel of a {self.width_px}×{self.height_px} sensor")
        c = (k - 1) / 2.0
        return replace(
            self,
            width_px=self.width_px // k,
            height_px=self.height_px // k,
            fx_px=self.fx_px / k,
            fy_px=self.fy_px / k,
            ppx_px=(self.ppx_px - c) / k,
            ppy_px=(self.ppy_px - c) / k,
        )

    def _coefficients(self) -> np.ndarray:
        """All 12 coefficients in OpenCV's order (:data:`DISTORTION_NAMES`), the kernels' input."""
        return np.array([getattr(self, name) for name in DISTORTION_NAMES], dtype=float)

    @property
    def distortion(self) -> np.ndarray:
        """OpenCV's distortion vector: (k1, k2, p1, p2, k3), extended to 8 entries (k4, k5, k6)
        or 12 (s1…s4) when those are non-zero."""
        full = self._coefficients()
        nz = np.flatnonzero(full != 0.0)
        n = 5 if nz.size == 0 or nz[-1] < 5 else (8 if nz[-1] < 8 else 12)
        return full[:n]

    @property
    def is_brown(self) -> bool:
        """True if only the Brown coefficients (k1, k2, p1, p2, k3) may be non-zero (the model
        the calibration estimates)."""
        return self.distortion.size == 5

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of per-pixel arrays."""
        return (self.height_px, self.width_px)

    # ------------------------------------------------------------------ model
    def distort(self, xy_n) -> np.ndarray:
        """Eq. (3) with OpenCV's rational and thin-prism terms: undistorted → distorted
        normalised coordinates, shape (..., 2) → (..., 2).

            x' = x·R(r²) + 2 p1 x y + p2 (r² + 2x²) + s1 r² + s2 r⁴
            y' = y·R(r²) + p1 (r² + 2y²) + 2 p2 x y + s3 r² + s4 r⁴
            R(r²) = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
        """
        xy = np.asarray(xy_n, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = (1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))) / (
            1.0 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6)))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x) + r2 * (self.s1 + r2 * self.s2)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y + r2 * (self.s3 + r2 * self.s4)
        return np.stack([xd, yd], axis=-1)

    def distortion_jacobian(self, xy_n) -> np.ndarray:
        """∂(x', y')/∂(x, y) of :meth:`distort` at undistorted normalised points (..., 2):
        (..., 2, 2), rows (x', y'), columns (x, y) (the Jacobian Newton's inversion uses)."""
        xy = np.asarray(xy_n, dtype=float)
        flat = np.ascontiguousarray(xy.reshape(-1, 2))
        out = np.empty((flat.shape[0], 2, 2))
        _jacobian_kernel(flat, self._coefficients(), out)
        return out.reshape(xy.shape[:-1] + (2, 2))

    def undistort(self, xyd_n, tol: float = UNDISTORT_TOL) -> tuple[np.ndarray, np.ndarray]:
        """Invert the distortion numerically (Newton iteration to convergence).

        Parameters
        ----------
        xyd_n : array_like, shape (..., 2)
            Distorted normalised coordinates.
        tol : float
            Convergence tolerance in normalised coordinates (step and residual).

        Returns
        -------
        xy_n : ndarray, shape (..., 2)
            Undistorted normalised coordinates.
        converged : ndarray of bool, shape (...)
            False where the iteration did not converge or converged to a non-physical solution
            (beyond a fold-over of the distortion, where det J ≤ 0, the radial factor ≤ 0 or the
            rational model's denominator ≤ 0).
        """
        xyd = np.asarray(xyd_n, dtype=float)
        shape = xyd.shape[:-1]
        flat = np.ascontiguousarray(xyd.reshape(-1, 2))
        out = np.empty_like(flat)
        ok = np.empty(flat.shape[0], dtype=np.bool_)
        _undistort_kernel(flat, self._coefficients(), tol, _UNDISTORT_MAX_ITER, out, ok)
        return out.reshape(shape + (2,)), ok.reshape(shape)

    def project(self, p_cam) -> np.ndarray:
        """Eqs. (2)–(4): camera-frame points (..., 3) → pixel coordinates (..., 2).

        Points with z ≤ 0 (behind the pinhole) give NaN.
        """
        p = np.asarray(p_cam, dtype=float)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[..., :2] / z[..., None]
        xy = np.where((z > 0)[..., None], xy, np.nan)
        xyd = self.distort(xy)
        return np.stack(
            [self.fx_px * xyd[..., 0] + self.ppx_px, self.fy_px * xyd[..., 1] + self.ppy_px], axis=-1
        )

    def pixel_to_normalized(self, uv_px) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) → undistorted normalised (x_ip, y_ip) (..., 2) and converged."""
        uv = np.asarray(uv_px, dtype=float)
        xyd = np.stack(
            [(uv[..., 0] - self.ppx_px) / self.fx_px, (uv[..., 1] - self.ppy_px) / self.fy_px], axis=-1
        )
        if not np.any(self._coefficients()):
            return xyd, np.ones(xyd.shape[:-1], dtype=bool)
        return self.undistort(xyd)

    def view_rays(self, uv_px) -> tuple[np.ndarray, np.ndarray]:
        """View-ray directions (x_ip, y_ip, 1) in the camera frame for pixels (..., 2) (paper §2.2).

        Returns
        -------
        d_cam : ndarray, shape (..., 3)
            Direction vectors, not normalised (z = 1).
        converged : ndarray of bool, shape (...)
        """
        return self._rays(np.asarray(uv_px, dtype=float))

    def _rays(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`view_rays` of pixels ``uv`` (..., 2), or of every sensor pixel (None): one
        compiled pass (:func:`_rays_kernel`)."""
        if uv is None:
            shape, flat, grid_w = (self.height_px, self.width_px), np.empty((1, 2)), self.width_px
        else:
            shape, grid_w = uv.shape[:-1], 0
            flat = np.ascontiguousarray(uv.reshape(-1, 2))
        coeffs = self._coefficients()
        n = int(np.prod(shape))
        d = np.empty((n, 3))
        ok = np.empty(n, dtype=np.bool_)
        _rays_kernel(flat, grid_w, float(self.fx_px), float(self.fy_px), float(self.ppx_px), float(self.ppy_px), coeffs,
                     bool(np.any(coeffs)), UNDISTORT_TOL, _UNDISTORT_MAX_ITER, d, ok)
        return d.reshape(shape + (3,)), ok.reshape(shape)

    def pixel_grid(self) -> np.ndarray:
        """Integer pixel centres (H, W, 2) as (u, v)."""
        v, u = np.mgrid[0 : self.height_px, 0 : self.width_px]
        return np.stack([u, v], axis=-1).astype(float)

    def sensor_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """View rays of every pixel of the sensor: d_cam (H, W, 3) and converged (H, W).

        The paper precomputes them per camera (§2.2); so does pmdsim: the arrays of the last few
        cameras are cached (read-only).
        """
        return _sensor_rays_cached(self)
