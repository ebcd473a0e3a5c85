"""Where a point of a planar optic is seen, from the optic's outline in the image.

An instrument that measures a distance to a marked point of the optic (SOFAST's measure point,
``v_measure_point_facet``) needs the pixel that sees that point. The optic's outline corners are
known in its own frame (e.g. ``Facet_NSTTF.json``) and found in the image (the lit region's
corners); two ways from there to the point's pixel:

* :func:`outline_point_pixel` — the plane-to-image **homography** of the outline corners, in
  undistorted normalised coordinates, applied to the point (a pinhole maps a plane
  projectively; Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., §4.1, the DLT). Exact for
  any point in the plane of the corners and any tilt; it uses no more than the corners' image
  positions, and needs no intrinsic beyond the undistortion. For a parallelogram's centre it is
  the intersection of the image diagonals.
* :func:`outline_pose` — a **pose fit** (perspective-n-point: rotation and translation that
  project the known corners onto the found ones, least squares in pixels, pmdsim's camera model)
  and the projection of the point. Needed for a point off the corners' plane; the fit's residual
  (px) and the distance it implies are a consistency check of the found outline against the
  optic's nominal size.

The two agree for exact corners. With found corners they differ by the corners' errors: an
offset of one side moves either centre by about half of it, but corner errors that do not fit
the known shape (the pose fit's residual) move them differently. On a facet rendered at the
SOFAST facet's pose (84 px wide, 9.7 m away) the pose fit of pmdsim's outline is within
0.009 / 0.012 px (column / row) of the true centre, the homography 0.020 / 0.015 px; on the
real facet the two are 0.03 px apart and the pose fit's residual is 0.033 px RMS
(docs/benchmarks.md, issue 12; ``benchmarks/sofast_anchor.py``). The importer uses the pose fit
(a measure point may be anywhere on the optic) and records the homography's pixel beside it.

Pixel coordinates (u, v) with integer values at pixel centres (OpenCV's convention, as
:meth:`Camera.project`); object points (..., 3) in the optic's frame, any unit (the pose's
translation has the same unit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import PmdsimError
from ...geometry.camera import Camera
from ...geometry.transform import RigidTransform

__all__ = ["OutlineError", "OutlinePose", "outline_point_pixel", "outline_pose", "homography_from_points"]


class OutlineError(PmdsimError, ValueError):
    """The outline's corners do not determine the point (degenerate corners, points off the
    plane, undistortion failed)."""


def _normalised(cam: Camera, uv_px: np.ndarray) -> np.ndarray:
    xy, ok = cam.pixel_to_normalized(np.asarray(uv_px, dtype=float))
    if not np.all(ok):
        raise OutlineError(f"the outline corners {np.asarray(uv_px).tolist()} px could not be undistorted "
                           f"by the camera model (outside its valid region?)")
    return xy


def _pixel(cam: Camera, xy_n: np.ndarray) -> np.ndarray:
    xyd = cam.distort(xy_n)
    return np.stack([cam.fx_px * xyd[..., 0] + cam.ppx_px, cam.fy_px * xyd[..., 1] + cam.ppy_px], axis=-1)


def homography_from_points(src_xy, dst_xy) -> np.ndarray:
    """3×3 homography H with dst ~ H·src from ≥ 4 point pairs (K, 2) (normalised DLT, Hartley &
    Zisserman §4.4: both point sets shifted to their centroid and scaled to mean distance √2;
    H[2,2] = 1)."""
    src = np.asarray(src_xy, dtype=float)
    dst = np.asarray(dst_xy, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2 or src.shape[0] < 4:
        raise OutlineError(f"a homography needs ≥ 4 point pairs (K, 2), got {src.shape} and {dst.shape}")

    def cond(p):
        c = p.mean(axis=0)
        s = np.sqrt(2.0) / max(np.mean(np.linalg.norm(p - c, axis=1)), 1e-300)
        return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])

    Ts, Td = cond(src), cond(dst)
    a = np.c_[src, np.ones(len(src))] @ Ts.T
    b = np.c_[dst, np.ones(len(dst))] @ Td.T
    rows = []
    for (x, y, w), (u, v, t) in zip(a, b):
        rows.append([0, 0, 0, -t * x, -t * y, -t * w, v * x, v * y, v * w])
        rows.append([t * x, t * y, t * w, 0, 0, 0, -u * x, -u * y, -u * w])
    _, sv, vt = np.linalg.svd(np.asarray(rows))
    if sv[-2] < 1e-12 * sv[0]:
        raise OutlineError("the outline's corners are degenerate (three of them on a line?)")
    Hn = vt[-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ Hn @ Ts
    return H / H[2, 2]


def _plane_frame(corners_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Origin, 2×3 in-plane axes of the corners' best plane, and the corners' largest distance
    from it."""
    c0 = corners_obj.mean(axis=0)
    _, _, vt = np.linalg.svd(corners_obj - c0)
    off = float(np.abs((corners_obj - c0) @ vt[2]).max())
    return c0, vt[:2], off


