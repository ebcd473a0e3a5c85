"""pmdsim: simulation and evaluation of phase-measuring deflectometry (PMD).

Founding document: "The effects of pattern screen surface deformation on deflectometric
measurements — a simulation study". Conventions: docs/conventions.md; the package map:
docs/architecture.md; a walk-through: docs/api.md.

The names a notebook needs are available here (imported on first use, so that ``import pmdsim``
and ``pmdsim --version`` stay fast and compile nothing)::

    import pmdsim
    setup = pmdsim.default_setup().with_bulge(3.0).binned(4)
    m = pmdsim.simulate(setup, "left")                 # traced mapping + fringe images
    decoded = pmdsim.decode(m.images, setup)           # screen coordinates per pixel
    ev = pmdsim.evaluate(decoded, setup.with_bulge(0.0), "left", seed_pixel=(150, 240),
                         seed_height_mm=0.0)           # planar-screen evaluation, as the paper's

Setups: :class:`Setup`, :func:`default_setup` (Table 1), :func:`load_setup`, :func:`parse_setup`.
Steps: :func:`simulate`, :func:`decode`, :func:`evaluate`, :func:`reconstruct`,
:func:`calibrate`, :func:`calibrated_setup`. Results: :class:`Measurement`,
:class:`ScreenCoordinates`, :class:`Evaluation`, :class:`Reconstruction`,
:class:`CalibrationResult`. Files: :func:`open_evaluation` (an ``evaluation.h5`` as an
xarray Dataset; extra ``pmdsim[xarray]``). Errors: :class:`PmdsimError` and its subclasses;
:class:`ConsistencyWarning`.
"""

from __future__ import annotations

import importlib
import os
import sys

__version__ = "0.1.0"


def _writable_dir(path: str) -> bool:
    """Whether ``path`` exists or can be made, and files can be created in it (numba's test)."""
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)


def _numba_cache_fallback() -> str | None:
    """Make numba's on-disk cache work where the install and the home directory are read-only.

    numba caches compiled kernels next to the sources (``__pycache__``), else in the user's
    cache directory (``~/.cache/numba``), else fails at import ("cannot cache function … no
    locator available"). If neither is writable and ``NUMBA_CACHE_DIR`` is not set, the cache
    goes to a per-user directory in the temporary directory; if that is not writable either,
    the kernels are compiled without a cache. Nothing is imported or compiled here (only a few
    file-system checks). Returns the one-line note (also printed to stderr), or None.
    """
    if os.environ.get("NUMBA_CACHE_DIR") or os.environ.get("PMDSIM_NO_CACHE_FALLBACK"):
        return None
    here = os.path.dirname(os.path.abspath(__file__))
    packages = [os.path.join(here, d) for d in ("geometry", "simulation", "evaluation", "calibration")]
    if all(_writable_dir(os.path.join(d, "__pycache__")) for d in packages):
        return None
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    if _writable_dir(os.path.join(xdg, "numba")):
        return None  # numba's own fallback (user-wide cache) works
    import tempfile

    uid = os.getuid() if hasattr(os, "getuid") else 0
    try:
        bases = [tempfile.gettempdir(), "/dev/shm"]
    except OSError:  # "No usable temporary directory found"
        bases = ["/dev/shm"]
    for base in bases:
        tmp = os.path.join(base, f"pmdsim-numba-cache-{uid}")
        if _writable_dir(tmp):
            _set_numba_cache_dir(tmp)
            note = (f"pmdsim: note: the install and home directories are read-only; numba's cache is in {tmp} "
                    "(set NUMBA_CACHE_DIR to choose another)")
            break
    else:
        _uncached_numba()
        note = ("pmdsim: note: no writable directory for numba's cache (install, home and temporary directory are "
                "read-only); kernels are compiled at each run (set NUMBA_CACHE_DIR to a writable directory)")
    print(note, file=sys.stderr)
    return note


def _set_numba_cache_dir(path: str) -> None:
    os.environ["NUMBA_CACHE_DIR"] = path
    if "numba" in sys.modules:  # numba read its configuration already
        sys.modules["numba"].config.CACHE_DIR = path


