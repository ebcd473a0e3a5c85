"""The cameras of ``pmdsim evaluate`` two at a time (studies/evaluate_cameras, issue 25): results
in camera order whatever order the threads finish in, the first failing camera's error (in camera
order) after the results before it, the cameras after it stopped, serial where numba's threading
layer is not thread-safe; end to end, a bad image in the second camera gives the one line the
serial loop gave, and nothing is written."""

from __future__ import annotations

import threading
import time

import pytest

from pmdsim.studies import evaluate_cameras as ec


def _slow_first(delays: dict, seen: list, fail: dict | None = None):
    """A camera pipeline that sleeps ``delays[cam]`` s, records its thread, raises ``fail[cam]``."""
    def work(cam, stop, stage):
        with stage("decode"):
            seen.append((cam, threading.current_thread().name))
        t = time.perf_counter()
        while time.perf_counter() - t < delays.get(cam, 0.0):
            if stop.is_set():
                raise ec.CameraCancelled(cam)
            time.sleep(0.005)
        if fail and cam in fail:
            raise fail[cam]
        return ec.CameraResult(cam)
    return work


def test_results_in_camera_order_when_the_second_finishes_first():
    seen = []
    out = [r.cam for r in ec.camera_results(["left", "right"], _slow_first({"left": 0.2}, seen), concurrent=True)]
    assert out == ["left", "right"]
    assert all(name.startswith("pmdsim-camera") for _, name in seen)  # both in the pool, at once
    seen = []
    out = [r.cam for r in ec.camera_results(["left", "right"], _slow_first({}, seen), concurrent=False)]
    assert out == ["left", "right"] and {n for _, n in seen} == {threading.current_thread().name}


def test_first_error_in_camera_order_after_the_results_before_it():
    # the right camera fails at once, the left one later: the left result first, then the right error
    got = []
    with pytest.raises(OSError, match="right broken"):
        for r in ec.camera_results(["left", "right"], _slow_first({"left": 0.2}, [], {"right": OSError("right broken")}),
                                   concurrent=True):
            got.append(r.cam)
    assert got == ["left"]
    # both fail: the left camera's error, as in a serial loop
    with pytest.raises(OSError, match="left broken"):
        list(ec.camera_results(["left", "right"], _slow_first({"left": 0.1}, [], {"left": OSError("left broken"),
                                                                              "right": OSError("right broken")}),
                               concurrent=True))


def test_cameras_after_a_failure_are_stopped_and_waited_for():
    stopped = []

    def work(cam, stop, stage):
        if cam == "a":
            raise ValueError("a failed")
        with stage("decode"):
            pass
        for _ in range(400):  # ≤ 2 s unless told to stop
            if stop.is_set():
                stopped.append(cam)
                raise ec.CameraCancelled(cam)
            time.sleep(0.005)
        return ec.CameraResult(cam)

    t = time.perf_counter()
    with pytest.raises(ValueError, match="a failed"):
        list(ec.camera_results(["a", "b", "c"], work, concurrent=True))
    assert sorted(stopped) == ["b", "c"] and time.perf_counter() - t < 1.5  # stopped, not run out, and waited for


@pytest.mark.parametrize("mode", ["stages", "full"])
def test_one_camera_at_a_time_per_stage_in_camera_order(monkeypatch, mode):
    """Overlapped by stage (the default), no two cameras are in the same stage at once and they
    enter each stage in camera order (a pipeline); ``full`` lets them into the same stage."""
    monkeypatch.setenv(ec.CAMERA_OVERLAP_ENV, mode)
    log = []

    def work(cam, stop, stage):
        for name in ec.STAGES:
            with stage(name):
                log.append((name, cam, "in", time.perf_counter()))
                time.sleep(0.03)
                log.append((name, cam, "out", time.perf_counter()))
        return ec.CameraResult(cam)

    assert [r.cam for r in ec.camera_results(["left", "right"], work, concurrent=True)] == ["left", "right"]
    for name in ec.STAGES:
        ev = sorted((t, cam, what) for n, cam, what, t in log if n == name)
        if mode == "stages":
            assert [(c, w) for _, c, w in ev] == [("left", "in"), ("left", "out"), ("right", "in"), ("right", "out")]
    overlap = any(a[1] != b[1] and a[0] == b[0] and a[2] == "in" and b[2] == "in" and a[3] < b[3] < next(
        t for n, c, w, t in log if (n, c, w) == (a[0], a[1], "out")) for a in log for b in log)
    assert overlap is (mode == "full")


@pytest.mark.parametrize("layer, expect", [("omp", True), ("tbb", True), ("workqueue", False)])
def test_serial_unless_the_threading_layer_is_thread_safe(monkeypatch, layer, expect):
    import numba

    monkeypatch.setattr(numba, "threading_layer", lambda: layer)
    monkeypatch.delenv(ec.CAMERA_THREADS_ENV, raising=False)
    assert ec.concurrent_cameras(2) is expect
    assert ec.concurrent_cameras(1) is False
    monkeypatch.setenv(ec.CAMERA_THREADS_ENV, "1")
    assert ec.concurrent_cameras(2) is False


