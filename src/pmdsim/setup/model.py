"""Measurement setups as small immutable value objects: cameras, pattern screen, sample, poses.

The paper's Table 1 is built in (:func:`default_setup`). A setup is written and read as TOML
by :mod:`pmdsim.setup.toml` (:meth:`Setup.to_toml`, :func:`~pmdsim.setup.toml.load_setup`,
:func:`~pmdsim.setup.toml.parse_setup`); an invalid setup raises
:class:`~pmdsim.errors.SetupError` naming the key and the problem. Units are in the names (mm,
deg, px); conventions in docs/conventions.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..geometry.camera import DISTORTION_NAMES, Camera
from ..geometry.cover_glass import DEFAULT_GLASS_INDEX, CoverGlass
from ..errors import SetupError
from .covariance import CalibrationCovariance
from .fringes import FringeSequence
from .lcd import LCD_DEFAULTS, validate_lcd
from ..geometry.surface import SplineSurface
from ..geometry.transform import RigidTransform
from .sample_shape import HeightMapData, HeightMapSource, InterpolationReport, SampleShape, resample_height_map

__all__ = [
    "Pose",
    "CameraSetup",
    "ScreenSetup",
    "SampleSetup",
    "PatternSetup",
    "Setup",
    "CalibrationSetup",
    "ImagingSetup",
    "default_setup",
    "SETUP_FORMAT",
]

SETUP_FORMAT = "pmdsim-setup"
SETUP_FORMAT_VERSION = 1


# ============================================================================ value objects
class FrozenMap(Mapping):
    """An immutable, hashable mapping that keeps its insertion order (``Setup.cameras``): reads
    like a dict (``setup.cameras["left"]``, iteration, ``len``, ``in``), equal to a dict with the
    same items, and cannot be changed in place — a setup's parts are values (issue 23)."""

    __slots__ = ("_items",)

    def __init__(self, items=()):
        object.__setattr__(self, "_items", dict(items))

    def __getitem__(self, key):
        return self._items[key]

    def __iter__(self):
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __hash__(self) -> int:
        return hash(tuple(self._items.items()))

    def __setattr__(self, name, value):
        raise AttributeError("FrozenMap is immutable")

    def __reduce__(self):
        return (FrozenMap, (tuple(self._items.items()),))

    def __repr__(self) -> str:
        return f"FrozenMap({self._items!r})"


@dataclass(frozen=True)
class Pose:
    """Six pose parameters of a component (paper §2.1): origin in world (mm), Givens angles (deg).

    ``T_world_x`` maps component coordinates to world; its inverse is the paper's T_xw.
    """

    origin_world_mm: tuple[float, float, float]
    angles_deg: tuple[float, float, float]

    @cached_property
    def T_world_x(self) -> RigidTransform:
        return RigidTransform.from_origin_angles(self.origin_world_mm, self.angles_deg)

    @classmethod
    def from_transform(cls, T_world_x: RigidTransform) -> "Pose":
        o, a = T_world_x.as_origin_angles()
        return cls(tuple(float(v) for v in o), tuple(float(v) for v in a))


@dataclass(frozen=True)
class CameraSetup:
    """One camera: intrinsic model and pose."""

    camera: Camera
    pose: Pose

    @property
    def T_world_cam(self) -> RigidTransform:
        return self.pose.T_world_x


