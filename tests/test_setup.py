"""Measurement setups: the built-in Table 1 setup, the TOML round trip and validation errors.

Truths used here: the paper's Table 1 numbers (written literally), tomllib as an independent
TOML reader, and hand-edited copies of the default setup document.
"""

from __future__ import annotations

import copy
import math
import tomllib

import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.errors import SetupError
from pmdsim.setup import default_setup, load_setup, parse_setup

# ----------------------------------------------------------------------------- paper Table 1
TABLE1_CAMERA = {
    "image_size_px": [1920, 1200],
    "focal_length_px": [4400.0, 4400.0],
    "principal_point_px": [960.0, 600.0],
    "distortion": {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0},
}
TABLE1_POSES = {
    "left": ([-90.0, 295.0, -295.0], [45.0, 10.0, 10.0]),
    "right": ([90.0, 295.0, -295.0], [45.0, -10.0, -10.0]),
}
TABLE1_SCREEN = {
    "origin_world_mm": [-354.0, -78.0, -400.0],
    "angles_deg": [135.0, 0.0, 0.0],
    "grid_x_mm": [0.0, 354.0, 708.0],
    "grid_y_mm": [0.0, 199.0, 398.0],
}
TABLE1_SAMPLE_POSE = ([-200.0, -200.0, 0.0], [0.0, 0.0, 0.0])


def test_default_setup_is_table1_objects():
    s = default_setup()
    assert list(s.cameras) == ["left", "right"]
    for name, (origin, angles) in TABLE1_POSES.items():
        cs = s.cameras[name]
        c = cs.camera
        assert (c.width_px, c.height_px) == (1920, 1200)
        assert (c.fx_px, c.fy_px) == (4400.0, 4400.0)
        assert (c.ppx_px, c.ppy_px) == (960.0, 600.0)
        assert (c.k1, c.k2, c.p1, c.p2, c.k3) == (0.0, 0.0, 0.0, 0.0, 0.0)
        assert c.shape == (1200, 1920)
        assert list(cs.pose.origin_world_mm) == origin
        assert list(cs.pose.angles_deg) == angles
    scr = s.screen
    assert list(scr.pose.origin_world_mm) == [-354.0, -78.0, -400.0]
    assert list(scr.pose.angles_deg) == [135.0, 0.0, 0.0]
    assert list(scr.grid_x_mm) == [0.0, 354.0, 708.0]
    assert list(scr.grid_y_mm) == [0.0, 199.0, 398.0]
    assert scr.size_mm == (708.0, 398.0)
    assert scr.bulge_mm == 0.0
    assert (scr.control_heights() == 0.0).all() and scr.control_heights().shape == (3, 3)
    assert list(s.sample.pose.origin_world_mm) == [-200.0, -200.0, 0.0]
    assert list(s.sample.pose.angles_deg) == [0.0, 0.0, 0.0]


def test_default_setup_to_dict_is_table1():
    d = default_setup().to_dict()
    assert d["format"] == "pmdsim-setup"
    assert d["format_version"] == 1
    assert list(d["cameras"]) == ["left", "right"]
    for name, (origin, angles) in TABLE1_POSES.items():
        assert d["cameras"][name] == {**TABLE1_CAMERA, "origin_world_mm": origin, "angles_deg": angles}
    assert {k: d["screen"][k] for k in TABLE1_SCREEN} == TABLE1_SCREEN
    assert d["screen"].get("bulge_mm", 0.0) == 0.0
    assert (d["sample"]["origin_world_mm"], d["sample"]["angles_deg"]) == TABLE1_SAMPLE_POSE


def test_default_setup_poses_are_independent_of_each_call():
    # default_setup() builds a fresh object each time; with_bulge must not change the default
    a = default_setup()
    a.with_bulge(2.5)
    assert default_setup().screen.bulge_mm == 0.0
    assert a.screen.bulge_mm == 0.0


# ----------------------------------------------------------------------------- TOML round trip
def test_toml_round_trip_default(default_toml):
    s = default_setup()
    doc = tomllib.loads(default_toml)
    assert parse_setup(doc).to_dict() == s.to_dict()
    # the parsed TOML is the same plain data as to_dict (no writer-specific types or losses)
    assert doc == s.to_dict()


