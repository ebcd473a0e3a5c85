"""The cameras of ``pmdsim evaluate``, two at a time (issue 25, item 1).

Each camera is independent from reading its images to its σ (:func:`evaluate_camera`: decode,
consistency checks, registration, reconstruction, uncertainty); only the surface fit and the
files join them. Much of a camera's work runs on one thread (the stepwise integration, Python
glue, PNG reads), so :func:`camera_results` runs the cameras' pipelines in two threads and hands
their results back **in camera order**: the caller prints progress, collects warnings, submits
figures and raises errors exactly as when the cameras run one after the other — the same
messages in the same order, the error of the first failing camera (in camera order) as the same
one line. Each pipeline's warnings are its own; the join adds them to the run's in camera order
(:class:`CameraResult`), and the "likely cause" of a failed reconstruction is composed at the
join from every warning before it, as the serial loop did.

Two numba parallel regions may run at once only with a thread-safe threading layer (``omp``,
``tbb``); with numba's ``workqueue`` (no OpenMP, no TBB) concurrent launches abort the
process, so the cameras then run one after the other (:func:`concurrent_cameras`).
"""

from __future__ import annotations

import contextlib
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, ContextManager, Iterator, Sequence

from ..errors import InputError, PmdsimError

__all__ = ["CameraResult", "CameraCancelled", "evaluate_camera", "camera_results", "concurrent_cameras",
           "THREAD_SAFE_LAYERS", "CAMERA_THREADS_ENV", "CAMERA_OVERLAP_ENV", "SIGMA_STAGE_ENV", "STAGES",
           "sigma_stage"]

#: numba threading layers that allow parallel regions launched from two threads at once.
THREAD_SAFE_LAYERS = ("omp", "tbb")
#: Environment variable: ``1`` runs the cameras one after the other (for A/B measurements and
#: machines where overlapping does not pay); unset or ``2``: two at a time where safe.
CAMERA_THREADS_ENV = "PMDSIM_CAMERA_THREADS"
#: Environment variable: ``stages`` (default) lets two cameras overlap only in different stages
#: (:data:`STAGES`: one camera decodes while the other reconstructs, …), ``full`` without that
#: rule (measured: more memory, two cameras' largest working sets at once).
CAMERA_OVERLAP_ENV = "PMDSIM_CAMERA_OVERLAP"
#: Environment variable: the stage the least-squares σ is gated with (:func:`sigma_stage`):
#: ``reconstruct`` (default; the peak memory of two cameras' largest working sets at once is
#: avoided) or ``sigma`` (its own stage, as the stepwise σ; for A/B measurements).
SIGMA_STAGE_ENV = "PMDSIM_LSQ_SIGMA_STAGE"
#: The stages of :func:`evaluate_camera`, each entered by one camera at a time when overlapped
#: by stage: reading + decoding + checks, registration + reconstruction, σ.
STAGES = ("decode", "reconstruct", "sigma")


def _env_choice(name: str, allowed: tuple[str, ...]) -> str:
    """The value of environment variable ``name`` (stripped; unset or empty: ``allowed[0]``).

    Raises
    ------
    InputError
        A value not in ``allowed`` (a typo would otherwise silently run the default)."""
    value = os.environ.get(name, "").strip()
    if value == "":
        return allowed[0]
    if value not in allowed:
        raise InputError(f"environment variable {name}={value!r}: expected one of {', '.join(allowed)} "
                         f"(unset: {allowed[0]})")
    return value


class CameraCancelled(Exception):
    """A camera's pipeline stopped early because an earlier camera failed (never surfaces)."""


@dataclass
class CameraResult:
    """One camera's evaluation: what the join needs, in the serial loop's terms.

    ``warnings`` the camera's own warnings in the serial order (orientation, coverage, σ);
    ``failure`` the reconstruction's error with the camera's warnings before it and its coverage
    warnings (the join composes the message); ``kept`` the ``(decoded, reg, rec)`` of
    :func:`pmdsim.studies.evaluate_memory.kept_for_files`; ``unc`` the σ (or None)."""

    cam: str
    cons: object = None
    warnings: list = field(default_factory=list)
    failure: tuple | None = None  # (exception, warnings before it, coverage warnings)
    kept: tuple | None = None
    anchor: dict | None = None
    relative: bool = False
    unc: object = None


