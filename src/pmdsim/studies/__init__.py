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

from .calibration_data import observe_calibration_poses, simulate_calibration_observations, trace_calibration_poses
from .experiment1 import PAPER_TABLE2, CaseResult, experiment1, run_experiment1_case
from .experiment2 import (
    INITIAL_ERRORS,
    PAPER_TABLE3,
    Experiment2Bulge,
    calibrate_and_reconstruct,
    run_experiment2_bulge,
)
from .experiment3 import (
    SCREEN_DEFORMATIONS,
    Experiment3Scenario,
    experiment3_records,
    experiment3_scenarios,
    run_experiment3,
    screen_deformation,
    screen_shape_error_um,
)
from .study import StudyRun, run_case, run_study, write_results
from .study_file import Study, StudyError, load_study, parse_study

__all__ = [
    "observe_calibration_poses", "simulate_calibration_observations", "trace_calibration_poses",
    "PAPER_TABLE2", "CaseResult", "experiment1", "run_experiment1_case",
    "INITIAL_ERRORS", "PAPER_TABLE3", "Experiment2Bulge", "calibrate_and_reconstruct", "run_experiment2_bulge",
    "SCREEN_DEFORMATIONS", "Experiment3Scenario", "experiment3_records", "experiment3_scenarios",
    "run_experiment3", "screen_deformation", "screen_shape_error_um",
    "StudyRun", "run_case", "run_study", "write_results", "Study", "StudyError", "load_study", "parse_study",
]
