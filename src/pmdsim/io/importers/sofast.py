"""Import a SOFAST fringe measurement (Sandia's OpenCSP) as a pmdsim setup and image set.

``pmdsim import sofast --measurement M.h5 --camera C.h5 --display D.h5 --orientation O.h5
--calibration CAL.h5 [--facet F.json] --out DIR`` writes

* ``DIR/setup.toml`` — the camera (OpenCV intrinsics, Brown terms), the screen (pose from the
  spatial orientation; for a ``distorted3D`` display its measured shape as the screen surface),
  a nominal sample frame at the measured optic position, the fringe sequence;
* ``DIR/images/`` — ``manifest.json``, the 32 fringe images as PNG, ``response.json`` (the
  display → camera grey-level series), ``mask.png`` (lit pixels), ``screen_map.json`` (SOFAST's
  screen fraction → pmdsim screen coordinates) and, in the manifest, the measured
  optic-to-screen distance as the depth anchor.

SOFAST's formats, as OpenCSP writes and reads them (facts taken from its files and code; the
conventions are written out in docs/conventions.md, "SOFAST import"):

* lengths in metres; the display frame is centred on the screen, with SOFAST's screen fraction
  (f_x, f_y) ∈ [0, 1]² → display coordinates by the display model (``rectangular2D``:
  ((f_x − ½)·screen_x, (f_y − ½)·screen_y, 0); ``distorted2D``/``distorted3D``: piecewise-linear
  interpolation of measured (f → x, y[, z]) samples over their Delaunay triangulation);
* fringes: ``fringe_images`` (H, W, n) holds the y fringes first, then x; per period 4 shifts;
  periods as *fringes per screen* n, phase 2π·n·w, shift k: intensity ∝ cos(2π·n·w − k·π/2) —
  i.e. pmdsim's I_k = A + B·cos(φ − δ_k) with φ = 2π·x_q/p for x_q = w·W, p = W/n. SOFAST's
  screen fraction is f_x = w_x, but f_y = 1 − w_y ("the screen is flipped in y");
* orientation: ``r_cam_screen`` (rotation vector) maps camera-frame coordinates to display
  coordinates, ``v_cam_screen_cam`` is the display origin in the camera frame (m):
  p_cam = R(r_cam_screen)ᵀ·p_display + v_cam_screen_cam;
* camera: OpenCV ``intrinsic_mat`` and ``distortion_coef`` (k1, k2, p1, p2[, k3]); OpenCV and
  SOFAST ignore K[2,2] (pmdsim does too, with a warning when it is not 1);
* ``dist_optic_screen``: the distance from the optic's measure point (``v_measure_point_facet``,
  facet coordinates) to the display origin; ``mask_images`` (dark, light).

pmdsim's frames: world = the camera frame (mm). The pmdsim screen frame is SOFAST's display frame
scaled to mm, moved to the screen's corner and turned by 180° about x (y and z flipped) so that
its +z points away from the sample (docs/conventions.md "Surfaces"); pattern coordinates are
(x_q, y_q) = (f_x·W, (1 − f_y)·H), and the screen map takes them to the screen frame (for the
rectangular model the map is the identity: x_q, y_q are screen-frame coordinates).
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ImageSetError, PmdsimError
from ...geometry.camera import Camera
from ...geometry.transform import RigidTransform
from ...setup.fringes import FringeSequence
from ...setup.model import CameraSetup, PatternSetup, Pose, SampleSetup, ScreenSetup, Setup
from ..images import write_png
from ..outputs import IMAGESET_FORMAT, MANIFEST_NAME, atomic_output_dir, provenance, write_json
from .sofast_checks import MIN_LIT_PIXELS, check_calibration, check_screen_faces_optic

__all__ = ["SofastImportError", "SofastImportWarning", "SofastImportSummary", "import_sofast",
           "sofast_screen_transform", "read_sofast_display", "read_sofast_camera"]

CAMERA_NAME = "camera"

#: Plausible SOFAST lengths (metres): a display 0.05 … 100 m wide, distances below 1 km.
_DISPLAY_RANGE_M = (0.05, 100.0)
_MAX_DISTANCE_M = 1000.0
#: The widest field of view (deg, per image axis) an imported camera may have: pmdsim's pinhole
#: + Brown–Conrady model is not a fisheye's, and a focal length of a pixel or less is a unit mistake.
_MAX_FIELD_OF_VIEW_DEG = 150.0


class SofastImportError(PmdsimError, ValueError):
    """A SOFAST file is missing, incomplete, or holds values pmdsim cannot take (the message
    names the file and the dataset)."""


class SofastImportWarning(UserWarning):
    """Something in the SOFAST files that pmdsim reads in a documented way but that may be a
    mistake (e.g. an intrinsic matrix with K[2,2] ≠ 1)."""


# ============================================================================ reading
def _read(path, names: dict[str, str], what: str) -> dict:
    """Datasets ``names`` (key → HDF5 path) of ``path``; missing ones are an error naming them."""
    import h5py

    p = Path(path)
    if not p.is_file():
        raise SofastImportError(f"{what} file {str(p)!r} does not exist")
    out = {}
    try:
        with h5py.File(p, "r") as f:
            for key, ds in names.items():
                if ds not in f:
                    have = []
                    f.visit(have.append)
                    raise SofastImportError(f"{str(p)!r} is not a SOFAST {what} file: no dataset {ds!r} "
                                            f"(it holds: {', '.join(have[:12])})")
                v = f[ds][()]
                out[key] = v.decode() if isinstance(v, bytes) else v
    except OSError as e:
        raise SofastImportError(f"cannot read {what} file {str(p)!r}: {e}") from None
    return out


def _optional(path, ds: str):
    import h5py

    with h5py.File(path, "r") as f:
        if ds not in f:
            return None
        v = f[ds][()]
        return v.decode() if isinstance(v, bytes) else v


def read_sofast_camera(path, *, image_size_px=None) -> tuple[Camera, list[str]]:
    """SOFAST/OpenCV camera file → (pmdsim :class:`Camera`, warnings).

    ``intrinsic_mat`` K: fx = K[0,0], fy = K[1,1], (ppx, ppy) = (K[0,2], K[1,2]) as OpenCV takes
    them (K[2,2] ignored: a value other than 1 is reported); ``distortion_coef`` (k1, k2, p1, p2
    [, k3]) — 8/12/14-coefficient vectors with non-zero rational, thin-prism or tilt terms are
    refused (pmdsim's camera has the five Brown terms)."""
    d = _read(path, {"K": "Camera/intrinsic_mat", "dist": "Camera/distortion_coef", "size": "Camera/image_shape_xy"},
              "camera")
    K = np.asarray(d["K"], dtype=float)
    src = f"{str(path)!r}"
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise SofastImportError(f"{src}: Camera/intrinsic_mat must be a finite 3×3 matrix, got shape {K.shape}")
    warn = []
    size = np.asarray(d["size"]).ravel().astype(int)
    if size.size != 2:
        raise SofastImportError(f"{src}: Camera/image_shape_xy must be (width, height), got {d['size']!r}")
    w, h = int(size[0]), int(size[1])
    if abs(K[2, 2] - 1.0) > 1e-12:
        pp_norm = (K[0, 2] / K[2, 2], K[1, 2] / K[2, 2])
        warn.append(
            f"{src}: Camera/intrinsic_mat has K[2,2] = {K[2, 2]:g}, not 1. OpenCV (and SOFAST) ignore K[2,2] and take "
            f"fx = {K[0, 0]:g}, fy = {K[1, 1]:g}, principal point ({K[0, 2]:g}, {K[1, 2]:g}) px as they stand; pmdsim "
            f"does the same. (Dividing K by K[2,2] would give fx = {K[0, 0] / K[2, 2]:g} px and the principal point "
            f"({pp_norm[0]:g}, {pp_norm[1]:g}) px for a {w}×{h} px image" +
            (", outside it" if not (0 <= pp_norm[0] < w and 0 <= pp_norm[1] < h) else "") + ".)")
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or np.any(np.abs(K[2, :2]) > 1e-12) or abs(K[1, 0]) > 0:
        raise SofastImportError(f"{src}: Camera/intrinsic_mat has skew or a non-zero K[1,0]/K[2,0:2] ({K.tolist()}); "
                                f"pmdsim's camera has none")
    dist = np.asarray(d["dist"], dtype=float).ravel()
    if dist.size not in (4, 5, 8, 12, 14):
        raise SofastImportError(f"{src}: Camera/distortion_coef has {dist.size} coefficients; OpenCV vectors have "
                                f"4, 5, 8, 12 or 14")
    if dist.size > 5 and np.any(dist[5:] != 0):
        names = ["k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y"][: dist.size - 5]
        nz = [f"{n} = {v:g}" for n, v in zip(names, dist[5:]) if v != 0]
        raise SofastImportError(f"{src}: Camera/distortion_coef has non-zero terms beyond k1 k2 p1 p2 k3 "
                                f"({', '.join(nz)}); this importer takes the five Brown terms only")
    k = list(dist[:5]) + [0.0] * (5 - min(5, dist.size))
    if image_size_px is not None and (w, h) != tuple(image_size_px):
        raise SofastImportError(
            f"{src}: the camera model is for {w}×{h} px images, but the measurement's images are "
            f"{image_size_px[0]}×{image_size_px[1]} px; use the camera file at the measurement's resolution "
            f"(SOFAST's camera_sofast_downsampled.h5 for downsampled measurements)")
    fov = [2.0 * math.degrees(math.atan(0.5 * n / f)) if f > 0 else 180.0 for n, f in ((w, K[0, 0]), (h, K[1, 1]))]
    if max(fov) > _MAX_FIELD_OF_VIEW_DEG:
        raise SofastImportError(
            f"{src}: Camera/intrinsic_mat has fx = {K[0, 0]:g} px, fy = {K[1, 1]:g} px: a field of view of "
            f"{fov[0]:.1f}° × {fov[1]:.1f}° over the {w}×{h} px image (at most {_MAX_FIELD_OF_VIEW_DEG:g}° "
            f"expected of a pinhole camera with OpenCV's distortion); focal lengths are in pixels — was it given in "
            f"millimetres or for another resolution?")
    cam = Camera(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                 float(k[0]), float(k[1]), float(k[2]), float(k[3]), float(k[4]))
    return cam, warn


@dataclass(frozen=True, eq=False)
class SofastDisplay:
    """A SOFAST display model in pmdsim's terms.

    Attributes
    ----------
    model : str
        ``rectangular2D``, ``distorted2D`` or ``distorted3D``.
    size_mm : (W, H)
        The extent that screen fractions scale to (pattern coordinates x_q = f_x·W, y_q = f_y·H).
    fraction : ndarray (M, 2)
        Sample screen fractions.
    display_m : ndarray (M, 3)
        Their display coordinates (SOFAST's frame, metres).
    """

    model: str
    size_mm: tuple[float, float]
    fraction: np.ndarray
    display_m: np.ndarray


def read_sofast_display(path) -> SofastDisplay:
    """A SOFAST ``DisplayShape`` file (three models) → :class:`SofastDisplay`."""
    src = f"{str(path)!r}"
    model = _read(path, {"m": "DisplayShape/screen_model"}, "display")["m"]
    if model == "rectangular2D":
        d = _read(path, {"x": "DisplayShape/screen_x", "y": "DisplayShape/screen_y"}, "display")
        sx, sy = float(d["x"]), float(d["y"])
        f = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
        xyz = np.stack([(f[:, 0] - 0.5) * sx, (f[:, 1] - 0.5) * sy, np.zeros(4)], axis=-1)
    elif model in ("distorted2D", "distorted3D"):
        key = "xy_screen_coords" if model == "distorted2D" else "xyz_screen_coords"
        d = _read(path, {"f": "DisplayShape/xy_screen_fraction", "c": f"DisplayShape/{key}"}, "display")
        f = np.asarray(d["f"], dtype=float)
        c = np.asarray(d["c"], dtype=float)
        nc = 2 if model == "distorted2D" else 3
        if f.ndim != 2 or f.shape[0] != 2 or c.shape != (nc, f.shape[1]) or f.shape[1] < 3:
            raise SofastImportError(f"{src}: DisplayShape/xy_screen_fraction must be (2, M) and DisplayShape/{key} "
                                    f"({nc}, M) with M ≥ 3, got {f.shape} and {c.shape}")
        f = f.T
        xyz = np.zeros((f.shape[0], 3))
        xyz[:, :nc] = c.T
        if not (np.isfinite(f).all() and np.isfinite(xyz).all()):
            raise SofastImportError(f"{src}: the display samples must be finite")
        # Extent per screen fraction: least-squares slope of x over f_x and y over f_y.
        sx = float(np.polyfit(f[:, 0], xyz[:, 0], 1)[0])
        sy = float(np.polyfit(f[:, 1], xyz[:, 1], 1)[0])
    else:
        raise SofastImportError(f"{src}: DisplayShape/screen_model {model!r} is not one of rectangular2D, "
                                f"distorted2D, distorted3D")
    if not (_DISPLAY_RANGE_M[0] <= abs(sx) <= _DISPLAY_RANGE_M[1] and _DISPLAY_RANGE_M[0] <= abs(sy) <= _DISPLAY_RANGE_M[1]):
        raise SofastImportError(
            f"{src}: the display is {abs(sx):g} × {abs(sy):g} (in the file's units) — implausible in metres, which "
            f"SOFAST uses; a display {_DISPLAY_RANGE_M[0]:g} … {_DISPLAY_RANGE_M[1]:g} m wide was expected "
            f"(were the values written in millimetres?)")
    if sx <= 0 or sy <= 0:
        raise SofastImportError(f"{src}: display coordinates must grow with the screen fraction (x by f_x, y by f_y); "
                                f"here dx/df_x = {sx:g}, dy/df_y = {sy:g} — a flipped display model?")
    return SofastDisplay(model, (1000.0 * sx, 1000.0 * sy), f, xyz)


# ============================================================================ conventions
def sofast_screen_transform(size_mm) -> RigidTransform:
    """``T_display_screen``: pmdsim screen frame (mm, origin at the corner) → SOFAST display
    frame (scaled to mm, centred): p_display_mm = F·(p_screen − (W/2, H/2, 0)), F = diag(1, −1, −1)
    (180° about x). The display frame in metres is this divided by 1000."""
    w, h = size_mm
    F = np.diag([1.0, -1.0, -1.0])
    return RigidTransform(F, -F @ np.array([w / 2.0, h / 2.0, 0.0]))


def fraction_to_screen_mm(fraction, display: SofastDisplay) -> np.ndarray:
    """SOFAST screen fractions (..., 2) → pmdsim screen-frame points (..., 3), mm, through the
    display model (rectangular: exact; distorted: SOFAST's piecewise-linear interpolation)."""
    from scipy.interpolate import LinearNDInterpolator

    f = np.asarray(fraction, dtype=float)
    if display.model == "rectangular2D":
        d_m = np.stack([(f[..., 0] - 0.5) * display.size_mm[0] / 1e3, (f[..., 1] - 0.5) * display.size_mm[1] / 1e3,
                        np.zeros(f.shape[:-1])], axis=-1)
    else:
        d_m = LinearNDInterpolator(display.fraction, display.display_m)(f.reshape(-1, 2)).reshape(f.shape[:-1] + (3,))
    return sofast_screen_transform(display.size_mm).inv().apply(1e3 * d_m)


def fraction_to_pattern_mm(fraction, size_mm) -> np.ndarray:
    """SOFAST screen fractions (..., 2) → the pattern coordinates (x_q, y_q) mm that the fringe
    images encode: x_q = f_x·W, y_q = (1 − f_y)·H (SOFAST flips y after unwrapping:
    f_y = 1 − the phase's fraction)."""
    f = np.asarray(fraction, dtype=float)
    return np.stack([f[..., 0] * size_mm[0], (1.0 - f[..., 1]) * size_mm[1]], axis=-1)


def pattern_mm_to_fraction(pattern_xy_mm, size_mm) -> np.ndarray:
    """Inverse of :func:`fraction_to_pattern_mm`."""
    q = np.asarray(pattern_xy_mm, dtype=float)
    return np.stack([q[..., 0] / size_mm[0], 1.0 - q[..., 1] / size_mm[1]], axis=-1)


# ============================================================================ mask
def _mask(dark: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Lit pixels: light − dark above the level halfway between the dark and the lit pixels
    (separated by Otsu's threshold of the difference), largest connected region (SOFAST's raw
    mask keeps the largest area as well)."""
    from scipy import ndimage

    delta = light.astype(float) - dark.astype(float)
    if not np.all(np.isfinite(delta)) or np.ptp(delta) <= 0:  # no pixel lighter than another: none lit
        return np.zeros(delta.shape, bool)
    hist, edges = np.histogram(delta, bins=256)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu0 = m0 / w0
        mu1 = (m0[-1] - m0) / w1
        between = w0 * w1 * (mu0 - mu1) ** 2
    if not np.any(np.isfinite(between)):
        return np.zeros(delta.shape, bool)
    otsu = centres[int(np.nanargmax(between))]
    # A pixel is lit when the light covers more than half of it: threshold halfway between the
    # dark and the lit level (the means of the two Otsu classes), so that the region's edge is
    # where the lit fraction crosses ½ (unbiased to the pixel quantisation).
    thr = 0.5 * (np.median(delta[delta <= otsu]) + np.median(delta[delta > otsu]))
    m = delta > thr
    lab, n = ndimage.label(m)
    if n > 1:
        sizes = ndimage.sum(m, lab, index=np.arange(1, n + 1))
        m = lab == (1 + int(np.argmax(sizes)))
    return m


def _edge_span(mask: np.ndarray, delta: np.ndarray, reach: int = 6) -> int:
    """Half-width h (px) of the profile :func:`_boundary` integrates across an edge, such that
    the span reaches h + ½ ≥ 3.5 σ_eff beyond the edge (the tails outside hold ≲ 1e-3 px of
    area; measured ≤ 5e-4 px for Gaussian blurs up to 2 px) for the edges' width σ_eff (blur
    and pixel together). σ_eff from the number of pixels whose level is between 10 % and 90 % of
    the local step, ≈ 2.56 σ_eff per profile across an
    edge (the 10–90 % width of a Gaussian edge; a sharp edge gives 0 or 1 depending on the
    partial pixel's coverage: σ_eff ≈ 0.31): counted on each pair's profile within ``reach`` px,
    normalised between the levels just beyond it (so independent of noise and of non-uniform
    surroundings), averaged over the pairs."""
    m = np.asarray(mask, bool)
    counts = []
    for axis in (0, 1):
        a_m, b_m = (m[:-1, :], m[1:, :]) if axis == 0 else (m[:, :-1], m[:, 1:])
        sel = a_m != b_m
        v, u = np.nonzero(sel)
        i = v if axis == 0 else u
        n = delta.shape[axis]
        ok = (i - reach >= 0) & (i + reach + 1 < n)
        v, u, i, first_in = v[ok], u[ok], i[ok], a_m[sel][ok]
        js = np.arange(-reach, reach + 2)
        idx = i[:, None] + js[None, :]
        prof = delta[idx, u[:, None]] if axis == 0 else delta[v[:, None], idx]
        lit = np.where(first_in, prof[:, 0], prof[:, -1])
        dk = np.where(first_in, prof[:, -1], prof[:, 0])
        good = lit > dk
        with np.errstate(invalid="ignore", divide="ignore"):
            nrm = (prof[:, 1:-1] - dk[:, None]) / (lit - dk)[:, None]
        counts.append(((nrm > 0.1) & (nrm < 0.9)).sum(axis=1)[good])
    c = np.concatenate(counts)
    if c.size == 0:
        return 1
    sigma_eff = float(c.mean()) / 2.56
    return int(np.clip(np.ceil(3.5 * sigma_eff - 0.5), 1, 8))


def _boundary(mask: np.ndarray, delta: np.ndarray | None = None, *, with_axis: bool = False,
              span_px: int | None = None):
    """Edge points (u, v) of the lit region, (K, 2), one per pair of 4-neighbouring pixels of
    which one is inside the mask and one outside (and, with ``with_axis``, the pair's axis (K,):
    0 = the pair is vertical, the point's v is sub-pixel; 1 = horizontal, u sub-pixel).

    Without ``delta``: the pair's midpoint. With the light − dark image ``delta``: the edge's
    position along the pair's axis from the **area** of the profile across it (moment-preserving
    edge location, Tabatabai & Mitchell, IEEE PAMI 6 (1984) 188): the 2h + 2 pixels from h before
    to h after the pair, normalised between the local dark and lit levels (``delta`` one pixel
    beyond them on either side), sum to the lit length of their span — exact for a straight edge
    (any orientation: a row's pixels integrate a trapezoid, whose mean width is its width at the
    row's centre) under the pixels' own integration and a blur whose tails the span holds
    (h = ``span_px``, by default :func:`_edge_span` of the image: 1 for the SOFAST facet's edges),
    where the crossing of half the level between two pixel centres is off by up to 0.086 px for a sharp
    edge (c + 1/(2c) − 3/2 for a partial pixel of coverage c ≥ ½), which does not average out
    along a side nearly parallel to the pixel grid (on the SOFAST facet it moved the centre by
    0.05 px; docs/benchmarks.md, issue 12). Local levels, not global ones: the light around an
    optic is rarely uniform (on that facet the outside is 7 DN below it and 32 DN right of it).
    Where the levels cannot be read (image border, no contrast) the half-level crossing of a
    global level (halfway between the median lit and dark pixels) between the pair is used."""
    m = np.asarray(mask, bool)
    glob = None
    if delta is not None:
        delta = np.asarray(delta, dtype=float)
        glob = 0.5 * (np.median(delta[m]) + np.median(delta[~m]))
        h = _edge_span(m, delta) if span_px is None else int(span_px)
    out, axes = [], []
    for axis in (0, 1):
        a_m, b_m = (m[:-1, :], m[1:, :]) if axis == 0 else (m[:, :-1], m[:, 1:])
        sel = a_m != b_m
        v, u = np.nonzero(sel)
        t = np.full(v.shape, 0.5)
        if delta is not None:
            n = delta.shape[axis]
            i = v if axis == 0 else u  # index of the pair's first pixel along the axis

            def at(k):
                ok = (k >= 0) & (k < n)
                val = np.full(k.shape, np.nan)
                kk = np.clip(k, 0, n - 1)
                val[ok] = (delta[kk, u] if axis == 0 else delta[v, kk])[ok]
                return val

            a, b = at(i), at(i + 1)
            first_in = a_m[sel]
            lit = np.where(first_in, at(i - h - 1), at(i + h + 2))
            dk = np.where(first_in, at(i + h + 2), at(i - h - 1))
            span = np.stack([at(i + j) for j in range(-h, h + 2)], -1)
            with np.errstate(invalid="ignore", divide="ignore"):
                frac = ((span - dk[:, None]) / (lit - dk)[:, None]).sum(axis=-1)  # unclipped: noise unbiased
                # Lit part of [i − h − ½, i + h + 1½]: [i − h − ½, x] (lit first) or [x, i + h + 1½].
                t_area = np.where(first_in, -h - 0.5 + frac, h + 1.5 - frac)
                tt = (glob - a) / (b - a)
            contrast = (lit - dk) > 0.25 * abs(np.median(delta[m]) - np.median(delta[~m]))
            good = np.isfinite(t_area) & contrast & (t_area >= -0.5) & (t_area <= 1.5)
            t_glob = np.where(np.isfinite(tt) & (tt >= 0) & (tt <= 1), tt, 0.5)
            t = np.where(good, t_area, t_glob)
        out.append(np.stack([u.astype(float), v + t], -1) if axis == 0 else np.stack([u + t, v.astype(float)], -1))
        axes.append(np.full(v.shape, axis))
    pts = np.concatenate(out)
    return (pts, np.concatenate(axes)) if with_axis else pts


def _line_fit(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares line n·p = c through points (K, 2) (unit normal n)."""
    c0 = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c0)
    n = vt[-1]
    return n, float(n @ c0)


def facet_outline_corners(mask: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
    """The four corners (u, v) px of a quadrilateral mask, in cyclic order: initial corners are
    the boundary points extreme along the diagonals of the frame (rotated in 15° steps, the set
    of largest area kept); each side's boundary points (nearest to it, away from the corners)
    are fitted by a total-least-squares line, twice, and adjacent lines intersected. Edge points:
    :func:`_boundary` (sub-pixel with the light − dark image ``delta``), of each side only those
    located across it (the pair's axis the one more perpendicular to the side)."""
    pts, pair_axis = _boundary(mask, delta, with_axis=True)
    if len(pts) < 16:
        raise SofastImportError("the lit region is too small to find the facet's outline")
    best, best_area = None, -1.0
    for ang in np.radians(np.arange(0.0, 90.0, 15.0)):
        c, s_ = np.cos(ang), np.sin(ang)
        r = pts @ np.array([[c, -s_], [s_, c]])
        idx = [int(np.argmax(r[:, 0] + r[:, 1])), int(np.argmax(-r[:, 0] + r[:, 1])),
               int(np.argmax(-r[:, 0] - r[:, 1])), int(np.argmax(r[:, 0] - r[:, 1]))]
        q = pts[idx]
        area = 0.5 * abs(sum(q[i, 0] * q[(i + 1) % 4, 1] - q[(i + 1) % 4, 0] * q[i, 1] for i in range(4)))
        if area > best_area:
            best, best_area = q, area
    corners = best
    for _ in range(3):
        lines = []
        for i in range(4):
            a, b = corners[i], corners[(i + 1) % 4]
            ab = b - a
            L = float(np.linalg.norm(ab))
            t = (pts - a) @ ab / L**2
            dist = np.abs((pts - a) @ np.array([-ab[1], ab[0]]) / L)
            across = 1 if abs(ab[0]) < abs(ab[1]) else 0  # near-vertical side: horizontal pairs
            sel = (t > 0.1) & (t < 0.9) & (dist < max(3.0, 0.05 * L)) & (pair_axis == across)
            if sel.sum() < 4:
                raise SofastImportError("cannot fit the facet's outline to the lit region (a side has too few "
                                        "boundary pixels); is the facet fully in view?")
            lines.append(_line_fit(pts[sel]))
        new = []
        for i in range(4):
            (n1, c1), (n2, c2) = lines[i - 1], lines[i]
            new.append(np.linalg.solve(np.stack([n1, n2]), np.array([c1, c2])))
        corners = np.array(new)
    return corners


def facet_centre_pixel(mask: np.ndarray, cam: Camera, delta: np.ndarray | None = None) -> tuple[float, float]:
    """Pixel (row, column) of the centre of a parallelogram facet (a rectangle, a square) from
    its outline in ``mask``: the intersection of the diagonals of the outline's corners in
    undistorted normalised coordinates (a pinhole maps the facet's plane projectively, which
    keeps the diagonals' intersection), distorted back to pixels (= the homography of
    :func:`~pmdsim.io.importers.outline.outline_point_pixel` for the centre)."""
    corners = facet_outline_corners(mask, delta)
    xy_d = np.stack([(corners[:, 0] - cam.ppx_px) / cam.fx_px, (corners[:, 1] - cam.ppy_px) / cam.fy_px], -1)
    xy, ok = cam.undistort(xy_d)
    if not np.all(ok):
        raise SofastImportError("the facet's corners could not be undistorted")
    p0, p1, p2, p3 = xy
    # p0 + s (p2 − p0) = p1 + t (p3 − p1)
    st = np.linalg.solve(np.stack([p2 - p0, -(p3 - p1)], axis=-1), p1 - p0)
    c = cam.distort((p0 + st[0] * (p2 - p0))[None])[0]
    return (float(c[1] * cam.fy_px + cam.ppy_px), float(c[0] * cam.fx_px + cam.ppx_px))


@dataclass(frozen=True)
class MeasurePointLocation:
    """Where the optic's measure point is seen (:func:`measure_point_pixel`).

    Attributes
    ----------
    pixel_vu : (row, column)
        By the pose fit of the outline corners (the anchor pixel).
    pixel_vu_homography : (row, column) or None
        By the corners' homography (a cross-check; None when the point is off the corners' plane).
    corners_px : ndarray (K, 2)
        The found corners (u, v), in the order of the optic's corners.
    rms_px : float
        Reprojection RMS of the pose fit.
    T_cam_obj : RigidTransform
        The pose fit (optic frame → camera frame, the optic file's unit).
    """

    pixel_vu: tuple[float, float]
    pixel_vu_homography: tuple[float, float] | None
    corners_px: np.ndarray
    rms_px: float
    T_cam_obj: RigidTransform


def measure_point_pixel(mask: np.ndarray, cam: Camera, corners_obj, point_obj,
                        delta: np.ndarray | None = None) -> MeasurePointLocation:
    """Pixel of a point ``point_obj`` (3,) of a four-cornered optic whose corners ``corners_obj``
    (4, 3) are known in its frame: the corners found in ``mask`` (:func:`facet_outline_corners`,
    sub-pixel with ``delta``), matched to the known ones, a pose fit (perspective-n-point with
    pmdsim's camera model, :func:`~pmdsim.io.importers.outline.outline_pose`), the point projected.

    Matching: of the 8 cyclic orders, those whose pose fit is within 1.5× (+0.05 px) of the best
    RMS; among them (a square's four turns fit equally) the one whose optic x axis points most
    along the image's +u and y axis along −v (SOFAST's convention: its expected optic orientation
    is the camera's turned 180° about x). On a facet rendered at the shared facet's pose with its
    measured edge blur, the pose fit is within 0.009 / 0.012 px (column / row, worst of 16
    sub-pixel positions) of the true centre, the diagonals 0.020 / 0.015 px (docs/benchmarks.md,
    issue 12; benchmarks/sofast_anchor.py)."""
    from .outline import OutlineError, outline_point_pixel, outline_pose

    obj = np.asarray(corners_obj, dtype=float)
    pt = np.asarray(point_obj, dtype=float).reshape(3)
    if obj.shape != (4, 3):
        raise SofastImportError(f"the optic's outline must have 4 corners (4, 3), got {obj.shape}")
    found = facet_outline_corners(mask, delta)
    fits = []
    for direction in (1, -1):
        for shift in range(4):
            order = [(shift + direction * k) % 4 for k in range(4)]
            c = found[order]
            try:
                fits.append((outline_pose(cam, c, obj), c))
            except OutlineError as e:
                raise SofastImportError(f"the facet's outline: {e}") from None
    best = min(f[0].rms_px for f in fits)
    ok = [f for f in fits if f[0].rms_px <= 1.5 * best + 0.05 and f[0].T_cam_obj.translation[2] > 0]
    R_of = lambda f: f[0].T_cam_obj.rotation  # noqa: E731
    pose, corners = max(ok, key=lambda f: R_of(f)[0, 0] - R_of(f)[1, 1])
    uv = pose.pixel_of(cam, pt)
    try:
        h = outline_point_pixel(cam, corners, obj, pt)
        hv = (float(h[1]), float(h[0]))
    except OutlineError:
        hv = None
    return MeasurePointLocation((float(uv[1]), float(uv[0])), hv, corners, pose.rms_px, pose.T_cam_obj)


# ============================================================================ import
@dataclass(frozen=True)
class SofastImportSummary:
    """What :func:`import_sofast` wrote."""

    out_dir: Path
    display_model: str
    n_images: int
    image_size_px: tuple[int, int]
    mask_pixels: int
    anchor_pixel_vu: tuple[float, float]
    distance_mm: float
    warnings: tuple[str, ...]

    def lines(self) -> list[str]:
        return [f"imported a SOFAST measurement ({self.display_model} display): {self.n_images} images of "
                f"{self.image_size_px[0]}×{self.image_size_px[1]} px, {self.mask_pixels} lit pixels; anchor: "
                f"{self.distance_mm:g} mm from the screen origin at pixel ({self.anchor_pixel_vu[0]:.2f}, "
                f"{self.anchor_pixel_vu[1]:.2f})",
                f"evaluate with: pmdsim evaluate {self.out_dir / 'images'} --setup {self.out_dir / 'setup.toml'} "
                f"--out EVAL"]


def _frame_from_z(z: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    z = z / np.linalg.norm(z)
    x = x_hint - (x_hint @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def import_sofast(*, measurement, camera, display, orientation, calibration, facet=None, out_dir,
                  force: bool = False, command: str | None = None) -> SofastImportSummary:
    """Import a SOFAST fringe measurement (module docstring) into ``out_dir``.

    Raises
    ------
    SofastImportError
        A file is missing or not the expected SOFAST file, values are implausible (lengths not
        in metres), the camera model does not fit the images or has terms pmdsim lacks.
    """
    warn: list[str] = []
    m = _read(measurement, {"fringes": "MeasurementSofastFringe/fringe_images",
                            "px": "MeasurementSofastFringe/fringe_periods_x",
                            "py": "MeasurementSofastFringe/fringe_periods_y",
                            "mask": "MeasurementSofastFringe/mask_images",
                            "dist": "MeasurementSofastFringe/dist_optic_screen",
                            "mp": "MeasurementSofastFringe/v_measure_point_facet"}, "measurement")
    fr = np.asarray(m["fringes"])
    src_m = f"{str(measurement)!r}"
    px = np.asarray(m["px"], dtype=float).ravel()
    py = np.asarray(m["py"], dtype=float).ravel()
    if fr.ndim != 3 or fr.shape[2] != 4 * (px.size + py.size):
        raise SofastImportError(f"{src_m}: fringe_images has shape {fr.shape}; expected (H, W, 4·(periods_y + "
                                f"periods_x)) = (H, W, {4 * (px.size + py.size)})")
    if fr.dtype not in (np.uint8, np.uint16):
        raise SofastImportError(f"{src_m}: fringe_images are {fr.dtype}; 8- or 16-bit grey levels expected")
    if np.any(px <= 0) or np.any(py <= 0):
        raise SofastImportError(f"{src_m}: fringe periods must be > 0 fringes per screen, got x {px}, y {py}")
    H, W = fr.shape[:2]
    dist_m = float(m["dist"])
    if not (0 < dist_m < _MAX_DISTANCE_M):
        raise SofastImportError(f"{src_m}: dist_optic_screen = {dist_m:g} is implausible in metres (SOFAST's unit); "
                                f"was it written in millimetres?")
    mp = np.asarray(m["mp"], dtype=float).ravel()
    cam, w_cam = read_sofast_camera(camera, image_size_px=(W, H))
    warn += w_cam
    disp = read_sofast_display(display)
    o = _read(orientation, {"r": "SpatialOrientation/r_cam_screen", "v": "SpatialOrientation/v_cam_screen_cam"},
              "spatial orientation")
    v_cs = np.asarray(o["v"], dtype=float).ravel()
    r_cs = np.asarray(o["r"], dtype=float).ravel()
    if v_cs.size != 3 or r_cs.size != 3 or np.linalg.norm(v_cs) > _MAX_DISTANCE_M:
        raise SofastImportError(f"{str(orientation)!r}: r_cam_screen and v_cam_screen_cam must be 3-vectors in metres, "
                                f"got {r_cs.tolist()}, {v_cs.tolist()}")
    cal = _read(calibration, {"d": "ImageCalibration/display_values", "c": "ImageCalibration/camera_values"},
                "image calibration")
    ctype = _optional(calibration, "ImageCalibration/calibration_type")
    dv = np.asarray(cal["d"], dtype=float).ravel()
    cv = np.asarray(cal["c"], dtype=float).ravel()
    check_calibration(calibration, dv, cv, fr, measurement)
    keep = np.concatenate([[True], np.diff(cv) > 0])
    if not keep.all():
        warn.append(f"{str(calibration)!r}: dropped {int((~keep).sum())} grey level(s) whose camera value does not "
                    f"increase (as SOFAST does)")
        dv, cv = dv[keep], cv[keep]

    # --- frames: world = camera (mm); pmdsim screen = display scaled, at its corner, flipped.
    R_cam_display = RigidTransform.from_rotvec(r_cs, np.zeros(3)).rotation.T  # display → camera
    T_cam_display_mm = RigidTransform(R_cam_display, 1e3 * v_cs)
    T_world_screen = T_cam_display_mm @ sofast_screen_transform(disp.size_mm)
    s_world = 1e3 * v_cs  # the display origin (SOFAST's distance is measured to it)
    Wmm, Hmm = disp.size_mm

    # Screen map and surface: pattern (f·W, f·H) → screen frame; distorted3D heights → surface.
    if disp.model == "rectangular2D":
        f_s = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    else:
        f_s = disp.fraction
    p_scr = fraction_to_screen_mm(f_s, disp)
    # Triangulated in SOFAST's screen fractions (f_x = x_q/W, f_y = 1 − y_q/H), as SOFAST does.
    smap = {"pattern_xy_mm": fraction_to_pattern_mm(f_s, disp.size_mm).tolist(), "screen_xy_mm": p_scr[:, :2].tolist(),
            "unit_affine": [[1.0 / Wmm, 0.0, 0.0], [0.0, -1.0 / Hmm, 1.0]], "unit_xy": f_s.tolist()}
    gx = (0.0, 0.5 * float(Wmm), float(Wmm))
    gy = (0.0, 0.5 * float(Hmm), float(Hmm))
    heights = None
    if disp.model == "distorted3D":
        from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

        nx = max(3, len(np.unique(np.round(disp.fraction[:, 0], 6))))
        ny = max(3, len(np.unique(np.round(disp.fraction[:, 1], 6))))
        gx = tuple(float(v) for v in np.linspace(0.0, Wmm, nx))
        gy = tuple(float(v) for v in np.linspace(0.0, Hmm, ny))
        GX, GY = np.meshgrid(gx, gy)
        z = LinearNDInterpolator(p_scr[:, :2], p_scr[:, 2])(GX, GY)
        z = np.where(np.isfinite(z), z, NearestNDInterpolator(p_scr[:, :2], p_scr[:, 2])(GX, GY))
        heights = tuple(tuple(float(v) for v in row) for row in z)
    screen = ScreenSetup(Pose.from_transform(T_world_screen), gx, gy, heights, None)

    # --- mask, anchor pixel (mask centroid: SOFAST's own estimate of the optic centroid), sample frame.
    mask_imgs = np.asarray(m["mask"])
    if mask_imgs.shape != (H, W, 2):
        raise SofastImportError(f"{src_m}: mask_images must be (H, W, 2) (dark, light) like the fringes, got "
                                f"{mask_imgs.shape}")
    mask = _mask(mask_imgs[..., 0], mask_imgs[..., 1])
    if mask.sum() < MIN_LIT_PIXELS:
        raise SofastImportError(f"{src_m}: MeasurementSofastFringe/mask_images has {int(mask.sum())} lit pixel(s) "
                                f"(light − dark above the dark level); at least {MIN_LIT_PIXELS} expected: are the "
                                f"dark and light images (…, 0) and (…, 1) in that order, and was the display on?")
    vv, uu = np.nonzero(mask)
    pix = (float(vv.mean()), float(uu.mean()))
    anchor_how = "the mask centroid (no --facet)"
    fcent = None
    outline_info = None
    if facet is not None:
        try:
            fdoc = json.loads(Path(facet).read_text(encoding="utf-8"))
            fc = np.stack([np.asarray(fdoc["v_facet_corners"][k], dtype=float) for k in ("x", "y", "z")], -1)
            fcent = np.array([float(np.ravel(fdoc["v_centroid_facet"][k])[0]) for k in ("x", "y", "z")])
        except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
            raise SofastImportError(f"facet file {str(facet)!r}: expected JSON with v_facet_corners.x/.y/.z and "
                                    f"v_centroid_facet (m): {e!r}") from None
        if fc.shape != (4, 3):
            raise SofastImportError(f"facet file {str(facet)!r}: v_facet_corners must hold 4 corners, got {fc.shape[0]}")
        delta = mask_imgs[..., 1].astype(float) - mask_imgs[..., 0].astype(float)
        loc = measure_point_pixel(mask, cam, fc, mp, delta)
        pix = loc.pixel_vu
        v_mp = loc.T_cam_obj.apply(mp[None])[0]  # metres, camera frame
        outline_info = {"pixel_vu_pose_fit": list(loc.pixel_vu),
                        "pixel_vu_homography": None if loc.pixel_vu_homography is None else list(loc.pixel_vu_homography),
                        "corners_px_uv": loc.corners_px.tolist(), "reprojection_rms_px": loc.rms_px,
                        "distance_from_outline_mm": 1e3 * float(np.linalg.norm(v_cs - v_mp)),
                        "distance_measured_mm": 1e3 * dist_m}
        anchor_how = (f"the measure point {mp.tolist()} m of the facet, located by a pose fit of the facet's outline "
                      f"corners (reprojection RMS {loc.rms_px:.3f} px)")
        d_outline = outline_info["distance_from_outline_mm"]
        if loc.rms_px > 1.0 or abs(d_outline / (1e3 * dist_m) - 1.0) > 0.02:
            warn.append(f"{str(facet)!r}: the facet's corners do not match its outline in the image: pose fit "
                        f"reprojection RMS {loc.rms_px:.2f} px, and the pose puts the measure point "
                        f"{d_outline:.0f} mm from the display origin where {src_m} measured {1e3 * dist_m:.0f} mm; "
                        f"is this the facet's file (corners in metres, in cyclic order), and is the facet fully in "
                        f"view? The anchor pixel may be off")
    elif np.any(mp != 0):
        warn.append(f"{src_m}: v_measure_point_facet = {mp.tolist()} is not the facet origin; the anchor pixel is the "
                    f"mask centroid, which is where SOFAST places the optic's origin before refining it")
    ray, ok = cam.sensor_rays()
    iv, iu = int(round(pix[0])), int(round(pix[1]))
    d = ray[iv, iu] / np.linalg.norm(ray[iv, iu])
    b = -2.0 * d @ s_world
    c = s_world @ s_world - (1e3 * dist_m) ** 2
    t = (-b + math.sqrt(max(b * b - 4 * c, 0.0))) / 2.0
    p_opt = t * d
    check_screen_faces_optic(r_cs, s_world, p_opt, orientation)
    z_s = -((-p_opt) / np.linalg.norm(p_opt) + (s_world - p_opt) / np.linalg.norm(s_world - p_opt))
    R_s = _frame_from_z(z_s, np.array([1.0, 0.0, 0.0]))
    half = 1000.0
    if fcent is not None:
        half = 1e3 * float(np.abs(fc[:, :2] - fcent[:2]).max())
    sample = SampleSetup(Pose.from_transform(RigidTransform(R_s, p_opt)), (-half, half), (-half, half))
    seq = FringeSequence(tuple(sorted((float(Wmm / n) for n in px), reverse=True)),
                         tuple(sorted((float(Hmm / n) for n in py), reverse=True)), n_shifts=4, mean_level=0.5, amplitude=0.5)
    bits = 8 if fr.dtype == np.uint8 else 16
    setup = Setup(cameras={CAMERA_NAME: CameraSetup(cam, Pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))}, screen=screen,
                  sample=sample, patterns=PatternSetup(seq, bit_depth=bits))

    # --- write.
    out = Path(out_dir)
    prov = provenance(command, setup.to_toml())
    inputs = [measurement, camera, display, orientation, calibration, facet]
    with atomic_output_dir(out, force=force, inputs=inputs, command=command) as tmp:
        (tmp / "setup.toml").write_text(setup.to_toml(), encoding="utf-8")
        img_dir = tmp / "images"
        img_dir.mkdir()
        entries = []
        idx = 0
        for direction, periods in (("y", py), ("x", px)):
            for i, n in enumerate(periods):
                for k in range(4):
                    name = f"{CAMERA_NAME}_{direction}_p{i}_s{k}.png"
                    write_png(img_dir / name, np.ascontiguousarray(fr[..., idx]))
                    entries.append({"file": name, "camera": CAMERA_NAME, "direction": direction,
                                    "period_fraction": float(1.0 / n), "shift_index": k, "n_shifts": 4})
                    idx += 1
        write_png(img_dir / "mask.png", np.where(mask, 255, 0).astype(np.uint8))
        write_json(img_dir / "response.json", {"display_values": dv.tolist(), "camera_values": cv.tolist(),
                                               "source": str(calibration), "calibration_type": ctype})
        write_json(img_dir / "screen_map.json", smap)
        manifest = {
            "format": IMAGESET_FORMAT, "format_version": 1, **prov, "bit_depth": bits,
            "screen_size_mm": [Wmm, Hmm],
            "cameras": {CAMERA_NAME: {"image_size_px": [W, H]}},
            "images": entries,
            "response": {"file": "response.json", "display_full_scale": 255.0,
                         "camera_full_scale": float(2**bits - 1), "interpolation": "linear"},
            "mask": {"file": "mask.png"},
            "screen_map": {"file": "screen_map.json"},
            "anchor": {"kind": "distance", "pixel_vu": [pix[0], pix[1]], "distance_mm": 1e3 * dist_m,
                       "point_world_mm": s_world.tolist(),
                       "description": f"SOFAST dist_optic_screen: the optic's measure point (seen at {anchor_how}) "
                                      f"to the display origin"},
            "screen_model": "setup" if disp.model == "distorted3D" else "planar",
            # A measured slope field is not exactly integrable: stepwise integration accumulates its
            # noise along the paths (4.7 µm p95 on the shared facet, least squares 0.69 µm;
            # docs/benchmarks.md, "Real data: the SOFAST heliostat facet").
            "method": "least_squares",
            "description": f"imported from SOFAST: {measurement}",
            "metadata": {"sofast": {"measurement": str(measurement), "camera": str(camera), "display": str(display),
                                    "display_model": disp.model, "orientation": str(orientation),
                                    "calibration": str(calibration), "facet": None if facet is None else str(facet)},
                         "outline": outline_info, "warnings": warn},
        }
        write_json(img_dir / MANIFEST_NAME, manifest)
    for w in warn:
        warnings.warn(w, SofastImportWarning, stacklevel=2)
    return SofastImportSummary(out, disp.model, len(entries), (W, H), int(mask.sum()), pix, 1e3 * dist_m, tuple(warn))
