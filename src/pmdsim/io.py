"""File input and output: atomic output directories, images, manifests, HDF5 mappings.

Everything pmdsim writes records the pmdsim version and the command/setup that produced it.
Outputs are written atomically: a run writes into a hidden temporary directory next to the
target and renames it into place at the end, so an interrupted run leaves no half-written
output; an existing output is replaced only with ``force``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np
from PIL import Image

from . import __version__
from .errors import ImageSetError, OutputExistsError

#: HDF5 filters for float maps: byte shuffle + gzip level 1 (standard filters any HDF5 reader
#: decodes; the shuffle makes float maps ≈ 25 % smaller and faster to write than gzip alone).
_GZIP_FLOAT = dict(compression="gzip", compression_opts=1, shuffle=True)

__all__ = [
    "atomic_output_dir",
    "atomic_file",
    "write_png",
    "read_image",
    "write_json",
    "provenance",
    "MANIFEST_NAME",
    "MAPPING_NAME",
]

MANIFEST_NAME = "manifest.json"
MAPPING_NAME = "mapping.h5"
IMAGESET_FORMAT = "pmdsim-imageset"


def provenance(command: str | None = None, setup_toml: str | None = None) -> dict[str, Any]:
    """What produced an output: pmdsim version, command line, and the setup as TOML."""
    return {
        "pmdsim_version": __version__,
        "command": command if command is not None else " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
        "setup_toml": setup_toml,
    }


def _check_target(target: Path, force: bool) -> None:
    if target.exists() and not force:
        raise OutputExistsError(f"output {str(target)!r} exists; pass --force to replace it")
    if target.exists() and not target.is_dir() and target.suffix == "":
        raise OutputExistsError(f"output {str(target)!r} exists and is not a directory")


@contextlib.contextmanager
def atomic_output_dir(target: str | Path, *, force: bool = False) -> Iterator[Path]:
    """Context manager yielding a temporary directory that becomes ``target`` on success.

    On an exception (including KeyboardInterrupt) the temporary directory is removed and an
    existing ``target`` is left untouched.
    """
    target = Path(target)
    if target.name in ("", ".", "..") or Path.cwd().resolve().is_relative_to(target.resolve()):
        raise OutputExistsError(
            f"output {str(target)!r} is the current directory or one of its parents; name a new directory"
        )
    _check_target(target, force)
    parent = target.parent if str(target.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-", dir=parent))
    try:
        yield tmp
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=parent))
            os.rename(target, old / "x")
            os.rename(tmp, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def atomic_file(target: str | Path, *, force: bool = False, mode: str = "wb") -> Iterator[Any]:
    """Write a single file atomically (temporary file in the same directory, then rename)."""
    target = Path(target)
    if target.exists() and not force:
        raise OutputExistsError(f"output {str(target)!r} exists; pass --force to replace it")
    parent = target.parent if str(target.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    fd, tmpname = tempfile.mkstemp(prefix=f".{target.name}.partial-", dir=parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        os.replace(tmpname, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmpname)
        raise


def write_png(path: str | Path, image: np.ndarray, *, compress_level: int = 1) -> None:
    """Write an 8- or 16-bit greyscale PNG (H, W). Deterministic: no timestamps are embedded."""
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"write_png needs a (H, W) uint8 or uint16 image, got {img.shape} {img.dtype}")
    if img.dtype == np.uint8:
        pil = Image.fromarray(img, mode="L")
    else:
        pil = Image.fromarray(img.astype("<u2"), mode="I;16")
    pil.save(path, format="PNG", compress_level=compress_level)


def read_image(path: str | Path) -> np.ndarray:
    """Read a greyscale 8- or 16-bit PNG or TIFF as (H, W) uint8/uint16.

    Raises
    ------
    ImageSetError
        If the file is missing, unreadable, not greyscale or of another bit depth.
    """
    p = Path(path)
    if not p.is_file():
        raise ImageSetError(f"image file {str(p)!r} does not exist")
    try:
        with Image.open(p) as im:
            mode = im.mode
            arr = np.array(im)
    except Exception as e:  # PIL raises several types for broken files
        raise ImageSetError(f"cannot read image {str(p)!r}: {e}") from None
    if arr.ndim != 2 or mode not in ("L", "I;16", "I;16B", "I;16L", "I"):
        raise ImageSetError(
            f"image {str(p)!r} is not greyscale: not an 8- or 16-bit grey image (mode {mode}, shape {arr.shape}); "
            "palette, colour and 1-bit images are not fringe images"
        )
    if mode in ("I;16", "I;16B", "I;16L", "I") and arr.dtype != np.uint16:
        if arr.min() < 0 or arr.max() > 65535:
            raise ImageSetError(f"image {str(p)!r}: values outside the 16-bit range")
        arr = arr.astype(np.uint16)
    if arr.dtype == np.bool_:
        raise ImageSetError(f"image {str(p)!r} is a 1-bit image; 8- or 16-bit greyscale expected")
    if arr.dtype not in (np.uint8, np.uint16):
        raise ImageSetError(f"image {str(p)!r} has pixel type {arr.dtype}; 8- or 16-bit greyscale expected")
    return arr


def write_json(path: str | Path, obj: Any) -> None:
    """Write JSON (UTF-8, indented, sorted for stable diffs is not used: order is meaningful)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=2, ensure_ascii=False, allow_nan=False)
        f.write("\n")


