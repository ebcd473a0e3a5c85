"""``pmdsim evaluate --stereo``: the stereo evaluation of an image set, disk to disk (issues 14, 25).

The job of :func:`pmdsim.studies.jobs.evaluate_image_set_stereo` (which calls
:func:`evaluate_image_set_stereo` here). The files are written while the later stages compute,
as the mono path does (:func:`pmdsim.studies.jobs.evaluate_image_set`): each camera's maps go to
``evaluation.h5`` in a background thread (:class:`pmdsim.io.hdf5.EvaluationFile`,
:func:`pmdsim.studies.evaluate_files.background_files`) as soon as its anchored integration ends —
while the other camera integrates, the agreement report and σ compute — and its height map PNG
in another; numpy's huge-page hint is off while the job runs
(:func:`pmdsim.studies.evaluate_memory.small_pages`), the decoder's modulation and offset maps are
dropped after decoding and the registrations' rays and screen points after σ
(:func:`pmdsim.studies.evaluate_memory.kept_for_files`). The file's layout and contents, the
messages and the errors are those of the serial job (write order of ``evaluation.h5``: every
camera's maps, then each camera's σ maps, the file attributes, the stereo report, the
consistency maps).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Sequence


from ..errors import ComputationError
from ..io import atomic_output_dir, provenance
from ..io.hdf5 import EvaluationFile, append_stereo_h5, write_consistency_h5
from ..io.imageset import load_manifest
from ..setup import Setup
from .map_png import write_height_map_png

__all__ = ["evaluate_image_set_stereo"]


def _start_warm_up(warm_up):
    """``warm_up`` (:func:`pmdsim.evaluation.stereo.warm_up`) started in a daemon thread, if
    numba's threading layer allows parallel kernels from two threads at once
    (:func:`~pmdsim.studies.evaluate_cameras.concurrent_cameras`); returns the thread or None."""
    from .evaluate_cameras import concurrent_cameras

    if not concurrent_cameras(2):
        return None

    def run():
        try:
            warm_up()
        except Exception:  # noqa: BLE001 (only a warm-up: the integration loads its kernels itself)
            pass

    thread = threading.Thread(target=run, name="pmdsim-stereo-warm-up", daemon=True)
    thread.start()
    return thread


def evaluate_image_set_stereo(image_dir: str | Path, setup: Setup, out_dir: str | Path, *,
                              screen_model: str | None = None, search_range_mm=None, noise_std=None, force: bool = False,
                              command: str | None = None, progress=None, inputs: Sequence[str | Path | None] = (),
                              min_valid_fraction: float | None = None, consistency: bool = True,
                              uncertainty: bool = True):
    """Stereo evaluation of an image set: :func:`pmdsim.studies.jobs.evaluate_image_set_stereo`
    (its parameters, outputs, summary and errors; ``min_valid_fraction`` None: its default);
    the files written while later stages compute (module docstring)."""
    from ..evaluation.integration import ReconstructionError
    from ..evaluation.stereo import DEFAULT_SEARCH_RANGE_MM, reconstruct_stereo, stereo_views, warm_up
    from . import uncertainty_job as uj
    from .evaluate_files import background_files
    from .evaluate_memory import KeptDecoding, kept_for_files, small_pages
    from .jobs import (DEFAULT_MIN_VALID_FRACTION, EvaluationSummary, JobInputError, _decode_checked, _camera_summary,
                       _image_files, _tick)

    if min_valid_fraction is None:
        min_valid_fraction = DEFAULT_MIN_VALID_FRACTION
    manifest = load_manifest(image_dir, screen_size_mm=setup.screen.size_mm)
    if screen_model is None:
        screen_model = manifest.instrument.screen_model or "planar"
    if screen_model not in ("planar", "setup"):
        raise JobInputError(f"screen model must be 'planar' or 'setup', got {screen_model!r}")
    unknown = [c for c in manifest.cameras if c not in setup.cameras]
    if unknown:
        raise JobInputError(f"camera(s) {unknown} of {image_dir}/manifest.json are not in the setup "
                            f"(setup cameras: {list(setup.cameras)})")
    if len(manifest.cameras) < 2:
        raise JobInputError(f"--stereo needs images of at least two cameras; {image_dir}/manifest.json has "
                            f"{list(manifest.cameras)}")
    if not 0.0 <= float(min_valid_fraction) <= 1.0:
        raise JobInputError(f"min_valid_fraction must be in [0, 1], got {min_valid_fraction!r}")
    search = DEFAULT_SEARCH_RANGE_MM if search_range_mm is None else tuple(search_range_mm)
    prov = provenance(command, setup.to_toml())
    t0 = time.perf_counter()
    warm = _start_warm_up(warm_up)  # the integration's kernels loaded while the images are decoded
    decoded = {}
    checks = {}
    with small_pages():  # 4 kB pages: huge ones cost ≈ 2.8 ms/MB of system time on first touch here
        for cam in manifest.cameras:
            dec, cons = _decode_checked(manifest, setup, cam, noise_std, image_dir, consistency)
            # what registration, σ, the files and the summary read: the modulation and offset maps go
            decoded[cam] = KeptDecoding(dec.screen_xy_mm, dec.valid, dec.flags, dec.std_xy_mm,
                                        getattr(dec, "reversed", None))
            del dec
            if cons is not None:
                checks[cam] = cons
            _tick(progress, f"decoded {cam}")
        try:
            views = stereo_views(setup, decoded, screen_model=None if screen_model == "planar" else setup.screen.surface)
        except ReconstructionError as e:
            raise ComputationError(f"stereo evaluation of {image_dir}: {e}") from None
        with atomic_output_dir(out_dir, force=force, inputs=[image_dir, *inputs], command=command) as tmp, \
                EvaluationFile(tmp / "evaluation.h5") as h5, background_files() as figures, \
                background_files() as h5_tasks:

            def camera_done(cam, rec):  # its maps and height figure while the others compute
                h5_tasks.submit(h5.add_camera, cam, decoded[cam], views[cam].registration, rec)
                p = rec.p_sample_mm
                figures.submit(write_height_map_png, p[..., 0], p[..., 1], rec.height_mm * 1e3,
                               title=f"{cam}: absolute height in the sample frame (stereo, {screen_model} screen model)",
                               label="height (µm)", path=tmp / f"height_{cam}.png")

            if warm is not None:
                warm.join()
            try:
                st = reconstruct_stereo(views, search_range_mm=search, on_reconstruction=camera_done)
            except ReconstructionError as e:
                raise ComputationError(f"stereo evaluation of {image_dir}: {e}") from None
            st, uncs, u_warn = uj.stereo_uncertainty(setup, views, decoded, st, screen=screen_model,
                                                     enabled=uncertainty)
            # the view rays and screen points (110 MB per 1920 × 1200 camera) are released: only the files'
            results = {cam: kept_for_files(decoded[cam], views[cam].registration, st.cameras[cam].reconstruction)
                       for cam in decoded}
            views = decoded = None
            figures.submit(uj.stereo_figures, tmp, results, uncs)
            for cam in results:
                h5_tasks.submit(h5.add_extras, cam, uj.uncertainty_datasets(uncs.get(cam)) or {})
            h5_tasks.submit(h5.finish, {**prov, "method": "stereo", "screen_model": screen_model,
                                        "image_dir": str(image_dir), "uncertainty": uj.stereo_attribute(uncs, uncertainty)})
            h5_tasks.submit(append_stereo_h5, tmp / "evaluation.h5", st,
                            {"search_range_mm": list(st.search_range_mm), "search_step_mm": st.search_step_mm,
                             "stride_px": st.stride_px})
            if checks:
                h5_tasks.submit(write_consistency_h5, tmp / "evaluation.h5", checks,
                                {cam: _image_files(manifest, cam, c.images) for cam, c in checks.items()})
            summary = st.summary()
    cams = {cam: _camera_summary(cam, dec, rec, checks.get(cam), manifest, uncs.get(cam), stereo=summary[cam])
            for cam, (dec, _, rec) in results.items()}
    return EvaluationSummary(cams, time.perf_counter() - t0, warnings=tuple(u_warn),
                             response=manifest.instrument.response_info, min_valid_fraction=float(min_valid_fraction))
