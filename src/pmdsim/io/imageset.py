"""Image sets: a manifest plus phase-shifted fringe images, read and decoded per camera.

An *image set* is a directory holding ``manifest.json`` (:data:`pmdsim.io.MANIFEST_NAME`) and
8- or 16-bit greyscale PNG or TIFF images. It is written by ``pmdsim simulate`` or assembled by
a user from a real camera. The manifest is a JSON object::

    {
      "format": "pmdsim-imageset",          # optional; if given, must be this
      "format_version": 1,                  # optional; if given, must be 1
      "bit_depth": 8,                       # optional: 8, 10, 12, 14 or 16; images must agree
                                            # (10–14 bit: stored in 16-bit files)
      "screen_size_mm": [708.0, 398.0],     # optional: screen width (x_q) and height (y_q), mm
      "cameras": {"left": {"image_size_px": [W, H]}, ...},   # optional
      "images": [
        {"file": "left_x_p0_s0.png", "camera": "left", "direction": "x",
         "period_mm": 720.0, "shift_index": 0, "n_shifts": 4},
        ...
      ]
    }

plus the provenance keys ``pmdsim_version``, ``command`` and ``setup_toml`` that pmdsim writes
and free-form ``description``/``metadata``. A real instrument's manifest may also declare its
intensity ``response`` (applied before decoding), a pixel ``mask``, a ``screen_map`` (pattern →
physical screen coordinates), the depth ``anchor``, ``full_scale`` of float (TIFF float32)
images and the default ``screen_model``: :mod:`pmdsim.io.imageset_instrument`. Every image entry needs ``file``, ``camera``,
``direction`` (``"x"`` for fringes encoding the screen's x_q, ``"y"`` for y_q),
``shift_index`` k (shift δ_k = 2πk/N, docs/conventions.md) and exactly one of

* ``period_mm`` — the fringe period in mm, or
* ``period_fraction`` — the period as a fraction of the screen width (direction x) or height
  (direction y); then the screen size must be known (manifest ``screen_size_mm`` or the
  ``screen_size_mm`` argument of :func:`load_manifest`).

``page`` selects a page of a multi-page TIFF (required for multi-page files). ``n_shifts`` N is optional (default: the number of shifts listed for that camera, direction and
period); ``period_index`` (written by ``pmdsim simulate``) is accepted and checked for
consistency. The shifts of every (camera, direction, period) group must be exactly 0 … N−1 with
N ≥ 3, and every camera needs at least one period per direction.

The module is pure I/O and validation (nothing is printed): every problem raises
:class:`~pmdsim.errors.ImageSetError` with a message naming the manifest, the entry
(``images[i]``), its file and the offending key.

Functions
---------
:func:`load_manifest`
    Read and validate a manifest → :class:`ImageSetManifest`.
:func:`load_camera_stacks`
    Read one camera's images → :class:`CameraImages` (stacks per period, coarsest first).
:func:`camera_images_from_arrays`
    The same :class:`CameraImages` from in-memory images (no files).
:func:`decode_camera`, :func:`decode_camera_images`
    Decode the pixel → screen mapping with :func:`pmdsim.evaluation.phase.decode_screen_coordinates`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..errors import ImageSetError
from .imageset_instrument import INTEGER_BIT_DEPTHS, InstrumentInfo, parse_instrument, read_frame
from .imageset_prefetch import prefaulted, stop_prefetch
from .imageset_prefetch import take as take_prefetched
from .outputs import IMAGESET_FORMAT, MANIFEST_NAME

__all__ = [
    "DIRECTIONS",
    "ImageEntry",
    "PeriodGroup",
    "ImageSetManifest",
    "CameraImages",
    "load_manifest",
    "load_camera_stacks",
    "camera_images_from_arrays",
    "decode_camera",
    "decode_camera_images",
]

#: Fringe directions: "x" encodes the screen's x_q, "y" its y_q.
DIRECTIONS = ("x", "y")

#: Supported manifest ``format_version``.
FORMAT_VERSION = 1

_REQUIRED_ENTRY_KEYS = ("file", "camera", "direction", "shift_index")
_PERIOD_KEYS = ("period_mm", "period_fraction")
_OPTIONAL_ENTRY_KEYS = ("n_shifts", "period_index", "page")
_ENTRY_KEYS = _REQUIRED_ENTRY_KEYS + _PERIOD_KEYS + _OPTIONAL_ENTRY_KEYS
_TOP_KEYS = ("format", "format_version", "pmdsim_version", "command", "setup_toml", "bit_depth",
             "screen_size_mm", "cameras", "images", "description", "metadata",
             "response", "mask", "screen_map", "anchor", "full_scale", "screen_model", "method")

#: Two periods of one camera and direction are the same period if they differ by less than this
#: relative amount (periods computed from ``period_fraction`` may differ in the last bits).
_PERIOD_RTOL = 1e-9

_MAX_VALUE = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}
_BITS = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}
_FLOAT_TYPES = (np.dtype(np.float32), np.dtype(np.float64))


# ============================================================================ data types
@dataclass(frozen=True)
class ImageEntry:
    """One validated image entry of a manifest.

    Attributes
    ----------
    index : int
        Position in the manifest's ``images`` list (``images[index]``).
    file : str or None
        File name as written in the manifest (None for in-memory images without one).
    path : pathlib.Path or None
        The file resolved against the image set's directory (None for in-memory images).
    camera : str
        Camera name.
    direction : {"x", "y"}
        Fringe direction: "x" encodes the screen's x_q, "y" its y_q.
    period_mm : float
        Fringe period in mm (converted from ``period_fraction`` where that was given).
    shift_index : int
        Phase-shift index k, 0 ≤ k < N (shift δ_k = 2πk/N).
    n_shifts : int
        Number of shifts N of this (camera, direction, period) group.
    """

    index: int
    file: str | None
    path: Path | None
    camera: str
    direction: str
    period_mm: float
    shift_index: int
    n_shifts: int
    page: int | None = None

    def label(self) -> str:
        """``images[i] ('file')`` — how messages name this entry."""
        return f"images[{self.index}]" + (f" ({self.file!r})" if self.file is not None else "")


@dataclass(frozen=True)
class PeriodGroup:
    """The N phase-shifted images of one camera, direction and period.

    Attributes
    ----------
    period_mm : float
        Fringe period in mm.
    n_shifts : int
        Number of shifts N ≥ 3.
    entries : tuple of ImageEntry, length N
        The images ordered by shift index 0 … N−1.
    """

    period_mm: float
    n_shifts: int
    entries: tuple[ImageEntry, ...]

    @property
    def files(self) -> tuple[Path | None, ...]:
        """Resolved image paths ordered by shift index."""
        return tuple(e.path for e in self.entries)


@dataclass(frozen=True)
class ImageSetManifest:
    """A validated image-set manifest (see the module docstring for the format).

    Attributes
    ----------
    path : pathlib.Path
        The manifest file.
    directory : pathlib.Path
        The image set's directory (image file names are relative to it).
    cameras : tuple of str
        Camera names in manifest order (the ``cameras`` table's order if present, else the
        order of first appearance in ``images``).
    screen_size_mm : (float, float) or None
        Screen (width along x_q, height along y_q) in mm: the ``screen_size_mm`` argument of
        :func:`load_manifest` if given, else the manifest's, else None.
    bit_depth : int or None
        8 or 16 if the manifest states it.
    image_size_px : mapping of str to (int, int)
        ``[width, height]`` per camera from the manifest's ``cameras`` table, where given.
    entries : tuple of ImageEntry
        All image entries in manifest order.
    layout : mapping
        ``layout[camera][direction]`` is a tuple of :class:`PeriodGroup`, coarsest period first.
    raw : mapping
        The manifest's top-level JSON object (read-only view), e.g. for ``setup_toml``.
    """

    path: Path
    directory: Path
    cameras: tuple[str, ...]
    screen_size_mm: tuple[float, float] | None
    bit_depth: int | None
    image_size_px: Mapping[str, tuple[int, int]]
    entries: tuple[ImageEntry, ...]
    layout: Mapping[str, Mapping[str, tuple[PeriodGroup, ...]]]
    raw: Mapping[str, Any]
    instrument: InstrumentInfo = InstrumentInfo()

    def groups(self, camera: str, direction: str) -> tuple[PeriodGroup, ...]:
        """The period groups of ``camera`` and ``direction`` ("x" or "y"), coarsest first."""
        _check_camera_direction(self.layout, camera, direction, str(self.path))
        return self.layout[camera][direction]

    def periods_mm(self, camera: str, direction: str) -> tuple[float, ...]:
        """Fringe periods in mm of ``camera`` and ``direction``, coarsest first."""
        return tuple(g.period_mm for g in self.groups(camera, direction))

    def files(self, camera: str, direction: str, period_mm: float) -> tuple[Path, ...]:
        """Image paths of one period of ``camera`` and ``direction``, ordered by shift index."""
        for g in self.groups(camera, direction):
            if _same_period(g.period_mm, float(period_mm)):
                return g.files
        raise ImageSetError(
            f"{self.path}: camera {camera!r}, direction {direction!r} has no period {period_mm!r} mm "
            f"(periods: {list(self.periods_mm(camera, direction))})"
        )


@dataclass(frozen=True, eq=False)
class CameraImages:
    """The fringe images of one camera, stacked per period (arrays are read-only).

    Attributes
    ----------
    camera : str
        Camera name.
    x_stacks, y_stacks : tuple of ndarray, each shape (N_i, H, W), uint8, uint16 or float
        One stack per period for direction x (encoding x_q) and y (y_q), coarsest period
        first; ``stack[k]`` is shift k (δ_k = 2πk/N_i). Grey levels.
    x_periods_mm, y_periods_mm : tuple of float
        The stacks' fringe periods in mm, coarsest first.
    max_value : int or float
        Full-scale grey level: 2^bits − 1 of the (declared) bit depth, or the manifest's
        ``full_scale`` for float images (default 1.0).
    shape : (int, int)
        Image size (H, W) in pixels.
    """

    camera: str
    x_stacks: tuple[np.ndarray, ...]
    x_periods_mm: tuple[float, ...]
    y_stacks: tuple[np.ndarray, ...]
    y_periods_mm: tuple[float, ...]
    max_value: int
    shape: tuple[int, int]

    @property
    def bit_depth(self) -> int | None:
        """8 … 16 for integer images (from ``max_value`` = 2^bits − 1), None for float images."""
        if self.x_stacks and np.issubdtype(self.x_stacks[0].dtype, np.floating):
            return None
        return int(round(math.log2(self.max_value + 1)))

    def stacks(self, direction: str) -> tuple[np.ndarray, ...]:
        """``x_stacks`` or ``y_stacks``."""
        return {"x": self.x_stacks, "y": self.y_stacks}[direction]

    def periods_mm(self, direction: str) -> tuple[float, ...]:
        """``x_periods_mm`` or ``y_periods_mm``."""
        return {"x": self.x_periods_mm, "y": self.y_periods_mm}[direction]


# ============================================================================ helpers
def _same_period(a: float, b: float) -> bool:
    return abs(a - b) <= _PERIOD_RTOL * max(abs(a), abs(b))


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_camera_direction(layout, camera: str, direction: str, source: str) -> None:
    if camera not in layout:
        raise ImageSetError(f"{source}: no camera {camera!r} in the image set (cameras: {list(layout)})")
    if direction not in DIRECTIONS:
        raise ImageSetError(f"direction must be 'x' or 'y', got {direction!r}")


def _screen_size(value: Any, what: str) -> tuple[float, float]:
    """Validate a (width, height) pair in mm."""
    try:
        arr = [float(v) for v in value] if not isinstance(value, (str, bytes)) else None
    except (TypeError, ValueError):
        arr = None
    if (arr is None or len(arr) != 2 or any(isinstance(v, bool) for v in value)
            or not all(math.isfinite(v) and v > 0 for v in arr)):
        raise ImageSetError(f"{what} must be [width, height] in mm, two positive finite numbers, got {value!r}")
    return (arr[0], arr[1])


def _fmt_list(items: Sequence[str], limit: int = 10) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f", … ({len(items) - limit} more)" if len(items) > limit else "")


def _parse_entry(i: int, raw: Any, source: str, screen_size: tuple[float, float] | None,
                 directory: Path | None, require_file: bool) -> tuple[ImageEntry, int | None, int | None]:
    """Validate ``images[i]``; returns (entry with n_shifts = −1 if not given, n_shifts, period_index)."""
    if not isinstance(raw, dict):
        raise ImageSetError(f"{source}: images[{i}] must be an object, got {type(raw).__name__}")
    file = raw.get("file")
    label = f"{source}: images[{i}]" + (f" ({file!r})" if isinstance(file, str) else "")
    unknown = [k for k in raw if k not in _ENTRY_KEYS]
    if unknown:
        raise ImageSetError(f"{label}: unknown key(s) {', '.join(map(repr, unknown))} "
                            f"(allowed: {', '.join(_ENTRY_KEYS)})")
    required = _REQUIRED_ENTRY_KEYS if require_file else tuple(k for k in _REQUIRED_ENTRY_KEYS if k != "file")
    missing = [k for k in required if k not in raw]
    if missing:
        raise ImageSetError(f"{label}: missing key(s) {', '.join(map(repr, missing))}")
    if "file" in raw and (not isinstance(file, str) or not file.strip()):
        raise ImageSetError(f"{label}: key 'file' must be a non-empty file name, got {file!r}")
    camera = raw["camera"]
    if not isinstance(camera, str) or not camera:
        raise ImageSetError(f"{label}: key 'camera' must be a non-empty string, got {camera!r}")
    direction = raw["direction"]
    if direction not in DIRECTIONS:
        raise ImageSetError(f"{label}: key 'direction' must be 'x' or 'y', got {direction!r}")
    k = raw["shift_index"]
    if not _is_int(k) or k < 0:
        raise ImageSetError(f"{label}: key 'shift_index' must be an integer ≥ 0, got {k!r}")
    n = raw.get("n_shifts")
    if n is not None and (not _is_int(n) or n < 3):
        raise ImageSetError(f"{label}: key 'n_shifts' must be an integer ≥ 3 (N-step phase shifting "
                            f"needs at least 3 shifts), got {n!r}")
    if n is not None and k >= n:
        raise ImageSetError(f"{label}: key 'shift_index' = {k} is out of range for n_shifts = {n} "
                            f"(shift indices are 0 … {n - 1})")
    pidx = raw.get("period_index")
    if pidx is not None and (not _is_int(pidx) or pidx < 0):
        raise ImageSetError(f"{label}: key 'period_index' must be an integer ≥ 0, got {pidx!r}")
    page = raw.get("page")
    if page is not None and (not _is_int(page) or page < 0):
        raise ImageSetError(f"{label}: key 'page' must be an integer ≥ 0 (a page of a multi-page TIFF), got {page!r}")
    given = [key for key in _PERIOD_KEYS if key in raw]
    if len(given) != 1:
        what = "both" if given else "neither"
        raise ImageSetError(f"{label}: exactly one of the keys 'period_mm' and 'period_fraction' must be "
                            f"given, got {what}")
    key = given[0]
    value = raw[key]
    if not _is_number(value) or not math.isfinite(value) or value <= 0:
        raise ImageSetError(f"{label}: key {key!r} must be a positive finite number, got {value!r}")
    if key == "period_mm":
        period = float(value)
    else:
        if screen_size is None:
            raise ImageSetError(
                f"{label}: key 'period_fraction' needs the screen size, but neither the manifest's "
                f"'screen_size_mm' nor a screen_size_mm argument gives it"
            )
        period = float(value) * screen_size[DIRECTIONS.index(direction)]
    path = None
    if directory is not None and isinstance(file, str):
        path = directory / file
    entry = ImageEntry(index=i, file=file if isinstance(file, str) else None, path=path, camera=camera,
                       direction=direction, period_mm=period, shift_index=k, n_shifts=-1, page=page)
    return entry, n, pidx


def _build_layout(raw_entries: Sequence, source: str, screen_size: tuple[float, float] | None,
                  directory: Path | None, require_file: bool, camera_order: Sequence[str] | None = None):
    """Validate and group entries: returns (entries, cameras, layout)."""
    if not isinstance(raw_entries, (list, tuple)) or not raw_entries:
        raise ImageSetError(f"{source}: key 'images' must be a non-empty list of image entries, "
                            f"got {raw_entries!r:.80}")
    parsed = [_parse_entry(i, r, source, screen_size, directory, require_file) for i, r in enumerate(raw_entries)]

    # The same file twice is a copy-and-paste error, not a second image.
    seen_files: dict[tuple, int] = {}
    for e, _, _ in parsed:
        if e.file is not None:
            key = (str(Path(e.file)), e.page)
            if key in seen_files:
                what = "file" if e.page is None else f"file and page {e.page}"
                raise ImageSetError(f"{source}: images[{e.index}] ({e.file!r}): key 'file' repeats "
                                    f"images[{seen_files[key]}]'s {what}")
            seen_files[key] = e.index

    # Group by (camera, direction, period); periods equal to within _PERIOD_RTOL.
    groups: dict[str, dict[str, list[list]]] = {}
    for item in parsed:
        e = item[0]
        per_dir = groups.setdefault(e.camera, {}).setdefault(e.direction, [])
        for g in per_dir:
            if _same_period(g[0][0].period_mm, e.period_mm):
                g.append(item)
                break
        else:
            per_dir.append([item])

    if camera_order is not None:
        for e, _, _ in parsed:
            if e.camera not in camera_order:
                raise ImageSetError(f"{source}: {e.label()}: key 'camera' = {e.camera!r} is not in the "
                                    f"manifest's 'cameras' table ({list(camera_order)})")
    cameras = list(groups) if camera_order is None else list(camera_order)
    entries_out: dict[int, ImageEntry] = {}
    layout: dict[str, dict[str, tuple[PeriodGroup, ...]]] = {}
    for cam in cameras:
        layout[cam] = {}
        for direction in DIRECTIONS:
            items = groups.get(cam, {}).get(direction)
            if not items:
                raise ImageSetError(
                    f"{source}: camera {cam!r} has no images for direction {direction!r}; at least one "
                    f"fringe period per direction is needed (x encodes the screen's x_q, y its y_q)"
                )
            pgroups = []
            for g in items:
                period = g[0][0].period_mm
                what = f"camera {cam!r}, direction {direction!r}, period {period:g} mm"
                by_shift: dict[int, ImageEntry] = {}
                for e, _, _ in g:
                    if e.shift_index in by_shift:
                        raise ImageSetError(
                            f"{source}: images[{e.index}] ({e.file!r}): duplicate image for {what}, "
                            f"key 'shift_index' = {e.shift_index} (also images[{by_shift[e.shift_index].index}] "
                            f"({by_shift[e.shift_index].file!r}))"
                        )
                    by_shift[e.shift_index] = e
                stated = {n for _, n, _ in g if n is not None}
                if len(stated) > 1:
                    bad = [f"images[{e.index}]: {n}" for e, n, _ in g if n is not None]
                    raise ImageSetError(f"{source}: key 'n_shifts' differs within {what} ({_fmt_list(bad)})")
                n = stated.pop() if stated else len(g)
                if n < 3:
                    raise ImageSetError(
                        f"{source}: {what} has N = {n} phase shifts ({_fmt_list([e.label() for e, _, _ in g])}); "
                        f"N-step phase shifting needs N ≥ 3 (key 'n_shifts' / 'shift_index')"
                    )
                missing = [k for k in range(n) if k not in by_shift]
                extra = sorted(k for k in by_shift if k >= n)
                if extra:
                    e = by_shift[extra[0]]
                    raise ImageSetError(f"{source}: {e.label()}: key 'shift_index' = {e.shift_index} is out of "
                                        f"range for {what} with N = {n} shifts (0 … {n - 1})")
                if missing:
                    listed = [f"{e.label()} k={e.shift_index}" for e in sorted(by_shift.values(),
                                                                               key=lambda e: e.shift_index)]
                    raise ImageSetError(
                        f"{source}: {what}: shift indices must be 0 … {n - 1} (N = {n}), missing "
                        f"key 'shift_index' value(s) {missing}; listed: {_fmt_list(listed)}"
                    )
                pidx = {p for _, _, p in g if p is not None}
                if len(pidx) > 1:
                    raise ImageSetError(f"{source}: key 'period_index' differs within {what}: {sorted(pidx)}")
                ordered = []
                for k in range(n):
                    e = by_shift[k]
                    e = ImageEntry(e.index, e.file, e.path, e.camera, e.direction, period, e.shift_index, n, e.page)
                    entries_out[e.index] = e
                    ordered.append(e)
                pgroups.append(PeriodGroup(period_mm=period, n_shifts=n, entries=tuple(ordered)))
            pgroups.sort(key=lambda pg: -pg.period_mm)
            layout[cam][direction] = tuple(pgroups)
    entries = tuple(entries_out[i] for i in sorted(entries_out))
    frozen = MappingProxyType({c: MappingProxyType(d) for c, d in layout.items()})
    return entries, tuple(cameras), frozen


# ============================================================================ manifest
def load_manifest(path_or_dir: str | Path, *, screen_size_mm=None, check_files: bool = True) -> ImageSetManifest:
    """Read and validate an image set's manifest.

    Parameters
    ----------
    path_or_dir : str or pathlib.Path
        The image set's directory (containing ``manifest.json``) or the manifest file itself;
        image file names are relative to the manifest's directory.
    screen_size_mm : (float, float), optional
        Screen (width along x_q, height along y_q) in mm, e.g. from the measurement setup.
        Overrides the manifest's ``screen_size_mm``; needed for ``period_fraction`` entries if the
        manifest does not give it.
    check_files : bool
        Check that every image file exists (default True). All missing files are listed in one
        error.

    Returns
    -------
    ImageSetManifest
        Cameras, and per camera and direction the periods (mm, coarsest first) with their
        files ordered by shift index.

    Raises
    ------
    ImageSetError
        If the manifest is missing or not valid JSON, a key is missing, unknown or has an invalid
        value, periods or shifts are inconsistent (duplicates, shifts not 0 … N−1, N < 3), a camera
        lacks a direction, a ``period_fraction`` has no screen size, or image files are missing.
        The message names the manifest, the entry ``images[i]``, its file and the key.
    """
    p = Path(path_or_dir)
    manifest_path = p / MANIFEST_NAME if p.is_dir() else p
    if not manifest_path.is_file():
        where = f"no {MANIFEST_NAME} in directory {str(p)!r}" if p.is_dir() else f"manifest {str(p)!r} does not exist"
        raise ImageSetError(f"{where}: an image set needs a manifest (see pmdsim.io.imageset)")
    src = str(manifest_path)
    try:
        text = manifest_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ImageSetError(f"{src}: cannot read the manifest: {e}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise ImageSetError(f"{src}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    if not isinstance(doc, dict):
        raise ImageSetError(f"{src}: the manifest must be a JSON object, got {type(doc).__name__}")
    unknown = [k for k in doc if k not in _TOP_KEYS]
    if unknown:
        raise ImageSetError(f"{src}: unknown top-level key(s) {', '.join(map(repr, unknown))} "
                            f"(allowed: {', '.join(_TOP_KEYS)})")
    if "format" in doc and doc["format"] != IMAGESET_FORMAT:
        raise ImageSetError(f"{src}: key 'format' must be {IMAGESET_FORMAT!r}, got {doc['format']!r}")
    if "format_version" in doc and doc["format_version"] != FORMAT_VERSION:
        raise ImageSetError(f"{src}: key 'format_version' = {doc['format_version']!r} is not supported "
                            f"(this pmdsim reads version {FORMAT_VERSION})")
    bit_depth = doc.get("bit_depth")
    if bit_depth is not None and (not _is_int(bit_depth) or bit_depth not in INTEGER_BIT_DEPTHS):
        raise ImageSetError(f"{src}: key 'bit_depth' must be one of {list(INTEGER_BIT_DEPTHS)} (10–14 bit are "
                            f"stored in 16-bit files), got {bit_depth!r}")
    size = None
    if "screen_size_mm" in doc:
        size = _screen_size(doc["screen_size_mm"], f"{src}: key 'screen_size_mm'")
    if screen_size_mm is not None:
        size = _screen_size(screen_size_mm, "argument screen_size_mm")
    camera_order = None
    image_size: dict[str, tuple[int, int]] = {}
    if "cameras" in doc:
        cams = doc["cameras"]
        if not isinstance(cams, dict) or not cams:
            raise ImageSetError(f"{src}: key 'cameras' must be a non-empty object of camera tables, got {cams!r:.80}")
        for name, table in cams.items():
            if not isinstance(table, dict):
                raise ImageSetError(f"{src}: key 'cameras.{name}' must be an object, got {table!r:.80}")
            if "image_size_px" in table:
                wh = table["image_size_px"]
                if (not isinstance(wh, list) or len(wh) != 2 or not all(_is_int(v) and v > 0 for v in wh)):
                    raise ImageSetError(f"{src}: key 'cameras.{name}.image_size_px' must be [width, height], "
                                        f"two positive integers, got {wh!r}")
                image_size[name] = (wh[0], wh[1])
        camera_order = list(cams)
    if "images" not in doc:
        raise ImageSetError(f"{src}: missing key 'images' (the list of image entries)")
    entries, cameras, layout = _build_layout(doc["images"], src, size, manifest_path.parent, True, camera_order)
    if check_files:
        missing = [f"images[{e.index}] {e.file!r}" for e in entries if not e.path.is_file()]
        if missing:
            raise ImageSetError(f"{src}: {len(missing)} image file(s) missing in {str(manifest_path.parent)!r}: "
                                f"{_fmt_list(missing)}")
    instrument = parse_instrument(doc, src, manifest_path.parent)
    return ImageSetManifest(
        path=manifest_path, directory=manifest_path.parent, cameras=cameras, screen_size_mm=size,
        bit_depth=bit_depth, image_size_px=MappingProxyType(image_size), entries=entries, layout=layout,
        raw=MappingProxyType(doc), instrument=instrument,
    )


# ============================================================================ stacks
def _check_depth(img: np.ndarray, e: ImageEntry, source: str, bit_depth: int | None) -> None:
    """The image's pixel type against the declared bit depth (module docstring)."""
    if img.dtype in _FLOAT_TYPES:
        if bit_depth is not None:
            raise ImageSetError(f"{source}: {e.label()}: a floating-point image ({img.dtype}), but 'bit_depth' is "
                                f"{bit_depth}; float images take 'full_scale' (their grey level of full scale)")
        return
    if img.dtype not in _MAX_VALUE:
        raise ImageSetError(f"{source}: {e.label()}: pixel type {img.dtype}; 8-bit (uint8), 16-bit (uint16) or "
                            f"float32 grey levels expected")
    if bit_depth is None:
        return
    container = 8 if bit_depth == 8 else 16
    if _BITS[img.dtype] != container:
        raise ImageSetError(f"{source}: {e.label()}: the image is {_BITS[img.dtype]}-bit, but 'bit_depth' is "
                            f"{bit_depth} (stored in {container}-bit files)")
    top = 2**bit_depth - 1
    if top >= _MAX_VALUE[img.dtype]:  # the container's range: no grey level can exceed it (no pass over the image)
        return
    mx = int(img.max()) if img.size else 0
    if mx > top:
        raise ImageSetError(f"{source}: {e.label()}: grey levels up to {mx} exceed the declared {bit_depth}-bit range "
                            f"0 … {top}; is 'bit_depth' right (e.g. 12-bit images scaled to 16 bit)?")


