"""The background figure writer of ``pmdsim evaluate`` (studies/evaluate_files, issue 25): every
submitted file is written when the block ends, a writer's exception is raised there, and an
exception inside the block drops the files not started and finishes the one being written before
it propagates (nothing writes into a discarded output directory afterwards)."""

from __future__ import annotations

import threading

import pytest

from pmdsim.studies.evaluate_files import background_files


def test_files_written_in_order_by_one_thread(tmp_path):
    seen = []

    def write(path, text):
        seen.append((path.name, threading.current_thread() is threading.main_thread()))
        path.write_text(text)

    with background_files() as files:
        for k in range(5):
            files.submit(write, tmp_path / f"f{k}.txt", text=str(k))
    assert [p for p, _ in seen] == [f"f{k}.txt" for k in range(5)]
    assert not any(main for _, main in seen)
    assert [(tmp_path / f"f{k}.txt").read_text() for k in range(5)] == [str(k) for k in range(5)]


def test_writer_exception_raised_at_the_end(tmp_path):
    def bad():
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        with background_files() as files:
            files.submit(bad)
            files.submit((tmp_path / "after.txt").write_text, "x")


def test_exception_in_block_cancels_queued_and_finishes_running(tmp_path):
    started, release = threading.Event(), threading.Event()
    done = []

    def slow():
        started.set()
        release.wait(5)
        done.append("slow")

    def later():
        done.append("later")

    with pytest.raises(KeyboardInterrupt):
        with background_files() as files:
            files.submit(slow)
            files.submit(later)
            assert started.wait(5)
            threading.Timer(0.5, release.set).start()  # still running when the block is left
            raise KeyboardInterrupt
    assert done == ["slow"]  # the running one finished before the exception left the block; the queued one dropped
