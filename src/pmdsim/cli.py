"""Command-line interface: parses options, calls the library, prints (docs/architecture.md).

    pmdsim setup --show | --setup FILE
    pmdsim simulate [--setup FILE] [--bulge-mm H] --out DIR [--force]
    pmdsim evaluate IMAGE_DIR [--setup FILE] --out DIR [--anchor-* | --seed-*]
    pmdsim import sofast --measurement M.h5 --camera C.h5 --display D.h5 --orientation O.h5
                         --calibration CAL.h5 [--facet F.json] --out DIR
    pmdsim calibrate POSE_DIRS... [--setup FILE] --out FILE
    pmdsim experiment 1|2|3|4|5|6 --out DIR
    pmdsim study STUDY.toml --out OUT [--scheduler ADDRESS] [--workers N]

Every pmdsim error becomes one line ``pmdsim: error: …`` and exit code 2. SIGINT, SIGTERM and
SIGHUP abort cleanly (:mod:`pmdsim.interrupts`): exit code 130 / 143 / 129, no output written. Nothing
heavy (numba, numpy kernels) is imported before a command runs: ``--version`` and ``--help``
compile nothing. The work is done by
:mod:`pmdsim.studies.jobs` (one measurement, disk to disk) and :mod:`pmdsim.studies.runs`
(the experiments); tables and figures live in the studies layer.
"""

from __future__ import annotations

import logging
import shlex
import signal
import sys
from typing import TYPE_CHECKING

import click

from . import __version__, interrupts
from .errors import ComputationError, PmdsimError

if TYPE_CHECKING:
    from .setup import Setup


def _load(setup_path: str | None, bulge_mm: float | None) -> Setup:
    from .io.heightmap import load_setup  # reads any [sample] height_map file (pmdsim.io.heightmap)
    from .setup import default_setup

    setup = default_setup() if setup_path is None else load_setup(setup_path)
    if bulge_mm is not None:
        setup = setup.with_bulge(bulge_mm)
    return setup


def _inputs(setup_path: str | None, setup: Setup | None = None) -> list[str]:
    """The files a setup brings in (the setup file, a ``[sample] height_map`` file relative to
    it): outputs must not touch them (:func:`pmdsim.io.outputs.check_output_target`)."""
    from pathlib import Path

    out = [setup_path] if setup_path else []
    shape = None if setup is None else setup.sample.shape
    f = getattr(shape, "file", None)
    if f:
        p = Path(f)
        out.append(str(p if p.is_absolute() or not setup_path else Path(setup_path).parent / p))
    return out


#: The kernel subpackages each command compiles on first use, and the cold time measured for it
#: (docs/benchmarks.md, "First run"); the first-run note (:class:`_Command`) names them.
_KERNELS = {
    "simulate": (("geometry", "simulation"), "about 45 s"),
    "evaluate": (("geometry", "evaluation"), None),
    "calibrate": (("geometry", "evaluation", "calibration"), None),
    "experiment": (("geometry", "simulation", "evaluation"), None),
    "study": (("geometry", "simulation", "evaluation"), None),
}


class _Command(click.Command):
    """A command that says, in one line on stderr before it starts, that it is compiling numba
    kernels when their cache is cold (:func:`pmdsim._cold_kernel_packages`: a fresh install or
    new sources); silent on warm runs. ``--help`` and ``--version`` never get here. Printed with
    ``--quiet`` too (that flag hides progress bars, not notes): a silent minute is what it explains."""

    def invoke(self, ctx):
        _RAN["command"] = self.name
        if self.name not in _NOTE_AFTER_CHECKS:
            _cold_note(self.name)
        return super().invoke(ctx)


#: The command this process ran (:class:`_Command`), for :data:`_FAST_EXIT`.
_RAN: dict = {}

#: Commands whose process, once the command is over, ends by :func:`_exit_now` instead of
#: Python's full shutdown: their outputs are committed and closed by then, and tearing down the
#: modules (numba's and LLVM's objects) and freeing the arrays one by one took 0.20 s of each
#: ``pmdsim evaluate`` (issue 25; docs/benchmarks.md, "the command's start-up").
_FAST_EXIT = {"evaluate"}


