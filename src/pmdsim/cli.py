"""Command-line interface (thin: parse, call the library, report).

    pmdsim setup --show
    pmdsim simulate [--setup FILE] [--bulge-mm H] --out DIR [--force]
    pmdsim study STUDY.toml --out OUT [--scheduler ADDRESS] [--workers N]
"""

from __future__ import annotations

import shlex
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import click

from . import __version__
from .errors import PmdsimError
from .io import MANIFEST_NAME, MAPPING_NAME, IMAGESET_FORMAT, atomic_output_dir, provenance, write_json, write_mapping_h5, write_png
from .setup import Setup, default_setup, load_setup
from .studies.report import experiment3_table, format_table, json_ready, scenario_label


def _load(setup_path: str | None, bulge_mm: float | None) -> Setup:
    setup = default_setup() if setup_path is None else load_setup(setup_path)
    if bulge_mm is not None:
        setup = setup.with_bulge(bulge_mm)
    return setup


class _Group(click.Group):
    """Turns pmdsim's own errors into a one-line message and exit code 2 (no traceback)."""

    def parse_args(self, ctx, args):
        # The command line as invoked (also when main() is called with args, not from sys.argv),
        # recorded in the outputs' provenance.
        ctx.meta["pmdsim.command"] = "pmdsim " + " ".join(shlex.quote(a) for a in args)
        return super().parse_args(ctx, args)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except PmdsimError as e:
            click.echo(f"pmdsim: error: {e}", err=True)
            ctx.exit(2)


@click.group(cls=_Group)
@click.version_option(__version__, prog_name="pmdsim")
def main() -> None:
    """pmdsim: simulate and evaluate phase-measuring deflectometry (PMD)."""


@main.command("setup")
@click.option("--show", is_flag=True, help="Print the setup as TOML (the built-in Table 1 setup by default).")
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False), help="Setup TOML file to validate/show.")
@click.option("--bulge-mm", type=float, default=None, help="Central screen control height Δh in mm (see docs/conventions.md).")
def setup_cmd(show: bool, setup_path: str | None, bulge_mm: float | None) -> None:
    """Show or validate a measurement setup."""
    setup = _load(setup_path, bulge_mm)
    if show:
        click.echo(setup.to_toml(), nl=False)
    else:
        click.echo(f"setup OK: cameras {', '.join(setup.cameras)}; use --show to print it", err=True)


@main.command("simulate")
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False), help="Setup TOML file (default: built-in Table 1 setup).")
@click.option("--bulge-mm", type=float, default=None, help="Central screen control height Δh in mm; + is away from the sample.")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output directory.")
@click.option("--calibration-pose", type=click.IntRange(min=0), default=None,
              help="Image the calibration mirror in this pose (0 = base, see [calibration]) instead of the sample.")
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def simulate_cmd(setup_path, bulge_mm, out_dir, calibration_pose, force, quiet) -> None:
    """Simulate a measurement: fringe images, manifest.json and mapping.h5 (paper §2)."""
    from .simulation.render import image_specs, render_images, trace_setup_camera

    setup = _load(setup_path, bulge_mm)
    if calibration_pose is not None:
        setup = setup.with_mirror_pose(calibration_pose)
    prov = provenance(click.get_current_context().meta.get("pmdsim.command"), setup.to_toml())
    t0 = time.perf_counter()
    with atomic_output_dir(out_dir, force=force) as tmp:
        mappings = {}
        entries = []
        n_images = sum(len(image_specs(setup, c)) for c in setup.cameras)
        with ThreadPoolExecutor(max_workers=2) as pool, click.progressbar(
            length=len(setup.cameras) + n_images, label="simulating", file=sys.stderr, hidden=quiet
        ) as bar:
            for cam in setup.cameras:
                m = trace_setup_camera(setup, cam)
                mappings[cam] = m
                bar.update(1)
                futures = []
                # Calibration pose K uses noise stream K + 1, as the in-memory experiments do.
                stream = None if calibration_pose is None else calibration_pose + 1
                for spec, img in render_images(setup, cam, m, stream=stream):
                    futures.append(pool.submit(write_png, tmp / spec.file, img))
                    entries.append(spec.as_manifest_entry())
                for f in futures:
                    f.result()
                    bar.update(1)
        write_mapping_h5(tmp / MAPPING_NAME, mappings, {k: v for k, v in prov.items()})
        sx, sy = setup.screen.size_mm
        manifest = {
            "format": IMAGESET_FORMAT,
            "format_version": 1,
            **prov,
            "bit_depth": setup.patterns.bit_depth,
            "screen_size_mm": [sx, sy],
            "cameras": {c: {"image_size_px": [cs.camera.width_px, cs.camera.height_px],
                            "status_counts": mappings[c].status_counts()} for c, cs in setup.cameras.items()},
            "images": entries,
        }
        write_json(tmp / MANIFEST_NAME, manifest)
    dt = time.perf_counter() - t0
    valid = ", ".join(f"{c}: {int(m.valid.sum())}/{m.valid.size} valid pixels" for c, m in mappings.items())
    click.echo(f"wrote {len(entries)} images, {MANIFEST_NAME} and {MAPPING_NAME} to {out_dir} in {dt:.1f} s ({valid})", err=True)


