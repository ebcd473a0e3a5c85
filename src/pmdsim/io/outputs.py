"""Outputs: atomic output directories and files, their marker and lock, provenance, JSON.

Everything pmdsim writes records the pmdsim version and the command/setup that produced it.
The rules (docs/reliability.md, "Outputs, interrupts and environment"):

* **Atomic.** A run writes into a hidden partial directory (file) next to the target,
  ``.{name}.partial-*``, and renames it into place at the end: an interrupted or failed run
  leaves no half-written output and an existing output untouched.
* **Marked.** Every output directory carries :data:`MARKER_NAME` (``.pmdsim-output.json``:
  format, pmdsim version, command, time). ``force`` replaces only a directory with that marker
  — never a user's directory — and never a path that touches an input of the same command
  (``inputs``): the output is not an input, does not contain one (``pmdsim evaluate run --out
  run --force`` would destroy the image set) and is not inside an input directory (``pmdsim
  calibrate pose0 … --out pose0/left_x_p0_s0.png --force`` would replace a fringe image). A file
  output is replaced with ``force`` only if it is a regular file and not an input. A refusal
  suggests ``--force`` only where ``--force`` would be accepted.
* **Locked.** A run holds ``fcntl.flock`` on ``.{name}.lock`` beside the output from before its
  computation to its commit; a second run on the same output is refused with a message naming
  the holder (pid, host, start time, command). The lock file is removed when released.
* **Stale partials cleaned.** Holding the lock, a run removes the ``.{name}.partial-*`` and
  ``.{name}.old-*`` left by runs that were killed (SIGKILL, power loss): their lock is free, so
  nobody is writing them. A partial whose lock is held belongs to a running run: it is named in
  the refusal, not touched.
* **Checked first.** The path is checked before any computation: not under a regular file,
  the nearest existing directory writable and not on a read-only file system.
* **Interrupts.** The commit checks :func:`pmdsim.interrupts.check` (so a Ctrl-C that Python
  swallowed in a finaliser still aborts) and runs with SIGINT/SIGTERM held back; after it the
  output is complete.
* **umask.** Partial directories and files are created with mode 0o777 / 0o666 and the
  process's umask, like any other tool's outputs (``tempfile`` would make them 0700 / 0600).
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import logging
import os
import secrets
import shutil
import socket
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator

from .. import __version__
from .. import interrupts
from ..errors import OutputExistsError, OutputLockedError, OutputPathError

__all__ = ["MANIFEST_NAME", "MAPPING_NAME", "IMAGESET_FORMAT", "MARKER_NAME", "MARKER_FORMAT", "provenance",
           "atomic_output_dir", "atomic_file", "reused_output_dir", "check_output_target", "output_lock",
           "read_marker", "stale_partials", "partial_file", "write_json"]

log = logging.getLogger("pmdsim")

MANIFEST_NAME = "manifest.json"

MAPPING_NAME = "mapping.h5"

IMAGESET_FORMAT = "pmdsim-imageset"

#: The marker file of every output directory pmdsim writes.
MARKER_NAME = ".pmdsim-output.json"

#: The marker's ``format`` value.
MARKER_FORMAT = "pmdsim-output"


def provenance(command: str | None = None, setup_toml: str | None = None) -> dict[str, Any]:
    """What produced an output: pmdsim version, command line, and the setup as TOML."""
    return {
        "pmdsim_version": __version__,
        "command": _command(command),
        "setup_toml": setup_toml,
    }


def _command(command: str | None) -> str:
    return command if command else " ".join([Path(sys.argv[0]).name] + sys.argv[1:])


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


# ============================================================================ names beside a target
def _parent(target: Path) -> Path:
    return target.parent if str(target.parent) else Path(".")


def _lock_path(target: Path) -> Path:
    return _parent(target) / f".{target.name}.lock"


def stale_partials(target: str | Path) -> list[Path]:
    """The hidden leftovers of earlier runs on ``target``: ``.{name}.partial-*`` and
    ``.{name}.old-*`` beside it (stale only if nobody holds ``target``'s lock)."""
    target = Path(target)
    parent = _parent(target)
    if not parent.is_dir():
        return []
    return sorted(p for pat in (f".{target.name}.partial-*", f".{target.name}.old-*") for p in parent.glob(pat))


def read_marker(directory: str | Path) -> dict | None:
    """The marker of an output directory pmdsim wrote, or None (no marker, unreadable, foreign)."""
    try:
        m = json.loads((Path(directory) / MARKER_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) and m.get("format") == MARKER_FORMAT else None


def _write_marker(directory: Path, command: str | None, kind: str) -> None:
    write_json(directory / MARKER_NAME, {"format": MARKER_FORMAT, "pmdsim_version": __version__,
                                         "command": _command(command), "kind": kind, "created_utc": _now(),
                                         "host": socket.gethostname(), "pid": os.getpid()})


# ============================================================================ checks
def _is_input(target: Path, inputs: Iterable[str | Path]) -> tuple[str, str] | None:
    """The input that writing ``target`` would touch, and how: ``(input, relation)`` with
    relation ``"an"`` (``target`` is the input), ``"a parent of an"`` (``target`` contains it)
    or ``"inside an"`` (``target`` is a file or directory inside an input directory).

    Paths are compared after resolving symbolic links, so a link to an input counts as the input.
    """
    t = target.resolve()
    for p in inputs:
        if p is None:
            continue
        q = Path(p).resolve()
        if q == t:
            return str(p), "an"
        if q.is_relative_to(t):
            return str(p), "a parent of an"
        if t.is_relative_to(q):
            return str(p), "inside an"
    return None


def _input_refusal(target: Path, inputs: Iterable[str | Path]) -> str | None:
    """The refusal message when ``target`` touches an input (no ``--force`` can change it)."""
    hit = _is_input(target, inputs)
    if hit is None:
        return None
    p, rel = hit
    return (f"output {str(target)!r} is {rel} input of this command ({p!r}); writing it could destroy the input "
            "(--force does not change this) — choose an output path outside every input")


def _check_writable_location(target: Path) -> None:
    """Raise :class:`OutputPathError` if ``target`` cannot be created: a path component is a
    regular file, or the nearest existing directory is read-only or not writable."""
    a = _parent(target).absolute()
    missing = []
    while not a.exists() and a != a.parent:
        if a.is_symlink():  # a dangling symlink
            raise OutputPathError(f"cannot write output {str(target)!r}: {str(a)!r} is a broken symbolic link")
        missing.append(a)
        a = a.parent
    if not a.is_dir():
        raise OutputPathError(f"cannot write output {str(target)!r}: {str(a)!r} is a file, not a directory")
    if not os.access(a, os.W_OK | os.X_OK):
        try:
            ro = bool(os.statvfs(a).f_flag & os.ST_RDONLY)
        except OSError:
            ro = False
        why = "is on a read-only file system" if ro else "is not writable (permission denied)"
        raise OutputPathError(f"cannot write output {str(target)!r}: directory {str(a)!r} {why}; "
                              "choose another output path")


#: Room a name needs beside it for the hidden partial/lock names: ``.{name}.partial-{pid}-{8 hex}``.
_PARTIAL_EXTRA = len(".") + len(".partial-") + 10 + 1 + 8


def _check_path_length(target: Path) -> None:
    """Refuse a name or path the file system cannot hold, before anything is created: a name
    (with its hidden partial's suffix) longer than the file system's NAME_MAX bytes (255 on
    Linux) or a path longer than PATH_MAX (4096) — instead of an ``OSError`` traceback later."""
    name_max, path_max = 255, 4096  # Linux's; the file system's own where it can be asked
    a = _parent(target).absolute()
    while a != a.parent:
        try:
            if a.is_dir():
                name_max = os.pathconf(a, "PC_NAME_MAX")
                path_max = os.pathconf(a, "PC_PATH_MAX")
                break
        except (OSError, ValueError):  # a component too long to even look up
            pass
        a = a.parent
    full = os.fsencode(str(target.absolute()))
    if len(full) + _PARTIAL_EXTRA >= path_max:
        raise OutputPathError(f"output path is {len(full)} bytes long ({str(target)[:60]!r}…); the file system takes "
                              f"paths of at most {path_max} bytes (with room for pmdsim's hidden partial names: "
                              f"{path_max - _PARTIAL_EXTRA - 1}) — choose a shorter output path")
    for part in target.absolute().parts:
        n = len(os.fsencode(part))
        limit = name_max - _PARTIAL_EXTRA if part == target.name else name_max
        if n > limit:
            raise OutputPathError(f"output name {part[:40]!r}… is {n} bytes long; the file system takes names of at "
                                  f"most {name_max} bytes"
                                  + (f", and pmdsim needs {_PARTIAL_EXTRA} of them for its hidden partial output "
                                     f"beside it: at most {limit}" if part == target.name else "")
                                  + " — choose a shorter output name")


def check_output_target(target: str | Path, *, force: bool = False, inputs: Iterable[str | Path] = (),
                        kind: str = "file") -> None:
    """Check an output path before a long computation, so that it does not fail only when writing.

    Parameters
    ----------
    target : path
        The output directory (``kind="dir"``) or file (``kind="file"``).
    force : bool
        Replace an existing output: a directory only if it carries :data:`MARKER_NAME`, a
        file only if it is a regular file.
    inputs : paths
        The inputs of the command: ``target`` must be none of them and contain none of them.

    Raises
    ------
    OutputExistsError
        ``target`` exists (without ``force``), is not a pmdsim output, or is an input.
    OutputPathError
        ``target`` cannot be created (under a regular file, read-only or unwritable directory).
    """
    target = Path(target)
    _check_path_length(target)
    if target.name in ("", ".", "..") or Path.cwd().resolve().is_relative_to(target.resolve()):
        raise OutputExistsError(
            f"output {str(target)!r} is the current directory or one of its parents; name a new "
            f"{'directory' if kind == 'dir' else 'file'}")
    refusal = _input_refusal(target, inputs)
    if refusal is not None:
        raise OutputExistsError(refusal)
    if target.exists() or target.is_symlink():
        what = "directory" if kind == "dir" else "file"
        if kind == "dir":
            if not target.is_dir():
                raise OutputExistsError(f"output {str(target)!r} exists and is not a directory; pmdsim --force "
                                        "replaces only directories it wrote — choose another output path")
            if read_marker(target) is None:
                raise OutputExistsError(f"output {str(target)!r} exists and is not a pmdsim output (no {MARKER_NAME} "
                                        "in it); --force replaces only directories pmdsim wrote — remove it "
                                        "yourself or choose another output path")
        elif not target.is_file():
            raise OutputExistsError(f"output {str(target)!r} exists and is not a regular file; choose another "
                                    "output path")
        if not force:  # only now: --force would be accepted, and the target is no input
            raise OutputExistsError(f"output {str(target)!r} exists (an earlier pmdsim {what}); pass --force to "
                                    "replace it")
    _check_writable_location(target)


# ============================================================================ lock
_held: dict[str, int] = {}  # lock files this process holds → depth


@contextlib.contextmanager
def output_lock(target: str | Path, command: str | None = None) -> Iterator[None]:
    """Hold the lock of ``target`` (``fcntl.flock`` on ``.{name}.lock`` beside it).

    Raises :class:`~pmdsim.errors.OutputLockedError` naming the holder (pid, host, start,
    command) and its partial output if another run holds it. The lock file is removed on
    release (while still locked; a run that opened the removed file notices and retries).
    """
    target = Path(target)
    path = _lock_path(target)
    key = str(path.absolute())
    if key in _held:  # this process holds it already (an outer call): re-enter
        _held[key] += 1
        try:
            yield
        finally:
            _held[key] -= 1
        return
    try:
        _parent(target).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create the directory of output {str(target)!r}: {e.strerror}") from None
    for _ in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as e:
            raise OutputPathError(f"cannot create the lock file {str(path)!r} of output {str(target)!r}: "
                                  f"{e.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = _read_holder(fd)
            os.close(fd)
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputPathError(f"cannot lock {str(path)!r}: {e.strerror}") from None
            partials = [p.name for p in stale_partials(target)]
            raise OutputLockedError(
                f"output {str(target)!r} is being written by another pmdsim run ({holder}; lock {str(path)!r}"
                + (f", its partial output {', '.join(partials)}" if partials else "")
                + "); wait for it to finish or choose another output path") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the file was removed by its previous holder in the meantime: retry
    else:  # pragma: no cover
        raise OutputLockedError(f"cannot take the lock {str(path)!r} of output {str(target)!r}")
    try:
        info = {"pid": os.getpid(), "host": socket.gethostname(), "started_utc": _now(), "command": _command(command)}
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(info) + "\n").encode("utf-8"))
        _held[key] = 1
        yield
    finally:
        _held.pop(key, None)
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


def _read_holder(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 65536, 0).decode("utf-8"))
        return (f"pid {info['pid']} on {info['host']}, started {info['started_utc']}: {info['command']}")
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _clean_stale(target: Path) -> None:
    """Remove the leftovers of killed runs on ``target`` (call with its lock held)."""
    for p in stale_partials(target):
        _remove(p)
        log.warning("removed %s, the partial output of an earlier run on %s that was killed", p, target)


