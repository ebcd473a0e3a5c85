"""The paper's experiments run into an output directory: results, tables, figures, heights.

What ``pmdsim experiment 1|2|3`` runs (the CLI parses, calls one of these and prints the
returned table). Outputs (contracts, README): ``results.json`` (one object per case),
``run.json`` (provenance and options), ``heights.h5``, ``table.txt`` and the figure
(``figure4.png`` / ``figure5.png`` / ``error_vs_free_parameters.png``); Experiment 2 and 3 add
``calibration.json``. Everything is written atomically.

``progress`` is called once per step; :func:`experiment_steps` says how many to expect.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..calibration import calibration_summary
from .. import interrupts
from ..errors import ComputationError
from ..io import atomic_output_dir, provenance, reconstructions_h5, write_json, write_png, write_reconstructions_h5
from ..setup import Setup
from .experiment1 import PAPER_TABLE2, run_experiment1_case
from .experiment2 import PAPER_TABLE3, run_experiment2_bulge
from .experiment3 import SCREEN_DEFORMATIONS, experiment3_scenarios, run_experiment3
from .figures import error_vs_free_parameters_figure, height_grid_figure
from .report import experiment3_table, format_table, json_ready, scenario_label

__all__ = ["ExperimentError", "ExperimentOutput", "experiment_steps", "write_experiment", "write_experiment3",
           "experiment3_figure"]

Progress = Callable[[str], None]


class ExperimentError(ComputationError):
    """An experiment could not be completed (e.g. a calibration did not converge)."""


@dataclass(frozen=True)
class ExperimentOutput:
    """What an experiment run wrote: the table (as printed), the file names, the seconds taken."""

    table: str
    files: tuple[str, ...]
    seconds: float

    def summary(self, out_dir) -> str:
        return f"wrote {', '.join(self.files)} to {out_dir} in {self.seconds:.1f} s"


def _tick(progress: Progress | None, msg: str) -> None:
    interrupts.check()  # an interrupt Python swallowed (in a finaliser) aborts here
    if progress is not None:
        progress(msg)


def experiment_steps(number: int, base: Setup, bulges: Sequence[float] = (), n_scenarios: int = 0,
                     n_models: int = 0) -> int:
    """How many ``progress`` calls :func:`write_experiment` (1, 2) or :func:`write_experiment3` makes."""
    if number == 1:
        return len(bulges) * len(base.cameras)
    if number == 2:
        return len(bulges) * (len(base.calibration.mirror_poses(base.sample)) * len(base.cameras) + 1
                              + len(base.cameras))
    return n_scenarios * (n_models + 1)


def write_experiment(number: int, out_dir: str | Path, base: Setup, *, bulges: Sequence[float],
                     downsample: int = 1, method: str = "stepwise", seed: int = 0, write_images: bool = False,
                     force: bool = False, command: str | None = None,
                     progress: Progress | None = None) -> ExperimentOutput:
    """Experiment 1 (paper §3: perfect knowledge, planar screen model; Table 2, Fig. 4) or 2
    (§4: simulated holistic calibration, then reconstruction; Table 3, Fig. 5) for every Δh in
    ``bulges`` and camera of ``base``, written to ``out_dir``."""
    if number not in (1, 2):
        raise ValueError(f"write_experiment runs experiments 1 and 2, got {number!r}")
    bulges = [float(b) for b in bulges]
    prov = provenance(command, base.to_toml())
    t0 = time.perf_counter()
    cases, calibrations = [], []
    paper = PAPER_TABLE2 if number == 1 else PAPER_TABLE3
    with atomic_output_dir(out_dir, force=force, command=command) as tmp:
        if number == 1:
            pool = ThreadPoolExecutor(max_workers=2) if write_images else None
            futures = []
            sink = None
            for dh in bulges:
                for cam in base.cameras:
                    if pool is not None:
                        d = tmp / "images" / f"bulge_{dh:g}mm"
                        d.mkdir(parents=True, exist_ok=True)
                        sink = lambda spec, img, d=d: futures.append(pool.submit(write_png, d / spec.file, img))
                    cases.append(run_experiment1_case(dh, cam, base=base, downsample=downsample, method=method,
                                                      image_sink=sink))
                    _tick(progress, f"Δh={dh:g} mm {cam}")
            if pool is not None:
                for f in futures:
                    f.result()
                pool.shutdown()
            records = [c.as_record() for c in cases]
        else:
            for dh in bulges:
                e2 = run_experiment2_bulge(dh, base=base, downsample=downsample, method=method, seed=seed,
                                           progress=progress)
                if not e2.result.converged:
                    raise ExperimentError(f"Δh = {dh:g} mm: the calibration did not converge: {e2.result.reason}")
                summary = calibration_summary(e2.result, e2.model)
                calibrations.append({"bulge_mm": dh, **summary, "deviation_from_truth": e2.deviation})
                cases.extend(e2.cases)
            records = []
            for c in cases:
                rec = c.as_record()
                cal = next(x for x in calibrations if x["bulge_mm"] == c.bulge_mm)
                rec["frame_turn_deg"] = cal["deviation_from_truth"]["table_turn_deg"]
                rec["calibration_rms_px"] = cal["rms_px"]
                rec["calibrated_camera"] = cal["cameras"][c.camera]
                rec["camera_deviation_from_truth"] = cal["deviation_from_truth"][c.camera]
                records.append(rec)
            write_json(tmp / "calibration.json", json_ready(calibrations))
        cam0 = next(iter(base.cameras.values())).camera.binned(downsample)
        meta = {**prov, "experiment": number, "downsample": downsample, "method": method,
                "image_size_px": [cam0.width_px, cam0.height_px],
                f"paper_table{2 if number == 1 else 3}": [
                    {"bulge_mm": b, "camera": c, "max_height_diff_um": v[0], "max_dev_plane_um": v[1], "tilt_urad": v[2]}
                    for (b, c), v in paper.items()]}
        write_json(tmp / "results.json", json_ready(records))
        write_json(tmp / "run.json", meta)
        write_reconstructions_h5(tmp / "heights.h5", cases, dict(prov))
        shown = ([b for b in (0.0, 3.0) if b in bulges] or bulges[:2]) if number == 1 else [max(bulges)]
        panels = []
        for b in shown:
            row = []
            for c in cases:
                if c.bulge_mm == b:
                    p = c.p_sample_mm
                    row.append((p[..., 0], p[..., 1], c.height_error_mm * 1e3,
                                f"Δh = {b:g} mm, {c.camera} camera: PV {c.metrics['max_height_diff_um']:.3g} µm"))
            panels.append(row)
        what = ("perfect setup knowledge, planar screen model" if number == 1
                else "simulated holistic calibration, planar screen model")
        frame = "sample frame" if number == 1 else "calibrated table frame"
        figure = f"figure{3 + number}.png"
        height_grid_figure(panels, path=tmp / figure,
                           suptitle=f"Experiment {number}: reconstructed planar sample, height error ({frame}, {method})")
        table = format_table(records, paper, f"Experiment {number} — {what}; {method} integration, "
                                             f"{cam0.width_px}×{cam0.height_px} px per camera")
        if calibrations:
            table += "\n" + "\n".join(
                f"Δh = {c['bulge_mm']:g} mm: calibration RMS {c['rms_px']:.4f} px, {c['iterations']} iterations; "
                f"calibrated frame turned {c['deviation_from_truth']['table_turn_deg']:.3f}° against the truth"
                for c in calibrations)
        (tmp / "table.txt").write_text(table + "\n", encoding="utf-8")
    files = ("results.json", "heights.h5", figure, "table.txt") + (("calibration.json",) if number == 2 else ())
    return ExperimentOutput(table, files, time.perf_counter() - t0)


def experiment3_figure(records: list[dict], downsample: int, path: str | Path | None = None):
    """Experiment 3's figure: error and calibration residual against the number of free screen
    heights, one line per scenario (returns the matplotlib Figure; saved when ``path`` given)."""
    models = list(dict.fromkeys((r["screen_model"], r["free_parameters"]) for r in records))
    series = []
    for sl in dict.fromkeys(scenario_label(r) for r in records):
        err, rms = [], []
        for m, _ in models:
            rs = [r for r in records if scenario_label(r) == sl and r["screen_model"] == m]
            err.append(max((r["max_height_diff_um"] for r in rs), default=np.nan))
            rms.append(rs[0]["calibration_rms_px"] if rs else np.nan)
        series.append((sl, err, rms))
    floor = [r["max_height_diff_um"] for r in records
             if r["scenario"] == "bulge" and r["bulge_mm"] == 0 and r["screen_model"] == "planar"]
    return error_vs_free_parameters_figure(series, [f"{m.replace('x', '×')} ({n})" for m, n in models],
                                           suptitle=f"Experiment 3: calibrated screen models (downsample {downsample})",
                                           floor_um=max(floor) if floor else None, path=path)


def write_experiment3(out_dir: str | Path, base: Setup, *, bulges: Sequence[float], grids: Sequence[int],
                      deformations: Sequence[str], mirror_sags_um: Sequence[float], sag_bulge_mm: float = 3.0,
                      downsample: int = 1, method: str = "stepwise", force: bool = False,
                      command: str | None = None, progress: Progress | None = None) -> ExperimentOutput:
    """Experiment 3 (beyond the paper, §5): for every scenario (the paper's bulges, mismatching
    deformations, a sagged calibration mirror) and screen model (planar, n×n free-form grids)
    calibrate and reconstruct the planar sample; errors against the number of free heights."""
    bad = [k for k in deformations if k not in SCREEN_DEFORMATIONS]
    if bad:
        raise ValueError(f"unknown screen deformation(s) {bad}; expected some of {list(SCREEN_DEFORMATIONS)}")
    if any(g < 3 for g in grids):
        raise ValueError(f"every screen grid needs at least 3 × 3 control points, got {list(grids)}")
    prov = provenance(command, base.to_toml())
    t0 = time.perf_counter()
    scenarios = experiment3_scenarios(base, downsample=downsample, bulges=bulges, deformations=deformations,
                                      mirror_sags_um=mirror_sags_um, sag_bulge_mm=sag_bulge_mm)
    if not scenarios:
        raise ValueError("nothing to run: no bulges, deformations or mirror sags given")
    records, calibrations, undetermined = [], [], []
    with atomic_output_dir(out_dir, force=force, command=command) as tmp, reconstructions_h5(tmp / "heights.h5", dict(prov)) as add_case:
        for sc, label, e, recs in run_experiment3(scenarios, list(grids), method=method, progress=progress):
            if isinstance(e, Exception):  # the data cannot determine this model: say so, go on
                undetermined.append(f"{sc.label}, {label} screen model: {e}")
                calibrations.append({"scenario": sc.name, "bulge_mm": sc.bulge_mm, "mirror_sag_um": sc.mirror_sag_um,
                                     "screen_model": label, "error": str(e)})
                continue
            if not e.result.converged:
                raise ExperimentError(f"{sc.label}, screen model {label}: calibration did not converge: "
                                      f"{e.result.reason}")
            records.extend(recs)
            calibrations.append({"scenario": sc.name, "bulge_mm": sc.bulge_mm, "mirror_sag_um": sc.mirror_sag_um,
                                 "screen_model": label, **e.result.to_dict(), "deviation_from_truth": e.deviation})
            for c in e.cases:  # written as they come: the run never holds all height maps
                add_case(c, {"scenario": sc.name, "bulge_mm": float(sc.bulge_mm),
                                  "mirror_sag_um": float(sc.mirror_sag_um), "screen_model": label})
        write_json(tmp / "results.json", json_ready(records))
        write_json(tmp / "calibration.json", json_ready(calibrations))
        write_json(tmp / "run.json", {**prov, "experiment": 3, "downsample": downsample, "method": method,
                                      "grids": list(grids), "deformations": list(deformations),
                                      "mirror_sags_um": list(mirror_sags_um), "sag_bulge_mm": sag_bulge_mm})
        table = experiment3_table(records)
        if undetermined:
            table += "\n\nNot determined by the calibration data (full reasons in calibration.json):\n" + "\n".join(
                "  " + (u if len(u) <= 400 else u[:400] + " …") for u in undetermined)
        (tmp / "table.txt").write_text(table + "\n", encoding="utf-8")
        if records:
            experiment3_figure(records, downsample, path=tmp / "error_vs_free_parameters.png")
    return ExperimentOutput(table, ("results.json", "calibration.json", "heights.h5", "table.txt",
                                    "error_vs_free_parameters.png"), time.perf_counter() - t0)
