"""Error messages that guide the user: misspelt keys, dangerous output paths."""

import tomllib

import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.errors import SetupError
from pmdsim.setup import default_setup, parse_setup


def _doc():
    return tomllib.loads(default_setup().to_toml())


def test_misspelt_required_key_is_named():
    d = _doc()
    d["cameras"]["left"]["focal_lenght_px"] = d["cameras"]["left"].pop("focal_length_px")
    with pytest.raises(SetupError) as e:
        parse_setup(d)
    msg = str(e.value)
    assert "missing key cameras.left.focal_length_px" in msg and "focal_lenght_px" in msg


def test_misspelt_optional_key_gets_a_suggestion():
    d = _doc()
    d["screen"]["bulge"] = 1.0
    with pytest.raises(SetupError, match=r"unknown key screen\.bulge \(did you mean screen\.bulge_mm\?"):
        parse_setup(d)


def test_output_into_the_current_directory_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep.txt").write_text("precious")
    r = CliRunner().invoke(main, ["simulate", "--out", ".", "--force", "--quiet"])
    assert r.exit_code == 2 and "current directory" in r.output
    assert (tmp_path / "keep.txt").read_text() == "precious"


@pytest.mark.parametrize("args,msg", [
    (["experiment", "1", "--bulges-mm", "abc"], "--bulges-mm must be comma-separated numbers"),
    (["experiment", "3", "--bulges-mm", ","], "--bulges-mm lists no value"),
    (["experiment", "3", "--grids", "3,x"], "--grids must be comma-separated integers"),
    (["experiment", "3", "--grids", "2"], "at least 3 × 3"),
    (["experiment", "3", "--deformations", "wavy"], "--deformations: unknown ['wavy']"),
    (["experiment", "3", "--mirror-sags-um", "1,x"], "--mirror-sags-um must be comma-separated numbers"),
])
def test_bad_experiment_lists_are_refused_before_any_work(tmp_path, args, msg):
    out = tmp_path / "o"
    r = CliRunner().invoke(main, [*args, "--out", str(out), "--quiet"])
    assert r.exit_code == 2 and msg in r.output
    assert not out.exists()


@pytest.mark.parametrize("args, names", [
    (["evaluate", "run", "--out", "e", "--method", "simpson"], ["'--method'", "simpson"]),
    (["simulate", "--out", "s", "--bulge-mm", "three"], ["'--bulge-mm'", "three"]),
    (["evaluate", "run", "--out", "e", "--min-valid-fraction", "1.5"], ["'--min-valid-fraction'", "1.5"]),
    (["simulate", "--out", "s", "--no-such-option"], ["--no-such-option"]),
    (["experiment", "9", "--out", "x"], ["'9'"]),
    (["frobnicate"], ["frobnicate"]),
])
def test_bad_options_get_one_pmdsim_error_line(tmp_path, monkeypatch, args, names):
    """Click's usage errors (a bad choice, a number that is not one, an unknown option or
    command) come out in pmdsim's one style (issue 11, item 3): one ``pmdsim: error:`` line
    naming the option and the value, exit code 2, nothing written."""
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("pmdsim: error: "), r.output
    for n in names:
        assert n in lines[0], lines[0]
    assert "--help" in lines[0]
    assert not any(tmp_path.iterdir())
