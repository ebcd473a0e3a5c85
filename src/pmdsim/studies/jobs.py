"""One measurement, disk to disk: simulate an image set, evaluate one, calibrate from several.

These are what ``pmdsim simulate``, ``pmdsim evaluate`` and ``pmdsim calibrate`` run; the CLI
only parses its options, calls one of them and prints the returned summary. Every function
writes atomically (:func:`pmdsim.io.atomic_output_dir`, :func:`pmdsim.io.atomic_file`) and
records the pmdsim version and the producing command (``command``).

``progress``, where accepted, is called with a short message after each step; ``n_steps``
functions say how many calls to expect (for a progress bar).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from .. import interrupts
from ..errors import ComputationError, PmdsimError
from ..evaluation.phase import PhaseFlag
from ..io import (
    IMAGESET_FORMAT,
    MANIFEST_NAME,
    MAPPING_NAME,
    atomic_file,
    atomic_output_dir,
    provenance,
    write_json,
    write_mapping_h5,
    write_png,
)
from ..io.hdf5 import EvaluationFile, write_consistency_h5
from ..io.imageset import decode_camera_images, load_camera_stacks, load_manifest
from ..io.imageset_instrument import apply_mask_and_map, consistency_stacks
from ..evaluation.consistency import check_consistency, nominal_screen_xy, with_consistency
from .checks import check_memory
from ..setup import Setup
from .map_png import warm_up, write_height_map_png
from .uncertainty_job import uncertainty_line
from .report import json_ready

if TYPE_CHECKING:  # the calibration and the simulation are imported where used: not on evaluate's path (start-up)
    from ..calibration import CalibrationResult

__all__ = ["JobInputError", "simulation_steps", "simulate_to_dir", "evaluate_image_set", "evaluate_image_set_stereo",
           "calibrate_image_sets", "CalibrationNotConverged", "ConsistencyFailure", "check_image_sizes",
           "DEFAULT_MIN_VALID_FRACTION"]

Progress = Callable[[str], None]


class JobInputError(PmdsimError, ValueError):
    """The inputs of a job do not fit together (e.g. a camera of the images is not in the setup)."""


class CalibrationNotConverged(ComputationError):
    """The calibration did not converge; nothing was written."""


def _tick(progress: Progress | None, msg: str) -> None:
    interrupts.check()  # an interrupt Python swallowed (in a finaliser) aborts here
    if progress is not None:
        progress(msg)


# ============================================================================ simulate
def simulation_steps(setup: Setup) -> int:
    """Number of progress calls of :func:`simulate_to_dir`: one per traced camera and image."""
    from ..simulation.render import image_specs

    return sum(1 + len(image_specs(setup, c)) for c in setup.cameras)


@dataclass(frozen=True)
class SimulationSummary:
    """What :func:`simulate_to_dir` wrote: image count, valid pixels per camera, seconds."""

    n_images: int
    valid_pixels: dict[str, tuple[int, int]]  # camera → (valid, total)
    seconds: float

    def as_text(self, out_dir) -> str:
        valid = ", ".join(f"{c}: {v}/{n} valid pixels" for c, (v, n) in self.valid_pixels.items())
        return (f"wrote {self.n_images} images, {MANIFEST_NAME} and {MAPPING_NAME} to {out_dir} in "
                f"{self.seconds:.1f} s ({valid})")


def simulate_to_dir(setup: Setup, out_dir: str | Path, *, force: bool = False, command: str | None = None,
                    calibration_pose: int | None = None, progress: Progress | None = None,
                    inputs: Sequence[str | Path | None] = ()) -> SimulationSummary:
    """Simulate a measurement (paper §2) and write it as an image set.

    Writes into ``out_dir``: ``{camera}_{direction}_p{i}_s{k}.png`` fringe images, ``manifest.json``
    (provenance, the setup as TOML, one entry per image) and ``mapping.h5`` (per camera
    ``screen_xy_mm`` (H, W, 2), ``valid`` and ``status``). ``calibration_pose`` K images the
    calibration mirror in pose K (noise stream K + 1, as the in-memory experiments use) instead
    of the sample. ``inputs`` (e.g. the setup file) must not be replaced by ``out_dir``
    (:func:`pmdsim.io.outputs.atomic_output_dir`).
    """
    from ..setup.sensor import SensorModel
    from ..simulation.imaging import needs_points
    from ..simulation.render import render_images, trace_setup_camera

    if calibration_pose is not None:
        setup = setup.with_mirror_pose(calibration_pose)
    check_memory(setup, "simulate")
    prov = provenance(command, setup.to_toml())
    t0 = time.perf_counter()
    with atomic_output_dir(out_dir, force=force, inputs=inputs, command=command) as tmp:
        mappings = {}
        entries = []
        pool = ThreadPoolExecutor(max_workers=2)
        try:
            for cam in setup.cameras:
                m = trace_setup_camera(setup, cam, store_points=needs_points(setup))
                mappings[cam] = m
                _tick(progress, f"traced {cam}")
                futures = []
                stream = None if calibration_pose is None else calibration_pose + 1
                for spec, img in render_images(setup, cam, m, stream=stream):
                    futures.append(pool.submit(write_png, tmp / spec.file, img))
                    entries.append(spec.as_manifest_entry())
                for f in futures:
                    f.result()
                    _tick(progress, "image written")
        finally:  # on an interrupt: drop the queued writes instead of finishing them
            pool.shutdown(wait=True, cancel_futures=True)
        write_mapping_h5(tmp / MAPPING_NAME, mappings, dict(prov))
        sx, sy = setup.screen.size_mm
        manifest = {
            "format": IMAGESET_FORMAT,
            "format_version": 1,
            **prov,
            "bit_depth": 8 if SensorModel.from_setup(setup).bit_depth == 8 else 16,  # the files' depth
            "screen_size_mm": [sx, sy],
            "cameras": {c: {"image_size_px": [cs.camera.width_px, cs.camera.height_px],
                            "status_counts": mappings[c].status_counts()} for c, cs in setup.cameras.items()},
            "images": entries,
        }
        write_json(tmp / MANIFEST_NAME, manifest)
    return SimulationSummary(len(entries), {c: (int(m.valid.sum()), int(m.valid.size)) for c, m in mappings.items()},
                             time.perf_counter() - t0)


# ============================================================================ evaluate
#: Default ``min_valid_fraction`` of :func:`evaluate_image_set`: below this fraction of the pixels
#: that see fringes being reconstructed, the evaluation fails (exit 1 in the CLI).
DEFAULT_MIN_VALID_FRACTION = 0.5
#: Below this fraction (or with more than :data:`WARN_FLAGGED_FRACTION` of the pixels flagged by the
#: consistency checks) the evaluation warns.
WARN_VALID_FRACTION = 0.9
WARN_FLAGGED_FRACTION = 0.001


@dataclass(frozen=True)
class EvaluationSummary:
    """Per camera: decoded, reconstructed pixels, height range (µm), convergence, the pixels that
    see fringes (``usable``), consistency flag counts and reasons; seconds; the anchor (or that
    heights are relative), the surface fit and the plausibility warnings (``warnings``; the data
    warnings of the consistency checks: :meth:`data_warnings`)."""

    cameras: dict[str, dict]
    seconds: float
    surface_fit: dict | None = None
    warnings: tuple[str, ...] = ()
    response: dict | None = None
    min_valid_fraction: float = DEFAULT_MIN_VALID_FRACTION
    notes: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        out = []
        if self.response:
            r = self.response
            what = (f"gamma {r['gamma']:g}" if r.get("kind") == "gamma" else
                    f"a {r.get('n_levels')}-level grey series{' from ' + r['file'] if r.get('file') else ''}")
            out.append(f"images linearised with the declared response ({what}, {r.get('interpolation')} "
                       f"interpolation) before decoding")
        for cam, c in self.cameras.items():
            rng = (f"height {c['height_min_um']:.3f} … {c['height_max_um']:.3f} µm (sample frame)"
                   if c["reconstructed"] else "no height")
            out.append(f"{cam}: {c['decoded']}/{c['pixels']} pixels decoded, {c['reconstructed']} reconstructed; "
                       f"{rng}, {'converged' if c['converged'] else 'NOT converged'}")
            a = c.get("anchor")
            if a is not None:
                if a["kind"] == "none":
                    out.append(f"{cam}: heights are RELATIVE (no anchor): seeded at pixel {tuple(a['seed_pixel_vu'])} "
                               f"with height 0; give an anchor (a known point or a measured distance) for absolute "
                               f"heights and slopes")
                elif a["kind"] == "distance":
                    out.append(f"{cam}: anchored: the surface at pixel ({a['pixel_vu'][0]:.2f}, {a['pixel_vu'][1]:.2f}) "
                               f"is {a['distance_mm']:g} mm from {a['point_world_mm']} (world)")
                else:
                    out.append(f"{cam}: anchored: height {a['height_mm']:g} mm at pixel "
                               f"({a['pixel_vu'][0]:.2f}, {a['pixel_vu'][1]:.2f})")
            if "height_std_rms_um" in c:
                out.append(uncertainty_line(cam, c))
            if "stereo" in c:  # evaluate_image_set_stereo
                st = c["stereo"]
                out.append(f"{cam}: stereo: {st['anchors']} anchors of {st['searched']} searched pixels, overlap "
                           f"{st['overlap']} pixels; normal disagreement median "
                           f"{st['normal_disagreement_median_urad']:.3g} µrad (max {st['normal_disagreement_max_urad']:.3g}), "
                           f"height discrepancy median {st['height_discrepancy_median_um']:.3g} µm "
                           f"(max {st['height_discrepancy_max_um']:.3g})")
        if self.surface_fit:
            f = self.surface_fit

            def fmt(v, spec):
                return "∞ (flat)" if v is None else format(v, spec)

            out.append(f"paraboloid over the slopes: focal length x {fmt(f['focal_length_x_mm'], '.6g')} mm, "
                       f"y {fmt(f['focal_length_y_mm'], '.6g')} mm; slope residual RMS "
                       f"{fmt(f['slope_residual_rms_mrad'], '.4g')} mrad")
        out += list(self.notes)
        return out

    def data_warnings(self) -> list[str]:
        """One line per camera whose data look wrong (few valid pixels, consistency flags)."""
        out = []
        for cam, c in self.cameras.items():
            if "valid_fraction" not in c:  # a stereo summary: its report is in lines()
                continue
            flagged = sum(c.get("consistency_counts", {}).values())
            if c["valid_fraction"] < WARN_VALID_FRACTION or flagged > max(10, WARN_FLAGGED_FRACTION * c["usable"]):
                why = "; ".join(c.get("reasons", [])[:3]) or "see phase_flags in evaluation.h5"
                out.append(f"{cam}: {c['reconstructed']} of {c['usable']} pixels that see fringes reconstructed "
                           f"({c['valid_fraction']:.1%}); {why}")
        return out

    def failures(self) -> list[str]:
        """One line per camera whose valid fraction is below ``min_valid_fraction``."""
        return [f"{cam}: only {c['valid_fraction']:.1%} of the {c['usable']} pixels that see fringes were "
                f"reconstructed (minimum {self.min_valid_fraction:.0%}); "
                + ("; ".join(c.get("reasons", [])[:2]) or "see phase_flags in evaluation.h5")
                for cam, c in self.cameras.items()
                if "valid_fraction" in c and not c["valid_fraction"] >= self.min_valid_fraction]


def check_image_sizes(manifest, setup: Setup, where: str = "the setup") -> None:
    """Refuse an image set whose images differ in size from the setup's cameras (before any work).

    The size is the manifest's ``cameras.<name>.image_size_px`` if given, else read from the
    header of the camera's first image (nothing else is loaded).

    Raises
    ------
    JobInputError
        One line naming both sizes.
    """
    for cam in manifest.cameras:
        if cam not in setup.cameras:
            continue
        c = setup.cameras[cam].camera
        want = (c.width_px, c.height_px)
        got = manifest.image_size_px.get(cam)
        src = f"{manifest.path}: cameras.{cam}.image_size_px"
        if got is None:
            first = manifest.layout[cam]["x"][0].entries[0]
            got = _image_size_px(first.path)
            src = f"{first.path}"
        if tuple(got) != want:
            raise JobInputError(f"images of camera {cam!r} are {got[0]}×{got[1]} px (W×H, {src}) but {where}'s camera "
                                f"{cam!r} is {want[0]}×{want[1]} px (image_size_px); give the setup of these images "
                                f"with --setup")


def _image_size_px(path: Path) -> tuple[int, int]:
    """(W, H) from an image file's header (PNG/TIFF; the pixels are not decoded)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception as e:  # PIL raises several types for broken files
        raise JobInputError(f"cannot read image {str(path)!r}: {e}") from None