@contextlib.contextmanager
def _prepared(target: Path, force: bool, inputs, command, kind: str) -> Iterator[None]:
    check_output_target(target, force=force, inputs=inputs, kind=kind)
    with output_lock(target, command):
        _clean_stale(target)
        check_output_target(target, force=force, inputs=inputs, kind=kind)  # again, now that it is ours
        yield


def _new_partial(target: Path, make) -> Path:
    parent = _parent(target)
    for _ in range(100):
        p = parent / f".{target.name}.partial-{os.getpid()}-{secrets.token_hex(4)}"
        try:
            make(p)
            return p
        except FileExistsError:
            continue
        except OSError as e:
            raise OutputPathError(f"cannot write output {str(target)!r}: {e.strerror} ({str(p)!r})") from None
    raise OutputPathError(f"cannot create a partial output beside {str(target)!r}")  # pragma: no cover


def partial_file(target: str | Path) -> tuple[int, str]:
    """A new hidden partial file beside ``target`` (``.{name}.partial-*``), opened for writing:
    ``(fd, path)`` like :func:`tempfile.mkstemp`, but with mode 0o666 and the umask (mkstemp
    makes 0600 files, which the umask cannot open up for colleagues)."""
    target = Path(target)
    fds: list[int] = []
    p = _new_partial(target, lambda q: fds.append(os.open(q, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)))
    return fds[0], str(p)