@main.command("evaluate")
@click.argument("image_dir", type=click.Path(file_okay=False))
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False),
              help="Setup with the evaluation's knowledge of cameras and screen (default: Table 1).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output directory.")
@click.option("--method", type=click.Choice(["stepwise", "least_squares"]), default="stepwise", show_default=True)
@click.option("--screen-model", type=click.Choice(["planar", "setup"]), default="planar", show_default=True,
              help="planar: the screen frame's x–y plane (the paper's assumption); setup: the setup's screen surface.")
@click.option("--seed-pixel", type=(int, int), default=None, help="Initial pixel (row, column); default: the image centre.")
@click.option("--seed-height-mm", type=float, default=0.0, show_default=True,
              help="Height of the initial point in the sample frame.")
@click.option("--noise-std", type=float, default=None, help="Intensity noise σ_I in grey levels for the σ model (default: quantisation).")
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def evaluate_cmd(image_dir, setup_path, out_dir, method, screen_model, seed_pixel, seed_height_mm, noise_std, force,
                 quiet) -> None:
    """Evaluate a fringe image set: decode, register, reconstruct (paper §2.5).

    IMAGE_DIR holds manifest.json and the images (as written by `pmdsim simulate`, or a real
    camera's images described by such a manifest). Writes OUT/evaluation.h5 and
    OUT/height_{camera}.png.
    """
    import numpy as np

    from .evaluation.pipeline import evaluate_decoded
    from .io.imageset import decode_camera, load_manifest
    from .io import write_evaluation_h5
    from .studies.figures import height_map_figure

    setup = _load(setup_path, None)
    manifest = load_manifest(image_dir, screen_size_mm=setup.screen.size_mm)
    unknown = [c for c in manifest.cameras if c not in setup.cameras]
    if unknown:
        raise click.UsageError(f"camera(s) {unknown} of {image_dir}/manifest.json are not in the setup "
                               f"(setup cameras: {list(setup.cameras)})")
    prov = provenance(click.get_current_context().meta.get("pmdsim.command"), setup.to_toml())
    model_surface = None if screen_model == "planar" else setup.screen.surface
    t0 = time.perf_counter()
    results = {}
    with atomic_output_dir(out_dir, force=force) as tmp:
        with click.progressbar(manifest.cameras, label="evaluating", file=sys.stderr, hidden=quiet) as bar:
            for cam in bar:
                decoded = decode_camera(manifest, cam, screen_size_mm=setup.screen.size_mm, noise_std=noise_std)
                reg, rec = evaluate_decoded(setup, cam, decoded, screen_model=model_surface, method=method,
                                            seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
                results[cam] = (decoded, reg, rec)
                p = rec.points
                height_map_figure(p[..., 0], p[..., 1], rec.height_mm * 1e3,
                                  title=f"{cam}: height in the sample frame ({method}, {screen_model} screen model)",
                                  label="height (µm)", path=tmp / f"height_{cam}.png")
        write_evaluation_h5(tmp / "evaluation.h5", results,
                            {**prov, "method": method, "screen_model": screen_model, "image_dir": str(image_dir)})
    for cam, (decoded, reg, rec) in results.items():
        h = rec.height_mm[rec.reconstructed] * 1e3
        click.echo(f"{cam}: {int(decoded.valid.sum())}/{decoded.valid.size} pixels decoded, "
                   f"{int(rec.reconstructed.sum())} reconstructed; height {np.min(h):.3f} … {np.max(h):.3f} µm "
                   f"(sample frame), {'converged' if rec.converged else 'NOT converged'}")
    click.echo(f"wrote evaluation.h5 and height_*.png to {out_dir} in {time.perf_counter() - t0:.1f} s", err=True)


@main.command("calibrate")
@click.argument("image_dirs", nargs=-1, required=True, type=click.Path(file_okay=False))
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False),
              help="Nominal setup: start values and the calibration poses (default: Table 1).")
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False), help="Calibrated setup (TOML).")
@click.option("--stride", type=click.IntRange(min=1), default=None,
              help="Use every stride-th pixel (default: the setup's calibration.observation_stride_px).")
