"""Command-line interface (thin: parse, call the library, report).

    pmdsim setup --show
    pmdsim simulate [--setup FILE] [--bulge-mm H] --out DIR [--force]
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
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def simulate_cmd(setup_path, bulge_mm, out_dir, force, quiet) -> None:
    """Simulate a measurement: fringe images, manifest.json and mapping.h5 (paper §2)."""
    from .simulation import image_specs, render_images, trace_setup_camera

    setup = _load(setup_path, bulge_mm)
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
                for spec, img in render_images(setup, cam, m):
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


if __name__ == "__main__":  # pragma: no cover
    main()
