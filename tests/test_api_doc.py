"""docs/api.md runs: its Python code blocks are executed in order, in one namespace, in a
temporary directory (the walk-through's own asserts compare with the truth it simulated)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def code_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_api_walkthrough_runs(tmp_path, monkeypatch, capsys):
    blocks = code_blocks(DOC.read_text(encoding="utf-8"))
    assert len(blocks) >= 6
    monkeypatch.chdir(tmp_path)
    mods_before = set(sys.modules)
    namespace: dict = {"__name__": "api_doc"}
    for i, block in enumerate(blocks):
        try:
            exec(compile(block, f"docs/api.md block {i + 1}", "exec"), namespace)
        except Exception as e:  # pragma: no cover - the message names the block
            pytest.fail(f"docs/api.md code block {i + 1} failed: {type(e).__name__}: {e}")
    assert (tmp_path / "height_error.png").stat().st_size > 10_000
    out = capsys.readouterr().out
    assert "converged: True" in out


def test_import_pmdsim_neither_compiles_nor_switches_backend():
    import subprocess

    # The old figures module called matplotlib.use("Agg") on import, which breaks inline plots.
    code = ("import sys, numpy as np, matplotlib; b = matplotlib.rcParams._get_backend_or_none(); "
            "import pmdsim; v = pmdsim.__version__; "
            "print('numba' in sys.modules); "
            "import pmdsim.studies.figures as f; "
            "fig = f.height_map_figure(*np.meshgrid(np.arange(4.0), np.arange(3.0)), np.ones((3, 4)), title='t'); "
            "assert matplotlib.rcParams._get_backend_or_none() == b, (b, matplotlib.rcParams._get_backend_or_none()); "
            "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot imported'")
    env = {k: v for k, v in __import__("os").environ.items() if k != "MPLBACKEND"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[0] == "False"  # import pmdsim (and its version) imports no numba
