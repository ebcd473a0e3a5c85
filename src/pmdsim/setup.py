"""Measurement setups: cameras, pattern screen, sample and their poses, as data (TOML).

The paper's Table 1 is built in (:func:`default_setup`). A setup is written and read as TOML
(:meth:`Setup.to_toml`, :func:`load_setup`, :func:`parse_setup`); every value is validated and
an invalid setup raises :class:`~pmdsim.errors.SetupError` naming the key and the problem.
Units are in the key names (mm, deg, px); conventions in docs/conventions.md.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from .camera import Camera
from .errors import SetupError
from .patterns import FringeSequence
from .surface import SplineSurface
from .transform import RigidTransform

__all__ = [
    "Pose",
    "CameraSetup",
    "ScreenSetup",
    "SampleSetup",
    "PatternSetup",
    "Setup",
    "default_setup",
    "parse_setup",
    "load_setup",
    "SETUP_FORMAT",
]

SETUP_FORMAT = "pmdsim-setup"
SETUP_FORMAT_VERSION = 1


# ============================================================================ value objects
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
    """The sample: a spline surface (a plane when all heights are 0) and its pose."""

    pose: Pose
    grid_x_mm: tuple[float, ...]
    grid_y_mm: tuple[float, ...]
    heights_mm: tuple[tuple[float, ...], ...] | None = None

    @cached_property
    def surface(self) -> SplineSurface:
        ny, nx = len(self.grid_y_mm), len(self.grid_x_mm)
        z = np.zeros((ny, nx)) if self.heights_mm is None else np.array(self.heights_mm, dtype=float)
        return SplineSurface(self.grid_x_mm, self.grid_y_mm, z)

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
    """

    mirror_lifts_mm: tuple[float, ...] = (10.0, 20.0, 30.0)
    mirror_tilts_deg: tuple[float, ...] = (1.0, 2.0, 3.0)
    mirror_size_mm: tuple[float, float] = (400.0, 400.0)
    observation_stride_px: int = 8
    mirror_sag_um: float = 0.0

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
        from .surface import PlaneSurface, SplineSurface

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

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (the TOML document's content)."""
        cams = {}
        for name, cs in self.cameras.items():
            c = cs.camera
            cams[name] = {
                "image_size_px": [c.width_px, c.height_px],
                "focal_length_px": [c.fx_px, c.fy_px],
                "principal_point_px": [c.ppx_px, c.ppy_px],
                "distortion": {"k1": c.k1, "k2": c.k2, "p1": c.p1, "p2": c.p2, "k3": c.k3},
                "origin_world_mm": list(cs.pose.origin_world_mm),
                "angles_deg": list(cs.pose.angles_deg),
            }
        scr: dict[str, Any] = {
            "origin_world_mm": list(self.screen.pose.origin_world_mm),
            "angles_deg": list(self.screen.pose.angles_deg),
            "grid_x_mm": list(self.screen.grid_x_mm),
            "grid_y_mm": list(self.screen.grid_y_mm),
        }
        if self.screen.heights_mm is not None:
            scr["heights_mm"] = [list(r) for r in self.screen.heights_mm]
        if self.screen.bulge_mm is not None:
            scr["bulge_mm"] = self.screen.bulge_mm
        smp: dict[str, Any] = {
            "origin_world_mm": list(self.sample.pose.origin_world_mm),
            "angles_deg": list(self.sample.pose.angles_deg),
            "grid_x_mm": list(self.sample.grid_x_mm),
            "grid_y_mm": list(self.sample.grid_y_mm),
        }
        if self.sample.heights_mm is not None:
            smp["heights_mm"] = [list(r) for r in self.sample.heights_mm]
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
            },
        }

    def to_toml(self) -> str:
        """TOML text that :func:`parse_setup` reads back to an equal setup, with unit comments."""
        return _dump_toml(self.to_dict())


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