def _stack_camera(camera: str, layout, get: Callable[[ImageEntry], np.ndarray], source: str,
                  bit_depth: int | None, size_wh: tuple[int, int] | None,
                  full_scale: float | None = None, empty: Callable = np.empty) -> CameraImages:
    """Fetch every image of ``camera`` with ``get``, check size and dtype, stack per period.

    The images are copied into one (N, H, W) array of the camera (x then y, coarse → fine, shift
    by shift), allocated at the first image (by ``empty(shape, dtype)``); the stacks are its consecutive slices, so that the
    decoder and the checks read them as one array without another copy
    (:func:`pmdsim.evaluation.decoding_fused.common_image_stack`)."""
    groups = [g for direction in DIRECTIONS for g in layout[camera][direction]]
    frames = None  # (N, H, W): the camera's images
    ref: tuple[ImageEntry, tuple[int, int], np.dtype] | None = None
    i = 0
    for g in groups:
        for e in g.entries:
            img = get(e)
            if img.ndim != 2:
                raise ImageSetError(f"{source}: {e.label()}: expected a greyscale (H, W) image, "
                                    f"got shape {img.shape}")
            _check_depth(img, e, source, bit_depth)
            if ref is None:
                if size_wh is not None and (img.shape[1], img.shape[0]) != size_wh:
                    raise ImageSetError(
                        f"{source}: {e.label()}: image size {img.shape[1]}×{img.shape[0]} px (W×H) differs "
                        f"from 'cameras.{camera}.image_size_px' = {size_wh[0]}×{size_wh[1]}"
                    )
                ref = (e, img.shape, img.dtype)
            elif img.shape != ref[1] or img.dtype != ref[2]:
                r = ref[0]
                if img.shape != ref[1]:
                    what = (f"image size {img.shape[1]}×{img.shape[0]} px (W×H), expected "
                            f"{ref[1][1]}×{ref[1][0]} px")
                else:
                    what = (f"{_BITS[img.dtype]}-bit ({img.dtype}), expected {_BITS[ref[2]]}-bit ({ref[2]})"
                            if img.dtype in _BITS and ref[2] in _BITS else f"pixel type {img.dtype}, expected {ref[2]}")
                raise ImageSetError(f"{source}: {e.label()}: {what} like {r.label()}, the first image "
                                    f"of camera {camera!r}; all images of a camera must agree")
            if frames is None:
                shape = (sum(len(gr.entries) for gr in groups),) + img.shape
                frames = empty(shape, img.dtype)
            frames[i] = img
            i += 1
    assert ref is not None and frames is not None
    frames.setflags(write=False)
    out: dict[str, list[np.ndarray]] = {}
    i = 0
    for direction in DIRECTIONS:
        out[direction] = []
        for g in layout[camera][direction]:
            out[direction].append(frames[i:i + len(g.entries)])
            i += len(g.entries)
    return CameraImages(
        camera=camera,
        x_stacks=tuple(out["x"]), x_periods_mm=tuple(g.period_mm for g in layout[camera]["x"]),
        y_stacks=tuple(out["y"]), y_periods_mm=tuple(g.period_mm for g in layout[camera]["y"]),
        max_value=_full_scale(ref[2], bit_depth, full_scale), shape=(int(ref[1][0]), int(ref[1][1])),
    )


