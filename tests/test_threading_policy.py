"""How pmdsim's parallel kernels wait (docs/benchmarks.md, "Parallel kernels under load: passive
OpenMP waiting"): ``import pmdsim`` asks GNU OpenMP for passive waiting unless the user chose,
in a fresh interpreter (the variable is read by libgomp when it is loaded), and the thread-limit
context restores numba's setting."""

from __future__ import annotations

import os
import subprocess
import sys

import numba

from pmdsim.geometry.kernel_args import numba_threads

_PROBE = "import os, sys, pmdsim; print(os.environ['OMP_WAIT_POLICY'], 'numba' in sys.modules)"


def _probe(**env):
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", _PROBE], env={**base, **env}, capture_output=True, text=True,
                         check=True)
    return out.stdout.split()


def test_import_asks_for_passive_waiting_and_keeps_the_users_choice():
    assert _probe() == ["PASSIVE", "False"]  # set, and nothing compiled or imported for it
    assert _probe(OMP_WAIT_POLICY="ACTIVE") == ["ACTIVE", "False"]


def test_thread_limit_is_restored_after_the_block_and_after_an_error():
    before = numba.get_num_threads()
    with numba_threads(1):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == before
    try:
        with numba_threads(1):
            raise KeyError("x")
    except KeyError:
        pass
    assert numba.get_num_threads() == before
    with numba_threads(before + 5):  # never above the current setting
        assert numba.get_num_threads() == before