@click.option("--max-iter", type=click.IntRange(min=1), default=100, show_default=True)
@click.option("--force", is_flag=True, help="Replace an existing output file.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def calibrate_cmd(image_dirs, setup_path, out_path, stride, max_iter, force, quiet) -> None:
    """Holistic calibration with a planar mirror (paper §4).

    IMAGE_DIRS: one image set per mirror pose, in the order of the setup's calibration poses
    (base, lifts, tilts; see `pmdsim setup --show`). Cameras (intrinsics, distortion, poses) and
    the mirror planes are estimated jointly; the screen is held at its nominal pose (the gauge)
    and modelled as planar. Writes a setup file for `pmdsim evaluate --setup` whose sample frame
    is the calibrated table plane (pose 0), with the standard deviations in [calibration_report].
    """
    from .calibration import calibrate, nominal_state, observations_from_mapping
    from .calibration import calibrated_setup, calibration_summary
    from .io.imageset import decode_camera, load_manifest
    from .io import atomic_file

    nominal = _load(setup_path, None).with_bulge(0.0)
    poses = nominal.calibration.mirror_poses(nominal.sample)
    if len(image_dirs) != len(poses):
        raise click.UsageError(f"got {len(image_dirs)} image directories, but the setup lists {len(poses)} "
                               f"calibration poses ({', '.join(l for l, _ in poses)}); give one per pose, in order")
    if Path(out_path).exists() and not force:
        raise click.ClickException(f"output {out_path!r} exists; pass --force to replace it")
    stride = stride or nominal.calibration.observation_stride_px
    obs = []
    with click.progressbar(list(enumerate(image_dirs)), label="decoding", file=sys.stderr, hidden=quiet) as bar:
        for k, d in bar:
            manifest = load_manifest(d, screen_size_mm=nominal.screen.size_mm)
            for cam in manifest.cameras:
                if cam not in nominal.cameras:
                    raise click.UsageError(f"camera {cam!r} of {d} is not in the setup ({list(nominal.cameras)})")
                dec = decode_camera(manifest, cam, screen_size_mm=nominal.screen.size_mm)
                obs.append(observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=stride,
                                                     screen_std_xy_mm=dec.std_xy_mm))
    start = nominal_state(nominal, [T for _, T in poses])
    result = calibrate(obs, start, max_iter=max_iter)
    if not result.converged:
        raise click.ClickException(f"the calibration did not converge: {result.reason} "
                                   f"(RMS {result.rms_px:.4g} px after {result.iterations} iterations); nothing written")
    model = calibrated_setup(nominal, result)
    summary = json_ready(calibration_summary(result, model))
    report = {"pmdsim_version": __version__,
              "command": click.get_current_context().meta.get("pmdsim.command") or "",
              "converged": summary["converged"], "reason": summary["reason"], "iterations": summary["iterations"],
              "rms_px": summary["rms_px"], "n_residuals": summary["n_residuals"],
              "condition_number": summary["condition_number"],
              "determination": result.determination_report(),
              "std": {name: c["std"] for name, c in summary["cameras"].items()}}
    from .setup.toml import dump_toml

    doc = model.to_dict()
    doc["calibration_report"] = report
    with atomic_file(out_path, force=force, mode="w") as f:
        f.write(dump_toml(doc))
    for name, c in summary["cameras"].items():
        click.echo(f"{name}: fx {c['fx_px']:.3f} ± {c['std']['fx_px']:.3f} px, fy {c['fy_px']:.3f} ± "
                   f"{c['std']['fy_px']:.3f} px, pp ({c['ppx_px']:.3f}, {c['ppy_px']:.3f}) px")
    click.echo(result.determination_report(), err=True)
    click.echo(f"calibration converged ({result.reason}); RMS {result.rms_px:.4f} px over {result.n_residuals} "
               f"residuals; wrote {out_path}", err=True)