def _resolve_anchor(manifest, seed_pixel, seed_height_mm, anchor):
    """The anchor of an evaluation: explicit > seed options > the manifest's > none."""
    from ..evaluation.anchor import HeightAnchor, anchor_from_dict

    if anchor is not None:
        return anchor
    if seed_pixel is not None:
        return HeightAnchor((float(seed_pixel[0]), float(seed_pixel[1])),
                            0.0 if seed_height_mm is None else float(seed_height_mm))
    if seed_height_mm is not None:
        return ("default-pixel", float(seed_height_mm))
    if manifest.instrument.anchor is not None:
        return anchor_from_dict(manifest.instrument.anchor, source=f"{manifest.path}: key 'anchor'")
    return None


def _expected_screen_xy(setup: Setup, cam: str) -> np.ndarray:
    """The screen coordinates (H, W, 2) the setup predicts for ``cam``: the reference of the
    consistency checks' orientation test. For a flat sample the nominal plane's mapping
    (:func:`nominal_screen_xy`, closed form); for a curved one (a shape, a height map, non-zero
    heights) the mapping traced through the setup's own sample, so that a concave sample that
    legitimately inverts the image (seen beyond its focal distance) is not read as a reversed
    shift order, nor its caustics as defects."""
    s = setup.sample
    if not s.curved:
        cs = setup.cameras[cam]
        return nominal_screen_xy(cs.camera, cs.T_world_cam, s.T_world_sample, setup.screen.T_world_screen)
    from ..simulation.render import trace_setup_camera

    return trace_setup_camera(setup, cam).screen_xy_mm


