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
    # The main paths reach the tracer, the decoder, both integrations (the stepwise one in rows where it
    # can: stepwise_rows) and the calibration.
    for name in ("pmdsim.simulation.trace._trace_kernel", "pmdsim.geometry.camera._rays_kernel",
                 "pmdsim.simulation.patterns._render_stack_kernel", "pmdsim.evaluation.decoding_fused._fused_kernel",
                 "pmdsim.evaluation.stepwise_rows.rows_stepwise_kernel", "pmdsim.evaluation.least_squares._apply_update",
                 "pmdsim.evaluation.surface_fit_sums._block_sums", "pmdsim.calibration.kernel._chunks_kernel"):
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


def test_readonly_is_a_view_that_leaves_the_array_writable():
    import numpy as np

    from pmdsim.geometry.kernel_args import readonly

    a = np.arange(6.0).reshape(2, 3)
    v = readonly(a)
    assert np.shares_memory(a, v) and v.shape == a.shape and v.dtype == a.dtype and v.flags.c_contiguous
    assert not v.flags.writeable and a.flags.writeable
    assert readonly(v) is v


def _argument_types(monkeypatch, module, kernel_name):
    """Replace ``module.<kernel_name>`` by a recorder of the numba types of its arguments
    (``numba.typeof``: what the dispatcher compiles a signature for); nothing is compiled or run."""
    import numba

    seen = []
    monkeypatch.setattr(module, kernel_name, lambda *args: seen.append(tuple(numba.typeof(a) for a in args)))
    return seen


def test_writable_and_read_only_inputs_reach_one_compiled_kernel(monkeypatch, small_toml):
    # A plane's zero coefficients, rays built by hand, images read from disk are writable; a
    # spline's coefficients, a camera's cached rays, pmdsim.simulate's images are read-only.
    # numba types the two differently: each mix compiled the tracer again (five times in the
    # test suite, minutes each on a cold cache). The wrappers hand the kernels read-only views,
    # so that every mix is typed like the main path (one signature).
    import tomllib

    import numpy as np

    import pmdsim
    from pmdsim.evaluation import consistency, decoding, decoding_fused
    from pmdsim.evaluation.phase import wrapped_phase
    from pmdsim.geometry.shapes import QuadricSurface
    from pmdsim.geometry.surface import PlaneSurface, SplineSurface
    from pmdsim.geometry.transform import RigidTransform
    from pmdsim.simulation import trace
    from pmdsim.simulation.render import trace_setup_camera

    traced = _argument_types(monkeypatch, trace, "_trace_kernel")
    setup = pmdsim.parse_setup(tomllib.loads(small_toml))
    trace_setup_camera(setup, "left")  # the main path
    trace_setup_camera(setup.with_sample_shape("sphere", radius_mm=1000.0), "left", store_points=True)
    T_screen_sample = RigidTransform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, -500.0]).inv()
    d = np.array([[0.01, 0.02, 1.0], [-0.02, 0.01, 1.0]])
    g = np.linspace(-300.0, 300.0, 5)
    z = np.zeros((5, 5))
    z[2, 2] = 1.0
    samples = (PlaneSurface((-300.0, 300.0), (-300.0, 300.0)), QuadricSurface.sphere(g, g, 1000.0, (0.0, 0.0)),
               SplineSurface(g, g, z))
    screens = (PlaneSurface((-1e5, 1e5), (-1e5, 1e5)), SplineSurface(g * 400.0, g * 400.0, z))
    for rays in (d, _readonly_copy(d)):
        for ok in (np.ones(2, bool), _readonly_copy(np.ones(2, bool))):
            for sample in samples:
                for screen in screens:
                    trace.trace_rays(rays, ok, RigidTransform(np.eye(3), [0.0, 0.0, -100.0]), T_screen_sample,
                                     sample, screen, store_points=True)
    assert len(traced) == 2 + 2 * 2 * len(samples) * len(screens)
    assert len(set(traced)) == 1, sorted(set(map(str, traced)))

    decoded = _argument_types(monkeypatch, decoding, "_decode_kernel")
    stacked = _argument_types(monkeypatch, consistency, "_stack_kernel")
    img = (np.arange(4 * 3 * 5) % 7 * 30).astype(np.uint8).reshape(4, 3, 5)
    for images in (img, _readonly_copy(img)):
        wrapped_phase(images)
        consistency._stack_stats(images)
    assert len(decoded) == 2 and decoded[0] == decoded[1] and not decoded[0][0].mutable, decoded
    # the checks' stack kernel takes a read-only (N, H, W) array (no typed list), as the fused decoder
    assert len(stacked) == 2 and stacked[0] == stacked[1] and not stacked[0][0].mutable, stacked
    # decode_screen_coordinates (the fused kernel): per-image lists and stacks, writable or not
    fused = _argument_types(monkeypatch, decoding_fused, "_fused_kernel")
    for images in (img, _readonly_copy(img), list(img), [_readonly_copy(im) for im in img]):
        decoding.decode_screen_coordinates([images], [10.0], [images], [10.0], (10.0, 10.0), 255)
    assert len(fused) == 4 and len(set(fused)) == 1 and not fused[0][0].mutable, fused


def _readonly_copy(a):
    b = a.copy()
    b.flags.writeable = False
    return b