def _is_program() -> bool:
    """Whether this process is the ``pmdsim`` program (the console script, ``python -m pmdsim``
    or ``python -m pmdsim.cli``), not a Python program that called :func:`main` itself."""
    import os

    prog = os.path.abspath(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    here = os.path.dirname(os.path.abspath(__file__))
    return os.path.basename(prog) == "pmdsim" or prog in (os.path.join(here, "cli.py"), os.path.join(here, "__main__.py"))


def _exit_now(code) -> None:
    """End the process with ``code`` (a :class:`SystemExit` code: None → 0, an int, else printed
    and 1) after what Python's shutdown runs first — the threads' exit hooks and joins
    (``threading._shutdown``: ``concurrent.futures`` workers), the :mod:`atexit` handlers, the
    flush of stdout and stderr — but without the module teardown and garbage collection."""
    import atexit
    import os
    import threading

    shutdown = getattr(threading, "_shutdown", None)
    if shutdown is None:  # not CPython's threading: leave the exit to Python
        raise SystemExit(code)
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code
    else:
        print(code, file=sys.stderr)
        status = 1
    shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # closed or broken pipe: nothing more to write
            pass
    os._exit(status & 0xFF)


#: Commands that print the first-run note themselves, once their input is checked and before
#: the work that compiles: a bad study file or an unreachable scheduler is refused in its one
#: line without a note about compiling that will not happen (the kernels compile in the workers).
_NOTE_AFTER_CHECKS = {"study"}


def _cold_note(command: str) -> None:
    """The first-run note of ``command`` on stderr when its kernels' cache is cold (:class:`_Command`)."""
    packages, took = _KERNELS.get(command, ((), None))
    if packages:
        from . import _cold_kernel_packages

        cold = _cold_kernel_packages(packages)
        if cold:
            click.echo(f"pmdsim: note: numba kernels not compiled yet ({', '.join(cold)}): this run compiles "
                       f"them first ({took or 'minutes'} on 2 cores), later runs use the cache", err=True)


class _Group(click.Group):
    """Turns pmdsim's own errors into a one-line message (no traceback): exit code 2 for bad
    input, 1 for a computation that failed (:class:`~pmdsim.errors.ComputationError`)."""

    command_class = _Command

    def parse_args(self, ctx, args):
        # The command line as invoked (also when main() is called with args, not from sys.argv),
        # recorded in the outputs' provenance.
        ctx.meta["pmdsim.command"] = "pmdsim " + " ".join(shlex.quote(a) for a in args)
        return super().parse_args(ctx, args)

    def main(self, args=None, *a, **k):
        # SIGINT/SIGTERM → Interrupted (pmdsim.interrupts); notes of the output layer (a stale
        # partial removed) → "pmdsim: note: …". A call with explicit args (tests, scripts) gets
        # the previous handlers back; the command-line process keeps them until it exits, so
        # that a signal during the interpreter's shutdown is not reported as "Exception ignored".
        interrupts.reset()
        old = {s: signal.getsignal(s) for s in interrupts.SIGNALS}
        interrupts.install()
        log = logging.getLogger("pmdsim")
        note = logging.StreamHandler(sys.stderr)
        note.setFormatter(logging.Formatter("pmdsim: note: %(message)s"))
        log.addHandler(note)
        code = _RUNNING = object()
        try:
            return super().main(args, *a, **k)
        except SystemExit as e:  # click's standalone mode ends every command so
            code = e.code
            raise
        finally:
            log.removeHandler(note)
            interrupts.finish(block=args is None)  # from now on signals are only recorded (or held back)
            if args is not None and interrupts.installed():
                for s, h in old.items():
                    signal.signal(s, h)
            if args is None and code is not _RUNNING and _RAN.get("command") in _FAST_EXIT and _is_program():
                _exit_now(code)

    def invoke(self, ctx):
        try:
            rv = super().invoke(ctx)
        except click.UsageError as e:  # a bad option or argument: one line in pmdsim's style, exit 2
            where = e.ctx.command_path if e.ctx is not None else "pmdsim"
            click.echo(f"pmdsim: error: {e.format_message()} (see '{where} --help')", err=True)
            ctx.exit(2)
        except ComputationError as e:  # the inputs were fine, the computation failed: exit 1
            click.echo(f"pmdsim: error: {e}", err=True)
            ctx.exit(1)
        except PmdsimError as e:  # bad input: exit 2
            click.echo(f"pmdsim: error: {e}", err=True)
            ctx.exit(2)
        except KeyboardInterrupt:  # SIGINT or SIGTERM (pmdsim.interrupts): nothing was committed
            _interrupted(ctx, interrupts.received() or signal.SIGINT)
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise  # click's own control flow
        except Exception:
            # C code that ran the signal's handler can turn the Interrupted raised there into an
            # error of its own: an extension module interrupted in its initialisation gives
            # "ImportError: initialization failed" (seen with scipy's while a command imports it).
            # With a signal recorded and nothing committed, the signal is what ended the run.
            signum = interrupts.received()
            if signum is None or interrupts.committed():
                raise
            _interrupted(ctx, signum)
        signum = interrupts.received()
        if signum is not None:  # a signal Python swallowed (in a finaliser), or one after the commit
            if interrupts.committed():
                click.echo(f"pmdsim: note: {interrupts.signal_name(signum)} received after "
                           f"{interrupts.committed()} was complete; it is kept", err=True)
            else:
                click.echo(f"pmdsim: interrupted ({interrupts.signal_name(signum)})", err=True)
                ctx.exit(interrupts.exit_code(signum))
        return rv


def _interrupted(ctx, signum: int) -> None:
    """The one line of an interrupted command, and its exit code (128 + signum)."""
    click.echo(f"pmdsim: interrupted ({interrupts.signal_name(signum)}): no output written, an existing "
               "output is unchanged", err=True)
    ctx.exit(interrupts.exit_code(signum))


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
        return
    shape = setup.sample.shape
    if shape is not None:  # curved sample (issue 14): what it is, and what resampling cost
        report = setup.sample.interpolation_report
        what = (f"height map {shape.file!r} resampled onto the {len(setup.sample.grid_x_mm)} × "
                f"{len(setup.sample.grid_y_mm)} spline grid, {report.summary()}" if report is not None
                else f"{shape.kind} (closed form, exact: no interpolation)" if hasattr(shape, "kind")
                else f"height map {shape.file!r}")
        click.echo(f"sample: {what}", err=True)
    n_warn = _setup_checks(setup)
    click.echo(f"setup OK: cameras {', '.join(setup.cameras)}"
               + (f" ({n_warn} warning{'s' if n_warn > 1 else ''} above)" if n_warn else "")
               + "; use --show to print it", err=True)


def _setup_checks(setup: Setup, info: bool = True) -> int:
    """The setup's findings (coverage, clipping, periods; issue 11) — the same for `setup --setup`
    and `simulate`: printed, exit 2 on a fatal one. Returns the number of warnings."""
    from .studies.checks import setup_findings

    findings = setup_findings(setup)
    for f in findings:
        if f.level == "info" and not info:
            continue
        prefix = {"fatal": "pmdsim: error: ", "warning": "pmdsim: warning: ", "info": "  "}[f.level]
        click.echo(prefix + f.message, err=True)
    if any(f.level == "fatal" for f in findings):
        sys.exit(2)
    return sum(f.level == "warning" for f in findings)


def _setup_source(setup_path: str | None) -> str:
    """How error messages name the setup: its file, or the built-in one when --setup is missing."""
    return f"setup {setup_path}" if setup_path else "the built-in Table 1 setup (no --setup given)"


def _command() -> str:
    return click.get_current_context().meta.get("pmdsim.command") or ""


class _Steps:
    """A command's progress on stderr, one ``step(message)`` per finished step.

    In a terminal: click's progress bar. Otherwise (a log file, a pipe, CI) click's bar prints its
    label once and then nothing until the end, so a 20-minute experiment looks hung: one line
    ``  LABEL i/n after T s: MESSAGE`` instead, at most one per ``every_s`` seconds, and always for
    the last step. ``--quiet`` hides both."""

    def __init__(self, length: int, label: str, quiet: bool, every_s: float = 10.0):
        import time

        self.length, self.label, self.quiet, self.every_s = length, label, quiet, every_s
        self.clock, self.done, self.bar = time.monotonic, 0, None
        self.t0 = self.last = time.monotonic()

    def __enter__(self) -> _Steps:
        if not self.quiet and sys.stderr.isatty():
            self.bar = click.progressbar(length=self.length, label=self.label, file=sys.stderr).__enter__()
        return self

    def step(self, message: str | None = None) -> None:
        self.done += 1
        if self.bar is not None:
            self.bar.update(1)
            return
        now = self.clock()
        if self.quiet or (now - self.last < self.every_s and self.done < self.length):
            return
        self.last = now
        tail = f": {message}" if message else ""
        click.echo(f"  {self.label} {self.done}/{self.length} after {now - self.t0:.0f} s{tail}", err=True)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.__exit__(*exc)
            self.bar = None


def _bar(length: int, label: str, quiet: bool) -> _Steps:
    return _Steps(length, label, quiet)


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
    from .studies.jobs import simulate_to_dir, simulation_steps

    setup = _load(setup_path, bulge_mm)
    _setup_checks(setup, info=False)  # as `setup --setup` does: refuse before writing, warn
    steps = simulation_steps(setup if calibration_pose is None else setup.with_mirror_pose(calibration_pose))
    with _bar(steps, "simulating", quiet) as bar:
        summary = simulate_to_dir(setup, out_dir, force=force, command=_command(), calibration_pose=calibration_pose,
                                  progress=bar.step, inputs=_inputs(setup_path, setup))
    click.echo(summary.as_text(out_dir), err=True)


@main.command("evaluate")
@click.argument("image_dir", type=click.Path(file_okay=False))
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False),
              help="Setup with the evaluation's knowledge of cameras and screen (default: Table 1).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output directory.")
