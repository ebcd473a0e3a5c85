"""Shared fixtures: the built-in setup as TOML text and a small, fast variant of it.

Also the expensive results that several test files only read (session-scoped, computed once on
first use): the small setup simulated with a 3 mm screen bulge and evaluated through the CLI;
Experiment 1 at downsample 4; the calibration observations of the Table 1 setup
binned 8×8 with a 3 mm screen
bulge and Experiment 2 run on them; an image set of the Table 1 setup binned 12×12 and its stereo
evaluation through the CLI.

The small setup is made by editing the default TOML text (not by pmdsim's own writer), so that
tests of the writer/reader do not depend on what they test: both cameras shrink from 1920×1200
to 96×60 px with the focal length and principal point scaled by the same factor 1/20 (the same
field of view as the paper's Table 1).
"""

from __future__ import annotations

import atexit
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pmdsim.setup import default_setup

SMALL_W, SMALL_H = 96, 60
SMALL_PERIODS_X = [720.0, 60.0, 4.0]
SMALL_PERIODS_Y = [420.0, 35.0, 4.0]
SMALL_N_SHIFTS = 4


def replace_exactly(text: str, old: str, new: str, count: int) -> str:
    """``text.replace(old, new)``, asserting that ``old`` occurs exactly ``count`` times."""
    assert text.count(old) == count, f"expected {count} × {old!r} in the setup TOML, found {text.count(old)}"
    return text.replace(old, new)


def make_small_toml(default_toml: str) -> str:
    t = default_toml
    t = replace_exactly(t, "image_size_px = [1920, 1200]", f"image_size_px = [{SMALL_W}, {SMALL_H}]", 2)
    t = replace_exactly(t, "focal_length_px = [4400.0, 4400.0]", "focal_length_px = [220.0, 220.0]", 2)
    t = replace_exactly(t, "principal_point_px = [960.0, 600.0]", "principal_point_px = [48.0, 30.0]", 2)
    t = replace_exactly(t, "periods_x_mm = [720.0, 48.0, 2.0]", f"periods_x_mm = {SMALL_PERIODS_X}", 1)
    t = replace_exactly(t, "periods_y_mm = [420.0, 28.0, 2.0]", f"periods_y_mm = {SMALL_PERIODS_Y}", 1)
    t = replace_exactly(t, "n_shifts = 4", f"n_shifts = {SMALL_N_SHIFTS}", 1)
    return t


def pytest_sessionstart(session):
    """Progress from the start (issue 25 item 4): on a cold numba cache the first tests compile
    the kernels for minutes before the first result appears; say so before they start (also
    with ``-q``; nothing on a warm cache). And use the vCPU those serial compiles leave idle:
    one background process compiles the kernels of ``precompile_signatures.txt`` into the same
    cache, so that later tests load them (:func:`_start_precompiler`)."""
    import pmdsim

    cold = pmdsim._cold_kernel_packages()
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    ahead = _start_precompiler() if cold else False
    if cold and reporter is not None:
        reporter.write_line(f"pmdsim: numba kernels not compiled yet ({', '.join(cold)}): the first tests using them "
                            "compile them (minutes on 2 cores, no output meanwhile)"
                            + (", a background process the later ones" if ahead else "") + "; later runs use the cache")


#: The background compiler of a cold session (a ``subprocess.Popen``), or None.
_PRECOMPILER = None
KERNEL_SIGNATURES = Path(__file__).with_name("precompile_signatures.txt")


