"""`pmdsim evaluate` ends its process without Python's module teardown (cli._exit_now, issue 25):
the exit code, the output, the threads' joins and the atexit handlers are kept."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = str(Path(__file__).resolve().parents[1] / "src")
ENV = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}

_CHILD = """
import atexit, sys, time
from concurrent.futures import ThreadPoolExecutor
from pmdsim.cli import _exit_now
atexit.register(lambda: print("atexit ran", flush=False))
pool = ThreadPoolExecutor(1)
pool.submit(lambda: (time.sleep(0.3), print("worker done", flush=False)))
print("out", flush=False)
_exit_now({code!r})
print("not reached")
"""


@pytest.mark.parametrize("code, status", [(None, 0), (0, 0), (1, 1), (2, 2), ("pmdsim: error: x", 1)])
def test_exit_now_keeps_status_output_threads_and_atexit(code, status):
    out = subprocess.run([sys.executable, "-c", _CHILD.format(code=code)], env=ENV, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == status, out.stderr[-2000:]
    assert out.stdout.split() == ["out", "worker", "done", "atexit", "ran"], out.stdout
    if isinstance(code, str):
        assert code in out.stderr


def test_evaluate_error_exit_code_from_the_program(tmp_path):
    # A missing image directory: the one-line error and exit code 2, through the fast exit.
    out = subprocess.run([sys.executable, "-m", "pmdsim.cli", "evaluate", str(tmp_path / "none"), "--out",
                          str(tmp_path / "o"), "--quiet"], env=ENV, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.startswith("pmdsim: error:") and "Traceback" not in out.stderr, out.stderr


def test_main_called_by_a_program_still_raises_system_exit():
    # Not the pmdsim program (sys.argv[0] is "-c"): main() ends by SystemExit as click's does.
    child = ("import sys\nfrom pmdsim.cli import main\nsys.argv = ['x', 'evaluate', '/nonexistent-dir', '--out', '/tmp/x']\n"
             "try:\n    main()\nexcept SystemExit as e:\n    print('caught', e.code)\n")
    out = subprocess.run([sys.executable, "-c", child], env=ENV, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "caught 2", (out.stdout, out.stderr[-2000:])