def outline_point_pixel(cam: Camera, corners_px, corners_obj, point_obj, *, plane_tol: float | None = None) -> np.ndarray:
    """Pixel (u, v) where the point ``point_obj`` (3,) of a planar optic is seen, from its outline
    corners found in the image ``corners_px`` (K, 2) and known in the optic's frame
    ``corners_obj`` (K, 3), K ≥ 4 (homography in undistorted normalised coordinates; module
    docstring).

    ``plane_tol`` (object units, default 1e-6 of the outline's size): the corners and the point
    must lie in one plane within it, else :class:`OutlineError` (use :func:`outline_pose`).
    """
    px = np.asarray(corners_px, dtype=float)
    obj = np.asarray(corners_obj, dtype=float)
    pt = np.asarray(point_obj, dtype=float).reshape(3)
    if obj.ndim != 2 or obj.shape[1] != 3 or px.shape != (obj.shape[0], 2):
        raise OutlineError(f"corners: (K, 2) pixels and (K, 3) object points expected, got {px.shape}, {obj.shape}")
    c0, axes, off = _plane_frame(obj)
    size = float(np.ptp(obj, axis=0).max())
    tol = 1e-6 * size if plane_tol is None else plane_tol
    normal = np.cross(axes[0], axes[1])
    if off > tol or abs((pt - c0) @ normal) > tol:
        raise OutlineError(f"the outline corners and the point {pt.tolist()} are not in one plane (off by "
                           f"{max(off, abs((pt - c0) @ normal)):g} > {tol:g}); a pose fit (outline_pose) places "
                           f"points off the plane")
    H = homography_from_points((obj - c0) @ axes.T, _normalised(cam, px))
    q = H @ np.r_[(pt - c0) @ axes.T, 1.0]
    return _pixel(cam, q[:2] / q[2])


@dataclass(frozen=True)
class OutlinePose:
    """A pose fit of an outline: ``T_cam_obj`` maps the optic's frame to the camera frame (same
    unit as the object points); ``rms_px`` the corners' reprojection RMS; ``residuals_px`` (K, 2)
    projected − found."""

    T_cam_obj: RigidTransform
    rms_px: float
    residuals_px: np.ndarray

    def pixel_of(self, cam: Camera, point_obj) -> np.ndarray:
        """Pixel (u, v) of a point (3,) of the optic's frame under this pose."""
        return cam.project(self.T_cam_obj.apply(np.asarray(point_obj, dtype=float).reshape(1, 3)))[0]


def outline_pose(cam: Camera, corners_px, corners_obj) -> OutlinePose:
    """Pose of a rigid optic from K ≥ 4 outline corners (perspective-n-point): rotation vector and
    translation minimising the corners' reprojection error in pixels (``scipy.optimize.least_squares``,
    Levenberg–Marquardt), started from the homography's decomposition (Zhang 2000, *A flexible new
    technique for camera calibration*, §3.1: r1, r2, t from the columns of H for a planar target).
    The corners need not be coplanar for the fit itself, but the start uses their best plane."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    px = np.asarray(corners_px, dtype=float)
    obj = np.asarray(corners_obj, dtype=float)
    if obj.ndim != 2 or obj.shape[1] != 3 or px.shape != (obj.shape[0], 2) or obj.shape[0] < 4:
        raise OutlineError(f"a pose fit needs ≥ 4 corners: (K, 2) pixels and (K, 3) object points, got {px.shape}, "
                           f"{obj.shape}")
    c0, axes, _ = _plane_frame(obj)
    H = homography_from_points((obj - c0) @ axes.T, _normalised(cam, px))
    # H ~ [r1 r2 t] in the plane's frame (Zhang §3.1); the scale from |h1|, |h2|; the sign so that z > 0.
    lam = 2.0 / (np.linalg.norm(H[:, 0]) + np.linalg.norm(H[:, 1]))
    if H[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * H[:, 0], lam * H[:, 1], lam * H[:, 2]
    U, _, Vt = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], axis=-1))
    R_cam_plane = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    R_plane_obj = np.stack([axes[0], axes[1], np.cross(axes[0], axes[1])])  # object → plane coordinates
    R0 = R_cam_plane @ R_plane_obj
    t0 = t - R0 @ c0

    def resid(x):
        p = Rotation.from_rotvec(x[:3]).apply(obj) + x[3:]
        return (cam.project(p) - px).ravel()

    x0 = np.r_[Rotation.from_matrix(R0).as_rotvec(), t0]
    sol = least_squares(resid, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    r = sol.fun.reshape(-1, 2)
    T = RigidTransform(Rotation.from_rotvec(sol.x[:3]).as_matrix(), sol.x[3:])
    return OutlinePose(T, float(np.sqrt((r**2).sum(axis=1).mean())), r)