def _start_precompiler() -> bool:
    """Start ``python -m pmdsim._precompile tests/precompile_signatures.txt`` (same interpreter,
    environment and ``pmdsim`` sources; no output; lower priority; it stops when this process
    ends), unless ``PMDSIM_NO_PRECOMPILE=1`` or the file is missing. numba's cache saves of this process
    are locked against the background process's (:func:`pmdsim._precompile.lock_cache_saves`).
    The list is written from a cold suite's cache (fresh ``NUMBA_CACHE_DIR``, the whole suite with
    ``PMDSIM_NO_PRECOMPILE=1``) by ``pmdsim._precompile.write_manifest(<cache dir>, "src",
    "tests/precompile_signatures.txt", head_s=150)``; a stale line costs nothing but its compile."""
    global _PRECOMPILER
    if os.environ.get("PMDSIM_NO_PRECOMPILE") == "1" or not KERNEL_SIGNATURES.exists():
        return False
    import pmdsim
    from pmdsim import _precompile

    _precompile.lock_cache_saves()
    src = os.path.dirname(os.path.dirname(os.path.abspath(pmdsim.__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, *filter(None, [os.environ.get("PYTHONPATH")])])}
    _PRECOMPILER = subprocess.Popen(
        [sys.executable, "-m", "pmdsim._precompile", "--parent", str(os.getpid()), str(KERNEL_SIGNATURES)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    atexit.register(_stop_precompiler)
    return True


def _stop_precompiler() -> None:
    global _PRECOMPILER
    proc, _PRECOMPILER = _PRECOMPILER, None
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def pytest_sessionfinish(session, exitstatus):
    """The background compiler does not outlive the session (also after Ctrl-C)."""
    _stop_precompiler()


@pytest.fixture(scope="session")
def default_toml() -> str:
    """The built-in (Table 1) setup as TOML text."""
    return default_setup().to_toml()


@pytest.fixture(scope="session")
def small_toml(default_toml) -> str:
    """TOML text of the small setup (96×60 px cameras, Table 1 field of view)."""
    return make_small_toml(default_toml)


@pytest.fixture(scope="session")
def small_setup_file(tmp_path_factory, small_toml):
    """The small setup written to a file."""
    p = tmp_path_factory.mktemp("setup") / "small.toml"
    p.write_text(small_toml, encoding="utf-8")
    return p


@pytest.fixture(scope="session")
def binned8_bulge3_observations():
    """Calibration observations (16 mirror poses × 2 cameras, 8-bit images, decoded) of the Table 1
    setup binned 8×8 with a 3 mm central screen bulge. Read-only: shared by several files."""
    from pmdsim.studies import simulate_calibration_observations

    return simulate_calibration_observations(default_setup().binned(8).with_bulge(3.0))


@pytest.fixture(scope="session")
def binned8_bulge3_experiment2(binned8_bulge3_observations):
    """Experiment 2 at Δh = 3 mm, downsample 8, on :func:`binned8_bulge3_observations`, keyed by
    the screen grid: None (planar screen model) and 3 (3 × 3 free-form screen, one free height).
    Read-only: shared by tests/test_experiment3.py and tests/test_experiment_uncertainty.py."""
    from pmdsim.studies import run_experiment2_bulge

    return {g: run_experiment2_bulge(3.0, downsample=8, screen_grid=g, observations=binned8_bulge3_observations)
            for g in (None, 3)}


@pytest.fixture(scope="session")
def binned12_stereo(tmp_path_factory):
    """The Table 1 setup binned 12×12 (160 × 100 px per camera, flat sample, ideal 8-bit images):
    ``setup`` (the Setup), ``setup_file`` (its TOML), ``images`` (``pmdsim simulate`` output) and
    ``stereo`` (``pmdsim evaluate --stereo`` of it; ``stereo_stdout`` what it printed). Both
    commands run in process and must exit 0. Read-only: tests that edit images copy them first
    (tests/test_stereo.py, tests/test_reliability_paths.py)."""
    from types import SimpleNamespace

    from click.testing import CliRunner

    from pmdsim.cli import main

    d = tmp_path_factory.mktemp("binned12")
    setup = default_setup().binned(12)
    setup_file = d / "setup.toml"
    setup_file.write_text(setup.to_toml(), encoding="utf-8")
    r = CliRunner().invoke(main, ["simulate", "--setup", str(setup_file), "--out", str(d / "img"), "--quiet"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["evaluate", str(d / "img"), "--setup", str(setup_file), "--out", str(d / "stereo"),
                                  "--stereo", "--quiet"])
    assert r.exit_code == 0, r.output
    return SimpleNamespace(setup=setup, setup_file=setup_file, images=d / "img", stereo=d / "stereo",
                           stereo_stdout=r.stdout)


@pytest.fixture(scope="session")
def experiment1_ds4():
    """Experiment 1 at downsample 4 (480 × 300 px), Δh ∈ {0, 1, 2, 3} mm × both cameras, keyed by
    (Δh, camera). Read-only: tests/test_experiment1.py checks it, tests/test_experiment2.py
    compares with it."""
    from pmdsim.studies import experiment1

    return {(r.bulge_mm, r.camera): r for r in experiment1(downsample=4)}


@pytest.fixture(scope="session")
def small_bulge3_evaluated(tmp_path_factory, small_setup_file):
    """``(sim, ev)``: ``pmdsim simulate --setup small.toml --bulge-mm 3`` and ``pmdsim evaluate``
    of it with the small setup (planar screen model), in process, both exit 0. Read-only:
    tests/test_evaluate.py and tests/test_hdf5_layout.py read the files."""
    from click.testing import CliRunner

    from pmdsim.cli import main

    d = tmp_path_factory.mktemp("small_bulge3")
    r = CliRunner().invoke(main, ["simulate", "--setup", str(small_setup_file), "--bulge-mm", "3", "--out",
                                  str(d / "sim"), "--quiet"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["evaluate", str(d / "sim"), "--setup", str(small_setup_file), "--out", str(d / "ev"),
                                  "--quiet"])
    assert r.exit_code == 0, r.output
    return d / "sim", d / "ev"