def _decode_checked(manifest, setup: Setup, cam: str, noise_std, image_dir, run_checks: bool):
    """Decode one camera of an image set (linearised with a declared response, masked and
    mapped with a declared mask and screen map) and, with ``run_checks``, check its consistency
    (:mod:`pmdsim.evaluation.consistency`): returns ``(decoded, ConsistencyResult or None)``,
    the flagged pixels invalid. Mono and stereo evaluation share it (same checks, same rules).

    Raises :class:`ConsistencyFailure` when pixels were tested and none passed.
    """
    inst = manifest.instrument
    c = setup.cameras[cam].camera
    images = load_camera_stacks(manifest, cam, expected_size_px=(c.width_px, c.height_px))
    decoded = decode_camera_images(images, setup.screen.size_mm, noise_std, response=inst.response)
    if inst.mask is not None or inst.screen_map is not None:
        decoded = apply_mask_and_map(decoded, mask=inst.mask, screen_map=inst.screen_map, source=str(manifest.path))
    if not run_checks:
        return decoded, None
    expected = _expected_screen_xy(setup, cam)
    photometric = np.uint8(PhaseFlag.DARK | PhaseFlag.SATURATED | PhaseFlag.LOW_MODULATION | PhaseFlag.NONFINITE)
    xs, ys, noise, _ = consistency_stacks(images, inst.response, noise_std, lit=(decoded.flags & photometric) == 0)
    cons = check_consistency(xs, images.x_periods_mm, ys, images.y_periods_mm, decoded, setup.screen.size_mm, noise,
                             expected_xy_mm=expected)
    decoded = with_consistency(decoded, cons, in_place=True)  # the decoder's maps: no one else holds them
    if not decoded.valid.any() and cons.tested.any():
        hint = _reversed_order_hint(images, inst, setup, cons, noise_std, expected, lit=(decoded.flags & photometric) == 0)
        raise ConsistencyFailure(
            f"{cam}: no pixel of {image_dir} passed the consistency checks; "
            + "; ".join(_name_files(r, manifest, cam, cons.images) for r in cons.reasons(2))
            + hint + "; nothing written")
    return decoded, cons