# ============================================================================ parsing
#: The keys each table of a setup file may hold (for typo hints in error messages).
_KNOWN_KEYS = {
    "": ("format", "format_version", "cameras", "screen", "sample", "patterns", "calibration", "calibration_report"),
    "camera": ("image_size_px", "focal_length_px", "principal_point_px", "distortion", "origin_world_mm", "angles_deg"),
    "distortion": ("k1", "k2", "p1", "p2", "k3"),
    "screen": ("origin_world_mm", "angles_deg", "grid_x_mm", "grid_y_mm", "heights_mm", "bulge_mm"),
    "sample": ("origin_world_mm", "angles_deg", "grid_x_mm", "grid_y_mm", "heights_mm"),
    "patterns": ("n_shifts", "periods_x_mm", "periods_y_mm", "mean_level", "amplitude", "bit_depth", "noise_std",
                 "seed"),
    "calibration": ("mirror_lifts_mm", "mirror_tilts_deg", "mirror_size_mm", "observation_stride_px", "mirror_sag_um"),
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


def _camera(r: _Reader) -> CameraSetup:
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
    dist = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0}
    if r.has("distortion"):
        d = r.table_("distortion", "distortion")
        for k in dist:
            dist[k] = d.number(k, 0.0)
        d.finish()
    else:
        r.used.add("distortion")
    cam = Camera(size[0], size[1], f[0], f[1], pp[0], pp[1], **dist)
    pose = _pose(r)
    r.finish()
    return CameraSetup(cam, pose)


def parse_setup(doc: dict[str, Any], *, source: str = "setup") -> Setup:
    """Validate a setup document (parsed TOML) and build the :class:`Setup`.

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
        cameras[name] = _camera(cams_r.table_(name, "camera"))

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
    s.finish()
    screen = ScreenSetup(screen_pose, gx, gy, heights, bulge)

    m = r.table_("sample")
    sample_pose = _pose(m)
    sgx = m.grid("grid_x_mm")
    sgy = m.grid("grid_y_mm")
    sh = m.matrix("heights_mm", (len(sgy), len(sgx))) if m.has("heights_mm") else None
    m.used.add("heights_mm")
    m.finish()
    sample = SampleSetup(sample_pose, sgx, sgy, sh)

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
        c.finish()
        calibration = CalibrationSetup(lifts, tilts, (size[0], size[1]), stride, sag)
    else:
        r.used.add("calibration")
        calibration = dc
    r.used.add("calibration_report")  # informational table written by `pmdsim calibrate`
    r.finish()
    setup = Setup(cameras, screen, sample, patterns, calibration)
    try:  # build the surfaces now so that any remaining problem shows here, with its key
        setup.screen.surface
    except ValueError as e:
        raise SetupError(f"screen: {e}") from None
    try:
        setup.sample.surface
    except ValueError as e:
        raise SetupError(f"sample: {e}") from None
    return setup


def load_setup(path: str | Path) -> Setup:
    """Read and validate a setup TOML file (see :func:`parse_setup`)."""
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
        return parse_setup(doc, source=str(p))
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
    "so a positive bulge is concave as seen from the sample.",
    "sample": "Sample surface: a plane unless heights_mm (len(grid_y_mm) × len(grid_x_mm)) is given.",
    "calibration": "Calibration mirror poses (paper §4): base = the sample's pose; lifts towards the cameras;\n"
    "each tilt applied +/− about the mirror's x and y axes through its centre; 1 + lifts + 4·tilts poses.\n"
    "mirror_sag_um: the mirror's flatness error, a paraboloid −s·(1 − r²/ρ²) (ρ = half the smaller side;\n"
    "+ = centre towards the cameras); 0 = a perfect plane, as the paper assumes.",
    "patterns": "Fringes I_k = A + B·cos(2π·c/p − 2πk/N); mean_level A and amplitude B are fractions of full scale;\n"
    "periods coarsest first (the coarsest must cover the screen); noise_std in grey levels.",
}


def _fmt_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError("TOML setup values must be finite")
        return repr(v)
    if isinstance(v, str):
        out = v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
        # Any other control character as \uXXXX (TOML basic strings allow none of them raw).
        return '"' + "".join(f"\\u{ord(ch):04x}" if ord(ch) < 0x20 or ord(ch) == 0x7F else ch for ch in out) + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_fmt_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _dump_toml(doc: dict[str, Any]) -> str:
    lines: list[str] = []

    def comment(key: str) -> None:
        if key in _COMMENTS:
            lines.extend("# " + c for c in _COMMENTS[key].splitlines())

    def inline(path: str, v: Any) -> bool:
        # Plain values, and small tables of plain values inside a table (e.g. distortion).
        return not isinstance(v, dict) or (bool(path) and not any(isinstance(x, dict) for x in v.values()))

    def table(path: str, tbl: dict[str, Any]) -> None:
        values = {k: v for k, v in tbl.items() if inline(path, v)}
        if path:
            lines.append("")
            comment(path)
            if values:
                lines.append(f"[{path}]")
        for k, v in values.items():
            lines.append(f"{k} = {_fmt_value(v)}")
        for k, v in tbl.items():
            if k not in values:
                table(f"{path}.{k}" if path else k, v)

    comment("")
    table("", doc)
    return "\n".join(lines) + "\n"