class _UncachedNumba:
    """Import hook: when numba's dispatcher module is loaded, its ``enable_caching`` (what
    ``@njit(cache=True)`` calls) becomes a no-op — the kernels compile uncached instead of
    failing. Imports nothing itself (``pmdsim --version`` stays free of numba)."""

    def find_spec(self, name, path, target=None):
        if name != "numba.core.dispatcher":
            return None
        import importlib.util

        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            module.Dispatcher.enable_caching = lambda self: None

        spec.loader.exec_module = exec_module
        return spec


def _uncached_numba() -> None:
    if "numba.core.dispatcher" in sys.modules:
        sys.modules["numba.core.dispatcher"].Dispatcher.enable_caching = lambda self: None
    else:
        sys.meta_path.insert(0, _UncachedNumba())


#: The subpackages that hold numba kernels (``@njit(cache=True)``); their sources fingerprint the cache.
_KERNEL_PACKAGES = ("geometry", "simulation", "evaluation", "calibration")
_STAMP = "pmdsim-kernel-sources.sha256"


def _kernel_sources_fingerprint(root: str) -> str:
    """SHA-256 over the relative path and the bytes of every ``.py`` file of the kernel
    subpackages (sorted): any edit of any kernel source changes it."""
    import hashlib

    h = hashlib.sha256()
    for pkg in _KERNEL_PACKAGES:
        for dirpath, dirnames, filenames in os.walk(os.path.join(root, pkg)):
            dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
            for name in sorted(f for f in filenames if f.endswith(".py")):
                path = os.path.join(dirpath, name)
                h.update(os.path.relpath(path, root).encode() + b"\0")
                with open(path, "rb") as f:
                    h.update(f.read())
                h.update(b"\0")
    return h.hexdigest()


def _numba_cache_dirs(root: str) -> list[str]:
    """The directories numba caches pmdsim's kernels in, by numba's own rule: ``NUMBA_CACHE_DIR``
    (``<dir>/<package>_<sha1 of the package path>``), else ``__pycache__`` next to the sources if
    writable, else ``$XDG_CACHE_HOME/numba`` (``~/.cache/numba``) with the same sub-path."""
    import hashlib

    base = os.environ.get("NUMBA_CACHE_DIR")
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    out = []
    for pkg in _KERNEL_PACKAGES:
        d = os.path.abspath(os.path.join(root, pkg))
        sub = f"{os.path.basename(d)}_{hashlib.sha1(d.encode()).hexdigest()}"
        if base:
            out.append(os.path.join(base, sub))
        elif _writable_dir(os.path.join(d, "__pycache__")):
            out.append(os.path.join(d, "__pycache__"))
        else:
            out.append(os.path.join(xdg, "numba", sub))
    return out


def _drop_stale_kernel_cache(root: str | None = None) -> int:
    """Remove numba cache files compiled from other versions of pmdsim's kernel sources.

    numba validates a cached kernel only against its *own* source file (its size and mtime, or
    a hash of it); a kernel that calls or inlines a function from another file (``trace`` calls
    ``trace_rows``, most kernels call ``surface``'s) keeps its old machine code when only that
    other file changes — after ``git pull`` or an upgrade that edits ``surface.py`` alone, the
    tracer would run stale code (it has crashed with "corrupted size vs. prev_size" this way).
    Each cache directory therefore holds a stamp, the SHA-256 of all kernel sources
    (:func:`_kernel_sources_fingerprint`); where it is missing or differs, pmdsim's ``.nbi`` and
    ``.nbc`` files there are deleted (recompiled on first use) and the stamp is written.
    Imports nothing and compiles nothing; costs about a millisecond. Returns the number of files
    removed. ``root``: the package directory (default pmdsim's own). ``PMDSIM_NO_CACHE_CHECK=1``
    skips it (used to reproduce the hazard in the tests).
    """
    if os.environ.get("PMDSIM_NO_CACHE_CHECK"):
        return 0
    root = os.path.dirname(os.path.abspath(__file__)) if root is None else root
    try:
        fingerprint = _kernel_sources_fingerprint(root)
    except OSError:
        return 0
    removed = 0
    current = []  # (package, cache directory) whose stamp is this fingerprint
    for pkg, cache in zip(_KERNEL_PACKAGES, _numba_cache_dirs(root)):
        stamp = os.path.join(cache, _STAMP)
        if _read_stamp(cache) == fingerprint:
            current.append((pkg, cache))
            continue
        if not _writable_dir(cache):
            continue
        try:
            for name in os.listdir(cache):
                if name.endswith((".nbi", ".nbc")):
                    try:
                        os.unlink(os.path.join(cache, name))
                        removed += 1
                    except FileNotFoundError:  # another process removed it first
                        pass
            tmp = f"{stamp}.{os.getpid()}.tmp"
            with open(tmp, "w", encoding="ascii") as f:
                f.write(fingerprint + "\n")
            os.replace(tmp, stamp)
        except OSError:
            continue
        current.append((pkg, cache))
    _share_kernel_caches(current, fingerprint)
    return removed


