"""Figures of a study's results (matplotlib, without pyplot; see :mod:`.figures`).

* :func:`metric_vs_parameter_figure` — each metric column against one varied parameter, one
  line per value of a second grid parameter (if any);
* :func:`mc_histogram_figure` — histograms of the metric columns over Monte-Carlo cases.

``rows`` are the result rows of a study, one per case (dicts; :func:`~.study_results.wide_rows`
of ``results.parquet``; ``status`` ``ok`` rows are drawn); metric columns are ``{camera}.{metric}``. Every function returns the Figure and
saves it only when ``path`` is given.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .figures import _save

__all__ = ["metric_vs_parameter_figure", "mc_histogram_figure"]


def _grid(n: int) -> tuple[int, int]:
    ncol = min(n, 3)
    return math.ceil(n / ncol), ncol


def _num(v):
    return float("nan") if v is None else float(v)


def metric_vs_parameter_figure(rows: list[dict], metrics: list[str], parameter: str, *,
                               group_by: str | list[str] | None = None, lines: bool = True, title: str = "",
                               path: str | Path | None = None) -> Figure:
    """Each of ``metrics`` (columns) against ``parameter`` (a numeric column), one line per
    value (combination of values) of ``group_by`` (other columns) or all cases as one line.

    Parameters
    ----------
    rows : list of dict
        Result rows (one per case); rows whose ``status`` is not ``ok`` are left out.
    metrics : list of str
        Metric columns, e.g. ``left.max_dev_plane_um``; one panel each.
    parameter : str
        Column name of a varied parameter (the x axis).
    group_by : str or list of str, optional
        Columns of the other varied parameters: one line per combination of their values.
    lines : bool
        Join the points (False: markers only, e.g. for Monte-Carlo draws at each x).
    """
    ok = [r for r in rows if r.get("status") == "ok"]
    nr, nc = _grid(len(metrics))
    fig = Figure(figsize=(4.2 * nc, 3.2 * nr))
    cols = [group_by] if isinstance(group_by, str) else list(group_by or [])
    groups = list(dict.fromkeys(tuple(r.get(c) for c in cols) for r in ok))  # in case order
    for i, m in enumerate(metrics):
        ax = fig.add_subplot(nr, nc, i + 1)
        for g in groups:
            sel = [r for r in ok if tuple(r.get(c) for c in cols) == g]
            xy = sorted((_num(r.get(parameter)), _num(r.get(m))) for r in sel)
            if not xy:
                continue
            x, y = np.array(xy).T
            label = ", ".join(f"{c} = {v}" for c, v in zip(cols, g)) or None
            ax.plot(x, y, "o-" if lines else "o", ms=3, lw=1, label=label)
        ax.set_xlabel(parameter)
        ax.set_ylabel(m)
        ax.grid(alpha=0.3)
        if cols and i == 0:
            ax.legend(fontsize=6)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def mc_histogram_figure(rows: list[dict], metrics: list[str], *, bins: int = 30, title: str = "",
                        path: str | Path | None = None) -> Figure:
    """Histograms of ``metrics`` (columns) over the ``ok`` rows, with the median and the 5 % /
    95 % quantiles marked."""
    ok = [r for r in rows if r.get("status") == "ok"]
    nr, nc = _grid(len(metrics))
    fig = Figure(figsize=(4.2 * nc, 3.2 * nr))
    for i, m in enumerate(metrics):
        ax = fig.add_subplot(nr, nc, i + 1)
        v = np.array([_num(r.get(m)) for r in ok])
        v = v[np.isfinite(v)]
        if v.size:
            ax.hist(v, bins=bins, color="tab:blue", alpha=0.8)
            for q, ls in ((0.05, ":"), (0.5, "-"), (0.95, ":")):
                ax.axvline(np.quantile(v, q), color="k", ls=ls, lw=1)
        ax.set_xlabel(m)
        ax.set_ylabel("cases")
        ax.set_title(f"{m}: {v.size} cases (median, 5 %, 95 %)", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)
