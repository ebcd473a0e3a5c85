"""The study engine on real Dask processes (issue 15; moved here from tests/test_study.py): the
CLI's LocalCluster, an external ``dask scheduler`` with ``dask worker`` processes (one scheduler
for the module, workers started as tests need them), a worker killed with SIGKILL, all workers
gone, workers importing another pmdsim or none. Each Dask run must equal the serial in-process run
bit for bit (every case is deterministic).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_study import EXAMPLE, GOOD, QUICK16, _env, _records, _rows, _wait_for_records, _write

from pmdsim.studies.study import run_study
from pmdsim.studies.study_file import StudyError, load_study


@pytest.fixture(scope="module")
def example_serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "out"
    run = run_study(load_study(EXAMPLE), out, serial=True)
    assert (run.n_cases, run.n_computed, run.n_failed) == (32, 32, 0)
    return _rows(out)


def test_example_serial_physics(example_serial):
    rows = example_serial
    # The left camera's focal-length error cannot change the right camera's reconstruction.
    for bulge in (0.0, 1.0, 2.0, 3.0):
        right = {tuple(r[k] for k in r if k.startswith("right.")) for r in rows if r["screen.bulge_mm"] == bulge}
        assert len(right) == 1
    # No bulge, no focal error: the reconstruction of the true plane is exact to < 0.1 µm.
    (r0,) = [r for r in rows if r["screen.bulge_mm"] == 0.0 and r["offset(model.cameras.left.focal_length_px)"] == 0.0]
    assert r0["left.max_height_diff_um"] < 0.1 and r0["right.max_height_diff_um"] < 0.1


@pytest.mark.slow
def test_example_on_local_cluster_equals_serial(tmp_path, example_serial):
    res = subprocess.run([sys.executable, "-m", "pmdsim.cli", "study", str(EXAMPLE), "--out", str(tmp_path / "out")],
                         env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "32 cases computed, 0 reused, 0 failed, 0 missing" in res.stderr
    # Not a terminal: one progress line per max(1, min(1000, 32 // 20)) = 1 case.
    assert sum(" done, " in line for line in res.stderr.splitlines()) == 32
    assert _rows(tmp_path / "out") == example_serial
    workers = {r["worker"] for r in _records(tmp_path / "out").values()}
    assert len(workers) == min(2, os.cpu_count())  # the cases ran in the LocalCluster's worker processes
    for name in ("results.csv", "summary.txt", "metrics_vs_screen.bulge_mm.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0


def _start(args, log: Path) -> subprocess.Popen:
    return subprocess.Popen(args, env=_env(NUMBA_NUM_THREADS="1"), stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)


def _dask_cli() -> str:
    dask_cli = Path(sys.executable).with_name("dask")  # the `dask` command of this interpreter's install
    if not dask_cli.exists():
        import shutil

        dask_cli = Path(shutil.which("dask"))
    return str(dask_cli)


@pytest.fixture(scope="module")
def dask_scheduler(tmp_path_factory):
    """A ``dask scheduler`` on 127.0.0.1 shared by the module's tests; yields (address, the
    processes started for it: the scheduler, then the workers :func:`dask_cluster` adds, their
    log directory). One start-up instead of one per test (≈ 1 s each)."""
    tmp = tmp_path_factory.mktemp("dask")
    sched_file = tmp / "scheduler.json"
    procs = [_start([_dask_cli(), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sched_file)], tmp / "scheduler.log")]
    try:
        t0 = time.monotonic()
        while not sched_file.exists() and time.monotonic() - t0 < 60:
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        yield address, procs, tmp
    finally:
        for p in procs[::-1]:  # the processes this fixture started, by their pid (a graceful stop takes ~20 s)
            if p.poll() is None:
                p.kill()
            p.wait(timeout=30)


@pytest.fixture
def dask_cluster(dask_scheduler):
    """The shared scheduler with exactly two live ``dask worker`` processes (real ones, no nanny):
    those an earlier test left alive (their kernels loaded), new ones for those it killed; yields
    (address, workers)."""
    address, procs, tmp = dask_scheduler
    workers = [p for p in procs[1:] if p.poll() is None]
    while len(workers) < 2:
        name = f"w{len(procs)}"
        procs.append(_start([_dask_cli(), "worker", address, "--host", "127.0.0.1", "--nthreads", "1", "--no-nanny",
                             "--no-dashboard", "--name", name], tmp / f"{name}.log"))
        workers.append(procs[-1])
    from distributed import Client

    names = {f"w{procs.index(w)}" for w in workers}
    with Client(address, timeout=60) as c:  # the scheduler knows these two and no killed one
        t0 = time.monotonic()
        while {w["name"] for w in c.scheduler_info(n_workers=-1)["workers"].values()} != names:
            assert time.monotonic() - t0 < 120, "the workers did not (un)register"
            time.sleep(0.1)
    yield address, workers


@pytest.mark.slow
def test_example_on_scheduler_and_two_workers_equals_serial(tmp_path, dask_cluster, example_serial):
    address, workers = dask_cluster
    res = subprocess.run([sys.executable, "-m", "pmdsim.cli", "study", str(EXAMPLE), "--out", str(tmp_path / "out"),
                          "--scheduler", address], env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert _rows(tmp_path / "out") == example_serial
    pids = {int(r["worker"].rsplit(":", 1)[1]) for r in _records(tmp_path / "out").values()}
    assert pids == {w.pid for w in workers}  # both external workers computed cases


@pytest.mark.slow
def test_killed_worker_study_completes(tmp_path, dask_cluster):
    address, workers = dask_cluster  # QUICK16: the 14–15 cases after the kill outlast it, also on warm workers
    study, out = _write(tmp_path, QUICK16), tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "pmdsim.cli", "study", str(study), "--out", str(out),
                             "--scheduler", address, "--quiet"], env=_env(), stderr=subprocess.PIPE, text=True)
    _wait_for_records(out, 1, proc)
    workers[0].send_signal(signal.SIGKILL)
    assert workers[0].wait(timeout=30) == -signal.SIGKILL
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    rows = _rows(out)
    assert len(rows) == 16 and all(r["status"] == "ok" for r in rows)
    assert "0 missing" in err


def _fake_pmdsim(root: Path, init: str) -> Path:
    (root / "pmdsim").mkdir(parents=True)
    (root / "pmdsim" / "__init__.py").write_text(init, encoding="utf-8")
    return root


@pytest.mark.slow
def test_workers_with_another_or_no_pmdsim_are_named(tmp_path):
    """A real ``dask scheduler`` and ``dask worker`` processes: a worker whose ``import pmdsim``
    finds another version (a package earlier on its PYTHONPATH), then one where it fails, then
    none at all; each is refused before OUT is created, naming the worker."""
    from pmdsim import __version__
    from pmdsim.studies.study_cluster import check_workers

    dask_cli = Path(sys.executable).with_name("dask")
    sched_file = tmp_path / "scheduler.json"
    procs = [_start([str(dask_cli), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sched_file)], tmp_path / "scheduler.log")]
    other = _fake_pmdsim(tmp_path / "other", '__version__ = "0.0.1.fake"\n')
    broken = _fake_pmdsim(tmp_path / "broken", 'raise ModuleNotFoundError("No module named \'pmdsim\'")\n')
    study = _write(tmp_path, GOOD)

    def worker(pythonpath: Path, name: str) -> subprocess.Popen:
        return subprocess.Popen([str(dask_cli), "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                                 "--no-nanny", "--no-dashboard"], env=_env(PYTHONPATH=str(pythonpath)),
                                stdout=(tmp_path / f"{name}.log").open("w"), stderr=subprocess.STDOUT,
                                start_new_session=True)

    def cli(timeout="30") -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "pmdsim.cli", "study", str(study), "--out",
                               str(tmp_path / "out"), "--scheduler", address, "--connect-timeout", timeout],
                              env=_env(), capture_output=True, text=True, timeout=120)

    from distributed import Client

    try:
        t0 = time.monotonic()
        while not sched_file.exists() and time.monotonic() - t0 < 60:
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        for pythonpath, name, words in ((other, "other", ["runs pmdsim 0.0.1.fake", f"pmdsim {__version__}"]),
                                        (broken, "broken", ["cannot import pmdsim", "ModuleNotFoundError"])):
            w = worker(pythonpath, name)
            procs.append(w)
            with Client(address, timeout=60) as c:
                c.wait_for_workers(1, timeout=120)
                (addr,) = c.scheduler_info(n_workers=-1)["workers"]
            res = cli()
            assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
            err = res.stderr.strip().splitlines()[-1]
            assert err.startswith("pmdsim: error: worker " + addr) and f"pid {w.pid}" in err, err
            assert all(word in err for word in words), err
            assert not (tmp_path / "out").exists()
            w.kill()
            w.wait(timeout=30)
            with Client(address, timeout=60) as c:  # the scheduler notices the lost worker
                t0 = time.monotonic()
                while c.scheduler_info(n_workers=-1)["workers"] and time.monotonic() - t0 < 60:
                    time.sleep(0.2)
        with Client(address, timeout=60) as c:  # no worker at all
            with pytest.raises(StudyError, match=r"has no workers \(waited 1 s\)"):
                check_workers(c, timeout_s=1)
    finally:
        for p in procs[::-1]:
            if p.poll() is None:
                p.kill()
            p.wait(timeout=30)


@pytest.mark.slow
def test_all_workers_gone_stops_the_study(tmp_path, dask_cluster):
    address, workers = dask_cluster
    study, out = load_study(_write(tmp_path, QUICK16)), tmp_path / "out"  # the kill ends it at the first case

    def kill_all(d):  # the first finished case: both workers die (no nanny restarts them)
        if d["done"] == 1:
            for w in workers:
                w.kill()
                w.wait(timeout=30)

    with pytest.raises(StudyError, match=r"all workers of the Dask scheduler .* are gone \(none for 3 s\)"):
        run_study(study, out, scheduler=address, progress=kill_all, worker_timeout_s=3)
    rows = _rows(out)  # the finished cases are recorded, the rest marked missing
    assert len(rows) == 16 and 1 <= sum(r["status"] == "ok" for r in rows) < 16
