"""The command line: ``pmdsim setup --show`` and ``pmdsim simulate`` (outputs, atomicity, errors).

Runs use a small setup (conftest.py: 96×60 px cameras with the Table 1 field of view) so the
whole file stays fast. Truths: counts and sizes read from the setup TOML with tomllib, the
fringe formula of docs/conventions.md, package metadata, the bytes of another run.
"""

from __future__ import annotations

import importlib.metadata
import json
import shlex
import shutil
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

import pmdsim.cli
import pmdsim.studies.jobs
from pmdsim.cli import main
from pmdsim.setup import default_setup


# ----------------------------------------------------------------------------- helpers
def replace_exactly(text: str, old: str, new: str, count: int) -> str:
    assert text.count(old) == count, f"expected {count} × {old!r}, found {text.count(old)}"
    return text.replace(old, new)


def run_subprocess(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``pmdsim ARGS`` in a fresh interpreter (real exit codes, real stderr)."""
    return subprocess.run([sys.executable, "-m", "pmdsim.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def run_inprocess(*args: str):
    return CliRunner().invoke(main, list(args))


def command_string(*args: str) -> str:
    return "pmdsim " + " ".join(shlex.quote(a) for a in args)


def snapshot(d: Path) -> dict[str, bytes]:
    """Every file below ``d`` (relative path → bytes)."""
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def hidden_leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def read_mapping(path: Path) -> dict[str, dict[str, np.ndarray]]:
    with h5py.File(path, "r") as f:
        return {g: {k: f[g][k][()] for k in f[g]} for g in f}


def expected_images(setup_doc: dict) -> set[tuple[str, str, float, int]]:
    """(camera, direction, period_mm, shift_index) of every image the setup asks for."""
    p = setup_doc["patterns"]
    return {
        (cam, direction, float(period), k)
        for cam in setup_doc["cameras"]
        for direction, periods in (("x", p["periods_x_mm"]), ("y", p["periods_y_mm"]))
        for period in periods
        for k in range(p["n_shifts"])
    }


# ----------------------------------------------------------------------------- shared runs
@pytest.fixture(scope="module")
def small_doc(small_toml) -> dict:
    return tomllib.loads(small_toml)


@pytest.fixture(scope="module")
def run_a(tmp_path_factory, small_setup_file):
    """The small setup simulated in a separate process."""
    parent = tmp_path_factory.mktemp("run_a")
    out = parent / "OUT"
    args = ("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")
    r = run_subprocess(*args)
    assert r.returncode == 0, r.stderr
    return {"out": out, "args": args, "stderr": r.stderr}


@pytest.fixture(scope="module")
def run_b(tmp_path_factory, small_setup_file):
    """The same command in-process (CliRunner), into another directory."""
    parent = tmp_path_factory.mktemp("run_b")
    out = parent / "OUT"
    args = ("simulate", "--setup", str(small_setup_file), "--out", str(out))
    r = run_inprocess(*args)
    assert r.exit_code == 0, r.output
    return {"out": out, "args": args, "output": r.output}


def test_progress_without_a_terminal_is_lines(run_a, run_b):
    """Not a terminal (CliRunner's streams, a log file): click's bar would print its label and then
    nothing until the end; the command prints ``  LABEL i/n after T s: MESSAGE`` lines instead, the
    last step always. ``--quiet`` (run_a, a real subprocess with piped stderr) prints none."""
    import re

    lines = [ln for ln in run_b["output"].splitlines() if ln.startswith("  simulating ")]
    assert lines, run_b["output"]
    m = re.fullmatch(r"  simulating (\d+)/(\d+) after \d+ s: (.+)", lines[-1])
    assert m and m.group(1) == m.group(2) and int(m.group(2)) >= 2, lines
    assert not any(ln.startswith("  simulating ") for ln in run_a["stderr"].splitlines())


# ----------------------------------------------------------------------------- setup --show
def test_setup_show_prints_default_setup():
    r = run_subprocess("setup", "--show")
    assert r.returncode == 0, r.stderr
    doc = tomllib.loads(r.stdout)
    assert doc == default_setup().to_dict()
    # Table 1, literally
    assert doc["cameras"]["left"]["origin_world_mm"] == [-90.0, 295.0, -295.0]
    assert doc["cameras"]["right"]["angles_deg"] == [45.0, -10.0, -10.0]
    assert doc["screen"]["origin_world_mm"] == [-354.0, -78.0, -400.0]


def test_setup_validates_a_file(small_setup_file):
    r = run_inprocess("setup", "--setup", str(small_setup_file), "--show")
    assert r.exit_code == 0
    assert tomllib.loads(r.stdout)["cameras"]["left"]["image_size_px"] == [96, 60]


def test_version_option():
    r = run_inprocess("--version")
    assert r.exit_code == 0
    assert importlib.metadata.version("pmdsim") in r.output


@pytest.mark.skipif(shutil.which("pmdsim") is None, reason="console script not on PATH")
def test_console_script_error_exit_code(tmp_path):
    """The installed ``pmdsim`` entry point: a user error is one line on stderr and exit code 2."""
    r = subprocess.run(["pmdsim", "simulate", "--setup", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "OUT")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    assert r.stderr.startswith("pmdsim: error: ") and "nope.toml" in r.stderr and "Traceback" not in r.stderr
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- simulate outputs
def test_simulate_writes_listed_images(run_a, small_doc):
    out = run_a["out"]
    manifest = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
    entries = manifest["images"]
    want = expected_images(small_doc)
    assert len(want) == 2 * 2 * 3 * 4 == 48
    assert len(entries) == 48
    for e in entries:
        assert {"file", "camera", "direction", "period_mm", "shift_index"} <= set(e)
    got = {(e["camera"], e["direction"], e["period_mm"], e["shift_index"]) for e in entries}
    assert got == want
    files = [e["file"] for e in entries]
    assert len(set(files)) == 48
    # exactly the listed images, the manifest, the mapping and pmdsim's output marker; nothing else
    assert sorted(p.name for p in out.iterdir()) == sorted(files + ["manifest.json", "mapping.h5",
                                                                    ".pmdsim-output.json"])
    for f in files:
        with Image.open(out / f) as im:
            assert im.format == "PNG" and im.mode == "L"
            a = np.array(im)
        assert a.shape == (60, 96) and a.dtype == np.uint8
    assert manifest["bit_depth"] == 8
    assert manifest["cameras"]["left"]["image_size_px"] == [96, 60]


def test_simulate_mapping_h5(run_a):
    with h5py.File(run_a["out"] / "mapping.h5", "r") as f:
        assert sorted(f) == ["left", "right"]
        for cam in ("left", "right"):
            xy, valid = f[cam]["screen_xy_mm"], f[cam]["valid"]
            assert xy.shape == (60, 96, 2) and xy.dtype == np.float64
            assert valid.shape == (60, 96) and valid.dtype == np.bool_
            xy, valid = xy[()], valid[()]
            assert np.isnan(xy).any(axis=-1).tolist() == (~valid).tolist()
            assert np.isnan(xy).all(axis=-1).tolist() == (~valid).tolist()
            # valid points lie on the screen (0…708 × 0…398 mm, Table 1)
            v = xy[valid]
            assert v.size and (v[:, 0] >= 0).all() and (v[:, 0] <= 708).all()
            assert (v[:, 1] >= 0).all() and (v[:, 1] <= 398).all()


def test_simulate_records_version_command_and_setup(run_a, run_b, small_doc):
    version = importlib.metadata.version("pmdsim")
    for run in (run_a, run_b):  # a separate process and an in-process call (main(args))
        out = run["out"]
        manifest = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
        assert manifest["pmdsim_version"] == version
        assert manifest["command"] == command_string(*run["args"])
        assert tomllib.loads(manifest["setup_toml"]) == small_doc
        with h5py.File(out / "mapping.h5", "r") as f:
            assert f.attrs["pmdsim_version"] == version
            assert f.attrs["command"] == command_string(*run["args"])
            assert tomllib.loads(f.attrs["setup_toml"]) == small_doc


def test_simulate_images_follow_the_fringe_formula(run_a, small_doc):
    """Each grey level is round(255·(A + B·cos(2π·c/p − 2πk/N))) at the pixel's mapped screen point."""
    out = run_a["out"]
    manifest = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
    mapping = read_mapping(out / "mapping.h5")
    pat = small_doc["patterns"]
    A, B, N = pat["mean_level"], pat["amplitude"], pat["n_shifts"]
    for e in manifest["images"]:
        m = mapping[e["camera"]]
        c = m["screen_xy_mm"][..., 0 if e["direction"] == "x" else 1]
        with Image.open(out / e["file"]) as im:
            img = np.array(im).astype(int)
        ok = m["valid"]
        ideal = 255.0 * (A + B * np.cos(2 * np.pi * c[ok] / e["period_mm"] - 2 * np.pi * e["shift_index"] / N))
        assert np.abs(img[ok] - ideal).max() <= 0.5 + 1e-6, e["file"]
        assert (img[~ok] == 0).all()


def test_simulate_is_deterministic(run_a, run_b):
    a, b = snapshot(run_a["out"]), snapshot(run_b["out"])
    assert sorted(a) == sorted(b)
    pngs = [k for k in a if k.endswith(".png")]
    assert len(pngs) == 48
    for k in pngs:
        assert a[k] == b[k], k
    ma, mb = read_mapping(run_a["out"] / "mapping.h5"), read_mapping(run_b["out"] / "mapping.h5")
    assert sorted(ma) == sorted(mb) == ["left", "right"]
    for cam in ma:
        for k in ("screen_xy_mm", "valid"):
            assert np.array_equal(ma[cam][k], mb[cam][k], equal_nan=True), (cam, k)


def test_simulate_with_invalid_pixels(tmp_path, small_toml):
    """A sample smaller than the field of view: NaN exactly where invalid, black pixels there."""
    t = replace_exactly(small_toml, "grid_x_mm = [0.0, 400.0]", "grid_x_mm = [0.0, 250.0]", 1)
    t = replace_exactly(t, "grid_y_mm = [0.0, 400.0]", "grid_y_mm = [0.0, 250.0]", 1)
    setup_file = tmp_path / "cropped.toml"
    setup_file.write_text(t, encoding="utf-8")
    out = tmp_path / "OUT"
    r = run_inprocess("simulate", "--setup", str(setup_file), "--out", str(out), "--quiet")
    assert r.exit_code == 0, r.output
    manifest = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
    mapping = read_mapping(out / "mapping.h5")
    for cam, m in mapping.items():
        valid, xy = m["valid"], m["screen_xy_mm"]
        assert 0 < valid.sum() < valid.size, "the test needs both valid and invalid pixels"
        assert np.array_equal(np.isnan(xy[..., 0]), ~valid) and np.array_equal(np.isnan(xy[..., 1]), ~valid)
        assert np.isfinite(xy[valid]).all()
        counts = manifest["cameras"][cam]["status_counts"]
        assert sum(counts.values()) == 96 * 60 and counts["VALID"] == int(valid.sum())
    for e in manifest["images"]:
        with Image.open(out / e["file"]) as im:
            img = np.array(im)
        assert (img[~mapping[e["camera"]]["valid"]] == 0).all()


# ----------------------------------------------------------------------------- existing output
def test_existing_output_needs_force(tmp_path, run_a, small_setup_file):
    out = tmp_path / "OUT"
    shutil.copytree(run_a["out"], out)  # a previous run's output
    (out / "notes.txt").write_text("kept?", encoding="utf-8")
    before = snapshot(out)
    args = ("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")

    r = run_subprocess(*args)
    assert r.returncode == 2
    assert "--force" in r.stderr and "pmdsim: error:" in r.stderr and "Traceback" not in r.stderr
    assert snapshot(out) == before
    assert hidden_leftovers(tmp_path) == []

    r = run_inprocess(*args, "--force")
    assert r.exit_code == 0, r.output
    after = snapshot(out)
    assert "notes.txt" not in after  # replaced, not merged
    ref = snapshot(run_a["out"])
    assert {k: v for k, v in after.items() if k.endswith(".png")} == {
        k: v for k, v in ref.items() if k.endswith(".png")}
    assert sorted(after) == sorted(ref)
    assert hidden_leftovers(tmp_path) == []


# ----------------------------------------------------------------------------- user errors
@pytest.mark.parametrize(
    "old, new, key",
    [
        ("focal_length_px = [220.0, 220.0]", "focal_length_px = [-220.0, 220.0]", "cameras.left.focal_length_px"),
        ("n_shifts = 4", "n_shifts = 2", "patterns.n_shifts"),
        ("bulge_mm = 0.0", "bulge_mm = nan", "screen.bulge_mm"),
    ],
    ids=["negative-focal-length", "two-shifts", "nan-bulge"],
)
def test_malformed_setup_file(tmp_path, small_toml, old, new, key):
    assert old in small_toml
    bad = tmp_path / "bad.toml"
    bad.write_text(small_toml.replace(old, new, 1), encoding="utf-8")
    parent = tmp_path / "results"
    parent.mkdir()
    out = parent / "OUT"
    # the exit code and streams of a real process once (the refusal's path is the same for every
    # key); the other keys in-process: the same parsing, exit code and message
    if key == "cameras.left.focal_length_px":
        r = run_subprocess("simulate", "--setup", str(bad), "--out", str(out))
    else:
        res = run_inprocess("simulate", "--setup", str(bad), "--out", str(out))
        r = subprocess.CompletedProcess("simulate", res.exit_code, res.stdout, res.stderr)
    assert r.returncode == 2
    assert r.stderr.startswith("pmdsim: error: ")
    assert key in r.stderr and str(bad) in r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    assert not out.exists()
    assert list(parent.iterdir()) == []


@pytest.mark.parametrize(
    "extra, needle",
    [
        (("--setup", "MISSING"), "does not exist"),
        (("--bulge-mm", "nan"), "bulge"),
        (("--bulge-mm", "inf"), "bulge"),
    ],
    ids=["missing-setup-file", "nan-bulge-option", "inf-bulge-option"],
)
def test_simulate_user_errors_in_process(tmp_path, extra, needle):
    extra = tuple(str(tmp_path / "missing.toml") if a == "MISSING" else a for a in extra)
    out = tmp_path / "OUT"
    r = run_inprocess("simulate", *extra, "--out", str(out))
    assert r.exit_code == 2
    assert "pmdsim: error:" in r.output and needle in r.output
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert not out.exists() and hidden_leftovers(tmp_path) == []


def test_bulge_with_even_screen_grid(tmp_path, small_toml):
    t = replace_exactly(small_toml, "grid_x_mm = [0.0, 354.0, 708.0]", "grid_x_mm = [0.0, 236.0, 472.0, 708.0]", 1)
    t = replace_exactly(t, "bulge_mm = 0.0\n", "", 1)
    f = tmp_path / "even.toml"
    f.write_text(t, encoding="utf-8")
    out = tmp_path / "OUT"
    r = run_inprocess("simulate", "--setup", str(f), "--bulge-mm", "1", "--out", str(out))
    assert r.exit_code == 2
    assert "screen.bulge_mm" in r.output and "odd" in r.output
    assert not out.exists()


# ----------------------------------------------------------------------------- interruption
class _InterruptAfter:
    """Stands in for write_png: writes ``n`` images, then raises KeyboardInterrupt (thread-safe)."""

    def __init__(self, real, n):
        self.real, self.n, self.calls = real, n, 0
        self.lock = threading.Lock()

    def __call__(self, *args, **kwargs):
        with self.lock:
            self.calls += 1
            k = self.calls
        if k > self.n:
            raise KeyboardInterrupt
        return self.real(*args, **kwargs)


def test_interrupted_run_leaves_nothing(tmp_path, monkeypatch, small_setup_file):
    assert pmdsim.studies.jobs.write_png is pmdsim.io.write_png  # the name simulate_to_dir calls
    fake = _InterruptAfter(pmdsim.io.write_png, 5)
    monkeypatch.setattr(pmdsim.studies.jobs, "write_png", fake)
    out = tmp_path / "OUT"
    r = run_inprocess("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")
    assert fake.calls > 5  # the interruption happened
    assert r.exit_code != 0
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_interrupted_forced_run_keeps_old_output(tmp_path, monkeypatch, run_a, small_setup_file):
    out = tmp_path / "OUT"
    shutil.copytree(run_a["out"], out)
    before = snapshot(out)
    fake = _InterruptAfter(pmdsim.io.write_png, 30)
    monkeypatch.setattr(pmdsim.studies.jobs, "write_png", fake)
    r = run_inprocess("simulate", "--setup", str(small_setup_file), "--out", str(out), "--force", "--quiet")
    assert fake.calls > 30 and r.exit_code != 0
    assert snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["OUT"]


def test_interrupt_while_writing_mapping(tmp_path, monkeypatch, small_setup_file):
    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pmdsim.studies.jobs, "write_mapping_h5", boom)
    out = tmp_path / "OUT"
    r = run_inprocess("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")
    assert r.exit_code != 0
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- bulge
def test_bulge_changes_mapping_and_is_recorded(tmp_path, run_a, small_setup_file):
    out = tmp_path / "OUT"
    r = run_inprocess("simulate", "--setup", str(small_setup_file), "--bulge-mm", "3", "--out", str(out), "--quiet")
    assert r.exit_code == 0, r.output
    manifest = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
    setup_doc = tomllib.loads(manifest["setup_toml"])
    assert setup_doc["screen"]["bulge_mm"] == 3.0
    with h5py.File(out / "mapping.h5", "r") as f:
        assert tomllib.loads(f.attrs["setup_toml"])["screen"]["bulge_mm"] == 3.0
    flat, bulged = read_mapping(run_a["out"] / "mapping.h5"), read_mapping(out / "mapping.h5")
    for cam in ("left", "right"):
        both = flat[cam]["valid"] & bulged[cam]["valid"]
        assert both.sum() > 0.5 * both.size
        d = np.abs(flat[cam]["screen_xy_mm"][both] - bulged[cam]["screen_xy_mm"][both])
        assert d.max() > 0.1, cam  # a 3 mm bulge moves the mapped points by a visible amount
    # the images change too
    a, b = snapshot(run_a["out"]), snapshot(out)
    assert sum(a[k] != b[k] for k in a if k.endswith(".png")) > 0
