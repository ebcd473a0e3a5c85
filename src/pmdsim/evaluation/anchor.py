"""What fixes the height of a reconstruction: a known point, a measured distance, or nothing.

Deflectometry measures slopes; the surface follows by integration up to one constant, which the
paper's method fixes with "an initial point of known height" (§2.5). Because each pixel's
surface point slides along its view ray, that constant also changes the *slopes* (the bisector
normal depends on where on the ray the point is): a height 12 mm off at a 10 m stand-off tilts
every normal by about 0.26 mrad (issue 12). An evaluation therefore needs an anchor:

* :class:`HeightAnchor` — the surface seen at pixel (v, u) has height h (sample frame, mm);
* :class:`DistanceAnchor` — the surface point seen at pixel (v, u) lies at distance D (mm) from a
  known point S (world frame, mm), as SOFAST measures the optic-to-screen distance at a marked
  point of the optic (S = the screen's centre);
* none — :func:`default_seed_pixel` (the valid pixel nearest the centroid of the valid
  pixels, ties to the first in row-major order) at height 0: the heights are **relative**
  (one unknown constant, and the slopes are those of that assumption).

The anchor's pixel may be fractional: the reconstruction is seeded at the nearest valid pixel
and its seed height is solved (secant iteration, each step a full reconstruction) so that the
surface point interpolated at the anchor pixel (bilinear in the ray parameter t, p = o + t·d)
meets the anchor to 1e-9 relative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import PmdsimError
from .integration import Reconstruction, _default_seed
from .reconstruction import reconstruct

__all__ = ["AnchorError", "HeightAnchor", "DistanceAnchor", "AnchoredReconstruction", "default_seed_pixel",
           "evaluate_anchored", "register_model",
           "anchor_from_dict", "reconstruct_anchored"]


class AnchorError(PmdsimError, ValueError):
    """An anchor is invalid or cannot be met (no valid pixel near it, the distance sphere missed)."""


def default_seed_pixel(valid) -> tuple[int, int]:
    """The documented default seed, shared by the CLI and the library: the valid pixel nearest
    (Euclidean, pixels) to the centroid of ``valid`` (H, W); ties go to the first in row-major
    order."""
    valid = np.asarray(valid, dtype=bool)
    if not valid.any():
        raise AnchorError("no valid pixel: nothing to seed a reconstruction at")
    return _default_seed(valid)


def _pixel(value, what: str) -> tuple[float, float]:
    try:
        v, u = (float(x) for x in value)
    except (TypeError, ValueError):
        raise AnchorError(f"{what} must be a (row, column) pair of numbers, got {value!r}") from None
    if not (math.isfinite(v) and math.isfinite(u)):
        raise AnchorError(f"{what} must be finite, got {value!r}")
    return (v, u)


@dataclass(frozen=True)
class HeightAnchor:
    """The surface seen at ``pixel_vu`` (row, column; may be fractional) has height ``height_mm``
    along the sample frame's +z."""

    pixel_vu: tuple[float, float]
    height_mm: float
    height_std_mm: float = 0.0  # its standard uncertainty (issue 22)

    def describe(self) -> dict:
        out = {"kind": "height", "pixel_vu": list(self.pixel_vu), "height_mm": self.height_mm}
        return {**out, "height_std_mm": self.height_std_mm} if self.height_std_mm else out


@dataclass(frozen=True)
class DistanceAnchor:
    """The surface point seen at ``pixel_vu`` lies at ``distance_mm`` from ``point_world_mm``."""

    pixel_vu: tuple[float, float]
    distance_mm: float
    point_world_mm: tuple[float, float, float]
    distance_std_mm: float = 0.0  # its standard uncertainty (issue 22)

    def describe(self) -> dict:
        out = {"kind": "distance", "pixel_vu": list(self.pixel_vu), "distance_mm": self.distance_mm,
               "point_world_mm": list(self.point_world_mm)}
        return {**out, "distance_std_mm": self.distance_std_mm} if self.distance_std_mm else out


