"""Tests of pmdsim.imageset: manifests, image stacks and decoding of image sets on disk.

The image sets are written here with Pillow and numpy, independently of pmdsim's writers, from
a known *linear* screen-coordinate field per camera, c(u, v) = c0 + a·u + b·v (mm), rendered
with the fringe model of docs/conventions.md:

    I_k = round(A + B·cos(2π·c/p − 2π·k/N)),   8 bit: A = 127.5, B = 110.

Quantisation bound on the decoded coordinate (used by every decoding test)
--------------------------------------------------------------------------
With rounding errors e_k ∈ [−½, ½] the N-step sums are

    C = Σ I_k cos δ_k = (N·B/2)·cos φ + Σ e_k cos δ_k,
    S = Σ I_k sin δ_k = (N·B/2)·sin φ + Σ e_k sin δ_k,

i.e. the signal vector (N·B/2)(cos φ, sin φ) plus a perturbation of length
|Σ e_k e^{iδ_k}| ≤ Σ |e_k| ≤ N/2. Adding a vector of length d to one of length R turns it by at
most arcsin(d/R), so |Δφ| ≤ arcsin((N/2)/(N·B/2)) = arcsin(1/B) ≈ 1/B, independent of N. As
long as hierarchical unwrapping picks the right fringe order (the coarser levels' errors,
p_coarse/(2πB), are far below 0.25·p_finer here), the coordinate is p_f·(φ/2π + order), so

    |c_decoded − c_true| ≤ p_f/(2π) · arcsin(1/B)  ≈  p_f/(2π) · (1/B)

for the finest period p_f.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from pmdsim.geometry.camera import Camera
from pmdsim.cli import main
from pmdsim.errors import ImageSetError
from pmdsim.io.imageset import (
    CameraImages,
    ImageSetManifest,
    camera_images_from_arrays,
    decode_camera,
    decode_camera_images,
    load_camera_stacks,
    load_manifest,
)
from pmdsim.setup import CameraSetup, default_setup

H, W = 40, 64
SCREEN_MM = (400.0, 300.0)
PERIODS = {"x": (420.0, 30.0, 4.0), "y": (320.0, 25.0, 4.0)}
N_SHIFTS = 4
A8, B8 = 127.5, 110.0
A16, B16 = 32767.5, 28000.0

# Linear coordinate fields c = c0 + a·u + b·v (mm), inside the 400 × 300 mm screen.
FIELDS = {
    "left": {"x": (20.0, 5.5, 0.3), "y": (15.0, 0.2, 6.5)},
    "right": {"x": (380.0, -5.0, 0.4), "y": (290.0, -0.3, -6.0)},
}


def true_field(camera: str) -> np.ndarray:
    """(H, W, 2) true (x_q, y_q) in mm of ``camera``."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([c0 + a * u + b * v for c0, a, b in (FIELDS[camera]["x"], FIELDS[camera]["y"])], axis=-1)


def fringe(coord: np.ndarray, period: float, k: int, n: int, bits: int = 8) -> np.ndarray:
    """One quantised fringe image (round half up, as the simulator does)."""
    a, b = (A8, B8) if bits == 8 else (A16, B16)
    img = np.floor(a + b * np.cos(2 * np.pi * coord / period - 2 * np.pi * k / n) + 0.5)
    return img.astype(np.uint8 if bits == 8 else np.uint16)


def bound_mm(p_finest: float, amplitude: float) -> float:
    """p_f/(2π)·arcsin(1/B) (module docstring) plus float slack."""
    return p_finest / (2 * np.pi) * math.asin(1.0 / amplitude) + 1e-9


