"""Where the tracer's time goes, by compiled function: ``perf record`` with numba's JIT symbols.

    NUMBA_NUM_THREADS=1 python benchmarks/profile_trace_perf.py [--bulge-mm 3] [--glass-mm 3] [--traces 15]
        [--out perf.data] [--dump-code DIR] [--cached]

perf cannot name numba's JIT code (no symbol table), so this script compiles the tracer in the
process (numba's cache loading switched off: a library loaded from the cache has no LLVM module
to list), writes ``/tmp/perf-PID.map`` (perf's map of JIT symbols: address, size, name of every
function of the compiled library and the libraries it links) and runs ``perf record -e cpu-clock
-F 2000 -p PID`` over ``--traces`` traces of Table 1's left camera (1920 × 1200 px). It prints
``perf report``'s functions with their share and the time per trace. ``--dump-code DIR`` also
writes the machine code of the tracer's row and glass kernels (``DIR/NAME_ADDRESS.bin``), to be
disassembled with ``objdump -D -b binary -mi386:x86-64 --adjust-vma=0xADDRESS`` and matched
against ``perf script -F ip,sym``. The compile takes 1–2 min (not timed). ``--cached`` loads the
kernels from numba's cache instead (seconds): the JIT functions are then unnamed addresses, the
kernel's and libraries' symbols (page clearing, ``clear_page_erms``) are not — to compare those
between the traces with and without glass.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import subprocess
import sys
import time

import numba.core.caching as _caching

_DUMPED = ("glass_block", "_foot_run", "skip_check_run", "trace_row", "_patches_at", "_glass_rows_update", "_newton_run")


def _symbols(dispatcher) -> dict[int, str]:
    """Address → name of every defined function of the dispatcher's compiled libraries."""
    syms = {}
    for cres in dispatcher.overloads.values():
        seen, stack = set(), [cres.library]
        while stack:
            lib = stack.pop()
            if id(lib) in seen:
                continue
            seen.add(id(lib))
            stack.extend(getattr(lib, "_linking_libraries", []))
            try:
                functions = list(lib._final_module.functions)
            except Exception:  # a library without its LLVM module (loaded from a cache)
                continue
            for f in functions:
                if not f.is_declaration:
                    address = lib._codegen._engine.get_function_address(f.name)
                    if address:
                        syms[address] = f.name
    return syms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bulge-mm", type=float, default=3.0)
    ap.add_argument("--glass-mm", type=float, default=3.0, help="cover glass thickness (n = 1.52); 0: none")
    ap.add_argument("--traces", type=int, default=15)
    ap.add_argument("--out", default="perf.data")
    ap.add_argument("--dump-code", default="")
    ap.add_argument("--cached", action="store_true", help="kernels from numba's cache (JIT code unnamed)")
    args = ap.parse_args()
    if not args.cached:  # compile in this process (see the docstring); nothing is written to the cache either
        _caching.Cache.load_overload = lambda *args, **kwargs: None
        _caching.Cache.save_overload = lambda *args, **kwargs: None
    from pmdsim.geometry.cover_glass import CoverGlass
    from pmdsim.setup import default_setup
    from pmdsim.simulation import trace

    setup = default_setup().with_bulge(args.bulge_mm)
    cam = setup.cameras["left"]
    rays = cam.camera.sensor_rays()
    glass = CoverGlass(args.glass_mm, 1.52) if args.glass_mm > 0 else None

    def run():
        return trace.trace_camera(cam.camera, cam.T_world_cam, setup.sample.T_world_sample, setup.sample.surface,
                                  setup.screen.T_world_screen, setup.screen.surface, rays=rays, glass=glass)

    run()  # compile (or load from the cache)
    run()  # the process's first touch of the allocator's memory, outside the profile
    syms = _symbols(trace._trace_kernel_glass if glass is not None else trace._trace_kernel)
    addresses = sorted(syms)
    ends = addresses[1:] + [addresses[-1] + 0x10000] if addresses else []
    with open(f"/tmp/perf-{os.getpid()}.map", "w") as fh:
        for a, e in zip(addresses, ends):
            fh.write(f"{a:x} {min(e - a, 0x100000):x} {syms[a]}\n")
    if args.dump_code:
        os.makedirs(args.dump_code, exist_ok=True)
        for a, e in zip(addresses, ends):
            name = syms[a]
            # (mangled names hold each part as <length><text>: "9trace_rowB…", not "10trace_rows…")
            key = next((k for k in _DUMPED if f"{len(k)}{k}B" in name), None)
            if key and name.startswith("_ZN6pmdsim"):  # the function itself, not its C wrappers
                with open(os.path.join(args.dump_code, f"{key}_{a:x}.bin"), "wb") as fh:
                    fh.write(ctypes.string_at(a, min(e - a, 0x40000)))
    perf = subprocess.Popen(["perf", "record", "-q", "-F", "2000", "-e", "cpu-clock", "-o", args.out,
                             "-p", str(os.getpid())])
    time.sleep(1.0)  # perf attached
    t0 = time.perf_counter()
    for _ in range(args.traces):
        run()
    wall = time.perf_counter() - t0
    perf.send_signal(2)
    perf.wait()
    report = subprocess.run(["perf", "report", "-i", args.out, "--no-children", "--sort", "sym", "--stdio"],
                            capture_output=True, text=True).stdout
    per_trace_ms = 1e3 * wall / args.traces
    print(f"{args.traces} traces, {per_trace_ms:.1f} ms wall each (perf attached), load {os.getloadavg()[0]:.1f}")
    for line in report.splitlines():
        if line.strip() and not line.startswith("#") and "%" in line:
            share = float(line.split("%")[0])
            if share >= 0.5:
                name = line.split("]")[-1].strip()
                print(f"  {share:5.1f} %  {share * per_trace_ms / 100:6.1f} ms  {name[:110]}")


if __name__ == "__main__":
    sys.exit(main())