def anchor_from_dict(doc: dict, source: str = "anchor"):
    """``{"kind": "height", "pixel_vu": [v, u], "height_mm": h}`` or ``{"kind": "distance",
    "pixel_vu": [v, u], "distance_mm": D, "point_world_mm": [x, y, z]}`` → an anchor."""
    if not isinstance(doc, dict):
        raise AnchorError(f"{source} must be an object, got {doc!r:.80}")
    kind = doc.get("kind")
    keys = {"height": {"kind", "pixel_vu", "height_mm", "height_std_mm"},
            "distance": {"kind", "pixel_vu", "distance_mm", "point_world_mm", "description", "distance_std_mm"}}
    if kind not in keys:
        raise AnchorError(f"{source}: key 'kind' must be 'height' or 'distance', got {kind!r}")
    unknown = sorted(set(doc) - keys[kind] - {"description"})
    if unknown:
        raise AnchorError(f"{source}: unknown key(s) {unknown} for a {kind} anchor (allowed: {sorted(keys[kind])})")
    if "pixel_vu" not in doc:
        raise AnchorError(f"{source}: missing key 'pixel_vu' (row, column of the anchored pixel)")
    pix = _pixel(doc["pixel_vu"], f"{source}: key 'pixel_vu'")
    try:
        if kind == "height":
            h = float(doc["height_mm"])
            if not math.isfinite(h):
                raise ValueError
            hs = float(doc.get("height_std_mm", 0.0))
            if not (hs >= 0 and math.isfinite(hs)):
                raise ValueError
            return HeightAnchor(pix, h, hs)
        dist = float(doc["distance_mm"])
        s = tuple(float(x) for x in doc["point_world_mm"])
        ds = float(doc.get("distance_std_mm", 0.0))
        if (not (dist > 0 and math.isfinite(dist)) or len(s) != 3 or not all(map(math.isfinite, s))
                or not (ds >= 0 and math.isfinite(ds))):
            raise ValueError
        return DistanceAnchor(pix, dist, s, ds)
    except KeyError as e:
        raise AnchorError(f"{source}: missing key {e.args[0]!r} for a {kind} anchor") from None
    except (TypeError, ValueError):
        raise AnchorError(f"{source}: a {kind} anchor needs finite numbers: height_mm, or distance_mm > 0 and "
                          f"point_world_mm [x, y, z] (standard uncertainties height_std_mm / distance_std_mm ≥ 0); "
                          f"got {doc!r:.200}") from None


@dataclass(frozen=True)
class AnchoredReconstruction:
    """A reconstruction with what fixed its height.

    Attributes
    ----------
    reconstruction : Reconstruction
    anchor : dict
        The anchor's description (``kind`` "height", "distance" or "none").
    relative : bool
        True when nothing fixed the height (heights relative to the default seed at 0).
    residual_mm : float
        How far the reconstructed surface misses the anchor (0 for none).
    iterations : int
        Reconstructions run to meet the anchor.
    """

    reconstruction: Reconstruction
    anchor: dict
    relative: bool
    residual_mm: float
    iterations: int


def _bilinear_point(o, d, t, pix):
    """Surface point at a fractional pixel: t and d bilinear over the 4 surrounding pixels
    (those with a finite t, weights renormalised). Returns (p (3,), ok)."""
    H, W = t.shape
    v, u = pix
    v0, u0 = int(math.floor(v)), int(math.floor(u))
    acc_t = 0.0
    acc_d = np.zeros(3)
    wsum = 0.0
    for dv in (0, 1):
        for du in (0, 1):
            vv, uu = v0 + dv, u0 + du
            if not (0 <= vv < H and 0 <= uu < W) or not np.isfinite(t[vv, uu]):
                continue
            w = (1 - abs(v - vv)) * (1 - abs(u - uu))
            if w <= 0:
                continue
            acc_t += w * t[vv, uu]
            acc_d += w * d[vv, uu]
            wsum += w
    if wsum <= 0:
        return None
    return o + (acc_t / wsum) * (acc_d / wsum)


