"""One measurement, disk to disk: simulate an image set, evaluate one, calibrate from several.

These are what ``pmdsim simulate``, ``pmdsim evaluate`` and ``pmdsim calibrate`` run; the CLI
only parses its options, calls one of them and prints the returned summary. Every function
writes atomically (:func:`pmdsim.io.atomic_output_dir`, :func:`pmdsim.io.atomic_file`) and
records the pmdsim version and the producing command (``command``).

``progress``, where accepted, is called with a short message after each step; ``n_steps``
functions say how many calls to expect (for a progress bar).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..calibration import (
    CalibrationResult,
    calibrate,
    calibrated_setup,
    calibration_summary,
    nominal_state,
    observations_from_mapping,
)
from ..errors import ComputationError, PmdsimError
from ..evaluation.phase import PhaseFlag
from ..evaluation.pipeline import evaluate_decoded
from ..io import (
    IMAGESET_FORMAT,
    MANIFEST_NAME,
    MAPPING_NAME,
    atomic_file,
    atomic_output_dir,
    provenance,
    write_evaluation_h5,
    write_json,
    write_mapping_h5,
    write_png,
)
from ..io.hdf5 import write_consistency_h5
from ..io.imageset import decode_camera_images, load_camera_stacks, load_manifest
from ..calibration.diagnostics import residual_report
from ..evaluation.consistency import check_consistency, nominal_screen_xy, with_consistency
from .checks import check_memory
from ..setup import Setup
from ..simulation.imaging import needs_points
from ..setup.sensor import SensorModel
from ..simulation.render import image_specs, render_images, trace_setup_camera
from .figures import height_map_figure
from .report import json_ready

__all__ = [
    "JobInputError",
    "simulation_steps",
    "simulate_to_dir",
    "evaluate_image_set",
    "calibrate_image_sets",
    "CalibrationNotConverged",
    "ConsistencyFailure",
    "check_image_sizes",
    "DEFAULT_MIN_VALID_FRACTION",
]

Progress = Callable[[str], None]


class JobInputError(PmdsimError, ValueError):
    """The inputs of a job do not fit together (e.g. a camera of the images is not in the setup)."""


class CalibrationNotConverged(ComputationError):
    """The calibration did not converge; nothing was written."""


def _tick(progress: Progress | None, msg: str) -> None:
    if progress is not None:
        progress(msg)


# ============================================================================ simulate
def simulation_steps(setup: Setup) -> int:
    """Number of progress calls of :func:`simulate_to_dir`: one per traced camera and image."""
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
                    calibration_pose: int | None = None, progress: Progress | None = None) -> SimulationSummary:
    """Simulate a measurement (paper §2) and write it as an image set.

    Writes into ``out_dir``: ``{camera}_{direction}_p{i}_s{k}.png`` fringe images, ``manifest.json``
    (provenance, the setup as TOML, one entry per image) and ``mapping.h5`` (per camera
    ``screen_xy_mm`` (H, W, 2), ``valid`` and ``status``). ``calibration_pose`` K images the
    calibration mirror in pose K (noise stream K + 1, as the in-memory experiments use) instead
    of the sample.
    """
    if calibration_pose is not None:
        setup = setup.with_mirror_pose(calibration_pose)
    check_memory(setup, "simulate")
    prov = provenance(command, setup.to_toml())
    t0 = time.perf_counter()
    with atomic_output_dir(out_dir, force=force) as tmp:
        mappings = {}
        entries = []
        with ThreadPoolExecutor(max_workers=2) as pool:
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
    see fringes (``usable``), consistency flag counts and reasons; seconds."""

    cameras: dict[str, dict]
    seconds: float
    min_valid_fraction: float = DEFAULT_MIN_VALID_FRACTION

    def lines(self) -> list[str]:
        out = []
        for cam, c in self.cameras.items():
            rng = (f"height {c['height_min_um']:.3f} … {c['height_max_um']:.3f} µm (sample frame)"
                   if c["reconstructed"] else "no height")
            out.append(f"{cam}: {c['decoded']}/{c['pixels']} pixels decoded, {c['reconstructed']} reconstructed; "
                       f"{rng}, {'converged' if c['converged'] else 'NOT converged'}")
        return out

    def warnings(self) -> list[str]:
        """One line per camera whose data look wrong (few valid pixels, consistency flags)."""
        out = []
        for cam, c in self.cameras.items():
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
                for cam, c in self.cameras.items() if not c["valid_fraction"] >= self.min_valid_fraction]


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


