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
    for cache in _numba_cache_dirs(root):
        stamp = os.path.join(cache, _STAMP)
        try:
            with open(stamp, encoding="ascii") as f:
                if f.read().strip() == fingerprint:
                    continue
        except (OSError, ValueError):
            pass
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
    return removed


def _cold_kernel_packages(packages=_KERNEL_PACKAGES, root: str | None = None) -> list[str]:
    """The kernel subpackages among ``packages`` whose numba cache is cold: its directory (where
    numba puts it, :func:`_numba_cache_dirs`) holds no index file (``*.nbi``) of a kernel
    compiled for this Python — a fresh install, a new cache directory, or one whose kernels
    :func:`_drop_stale_kernel_cache` removed. Per package, not per module: a command that uses
    only some of a package's kernels would otherwise count as cold on every warm run. Imports
    nothing; a directory listing per package (well under a millisecond)."""
    root = os.path.dirname(os.path.abspath(__file__)) if root is None else root
    tag = f".py{sys.version_info[0]}{sys.version_info[1]}{getattr(sys, 'abiflags', '')}.nbi"
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