def test_toml_round_trip_bulge():
    s = default_setup().with_bulge(2.5)
    assert s.screen.bulge_mm == 2.5
    back = parse_setup(tomllib.loads(s.to_toml()))
    assert back.to_dict() == s.to_dict()
    assert back.screen.bulge_mm == 2.5
    z = back.screen.control_heights()
    assert z[1, 1] == 2.5
    z[1, 1] = 0.0
    assert (z == 0.0).all()


def test_toml_round_trip_nondefault_values(default_toml):
    """Values that stress the number formatting (tiny, huge, negative, non-terminating decimals)."""
    doc = tomllib.loads(default_toml)
    left = doc["cameras"]["left"]
    left["distortion"] = {"k1": -0.1234567890123, "k2": 1.5e-07, "p1": 2e-4, "p2": -1e-4, "k3": 1e20}
    left["principal_point_px"] = [959.5, 0.1 + 0.2]
    # bulge_mm and the centre of heights_mm must agree (issue 24: disagreeing ones are refused)
    doc["screen"]["heights_mm"] = [[0.0, 0.25, 0.0], [-0.5, -1.75, 1.0 / 3.0], [0.0, 0.0, 0.0]]
    doc["screen"]["bulge_mm"] = -1.75
    doc["sample"]["grid_x_mm"] = [0.0, 100.0, 250.0, 400.0]
    doc["sample"]["heights_mm"] = [[0.0, 0.001, -0.002, 0.0], [0.0, 0.0, 0.0, 0.003]]
    doc["patterns"].update(n_shifts=8, periods_x_mm=[800.0, 7.5], bit_depth=16, noise_std=0.5, seed=7)
    s = parse_setup(doc)
    text = s.to_toml()
    back = tomllib.loads(text)
    assert back == s.to_dict()
    assert parse_setup(back).to_dict() == s.to_dict()
    # the values are the ones that were put in (not just self-consistent)
    assert back["cameras"]["left"]["distortion"]["k2"] == 1.5e-07
    assert back["cameras"]["left"]["principal_point_px"][1] == 0.1 + 0.2
    assert back["screen"]["heights_mm"][1][2] == 1.0 / 3.0
    assert back["screen"]["bulge_mm"] == -1.75
    assert back["patterns"]["bit_depth"] == 16 and back["patterns"]["n_shifts"] == 8
    # the bulge is the central control height
    assert s.screen.control_heights()[1][1] == -1.75


def test_optional_tables_take_defaults(default_toml):
    doc = tomllib.loads(default_toml)
    del doc["patterns"]
    del doc["format"]
    del doc["format_version"]
    for cam in doc["cameras"].values():
        del cam["distortion"]
    assert parse_setup(doc).to_dict() == default_setup().to_dict()


def test_setup_show_parses_with_tomllib():
    result = CliRunner().invoke(main, ["setup", "--show"])
    assert result.exit_code == 0, result.output
    doc = tomllib.loads(result.stdout)
    assert doc["cameras"]["left"]["focal_length_px"] == [4400.0, 4400.0]
    assert parse_setup(doc).to_dict() == default_setup().to_dict()


def test_setup_show_with_bulge_records_it():
    result = CliRunner().invoke(main, ["setup", "--show", "--bulge-mm", "2.5"])
    assert result.exit_code == 0, result.output
    assert tomllib.loads(result.stdout)["screen"]["bulge_mm"] == 2.5


def test_load_setup_file(tmp_path, default_toml):
    p = tmp_path / "s.toml"
    p.write_text(default_toml, encoding="utf-8")
    assert load_setup(p).to_dict() == default_setup().to_dict()
    assert load_setup(str(p)).to_dict() == default_setup().to_dict()


# ----------------------------------------------------------------------------- malformed setups
def _set(path, value):
    """Mutation: set doc[path] = value (path: dotted keys)."""

    def f(doc):
        *parents, last = path.split(".")
        t = doc
        for k in parents:
            t = t[k]
        t[last] = value

    return f


