"""Outputs: atomic output directories and files, provenance, JSON.

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

from .. import __version__
from ..errors import OutputExistsError

__all__ = ["MANIFEST_NAME", "MAPPING_NAME", "IMAGESET_FORMAT", "provenance", "atomic_output_dir", "atomic_file",
           "check_output_target", "write_json"]


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


def check_output_target(target: str | Path, *, force: bool = False) -> None:
    """Raise :class:`~pmdsim.errors.OutputExistsError` if ``target`` exists and ``force`` is not
    given — before a long computation, so that it does not fail only when writing."""
    target = Path(target)
    if target.exists() and not force:
        raise OutputExistsError(f"output {str(target)!r} exists; pass --force to replace it")


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


def write_json(path: str | Path, obj: Any) -> None:
    """Write JSON (UTF-8, indented, sorted for stable diffs is not used: order is meaningful)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=2, ensure_ascii=False, allow_nan=False)
        f.write("\n")