@click.option("--method", type=click.Choice(["stepwise", "least_squares"]), default=None,
              help="Surface integration. Default: the manifest's method (least_squares for imported real "
                   "measurements), else stepwise. Not with --stereo.")
@click.option("--screen-model", type=click.Choice(["planar", "setup"]), default=None,
              help="planar: the screen frame's x–y plane (the paper's assumption); setup: the setup's screen surface. "
                   "Default: the manifest's screen_model, else planar.")
@click.option("--seed-pixel", type=(int, int), default=None,
              help="Pixel (row, column) of known height (--seed-height-mm, default 0); default: the valid pixel nearest "
                   "the mask centroid.")
@click.option("--seed-height-mm", type=float, default=None,
              help="Known height of the seed pixel in the sample frame (an anchor).")
@click.option("--anchor-distance-mm", type=float, default=None,
              help="Anchor: the surface at --anchor-pixel is this far (mm) from --anchor-point-mm (world).")
@click.option("--anchor-pixel", type=(float, float), default=None, help="Anchor pixel (row, column), may be fractional.")
@click.option("--anchor-point-mm", type=(float, float, float), default=None,
              help="Anchor point (world, mm) of --anchor-distance-mm.")
@click.option("--noise-std", type=float, default=None, help="Intensity noise σ_I in grey levels for the σ model (default: quantisation).")
@click.option("--anchor-distance-std-mm", type=click.FloatRange(0.0), default=None,
              help="Standard uncertainty of the anchor's distance (or seed height), mm, added to height_std_um "
                   "(default: the manifest anchor's distance_std_mm, else 0).")
