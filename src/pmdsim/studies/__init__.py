"""Studies (layer 4): the paper's experiments and beyond, with their tables and figures.

* :mod:`.experiment1` — Table 2 / Fig. 4 (perfect knowledge, planar screen model);
* :mod:`.calibration_data` — simulated calibration measurements (mirror poses → observations);
* :mod:`.experiment2` — Table 3 / Fig. 5 (holistic calibration, then reconstruction);
* :mod:`.experiment3` — free-form screen calibration (beyond the paper, §5);
* :mod:`.study_file`, :mod:`.study` — the study engine: STUDY.toml sweeps and Monte-Carlo
  studies of any setup key on ``dask.distributed``, resumable (:mod:`.study_summary`,
  :mod:`.study_figures`: quantiles and figures of the results);
* :mod:`.report` — tables as text; :mod:`.figures` — matplotlib figures (returned; saved only
  when a path is given; the backend is never switched).

May import every layer below it (geometry, setup, simulation, evaluation, calibration, io).
The CLI calls these and prints; it formats no table and draws no figure itself.
"""

import importlib
import sys
import types

#: Public name → the submodule defining it, imported on first use (PEP 562): ``pmdsim evaluate``
#: imports :mod:`.jobs` only, not the experiments, the study engine and what they import
#: (docs/benchmarks.md, "start-up").
_LAZY = {
    **dict.fromkeys(("observe_calibration_poses", "simulate_calibration_observations", "trace_calibration_poses"),
                    "calibration_data"),
    **dict.fromkeys(("PAPER_TABLE2", "CaseResult", "experiment1", "run_experiment1_case"), "experiment1"),
    **dict.fromkeys(("INITIAL_ERRORS", "PAPER_TABLE3", "Experiment2Bulge", "calibrate_and_reconstruct",
                     "run_experiment2_bulge"), "experiment2"),
    **dict.fromkeys(("SCREEN_DEFORMATIONS", "Experiment3Scenario", "experiment3_records", "experiment3_scenarios",
                     "run_experiment3", "screen_deformation", "screen_shape_error_um"), "experiment3"),
    **dict.fromkeys(("StudyRun", "run_case", "run_study", "write_results"), "study"),
    **dict.fromkeys(("Study", "StudyError", "load_study", "parse_study"), "study_file"),
}

__all__ = list(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = globals()[name] = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


class _Package(types.ModuleType):
    """This package, whose public names stay bound to themselves when a submodule of the same
    name is imported. The import system binds a submodule to its package's attribute once it
    has run (``from .experiment1 import Progress`` in another submodule binds
    ``pmdsim.studies.experiment1`` to the *module*), which would shadow the lazily imported
    function :func:`experiment1` for every later ``from pmdsim.studies import experiment1``
    (the eager imports this package had before always rebound the function afterwards)."""

    def __setattr__(self, name: str, value) -> None:
        if isinstance(value, types.ModuleType) and _LAZY.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
