"""Compile pmdsim's numba kernels from a list of signatures, ahead of their first use.

numba compiles a signature-less ``@njit(cache=True)`` kernel at its first call, in the calling
process, one kernel after another. On a cold cache the test suite spent ≥ 230 s of its
≈ 680 s compiling this way on one vCPU of the two (issue 25 item 4). A second process that
compiles the same signatures into the same on-disk cache (``NUMBA_CACHE_DIR``) lets the first
process load them instead. The list ("manifest") is a text file, one signature a line::

    pmdsim.evaluation.decoding._decode_kernel<TAB>(Array(uint8, 3, 'C', True, aligned=True), float64)<TAB>37.2

(the module, the kernel's name in it, the argument types as numba's ``repr`` writes them — as
in its cache index —, and optionally when a cold session first compiled it, in seconds).
:func:`write_manifest` makes one from a cache directory; :func:`compile_manifest` compiles a
manifest's entries in order, leaving to the session those it has reached
(:func:`session_frontier`). An entry whose kernel no longer exists or whose types
do not parse or compile is skipped: the kernel then compiles at its first call, as without this
module. Outputs do not change: a kernel loaded from the cache is the code the first process
would have compiled.

Two processes saving *different* signatures of one kernel at the same moment could both number
their data file ``1`` in numba's index (read, add, write back: not locked), and the index could
then point a signature at the other one's machine code. :func:`lock_cache_saves` serialises
numba's saves across the processes that call it (an ``flock`` per cache directory); the
compiling process and the process it serves both call it.

``python -m pmdsim._precompile MANIFEST [--parent PID]``: compile quietly (no output), at a
lower priority, and stop when the process ``PID`` is gone (between kernels; on Linux at once, by
the kernel's parent-death signal). SIGTERM ends it at once. ``PMDSIM_PRECOMPILE_LOG=<file>``:
append a line per kernel (UTC time, seconds, outcome, name) for measurements.
"""

from __future__ import annotations

import ast
import importlib
import os
import re
import sys

#: numba's type names in a signature's ``repr`` that are not attributes of ``numba.types`` by that name.
_SCALAR_ALIASES = {"bool": "boolean", "none": "none"}
_CONSTRUCTORS = ("Array", "ListType", "UniTuple", "Tuple", "literal")


def parse_signature(text: str) -> tuple:
    """The argument types of one signature, from numba's ``repr`` of them.

    Parameters
    ----------
    text : str
        ``"(Array(float64, 2, 'C', True, aligned=True), int64, Literal[bool](True), UniTuple(float64 x 3))"``;
        a return type (``" -> none"``) is ignored.

    Returns
    -------
    tuple of numba types

    Raises
    ------
    ValueError
        A name or form that is not one of numba's scalar types, ``Array``, ``ListType``,
        ``UniTuple``, ``Tuple`` or an integer/boolean literal. Nothing is evaluated: the text
        is parsed and only these constructors are applied.
    """
    from numba.core import types

    text = text.split(" -> ")[0].strip()
    text = re.sub(r"Literal\[(?:int|bool)\]\(", "literal(", text)
    text = re.sub(r" x (\d+)\)", r", \1)", text)
    try:
        tree = ast.parse(text, mode="eval").body
    except SyntaxError as e:
        raise ValueError(f"not a signature: {text!r}") from e

    def build(node):
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.Name):
            t = getattr(types, _SCALAR_ALIASES.get(node.id, node.id), None)
            if not isinstance(t, types.Type):
                raise ValueError(f"not a numba type: {node.id!r}")
            return t
        if isinstance(node, ast.Tuple):
            return tuple(build(e) for e in node.elts)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _CONSTRUCTORS:
            args = [build(a) for a in node.args]
            kwargs = {k.arg: build(k.value) for k in node.keywords}
            if node.func.id == "literal":
                return types.literal(*args)
            return getattr(types, node.func.id)(*args, **kwargs)
        raise ValueError(f"unsupported form in a signature: {ast.dump(node)[:80]}")

    sig = build(tree)
    return sig if isinstance(sig, tuple) else (sig,)


def read_manifest(path) -> list[tuple[str, str, str, float | None]]:
    """``(module, kernel name, signature text, first need in s or None)`` per non-empty,
    non-comment line of ``path`` (``module.kernel<TAB>types[<TAB>seconds]``)."""
    out = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip() and not line.startswith("#"):
                name, sig, *need = line.rstrip("\n").split("\t")
                module, _, kernel = name.rpartition(".")
                out.append((module, kernel, sig, float(need[0]) if need else None))
    return out


