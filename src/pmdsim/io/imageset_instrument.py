"""What a real instrument's image set declares beside its images (issue 12), and how decoding
applies it: the intensity response, the pixel mask, the display's screen map, the depth anchor,
and image pages, bit depths and floating-point images.

Manifest keys (all optional; :mod:`pmdsim.io.imageset` validates the rest of the manifest)::

    "bit_depth": 12,                 # 8, 10, 12, 14 or 16: grey levels 0 … 2^bits − 1 (10- to
                                     # 14-bit images are stored in 16-bit files); samples at
                                     # 2^bits − 1 are flagged SATURATED per pixel
    "full_scale": 1.0,               # float images (TIFF float32): the grey level of full scale
    "response": {...},               # the display → camera response, applied before decoding
    "mask": {"file": "mask.png"},    # pixels to evaluate (non-zero); others are flagged DARK
    "screen_map": {"file": "screen_map.json"},   # pattern → physical screen coordinates
    "anchor": {...},                 # what fixes the height (pmdsim.evaluation.anchor)
    "screen_model": "setup",         # the screen model `pmdsim evaluate` uses by default
    "method": "least_squares",       # the integration `pmdsim evaluate` uses by default (real
                                     # slope fields are not exactly integrable: least squares)

An image entry may name a ``page`` of a multi-page TIFF (0-based); a multi-page file without
``page`` is refused (never page 0 silently).

**Response** (docs/conventions.md, "Intensity response"): one of

* ``{"gamma": γ, "black_level": b, "white_level": w}`` — c = b + (w − b)·d^γ;
* ``{"display_levels": [...], "camera_levels": [...]}`` — fractions of full scale;
* ``{"file": "response.json" | "image_calibration.h5", "display_full_scale": 255,
  "camera_full_scale": 255}`` — a measured grey-level series in grey units: a JSON object with
  ``display_values`` and ``camera_values``, or an HDF5 file with those datasets at its root or
  under ``ImageCalibration/`` (SOFAST's ``image_calibration.h5``);

plus ``"interpolation": "pchip"`` (default, :class:`~pmdsim.setup.response.IntensityResponse`)
or ``"linear"`` (the piecewise-linear interpolant of the series, as SOFAST's image calibration
defines it). Linearising maps each recorded sample c to the display level d(c) ∈ [0, 1] before
the N-step formula; samples above the brightest level of the series are flagged SATURATED.

**Screen map**: ``{"pattern_xy_mm": [[x, y], ...], "screen_xy_mm": [[x, y], ...]}`` and
optionally ``"unit_affine": [[a, b, c], [d, e, f]]`` with the samples' own unit coordinates
``"unit_xy"`` (in the manifest or a JSON file): scattered pattern coordinates (what the fringes encode, mm) and the
physical screen-frame positions (mm) where the display shows them; decoded pattern coordinates
are mapped by piecewise-linear interpolation over the Delaunay triangulation of the pattern
samples mapped to unit coordinates — by ``unit_affine`` (u = a·x + b·y + c, v = d·x + e·y + f)
if given, else scaled to their bounding box; the triangulation of a nearly regular grid is
ambiguous (even last-bit differences flip diagonals), so an instrument's own coordinates fix it:
``unit_xy`` gives the samples' unit coordinates exactly as the instrument triangulates them
(SOFAST's screen fractions) (:class:`scipy.interpolate.LinearNDInterpolator`); outside the triangulation a pixel is NaN
(registration marks it *outside the screen model*). This is how a display whose pattern is
distorted in its plane (a projector, SOFAST's ``distorted2D``/``distorted3D`` models) is
described; heights out of the plane belong to the setup's screen surface.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ImageSetError
from ..evaluation.phase import PhaseFlag, ScreenCoordinates
from ..setup.response import IntensityResponse, ResponseError
# read_frame (image pages, bit depths, float images) lives in .images, whose imports are light (the
# background decoding of .imageset_prefetch runs it in its thread), and is re-exported here
from .images import read_frame

__all__ = [
    "INTEGER_BIT_DEPTHS",
    "LinearResponse",
    "ScreenMap",
    "InstrumentInfo",
    "read_frame",
    "parse_instrument",
    "linearise_stacks",
    "linearise_camera",
    "linearised_noise_std",
    "consistency_stacks",
    "apply_mask_and_map",
]

#: Declared bit depths of integer images (10–14 bit are stored in 16-bit files).
INTEGER_BIT_DEPTHS = (8, 10, 12, 14, 16)

_RESPONSE_KEYS = {"gamma", "black_level", "white_level", "display_levels", "camera_levels", "file",
                  "display_full_scale", "camera_full_scale", "interpolation"}


# ============================================================================ response
@dataclass(frozen=True)
class LinearResponse:
    """The piecewise-linear display → camera response through a grey-level series (fractions
    of full scale; strictly increasing) and its exact inverse (piecewise linear as well)."""

    display_levels: tuple[float, ...]
    camera_levels: tuple[float, ...]

    def __post_init__(self) -> None:
        IntensityResponse(self.display_levels, self.camera_levels)  # the same validation

    def forward(self, display_level) -> np.ndarray:
        """Camera level c(d) (clipped to the measured range)."""
        return np.interp(np.asarray(display_level, dtype=float), self.display_levels, self.camera_levels)

    def linearise(self, camera_level) -> tuple[np.ndarray, np.ndarray]:
        """(d(c), out of the measured camera range) as :meth:`IntensityResponse.linearise`."""
        c = np.asarray(camera_level, dtype=float)
        lo, hi = self.camera_levels[0], self.camera_levels[-1]
        out = (c < lo) | (c > hi) | ~np.isfinite(c)
        return np.interp(np.nan_to_num(c, nan=lo), self.camera_levels, self.display_levels), out


def _read_series(path: Path, src: str) -> tuple[np.ndarray, np.ndarray]:
    """(display_values, camera_values) in grey units from a JSON or HDF5 file."""
    if not path.is_file():
        raise ImageSetError(f"{src}: key 'response.file': {str(path)!r} does not exist")
    if path.suffix.lower() in (".h5", ".hdf5", ".hdf"):
        import h5py

        try:
            with h5py.File(path, "r") as f:
                for prefix in ("", "ImageCalibration/"):
                    if prefix + "display_values" in f and prefix + "camera_values" in f:
                        return (np.asarray(f[prefix + "display_values"][()], dtype=float),
                                np.asarray(f[prefix + "camera_values"][()], dtype=float))
        except OSError as e:
            raise ImageSetError(f"{src}: key 'response.file': cannot read {str(path)!r}: {e}") from None
        raise ImageSetError(f"{src}: key 'response.file': {str(path)!r} has no datasets display_values and "
                            f"camera_values (at its root or under ImageCalibration/)")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        return np.asarray(doc["display_values"], dtype=float), np.asarray(doc["camera_values"], dtype=float)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ImageSetError(f"{src}: key 'response.file': {str(path)!r} must be JSON with 'display_values' and "
                            f"'camera_values' lists (grey levels): {e!r}") from None


def parse_response(doc: Any, src: str, directory: Path):
    """The manifest's ``response`` → (response object, description dict for the outputs)."""
    if not isinstance(doc, dict):
        raise ImageSetError(f"{src}: key 'response' must be an object, got {doc!r:.80}")
    unknown = sorted(set(doc) - _RESPONSE_KEYS)
    if unknown:
        raise ImageSetError(f"{src}: key 'response': unknown key(s) {unknown} (allowed: {sorted(_RESPONSE_KEYS)})")
    interp = doc.get("interpolation", "pchip")
    if interp not in ("pchip", "linear"):
        raise ImageSetError(f"{src}: key 'response.interpolation' must be 'pchip' or 'linear', got {interp!r}")
    kinds = [k for k in ("gamma", "display_levels", "file") if k in doc]
    if len(kinds) != 1:
        raise ImageSetError(f"{src}: key 'response' needs exactly one of 'gamma', 'display_levels'/'camera_levels' "
                            f"or 'file', got {kinds or 'none'}")
    kind = kinds[0]
    try:
        if kind == "gamma":
            g = doc["gamma"]
            if not isinstance(g, (int, float)) or isinstance(g, bool):
                raise ImageSetError(f"{src}: key 'response.gamma' must be a number, got {g!r}")
            base = IntensityResponse.from_gamma(float(g), black_level=float(doc.get("black_level", 0.0)),
                                                white_level=float(doc.get("white_level", 1.0)))
            desc = {"kind": "gamma", "gamma": float(g), "black_level": float(doc.get("black_level", 0.0)),
                    "white_level": float(doc.get("white_level", 1.0))}
        elif kind == "display_levels":
            base = IntensityResponse(tuple(doc["display_levels"]), tuple(doc.get("camera_levels", ())))
            desc = {"kind": "series"}
        else:
            f = doc["file"]
            if not isinstance(f, str) or not f:
                raise ImageSetError(f"{src}: key 'response.file' must be a file name, got {f!r}")
            dv, cv = _read_series(directory / f, src)
            dfs = float(doc.get("display_full_scale", 255.0))
            cfs = float(doc.get("camera_full_scale", 255.0))
            base = IntensityResponse.from_samples(dv, cv, display_full_scale=dfs, camera_full_scale=cfs)
            desc = {"kind": "series", "file": f, "display_full_scale": dfs, "camera_full_scale": cfs}
    except ResponseError as e:
        raise ImageSetError(f"{src}: key 'response': {e}") from None
    except (TypeError, ValueError) as e:
        raise ImageSetError(f"{src}: key 'response': {e}") from None
    resp = base if interp == "pchip" else LinearResponse(base.display_levels, base.camera_levels)
    desc.update(interpolation=interp, n_levels=len(base.display_levels),
                camera_range=[base.camera_levels[0], base.camera_levels[-1]])
    return resp, desc