def _discard(p: Path) -> None:
    with interrupts.deferred():
        _remove(p)


# ============================================================================ atomic outputs
@contextlib.contextmanager
def atomic_output_dir(target: str | Path, *, force: bool = False, inputs: Iterable[str | Path] = (),
                      command: str | None = None) -> Iterator[Path]:
    """Context manager yielding a partial directory that becomes ``target`` on success.

    Checks ``target`` (:func:`check_output_target`) and takes its lock (:func:`output_lock`)
    on entry — before the caller's computation — and removes stale partials of killed runs.
    On success writes :data:`MARKER_NAME` and renames the partial directory to ``target``
    (replacing a pmdsim output with ``force``). On an exception (including
    :class:`KeyboardInterrupt` and :class:`pmdsim.interrupts.Interrupted`) the partial
    directory is removed and an existing ``target`` is left untouched.
    """
    target = Path(target)
    inputs = list(inputs)
    with _prepared(target, force, inputs, command, "dir"):
        tmp = _new_partial(target, lambda p: os.mkdir(p, 0o777))
        old = None
        try:
            yield tmp
            _write_marker(tmp, command, "directory")
            interrupts.check()
            with interrupts.deferred():
                interrupts.check()
                if target.exists() or target.is_symlink():
                    old = _parent(target) / f".{target.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
                    os.rename(target, old)
                os.rename(tmp, target)
                interrupts.output_committed(target)
        except BaseException:
            _discard(tmp)
            raise
        if old is not None:
            _remove(old)