@dataclass(frozen=True)
class ScreenSetup:
    """The pattern screen: a spline surface over its grid (paper §2.3, §2.5) and its pose.

    ``heights_mm`` is the full (n_y, n_x) matrix of control heights; ``bulge_mm``, when not None,
    sets the central control point (the paper's Δh; both grids then need an odd count).
    """

    pose: Pose
    grid_x_mm: tuple[float, ...]
    grid_y_mm: tuple[float, ...]
    heights_mm: tuple[tuple[float, ...], ...] | None = None
    bulge_mm: float | None = 0.0
    # Cover glass (issue 21, docs/conventions.md "Cover glass"): thickness t ≥ 0 (0 = none)
    # and index n > 1 (None: 1.5 when t > 0).
    cover_glass_thickness_mm: float = 0.0
    cover_glass_index: float | None = None

    def __post_init__(self) -> None:
        t = self.cover_glass_thickness_mm
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
            raise SetupError(f"screen.cover_glass_thickness_mm must be a finite number ≥ 0 (mm), got {t!r}")
        n = self.cover_glass_index
        if n is not None and (isinstance(n, bool) or not isinstance(n, (int, float)) or not math.isfinite(n) or n <= 1):
            raise SetupError(f"screen.cover_glass_index must be a finite number > 1, got {n!r}")

    @property
    def cover_glass(self) -> CoverGlass:
        """The screen's :class:`~pmdsim.geometry.cover_glass.CoverGlass` (thickness 0: none)."""
        n = DEFAULT_GLASS_INDEX if self.cover_glass_index is None else self.cover_glass_index
        return CoverGlass(float(self.cover_glass_thickness_mm), float(n))

    def control_heights(self) -> np.ndarray:
        """(n_y, n_x) control heights with the bulge applied."""
        ny, nx = len(self.grid_y_mm), len(self.grid_x_mm)
        z = np.zeros((ny, nx)) if self.heights_mm is None else np.array(self.heights_mm, dtype=float)
        if self.bulge_mm is not None:
            z[ny // 2, nx // 2] = self.bulge_mm
        return z

    @cached_property
    def surface(self) -> SplineSurface:
        return SplineSurface(self.grid_x_mm, self.grid_y_mm, self.control_heights())

    @property
    def T_world_screen(self) -> RigidTransform:
        return self.pose.T_world_x

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the screen's grid."""
        return (self.grid_x_mm[-1] - self.grid_x_mm[0], self.grid_y_mm[-1] - self.grid_y_mm[0])


@dataclass(frozen=True)
class SampleSetup:
    """The sample: a spline surface (a plane when all heights are 0) and its pose.

    ``shape`` (issue 14, docs/conventions.md "Curved samples"): a
    :class:`~pmdsim.setup.sample_shape.SampleShape` makes the sample that analytic shape in
    closed form over the grid's rectangle (``heights_mm`` must then be None); a
    :class:`~pmdsim.setup.sample_shape.HeightMapSource` records the file that ``heights_mm``
    were resampled from, with the interpolation error (:meth:`Setup.with_sample_height_map`).
    """

    pose: Pose
    grid_x_mm: tuple[float, ...]
    grid_y_mm: tuple[float, ...]
    heights_mm: tuple[tuple[float, ...], ...] | None = None
    shape: SampleShape | HeightMapSource | None = None

    def __post_init__(self) -> None:
        if isinstance(self.shape, SampleShape) and self.heights_mm is not None:
            raise SetupError(f"sample: give either shape = {self.shape.kind!r} or heights_mm, not both")
        if isinstance(self.shape, HeightMapSource) and self.heights_mm is None:
            raise SetupError(f"sample: the height map {self.shape.file!r} has not been resampled onto the grid "
                             f"(use Setup.with_sample_height_map)")

    @property
    def curved(self) -> bool:
        """True for a shape, a height map or non-zero ``heights_mm``: the sample is not its frame's
        x–y plane (then the consistency checks' orientation reference is the mapping traced
        through it, not the nominal plane's; docs/reliability.md, issue 24)."""
        return self.shape is not None or (self.heights_mm is not None
                                          and any(v != 0.0 for row in self.heights_mm for v in row))

    @cached_property
    def surface(self) -> SplineSurface:
        """The sample surface in its frame: a SplineSurface, or a QuadricSurface for a shape."""
        if isinstance(self.shape, SampleShape):
            return self.shape.surface(self.grid_x_mm, self.grid_y_mm)
        ny, nx = len(self.grid_y_mm), len(self.grid_x_mm)
        z = np.zeros((ny, nx)) if self.heights_mm is None else np.array(self.heights_mm, dtype=float)
        return SplineSurface(self.grid_x_mm, self.grid_y_mm, z)

    @property
    def interpolation_report(self) -> InterpolationReport | None:
        """For a height map: how far the spline is from the file's heights (None otherwise;
        an analytic shape is exact — :func:`~pmdsim.setup.sample_shape.spline_report` gives
        what its spline on the grid would miss)."""
        return self.shape.report if isinstance(self.shape, HeightMapSource) else None

    @property
    def T_world_sample(self) -> RigidTransform:
        return self.pose.T_world_x


@dataclass(frozen=True)
class PatternSetup:
    """Fringe sequence plus image formation (bit depth, noise)."""

    sequence: FringeSequence
    bit_depth: int = 8
    noise_std: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class ImagingSetup:
    """Image-formation effects beyond the paper's ideal camera (issue 13); ``None``/``False`` = off.

    Units and conventions: docs/conventions.md, "Image formation". All effects off reproduce the
    ideal renderer bit for bit. Noise is seeded by ``patterns.seed``.

    Attributes
    ----------
    bit_depth : {8, 10, 12, 16} or None
        Camera bit depth (None: ``patterns.bit_depth``); above 8 bit the images are uint16.
    full_well_e : float or None
        Full-well capacity in electrons; switches the sensor model (shot and read noise, dark
        offset, gain, saturation) on.
    exposure : float
        Signal of a full-white, normally viewed screen as a fraction of the full well (> 0).
    read_noise_e : float
        Read noise σ in electrons (≥ 0).
    dark_offset_dn : float
        Dark offset in grey levels (DN) added to every sample (≥ 0).
    gain_dn_per_e : float or None
        Conversion gain DN per electron; None: (2^bits − 1)/full_well_e (the full well fills
        the range).
    display_gamma : float or None
        Display response radiance ∝ black + (1 − black)·d^γ for commanded level d ∈ [0, 1].
    display_black_level : float
        Black level as a fraction of white (1 / contrast), in [0, 1).
    linearise : bool
        The evaluation linearises the images with the response measured from a simulated
        grey-level series (``grey_levels`` uniform screens through the same sensor model).
    grey_levels : int
        Number of levels of that series (≥ 3).
    emission_exponent : float or None
        Screen radiance falls off with the viewing angle θ (from the screen normal) as cos^m θ.
    screen_pixel_pitch_mm : float or None
        Screen pixel pitch; switches the pixel structure (sample-and-hold, black matrix) on.
    screen_fill_factor : float
        Emitting fraction of a screen pixel's area, in (0, 1].
    f_number : float or None
        Lens f-number; switches defocus on: a thin lens whose entrance pupil is a uniform disc
        of diameter focal_length_mm / f_number at the pinhole, with one plane of sharp focus.
    focal_length_mm : float
        Lens focal length (the aperture diameter is focal_length_mm / f_number).
    pixel_area : bool
        Integrate the pattern over each camera pixel's footprint (box of one pixel).
    focus_distance_mm : float or None
        Distance (mm, along the optical axis from the pinhole) of the plane of sharp focus,
        perpendicular to the optical axis (issue 20). None: per camera, the axial distance of the
        sample point seen by the principal point.
    display_levels : int or None
        The commanded pattern is rounded to this many display levels (e.g. 256 for an 8-bit
        display) before the response; None: continuous levels (issue 20).
    lcd_mode, lcd_retardation_nm, lcd_indices, lcd_rubbing_deg, lcd_wavelength_nm
        The LCD's viewing-angle model (``lcd_mode = "ips"``; None: off): :mod:`pmdsim.setup.lcd`.
    sampling_step_px : int
        The simulated cameras sample every K-th pixel of the real sensor (K × K fewer pixels of the
        same camera, issue 20): pixel-area integration is over the real pixel, 1/K of the sampling
        step; full well and noise are the real pixel's. :meth:`Setup.binned` multiplies it by
        the binning factor (``--downsample K``). Default 1.
    """

    bit_depth: int | None = None
    full_well_e: float | None = None
    exposure: float = 0.8
    read_noise_e: float = 0.0
    dark_offset_dn: float = 0.0
    gain_dn_per_e: float | None = None
    display_gamma: float | None = None
    display_black_level: float = 0.0
    linearise: bool = False
    grey_levels: int = 17
    emission_exponent: float | None = None
    screen_pixel_pitch_mm: float | None = None
    screen_fill_factor: float = 1.0
    f_number: float | None = None
    focal_length_mm: float = 25.0
    pixel_area: bool = False
    focus_distance_mm: float | None = None
    sampling_step_px: int = 1
    display_levels: int | None = None
    lcd_mode: str | None = None
    lcd_retardation_nm: float = LCD_DEFAULTS["lcd_retardation_nm"]
    lcd_indices: tuple[float, float] = LCD_DEFAULTS["lcd_indices"]
    lcd_rubbing_deg: float = LCD_DEFAULTS["lcd_rubbing_deg"]
    lcd_wavelength_nm: float = LCD_DEFAULTS["lcd_wavelength_nm"]

    def __post_init__(self) -> None:
        def num(name, lo=None, lo_open=False, hi=None, hi_open=False, optional=False):
            v = getattr(self, name)
            if v is None and optional:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise SetupError(f"imaging.{name} must be a finite number, got {v!r}")
            if lo is not None and (v <= lo if lo_open else v < lo):
                raise SetupError(f"imaging.{name} must be {'>' if lo_open else '≥'} {lo}, got {v!r}")
            if hi is not None and (v >= hi if hi_open else v > hi):
                raise SetupError(f"imaging.{name} must be {'<' if hi_open else '≤'} {hi}, got {v!r}")

        if self.bit_depth is not None and (isinstance(self.bit_depth, bool) or self.bit_depth not in (8, 10, 12, 16)):
            raise SetupError(f"imaging.bit_depth must be one of [8, 10, 12, 16], got {self.bit_depth!r}")
        num("full_well_e", 0, True, optional=True)
        num("exposure", 0, True)
        num("read_noise_e", 0)
        num("dark_offset_dn", 0)
        num("gain_dn_per_e", 0, True, optional=True)
        num("display_gamma", 0, True, optional=True)
        num("display_black_level", 0, False, 1, True)
        num("emission_exponent", 0, optional=True)
        num("screen_pixel_pitch_mm", 0, True, optional=True)
        num("screen_fill_factor", 0, True, 1)
        num("f_number", 0, True, optional=True)
        num("focal_length_mm", 0, True)
        num("focus_distance_mm", 0, True, optional=True)
        for name in ("linearise", "pixel_area"):
            if not isinstance(getattr(self, name), bool):
                raise SetupError(f"imaging.{name} must be true or false, got {getattr(self, name)!r}")
        if (isinstance(self.sampling_step_px, bool) or not isinstance(self.sampling_step_px, int)
                or self.sampling_step_px < 1):
            raise SetupError(f"imaging.sampling_step_px must be an integer ≥ 1, got {self.sampling_step_px!r}")
        if self.display_levels is not None and (isinstance(self.display_levels, bool)
                                                or not isinstance(self.display_levels, int) or self.display_levels < 2):
            raise SetupError(f"imaging.display_levels must be an integer ≥ 2, got {self.display_levels!r}")
        if isinstance(self.grey_levels, bool) or not isinstance(self.grey_levels, int) or self.grey_levels < 3:
            raise SetupError(f"imaging.grey_levels must be an integer ≥ 3, got {self.grey_levels!r}")
        validate_lcd(self)

    @property
    def any_on(self) -> bool:
        """True if any effect changes the images (False: the ideal renderer's images)."""
        return any((self.bit_depth is not None, self.full_well_e is not None, self.display_gamma is not None,
                    self.emission_exponent is not None, self.screen_pixel_pitch_mm is not None,
                    self.f_number is not None, self.pixel_area, self.display_levels is not None,
                    self.lcd_mode is not None))

    def with_(self, **changes: Any) -> "ImagingSetup":
        """The same effects with some values changed (validated)."""
        return replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """The ``[imaging]`` table: only values that differ from the defaults."""
        default = ImagingSetup()
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) != getattr(default, f.name)}


