"""An image set's files decoded in a background thread while ``pmdsim evaluate`` imports (issue 25).

``pmdsim evaluate`` spends its first seconds importing its modules and loading compiled numba
kernels; the image set's 48 PNGs (0.53 s of Pillow decoding at 1920×1200) had to wait for them.
:func:`start_prefetch` — the first call of the command — starts one daemon thread that reads the
manifest's image entries (a bare JSON read: validating the manifest is
:func:`~pmdsim.io.imageset.load_manifest`'s, in the main thread) and decodes the files in manifest
order with :func:`~pmdsim.io.images.read_frame`; Pillow releases the GIL while it inflates, so this
overlaps the imports. After a camera's first frame it also allocates that camera's (N, H, W)
array and touches its pages (:func:`prefaulted`). :func:`~pmdsim.io.imageset.load_camera_stacks`
then takes each decoded frame (:func:`take`) and copies it into that array.

Nothing about errors changes: a file the thread cannot read (missing, truncated, wrong kind) is
only marked; :func:`take` returns None for it, and the main thread reads it itself at the point
it is needed — the same call, the same one-line message naming the manifest entry and the file.
A frame the thread has not started is read by the main thread too (it never waits for one), so
no order of calls can deadlock. The thread keeps at most :data:`MAX_AHEAD_BYTES` of decoded,
not yet taken frames and arrays (frames of a camera no one loads stay until exit), stops when the set is
read, when :func:`stop_prefetch` is called (on an image error) and at interpreter exit (an
``atexit`` handler joins it).
"""

from __future__ import annotations

import atexit
import json
import os
import threading
from pathlib import Path

__all__ = ["MAX_AHEAD_BYTES", "start_prefetch", "take", "prefaulted", "stop_prefetch"]

#: Decoded frames and prefaulted arrays not yet taken, at most (bytes): 2 cameras × 24 8-bit
#: 1920×1200 frames are 111 MB, and their arrays as much.
MAX_AHEAD_BYTES = 256 * 2**20

_PENDING = object()  # listed, not started
_RUNNING = object()  # being decoded by the thread
_TAKEN = object()  # handed over, or claimed by the main thread
_FAILED = object()  # the thread could not read it: the main thread reads it again (and raises)

_ACTIVE: dict[str, "_Prefetch"] = {}
_REGISTRY_LOCK = threading.Lock()


def _manifest_key(path_or_dir) -> str:
    p = Path(path_or_dir)
    return os.path.realpath(p / "manifest.json" if p.is_dir() else p)


def _frame_key(path, page) -> tuple[str, int | None]:
    return os.path.realpath(path), page


class _Prefetch:
    """The background decoding of one image set (module docstring)."""

    def __init__(self, manifest_path: str):
        self.manifest_path = manifest_path
        self.cond = threading.Condition()
        self.state: dict[tuple[str, int | None], object] = {}
        self.listed = False  # the manifest was read (or could not be: nothing prefetched)
        self.stopped = False
        self.ahead = 0  # bytes of decoded frames and arrays not taken
        self.per_camera: dict = {}  # frames per camera name (the thread's, from the manifest)
        self.buffers: dict = {}  # camera → its (N, H, W) array, pages touched (prefaulted)
        self.claimed: set = set()  # cameras whose array the caller asked for: none made after
        self.thread = threading.Thread(target=self._run, name="pmdsim-image-prefetch", daemon=True)

    def _keys(self) -> list[tuple[str, int | None]]:
        with open(self.manifest_path, encoding="utf-8") as f:
            doc = json.load(f)
        directory = os.path.dirname(self.manifest_path)
        keys = {}
        for e in doc["images"]:
            file, page = e.get("file"), e.get("page")
            if isinstance(file, str) and file.strip() and (page is None or type(page) is int):
                keys.setdefault(_frame_key(os.path.join(directory, file), page), e.get("camera"))
        self.per_camera = {c: list(keys.values()).count(c) for c in set(keys.values())}
        return list(keys.items())

    def _run(self) -> None:
        try:
            keys = self._keys()
        except Exception:  # an unreadable manifest: load_manifest says what is wrong
            keys = []
        with self.cond:
            for k, _ in keys:
                self.state.setdefault(k, _PENDING)
            self.listed = True
            self.cond.notify_all()
        if not keys:
            return
        from .images import read_frame  # numpy and Pillow: imported here, in the thread

        for key, camera in keys:
            with self.cond:
                self.cond.wait_for(lambda: self.stopped or self.ahead < MAX_AHEAD_BYTES)
                if self.stopped:
                    return
                if self.state.get(key) is not _PENDING:
                    continue
                self.state[key] = _RUNNING
            try:
                frame = read_frame(Path(key[0]), key[1], writable=False)
            except Exception:
                frame = _FAILED
            with self.cond:
                if self.stopped:  # stopped while decoding: the frame is dropped
                    return
                if frame is not _FAILED:
                    self.ahead += frame.nbytes
                self.state[key] = frame
                self.cond.notify_all()
            n = self.per_camera.pop(camera, None) if frame is not _FAILED else None
            if n is not None:
                try:
                    self._prefault(camera, n, frame)
                except MemoryError:  # the caller allocates its own array
                    pass

    def _prefault(self, camera, n: int, frame) -> None:
        """A camera's (n, H, W) array for :func:`prefaulted`, its pages touched here (a first
        write faults each 4 kB page in: 27 000 faults for 24 8-bit 1920×1200 frames)."""
        import numpy as np

        with self.cond:
            if self.stopped or camera in self.claimed:
                return
        buf = np.empty((n,) + frame.shape, frame.dtype)
        buf.fill(0)
        with self.cond:
            if self.stopped or camera in self.claimed:  # asked for meanwhile: the caller made its own
                return
            self.buffers[camera] = buf
            self.ahead += buf.nbytes
            self.cond.notify_all()

    def take(self, path, page):
        key = _frame_key(path, page)
        with self.cond:
            self.cond.wait_for(lambda: self.listed)
            while self.state.get(key) is _RUNNING:
                self.cond.wait()
            frame = self.state.get(key)
            if frame is None:
                return None
            self.state[key] = _TAKEN
            if frame is _PENDING or frame is _TAKEN or frame is _FAILED:
                return None
            self.ahead -= frame.nbytes
            self.cond.notify_all()
            return frame

    def prefaulted(self, camera, shape, dtype):
        with self.cond:
            self.claimed.add(camera)
            buf = self.buffers.pop(camera, None)
            if buf is None:
                return None
            self.ahead -= buf.nbytes
            self.cond.notify_all()
        return buf if buf.shape == tuple(shape) and buf.dtype == dtype else None

    def stop(self) -> None:
        with self.cond:
            self.stopped = True
            self.listed = True
            self.state.clear()  # the decoded frames are dropped
            self.buffers.clear()
            self.ahead = 0
            self.cond.notify_all()