def evaluate_image_set(image_dir: str | Path, setup: Setup, out_dir: str | Path, *, method: str = "stepwise",
                       screen_model: str = "planar", seed_pixel=None, seed_height_mm: float = 0.0,
                       noise_std=None, force: bool = False, command: str | None = None,
                       progress: Progress | None = None, min_valid_fraction: float = DEFAULT_MIN_VALID_FRACTION,
                       consistency: bool = True, setup_source: str = "the setup") -> EvaluationSummary:
    """Decode, check, register and reconstruct every camera of an image set (paper §2.5).

    ``screen_model`` "planar" (the screen frame's x–y plane, the paper's assumption) or
    "setup" (the setup's screen surface). The decoded images are checked for consistency
    (:mod:`pmdsim.evaluation.consistency`: per-image fit residuals, agreement of the periods,
    geometry) unless ``consistency`` is False; flagged pixels are not reconstructed. Writes
    ``evaluation.h5`` (per camera ``screen_xy_mm``, ``std_xy_mm``, ``decoded``, ``phase_flags``,
    ``registration_status``, ``normals``, ``points_mm``, ``height_mm``, ``reconstructed`` and the
    consistency maps ``consistency_flags``, ``fit_residual_ratio``, ``period_mismatch_ratio``,
    ``worst_image``) and ``height_{camera}.png``. The returned summary's :meth:`warnings` and
    :meth:`failures` (valid fraction below ``min_valid_fraction``) are for the caller to report.

    Raises
    ------
    JobInputError
        Unknown camera, images of another size than the setup's cameras, too little memory.
    ConsistencyFailure
        If no pixel of a camera passes decoding and the consistency checks (nothing written).
    """
    if screen_model not in ("planar", "setup"):
        raise JobInputError(f"screen model must be 'planar' or 'setup', got {screen_model!r}")
    if not 0.0 <= float(min_valid_fraction) <= 1.0:
        raise JobInputError(f"min_valid_fraction must be in [0, 1], got {min_valid_fraction!r}")
    manifest = load_manifest(image_dir, screen_size_mm=setup.screen.size_mm)
    unknown = [c for c in manifest.cameras if c not in setup.cameras]
    if unknown:
        raise JobInputError(f"camera(s) {unknown} of {image_dir}/manifest.json are not in the setup "
                            f"(setup cameras: {list(setup.cameras)})")
    check_image_sizes(manifest, setup, setup_source)
    check_memory(setup, "evaluate", cameras=manifest.cameras, n_images=len(manifest.entries))
    prov = provenance(command, setup.to_toml())
    model_surface = None if screen_model == "planar" else setup.screen.surface
    t0 = time.perf_counter()
    results = {}
    checks = {}
    with atomic_output_dir(out_dir, force=force) as tmp:
        for cam in manifest.cameras:
            images = load_camera_stacks(manifest, cam)
            decoded = decode_camera_images(images, setup.screen.size_mm, noise_std)
            if consistency:
                cs = setup.cameras[cam]
                expected = nominal_screen_xy(cs.camera, cs.T_world_cam, setup.sample.T_world_sample,
                                             setup.screen.T_world_screen)
                cons = check_consistency(images.x_stacks, images.x_periods_mm, images.y_stacks, images.y_periods_mm,
                                         decoded, setup.screen.size_mm, noise_std, expected_xy_mm=expected)
                decoded = with_consistency(decoded, cons)
                checks[cam] = cons
                if not decoded.valid.any() and cons.tested.any():
                    raise ConsistencyFailure(
                        f"{cam}: no pixel of {image_dir} passed the consistency checks; "
                        + "; ".join(_name_files(r, manifest, cam, cons.images) for r in cons.reasons(2))
                        + "; nothing written")
            reg, rec = evaluate_decoded(setup, cam, decoded, screen_model=model_surface, method=method,
                                        seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
            results[cam] = (decoded, reg, rec)
            p = rec.p_sample_mm
            height_map_figure(p[..., 0], p[..., 1], rec.height_mm * 1e3,
                              title=f"{cam}: height in the sample frame ({method}, {screen_model} screen model)",
                              label="height (µm)", path=tmp / f"height_{cam}.png")
            _tick(progress, f"evaluated {cam}")
        write_evaluation_h5(tmp / "evaluation.h5", results,
                            {**prov, "method": method, "screen_model": screen_model, "image_dir": str(image_dir)})
        if checks:
            write_consistency_h5(tmp / "evaluation.h5", checks,
                                 {cam: _image_files(manifest, cam, c.images) for cam, c in checks.items()})
    cams = {}
    photometric = int(PhaseFlag.DARK | PhaseFlag.SATURATED | PhaseFlag.LOW_MODULATION | PhaseFlag.NONFINITE)
    for cam, (decoded, reg, rec) in results.items():
        h = rec.height_mm[rec.reconstructed] * 1e3
        usable = int(np.count_nonzero((decoded.flags & photometric) == 0))
        n_rec = int(rec.reconstructed.sum())
        c = checks.get(cam)
        cams[cam] = {"pixels": int(decoded.valid.size), "decoded": int(decoded.valid.sum()),
                     "reconstructed": n_rec,
                     "height_min_um": float(np.min(h)) if h.size else float("nan"),
                     "height_max_um": float(np.max(h)) if h.size else float("nan"),
                     "converged": bool(rec.converged), "usable": usable,
                     "valid_fraction": n_rec / usable if usable else 0.0,
                     "consistency_counts": c.counts() if c is not None else {},
                     "reasons": [_name_files(r, manifest, cam, c.images) for r in c.reasons()] if c is not None else []}
    return EvaluationSummary(cams, time.perf_counter() - t0, float(min_valid_fraction))


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
                         setup_source: str = "the setup", consistency: bool = True) -> CalibrationRun:
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
    from ..io.outputs import check_output_target
    from .. import __version__

    nominal = nominal.with_bulge(0.0)
    poses = nominal.calibration.mirror_poses(nominal.sample)
    if len(image_dirs) != len(poses):
        raise JobInputError(f"got {len(image_dirs)} image directories, but the setup lists {len(poses)} calibration "
                            f"poses ({', '.join(label for label, _ in poses)}); give one per pose, in order")
    check_output_target(out_path, force=force)
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
    from ..setup.toml import dump_toml

    doc = model.to_dict()
    doc["calibration_report"] = report
    with atomic_file(out_path, force=force, mode="w") as f:
        f.write(dump_toml(doc))
    return CalibrationRun(result, model, summary, tuple(warnings), residuals)
