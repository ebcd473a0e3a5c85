"""Study files (STUDY.toml): parsing and validation, and the expansion into cases.

A study file names a base setup, the setup keys to vary (by their TOML path) and what each case
does. Example (``examples/study_bulge_focal.toml``)::

    format = "pmdsim-study"
    setup = "default"            # or a setup TOML path, relative to the study file
    action = "simulate+evaluate" # simulate | simulate+evaluate | calibrate+evaluate
    downsample = 8               # cameras binned 8 × 8 after the parameters are applied
    seed = 0                     # start-value seed of calibrate+evaluate
    metrics = ["max_height_diff_um", "max_dev_plane_um", "tilt_urad"]
    save_maps = false            # true: OUT/maps/{case key}.h5 with each case's reconstructions

    [[parameters]]
    path = "screen.bulge_mm"     # any setup key, as in the setup TOML
    values = [0.0, 1.0, 2.0, 3.0]

    [[parameters]]
    path = "cameras.left.focal_length_px"
    applies_to = "model"         # truth (default): the simulated setup; model: the setup the
    mode = "offset"              # evaluation assumes. set (default) | offset (added) | scale (×)
    values = [-8.0, -4.0, 0.0, 4.0, 8.0]

    [[parameters]]                # Monte Carlo: one draw per sample (needs [monte_carlo])
    path = "cameras.right.angles_deg"
    mode = "offset"
    distribution = "normal"      # normal (mean, std) | uniform (low, high)
    mean = 0.0
    std = 0.05

    [monte_carlo]
    samples = 100
    seed = 1

A path may end in list indices to vary one entry: ``cameras.left.angles_deg[2]``,
``screen.heights_mm[1][1]``. A list of paths links setup keys: each value is set on every one
of them (``path = ["patterns.periods_x_mm[2]", "patterns.periods_y_mm[2]"]`` varies the finest
period of both directions together); such a parameter needs a ``name`` (its column). A
parameter whose path is ``screen_model``, ``method`` or ``seed`` varies that case option
instead of a setup key (a grid of values, e.g. ``values = ["planar", "grid3", "grid5"]``).

Cases are the Cartesian product of the grid parameters (in file order, the last varying
fastest) times the Monte-Carlo samples. A parameter is applied to the setup's plain-data form
(:meth:`Setup.to_dict`, the key changed, then :func:`~pmdsim.setup.parse_setup`), so every setup
key works and is validated by the setup parser; values apply to the unbinned setup (pixels of
the full-resolution camera), then the cameras are binned ``downsample`` × ``downsample``.

Two parameters may not vary the same setup key (or one an entry of the other's list) for the
same setup (truth or model): their values would collapse into one case.

Every problem raises :class:`StudyError` naming the file and key before anything runs.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .. import __version__
from ..errors import PmdsimError, SetupError
from ..io.heightmap import load_setup, parse_setup  # height-map files of curved samples read (issue 14)
from ..setup import Setup, default_setup
from .study_uncertainty import UNCERTAINTY_METRICS

__all__ = ["StudyError", "Parameter", "Study", "CaseSpec", "parse_study", "load_study", "ACTIONS", "METRICS",
           "STUDY_FORMAT", "OPTION_PATHS"]

STUDY_FORMAT = "pmdsim-study"

#: Parameter paths that name a case option instead of a setup key (grids only): vary the
#: screen model, the reconstruction method or the calibration start seed from case to case.
OPTION_PATHS = ("screen_model", "method", "seed")

#: What a case does.
ACTIONS = ("simulate", "simulate+evaluate", "calibrate+evaluate")

_SURFACE_METRICS = ("max_height_diff_um", "max_dev_plane_um", "tilt_urad", "tilt_x_urad", "tilt_y_urad", "rms_um",
                    "mean_um", "n_pixels")

#: The metrics each action can record (per camera unless marked; see :mod:`.study`); the
#: default is all of them except the σ metrics (:mod:`.study_uncertainty`), which are computed
#: only when the study lists them.
METRICS = {
    "simulate": ("valid_fraction", "n_valid_px"),
    "simulate+evaluate": ("valid_fraction", "reconstructed_fraction") + _SURFACE_METRICS + UNCERTAINTY_METRICS,
    "calibrate+evaluate": ("reconstructed_fraction",) + _SURFACE_METRICS
    + ("calibration_rms_px", "calibration_converged", "calibration_iterations", "fx_error_px", "fx_std_px",
       "position_error_mm", "rotation_error_deg", "table_turn_deg"),
}

#: Columns of the results tables that a parameter name may not take (``seed`` may: the case
#: option ``seed`` is that column).
RESERVED_COLUMNS = ("case_id", "case_key", "mc_sample", "camera", "status", "error", "elapsed_s", "worker", "run_id")

_TOP_KEYS = ("format", "name", "setup", "action", "downsample", "seed", "method", "screen_model", "cameras",
             "metrics", "save_maps", "parameters", "monte_carlo")
_PARAM_KEYS = ("path", "name", "applies_to", "mode", "values", "distribution", "mean", "std", "low", "high")
_MC_KEYS = ("samples", "seed")


class StudyError(PmdsimError, ValueError):
    """A study file is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class Parameter:
    """One varied setup key.

    Attributes
    ----------
    path : str
        TOML path of the setup key (``screen.bulge_mm``); of the first key of linked keys.
    name : str
        Column name in the results (default: the path, prefixed ``model.`` for model keys, and
        for an ``offset`` / ``scale`` parameter wrapped as ``offset(path)`` / ``scale(path)``:
        the column holds the value added / the factor, not the key's value).
    applies_to : {"truth", "model"}
    mode : {"set", "offset", "scale"}
        The value replaces the key, is added to it, or multiplies it (every entry of a list).
    values : tuple or None
        Grid values (None for a Monte-Carlo parameter).
    distribution : tuple or None
        ``("normal", mean, std)`` or ``("uniform", low, high)``.
    linked : tuple of str
        Further setup keys that take the same value (``path = [key, …]`` in the study file).
    """

    path: str
    name: str
    applies_to: str = "truth"
    mode: str = "set"
    values: tuple | None = None
    distribution: tuple | None = None
    linked: tuple = ()

    @property
    def paths(self) -> tuple:
        """Every setup key the parameter sets: ``path`` and the ``linked`` keys."""
        return (self.path,) + self.linked

    def draw(self, rng: np.random.Generator) -> float:
        """One Monte-Carlo draw."""
        kind, a, b = self.distribution
        return float(rng.normal(a, b)) if kind == "normal" else float(rng.uniform(a, b))