# ============================================================================ screen map
@dataclass(frozen=True, eq=False)
class ScreenMap:
    """Pattern coordinates → physical screen-frame coordinates (mm), piecewise linear over
    the Delaunay triangulation of scattered samples (see the module docstring).

    Attributes
    ----------
    pattern_xy_mm, screen_xy_mm : ndarray, shape (M, 2)
        The samples: pattern coordinates and the screen-frame position shown there.
    """

    pattern_xy_mm: np.ndarray
    screen_xy_mm: np.ndarray
    unit_affine: np.ndarray | None = None
    unit_xy: np.ndarray | None = None

    def __post_init__(self) -> None:
        from scipy.interpolate import LinearNDInterpolator

        a = np.asarray(self.pattern_xy_mm, dtype=float)
        b = np.asarray(self.screen_xy_mm, dtype=float)
        if a.ndim != 2 or a.shape[1] != 2 or a.shape != b.shape or a.shape[0] < 3:
            raise ImageSetError(f"screen map: pattern_xy_mm and screen_xy_mm must be (M, 2) with M ≥ 3, "
                                f"got {a.shape} and {b.shape}")
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            raise ImageSetError("screen map: samples must be finite")
        object.__setattr__(self, "pattern_xy_mm", a)
        object.__setattr__(self, "screen_xy_mm", b)
        if self.unit_affine is None:
            lo = a.min(axis=0)
            ext = a.max(axis=0) - lo
            if not np.all(ext > 0):
                raise ImageSetError(f"screen map: the pattern samples span no area (extent {ext.tolist()} mm)")
            A = np.array([[1.0 / ext[0], 0.0, -lo[0] / ext[0]], [0.0, 1.0 / ext[1], -lo[1] / ext[1]]])
        else:
            A = np.asarray(self.unit_affine, dtype=float)
            if A.shape != (2, 3) or not np.isfinite(A).all() or abs(np.linalg.det(A[:, :2])) == 0:
                raise ImageSetError(f"screen map: unit_affine must be an invertible 2×3 affine map, got {A.tolist()}")
        object.__setattr__(self, "unit_affine", A)
        if self.unit_xy is not None:
            un = np.asarray(self.unit_xy, dtype=float)
            if un.shape != a.shape or not np.isfinite(un).all():
                raise ImageSetError(f"screen map: unit_xy must be finite and (M, 2) like pattern_xy_mm, got {un.shape}")
            if np.abs(un - self._unit(a)).max() > 1e-9:
                raise ImageSetError("screen map: unit_xy disagrees with unit_affine applied to pattern_xy_mm")
            object.__setattr__(self, "unit_xy", un)
        else:
            un = self._unit(a)
        try:
            object.__setattr__(self, "_interp", LinearNDInterpolator(un, b))
        except Exception as e:  # qhull errors: degenerate samples
            raise ImageSetError(f"screen map: cannot triangulate the pattern samples: {e}") from None

    def __call__(self, pattern_xy_mm) -> np.ndarray:
        """Screen-frame (x, y) in mm for pattern coordinates (..., 2); NaN outside the samples' hull."""
        p = np.asarray(pattern_xy_mm, dtype=float)
        out = np.full(p.shape, np.nan)
        ok = np.isfinite(p).all(axis=-1)
        if ok.any():
            out[ok] = self._interp(self._unit(p[ok]))
        return out

    def _unit(self, p: np.ndarray) -> np.ndarray:
        A = self.unit_affine
        return np.stack([A[0, 0] * p[:, 0] + A[0, 1] * p[:, 1] + A[0, 2],
                         A[1, 0] * p[:, 0] + A[1, 1] * p[:, 1] + A[1, 2]], axis=-1)

    def as_dict(self) -> dict:
        out = {"pattern_xy_mm": self.pattern_xy_mm.tolist(), "screen_xy_mm": self.screen_xy_mm.tolist(),
               "unit_affine": self.unit_affine.tolist()}
        if self.unit_xy is not None:
            out["unit_xy"] = self.unit_xy.tolist()
        return out


