"""Reliability of outputs, interrupts and the environment (issue 11; docs/reliability.md).

Every case is reproduced the way a user meets it: the command line (in a fresh interpreter
where exit codes, signals, file modes or mounts matter), real files and directories, real
signals sent to a running ``python -m pmdsim.cli`` (not a patched exception: a patch does not
reproduce the race), a real read-only file system (a private mount namespace, when the test
runs as root), another user reading the outputs. Truths: the bytes of files the command must
not touch, the manifest's own list of images, ``os.stat`` modes against the umask, tomllib.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.io.outputs import MARKER_NAME, atomic_file, output_lock

# ----------------------------------------------------------------------------- helpers
SRC = Path(__file__).resolve().parents[1] / "src"


def cli(*args: str):
    return CliRunner().invoke(main, list(args))


def run_subprocess(*args: str, umask: int | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    pre = (lambda: os.umask(umask)) if umask is not None else None
    return subprocess.run([sys.executable, "-m", "pmdsim.cli", *args], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=pre)


def snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def hidden(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def one_error_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.startswith("pmdsim: error:")]
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


def assert_complete_image_set(out: Path) -> None:
    """Everything the manifest lists is there, and the marker names a pmdsim output."""
    manifest = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
    files = [e["file"] for e in manifest["images"]]
    assert files and all((out / f).is_file() for f in files)
    assert (out / "mapping.h5").is_file()
    marker = json.loads((out / MARKER_NAME).read_text(encoding="utf-8"))
    assert marker["format"] == "pmdsim-output" and "simulate" in marker["command"]


@pytest.fixture(scope="module")
def mid_setup_file(tmp_path_factory, default_toml):
    """The Table 1 setup with cameras binned 4× (480×300 px, same field of view), edited as
    text (focal length and principal point scaled by 1/4): a run of a few seconds."""
    t = default_toml
    for old, new in (("image_size_px = [1920, 1200]", "image_size_px = [480, 300]"),
                     ("focal_length_px = [4400.0, 4400.0]", "focal_length_px = [1100.0, 1100.0]"),
                     ("principal_point_px = [960.0, 600.0]", "principal_point_px = [240.0, 150.0]")):
        assert t.count(old) == 2
        t = t.replace(old, new)
    p = tmp_path_factory.mktemp("setup") / "mid.toml"
    p.write_text(t, encoding="utf-8")
    return p


@pytest.fixture(scope="module")
def image_set(tmp_path_factory, small_setup_file):
    """A small simulated image set (96×60 px), written by the command line."""
    out = tmp_path_factory.mktemp("sim") / "run"
    r = cli("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")
    assert r.exit_code == 0, r.output
    return out


# ============================================================================ --force, inputs, marker
def test_marker_records_the_command(image_set, small_setup_file):
    marker = json.loads((image_set / MARKER_NAME).read_text(encoding="utf-8"))
    assert marker["format"] == "pmdsim-output"
    assert marker["command"] == f"pmdsim simulate --setup {small_setup_file} --out {image_set} --quiet"
    import pmdsim

    assert marker["pmdsim_version"] == pmdsim.__version__


def test_force_refuses_a_user_directory(tmp_path, small_setup_file):
    """`simulate --out d --force` on a directory pmdsim did not write: refused, naming it."""
    d = tmp_path / "thesis"
    d.mkdir()
    (d / "thesis.tex").write_text("\\documentclass{article}\n", encoding="utf-8")
    before = snapshot(d)
    r = cli("simulate", "--setup", str(small_setup_file), "--out", str(d), "--force", "--quiet")
    assert r.exit_code == 2
    line = one_error_line(r.output)
    assert str(d) in line and MARKER_NAME in line
    assert snapshot(d) == before and hidden(tmp_path) == []


def test_force_refuses_a_regular_file_as_output_directory(tmp_path, small_setup_file):
    f = tmp_path / "notes.txt"
    f.write_text("keep me\n", encoding="utf-8")
    r = cli("simulate", "--setup", str(small_setup_file), "--out", str(f), "--force", "--quiet")
    assert r.exit_code == 2 and str(f) in r.output and "Traceback" not in r.output  # click's check of --out
    assert f.read_text(encoding="utf-8") == "keep me\n"
    from pmdsim.errors import OutputExistsError
    from pmdsim.io.outputs import atomic_output_dir

    with pytest.raises(OutputExistsError, match="not a directory"):  # the library's own check
        with atomic_output_dir(f, force=True):
            pass
    assert f.read_text(encoding="utf-8") == "keep me\n"


def test_force_replaces_a_pmdsim_output(tmp_path, image_set, small_setup_file):
    out = tmp_path / "run"
    shutil.copytree(image_set, out)
    (out / "stale.txt").write_text("from an older run\n", encoding="utf-8")
    r = cli("simulate", "--setup", str(small_setup_file), "--bulge-mm", "1", "--out", str(out), "--force", "--quiet")
    assert r.exit_code == 0, r.output
    assert not (out / "stale.txt").exists()  # replaced as a whole
    assert_complete_image_set(out)
    assert tomllib.loads(json.loads((out / "manifest.json").read_text())["setup_toml"])["screen"]["bulge_mm"] == 1.0
    assert hidden(tmp_path) == []


def test_evaluate_refuses_to_replace_its_input(tmp_path, image_set, small_setup_file):
    """`pmdsim evaluate run --out run --force` would destroy the image set: refused."""
    run = tmp_path / "run"
    shutil.copytree(image_set, run)
    before = snapshot(run)
    r = cli("evaluate", str(run), "--setup", str(small_setup_file), "--out", str(run), "--force", "--quiet")
    assert r.exit_code == 2
    line = one_error_line(r.output)
    assert "input" in line and str(run) in line
    assert snapshot(run) == before


def test_simulate_refuses_a_directory_holding_its_setup(tmp_path, image_set, small_setup_file):
    run = tmp_path / "run"
    shutil.copytree(image_set, run)
    shutil.copy(small_setup_file, run / "setup.toml")
    before = snapshot(run)
    r = cli("simulate", "--setup", str(run / "setup.toml"), "--out", str(run), "--force", "--quiet")
    assert r.exit_code == 2 and "setup.toml" in one_error_line(r.output)
    assert snapshot(run) == before


def test_calibrate_refuses_its_setup_as_output_before_computing(tmp_path, small_setup_file):
    """`calibrate … --setup s.toml --out s.toml --force`: refused before any image set is read
    (the image directories do not even exist: had it read them first, the error would name them)."""
    setup = tmp_path / "s.toml"
    shutil.copy(small_setup_file, setup)
    before = setup.read_bytes()
    n_poses = len(tomllib.loads(before.decode())["calibration"].get("lift_mm", [])) + 1 + 4 * len(
        tomllib.loads(before.decode())["calibration"].get("tilt_deg", []))
    dirs = [str(tmp_path / f"pose{k}") for k in range(n_poses)]
    r = cli("calibrate", *dirs, "--setup", str(setup), "--out", str(setup), "--force", "--quiet")
    line = one_error_line(r.output)
    assert r.exit_code == 2 and "input" in line and str(setup) in line, r.output
    assert setup.read_bytes() == before


def test_calibrate_output_under_a_file_fails_before_computing(tmp_path, small_setup_file):
    blocker = tmp_path / "results"
    blocker.write_text("a file, not a directory\n", encoding="utf-8")
    doc = tomllib.loads(small_setup_file.read_text())
    n_poses = 1 + len(doc["calibration"].get("lift_mm", [])) + 4 * len(doc["calibration"].get("tilt_deg", []))
    dirs = [str(tmp_path / f"pose{k}") for k in range(n_poses)]  # absent: reading them would fail first
    r = cli("calibrate", *dirs, "--setup", str(small_setup_file), "--out", str(blocker / "cal.toml"), "--quiet")
    line = one_error_line(r.output)
    assert r.exit_code == 2 and str(blocker) in line and "not a directory" in line, r.output


def _unshare_available() -> bool:
    return os.geteuid() == 0 and shutil.which("unshare") is not None and subprocess.run(
        ["unshare", "-m", "true"], capture_output=True).returncode == 0


needs_mount_ns = pytest.mark.skipif(not _unshare_available(), reason="needs root and unshare -m (private mounts)")


@needs_mount_ns
def test_output_on_a_read_only_file_system(tmp_path, small_setup_file):
    """A real read-only mount (private to the subprocess): one line naming the directory, exit 2."""
    ro = tmp_path / "ro"
    ro.mkdir()
    script = (f"mount -t tmpfs -o ro,size=1m tmpfs {ro} && exec {sys.executable} -m pmdsim.cli simulate "
              f"--setup {small_setup_file} --out {ro}/out --quiet")
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    line = one_error_line(r.stderr)
    assert "read-only file system" in line and str(ro) in line


# ============================================================================ lock, stale partials
def test_concurrent_run_is_refused_and_named(tmp_path, small_setup_file):
    """While another run holds the output's lock (taken here with the function every run uses),
    a second run is refused naming the holder's pid and its partial output, which it leaves alone."""
    out = tmp_path / "run"
    partial = tmp_path / ".run.partial-other"
    partial.mkdir()
    (partial / "left_x_p0_s0.png").write_bytes(b"being written")
    with output_lock(out, command="pmdsim simulate --out run (the first run)"):
        r = run_subprocess("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")
        assert (tmp_path / ".run.lock").exists()
    assert r.returncode == 2, r.stderr
    line = one_error_line(r.stderr)
    assert f"pid {os.getpid()}" in line and "the first run" in line and partial.name in line
    assert partial.is_dir() and not out.exists()  # the running run's partial is not touched
    # The holder is gone: its partial is stale now, the next run removes it and says so.
    r = cli("simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet")
    assert r.exit_code == 0, r.output
    assert "removed" in r.output and partial.name in r.output
    assert_complete_image_set(out)
    assert hidden(tmp_path) == []