@dataclass(frozen=True)
class CaseSpec:
    """One case: everything a worker needs, in plain data (picklable, hashable by content).

    Attributes
    ----------
    index : int
        Position in the study (results are ordered by it).
    key : str
        SHA-256 (hex, 16 characters) of the case's inputs: the truth and model setup TOML,
        the action and its options, the seed and the pmdsim version.
    params : dict
        Column name → applied value (what the results table shows).
    truth_toml, model_toml : str
        The simulated setup and the setup the evaluation assumes (binned), as TOML.
    """

    index: int
    key: str
    params: dict
    action: str
    truth_toml: str
    model_toml: str
    cameras: tuple
    method: str
    screen_model: str
    seed: int
    mc_sample: int | None


@dataclass(frozen=True)
class Study:
    """A validated study file (see the module docstring)."""

    source: str
    name: str
    base: Setup
    action: str
    downsample: int
    seed: int
    method: str
    screen_model: str
    cameras: tuple
    metrics: tuple
    parameters: tuple
    mc_samples: int | None
    mc_seed: int
    save_maps: bool = False

    @property
    def grid_parameters(self) -> tuple:
        return tuple(p for p in self.parameters if p.values is not None)

    @property
    def mc_parameters(self) -> tuple:
        return tuple(p for p in self.parameters if p.distribution is not None)

    @property
    def n_cases(self) -> int:
        n = math.prod(len(p.values) for p in self.grid_parameters)
        return n * (self.mc_samples or 1)

    def iter_cases(self) -> Iterator[CaseSpec]:
        """The cases one at a time, in order (grid product, last parameter fastest; then
        Monte-Carlo samples), built lazily: a grid of millions of cases starts at once and
        holds one case in memory (building one takes ≈ 5 ms: two setups parsed, binned and
        written as TOML).

        Monte-Carlo draws of sample k come from ``default_rng([mc_seed, k])`` in parameter
        order, so a case's values do not depend on the order cases run in.
        """
        grid = self.grid_parameters
        mc = self.mc_parameters
        index = 0
        samples = range(self.mc_samples) if self.mc_samples else [None]
        for combo in itertools.product(*[p.values for p in grid]):
            for k in samples:
                vals = list(zip(grid, combo))
                if k is not None:
                    rng = np.random.default_rng([self.mc_seed, k])
                    vals += [(p, p.draw(rng)) for p in mc]
                truth, model = build_case_setups(self.base, vals, self.downsample)
                yield _case_spec(self, index, vals, truth, model, k)
                index += 1

    def cases(self) -> list[CaseSpec]:
        """All cases as a list (:meth:`iter_cases`; for small studies and tests)."""
        return list(self.iter_cases())

    @property
    def all_cameras(self) -> tuple:
        """The cameras each case reports on (``cameras``, default: every camera of the setup)."""
        return self.cameras or tuple(self.base.cameras)