def _full_scale(dtype: np.dtype, bit_depth: int | None, full_scale: float | None):
    """The grey level of full scale: declared bit depth, the dtype's, or ``full_scale`` (floats)."""
    if dtype in _FLOAT_TYPES:
        return 1.0 if full_scale is None else float(full_scale)
    return 2**bit_depth - 1 if bit_depth is not None else _MAX_VALUE[dtype]


def load_camera_stacks(manifest: ImageSetManifest, camera: str, *,
                       expected_size_px: tuple[int, int] | None = None) -> CameraImages:
    """Read one camera's images and stack them per period.

    Parameters
    ----------
    manifest : ImageSetManifest
        From :func:`load_manifest`.
    camera : str
        One of ``manifest.cameras``.
    expected_size_px : (int, int), optional
        ``[width, height]`` the images must have, e.g. the setup camera's ``image_size_px``.

    Returns
    -------
    CameraImages
        ``x_stacks``/``y_stacks``: one (N_i, H, W) uint8/uint16 array per period, coarsest
        first, shift k at index k; ``x_periods_mm``/``y_periods_mm`` in mm; ``max_value`` 255 or
        65535 from the images' dtype; ``shape`` (H, W).

    Raises
    ------
    ImageSetError
        If the camera is unknown, an image is missing, unreadable, not greyscale, or differs in
        size or bit depth from the camera's first image (or from the manifest's ``bit_depth`` /
        ``cameras.<camera>.image_size_px``). The message names the file, its entry and the
        expected vs found size or bit depth.
    """
    src = str(manifest.path)
    _check_camera_direction(manifest.layout, camera, "x", src)

    def get(e: ImageEntry) -> np.ndarray:
        # decoded in the background if `pmdsim evaluate` started it (.imageset_prefetch), else
        # (or where the background read failed) read here; either is copied into the camera's array
        frame = take_prefetched(manifest.path, e.path, e.page)
        if frame is not None:
            return frame
        try:
            return read_frame(e.path, e.page, writable=False)
        except ImageSetError as exc:
            raise ImageSetError(f"{src}: {e.label()}: {exc}") from None

    try:
        imgs = _stack_camera(camera, manifest.layout, get, src, manifest.bit_depth,
                             manifest.image_size_px.get(camera), manifest.instrument.full_scale,
                             lambda shape, dtype: prefaulted(manifest.path, camera, shape, dtype))
    except ImageSetError:
        stop_prefetch(manifest.path)  # nothing more is read: no thread decodes on after the error
        raise
    if expected_size_px is not None:
        w, h = (int(v) for v in expected_size_px)
        if (imgs.shape[1], imgs.shape[0]) != (w, h):
            raise ImageSetError(
                f"{src}: camera {camera!r}: the images are {imgs.shape[1]}×{imgs.shape[0]} px (W×H), but the setup's "
                f"cameras.{camera}.image_size_px is {w}×{h}; use the setup of the camera that took them (binned or "
                f"downsampled images need a camera model at their resolution)")
    return imgs