def _reversed_order_hint(images, inst, setup: Setup, cons, noise_std, expected, lit) -> str:
    """For each period that disagrees with the coarser one as a whole: does it agree with its
    shifts taken in reverse order (δ_k → −δ_k negates its phase)? Then say so — a reversed shift
    order, not a wrong period. Runs only on the failure path (one more decode and check)."""
    import re

    out = []
    for m in re.finditer(r"direction (x|y), period ([0-9.e+-]+) mm disagrees", " ".join(cons.defects)):
        direction, period = m.group(1), float(m.group(2))
        periods = list(getattr(images, f"{direction}_periods_mm"))
        k = min(range(len(periods)), key=lambda j: abs(periods[j] - period))
        stacks = list(getattr(images, f"{direction}_stacks"))
        st = np.asarray(stacks[k])
        stacks[k] = np.concatenate([st[:1], st[:0:-1]])  # shifts 0, N−1, …, 1: the reverse order
        trial = dataclasses.replace(images, **{f"{direction}_stacks": tuple(stacks)})
        dec = decode_camera_images(trial, setup.screen.size_mm, noise_std, response=inst.response)
        if inst.mask is not None or inst.screen_map is not None:
            dec = apply_mask_and_map(dec, mask=inst.mask, screen_map=inst.screen_map)
        xs, ys, noise, _ = consistency_stacks(trial, inst.response, noise_std, lit)
        again = check_consistency(xs, trial.x_periods_mm, ys, trial.y_periods_mm, dec, setup.screen.size_mm, noise,
                                  expected_xy_mm=expected)
        if not any(f"direction {direction}, period {period:g} mm disagrees" in d for d in again.defects):
            out.append(f"the {period:g} mm period of direction {direction} agrees when its shifts are taken in "
                       f"reverse order: its images' shift order (shift_index in the manifest) looks reversed")
    return ("; " + "; ".join(out)) if out else ""