def _parse_screen_map(doc: Any, src: str, directory: Path) -> ScreenMap:
    if isinstance(doc, dict) and set(doc) == {"file"}:
        path = directory / str(doc["file"])
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise ImageSetError(f"{src}: key 'screen_map.file': cannot read {str(path)!r}: {e}") from None
    if not isinstance(doc, dict) or not ({"pattern_xy_mm", "screen_xy_mm"} <= set(doc) <=
                                         {"pattern_xy_mm", "screen_xy_mm", "unit_affine", "unit_xy"}):
        raise ImageSetError(f"{src}: key 'screen_map' must hold 'pattern_xy_mm' and 'screen_xy_mm' (and optionally "
                            f"'unit_affine'), or be {{'file': ...}} naming a JSON file that does")
    try:
        ua, un = doc.get("unit_affine"), doc.get("unit_xy")
        if un is not None and ua is None:
            raise ImageSetError(f"{src}: key 'screen_map': unit_xy needs unit_affine (to map decoded points)")
        return ScreenMap(np.asarray(doc["pattern_xy_mm"], dtype=float), np.asarray(doc["screen_xy_mm"], dtype=float),
                         None if ua is None else np.asarray(ua, dtype=float),
                         None if un is None else np.asarray(un, dtype=float))
    except (TypeError, ValueError) as e:
        raise ImageSetError(f"{src}: key 'screen_map': {e}") from None
    except ImageSetError as e:
        raise ImageSetError(f"{src}: key 'screen_map': {e}") from None


