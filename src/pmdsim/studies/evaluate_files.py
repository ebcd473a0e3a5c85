"""The figures of ``pmdsim evaluate`` written in a background thread (issue 25, item 1: files).

Writing a figure (binning a map at the figure's resolution, colouring, drawing text, zlib) runs
mostly outside the GIL: the binning kernels are compiled ``nogil`` and Pillow encodes without
the GIL, as h5py writes and Pillow decodes. So each camera's height and σ maps are drawn while
the next camera is evaluated, and the slope-error figure while ``evaluation.h5`` is written,
instead of one after the other (docs/benchmarks.md, "`evaluate` end to end: the files").
"""

from __future__ import annotations

import contextlib
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Iterator

__all__ = ["BackgroundFiles", "background_files"]


class BackgroundFiles:
    """Files written by one worker thread, in the order submitted."""

    def __init__(self, pool: ThreadPoolExecutor):
        self._pool = pool
        self._futures: list[Future] = []

    def submit(self, write: Callable, *args, **kwargs) -> None:
        """Write a file in the worker: ``write(*args, **kwargs)``."""
        self._futures.append(self._pool.submit(write, *args, **kwargs))

    def wait(self) -> None:
        """Wait for every submitted file; re-raise the first writer's exception."""
        for f in self._futures:
            f.result()


@contextlib.contextmanager
def background_files() -> Iterator[BackgroundFiles]:
    """A :class:`BackgroundFiles` whose files are all written when the ``with`` block ends
    normally (an exception of a writer is raised there). On an exception or interrupt in the
    block, the files not yet started are dropped and the one being written is finished before
    the exception propagates, so that nothing writes into an output directory being discarded
    (:func:`pmdsim.io.outputs.atomic_output_dir`)."""
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pmdsim-files")
    files = BackgroundFiles(pool)
    try:
        yield files
        files.wait()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
