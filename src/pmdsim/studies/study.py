"""The study engine: run the cases of a study file on ``dask.distributed``, resumably.

* :func:`run_case` — one case, in plain data in and out (runs on a worker; never raises: a
  failing case returns a record with ``status = "failed"`` and its error);
* :func:`run_study` — every case not yet recorded in ``OUT/cases/``, on a Dask cluster (a
  :class:`distributed.LocalCluster` of processes by default, or an existing scheduler), each
  record written atomically as its case finishes; then :func:`write_results` combines the
  records into ``OUT/results.parquet`` and ``OUT/results.csv`` (one row per case).

Cases are keyed by a hash of their inputs (:class:`~.study_file.CaseSpec`), so a rerun of an
interrupted study (Ctrl-C, a killed worker, a lost node) computes only the missing cases. A
record whose case failed is kept (the failure is deterministic); a case whose worker died is
retried by Dask on another worker and, if it cannot finish, left unrecorded for the next run.

Record (``OUT/cases/{key}.json``): ``case_key``, ``case_index``, the parameter columns,
``mc_sample``, ``seed``, ``status`` (``ok``/``failed``), ``error``, ``elapsed_s``, ``worker``,
``run_id`` (which invocation computed it) and the metrics as ``{camera}.{metric}`` (see
:data:`~.study_file.METRICS`).
"""

from __future__ import annotations

import json
import os
import socket
import time
import traceback
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..simulation.imaging import decoder_response
from .. import __version__, interrupts
from ..io.outputs import partial_file
from .experiment1 import CaseResult
from .study_file import CaseSpec, Study, StudyError

__all__ = ["run_case", "run_study", "StudyRun", "write_results", "read_records", "CASES_DIR", "MAPS_DIR",
           "RESULTS_PARQUET", "RESULTS_CSV"]

CASES_DIR = "cases"
MAPS_DIR = "maps"
RESULTS_PARQUET = "results.parquet"
RESULTS_CSV = "results.csv"


# ============================================================================ one case
def _camera_metrics_simulate(truth, cam) -> dict:
    from ..simulation.render import trace_setup_camera

    m = trace_setup_camera(truth, cam, store_points=False)
    valid = np.asarray(m.valid)
    return {"valid_fraction": float(valid.mean()), "n_valid_px": int(valid.sum())}