def evaluate_image_set(image_dir: str | Path, setup: Setup, out_dir: str | Path, *, method: str | None = None,
                       screen_model: str | None = None, seed_pixel=None, seed_height_mm: float | None = None,
                       anchor=None, noise_std=None, force: bool = False, command: str | None = None,
                       progress: Progress | None = None, inputs: Sequence[str | Path | None] = (),
                       min_valid_fraction: float = DEFAULT_MIN_VALID_FRACTION, consistency: bool = True,
                       setup_source: str = "the setup", uncertainty: bool = True,
                       anchor_std_mm: float | None = None) -> EvaluationSummary:
    """Decode, register and reconstruct every camera of an image set (paper §2.5).

    ``screen_model`` "planar" (the screen frame's x–y plane, the paper's assumption) or
    "setup" (the setup's screen surface); None: the manifest's ``screen_model``, else "planar".
    ``method`` "stepwise" or "least_squares"; None: the manifest's ``method``, else "stepwise".
    The height is fixed by ``anchor`` (:mod:`pmdsim.evaluation.anchor`), else by ``seed_pixel``
    / ``seed_height_mm`` (a known point), else by the manifest's ``anchor``; without any, heights
    are relative (default seed at height 0) and the summary says so. Writes ``evaluation.h5``
    (per camera ``screen_xy_mm``, ``std_xy_mm``, ``decoded``, ``phase_flags``,
    ``registration_status``, ``normals``, ``points_mm``, ``height_mm``, ``reconstructed``,
    ``slopes``, ``height_detrended_mm``, ``residual_slopes``), ``height_{camera}.png``,
    ``surface_fit.json`` (``focal_length_x_mm``, ``focal_length_y_mm``,
    ``slope_residual_rms_mrad``) and ``slope_error.png``.
    ``out_dir`` must not be ``image_dir`` nor another of ``inputs`` (e.g. the setup file).
    ``uncertainty``: per-pixel standard uncertainties (:mod:`.uncertainty_job`; ``anchor_std_mm``
    the anchor's own σ, default the manifest anchor's ``distance_std_mm``). The cameras run as a
    pipeline in two threads where numba's threading layer allows it
    (:mod:`pmdsim.studies.evaluate_cameras`), joined in camera order: the same outputs, messages
    and errors as one after the other; ``evaluation.h5`` is written camera by camera in a thread.

    The decoded images are checked for consistency (:mod:`pmdsim.evaluation.consistency`:
    per-image fit residuals, agreement of the periods, geometry) unless ``consistency`` is False
    or the manifest declares a response or a screen map (the checks model the raw images as
    sinusoids of the pattern coordinates; skipped with a warning); flagged pixels are not
    reconstructed and ``evaluation.h5`` gets the maps ``consistency_flags``,
    ``fit_residual_ratio``, ``period_mismatch_ratio``, ``worst_image``. The returned summary's
    :meth:`EvaluationSummary.data_warnings` and :meth:`EvaluationSummary.failures` (valid
    fraction below ``min_valid_fraction``) are for the caller to report.

    Raises
    ------
    JobInputError
        Unknown camera, images of another size than the setup's cameras, too little memory.
    ConsistencyFailure
        If no pixel of a camera passes decoding and the consistency checks (nothing written).
    """
    from ..evaluation.plausibility import check_scale
    from ..evaluation.surface_fit import surface_fit_summary
    from .surface_figures import write_slope_error_png
    from . import uncertainty_job as uj
    from .evaluate_cameras import camera_results, evaluate_camera
    from .evaluate_files import background_files
    from .evaluate_memory import small_pages

    manifest = load_manifest(image_dir, screen_size_mm=setup.screen.size_mm)
    if screen_model is None:
        screen_model = manifest.instrument.screen_model or "planar"
    if screen_model not in ("planar", "setup"):
        raise JobInputError(f"screen model must be 'planar' or 'setup', got {screen_model!r}")
    if method is None:
        method = manifest.instrument.method or "stepwise"
    if not 0.0 <= float(min_valid_fraction) <= 1.0:
        raise JobInputError(f"min_valid_fraction must be in [0, 1], got {min_valid_fraction!r}")
    unknown = [c for c in manifest.cameras if c not in setup.cameras]
    if unknown:
        raise JobInputError(f"camera(s) {unknown} of {image_dir}/manifest.json are not in the setup "
                            f"(setup cameras: {list(setup.cameras)})")
    anchor = _resolve_anchor(manifest, seed_pixel, seed_height_mm, anchor)
    check_image_sizes(manifest, setup, setup_source)
    check_memory(setup, "evaluate", cameras=manifest.cameras, n_images=len(manifest.entries))
    prov = provenance(command, setup.to_toml())
    model_surface = None if screen_model == "planar" else setup.screen.surface
    warnings = list(check_scale(setup))
    t0 = time.perf_counter()
    results = {}
    anchors = {}
    uncs: dict = {}
    checks = {}
    inst = manifest.instrument
    run_checks = consistency
    notes = []
    with small_pages(), atomic_output_dir(out_dir, force=force, inputs=[image_dir, *inputs], command=command) as tmp, \
            EvaluationFile(tmp / "evaluation.h5") as h5, background_files() as figures, background_files() as h5_tasks:
        # 4 kB pages (huge ones cost ≈ 2.8 ms/MB here); PNGs drawn in a thread, evaluation.h5 written in another
        figures.submit(warm_up)  # the figures' imports, fonts and kernels while the images are read
        work = functools.partial(evaluate_camera, setup, manifest=manifest, noise_std=noise_std, image_dir=image_dir,
                                 run_checks=run_checks, model_surface=model_surface, anchor=anchor, method=method,
                                 uncertainty=uncertainty, anchor_std_mm=anchor_std_mm)
        for r in camera_results(manifest.cameras, work):  # two at a time, joined in camera order
            cam = r.cam
            if r.cons is not None:
                checks[cam] = r.cons
            if r.failure is not None:
                exc, before, coverage = r.failure
                if not (coverage or warnings or before):
                    raise exc
                raise type(exc)(f"{exc}; likely cause: {' / '.join(coverage or warnings + before)}") from None
            warnings += r.warnings
            anchors[cam] = r.anchor
            decoded, reg, rec = results[cam] = r.kept
            h5_tasks.submit(h5.add_camera, cam, decoded, reg, rec)  # while the next camera and the fit compute
            # only the file reads the coordinates and their σ (74 MB per camera): freed once written
            results[cam] = (dataclasses.replace(decoded, screen_xy_mm=None, std_xy_mm=None), reg, rec)
            if uncertainty:
                uncs[cam] = r.unc
                if r.unc is not None:  # the σ maps too (groups list by name: the write order is free)
                    h5_tasks.submit(h5.add_extras, cam, uj.uncertainty_datasets(r.unc))
                    figures.submit(uj.height_std_figure, rec, r.unc, cam, tmp / f"height_std_{cam}.png")
            p = rec.p_sample_mm
            figures.submit(write_height_map_png, p[..., 0], p[..., 1], rec.height_mm * 1e3,
                           title=f"{cam}: height in the sample frame ({method}, {screen_model} screen model"
                                 f"{', relative' if r.relative else ''})", label="height (µm)",
                           path=tmp / f"height_{cam}.png")
            _tick(progress, f"evaluated {cam}")
        cam0 = manifest.cameras[0]
        try:
            fit, extras = surface_fit_summary([results[c][2] for c in manifest.cameras],
                                              float(results[cam0][1].o_ref_mm[2]), uj.fit_slope_std(uncs, manifest.cameras))
        except ComputationError as exc:  # too few points for a paraboloid: the rest stands
            warnings.append(f"no surface fit: {exc}")
            fit, extras = None, [{} for _ in manifest.cameras]
        fit_json = (fit.as_json() if fit is not None else
                    {"focal_length_x_mm": None, "focal_length_y_mm": None, "slope_residual_rms_mrad": None})
        write_json(tmp / "surface_fit.json", fit_json)
        if fit is not None:
            per_cam = {c: (results[c][2].p_sample_mm, ex["residual_slopes"]) for c, ex in zip(manifest.cameras, extras)}
            figures.submit(write_slope_error_png, per_cam, fit, path=tmp / "slope_error.png")
        for c, ex in zip(manifest.cameras, extras):
            h5_tasks.submit(h5.add_extras, c, ex)
        h5_tasks.submit(h5.finish, {**prov, "method": method, "screen_model": screen_model, "image_dir": str(image_dir),
                                    "instrument": json.dumps(json_ready(manifest.instrument.describe())),
                                    "anchors": json.dumps(json_ready(anchors)),
                                    "heights_relative": any(a["kind"] == "none" for a in anchors.values()),
                                    "warnings": json.dumps(warnings),
                                    "uncertainty": uj.uncertainty_attribute(uncs, None if uncertainty else "not requested")})
        if checks:
            h5_tasks.submit(write_consistency_h5, tmp / "evaluation.h5", checks,
                            {cam: _image_files(manifest, cam, c.images) for cam, c in checks.items()})
    cams = {cam: _camera_summary(cam, decoded, rec, checks.get(cam), manifest, uncs.get(cam), anchor=anchors[cam])
            for cam, (decoded, reg, rec) in results.items()}
    return EvaluationSummary(cams, time.perf_counter() - t0, fit_json if fit is not None else None, tuple(warnings),
                             manifest.instrument.response_info, float(min_valid_fraction), tuple(notes))


