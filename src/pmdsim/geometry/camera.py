"""Pinhole camera with Brown lens distortion (paper §2.2, eqs. 2–4).

Conventions (docs/conventions.md): camera frame x right, y down, z forward; pixel (0, 0) is the
centre of the top-left pixel; per-pixel arrays are indexed ``[v, u]``. The distortion model is
OpenCV's 5-coefficient model (k1, k2, p1, p2, k3); the paper's eq. (3) is the case k3 = 0.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields, replace

import numba
import numpy as np

__all__ = ["Camera", "UNDISTORT_TOL"]

#: Convergence tolerance of the distortion inversion, in normalised image coordinates.
UNDISTORT_TOL = 1e-12
_UNDISTORT_MAX_ITER = 100


@numba.njit(cache=True)
def _distort(x, y, k1, k2, k3, p1, p2):
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@numba.njit(cache=True)
def _distort_jac(x, y, k1, k2, k3, p1, p2):
    """Jacobian of eq. (3) with respect to (x, y): (dxd/dx, dxd/dy, dyd/dx, dyd/dy)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    c = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, c, d


@numba.njit(cache=True)
def _undistort_one(xd, yd, k1, k2, k3, p1, p2, tol, max_iter):
    """Invert eq. (3) by Newton's method. Returns (x, y, converged)."""
    x = xd
    y = yd
    for _ in range(max_iter):
        fx, fy = _distort(x, y, k1, k2, k3, p1, p2)
        rx = fx - xd
        ry = fy - yd
        a, b, c, d = _distort_jac(x, y, k1, k2, k3, p1, p2)
        det = a * d - b * c
        if det == 0.0 or not np.isfinite(det):
            return x, y, False
        dx = (d * rx - b * ry) / det
        dy = (-c * rx + a * ry) / det
        x -= dx
        y -= dy
        if abs(dx) <= tol and abs(dy) <= tol:
            fx, fy = _distort(x, y, k1, k2, k3, p1, p2)
            ok = abs(fx - xd) <= tol and abs(fy - yd) <= tol
            # A physical inverse lies on the branch of the identity: the distortion must be
            # orientation-preserving there (det J > 0) and the radial factor positive. Beyond a
            # fold-over of strong distortion Newton may find a solution on the far side.
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            a, b, c, d = _distort_jac(x, y, k1, k2, k3, p1, p2)
            ok = ok and radial > 0.0 and (a * d - b * c) > 0.0
            return x, y, ok
    return x, y, False


@numba.njit(cache=True, parallel=True)
def _undistort_kernel(xyd, k1, k2, k3, p1, p2, tol, max_iter, out, ok):
    n = xyd.shape[0]
    for i in numba.prange(n):
        x, y, c = _undistort_one(xyd[i, 0], xyd[i, 1], k1, k2, k3, p1, p2, tol, max_iter)
        out[i, 0] = x
        out[i, 1] = y
        ok[i] = c


@functools.lru_cache(maxsize=4)
def _sensor_rays_cached(camera: "Camera") -> tuple[np.ndarray, np.ndarray]:
    d, ok = camera.view_rays(camera.pixel_grid())
    d.setflags(write=False)
    ok.setflags(write=False)
    return d, ok


@dataclass(frozen=True)
class Camera:
    """Intrinsic model of one camera: pinhole + Brown distortion (paper §2.2).

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
        Distortion coefficients of eq. (3) (k3 beyond the paper, OpenCV's fifth coefficient).
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
    def from_opencv(cls, camera_matrix, dist_coeffs, image_size_px) -> "Camera":
        """From OpenCV's 3×3 camera matrix, distortion vector (k1, k2, p1, p2[, k3]) and (W, H)."""
        k = np.asarray(camera_matrix, dtype=float)
        d = np.zeros(5)
        dc = np.asarray(dist_coeffs, dtype=float).ravel()
        if dc.size not in (4, 5):
            raise ValueError(f"dist_coeffs must have 4 or 5 entries (k1, k2, p1, p2[, k3]), got {dc.size}")
        if abs(k[0, 1]) > 0:
            raise ValueError("camera_matrix with skew is not supported (K[0, 1] must be 0)")
        d[: dc.size] = dc
        w, h = image_size_px
        return cls(w, h, k[0, 0], k[1, 1], k[0, 2], k[1, 2], d[0], d[1], d[2], d[3], d[4])

    def as_opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """(camera_matrix (3, 3), dist_coeffs (5,)) in OpenCV's layout."""
        k = np.array([[self.fx_px, 0.0, self.ppx_px], [0.0, self.fy_px, self.ppy_px], [0.0, 0.0, 1.0]])
        return k, self.distortion

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

    @property
    def distortion(self) -> np.ndarray:
        """(k1, k2, p1, p2, k3), OpenCV's order."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of per-pixel arrays."""
        return (self.height_px, self.width_px)

    # ------------------------------------------------------------------ model
    def distort(self, xy_n) -> np.ndarray:
        """Eq. (3): undistorted → distorted normalised coordinates, shape (..., 2) → (..., 2)."""
        xy = np.asarray(xy_n, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xyd_n, tol: float = UNDISTORT_TOL) -> tuple[np.ndarray, np.ndarray]:
        """Invert eq. (3) numerically (Newton iteration to convergence).

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
            (beyond a fold-over of the distortion, where det J ≤ 0 or the radial factor ≤ 0).
        """
        xyd = np.asarray(xyd_n, dtype=float)
        shape = xyd.shape[:-1]
        flat = np.ascontiguousarray(xyd.reshape(-1, 2))
        out = np.empty_like(flat)
        ok = np.empty(flat.shape[0], dtype=np.bool_)
        _undistort_kernel(flat, self.k1, self.k2, self.k3, self.p1, self.p2, tol, _UNDISTORT_MAX_ITER, out, ok)
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
        if self.k1 == 0.0 and self.k2 == 0.0 and self.k3 == 0.0 and self.p1 == 0.0 and self.p2 == 0.0:
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
        xy, ok = self.pixel_to_normalized(uv_px)
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return d, ok

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