def _camera_metrics_evaluate(truth, model, cam, method: str, screen_model: str) -> dict:
    from ..evaluation.metrics import surface_error_metrics
    from ..evaluation.pipeline import decode_images, evaluate_decoded
    from ..simulation.render import render_images, trace_setup_camera

    mapping = trace_setup_camera(truth, cam, store_points=True)
    images: dict = {}
    for spec, img in render_images(truth, cam, mapping):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    decoded = decode_images(truth, images, response=decoder_response(truth))
    del images
    c = model.cameras[cam].camera
    seed = (c.height_px // 2, c.width_px // 2)
    seed_height = float(mapping.p_sample_mm[seed][2])  # perfect knowledge of the seed (Experiment 1)
    if not np.isfinite(seed_height):
        raise RuntimeError(f"the central pixel of camera {cam!r} does not see the sample; cannot seed")
    surf = model.screen.surface if screen_model == "setup" else None
    _, rec = evaluate_decoded(model, cam, decoded, method=method, seed_pixel=seed, seed_height_mm=seed_height,
                              screen_model=surf)
    p = rec.p_sample_mm
    err = np.where(rec.reconstructed, rec.height_mm - truth.sample.surface.height(p[..., 0], p[..., 1]), np.nan)
    out = {"valid_fraction": float(np.asarray(mapping.valid).mean()),
           "reconstructed_fraction": float(np.asarray(rec.reconstructed).mean())}
    out.update(surface_error_metrics(p[..., 0], p[..., 1], err))
    z = truth.screen.control_heights()
    return out, CaseResult.from_reconstruction(float(z[z.shape[0] // 2, z.shape[1] // 2]), cam, rec, err, out)


def _metrics_calibrate(truth, spec: CaseSpec) -> dict:
    """Experiment 2's chain (:func:`~.experiment2.calibrate_and_reconstruct`); start values
    perturbed by ``default_rng([seed, mc_sample or 0])``."""
    from .experiment2 import calibrate_and_reconstruct

    grid = None if spec.screen_model == "planar" else int(spec.screen_model[4:])
    e = calibrate_and_reconstruct(truth, method=spec.method, start_seed=[spec.seed, spec.mc_sample or 0],
                                  screen_grid=grid)
    out = {}
    for case in e.cases:
        if case.camera not in spec.cameras:
            continue
        d = e.deviation[case.camera]
        m = {"reconstructed_fraction": float(np.asarray(case.reconstructed).mean()), **case.metrics,
             "calibration_rms_px": float(e.result.rms_px), "calibration_converged": bool(e.result.converged),
             "calibration_iterations": int(e.result.iterations), "fx_error_px": float(d["fx_px"]),
             "fx_std_px": e.result.std(f"{case.camera}.fx_px"),
             "position_error_mm": float(d["position_mm"]), "rotation_error_deg": float(d["rotation_deg"]),
             "table_turn_deg": float(e.deviation["table_turn_deg"])}
        out[case.camera] = m
    return out, {c.camera: c for c in e.cases if c.camera in spec.cameras}


def _write_maps(path: str, maps: dict, spec: CaseSpec) -> None:
    """The case's reconstructions as HDF5 (one group per camera; layout of
    :func:`~pmdsim.io.hdf5.write_reconstructions_h5`), written atomically."""
    from ..io.hdf5 import reconstructions_h5

    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = partial_file(target)  # mode 0o666 & ~umask (mkstemp: 0600)
    os.close(fd)
    try:
        attrs = {"pmdsim_version": __version__, "case_key": spec.key, "params": json.dumps(spec.params),
                 "setup_toml": spec.truth_toml, "model_setup_toml": spec.model_toml}
        with reconstructions_h5(tmp, attrs) as add:
            for cam, c in maps.items():
                add(c, group=cam)
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def run_case(spec: CaseSpec, metrics: tuple, numba_threads: int | None = None, maps_path: str | None = None) -> dict:
    """Compute one case (on a worker) and return its record (plain data, JSON-ready).

    Parameters
    ----------
    spec : CaseSpec
        The case (setups as TOML text; see :mod:`.study_file`).
    metrics : tuple of str
        The metrics to record per camera.
    numba_threads : int, optional
        Numba threads of this case (``numba.set_num_threads``, at most the pool size); None:
        numba's default. (Setting ``NUMBA_NUM_THREADS`` in a worker's environment instead
        breaks numba's first compilation there: the pool was already launched.)
    maps_path : str, optional
        Also write the reconstructions (height, error, points, valid per camera) to this HDF5
        file (``OUT/maps/{key}.h5``: the workers must see OUT, e.g. a shared file system).

    Returns
    -------
    dict
        The record (module docstring); a failing case has ``status = "failed"`` and ``error``
        (exception type and message) and no metrics. Never raises for a failing case.
    """
    import tomllib

    from ..setup import parse_setup

    if numba_threads is not None:
        import numba

        numba.set_num_threads(max(1, min(int(numba_threads), numba.config.NUMBA_NUM_THREADS)))
    t0 = time.perf_counter()
    rec = {"case_key": spec.key, "case_index": spec.index, **spec.params, "mc_sample": spec.mc_sample,
           "seed": spec.seed, "status": "ok", "error": None}
    try:
        truth = parse_setup(tomllib.loads(spec.truth_toml))
        model = parse_setup(tomllib.loads(spec.model_toml))
        maps = {}
        if spec.action == "simulate":
            per_cam = {c: _camera_metrics_simulate(truth, c) for c in spec.cameras}
        elif spec.action == "simulate+evaluate":
            per_cam = {}
            for c in spec.cameras:
                per_cam[c], maps[c] = _camera_metrics_evaluate(truth, model, c, spec.method, spec.screen_model)
        else:
            per_cam, maps = _metrics_calibrate(truth, spec)
        if maps_path is not None and maps:
            _write_maps(maps_path, maps, spec)
        for cam, m in per_cam.items():
            for k in metrics:
                v = m[k]
                rec[f"{cam}.{k}"] = v if isinstance(v, (bool, int)) or np.isfinite(v) else None
    except Exception as e:  # noqa: BLE001 — a failing case is recorded, the study goes on
        rec["status"] = "failed"
        rec["error"] = f"{type(e).__name__}: {e}"
        rec["traceback"] = traceback.format_exc(limit=8)
    rec["elapsed_s"] = time.perf_counter() - t0
    rec["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return rec


# ============================================================================ records on disk
def _write_json_atomic(path: Path, obj) -> None:
    fd, tmp = partial_file(path)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(obj, f, indent=1, ensure_ascii=False, allow_nan=False)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_records(out: str | Path, cases: list[CaseSpec]) -> dict[str, dict]:
    """The records already in ``OUT/cases/`` for these cases: case key → record (unreadable or
    partial files count as missing)."""
    d = Path(out) / CASES_DIR
    found = {}
    for c in cases:
        p = d / f"{c.key}.json"
        try:
            found[c.key] = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
    return found


def _atomic_write_via(target: Path, writer: Callable[[str], None]) -> None:
    fd, tmp = partial_file(target)  # mode 0o666 & ~umask (mkstemp: 0600)
    os.close(fd)
    try:
        writer(tmp)
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_results(out: str | Path, study: Study, cases: list[CaseSpec]) -> list[dict]:
    """Combine the records of ``cases`` into ``OUT/results.parquet`` and ``OUT/results.csv``
    (atomically), one row per case in case order; cases without a record are rows with
    ``status = "missing"``. Returns the rows."""
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    out = Path(out)
    recs = read_records(out, cases)
    rows = []
    for c in cases:
        r = recs.get(c.key)
        if r is None:
            r = {"case_key": c.key, "case_index": c.index, **c.params, "mc_sample": c.mc_sample, "seed": c.seed,
                 "status": "missing", "error": None}
        # (identical cases share a record; each keeps its own row index)
        r = {k: v for k, v in r.items() if k != "traceback"} | {"case_index": c.index}
        for k, v in list(r.items()):
            if isinstance(v, list):  # a list-valued setup key: a string column (parquet needs one type)
                r[k] = json.dumps(v)
        rows.append(r)
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    table = pa.Table.from_pylist([{k: r.get(k) for k in columns} for r in rows])
    _atomic_write_via(out / RESULTS_PARQUET, lambda p: pq.write_table(table, p))
    _atomic_write_via(out / RESULTS_CSV, lambda p: pacsv.write_csv(table, p))
    return rows


# ============================================================================ the engine
@dataclass(frozen=True)
class StudyRun:
    """Outcome of :func:`run_study`.

    Attributes
    ----------
    n_cases, n_reused, n_computed, n_failed, n_missing : int
        All cases; cases recorded before this run; computed now; failed (recorded, either run);
        still without a record (a worker died too often, or the run was interrupted). Identical
        cases (the same key) count once in all but ``n_cases``.
    run_id : str
        This invocation's id (the ``run_id`` of the records it wrote).
    elapsed_s : float
    """

    n_cases: int
    n_reused: int
    n_computed: int
    n_failed: int
    n_missing: int
    run_id: str
    elapsed_s: float


Progress = Callable[[dict], None]


def _local_cluster(n_workers: int | None):
    from distributed import LocalCluster

    cores = os.cpu_count() or 1
    n = max(1, n_workers or cores)
    # workers × numba threads = cores (run_case sets the threads); one Dask thread per worker.
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                           host="127.0.0.1")
    return cluster, max(1, cores // n)


def run_study(study: Study, out: str | Path, *, scheduler: str | None = None, n_workers: int | None = None,
              progress: Progress | None = None, serial: bool = False, connect_timeout_s: float = 30.0) -> StudyRun:
    """Run every case of ``study`` that ``OUT/cases/`` does not hold yet, then write the results.

    Parameters
    ----------
    study : Study
    out : path
        Output directory (created; reused by a rerun).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:port``); None: a LocalCluster of
        ``n_workers`` processes (default: one per core) with numba threads = cores // workers.
    progress : callable, optional
        Called with ``{"done", "failed", "total", "eta_s", "record"}`` after each finished case.
    serial : bool
        Run the cases in this process, one after another (no Dask; the reference of the tests).
    connect_timeout_s : float
        How long to try to reach the scheduler.

    Raises
    ------
    StudyError
        The scheduler cannot be reached (nothing is computed).
    """
    t0 = time.perf_counter()
    out = Path(out)
    (out / CASES_DIR).mkdir(parents=True, exist_ok=True)
    cases = study.cases()
    _write_json_atomic(out / "study.json", {
        "pmdsim_version": __version__, "study": study.source, "name": study.name, "action": study.action,
        "n_cases": len(cases), "parameters": [p.name for p in study.parameters],
        "cases": [{"case_key": c.key, "case_index": c.index, **c.params} for c in cases]})
    unique = list({c.key: c for c in cases}.values())  # identical cases (same key) run once
    have = read_records(out, unique)
    todo = [c for c in unique if c.key not in have]
    run_id = uuid.uuid4().hex[:12]
    state = {"done": len(have), "failed": sum(r.get("status") == "failed" for r in have.values()), "computed": 0}

    def finished(rec: dict) -> None:
        rec["run_id"] = run_id
        _write_json_atomic(out / CASES_DIR / f"{rec['case_key']}.json", rec)
        state["done"] += 1
        state["computed"] += 1
        state["failed"] += rec["status"] == "failed"
        if progress is not None:
            left = len(unique) - state["done"]
            rate = state["computed"] / (time.perf_counter() - t_start)
            progress({"done": state["done"], "failed": state["failed"], "total": len(unique),
                      "eta_s": left / rate if rate > 0 else float("nan"), "record": rec})

    maps_dir = (out / MAPS_DIR).resolve() if study.save_maps else None
    maps = {c.key: None if maps_dir is None else str(maps_dir / f"{c.key}.h5") for c in todo}
    t_start = time.perf_counter()
    try:
        if serial or not todo:
            for c in todo:
                finished(run_case(c, study.metrics, None, maps[c.key]))
                interrupts.check()
        else:
            _run_on_dask(todo, study.metrics, maps, finished, scheduler, n_workers, connect_timeout_s)
    finally:
        write_results(out, study, cases)
    recs = read_records(out, unique)
    return StudyRun(len(cases), len(have), state["computed"],
                    sum(r.get("status") == "failed" for r in recs.values()), len(unique) - len(recs), run_id,
                    time.perf_counter() - t0)


#: How often (s) the study loop looks for a signal that was recorded but not raised.
_POLL_S = 0.5


def _run_on_dask(todo: list[CaseSpec], metrics: tuple, maps: dict, finished, scheduler: str | None,
                 n_workers: int | None, connect_timeout_s: float) -> None:
    from distributed import Client, wait

    cluster, threads = (None, None) if scheduler else _local_cluster(n_workers)
    try:
        client = Client(scheduler if scheduler else cluster, timeout=connect_timeout_s)
    except (OSError, TimeoutError) as e:
        if cluster is not None:
            cluster.close()
        raise StudyError(f"cannot connect to the Dask scheduler {scheduler or cluster.scheduler_address!r} "
                         f"within {connect_timeout_s:g} s: {e}") from None
    try:
        futures = [client.submit(run_case, c, metrics, threads, maps[c.key], key=f"pmdsim-case-{c.key}", pure=False)
                   for c in todo]
        pending = set(futures)
        while pending:
            # A signal that landed in a finaliser (a Future's __del__, a weakref callback: dask
            # runs many in this thread) is only recorded by pmdsim.interrupts, not raised: look
            # for it at least every _POLL_S, not only when the study ends.
            interrupts.check()
            try:
                done = wait(list(pending), timeout=_POLL_S, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                continue
            for fut in sorted(done, key=lambda f: f.key):
                pending.discard(fut)
                try:
                    rec = fut.result()
                except Exception:  # noqa: BLE001 — the worker died too often: left for the next run
                    continue
                finished(rec)
                fut.release()
        interrupts.check()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