def _camera_summary(cam, decoded, rec, check, manifest, unc, **extra) -> dict:
    """One camera's entry of :class:`EvaluationSummary` (mono and stereo ``evaluate``): pixel
    counts, the height range (µm), convergence, the consistency counts and reasons (image files
    named), the σ statistics; ``extra`` adds path-specific keys (``anchor`` or ``stereo``)."""
    from . import uncertainty_job as uj

    photometric = int(PhaseFlag.DARK | PhaseFlag.SATURATED | PhaseFlag.LOW_MODULATION | PhaseFlag.NONFINITE)
    h = rec.height_mm[rec.reconstructed] * 1e3
    usable = int(np.count_nonzero((decoded.flags & photometric) == 0))
    n_rec = int(rec.reconstructed.sum())
    return {"pixels": int(decoded.valid.size), "decoded": int(decoded.valid.sum()), "reconstructed": n_rec,
            "height_min_um": float(np.min(h)) if h.size else float("nan"),
            "height_max_um": float(np.max(h)) if h.size else float("nan"),
            "converged": bool(rec.converged), **extra, "usable": usable,
            "valid_fraction": n_rec / usable if usable else 0.0,
            "consistency_counts": check.counts() if check is not None else {},
            "reasons": [_name_files(r, manifest, cam, check.images) for r in check.reasons()] if check is not None else [],
            **uj.uncertainty_stats(unc)}


def _ratios_by_camera_pose(residuals) -> dict:
    out: dict = {}
    for b in residuals.blocks:
        out.setdefault(b.camera, {})[f"pose{b.pose_index}"] = float(b.ratio)
    return out


class ConsistencyFailure(ComputationError):
    """The images decode, but no pixel passes the consistency checks (nothing was written)."""


def _image_files(manifest, cam: str, labels) -> list[str]:
    """File name of each consistency image label (``"a|b|c|d"`` for a period's unidentified frame)."""
    out = []
    for lab in labels:
        files = [p.name for p in manifest.files(cam, lab.direction, lab.period_mm)]
        out.append("|".join(files) if lab.shift_index is None else files[lab.shift_index])
    return out