# ============================================================================ all of it
@dataclass(frozen=True, eq=False)
class InstrumentInfo:
    """The instrument keys of a manifest, validated (see the module docstring)."""

    response: Any = None
    response_info: dict | None = None
    mask: np.ndarray | None = None
    mask_file: str | None = None
    screen_map: ScreenMap | None = None
    anchor: dict | None = None
    full_scale: float | None = None
    screen_model: str | None = None
    method: str | None = None

    def describe(self) -> dict:
        """JSON-ready summary for the evaluation's outputs."""
        return {"response": self.response_info or "none (images decoded as recorded)",
                "mask": self.mask_file, "screen_map": self.screen_map is not None,
                "anchor": self.anchor}


def parse_instrument(doc: dict, src: str, directory: Path) -> InstrumentInfo:
    """Validate the instrument keys of a manifest ``doc``; errors name ``src`` and the key."""
    resp = info = None
    if "response" in doc:
        resp, info = parse_response(doc["response"], src, directory)
    mask = mask_file = None
    if "mask" in doc:
        m = doc["mask"]
        if not isinstance(m, dict) or set(m) != {"file"} or not isinstance(m["file"], str):
            raise ImageSetError(f"{src}: key 'mask' must be {{'file': 'mask.png'}}, got {m!r:.80}")
        mask_file = m["file"]
        try:
            mask = read_frame(directory / mask_file, None) != 0
        except ImageSetError as e:
            raise ImageSetError(f"{src}: key 'mask.file': {e}") from None
    smap = _parse_screen_map(doc["screen_map"], src, directory) if "screen_map" in doc else None
    anchor = doc.get("anchor")
    if anchor is not None and not isinstance(anchor, dict):
        raise ImageSetError(f"{src}: key 'anchor' must be an object, got {anchor!r:.80}")
    full = doc.get("full_scale")
    if full is not None and (not isinstance(full, (int, float)) or isinstance(full, bool)
                             or not math.isfinite(full) or full <= 0):
        raise ImageSetError(f"{src}: key 'full_scale' must be a positive number (the grey level of full scale of "
                            f"float images), got {full!r}")
    sm = doc.get("screen_model")
    if sm is not None and sm not in ("planar", "setup"):
        raise ImageSetError(f"{src}: key 'screen_model' must be 'planar' or 'setup', got {sm!r}")
    method = doc.get("method")
    if method is not None and method not in ("stepwise", "least_squares"):
        raise ImageSetError(f"{src}: key 'method' must be 'stepwise' or 'least_squares', got {method!r}")
    return InstrumentInfo(resp, info, mask, mask_file, smap, anchor, None if full is None else float(full), sm,
                          method)


