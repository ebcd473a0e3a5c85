"""Try pmdsim's outputs, interrupts and environment as a user (and a hostile tester) would.

Every case runs ``python -m pmdsim.cli`` in a fresh interpreter (real exit codes, signals,
files) and is classified:

* **refused** — an action that would lose data (replace a user's directory, an input of the
  command, a running run's output) is refused: one ``pmdsim: error:`` line naming the path,
  exit 2, nothing touched;
* **clear** — a bad output path gets one ``pmdsim: error:`` line naming it (exit 2), or an
  interrupted run ends with its signal's exit code (130 / 143), a one-line message and no
  output; a run killed with SIGKILL leaves a partial that the next run removes with a note;
* **ok** — the environment case works (with a one-line note where it says so);
* **BAD** — anything else (a traceback, exit 0 with a partial, a destroyed file, a leftover).

Usage (about 3–4 minutes on 2 loaded cores)::

    PYTHONPATH=src nice python benchmarks/reliability_outputs.py [--trials N] [--seed S] [--only issue24]

Prints one line per case and the counts per category (docs/reliability.md).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

PY = sys.executable


def _foreground():
    """As an interactive shell starts a foreground job: SIGINT and SIGTERM at their defaults (a
    background job of a script inherits SIGINT ignored, and pmdsim keeps an ignored signal
    ignored, as Python does)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
ROOT = Path(__file__).resolve().parents[1]


def pmdsim(*args, umask=None, cwd=None, env=None):
    pre = (lambda: os.umask(umask)) if umask is not None else None
    return subprocess.run([PY, "-m", "pmdsim.cli", *map(str, args)], capture_output=True, text=True, timeout=600,
                          preexec_fn=pre, cwd=cwd, env=env)


def one_line_error(r) -> bool:
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("pmdsim: error:")]
    return len(lines) == 1 and "Traceback" not in r.stderr


def snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def hidden(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith("."))


def setup_text(factor: int) -> str:
    sys.path.insert(0, str(ROOT / "src"))
    from pmdsim.setup import default_setup

    t = default_setup().to_toml()
    w, h, f, cx, cy = 1920 // factor, 1200 // factor, 4400 / factor, 960 / factor, 600 / factor
    t = t.replace("image_size_px = [1920, 1200]", f"image_size_px = [{w}, {h}]")
    t = t.replace("focal_length_px = [4400.0, 4400.0]", f"focal_length_px = [{f}, {f}]")
    return t.replace("principal_point_px = [960.0, 600.0]", f"principal_point_px = [{cx}, {cy}]")


class Cases:
    def __init__(self):
        self.rows = []

    def add(self, category, case, outcome, detail=""):
        self.rows.append((category, case, outcome, detail))
        print(f"[{category}] {case}: {outcome}  {detail}"[:300], flush=True)


def complete(out: Path) -> bool:
    try:
        m = json.loads((out / "manifest.json").read_text())
        marker = json.loads((out / ".pmdsim-output.json").read_text())
    except (OSError, ValueError):
        return False
    return marker.get("format") == "pmdsim-output" and all((out / e["file"]).is_file() for e in m["images"])


