"""The study engine: run the cases of a study file on ``dask.distributed``, resumably.

* :func:`run_case` — one case, in plain data in and out (runs on a worker; never raises: a
  failing case returns a record with ``status = "failed"`` and its error);
* :func:`run_study` — every case not yet recorded in ``OUT/cases/``, on a Dask cluster (a
  :class:`distributed.LocalCluster` of processes by default, an existing scheduler, or the
  caller's :class:`distributed.Client`; checked first by :mod:`.study_cluster`), each record
  written atomically as its case finishes; then :func:`~.study_results.write_results`
  combines the records into ``OUT/results.parquet`` (tidy: one row per case and camera),
  ``results.csv`` (the same) and ``results_wide.csv`` (one row per case).

Cases are streamed (:meth:`~.study_file.Study.iter_cases`): each is built when a worker
thread is about to be free, with at most :data:`IN_FLIGHT_PER_THREAD` cases per Dask worker
thread (and at least :data:`MIN_IN_FLIGHT`) submitted and not finished — a grid of millions of
cases starts at once and the client's memory does not grow with the grid.

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
from .study_cluster import StudyCluster, open_cluster
from .study_file import CaseSpec, Study, StudyError
from .study_uncertainty import UNCERTAINTY_METRICS, uncertainty_metrics
from .study_results import (CASES_DIR, RESULTS_CSV, RESULTS_PARQUET, RESULTS_WIDE_CSV, read_record,
                            write_results)

__all__ = ["run_case", "run_study", "StudyRun", "write_results", "read_records", "CASES_DIR", "MAPS_DIR",
           "RESULTS_PARQUET", "RESULTS_CSV", "RESULTS_WIDE_CSV", "IN_FLIGHT_PER_THREAD", "MIN_IN_FLIGHT"]

MAPS_DIR = "maps"

#: Cases submitted and not yet finished, per Dask worker thread of the cluster …
IN_FLIGHT_PER_THREAD = 4
#: … and at least this many: the bound on the client's memory (a case is ≈ 10 kB of TOML).
MIN_IN_FLIGHT = 8
#: An interrupted study rewrites its tables (the finished cases, the rest ``missing``) only up
#: to this many cases: a larger grid would take ≈ 5 ms per case to list (the next run writes them).
RESULTS_ON_INTERRUPT_MAX = 100_000


# ============================================================================ one case
def _camera_metrics_simulate(truth, cam) -> dict:
    from ..simulation.render import trace_setup_camera

    m = trace_setup_camera(truth, cam, store_points=False)
    valid = np.asarray(m.valid)
    return {"valid_fraction": float(valid.mean()), "n_valid_px": int(valid.sum())}


def _camera_metrics_evaluate(truth, model, cam, method: str, screen_model: str, sigma: bool = False) -> dict:
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
    reg, rec = evaluate_decoded(model, cam, decoded, method=method, seed_pixel=seed, seed_height_mm=seed_height,
                                screen_model=surf)
    p = rec.p_sample_mm
    err = np.where(rec.reconstructed, rec.height_mm - truth.sample.surface.height(p[..., 0], p[..., 1]), np.nan)
    out = {"valid_fraction": float(np.asarray(mapping.valid).mean()),
           "reconstructed_fraction": float(np.asarray(rec.reconstructed).mean())}
    out.update(surface_error_metrics(p[..., 0], p[..., 1], err))
    if sigma:  # the evaluation's height σ (issue 22): only when a σ metric is asked for
        out.update(uncertainty_metrics(model, cam, decoded, reg, rec, err, method=method, screen_model=surf))
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
    numba_threads : int or dict, optional
        Numba threads of this case (``numba.set_num_threads``, at most the pool size), or a
        mapping host name → threads (:func:`socket.gethostname` of the worker); None: numba's
        default. (Setting ``NUMBA_NUM_THREADS`` in a worker's environment instead
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

    if isinstance(numba_threads, dict):
        numba_threads = numba_threads.get(socket.gethostname())
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
                per_cam[c], maps[c] = _camera_metrics_evaluate(truth, model, c, spec.method, spec.screen_model,
                                                               any(m in UNCERTAINTY_METRICS for m in metrics))
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


def read_records(out: str | Path, cases) -> dict[str, dict]:
    """The records already in ``OUT/cases/`` for these cases: case key → record (unreadable or
    partial files count as missing)."""
    found = {}
    for c in cases:
        r = read_record(out, c.key)
        if r is not None:
            found[c.key] = r
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


# ============================================================================ the engine
@dataclass(frozen=True)
class StudyRun:
    """Outcome of :func:`run_study`.

    Attributes
    ----------
    n_cases, n_reused, n_computed, n_failed, n_missing : int
        All cases; cases whose record an earlier run wrote; computations this run (identical
        cases — the same key — are computed once); cases whose record says failed (either
        run); cases still without a record (a worker died too often, or the run was stopped).
    run_id : str
        This invocation's id (the ``run_id`` of the records it wrote).
    elapsed_s : float
    cluster : str
        The workers and threads the cases ran on (empty for a serial run).
    """

    n_cases: int
    n_reused: int
    n_computed: int
    n_failed: int
    n_missing: int
    run_id: str
    elapsed_s: float
    cluster: str = ""


Progress = Callable[[dict], None]


def _study_json(study: Study) -> dict:
    """What ``OUT/study.json`` records: the study, not its expanded cases (those are the rows
    of the results tables; a grid of millions of cases is not listed before it starts)."""
    def param(p):
        d = {"name": p.name, "path": p.path if not p.linked else list(p.paths), "applies_to": p.applies_to,
             "mode": p.mode}
        if p.values is not None:
            d["values"] = list(p.values)
        else:
            d["distribution"] = list(p.distribution)
        return d

    return {"pmdsim_version": __version__, "study": study.source, "name": study.name, "action": study.action,
            "n_cases": study.n_cases, "parameters": [param(p) for p in study.parameters],
            "monte_carlo": None if not study.mc_samples else {"samples": study.mc_samples, "seed": study.mc_seed},
            "cameras": list(study.all_cameras), "metrics": list(study.metrics)}


def run_study(study: Study, out: str | Path, *, scheduler: str | None = None, n_workers: int | None = None,
              progress: Progress | None = None, serial: bool = False, connect_timeout_s: float = 30.0,
              client=None, worker_timeout_s: float = 60.0) -> StudyRun:
    """Run every case of ``study`` that ``OUT/cases/`` does not hold yet, then write the results.

    Parameters
    ----------
    study : Study
    out : path
        Output directory (created once the cluster is checked; reused by a rerun).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:port``); None: a LocalCluster of
        ``n_workers`` processes (default: one per core) with numba threads = cores // workers.
    client : distributed.Client, optional
        Run on this client's cluster instead (it is checked, used and left open).
    progress : callable, optional
        Called with ``{"done", "failed", "total", "eta_s", "record"}`` after each computed case
        (``done`` counts cases, also those recorded before this run).
    serial : bool
        Run the cases in this process, one after another (no Dask; the reference of the tests).
    connect_timeout_s : float
        How long to try to reach the scheduler and to wait for a first worker.
    worker_timeout_s : float
        How long the cluster may have no worker at all during the run before the study stops.

    Raises
    ------
    StudyError
        Before anything is written: the scheduler cannot be reached, has no worker, or a worker
        runs another pmdsim (:func:`.study_cluster.check_workers`). During the run: every worker
        is gone for ``worker_timeout_s`` (the finished cases are recorded).
    """
    from ..errors import require_extra

    # pmdsim[study]: results are Arrow tables, cases run on Dask (serial runs still write Parquet)
    require_extra("study", "pyarrow", *(() if serial else ("distributed",)), feature="run_study")
    t0 = time.perf_counter()
    out = Path(out)
    if client is not None and scheduler is not None:
        raise StudyError("give either a scheduler address or a client, not both")
    cluster = None if serial else open_cluster(scheduler, n_workers, client=client, timeout_s=connect_timeout_s)
    run_id = uuid.uuid4().hex[:12]
    state = {"done": 0, "failed": 0, "computed": 0, "reused": 0, "t_start": time.perf_counter()}
    interrupted = False
    try:
        (out / CASES_DIR).mkdir(parents=True, exist_ok=True)
        _write_json_atomic(out / "study.json", _study_json(study))
        maps_dir = (out / MAPS_DIR).resolve() if study.save_maps else None
        engine = _Engine(study, out, run_id, state, progress, maps_dir, cluster, worker_timeout_s)
        engine.run()
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        try:
            if cluster is not None:
                cluster.close()
        finally:
            if out.is_dir() and (not interrupted or study.n_cases <= RESULTS_ON_INTERRUPT_MAX):
                counts = write_results(out, study)
    return StudyRun(study.n_cases, state["reused"], state["computed"], counts["failed"], counts["missing"], run_id,
                    time.perf_counter() - t0, "" if cluster is None else cluster.describe())


#: How often (s) the study loop looks for a signal that was recorded but not raised.
_POLL_S = 0.5


class _Engine:
    """The streaming loop of :func:`run_study` (one instance per run)."""

    def __init__(self, study: Study, out: Path, run_id: str, state: dict, progress, maps_dir,
                 cluster: StudyCluster | None, worker_timeout_s: float):
        self.study, self.out, self.run_id, self.state, self.progress = study, out, run_id, state, progress
        self.maps_dir, self.cluster, self.worker_timeout_s = maps_dir, cluster, worker_timeout_s
        self.pending: dict = {}  # case key → [future, number of cases waiting for it]
        self.limit = 0 if cluster is None else max(MIN_IN_FLIGHT, IN_FLIGHT_PER_THREAD * cluster.n_threads)
        self.no_worker_since: float | None = None

    def maps_path(self, c: CaseSpec) -> str | None:
        return None if self.maps_dir is None else str(self.maps_dir / f"{c.key}.h5")

    def run(self) -> None:
        try:
            self._run()
        except BaseException:
            if self.pending:  # stopped: the cases still queued or running are not wanted any more
                futures = [f for f, _ in self.pending.values()]
                try:
                    self.cluster.client.cancel(futures)
                except Exception:  # noqa: BLE001 — the cluster may be gone already
                    pass
                self.pending.clear()
            raise

    def _run(self) -> None:
        for c in self.study.iter_cases():
            interrupts.check()
            if c.key in self.pending:  # an identical case is being computed: it counts for both
                self.pending[c.key][1] += 1
                continue
            rec = read_record(self.out, c.key)
            if rec is not None:
                self.state["done"] += 1
                self.state["failed"] += rec.get("status") == "failed"
                self.state["reused"] += rec.get("run_id") != self.run_id
                continue
            if self.cluster is None:
                self.finished(run_case(c, self.study.metrics, None, self.maps_path(c)), 1)
                continue
            while len(self.pending) >= self.limit:
                self.drain()
            fut = self.cluster.client.submit(run_case, c, self.study.metrics, self.cluster.numba_threads,
                                             self.maps_path(c), key=f"pmdsim-case-{c.key}", pure=False)
            self.pending[c.key] = [fut, 1]
        while self.pending:
            self.drain()
        interrupts.check()

    def finished(self, rec: dict, n: int) -> None:
        rec["run_id"] = self.run_id
        _write_json_atomic(self.out / CASES_DIR / f"{rec['case_key']}.json", rec)
        st = self.state
        st["done"] += n
        st["computed"] += 1
        st["failed"] += n * (rec["status"] == "failed")
        if self.progress is not None:
            left = self.study.n_cases - st["done"]
            rate = st["computed"] / (time.perf_counter() - st["t_start"])
            self.progress({"done": st["done"], "failed": st["failed"], "total": self.study.n_cases,
                           "eta_s": left / rate if rate > 0 else float("nan"), "record": rec})

    def drain(self) -> None:
        """Wait (at most ``_POLL_S``) for cases to finish and record them."""
        from distributed import wait

        # A signal that landed in a finaliser (a Future's __del__, a weakref callback: dask runs
        # many in this thread) is only recorded by pmdsim.interrupts, not raised: look for it at
        # least every _POLL_S, not only when the study ends.
        interrupts.check()
        try:
            with self.cluster.client.as_current():  # also a client that is not the default one
                done = wait([f for f, _ in self.pending.values()], timeout=_POLL_S,
                            return_when="FIRST_COMPLETED").done
        except TimeoutError:
            self.check_workers_alive()
            return
        for fut in sorted(done, key=lambda f: f.key):
            key = fut.key.removeprefix("pmdsim-case-")
            _, n = self.pending.pop(key)
            try:
                rec = fut.result()
            except Exception:  # noqa: BLE001 — the worker died too often: left for the next run
                fut.release()
                continue
            fut.release()
            self.finished(rec, n)

    def check_workers_alive(self) -> None:
        n = len(self.cluster.client.scheduler_info(n_workers=-1).get("workers", {}))
        if n:
            self.no_worker_since = None
            return
        now = time.monotonic()
        self.no_worker_since = self.no_worker_since or now
        if now - self.no_worker_since >= self.worker_timeout_s:
            raise StudyError(f"all workers of the Dask scheduler {self.cluster.address} are gone (none for "
                             f"{self.worker_timeout_s:g} s); {self.state['done']} of {self.study.n_cases} cases are "
                             f"recorded in {self.out}: rerun the same command when workers are back")
