"""`pmdsim evaluate IMAGE_DIR --method least_squares` in this process with an RSS timeline (50 ms
samples of /proc/self/status VmRSS) and the camera stages' calls (decode, reconstruct, the σ's
linearisation, Jacobian and samples: entry and exit, thread, RSS); prints the peak, the calls
and the timeline (one sample per second) to stderr at exit (docs/benchmarks.md, lsq25h).

    python benchmarks/trace_evaluate_memory.py IMAGE_DIR OUT_DIR
"""

from __future__ import annotations

import atexit
import sys
import threading
import time

T0 = time.perf_counter()
EVENTS: list = []
SAMPLES: list = []


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _sample() -> None:
    while True:
        SAMPLES.append((time.perf_counter() - T0, _rss_mb()))
        time.sleep(0.05)


def _wrap(module, name: str) -> None:
    """Record entry and exit of module.name (time, thread, RSS)."""
    f = getattr(module, name)

    def traced(*args, **kwargs):
        EVENTS.append((time.perf_counter() - T0, threading.get_ident() % 1000, name + " +", _rss_mb()))
        try:
            return f(*args, **kwargs)
        finally:
            EVENTS.append((time.perf_counter() - T0, threading.get_ident() % 1000, name + " −", _rss_mb()))

    setattr(module, name, traced)


def _report() -> None:
    t, peak = max(SAMPLES, key=lambda s: s[1])
    print(f"peak {peak:.0f} MB at {t:.2f} s", file=sys.stderr)
    for t, thread, what, rss in EVENTS:
        print(f"{t:7.2f} s  thread {thread:3d}  {what:28s} {rss:.0f} MB", file=sys.stderr)
    last = -1
    for t, rss in SAMPLES:
        if int(t) != last:
            last = int(t)
            print(f"  t = {t:5.1f} s: {rss:.0f} MB", file=sys.stderr)


def main() -> None:
    image_dir, out_dir = sys.argv[1], sys.argv[2]
    threading.Thread(target=_sample, daemon=True).start()
    from pmdsim.evaluation import uncertainty as U
    from pmdsim.studies import evaluate_cameras as EC
    from pmdsim.studies import jobs as J

    for module, name in ((U, "_sampled_std"), (U, "_LinearisedIntegration"), (U, "_jacobian_scaled"),
                         (EC, "_reconstruct"), (J, "_decode_checked")):
        _wrap(module, name)
    atexit.register(_report)  # the program ends by its own exit path (cli._exit_now runs atexit)
    from pmdsim.cli import main as cli_main

    sys.argv = ["pmdsim", "evaluate", image_dir, "--out", out_dir, "--quiet", "--method", "least_squares"]
    cli_main()


if __name__ == "__main__":
    main()