def output_cases(c: Cases, w: Path, small: Path) -> None:
    cat = "output paths"
    run = w / "run"
    assert pmdsim("simulate", "--setup", small, "--out", run, "--quiet").returncode == 0

    def refused(case, args, keep: Path, expect: str):
        before = snapshot(keep) if keep.is_dir() else keep.read_bytes()
        r = pmdsim(*args)
        after = snapshot(keep) if keep.is_dir() else keep.read_bytes()
        good = r.returncode == 2 and one_line_error(r) and expect in r.stderr and after == before
        c.add(cat, case, "refused" if good else "BAD", r.stderr.strip().splitlines()[-1] if r.stderr else "")

    user = w / "thesis"
    user.mkdir()
    (user / "thesis.tex").write_text("\\documentclass{article}\n")
    refused("simulate --out USERDIR --force (no marker)", ["simulate", "--setup", small, "--out", user, "--force",
                                                           "--quiet"], user, str(user))
    refused("evaluate run --out run --force", ["evaluate", run, "--setup", small, "--out", run, "--force", "--quiet"],
            run, "input")
    shutil.copy(small, run / "s.toml")
    refused("simulate --setup run/s.toml --out run --force", ["simulate", "--setup", run / "s.toml", "--out", run,
                                                              "--force", "--quiet"], run, "input")
    (run / "s.toml").unlink()
    s2 = w / "s2.toml"
    shutil.copy(small, s2)
    sys.path.insert(0, str(ROOT / "src"))
    from pmdsim.setup import load_setup

    su = load_setup(small)
    n_poses = len(su.calibration.mirror_poses(su.sample))
    dirs = [w / f"pose{k}" for k in range(n_poses)]
    refused("calibrate … --setup s.toml --out s.toml --force", ["calibrate", *dirs, "--setup", s2, "--out", s2,
                                                                "--force", "--quiet"], s2, "input")
    refused("evaluate run --out run (no --force)", ["evaluate", run, "--setup", small, "--out", run, "--quiet"], run,
            "input")
    refused("simulate --out run (exists, no --force)", ["simulate", "--setup", small, "--out", run, "--quiet"], run,
            "exists")
    # --force on a pmdsim output: replaced (not a refusal: the intended use)
    r = pmdsim("simulate", "--setup", small, "--bulge-mm", "1", "--out", run, "--force", "--quiet")
    c.add(cat, "simulate --out PMDSIM_OUTPUT --force", "ok" if r.returncode == 0 and complete(run) and
          hidden(w) == [] else "BAD")

    def clear(case, args, expect):
        r = pmdsim(*args)
        good = r.returncode == 2 and one_line_error(r) and all(e in r.stderr for e in expect)
        c.add(cat, case, "clear" if good else "BAD", r.stderr.strip().splitlines()[-1] if r.stderr else "")

    f = w / "afile"
    f.write_text("x\n")
    clear("simulate --out FILE/sub", ["simulate", "--setup", small, "--out", f / "sub", "--quiet"], [str(f)])
    clear("calibrate --out FILE/cal.toml (before computing)", ["calibrate", *dirs, "--setup", small, "--out",
                                                               f / "cal.toml", "--quiet"], [str(f), "not a directory"])
    clear("simulate --out .", ["simulate", "--setup", small, "--out", ".", "--quiet"], ["current directory"])
    clear("evaluate --out .. ", ["evaluate", run, "--setup", small, "--out", "..", "--quiet"], ["current directory"])
    if os.geteuid() == 0 and shutil.which("unshare"):
        ro = w / "ro"
        ro.mkdir()
        for cmd in (["simulate", "--setup", small, "--out", f"{ro}/out", "--quiet"],
                    ["calibrate", *dirs, "--setup", small, "--out", f"{ro}/cal.toml", "--quiet"],
                    ["experiment", "1", "--downsample", "16", "--out", f"{ro}/e1", "--quiet"],
                    ["simulate", "--setup", small, "--out", f"{ro}/a/b/out", "--quiet"]):
            script = f"mount -t tmpfs -o ro,size=1m tmpfs {ro} && exec {PY} -m pmdsim.cli " + " ".join(map(str, cmd))
            r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=600)
            good = r.returncode == 2 and one_line_error(r) and "read-only file system" in r.stderr
            c.add(cat, f"{cmd[0]} --out on a read-only file system ({Path(cmd[-2]).name})", "clear" if good else "BAD",
                  r.stderr.strip().splitlines()[-1] if r.stderr else "")


