"""What `pmdsim evaluate` (or any pmdsim command) spends around its work (issue 25, item 1).

    python benchmarks/bench_cli_startup.py loads evaluate SET --out DIR --quiet
    python benchmarks/bench_cli_startup.py exit evaluate SET --out DIR --quiet

``loads``: runs the command in this process with numba's ``Dispatcher.compile`` timed — every
kernel's load from the cache (or compile), with its name and when it happened — and prints them,
largest first, with the scipy subpackages the run imported. ``exit``: runs the command in a child
process that reports when ``main()`` returned; the rest of the wall time is the interpreter's
exit (thread joins, atexit handlers, freeing the arrays). Delete DIR afterwards.
"""

from __future__ import annotations

import atexit
import resource
import subprocess
import sys
import time

_CHILD = r'''
import sys, time
t0 = time.time()
from pmdsim.cli import main
t_imp = time.time()
sys.argv = ["pmdsim-bench"] + sys.argv[1:]  # not "pmdsim": main() returns (cli._is_program)
try:
    main()
except SystemExit:
    pass
print(f"IMPORT_CLI {t_imp - t0:.3f} MAIN_END {time.time():.6f} START {t0:.6f}", file=sys.stderr)
'''


def _exit_split(args: list[str]) -> None:
    t0 = time.time()
    p = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True, text=True)
    t1 = time.time()
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    line = [x for x in p.stderr.splitlines() if x.startswith("IMPORT_CLI")][-1].split()
    main_end, start = float(line[3]), float(line[5])
    print(f"wall {t1 - t0:.2f} s (interpreter start {start - t0:.2f} s, cli import {float(line[1]):.2f} s, "
          f"exit after main {t1 - main_end:.2f} s); CPU user {ru.ru_utime:.2f} s sys {ru.ru_stime:.2f} s; "
          f"maxrss {ru.ru_maxrss} KB")


def _kernel_loads(args: list[str]) -> None:
    t_start = time.perf_counter()
    from numba.core import dispatcher

    rec = []
    orig = dispatcher.Dispatcher.compile

    def compile(self, sig):
        t0 = time.perf_counter()
        r = orig(self, sig)
        rec.append((time.perf_counter() - t0, f"{self.py_func.__module__}.{self.py_func.__qualname__}", t0 - t_start))
        return r

    dispatcher.Dispatcher.compile = compile

    def report():
        print(f"{len(rec)} compiles/loads, {sum(r[0] for r in rec):.3f} s total; scipy subpackages: "
              f"{sorted(m for m in sys.modules if m.startswith('scipy.') and m.count('.') == 1)}", file=sys.stderr)
        for dt, name, at in sorted(rec, reverse=True):
            print(f"{dt * 1e3:8.1f} ms at {at:6.2f} s  {name}", file=sys.stderr)

    atexit.register(report)
    from pmdsim.cli import main

    sys.argv = ["pmdsim-bench", *args]  # not "pmdsim": the atexit report runs either way
    main()


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("loads", "exit"):
        sys.exit(__doc__)
    (_kernel_loads if sys.argv[1] == "loads" else _exit_split)(sys.argv[2:])