def _indexed(cache_dirs) -> set[str]:
    """``<module file stem>.<kernel>`` of every numba index file in ``cache_dirs``."""
    out = set()
    for d in cache_dirs:
        try:
            names = os.listdir(d)
        except OSError:
            continue
        out.update(n.rpartition("-")[0] for n in names if n.endswith(".nbi"))
    return out


def compiled_here(prefix: str = "pmdsim.") -> set[str]:
    """``<module file stem>.<kernel>`` of every numba dispatcher in the loaded modules named
    ``prefix…`` that this process compiled (numba counted a cache miss), callees included — the
    index files this process wrote, told apart from the ones another process wrote meanwhile."""
    from numba.core.dispatcher import Dispatcher

    out = set()
    for name, module in list(sys.modules.items()):
        if name.startswith(prefix) and module is not None:
            for obj in list(vars(module).values()):
                if isinstance(obj, Dispatcher) and obj._cache_misses:
                    out.add(f"{obj.py_func.__module__.rpartition('.')[2]}.{obj.py_func.__name__}")
    return out


def session_frontier(entries, indexed, own, coverage=0.7) -> float | None:
    """How far the session being served has come, in the manifest's seconds.

    The latest first need among the kernels with an index file (``indexed``) that this process
    did not write (``own``: what appeared while it compiled, callees included), counting only
    kernels up to which at least ``coverage`` of the manifest's kernels are indexed — a kernel
    the session compiled out of the manifest's order (a new test) does not move the frontier.
    None: no such kernel yet."""
    first = {}
    for module, kernel, _, need in entries:
        if need is not None:
            key = f"{module.rpartition('.')[2]}.{kernel}"
            first[key] = min(need, first.get(key, need))
    frontier, have = None, 0
    for n, (key, t) in enumerate(sorted(first.items(), key=lambda kv: kv[1]), start=1):
        have += key in indexed
        if key in indexed and key not in own and have >= coverage * n:
            frontier = t
    return frontier


