"""Reliability on the paths added since issue 11 (issue 24; docs/reliability.md, "Issue 24").

Each case is met the way a user meets it: a real ``python -m pmdsim.cli`` subprocess, real
files and directories (their bytes are the truth: a refused command must leave them
unchanged), real signals. The cases: outputs that touch an input (item 1), over-long paths
and SIGHUP (item 5).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pmdsim.io.outputs import MARKER_NAME


def run(*args, timeout: float = 120, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pmdsim.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


def snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def one_error_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.startswith("pmdsim: error:")]
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


@pytest.fixture()
def pose_dirs(tmp_path):
    """Two calibration pose directories holding a fringe image and a manifest (their bytes are
    what must survive; the command is refused before it reads them)."""
    dirs = []
    for k in (0, 3):
        d = tmp_path / "calx" / f"pose{k}"
        d.mkdir(parents=True)
        (d / "left_x_p0_s0.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
        (d / "manifest.json").write_text(json.dumps({"format": "pmdsim-imageset", "pose": k}), encoding="utf-8")
        dirs.append(d)
    return dirs


@pytest.mark.parametrize("victim", ["pose0/left_x_p0_s0.png", "pose3/manifest.json", "pose3/new.toml"])
def test_calibrate_out_inside_an_input_directory_is_refused(tmp_path, pose_dirs, victim):
    """Issue 24's data loss: `calibrate … --out calx/pose0/left_x_p0_s0.png --force` replaced an
    input fringe image with TOML (exit 0). Now refused (exit 2) before anything is read or
    written; the message names the input and does not suggest --force."""
    before = snapshot(tmp_path / "calx")
    out = tmp_path / "calx" / victim
    r = run("calibrate", *pose_dirs, "--out", out, "--force", "--quiet")
    line = one_error_line(r.stderr)
    assert r.returncode == 2, r.stderr
    assert "inside an input" in line and str(pose_dirs[0 if "pose0" in victim else 1]) in line
    assert "pass --force" not in line
    assert snapshot(tmp_path / "calx") == before
    assert sorted(p.name for p in (tmp_path / "calx").rglob(".*")) == []  # no lock, no partial


def test_evaluate_out_inside_its_image_set_is_refused(tmp_path, pose_dirs):
    before = snapshot(tmp_path / "calx")
    r = run("evaluate", pose_dirs[0], "--out", pose_dirs[0] / "ev", "--quiet")
    assert r.returncode == 2 and "inside an input" in one_error_line(r.stderr)
    assert snapshot(tmp_path / "calx") == before and not (pose_dirs[0] / "ev").exists()


def test_force_is_suggested_only_where_it_is_accepted(tmp_path, pose_dirs):
    """Without --force: a user's directory gets no "--force" hint (it would be refused), a
    directory pmdsim wrote does (--force replaces it), an input never does."""
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep\n", encoding="utf-8")
    r = run("evaluate", pose_dirs[0], "--out", user, "--quiet")
    line = one_error_line(r.stderr)
    assert r.returncode == 2 and "--force" in line and "pass --force" not in line and "not a pmdsim output" in line
    r = run("evaluate", pose_dirs[0], "--out", user, "--quiet", "--force")  # and indeed --force is refused
    assert r.returncode == 2 and (user / "notes.txt").read_text() == "keep\n"

    ours = tmp_path / "ours"
    ours.mkdir()
    (ours / MARKER_NAME).write_text(json.dumps({"format": "pmdsim-output"}), encoding="utf-8")
    r = run("evaluate", pose_dirs[0], "--out", ours, "--quiet")
    assert r.returncode == 2 and "pass --force to replace it" in one_error_line(r.stderr)

    r = run("evaluate", pose_dirs[0], "--out", pose_dirs[0], "--quiet")  # the input itself
    line = one_error_line(r.stderr)
    assert r.returncode == 2 and "is an input" in line and "pass --force" not in line


def test_output_containing_or_through_a_link_to_an_input(tmp_path, pose_dirs):
    """A pmdsim output directory that holds an input (a symbolic link to one counts too) is not
    replaced by --force."""
    ours = tmp_path / "ours"
    ours.mkdir()
    (ours / MARKER_NAME).write_text(json.dumps({"format": "pmdsim-output"}), encoding="utf-8")
    setup = ours / "setup.toml"
    r = run("setup", "--show")
    setup.write_text(r.stdout, encoding="utf-8")
    before = snapshot(ours)
    r = run("evaluate", pose_dirs[0], "--setup", setup, "--out", ours, "--force", "--quiet")
    assert r.returncode == 2 and "a parent of an input" in one_error_line(r.stderr)
    link = tmp_path / "link"
    link.symlink_to(pose_dirs[0])
    r = run("calibrate", pose_dirs[0], "--out", link / "cal.toml", "--force", "--quiet")
    assert r.returncode == 2 and "inside an input" in one_error_line(r.stderr)
    assert snapshot(ours) == before


# ----------------------------------------------------------------------------- item 2: stereo
@pytest.fixture(scope="module")
def stereo_set(tmp_path_factory):
    """A simulated two-camera image set of the Table 1 setup binned 12× (160 × 100 px)."""
    from pmdsim.setup import default_setup

    d = tmp_path_factory.mktemp("stereo")
    setup_file = d / "setup.toml"
    setup_file.write_text(default_setup().binned(12).to_toml(), encoding="utf-8")
    r = run("simulate", "--setup", setup_file, "--out", d / "img", "--quiet")
    assert r.returncode == 0, r.stderr
    return d, setup_file


def test_stereo_runs_the_consistency_checks(tmp_path, stereo_set):
    """Issue 24: with one black frame mono exited 1, stereo exited 0 with heights off by up to
    1236 µm. Now stereo checks each camera like mono: the frame is named, exit 1, nothing
    written; the clean set still passes (its flat sample's heights within 1 µm: the truth is
    the plane z = 0)."""
    import shutil

    import h5py

    d, setup_file = stereo_set
    img = tmp_path / "img"
    shutil.copytree(d / "img", img)
    manifest = json.loads((img / "manifest.json").read_text())
    victim = next(e["file"] for e in manifest["images"] if e["camera"] == manifest["images"][0]["camera"]
                  and e["direction"] == "x" and e.get("shift_index", 1) == 1)
    from pmdsim.io.images import read_image, write_png

    a = read_image(img / victim)
    write_png(img / victim, np.zeros_like(a))
    for extra in ([], ["--stereo"]):
        r = run("evaluate", img, "--setup", setup_file, "--out", tmp_path / f"ev{len(extra)}", *extra, "--quiet")
        line = one_error_line(r.stderr)
        assert r.returncode == 1 and victim.rsplit("_s", 1)[0] in line, r.stderr
        assert not (tmp_path / f"ev{len(extra)}").exists()
    r = run("evaluate", d / "img", "--setup", setup_file, "--out", tmp_path / "ok", "--stereo", "--quiet")
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "ok" / "evaluation.h5") as f:
        for cam in f.attrs.get("cameras", []) or [k for k in f if isinstance(f[k], h5py.Group) and "overlap" in f[k]]:
            assert "consistency_flags" in f[cam]
            ov = f[cam]["overlap"][()]
            assert np.nanmax(np.abs(f[cam]["height_mm"][()][ov])) * 1e3 <= 1.0


def test_stereo_refuses_method_and_honours_min_valid_fraction(tmp_path, stereo_set):
    d, setup_file = stereo_set
    r = run("evaluate", d / "img", "--setup", setup_file, "--out", tmp_path / "a", "--stereo", "--method",
            "stepwise", "--quiet")
    assert r.returncode == 2 and "--method stepwise does not apply to --stereo" in one_error_line(r.stderr)
    # A band of 10 % of one frame's columns black: those pixels are flagged (FIT_RESIDUAL), the
    # camera's valid fraction drops to ≈ 90 %: a warning by default, exit 1 below a 95 % minimum.
    import shutil

    from pmdsim.io.images import read_image, write_png

    img = tmp_path / "img"
    shutil.copytree(d / "img", img)
    manifest = json.loads((img / "manifest.json").read_text())
    e = next(e for e in manifest["images"] if e["direction"] == "y")
    a = read_image(img / e["file"])
    w = a.shape[1]
    a[:, w // 2: w // 2 + w // 10] = 0
    write_png(img / e["file"], a)
    r = run("evaluate", img, "--setup", setup_file, "--out", tmp_path / "b", "--stereo", "--quiet")
    assert r.returncode == 0 and "pmdsim: warning: " + e["camera"] in r.stderr, r.stderr
    r = run("evaluate", img, "--setup", setup_file, "--out", tmp_path / "c", "--stereo", "--min-valid-fraction",
            "0.95", "--quiet")
    line = one_error_line(r.stderr)
    assert r.returncode == 1 and "minimum 95%" in line and e["camera"] in line, r.stderr
    assert (tmp_path / "c" / "evaluation.h5").exists()  # outputs kept for inspection, as for mono


# ----------------------------------------------------------------------------- item 7: curved samples
@pytest.mark.parametrize("kind, radius_mm", [("sphere", 300.0), ("sphere", -300.0), ("sphere", 1000.0),
                                             ("sphere", -1000.0), ("cylinder", 500.0)])
def test_curved_samples_are_not_masked_as_folds(tmp_path, kind, radius_mm):
    """Issue 24: a 1 m sphere through the CLI masked 210 px as folded geometry that reconstruct
    correctly; a concave R = 300 mm sphere (seen beyond its focal distance, the image inverts)
    was refused as "a reversed shift order". The orientation reference is now the mapping
    traced through the declared sample: no pixel is flagged GEOMETRY, every usable pixel is
    reconstructed, and their decoded screen coordinates are the traced ones (truth: the tracer's
    mapping through the closed-form surface) within 6 σ."""
    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import evaluate_image_set, simulate_to_dir

    setup = default_setup().binned(16).with_sample_shape(kind, radius_mm=radius_mm)
    simulate_to_dir(setup, tmp_path / "img")
    s = evaluate_image_set(tmp_path / "img", setup, tmp_path / "ev")
    import h5py

    from pmdsim.simulation.render import trace_setup_camera

    for cam, c in s.cameras.items():
        assert c["consistency_counts"]["GEOMETRY"] == 0, (cam, c["consistency_counts"])
        assert c["reconstructed"] == c["usable"]
        with h5py.File(tmp_path / "ev" / "evaluation.h5") as f:
            xy = f[cam]["screen_xy_mm"][()]
            sd = f[cam]["std_xy_mm"][()]
        truth = trace_setup_camera(setup, cam).screen_xy_mm
        ok = np.isfinite(xy).all(axis=-1)
        z = np.abs(xy[ok] - truth[ok]) / sd[ok]
        assert ok.sum() > 0 and np.nanmax(z) < 6.0, (cam, np.nanmax(z))  # the kept pixels' data are right


def test_reversed_shift_order_on_a_concave_sample_is_still_caught(tmp_path):
    """The traced reference keeps the orientation test's power on a curved sample."""
    import shutil

    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import ConsistencyFailure, evaluate_image_set, simulate_to_dir

    setup = default_setup().binned(16).with_sample_shape("sphere", radius_mm=-300.0)
    simulate_to_dir(setup, tmp_path / "img")
    m = json.loads((tmp_path / "img" / "manifest.json").read_text())
    for e in m["images"]:
        if e["shift_index"] in (1, 3):
            e["shift_index"] = 4 - e["shift_index"]
    (tmp_path / "img" / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ConsistencyFailure, match="orientation is flipped"):
        evaluate_image_set(tmp_path / "img", setup, tmp_path / "ev")
    assert not (tmp_path / "ev").exists()
    shutil.rmtree(tmp_path / "img")