def _nearest_valid(valid, pix) -> tuple[int, int]:
    vv, uu = np.nonzero(valid)
    k = int(np.argmin((vv - pix[0]) ** 2 + (uu - pix[1]) ** 2))
    return int(vv[k]), int(uu[k])


def reconstruct_anchored(o_ref_mm, d_ref, q_ref_mm, valid, *, anchor=None, T_world_ref=None, method="stepwise",
                         max_iter: int = 12) -> AnchoredReconstruction:
    """Reconstruct (:func:`pmdsim.evaluation.reconstruction.reconstruct`) with the height fixed by
    ``anchor`` (module docstring).

    Parameters
    ----------
    o_ref_mm, d_ref, q_ref_mm, valid
        A registration in the reconstruction (sample) frame (:class:`Registration` fields).
    anchor : HeightAnchor or DistanceAnchor, optional
        None: :func:`default_seed_pixel` at height 0 (relative heights).
    T_world_ref : RigidTransform, optional
        Pose of the reconstruction frame in world (needed for a :class:`DistanceAnchor`, whose
        point is in world coordinates).
    method : {"stepwise", "least_squares"}

    Raises
    ------
    AnchorError
        The anchor pixel is outside the image or has no valid pixel within 2 px, the distance
        sphere does not meet the anchor pixel's ray in exactly one point in front of the camera,
        or the iteration does not meet the anchor.
    """
    o = np.asarray(o_ref_mm, dtype=float)
    d = np.asarray(d_ref, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    H, W = valid.shape
    if anchor is None:
        seed = default_seed_pixel(valid)
        rec = reconstruct(o, d, q_ref_mm, valid, method=method, seed_pixel=seed, seed_height_mm=0.0)
        return AnchoredReconstruction(rec, {"kind": "none", "seed_pixel_vu": list(seed), "height_mm": 0.0,
                                            "note": "heights are relative (no anchor): seed at the valid pixel "
                                                    "nearest the mask centroid, height 0"}, True, 0.0, 1)
    pix = anchor.pixel_vu
    if not (-0.5 <= pix[0] <= H - 0.5 and -0.5 <= pix[1] <= W - 0.5):
        raise AnchorError(f"anchor pixel (row, column) {pix} is outside the {W}×{H} px image")
    seed = _nearest_valid(valid, pix)
    if math.hypot(seed[0] - pix[0], seed[1] - pix[1]) > 2.0:
        raise AnchorError(f"anchor pixel {pix} has no valid (decoded and registered) pixel within 2 px (nearest: "
                          f"{seed}); the anchored point must be on the measured surface")
    # The anchor's ray (d bilinear over the surrounding pixels' rays).
    ray = _bilinear_point(np.zeros(3), d, np.where(np.isfinite(d[..., 0]), 1.0, np.nan), pix)
    if isinstance(anchor, DistanceAnchor):
        if T_world_ref is None:
            raise AnchorError("a distance anchor needs T_world_ref (its point is in world coordinates)")
        s_ref = T_world_ref.inv().apply(np.asarray(anchor.point_world_mm, dtype=float))
        # |o + t·ray − S| = D: t² |ray|² + 2t ray·(o − S) + |o − S|² − D² = 0.
        a = ray @ ray
        b = 2.0 * ray @ (o - s_ref)
        c = (o - s_ref) @ (o - s_ref) - anchor.distance_mm**2
        disc = b * b - 4 * a * c
        roots = [] if disc < 0 else sorted({(-b - math.sqrt(disc)) / (2 * a), (-b + math.sqrt(disc)) / (2 * a)})
        ahead = [r for r in roots if r > 0]
        if len(ahead) != 1:
            raise AnchorError(
                f"the sphere of radius {anchor.distance_mm:g} mm about {list(anchor.point_world_mm)} (world) meets the "
                f"anchor pixel {pix}'s view ray in {len(ahead)} point(s) in front of the camera (ray parameters "
                f"{[round(r, 6) for r in roots]}); expected exactly one — is the distance in mm and the point right?")
        target = o + ahead[0] * ray
    else:
        t_target = (anchor.height_mm - o[2]) / ray[2]
        if not t_target > 0:
            raise AnchorError(f"height {anchor.height_mm} mm at anchor pixel {pix} is behind the camera")
        target = o + t_target * ray

    def miss(rec) -> float:
        z = rec.height_mm
        t = (z - o[2]) / d[..., 2]
        p = _bilinear_point(o, d, t, pix)
        if p is None:
            raise AnchorError(f"the reconstruction did not reach the pixels around the anchor pixel {pix}")
        if isinstance(anchor, DistanceAnchor):
            return float(np.linalg.norm(p - s_ref) - anchor.distance_mm)
        return float(p[2] - anchor.height_mm)

    # Seed height: the target's height where the seed is the anchor pixel; secant iteration on it.
    z0 = float(target[2])
    rec0 = reconstruct(o, d, q_ref_mm, valid, method=method, seed_pixel=seed, seed_height_mm=z0)
    f0 = miss(rec0)
    scale = max(1.0, float(np.linalg.norm(target - o)))
    tol = 1e-9 * scale
    it = 1
    # First step from the derivative of the miss w.r.t. the seed height along the anchor ray.
    if isinstance(anchor, DistanceAnchor):
        u_s = (target - s_ref) / np.linalg.norm(target - s_ref)
        slope = float(u_s @ ray / ray[2])
    else:
        slope = 1.0
    z1 = z0 - f0 / slope if slope != 0 else z0 + 1.0
    best = (abs(f0), rec0, f0)
    while abs(best[2]) > tol and it < max_iter:
        rec1 = reconstruct(o, d, q_ref_mm, valid, method=method, seed_pixel=seed, seed_height_mm=z1)
        f1 = miss(rec1)
        it += 1
        if abs(f1) < best[0]:
            best = (abs(f1), rec1, f1)
        if f1 == f0:
            break
        z0, z1, f0 = z1, z1 - f1 * (z1 - z0) / (f1 - f0), f1
    if best[0] > max(tol, 1e-6 * scale):
        raise AnchorError(f"the reconstruction does not meet the anchor {anchor.describe()}: {best[0]:.3g} mm off after "
                          f"{it} reconstructions")
    return AnchoredReconstruction(best[1], {**anchor.describe(), "seed_pixel_vu": list(seed)}, False, best[2], it)


def evaluate_anchored(model, camera: str, decoded, *, screen_model=None, method: str = "stepwise", anchor=None):
    """Register ``decoded`` with ``model``'s camera and screen (as
    :func:`pmdsim.evaluation.pipeline.evaluate_decoded`), then :func:`reconstruct_anchored` in
    the model's sample frame. Returns (Registration, AnchoredReconstruction)."""
    reg = register_model(model, camera, decoded, screen_model=screen_model)
    if not reg.valid.any():
        raise AnchorError(f"camera {camera!r}: no pixel was decoded and registered; nothing to reconstruct")
    out = reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=anchor,
                               T_world_ref=model.sample.T_world_sample, method=method)
    return reg, out


def register_model(model, camera: str, decoded, *, screen_model=None):
    """:func:`pmdsim.evaluation.registration.register` with ``model``'s camera, screen pose and
    sample frame; ``screen_model`` None is the plane z = 0 of the screen frame over its grid."""
    from ..geometry.surface import SplineSurface
    from .registration import register

    cs = model.cameras[camera]
    if screen_model is None:
        scr = model.screen
        screen_model = SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
    return register(cs.camera, cs.T_world_cam, screen_model, model.screen.T_world_screen,
                    decoded.screen_xy_mm, decoded.valid, model.sample.T_world_sample,
                    glass=model.screen.cover_glass)  # with a glass: P on the sample plane z = 0