def _experiment3(out_dir, setup_path, downsample, method, bulges_mm, grids, deformations, mirror_sags_um,
                 sag_bulge_mm, force, quiet) -> None:
    """`pmdsim experiment 3`: calibrate the screen's shape (paper §5).

    For every scenario (the paper's bulges, mismatching deformations, a sagged calibration
    mirror) and screen model (planar, n×n free-form grids) calibrate and reconstruct the planar
    sample; errors against the number of free screen heights.
    """
    from .studies import SCREEN_DEFORMATIONS, experiment3_scenarios, run_experiment3
    from .io import reconstructions_h5

    bulges = _parse_list(bulges_mm, float, "--bulges-mm") if bulges_mm.strip() else []
    sizes = _parse_list(grids, int, "--grids") if grids.strip() else []
    if any(g < 3 for g in sizes):
        raise click.BadParameter(f"--grids: every grid needs at least 3 × 3 control points, got {grids!r}")
    kinds = [k.strip() for k in deformations.split(",") if k.strip()]
    bad = [k for k in kinds if k not in SCREEN_DEFORMATIONS]
    if bad:
        raise click.BadParameter(f"--deformations: unknown {bad}; expected some of {list(SCREEN_DEFORMATIONS)}")
    sags = _parse_list(mirror_sags_um, float, "--mirror-sags-um") if mirror_sags_um.strip() else []
    base = _load(setup_path, None)
    prov = provenance(click.get_current_context().meta.get("pmdsim.command"), base.to_toml())
    t0 = time.perf_counter()
    scenarios = experiment3_scenarios(base, downsample=downsample, bulges=bulges, deformations=kinds,
                                      mirror_sags_um=sags, sag_bulge_mm=sag_bulge_mm)
    if not scenarios:
        raise click.BadParameter("nothing to run: no bulges, deformations or mirror sags given")
    records, calibrations, undetermined = [], [], []
    n_models = 1 + len(sizes)
    with atomic_output_dir(out_dir, force=force) as tmp, \
            reconstructions_h5(tmp / "heights.h5", {k: v for k, v in prov.items()}) as add_case:
        with click.progressbar(length=len(scenarios) * (n_models + 1), label="experiment 3", file=sys.stderr,
                               hidden=quiet) as bar:
            for sc, label, e, recs in run_experiment3(scenarios, sizes, method=method,
                                                      progress=lambda msg: bar.update(1)):
                if isinstance(e, Exception):  # the data cannot determine this model: say so, go on
                    undetermined.append(f"{sc.label}, {label} screen model: {e}")
                    calibrations.append({"scenario": sc.name, "bulge_mm": sc.bulge_mm,
                                         "mirror_sag_um": sc.mirror_sag_um, "screen_model": label,
                                         "error": str(e)})
                    continue
                if not e.result.converged:
                    raise click.ClickException(f"{sc.label}, screen model {label}: calibration did not converge: "
                                               f"{e.result.reason}")
                tag = {"bulge": f"bulge_{sc.bulge_mm:g}mm", "mirror_sag": f"mirror_sag_{sc.mirror_sag_um:g}um"}.get(
                    sc.name, sc.name)
                records.extend(recs)
                calibrations.append({"scenario": sc.name, "bulge_mm": sc.bulge_mm, "mirror_sag_um": sc.mirror_sag_um,
                                     "screen_model": label, **e.result.to_dict(), "deviation_from_truth": e.deviation})
                for c in e.cases:  # written as they come: the run never holds all height maps
                    add_case(c, f"{tag}/{label}/{c.camera}")
        write_json(tmp / "results.json", json_ready(records))
        write_json(tmp / "calibration.json", json_ready(calibrations))
        write_json(tmp / "run.json", {**prov, "experiment": 3, "downsample": downsample, "method": method,
                                      "grids": sizes, "deformations": kinds, "mirror_sags_um": sags,
                                      "sag_bulge_mm": sag_bulge_mm})
        table = experiment3_table(records)
        if undetermined:
            table += "\n\nNot determined by the calibration data (full reasons in calibration.json):\n" + "\n".join(
                "  " + (u if len(u) <= 400 else u[:400] + " …") for u in undetermined)
        (tmp / "table.txt").write_text(table + "\n", encoding="utf-8")
        if records:
            _experiment3_figure(tmp / "error_vs_free_parameters.png", records, downsample)
    click.echo(table)
    click.echo(f"wrote results.json, calibration.json, heights.h5, table.txt, error_vs_free_parameters.png to "
               f"{out_dir} in {time.perf_counter() - t0:.1f} s", err=True)