def lock_cases(c: Cases, w: Path, small: Path, mid: Path) -> None:
    cat = "concurrent runs, stale partials"
    sys.path.insert(0, str(ROOT / "src"))
    from pmdsim.io.outputs import output_lock

    out = w / "busy"
    with output_lock(out, command="the first run"):
        r = pmdsim("simulate", "--setup", small, "--out", out, "--quiet")
    good = r.returncode == 2 and one_line_error(r) and f"pid {os.getpid()}" in r.stderr and not out.exists()
    c.add(cat, "second run while the output's lock is held", "refused" if good else "BAD", r.stderr.strip()[-160:])
    # two real runs started together: exactly one writes, the other is refused (or finds it done)
    out = w / "race"
    ps = [subprocess.Popen([PY, "-m", "pmdsim.cli", "simulate", "--setup", str(mid), "--out", str(out), "--quiet"],
                           stderr=subprocess.PIPE, text=True, preexec_fn=_foreground) for _ in range(2)]
    errs = [p.communicate()[1] for p in ps]
    codes = sorted(p.returncode for p in ps)
    good = codes == [0, 2] and complete(out) and hidden(w) == [] and any(
        "being written by another pmdsim run" in e or "exists" in e for e in errs)
    c.add(cat, "two runs started at once on one --out", "refused" if good else "BAD", f"exit codes {codes}")
    # SIGKILL in the write phase, then the next run
    for k in (1, 20):
        out = w / f"killed{k}"
        p = subprocess.Popen([PY, "-m", "pmdsim.cli", "simulate", "--setup", str(mid), "--out", str(out), "--quiet"],
                             stderr=subprocess.PIPE, text=True, preexec_fn=_foreground)
        t0 = time.time()
        while p.poll() is None and time.time() - t0 < 120:
            if sum(len(list(d.glob("*.png"))) for d in w.glob(f".{out.name}.partial-*")) >= k:
                break
            time.sleep(0.005)
        p.kill()
        p.communicate()
        left = [n for n in hidden(w) if n.startswith(f".{out.name}.")]
        r = pmdsim("simulate", "--setup", small, "--out", out, "--quiet")
        good = (p.returncode == -9 and left and r.returncode == 0 and "removed" in r.stderr and complete(out)
                and not [n for n in hidden(w) if n.startswith(f".{out.name}.")])
        c.add(cat, f"SIGKILL after {k} image(s), then the next run", "clear" if good else "BAD",
              f"left {left}; next run: {r.stderr.strip().splitlines()[0] if r.stderr else ''}")


def _caught(pid: int) -> bool:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    except OSError:
        return False
    return False


def signal_cases(c: Cases, w: Path, mid: Path, trials: int, rng: random.Random) -> None:
    cat = "interrupts"
    outcomes = Counter()
    for i in range(trials):
        sig = rng.choice([signal.SIGINT, signal.SIGTERM])
        phase = rng.choice(["compute", "write", "write", "commit"])
        cmd = "simulate"
        d = w / f"sig{i}"
        d.mkdir()
        out = d / "run"
        p = subprocess.Popen([PY, "-m", "pmdsim.cli", "simulate", "--setup", str(mid), "--out", str(out), "--quiet"],
                             stderr=subprocess.PIPE, text=True, preexec_fn=_foreground)
        t0 = time.time()
        while p.poll() is None and not _caught(p.pid) and time.time() - t0 < 60:
            time.sleep(0.002)
        if phase == "compute":
            time.sleep(rng.uniform(0, 0.6))
        else:
            k = rng.randint(1, 47)
            while p.poll() is None and time.time() - t0 < 120:
                parts = list(d.glob(".run.partial-*"))
                n = sum(len(list(q.glob("*.png"))) for q in parts)
                if (phase == "write" and n >= k) or (phase == "commit" and any((q / "mapping.h5").exists()
                                                                               for q in parts)):
                    break
                time.sleep(0.001)
        if p.poll() is None:
            p.send_signal(sig)
        err = p.communicate()[1]
        name = signal.Signals(sig).name
        noise = "Traceback" in err or "Exception ignored" in err
        if p.returncode == 128 + sig and not out.exists() and hidden(d) == [] and not noise:
            res = "clear"
            outcomes[(phase, name, "aborted")] += 1
        elif p.returncode == 0 and complete(out) and hidden(d) == [] and not noise:
            res = "ok"  # the signal came after the commit: complete output, exit 0
            outcomes[(phase, name, "completed")] += 1
        else:
            res = "BAD"
        c.add(cat, f"{cmd}: {name} in the {phase} phase", res, f"exit {p.returncode}")
    # evaluate and experiment: SIGTERM during the run
    run = w / "evalinput"
    assert pmdsim("simulate", "--setup", mid, "--out", run, "--quiet").returncode == 0
    for args, label in ((["evaluate", run, "--setup", mid, "--out", w / "ev", "--quiet"], "evaluate"),
                        (["experiment", "1", "--downsample", "8", "--bulges-mm", "0,3", "--out", w / "e1", "--quiet"],
                         "experiment 1")):
        for sig in (signal.SIGINT, signal.SIGTERM):
            out = Path(args[args.index("--out") + 1])
            p = subprocess.Popen([PY, "-m", "pmdsim.cli", *map(str, args)], stderr=subprocess.PIPE, text=True,
                                 preexec_fn=_foreground)
            t0 = time.time()
            while p.poll() is None and not _caught(p.pid) and time.time() - t0 < 60:
                time.sleep(0.002)
            time.sleep(rng.uniform(0.5, 2.0))
            if p.poll() is None:
                p.send_signal(sig)
            err = p.communicate()[1]
            left = [n for n in hidden(w) if n.startswith(f".{out.name}.")]
            ok = ("Traceback" not in err and not left and
                  ((p.returncode == 128 + sig and not out.exists()) or (p.returncode == 0 and out.exists())))
            c.add(cat, f"{label}: {signal.Signals(sig).name} during the run",
                  ("clear" if p.returncode == 128 + sig else "ok") if ok else "BAD", f"exit {p.returncode}")
            shutil.rmtree(out, ignore_errors=True)
    print("signal outcomes:", dict(outcomes))


