"""numba's cache and kernels spread over several files (pmdsim/__init__.py, issue 11's "nothing
silently wrong"): numba checks a cached kernel only against its own source file, so a kernel
that calls a function from another file keeps the old machine code when only that file changes.
Reproduced with real files and real numba caching in subprocesses, then repaired by the stamp."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pmdsim

CALLEE = "import numba\n\n@numba.njit(cache=True)\ndef g(x):\n    return x + {value}\n"
CALLER = textwrap.dedent("""
    import numba
    from .callee import g

    @numba.njit(cache=True)
    def f(x):
        return g(x) * 1.0
""")


def _package(tmp_path: Path, value: float) -> Path:
    """A package ``probe`` laid out like pmdsim (kernels in ``geometry``), caller and callee in
    two files."""
    root = tmp_path / "probe"
    (root / "geometry").mkdir(parents=True, exist_ok=True)
    (root / "__init__.py").write_text("")
    (root / "geometry" / "__init__.py").write_text("")
    (root / "geometry" / "callee.py").write_text(CALLEE.format(value=value))
    (root / "geometry" / "caller.py").write_text(CALLER)
    return root


def _run(tmp_path: Path, *, check: bool, xdg: Path | None = None, log: list | None = None) -> str:
    code = ("import sys, pmdsim\n"
            f"n = pmdsim._drop_stale_kernel_cache({str(tmp_path / 'probe')!r})\n"
            "from probe.geometry.caller import f\n"
            "print(f(1.0), n)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(pmdsim.__file__).parents[1])]),
           "XDG_CACHE_HOME": str(xdg or tmp_path / "xdg"), "NUMBA_DEBUG_CACHE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    if check:
        env.pop("PMDSIM_NO_CACHE_CHECK", None)
    else:
        env["PMDSIM_NO_CACHE_CHECK"] = "1"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    out = [line for line in r.stdout.splitlines() if not line.startswith("[cache]")]
    if log is not None:
        log.append(r.stdout)
    return out[-1].split()


def test_an_edit_of_a_called_file_alone_recompiles_the_caller(tmp_path):
    root = _package(tmp_path, 1.0)
    # without the stamp: numba's own check serves the caller's stale code
    assert _run(tmp_path, check=False)[0] == "2.0"
    (root / "geometry" / "callee.py").write_text(CALLEE.format(value=10.0))
    assert _run(tmp_path, check=False)[0] == "2.0"  # stale: the callee now adds 10
    # with it: the cache compiled from other sources is dropped, the caller recompiled
    value, removed = _run(tmp_path, check=True)
    assert value == "11.0" and int(removed) >= 2
    cache = root / "geometry" / "__pycache__"
    assert (cache / "pmdsim-kernel-sources.sha256").read_text().strip() == \
        pmdsim._kernel_sources_fingerprint(str(root))
    # unchanged sources: the cache is kept (nothing removed) and still right
    assert _run(tmp_path, check=True) == ["11.0", "0"]
    assert any(p.suffix == ".nbi" for p in cache.iterdir())
    # the next edit is caught the same way
    (root / "geometry" / "callee.py").write_text(CALLEE.format(value=100.0))
    value, removed = _run(tmp_path, check=True)
    assert value == "101.0" and int(removed) >= 2


def test_numba_cache_dir_is_checked_where_numba_puts_it(tmp_path, monkeypatch):
    """With ``NUMBA_CACHE_DIR`` set, numba caches in ``<dir>/<package>_<sha1 of its path>``;
    the stamp goes there (numba's own locator names the directory: compared with it)."""
    from numba.core import caching

    locator = getattr(caching, "UserProvidedCacheLocator", None) or caching._UserProvidedCacheLocator  # < 0.61
    root = _package(tmp_path, 1.0)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "nc"))
    dirs = pmdsim._numba_cache_dirs(str(root))
    expected = os.path.join(str(tmp_path / "nc"),
                            locator.get_suitable_cache_subpath(str(root / "geometry" / "callee.py")))
    assert dirs[0] == expected