def _experiment3_figure(path, records: list[dict], downsample: int) -> None:
    """Error and calibration residual against the number of free screen heights."""
    import numpy as np

    from .studies.figures import error_vs_free_parameters_figure

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
    error_vs_free_parameters_figure(series, [f"{m.replace('x', '×')} ({n})" for m, n in models],
                                    suptitle=f"Experiment 3: calibrated screen models (downsample {downsample})",
                                    floor_um=max(floor) if floor else None, path=path)


def scenario_label(r: dict) -> str:
    if r["scenario"] == "bulge":
        return f"bulge Δh = {r['bulge_mm']:g} mm"
    if r["scenario"] == "mirror_sag":
        return f"mirror sag {r['mirror_sag_um']:g} µm (Δh = {r['bulge_mm']:g} mm)"
    return f"{r['scenario']} deformation"


def experiment3_table(records: list[dict]) -> str:
    """Experiment 3's table: one line per scenario and screen model, cameras L / R."""
    lines = [f"Experiment 3 — calibrated screen models; {len(records)} reconstructions",
             f"{'scenario':34s} {'model':>7s} {'free':>5s} {'max.diff µm L/R':>19s} {'dev µm L/R':>17s} "
             f"{'tilt µrad L/R':>15s} {'calib RMS px':>13s} {'screen err µm':>14s} {'centre h mm':>12s}"]
    keyed = {}
    for r in records:
        keyed.setdefault((scenario_label(r), r["screen_model"]), []).append(r)
    for (sl, model), rs in keyed.items():
        def pair(k, f):
            return "/".join(format(x[k], f) for x in rs)
        ch = rs[0].get("screen_central_height_mm")
        lines.append(f"{sl:34s} {model:>7s} {rs[0]['free_parameters']:5d} {pair('max_height_diff_um', '.4f'):>19s} "
                     f"{pair('max_dev_plane_um', '.4f'):>17s} {pair('tilt_urad', '.2f'):>15s} "
                     f"{rs[0]['calibration_rms_px']:13.5f} {rs[0]['screen_shape_max_error_um']:14.2f} "
                     f"{'' if ch is None else f'{ch:12.6f}'}")
    return "\n".join(lines)