def camera_images_from_arrays(entries: Sequence[Mapping[str, Any]], images: Sequence, *,
                              camera: str | None = None, screen_size_mm=None,
                              bit_depth: int | None = None) -> CameraImages:
    """Build :class:`CameraImages` from in-memory images described by manifest entries.

    Parameters
    ----------
    entries : sequence of dict
        Manifest image entries (see the module docstring; ``file`` is optional here), e.g.
        :meth:`pmdsim.simulation.ImageSpec.as_manifest_entry` results.
    images : sequence of array_like, each shape (H, W), uint8 or uint16
        ``images[i]`` is the image of ``entries[i]`` (grey levels).
    camera : str, optional
        Which camera to build; required only if the entries name several cameras.
    screen_size_mm : (float, float), optional
        Screen (width, height) in mm, needed for ``period_fraction`` entries.
    bit_depth : {8, 16}, optional
        If given, the images' bit depth must agree.

    Returns
    -------
    CameraImages
        As :func:`load_camera_stacks` returns for the same images read from files.

    Raises
    ------
    ImageSetError
        As :func:`load_manifest` and :func:`load_camera_stacks`, naming ``entries[i]`` (as
        ``images[i]``); also if the numbers of entries and images differ.
    """
    source = "in-memory image set"
    entries = list(entries)
    images = list(images)
    if len(entries) != len(images):
        raise ImageSetError(f"{source}: {len(entries)} entries but {len(images)} images; one image per entry")
    if bit_depth is not None and bit_depth not in INTEGER_BIT_DEPTHS:
        raise ImageSetError(f"{source}: bit_depth must be one of {list(INTEGER_BIT_DEPTHS)}, got {bit_depth!r}")
    size = None if screen_size_mm is None else _screen_size(screen_size_mm, "argument screen_size_mm")
    if camera is None:
        names = list(dict.fromkeys(e.get("camera") for e in entries if isinstance(e, Mapping)))
        if len(names) > 1:
            raise ImageSetError(f"{source}: the entries name several cameras {names}; pass camera=")
    elif not any(isinstance(e, Mapping) and e.get("camera") == camera for e in entries):
        raise ImageSetError(f"{source}: no entry has camera {camera!r}")
    raw = [dict(e) if isinstance(e, Mapping) else e for e in entries]
    _, cameras, layout = _build_layout(raw, source, size, None, False)
    cam = cameras[0] if camera is None else camera

    def get(e: ImageEntry) -> np.ndarray:
        return np.asarray(images[e.index])

    return _stack_camera(cam, layout, get, source, bit_depth, None)


# The decoding of a loaded image set lives in .imageset_decode (it needs the types above);
# imported last so that this module's names exist when it imports them, and re-exported here
# because `pmdsim.io.imageset.decode_camera(_images)` is where users' scripts find them.
from .imageset_decode import decode_camera, decode_camera_images  # noqa: E402
