"""Packaging (issue 23 item 6): LICENSE, py.typed, the optional extras and their import guards,
the README's set-up commands and CI running the README's test command."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_license_and_py_typed_are_shipped():
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "BSD 3-Clause License" in text and "pmdsim developers" in text
    proj = _pyproject()
    assert proj["project"]["license"] == {"text": "BSD-3-Clause"}
    assert (ROOT / "src" / "pmdsim" / "py.typed").exists()
    assert "py.typed" in proj["tool"]["setuptools"]["package-data"]["pmdsim"]


def test_dask_and_pyarrow_are_an_extra_and_tests_get_every_extra():
    proj = _pyproject()["project"]
    base = " ".join(proj["dependencies"])
    assert "dask" not in base and "pyarrow" not in base and "xarray" not in base
    extras = proj["optional-dependencies"]
    assert any(d.startswith("dask[distributed]") for d in extras["study"]) and any(
        d.startswith("pyarrow") for d in extras["study"])
    assert {d.split(">")[0] for d in extras["xarray"]} == {"xarray", "h5netcdf"}
    assert "pmdsim[study,xarray]" in extras["test"]


def test_ci_runs_the_readme_test_command_in_a_virtual_environment():
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(encoding="utf-8"), re.S)
    install, test = blocks[0].strip(), blocks[1].strip()
    for cmd in (install, test):  # each line creates and uses its own virtual environment
        assert cmd.startswith("python3 -m venv .venv && . .venv/bin/activate && pip install ")
    assert test in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()


def test_missing_extra_is_one_line_naming_it(tmp_path, monkeypatch):
    import importlib.util

    from pmdsim.cli import main

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pyarrow" else real(name, *a))
    study = tmp_path / "s.toml"
    study.write_text("x", encoding="utf-8")
    r = CliRunner().invoke(main, ["study", str(study), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2
    assert r.output.strip() == ("pmdsim: error: pmdsim study needs pyarrow (optional extra 'study'); install it with: "
                                "pip install 'pmdsim[study]'")
    assert not (tmp_path / "o").exists()


def test_open_evaluation_without_xarray_names_the_extra(monkeypatch, tmp_path):
    import importlib.util

    import pmdsim

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "h5netcdf" else real(name, *a))
    with pytest.raises(pmdsim.OptionalDependencyError, match=r"needs h5netcdf .* pip install 'pmdsim\[xarray\]'"):
        pmdsim.open_evaluation(tmp_path / "evaluation.h5")
