"""An image set's stacks as slices of one array per camera, handed to the kernels without a copy
or a typed list, and the background decoding of `pmdsim evaluate` (pmdsim.io.imageset_prefetch,
issue 25 item 1).

The references are independent of the code under test: the images as Pillow reads them, numpy's
own stacking, the error messages of the main-thread read (no prefetch), and a subprocess's exit.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pmdsim.errors import ImageSetError
from pmdsim.evaluation.decoding_fused import common_image_stack
from pmdsim.io import imageset_prefetch as pf
from pmdsim.io.imageset import load_camera_stacks, load_manifest
from test_imageset import F6, write_full_set

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("prefetch") / "set"
    write_full_set(d)
    return d


@pytest.fixture(autouse=True)
def _no_prefetch_left():
    yield
    pf.stop_prefetch()
    assert not [t for t in threading.enumerate() if t.name == "pmdsim-image-prefetch"]


def _pillow_stacks(d: Path, camera: str):
    """Per (direction, period) the images as Pillow reads them, stacked by numpy: the reference."""
    doc = json.loads((d / "manifest.json").read_text())
    out: dict = {}
    for e in doc["images"]:
        if e["camera"] == camera:
            out.setdefault((e["direction"], e["period_mm"]), {})[e["shift_index"]] = np.asarray(Image.open(d / e["file"]))
    return {k: np.stack([v[i] for i in range(len(v))]) for k, v in out.items()}


def _check_stacks(imgs, ref):
    for direction in "xy":
        for p, st in zip(imgs.periods_mm(direction), imgs.stacks(direction)):
            np.testing.assert_array_equal(st, ref[(direction, p)], strict=True)
            assert not st.flags.writeable
    every = [*imgs.x_stacks, *imgs.y_stacks]
    base = common_image_stack([im for st in every for im in st])
    # one array per camera: the kernels' (N, H, W) view of all stacks shares their memory
    assert base.shape == (sum(len(st) for st in every),) + imgs.shape and not base.flags.writeable
    assert all(np.shares_memory(base, st) for st in every)
    np.testing.assert_array_equal(base, np.concatenate(every), strict=True)


@pytest.mark.parametrize("prefetch", ["no", "done", "racing"], ids=["main-thread", "prefetched", "racing"])
def test_stacks_are_slices_of_one_array_and_the_files_values(two_cameras, prefetch):
    p = bufs = None
    if prefetch != "no":
        pf.start_prefetch(two_cameras)
        p = pf._ACTIVE[pf._manifest_key(two_cameras)]
    if prefetch == "done":  # every frame decoded and both arrays made before the first load
        p.thread.join(5.0)
        bufs = dict(p.buffers)
        assert set(bufs) == {"left", "right"}
    m = load_manifest(two_cameras)
    for cam in ("right", "left"):  # not the manifest's order: frames are found by file
        imgs = load_camera_stacks(m, cam)
        _check_stacks(imgs, _pillow_stacks(two_cameras, cam))
        if bufs is not None:  # filled into the thread's (prefaulted) array
            assert np.shares_memory(imgs.x_stacks[0], bufs[cam])
    if p is not None:
        p.thread.join(5.0)
        # every frame handed over once; no array left behind (one asked for before the thread
        # made it is not made)
        assert not p.thread.is_alive() and p.ahead == 0 and not p.buffers
        assert {id(v) for v in p.state.values()} == {id(pf._TAKEN)}


def test_image_stack_copies_only_what_is_not_consecutive():
    cam = np.arange(6 * 3 * 4, dtype=np.uint16).reshape(6, 3, 4)
    images = list(cam[1:5])
    view = common_image_stack(images)
    assert np.shares_memory(view, cam) and view.__array_interface__["data"][0] == cam[1:].ctypes.data
    np.testing.assert_array_equal(view, cam[1:5], strict=True)
    for other in ([cam[1], cam[3], cam[2]], [cam[1], cam[2].copy(), cam[3]], [im.copy() for im in images]):
        out = common_image_stack(other)
        assert not np.shares_memory(out, cam) and not out.flags.writeable
        np.testing.assert_array_equal(out, np.stack(other), strict=True)
    mixed = common_image_stack([cam[0].astype(np.uint8), cam[1]])  # promoted: uint16 keeps both
    np.testing.assert_array_equal(mixed, cam[:2], strict=True)


@pytest.mark.parametrize("damage", ["truncated", "missing"])
def test_a_bad_file_gives_the_main_threads_message_and_stops_the_thread(tmp_path, two_cameras, damage):
    d = tmp_path / "set"
    shutil.copytree(two_cameras, d)
    m = load_manifest(d)  # the files exist when the manifest is read
    if damage == "truncated":
        (d / F6).write_bytes((d / F6).read_bytes()[:200])
    else:
        (d / F6).unlink()
    with pytest.raises(ImageSetError) as plain:
        load_camera_stacks(m, "left")
    pf.start_prefetch(d)
    p = pf._ACTIVE[pf._manifest_key(d)]
    with pytest.raises(ImageSetError) as fetched:
        load_camera_stacks(m, "left")
    assert str(fetched.value) == str(plain.value)
    assert "images[6] ('left_x_p1_s2.png')" in str(plain.value) and str(d / F6) in str(plain.value)
    assert "\n" not in str(plain.value)
    # stopped at the error: no thread decodes on, its frames are dropped
    assert pf._manifest_key(d) not in pf._ACTIVE and not p.thread.is_alive() and not p.state


def test_an_error_elsewhere_leaves_no_thread_and_no_hang(tmp_path, two_cameras):
    # the command fails before it reads an image (e.g. its setup): the process still exits at once
    code = ("import sys; from pmdsim.io.imageset_prefetch import start_prefetch; "
            f"start_prefetch({str(two_cameras)!r}); raise SystemExit('pmdsim: error: bad setup')")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 1 and r.stderr.strip() == "pmdsim: error: bad setup"


def test_frames_ahead_are_bounded(monkeypatch, two_cameras):
    monkeypatch.setattr(pf, "MAX_AHEAD_BYTES", 3 * 40 * 64)  # three 8-bit frames
    pf.start_prefetch(two_cameras)
    p = pf._ACTIVE[pf._manifest_key(two_cameras)]
    with p.cond:
        assert p.cond.wait_for(lambda: p.ahead >= pf.MAX_AHEAD_BYTES, timeout=10.0)
        ahead, decoded = p.ahead, sum(isinstance(v, np.ndarray) for v in p.state.values())
    p.thread.join(0.2)
    # it waits for the caller to take frames: no more decoded (one frame, the first camera's array)
    assert p.thread.is_alive() and p.ahead == ahead and decoded == 1 and len(p.buffers) == 1
    m = load_manifest(two_cameras)
    _check_stacks(load_camera_stacks(m, "left"), _pillow_stacks(two_cameras, "left"))
    _check_stacks(load_camera_stacks(m, "right"), _pillow_stacks(two_cameras, "right"))
    p.thread.join(5.0)
    assert not p.thread.is_alive()


def test_no_manifest_no_thread(tmp_path):
    pf.start_prefetch(tmp_path)  # no manifest.json: nothing started, nothing raised
    pf.start_prefetch(tmp_path / "nowhere")
    assert not pf._ACTIVE


def test_a_second_start_drops_the_first_ones_frames(tmp_path, two_cameras):
    d = tmp_path / "set"
    shutil.copytree(two_cameras, d)
    pf.start_prefetch(d)
    first = pf._ACTIVE[pf._manifest_key(d)]
    first.thread.join(5.0)  # every frame decoded, none taken (as for a camera no setup names)
    Image.fromarray(np.full((40, 64), 7, np.uint8)).save(d / F6)  # the file changes between two commands
    pf.start_prefetch(d)
    assert not first.state and not first.thread.is_alive()
    imgs = load_camera_stacks(load_manifest(d), "left")
    assert (imgs.x_stacks[1][2] == 7).all()
    _check_stacks(imgs, _pillow_stacks(d, "left"))