def lock_cache_saves() -> None:
    """Serialise numba's cache saves (index read, update, write, then the data file) across the
    processes that call this, with an exclusive ``flock`` on ``.pmdsim-save.lock`` in the cache
    directory. Idempotent; a no-op where ``fcntl`` does not exist."""
    try:
        import fcntl
    except ImportError:
        return
    from numba.core import caching

    cls = caching.IndexDataCacheFile
    if getattr(cls.save, "_pmdsim_locked", False):
        return
    save = cls.save

    def locked_save(self, key, data):
        with open(os.path.join(self._cache_path, ".pmdsim-save.lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            return save(self, key, data)

    locked_save._pmdsim_locked = True
    cls.save = locked_save


def compile_manifest(entries, keep_going=lambda: True, log=None, cache_dirs=None, lead_s=30.0) -> dict[str, int]:
    """Compile (or load from the cache) each entry's signature in order.

    Parameters
    ----------
    entries : list of (module, kernel name, signature text, first need in s or None)
    keep_going : callable
        Asked before each entry; False stops.
    log : file, optional
        One line per entry: UTC time (s), seconds it took, ``done``/``skipped``/``passed``, the kernel.
    cache_dirs : list of str, optional
        The cache directories the served session writes to. With them, an entry first needed
        less than ``lead_s`` after the session's frontier (:func:`session_frontier`) is passed
        over: the session compiles it now or has done so, and compiling it here as well would
        only duplicate the work.

    Returns
    -------
    dict
        Counts: ``"done"`` (compiled or loaded), ``"skipped"`` (kernel missing, not a numba
        dispatcher, signature not parsed or not compiled), ``"passed"`` (left to the session).
    """
    import time

    counts = {"done": 0, "skipped": 0, "passed": 0}
    for module, kernel, sig_text, need in entries:
        if not keep_going():
            break
        t0, outcome = time.time(), "done"
        frontier = None
        if cache_dirs is not None and need is not None:
            frontier = session_frontier(entries, _indexed(cache_dirs), compiled_here())
        if frontier is not None and need < frontier + lead_s:
            outcome = "passed"
        else:
            try:
                dispatcher = getattr(importlib.import_module(module), kernel)
                dispatcher.compile(parse_signature(sig_text))
            except Exception:  # noqa: BLE001 - a stale entry compiles at first use instead
                outcome = "skipped"
        counts[outcome] += 1
        if log is not None:
            log.write(f"{time.time():.3f}\t{time.time() - t0:.3f}\t{outcome}\t{module}.{kernel}\n")
            log.flush()
    return counts


def write_manifest(cache_root, src_root, path, head_s=0.0) -> int:
    """Write the manifest of every signature in the numba cache under ``cache_root`` (its
    ``<package>_<sha1 of the package path>`` directories, ``NUMBA_CACHE_DIR`` layout) compiled
    from the sources under ``src_root`` (the directory holding ``pmdsim``).

    The lines follow the data files' mtimes (the order the kernels were first compiled in),
    except that those compiled in the first ``head_s`` seconds (from the first one) come last,
    latest first: a background process that starts with the kernels a session needs at once
    would compile them beside the session, not ahead of it (the test suite's manifest uses
    ``head_s=150``; docs/benchmarks.md). The third column is that time, in seconds from the
    first. Kernels whose name is not a module attribute (nested functions) are left out. Returns
    the number of lines.
    """
    import glob
    import hashlib
    import pickle

    package_of = {}
    for dirpath, dirnames, _ in os.walk(os.path.join(src_root, "pmdsim")):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        d = os.path.abspath(dirpath)
        sub = f"{os.path.basename(d)}_{hashlib.sha1(d.encode()).hexdigest()}"
        package_of[sub] = os.path.relpath(d, src_root).replace(os.sep, ".")
    rows = []
    for index in glob.glob(os.path.join(cache_root, "*", "*.nbi")):
        package = package_of.get(os.path.basename(os.path.dirname(index)))
        stem, _, rest = os.path.basename(index).partition(".")
        kernel = rest.rpartition("-")[0]
        if package is None or not kernel.isidentifier():
            continue
        with open(index, "rb") as f:
            pickle.load(f)  # numba's version
            _, overloads = pickle.loads(f.read())
        for key, data in overloads.items():
            data_path = os.path.join(os.path.dirname(index), data)
            if not os.path.exists(data_path):
                continue
            rows.append((f"{package}.{stem}", kernel, repr(key[0]), os.path.getmtime(data_path)))
    rows.sort(key=lambda r: r[3])
    first = rows[0][3] if rows else 0.0
    rows = [r for r in rows if r[3] - first >= head_s] + [r for r in rows if r[3] - first < head_s][::-1]
    with open(path, "w", encoding="utf-8") as f:
        f.write("# pmdsim kernel signatures to compile ahead (pmdsim._precompile): module.kernel<TAB>argument types"
                "<TAB>first compiled at (s, from the first)\n")
        f.writelines(f"{m}.{k}\t{s}\t{t - first:.1f}\n" for m, k, s, t in rows)
    return len(rows)


def _die_with_parent(parent: int) -> None:
    """On Linux, have the kernel send SIGTERM when the parent thread exits (``prctl``)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # gone before the call
        raise SystemExit(0)


def main(argv=None) -> int:
    import argparse
    import signal

    p = argparse.ArgumentParser(prog="python -m pmdsim._precompile", description=__doc__.splitlines()[0])
    p.add_argument("manifest")
    p.add_argument("--parent", type=int, default=None, help="stop when this process is gone")
    args = p.parse_args(argv)

    # SIGTERM keeps its default action, ending the process at once, also inside a compile (seconds
    # in LLVM): numba writes each cache file to a temporary name and renames it, so no file is
    # left half-written, and an index entry whose data file is missing is recompiled at first use.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if args.parent is not None:
        _die_with_parent(args.parent)
    try:
        os.nice(10)
    except (OSError, AttributeError):
        pass
    entries = read_manifest(args.manifest)
    lock_cache_saves()
    alive = (lambda: os.getppid() == args.parent) if args.parent is not None else (lambda: True)
    import pmdsim

    cache_dirs = pmdsim._numba_cache_dirs(os.path.dirname(os.path.abspath(pmdsim.__file__)))
    log_path = os.environ.get("PMDSIM_PRECOMPILE_LOG")
    log = open(log_path, "a", encoding="utf-8") if log_path else None
    try:
        compile_manifest(entries, keep_going=alive, log=log, cache_dirs=cache_dirs if args.parent is not None else None)
    except KeyboardInterrupt:
        return 130
    finally:
        if log is not None:
            log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
