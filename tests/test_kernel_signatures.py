"""One compiled signature per numba kernel on the main paths (issue 25 item 2: a first run that
does not stall).

numba compiles a kernel once per distinct argument *type*: an int64 and a uint64 index, a
C-contiguous and a strided array, a writable and a read-only one, are different types, and
each costs a full compile on a cold cache (the tracer's band kernel took minutes). A
``prange(n)`` loop index is uint64 in the parallel body but int64 where numba types the loop
sequentially, so a kernel called with it compiles twice; ``prange(0, n)`` is int64 in both.

The check runs ``simulate``, ``evaluate`` (stepwise and least squares) and ``calibrate`` on the
small setup in a fresh interpreter, then asks every numba dispatcher of pmdsim for its
signatures (``dispatcher.signatures``, numba's own record). On a cold cache that is every
kernel, nested ones included; on a warm cache numba loads only the kernels called from Python
(their nested callers' code is inside them), each loaded signature counted. A kernel may be
specialised on *literal* constants by its callers (``Literal[bool](True)``: a branch removed
at compile time, on purpose); apart from that, every kernel must have exactly one signature.
The ``prange`` rule is checked on the sources (a warm cache cannot show nested compiles) and
shown on a throwaway kernel.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pmdsim

SCRIPT = textwrap.dedent("""
    import importlib, json, pkgutil, sys
    from pathlib import Path
    from click.testing import CliRunner
    from numba.core import types
    from numba.core.registry import CPUDispatcher
    import pmdsim
    from pmdsim.cli import main

    tmp, setup = Path(sys.argv[1]), sys.argv[2]
    runner = CliRunner()

    def run(*args):
        r = runner.invoke(main, [*args, "--quiet"])
        assert r.exit_code == 0, r.output

    run("simulate", "--setup", setup, "--out", str(tmp / "sample"))
    run("evaluate", str(tmp / "sample"), "--setup", setup, "--out", str(tmp / "ev_stepwise"))
    run("evaluate", str(tmp / "sample"), "--setup", setup, "--out", str(tmp / "ev_lsq"), "--method", "least_squares")
    poses = []
    for k in range(16):
        run("simulate", "--setup", setup, "--calibration-pose", str(k), "--out", str(tmp / f"pose{k:02d}"))
        poses.append(str(tmp / f"pose{k:02d}"))
    run("calibrate", *poses, "--setup", setup, "--out", str(tmp / "calibrated.toml"), "--stride", "4")

    for m in pkgutil.walk_packages(pmdsim.__path__, "pmdsim."):
        importlib.import_module(m.name)
    out = {}
    for name, mod in sorted(sys.modules.items()):
        if not name.startswith("pmdsim"):
            continue
        for attr, f in vars(mod).items():
            if isinstance(f, CPUDispatcher) and f.py_func.__module__ == name and f.signatures:
                out[name + "." + attr] = [[str(t) for t in sig] for sig in f.signatures]
                out[name + "." + attr + " (unliteral)"] = sorted({str(tuple(types.unliteral(t) for t in sig))
                                                                   for sig in f.signatures})
    print("SIGNATURES " + json.dumps(out))
""")


def test_each_kernel_compiles_once_on_the_main_paths(tmp_path, small_setup_file):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(pmdsim.__file__).parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), str(small_setup_file)], capture_output=True,
                       text=True, env=env, timeout=1800)
    assert r.returncode == 0, r.stderr[-3000:]
    line = next(x for x in r.stdout.splitlines() if x.startswith("SIGNATURES "))
    sigs = json.loads(line[len("SIGNATURES "):])
    kernels = {k: v for k, v in sigs.items() if not k.endswith(" (unliteral)")}
    # The main paths reach the tracer, the decoder, both integrations and the calibration.
    for name in ("pmdsim.simulation.trace._trace_kernel", "pmdsim.geometry.camera._rays_kernel",
                 "pmdsim.simulation.patterns._render_stack_kernel", "pmdsim.evaluation.decoding._decode_kernel",
                 "pmdsim.evaluation.stepwise._stepwise_kernel", "pmdsim.evaluation.least_squares._apply_update",
                 "pmdsim.evaluation.surface_fit._weighted_sums", "pmdsim.calibration.kernel._chunks_kernel"):
        assert name in kernels, sorted(kernels)
    assert len(kernels) >= 30, sorted(kernels)
    several = {k: kernels[k] for k in kernels if len(sigs[k + " (unliteral)"]) != 1}
    assert not several, "kernels compiled for more than one argument type:\n" + json.dumps(several, indent=1)


def test_prange_loops_start_at_zero_explicitly():
    # numba types the index of prange(n) as uint64 in the parallel body and as int64 where it
    # types the loop sequentially: a kernel called with the index then compiles twice (the
    # tracer's row kernel: minutes on a cold cache). prange(0, n) is int64 in both.
    import re

    root = Path(pmdsim.__file__).parent
    bad = [f"{p.relative_to(root)}:{i}: {line.strip()}" for p in sorted(root.rglob("*.py"))
           for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
           if re.search(r"\bprange\((?!0, )", line)]
    assert not bad, "use numba.prange(0, n):\n" + "\n".join(bad)


def test_prange_from_zero_compiles_a_called_kernel_once():
    # The rule above, shown on numba itself: the same callee, called with the loop index.
    import numba
    import numpy as np

    def callee(i, a):
        a[i] = i

    one_arg, two_args = numba.njit(callee), numba.njit(callee)

    @numba.njit(parallel=True)
    def loop_n(a):
        for i in numba.prange(a.shape[0]):
            one_arg(i, a)

    @numba.njit(parallel=True)
    def loop_0_n(a):
        for i in numba.prange(0, a.shape[0]):
            two_args(i, a)

    a, b = np.zeros(5), np.zeros(5)
    loop_n(a)
    loop_0_n(b)
    assert np.array_equal(a, np.arange(5.0)) and np.array_equal(b, a)
    assert len(two_args.signatures) == 1
    assert len(one_arg.signatures) == 2  # int64 and uint64: why the rule exists
