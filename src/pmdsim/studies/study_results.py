"""A study's records on disk and its result tables (issue 23: tidy tables with units).

* ``OUT/cases/{key}.json`` — one record per computed case (:mod:`.study`), written atomically;
* ``OUT/results.parquet`` — the **tidy** table: one row per case and camera (columns below);
* ``OUT/results.csv`` — the same table as CSV;
* ``OUT/results_wide.csv`` — one row per case, the metrics as ``{camera}.{metric}`` columns
  (the layout of earlier versions, for spreadsheets).

Columns of the tidy table, in order: ``case_id`` (int64, the case's position in the study),
``case_key`` (the hash of its inputs; identical cases share it), one column per parameter (its
name: the setup key, ``model.`` + key for the evaluation's setup, ``offset(…)`` / ``scale(…)``
when the column holds what was added / the factor), ``mc_sample``, ``seed``, ``camera``,
``status`` (``ok`` / ``failed`` / ``missing``), ``error``, the study's metrics, ``elapsed_s``,
``worker``, ``run_id``. Every column has its declared type whatever the values (an all-null
column is still ``double`` / ``string``, never Arrow's ``null`` type), so reruns, partial runs
and failed studies give the same schema. Field metadata (bytes): ``units`` (``mm``, ``um``,
``urad``, ``degree``, ``pixel``, ``s``, ``1`` = dimensionless or a count) on numeric columns, and
``setup_key`` / ``applies_to`` / ``mode`` on parameter columns.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Callable, Iterable

from .. import __version__
from ..io.outputs import partial_file
from .study_file import OPTION_PATHS, CaseSpec, Parameter, Study

__all__ = ["CASES_DIR", "RESULTS_PARQUET", "RESULTS_CSV", "RESULTS_WIDE_CSV", "read_record", "write_results",
           "results_schema", "wide_rows", "column_units"]

CASES_DIR = "cases"
RESULTS_PARQUET = "results.parquet"
RESULTS_CSV = "results.csv"
RESULTS_WIDE_CSV = "results_wide.csv"

#: Cases per batch when the tables are written (memory stays flat for any number of cases).
BATCH_CASES = 4096

_SUFFIX_UNITS = (("_um", "um"), ("_urad", "urad"), ("_mm", "mm"), ("_px", "pixel"), ("_deg", "degree"),
                 ("_s", "s"))
_INT_METRICS = ("n_pixels", "n_valid_px", "calibration_iterations")
_BOOL_METRICS = ("calibration_converged",)


def column_units(name: str) -> str:
    """Units of a column from its name's suffix (``_um`` → ``um``, ``_px`` → ``pixel``, …),
    ``1`` otherwise (fractions, counts)."""
    base = re.sub(r"(\[\d+\])+$", "", name)
    for suffix, units in _SUFFIX_UNITS:
        if base.endswith(suffix):
            return units
    return "1"


def _meta(**kv) -> dict:
    return {k.encode(): str(v).encode() for k, v in kv.items() if v is not None}


def _param_type(p: Parameter):
    import pyarrow as pa

    if p.path == "seed":
        return pa.int64()
    if p.values is None:  # a Monte-Carlo draw
        return pa.float64()
    if all(isinstance(v, bool) for v in p.values):
        return pa.bool_()
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in p.values):
        return pa.float64()
    return pa.string()  # strings; lists as JSON


def _param_field(p: Parameter):
    import pyarrow as pa

    t = _param_type(p)
    if p.path in OPTION_PATHS:
        return pa.field(p.name, t, metadata=_meta(case_option=p.path))
    units = None if t == pa.bool_() else ("1" if p.mode == "scale" else column_units(p.path))
    return pa.field(p.name, t, metadata=_meta(units=units, setup_key=",".join(p.paths), applies_to=p.applies_to, mode=p.mode))


def _metric_field(name: str, metric: str):
    import pyarrow as pa

    if metric in _BOOL_METRICS:
        return pa.field(name, pa.bool_())
    t = pa.int64() if metric in _INT_METRICS else pa.float64()
    return pa.field(name, t, metadata=_meta(units=column_units(metric)))


def _head_fields(study: Study) -> list:
    import pyarrow as pa

    fields = [pa.field("case_id", pa.int64()), pa.field("case_key", pa.string())]
    fields += [_param_field(p) for p in study.parameters]
    fields += [pa.field("mc_sample", pa.int64())]
    if not any(p.name == "seed" for p in study.parameters):
        fields.append(pa.field("seed", pa.int64()))
    return fields


def _tail_fields() -> list:
    import pyarrow as pa

    return [pa.field("elapsed_s", pa.float64(), metadata=_meta(units="s")), pa.field("worker", pa.string()),
            pa.field("run_id", pa.string())]


def _schema_meta(study: Study, layout: str) -> dict:
    return _meta(pmdsim_version=__version__, study=study.name, action=study.action, layout=layout)


def results_schema(study: Study):
    """The Arrow schema of ``results.parquet`` (module docstring); the same for every run of
    the same study."""
    import pyarrow as pa

    fields = _head_fields(study) + [pa.field("camera", pa.string()), pa.field("status", pa.string()),
                                    pa.field("error", pa.string())]
    fields += [_metric_field(m, m) for m in study.metrics] + _tail_fields()
    return pa.schema(fields, metadata=_schema_meta(study, "one row per case and camera"))


def _wide_schema(study: Study):
    import pyarrow as pa

    fields = _head_fields(study) + [pa.field("status", pa.string()), pa.field("error", pa.string())]
    fields += [_metric_field(f"{c}.{m}", m) for c in study.all_cameras for m in study.metrics] + _tail_fields()
    return pa.schema(fields, metadata=_schema_meta(study, "one row per case"))


def read_record(out: str | Path, key: str) -> dict | None:
    """The record of case ``key`` in ``OUT/cases/``, or None (no file, or an unreadable one)."""
    try:
        return json.loads((Path(out) / CASES_DIR / f"{key}.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _cell(value, typ):
    import pyarrow as pa

    if value is None:
        return None
    if typ == pa.string():
        return value if isinstance(value, str) else json.dumps(value)
    if typ == pa.float64():
        return float(value)
    if typ == pa.int64():
        return int(value)
    return bool(value)


def _rows_of(study: Study, c: CaseSpec, rec: dict | None, long_schema, wide_schema) -> tuple[list, dict]:
    """The tidy rows (one per camera) and the wide row of one case."""
    if rec is None:
        rec = {"status": "missing", "error": None}
    head = {"case_id": c.index, "case_key": c.key, **c.params, "mc_sample": c.mc_sample, "seed": c.seed,
            "status": rec.get("status"), "error": rec.get("error"), "elapsed_s": rec.get("elapsed_s"),
            "worker": rec.get("worker"), "run_id": rec.get("run_id")}
    long_rows = []
    for cam in c.cameras:
        r = {**head, "camera": cam, **{m: rec.get(f"{cam}.{m}") for m in study.metrics}}
        long_rows.append({f.name: _cell(r.get(f.name), f.type) for f in long_schema})
    wide = {**head, **{k: v for k, v in rec.items() if "." in k and k.split(".", 1)[1] in study.metrics}}
    return long_rows, {f.name: _cell(wide.get(f.name), f.type) for f in wide_schema}


def write_results(out: str | Path, study: Study, cases: Iterable[CaseSpec] | None = None,
                  on_case: Callable[[CaseSpec, dict | None], None] | None = None) -> dict:
    """Write ``results.parquet``, ``results.csv`` and ``results_wide.csv`` (atomically, in
    batches of :data:`BATCH_CASES` cases: memory does not grow with the study) from the records
    in ``OUT/cases/``, in case order; a case without a record has ``status = "missing"``.

    Parameters
    ----------
    cases : iterable of CaseSpec, optional
        Default: :meth:`Study.iter_cases` (≈ 5 ms per case to build).
    on_case : callable, optional
        Called with each case and its record (None if missing).

    Returns
    -------
    dict
        Number of cases per status: ``{"ok": …, "failed": …, "missing": …}``.
    """
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    out = Path(out)
    long_schema, wide_schema = results_schema(study), _wide_schema(study)
    targets = [out / RESULTS_PARQUET, out / RESULTS_CSV, out / RESULTS_WIDE_CSV]
    tmps = []
    counts = {"ok": 0, "failed": 0, "missing": 0}
    try:
        for t in targets:
            fd, tmp = partial_file(t)  # mode 0o666 & ~umask
            os.close(fd)
            tmps.append(tmp)
        with pq.ParquetWriter(tmps[0], long_schema) as pw, pacsv.CSVWriter(tmps[1], long_schema) as cw, \
                pacsv.CSVWriter(tmps[2], wide_schema) as ww:
            long_rows, wide_rows_ = [], []

            def flush() -> None:
                if wide_rows_:
                    lt = pa.Table.from_pylist(long_rows, schema=long_schema)
                    pw.write_table(lt)
                    cw.write_table(lt)
                    ww.write_table(pa.Table.from_pylist(wide_rows_, schema=wide_schema))
                    long_rows.clear()
                    wide_rows_.clear()

            for c in (study.iter_cases() if cases is None else cases):
                rec = read_record(out, c.key)
                counts[rec["status"] if rec is not None else "missing"] += 1
                if on_case is not None:
                    on_case(c, rec)
                lr, wr = _rows_of(study, c, rec, long_schema, wide_schema)
                long_rows += lr
                wide_rows_.append(wr)
                if len(wide_rows_) >= BATCH_CASES:
                    flush()
            flush()
        for tmp, t in zip(tmps, targets):
            os.replace(tmp, t)
    except BaseException:
        for tmp in tmps:
            if os.path.exists(tmp):
                os.unlink(tmp)
        raise
    return counts


def wide_rows(table) -> list[dict]:
    """The rows of a tidy results table (``pyarrow.Table`` read from ``results.parquet``) as one
    dict per case, the metrics as ``{camera}.{metric}`` (the summary's and figures' form)."""
    metrics = [f.name for f in table.schema if f.name not in ("camera",) and table.schema.names.index(f.name)
               > table.schema.names.index("error") and f.name not in ("elapsed_s", "worker", "run_id")]
    by_case: dict[int, dict] = {}
    for r in table.to_pylist():
        w = by_case.setdefault(r["case_id"], {k: v for k, v in r.items() if k not in metrics and k != "camera"})
        for m in metrics:
            w[f"{r['camera']}.{m}"] = r[m]
    return list(by_case.values())