@click.option("--no-uncertainty", is_flag=True,
              help="Skip the per-pixel standard uncertainties (height_std_um, slope_std_urad; docs/conventions.md).")
@click.option("--stereo", is_flag=True,
              help="Stereo: absolute heights from all cameras without a seed (docs/stereo.md); no --seed-pixel.")
@click.option("--search-range-mm", type=(float, float), default=None,
              help="--stereo: heights searched along the view rays, sample frame (default: -20 20).")
@click.option("--min-valid-fraction", type=click.FloatRange(0.0, 1.0), default=0.5, show_default=True,
              help="Fail (exit 1, outputs kept for inspection) when fewer of the pixels that see fringes are "
                   "reconstructed (consistency checks: docs/reliability.md); per camera, also with --stereo.")
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def evaluate_cmd(image_dir, setup_path, out_dir, method, screen_model, seed_pixel, seed_height_mm, anchor_distance_mm,
                 anchor_pixel, anchor_point_mm, noise_std, anchor_distance_std_mm, no_uncertainty, stereo,
                 search_range_mm, min_valid_fraction, force, quiet) -> None:
    """Evaluate a fringe image set: decode, register, reconstruct (paper §2.5).

    IMAGE_DIR holds manifest.json and the images (as written by `pmdsim simulate`, or a real
    camera's images described by such a manifest). Writes OUT/evaluation.h5,
    OUT/height_{camera}.png, OUT/surface_fit.json and OUT/slope_error.png. The height is fixed by
    an anchor (--anchor-*, --seed-*, or the manifest's); without one the heights are relative.
    Per-pixel standard uncertainties (k = 1) of heights and slopes go to evaluation.h5 and
    OUT/height_std_{camera}.png unless --no-uncertainty (with --stereo: absolute σ).
    """
    from .io.imageset_prefetch import start_prefetch

    start_prefetch(image_dir)  # the images decode in a background thread meanwhile (issue 25)
    from .evaluation.anchor import DistanceAnchor
    from .studies.jobs import JobInputError, evaluate_image_set, evaluate_image_set_stereo

    import math

    for opt, v in (("--seed-height-mm", seed_height_mm), ("--anchor-distance-mm", anchor_distance_mm),
                   ("--anchor-pixel", anchor_pixel), ("--anchor-point-mm", anchor_point_mm),
                   ("--noise-std", noise_std), ("--search-range-mm", search_range_mm)):
        if v is not None and not all(math.isfinite(x) for x in (v if isinstance(v, tuple) else (v,))):
            raise click.BadParameter(f"{opt} must be finite, got {' '.join(str(x) for x in (v if isinstance(v, tuple) else (v,)))} "
                                     "(NaN or infinity is no height, distance or noise)")
    given = [anchor_distance_mm is not None, anchor_pixel is not None, anchor_point_mm is not None]
    if any(given) and not all(given):
        raise click.UsageError("a distance anchor needs --anchor-distance-mm, --anchor-pixel and --anchor-point-mm")
    anchor = DistanceAnchor(anchor_pixel, anchor_distance_mm, anchor_point_mm) if all(given) else None
    setup = _load(setup_path, None)
    from .io.outputs import check_output_target

    check_output_target(out_dir, force=force, inputs=[image_dir, *_inputs(setup_path, setup)], kind="dir")
    if stereo:
        if seed_pixel is not None or seed_height_mm is not None or anchor is not None:
            raise JobInputError("--stereo needs no seed or anchor: drop --seed-pixel/--seed-height-mm/--anchor-*")
        if anchor_distance_std_mm is not None:
            raise JobInputError("--anchor-distance-std-mm needs an anchor; --stereo has none: drop it")
        if method is not None:
            raise JobInputError(f"--method {method} does not apply to --stereo (stereo fits each camera's heights "
                                "to the anchors it finds, docs/stereo.md): drop --method")
        with _bar(len(setup.cameras), "evaluating (stereo)", quiet) as bar:
            summary = evaluate_image_set_stereo(image_dir, setup, out_dir, screen_model=screen_model,
                                                search_range_mm=search_range_mm, noise_std=noise_std, force=force,
                                                command=_command(), progress=bar.step,
                                                inputs=_inputs(setup_path, setup),
                                                min_valid_fraction=min_valid_fraction, uncertainty=not no_uncertainty)
        for line in summary.lines():
            click.echo(line)
        for w in (*summary.warnings, *summary.data_warnings()):
            click.echo(f"pmdsim: warning: {w}", err=True)
        click.echo(f"wrote evaluation.h5 and height_*.png to {out_dir} in {summary.seconds:.1f} s", err=True)
        failures = summary.failures()
        if failures:
            click.echo(f"pmdsim: error: {' | '.join(failures)} (outputs kept in {out_dir} for inspection; "
                       f"--min-valid-fraction sets the limit)", err=True)
            sys.exit(1)
        return
    if search_range_mm is not None:
        raise JobInputError("--search-range-mm is an option of --stereo")
    with _bar(len(setup.cameras), "evaluating", quiet) as bar:
        summary = evaluate_image_set(image_dir, setup, out_dir, method=method, screen_model=screen_model,
                                     seed_pixel=seed_pixel, seed_height_mm=seed_height_mm, anchor=anchor,
                                     noise_std=noise_std, force=force, command=_command(),
                                     progress=bar.step, inputs=_inputs(setup_path, setup),
                                     min_valid_fraction=min_valid_fraction, setup_source=_setup_source(setup_path),
                                     uncertainty=not no_uncertainty, anchor_std_mm=anchor_distance_std_mm)
    for line in summary.lines():
        click.echo(line)
    for w in (*summary.warnings, *summary.data_warnings()):
        click.echo(f"pmdsim: warning: {w}", err=True)
    click.echo(f"wrote evaluation.h5, height_*.png, surface_fit.json and slope_error.png to {out_dir} in "
               f"{summary.seconds:.1f} s", err=True)
    failures = summary.failures()
    if failures:
        click.echo(f"pmdsim: error: {' | '.join(failures)} (outputs kept in {out_dir} for inspection; "
                   f"--min-valid-fraction sets the limit)", err=True)
        sys.exit(1)


