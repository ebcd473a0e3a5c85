"""Plausibility checks of camera models (issue 12, item 5: no silent mistakes).

What users get wrong when they bring a camera from elsewhere (an OpenCV calibration file, a
datasheet), and what pmdsim says instead of computing silently with it:

* :func:`check_camera_matrix` — an intrinsic matrix K that is not normalised (K[2,2] ≠ 1),
  transposed, skewed or with a negative focal length: :class:`~pmdsim.errors.SetupError`;
* :func:`check_image_size` — an image size that cannot belong to the camera (not positive, absurdly
  large, not containing the principal point: another resolution; width and height swapped):
  :class:`~pmdsim.errors.SetupError`; a principal point far off the image centre: a warning;
* :func:`fold_over` / :func:`warn_if_folds_over` — a distortion model that folds over inside the
  image (the distorted radius r_d(r) stops increasing, det ∂(x', y')/∂(x, y) ≤ 0, before the view
  ray leaves the image): no pixel beyond the fold has a unique view ray. This typically happens
  when a model fitted on the image centre is used over the full field; a
  :class:`CameraModelWarning`.

Conventions: docs/conventions.md ("OpenCV cameras").
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import SetupError

if TYPE_CHECKING:  # pragma: no cover
    from .camera import Camera

__all__ = ["CameraModelWarning", "FoldOver", "check_camera_matrix", "check_image_size", "fold_over",
           "warn_if_folds_over", "MAX_IMAGE_SIDE_PX"]

#: Largest plausible image side (px). The largest area sensors have about 15 000 px per side.
MAX_IMAGE_SIDE_PX = 65536
#: Largest plausible offset of the principal point from the image centre, as a fraction of the
#: image side (calibrated lenses: typically < 5 %); beyond it a warning.
MAX_PRINCIPAL_OFFSET = 0.15


class CameraModelWarning(UserWarning):
    """A camera model that is valid but probably not what the user meant (e.g. a fold-over)."""


def check_camera_matrix(camera_matrix, *, source: str = "camera_matrix") -> np.ndarray:
    """Check an OpenCV intrinsic matrix K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels).

    Parameters
    ----------
    camera_matrix : array_like, shape (3, 3)
    source : str
        Name of the file or key for the messages.

    Returns
    -------
    ndarray, shape (3, 3)
        K as float.

    Raises
    ------
    SetupError
        K is not 3 × 3 or not finite; K[2, 2] ≠ 1 (not normalised); the bottom row is not
        (0, 0, 1) (transposed?); K[1, 0] ≠ 0; skew K[0, 1] ≠ 0; fx or fy ≤ 0.
    """
    k = np.asarray(camera_matrix, dtype=float)
    if k.shape != (3, 3):
        raise SetupError(f"{source}: the camera matrix must be 3 × 3, got shape {k.shape}")
    if not np.isfinite(k).all():
        raise SetupError(f"{source}: the camera matrix must be finite, got {k.tolist()}")
    e = k.tolist()  # plain floats for the messages
    if e[2][0] != 0.0 or e[2][1] != 0.0:
        hint = (" — it looks transposed (the principal point belongs in K[0, 2], K[1, 2])"
                if e[0][2] == 0.0 and e[1][2] == 0.0 else "")
        raise SetupError(f"{source}: the camera matrix's last row must be (0, 0, 1), got {e[2]}{hint}")
    if e[2][2] != 1.0:
        raise SetupError(f"{source}: the camera matrix is not normalised: K[2, 2] = {e[2][2]!r}, expected 1 "
                         f"(a projective scale of K; divide K by K[2, 2] if that is what it is)")
    if e[1][0] != 0.0:
        raise SetupError(f"{source}: K[1, 0] must be 0 in a camera matrix, got {e[1][0]!r}")
    if e[0][0] <= 0.0 or e[1][1] <= 0.0:
        raise SetupError(f"{source}: focal lengths must be > 0, got fx = K[0, 0] = {e[0][0]!r}, "
                         f"fy = K[1, 1] = {e[1][1]!r} (a flipped image axis? pmdsim and OpenCV both have "
                         f"x right and y down: flip the images, not the focal length)")
    if abs(e[0][1]) > 1e-9 * e[0][0]:
        raise SetupError(f"{source}: skew K[0, 1] = {e[0][1]!r} is not supported (pmdsim's pixel axes are "
                         f"perpendicular); calibrate with zero skew (OpenCV's default)")
    return k


def check_image_size(image_size_px, principal_point_px=None, *, source: str = "camera") -> tuple[int, int]:
    """Check an image size (width, height) in pixels, optionally against the principal point.

    Parameters
    ----------
    image_size_px : (width, height)
        Whole numbers of pixels (integral floats accepted, as files store them).
    principal_point_px : (cx, cy), optional
        The principal point (pixels, pixel (0, 0) the centre of the top-left pixel). It must lie
        in the image, u ∈ [−0.5, W − 0.5], v ∈ [−0.5, H − 0.5].
    source : str
        Name of the file or key for the messages.

    Returns
    -------
    (int, int)

    Raises
    ------
    SetupError
        Not two positive whole numbers; larger than :data:`MAX_IMAGE_SIDE_PX` per side; not
        containing the principal point (calibrated at another resolution?); or the principal
        point far from this image's centre but at the centre of the swapped size (width and
        height swapped).

    Warns
    -----
    CameraModelWarning
        The principal point is farther than :data:`MAX_PRINCIPAL_OFFSET` of the image side
        from the image centre.
    """
    try:
        w_raw, h_raw = (float(v) for v in image_size_px)
    except (TypeError, ValueError):
        raise SetupError(f"{source}: the image size must be (width, height) in pixels, got {image_size_px!r}") from None
    if not (math.isfinite(w_raw) and math.isfinite(h_raw)) or w_raw != int(w_raw) or h_raw != int(h_raw):
        raise SetupError(f"{source}: the image size must be whole pixels, got {w_raw!r} × {h_raw!r}")
    w, h = int(w_raw), int(h_raw)
    if w <= 0 or h <= 0:
        raise SetupError(f"{source}: the image size must be positive, got {w} × {h} px (missing in the file?)")
    if w > MAX_IMAGE_SIDE_PX or h > MAX_IMAGE_SIDE_PX:
        raise SetupError(f"{source}: implausible image size {w} × {h} px (more than {MAX_IMAGE_SIDE_PX} px "
                         f"per side); expected the calibrated image's width and height in pixels")
    if principal_point_px is not None:
        cx, cy = (float(v) for v in principal_point_px)
        # Offsets of the principal point from the image centre, as fractions of the image's sides.
        ox, oy = abs(cx - (w - 1) / 2.0) / w, abs(cy - (h - 1) / 2.0) / h
        sx, sy = abs(cx - (h - 1) / 2.0) / h, abs(cy - (w - 1) / 2.0) / w  # … of the swapped size
        if max(ox, oy) > MAX_PRINCIPAL_OFFSET and max(sx, sy) <= 0.05:
            raise SetupError(f"{source}: implausible image size {w} × {h} px: the principal point ({cx:g}, {cy:g}) "
                             f"px lies near the centre of a {h} × {w} image — width and height swapped?")
        if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
            fx_, fy_ = (2.0 * cx + 1.0) / w, (2.0 * cy + 1.0) / h  # principal point over image centre
            raise SetupError(f"{source}: implausible image size {w} × {h} px: it does not contain the principal "
                             f"point ({cx:g}, {cy:g}) px — calibrated at another resolution? (the principal "
                             f"point is {fx_:.3g} × and {fy_:.3g} × the image centre)")
        if max(ox, oy) > MAX_PRINCIPAL_OFFSET:
            warnings.warn(f"{source}: the principal point ({cx:g}, {cy:g}) px is {100 * max(ox, oy):.0f} % of the "
                          f"image size from the centre of the {w} × {h} px image (more than "
                          f"{100 * MAX_PRINCIPAL_OFFSET:.0f} %): is the image size the calibrated one?",
                          CameraModelWarning, stacklevel=3)
    return w, h


@dataclass(frozen=True)
class FoldOver:
    """Where a camera's distortion first folds over inside its image.

    Attributes
    ----------
    radius : float
        Undistorted normalised radius r = √(x² + y²) of the fold (tan of the field angle).
    field_angle_deg : float
        The field angle atan(r) in degrees.
    uv_px : (float, float)
        The pixel where the fold lies (u, v).
    radius_step : float
        The sampling step in r (the fold lies within one step below ``radius``).
    """

    radius: float
    field_angle_deg: float
    uv_px: tuple[float, float]
    radius_step: float


def fold_over(camera: "Camera", *, n_directions: int = 72, steps_per_field: int = 250) -> FoldOver | None:
    """The first fold-over of the camera's distortion inside its image, or None.

    Along ``n_directions`` rays from the principal point in undistorted normalised coordinates
    (plus the directions of the four corners and the four edge midpoints), the distortion is
    sampled outward from r = 0 in steps of r_c / ``steps_per_field`` (r_c: the pinhole radius of
    the farthest image corner) until the distorted point leaves the image (or r reaches
    max(20 r_c, 5)). The model folds over where the distorted radius r_d(r) stops increasing or
    the Jacobian determinant det ∂(x', y')/∂(x, y) (or the rational model's denominator or
    radial factor) becomes ≤ 0 while the distorted point is still inside the image; pixels beyond
    that have no unique view ray. Sampling is numerical: a fold narrower than a step can be missed.

    Returns
    -------
    FoldOver or None
        The fold of smallest radius over all directions.
    """
    if not np.any(camera._coefficients()):
        return None  # a pinhole maps rays to pixels one to one
    return _fold_over_cached(camera, int(n_directions), int(steps_per_field))


@functools.lru_cache(maxsize=32)
def _fold_over_cached(camera: "Camera", n_directions: int, steps_per_field: int) -> FoldOver | None:
    w, h = camera.width_px, camera.height_px
    fx, fy, cx, cy = camera.fx_px, camera.fy_px, camera.ppx_px, camera.ppy_px
    # Directions: to the corners and edge midpoints of the image (pinhole approximation), and uniform.
    u_ref = np.array([-0.5, w - 0.5, w - 0.5, -0.5, cx, w - 0.5, cx, -0.5])
    v_ref = np.array([-0.5, -0.5, h - 0.5, h - 0.5, -0.5, cy, h - 0.5, cy])
    ref = np.column_stack([(u_ref - cx) / fx, (v_ref - cy) / fy])
    theta = np.concatenate([np.arctan2(ref[:, 1], ref[:, 0]), np.linspace(-np.pi, np.pi, n_directions, endpoint=False)])
    dirs = np.column_stack([np.cos(theta), np.sin(theta)])
    r_corner = float(np.max(np.hypot(ref[:, 0], ref[:, 1])))
    r_max = max(20.0 * r_corner, 5.0)
    step = r_corner / steps_per_field
    c = camera._coefficients()
    active = np.arange(len(dirs))  # rays still inside the image without a fold
    rd_prev = np.zeros(len(dirs))
    r0 = 0.0
    chunk = 2 * steps_per_field
    while active.size and r0 < r_max:
        r = r0 + step * np.arange(1, chunk + 1)
        xy = r[None, :, None] * dirs[active, None, :]  # (n_active, chunk, 2)
        xyd = camera.distort(xy)
        u = fx * xyd[..., 0] + cx
        v = fy * xyd[..., 1] + cy
        inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
        inside_prefix = np.cumprod(inside, axis=1).astype(bool)  # before the ray first leaves the image
        jac = camera.distortion_jacobian(xy)
        det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
        r2 = r * r
        num = 1.0 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
        den = 1.0 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
        rd = np.hypot(xyd[..., 0], xyd[..., 1])
        bad = ~(det > 0.0) | ~(den > 0.0)[None, :] | ~(num * den > 0.0)[None, :]
        bad[:, 0] |= ~(rd[:, 0] > rd_prev[active])  # the distorted radius must keep increasing
        bad[:, 1:] |= ~(rd[:, 1:] > rd[:, :-1])
        bad &= inside_prefix
        if bad.any():  # rays march in step: the first chunk with a fold holds the smallest radius
            first = np.where(bad.any(axis=1), bad.argmax(axis=1), chunk)
            i = int(np.argmin(first))
            j = int(first[i])
            return FoldOver(radius=float(r[j]), field_angle_deg=float(np.degrees(np.arctan(r[j]))),
                            uv_px=(float(u[i, j]), float(v[i, j])), radius_step=step)
        rd_prev[active] = rd[:, -1]
        active = active[inside_prefix[:, -1]]
        r0 = float(r[-1])
    return None


def warn_if_folds_over(camera: "Camera", *, source: str = "camera") -> FoldOver | None:
    """Warn (:class:`CameraModelWarning`) if the camera's distortion folds over inside its image.

    Returns the :class:`FoldOver` (or None).
    """
    f = fold_over(camera)
    if f is not None:
        warnings.warn(
            f"{source}: the distortion model folds over inside the image at field angle "
            f"{f.field_angle_deg:.2f}° (undistorted radius {f.radius:.4g}), near pixel "
            f"({f.uv_px[0]:.1f}, {f.uv_px[1]:.1f}): pixels beyond it have no unique view ray "
            f"(a model fitted on the image centre used over the full field? check the coefficients "
            f"and the image size)", CameraModelWarning, stacklevel=3)
    return f