def _case_spec(study: Study, index: int, vals, truth: Setup, model: Setup, mc_sample) -> CaseSpec:
    truth_toml, model_toml = truth.to_toml(), model.to_toml()
    cams = study.cameras or tuple(truth.cameras)
    opts = {"method": study.method, "screen_model": study.screen_model, "seed": study.seed}
    opts.update({p.path: v for p, v in vals if p.path in OPTION_PATHS})
    ident = {"truth": truth_toml, "model": model_toml, "action": study.action, "cameras": list(cams), **opts,
             "pmdsim_version": __version__}
    key = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]
    params = {p.name: (list(v) if isinstance(v, (list, tuple)) else v) for p, v in vals}
    return CaseSpec(index, key, params, study.action, truth_toml, model_toml, cams, opts["method"],
                    opts["screen_model"], opts["seed"], mc_sample)


# ============================================================================ applying a parameter
def _lookup(doc: dict, path: str):
    """(parent table, leaf key) of a dotted path in a setup document; KeyError naming the part."""
    parts = path.split(".")
    node = doc
    for i, part in enumerate(parts[:-1]):
        if not isinstance(node, dict) or part not in node or not isinstance(node[part], dict):
            raise KeyError(".".join(parts[: i + 1]))
        node = node[part]
    return node, parts[-1]


def _combine(old, value, mode: str, path: str):
    if mode == "set":
        return value
    if isinstance(old, bool) or not isinstance(old, (int, float, list)):
        raise SetupError(f"{path}: mode {mode!r} needs a numeric setup key, which {old!r} is not")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SetupError(f"{path}: mode {mode!r} needs a number, got {value!r}")
    f = (lambda x: x + value) if mode == "offset" else (lambda x: x * value)
    if isinstance(old, list):
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in old):
            raise SetupError(f"{path}: mode {mode!r} needs a list of numbers, which {old!r} is not")
        return [f(x) for x in old]
    return f(old)