def _name_files(reason: str, manifest, cam: str, labels) -> str:
    """The reason with each image label replaced by its file name(s)."""
    for lab, f in zip(labels, _image_files(manifest, cam, labels)):
        text = f"image ({lab})"
        if text in reason:
            name = f if lab.shift_index is not None else f"one of {f.replace('|', ', ')} (N = 4 cannot tell which)"
            reason = reason.replace(text, f"image {name}")
    return reason


def evaluate_image_set_stereo(image_dir: str | Path, setup: Setup, out_dir: str | Path, *,
                              screen_model: str | None = None, search_range_mm=None, noise_std=None, force: bool = False,
                              command: str | None = None, progress: Progress | None = None,
                              inputs: Sequence[str | Path | None] = (),
                              min_valid_fraction: float = DEFAULT_MIN_VALID_FRACTION,
                              consistency: bool = True, uncertainty: bool = True) -> EvaluationSummary:
    """Stereo evaluation of an image set (issue 14, docs/stereo.md): decode and register every
    camera, then :func:`pmdsim.evaluation.stereo.reconstruct_stereo` — absolute heights without
    a seed. Writes ``evaluation.h5`` (the per-camera datasets of :func:`evaluate_image_set`
    plus the agreement report, :func:`pmdsim.io.hdf5.append_stereo_h5`) and
    ``height_{camera}.png``; the summary adds per camera the anchors and the median/max
    normal disagreement (µrad) and height discrepancy (µm) over the overlap. ``screen_model``
    None: the manifest's, else "planar"; ``out_dir`` must not be ``image_dir`` nor one of ``inputs``.

    Every camera's images are checked for consistency as in :func:`evaluate_image_set` (same
    checks, flagged pixels not used, :class:`ConsistencyFailure` if none passes, the maps in
    ``evaluation.h5``); the summary carries each camera's valid fraction, so that
    :meth:`EvaluationSummary.failures` applies ``min_valid_fraction`` as for mono."""
    from .evaluate_stereo import evaluate_image_set_stereo as run  # the job (its files written while it computes)

    return run(image_dir, setup, out_dir, screen_model=screen_model, search_range_mm=search_range_mm,
               noise_std=noise_std, force=force, command=command, progress=progress, inputs=inputs,
               min_valid_fraction=min_valid_fraction, consistency=consistency, uncertainty=uncertainty)


# ============================================================================ calibrate
@dataclass(frozen=True)
class CalibrationRun:
    """A finished calibration: the result, the calibrated setup and its summary (JSON-ready)."""

    result: CalibrationResult
    model: Setup
    summary: dict
    warnings: tuple = ()  # one line each: inconsistent images, residuals above the predicted noise
    residuals: object = None  # pmdsim.calibration.diagnostics.ResidualReport


def calibrate_image_sets(image_dirs: Sequence[str | Path], nominal: Setup, out_path: str | Path, *,
                         stride: int | None = None, max_iter: int = 100, force: bool = False,
                         command: str | None = None, progress: Progress | None = None,
                         inputs: Sequence[str | Path | None] = (), setup_source: str = "the setup",
                         consistency: bool = True) -> CalibrationRun:
    """Holistic calibration with a planar mirror (paper §4); see :func:`_calibrate_image_sets`.

    ``out_path`` is checked (writable, not an input: ``image_dirs`` and ``inputs``) and locked
    before the computation, so that a bad path or a concurrent run fails at once, not after it.
    """
    from ..io.outputs import check_output_target, output_lock

    check_output_target(out_path, force=force, inputs=[*image_dirs, *inputs], kind="file")
    with output_lock(out_path, command):
        return _calibrate_image_sets(image_dirs, nominal, out_path, stride=stride, max_iter=max_iter, force=force,
                                     command=command, progress=progress, inputs=[*image_dirs, *inputs],
                                     setup_source=setup_source, consistency=consistency)