def _read_stamp(cache: str) -> str | None:
    try:
        with open(os.path.join(cache, _STAMP), encoding="ascii") as f:
            return f.read().strip()
    except (OSError, ValueError):
        return None


def _index_tag() -> str:
    """How numba's index files of this Python end (``<module>.<function>-<line>.py312.nbi``)."""
    return f".py{sys.version_info[0]}{sys.version_info[1]}{getattr(sys, 'abiflags', '')}.nbi"


def _share_kernel_caches(current: list[tuple[str, str]], fingerprint: str) -> int:
    """Reuse kernels compiled by another install of byte-identical kernel sources (issue 25 item 2).

    numba caches a kernel in a directory named by its source file's *path* (``__pycache__``
    next to it, or ``<cache dir>/<package>_<sha1 of the path>``), so an editable install after a
    regular one — same sources, other path — starts cold. Every cache directory stamped with
    the current fingerprint is listed in ``$XDG_CACHE_HOME/pmdsim/kernel-caches.txt``; a cold
    one (no index file for this Python) copies the kernels of a listed directory of the same
    subpackage whose stamp is *still* this fingerprint — compiled from the same bytes of every
    kernel source, so the stale-kernel guard holds. Each kernel's index and its data files are
    copied together (data first, each by an atomic rename) and only where the target has none
    of them, so an index never points at another compilation's data; the source's stamp is read
    again after the copy, and the copies are removed if it changed meanwhile. numba ≥ 0.68
    validates a cached kernel by a hash of its source's content and accepts the copies; older
    numba compares the file's mtime, rejects them and recompiles (nothing wrong, nothing gained).
    Returns the number of kernels copied."""
    if not current:
        return 0
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    registry = os.path.join(xdg, "pmdsim", "kernel-caches.txt")
    try:
        with open(registry, encoding="utf-8") as f:
            known = [tuple(line.rstrip("\n").split("\t", 1)) for line in f if "\t" in line]
    except (OSError, ValueError):
        known = []
    tag, copied = _index_tag(), 0
    for pkg, cache in current:
        try:
            names = os.listdir(cache)
        except OSError:
            continue
        if any(n.endswith(tag) for n in names):
            continue
        for other_pkg, other in known:
            if other_pkg != pkg or os.path.realpath(other) == os.path.realpath(cache) \
                    or _read_stamp(other) != fingerprint:
                continue
            n = _copy_kernels(other, cache, tag)
            if n and _read_stamp(other) != fingerprint:  # recompiled from other sources meanwhile
                try:
                    for x in os.listdir(cache):
                        if x.endswith((".nbi", ".nbc")):
                            os.unlink(os.path.join(cache, x))
                except OSError:
                    pass
                n = 0
            copied += n
            if n:
                break
    entries = list(dict.fromkeys([*((p, c) for p, c in known if os.path.isdir(c)), *current]))[-64:]
    if entries != known:
        try:
            os.makedirs(os.path.dirname(registry), exist_ok=True)
            tmp = f"{registry}.{os.getpid()}.tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                f.writelines(f"{p}\t{c}\n" for p, c in entries)
            os.replace(tmp, registry)
        except OSError:
            pass
    return copied