def _del(path):
    def f(doc):
        *parents, last = path.split(".")
        t = doc
        for k in parents:
            t = t[k]
        del t[last]

    return f


def _rename(path, new):
    def f(doc):
        *parents, last = path.split(".")
        t = doc
        for k in parents:
            t = t[k]
        t[new] = t.pop(last)

    return f


def _rename_camera(old, new):
    def f(doc):
        doc["cameras"] = {(new if k == old else k): v for k, v in doc["cameras"].items()}

    return f


def _all(*mutations):
    def f(doc):
        for m in mutations:
            m(doc)

    return f


# (id, mutation of the default document, substrings the message must contain)
DOC_CASES = [
    ("missing-focal-length", _del("cameras.left.focal_length_px"),
     ["cameras.left.focal_length_px", "missing"]),
    ("missing-screen-table", _del("screen"), ["screen", "missing"]),
    ("missing-sample-grid", _del("sample.grid_y_mm"), ["sample.grid_y_mm", "missing"]),
    ("unknown-key-typo-added", _set("cameras.left.focal_lenght_px", [4400.0, 4400.0]),
     ["cameras.left.focal_lenght_px", "unknown"]),
    ("unknown-key-typo-renamed", _rename("cameras.left.focal_length_px", "focal_lenght_px"),
     ["cameras.left.focal_length_px", "missing"]),
    ("unknown-key-patterns", _set("patterns.n_shift", 4), ["patterns.n_shift", "unknown"]),
    ("unknown-key-distortion", _set("cameras.right.distortion.k7", 0.0),
     ["cameras.right.distortion.k7", "unknown"]),
    ("unknown-top-level-table", _set("lighting", {"lux": 500.0}), ["lighting", "unknown"]),
    ("grid-repeated", _set("screen.grid_x_mm", [0, 354, 354]), ["screen.grid_x_mm", "increasing"]),
    ("grid-decreasing", _set("sample.grid_y_mm", [400.0, 0.0]), ["sample.grid_y_mm", "increasing"]),
    ("grid-single-point", _set("sample.grid_x_mm", [0.0]), ["sample.grid_x_mm", "at least 2"]),
    ("heights-wrong-rows", _set("screen.heights_mm", [[0.0] * 3] * 2), ["screen.heights_mm", "shape", "(3, 3)"]),
    ("heights-ragged", _set("screen.heights_mm", [[0.0] * 3, [0.0] * 2, [0.0] * 3]),
     ["screen.heights_mm", "shape"]),
    ("heights-transposed", _all(_set("sample.grid_x_mm", [0.0, 200.0, 400.0]), _set("sample.heights_mm", [[0.0] * 2] * 3)),
     ["sample.heights_mm", "shape", "(2, 3)"]),
    ("heights-not-a-matrix", _set("screen.heights_mm", [0.0] * 9), ["screen.heights_mm"]),
    ("focal-negative", _set("cameras.right.focal_length_px", [-4400.0, 4400.0]),
     ["cameras.right.focal_length_px", "> 0"]),
    ("focal-zero", _set("cameras.left.focal_length_px", [4400.0, 0.0]), ["cameras.left.focal_length_px", "> 0"]),
    ("size-zero", _set("cameras.left.image_size_px", [0, 1200]), ["cameras.left.image_size_px", "positive"]),
    ("size-negative", _set("cameras.left.image_size_px", [1920, -1200]), ["cameras.left.image_size_px", "positive"]),
    ("size-non-integer", _set("cameras.left.image_size_px", [1920.5, 1200]), ["cameras.left.image_size_px", "whole"]),
    ("size-float-integral", _set("cameras.left.image_size_px", [1920.0, 1200.0]), ["cameras.left.image_size_px"]),
    ("size-three-entries", _set("cameras.left.image_size_px", [1920, 1200, 3]), ["cameras.left.image_size_px"]),
    ("size-absurdly-large", _set("cameras.left.image_size_px", [2**70, 1200]), ["cameras.left.image_size_px"]),
    ("origin-two-entries", _set("cameras.left.origin_world_mm", [-90.0, 295.0]),
     ["cameras.left.origin_world_mm", "3 entries", "got 2"]),
    ("angles-four-entries", _set("screen.angles_deg", [135.0, 0.0, 0.0, 0.0]), ["screen.angles_deg", "3 entries"]),
    ("vector-is-string", _set("sample.origin_world_mm", "-200, -200, 0"), ["sample.origin_world_mm", "list"]),
    ("number-is-string-in-vector", _set("cameras.left.focal_length_px", ["4400", 4400.0]),
     ["cameras.left.focal_length_px[0]", "number"]),
    ("number-is-string", _set("screen.bulge_mm", "2.5"), ["screen.bulge_mm", "number"]),
    ("number-is-bool", _set("patterns.mean_level", True), ["patterns.mean_level", "number"]),
    ("bulge-even-grid", _set("screen.grid_x_mm", [0.0, 236.0, 472.0, 708.0]), ["screen.bulge_mm", "odd"]),
    ("n-shifts-two", _set("patterns.n_shifts", 2), ["patterns.n_shifts", "3"]),
    ("n-shifts-float", _set("patterns.n_shifts", 4.0), ["patterns.n_shifts", "integer"]),
    ("bit-depth-12", _set("patterns.bit_depth", 12), ["patterns.bit_depth", "12"]),
    ("amplitude-above-one", _set("patterns.amplitude", 1.5), ["patterns.amplitude", "1"]),
    ("amplitude-zero", _set("patterns.amplitude", 0.0), ["patterns.amplitude", "> 0"]),
    ("noise-negative", _set("patterns.noise_std", -1.0), ["patterns.noise_std"]),
    ("seed-negative", _set("patterns.seed", -1), ["patterns.seed"]),
    ("period-zero", _set("patterns.periods_x_mm", [720.0, 0.0]), ["patterns.periods_x_mm", "> 0"]),
    ("periods-empty", _set("patterns.periods_y_mm", []), ["patterns.periods_y_mm"]),
    # two frames with the same period would be written to the same image file name
    ("periods-repeated", _set("patterns.periods_y_mm", [420.0, 35.0, 35.0]), ["patterns.periods_y_mm", "35"]),
    ("cameras-empty", _set("cameras", {}), ["cameras", "at least one"]),
    ("cameras-not-a-table", _set("cameras", ["left"]), ["cameras", "table"]),
    ("camera-not-a-table", _set("cameras.left", 5), ["cameras.left", "table"]),
    ("camera-name-with-space", _rename_camera("left", "left cam"), ["left cam"]),
    # a camera name must survive to_toml as a bare TOML key (and name files and HDF5 groups)
    ("camera-name-non-ascii", _rename_camera("left", "linké"), ["linké"]),
    ("format-wrong", _set("format", "pmdsim-imageset"), ["format", "pmdsim-setup", "pmdsim-imageset"]),
    ("format-version-wrong", _set("format_version", 2), ["format_version", "2"]),
]