@main.group("import")
def import_group() -> None:
    """Import another instrument's measurement as a pmdsim setup and image set."""


@import_group.command("sofast")
@click.option("--measurement", required=True, type=click.Path(dir_okay=False), help="SOFAST measurement (.h5).")
@click.option("--camera", required=True, type=click.Path(dir_okay=False), help="SOFAST camera (.h5).")
@click.option("--display", required=True, type=click.Path(dir_okay=False),
              help="SOFAST display shape (.h5): rectangular2D, distorted2D or distorted3D.")
@click.option("--orientation", required=True, type=click.Path(dir_okay=False), help="SOFAST spatial orientation (.h5).")
@click.option("--calibration", required=True, type=click.Path(dir_okay=False), help="SOFAST image calibration (.h5).")
@click.option("--facet", type=click.Path(dir_okay=False), default=None, help="SOFAST facet definition (.json).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output directory: setup.toml and images/.")
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
def import_sofast_cmd(measurement, camera, display, orientation, calibration, facet, out_dir, force) -> None:
    """A SOFAST fringe measurement → OUT/setup.toml and the image set OUT/images/ for `pmdsim evaluate`."""
    import warnings

    from .io.importers import import_sofast

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # reported below, once
        summary = import_sofast(measurement=measurement, camera=camera, display=display, orientation=orientation,
                                calibration=calibration, facet=facet, out_dir=out_dir, force=force, command=_command())
    for w in summary.warnings:
        click.echo(f"pmdsim: warning: {w}", err=True)
    for line in summary.lines():
        click.echo(line)


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
    from .studies.jobs import calibrate_image_sets

    nominal = _load(setup_path, None)
    with _bar(len(image_dirs), "decoding", quiet) as bar:
        run = calibrate_image_sets(image_dirs, nominal, out_path, stride=stride, max_iter=max_iter, force=force,
                                   command=_command(), progress=bar.step,
                                   inputs=_inputs(setup_path, nominal), setup_source=_setup_source(setup_path))
    for name, c in run.summary["cameras"].items():
        click.echo(f"{name}: fx {c['fx_px']:.3f} ± {c['std']['fx_px']:.3f} px, fy {c['fy_px']:.3f} ± "
                   f"{c['std']['fy_px']:.3f} px, pp ({c['ppx_px']:.3f}, {c['ppy_px']:.3f}) px")
    click.echo(run.result.determination_report(), err=True)
    for line in run.warnings:
        click.echo(f"pmdsim: warning: {line}", err=True)
    click.echo(f"calibration converged ({run.result.reason}); RMS {run.result.rms_px:.4f} px over "
               f"{run.result.n_residuals} residuals; wrote {out_path}", err=True)