def test_bad_image_in_the_second_camera_gives_the_serial_error(tmp_path, monkeypatch):
    """End to end: the right camera's first image is not a PNG. Concurrent and serial runs fail
    with the same one line naming that file; nothing is written; the left camera's progress
    message (done before the error in camera order) is printed in both."""
    import shutil

    from pmdsim.errors import PmdsimError
    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import evaluate_image_set, simulate_to_dir

    setup = default_setup().binned(32)  # 60 × 37 px per camera
    simulate_to_dir(setup, tmp_path / "img")
    bad = sorted((tmp_path / "img").glob("right_*.png"))[5]
    bad.write_bytes(b"not a png")
    lines = {}
    for threads in ("2", "1"):
        monkeypatch.setenv(ec.CAMERA_THREADS_ENV, threads)
        progress = []
        with pytest.raises(PmdsimError) as e:
            evaluate_image_set(tmp_path / "img", setup, tmp_path / f"ev{threads}", progress=progress.append)
        assert not (tmp_path / f"ev{threads}").exists()
        lines[threads] = (type(e.value), str(e.value), progress)
    assert lines["2"] == lines["1"]
    assert bad.name in lines["2"][1] and "\n" not in lines["2"][1]
    assert lines["2"][2] == ["evaluated left"]
    shutil.rmtree(tmp_path / "img")


def test_evaluation_file_camera_by_camera_keeps_the_documented_order(tmp_path):
    """``EvaluationFile`` as ``evaluate`` uses it — each camera's maps when it is joined, the
    extras of every camera after the fit, the file attributes last — lists the cameras in
    camera order and the file attributes as given, then the two code tables (the file tracks
    creation order; the attributes written last still list in write_evaluation_h5's order); the
    camera groups list their maps by name; the values unchanged."""
    from types import SimpleNamespace

    import h5py
    import numpy as np

    from pmdsim.io import hdf5

    H, W = 5, 7
    rng = np.random.default_rng(1)
    res = {c: (SimpleNamespace(screen_xy_mm=rng.random((H, W, 2)), std_xy_mm=rng.random((H, W, 2)),
                               valid=np.ones((H, W), bool), flags=np.zeros((H, W), np.uint8),
                               reversed=np.zeros((H, W, 2), bool)),
               SimpleNamespace(status=np.zeros((H, W), np.uint8)),
               SimpleNamespace(n_sample=rng.random((H, W, 3)), p_sample_mm=rng.random((H, W, 3)),
                               height_mm=rng.random((H, W)), reconstructed=np.ones((H, W), bool), method="stepwise",
                               seed_pixel=(1, 2), converged=True, iterations=3)) for c in ("left", "right")}
    extras = {c: {"slopes": rng.random((H, W, 2)), "residual_slopes": rng.random((H, W, 2)),
                  "height_std_um": rng.random((H, W))} for c in res}
    attrs = {"pmdsim_version": "x", "method": "stepwise", "warnings": "[]"}
    path = tmp_path / "evaluation.h5"
    with hdf5.EvaluationFile(path) as f:
        for c, (d, r, rec) in res.items():
            f.add_camera(c, d, r, rec)
        for c in res:
            f.add_extras(c, extras[c])
        f.finish(attrs)
    maps = ["screen_xy_mm", "std_xy_mm", "decoded", "phase_flags", "reversed_contrast", "registration_status",
            "normals", "points_mm", "height_mm", "reconstructed", "slopes", "residual_slopes", "height_std_um"]
    with h5py.File(path) as f:
        assert list(f) == ["left", "right"]
        assert list(f.attrs) == [*attrs, "phase_flags", "registration_status"]
        for c, (d, r, rec) in res.items():
            assert [k for k in f[c] if k in maps] == sorted(maps)  # camera groups list by name
            assert list(f[c].attrs) == sorted(["method", "seed_pixel", "converged", "iterations"])
            np.testing.assert_array_equal(f[c]["screen_xy_mm"][()], d.screen_xy_mm)
            np.testing.assert_array_equal(f[c]["height_std_um"][()], extras[c]["height_std_um"])


@pytest.mark.parametrize("name, value", [("PMDSIM_CAMERA_THREADS", "one"), ("PMDSIM_CAMERA_THREADS", "3"),
                                         ("PMDSIM_CAMERA_OVERLAP", "ful")])
def test_unknown_environment_value_is_one_line_naming_it(tmp_path, monkeypatch, name, value):
    """A typo in either variable is refused with one line naming the variable, the value and the
    choices — not silently run as the default — and nothing is written."""
    from pmdsim.errors import InputError
    from pmdsim.setup import default_setup
    from pmdsim.studies.jobs import evaluate_image_set, simulate_to_dir

    setup = default_setup().binned(32)
    simulate_to_dir(setup, tmp_path / "img")
    monkeypatch.delenv(ec.CAMERA_THREADS_ENV, raising=False)
    monkeypatch.setenv(name, value)
    with pytest.raises(InputError) as e:
        evaluate_image_set(tmp_path / "img", setup, tmp_path / "ev", progress=None)
    msg = str(e.value)
    assert name in msg and repr(value) in msg and "expected one of" in msg and "\n" not in msg
    assert not (tmp_path / "ev").exists()
    monkeypatch.setenv(name, "")  # empty = unset: the default
    assert ec._env_choice(name, ("a", "b")) == "a"
