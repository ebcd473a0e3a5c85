"""One-line reprs for result objects that hold per-pixel arrays (issue 23: a repr fits on one
screen — numpy's own repr of a dozen (H, W, k) arrays is hundreds of lines)."""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["compact_repr", "describe"]


def describe(value, depth: int = 0) -> str:
    """A short description: arrays as ``array((H, W, 2), float64)``, mappings and dataclasses
    one level deep, long strings cut."""
    if isinstance(value, np.ndarray):
        return f"array({value.shape}, {value.dtype})" if value.size > 4 else np.array2string(value, separator=", ")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return compact_repr(value, depth) if depth <= 1 else f"{type(value).__name__}(…)"
    if isinstance(value, dict) or hasattr(value, "keys") and hasattr(value, "__getitem__"):
        items = list(value.items()) if hasattr(value, "items") else []
        body = ", ".join(f"{k!r}: {describe(v, depth + 1)}" for k, v in items[:6])
        return "{" + body + (", …" if len(items) > 6 else "") + "}"
    r = repr(value)
    return r if len(r) <= 80 else r[:77] + "…"


def compact_repr(self, depth: int = 0) -> str:
    """``Name(field=…, …)`` with arrays by shape and dtype (a dataclass's ``__repr__``)."""
    parts = [f"{f.name}={describe(getattr(self, f.name, None), depth + 1)}" for f in dataclasses.fields(self) if f.repr]
    return f"{type(self).__name__}({', '.join(parts)})"