@main.command("experiment")
@click.argument("number", type=click.Choice(["1", "2", "3", "4", "5", "6"]))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output directory.")
@click.option("--setup", "setup_path", type=click.Path(dir_okay=False), help="Base setup (default: Table 1).")
@click.option("--downsample", type=click.IntRange(min=1), default=1, show_default=True,
              help="Bin the cameras K×K (same field of view) for a quick look.")
@click.option("--method", type=click.Choice(["stepwise", "least_squares"]), default="stepwise", show_default=True,
              help="Surface integration (paper: stepwise).")
@click.option("--bulges-mm", default="0,1,2,3", show_default=True,
              help="Comma-separated screen bulge heights Δh (Experiment 5: default 0,3).")
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
@click.option("--effects", default=None,
              help="Experiment 4: comma-separated effects (default: all; see docs/experiments.md).")
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def experiment_cmd(number, out_dir, setup_path, downsample, method, bulges_mm, seed, write_images, grids,
                   deformations, mirror_sags_um, sag_bulge_mm, effects, force, quiet) -> None:
    """Run one of the paper's experiments.

    1 = perfect setup knowledge, planar screen model (Table 2, Fig. 4);
    2 = simulated holistic calibration with a planar mirror, then reconstruction (Table 3, Fig. 5);
    3 = beyond the paper (§5): calibrate free-form screen models of increasing flexibility, with
    the paper's bulges, mismatching deformations and a non-planar calibration mirror;
    4 = error budget of realistic image formation (sensor, display, optics; Δh = 3 mm, 3×3 screen);
    5 = a warped printed foil (the paper's application): mono with a seed and stereo without,
    each with the planar-screen and the free 3×3 screen calibration (docs/stereo.md);
    6 = the screen's cover glass (0.7, 1.1, 3 mm; Δh = 0, 3 mm): ignored, nominal or calibrated.
    """
    from .studies.experiment3 import SCREEN_DEFORMATIONS
    from .studies.runs import experiment_steps, write_experiment, write_experiment3

    from .io.outputs import check_output_target

    _refuse_inapplicable(number)
    base = _load(setup_path, None)
    check_output_target(out_dir, force=force, inputs=_inputs(setup_path, base), kind="dir")  # before hours of computing
    from .studies.checks import check_memory

    check_memory(base.binned(downsample), "evaluate")
    if number == "5":
        from .studies.experiment5 import experiment5_steps, write_experiment5

        ctx = click.get_current_context()
        default = ctx.get_parameter_source("bulges_mm") == click.core.ParameterSource.DEFAULT
        bulges = [0.0, 3.0] if default else _parse_list(bulges_mm, float, "--bulges-mm")
        with _bar(experiment5_steps(bulges), "experiment 5", quiet) as bar:
            out = write_experiment5(out_dir, base, bulges=bulges, downsample=downsample, method=method, seed=seed,
                                    force=force, command=_command(), progress=bar.step)
        click.echo(out.table)
        click.echo(out.summary(out_dir), err=True)
        return
    if number == "4":
        _experiment4(base, out_dir, effects, downsample, method, seed, force, quiet)
        return
    if number == "6":  # the screen's cover glass (issue 21)
        from .studies.experiment6 import GLASS_MODELS, GLASS_THICKNESSES_MM, write_experiment6

        with _bar(2 * len(GLASS_THICKNESSES_MM) * (1 + len(GLASS_MODELS)), "experiment 6", quiet) as bar:
            out = write_experiment6(out_dir, base, downsample=downsample, method=method, seed=seed, force=force,
                                    command=_command(), progress=bar.step)
        click.echo(out.table)
        click.echo(out.summary(out_dir), err=True)
        return
    if number == "3":
        bulges = _parse_list(bulges_mm, float, "--bulges-mm") if bulges_mm.strip() else []
        sizes = _parse_list(grids, int, "--grids") if grids.strip() else []
        if any(g < 3 for g in sizes):
            raise click.BadParameter(f"--grids: every grid needs at least 3 × 3 control points, got {grids!r}")
        kinds = [k.strip() for k in deformations.split(",") if k.strip()]
        bad = [k for k in kinds if k not in SCREEN_DEFORMATIONS]
        if bad:
            raise click.BadParameter(f"--deformations: unknown {bad}; expected some of {list(SCREEN_DEFORMATIONS)}")
        sags = _parse_list(mirror_sags_um, float, "--mirror-sags-um") if mirror_sags_um.strip() else []
        n_scenarios = len(bulges) + len(kinds) + len(sags)
        if not n_scenarios:
            raise click.BadParameter("nothing to run: no bulges, deformations or mirror sags given")
        with _bar(experiment_steps(3, base, n_scenarios=n_scenarios, n_models=1 + len(sizes)), "experiment 3",
                  quiet) as bar:
            out = write_experiment3(out_dir, base, bulges=bulges, grids=sizes, deformations=kinds, mirror_sags_um=sags,
                                    sag_bulge_mm=sag_bulge_mm, downsample=downsample, method=method, force=force,
                                    command=_command(), progress=bar.step)
    else:
        n = int(number)
        bulges = _parse_list(bulges_mm, float, "--bulges-mm")
        with _bar(experiment_steps(n, base, bulges), f"experiment {n}", quiet) as bar:
            out = write_experiment(n, out_dir, base, bulges=bulges, downsample=downsample, method=method, seed=seed,
                                   write_images=write_images, force=force, command=_command(),
                                   progress=bar.step)
    click.echo(out.table)
    click.echo(out.summary(out_dir), err=True)