def write_mapping_h5(path: str | Path, mappings: dict[str, Any], attrs: dict[str, Any]) -> None:
    """Write per-camera pixel → screen mappings (one group per camera).

    Each group holds ``screen_xy_mm`` (float64, H×W×2, NaN where invalid), ``valid``
    (bool, H×W) and ``status`` (uint8, H×W, :class:`pmdsim.trace.Status` codes).
    """
    from .trace import Status

    with h5py.File(path, "w", track_order=True) as f:
        for k, v in attrs.items():
            f.attrs[k] = v if v is not None else ""
        f.attrs["status_codes"] = json.dumps({s.name: int(s) for s in Status})
        for name, m in mappings.items():
            g = f.create_group(name)
            d = g.create_dataset("screen_xy_mm", data=m.screen_xy_mm, **_GZIP_FLOAT,
                                 chunks=(min(64, m.status.shape[0]), m.status.shape[1], 2))
            d.attrs["units"] = "mm"
            d.attrs["frame"] = "screen"
            d.attrs["description"] = "pattern coordinates (x_q, y_q) per pixel [v, u]; NaN where invalid"
            g.create_dataset("valid", data=m.valid, compression="gzip", compression_opts=1)
            st = g.create_dataset("status", data=m.status, compression="gzip", compression_opts=1)
            st.attrs["codes"] = json.dumps({s.name: int(s) for s in Status})
            for sname, count in m.status_counts().items():
                g.attrs[f"count_{sname}"] = count


@contextlib.contextmanager
def reconstructions_h5(path: str | Path, attrs: dict[str, Any]):
    """Open a reconstructions file for writing case by case (so that a long experiment need not
    hold every height map in memory); yields ``add(case, group=None)``. Layout: see
    :func:`write_reconstructions_h5`."""
    with h5py.File(path, "w", track_order=True) as f:
        for k, v in attrs.items():
            f.attrs[k] = v if v is not None else ""

        def add(c, group: str | None = None) -> None:
            g = f.create_group(f"bulge_{c.bulge_mm:g}mm/{c.camera}" if group is None else group)
            kw = _GZIP_FLOAT
            d = g.create_dataset("height_mm", data=c.height_mm, **kw)
            d.attrs["frame"] = "sample"
            g.create_dataset("height_error_um", data=(c.height_error_mm * 1e3).astype(np.float32), **kw)
            g.create_dataset("points_mm", data=c.points_mm, **kw)
            g.create_dataset("valid", data=c.valid, **kw)
            for k, v in c.as_record().items():
                g.attrs[k] = json.dumps(v) if isinstance(v, (list, dict)) else v

        yield add


def write_reconstructions_h5(path: str | Path, cases, attrs: dict[str, Any]) -> None:
    """Write reconstructions (one group per case: ``bulge_{Δh}mm/{camera}``).

    Each group holds ``height_mm`` (float64 H×W, reconstructed height in the sample frame,
    NaN outside the FOV), ``height_error_um`` (float32, reconstructed − true), ``points_mm``
    (float32 H×W×3, sample frame) and ``valid`` (bool), with the metrics as attributes.
    """
    with reconstructions_h5(path, attrs) as add:
        for c in cases:
            add(c)


def write_evaluation_h5(path: str | Path, results: dict, attrs: dict[str, Any]) -> None:
    """Write an evaluation: one group per camera with the decoded coordinates, masks, normals
    and the height map.

    Datasets per camera: ``screen_xy_mm`` (H×W×2, screen frame, NaN where not decoded),
    ``std_xy_mm`` (predicted σ), ``decoded`` (bool), ``phase_flags`` (uint8,
    :class:`pmdsim.phase.PhaseFlag`), ``registration_status`` (uint8,
    :class:`pmdsim.registration.RegistrationStatus`), ``normals`` (H×W×3, unit, sample frame),
    ``points_mm`` (H×W×3, sample frame), ``height_mm`` (H×W, sample frame, NaN where not
    reconstructed) and ``reconstructed`` (bool).
    """
    from .phase import PhaseFlag
    from .registration import RegistrationStatus

    kw = _GZIP_FLOAT
    with h5py.File(path, "w", track_order=True) as f:
        for k, v in attrs.items():
            f.attrs[k] = v if v is not None else ""
        f.attrs["phase_flags"] = json.dumps({fl.name: int(fl) for fl in PhaseFlag})
        f.attrs["registration_status"] = json.dumps({s.name: int(s) for s in RegistrationStatus})
        for cam, (decoded, reg, rec) in results.items():
            g = f.create_group(cam)
            g.create_dataset("screen_xy_mm", data=decoded.screen_xy_mm, **kw).attrs["frame"] = "screen"
            g.create_dataset("std_xy_mm", data=decoded.std_xy_mm, **kw)
            g.create_dataset("decoded", data=decoded.valid, **kw)
            g.create_dataset("phase_flags", data=decoded.flags, **kw)
            g.create_dataset("registration_status", data=reg.status, **kw)
            g.create_dataset("normals", data=rec.normals, **kw).attrs["frame"] = "sample"
            g.create_dataset("points_mm", data=rec.points, **kw).attrs["frame"] = "sample"
            d = g.create_dataset("height_mm", data=rec.height_mm, **kw)
            d.attrs["frame"] = "sample"
            d.attrs["description"] = "height along sample +z (docs/conventions.md), NaN where not reconstructed"
            g.create_dataset("reconstructed", data=rec.reconstructed, **kw)
            g.attrs["method"] = rec.method
            g.attrs["seed_pixel"] = list(rec.seed_pixel)
            g.attrs["converged"] = bool(rec.converged)
            g.attrs["iterations"] = int(rec.iterations)
