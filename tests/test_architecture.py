"""The layering of docs/architecture.md, checked on the source: each subpackage imports only from
the layers below it (read from the import statements, not from pmdsim's own claims)."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "pmdsim"

#: layer → the layers it may import (besides itself).
ALLOWED = {
    "errors": set(),
    "interrupts": set(),  # signal handling: standard library only
    "geometry": {"errors"},
    "setup": {"errors", "geometry"},
    "simulation": {"errors", "geometry", "setup"},
    "evaluation": {"errors", "geometry", "setup"},
    "calibration": {"errors", "geometry", "setup"},
    "io": {"__init__", "errors", "interrupts", "geometry", "setup", "simulation", "evaluation", "calibration"},
    "studies": {"__init__", "errors", "interrupts", "geometry", "setup", "simulation", "evaluation", "calibration", "io"},
    "api": {"errors", "geometry", "setup", "simulation", "evaluation", "calibration", "io"},
    "cli": {"__init__", "errors", "interrupts", "geometry", "setup", "simulation", "evaluation", "calibration", "io", "studies",
            "api"},
    "__init__": set(),
    "__main__": {"cli"},  # python -m pmdsim
    "_precompile": {"__init__"},  # compiles kernels named in a list (importlib); numba's cache directories
}


def _imports(path: Path) -> set[str]:
    """The top-level pmdsim modules/subpackages that ``path`` imports."""
    rel = path.relative_to(SRC).parts
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                if node.module and node.module.split(".")[0] == "pmdsim":
                    parts = node.module.split(".")
                    out.add(parts[1] if len(parts) > 1 else "__init__")
                continue
            base = list(rel[:-1])[: len(rel) - 1 - (node.level - 1)]
            target = base + (node.module.split(".") if node.module else [])
            out.add(target[0] if target else "__init__")
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "pmdsim":
                    out.add(parts[1] if len(parts) > 1 else "__init__")
    return out


def test_layers_import_only_downward():
    bad = []
    for path in SRC.rglob("*.py"):
        rel = path.relative_to(SRC).parts
        layer = rel[0].removesuffix(".py")
        if layer not in ALLOWED:
            bad.append(f"{path.relative_to(SRC)}: not in a known layer ({sorted(ALLOWED)})")
            continue
        for target in _imports(path) - {layer}:
            if target not in ALLOWED[layer]:
                bad.append(f"{path.relative_to(SRC)} ({layer}) imports {target}")
    assert not bad, "\n".join(bad)


def test_modules_stay_readable():
    """No module over ~800 lines (900 hard limit), no exemptions."""
    long = [f"{p.relative_to(SRC)}: {n} lines" for p in SRC.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 900]
    assert not long, long