# ============================================================================ decoding steps
def linearise_stacks(stacks, max_value: float, response):
    """Linearise image stacks with ``response``: returns (stacks of display levels d ∈ [0, 1],
    per-pixel saturated mask (H, W): a sample at full scale or above the series' brightest level).

    The linearised stacks (N_i, H, W) float64 are consecutive slices of one array, so that the
    decoder and the checks read them without another copy (pass a camera's x and y stacks in one
    call: :func:`pmdsim.evaluation.decoding_fused.common_image_stack`)."""
    top = response.camera_levels[-1]
    counts = [np.shape(st)[0] for st in stacks]
    lin = None
    sat = None
    i = 0
    for st, n in zip(stacks, counts):
        c = np.asarray(st, dtype=float) / max_value
        d, _ = response.linearise(c)
        s = ((c > top) | (np.asarray(st) >= max_value)).any(axis=0)
        sat = s if sat is None else (sat | s)
        if lin is None:
            lin = np.empty((sum(counts),) + d.shape[1:], d.dtype)
        lin[i:i + n] = d
        i += n
    offsets = np.cumsum([0] + counts)
    return [lin[a:b] for a, b in zip(offsets[:-1], offsets[1:])], sat


def linearise_camera(images, full: float, response):
    """(x stacks, y stacks, saturated (H, W)) of :func:`linearise_stacks` of a camera's x and y
    stacks in one call (slices of one array)."""
    n_x = len(images.x_stacks)
    lin, sat = linearise_stacks([*images.x_stacks, *images.y_stacks], full, response)
    return lin[:n_x], lin[n_x:], sat