@pytest.mark.parametrize("mutate, expected", [c[1:] for c in DOC_CASES], ids=[c[0] for c in DOC_CASES])
def test_malformed_document_raises_setup_error(default_toml, mutate, expected):
    doc = tomllib.loads(default_toml)
    parse_setup(copy.deepcopy(doc))  # the unedited document is valid
    mutate(doc)
    with pytest.raises(SetupError) as ei:
        parse_setup(doc)
    msg = str(ei.value)
    for s in expected:
        assert s in msg, f"{s!r} not in message {msg!r}"
    assert isinstance(ei.value, ValueError)


# Edits of the TOML text (TOML's own nan/inf literals), read through load_setup.
TEXT_CASES = [
    ("nan-focal-length", "focal_length_px = [4400.0, 4400.0]", "focal_length_px = [nan, 4400.0]",
     ["cameras.left.focal_length_px[0]", "finite"]),
    ("inf-bulge", "bulge_mm = 0.0", "bulge_mm = inf", ["screen.bulge_mm", "finite"]),
    ("minus-inf-origin", "origin_world_mm = [-354.0, -78.0, -400.0]", "origin_world_mm = [-354.0, -78.0, -inf]",
     ["screen.origin_world_mm[2]", "finite"]),
    ("nan-grid", "grid_x_mm = [0.0, 354.0, 708.0]", "grid_x_mm = [0.0, nan, 708.0]", ["screen.grid_x_mm[1]", "finite"]),
    ("nan-distortion", "k1 = 0.0", "k1 = nan", ["cameras.left.distortion.k1", "finite"]),
    ("inf-amplitude", "amplitude = 0.45", "amplitude = +inf", ["patterns.amplitude", "finite"]),
    ("nan-heights", "bulge_mm = 0.0", "heights_mm = [[0.0, 0.0, 0.0], [0.0, nan, 0.0], [0.0, 0.0, 0.0]]",
     ["screen.heights_mm[1][1]", "finite"]),
    ("nan-image-size", "image_size_px = [1920, 1200]", "image_size_px = [nan, 1200]", ["cameras.left.image_size_px"]),
]