@dataclass(frozen=True)
class CalibrationSetup:
    """The calibration mirror poses (paper §4): a planar front-surface mirror lying on the base
    table (the sample's pose), lifted parallel to it, and tilted about its x and y axes.

    The paper gives no values; the defaults keep every camera's reflected field of view on the
    screen (tilting the mirror by θ turns the reflected rays by 2θ; the screens' margins around
    the cameras' reflected views are ≈ 70 mm at ≈ 500 mm distance, i.e. |θ| ≲ 4°).

    Attributes
    ----------
    mirror_lifts_mm : lifts of the mirror, parallel to the table, towards the cameras (along the
        sample's −z, since the sample's +z points away from the cameras).
    mirror_tilts_deg : tilt magnitudes; each is applied with + and − sign about the mirror's
        x axis and about its y axis, through the centre of the mirror.
    mirror_size_mm : (width, height) of the mirror, centred on the sample's grid centre.
    observation_stride_px : the calibration uses every stride-th pixel in both directions.
    mirror_sag_um : flatness error of the mirror (beyond the paper, which assumes a perfect
        plane): a paraboloid of revolution (power, the dominant form error of a polished flat),
        z_mirror = −s·(1 − r²/ρ²) with s = ``mirror_sag_um`` (in mm: s/1000), r the distance
        from the mirror's centre and ρ half its smaller side. Positive: the centre stands s
        closer to the cameras than the edge midpoints (convex as seen from the cameras; the
        mirror frame's +z points away from them, like the sample's). 0: a perfect plane.
    fit_glass_thickness, fit_glass_index : estimate the screen's cover-glass thickness / index
        in ``pmdsim calibrate`` (start: ``[screen] cover_glass_thickness_mm`` / ``cover_glass_index``;
        docs/conventions.md "Cover glass"). Without them a declared glass is held.
    """

    mirror_lifts_mm: tuple[float, ...] = (10.0, 20.0, 30.0)
    mirror_tilts_deg: tuple[float, ...] = (1.0, 2.0, 3.0)
    mirror_size_mm: tuple[float, float] = (400.0, 400.0)
    observation_stride_px: int = 8
    mirror_sag_um: float = 0.0
    fit_glass_thickness: bool = False
    fit_glass_index: bool = False

    def __post_init__(self) -> None:
        sag = self.mirror_sag_um
        if isinstance(sag, bool) or not isinstance(sag, (int, float)) or not math.isfinite(sag):
            raise SetupError(f"calibration.mirror_sag_um must be a finite number (µm), got {sag!r}")
        if abs(sag) * 1e-3 >= 0.05 * min(self.mirror_size_mm):
            raise SetupError(f"calibration.mirror_sag_um must be small against the mirror (< 5 % of its "
                             f"{min(self.mirror_size_mm):g} mm side, i.e. a flat with a form error), got {sag} µm")

    def mirror_poses(self, sample: "SampleSetup") -> list[tuple[str, RigidTransform]]:
        """(label, T_world_mirror) of every pose: base, lifts, then tilts (+/− about x, then y).

        The mirror is the plane z = 0 of its frame over [0, w] × [0, h].
        """
        T_ws = sample.T_world_sample
        cx = 0.5 * (sample.grid_x_mm[0] + sample.grid_x_mm[-1])
        cy = 0.5 * (sample.grid_y_mm[0] + sample.grid_y_mm[-1])
        w, h = self.mirror_size_mm
        # Mirror frame: origin at its corner, centre on the sample's grid centre.
        T_centre_mirror = RigidTransform(np.eye(3), [-w / 2, -h / 2, 0.0])
        T_sample_centre = RigidTransform(np.eye(3), [cx, cy, 0.0])
        out = [("base", T_ws @ T_sample_centre @ T_centre_mirror)]
        for lift in self.mirror_lifts_mm:
            out.append((f"lift_{lift:g}mm", T_ws @ RigidTransform(np.eye(3), [cx, cy, -lift]) @ T_centre_mirror))
        for axis, angles in (("x", lambda t: (t, 0.0, 0.0)), ("y", lambda t: (0.0, t, 0.0))):
            for tilt in self.mirror_tilts_deg:
                for sign in (1.0, -1.0):
                    R = RigidTransform.from_origin_angles([0.0, 0.0, 0.0], angles(sign * tilt))
                    out.append((f"tilt_{axis}{sign * tilt:+g}deg", T_ws @ T_sample_centre @ R @ T_centre_mirror))
        return out

    def mirror_grid(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[tuple[float, ...], ...] | None]:
        """(grid_x_mm, grid_y_mm, heights_mm) of the mirror in its frame; heights None for a plane.

        With a sag the grid is 3 × 3: the not-a-knot spline through it reproduces the
        paraboloid z = −s·(1 − r²/ρ²) exactly (it lies in span{1, x, x²} ⊗ span{1, y, y²}).
        """
        w, h = self.mirror_size_mm
        if self.mirror_sag_um == 0.0:
            return (0.0, w), (0.0, h), None
        s = self.mirror_sag_um * 1e-3
        rho2 = (0.5 * min(w, h)) ** 2
        gx, gy = (0.0, 0.5 * w, w), (0.0, 0.5 * h, h)
        z = tuple(tuple(-s * (1.0 - ((x - 0.5 * w) ** 2 + (y - 0.5 * h) ** 2) / rho2) for x in gx) for y in gy)
        return gx, gy, z

    def mirror_surface(self):
        """The mirror in its frame: a plane over [0, w] × [0, h], or the sagged spline surface."""
        from ..geometry.surface import PlaneSurface, SplineSurface

        gx, gy, z = self.mirror_grid()
        if z is None:
            return PlaneSurface(gx, gy)
        return SplineSurface(gx, gy, np.array(z))