def evaluate_camera(setup, cam: str, *, manifest, noise_std, image_dir, run_checks: bool, model_surface, anchor,
                    method: str, uncertainty: bool, anchor_std_mm, stop: threading.Event | None = None,
                    stage: Callable[[str], ContextManager] | None = None) -> CameraResult:
    """Decode, check, register, reconstruct and (with ``uncertainty``) σ one camera of an image
    set: the body of :func:`pmdsim.studies.jobs.evaluate_image_set`'s loop over the cameras.

    Raises what the serial loop raised before the reconstruction (``ConsistencyFailure``, an
    image that cannot be read, …); the reconstruction's :class:`~pmdsim.errors.PmdsimError` is
    returned in ``failure`` instead (its message takes the warnings of every camera before it).
    ``stop`` set (another camera failed): :class:`CameraCancelled` at the next stage; ``stage(name)``
    (a context manager, :data:`STAGES`) is entered around each stage."""
    from . import uncertainty_job as uj
    from .evaluate_memory import kept_for_files
    from .jobs import _decode_checked

    def check_stop():
        if stop is not None and stop.is_set():
            raise CameraCancelled(cam)

    stage = stage or (lambda name: contextlib.nullcontext())
    out = CameraResult(cam)
    with stage("decode"):
        check_stop()
        decoded, out.cons = _decode_checked(manifest, setup, cam, noise_std, image_dir, run_checks)
    with stage("reconstruct"):
        check_stop()
        rec, reg, cam_anchor = _reconstruct(setup, cam, decoded, out, model_surface=model_surface, anchor=anchor,
                                            method=method)
    if rec is None:  # out.failure
        return out
    decoded = kept_for_files(decoded, reg, rec)[0]  # σ reads the coordinates and their σ: release the rest
    if uncertainty:
        with stage(sigma_stage(method)):
            check_stop()
            out.unc, w = uj.camera_uncertainty(setup, cam, decoded, reg, rec, method=method,
                                               screen_model=model_surface, anchor=cam_anchor,
                                               anchor_std=uj.anchor_std_mm(cam_anchor, anchor_std_mm))
        out.warnings += w
    out.kept = kept_for_files(decoded, reg, rec)  # release the rest now
    return out


def sigma_stage(method: str) -> str:
    """The stage (:data:`STAGES`) of a camera's σ: on the least-squares path the σ shares the
    reconstruction's stage, so that one camera's σ never overlaps the other camera's
    reconstruction (:data:`SIGMA_STAGE_ENV`); measured: docs/benchmarks.md, lsq26."""
    if method == "least_squares" and _env_choice(SIGMA_STAGE_ENV, ("reconstruct", "sigma")) == "reconstruct":
        return "reconstruct"
    return "sigma"


def _reconstruct(setup, cam: str, decoded, out: CameraResult, *, model_surface, anchor, method: str):
    """Registration, plausibility checks and the anchored reconstruction of one camera: returns
    ``(reconstruction, registration, the camera's anchor)``, or ``(None, …)`` with ``out.failure``
    set; the warnings go to ``out``, the anchor to ``out.anchor`` / ``out.relative``."""
    from ..evaluation.anchor import HeightAnchor, default_seed_pixel, reconstruct_anchored, register_model
    from ..evaluation.plausibility import check_orientation, check_screen_coverage
    from .jobs import JobInputError

    out.warnings += check_orientation(setup, cam, decoded.screen_xy_mm, decoded.valid)
    reg = register_model(setup, cam, decoded, screen_model=model_surface)
    bounds = (model_surface.bounds_mm if model_surface is not None else
              (setup.screen.grid_x_mm[0], setup.screen.grid_x_mm[-1], setup.screen.grid_y_mm[0],
               setup.screen.grid_y_mm[-1]))
    coverage = check_screen_coverage(decoded.valid, reg.status, decoded.screen_xy_mm, bounds, cam)
    out.warnings += coverage
    cam_anchor = anchor
    if isinstance(anchor, tuple):  # a seed height without a pixel: the default seed pixel
        px = default_seed_pixel(reg.valid) if reg.valid.any() else (0, 0)
        cam_anchor = HeightAnchor((float(px[0]), float(px[1])), anchor[1])
    try:
        if not reg.valid.any():
            raise JobInputError(f"camera {cam!r}: no pixel was decoded and registered; nothing to reconstruct")
        ar = reconstruct_anchored(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, anchor=cam_anchor,
                                  T_world_ref=setup.sample.T_world_sample, method=method)
    except PmdsimError as exc:
        out.failure = (exc, list(out.warnings), coverage)
        return None, reg, cam_anchor
    out.anchor, out.relative = ar.anchor, ar.relative
    return ar.reconstruction, reg, cam_anchor


