"""The background kernel compiler of a cold test session (:mod:`pmdsim._precompile`, tests/conftest.py).

The signature parser is checked against numba's own types (``numba.typeof`` of real arrays, numba's
constructors), the compiler against numba's cache index of a fresh cache directory it filled in
another process, the manifest writer by a round trip through that index, and the session's
process handling with real signals to a ``pytest`` subprocess.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from pmdsim import _precompile

TESTS = Path(__file__).parent
SRC = Path(_precompile.__file__).resolve().parents[1]


def _readonly(a):
    a.flags.writeable = False
    return a


def test_signatures_parse_back_to_numbas_types():
    import numba
    from numba.core import types

    values = [np.zeros((2, 3)), _readonly(np.zeros((2, 3, 4), np.uint8)), np.zeros((3, 2)).T,
              np.zeros(5, np.float32)[::2], np.zeros(4, np.int16), 1.5, 3, True]
    sig = tuple(numba.typeof(v) for v in values)
    sig += (types.UniTuple(types.float64, 8), types.Tuple([types.int64, types.float64]),
            types.literal(True), types.literal(0), types.ListType(numba.typeof(_readonly(np.zeros((2, 2))))))
    assert _precompile.parse_signature(repr(sig)) == sig
    assert _precompile.parse_signature(repr(sig) + " -> none") == sig
    assert _precompile.parse_signature("(float64,)") == (types.float64,)


@pytest.mark.parametrize("text", ["(os.system('true'),)", "(__import__('os'),)", "(float64.__class__,)",
                                  "(Array(float64, 1, 'C'), Undefined)", "(lambda: 0,)", "(float64"])
def test_anything_but_numba_types_is_refused(text):
    with pytest.raises(ValueError):
        _precompile.parse_signature(text)


def _run_precompile(tmp_path, manifest_lines, parent=None):
    manifest = tmp_path / "manifest.txt"
    manifest.write_text("# comment\n" + "".join(f"{line}\n" for line in manifest_lines), encoding="utf-8")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nc"), "XDG_CACHE_HOME": str(tmp_path / "xdg"),
           "PYTHONPATH": str(SRC)}
    cmd = [sys.executable, "-m", "pmdsim._precompile", str(manifest)]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300), manifest


def test_compiles_the_listed_signatures_into_the_cache_and_skips_stale_entries(tmp_path):
    """Two signatures of one small kernel land in a fresh cache's index (read by numba's own
    pickle format); a missing kernel, a missing module and an unparsable type are skipped
    silently; the manifest written back from that cache lists exactly the two signatures."""
    import pickle

    good = ["pmdsim.geometry.camera._unpack\t(Array(float64, 1, 'C', False, aligned=True),)",
            "pmdsim.geometry.camera._unpack\t(Array(float64, 1, 'C', True, aligned=True),)"]
    stale = ["pmdsim.geometry.camera._no_such_kernel\t(float64,)",
             "pmdsim.no_such_module._unpack\t(float64,)",
             "pmdsim.geometry.camera._unpack\t(Blob(float64),)"]
    proc, _ = _run_precompile(tmp_path, [stale[0], good[0], *stale[1:], good[1]])
    assert (proc.returncode, proc.stdout, proc.stderr) == (0, "", "")
    indexes = list((tmp_path / "nc").glob("geometry_*/camera._unpack-*.nbi"))
    assert len(indexes) == 1
    with open(indexes[0], "rb") as f:
        pickle.load(f)
        _, overloads = pickle.loads(f.read())
    assert sorted(repr(key[0]) for key in overloads) == sorted(g.split("\t")[1] for g in good)
    n = _precompile.write_manifest(tmp_path / "nc", SRC, tmp_path / "back.txt")
    assert n == 2
    back = _precompile.read_manifest(tmp_path / "back.txt")
    assert sorted(f"{m}.{k}\t{sig}" for m, k, sig, _ in back) == sorted(good)
    assert all(need >= 0.0 for *_, need in back)


def test_entries_the_session_is_at_or_past_are_left_to_it(tmp_path):
    """The frontier is the latest first need among kernels with an index this process did not
    write; entries first needed before it + lead are passed over, later ones attempted."""
    nc = tmp_path / "nc"
    nc.mkdir()
    entries = [("pmdsim.a.m", "k1", "(float64,)", 10.0), ("pmdsim.a.m", "k1", "(int64,)", 50.0),
               ("pmdsim.a.m", "k2", "(float64,)", 40.0), ("pmdsim.no_such.m", "k3", "(float64,)", 75.0),
               ("pmdsim.no_such.m", "k4", "(float64,)", 200.0), ("pmdsim.no_such.m", "k5", "(float64,)", None)]
    assert _precompile.session_frontier(entries, set(), set()) is None
    for name in ("m.k1-10.py311.nbi", "m.k2-20.py311.nbi", "other.k9-1.py311.nbi"):
        (nc / name).touch()
    indexed = _precompile._indexed([nc, tmp_path / "missing"])
    assert indexed == {"m.k1", "m.k2", "other.k9"}
    assert _precompile.session_frontier(entries, indexed, set()) == 40.0  # k1 counts at its first need, 10 s
    assert _precompile.session_frontier(entries, indexed, {"m.k2"}) == 10.0
    # a kernel compiled out of order (k10) does not move the frontier past the ones not yet indexed
    tens = [("pmdsim.a.m", f"k{i}", "(float64,)", 10.0 * i) for i in range(1, 11)]
    assert _precompile.session_frontier(tens, {"m.k1", "m.k2", "m.k3", "m.k10"}, set()) == 30.0
    assert _precompile.session_frontier(tens, {f"m.k{i}" for i in range(1, 11)} - {"m.k5"}, set()) == 100.0
    counts = _precompile.compile_manifest(entries, cache_dirs=[nc], lead_s=30.0)
    # k1 (10, 50 < 40 + 30), k2 (40) passed; k3 (75), k4 (200) and k5 (no time) attempted: no such module
    assert counts == {"done": 0, "skipped": 3, "passed": 3}


def test_only_what_this_process_compiled_is_its_own(monkeypatch):
    """A kernel counts as this process's once numba compiled it here (a cache miss), not before,
    and not when only imported; named by its defining module's file stem."""
    import types

    import numba

    mod = types.ModuleType("pmdsim_probe_mod.sub")
    exec("import numba\n@numba.njit\ndef twice(x):\n    return 2 * x\n@numba.njit\ndef unused(x):\n    return x\n",
         mod.__dict__)
    mod.twice.py_func.__module__ = mod.unused.py_func.__module__ = "pmdsim_probe_mod.sub"
    monkeypatch.setitem(sys.modules, "pmdsim_probe_mod.sub", mod)
    assert _precompile.compiled_here("pmdsim_probe_mod.") == set()
    assert mod.twice(3) == 6
    assert _precompile.compiled_here("pmdsim_probe_mod.") == {"sub.twice"}
    assert isinstance(mod.twice, numba.core.dispatcher.Dispatcher)