@dataclass(frozen=True)
class Setup:
    """A complete measurement setup (paper §2, Table 1)."""

    cameras: dict[str, CameraSetup]
    screen: ScreenSetup
    sample: SampleSetup
    patterns: PatternSetup
    calibration: CalibrationSetup = field(default_factory=CalibrationSetup)
    imaging: ImagingSetup | None = None
    # The calibrated parameters' covariance (setup/covariance.py; None: not calibrated).
    calibration_covariance: CalibrationCovariance | None = None

    def __post_init__(self) -> None:
        # cameras: an immutable mapping (issue 23) so that the setup is deeply immutable and hashable
        if not isinstance(self.cameras, FrozenMap):
            object.__setattr__(self, "cameras", FrozenMap(self.cameras))
        if self.calibration_covariance is not None:
            self.calibration_covariance.check_setup(self)

    def with_calibration_covariance(self, covariance: CalibrationCovariance | None) -> "Setup":
        """The same setup carrying ``covariance`` (:class:`~pmdsim.setup.covariance.CalibrationCovariance`;
        None: none)."""
        return replace(self, calibration_covariance=covariance)

    def with_camera(self, name: str, **changes: Any) -> "Setup":
        """The same setup with one camera's intrinsics or pose changed.

        Keywords are the setup file's keys (units in the names): ``image_size_px`` (w, h),
        ``focal_length_px`` (fx, fy), ``principal_point_px`` (ppx, ppy), ``distortion``
        (a mapping with any of k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4), ``origin_world_mm`` and
        ``angles_deg``;
        or :class:`~pmdsim.geometry.camera.Camera` field names (``fx_px``, ``k1``, …).

        >>> s = default_setup().with_camera("left", focal_length_px=(4410, 4410))
        """
        if name not in self.cameras:
            raise SetupError(f"no camera {name!r} in the setup (cameras: {', '.join(self.cameras)})")
        cs = self.cameras[name]
        cam_changes: dict[str, Any] = {}
        pose_changes: dict[str, Any] = {}
        pairs = {"image_size_px": ("width_px", "height_px"), "focal_length_px": ("fx_px", "fy_px"),
                 "principal_point_px": ("ppx_px", "ppy_px")}
        cam_fields = {f.name for f in fields(Camera)}
        for key, value in changes.items():
            if key in pairs:
                v = tuple(value)
                if len(v) != 2:
                    raise SetupError(f"cameras.{name}.{key} must have 2 entries, got {value!r}")
                cam_changes.update(zip(pairs[key], v))
            elif key == "distortion":
                bad = set(value) - set(DISTORTION_NAMES)
                if bad:
                    raise SetupError(f"cameras.{name}.distortion: unknown coefficient(s) {sorted(bad)}; "
                                     f"expected {', '.join(DISTORTION_NAMES)}")
                cam_changes.update({k: float(v) for k, v in value.items()})
            elif key in ("origin_world_mm", "angles_deg"):
                v = tuple(float(x) for x in value)
                if len(v) != 3:
                    raise SetupError(f"cameras.{name}.{key} must have 3 entries, got {value!r}")
                pose_changes[key] = v
            elif key in cam_fields:
                cam_changes[key] = value
            else:
                raise SetupError(f"cameras.{name}: unknown key {key!r} (expected image_size_px, focal_length_px, "
                                 f"principal_point_px, distortion, origin_world_mm, angles_deg or a Camera field)")
        try:
            camera = replace(cs.camera, **cam_changes)
        except ValueError as e:
            raise SetupError(f"cameras.{name}: {e}") from None
        pose = replace(cs.pose, **pose_changes)
        return replace(self, cameras={**self.cameras, name: CameraSetup(camera, pose)})

    def with_cameras(self, cameras: dict[str, "CameraSetup"]) -> "Setup":
        """The same setup with the cameras replaced (a mapping name → :class:`CameraSetup`)."""
        if not cameras:
            raise SetupError("cameras must define at least one camera")
        return replace(self, cameras=dict(cameras))

    def with_patterns(self, **changes: Any) -> "Setup":
        """The same setup with fringe or image-formation values changed: ``n_shifts``,
        ``periods_x_mm``, ``periods_y_mm``, ``mean_level``, ``amplitude`` (the fringe sequence)
        and ``bit_depth``, ``noise_std``, ``seed``."""
        seq_keys = {"n_shifts", "periods_x_mm", "periods_y_mm", "mean_level", "amplitude"}
        pat_keys = {"bit_depth", "noise_std", "seed"}
        bad = set(changes) - seq_keys - pat_keys
        if bad:
            raise SetupError(f"patterns: unknown key(s) {sorted(bad)} (expected {sorted(seq_keys | pat_keys)})")
        try:
            seq = replace(self.patterns.sequence, **{k: v for k, v in changes.items() if k in seq_keys})
        except ValueError as e:
            raise SetupError(f"patterns: {e}") from None
        pat = replace(self.patterns, sequence=seq, **{k: v for k, v in changes.items() if k in pat_keys})
        return replace(self, patterns=pat)

    def binned(self, factor: int) -> "Setup":
        """The setup with every camera binned ``factor`` × ``factor`` (the same field of view;
        see :meth:`~pmdsim.geometry.camera.Camera.binned`). ``factor`` 1 returns the setup."""
        if isinstance(factor, bool) or int(factor) != factor or factor < 1:
            raise SetupError(f"binning factor must be an integer ≥ 1, got {factor!r}")
        if factor == 1:
            return self
        try:
            cams = {n: CameraSetup(cs.camera.binned(int(factor)), cs.pose) for n, cs in self.cameras.items()}
        except ValueError as e:
            raise SetupError(f"cannot bin the cameras {factor} × {factor}: {e}") from None
        # Fewer pixels of the same camera: image formation keeps the real pixel (issue 20).
        im = None if self.imaging is None else self.imaging.with_(
            sampling_step_px=self.imaging.sampling_step_px * int(factor))
        cov = None if self.calibration_covariance is None else self.calibration_covariance.binned(int(factor))
        return replace(self, cameras=cams, imaging=im, calibration_covariance=cov)

    def with_bulge(self, bulge_mm: float) -> "Setup":
        """The same setup with the screen's central control height set to ``bulge_mm`` (Δh)."""
        if not math.isfinite(bulge_mm):
            raise SetupError(f"--bulge-mm / screen.bulge_mm must be finite, got {bulge_mm!r}")
        nx, ny = len(self.screen.grid_x_mm), len(self.screen.grid_y_mm)
        if nx % 2 == 0 or ny % 2 == 0:
            raise SetupError(
                f"screen.bulge_mm needs an odd number of grid lines in screen.grid_x_mm and "
                f"screen.grid_y_mm (a central control point), got {nx} × {ny}"
            )
        return replace(self, screen=replace(self.screen, bulge_mm=float(bulge_mm)))

    def with_cover_glass(self, thickness_mm: float, index: float | None = None) -> "Setup":
        """The same setup with the screen's cover glass set (docs/conventions.md, "Cover glass");
        ``index`` None keeps the screen's index (1.5 if it had none)."""
        n = self.screen.cover_glass_index if index is None else float(index)
        return replace(self, screen=replace(self.screen, cover_glass_thickness_mm=float(thickness_mm),
                                            cover_glass_index=n))

    def with_screen_heights(self, grid_x_mm, grid_y_mm, heights_mm) -> "Setup":
        """The same setup with the screen's control grid and full (n_y, n_x) height matrix
        replaced (no bulge override); the screen's pose is kept."""
        gx = tuple(float(v) for v in grid_x_mm)
        gy = tuple(float(v) for v in grid_y_mm)
        z = np.asarray(heights_mm, dtype=float)
        if z.shape != (len(gy), len(gx)):
            raise SetupError(f"screen.heights_mm must have shape (len(grid_y_mm), len(grid_x_mm)) = "
                             f"({len(gy)}, {len(gx)}), got {z.shape}")
        if not np.isfinite(z).all():
            raise SetupError("screen.heights_mm must be finite")
        scr = replace(self.screen, grid_x_mm=gx, grid_y_mm=gy, heights_mm=tuple(tuple(float(v) for v in r) for r in z),
                      bulge_mm=None)
        scr.surface  # validate the grid now (raises with the problem)
        return replace(self, screen=scr)

    def with_sample_shape(self, shape: "SampleShape | str | None", **params: Any) -> "Setup":
        """The same setup with an analytic sample shape (docs/conventions.md, "Curved samples").

        ``shape`` is a :class:`~pmdsim.setup.sample_shape.SampleShape`, or its kind with the
        ``[sample]`` keys as keywords; None makes the sample a plane again. The pose and the
        grid (the shape's bounds) are kept.

        >>> s = default_setup().with_sample_shape("sphere", radius_mm=1000.0)
        """
        if shape is not None and not isinstance(shape, SampleShape):
            shape = SampleShape(str(shape), **params)
        elif params:
            raise SetupError(f"with_sample_shape: keywords {sorted(params)} need a shape name, not a SampleShape")
        smp = replace(self.sample, heights_mm=None, shape=shape)
        smp.surface  # validate now (a radius too small for the grid raises here)
        return replace(self, sample=smp)

    def with_sample_height_map(self, data: "HeightMapData", source: "HeightMapSource | None" = None, *,
                               grid_x_mm=None, grid_y_mm=None, max_error_um: float | None = None) -> "Setup":
        """The same setup with the sample's heights resampled from a height map.

        ``data`` (:class:`~pmdsim.setup.sample_shape.HeightMapData`, e.g. from
        :func:`pmdsim.io.heightmap.read_height_map`) is resampled onto the sample's spline grid
        (or ``grid_x_mm`` × ``grid_y_mm``); ``sample.interpolation_report`` then holds the
        error. Raises SetupError for a map that does not cover the grid or is coarser than it,
        or that the grid misses by more than ``max_error_um`` (default: the source's
        ``max_error_um``, 1 µm).
        """
        gx = tuple(float(v) for v in (self.sample.grid_x_mm if grid_x_mm is None else grid_x_mm))
        gy = tuple(float(v) for v in (self.sample.grid_y_mm if grid_y_mm is None else grid_y_mm))
        src = source if source is not None else HeightMapSource(data.source)
        if max_error_um is not None:
            src = replace(src, max_error_um=max_error_um)
        heights, report = resample_height_map(data, gx, gy, src.max_error_um)
        src = src.with_report(report)
        z = tuple(tuple(float(v) for v in row) for row in heights)
        return replace(self, sample=replace(self.sample, grid_x_mm=gx, grid_y_mm=gy, heights_mm=z, shape=src))

    def with_mirror_sag(self, sag_um: float) -> "Setup":
        """The same setup with a calibration mirror of sag ``sag_um`` (see :class:`CalibrationSetup`)."""
        return replace(self, calibration=replace(self.calibration, mirror_sag_um=sag_um))  # validated there

    def with_mirror_pose(self, index: int) -> "Setup":
        """The setup with the sample replaced by the calibration mirror in pose ``index``."""
        poses = self.calibration.mirror_poses(self.sample)
        if not 0 <= index < len(poses):
            raise SetupError(f"calibration pose index must be in 0 … {len(poses) - 1}, got {index}")
        gx, gy, z = self.calibration.mirror_grid()
        return replace(self, sample=SampleSetup(Pose.from_transform(poses[index][1]), gx, gy, z))

    def with_imaging(self, imaging: "ImagingSetup | None" = None, **changes: Any) -> "Setup":
        """The same setup with image-formation effects (:class:`ImagingSetup`; None = none);
        keywords change single values of the current (or default) effects."""
        base = imaging if imaging is not None else (self.imaging if changes and self.imaging is not None
                                                     else ImagingSetup())
        if imaging is None and not changes:
            return replace(self, imaging=None)
        try:
            new = replace(base, **changes)
        except TypeError as e:
            raise SetupError(f"imaging: {e}") from None
        return replace(self, imaging=new)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (the TOML document's content)."""
        cams = {}
        for name, cs in self.cameras.items():
            c = cs.camera
            cams[name] = {
                "image_size_px": [c.width_px, c.height_px],
                "focal_length_px": [c.fx_px, c.fy_px],
                "principal_point_px": [c.ppx_px, c.ppy_px],
                "distortion": {"k1": c.k1, "k2": c.k2, "p1": c.p1, "p2": c.p2, "k3": c.k3,
                               **{k: getattr(c, k) for k in DISTORTION_NAMES[5:] if getattr(c, k) != 0.0}},
                "origin_world_mm": list(cs.pose.origin_world_mm),
                "angles_deg": list(cs.pose.angles_deg),
            }
        scr: dict[str, Any] = {
            "origin_world_mm": list(self.screen.pose.origin_world_mm),
            "angles_deg": list(self.screen.pose.angles_deg),
            "grid_x_mm": list(self.screen.grid_x_mm),
            "grid_y_mm": list(self.screen.grid_y_mm),
        }
        if self.screen.heights_mm is not None:  # with the bulge applied: the file's two keys then agree
            scr["heights_mm"] = [[float(v) for v in r] for r in self.screen.control_heights()]
        if self.screen.bulge_mm is not None:
            scr["bulge_mm"] = self.screen.bulge_mm
        if self.screen.cover_glass_thickness_mm > 0 or self.screen.cover_glass_index is not None:
            scr["cover_glass_thickness_mm"] = self.screen.cover_glass_thickness_mm
            scr["cover_glass_index"] = self.screen.cover_glass.index
        smp: dict[str, Any] = {
            "origin_world_mm": list(self.sample.pose.origin_world_mm),
            "angles_deg": list(self.sample.pose.angles_deg),
            "grid_x_mm": list(self.sample.grid_x_mm),
            "grid_y_mm": list(self.sample.grid_y_mm),
        }
        if self.sample.heights_mm is not None:
            smp["heights_mm"] = [list(r) for r in self.sample.heights_mm]
        if isinstance(self.sample.shape, SampleShape):
            smp.update(self.sample.shape.as_dict())
        elif isinstance(self.sample.shape, HeightMapSource):  # a record: the heights above are used
            smp["height_map_source"] = self.sample.shape.as_dict()
        seq = self.patterns.sequence
        pat = {
            "n_shifts": seq.n_shifts,
            "periods_x_mm": list(seq.periods_x_mm),
            "periods_y_mm": list(seq.periods_y_mm),
            "mean_level": seq.mean_level,
            "amplitude": seq.amplitude,
            "bit_depth": self.patterns.bit_depth,
            "noise_std": self.patterns.noise_std,
            "seed": self.patterns.seed,
        }
        cal = self.calibration
        return {
            "format": SETUP_FORMAT,
            "format_version": SETUP_FORMAT_VERSION,
            "cameras": cams,
            "screen": scr,
            "sample": smp,
            "patterns": pat,
            "calibration": {
                "mirror_lifts_mm": list(cal.mirror_lifts_mm),
                "mirror_tilts_deg": list(cal.mirror_tilts_deg),
                "mirror_size_mm": list(cal.mirror_size_mm),
                "observation_stride_px": cal.observation_stride_px,
                "mirror_sag_um": cal.mirror_sag_um,
                **({"fit_glass_thickness": True} if cal.fit_glass_thickness else {}),
                **({"fit_glass_index": True} if cal.fit_glass_index else {}),
            },
            **({"imaging": self.imaging.as_dict()} if self.imaging is not None else {}),
            **({"calibration_report": self.calibration_covariance.as_dict()}
               if self.calibration_covariance is not None else {}),
        }

    def to_toml(self) -> str:
        """TOML text that :func:`parse_setup` reads back to an equal setup, with unit comments."""
        from .toml import dump_toml

        return dump_toml(self.to_dict())


# ============================================================================ default (Table 1)
def default_setup() -> Setup:
    """The paper's Table 1 setup with a planar screen (Δh = 0).

    Values not in Table 1 (documented in docs/conventions.md and the README): the sample's
    extent (a 400 × 400 mm plane centred on the world origin, which contains both cameras'
    fields of view), and the fringe sequence (N = 4 shifts, three periods per direction).
    """
    cam = Camera(1920, 1200, 4400.0, 4400.0, 960.0, 600.0)
    return Setup(
        cameras={
            "left": CameraSetup(cam, Pose((-90.0, 295.0, -295.0), (45.0, 10.0, 10.0))),
            "right": CameraSetup(cam, Pose((90.0, 295.0, -295.0), (45.0, -10.0, -10.0))),
        },
        screen=ScreenSetup(
            Pose((-354.0, -78.0, -400.0), (135.0, 0.0, 0.0)),
            (0.0, 354.0, 708.0),
            (0.0, 199.0, 398.0),
            None,
            0.0,
        ),
        sample=SampleSetup(Pose((-200.0, -200.0, 0.0), (0.0, 0.0, 0.0)), (0.0, 400.0), (0.0, 400.0)),
        patterns=PatternSetup(
            FringeSequence((720.0, 48.0, 2.0), (420.0, 28.0, 2.0), n_shifts=4, mean_level=0.5, amplitude=0.45),
            bit_depth=8,
            noise_std=0.0,
            seed=0,
        ),
    )