_METRIC_ROWS = (
    ("max_height_diff_um", "Max. height difference [µm]", 0),
    ("max_dev_plane_um", "Max. deviation from best-fit plane [µm]", 1),
    ("tilt_urad", "Best-fit plane tilt angle [µrad]", 2),
)


def format_table(records: list[dict], paper: dict, title: str) -> str:
    """The paper's table layout (Δh across, L/R below), ours with the paper's values beneath."""
    bulges = sorted({r["bulge_mm"] for r in records})
    cams = list(dict.fromkeys(r["camera"] for r in records))
    by = {(r["bulge_mm"], r["camera"]): r for r in records}
    w = 9
    lines = [title]
    head = f"{'Screen bulge height Δh':42s}" + "".join(f"{f'{b:g} mm':^{w * len(cams)}s}" for b in bulges)
    lines.append(head)
    lines.append(f"{'Camera':42s}" + "".join(f"{c[:1].upper():>{w}s}" for b in bulges for c in cams))
    for key, label, idx in _METRIC_ROWS:
        ours = "".join(f"{by[(b, c)][key]:{w}.{3 if key != 'tilt_urad' else 1}f}" if (b, c) in by else " " * w
                       for b in bulges for c in cams)
        lines.append(f"{label:42s}{ours}")
        ref = "".join(f"{paper[(b, c)][idx]:{w}.1f}" if (b, c) in paper else f"{'–':>{w}s}" for b in bulges for c in cams)
        lines.append(f"{'  paper':42s}{ref}")
    return "\n".join(lines)


@main.command("experiment")
@click.argument("number", type=click.Choice(["1", "2", "3"]))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output directory.")
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False), help="Base setup (default: Table 1).")
@click.option("--downsample", type=click.IntRange(min=1), default=1, show_default=True,
              help="Bin the cameras K×K (same field of view) for a quick look.")
@click.option("--method", type=click.Choice(["stepwise", "least_squares"]), default="stepwise", show_default=True,
              help="Surface integration (paper: stepwise).")
@click.option("--bulges-mm", default="0,1,2,3", show_default=True, help="Comma-separated screen bulge heights Δh.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Experiment 2: seed of the start values' errors.")
@click.option("--write-images", is_flag=True, help="Experiment 1: also write the rendered fringe images under OUT/images.")
@click.option("--grids", default="3,5,9", show_default=True,
              help="Experiment 3: free-form screen models, comma-separated n for n×n grids (planar always run).")
@click.option("--deformations", default="offcentre,random", show_default=True,
              help="Experiment 3: mismatching true screen deformations (offcentre, random; empty for none).")
@click.option("--mirror-sags-um", default="1,5", show_default=True,
              help="Experiment 3: sags of a non-planar calibration mirror in µm (empty for none).")