def _calibrate_image_sets(image_dirs: Sequence[str | Path], nominal: Setup, out_path: str | Path, *,
                          stride: int | None = None, max_iter: int = 100, force: bool = False,
                          command: str | None = None, progress: Progress | None = None,
                          inputs: Sequence[str | Path | None] = (), setup_source: str = "the setup",
                          consistency: bool = True) -> CalibrationRun:
    """Holistic calibration with a planar mirror (paper §4) from one image set per mirror pose.

    ``image_dirs`` are in the order of ``nominal``'s calibration poses (base, lifts, tilts).
    Cameras and mirror planes are estimated jointly from ``nominal``'s values; the screen is held
    at its nominal pose (the gauge) and planar. Writes a setup TOML (``out_path``) whose sample
    frame is the calibrated table plane (pose 0), with the fit and the standard deviations in
    ``[calibration_report]``.

    Raises
    ------
    JobInputError
        If the number of image sets differs from the setup's poses or a camera is unknown.
    CalibrationNotConverged
        If the calibration does not converge (nothing is written).
    """
    from .. import __version__
    from ..calibration import calibrate, calibrated_setup, calibration_summary, nominal_state, observations_from_mapping
    from ..calibration.diagnostics import residual_report

    nominal = nominal.with_bulge(0.0)
    poses = nominal.calibration.mirror_poses(nominal.sample)
    if len(image_dirs) != len(poses):
        raise JobInputError(f"got {len(image_dirs)} image directories, but the setup lists {len(poses)} calibration "
                            f"poses ({', '.join(label for label, _ in poses)}); give one per pose, in order")
    stride = stride or nominal.calibration.observation_stride_px
    manifests = []
    for d in image_dirs:  # every input checked before any decoding
        manifest = load_manifest(d, screen_size_mm=nominal.screen.size_mm)
        for cam in manifest.cameras:
            if cam not in nominal.cameras:
                raise JobInputError(f"camera {cam!r} of {d} is not in the setup ({list(nominal.cameras)})")
        check_image_sizes(manifest, nominal, setup_source)
        manifests.append(manifest)
    check_memory(nominal, "calibrate", cameras=manifests[0].cameras if manifests else None,
                 n_images=len(manifests[0].entries) if manifests else 0)
    obs = []
    pose_notes = []
    for k, manifest in enumerate(manifests):
        for cam in manifest.cameras:
            images = load_camera_stacks(manifest, cam)
            dec = decode_camera_images(images, nominal.screen.size_mm)
            if consistency:
                cs = nominal.cameras[cam]
                expected = nominal_screen_xy(cs.camera, cs.T_world_cam, poses[k][1], nominal.screen.T_world_screen)
                cons = check_consistency(images.x_stacks, images.x_periods_mm, images.y_stacks,
                                         images.y_periods_mm, dec, nominal.screen.size_mm, expected_xy_mm=expected)
                dec = with_consistency(dec, cons, rescale_std=True)  # σ from the images' own noise
                if cons.defects:
                    pose_notes.append(f"pose {k} ({poses[k][0]}) camera {cam!r}: " + "; ".join(cons.defects[:2]))
            if not dec.valid.any():
                raise ConsistencyFailure(f"pose {k} ({image_dirs[k]}), camera {cam!r}: no pixel was decoded and passed "
                                         f"the consistency checks" + (f" ({pose_notes[-1]})" if pose_notes else "")
                                         + "; nothing written")
            obs.append(observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=stride,
                                                 screen_std_xy_mm=dec.std_xy_mm))
        _tick(progress, f"decoded pose {k}")
    start = nominal_state(nominal, [T for _, T in poses])
    glass, cal = nominal.screen.cover_glass, nominal.calibration
    if glass.present or cal.fit_glass_thickness or cal.fit_glass_index:  # docs/conventions.md "Cover glass"
        from ..calibration.glass import calibrate_with_glass

        result = calibrate_with_glass(obs, start, glass, fit_thickness=cal.fit_glass_thickness,
                                      fit_index=cal.fit_glass_index, max_iter=max_iter)
    else:
        result = calibrate(obs, start, max_iter=max_iter)
    residuals = residual_report(obs, result)
    if not result.converged:
        worst = sorted((b for b in residuals.blocks if b.ratio == b.ratio), key=lambda b: -b.ratio)[:2]
        where = "; largest residuals (× the predicted noise) in " + ", ".join(
            f"pose {b.pose_index} ({poses[b.pose_index][0]}) camera {b.camera!r} ({b.ratio:.0f}×)" for b in worst)
        raise CalibrationNotConverged(f"the calibration did not converge: {result.reason} (RMS {result.rms_px:.4g} px "
                                      f"after {result.iterations} iterations){where if worst else ''}; nothing written")
    warnings = list(pose_notes)
    w = residuals.warning([label for label, _ in poses])
    if w:
        warnings.append(w)
    model = calibrated_setup(nominal, result)
    summary = json_ready(calibration_summary(result, model))
    report = {"pmdsim_version": __version__, "command": command or "",
              "converged": summary["converged"], "reason": summary["reason"], "iterations": summary["iterations"],
              "rms_px": summary["rms_px"], "n_residuals": summary["n_residuals"],
              "condition_number": summary["condition_number"],
              "predicted_noise_rms_px": residuals.predicted_rms_px,
              "residual_to_noise_ratio": residuals.ratio,
              "residual_ratio_by_camera_pose": _ratios_by_camera_pose(residuals),
              "warnings": warnings,
              "determination": result.determination_report(),
              "std": {name: c["std"] for name, c in summary["cameras"].items()}}
    if result.glass is not None:
        g = result.to_dict()["glass"]
        report["glass"] = {k: v for k, v in g.items() if v is not None}  # TOML has no null
    from ..setup.toml import dump_toml

    doc = model.to_dict()
    doc["calibration_report"] = {**report, **doc.get("calibration_report", {})}  # + the covariance
    with atomic_file(out_path, force=force, mode="w", inputs=inputs, command=command) as f:
        f.write(dump_toml(doc))
    return CalibrationRun(result, model, summary, tuple(warnings), residuals)
