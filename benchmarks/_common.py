"""Shared helpers of the benchmark scripts (run them as `python benchmarks/NAME.py`)."""

from __future__ import annotations

import json
import resource
import sys
import time

import numpy as np


def best_of(fn, repeat):
    """(best wall time in s, last result) of ``repeat`` calls of ``fn``."""
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def dump_json(res: dict) -> None:
    json.dump(res, sys.stdout)
    sys.stdout.write("\n")