@click.option("--sag-bulge-mm", type=float, default=3.0, show_default=True,
              help="Experiment 3: the screen bulge Δh of the mirror-sag scenarios.")
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def experiment_cmd(number, out_dir, setup_path, downsample, method, bulges_mm, seed, write_images, grids,
                   deformations, mirror_sags_um, sag_bulge_mm, force, quiet) -> None:
    """Run one of the paper's experiments.

    1 = perfect setup knowledge, planar screen model (Table 2, Fig. 4);
    2 = simulated holistic calibration with a planar mirror, then reconstruction (Table 3, Fig. 5);
    3 = beyond the paper (§5): calibrate free-form screen models of increasing flexibility, with
    the paper's bulges, mismatching deformations and a non-planar calibration mirror.
    """
    from .studies import PAPER_TABLE2, PAPER_TABLE3, run_experiment1_case, run_experiment2_bulge
    from .io import write_reconstructions_h5
    from .studies.figures import height_grid_figure

    if number == "3":
        return _experiment3(out_dir, setup_path, downsample, method, bulges_mm, grids, deformations, mirror_sags_um,
                            sag_bulge_mm, force, quiet)

    bulges = _parse_list(bulges_mm, float, "--bulges-mm")
    base = _load(setup_path, None)
    prov = provenance(click.get_current_context().meta.get("pmdsim.command"), base.to_toml())
    t0 = time.perf_counter()
    cases = []
    calibrations = []
    paper = PAPER_TABLE2 if number == "1" else PAPER_TABLE3
    with atomic_output_dir(out_dir, force=force) as tmp:
        if number == "1":
            sink = None
            pool = ThreadPoolExecutor(max_workers=2) if write_images else None
            futures = []
            jobs = [(b, c) for b in bulges for c in base.cameras]
            with click.progressbar(jobs, label="experiment 1", file=sys.stderr, hidden=quiet,
                                   item_show_func=lambda j: f"Δh={j[0]:g} mm {j[1]}" if j else "") as bar:
                for dh, cam in bar:
                    if pool is not None:
                        d = tmp / "images" / f"bulge_{dh:g}mm"
                        d.mkdir(parents=True, exist_ok=True)
                        sink = lambda spec, img, d=d: futures.append(pool.submit(write_png, d / spec.file, img))
                    cases.append(run_experiment1_case(dh, cam, base=base, downsample=downsample, method=method,
                                                      image_sink=sink))
            if pool is not None:
                for f in futures:
                    f.result()
                pool.shutdown()
            records = [c.as_record() for c in cases]
        else:
            n_steps = len(bulges) * (len(base.calibration.mirror_poses(base.sample)) * len(base.cameras) + 1
                                     + len(base.cameras))
            with click.progressbar(length=n_steps, label="experiment 2", file=sys.stderr, hidden=quiet) as bar:
                for dh in bulges:
                    e2 = run_experiment2_bulge(dh, base=base, downsample=downsample, method=method, seed=seed,
                                               progress=lambda msg: bar.update(1))
                    if not e2.result.converged:
                        raise click.ClickException(
                            f"Δh = {dh:g} mm: the calibration did not converge: {e2.result.reason}")
                    from .calibration import calibration_summary

                    summary = calibration_summary(e2.result, e2.model)
                    calibrations.append({"bulge_mm": dh, **summary, "deviation_from_truth": e2.deviation})
                    for c in e2.cases:
                        cases.append(c)
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
        meta = {**prov, "experiment": int(number), "downsample": downsample, "method": method,
                "image_size_px": [cam0.width_px, cam0.height_px],
                f"paper_table{2 if number == '1' else 3}": [
                    {"bulge_mm": b, "camera": c, "max_height_diff_um": v[0], "max_dev_plane_um": v[1], "tilt_urad": v[2]}
                    for (b, c), v in paper.items()]}
        write_json(tmp / "results.json", json_ready(records))
        write_json(tmp / "run.json", meta)
        write_reconstructions_h5(tmp / "heights.h5", cases, {k: v for k, v in prov.items()})
        shown = ([b for b in (0.0, 3.0) if b in bulges] or bulges[:2]) if number == "1" else [max(bulges)]
        panels = []
        for b in shown:
            row = []
            for c in cases:
                if c.bulge_mm == b:
                    p = c.points_mm
                    row.append((p[..., 0], p[..., 1], c.height_error_mm * 1e3,
                                f"Δh = {b:g} mm, {c.camera} camera: PV {c.metrics['max_height_diff_um']:.3g} µm"))
            panels.append(row)
        what = ("perfect setup knowledge, planar screen model" if number == "1"
                else "simulated holistic calibration, planar screen model")
        frame = "sample frame" if number == "1" else "calibrated table frame"
        height_grid_figure(panels, path=tmp / f"figure{3 + int(number)}.png",
                           suptitle=f"Experiment {number}: reconstructed planar sample, height error ({frame}, {method})")
        table = format_table(records, paper,
                             f"Experiment {number} — {what}; {method} integration, "
                             f"{cam0.width_px}×{cam0.height_px} px per camera")
        if calibrations:
            table += "\n" + "\n".join(
                f"Δh = {c['bulge_mm']:g} mm: calibration RMS {c['rms_px']:.4f} px, {c['iterations']} iterations; "
                f"calibrated frame turned {c['deviation_from_truth']['table_turn_deg']:.3f}° against the truth"
                for c in calibrations)
        (tmp / "table.txt").write_text(table + "\n", encoding="utf-8")
    click.echo(table)
    click.echo(f"wrote results.json, heights.h5, figure{3 + int(number)}.png, table.txt to {out_dir} "
               f"in {time.perf_counter() - t0:.1f} s", err=True)