def save(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(path)  # uint8 → mode L, uint16 → mode I;16


def write_full_set(d: Path, cameras=("left", "right"), bits: int = 8) -> dict:
    """A ``pmdsim simulate``-style image set (all manifest keys); returns the manifest dict."""
    d.mkdir(parents=True, exist_ok=True)
    entries = []
    for cam in cameras:
        xy = true_field(cam)
        for axis, direction in enumerate("xy"):
            for pi, p in enumerate(PERIODS[direction]):
                for k in range(N_SHIFTS):
                    f = f"{cam}_{direction}_p{pi}_s{k}.png"
                    save(d / f, fringe(xy[..., axis], p, k, N_SHIFTS, bits))
                    entries.append({"file": f, "camera": cam, "direction": direction, "period_mm": p,
                                    "period_index": pi, "shift_index": k, "n_shifts": N_SHIFTS})
    doc = {
        "format": "pmdsim-imageset", "format_version": 1, "pmdsim_version": "test", "command": "test",
        "setup_toml": "", "bit_depth": bits, "screen_size_mm": list(SCREEN_MM),
        "cameras": {c: {"image_size_px": [W, H], "status_counts": {"VALID": H * W}} for c in cameras},
        "images": entries,
    }
    write_manifest(d, doc)
    return doc


def write_manifest(d: Path, doc) -> None:
    (d / "manifest.json").write_text(json.dumps(doc, indent=1), encoding="utf-8")


# Minimal user set: TIFFs in a subfolder, period_fraction, no n_shifts, shuffled entries,
# N = 3, 4, 5 shifts for the three periods; no screen size in the manifest.
USER_SHIFTS = (3, 4, 5)


def write_user_set(d: Path, seed: int = 1) -> dict:
    entries = []
    for cam in ("cam_b", "cam_a"):  # not alphabetical: order of first appearance counts
        xy = true_field("left" if cam == "cam_a" else "right")
        for axis, direction in enumerate("xy"):
            for p, n in zip(PERIODS[direction], USER_SHIFTS):
                for k in range(n):
                    f = f"raw/{cam}_{len(entries):04d}.tif"
                    save(d / f, fringe(xy[..., axis], p, k, n))
                    entries.append({"file": f, "camera": cam, "direction": direction,
                                    "period_fraction": p / SCREEN_MM[axis], "shift_index": k})
    first = entries[0]
    rest = entries[1:]
    np.random.default_rng(seed).shuffle(rest)
    doc = {"images": [first] + rest}
    write_manifest(d, doc)
    return doc


@pytest.fixture(scope="module")
def full_set(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("full") / "set"
    write_full_set(d)
    return d


@pytest.fixture(scope="module")
def user_set(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("user") / "set"
    write_user_set(d)
    return d


# ============================================================================ manifest layout
def test_full_manifest_layout(full_set):
    m = load_manifest(full_set)
    assert isinstance(m, ImageSetManifest)
    assert m.cameras == ("left", "right")
    assert m.screen_size_mm == SCREEN_MM and m.bit_depth == 8
    assert m.path == full_set / "manifest.json" and m.directory == full_set
    assert m.image_size_px["right"] == (W, H)
    for cam in m.cameras:
        for d in "xy":
            assert m.periods_mm(cam, d) == PERIODS[d]
            for pi, p in enumerate(PERIODS[d]):
                assert m.files(cam, d, p) == tuple(full_set / f"{cam}_{d}_p{pi}_s{k}.png" for k in range(N_SHIFTS))
    assert len(m.entries) == 2 * 2 * 3 * N_SHIFTS
    # The manifest file itself may be given instead of the directory.
    assert load_manifest(full_set / "manifest.json").cameras == m.cameras


def test_user_manifest_fraction_and_order(user_set):
    doc = json.loads((user_set / "manifest.json").read_text())
    m = load_manifest(user_set, screen_size_mm=SCREEN_MM)
    assert m.cameras == ("cam_b", "cam_a")
    for cam in m.cameras:
        for axis, d in enumerate("xy"):
            got = m.periods_mm(cam, d)
            # period_fraction × screen width (x) / height (y), coarsest first
            assert got == pytest.approx(PERIODS[d], rel=1e-12)
            for g, n in zip(m.groups(cam, d), USER_SHIFTS):
                assert g.n_shifts == n
                # ordered by shift index regardless of the (shuffled) manifest order
                assert [e.shift_index for e in g.entries] == list(range(n))
                for e in g.entries:
                    raw = doc["images"][e.index]
                    assert (raw["camera"], raw["direction"], raw["shift_index"]) == (cam, d, e.shift_index)
                    assert raw["period_fraction"] * SCREEN_MM[axis] == pytest.approx(g.period_mm, rel=1e-12)
                    assert e.path == user_set / raw["file"]
    # The argument overrides a manifest's screen size.
    assert load_manifest(user_set, screen_size_mm=(800, 600)).periods_mm("cam_a", "x")[0] == pytest.approx(840.0)


# ============================================================================ decoding
def check_decoded(res, camera: str, p_finest: float, amplitude: float) -> float:
    truth = true_field(camera)
    assert res.valid.all(), f"{(~res.valid).sum()} invalid pixels, flags {np.unique(res.flags)}"
    err = np.abs(res.screen_xy_mm - truth).max()
    assert err <= bound_mm(p_finest, amplitude), (err, bound_mm(p_finest, amplitude))
    return err


def test_decode_full_set_8bit(full_set):
    m = load_manifest(full_set)
    for cam in m.cameras:
        res = decode_camera(m, cam)
        err = check_decoded(res, cam, 4.0, B8)
        # Not vacuous: 8-bit quantisation is visible, at most the bound (~5.8 µm).
        assert err > 0.05 * bound_mm(4.0, B8)


def test_decode_user_tiff_fraction(user_set):
    m = load_manifest(user_set, screen_size_mm=SCREEN_MM)
    check_decoded(decode_camera(m, "cam_a"), "left", 4.0, B8)
    check_decoded(decode_camera(m, "cam_b"), "right", 4.0, B8)
    # Without a screen size in the manifest object, decode_camera needs the argument.
    with pytest.raises(ImageSetError, match="screen size is unknown"):
        decode_camera(replace(m, screen_size_mm=None), "cam_a")
    res = decode_camera(replace(m, screen_size_mm=None), "cam_a", screen_size_mm=SCREEN_MM)
    check_decoded(res, "left", 4.0, B8)


def test_decode_16bit_png(tmp_path):
    d = tmp_path / "s16"
    write_full_set(d, cameras=("left",), bits=16)
    m = load_manifest(d)
    imgs = load_camera_stacks(m, "left")
    assert imgs.max_value == 65535 and imgs.bit_depth == 16
    assert all(s.dtype == np.uint16 for s in imgs.x_stacks + imgs.y_stacks)
    # 16-bit bound (B = 28000): 4/(2π)/28000 ≈ 0.023 µm, 250× tighter than 8 bit.
    check_decoded(decode_camera(m, "left"), "left", 4.0, B16)


def test_decode_needs_screen_size_and_long_coarsest_period(full_set):
    m = load_manifest(full_set)
    with pytest.raises(ImageSetError, match="screen size is unknown"):
        decode_camera(replace(m, screen_size_mm=None), "left")
    with pytest.raises(ImageSetError, match=r"direction 'x'.*coarsest period 420 mm.*width 500 mm"):
        decode_camera(m, "left", screen_size_mm=(500.0, 300.0))
    with pytest.raises(ImageSetError, match="no camera 'middle'"):
        decode_camera(m, "middle")


# ============================================================================ stacks
def read_independently(d: Path, f: str) -> np.ndarray:
    with Image.open(d / f) as im:
        return np.array(im)


def test_stacks_match_files_and_in_memory(full_set, user_set):
    for d, screen in ((full_set, None), (user_set, SCREEN_MM)):
        doc = json.loads((d / "manifest.json").read_text())
        m = load_manifest(d, screen_size_mm=screen)
        for cam in m.cameras:
            imgs = load_camera_stacks(m, cam)
            assert isinstance(imgs, CameraImages)
            assert imgs.camera == cam and imgs.shape == (H, W) and imgs.max_value == 255
            for direction in "xy":
                stacks = imgs.stacks(direction)
                assert imgs.periods_mm(direction) == m.periods_mm(cam, direction)
                for g, s in zip(m.groups(cam, direction), stacks):
                    assert s.shape == (g.n_shifts, H, W) and s.dtype == np.uint8
                    assert not s.flags.writeable
                    for k, e in enumerate(g.entries):
                        np.testing.assert_array_equal(s[k], read_independently(d, doc["images"][e.index]["file"]))
            # The same from in-memory arrays (all cameras' entries, camera selected).
            arrays = [read_independently(d, e["file"]) for e in doc["images"]]
            mem = camera_images_from_arrays(doc["images"], arrays, camera=cam, screen_size_mm=screen)
            assert mem.shape == imgs.shape and mem.max_value == imgs.max_value
            assert mem.x_periods_mm == imgs.x_periods_mm and mem.y_periods_mm == imgs.y_periods_mm
            for a, b in zip(mem.x_stacks + mem.y_stacks, imgs.x_stacks + imgs.y_stacks, strict=True):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)


def test_in_memory_single_camera_without_files_and_decoding():
    entries, images = [], []
    xy = true_field("right")
    for d in ("y", "x"):
        axis = "xy".index(d)
        for p in PERIODS[d][::-1]:  # finest first: must come out coarsest first
            for k in range(N_SHIFTS):
                entries.append({"camera": "c", "direction": d, "period_mm": p, "shift_index": k})
                images.append(fringe(xy[..., axis], p, k, N_SHIFTS))
    imgs = camera_images_from_arrays(entries, images)
    assert imgs.x_periods_mm == PERIODS["x"] and imgs.y_periods_mm == PERIODS["y"]
    check_decoded(decode_camera_images(imgs, SCREEN_MM), "right", 4.0, B8)


@pytest.mark.parametrize("case, needles", [
    ("count", ["24 entries but 23 images"]),
    ("size", ["images[5]", "63×40", "64×40", "images[0]"]),
    ("float", ["images[2]", "float64"]),
    ("cameras", ["several cameras", "camera="]),
    ("bit_depth", ["images[0]", "8-bit", "'bit_depth' is 16"]),
])
def test_in_memory_errors(case, needles):
    xy = true_field("left")
    entries, images = [], []
    for axis, d in enumerate("xy"):
        for p in PERIODS[d]:
            for k in range(N_SHIFTS):
                entries.append({"camera": "c", "direction": d, "period_mm": p, "shift_index": k})
                images.append(fringe(xy[..., axis], p, k, N_SHIFTS))
    kw = {}
    if case == "count":
        images.pop()
    elif case == "size":
        images[5] = images[5][:, :-1]
    elif case == "float":
        images[2] = images[2].astype(float)
    elif case == "cameras":
        for e in entries[12:]:
            e["camera"] = "d"
    elif case == "bit_depth":
        kw["bit_depth"] = 16
    with pytest.raises(ImageSetError) as ei:
        camera_images_from_arrays(entries, images, **kw)
    for n in needles:
        assert n in str(ei.value), (n, str(ei.value))


# ============================================================================ malformed sets
# Entry order of the one-camera base set: left x p0 (420 mm) s0..3 = images[0..3],
# x p1 (30 mm) = images[4..7], x p2 (4 mm) = images[8..11], y = images[12..23].
def _e(doc, i):
    return doc["images"][i]


def _del_key(i, key):
    def f(d, doc):
        del _e(doc, i)[key]
    return f


def _set_key(i, key, value):
    def f(d, doc):
        _e(doc, i)[key] = value
    return f


def _set_top(key, value):
    def f(d, doc):
        doc[key] = value
    return f


def _fraction_without_screen(d, doc):
    del doc["screen_size_mm"]
    e = _e(doc, 4)
    e["period_fraction"] = e.pop("period_mm") / SCREEN_MM[0]


def _negative_fraction(d, doc):
    del _e(doc, 4)["period_mm"]
    _e(doc, 4)["period_fraction"] = -0.1


def _drop_entry(i):
    def f(d, doc):
        del doc["images"][i]
    return f


def _two_shifts_only(d, doc):
    doc["images"] = [e for e in doc["images"] if not (e["period_index"] == 1 and e["direction"] == "x"
                                                      and e["shift_index"] >= 2)]
    for e in doc["images"]:
        del e["n_shifts"]


def _delete_files(*names):
    def f(d, doc):
        for n in names:
            (d / n).unlink()
    return f


def _no_y(d, doc):
    doc["images"] = [e for e in doc["images"] if e["direction"] == "x"]


def _camera_not_in_table(d, doc):
    doc["cameras"] = {"other": {"image_size_px": [W, H]}}


def _write_image(i, img):
    def f(d, doc):
        (d / _e(doc, i)["file"]).unlink()
        Image.fromarray(img).save(d / _e(doc, i)["file"])
    return f


def _sixteen_bit_no_depth(d, doc):
    del doc["bit_depth"]
    _write_image(7, np.full((H, W), 1000, np.uint16))(d, doc)


def _corrupt(i):
    def f(d, doc):
        (d / _e(doc, i)["file"]).write_bytes(np.random.default_rng(5).bytes(3000))
    return f


def _invalid_json(d, doc):
    (d / "manifest.json").write_text('{"images": [ {"file": "a.png",, }', encoding="utf-8")
    return "raw"


def _no_manifest(d, doc):
    (d / "manifest.json").unlink()
    return "raw"


F3, F4, F6, F7 = "left_x_p0_s3.png", "left_x_p1_s0.png", "left_x_p1_s2.png", "left_x_p1_s3.png"

# (id, mutation, stage, needles): stage "manifest" fails in load_manifest, "stacks" in
# load_camera_stacks. Needles must all occur in the message.
MALFORMED = [
    ("no-manifest", _no_manifest, "manifest", ["manifest.json", "set"]),
    ("invalid-json", _invalid_json, "manifest", ["manifest.json", "invalid JSON", "line 1, column"]),
    ("top-level-list", lambda d, doc: write_manifest(d, [1, 2]) or "raw", "manifest", ["JSON object", "list"]),
    ("unknown-top-key", _set_top("screen_size", [1, 2]), "manifest", ["manifest.json", "'screen_size'"]),
    ("no-images", lambda d, doc: doc.pop("images") and None, "manifest", ["missing key 'images'"]),
    ("empty-images", _set_top("images", []), "manifest", ["'images'", "non-empty"]),
    ("wrong-format", _set_top("format", "pmdsim-setup"), "manifest", ["'format'", "pmdsim-imageset"]),
    ("format-version", _set_top("format_version", 2), "manifest", ["'format_version'", "2"]),
    ("bit-depth-11", _set_top("bit_depth", 11), "manifest", ["'bit_depth'", "8, 10, 12, 14, 16", "11"]),
    ("bad-screen-size", _set_top("screen_size_mm", [400, -1]), "manifest", ["'screen_size_mm'", "-1"]),
    ("entry-not-object", lambda d, doc: doc["images"].__setitem__(2, "x.png"), "manifest",
     ["images[2]", "object"]),
    ("missing-shift-index", _del_key(3, "shift_index"), "manifest", ["images[3]", F3, "'shift_index'", "missing"]),
    ("missing-file-key", _del_key(3, "file"), "manifest", ["images[3]", "'file'", "missing"]),
    ("missing-camera", _del_key(4, "camera"), "manifest", ["images[4]", F4, "'camera'"]),
    ("unknown-entry-key", _set_key(4, "perod_mm", 30.0), "manifest", ["images[4]", F4, "'perod_mm'", "unknown"]),
    ("bad-direction", _set_key(4, "direction", "z"), "manifest", ["images[4]", F4, "'direction'", "'z'"]),
    ("period-negative", _set_key(4, "period_mm", -30.0), "manifest", ["images[4]", F4, "'period_mm'", "-30"]),
    ("period-zero", _set_key(4, "period_mm", 0), "manifest", ["images[4]", F4, "'period_mm'", "positive"]),
    ("period-nan", _set_key(4, "period_mm", float("nan")), "manifest", ["images[4]", F4, "'period_mm'", "nan"]),
    ("period-inf", _set_key(4, "period_mm", float("inf")), "manifest", ["images[4]", F4, "'period_mm'", "inf"]),
    ("period-string", _set_key(4, "period_mm", "30"), "manifest", ["images[4]", F4, "'period_mm'", "'30'"]),
    ("fraction-negative", _negative_fraction, "manifest", ["images[4]", F4, "'period_fraction'", "-0.1"]),
    ("both-periods", _set_key(4, "period_fraction", 0.075), "manifest",
     ["images[4]", F4, "period_mm", "period_fraction", "both"]),
    ("neither-period", _del_key(4, "period_mm"), "manifest",
     ["images[4]", F4, "period_mm", "period_fraction", "neither"]),
    ("fraction-without-screen", _fraction_without_screen, "manifest",
     ["images[4]", F4, "'period_fraction'", "screen_size_mm"]),
    ("shift-bool", _set_key(3, "shift_index", True), "manifest", ["images[3]", F3, "'shift_index'"]),
    ("duplicate-shift", _set_key(3, "shift_index", 0), "manifest",
     ["images[3]", F3, "images[0]", "duplicate", "'shift_index'", "period 420 mm"]),
    ("repeated-file", _set_key(3, "file", "left_x_p0_s0.png"), "manifest", ["images[3]", "images[0]", "'file'"]),
    ("shift-missing", _drop_entry(6), "manifest",
     ["camera 'left'", "direction 'x'", "period 30 mm", "'shift_index'", "[2]", F7]),
    ("shift-out-of-range", _set_key(3, "shift_index", 7), "manifest",
     ["images[3]", F3, "'shift_index'", "7", "n_shifts"]),
    ("n-shifts-2", _set_key(0, "n_shifts", 2), "manifest", ["images[0]", "'n_shifts'", "≥ 3"]),
    ("n-shifts-differ", _set_key(5, "n_shifts", 5), "manifest", ["images[5]", "'n_shifts'", "differs", "period 30 mm"]),
    ("too-few-shifts", _two_shifts_only, "manifest", ["N = 2", "N ≥ 3", "period 30 mm", F4]),
    ("no-y-direction", _no_y, "manifest", ["camera 'left'", "direction 'y'"]),
    ("camera-not-in-table", _camera_not_in_table, "manifest", ["images[0]", "'camera'", "'left'", "'cameras'"]),
    ("period-index-differs", _set_key(5, "period_index", 0), "manifest", ["'period_index'", "period 30 mm"]),
    ("missing-files", _delete_files(F4, F7), "manifest", ["2 image file(s) missing", F4, F7, "images[4]", "images[7]"]),
    # --- load_camera_stacks
    ("different-size", _write_image(6, np.zeros((H, W - 1), np.uint8)), "stacks",
     ["images[6]", F6, "63×40", "64×40", "images[0]"]),
    ("16-bit-in-8-bit-set", _write_image(7, np.full((H, W), 1000, np.uint16)), "stacks",
     ["images[7]", F7, "16-bit", "'bit_depth' is 8"]),
    ("16-bit-vs-first-image", _sixteen_bit_no_depth, "stacks",
     ["images[7]", F7, "16-bit (uint16)", "expected 8-bit (uint8)", "images[0]"]),
    ("declared-16-bit", _set_top("bit_depth", 16), "stacks", ["images[0]", "8-bit", "'bit_depth' is 16"]),
    ("rgb", _write_image(6, np.zeros((H, W, 3), np.uint8)), "stacks", ["images[6]", F6, "not greyscale"]),
    ("corrupt-png", _corrupt(6), "stacks", ["images[6]", F6, "cannot read image"]),
    ("size-vs-table", lambda d, doc: doc["cameras"]["left"].update(image_size_px=[60, 40]), "stacks",
     ["images[0]", "image_size_px", "60×40", "64×40"]),
]


@pytest.fixture(scope="module")
def base_set(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("base") / "set"
    write_full_set(d, cameras=("left",))
    return d


@pytest.mark.parametrize("mutate, stage, needles", [c[1:] for c in MALFORMED], ids=[c[0] for c in MALFORMED])
def test_malformed_image_set(tmp_path, base_set, mutate, stage, needles):
    d = tmp_path / "set"
    shutil.copytree(base_set, d)
    doc = json.loads((d / "manifest.json").read_text())
    if mutate(d, doc) != "raw":
        write_manifest(d, doc)
    if stage == "manifest":
        with pytest.raises(ImageSetError) as ei:
            load_manifest(d)
    else:
        m = load_manifest(d)
        with pytest.raises(ImageSetError) as ei:
            load_camera_stacks(m, "left")
    msg = str(ei.value)
    for n in needles:
        assert n in msg, f"{n!r} not in {msg!r}"
    assert "manifest.json" in msg, msg


def test_file_deleted_after_loading_manifest(tmp_path, base_set):
    d = tmp_path / "set"
    shutil.copytree(base_set, d)
    m = load_manifest(d)
    (d / F6).unlink()
    with pytest.raises(ImageSetError, match=r"images\[6\] \('left_x_p1_s2.png'\).*does not exist"):
        load_camera_stacks(m, "left")


def test_fraction_without_screen_size_is_fine_with_argument(user_set):
    with pytest.raises(ImageSetError, match=r"images\[0\].*period_fraction.*screen_size_mm"):
        load_manifest(user_set)
    assert load_manifest(user_set, screen_size_mm=SCREEN_MM).screen_size_mm == SCREEN_MM
    with pytest.raises(ImageSetError, match="screen_size_mm"):
        load_manifest(user_set, screen_size_mm=(400.0,))


def test_all_cases_are_distinct():
    assert len({c[0] for c in MALFORMED}) == len(MALFORMED) >= 12


# ============================================================================ end to end
def test_simulate_then_decode_matches_mapping(tmp_path):
    """``pmdsim simulate`` in-process on a 96×60 px setup, then decode camera 'left'."""
    setup = default_setup()
    cam = Camera(96, 60, 220.0, 220.0, 48.0, 30.0)
    setup = replace(setup, cameras={n: CameraSetup(cam, cs.pose) for n, cs in setup.cameras.items()})
    setup_file = tmp_path / "small.toml"
    setup_file.write_text(setup.to_toml(), encoding="utf-8")
    out = tmp_path / "sim"
    t0 = time.perf_counter()
    r = CliRunner().invoke(main, ["simulate", "--setup", str(setup_file), "--bulge-mm", "2", "--out", str(out),
                                  "--quiet"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    m = load_manifest(out)
    assert m.cameras == ("left", "right")
    seq = setup.patterns.sequence
    assert m.periods_mm("left", "x") == seq.periods_x_mm and m.periods_mm("left", "y") == seq.periods_y_mm
    res = decode_camera(m, "left")
    with h5py.File(out / "mapping.h5", "r") as f:
        truth = f["left/screen_xy_mm"][...]
        valid = f["left/valid"][...]
    assert valid.sum() > 0.5 * valid.size
    np.testing.assert_array_equal(res.valid, valid)
    # Finest period 2 mm, amplitude B = 0.45·255 = 114.75 grey levels, N = 4:
    # bound 2/(2π)·arcsin(1/114.75) ≈ 2.77 µm.
    p_f = min(seq.periods_x_mm + seq.periods_y_mm)
    assert p_f == 2.0
    err = np.abs(res.screen_xy_mm[valid] - truth[valid]).max()
    assert err <= bound_mm(p_f, 0.45 * 255), err
    assert time.perf_counter() - t0 < 60