def start_prefetch(image_dir) -> None:
    """Start decoding the image files of the image set ``image_dir`` (its directory or manifest)
    in a background thread (one already started for it is stopped and its frames dropped: the
    files may have changed since); a no-op if the path names no manifest file.
    Never raises: every problem is reported by the main thread's own reading."""
    try:
        key = _manifest_key(image_dir)
        if not os.path.isfile(key):
            return
    except (OSError, TypeError, ValueError):
        return
    with _REGISTRY_LOCK:
        old = _ACTIVE.pop(key, None)
        pf = _ACTIVE[key] = _Prefetch(key)
    if old is not None:  # an earlier command's (in this process): its frames may be stale
        old.stop()
        old.thread.join()
    try:
        pf.thread.start()
    except RuntimeError:  # no thread to be had: the images are read in the main thread
        with _REGISTRY_LOCK:
            _ACTIVE.pop(key, None)


def take(manifest_path, path, page):
    """The decoded frame of ``path`` (``page``) of the image set of ``manifest_path`` if its
    prefetch decoded it: a read-only (H, W) array as :func:`~pmdsim.io.images.read_frame`
    returns, handed over once; else None (not prefetched, not started, or unreadable: the
    caller reads the file itself). Waits only for a frame being decoded."""
    if not _ACTIVE:
        return None
    pf = _ACTIVE.get(_manifest_key(manifest_path))
    return None if pf is None else pf.take(path, page)


def prefaulted(manifest_path, camera: str, shape, dtype):
    """An uninitialised array of ``shape`` (N, H, W) and ``dtype`` for ``camera``'s frames whose
    memory pages the prefetch of ``manifest_path`` has already faulted in (N the camera's frames
    in the manifest, H, W and dtype its first frame's), handed over once; else a new ``np.empty``
    array (and the thread makes none for the camera after this call). Filling it is then a plain
    copy (:func:`pmdsim.io.imageset.load_camera_stacks`)."""
    import numpy as np

    pf = _ACTIVE.get(_manifest_key(manifest_path)) if _ACTIVE else None
    buf = None if pf is None else pf.prefaulted(camera, shape, dtype)
    return np.empty(shape, dtype) if buf is None else buf


def stop_prefetch(manifest_path=None) -> None:
    """Stop the prefetch of ``manifest_path`` (None: all), drop its frames and join its thread."""
    with _REGISTRY_LOCK:
        keys = list(_ACTIVE) if manifest_path is None else [_manifest_key(manifest_path)]
        stopping = [_ACTIVE.pop(k) for k in keys if k in _ACTIVE]
    for pf in stopping:
        pf.stop()
        if pf.thread.is_alive() and pf.thread is not threading.current_thread():
            pf.thread.join()


atexit.register(stop_prefetch)
