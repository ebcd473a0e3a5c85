"""The study engine (issue 15): study files, the engine on Dask, resumption, failures, summary.

References: the setup parser's own validation and closed-form parameter changes (offset/scale),
Experiment 1 run directly (not through the engine), a serial in-process run (the Dask runs must
equal it bit for bit: every case is deterministic), Python's ``statistics.quantiles`` for the
summary, and real processes and signals (the CLI interrupted with SIGINT; the runs on a Dask
scheduler and workers started with the ``dask`` command, a worker killed with SIGKILL, are in
tests/test_study_dask.py).
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.setup import default_setup
from pmdsim.studies.experiment1 import run_experiment1_case
from pmdsim.studies.study import CASES_DIR, run_study
from pmdsim.studies.study_file import StudyError, load_study, parse_study
from pmdsim.studies.study_results import wide_rows
from pmdsim.studies.study_summary import QUANTILES, metric_quantiles

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "study_bulge_focal.toml"
SRC = ROOT / "src"
#: Columns that depend on where and when a case ran, not on its inputs.
RUN_COLUMNS = {"elapsed_s", "worker", "run_id"}


def _env(**extra) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(SRC) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra)
    return env


def _rows(out) -> list[dict]:
    """One dict per case (``{camera}.{metric}``) from the tidy results.parquet."""
    return [{k: v for k, v in r.items() if k not in RUN_COLUMNS}
            for r in wide_rows(pq.read_table(Path(out) / "results.parquet"))]


def _records(out) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in (Path(out) / CASES_DIR).glob("*.json")}


def _foreground() -> None:
    """In the child, as an interactive shell starts a foreground job: SIGINT at its default (under
    a background runner SIGINT is inherited ignored, and pmdsim, like Python, keeps it ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _write(tmp_path, text: str, name="study.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


# ---------------------------------------------------------------------------- study files
GOOD = """
format = "pmdsim-study"
action = "simulate+evaluate"
downsample = 8
[[parameters]]
path = "screen.bulge_mm"
values = [0.0, 1.0]
"""


@pytest.mark.parametrize("text, key", [
    (GOOD.replace('path = "screen.bulge_mm"', 'path = "screen.bulge_m"'), "screen.bulge_m"),
    (GOOD.replace('path = "screen.bulge_mm"', 'path = "cameras.middle.focal_length_px"'), "cameras.middle"),
    (GOOD.replace("values = [0.0, 1.0]", 'values = [0.0, "one"]'), "parameters[0].values[1]"),
    (GOOD.replace("values = [0.0, 1.0]", "values = []"), "parameters[0].values"),
    (GOOD.replace("downsample = 8", "downsample = 8\nsamples = 3"), "samples"),
    (GOOD.replace('action = "simulate+evaluate"', 'action = "evaluate"'), "action"),
    (GOOD + '[[parameters]]\npath = "patterns.noise_std"\ndistribution = "normal"\nmean = 1.0\nstd = 0.1\n',
     "parameters[1].distribution"),
    (GOOD + '[[parameters]]\npath = "cameras.left.focal_length_px"\nmode = "offset"\nvalues = [[1.0, 2.0]]\n',
     "parameters[1].values[0]"),
    (GOOD.replace("values = [0.0, 1.0]", "values = [0.0, 1.0]\napplies_to = \"model\"")
     .replace("simulate+evaluate", "simulate"), "parameters[0].applies_to"),
    # Two parameters on one setup key would collapse into one case (issue 24), also as a list entry.
    (GOOD + '[[parameters]]\npath = "screen.bulge_mm"\nname = "again"\nvalues = [2.0]\n', "parameters[1].path"),
    (GOOD + '[[parameters]]\npath = "cameras.left.angles_deg"\nmode = "offset"\nvalues = [0.1]\n'
     '[[parameters]]\npath = "cameras.left.angles_deg[2]"\nvalues = [9.0]\n', "parameters[2].path"),
    (GOOD + '[[parameters]]\npath = "screen.bulge_mm"\nname = "camera"\napplies_to = "model"\nvalues = [2.0]\n',
     "parameters[1].name"),
])
def test_bad_study_file_refused_naming_the_key(tmp_path, text, key):
    p = _write(tmp_path, text)
    with pytest.raises(StudyError) as e:
        load_study(p)
    msg = str(e.value)
    assert key in msg and str(p) in msg and "\n" not in msg
    # The CLI refuses it before anything runs: one line, exit code 2, no output directory.
    res = CliRunner().invoke(main, ["study", str(p), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2
    assert res.output.strip().startswith("pmdsim: error:") and key in res.output
    assert not (tmp_path / "out").exists()


def test_setup_parser_errors_pass_through_with_the_key(tmp_path):
    # A negative focal length is refused by the setup parser; the study error names both keys.
    p = _write(tmp_path, GOOD.replace('path = "screen.bulge_mm"', 'path = "cameras.left.focal_length_px"')
               .replace("values = [0.0, 1.0]", "values = [[4400.0, 4400.0], [-1.0, 4400.0]]"))
    with pytest.raises(StudyError, match=r"parameters\[0\]\.values\[1\].*cameras\.left\.focal_length_px"):
        load_study(p)


def test_parameters_change_exactly_the_key():
    doc = {"format": "pmdsim-study", "action": "simulate", "parameters": [
        {"path": "cameras.left.focal_length_px", "mode": "offset", "values": [-7.5]},
        {"path": "cameras.right.principal_point_px", "mode": "scale", "values": [1.5]},
        {"path": "patterns.noise_std", "values": [0.25]},
    ]}
    (case,) = parse_study(doc).cases()
    from pmdsim.setup import parse_setup
    import tomllib

    truth = parse_setup(tomllib.loads(case.truth_toml))
    base = default_setup()
    b, t = base.cameras, truth.cameras
    assert (t["left"].camera.fx_px, t["left"].camera.fy_px) == (4400.0 - 7.5, 4400.0 - 7.5)
    assert (t["right"].camera.ppx_px, t["right"].camera.ppy_px) == (960.0 * 1.5, 600.0 * 1.5)
    assert truth.patterns.noise_std == 0.25
    # Everything else is the base setup.
    changed = truth.with_camera("left", fx_px=4400.0, fy_px=4400.0).with_camera(
        "right", ppx_px=960.0, ppy_px=600.0).with_patterns(noise_std=0.0)
    assert changed.to_dict() == base.to_dict()
    assert b["left"].camera.fx_px == 4400.0  # the base is not modified


def test_monte_carlo_draws_are_seeded_per_sample():
    doc = {"format": "pmdsim-study", "action": "simulate",
           "parameters": [{"path": "screen.bulge_mm", "values": [0.0, 1.0]},
                          {"path": "patterns.noise_std", "distribution": "uniform", "low": 0.5, "high": 2.0},
                          {"path": "cameras.left.focal_length_px", "mode": "offset", "distribution": "normal",
                           "mean": 0.0, "std": 3.0}],
           "monte_carlo": {"samples": 3, "seed": 11}}
    study = parse_study(doc)
    cases = study.cases()
    assert len(cases) == study.n_cases == 6
    for c in cases:
        rng = np.random.default_rng([11, c.mc_sample])  # the documented draw, in parameter order
        assert c.params["patterns.noise_std"] == rng.uniform(0.5, 2.0)
        assert c.params["offset(cameras.left.focal_length_px)"] == rng.normal(0.0, 3.0)
    # The same sample index draws the same values at every grid point; the keys all differ.
    assert [c.params["patterns.noise_std"] for c in cases[:3]] == [c.params["patterns.noise_std"] for c in cases[3:]]
    assert len({c.key for c in cases}) == 6
    assert [c.key for c in parse_study(doc).cases()] == [c.key for c in cases]


# ---------------------------------------------------------------------------- running
def test_engine_case_equals_experiment1(tmp_path):
    p = _write(tmp_path, GOOD.replace("values = [0.0, 1.0]", "values = [1.0]"))
    run = run_study(load_study(p), tmp_path / "out", serial=True)
    assert (run.n_computed, run.n_failed, run.n_missing) == (1, 0, 0)
    (row,) = _rows(tmp_path / "out")
    for cam in ("left", "right"):
        ref = run_experiment1_case(1.0, cam, downsample=8).metrics
        for k in ("max_height_diff_um", "max_dev_plane_um", "tilt_urad", "rms_um", "n_pixels"):
            assert row[f"{cam}.{k}"] == ref[k]


# A slower study (cameras binned 2 × 2: about a second per case) so that a signal lands mid-study.
SLOW = """
format = "pmdsim-study"
action = "simulate+evaluate"
downsample = 2
metrics = ["max_dev_plane_um"]
[[parameters]]
path = "screen.bulge_mm"
values = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
"""


def _wait_for_records(out: Path, n: int, proc: subprocess.Popen, timeout=240) -> None:
    t0 = time.monotonic()
    while len(list((out / CASES_DIR).glob("*.json"))) < n if (out / CASES_DIR).exists() else True:
        assert proc.poll() is None, "the study ended before the signal"
        assert time.monotonic() - t0 < timeout
        time.sleep(0.02)


#: 16 cases of ≈ 0.7 s: a Ctrl-C after the first record finds most of them still to do, also when
#: the first cases finish together (a cold worker compiling its kernels holds the others back).
SLOW16 = SLOW.replace("values = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]",
                      "values = [" + ", ".join(f"{0.25 * i:g}" for i in range(16)) + "]")

FINALISER_SIGINT = """
import os, signal, sys, weakref
from pmdsim import interrupts
from pmdsim.studies.study import run_study
from pmdsim.studies.study_file import load_study

fired = []

class Probe:
    pass

def progress(d):
    # The first finished case: a real SIGINT to this process, delivered while a finaliser runs
    # (weakref.finalize's callback, as dask's Future.__del__ and weakref callbacks run in this
    # thread): pmdsim.interrupts can only record it there, not raise it.
    if not fired:
        fired.append(d["done"])
        probe = Probe()
        weakref.finalize(probe, os.kill, os.getpid(), signal.SIGINT)
        del probe

if __name__ == "__main__":  # the LocalCluster's worker processes import this file
    interrupts.install()
    try:
        run = run_study(load_study(sys.argv[1]), sys.argv[2], n_workers=1, progress=progress,
                        serial=sys.argv[3] == "1")
        print("completed", run.n_computed, interrupts.received())
    except interrupts.Interrupted as e:
        print("interrupted", fired, e.signum)
"""


@pytest.mark.slow
@pytest.mark.parametrize("serial", [False, True])
def test_signal_in_a_finaliser_still_stops_the_study(tmp_path, serial):
    """A SIGINT that arrives while a finaliser runs in the main thread is recorded, not raised
    (Python would drop the exception); the study loop looks for it while it waits and stops
    (it used to run every remaining case and end with exit 0 — seen in a fresh-clone CI run)."""
    study, out = _write(tmp_path, SLOW16), tmp_path / "out"
    script = tmp_path / "probe.py"
    script.write_text(FINALISER_SIGINT, encoding="utf-8")
    r = subprocess.run([sys.executable, str(script), str(study), str(out), "1" if serial else "0"], env=_env(),
                       capture_output=True, text=True, timeout=300, preexec_fn=_foreground)
    assert r.returncode == 0, r.stderr
    words = r.stdout.split()
    assert words[0] == "interrupted", r.stdout
    assert len(_records(out)) < 16


#: SLOW16 binned 4 × 4: the rerun's 14–15 cases are the test's cost (≈ 15 s at 2 × 2).
QUICK16 = SLOW16.replace("downsample = 2", "downsample = 4")


@pytest.mark.slow
def test_interrupted_study_rerun_computes_only_missing(tmp_path):
    """Ctrl-C after the first record, then the same command again: it computes the missing cases
    only and reuses the recorded ones unchanged. On QUICK16: what is checked (which cases are
    recorded, missing, reused, their run ids) does not depend on the image size, and the study stops
    within 0.5 s of the signal, a few cases, so most of the 16 are still left to the rerun."""
    study, out = _write(tmp_path, QUICK16), tmp_path / "out"
    cmd = [sys.executable, "-m", "pmdsim.cli", "study", str(study), "--out", str(out), "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, env=_env(), stderr=subprocess.PIPE, text=True, preexec_fn=_foreground)
    _wait_for_records(out, 1, proc)
    proc.send_signal(signal.SIGINT)  # Ctrl-C
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err
    first = _records(out)
    n_done = len(first)
    assert 1 <= n_done < 16
    rows = _rows(out)  # the partial results were written, missing cases marked
    assert sum(r["status"] == "missing" for r in rows) == 16 - n_done

    res = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert f"{16 - n_done} cases computed, {n_done} reused" in res.stderr
    second = _records(out)
    assert len(second) == 16
    for key, rec in first.items():
        assert second[key] == rec  # not recomputed: the same record, same run id
    new_runs = {r["run_id"] for k, r in second.items() if k not in first}
    assert len(new_runs) == 1 and not new_runs & {r["run_id"] for r in first.values()}
    assert all(r["status"] == "ok" for r in _rows(out))


def test_failing_case_is_recorded_and_the_study_goes_on(tmp_path):
    # The sample moved 1 m sideways: a valid setup whose central pixels miss the sample, so the
    # reconstruction cannot be seeded — a run-time failure of that case only.
    p = _write(tmp_path, GOOD.replace('path = "screen.bulge_mm"', 'path = "sample.origin_world_mm"')
               .replace("values = [0.0, 1.0]", "values = [[-200.0, -200.0, 0.0], [800.0, -200.0, 0.0]]"))
    study = load_study(p)
    run = run_study(study, tmp_path / "out", serial=True)
    assert (run.n_computed, run.n_failed, run.n_missing) == (2, 1, 0)
    ok, failed = _rows(tmp_path / "out")
    assert ok["status"] == "ok" and ok["left.max_dev_plane_um"] < 0.1
    assert failed["status"] == "failed" and "does not see the sample" in failed["error"]
    # A rerun keeps the recorded failure (deterministic) and computes nothing.
    again = run_study(study, tmp_path / "out", serial=True)
    assert (again.n_computed, again.n_reused, again.n_failed) == (0, 2, 1)
    from pmdsim.studies.study_summary import write_study_outputs

    write_study_outputs(study, tmp_path / "out")
    assert "failed cases:" in (tmp_path / "out" / "summary.txt").read_text()


def test_summary_quantiles_match_statistics_module():
    rng = np.random.default_rng(3)
    values = rng.normal(5.0, 2.0, 57)
    rows = [{"status": "ok", "left.x_um": float(v)} for v in values] + [{"status": "failed", "left.x_um": None}]
    s = metric_quantiles(rows, "left.x_um")
    cuts = statistics.quantiles(values.tolist(), n=20, method="inclusive")  # 5 %, 10 %, …, 95 %
    assert s["n"] == 57
    for q in QUANTILES:
        assert s[f"q{round(q * 100):02d}"] == pytest.approx(cuts[round(q * 20) - 1], rel=1e-12)
    assert s["mean"] == pytest.approx(statistics.fmean(values.tolist()), rel=1e-12)
    assert s["std"] == pytest.approx(statistics.stdev(values.tolist()), rel=1e-12)


def test_unreachable_scheduler_is_one_clear_error(tmp_path):
    import socket

    with socket.socket() as s:  # a loopback port that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    study = load_study(_write(tmp_path, GOOD))
    with pytest.raises(StudyError, match=rf"cannot connect to the Dask scheduler 'tcp://127\.0\.0\.1:{port}'"):
        run_study(study, tmp_path / "out", scheduler=f"tcp://127.0.0.1:{port}", connect_timeout_s=1)
    assert not list((tmp_path / "out" / CASES_DIR).glob("*.json"))


MC = """
format = "pmdsim-study"
action = "simulate+evaluate"
downsample = 8
metrics = ["max_dev_plane_um", "tilt_urad"]
[[parameters]]
path = "cameras.left.angles_deg"
applies_to = "model"
mode = "offset"
distribution = "normal"
mean = 0.0
std = 0.01
[monte_carlo]
samples = 6
seed = 5
"""


def test_monte_carlo_study_summary_and_histogram(tmp_path):
    from pmdsim.studies.study_summary import write_study_outputs

    study = load_study(_write(tmp_path, MC))
    run = run_study(study, tmp_path / "out", serial=True)
    assert (run.n_computed, run.n_failed) == (6, 0)
    written = write_study_outputs(study, tmp_path / "out")
    assert "hist_metrics.png" in written and (tmp_path / "out" / "hist_metrics.png").stat().st_size > 0
    rows = _rows(tmp_path / "out")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    v = [r["left.tilt_urad"] for r in rows]
    assert summary["left.tilt_urad"]["n"] == 6
    assert summary["left.tilt_urad"]["q50"] == pytest.approx(statistics.median(v), rel=1e-12)
    # An angle error of the evaluation's left camera leaves the right camera's result unchanged.
    assert len({r["right.tilt_urad"] for r in rows}) == 1


def test_calibrate_evaluate_case_equals_experiment2_chain(tmp_path):
    from pmdsim.studies.experiment2 import calibrate_and_reconstruct

    p = _write(tmp_path, GOOD.replace('action = "simulate+evaluate"',
                                      'action = "calibrate+evaluate"\nscreen_model = "grid3"\nseed = 4')
               .replace("values = [0.0, 1.0]", "values = [2.0]"))
    run = run_study(load_study(p), tmp_path / "out", serial=True)
    assert (run.n_computed, run.n_failed) == (1, 0)
    (row,) = _rows(tmp_path / "out")
    ref = calibrate_and_reconstruct(default_setup().binned(8).with_bulge(2.0), start_seed=[4, 0], screen_grid=3)
    assert row["left.calibration_rms_px"] == ref.result.rms_px
    assert row["left.calibration_iterations"] == ref.result.iterations
    for case in ref.cases:
        for k in ("max_height_diff_um", "max_dev_plane_um", "tilt_urad"):
            assert row[f"{case.camera}.{k}"] == case.metrics[k]
    assert row["right.fx_error_px"] == ref.deviation["right"]["fx_px"]
    assert row["left.fx_std_px"] == ref.result.std("left.fx_px")


def test_save_maps_writes_each_case_reconstruction(tmp_path):
    import h5py

    p = _write(tmp_path, GOOD.replace("downsample = 8", "downsample = 8\nsave_maps = true")
               .replace("values = [0.0, 1.0]", "values = [1.0]"))
    run_study(load_study(p), tmp_path / "out", serial=True)
    (row,) = _rows(tmp_path / "out")
    with h5py.File(tmp_path / "out" / "maps" / f"{row['case_key']}.h5", "r") as f:
        assert json.loads(f.attrs["params"]) == {"screen.bulge_mm": 1.0}
        for cam in ("left", "right"):
            h = f[cam]["height_mm"][()]
            assert h.shape == (150, 240) and f[cam]["valid"][()].sum() == row[f"{cam}.n_pixels"]
            # The true sample is the plane z = 0 of the sample frame: the height is the error.
            assert (np.nanmax(h) - np.nanmin(h)) * 1e3 == pytest.approx(row[f"{cam}.max_height_diff_um"], rel=1e-12)
    # Without save_maps nothing heavy is written.
    run_study(load_study(_write(tmp_path, GOOD, "plain.toml")), tmp_path / "out2", serial=True)
    assert not (tmp_path / "out2" / "maps").exists()


def test_case_option_grid_screen_model(tmp_path):
    # Perfect knowledge of the bulged screen (screen_model = "setup") reconstructs the plane
    # exactly; the planar screen model leaves Experiment 1's error.
    p = _write(tmp_path, GOOD.replace("values = [0.0, 1.0]", "values = [2.0]")
               + '[[parameters]]\npath = "screen_model"\nvalues = ["planar", "setup"]\n')
    run_study(load_study(p), tmp_path / "out", serial=True)
    planar, exact = _rows(tmp_path / "out")
    assert (planar["screen_model"], exact["screen_model"]) == ("planar", "setup")
    assert planar["left.max_height_diff_um"] == run_experiment1_case(2.0, "left", downsample=8).metrics[
        "max_height_diff_um"]
    assert exact["left.max_height_diff_um"] < 0.1 and exact["right.max_height_diff_um"] < 0.1
    bad = _write(tmp_path, GOOD + '[[parameters]]\npath = "screen_model"\nvalues = ["planar", "grid3"]\n', "bad.toml")
    with pytest.raises(StudyError, match=r"parameters\[1\]\.values\[1\]"):
        load_study(bad)


def test_indexed_path_changes_one_entry(tmp_path):
    doc = {"format": "pmdsim-study", "action": "simulate", "parameters": [
        {"path": "cameras.left.angles_deg[2]", "mode": "offset", "values": [0.25]},
        {"path": "cameras.right.origin_world_mm[0]", "values": [91.5]}]}
    (case,) = parse_study(doc).cases()
    import tomllib

    from pmdsim.setup import parse_setup

    t = parse_setup(tomllib.loads(case.truth_toml))
    assert t.cameras["left"].pose.angles_deg == (45.0, 10.0, 10.25)
    assert t.cameras["right"].pose.origin_world_mm == (91.5, 295.0, -295.0)
    doc["parameters"][1]["path"] = "cameras.right.origin_world_mm[3]"
    with pytest.raises(StudyError,
                       match=r"parameters\[1\].*index 3 is out of range \(cameras\.right\.origin_world_mm has 3"):
        parse_study(doc)


def test_identical_cases_run_once(tmp_path):
    # A repeated grid value gives identical inputs: one key, one computation, two rows.
    p = _write(tmp_path, GOOD.replace("values = [0.0, 1.0]", "values = [1.0, 1.0]"))
    run = run_study(load_study(p), tmp_path / "out", serial=True)
    assert (run.n_cases, run.n_computed, run.n_missing) == (2, 1, 0)
    a, b = _rows(tmp_path / "out")
    assert a["case_key"] == b["case_key"] and a["status"] == b["status"] == "ok"
    assert (a["case_id"], b["case_id"]) == (0, 1)


def test_setup_path_relative_to_the_study_file(tmp_path, small_toml):
    (tmp_path / "setups").mkdir()
    (tmp_path / "setups" / "small.toml").write_text(small_toml, encoding="utf-8")
    text = GOOD.replace("downsample = 8", 'downsample = 1\nsetup = "setups/small.toml"')
    study = load_study(_write(tmp_path, text))
    assert study.base.cameras["left"].camera.width_px == 96
    run = run_study(study, tmp_path / "out", serial=True)
    assert (run.n_computed, run.n_failed) == (2, 0)
    with pytest.raises(StudyError, match=r"study\.toml: setup: setup file .*nowhere\.toml.* does not exist"):
        load_study(_write(tmp_path, GOOD.replace("downsample = 8", 'downsample = 8\nsetup = "nowhere.toml"')))


def test_workers_with_scheduler_refused(tmp_path):
    res = CliRunner().invoke(main, ["study", str(EXAMPLE), "--out", str(tmp_path / "out"),
                                    "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"])
    assert res.exit_code == 2 and "--workers" in res.output and not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- failing fast (issue 23)
@pytest.mark.parametrize("address, expected", [
    ("not-an-address", "scheduler address 'not-an-address' is not valid"),
    (None, "cannot connect to the Dask scheduler 'tcp://127.0.0.1:"),  # a loopback port nobody listens on
])
def test_bad_scheduler_is_one_line_and_leaves_nothing(tmp_path, address, expected):
    import socket

    if address is None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    study = _write(tmp_path, GOOD)
    res = subprocess.run([sys.executable, "-m", "pmdsim.cli", "study", str(study), "--out", str(tmp_path / "out"),
                          "--scheduler", address, "--connect-timeout", "1"], env=_env(), capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert lines[-1].startswith("pmdsim: error: ") and expected in lines[-1], res.stderr
    assert "Traceback" not in res.stderr and len(lines) == 2  # the study's header line, the error
    assert not (tmp_path / "out").exists()


def test_run_study_on_the_callers_client(tmp_path):
    from distributed import Client, LocalCluster

    study = load_study(_write(tmp_path, GOOD))
    run_study(study, tmp_path / "serial", serial=True)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as lc, \
            Client(lc) as client:
        run = run_study(study, tmp_path / "out", client=client)
        assert (run.n_computed, run.n_missing) == (2, 0)
        assert client.status == "running"  # the caller's client is left open
        assert client.submit(sum, [1, 2]).result() == 3
    assert _rows(tmp_path / "out") == _rows(tmp_path / "serial")


@pytest.mark.slow
def test_ctrl_c_in_a_terminal_is_one_line_and_leaves_nothing(tmp_path):
    """SIGINT to the whole foreground process group, as a terminal sends it on Ctrl-C: the
    LocalCluster's worker processes get it too and must not print tracebacks."""
    study, out = _write(tmp_path, SLOW16), tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "pmdsim.cli", "study", str(study), "--out", str(out),
                             "--workers", "2", "--quiet"], env=_env(), stderr=subprocess.PIPE, text=True,
                            preexec_fn=_foreground, start_new_session=True)
    _wait_for_records(out, 1, proc)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("pmdsim: interrupted (SIGINT); the finished cases are recorded"), err
    assert len(lines) == 3, err  # the header, the cluster, the interruption
    left = [p.name for p in tmp_path.rglob(".*") if ".partial-" in p.name or p.name.endswith(".lock")]
    assert not left


# ---------------------------------------------------------------------------- tidy tables (issue 23)
def test_tidy_results_schema_units_and_rerun(tmp_path):
    """results.parquet read back with pyarrow: one row per case and camera, values equal to the
    records on disk, every column of its declared type (also when all null), the same schema
    before any case is computed and after."""
    import pyarrow as pa

    from pmdsim.studies.study_results import RESULTS_WIDE_CSV, write_results

    text = GOOD + ('[[parameters]]\npath = "cameras.left.focal_length_px"\napplies_to = "model"\nmode = "offset"\n'
                   'values = [-5.0]\n')
    study = load_study(_write(tmp_path, text))
    out = tmp_path / "out"
    assert write_results(out.mkdir() or out, study) == {"ok": 0, "failed": 0, "missing": 2}
    before = pq.read_schema(out / "results.parquet")
    run_study(study, out, serial=True)
    table = pq.read_table(out / "results.parquet")
    assert table.schema.equals(before, check_metadata=True)
    assert not any(pa.types.is_null(f.type) for f in table.schema)
    f = table.schema.field("max_height_diff_um")
    assert f.type == pa.float64() and f.metadata[b"units"] == b"um"
    assert table.schema.field("tilt_urad").metadata[b"units"] == b"urad"
    assert table.schema.field("n_pixels").type == pa.int64()
    p = table.schema.field("offset(model.cameras.left.focal_length_px)")  # it holds the offset, says so
    assert p.metadata == {b"units": b"pixel", b"setup_key": b"cameras.left.focal_length_px",
                          b"applies_to": b"model", b"mode": b"offset"}
    rows = table.to_pylist()
    recs = _records(out)
    assert [(r["case_id"], r["camera"]) for r in rows] == [(0, "left"), (0, "right"), (1, "left"), (1, "right")]
    for r in rows:
        rec = recs[r["case_key"]]
        assert r["screen.bulge_mm"] == rec["screen.bulge_mm"] and r["status"] == "ok"
        assert r["offset(model.cameras.left.focal_length_px)"] == -5.0
        for m in study.metrics:
            assert r[m] == rec[f"{r['camera']}.{m}"]
    wide = (out / RESULTS_WIDE_CSV).read_text().splitlines()
    assert len(wide) == 3 and '"left.max_height_diff_um"' in wide[0]


def test_huge_grid_starts_at_once_with_bounded_futures(tmp_path):
    """9 million cases (300 × 300 × 100): the first cases finish within seconds and the client
    never holds more than the documented number of cases in flight; stopped after 12 cases,
    the study leaves their records (the tables of 9 million rows are left to a rerun)."""
    from distributed import Client, LocalCluster

    from pmdsim.studies.study import MIN_IN_FLIGHT, RESULTS_PARQUET

    grid = lambda n, step: "[" + ", ".join(f"{step * i:g}" for i in range(n)) + "]"  # noqa: E731
    text = ('format = "pmdsim-study"\naction = "simulate"\ndownsample = 8\n'
            f'[[parameters]]\npath = "screen.bulge_mm"\nvalues = {grid(300, 0.01)}\n'
            f'[[parameters]]\npath = "patterns.noise_std"\nvalues = {grid(300, 0.01)}\n'
            f'[[parameters]]\npath = "cameras.left.angles_deg[2]"\nmode = "offset"\nvalues = {grid(100, 0.001)}\n')
    study = load_study(_write(tmp_path, text))
    assert study.n_cases == 9_000_000
    seen = []

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as lc, \
            Client(lc) as client:
        def progress(d):
            seen.append((time.perf_counter(), len(client.futures)))
            if d["done"] == 12:
                raise KeyboardInterrupt

        t0 = time.perf_counter()
        with pytest.raises(KeyboardInterrupt):
            run_study(study, tmp_path / "out", client=client, progress=progress)
    assert seen[0][0] - t0 < 30  # the eager version built 9 M cases first (≈ 12 h)
    assert max(n for _, n in seen) <= MIN_IN_FLIGHT  # 1 Dask thread: at most 8 cases in flight
    assert len(_records(tmp_path / "out")) >= 12 and not (tmp_path / "out" / RESULTS_PARQUET).exists()


@pytest.mark.slow
def test_progress_bar_in_a_terminal(tmp_path):
    """stderr a terminal (a pseudo-terminal): a progress bar, not one line per case."""
    import pty

    master, slave = pty.openpty()
    study = _write(tmp_path, GOOD)
    proc = subprocess.Popen([sys.executable, "-m", "pmdsim.cli", "study", str(study), "--out", str(tmp_path / "out"),
                             "--workers", "1"], env=_env(), stdout=subprocess.DEVNULL, stderr=slave)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    assert proc.wait(timeout=120) == 0
    text = b"".join(chunks).decode()
    assert "study" in text and "2/2" in text and " done, " not in text, text
