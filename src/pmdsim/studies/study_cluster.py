"""The Dask cluster of a study: connect, check the workers, size numba's threads (issue 23).

:func:`open_cluster` connects to an existing scheduler (or starts a
:class:`distributed.LocalCluster`, or takes the user's :class:`distributed.Client`) and checks,
before the first case and before anything is written:

* the scheduler answers (a malformed address or an unreachable scheduler is one
  :class:`~.study_file.StudyError` line);
* it has at least one worker (waits up to the timeout for one);
* every worker imports pmdsim, of this process's version (the error names the worker, its
  host and both versions; a worker without pmdsim is named too);

and sizes numba's thread pool per worker: ``numba threads = max(1, cores of the host // Dask
threads of all workers on that host)`` — so that workers × threads never oversubscribe a host
(a ``dask worker`` runs ``--nthreads`` = cores tasks by default, and each case would otherwise
start numba on all cores: 2 workers on 2 cores ran 8 threads).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from dataclasses import dataclass, field
from typing import Any

from .. import __version__
from .study_file import StudyError

__all__ = ["StudyCluster", "open_cluster", "check_workers", "local_layout"]

# The probe runs on the workers. It is compiled here under a module name that no worker can
# import, so cloudpickle sends it by value: a worker without pmdsim can still run it and say so.
_PROBE_SRC = '''
def probe():
    import os, socket, sys
    info = {"host": socket.gethostname(), "pid": os.getpid(), "cores": os.cpu_count() or 1,
            "python": sys.version.split()[0]}
    try:
        import pmdsim
        info["version"] = str(getattr(pmdsim, "__version__", "unknown"))
        info["path"] = str(getattr(pmdsim, "__file__", ""))
    except Exception as e:
        info["error"] = f"{type(e).__name__}: {e}"
    return info
'''
_NS: dict = {"__name__": "pmdsim_worker_probe"}
exec(compile(_PROBE_SRC, "<pmdsim worker probe>", "exec"), _NS)  # noqa: S102 — fixed source above
_probe = _NS["probe"]


def local_layout(n_workers: int | None, cores: int | None = None) -> tuple[int, int]:
    """The default LocalCluster: (worker processes, numba threads per worker) with
    workers × threads = cores (one Dask thread per worker). Default workers: one per core."""
    cores = cores or os.cpu_count() or 1
    n = max(1, n_workers or cores)
    return n, max(1, cores // n)


@dataclass
class StudyCluster:
    """A connected, checked cluster.

    Attributes
    ----------
    client : distributed.Client
    address : str
        The scheduler's address.
    workers : dict
        Worker address → probe (``host``, ``pid``, ``cores``, ``version``, ``nthreads``).
    numba_threads : dict
        Host name → numba threads per case on that host.
    owned : bool
        Whether :meth:`close` closes the client (False for a client the caller passed).
    """

    client: Any
    address: str
    workers: dict
    numba_threads: dict
    owned: bool = True
    cluster: Any = None
    _closed: bool = field(default=False, repr=False)

    @property
    def n_threads(self) -> int:
        """Dask threads of all workers (cases that run at once)."""
        return sum(int(w.get("nthreads", 1)) for w in self.workers.values())

    def describe(self) -> str:
        hosts = sorted({w["host"] for w in self.workers.values()})
        per = ", ".join(f"{h}: {sum(w['host'] == h for w in self.workers.values())} workers × "
                        f"{self.numba_threads[h]} numba threads" for h in hosts)
        return f"{len(self.workers)} workers, {self.n_threads} Dask threads ({per})"

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.owned:
            with _quiet_dask():
                self.client.close()
                if self.cluster is not None:
                    self.cluster.close()

    def __enter__(self) -> "StudyCluster":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def _quiet_dask():
    """Dask's own log lines (a worker stopping, a connection closed) silenced while a cluster
    stops: the user asked it to stop."""
    log = logging.getLogger("distributed")
    old = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(old)


@contextlib.contextmanager
def _children_ignore_terminal_signals():
    """Worker processes started meanwhile ignore SIGINT and SIGHUP (SIG_IGN survives exec,
    and Python keeps an inherited SIG_IGN): Ctrl-C in a terminal reaches the whole foreground
    process group, and the workers would print their own tracebacks. This process stops them."""
    sigs = [s for s in (signal.SIGINT, getattr(signal, "SIGHUP", None)) if s is not None]
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        signal.signal(s, signal.SIG_IGN)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def _connect(scheduler: str, timeout_s: float):
    from distributed import Client

    with _quiet_dask():
        try:
            return Client(scheduler, timeout=timeout_s)
        except ValueError as e:
            raise StudyError(f"scheduler address {scheduler!r} is not valid ({e}); expected tcp://HOST:PORT") from None
        except (OSError, TimeoutError) as e:
            raise StudyError(f"cannot connect to the Dask scheduler {scheduler!r} within {timeout_s:g} s: {e}") \
                from None


def check_workers(client, timeout_s: float = 30.0) -> tuple[dict, dict]:
    """Wait for at least one worker, probe every worker, refuse a worker without pmdsim or with
    another version. Returns (worker address → probe, host → numba threads per case).

    Raises
    ------
    StudyError
        No worker within ``timeout_s``; a worker that cannot import pmdsim or has another
        version (naming the worker, its host and both versions).
    """
    address = client.scheduler.address
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except TimeoutError:
        raise StudyError(f"the Dask scheduler {address} has no workers (waited {timeout_s:g} s); "
                         "start workers with `dask worker " + address + "`") from None
    info = client.run(_probe, on_error="return")
    nthreads = client.nthreads()
    bad = []
    for w, p in sorted(info.items()):
        if isinstance(p, BaseException):
            bad.append(f"worker {w} cannot run the check: {type(p).__name__}: {p}")
        elif "error" in p:
            bad.append(f"worker {w} (host {p['host']}, pid {p['pid']}) cannot import pmdsim ({p['error']}); "
                       f"this process runs pmdsim {__version__}")
        elif p["version"] != __version__:
            bad.append(f"worker {w} (host {p['host']}, pid {p['pid']}) runs pmdsim {p['version']} ({p['path']}), "
                       f"this process pmdsim {__version__}")
    if bad:
        raise StudyError(bad[0] + (f" (and {len(bad) - 1} more workers)" if len(bad) > 1 else "")
                         + ": install the same pmdsim on every worker")
    workers = {w: {**p, "nthreads": int(nthreads.get(w, 1))} for w, p in info.items()}
    per_host: dict = {}
    for p in workers.values():
        per_host.setdefault(p["host"], [0, p["cores"]])[0] += p["nthreads"]
    threads = {h: max(1, cores // max(1, n)) for h, (n, cores) in per_host.items()}
    return workers, threads


def open_cluster(scheduler: str | None = None, n_workers: int | None = None, *, client=None,
                 timeout_s: float = 30.0) -> StudyCluster:
    """Connect (or start a LocalCluster of ``n_workers`` processes, one Dask thread each) and
    check the workers (module docstring). A ``client`` given is used as is and not closed.

    Raises
    ------
    StudyError
        Malformed or unreachable scheduler, no workers, a worker with another pmdsim.
    """
    cluster = None
    if client is not None:
        owned = False
    elif scheduler:
        client, owned = _connect(scheduler, timeout_s), True
    else:
        from distributed import Client, LocalCluster

        n, _ = local_layout(n_workers)
        with _children_ignore_terminal_signals():
            # silence_logs: the workers' own warnings (a case cancelled by Ctrl-C, a worker restarted)
            # are not the user's business; the study reports lost cases itself.
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   host="127.0.0.1", silence_logs=logging.ERROR)
        client, owned = Client(cluster, timeout=timeout_s), True
    try:
        workers, threads = check_workers(client, timeout_s)
    except BaseException:
        if owned:
            with _quiet_dask():
                client.close()
                if cluster is not None:
                    cluster.close()
        raise
    return StudyCluster(client, client.scheduler.address, workers, threads, owned, cluster)
