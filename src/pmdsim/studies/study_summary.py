"""A study's summary (quantiles per metric column) and its figures, from OUT/results.parquet.

The tidy table (one row per case and camera, :mod:`.study_results`) is read back as one row per
case with ``{camera}.{metric}`` columns (:func:`~.study_results.wide_rows`): the summary has one
line per camera and metric.

:func:`metric_quantiles` gives, per metric column, the count of finite values, mean, standard
deviation (n − 1), min, the 5/25/50/75/95 % quantiles (linear interpolation between order
statistics, numpy's default = Hyndman & Fan type 7) and max over the ``ok`` cases;
:func:`write_study_outputs` writes ``summary.txt``, ``summary.json`` and the figures
(``{metric}_vs_{parameter}.png`` for grid parameters, ``hist_{metric}.png`` for Monte-Carlo
studies) into the study's output directory.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .study_file import Study

__all__ = ["QUANTILES", "metric_columns", "metric_quantiles", "summary_text", "write_study_outputs"]

#: The quantiles of the summary.
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)


def metric_columns(study: Study, rows: list[dict]) -> list[str]:
    """The ``{camera}.{metric}`` columns present in ``rows``, in the study's metric order."""
    present = {k for r in rows for k in r}
    cams = sorted({k.split(".", 1)[0] for k in present if "." in k and k.split(".", 1)[1] in study.metrics})
    return [f"{c}.{m}" for m in study.metrics for c in cams if f"{c}.{m}" in present]


def metric_quantiles(rows: list[dict], column: str) -> dict:
    """Statistics of one metric column over the ``ok`` rows (see the module docstring)."""
    v = np.array([float(r[column]) for r in rows if r.get("status") == "ok" and r.get(column) is not None])
    v = v[np.isfinite(v)]
    out = {"n": int(v.size)}
    if v.size == 0:
        return out
    out.update(mean=float(v.mean()), std=float(v.std(ddof=1)) if v.size > 1 else float("nan"), min=float(v.min()))
    out.update({f"q{round(q * 100):02d}": float(np.quantile(v, q)) for q in QUANTILES})
    out["max"] = float(v.max())
    return out


def summary_text(study: Study, rows: list[dict]) -> str:
    """The summary table as text (one line per metric column)."""
    cols = metric_columns(study, rows)
    n_ok = sum(r.get("status") == "ok" for r in rows)
    n_failed = sum(r.get("status") == "failed" for r in rows)
    head = [f"study {study.name!r}: {len(rows)} cases, {n_ok} ok, {n_failed} failed, "
            f"{len(rows) - n_ok - n_failed} missing; action {study.action}",
            "parameters: " + ", ".join(
                f"{p.name} ({'grid of ' + str(len(p.values)) if p.values is not None else p.distribution[0]})"
                for p in study.parameters)]
    keys = ["n", "mean", "std", "min"] + [f"q{round(q * 100):02d}" for q in QUANTILES] + ["max"]
    w = max([len(c) for c in cols] + [6])
    lines = head + ["", f"{'metric':<{w}} " + " ".join(f"{k:>11}" for k in keys)]
    for c in cols:
        s = metric_quantiles(rows, c)
        lines.append(f"{c:<{w}} " + " ".join(f"{s[k]:>11d}" if k == "n" else
                                             (f"{s[k]:>11.4g}" if k in s else f"{'—':>11}") for k in keys))
    failed = [r for r in rows if r.get("status") == "failed"]
    if failed:
        lines += ["", "failed cases:"] + [f"  case {r['case_id']} ({r['case_key']}): {r['error']}" for r in failed]
    return "\n".join(lines) + "\n"


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "._-" else "_" for ch in name)


def write_study_outputs(study: Study, out: str | Path) -> list[str]:
    """Write ``summary.txt``, ``summary.json`` and the figures from ``OUT/results.parquet``;
    returns the names written."""
    import pyarrow.parquet as pq

    from .study import RESULTS_PARQUET, _atomic_write_via
    from .study_figures import mc_histogram_figure, metric_vs_parameter_figure
    from .study_results import wide_rows

    out = Path(out)
    rows = wide_rows(pq.read_table(out / RESULTS_PARQUET))
    cols = metric_columns(study, rows)
    written = ["summary.txt", "summary.json"]
    text = summary_text(study, rows)
    js = json.dumps({c: metric_quantiles(rows, c) for c in cols}, indent=1, allow_nan=True) + "\n"
    for name, content in (("summary.txt", text), ("summary.json", js)):
        _atomic_write_via(out / name, lambda p, content=content: Path(p).write_text(content, encoding="utf-8"))
    if not cols:
        return written
    varied = [p for p in study.grid_parameters if len(p.values) > 1]
    grid = [p for p in varied if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in p.values)]
    for p in grid:  # numeric parameters on the x axis; one line per value of the other parameter
        others = [q for q in varied if q is not p]
        name = f"metrics_vs_{_safe(p.name)}.png"
        metric_vs_parameter_figure(rows, cols, p.name, group_by=[q.name for q in others],
                                   lines=not study.mc_samples, title=study.name, path=out / name)
        written.append(name)
    if study.mc_samples:
        metric_vs = "hist_metrics.png"
        mc_histogram_figure(rows, cols, title=study.name, path=out / metric_vs)
        written.append(metric_vs)
    return written
