"""``pmdsim.studies``' public names imported lazily: each name is the object its submodule defines,
whatever was imported before (a fresh interpreter per order, as a user's script runs)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = str(Path(__file__).resolve().parents[1] / "src")

_CHECK = """
import sys, types
{first}
import pmdsim.studies as st
from pmdsim.studies import experiment1
mod = sys.modules["pmdsim.studies.experiment1"]
assert experiment1 is mod.experiment1, experiment1
assert callable(experiment1) and not isinstance(experiment1, types.ModuleType)
for name in st.__all__:
    value = getattr(st, name)
    assert not isinstance(value, types.ModuleType), name
print("ok")
"""


@pytest.mark.parametrize("first", [
    "",  # the package first, then the name
    "import pmdsim.studies.experiment2",  # a submodule that imports .experiment1 (the module) first
    "from pmdsim.studies.experiment1 import CaseResult",
    "import pmdsim.studies.runs, pmdsim.studies.study",
])
def test_public_names_are_not_shadowed_by_submodules(first):
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-c", _CHECK.format(first=first)], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
