"""Every numba compile of one pmdsim command: kernel, signature, seconds (issue 25 item 2).

Usage (a cold run: fresh numba cache *and* fresh XDG cache, else the shared kernel cache of
another install makes it warm)::

    export NUMBA_CACHE_DIR=$(mktemp -d) XDG_CACHE_HOME=$(mktemp -d) PYTHONPATH=$PWD/src
    python benchmarks/bench_compile.py simulate --bulge-mm 3 --out X --quiet

Prints the wall time, the CPU time, the number of compiles (nested kernels included) and, per
kernel, how often it was compiled, the seconds of its top-level compiles and the CPU seconds of
its own compiles (``own CPU``: the process CPU time of the compile minus that of the kernels it
compiled in turn, so that nested kernels are not counted twice; the column sums to the CPU time
of all compiles). A kernel listed more than once was compiled for several argument types (see
tests/test_kernel_signatures.py). On a loaded machine compare the CPU columns, not wall times.
"""

from __future__ import annotations

import resource
import sys
import time
from collections import defaultdict

from numba.core import event

RECORDS = []  # (depth, kernel, signature, seconds, own CPU seconds)
_STACK = []  # [wall start, CPU start, CPU of nested compiles]


class _Listener(event.Listener):
    def on_start(self, ev):
        _STACK.append([time.perf_counter(), time.process_time(), 0.0])

    def on_end(self, ev):
        t0, c0, nested = _STACK.pop()
        cpu = time.process_time() - c0
        if _STACK:
            _STACK[-1][2] += cpu
        f = ev.data["dispatcher"].py_func
        RECORDS.append((len(_STACK), f"{f.__module__}.{f.__qualname__}", str(ev.data["args"]),
                        time.perf_counter() - t0, cpu - nested))


def main(argv: list[str]) -> None:
    event.register("numba:compile", _Listener())
    from pmdsim.cli import main as cli

    t0 = time.perf_counter()
    try:
        cli(argv, standalone_mode=False)
    finally:
        wall = time.perf_counter() - t0
        ru = resource.getrusage(resource.RUSAGE_SELF)
        top = sum(r[3] for r in RECORDS if r[0] == 0)
        own = sum(r[4] for r in RECORDS)
        print(f"wall {wall:.1f} s, CPU user {ru.ru_utime:.1f} s sys {ru.ru_stime:.1f} s, peak RSS "
              f"{ru.ru_maxrss / 1024:.0f} MB; {len(RECORDS)} compiles, top-level compile {top:.1f} s, "
              f"compile CPU {own:.1f} s", file=sys.stderr)
        per = defaultdict(list)
        for depth, name, _sig, dt, cpu in RECORDS:
            per[name].append((depth, dt, cpu))
        for name, recs in sorted(per.items(), key=lambda kv: (-sum(c for _d, _t, c in kv[1]), kv[0])):
            print(f"{len(recs):3d} × {sum(dt for d, dt, _c in recs if d == 0):7.2f} s top-level "
                  f"{sum(c for _d, _t, c in recs):6.2f} s own CPU  {name}", file=sys.stderr)


if __name__ == "__main__":
    main(sys.argv[1:])