def linearised_noise_std(images, response, noise_std=None) -> np.ndarray:
    """σ_I of linearised images, per pixel (H, W), in display levels (fractions of full scale).

    The camera's σ_I (grey levels; default quantisation noise 1/√12) is carried through the
    inverse response by its slope at each pixel's mean level of the finest x period (first-order
    error propagation, σ_d = |∂d/∂c|·σ_c), the slope a central difference over one grey level.
    """
    full = float(images.max_value)
    s_grey = 1.0 / np.sqrt(12.0) if noise_std is None else np.asarray(noise_std, dtype=float)
    mean_c = np.mean(images.x_stacks[-1], axis=0, dtype=float) / full
    h = 0.5 / full
    lo, _ = response.linearise(mean_c - h)
    hi, _ = response.linearise(mean_c + h)
    return s_grey / full * np.abs(hi - lo) / (2.0 * h)


def _sinusoid_fit(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Modulation B and residual sum of squares of the least-squares fit I_k = A + B·cos(φ − δ_k),
    δ_k = 2πk/N, of a stack (N, H, W): both (H, W) (the N-point DFT's first bin)."""
    st = np.asarray(stack, dtype=float)
    n = st.shape[0]
    d = 2.0 * np.pi * np.arange(n) / n
    a = st.mean(axis=0)
    c = (2.0 / n) * np.tensordot(np.cos(d), st, axes=1)
    s = (2.0 / n) * np.tensordot(np.sin(d), st, axes=1)
    fit = a + np.cos(d)[:, None, None] * c + np.sin(d)[:, None, None] * s
    return np.hypot(c, s), ((st - fit) ** 2).sum(axis=0)


def linearisation_residual(stacks, lit) -> tuple[float, np.ndarray]:
    """How far linearised fringes are from sinusoids, relative to their modulation.

    A display response known at a few grey levels linearises the images only approximately; the
    remainder is mostly a second harmonic of the fringe, which an N = 4 phase shift does not
    take into the phase (it aliases into the fit residual only) but which the residual check
    would read as a defect in every pixel. Its relative amplitude κ is estimated from the images
    themselves: per stack the median over ``lit`` pixels of √(RSS/(N − 3)) / B, scaled by
    1/0.6745 (the median of |z| for a normal z), and κ is the median over the stacks, so that a
    defective stack (a black frame: √RSS ≈ B) among many good ones does not raise it.

    Parameters
    ----------
    stacks : sequence of ndarray (N_i, H, W)
        Linearised stacks, display levels.
    lit : ndarray (H, W) bool
        Pixels to estimate from.

    Returns
    -------
    (kappa, b_max)
        κ (dimensionless) and the largest modulation over the stacks per pixel, (H, W).
    """
    ratios = []
    b_max = None
    for st in stacks:
        n = np.asarray(st).shape[0]
        b, rss = _sinusoid_fit(st)
        b_max = b if b_max is None else np.maximum(b_max, b)
        if n > 3 and lit.any():
            with np.errstate(invalid="ignore", divide="ignore"):
                r = np.sqrt(rss[lit] / (n - 3)) / b[lit]
            r = r[np.isfinite(r)]
            if r.size:
                ratios.append(float(np.median(r)) / 0.6745)
    return (float(np.median(ratios)) if ratios else 0.0), b_max


def consistency_stacks(images, response, noise_std=None, lit=None):
    """The stacks and σ_I the consistency checks (:mod:`pmdsim.evaluation.consistency`) test.

    Without a declared response: the raw stacks and ``noise_std``. With one: the linearised
    stacks (display levels — the decoder's input, where the fringe model I_k = A + B·cos(φ − δ_k)
    holds up to the linearisation's error) and, per pixel, σ_I² = σ_d² + (κ·B_max)²: σ_d the
    camera noise carried through the response (:func:`linearised_noise_std`), κ·B_max the
    linearisation's residual (:func:`linearisation_residual`, estimated over the ``lit`` pixels).
    A measurement with a declared response is thus checked like any other, without reading a
    coarsely sampled response as a defect in every pixel.

    Returns
    -------
    (x_stacks, y_stacks, noise_std, kappa)
        Lists of (N, H, W) arrays, a scalar or (H, W) σ_I in the stacks' units, and κ (None
        without a response).
    """
    if response is None:
        return list(images.x_stacks), list(images.y_stacks), noise_std, None
    full = float(images.max_value)
    xs, ys = linearise_camera(images, full, response)[:2]
    sigma_d = linearised_noise_std(images, response, noise_std)
    if lit is None:
        lit = np.ones(sigma_d.shape, bool)
    kappa, b_max = linearisation_residual(xs + ys, lit)
    sigma = np.sqrt(sigma_d ** 2 + (kappa * np.nan_to_num(b_max)) ** 2)
    return xs, ys, np.maximum(sigma, 1e-12), kappa


def _map_derivative(screen_map: ScreenMap, xy: np.ndarray, mapped: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The map's derivative along ``step`` (shape (2,), mm) at pattern points ``xy`` (..., 2):
    a forward difference, and a backward one where the forward point leaves the map (its last
    ``|step|`` of pattern coordinates), so that a pixel mapped inside the map has a finite local
    scale (and σ) up to the map's edge. Returns (..., 2): d(screen_xy_mm)/d(pattern) along step."""
    h = float(np.hypot(*step))
    d = (screen_map(xy + step) - mapped) / h
    back = ~np.isfinite(d).all(axis=-1) & np.isfinite(mapped).all(axis=-1)
    if back.any():
        d[back] = (mapped[back] - screen_map(xy[back] - step)) / h
    return d


def apply_mask_and_map(dec: ScreenCoordinates, *, saturated=None, mask=None, screen_map: ScreenMap | None = None,
                       source: str = "") -> ScreenCoordinates:
    """Flag saturated pixels (SATURATED) and pixels outside ``mask`` (DARK: not lit in the
    instrument's mask), then map pattern coordinates to screen coordinates with ``screen_map``
    (σ scaled by the map's local scale per axis)."""
    flags = dec.flags.copy()
    if saturated is not None:
        flags |= np.where(saturated, np.uint8(PhaseFlag.SATURATED), np.uint8(0))
    if mask is not None:
        if mask.shape != flags.shape:
            raise ImageSetError(f"{source}: the mask is {mask.shape[1]}×{mask.shape[0]} px (W×H) but the images are "
                                f"{flags.shape[1]}×{flags.shape[0]} px")
        flags |= np.where(mask, np.uint8(0), np.uint8(PhaseFlag.DARK))
    valid = flags == 0
    xy = np.where(valid[..., None], dec.screen_xy_mm, np.nan)
    std = np.where(valid[..., None], dec.std_xy_mm, np.nan)
    if screen_map is not None:
        h = 1e-3 * max(1.0, float(np.nanmax(np.abs(screen_map.pattern_xy_mm))))
        mapped = screen_map(xy)
        jx = _map_derivative(screen_map, xy, mapped, np.array([h, 0.0]))
        jy = _map_derivative(screen_map, xy, mapped, np.array([0.0, h]))
        with np.errstate(invalid="ignore"):
            std = np.stack([np.hypot(jx[..., 0] * std[..., 0], jy[..., 0] * std[..., 1]),
                            np.hypot(jx[..., 1] * std[..., 0], jy[..., 1] * std[..., 1])], axis=-1)
        std = np.where(np.isfinite(std), std, np.nan)
        xy = mapped
    return replace(dec, screen_xy_mm=xy, valid=valid, flags=flags, std_xy_mm=std)