@main.command("study")
@click.argument("study_file", type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output directory (reused by a rerun: only missing cases are computed).")
@click.option("--scheduler", default=None, help="Address of an existing Dask scheduler (tcp://host:port); "
              "default: a LocalCluster on this machine.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="LocalCluster worker processes (default: one per core; numba threads = cores // workers).")
@click.option("--quiet", is_flag=True, help="No progress lines.")
def study_cmd(study_file, out_dir, scheduler, workers, quiet) -> None:
    """Run a parameter sweep / Monte-Carlo study (STUDY.toml) on Dask: OUT/results.parquet, .csv,
    summary.txt and figures."""
    from .studies.study import run_study
    from .studies.study_file import load_study
    from .studies.study_summary import write_study_outputs

    if scheduler is not None and workers is not None:
        raise click.UsageError("--workers sets the size of the LocalCluster; with --scheduler the cluster's "
                               "workers are used (omit --workers)")
    study = load_study(study_file)
    click.echo(f"study {study.name!r}: {study.n_cases} cases, action {study.action} "
               f"({'scheduler ' + scheduler if scheduler else 'LocalCluster'})", err=True)

    def progress(d: dict) -> None:
        if not quiet:
            eta = d["eta_s"]
            left = "?" if eta != eta else f"{eta:.0f} s"
            rec = d["record"]
            note = f"  [case {rec['case_index']} failed: {rec['error']}]" if rec["status"] == "failed" else ""
            click.echo(f"  {d['done']}/{d['total']} done, {d['failed']} failed, time left ≈ {left}{note}", err=True)

    try:
        run = run_study(study, out_dir, scheduler=scheduler, n_workers=workers, progress=progress)
    except KeyboardInterrupt:
        click.echo(f"pmdsim: interrupted; the finished cases are recorded in {out_dir}: rerun the same command "
                   "to compute the rest", err=True)
        sys.exit(130)
    written = write_study_outputs(study, out_dir)
    click.echo(f"{run.n_computed} cases computed, {run.n_reused} reused, {run.n_failed} failed, "
               f"{run.n_missing} missing, in {run.elapsed_s:.1f} s → {out_dir} ({', '.join(written)})", err=True)
    if run.n_missing:
        click.echo("pmdsim: error: some cases have no result (workers lost); rerun the same command to compute them",
                   err=True)
        sys.exit(1)


def _parse_list(text: str, kind, option: str) -> list:
    """Comma-separated numbers of an option, with a clear error."""
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        what = "integers" if kind is int else "numbers"
        raise click.BadParameter(f"{option} must be comma-separated {what}, got {text!r}") from None
    if not values:
        raise click.BadParameter(f"{option} lists no value")
    return values


def json_ready(obj):
    """numpy scalars → Python numbers, recursively (for JSON)."""
    import numpy as np

    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


if __name__ == "__main__":  # pragma: no cover
    main()
