"""Property-based tests (hypothesis) of bad input through the CLI, in-process (issue 11, item 5).

Generated setups (TOML), manifests and image sets — valid, slightly wrong and garbage — go
through ``pmdsim setup --setup`` and ``pmdsim evaluate``. Whatever the input, the outcome must be
one of

* exit 2 (bad input) or 1 (failed computation) with a ``pmdsim: error: …`` line and no traceback;
* exit 0 (or 1 with outputs kept for inspection) with an ``evaluation.h5`` in which every pixel
  not decoded carries a phase flag, and every decoded pixel agrees with the ray tracer's mapping
  of the clean measurement (mapping.h5, the truth) within the detection floor of the
  consistency checks (derived below from the noise model, not tuned): never a silent wrong number.

The detection floor. A corruption ε of one of N = 4 frames leaves the residual ε/2 (the
residual direction (1, −1, 1, −1)/2 has weight 1/2 on every frame); it passes the χ²(1) test
at α = 1e-6 while |ε| < 2·√q·σ_I, q = χ²₁ quantile, and then moves the phase by at most
(2/N)·|ε|/B = 2√q·√(2/N) σ_φ ≈ 6.9 σ_φ. A whole period that disagrees with the next coarser one
passes while the disagreement is below z·σ_pair (z the normal quantile at α/2). So the finest
coordinate is right to within z·hypot(σ_coarser, σ_finest) + (2√q·√(2/N) + 5)·σ_finest, with 5σ
for the noise itself.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import string
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
import tomli_w
from click.testing import CliRunner
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy import stats

from pmdsim.cli import main

from conftest import SMALL_N_SHIFTS, SMALL_PERIODS_X, SMALL_PERIODS_Y, replace_exactly

NOISE = 1.0
# PMDSIM_PROP_SCALE multiplies the example counts; PMDSIM_PROP_REPORT names a JSON file that gets
# the outcome counts per test (docs/reliability.md's table comes from a scaled run).
_SCALE = float(os.environ.get("PMDSIM_PROP_SCALE", "1"))
_REPORT = os.environ.get("PMDSIM_PROP_REPORT")


def _n(k: int) -> int:
    return max(1, int(k * _SCALE))


def _report(name: str, outcomes: dict) -> None:
    if _REPORT:
        p = Path(_REPORT)
        doc = json.loads(p.read_text()) if p.exists() else {}
        doc[name] = outcomes
        p.write_text(json.dumps(doc, indent=1, sort_keys=True))


SETTINGS = dict(deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def noisy(tmp_path_factory, small_toml):
    root = tmp_path_factory.mktemp("prop")
    setup = root / "noisy.toml"
    setup.write_text(replace_exactly(small_toml, "noise_std = 0.0", f"noise_std = {NOISE}", 1))
    clean = root / "clean"
    r = CliRunner().invoke(main, ["simulate", "--setup", str(setup), "--out", str(clean), "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(clean / "mapping.h5") as m:
        truth = {cam: m[cam]["screen_xy_mm"][()] for cam in m}
    return setup, clean, truth


def _floor_mm(period_list) -> float:
    """The detection floor of the finest coordinate (module docstring), mm."""
    alpha = 1e-6
    q = stats.chi2.isf(alpha, SMALL_N_SHIFTS - 3)
    z = stats.norm.isf(alpha / 2)
    sigma_i = math.sqrt(NOISE ** 2 + 1 / 12)
    b = 0.45 * 255
    ps = sorted(period_list, reverse=True)
    sig = [p / (2 * math.pi) * math.sqrt(2 / SMALL_N_SHIFTS) * sigma_i / b for p in ps]
    return z * math.hypot(sig[-2], sig[-1]) + (2 * math.sqrt(q) * math.sqrt(2 / SMALL_N_SHIFTS) + 5) * sig[-1]


def _check_outcome(r, out: Path, truth: dict, floor_mm=None) -> str:
    """The property: a clear error, or flags that explain every invalid pixel and no wrong number."""
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise AssertionError(f"uncaught {type(r.exception).__name__}: {r.exception}\n{r.output}")
    assert "Traceback" not in r.output
    assert r.exit_code in (0, 1, 2), r.output
    if r.exit_code != 0:
        errs = [line for line in r.output.splitlines() if line.startswith("pmdsim: error:")]
        assert errs, r.output
    h5 = out / "evaluation.h5"
    if r.exit_code == 2:
        assert not out.exists()
        return "refused"
    if not h5.exists():
        assert r.exit_code == 1
        return "failed, nothing written"
    if floor_mm is None:
        floor_mm = {d: _floor_mm(p) for d, p in (("x", SMALL_PERIODS_X), ("y", SMALL_PERIODS_Y))}
    with h5py.File(h5) as f:
        for cam in f:
            g = f[cam]
            decoded = g["decoded"][()]
            flags = g["phase_flags"][()]
            assert np.all(flags[~decoded] != 0), f"{cam}: invalid pixels without a flag"
            assert np.all(flags[decoded] == 0)
            xy = g["screen_xy_mm"][()]
            err = np.abs(xy - truth[cam])[decoded]
            for d, axis in (("x", 0), ("y", 1)):
                assert err.size == 0 or err[:, axis].max() <= floor_mm[d], (
                    f"{cam}: silent wrong number in {d}: {err[:, axis].max():.4g} mm > {floor_mm[d]:.4g} mm "
                    f"({np.count_nonzero(err[:, axis] > floor_mm[d])} px)")
    if r.exit_code:
        return "failed, outputs kept"
    return "warned" if "pmdsim: warning:" in r.output else "ok"


def _linked_copy(src: Path, dst: Path) -> None:
    dst.mkdir()
    for p in src.iterdir():
        if p.suffix == ".png":
            os.symlink(p, dst / p.name)


# ----------------------------------------------------------------------------- setups
_SETUP_KEYS = [
    ("cameras", "left", "image_size_px"), ("cameras", "left", "focal_length_px"),
    ("cameras", "left", "principal_point_px"), ("cameras", "left", "origin_world_mm"),
    ("cameras", "left", "angles_deg"), ("cameras", "right", "distortion", "k1"),
    ("screen", "origin_world_mm"), ("screen", "angles_deg"), ("screen", "grid_x_mm"), ("screen", "bulge_mm"),
    ("sample", "grid_x_mm"), ("sample", "angles_deg"),
    ("patterns", "n_shifts"), ("patterns", "periods_x_mm"), ("patterns", "periods_y_mm"),
    ("patterns", "mean_level"), ("patterns", "amplitude"), ("patterns", "bit_depth"), ("patterns", "noise_std"),
    ("calibration", "mirror_lifts_mm"), ("format_version",),
]
_numbers = st.one_of(st.integers(-10 ** 7, 10 ** 7), st.floats(allow_nan=True, allow_infinity=True, width=64))
_values = st.one_of(
    _numbers, st.text(max_size=8), st.booleans(),
    st.lists(_numbers, min_size=0, max_size=5),
    st.lists(st.floats(0.5, 2000, allow_nan=False), min_size=1, max_size=4),  # plausible but maybe wrong
)


@st.composite
def setup_texts(draw, base: dict):
    kind = draw(st.sampled_from(["valid-ish", "mutated", "mutated", "garbage"]))
    if kind == "garbage":
        return draw(st.one_of(st.text(max_size=200), st.text(string.printable, max_size=200)))
    doc = json.loads(json.dumps(base))
    n = 1 if kind == "valid-ish" else draw(st.integers(1, 3))
    for _ in range(n):
        path = draw(st.sampled_from(_SETUP_KEYS))
        node = doc
        for k in path[:-1]:
            node = node[k]
        if kind == "valid-ish":
            v = node[path[-1]]
            if isinstance(v, list) and v and all(isinstance(x, (int, float)) for x in v):
                f = draw(st.floats(0.9, 1.1))
                node[path[-1]] = [type(x)(x * f) if isinstance(x, float) else x for x in v]
        elif draw(st.booleans()) and path[-1] in node:
            del node[path[-1]]
        else:
            node[path[-1]] = draw(_values)
    try:
        return tomli_w.dumps(doc)
    except (TypeError, ValueError):
        assume(False)


@pytest.fixture(scope="module")
def base_setup(small_toml):
    return tomllib.loads(small_toml)


def test_setup_files(tmp_path_factory, base_setup):
    counts = {}

    @settings(max_examples=_n(30), **SETTINGS)
    @given(text=setup_texts(base_setup))
    def run(text):
        p = tmp_path_factory.mktemp("s") / "setup.toml"
        p.write_text(text)
        r = CliRunner().invoke(main, ["setup", "--setup", str(p)])
        if r.exception is not None and not isinstance(r.exception, SystemExit):
            raise AssertionError(f"uncaught {type(r.exception).__name__}: {r.exception}\n{text}")
        assert r.exit_code in (0, 2), r.output
        lines = [line for line in r.output.splitlines() if line.strip()]
        if r.exit_code == 2:
            assert any(line.startswith("pmdsim: error:") for line in lines), r.output
        else:
            assert lines[-1].startswith("setup OK")
        for line in lines:  # one style: errors, warnings, indented notes, the verdict
            assert line.startswith(("pmdsim: error:", "pmdsim: warning:", "  ", "setup OK")), line
        counts[r.exit_code] = counts.get(r.exit_code, 0) + 1

    run()
    _report("setup", {("refused" if k == 2 else "ok"): v for k, v in counts.items()})
    assert counts.get(2, 0) > 0 and counts.get(0, 0) > 0  # both outcomes were exercised


# ----------------------------------------------------------------------------- manifests
_json_values = st.one_of(st.none(), st.booleans(), _numbers, st.text(max_size=10),
                         st.lists(st.integers(-5, 2000), max_size=3), st.just({}))
_ENTRY_KEYS = ["file", "camera", "direction", "period_mm", "shift_index", "n_shifts", "period_index"]
_TOP_KEYS = ["bit_depth", "screen_size_mm", "cameras", "format_version", "images"]


@st.composite
def manifest_docs(draw, base: dict):
    kind = draw(st.sampled_from(["entry", "entry", "structure", "top", "garbage"]))
    if kind == "garbage":
        return draw(st.text(max_size=100))
    doc = json.loads(json.dumps(base))
    imgs = doc["images"]
    if kind == "entry":
        for _ in range(draw(st.integers(1, 3))):
            e = imgs[draw(st.integers(0, len(imgs) - 1))]
            key = draw(st.sampled_from(_ENTRY_KEYS))
            if draw(st.booleans()):
                e.pop(key, None)
            else:
                e[key] = draw(_json_values)
    elif kind == "structure":
        op = draw(st.sampled_from(["drop", "duplicate", "swap_files", "swap_files", "reverse_period"]))
        i = draw(st.integers(0, len(imgs) - 1))
        j = draw(st.integers(0, len(imgs) - 1))
        if op == "drop":
            imgs.pop(i)
        elif op == "duplicate":
            imgs.append(dict(imgs[i]))
        elif op == "swap_files":
            imgs[i]["file"], imgs[j]["file"] = imgs[j]["file"], imgs[i]["file"]
        else:
            e0 = imgs[i]
            for e in imgs:
                if (e["camera"], e["direction"], e["period_mm"]) == (e0["camera"], e0["direction"], e0["period_mm"]):
                    e["shift_index"] = (-e["shift_index"]) % e["n_shifts"]
    else:
        key = draw(st.sampled_from(_TOP_KEYS))
        if draw(st.booleans()):
            doc.pop(key, None)
        else:
            doc[key] = draw(_json_values)
    return json.dumps(doc)


def test_manifests(tmp_path_factory, noisy):
    setup, clean, truth = noisy
    base = json.loads((clean / "manifest.json").read_text())
    outcomes = {}

    @settings(max_examples=_n(20), **SETTINGS)
    @given(text=manifest_docs(base))
    def run(text):
        d = tmp_path_factory.mktemp("m") / "set"
        _linked_copy(clean, d)
        (d / "manifest.json").write_text(text)
        out = d.parent / "ev"
        r = CliRunner().invoke(main, ["evaluate", str(d), "--setup", str(setup), "--out", str(out), "--quiet"])
        o = _check_outcome(r, out, truth)
        outcomes[o] = outcomes.get(o, 0) + 1

    run()
    _report("manifest", outcomes)
    assert outcomes.get("refused", 0) > 0


# ----------------------------------------------------------------------------- images
@st.composite
def image_edits(draw, files: list[str]):
    f = draw(st.sampled_from(files))
    op = draw(st.sampled_from(["black", "constant", "duplicate", "noise", "gain", "patch", "roll", "swap",
                               "garbage_bytes", "wrong_size", "rgb"]))
    return dict(file=f, op=op, other=draw(st.sampled_from(files)), value=draw(st.integers(0, 255)),
                gain=draw(st.floats(0.5, 1.5)), seed=draw(st.integers(0, 2 ** 16)),
                box=(draw(st.integers(0, 59)), draw(st.integers(0, 95)), draw(st.integers(1, 30)),
                     draw(st.integers(1, 30))),
                shift=(draw(st.integers(-3, 3)), draw(st.integers(-3, 3))))


def _apply(d: Path, e: dict) -> None:
    p = d / e["file"]
    try:
        a = np.array(Image.open(p))
    except Exception:  # an earlier edit made it garbage: nothing more to do to it
        return
    rng = np.random.default_rng(e["seed"])
    op = e["op"]
    if op == "black":
        a[:] = 0
    elif op == "constant":
        a[:] = e["value"]
    elif op == "duplicate":
        try:
            a = np.array(Image.open(d / e["other"]))
        except Exception:
            return
    elif op == "noise":
        a = rng.integers(0, 256, a.shape, dtype=np.uint8)
    elif op == "gain":
        a = np.clip(np.rint(a * e["gain"]), 0, 255).astype(np.uint8)
    elif op == "patch":
        v, u, h, w = e["box"]
        a[v:v + h, u:u + w] = e["value"]
    elif op == "roll":  # the whole period stack of this image moved (misregistration)
        stem = e["file"].rsplit("_s", 1)[0]
        for q in sorted(d.glob(stem + "_s*.png")):
            try:
                b = np.roll(np.array(Image.open(q)), e["shift"], axis=(0, 1))
            except Exception:
                continue
            q.unlink()
            Image.fromarray(b).save(q)
        return
    elif op == "swap":
        q = d / e["other"]
        try:
            b = np.array(Image.open(q))
        except Exception:
            return
        q.unlink()
        Image.fromarray(a).save(q)
        a = b
    elif op == "garbage_bytes":
        p.unlink()
        p.write_bytes(rng.integers(0, 256, 300, dtype=np.uint8).tobytes())
        return
    elif op == "wrong_size":
        a = a[:-1]
    elif op == "rgb":
        a = np.stack([a] * 3, axis=-1)
    p.unlink()  # the clean set's file is a symlink: replace, never write through it
    Image.fromarray(a).save(p)


def test_image_sets(tmp_path_factory, noisy):
    setup, clean, truth = noisy
    files = sorted(p.name for p in clean.glob("*.png"))
    outcomes = {}

    @settings(max_examples=_n(25), **SETTINGS)
    @given(edits=st.lists(image_edits(files), min_size=1, max_size=2))
    def run(edits):
        d = tmp_path_factory.mktemp("i") / "set"
        _linked_copy(clean, d)
        shutil.copy(clean / "manifest.json", d / "manifest.json")
        for e in edits:
            _apply(d, e)
        out = d.parent / "ev"
        r = CliRunner().invoke(main, ["evaluate", str(d), "--setup", str(setup), "--out", str(out), "--quiet"])
        o = _check_outcome(r, out, truth)
        outcomes[o] = outcomes.get(o, 0) + 1

    run()
    _report("images", outcomes)
    assert sum(outcomes.values()) >= 1


# ----------------------------------------------------------------------------- outputs vs inputs (issue 24)
@st.composite
def output_placements(draw):
    """Where an output goes relative to the command's inputs: which command, which input it
    relates to, how (the input, inside it at some depth, its parent, a sibling, through a
    symbolic link), whether --force is given, and whether the target exists."""
    command = draw(st.sampled_from(["calibrate", "evaluate", "simulate"]))
    relation = draw(st.sampled_from(["is", "inside", "parent", "sibling", "link-inside"]))
    depth = draw(st.integers(1, 3))
    name = draw(st.text(string.ascii_lowercase + "_.-", min_size=1, max_size=12).filter(lambda s: s not in (".", "..")))
    return command, relation, depth, name, draw(st.booleans()), draw(st.booleans())


@settings(max_examples=_n(40), **SETTINGS)
@given(case=output_placements())
def test_no_output_touches_an_input(tmp_path_factory, small_toml, case):
    """Whatever the output path, a command never writes into, over or around one of its inputs:
    when the path touches an input (truth: the placement drawn, not the code's answer) it is
    refused with exit 2 naming the input, and the inputs' bytes are unchanged; a path that does
    not touch one is never refused as an input."""
    command, relation, depth, name, force, exists = case
    w = tmp_path_factory.mktemp("place")
    data = w / "data" / "pose0"
    data.mkdir(parents=True)
    (data / "left_x_p0_s0.png").write_bytes(b"\x89PNG fake")
    (data / "manifest.json").write_text("{}")
    setup = w / "data" / "s.toml"
    setup.write_text(small_toml, encoding="utf-8")
    inputs = {"calibrate": data, "evaluate": data, "simulate": setup}[command]
    if relation == "is":
        out = inputs
    elif relation == "inside":
        out = inputs.joinpath(*[name] * depth) if inputs.is_dir() else inputs.parent / name
    elif relation == "parent":
        out = inputs.parent
    elif relation == "sibling":
        out = inputs.parent / f"{name}_out"
    else:
        link = w / f"link_{name}"
        link.symlink_to(inputs.parent)
        out = link / inputs.name / name if inputs.is_dir() else link / name
    touches = relation in ("is", "parent") or (relation in ("inside", "link-inside") and inputs.is_dir())
    if exists and not out.exists() and not touches:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text("x") if command == "calibrate" else out.mkdir()
    before = {p: p.read_bytes() for p in (w / "data").rglob("*") if p.is_file()}
    args = {"calibrate": ["calibrate", str(data), "--out", str(out)],
            "evaluate": ["evaluate", str(data), "--out", str(out)],
            "simulate": ["simulate", "--setup", str(setup), "--out", str(out)]}[command]
    r = CliRunner().invoke(main, args + ["--quiet"] + (["--force"] if force else []))
    assert r.exception is None or isinstance(r.exception, SystemExit), r.output
    assert "Traceback" not in r.output
    if touches:
        # refused by pmdsim's input check, or already by click's check of the --out type
        # (calibrate --out DIR: "is a directory") — either way before anything is read or written
        refused = "input of this command" in r.output or "Invalid value for '--out'" in r.output
        assert r.exit_code == 2 and refused and "pass --force" not in r.output, r.output
    else:
        assert "input of this command" not in r.output, r.output
    assert {p: p.read_bytes() for p in before} == before  # every input file still there, unchanged