def _pmdsim(env: dict, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pmdsim", *args], capture_output=True, text=True, env=env,
                          timeout=120)


def test_a_cold_cache_is_announced_once_and_a_warm_one_is_not(tmp_path, monkeypatch):
    """Issue 23 item 6 / 25 item 2: one line before a command compiles on a cold cache (a fresh
    NUMBA_CACHE_DIR, as after an install), none once real numba caching has filled it. The run
    stops at a missing setup file, after the note and before any kernel is compiled."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nc"), "XDG_CACHE_HOME": str(tmp_path / "xdg"),
           "PYTHONPATH": os.pathsep.join([str(Path(pmdsim.__file__).parents[1]), os.environ.get("PYTHONPATH", "")])}
    args = ("simulate", "--setup", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "out"), "--quiet")
    note = "pmdsim: note: numba kernels not compiled yet"
    for eager in (("simulate", "--help"), ("--version",)):
        r = _pmdsim(env, *eager)
        assert r.returncode == 0 and note not in r.stderr + r.stdout
    r = _pmdsim(env, *args)
    assert r.returncode == 2 and "missing.toml" in r.stderr, r.stderr
    lines = [line for line in r.stderr.splitlines() if note in line]
    assert len(lines) == 1 and "(geometry, simulation)" in lines[0], r.stderr
    # compile one real kernel of each package simulate uses (numba writes its own index files)
    warm = ("from pmdsim.geometry.fast_trig import sincos\n"
            "from pmdsim.simulation.optics import jinc, JINC_TABLE\n"
            "sincos(0.5); jinc(0.5, JINC_TABLE)\n")
    assert subprocess.run([sys.executable, "-c", warm], env=env, timeout=120).returncode == 0
    r = _pmdsim(env, *args)
    assert r.returncode == 2 and "missing.toml" in r.stderr and note not in r.stderr, r.stderr
    # new kernel sources elsewhere would drop the cache (the stamp): cold again, announced again
    monkeypatch.setenv("NUMBA_CACHE_DIR", env["NUMBA_CACHE_DIR"])
    stamp = Path(pmdsim._numba_cache_dirs(os.path.dirname(pmdsim.__file__))[0]) / pmdsim._STAMP
    assert stamp.parent.name.startswith("geometry_") and stamp.exists()
    stamp.write_text("0" * 64 + "\n")
    r = _pmdsim(env, *args)
    assert "(geometry)" in r.stderr and note in r.stderr, r.stderr


def test_another_install_of_identical_sources_reuses_the_compiled_kernels(tmp_path):
    """Issue 25 item 2: a second install of byte-identical sources at another path (``pip
    install -e .`` after ``pip install .``) loads the kernels the first compiled instead of
    compiling them again (numba's own cache log says which); an install whose sources differ in
    one file is not served the other's kernels (the stale-kernel guard holds)."""
    import numba

    xdg = tmp_path / "xdg"
    regular, editable, edited = tmp_path / "site", tmp_path / "src", tmp_path / "edited"
    for where in (regular, editable, edited):
        _package(where, 1.0)
    (edited / "probe" / "geometry" / "callee.py").write_text(CALLEE.format(value=10.0))
    log: list[str] = []
    assert _run(regular, check=True, xdg=xdg, log=log)[0] == "2.0"
    assert "data saved" in log[-1] and "data loaded" not in log[-1]
    assert _run(editable, check=True, xdg=xdg, log=log)[0] == "2.0"
    content_stamp = tuple(int(x) for x in numba.__version__.split(".")[:2]) >= (0, 68)
    if content_stamp:  # numba >= 0.68 checks a cached kernel by its source's content
        assert "data loaded" in log[-1] and "data saved" not in log[-1], log[-1]
    assert any((editable / "probe" / "geometry" / "__pycache__").glob("caller.*.nbi"))
    assert _run(edited, check=True, xdg=xdg, log=log)[0] == "11.0"  # compiled from its own sources
    assert "data saved" in log[-1]
    assert _run(editable, check=True, xdg=xdg, log=log)[0] == "2.0"