@contextlib.contextmanager
def atomic_file(target: str | Path, *, force: bool = False, mode: str = "wb", inputs: Iterable[str | Path] = (),
                command: str | None = None) -> Iterator[Any]:
    """Write a single file atomically: a partial file beside it, renamed at the end.

    Checks ``target`` and takes its lock on entry, so a caller can enter before a long
    computation and write at the end; an exception inside removes the partial file and leaves
    an existing ``target`` untouched.
    """
    target = Path(target)
    inputs = list(inputs)
    with _prepared(target, force, inputs, command, "file"):
        fds = []
        tmp = _new_partial(target, lambda p: fds.append(os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)))
        try:
            with os.fdopen(fds[0], mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
                yield f
            interrupts.check()
            with interrupts.deferred():
                interrupts.check()
                os.replace(tmp, target)
                interrupts.output_committed(target)
        except BaseException:
            _discard(tmp)
            raise


@contextlib.contextmanager
def reused_output_dir(target: str | Path, *, inputs: Iterable[str | Path] = (),
                      command: str | None = None) -> Iterator[Path]:
    """An output directory that runs add to (a study's ``OUT``): checked, created, marked and
    locked for the run; stale partial files of killed runs inside it and beside it removed.

    Refuses a non-empty directory that pmdsim did not write (no :data:`MARKER_NAME`).
    """
    target = Path(target)
    inputs = list(inputs)
    _check_path_length(target)
    if target.exists() and not target.is_dir():
        raise OutputExistsError(f"output {str(target)!r} exists and is not a directory; choose another output path")
    if target.is_dir() and any(target.iterdir()) and read_marker(target) is None:
        raise OutputExistsError(f"output {str(target)!r} exists and is not a pmdsim output (no {MARKER_NAME} in "
                                "it); choose a new or empty directory")
    refusal = _input_refusal(target, inputs)
    if refusal is not None:
        raise OutputExistsError(refusal)
    _check_writable_location(target / MARKER_NAME)
    with output_lock(target, command):
        _clean_stale(target)
        try:
            target.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputPathError(f"cannot create output {str(target)!r}: {e.strerror}") from None
        for p in sorted(target.rglob(".*.partial-*")):
            _remove(p)
            log.warning("removed %s, a partial file of an earlier run that was killed", p)
        if read_marker(target) is None:
            _write_marker(target, command, "reused directory")
        yield target


def write_json(path: str | Path, obj: Any) -> None:
    """Write JSON (UTF-8, indented, sorted for stable diffs is not used: order is meaningful)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=2, ensure_ascii=False, allow_nan=False)
        f.write("\n")
