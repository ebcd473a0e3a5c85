"""Experiment 5 (beyond the paper; the paper's application, §1): a warped printed foil.

A foil with a global bow and local shrinkage warps (:class:`~pmdsim.geometry.warpage.FoilWarpage`)
is measured with the Table 1 setup for screen bulges Δh, through 8-bit images, and evaluated
four ways from two simulated holistic calibrations (Experiment 2's chain: 16 mirror poses,
nominal start values with :data:`~pmdsim.studies.experiment2.INITIAL_ERRORS`):

* ``mono_planar`` — planar-screen calibration, one camera, seeded at the central pixel with its
  true height (the paper's method, which needs a known point);
* ``mono_free3x3`` — calibrated free 3 × 3 screen, one camera, the same seed;
* ``stereo_planar`` — planar-screen calibration, both cameras, no seed (docs/stereo.md);
* ``stereo_free3x3`` — calibrated free 3 × 3 screen, both cameras, no seed.

Heights are relative to the calibrated table plane (the base mirror pose: the instrument's
reference, as in Experiment 2) and compared with the foil's true height above the true table
at the same (x, y): the two table frames are identified, as the instrument must (the
calibrated *world* of a planar-screen calibration at Δh = 3 mm differs from the true one by
far more than a rigid motion — cameras moved by ~30 mm, the table turned by ~1° — but
consistently, so only heights relative to the table are meaningful). The error includes
everything the instrument gets wrong, nothing removed. The nozzle of an ink-jet
printer follows the measured surface at a nominal stand-off of 0.5 mm (§1); its actual
stand-off is 0.5 mm − e (e = z − z_true, the sample's +z pointing away from the cameras and
the nozzle), so the stand-off error over the printable area is −e.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from matplotlib.figure import Figure

from ..calibration import calibrate, nominal_state, perturbed_state
from ..calibration.setup_bridge import calibrated_setup, calibration_deviation, free_screen_model, nominal_setup
from ..errors import ComputationError
from ..evaluation.metrics import surface_error_metrics
from ..evaluation.pipeline import decode_images, evaluate_decoded
from ..evaluation.stereo import evaluate_stereo_decoded
from ..evaluation.uncertainty_stereo import stereo_with_uncertainty
from ..geometry.warpage import FoilWarpage
from ..io import atomic_output_dir, provenance, reconstructions_h5, write_json
from ..setup import Setup
from ..setup.model import SampleSetup
from ..simulation.imaging import decoder_response
from ..simulation.render import render_images, trace_setup_camera
from .calibration_data import simulate_calibration_observations
from .experiment1 import CaseResult
from .experiment2 import INITIAL_ERRORS
from .experiment_uncertainty import case_uncertainty_record, stereo_uncertainty_record
from .figures import height_grid_figure
from .report import json_ready

__all__ = ["METHODS", "PRINTABLE_AREA_MM", "NOMINAL_STANDOFF_MM", "foil_setup", "default_warpage", "Experiment5Case",
           "run_experiment5_bulge", "experiment5_steps", "experiment5_table", "write_experiment5"]

Progress = Callable[[str], None]

#: The four evaluations (module docstring).
METHODS = ("mono_planar", "mono_free3x3", "stereo_planar", "stereo_free3x3")

#: The printable area: x0, x1, y0, y1 in the (true) sample frame, mm — a 100 × 110 mm region
#: in the middle of both cameras' fields of view (Table 1: x 122…278, y 111…283 mm for both).
PRINTABLE_AREA_MM = (150.0, 250.0, 140.0, 250.0)

#: Nominal nozzle stand-off of an ink-jet printer (paper §1), mm.
NOMINAL_STANDOFF_MM = 0.5

#: Spline grid spacing of the foil sample (mm); the default warps interpolate to ≈ 0.006 µm.
FOIL_GRID_MM = 4.0


def foil_setup(setup: Setup, warpage: FoilWarpage | None = None, spacing_mm: float = FOIL_GRID_MM) -> Setup:
    """``setup`` with its sample replaced by a warped foil over the sample's extent: the
    warpage's heights on a spline grid of at most ``spacing_mm`` (docs/conventions.md,
    "Foil warpage"). The default warpage: a 2 mm spherical bow and six ±30 µm Gaussian
    shrinkage warps of σ = 12 mm."""
    smp = setup.sample
    if warpage is None:
        warpage = default_warpage(setup)
    gx, gy = warpage.grid(spacing_mm)
    z = warpage.on_grid(gx, gy)
    return replace(setup, sample=SampleSetup(smp.pose, tuple(float(v) for v in gx), tuple(float(v) for v in gy),
                                             tuple(tuple(float(v) for v in r) for r in z)))


def default_warpage(setup: Setup) -> FoilWarpage:
    """The default foil (``FoilWarpage()``'s parameters) over ``setup``'s sample extent."""
    smp = setup.sample
    return FoilWarpage(x_range_mm=(smp.grid_x_mm[0], smp.grid_x_mm[-1]), y_range_mm=(smp.grid_y_mm[0], smp.grid_y_mm[-1]))


def _sample_label(w: FoilWarpage) -> str:
    return (f"foil: {w.bow_kind} bow {w.bow_mm:g} mm, {w.n_shrinks} {w.shrink_shape} shrinkage warps "
            f"±{w.shrink_depth_um:g} µm (width {w.shrink_width_mm:g} mm), seed {w.seed}")


@dataclass(frozen=True, eq=False)
class Experiment5Case:
    """One evaluation of one camera: the results.json record and the maps (CaseResult)."""

    method: str
    record: dict
    case: CaseResult


def _case(truth, model, bulge_mm, camera, method, rec, sample_label, extra):
    p = rec.p_sample_mm
    ok = rec.reconstructed
    tx = np.where(ok, p[..., 0], 0.0)  # the calibrated table frame is the table: (x, y) as they are
    ty = np.where(ok, p[..., 1], 0.0)
    zt = truth.sample.surface.height(tx, ty)
    err = np.where(ok, rec.height_mm - zt, np.nan)
    metrics = surface_error_metrics(p[..., 0], p[..., 1], err)
    x0, x1, y0, y1 = PRINTABLE_AREA_MM
    area = ok & (tx >= x0) & (tx <= x1) & (ty >= y0) & (ty <= y1)
    e_area = err[area] * 1e3
    record = {
        "bulge_mm": float(bulge_mm), "camera": camera,
        "max_height_diff_um": metrics["max_height_diff_um"], "max_dev_plane_um": metrics["max_dev_plane_um"],
        "tilt_urad": metrics["tilt_urad"],
        "method": method, "sample": sample_label,
        "max_abs_error_um": float(np.nanmax(np.abs(err)) * 1e3),
        "printable_max_abs_error_um": float(np.max(np.abs(e_area))) if e_area.size else float("nan"),
        "standoff_error_range_um": float(np.ptp(e_area)) if e_area.size else float("nan"),
        "printable_pixels": int(area.sum()),
        **{k: v for k, v in metrics.items() if k not in ("max_height_diff_um", "max_dev_plane_um", "tilt_urad")},
        "integration": rec.method, "converged": bool(rec.converged), **extra,
    }
    cr = CaseResult.from_reconstruction(bulge_mm, camera, rec, err, metrics)
    return Experiment5Case(method, record, cr)


def _calibrate(truth: Setup, obs, grid, start_seed):
    nominal = nominal_setup(truth)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    start = perturbed_state(nominal_state(nominal, poses), np.random.default_rng(start_seed), **INITIAL_ERRORS)
    result = calibrate(obs, start, screen_model=None if grid is None else free_screen_model(nominal, grid))
    if not result.converged:
        raise ComputationError(f"Experiment 5: the {'planar' if grid is None else f'{grid}×{grid}'} calibration did "
                               f"not converge: {result.reason}")
    return result, calibrated_setup(nominal, result)


def experiment5_steps(bulges: Sequence[float]) -> int:
    """How many ``progress`` calls :func:`write_experiment5` makes."""
    return len(bulges) * 5


def run_experiment5_bulge(bulge_mm: float, base: Setup, *, warpage: FoilWarpage | None = None, downsample: int = 1,
                          method: str = "stepwise", seed: int = 0, progress: Progress | None = None):
    """Experiment 5 at one Δh: calibrate (planar, free 3 × 3), simulate the foil, evaluate four
    ways. Returns (cases, calibration records)."""
    def tick(msg):
        if progress is not None:
            progress(msg)

    b = base.binned(downsample)
    w = warpage if warpage is not None else default_warpage(b)
    truth = foil_setup(b, w).with_bulge(bulge_mm)
    label = _sample_label(w)
    obs = simulate_calibration_observations(truth)
    tick(f"Δh = {bulge_mm:g} mm: calibration data")
    start_seed = [seed, 5, int(round(bulge_mm * 1000))]
    models, cal_records = {}, []
    for grid, name in ((None, "planar"), (3, "free3x3")):
        result, model = _calibrate(truth, obs, grid, start_seed)
        models[name] = model
        cal_records.append({"bulge_mm": float(bulge_mm), "screen_model": name, "converged": bool(result.converged),
                            "rms_px": float(result.rms_px), "iterations": int(result.iterations),
                            "deviation_from_truth": calibration_deviation(truth, model)})
        tick(f"Δh = {bulge_mm:g} mm: {name} calibration")
    decoded, maps = {}, {}
    for cam in truth.cameras:
        m = trace_setup_camera(truth, cam, store_points=True)
        images: dict = {}
        for spec, img in render_images(truth, cam, m):
            images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        decoded[cam] = decode_images(truth, images, response=decoder_response(truth))
        maps[cam] = m
    tick(f"Δh = {bulge_mm:g} mm: foil measured")
    cases = []
    for name, model in models.items():
        screen = None if name == "planar" else model.screen.surface
        for cam in truth.cameras:
            c = model.cameras[cam].camera
            seed_px = (c.height_px // 2, c.width_px // 2)
            if not (decoded[cam].valid[seed_px] and maps[cam].valid[seed_px]):
                raise ComputationError(f"Experiment 5: camera {cam!r}'s central pixel does not see the foil; no seed")
            seed_h = float(maps[cam].p_sample_mm[seed_px][2])  # its true height above the table
            reg, rec = evaluate_decoded(model, cam, decoded[cam], screen_model=screen, method=method,
                                        seed_pixel=seed_px, seed_height_mm=seed_h)
            cases.append(_case(truth, model, bulge_mm, cam, f"mono_{name}", rec, label,
                               {"seed_pixel": list(seed_px), "seed_height_mm": seed_h}))
            cases[-1].record.update(case_uncertainty_record(
                truth, model, cam, decoded[cam], reg, rec, [(seed_px, seed_h, rec.reconstructed)],
                cases[-1].case.height_error_mm, method=method, screen_grid=None if name == "planar" else 3,
                curved_sample=True))
        views, st = evaluate_stereo_decoded(model, decoded, screen_model=screen)
        # σ of the absolute stereo heights (noise and calibration; docs/conventions.md "Uncertainty: stereo");
        # without σ the records say "no σ" (stereo_uncertainty_record) and the heights stand
        st, _, _ = stereo_with_uncertainty(model, views, decoded, st, screen_model=screen)
        summ = st.summary()
        for cam, sc in st.cameras.items():
            extra = {"overlap_pixels": summ[cam]["overlap"], "anchors": summ[cam]["anchors"],
                     "normal_disagreement_median_urad": summ[cam]["normal_disagreement_median_urad"],
                     "height_discrepancy_median_um": summ[cam]["height_discrepancy_median_um"]}
            cases.append(_case(truth, model, bulge_mm, cam, f"stereo_{name}", sc.reconstruction, label, extra))
            cases[-1].record.update(stereo_uncertainty_record(truth, sc, cases[-1].case.height_error_mm,
                                                              screen_grid=None if name == "planar" else 3,
                                                              curved_sample=True))
        tick(f"Δh = {bulge_mm:g} mm: {name} evaluations")
    # the reference: no measurement, the foil assumed flat (z = 0 of the true table)
    x0, x1, y0, y1 = PRINTABLE_AREA_MM
    gx, gy = np.meshgrid(np.linspace(x0, x1, 101), np.linspace(y0, y1, 111))
    flat = truth.sample.surface.height(gx, gy) * 1e3
    cal_records.append({"bulge_mm": float(bulge_mm), "flat_assumption_standoff_error_max_um": float(np.max(np.abs(flat))),
                        "flat_assumption_standoff_error_range_um": float(np.ptp(flat))})
    return cases, cal_records


def experiment5_table(records: list[dict], references: list[dict], title: str) -> str:
    """One line per Δh and method, cameras L/R: max |error| over the evaluated area, over the
    printable area, stand-off error range, and the stereo agreement report's medians."""
    lines = [title, f"printable area x {PRINTABLE_AREA_MM[0]:g}…{PRINTABLE_AREA_MM[1]:g} mm, "
                    f"y {PRINTABLE_AREA_MM[2]:g}…{PRINTABLE_AREA_MM[3]:g} mm (sample frame); nominal stand-off "
                    f"{NOMINAL_STANDOFF_MM * 1e3:g} µm; errors in µm, cameras L/R",
             f"{'Δh':>5s} {'method':16s} {'max |e| (all)':>21s} {'max |e| printable':>21s} {'stand-off range':>21s} "
             f"{'disagree µrad':>15s}"]
    for b in sorted({r["bulge_mm"] for r in records}):
        for m in METHODS:
            rs = [r for r in records if r["bulge_mm"] == b and r["method"] == m]
            if not rs:
                continue

            def pair(k, f=".3f"):
                return "/".join(format(r[k], f) for r in rs)
            dis = pair("normal_disagreement_median_urad", ".1f") if "normal_disagreement_median_urad" in rs[0] else ""
            lines.append(f"{b:5g} {m:16s} {pair('max_abs_error_um'):>21s} {pair('printable_max_abs_error_um'):>21s} "
                         f"{pair('standoff_error_range_um'):>21s} {dis:>15s}")
        ref = next((x for x in references if x["bulge_mm"] == b), None)
        if ref is not None:
            lines.append(f"{b:5g} {'flat assumed':16s} {'':>21s} "
                         f"{ref['flat_assumption_standoff_error_max_um']:>21.1f} "
                         f"{ref['flat_assumption_standoff_error_range_um']:>21.1f}")
    return "\n".join(lines)


def standoff_figure(records: list[dict], references: list[dict], *, path=None) -> Figure:
    """Bar chart: largest stand-off error over the printable area (µm, log scale) per method
    and Δh (the larger camera), with the flat-foil assumption and the nominal stand-off."""
    bulges = sorted({r["bulge_mm"] for r in records})
    fig = Figure(figsize=(8.0, 4.4), dpi=110)
    ax = fig.subplots()
    width = 0.8 / max(len(bulges), 1)
    for i, b in enumerate(bulges):
        vals = [max((r["printable_max_abs_error_um"] for r in records if r["bulge_mm"] == b and r["method"] == m),
                    default=np.nan) for m in METHODS]
        ref = next((x["flat_assumption_standoff_error_max_um"] for x in references if x["bulge_mm"] == b), np.nan)
        xs = np.arange(len(METHODS) + 1) + (i - (len(bulges) - 1) / 2) * width
        ax.bar(xs, vals + [ref], width=width, label=f"Δh = {b:g} mm")
    ax.axhline(NOMINAL_STANDOFF_MM * 1e3, color="k", ls="--", lw=1, label="nominal stand-off 500 µm")
    ax.axhline(1.0, color="grey", ls=":", lw=1, label="1 µm")
    ax.set_xticks(np.arange(len(METHODS) + 1), [m.replace("_", "\n") for m in METHODS] + ["flat foil\nassumed"])
    ax.set_yscale("log")
    ax.set_ylabel("max |stand-off error| over printable area (µm)")
    ax.set_title("Experiment 5: warped foil — nozzle stand-off error", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path)
    return fig


@dataclass(frozen=True)
class Experiment5Output:
    table: str
    files: tuple[str, ...]
    seconds: float

    def summary(self, out_dir) -> str:
        return f"wrote {', '.join(self.files)} to {out_dir} in {self.seconds:.1f} s"


def write_experiment5(out_dir: str | Path, base: Setup, *, bulges: Sequence[float] = (0.0, 3.0),
                      downsample: int = 1, method: str = "stepwise", seed: int = 0,
                      warpage: FoilWarpage | None = None, force: bool = False, command: str | None = None,
                      progress: Progress | None = None) -> Experiment5Output:
    """Experiment 5 for every Δh in ``bulges``, written to ``out_dir``: ``results.json`` (per
    Δh, method and camera the Experiment 1 keys plus ``method``, ``sample`` and
    ``max_abs_error_um``, then diagnostics), ``calibration.json``, ``run.json``,
    ``heights.h5`` (group ``case_{k}/{camera}``, attributes ``bulge_mm``, ``method``), ``table.txt``,
    ``height_error.png`` and ``standoff_error.png``."""
    bulges = [float(b) for b in bulges]
    if not bulges:
        raise ValueError("Experiment 5 needs at least one bulge height")
    prov = provenance(command, base.to_toml())
    t0 = time.perf_counter()
    w = warpage if warpage is not None else default_warpage(base)
    interp_um = w.interpolation_error_mm(*w.grid(FOIL_GRID_MM)) * 1e3
    records, calibrations, refs, panels = [], [], [], []
    with atomic_output_dir(out_dir, force=force) as tmp, reconstructions_h5(tmp / "heights.h5", dict(prov)) as add:
        for dh in bulges:
            cases, cal = run_experiment5_bulge(dh, base, warpage=w, downsample=downsample, method=method,
                                               seed=seed, progress=progress)
            calibrations.extend(c for c in cal if "screen_model" in c)
            refs.extend(c for c in cal if "screen_model" not in c)
            row = []
            for c in cases:
                records.append(c.record)
                add(c.case, {"bulge_mm": float(dh), "method": c.method})
                if c.case.camera == next(iter(base.cameras)):
                    p = c.case.p_sample_mm
                    row.append((p[..., 0], p[..., 1], c.case.height_error_mm * 1e3,
                                f"Δh = {dh:g} mm, {c.method} ({c.case.camera}) max |e| "
                                f"{c.record['max_abs_error_um']:.3g} µm"))
            row.sort(key=lambda panel: [m in panel[3] for m in METHODS].index(True))
            panels.append(row)
        write_json(tmp / "results.json", json_ready(records))
        write_json(tmp / "calibration.json", json_ready(calibrations + refs))
        cam0 = next(iter(base.cameras.values())).camera.binned(downsample)
        write_json(tmp / "run.json", {**prov, "experiment": 5, "downsample": downsample, "method": method,
                                      "bulges_mm": bulges, "methods": list(METHODS),
                                      "image_size_px": [cam0.width_px, cam0.height_px],
                                      "printable_area_mm": list(PRINTABLE_AREA_MM),
                                      "nominal_standoff_mm": NOMINAL_STANDOFF_MM, "sample": _sample_label(w),
                                      "foil_grid_mm": FOIL_GRID_MM, "foil_interpolation_error_um": interp_um})
        height_grid_figure(panels, path=tmp / "height_error.png",
                           suptitle="Experiment 5: warped foil, absolute height error z − z_true (calibrated table "
                                    "frame, nothing removed)")
        standoff_figure(records, refs, path=tmp / "standoff_error.png")
        table = experiment5_table(records, refs, f"Experiment 5 — warped foil; {method} mono integration, "
                                                 f"{cam0.width_px}×{cam0.height_px} px per camera\n{_sample_label(w)}; "
                                                 f"{FOIL_GRID_MM:g} mm spline grid, interpolation error "
                                                 f"{interp_um:.3g} µm")
        (tmp / "table.txt").write_text(table + "\n", encoding="utf-8")
    return Experiment5Output(table, ("results.json", "calibration.json", "heights.h5", "table.txt",
                                     "height_error.png", "standoff_error.png"), time.perf_counter() - t0)