def apply_parameter(doc: dict, path: str, value, mode: str = "set") -> dict:
    """A copy of the setup document ``doc`` with the key ``path`` set (or offset/scaled).

    Raises
    ------
    SetupError
        The path does not name a table of the setup, or the mode does not fit the value.
    """
    doc = copy.deepcopy(doc)
    m = re.fullmatch(r"(.+?)((?:\[\d+\])*)", path)
    key_path, indices = m.group(1), [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    try:
        parent, leaf = _lookup(doc, key_path)
    except KeyError as e:
        raise SetupError(f"unknown setup key {path!r}: the setup has no table {e.args[0]!r}") from None
    if (mode != "set" or indices) and leaf not in parent:
        raise SetupError(f"{path}: mode {mode!r} needs the key in the base setup, which has none")
    for n, i in enumerate(indices):  # an element of a list (``angles_deg[2]``, ``heights_mm[1][1]``)
        node = parent[leaf]
        if not isinstance(node, list) or i >= len(node):
            where = key_path + "".join(f"[{j}]" for j in indices[:n])
            size = f"has {len(node)} entries" if isinstance(node, list) else "is not a list"
            raise SetupError(f"{path}: index {i} is out of range ({where} {size})")
        parent, leaf = node, i
    parent[leaf] = _combine(parent[leaf] if indices else parent.get(leaf), value, mode, path)
    return doc


def build_case_setups(base: Setup, vals, downsample: int) -> tuple[Setup, Setup]:
    """The (truth, model) setups of one case: truth parameters applied to the base setup's
    plain data, model parameters to the truth's, each parsed (validated) and binned."""
    truth_doc = base.to_dict()
    vals = [(p, v) for p, v in vals if p.path not in OPTION_PATHS]
    for p, v in vals:
        if p.applies_to == "truth":
            for path in p.paths:
                truth_doc = apply_parameter(truth_doc, path, v, p.mode)
    model_doc = truth_doc
    for p, v in vals:
        if p.applies_to == "model":
            for path in p.paths:
                model_doc = apply_parameter(model_doc, path, v, p.mode)
    truth = parse_setup(truth_doc).binned(downsample)
    model = truth if model_doc is truth_doc else parse_setup(model_doc).binned(downsample)
    return truth, model


# ============================================================================ parsing
class _Keys:
    """Key access with messages naming the study file and key."""

    def __init__(self, table: dict, prefix: str, src: str, known: tuple):
        self.t, self.prefix, self.src = table, prefix, src
        unknown = [k for k in table if k not in known]
        if unknown:
            raise StudyError(f"{src}: unknown key {self.name(unknown[0])} (known keys here: {', '.join(known)})")

    def name(self, k: str) -> str:
        return f"{self.prefix}{k}"

    def fail(self, k: str, what: str):
        raise StudyError(f"{self.src}: {self.name(k)} {what}")

    def str(self, k: str, default=None, choices=None) -> str:
        v = self.t.get(k, default)
        if v is None:
            self.fail(k, "is missing")
        if not isinstance(v, str):
            self.fail(k, f"must be a string, got {v!r}")
        if choices is not None and v not in choices:
            self.fail(k, f"must be one of {list(choices)}, got {v!r}")
        return v

    def int(self, k: str, default=None, minimum=None) -> int:
        v = self.t.get(k, default)
        if v is None:
            self.fail(k, "is missing")
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(k, f"must be an integer, got {v!r}")
        if minimum is not None and v < minimum:
            self.fail(k, f"must be ≥ {minimum}, got {v!r}")
        return v

    def num(self, k: str) -> float:
        v = self.t.get(k)
        if v is None:
            self.fail(k, "is missing")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(k, f"must be a finite number, got {v!r}")
        return float(v)

    def str_list(self, k: str) -> tuple | None:
        v = self.t.get(k)
        if v is None:
            return None
        if not isinstance(v, list) or not v or not all(isinstance(x, str) for x in v):
            self.fail(k, f"must be a non-empty list of strings, got {v!r}")
        return tuple(v)


def parse_study(doc: dict[str, Any], *, source: str = "study", base_dir: str | Path = ".") -> Study:
    """Validate a parsed study document and build the :class:`Study`.

    Every grid value and the centre of every Monte-Carlo distribution is applied to the base
    setup and parsed, so a wrong type or an out-of-range value is refused here, naming the key.

    Raises
    ------
    StudyError
        Naming ``source`` and the key (``parameters[1].values[2]``, ``monte_carlo.samples``, …).
    """
    if not isinstance(doc, dict):
        raise StudyError(f"{source}: a study must be a TOML table")
    r = _Keys(doc, "", source, _TOP_KEYS)
    fmt = r.str("format", STUDY_FORMAT)
    if fmt != STUDY_FORMAT:
        r.fail("format", f"must be {STUDY_FORMAT!r}, got {fmt!r}")
    setup_ref = r.str("setup", "default")
    if setup_ref == "default":
        base = default_setup()
    else:
        p = Path(setup_ref)
        p = p if p.is_absolute() else Path(base_dir) / p
        try:
            base = load_setup(p)
        except SetupError as e:
            raise StudyError(f"{source}: setup: {e}") from None
    action = r.str("action", None, ACTIONS)
    downsample = r.int("downsample", 1, minimum=1)
    seed = r.int("seed", 0, minimum=0)
    method = r.str("method", "stepwise", ("stepwise", "least_squares"))
    screen_choices = ("planar", "setup") if action != "calibrate+evaluate" else \
        ("planar",) + tuple(f"grid{n}" for n in range(3, 32, 2))
    screen_model = r.str("screen_model", "planar", screen_choices)
    cameras = r.str_list("cameras") or ()
    for i, c in enumerate(cameras):
        if c not in base.cameras:
            r.fail(f"cameras[{i}]", f"names no camera of the setup ({', '.join(base.cameras)}), got {c!r}")
    # σ metrics only when listed: they add the uncertainty computation to every case
    metrics = r.str_list("metrics") or tuple(m for m in METRICS[action] if m not in UNCERTAINTY_METRICS)
    for i, m in enumerate(metrics):
        if m not in METRICS[action]:
            r.fail(f"metrics[{i}]", f"must be one of {list(METRICS[action])} for action {action!r}, got {m!r}")
    try:
        base.binned(downsample)
    except SetupError as e:
        r.fail("downsample", f"does not fit the setup: {e}")

    raw = doc.get("parameters", [])
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        r.fail("parameters", "must be an array of tables ([[parameters]])")
    choices = {"screen_model": screen_choices, "method": ("stepwise", "least_squares")}
    params = [_parse_parameter(t, i, source, base, action, downsample, choices) for i, t in enumerate(raw)]
    for i, p in enumerate(params):  # two parameters on one key would collapse into one case (issue 24)
        for j, q in enumerate(params[:i]):
            same = [(a, b) for a in p.paths for b in q.paths if _same_key(a, b)]
            if q.applies_to == p.applies_to and same:
                a, b = same[0]
                raise StudyError(f"{source}: parameters[{i}].path {a!r} varies the same "
                                 f"{'case option' if a in OPTION_PATHS else 'setup key'} as parameters[{j}] "
                                 f"({b!r}{', both applied to the ' + p.applies_to if a not in OPTION_PATHS else ''}); "
                                 "give all its values in one parameter")
    names = [p.name for p in params]
    for i, n in enumerate(names):
        if n in names[:i]:
            raise StudyError(f"{source}: parameters[{i}].name {n!r} repeats parameters[{names.index(n)}]")
        if n in RESERVED_COLUMNS or n in METRICS[action] or (n == "seed" and params[i].path != "seed"):
            raise StudyError(f"{source}: parameters[{i}].name {n!r} is a column of the results table already "
                             "(choose another name)")

    mc_samples, mc_seed = None, 0
    has_mc = any(p.distribution is not None for p in params)
    if "monte_carlo" in doc:
        if not isinstance(doc["monte_carlo"], dict):
            r.fail("monte_carlo", "must be a table")
        m = _Keys(doc["monte_carlo"], "monte_carlo.", source, _MC_KEYS)
        mc_samples = m.int("samples", None, minimum=1)
        mc_seed = m.int("seed", 0, minimum=0)
        if not has_mc:
            r.fail("monte_carlo", "is given but no parameter has a distribution")
    elif has_mc:
        i = next(i for i, p in enumerate(params) if p.distribution is not None)
        raise StudyError(f"{source}: parameters[{i}].distribution needs a [monte_carlo] table with samples")
    name = r.str("name", Path(source).stem)
    save_maps = doc.get("save_maps", False)
    if not isinstance(save_maps, bool):
        r.fail("save_maps", f"must be true or false, got {save_maps!r}")
    if save_maps and action == "simulate":
        r.fail("save_maps", "needs an action that reconstructs (simulate+evaluate, calibrate+evaluate)")
    return Study(source, name, base, action, downsample, seed, method, screen_model, cameras, metrics,
                 tuple(params), mc_samples, mc_seed, save_maps)


def _same_key(a: str, b: str) -> bool:
    """Whether two parameter paths change the same setup value: equal, or one an entry of the
    other (``cameras.left.angles_deg`` and ``cameras.left.angles_deg[2]``)."""
    if a == b:
        return True
    short, long = sorted((a, b), key=len)
    return long.startswith(short) and long[len(short)] == "["


def _parse_parameter(t: dict, i: int, source: str, base: Setup, action: str, downsample: int,
                     choices: dict) -> Parameter:
    k = _Keys(t, f"parameters[{i}].", source, _PARAM_KEYS)
    linked = ()
    if isinstance(t.get("path"), list):  # linked keys: one value set on each of them
        paths = t["path"]
        if not paths or not all(isinstance(x, str) for x in paths):
            k.fail("path", f"must be a setup key or a non-empty list of setup keys, got {paths!r}")
        for n, x in enumerate(paths):
            if x in OPTION_PATHS:
                k.fail(f"path[{n}]", f"names the case option {x!r}, which cannot be linked to other keys")
            if any(_same_key(x, y) for y in paths[:n]):
                k.fail(f"path[{n}]", f"{x!r} repeats a key listed before it (or an entry of one)")
        if len(paths) > 1 and "name" not in t:
            k.fail("name", "is missing: a parameter with linked keys needs a name for its column")
        path, linked = paths[0], tuple(paths[1:])
        t = {**t, "path": path}
        k = _Keys(t, f"parameters[{i}].", source, _PARAM_KEYS)
    path = k.str("path")
    if path in OPTION_PATHS:
        return _parse_option_parameter(t, k, i, path, choices)
    applies_to = k.str("applies_to", "truth", ("truth", "model"))
    if applies_to == "model" and action != "simulate+evaluate":
        k.fail("applies_to", f"'model' needs action 'simulate+evaluate' (the evaluation's setup), "
                             f"the study's action is {action!r}")
    mode = k.str("mode", "set", ("set", "offset", "scale"))
    key = path if applies_to == "truth" else f"model.{path}"
    # The column holds the value given (issue 23): the setup key's value, or what was added to
    # it / multiplied with it — named so, not as if it held the key's value.
    name = k.str("name", key if mode == "set" else f"{mode}({key})")
    values, dist = None, None
    if "values" in t:
        if "distribution" in t:
            k.fail("values", "and distribution exclude each other (a grid or a Monte-Carlo draw)")
        values = t["values"]
        if not isinstance(values, list):
            k.fail("values", f"must be a list of values, got {values!r}")
        if not values:
            k.fail("values", "is an empty grid; give at least one value")
        values = tuple(values)
        trial = [(j, v) for j, v in enumerate(values)]
    elif "distribution" in t:
        kind = k.str("distribution", None, ("normal", "uniform"))
        if kind == "normal":
            a, b = k.num("mean"), k.num("std")
            if b < 0:
                k.fail("std", f"must be ≥ 0, got {b!r}")
            extra = [x for x in ("low", "high") if x in t]
        else:
            a, b = k.num("low"), k.num("high")
            if not b > a:
                k.fail("high", f"must be > low ({a!r}), got {b!r}")
            extra = [x for x in ("mean", "std") if x in t]
        if extra:
            k.fail(extra[0], f"does not belong to a {kind} distribution")
        dist = (kind, a, b)
        trial = [(None, a), (None, b)] if kind == "uniform" else [(None, a)]
    else:
        raise StudyError(f"{source}: parameters[{i}] needs values (a grid) or distribution (Monte Carlo)")
    p = Parameter(path, name, applies_to, mode, values, dist, linked)
    for j, v in trial:
        where = f"parameters[{i}].values[{j}]" if j is not None else f"parameters[{i}].distribution"
        try:
            build_case_setups(base, [(p, v)], downsample)
        except SetupError as e:
            shown = path if not linked else list(p.paths)
            raise StudyError(f"{source}: {where} = {v!r} (path {shown!r}): {e}") from None
    return p


def _parse_option_parameter(t: dict, k: _Keys, i: int, path: str, choices: dict) -> Parameter:
    """A grid over a case option (:data:`OPTION_PATHS`), each value checked."""
    extra = [x for x in t if x not in ("path", "name", "values")]
    if extra:
        k.fail(extra[0], f"does not apply to the case option {path!r} (a grid of values only)")
    values = t.get("values")
    if not isinstance(values, list):
        k.fail("values", f"must be a list of values, got {values!r}")
    if not values:
        k.fail("values", "is an empty grid; give at least one value")
    for j, v in enumerate(values):
        if path == "seed":
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                k.fail(f"values[{j}]", f"must be an integer ≥ 0 (a seed), got {v!r}")
        elif v not in choices[path]:
            k.fail(f"values[{j}]", f"must be one of {list(choices[path])} for {path}, got {v!r}")
    return Parameter(path, k.str("name", path), "truth", "set", tuple(values), None)


def load_study(path: str | Path) -> Study:
    """Read and validate a study file (setup paths are relative to the study file)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise StudyError(f"study file {str(p)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise StudyError(f"cannot read study file {str(p)!r}: {e}") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise StudyError(f"{p}: not valid TOML: {e}") from None
    return parse_study(doc, source=str(p), base_dir=p.parent)