def environment_cases(c: Cases, w: Path, small: Path) -> None:
    cat = "environment"
    base = Path(tempfile.mkdtemp(prefix="pmdsim-env-"))
    os.chmod(base, 0o755)
    try:
        out = base / "run"
        r = pmdsim("simulate", "--setup", small, "--out", out, "--quiet", umask=0o022)
        modes = {stat.S_IMODE(p.stat().st_mode) for p in [out, *out.rglob("*")]}
        good = r.returncode == 0 and modes == {0o755, 0o644}
        if good and os.geteuid() == 0 and shutil.which("setpriv"):
            rr = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "cat",
                                 str(out / "manifest.json")], capture_output=True)
            good = rr.returncode == 0
        c.add(cat, "outputs under umask 022 readable by another user", "ok" if good else "BAD", str(sorted(map(oct,
                                                                                                         modes))))
    finally:
        shutil.rmtree(base, ignore_errors=True)
    for args in (["--version"], ["--help"], ["simulate", "--help"]):
        probe = ("import runpy,sys\nsys.argv=['pmdsim',*sys.argv[1:]]\ntry:\n runpy.run_module('pmdsim.cli',"
                 "run_name='__main__')\nexcept SystemExit:\n pass\nprint('NUMBA' if 'numba' in sys.modules else "
                 "'clean',file=sys.stderr)")
        r = subprocess.run([PY, "-c", probe, *args], capture_output=True, text=True)
        c.add(cat, f"pmdsim {' '.join(args)} imports no numba", "ok" if r.stderr.strip().endswith("clean") else "BAD")
    if os.geteuid() == 0 and shutil.which("unshare"):
        src = ROOT / "src"
        for label, extra in (("read-only install and home", ""),
                             ("read-only install, home and temporary directories",
                              "for d in /tmp /var/tmp /dev/shm; do mount -t tmpfs -o ro,size=1m tmpfs $d; done")):
            home = w / "rohome"
            home.mkdir(exist_ok=True)
            script = (f"set -e; mount --bind {src} {src}; mount -o remount,bind,ro {src}; "
                      f"mount -t tmpfs -o ro,size=1m tmpfs {home}; {extra}\n cd {src}; export HOME={home}; "
                      f"unset XDG_CACHE_HOME NUMBA_CACHE_DIR; {PY} -m pmdsim.cli --version; "
                      f"{PY} -c 'from pmdsim.geometry import camera'")
            r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True,
                               env={**os.environ, "PYTHONPATH": str(src)})
            good = r.returncode == 0 and "pmdsim: note:" in r.stderr and "Traceback" not in r.stderr
            c.add(cat, f"{label}: --version and kernel import", "ok" if good else "BAD",
                  r.stderr.strip().splitlines()[0] if r.stderr else "")


# ============================================================================ issue 24: the paths added since
SOFAST = ROOT / "tests" / "data" / "sofast"