def _wait_for(pred, timeout: float = 90.0, poll: float = 0.005) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return True
        time.sleep(poll)
    return False


def _pngs_in_partial(parent: Path, name: str) -> int:
    n = 0
    for d in parent.glob(f".{name}.partial-*"):
        try:
            n = max(n, sum(1 for p in d.iterdir() if p.suffix == ".png"))
        except FileNotFoundError:
            pass
    return n


def test_sigkill_leaves_a_partial_that_the_next_run_removes(tmp_path, mid_setup_file):
    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "pmdsim.cli", "simulate", "--setup", str(mid_setup_file), "--out",
                          str(out), "--quiet"], stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: _pngs_in_partial(tmp_path, "run") >= 3 or p.poll() is not None)
        p.kill()
    finally:
        p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL
    left = hidden(tmp_path)
    assert any(n.startswith(".run.partial-") for n in left) and not out.exists()  # what SIGKILL leaves
    r = cli("simulate", "--setup", str(mid_setup_file), "--out", str(out), "--quiet")
    assert r.exit_code == 0, r.output
    assert "removed" in r.output
    assert_complete_image_set(out)
    assert hidden(tmp_path) == []


# ============================================================================ real signals
def _handlers_installed(pid: int) -> bool:
    """SIGTERM among the caught signals of ``pid`` (/proc/PID/status SigCgt): pmdsim's handler is in."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    except (FileNotFoundError, ProcessLookupError):
        return False
    return False


def _foreground() -> None:
    """In the child, as an interactive shell starts a foreground job: SIGINT and SIGTERM at their
    defaults (under a background runner SIGINT is inherited ignored, and pmdsim, like Python,
    keeps an ignored signal ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _interrupt_trial(workdir: Path, setup_file: Path, sig: int, phase: str, rng: random.Random) -> dict:
    """One run of `pmdsim simulate`, sent ``sig`` in ``phase``:
    "compute" (a random time 0–0.6 s after the handlers are in: loading, tracing, rendering),
    "write" (when the partial directory holds k random PNGs, k ≤ 30 of 48) or "commit" (when mapping.h5,
    written after all images, appears in the partial directory)."""
    workdir.mkdir()
    out = workdir / "run"
    p = subprocess.Popen([sys.executable, "-m", "pmdsim.cli", "simulate", "--setup", str(setup_file), "--out",
                          str(out), "--quiet"], stderr=subprocess.PIPE, text=True, preexec_fn=_foreground)
    try:
        assert _wait_for(lambda: _handlers_installed(p.pid) or p.poll() is not None)
        if phase == "compute":
            time.sleep(rng.uniform(0.0, 0.6))
        elif phase == "write":
            k = rng.randint(1, 30)  # of 48: the signal lands well before the last image
            _wait_for(lambda: _pngs_in_partial(workdir, "run") >= k or p.poll() is not None)
        else:
            _wait_for(lambda: any((d / "mapping.h5").exists() for d in workdir.glob(".run.partial-*"))
                      or p.poll() is not None, poll=0.001)
        if p.poll() is None:
            p.send_signal(sig)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    return {"rc": p.returncode, "err": err, "out": out, "workdir": workdir, "sig": sig, "phase": phase}


def test_real_signals_at_random_times(tmp_path, mid_setup_file):
    """SIGINT / SIGTERM sent to a running `pmdsim simulate` in every phase (seeded random times
    and image counts). Each run either ends 130 / 143 with no output and nothing hidden left,
    or — a signal that came after the commit — 0 with a complete output; never a traceback,
    never "Exception ignored", never exit 0 with a partial output. The next run on the same
    output then succeeds and leaves nothing behind."""
    rng = random.Random(20261125)
    plan = [(signal.SIGINT, "compute"), (signal.SIGTERM, "compute"), (signal.SIGINT, "write"),
            (signal.SIGTERM, "write"), (signal.SIGINT, "write"), (signal.SIGTERM, "commit")]
    results: list[dict] = []
    lock = threading.Lock()

    def trial(i, sig, phase, seed):
        r = _interrupt_trial(tmp_path / f"t{i}", mid_setup_file, sig, phase, random.Random(seed))
        with lock:
            results.append(r)

    seeds = [rng.random() for _ in plan]
    for start in (0, 3):  # three at a time: a few seconds each
        threads = [threading.Thread(target=trial, args=(i, *plan[i], seeds[i])) for i in range(start, start + 3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert len(results) == len(plan)
    outcomes = []
    for r in results:
        err, out, sig = r["err"], r["out"], r["sig"]
        assert "Traceback" not in err and "Exception ignored" not in err, err
        if r["rc"] == 128 + sig:
            assert f"pmdsim: interrupted ({signal.Signals(sig).name})" in err
            assert not out.exists(), r
            outcomes.append((r["phase"], "aborted"))
        else:
            assert r["rc"] == 0, (r["phase"], r["rc"], err)
            assert_complete_image_set(out)
            outcomes.append((r["phase"], "completed"))
        assert hidden(r["workdir"]) == [], (r["phase"], hidden(r["workdir"]))
    print("signal outcomes:", outcomes)
    # the write phase was really hit: those runs were aborted, not completed
    assert all(o == "aborted" for ph, o in outcomes if ph in ("compute", "write")), outcomes
    # the next run on each output works and leaves nothing hidden
    r0 = results[0]
    r = cli("simulate", "--setup", str(mid_setup_file), "--out", str(r0["out"]), "--quiet")
    assert r.exit_code == 0, r.output
    assert_complete_image_set(r0["out"])
    assert hidden(r0["workdir"]) == []


# ============================================================================ environment
def test_outputs_follow_the_umask(small_setup_file):
    """With umask 022 every directory is 0755 and every file 0644, and another user (nobody)
    reads them when the test runs as root; with umask 077, 0700 / 0600 and nobody cannot."""
    import tempfile

    base = Path(tempfile.mkdtemp(prefix="pmdsim-umask-"))
    try:
        os.chmod(base, 0o755)  # the test's own directory; the outputs' modes are under test
        procs = {umask: subprocess.Popen(  # both at once: the second import overlaps the first
            [sys.executable, "-m", "pmdsim.cli", "simulate", "--setup", str(small_setup_file), "--out",
             str(base / f"run{umask:03o}"), "--quiet"], stderr=subprocess.PIPE, text=True,
            preexec_fn=lambda umask=umask: os.umask(umask)) for umask in (0o022, 0o077)}
        for umask, p in procs.items():
            err = p.communicate(timeout=300)[1]
            assert p.returncode == 0, err
            out = base / f"run{umask:03o}"
            paths = [out, *out.rglob("*")]
            modes = {stat.S_IMODE(p.stat().st_mode) for p in paths if p.is_dir()}
            assert modes == {0o777 & ~umask}, (oct(umask), modes)
            modes = {stat.S_IMODE(p.stat().st_mode) for p in paths if p.is_file()}
            assert modes == {0o666 & ~umask}, (oct(umask), modes)
        setpriv = shutil.which("setpriv")
        if os.geteuid() == 0 and setpriv and stat.S_IMODE(base.parent.stat().st_mode) & 0o001:
            as_nobody = [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups"]
            for umask, readable in ((0o022, True), (0o077, False)):
                out = base / f"run{umask:03o}"
                for f in (out / "manifest.json", out / "mapping.h5", out / MARKER_NAME):
                    r = subprocess.run(as_nobody + ["cat", str(f)], capture_output=True)
                    assert (r.returncode == 0 and r.stdout == f.read_bytes()) if readable else r.returncode != 0
                r = subprocess.run(as_nobody + ["ls", str(out)], capture_output=True, text=True)
                assert (r.returncode == 0 and "manifest.json" in r.stdout) == readable
    finally:
        shutil.rmtree(base, ignore_errors=True)


def test_atomic_file_follows_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        with atomic_file(tmp_path / "cal.toml", mode="w") as f:
            f.write("a = 1\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "cal.toml").stat().st_mode) == 0o644
    assert hidden(tmp_path) == []


_IMPORT_PROBE = """
import json, runpy, sys
sys.argv = ["pmdsim", *sys.argv[1:]]
try:
    runpy.run_module("pmdsim.cli", run_name="__main__")
except SystemExit as e:
    code = e.code
print(json.dumps({"code": code, "numba": "numba" in sys.modules, "numpy": "numpy" in sys.modules,
                  "kernels": sorted(m for m in sys.modules if m.startswith(("pmdsim.geometry", "pmdsim.simulation",
                                                                           "pmdsim.evaluation")))}), file=sys.stderr)
"""


@pytest.mark.parametrize("args", [["--version"], ["--help"], ["simulate", "--help"], ["evaluate", "--help"]])
def test_version_and_help_import_no_numba(args):
    r = subprocess.run([sys.executable, "-c", _IMPORT_PROBE, *args], capture_output=True, text=True, timeout=60)
    probe = json.loads(r.stderr.strip().splitlines()[-1])
    assert probe["code"] in (0, None) and probe["numba"] is False and probe["kernels"] == [], probe
    assert ("0.1.0" in r.stdout) if args == ["--version"] else ("Usage:" in r.stdout)


def _read_only_script(tmp_path: Path, tmp_writable: bool) -> str:
    """Shell commands for a private mount namespace: the source tree remounted read-only, home
    a read-only file system; /tmp, /var/tmp and /dev/shm read-only too unless ``tmp_writable``
    (each bind-mounted onto itself read-only, so that a checkout or a virtual environment that
    lives under /tmp stays visible)."""
    lines = ["set -e", f"mount --bind {SRC} {SRC}", f"mount -o remount,bind,ro {SRC}"]
    if tmp_writable:
        home, tmpdir = tmp_path / "home", tmp_path / "tmp"
        home.mkdir()
        tmpdir.mkdir()
        lines.append(f"mount -t tmpfs -o ro,size=1m tmpfs {home}")
    else:
        home, tmpdir = Path("/tmp/home"), Path("/tmp")
        lines.append("for d in /tmp /var/tmp /dev/shm; do mount --bind $d $d; mount -o remount,bind,ro $d; done")
    lines += [f"cd {SRC}", f"export HOME={home} TMPDIR={tmpdir} PYTHONPATH={SRC}",
              "unset XDG_CACHE_HOME NUMBA_CACHE_DIR",
              f"{sys.executable} -m pmdsim.cli --version",
              f"{sys.executable} -c \"from pmdsim.geometry import camera; import numba; "
              "print('cache', numba.config.CACHE_DIR or '-')\""]
    return "\n".join(lines) + "\n"


@needs_mount_ns
@pytest.mark.parametrize("tmp_writable", [True, False])
def test_read_only_install_and_home(tmp_path, tmp_writable):
    """A read-only install (the source tree remounted read-only) and a read-only home: without
    the fallback numba fails at import ("no locator available"); with it `pmdsim --version` works
    and the kernels import — cached in the temporary directory, or (that read-only too)
    uncached — with a one-line note."""
    script = _read_only_script(tmp_path, tmp_writable)
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "pmdsim, version" in r.stdout and "Traceback" not in r.stderr
    notes = [ln for ln in r.stderr.splitlines() if ln.startswith("pmdsim: note:")]
    assert len(set(notes)) == 1, r.stderr  # one line (once per process)
    if tmp_writable:
        cache = tmp_path / "tmp" / "pmdsim-numba-cache-0"
        assert str(cache) in notes[0] and f"cache {cache}" in r.stdout
    else:
        assert "compiled at each run" in notes[0] and "cache -" in r.stdout
    # the same without the fallback: the failure it repairs
    r = subprocess.run(["unshare", "-m", "sh", "-c", "export PMDSIM_NO_CACHE_FALLBACK=1\n" + script],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "no locator available" in r.stderr


# ============================================================================ TOML with numpy values
def test_setup_with_numpy_camera_round_trips(tmp_path):
    """A camera from ``Camera.from_opencv`` (numpy float64 values) written to TOML and read back:
    every value equal (the hand-written writer produced ``np.float64(4410.2)``)."""
    from pmdsim.geometry.camera import Camera
    from pmdsim.setup import default_setup, load_setup

    K = np.array([[4410.2, 0.0, 961.5], [0.0, 4409.8, 598.25], [0.0, 0.0, 1.0]])
    cam = Camera.from_opencv(K, np.array([-0.05, 0.01, 1e-4, -2e-4, 0.001]), (np.int64(1920), np.int64(1200)))
    s = default_setup()
    name = next(iter(s.cameras))
    s = s.with_cameras({**s.cameras, name: replace(s.cameras[name], camera=cam)})
    text = s.to_toml()
    assert "np." not in text
    doc = tomllib.loads(text)
    assert doc["cameras"][name]["focal_length_px"] == [4410.2, 4409.8]
    assert doc["cameras"][name]["principal_point_px"] == [961.5, 598.25]
    f = tmp_path / "s.toml"
    f.write_text(text, encoding="utf-8")
    back = load_setup(f).cameras[name].camera
    assert back.as_opencv()[0].tolist() == K.tolist()
    assert back.distortion.tolist() == [-0.05, 0.01, 1e-4, -2e-4, 0.001]
    assert (back.width_px, back.height_px) == (1920, 1200)


def test_dump_toml_quotes_keys_that_need_it():
    from pmdsim.setup.toml import dump_toml

    doc = {"cameras": {"left cam": {"v": np.float32(0.5), "n": np.int64(3), "ok": np.bool_(True),
                                    "a": np.array([1.0, 2.0])}, "a.b": {"x": "q\"uote\n"}}}
    assert tomllib.loads(dump_toml(doc)) == {"cameras": {"left cam": {"v": 0.5, "n": 3, "ok": True, "a": [1.0, 2.0]},
                                                         "a.b": {"x": "q\"uote\n"}}}


def test_simulate_16_bit(tmp_path, small_toml):
    """`[imaging] bit_depth = 16`: 16-bit greyscale PNGs written with the installed Pillow
    (pyproject pins the tested range; run at both ends, docs/reliability.md), values above the
    12-bit range, read back by `pmdsim evaluate`."""
    from PIL import Image

    setup = tmp_path / "s16.toml"
    setup.write_text(small_toml + "\n[imaging]\nbit_depth = 16\nfull_well_e = 40000.0\nread_noise_e = 6.0\n",
                     encoding="utf-8")
    r = cli("simulate", "--setup", str(setup), "--out", str(tmp_path / "sim"), "--quiet")
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "sim" / "manifest.json").read_text())
    assert doc["bit_depth"] == 16
    for e in doc["images"]:  # the PNG header's own bit depth and colour type (IHDR: bytes 24, 25)
        head = (tmp_path / "sim" / e["file"]).read_bytes()[:26]
        assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[24] == 16 and head[25] == 0, e["file"]
    # Pillow < 13 reads 16-bit PNGs as mode "I" (int32), ≥ 13 as uint16: compare values
    imgs = [np.asarray(Image.open(tmp_path / "sim" / e["file"])).astype(np.int64) for e in doc["images"]]
    assert max(int(a.max()) for a in imgs) > 4095 and max(int(a.max()) for a in imgs) <= 65535
    r = cli("evaluate", str(tmp_path / "sim"), "--setup", str(setup), "--out", str(tmp_path / "ev"), "--quiet")
    assert r.exit_code == 0, r.output


# ============================================================================ study output (reused)
def test_study_refuses_a_user_directory_and_a_locked_output(tmp_path):
    """`pmdsim study` adds to its OUT across reruns: a non-empty directory pmdsim did not write is
    refused, and so is an OUT whose lock another run holds — both before any case is computed."""
    example = Path(__file__).resolve().parents[1] / "examples" / "study_bulge_focal.toml"
    user = tmp_path / "data"
    user.mkdir()
    (user / "notes.txt").write_text("mine\n", encoding="utf-8")
    r = cli("study", str(example), "--out", str(user), "--quiet")
    assert r.exit_code == 2 and str(user) in one_error_line(r.output) and MARKER_NAME in r.output
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    out = tmp_path / "out"
    with output_lock(out, command="pmdsim study (the first run)"):
        r = run_subprocess("study", str(example), "--out", str(out), "--quiet")
    assert r.returncode == 2, r.stderr
    assert f"pid {os.getpid()}" in one_error_line(r.stderr) and not (out / "cases").exists()