@pytest.mark.parametrize("old, new, expected", [c[1:] for c in TEXT_CASES], ids=[c[0] for c in TEXT_CASES])
def test_malformed_toml_text_raises_setup_error(tmp_path, default_toml, old, new, expected):
    assert old in default_toml
    text = default_toml.replace(old, new, 1)
    p = tmp_path / "bad.toml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(SetupError) as ei:
        load_setup(p)
    msg = str(ei.value)
    for s in expected + [str(p)]:
        assert s in msg, f"{s!r} not in message {msg!r}"


def test_load_setup_missing_file(tmp_path):
    p = tmp_path / "nope.toml"
    with pytest.raises(SetupError, match="does not exist") as ei:
        load_setup(p)
    assert str(p) in str(ei.value)


def test_load_setup_not_toml(tmp_path):
    p = tmp_path / "notes.toml"
    p.write_text("this is [not toml\n", encoding="utf-8")
    with pytest.raises(SetupError, match="not valid TOML") as ei:
        load_setup(p)
    assert str(p) in str(ei.value)


def test_load_setup_binary_file(tmp_path):
    p = tmp_path / "image.toml"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x00")
    with pytest.raises(SetupError) as ei:
        load_setup(p)
    assert str(p) in str(ei.value)


def test_load_setup_directory(tmp_path):
    with pytest.raises(SetupError) as ei:
        load_setup(tmp_path)
    assert str(tmp_path) in str(ei.value)


def test_load_setup_toml_of_wrong_shape(tmp_path):
    p = tmp_path / "other.toml"
    p.write_text('[tool.black]\nline-length = 100\n', encoding="utf-8")
    with pytest.raises(SetupError) as ei:
        load_setup(p)
    assert str(p) in str(ei.value) and ("cameras" in str(ei.value) or "tool" in str(ei.value))


# ----------------------------------------------------------------------------- with_bulge
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_with_bulge_non_finite_raises(bad):
    with pytest.raises(SetupError, match="bulge"):
        default_setup().with_bulge(bad)


def test_with_bulge_even_grid_raises(default_toml):
    doc = tomllib.loads(default_toml)
    del doc["screen"]["bulge_mm"]
    doc["screen"]["grid_x_mm"] = [0.0, 236.0, 472.0, 708.0]
    s = parse_setup(doc)
    assert s.screen.bulge_mm is None
    with pytest.raises(SetupError, match="odd"):
        s.with_bulge(1.0)


def test_with_bulge_sets_central_control_point_only():
    s = default_setup().with_bulge(-3.0)
    z = s.screen.control_heights()
    assert z.shape == (3, 3)
    assert z[1, 1] == -3.0
    assert (z.sum() == -3.0) and (z == 0).sum() == 8


def test_toml_strings_with_control_characters_round_trip_through_tomllib():
    import tomllib

    from pmdsim.setup.toml import _fmt_value

    for v in ["two\nlines", "tab\there", 'quote " and \\ backslash', "bell \x07 and cr \r and del \x7f", "µm ±"]:
        assert tomllib.loads("x = " + _fmt_value(v))["x"] == v