def _copy_kernels(src: str, dst: str, tag: str) -> int:
    """Copy each kernel's index file with its data files from ``src`` to ``dst`` where ``dst``
    holds none of them (see :func:`_share_kernel_caches`). Returns the number of kernels copied."""
    import shutil

    try:
        names, have = os.listdir(src), set(os.listdir(dst))
    except OSError:
        return 0
    n = 0
    for index in (x for x in names if x.endswith(tag)):
        base = index[:-len(".nbi")]
        data = [x for x in names if x.startswith(base + ".") and x.endswith(".nbc")
                and x[len(base) + 1:-len(".nbc")].isdigit()]
        if not data or any(x in have for x in [index, *data]):
            continue
        try:
            for x in [*data, index]:
                tmp = os.path.join(dst, f".{x}.{os.getpid()}.tmp")
                shutil.copyfile(os.path.join(src, x), tmp)
                os.replace(tmp, os.path.join(dst, x))
        except OSError:
            continue
        n += 1
    return n


def _cold_kernel_packages(packages=_KERNEL_PACKAGES, root: str | None = None) -> list[str]:
    """The kernel subpackages among ``packages`` whose numba cache is cold: its directory (where
    numba puts it, :func:`_numba_cache_dirs`) holds no index file (``*.nbi``) of a kernel
    compiled for this Python — a fresh install, a new cache directory, or one whose kernels
    :func:`_drop_stale_kernel_cache` removed. Per package, not per module: a command that uses
    only some of a package's kernels would otherwise count as cold on every warm run. Imports
    nothing; a directory listing per package (well under a millisecond)."""
    root = os.path.dirname(os.path.abspath(__file__)) if root is None else root
    tag = _index_tag()
    cold = []
    for pkg, cache in zip(_KERNEL_PACKAGES, _numba_cache_dirs(root)):
        if pkg not in packages:
            continue
        try:
            names = os.listdir(cache)
        except OSError:
            names = []
        if not any(n.endswith(tag) for n in names):
            cold.append(pkg)
    return cold


def _passive_openmp_wait() -> None:
    """Let numba's OpenMP worker threads sleep, not spin, while they wait (unless the user set
    ``OMP_WAIT_POLICY``).

    numba's default threading layer here is GNU OpenMP, whose threads spin-wait at each parallel
    kernel's barrier and between kernels. On a machine whose other CPUs are busy (the 2-vCPU
    machine under load 2–3) a spinning thread takes the CPU from the one it waits for: two small
    parallel kernels called 8 352 times took 52–75 s instead of 3.4 s with passive waiting
    (docs/benchmarks.md, "Parallel kernels under load: passive OpenMP waiting"). libgomp reads
    the variable when numba first loads it, at the first parallel kernel; nothing is imported here.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


_passive_openmp_wait()
_numba_cache_fallback()
_drop_stale_kernel_cache()

_LAZY = {
    "Setup": "pmdsim.setup",
    "default_setup": "pmdsim.setup",
    "load_setup": "pmdsim.io.heightmap",  # pmdsim.setup's, with height-map files read (issue 14)
    "parse_setup": "pmdsim.io.heightmap",
    "Measurement": "pmdsim.api",
    "simulate": "pmdsim.api",
    "decode": "pmdsim.api",
    "Evaluation": "pmdsim.api",
    "evaluate": "pmdsim.api",
    "evaluate_stereo": "pmdsim.api",
    "calibrate": "pmdsim.api",
    "calibrated_setup": "pmdsim.api",
    "reconstruct": "pmdsim.api",
    "ScreenCoordinates": "pmdsim.evaluation.phase",
    "Reconstruction": "pmdsim.evaluation.reconstruction",
    "CalibrationResult": "pmdsim.calibration",
    "PmdsimError": "pmdsim.errors",
    "SetupError": "pmdsim.errors",
    "ImageSetError": "pmdsim.errors",
    "ComputationError": "pmdsim.errors",
    "OptionalDependencyError": "pmdsim.errors",
    "InputError": "pmdsim.errors",
    "InputTypeError": "pmdsim.errors",
    "UnknownCameraError": "pmdsim.errors",
    "ConsistencyWarning": "pmdsim.errors",
    "open_evaluation": "pmdsim.io.datasets",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'pmdsim' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    """The public API only (``__all__``): no imported modules, no private helpers."""
    return sorted(__all__)