def _sofast_files(w: Path, edit_measurement=None, edit_orientation=None, edit_calibration=None, edit_camera=None):
    """The SOFAST fixture's files, with one of them edited in a copy (h5py)."""
    import h5py

    f = {"measurement": SOFAST / "measurement_facet.h5", "camera": SOFAST / "camera_sofast_downsampled.h5",
         "display": SOFAST / "display_distorted_2d.h5", "orientation": SOFAST / "spatial_orientation.h5",
         "calibration": SOFAST / "image_calibration.h5", "facet": SOFAST / "Facet_NSTTF.json"}
    for key, fn in (("measurement", edit_measurement), ("orientation", edit_orientation),
                    ("calibration", edit_calibration), ("camera", edit_camera)):
        if fn is not None:
            dst = w / f[key].name
            shutil.copy(f[key], dst)
            dst.chmod(0o644)
            with h5py.File(dst, "r+") as h:
                fn(h)
            f[key] = dst
    return f


def _import(f, out):
    return pmdsim("import", "sofast", *[a for k in ("measurement", "camera", "display", "orientation", "calibration",
                                                    "facet") for a in (f"--{k}", f[k])], "--out", out)


def _put(h, name, value):
    del h[name]
    h[name] = value


def issue24_cases(c: Cases, w: Path, small: Path, mid: Path) -> None:
    """Issue 24's cases: calibrate/evaluate outputs inside inputs, stereo with a black frame,
    real SOFAST data with broken files, setups, experiment options, long paths, SIGHUP."""
    import numpy as np

    sys.path.insert(0, str(ROOT / "src"))
    from pmdsim.io.images import read_image, write_png
    from pmdsim.setup import default_setup

    def row(cat, case, good, r, ok_word="clear"):
        c.add(cat, case, ok_word if good else "BAD", r.stderr.strip().splitlines()[-1] if r.stderr.strip() else "")

    # --- item 1: no output touches an input
    cat = "issue 24: outputs vs inputs"
    for k in (0, 3):
        d = w / "calx" / f"pose{k}"
        d.mkdir(parents=True)
        (d / "left_x_p0_s0.png").write_bytes(b"\x89PNG fake")
        (d / "manifest.json").write_text("{}")
    before = snapshot(w / "calx")
    for victim in ("pose0/left_x_p0_s0.png", "pose3/manifest.json"):
        r = pmdsim("calibrate", w / "calx" / "pose0", w / "calx" / "pose3", "--out", w / "calx" / victim, "--force",
                   "--quiet")
        row(cat, f"calibrate … --out calx/{victim} --force", r.returncode == 2 and "inside an input" in r.stderr
            and snapshot(w / "calx") == before, r, "refused")
    user = w / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep\n")
    r = pmdsim("evaluate", w / "calx" / "pose0", "--out", user, "--quiet")
    row(cat, "evaluate --out USERDIR (no --force): no --force hint", r.returncode == 2 and "pass --force" not in
        r.stderr, r)

    # --- item 2: stereo runs the checks; --method refused
    cat = "issue 24: stereo"
    s12 = w / "s12.toml"
    s12.write_text(default_setup().binned(12).to_toml())
    img = w / "st"
    assert pmdsim("simulate", "--setup", s12, "--out", img, "--quiet").returncode == 0
    m = json.loads((img / "manifest.json").read_text())
    victim = next(e["file"] for e in m["images"] if e["camera"] == "left" and e["direction"] == "x")
    write_png(img / victim, np.zeros_like(read_image(img / victim)))
    for extra in ([], ["--stereo"]):
        r = pmdsim("evaluate", img, "--setup", s12, "--out", w / f"ev{len(extra)}", *extra, "--quiet")
        row(cat, f"evaluate {' '.join(extra) or '(mono)'} with one black frame", r.returncode == 1 and
            one_line_error(r) and not (w / f"ev{len(extra)}").exists(), r)
    r = pmdsim("evaluate", img, "--setup", s12, "--out", w / "evm", "--stereo", "--method", "stepwise", "--quiet")
    row(cat, "evaluate --stereo --method stepwise", r.returncode == 2 and "does not apply" in r.stderr, r)

    # --- items 2, 3: real SOFAST data with broken files
    cat = "issue 24: SOFAST import"
    g = "MeasurementSofastFringe/"

    def swap(h):
        fr = h[g + "fringe_images"][()]
        ny = 4 * h[g + "fringe_periods_y"].size
        _put(h, g + "fringe_images", np.concatenate([fr[..., ny:], fr[..., :ny]], -1))

    def rot(fn):
        def edit(h):
            r_ = h["SpatialOrientation/r_cam_screen"]
            r_[...] = fn(r_[()])
        return edit

    def cal(fn):
        def edit(h):
            d_, c_ = fn(h["ImageCalibration/display_values"][()], h["ImageCalibration/camera_values"][()])
            _put(h, "ImageCalibration/display_values", d_)
            _put(h, "ImageCalibration/camera_values", c_)
        return edit

    def bits16(h):
        for k in ("fringe_images", "mask_images"):
            _put(h, g + k, h[g + k][()].astype(np.uint16) * 257)

    def focal(h):
        K = h["Camera/intrinsic_mat"][()]
        K[0, 0] = K[1, 1] = 0.69
        _put(h, "Camera/intrinsic_mat", K)

    def dark(h):
        mi = h[g + "mask_images"][()]
        mi[..., 1] = mi[..., 0]
        _put(h, g + "mask_images", mi)

    k = 0
    for case, kw in (("rotation vector in degrees", {"edit_orientation": rot(np.degrees)}),
                     ("r_cam_screen negated", {"edit_orientation": rot(lambda v: -v)}),
                     ("16-bit fringes, 8-bit calibration", {"edit_measurement": bits16}),
                     ("calibration ×256", {"edit_calibration": cal(lambda d_, c_: (d_, c_ * 256))}),
                     ("one calibration level", {"edit_calibration": cal(lambda d_, c_: (d_[:1], c_[:1]))}),
                     ("calibration levels reversed", {"edit_calibration": cal(lambda d_, c_: (d_[::-1], c_[::-1]))}),
                     ("focal length 0.69 px", {"edit_camera": focal}),
                     ("mask without a lit pixel", {"edit_measurement": dark})):
        k += 1
        (w / f"sf{k}").mkdir()
        f = _sofast_files(w / f"sf{k}", **kw)
        r = _import(f, w / f"sf{k}" / "imp")
        row(cat, f"import: {case}", r.returncode == 2 and one_line_error(r) and
            any(str(p) in r.stderr for p in f.values() if str(p).startswith(str(w))), r)
    for case, kw in (("x/y fringe blocks swapped", {"edit_measurement": swap}), ("clean", {})):
        k += 1
        (w / f"sf{k}").mkdir()
        f = _sofast_files(w / f"sf{k}", **kw)
        assert _import(f, w / f"sf{k}" / "imp").returncode == 0
        r = pmdsim("evaluate", w / f"sf{k}" / "imp" / "images", "--setup", w / f"sf{k}" / "imp" / "setup.toml",
                   "--out", w / f"sf{k}" / "ev", "--quiet")
        good = (r.returncode == 0 and "not run" not in r.stdout + r.stderr) if case == "clean" else (
            r.returncode == 1 and "swapped x/y" in r.stderr)
        row(cat, f"evaluate: {case}", good, r, "ok" if case == "clean" else "clear")

    # --- item 4: setups and experiment options
    cat = "issue 24: setups, options"
    t = default_setup().to_toml()
    both = w / "both.toml"
    both.write_text(t.replace("bulge_mm = 0.0\n", "bulge_mm = 0.0\nheights_mm = [[0.0, 0.0, 0.0], [0.0, 2.5, 0.0], "
                                                  "[0.0, 0.0, 0.0]]\n", 1))
    r = pmdsim("setup", "--setup", both)
    row(cat, "bulge_mm = 0 with heights_mm centre 2.5", r.returncode == 2 and "disagree" in r.stderr, r)
    short = w / "short.toml"
    short.write_text(small.read_text().replace("periods_x_mm = [720.0", "periods_x_mm = [100.0", 1))
    r = pmdsim("simulate", "--setup", short, "--out", w / "sim_short", "--quiet")
    row(cat, "simulate with a coarsest period shorter than the screen", r.returncode == 2 and one_line_error(r) and
        not (w / "sim_short").exists(), r)
    for args in (["1", "--grids", "3"], ["4", "--bulges-mm", "1"], ["4", "--grids", "5"], ["5", "--effects", "ideal"],
                 ["4", "--effects", "ideal,ideal"]):
        r = pmdsim("experiment", *args, "--out", w / "e", "--downsample", "16", "--quiet")
        row(cat, f"experiment {' '.join(args)}", r.returncode == 2 and one_line_error(r), r)

    # --- items 5, 6: long paths, SIGHUP, messages
    cat = "issue 24: paths, signals, messages"
    for case, out in (("--out name of 300 bytes", w / ("a" * 300)), ("--out path of 5000 bytes",
                                                                      w / "/".join(["b" * 200] * 25))):
        r = pmdsim("simulate", "--setup", small, "--out", out, "--quiet")
        row(cat, case, r.returncode == 2 and one_line_error(r), r)
    hup = w / "hup"
    hup.mkdir()
    p = subprocess.Popen([PY, "-m", "pmdsim.cli", "simulate", "--setup", mid, "--out", hup / "o", "--quiet"],
                         stderr=subprocess.PIPE, text=True, preexec_fn=lambda: [signal.signal(s, signal.SIG_DFL) for s in
                                                                               (signal.SIGINT, signal.SIGHUP)])
    t0 = time.time()
    while time.time() - t0 < 90 and p.poll() is None and not any(
            d.is_dir() and any(d.glob("*.png")) for d in hup.glob(".o.partial-*")):
        time.sleep(0.01)
    p.send_signal(signal.SIGHUP)
    _, err = p.communicate(timeout=120)
    c.add(cat, "SIGHUP while writing", "clear" if p.returncode == 129 and list(hup.iterdir()) == [] else "BAD",
          err.strip().splitlines()[-1] if err.strip() else "")
    r = pmdsim("evaluate", img, "--setup", s12, "--out", w / "evn", "--seed-height-mm", "nan", "--quiet")
    row(cat, "--seed-height-mm nan", r.returncode == 2 and "finite, got nan" in r.stderr, r)
    sw = w / "sw"
    shutil.copytree(w / "st", sw)
    m = json.loads((sw / "manifest.json").read_text())
    for e in m["images"]:
        e["direction"] = {"x": "y", "y": "x"}[e["direction"]]
    (sw / "manifest.json").write_text(json.dumps(m))
    r = pmdsim("evaluate", sw, "--setup", s12, "--out", w / "evs", "--quiet")
    row(cat, "x/y directions swapped in the manifest", r.returncode == 2 and "look swapped" in r.stderr, r)

    # --- item 7: curved samples through the CLI
    cat = "issue 24: curved samples"
    for kind, radius in (("sphere", 1000.0), ("sphere", -300.0), ("cylinder", 500.0)):
        f = w / f"{kind}{radius:g}.toml"
        f.write_text(default_setup().binned(8).with_sample_shape(kind, radius_mm=radius).to_toml())
        d = w / f"{kind}{radius:g}"
        assert pmdsim("simulate", "--setup", f, "--out", d, "--quiet").returncode == 0
        r = pmdsim("evaluate", d, "--setup", f, "--out", w / f"ev_{kind}{radius:g}", "--quiet")
        row(cat, f"{kind} R = {radius:g} mm: no pixel masked as a fold", r.returncode == 0 and "GEOMETRY" not in
            r.stderr, r, "ok")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=12)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--only", choices=["issue24"], default=None, help="run only issue 24's cases")
    a = ap.parse_args()
    w = Path(tempfile.mkdtemp(prefix="pmdsim-reliability-"))
    small, mid = w / "small.toml", w / "mid.toml"
    small.write_text(setup_text(16))
    mid.write_text(setup_text(4))
    c = Cases()
    t0 = time.time()
    try:
        for d in "olsei":
            (w / d).mkdir()
        issue24_cases(c, w / "i", small, mid)
        if a.only is None:
            output_cases(c, w / "o", small)
            lock_cases(c, w / "l", small, mid)
            signal_cases(c, w / "s", mid, a.trials, random.Random(a.seed))
            environment_cases(c, w / "e", small)
    finally:
        shutil.rmtree(w, ignore_errors=True)
    counts = defaultdict(Counter)
    for cat, _, outcome, _ in c.rows:
        counts[cat][outcome] += 1
    print(f"\n{len(c.rows)} cases in {time.time() - t0:.0f} s")
    for cat, n in counts.items():
        print(f"  {cat}: " + ", ".join(f"{k} {v}" for k, v in sorted(n.items())))


if __name__ == "__main__":
    main()