def concurrent_cameras(n_cameras: int) -> bool:
    """Whether :func:`camera_results` runs two cameras at once: more than one camera, not turned
    off (:data:`CAMERA_THREADS_ENV` = 1) and numba's threading layer thread-safe
    (:data:`THREAD_SAFE_LAYERS`; the layer is loaded here if no parallel kernel ran yet). Any
    other layer, or one that cannot be loaded: False (serial, never an abort)."""
    if _env_choice(CAMERA_THREADS_ENV, ("2", "1")) == "1" or n_cameras < 2:
        return False
    try:
        import numba
        from numba.np.ufunc import parallel

        parallel._launch_threads()  # idempotent: the layer the first parallel kernel would load
        return numba.threading_layer() in THREAD_SAFE_LAYERS
    except Exception:  # an internal that moved, no layer available: serial is always safe
        return False


def camera_results(cameras: Sequence[str], work: Callable[..., CameraResult], *,
                   concurrent: bool | None = None) -> Iterator[CameraResult]:
    """``work(cam, stop=event, stage=gate)`` for every camera, the results yielded in camera order.

    ``concurrent`` (default :func:`concurrent_cameras`): two cameras at a time in a pool of two
    threads, each next camera started when one finishes; else one after the other in the
    calling thread. Overlapped by stage (:data:`CAMERA_OVERLAP_ENV`), ``gate(name)`` lets one
    camera at a time into each of :data:`STAGES` (the cameras then run as a pipeline, in camera
    order); else it does nothing. An exception of a camera is raised when its turn comes (the results of the
    cameras before it yielded first, as in a serial loop); the cameras after it are told to stop
    (``stop``) and waited for, so that nothing runs once the caller handles the error. The same
    on an exception in the caller's loop body (the generator is closed)."""
    if concurrent is None:
        concurrent = concurrent_cameras(len(cameras))
    stop = threading.Event()
    if not concurrent:
        for cam in cameras:
            yield work(cam, stop=stop, stage=lambda name: contextlib.nullcontext())
        return
    gate = _Gates(full=_env_choice(CAMERA_OVERLAP_ENV, ("stages", "full")) == "full")
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="pmdsim-camera")
    try:
        futures: list[Future] = []
        for cam in cameras:
            futures.append(pool.submit(work, cam, stop=stop, stage=gate))
            gate.wait_entered(futures[-1])  # the next camera starts once this one holds the first stage
        for f in futures:
            yield f.result()
    finally:
        stop.set()  # no-op when every camera finished
        pool.shutdown(wait=True, cancel_futures=True)


class _Gates:
    """``gate(name)``: one camera at a time in each of :data:`STAGES` (``full``: no rule), and
    :meth:`wait_entered` so that the cameras enter the first stage in camera order."""

    def __init__(self, full: bool = False):
        self._locks = None if full else {name: threading.Lock() for name in STAGES}
        self._entered = threading.Event()

    @contextlib.contextmanager
    def __call__(self, name: str):
        if self._locks is None:
            self._entered.set()
            yield
            return
        with self._locks[name]:
            self._entered.set()
            yield

    def wait_entered(self, future: Future) -> None:
        """Until the camera of ``future`` entered a stage (or ended without one); then re-arm."""
        while not self._entered.wait(0.005) and not future.done():
            pass
        self._entered.clear()