@main.command("study")
@click.argument("study_file", type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output directory (reused by a rerun: only missing cases are computed).")
@click.option("--scheduler", default=None, help="Address of an existing Dask scheduler (tcp://host:port); "
              "default: a LocalCluster on this machine.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="LocalCluster worker processes (default: one per core; numba threads = cores // workers).")
@click.option("--connect-timeout", "connect_timeout_s", type=click.FloatRange(min=0.1), default=30.0, show_default=True,
              help="Seconds to wait for the scheduler and for its first worker.")
@click.option("--quiet", is_flag=True, help="No progress lines.")
def study_cmd(study_file, out_dir, scheduler, workers, connect_timeout_s, quiet) -> None:
    """Run a parameter sweep / Monte-Carlo study (STUDY.toml) on Dask: OUT/results.parquet (one row per
    case and camera), results.csv, results_wide.csv, summary.txt and figures."""
    from .io.outputs import reused_output_dir
    from .errors import require_extra

    require_extra("study", "distributed", "pyarrow", feature="pmdsim study")  # pmdsim[study]: one line, exit 2
    from .studies.study import run_study
    from .studies.study_cluster import open_cluster
    from .studies.study_file import load_study
    from .studies.study_summary import write_study_outputs

    if scheduler is not None and workers is not None:
        raise click.UsageError("--workers sets the size of the LocalCluster; with --scheduler the cluster's "
                               "workers are used (omit --workers)")
    study = load_study(study_file)
    click.echo(f"study {study.name!r}: {study.n_cases} cases, action {study.action} "
               f"({'scheduler ' + scheduler if scheduler else 'LocalCluster'})", err=True)
    # The scheduler, its workers and their pmdsim are checked before OUT is touched (issue 23).
    with open_cluster(scheduler, workers, timeout_s=connect_timeout_s) as cluster, _StudyProgress(study.n_cases, quiet) as progress:
        click.echo(f"  on {cluster.describe()}", err=True)
        _cold_note("study")  # after the study file and the cluster are checked (_NOTE_AFTER_CHECKS)
        with reused_output_dir(out_dir, inputs=[study_file], command=_command()):  # marked, locked
            try:
                run = run_study(study, out_dir, client=cluster.client, progress=progress,
                                connect_timeout_s=connect_timeout_s)
            except KeyboardInterrupt:
                progress.close()
                signum = interrupts.received() or signal.SIGINT
                click.echo(f"pmdsim: interrupted ({interrupts.signal_name(signum)}); the finished cases are recorded "
                           f"in {out_dir}: rerun the same command to compute the rest", err=True)
                sys.exit(interrupts.exit_code(signum))
            written = write_study_outputs(study, out_dir)
    click.echo(f"{run.n_computed} cases computed, {run.n_reused} reused, {run.n_failed} failed, "
               f"{run.n_missing} missing, in {run.elapsed_s:.1f} s → {out_dir} ({', '.join(written)})", err=True)
    if run.n_missing:
        click.echo("pmdsim: error: some cases have no result (workers lost); rerun the same command to compute them",
                   err=True)
        sys.exit(1)


#: The experiment options and the experiments they apply to (the others refuse them, issue 24).
_EXPERIMENT_OPTIONS = {"bulges_mm": ("1", "2", "3", "5"), "seed": ("2", "4", "5", "6"), "write_images": ("1",),
                       "grids": ("3",), "deformations": ("3",), "mirror_sags_um": ("3",), "sag_bulge_mm": ("3",),
                       "effects": ("4",)}


def _refuse_inapplicable(number: str) -> None:
    """Refuse an option given on the command line that experiment ``number`` does not use
    (e.g. ``experiment 1 --grids 3``): it would be silently ignored."""
    ctx = click.get_current_context()
    if number not in {n for ns in _EXPERIMENT_OPTIONS.values() for n in ns}:
        return  # an experiment this table does not describe
    for name, applies in _EXPERIMENT_OPTIONS.items():
        if number in applies or ctx.get_parameter_source(name) in (None, click.core.ParameterSource.DEFAULT):
            continue
        opt = "--" + name.replace("_", "-")
        raise click.UsageError(f"{opt} does not apply to experiment {number} (it is an option of experiment"
                               f"{'s' if len(applies) > 1 else ''} {', '.join(applies)}); drop it")


class _StudyProgress:
    """A study's progress on stderr: a bar in a terminal; otherwise one line per ``every`` cases
    (a twentieth of the study, 1 … 1000) or per minute, whichever comes first, and one per failed
    case."""

    def __init__(self, total: int, quiet: bool):
        import time

        self.total, self.quiet, self.clock = total, quiet, time.monotonic
        self.tty = sys.stderr.isatty()
        self.every = max(1, min(1000, total // 20))
        self.bar, self.shown, self.last = None, 0, time.monotonic()

    def __enter__(self):
        if self.tty and not self.quiet:
            self.bar = click.progressbar(length=self.total, label="study", file=sys.stderr, show_pos=True,
                                         show_eta=True).__enter__()
        return self

    def __call__(self, d: dict) -> None:
        if self.quiet:
            return
        rec = d["record"]
        if self.bar is not None:
            self.bar.update(d["done"] - self.shown)
            self.shown = d["done"]
        elif d["done"] - self.shown >= self.every or d["done"] == d["total"] or self.clock() - self.last >= 60:
            self.shown, self.last = d["done"], self.clock()
            eta = d["eta_s"]
            left = "?" if eta != eta else f"{eta:.0f} s"
            click.echo(f"  {d['done']}/{d['total']} done, {d['failed']} failed, time left ≈ {left}", err=True)
        if rec["status"] == "failed":
            click.echo(f"  case {rec['case_index']} failed: {rec['error']}", err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.__exit__(None, None, None)
            self.bar = None

    def __exit__(self, *exc) -> None:
        self.close()


def _experiment4(base, out_dir, effects, downsample, method, seed, force, quiet) -> None:
    from .studies.experiment4 import EFFECTS, experiment4_steps, write_experiment4

    names = list(EFFECTS) if effects is None else [e.strip() for e in effects.split(",") if e.strip()]
    twice = sorted({e for e in names if names.count(e) > 1})
    if twice:
        raise click.BadParameter(f"--effects lists {', '.join(twice)} more than once; give each effect once")
    bad = [e for e in names if e not in EFFECTS]
    if bad or not names:
        raise click.BadParameter(f"--effects: unknown {bad}; expected some of {list(EFFECTS)}" if bad
                                 else "--effects lists no effect")
    with _bar(experiment4_steps(base, names), "experiment 4", quiet) as bar:
        out = write_experiment4(out_dir, base, effects=names, downsample=downsample, method=method, seed=seed,
                                force=force, command=_command(), progress=bar.step)
    click.echo(out.table)
    click.echo(out.summary(out_dir), err=True)


def _parse_list(text: str, kind, option: str) -> list:
    """Comma-separated numbers of an option, with a clear error."""
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        what = "integers" if kind is int else "numbers"
        raise click.BadParameter(f"{option} must be comma-separated {what}, got {text!r}") from None
    if not values:
        raise click.BadParameter(f"{option} lists no value")
    twice = sorted({v for v in values if values.count(v) > 1})
    if twice:
        raise click.BadParameter(f"{option} lists {', '.join(f'{v:g}' for v in twice)} more than once "
                                 f"(each would be a duplicate row); give each value once")
    return values


if __name__ == "__main__":  # pragma: no cover
    main()