def test_the_suites_manifest_parses():
    """Every line of tests/precompile_signatures.txt is ``module.kernel<TAB>types`` with types the parser reads."""
    entries = _precompile.read_manifest(TESTS / "precompile_signatures.txt")
    assert len(entries) > 100
    for module, kernel, sig, need in entries:
        assert module.startswith("pmdsim.") and kernel.isidentifier() and need >= 0.0
        _precompile.parse_signature(sig)


def _children(pid):
    try:
        with open(f"/proc/{pid}/task/{pid}/children", encoding="ascii") as f:
            return [int(x) for x in f.read().split()]
    except OSError:
        return []


def _gone(pid, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat", encoding="ascii") as f:
                if f.read().split(") ")[1].startswith("Z"):
                    return True  # exited, not yet reaped by its (new) parent
        except OSError:
            return True
        time.sleep(0.05)
    return False


def _default_sigint():
    """A job started in the background by a non-interactive shell ignores SIGINT, and so would pytest."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_background_compiler_ends_with_the_session(tmp_path, sig):
    """A cold ``pytest`` session starts exactly one background compiler and it ends with the
    session: on Ctrl-C (a real SIGINT to pytest: exit status 2, nothing from the compiler in the
    output) and when pytest is killed (SIGKILL: the kernel's parent-death signal)."""
    (tmp_path / "waiter.py").write_text(textwrap.dedent("""
        import time, pytest
        @pytest.hookimpl(tryfirst=True)
        def pytest_runtestloop(session):
            print("WAITING", flush=True)
            time.sleep(120)
            return True
    """), encoding="utf-8")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nc"), "XDG_CACHE_HOME": str(tmp_path / "xdg"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(SRC)])}
    env.pop("PMDSIM_NO_PRECOMPILE", None)
    proc = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-s", "-p", "waiter", "-p", "no:cacheprovider",
                             str(TESTS / "test_precompile.py"), "-k", "no_test_has_this_name"],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=_default_sigint)
    try:
        first = proc.stdout.readline()
        assert first.startswith("pmdsim: numba kernels not compiled yet") and "a background process" in first
        assert proc.stdout.readline().strip() == "WAITING"
        children = _children(proc.pid)
        assert len(children) == 1
        time.sleep(1.0)  # compiling by now
        proc.send_signal(sig)
        out = proc.stdout.read()
        assert proc.wait(timeout=15) == (2 if sig == signal.SIGINT else -signal.SIGKILL)
        assert _gone(children[0], timeout=3)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if sig == signal.SIGINT:
        assert "KeyboardInterrupt" in out and "pmdsim._precompile" not in out and "Traceback" not in out
