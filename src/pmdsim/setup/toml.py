"""Setup files: TOML parsing with validation that names the key, and the TOML writer.

A setup is TOML with units in the key names (README, "The setup file"); :func:`parse_setup`
validates a parsed document and builds the :class:`~pmdsim.setup.model.Setup`;
:func:`load_setup` reads a file. Every problem raises :class:`~pmdsim.errors.SetupError`
naming the key (``cameras.left.focal_length_px``) and what was expected.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from ..errors import SetupError
from ..geometry.camera import DISTORTION_NAMES, Camera
from ..geometry.camera_checks import check_image_size, warn_if_folds_over
from ..geometry.transform import RigidTransform, rotvec_to_matrix
from .fringes import FringeSequence
from .sample_shape import SHAPES, HeightMapSource, SampleShape, resample_height_map
from .model import (
    SETUP_FORMAT,
    SETUP_FORMAT_VERSION,
    CalibrationSetup,
    CameraSetup,
    ImagingSetup,
    PatternSetup,
    Pose,
    SampleSetup,
    ScreenSetup,
    Setup,
    default_setup,
)
from .covariance import CalibrationCovariance
from .lcd import LCD_KEYS, read_lcd_keys
from .opencv_file import read_opencv_camera

__all__ = ["parse_setup", "load_setup", "dump_toml"]


# ============================================================================ parsing
#: The keys each table of a setup file may hold (for typo hints in error messages).
_KNOWN_KEYS = {
    "": ("format", "format_version", "cameras", "screen", "sample", "patterns", "calibration", "calibration_report",
         "imaging"),
    "camera": ("image_size_px", "focal_length_px", "principal_point_px", "distortion", "origin_world_mm", "angles_deg",
               "rotvec_deg", "rvec", "tvec", "opencv"),
    "distortion": DISTORTION_NAMES,
    "screen": ("origin_world_mm", "angles_deg", "grid_x_mm", "grid_y_mm", "heights_mm", "bulge_mm",
               "cover_glass_thickness_mm", "cover_glass_index"),
    "sample": ("origin_world_mm", "angles_deg", "grid_x_mm", "grid_y_mm", "heights_mm", "shape", "radius_mm",
               "focal_length_x_mm", "focal_length_y_mm", "axis_angle_deg", "vertex_xy_mm", "height_map",
               "height_map_dataset", "height_map_units", "height_map_grid_units", "height_map_x_dataset",
               "height_map_y_dataset", "height_map_x_mm", "height_map_y_mm", "height_map_max_error_um", "height_map_source"),
    "patterns": ("n_shifts", "periods_x_mm", "periods_y_mm", "mean_level", "amplitude", "bit_depth", "noise_std",
                 "seed"),
    "calibration": ("mirror_lifts_mm", "mirror_tilts_deg", "mirror_size_mm", "observation_stride_px", "mirror_sag_um",
                    "fit_glass_thickness", "fit_glass_index"),
    "imaging": ("bit_depth", "full_well_e", "exposure", "read_noise_e", "dark_offset_dn", "gain_dn_per_e",
                "display_gamma", "display_black_level", "linearise", "grey_levels", "emission_exponent",
                "screen_pixel_pitch_mm", "screen_fill_factor", "f_number", "focal_length_mm", "pixel_area",
                "focus_distance_mm", "sampling_step_px", "display_levels", *LCD_KEYS),
}


class _Reader:
    """Typed access to a TOML table with key paths in error messages."""

    def __init__(self, table: Any, path: str, known: tuple[str, ...] | None = None):
        if not isinstance(table, dict):
            raise SetupError(f"{path or 'setup'} must be a table, got {type(table).__name__}")
        self.table = table
        self.path = path
        self.used: set[str] = set()
        self.known = known

    def _typo_hint(self, missing: str) -> str:
        if self.known is None:
            return ""
        unknown = [k for k in self.table if k not in self.known]
        close = difflib.get_close_matches(missing, unknown, n=1, cutoff=0.75)
        return f" (found unknown key {self.key(close[0])}: a misspelling of {missing}?)" if close else ""

    def key(self, k: str) -> str:
        return f"{self.path}.{k}" if self.path else k

    def has(self, k: str) -> bool:
        return k in self.table

    def raw(self, k: str, default: Any = ...) -> Any:
        self.used.add(k)
        if k not in self.table:
            if default is ...:
                raise SetupError(f"missing key {self.key(k)}{self._typo_hint(k)}")
            return default
        return self.table[k]

    def number(self, k: str, default: Any = ..., *, positive: bool = False, nonneg: bool = False) -> float:
        v = self.raw(k, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SetupError(f"{self.key(k)} must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise SetupError(f"{self.key(k)} must be finite, got {v!r}")
        if positive and v <= 0:
            raise SetupError(f"{self.key(k)} must be > 0, got {v!r}")
        if nonneg and v < 0:
            raise SetupError(f"{self.key(k)} must be ≥ 0, got {v!r}")
        return v

    def integer(self, k: str, default: Any = ..., *, minimum: int | None = None, choices=None) -> int:
        v = self.raw(k, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise SetupError(f"{self.key(k)} must be an integer, got {v!r}")
        if minimum is not None and v < minimum:
            raise SetupError(f"{self.key(k)} must be ≥ {minimum}, got {v!r}")
        if choices is not None and v not in choices:
            raise SetupError(f"{self.key(k)} must be one of {list(choices)}, got {v!r}")
        return v

    def vector(self, k: str, n: int | None = None, default: Any = ..., *, min_len: int = 1) -> tuple[float, ...]:
        v = self.raw(k, default)
        if not isinstance(v, list):
            raise SetupError(f"{self.key(k)} must be a list of numbers, got {v!r}")
        if n is not None and len(v) != n:
            raise SetupError(f"{self.key(k)} must have {n} entries, got {len(v)}")
        if len(v) < min_len:
            raise SetupError(f"{self.key(k)} must have at least {min_len} entries, got {len(v)}")
        out = []
        for i, x in enumerate(v):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                raise SetupError(f"{self.key(k)}[{i}] must be a number, got {x!r}")
            if not math.isfinite(float(x)):
                raise SetupError(f"{self.key(k)}[{i}] must be finite, got {x!r}")
            out.append(float(x))
        return tuple(out)

    def grid(self, k: str) -> tuple[float, ...]:
        g = self.vector(k, min_len=2)
        for i in range(1, len(g)):
            if not g[i] > g[i - 1]:
                raise SetupError(
                    f"{self.key(k)} must be strictly increasing, but entry {i} ({g[i]}) ≤ entry {i - 1} ({g[i - 1]})"
                )
        return g

    def matrix(self, k: str, shape: tuple[int, int]) -> tuple[tuple[float, ...], ...]:
        v = self.raw(k)
        ny, nx = shape
        if not isinstance(v, list) or not all(isinstance(r, list) for r in v):
            raise SetupError(f"{self.key(k)} must be a list of {ny} rows of {nx} numbers")
        if len(v) != ny or any(len(r) != nx for r in v):
            got = f"{len(v)} rows of lengths {[len(r) for r in v]}"
            raise SetupError(
                f"{self.key(k)} must have shape (len(grid_y_mm), len(grid_x_mm)) = ({ny}, {nx}), got {got}"
            )
        rows = []
        for j, r in enumerate(v):
            row = []
            for i, x in enumerate(r):
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
                    raise SetupError(f"{self.key(k)}[{j}][{i}] must be a finite number, got {x!r}")
                row.append(float(x))
            rows.append(tuple(row))
        return tuple(rows)

    def table_(self, k: str, kind: str | None = None) -> "_Reader":
        return _Reader(self.raw(k), self.key(k), _KNOWN_KEYS.get(kind if kind is not None else k))

    def finish(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            known = sorted(self.known if self.known is not None else self.used)
            close = difflib.get_close_matches(unknown[0], known, n=1, cutoff=0.6)
            hint = f"did you mean {self.key(close[0])}? " if close else ""
            raise SetupError(f"unknown key {self.key(unknown[0])} ({hint}known keys here: {known})")


_MAX_IMAGE_SIDE_PX = 2**31 - 1  # the PNG format's limit on width and height


def _pose(r: _Reader) -> Pose:
    return Pose(r.vector("origin_world_mm", 3), r.vector("angles_deg", 3))


_INTRINSIC_KEYS = ("image_size_px", "focal_length_px", "principal_point_px", "distortion")


def _camera(r: _Reader, base_dir: Path | None = None) -> CameraSetup:
    if r.has("opencv"):
        return _camera_from_opencv_file(r, base_dir)
    size = r.raw("image_size_px")
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(s, int) and not isinstance(s, bool) for s in size)
    ):
        raise SetupError(f"{r.key('image_size_px')} must be [width, height] in whole pixels, got {size!r}")
    if size[0] <= 0 or size[1] <= 0:
        raise SetupError(f"{r.key('image_size_px')} must be positive, got {size!r}")
    if size[0] > _MAX_IMAGE_SIDE_PX or size[1] > _MAX_IMAGE_SIDE_PX:
        raise SetupError(f"{r.key('image_size_px')} must be ≤ {_MAX_IMAGE_SIDE_PX} px per side (PNG's limit), got {size!r}")
    f = r.vector("focal_length_px", 2)
    if f[0] <= 0 or f[1] <= 0:
        raise SetupError(f"{r.key('focal_length_px')} must be > 0, got {list(f)}")
    pp = r.vector("principal_point_px", 2)
    dist = {name: 0.0 for name in DISTORTION_NAMES}
    if r.has("distortion"):
        d = r.table_("distortion", "distortion")
        for k in dist:
            dist[k] = d.number(k, 0.0)
        d.finish()
    else:
        r.used.add("distortion")
    cam = Camera(size[0], size[1], f[0], f[1], pp[0], pp[1], **dist)
    pose = _camera_pose(r)
    r.finish()
    check_image_size(size, pp, source=f"{r.key('image_size_px')} with {r.key('principal_point_px')}")
    warn_if_folds_over(cam, source=r.path)
    return CameraSetup(cam, pose)


def _camera_from_opencv_file(r: _Reader, base_dir: Path | None) -> CameraSetup:
    """``[cameras.X] opencv = "file.yml"``: intrinsics from an OpenCV FileStorage file (path
    relative to the setup file's directory), the pose from the table."""
    name = r.raw("opencv")
    if not isinstance(name, str) or not name:
        raise SetupError(f"{r.key('opencv')} must be the path of an OpenCV camera file (.yml, .yaml, .xml, .json), "
                         f"got {name!r}")
    both = [k for k in _INTRINSIC_KEYS if r.has(k)]
    if both:
        raise SetupError(f"{r.key(both[0])}: the intrinsics come from {r.key('opencv')} = {name!r}; "
                         f"give them in one place only")
    path = Path(name)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    try:
        cam = read_opencv_camera(path)
    except SetupError as e:
        raise SetupError(f"{r.key('opencv')}: {e}") from None
    pose = _camera_pose(r)
    r.finish()
    return CameraSetup(cam, pose)


def _camera_pose(r: _Reader) -> Pose:
    """A camera's pose: ``origin_world_mm`` with ``angles_deg`` (Givens angles) or ``rotvec_deg``
    (rotation vector of R_world_cam, degrees: the camera's axes in world coordinates are the
    columns of R), or OpenCV's ``rvec`` (rad) and ``tvec`` (mm), which map world to camera:
    p_cam = R(rvec)·p_world + tvec (docs/conventions.md, "OpenCV cameras")."""
    given = [k for k in ("angles_deg", "rotvec_deg", "rvec") if r.has(k)]
    if len(given) != 1:
        found = f"found {' and '.join(r.key(k) for k in given)}" if given else "found none"
        raise SetupError(f"{r.path}: give the camera's orientation once: angles_deg (Givens angles), rotvec_deg "
                         f"(rotation vector, camera → world) or rvec + tvec (OpenCV, world → camera); {found}")
    if r.has("tvec") and given != ["rvec"]:
        raise SetupError(f"{r.key('tvec')} belongs with {r.key('rvec')} (OpenCV's world → camera pose); "
                         f"with {given[0]} give origin_world_mm instead")
    if given == ["rvec"]:
        if r.has("origin_world_mm"):
            raise SetupError(f"{r.path}: rvec + tvec already place the camera; remove {r.key('origin_world_mm')}")
        rvec = r.vector("rvec", 3)
        tvec = r.vector("tvec", 3)
        T_world_cam = RigidTransform(rotvec_to_matrix(np.array(rvec)), np.array(tvec)).inv()
    elif given == ["rotvec_deg"]:
        origin = r.vector("origin_world_mm", 3)
        rotvec = r.vector("rotvec_deg", 3)
        T_world_cam = RigidTransform(rotvec_to_matrix(np.radians(rotvec)), np.array(origin))
    else:
        return _pose(r)
    pose = Pose.from_transform(T_world_cam)
    # Givens angles are singular at β = ±90°: make sure the stored angles give the same rotation.
    err = float(np.max(np.abs(pose.T_world_x.rotation - T_world_cam.rotation)))
    if err > 1e-9:
        raise SetupError(f"{r.path}: this orientation lies at (or within float precision of) the Givens "
                         f"angles' singularity β = ±90° and cannot be stored as angles_deg (error {err:.1e}); "
                         f"choose world axes in which the camera is not turned by ±90° about its y axis")
    return pose


def _sample_shape(m: _Reader, gx, gy, heights, read_height_map, base_dir):
    """The ``[sample]`` shape keys (docs/conventions.md, "Curved samples"): (heights, shape)."""
    params = ("radius_mm", "focal_length_x_mm", "focal_length_y_mm", "axis_angle_deg")
    if m.has("shape"):
        kind = m.raw("shape")
        if not isinstance(kind, str):
            raise SetupError(f"sample.shape must be one of {list(SHAPES)}, got {kind!r}")
        kw = {k: m.raw(k) for k in params if m.has(k)}
        if m.has("vertex_xy_mm"):
            kw["vertex_xy_mm"] = m.vector("vertex_xy_mm", 2)
        for k in ("height_map", "heights_mm"):
            if m.has(k):
                raise SetupError(f"sample: give either sample.shape or sample.{k}, not both")
        shape = SampleShape(kind, **kw)
        shape.surface(gx, gy)  # its radius must cover the grid (SetupError otherwise)
        return None, shape
    for k in (*params, "vertex_xy_mm"):
        if m.has(k):
            raise SetupError(f"sample.{k} needs sample.shape (one of {list(SHAPES)})")
    hm_keys = [k for k in m.table if k.startswith("height_map") and k != "height_map_source"]
    if m.has("height_map_source"):
        if heights is None or hm_keys:
            raise SetupError("sample.height_map_source is the record pmdsim writes beside the resampled "
                             "sample.heights_mm; to read a file give sample.height_map (and no heights_mm)")
        rec = m.raw("height_map_source")
        if not isinstance(rec, dict):
            raise SetupError(f"sample.height_map_source must be a table, got {rec!r}")
        return heights, HeightMapSource.from_dict(rec)
    if not hm_keys:
        return heights, None
    if not m.has("height_map"):
        raise SetupError(f"sample.{hm_keys[0]} needs sample.height_map (the file)")
    if heights is not None:
        raise SetupError("sample: give either sample.height_map or sample.heights_mm, not both")
    file = m.raw("height_map")
    if not isinstance(file, str) or not file:
        raise SetupError(f"sample.height_map must be a file name (HDF5, NPY or CSV), got {file!r}")

    def text(k, default):
        v = m.raw(k, default)
        if v is not None and not isinstance(v, str):
            raise SetupError(f"sample.{k} must be a string, got {v!r}")
        return v

    src = HeightMapSource(
        file, text("height_map_dataset", None), text("height_map_units", "mm"), text("height_map_grid_units", "mm"),
        text("height_map_x_dataset", "x_mm"), text("height_map_y_dataset", "y_mm"),
        m.vector("height_map_x_mm", min_len=2) if m.has("height_map_x_mm") else None,
        m.vector("height_map_y_mm", min_len=2) if m.has("height_map_y_mm") else None,
        m.number("height_map_max_error_um", 1.0, positive=True),
    )
    if read_height_map is None:
        raise SetupError(f"sample.height_map = {file!r}: reading height-map files needs pmdsim.io; load the setup "
                         f"with pmdsim.load_setup or the pmdsim command (or pass read_height_map)")
    data = read_height_map(src, base_dir)
    z, report = resample_height_map(data, gx, gy, src.max_error_um)
    return tuple(tuple(float(v) for v in row) for row in z), src.with_report(report)


def parse_setup(doc: dict[str, Any], *, source: str = "setup", read_height_map=None,
                base_dir: str | Path | None = None) -> Setup:
    """Validate a setup document (parsed TOML) and build the :class:`Setup`.

    A ``[sample] height_map`` file is read by ``read_height_map(source, base_dir)`` →
    :class:`~pmdsim.setup.sample_shape.HeightMapData` (:func:`pmdsim.io.heightmap.read_height_map`;
    this layer reads no data files), relative paths against ``base_dir`` (default: the current
    directory), and resampled onto the sample's grid.
    ``base_dir`` is also what other relative file names in the document (``cameras.X.opencv``)
    are relative to: the setup file's directory (:func:`load_setup`).

    Raises
    ------
    SetupError
        Naming the key and the problem (missing or unknown keys, wrong types or shapes,
        non-finite values, non-increasing grids, non-positive sizes or focal lengths, …).
    """
    r = _Reader(doc, "", _KNOWN_KEYS[""])
    fmt = r.raw("format", SETUP_FORMAT)
    if fmt != SETUP_FORMAT:
        raise SetupError(f"{source}: format must be {SETUP_FORMAT!r}, got {fmt!r}")
    r.integer("format_version", SETUP_FORMAT_VERSION, choices=(SETUP_FORMAT_VERSION,))

    cams_r = _Reader(r.raw("cameras"), "cameras")
    if not cams_r.table:
        raise SetupError("cameras must define at least one camera, e.g. [cameras.left]")
    cameras = {}
    for name in cams_r.table:
        if not (name.isascii() and name.isidentifier()):  # a bare TOML key, file and HDF5 group name
            raise SetupError(f"camera name {name!r} must be a plain identifier (letters, digits, _)")
        cameras[name] = _camera(cams_r.table_(name, "camera"), None if base_dir is None else Path(base_dir))

    s = r.table_("screen")
    screen_pose = _pose(s)
    gx = s.grid("grid_x_mm")
    gy = s.grid("grid_y_mm")
    heights = s.matrix("heights_mm", (len(gy), len(gx))) if s.has("heights_mm") else None
    bulge = s.number("bulge_mm") if s.has("bulge_mm") else None
    s.used.update({"heights_mm", "bulge_mm"})
    if bulge is not None and (len(gx) % 2 == 0 or len(gy) % 2 == 0):
        raise SetupError(
            f"screen.bulge_mm needs an odd number of grid lines in screen.grid_x_mm and screen.grid_y_mm, "
            f"got {len(gx)} × {len(gy)}"
        )
    if bulge is not None and heights is not None:  # one centre height, not two (issue 24)
        centre = heights[len(gy) // 2][len(gx) // 2]
        if not math.isclose(centre, bulge, rel_tol=1e-12, abs_tol=1e-12):
            raise SetupError(
                f"screen.bulge_mm = {bulge:g} and the centre of screen.heights_mm (row {len(gy) // 2}, column "
                f"{len(gx) // 2}) = {centre:g} disagree: bulge_mm sets that control height; delete bulge_mm to use "
                f"heights_mm as given, or make them equal")
    glass_t = s.number("cover_glass_thickness_mm", 0.0, nonneg=True)
    glass_n = s.number("cover_glass_index") if s.has("cover_glass_index") else None
    s.used.add("cover_glass_index")
    if glass_n is not None and not glass_n > 1:
        raise SetupError(f"{s.key('cover_glass_index')} must be > 1 (a refractive index), got {glass_n!r}")
    s.finish()
    screen = ScreenSetup(screen_pose, gx, gy, heights, bulge, glass_t, glass_n)

    m = r.table_("sample")
    sample_pose = _pose(m)
    sgx = m.grid("grid_x_mm")
    sgy = m.grid("grid_y_mm")
    sh = m.matrix("heights_mm", (len(sgy), len(sgx))) if m.has("heights_mm") else None
    m.used.add("heights_mm")
    sh, shape = _sample_shape(m, sgx, sgy, sh, read_height_map, base_dir)
    m.finish()
    sample = SampleSetup(sample_pose, sgx, sgy, sh, shape)

    d = default_setup().patterns
    if r.has("patterns"):
        p = r.table_("patterns")
        n = p.integer("n_shifts", d.sequence.n_shifts, minimum=3)
        px = p.vector("periods_x_mm", None, list(d.sequence.periods_x_mm))
        py = p.vector("periods_y_mm", None, list(d.sequence.periods_y_mm))
        for key, ps in (("periods_x_mm", px), ("periods_y_mm", py)):
            if any(v <= 0 for v in ps):
                raise SetupError(f"patterns.{key} must be > 0, got {list(ps)}")
            if len(set(ps)) != len(ps):  # images are named by period index: a repeat would collide
                raise SetupError(f"patterns.{key} must not repeat a period, got {list(ps)}")
        mean = p.number("mean_level", d.sequence.mean_level, nonneg=True)
        amp = p.number("amplitude", d.sequence.amplitude, positive=True)
        if mean > 1 or amp > 1:
            raise SetupError(f"patterns.mean_level and patterns.amplitude are fractions of full scale (≤ 1), got {mean}, {amp}")
        bits = p.integer("bit_depth", d.bit_depth, choices=(8, 16))
        noise = p.number("noise_std", d.noise_std, nonneg=True)
        seed = p.integer("seed", d.seed, minimum=0)
        p.finish()
        patterns = PatternSetup(FringeSequence(px, py, n, mean, amp), bits, noise, seed)
    else:
        r.used.add("patterns")
        patterns = d
    dc = CalibrationSetup()
    if r.has("calibration"):
        c = r.table_("calibration")
        lifts = c.vector("mirror_lifts_mm", None, list(dc.mirror_lifts_mm), min_len=0)
        tilts = c.vector("mirror_tilts_deg", None, list(dc.mirror_tilts_deg), min_len=0)
        if any(not 0 < abs(t) < 30 for t in tilts):
            raise SetupError(f"calibration.mirror_tilts_deg must be non-zero and below 30°, got {list(tilts)}")
        size = c.vector("mirror_size_mm", 2, list(dc.mirror_size_mm))
        if min(size) <= 0:
            raise SetupError(f"calibration.mirror_size_mm must be > 0, got {list(size)}")
        stride = c.integer("observation_stride_px", dc.observation_stride_px, minimum=1)
        sag = c.number("mirror_sag_um", dc.mirror_sag_um)  # its size bound: CalibrationSetup
        fits = []
        for k in ("fit_glass_thickness", "fit_glass_index"):
            v = c.raw(k, False)
            if not isinstance(v, bool):
                raise SetupError(f"{c.key(k)} must be true or false, got {v!r}")
            fits.append(v)
        c.finish()
        calibration = CalibrationSetup(lifts, tilts, (size[0], size[1]), stride, sag, *fits)
    else:
        r.used.add("calibration")
        calibration = dc
    # Informational table written by `pmdsim calibrate`; its covariance is the setup's.
    covariance = _covariance(r.table_("calibration_report")) if r.has("calibration_report") else None
    r.used.add("calibration_report")
    imaging = _imaging(r.table_("imaging")) if r.has("imaging") else None
    r.used.add("imaging")
    r.finish()
    setup = Setup(cameras, screen, sample, patterns, calibration, imaging)
    if covariance is not None:
        setup = setup.with_calibration_covariance(covariance)  # checked against the cameras and the screen
    try:  # build the surfaces now so that any remaining problem shows here, with its key
        setup.screen.surface
    except ValueError as e:
        raise SetupError(f"screen: {e}") from None
    try:
        setup.sample.surface
    except ValueError as e:
        raise SetupError(f"sample: {e}") from None
    return setup


def _covariance(r: _Reader) -> CalibrationCovariance | None:
    """``calibration_report.covariance_parameters`` (names) and ``.covariance`` (rows), or None
    when neither is given (the rest of the table is informational)."""
    if not (r.has("covariance_parameters") or r.has("covariance")):
        return None
    names = r.raw("covariance_parameters")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise SetupError(f"{r.key('covariance_parameters')} must be a list of parameter names, got {names!r:.120}")
    rows, p = r.raw("covariance"), len(names)
    if not isinstance(rows, list) or len(rows) != p or any(not isinstance(x, list) or len(x) != p for x in rows):
        raise SetupError(f"{r.key('covariance')} must be {p} rows of {p} numbers (one per name of "
                         f"{r.key('covariance_parameters')}), got {rows!r:.120}")
    for j, row in enumerate(rows):
        for i, x in enumerate(row):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
                raise SetupError(f"{r.key('covariance')}[{j}][{i}] must be a finite number, got {x!r}")
    try:
        return CalibrationCovariance(tuple(names), np.array(rows, dtype=float).reshape(p, p))
    except SetupError as e:
        raise SetupError(f"{r.key('covariance')}: {e}") from None


def _imaging(r: _Reader) -> ImagingSetup:
    """The optional ``[imaging]`` table (docs/conventions.md, "Image formation")."""
    kw: dict[str, Any] = {}
    if r.has("bit_depth"):
        kw["bit_depth"] = r.integer("bit_depth", choices=(8, 10, 12, 16))
    if r.has("grey_levels"):
        kw["grey_levels"] = r.integer("grey_levels", minimum=3)
    if r.has("display_levels"):
        kw["display_levels"] = r.integer("display_levels", minimum=2)
    if r.has("sampling_step_px"):
        kw["sampling_step_px"] = r.integer("sampling_step_px", minimum=1)
    for k in ("linearise", "pixel_area"):
        if r.has(k):
            v = r.raw(k)
            if not isinstance(v, bool):
                raise SetupError(f"{r.key(k)} must be true or false, got {v!r}")
            kw[k] = v
    for k, rule in (("full_well_e", "positive"), ("exposure", "positive"), ("read_noise_e", "nonneg"),
                    ("dark_offset_dn", "nonneg"), ("gain_dn_per_e", "positive"), ("display_gamma", "positive"),
                    ("display_black_level", "nonneg"), ("emission_exponent", "nonneg"),
                    ("screen_pixel_pitch_mm", "positive"), ("screen_fill_factor", "positive"),
                    ("f_number", "positive"), ("focal_length_mm", "positive"), ("focus_distance_mm", "positive")):
        if r.has(k):
            kw[k] = r.number(k, **{rule: True})
    read_lcd_keys(r, kw)
    r.finish()
    return ImagingSetup(**kw)  # cross-field bounds (e.g. fill factor ≤ 1) name the key there


def load_setup(path: str | Path, *, read_height_map=None) -> Setup:
    """Read and validate a setup TOML file (see :func:`parse_setup`; height-map files are read
    relative to the setup file's directory — :func:`pmdsim.io.heightmap.load_setup` passes the
    reader)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SetupError(f"setup file {str(p)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SetupError(f"cannot read setup file {str(p)!r}: {e}") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SetupError(f"{p}: not valid TOML: {e}") from None
    try:
        return parse_setup(doc, source=str(p), read_height_map=read_height_map, base_dir=p.parent)
    except SetupError as e:
        raise SetupError(f"{p}: {e}") from None


# ============================================================================ TOML writer
_COMMENTS = {
    "": "pmdsim measurement setup. Units are in the key names (mm, deg, px); frames, signs and\n"
    "rotation order are fixed in docs/conventions.md. Angles (α, β, γ): R = Rz(γ)·Ry(β)·Rx(α),\n"
    "whose columns are the component's axes in world coordinates.",
    "cameras": "Pinhole + Brown distortion (paper §2.2). Pixel (0, 0) is the centre of the top-left pixel.",
    "screen": "Pattern screen (paper §2.3, §2.5). heights_mm (optional) is (len(grid_y_mm), len(grid_x_mm));\n"
    "bulge_mm sets the central control point (Δh); +z of the screen points away from the sample,\n"
    "so a positive bulge is concave as seen from the sample. When you add heights_mm, delete bulge_mm\n"
    "(or make it equal to the centre of heights_mm: a setup where they differ is refused).\n"
    "cover_glass_thickness_mm (default 0: none) and cover_glass_index (default 1.5) model the cover glass\n"
    "on the sample side of the emitting surface.",
    "sample": "Sample surface: a plane unless heights_mm (len(grid_y_mm) × len(grid_x_mm)) is given, or shape =\n"
    "\"sphere\" | \"paraboloid\" | \"cylinder\" (radius_mm / focal_length_x_mm, focal_length_y_mm; + = convex as seen\n"
    "from the cameras; exact over the grid's rectangle), or height_map = \"file\" (HDF5/NPY/CSV, resampled onto the grid).",
    "calibration": "Calibration mirror poses (paper §4): base = the sample's pose; lifts towards the cameras;\n"
    "each tilt applied +/− about the mirror's x and y axes through its centre; 1 + lifts + 4·tilts poses.\n"
    "mirror_sag_um: the mirror's flatness error, a paraboloid −s·(1 − r²/ρ²) (ρ = half the smaller side;\n"
    "+ = centre towards the cameras); 0 = a perfect plane, as the paper assumes.\n"
    "fit_glass_thickness, fit_glass_index (true/false): pmdsim calibrate estimates the screen's cover glass.",
    "imaging": "Image-formation effects (docs/conventions.md, \"Image formation\"); absent keys are off:\n"
    "sensor (bit_depth 8/10/12/16, full_well_e, exposure, read_noise_e, dark_offset_dn, gain_dn_per_e),\n"
    "display (display_gamma, display_black_level, linearise, grey_levels, emission_exponent,\n"
    "screen_pixel_pitch_mm, screen_fill_factor), optics (f_number, focal_length_mm, focus_distance_mm, pixel_area).",
    "patterns": "Fringes I_k = A + B·cos(2π·c/p − 2πk/N); mean_level A and amplitude B are fractions of full scale;\n"
    "periods coarsest first (the coarsest must cover the screen); noise_std in grey levels.",
}


def _plain(v: Any) -> Any:
    """numpy scalars and arrays as Python values (a camera from ``Camera.from_opencv`` holds
    ``np.float64``; its repr ``np.float64(4410.2)`` is not TOML)."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if not isinstance(v, (str, bytes)) and hasattr(v, "tolist"):  # numpy scalar or array
        return _plain(v.tolist())
    return v


def _key(k: str) -> str:
    """A key as TOML writes it (bare, or quoted by tomli-w when it needs to be)."""
    return tomli_w.dumps({k: 0}).removesuffix(" = 0\n")


def _fmt_value(v: Any) -> str:
    """One value: scalars written by tomli-w; arrays on one line, small tables inline."""
    v = _plain(v)
    if isinstance(v, float) and not math.isfinite(v):
        raise ValueError("TOML setup values must be finite")
    if isinstance(v, list):
        return "[" + ", ".join(_fmt_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_fmt_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (bool, int, float, str)):
        return tomli_w.dumps({"v": v}).removeprefix("v = ").removesuffix("\n")
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: dict[str, Any]) -> str:
    """A setup document as TOML: its tables in order with their comments, every value written by
    tomli-w (numpy values as Python's); ``tomllib.loads(dump_toml(d))`` gives ``d`` back."""
    lines: list[str] = []

    def comment(key: str) -> None:
        if key in _COMMENTS:
            lines.extend("# " + c for c in _COMMENTS[key].splitlines())

    def inline(path: str, v: Any) -> bool:
        # Plain values, and small tables of plain values inside a table (e.g. distortion).
        return not isinstance(v, dict) or (bool(path) and not any(isinstance(x, dict) for x in v.values()))

    def table(path: str, header: str, tbl: dict[str, Any]) -> None:
        values = {k: v for k, v in tbl.items() if inline(path, v)}
        if path:
            lines.append("")
            comment(path)
            if values:
                lines.append(f"[{header}]")
        for k, v in values.items():
            lines.append(f"{_key(k)} = {_fmt_value(v)}")
        for k, v in tbl.items():
            if k not in values:
                table(f"{path}.{k}" if path else k, f"{header}.{_key(k)}" if header else _key(k), v)

    comment("")
    table("", "", _plain(doc))
    return "\n".join(lines) + "\n"
