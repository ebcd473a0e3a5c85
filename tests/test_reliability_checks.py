"""Checks before any work and after a calibration (issue 11), through the CLI as a user runs it.

* image sizes against the setup (also with --setup forgotten), memory for huge cameras,
  --downsample out of range: one line ``pmdsim: error: …``, exit 2, nothing written;
* ``pmdsim setup --setup``: coverage, clipping, coarsest period, noise vs period steps;
* ``pmdsim calibrate``: residuals compared with the noise the images show; one pose taken with
  a camera moved by 5 mm is named.

Truths: sizes written into the TOML by text edits (not by pmdsim's writer), the clipping
arithmetic of docs/conventions.md, geometry (a camera turned away from the sample sees nothing),
and a simulated calibration whose bad pose is known.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.studies.checks import InsufficientMemoryError, check_memory, estimate_bytes

from conftest import SMALL_H, SMALL_W, replace_exactly


def _run(args):
    r = CliRunner().invoke(main, args)
    assert "Traceback" not in r.output
    return r


def _errors(r) -> list[str]:
    return [line for line in r.output.splitlines() if line.startswith("pmdsim: error:")]


@pytest.fixture(scope="module")
def small_set(tmp_path_factory, small_setup_file):
    d = tmp_path_factory.mktemp("sets") / "small"
    r = _run(["simulate", "--setup", str(small_setup_file), "--out", str(d), "--quiet"])
    assert r.exit_code == 0, r.output
    return d


# ----------------------------------------------------------------------------- image sizes
def test_evaluate_without_setup_refuses_other_image_size(tmp_path, small_set):
    out = tmp_path / "ev"
    r = _run(["evaluate", str(small_set), "--out", str(out), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert f"{SMALL_W}×{SMALL_H}" in err and "1920×1200" in err and "no --setup given" in err
    assert not out.exists()


def test_evaluate_with_other_setup_refuses(tmp_path, small_set, small_toml):
    other = tmp_path / "other.toml"
    t = replace_exactly(small_toml, f"image_size_px = [{SMALL_W}, {SMALL_H}]", "image_size_px = [480, 300]", 2)
    other.write_text(t)
    r = _run(["evaluate", str(small_set), "--setup", str(other), "--out", str(tmp_path / "ev"), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert f"{SMALL_W}×{SMALL_H}" in err and "480×300" in err and str(other) in err


def test_calibrate_without_setup_refuses_other_image_size(tmp_path, small_set):
    """The issue: calibrate without --setup on small images wrote a 1920×1200 camera. Now: refused
    before any decoding, nothing written."""
    n_poses = len(load_setup_default_poses())
    out = tmp_path / "cal.toml"
    r = _run(["calibrate", *[str(small_set)] * n_poses, "--out", str(out), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert f"{SMALL_W}×{SMALL_H}" in err and "1920×1200" in err
    assert not out.exists()


def load_setup_default_poses():
    from pmdsim.setup import default_setup

    s = default_setup()
    return s.calibration.mirror_poses(s.sample)


# ----------------------------------------------------------------------------- memory, binning
def test_huge_camera_refused_before_allocation(tmp_path, default_toml):
    # 60000 px per side: a plausible camera model (pmdsim.geometry.camera_checks refuses more
    # than 65536), whose images would not fit in memory: the memory estimate refuses it.
    huge = tmp_path / "huge.toml"
    huge.write_text(replace_exactly(default_toml, "image_size_px = [1920, 1200]", "image_size_px = [60000, 60000]", 2))
    out = tmp_path / "sim"
    r = _run(["simulate", "--setup", str(huge), "--out", str(out), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert "60000×60000" in err and "GiB" in err
    assert not out.exists()
    r = _run(["experiment", "1", "--setup", str(huge), "--out", str(tmp_path / "e1"), "--quiet"])
    assert r.exit_code == 2 and "GiB" in _errors(r)[0]


def _huge_png(path: Path, width: int, height: int) -> None:
    """A valid PNG header claiming width × height px (the pixel data are not there)."""
    import struct
    import zlib

    from PIL import Image

    Image.new("L", (2, 2)).save(path)
    b = bytearray(path.read_bytes())
    assert b[12:16] == b"IHDR"
    b[16:24] = struct.pack(">II", width, height)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])))
    path.write_bytes(bytes(b))


def test_huge_image_file_refused(tmp_path, small_set, small_setup_file, default_toml):
    """An image set whose first image claims 100000×100000 px: refused from its header (no
    cameras block in the manifest), or when read (PIL's decompression-bomb limit), or — when the
    setup and manifest agree on that size — by the memory estimate; never a 149 GiB allocation."""
    import json
    import shutil

    d = tmp_path / "set"
    shutil.copytree(small_set, d)
    _huge_png(d / "left_x_p0_s0.png", 100000, 100000)
    r = _run(["evaluate", str(d), "--setup", str(small_setup_file), "--out", str(tmp_path / "ev"), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert "left_x_p0_s0.png" in err and "10000000000 pixels" in err
    doc = json.loads((d / "manifest.json").read_text())
    del doc["cameras"]
    (d / "manifest.json").write_text(json.dumps(doc))
    r = _run(["evaluate", str(d), "--out", str(tmp_path / "ev"), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert "left_x_p0_s0.png" in err
    # The same size in the setup: the size check passes, the memory estimate refuses.
    huge = tmp_path / "huge.toml"
    huge.write_text(replace_exactly(default_toml, "image_size_px = [1920, 1200]", "image_size_px = [60000, 60000]", 2))
    d2 = tmp_path / "set2"
    shutil.copytree(small_set, d2)
    man = d2 / "manifest.json"
    doc = json.loads(man.read_text())
    doc["cameras"] = {c: {"image_size_px": [60000, 60000]} for c in doc["cameras"]}
    man.write_text(json.dumps(doc))
    r = _run(["evaluate", str(d2), "--setup", str(huge), "--out", str(tmp_path / "ev2"), "--quiet"])
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert "GiB" in err and "60000×60000" in err


def test_memory_estimate_scales_with_pixels(default_toml, tmp_path):
    from pmdsim.setup import default_setup

    s = default_setup()
    full = estimate_bytes(s, "evaluate")
    assert estimate_bytes(s.binned(2), "evaluate") == pytest.approx(full / 4, rel=1e-3)
    with pytest.raises(InsufficientMemoryError, match="1920×1200"):
        check_memory(s, "evaluate", available=full - 1)
    assert check_memory(s, "evaluate", available=full) == full


def test_downsample_out_of_range(tmp_path):
    r = _run(["experiment", "1", "--downsample", "5000", "--out", str(tmp_path / "e"), "--quiet"])
    assert r.exit_code == 2
    (err,) = _errors(r)
    assert "5000" in err and "1920×1200" in err


# ----------------------------------------------------------------------------- setup --setup
def _setup_run(tmp_path, text):
    p = tmp_path / "s.toml"
    p.write_text(text)
    return _run(["setup", "--setup", str(p)])


def test_setup_check_ok(tmp_path, small_toml):
    r = _setup_run(tmp_path, small_toml)
    assert r.exit_code == 0 and "setup OK" in r.output and "warning" not in r.output
    assert "cameras.left:" in r.output and "see the screen via the sample" in r.output


def test_setup_check_camera_sees_nothing(tmp_path, small_toml):
    # The left camera turned by 180° about its x axis looks away from the sample.
    t = replace_exactly(small_toml, "angles_deg = [45.0, 10.0, 10.0]", "angles_deg = [225.0, 10.0, 10.0]", 1)
    r = _setup_run(tmp_path, t)
    assert r.exit_code == 0, r.output
    assert "pmdsim: warning: cameras.left: no pixel sees the screen" in r.output
    t2 = replace_exactly(t, "angles_deg = [45.0, -10.0, -10.0]", "angles_deg = [225.0, -10.0, -10.0]", 1)
    r = _setup_run(tmp_path, t2)
    assert r.exit_code == 2 and "no camera sees the screen" in _errors(r)[0]


def test_setup_check_clipping(tmp_path, small_toml):
    t = replace_exactly(small_toml, "mean_level = 0.5", "mean_level = 0.6", 1)
    r = _setup_run(tmp_path, t)
    assert r.exit_code == 0 and "mean_level + amplitude = 1.05 > 1" in r.output  # 0.6 + 0.45
    t = replace_exactly(small_toml, "mean_level = 0.5", "mean_level = 0.4", 1)
    r = _setup_run(tmp_path, t)
    assert r.exit_code == 0 and "mean_level − amplitude = -0.05 < 0" in r.output


def test_setup_check_coarsest_period(tmp_path, small_toml):
    t = replace_exactly(small_toml, "periods_x_mm = [720.0, 60.0, 4.0]", "periods_x_mm = [600.0, 60.0, 4.0]", 1)
    r = _setup_run(tmp_path, t)
    assert r.exit_code == 2, r.output
    (err,) = _errors(r)
    assert "patterns.periods_x_mm" in err and "600 mm" in err and "708 mm" in err


def test_setup_check_period_step_vs_noise(tmp_path, small_toml):
    # σ of the 720 mm period at σ_I = 5 grey levels: 720/2π·√(2/4)·5/114.75 ≈ 3.5 mm; ×5 > 0.25·4 mm.
    t = replace_exactly(small_toml, "periods_x_mm = [720.0, 60.0, 4.0]", "periods_x_mm = [720.0, 4.0]", 1)
    t = replace_exactly(t, "noise_std = 0.0", "noise_std = 5.0", 1)
    r = _setup_run(tmp_path, t)
    assert r.exit_code == 0 and "step 720 → 4 mm is too large for the noise" in r.output


# ----------------------------------------------------------------------------- calibrate residuals
@pytest.fixture(scope="module")
def calibration_sets(tmp_path_factory, small_toml):
    """6 poses (base, one lift, 4 tilts) of the small noisy setup, and pose 3 again with the left
    camera moved by 5 mm along world x."""
    root = tmp_path_factory.mktemp("cal")
    t = replace_exactly(small_toml, "noise_std = 0.0", "noise_std = 1.0", 1)
    t = replace_exactly(t, "mirror_lifts_mm = [10.0, 20.0, 30.0]", "mirror_lifts_mm = [10.0]", 1)
    t = replace_exactly(t, "mirror_tilts_deg = [1.0, 2.0, 3.0]", "mirror_tilts_deg = [2.0]", 1)
    nominal = root / "nominal.toml"
    nominal.write_text(t)
    moved = root / "moved.toml"
    moved.write_text(replace_exactly(t, "origin_world_mm = [-90.0, 295.0, -295.0]",
                                     "origin_world_mm = [-85.0, 295.0, -295.0]", 1))
    dirs = []
    for k in range(6):
        d = root / f"p{k}"
        r = _run(["simulate", "--setup", str(nominal), "--calibration-pose", str(k), "--out", str(d), "--quiet"])
        assert r.exit_code == 0, r.output
        dirs.append(d)
    bad = root / "p3moved"
    r = _run(["simulate", "--setup", str(moved), "--calibration-pose", "3", "--out", str(bad), "--quiet"])
    assert r.exit_code == 0, r.output
    return nominal, dirs, bad


def test_calibrate_clean_no_warning(tmp_path, calibration_sets):
    nominal, dirs, _ = calibration_sets
    out = tmp_path / "cal.toml"
    r = _run(["calibrate", *map(str, dirs), "--setup", str(nominal), "--out", str(out), "--stride", "2", "--quiet"])
    assert r.exit_code == 0, r.output
    assert "warning" not in r.output
    rep = tomllib.loads(out.read_text())["calibration_report"]
    # A model that fits leaves residuals at the noise the images show (ratio ≈ 1).
    assert 0.5 < rep["residual_to_noise_ratio"] < 2.0, rep["residual_to_noise_ratio"]


def test_calibrate_names_the_bad_pose(tmp_path, calibration_sets):
    nominal, dirs, bad = calibration_sets
    mixed = [*dirs[:3], bad, *dirs[4:]]
    out = tmp_path / "cal.toml"
    r = _run(["calibrate", *map(str, mixed), "--setup", str(nominal), "--out", str(out), "--stride", "2",
              "--max-iter", "400", "--quiet"])
    assert r.exit_code == 0, r.output
    warn = [line for line in r.output.splitlines() if line.startswith("pmdsim: warning: calibration RMS")]
    assert len(warn) == 1 and "pose 3" in warn[0] and "'left'" in warn[0], r.output
    for k in (0, 1, 2, 4, 5):
        assert f"pose {k} " not in warn[0]
    rep = tomllib.loads(out.read_text())["calibration_report"]
    assert rep["residual_to_noise_ratio"] > 10
    ratios = rep["residual_ratio_by_camera_pose"]["left"]
    assert max(ratios, key=ratios.get) == "pose3"
