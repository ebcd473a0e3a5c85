"""Experiment 3 (beyond the paper, §5): calibrating the screen's shape with free-form models.

For the paper's bulges, for true deformations the model grids cannot all represent and for a
calibration mirror that is not flat: calibrate with the planar model and n × n spline grids,
reconstruct with each, and record the error against the number of free parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ..setup import Setup
from .calibration_data import simulate_calibration_observations
from .experiment1 import Progress
from .experiment2 import Experiment2Bulge, calibrate_and_reconstruct

__all__ = ["SCREEN_DEFORMATIONS", "screen_deformation", "Experiment3Scenario", "experiment3_scenarios",
           "screen_shape_error_um", "experiment3_records", "run_experiment3"]


#: True screen deformations that the centred models cannot all represent (the mismatch case).
SCREEN_DEFORMATIONS = ("offcentre", "random")


def screen_deformation(setup: Setup, kind: str, *, peak_mm: float = 3.0, seed: int = 0) -> Setup:
    """``setup`` with a true screen deformation of the mismatch case (Experiment 3).

    Both hold the screen's border at 0 (a rigid frame, as the paper's bulge does):

    ``"offcentre"``
        A 5 × 5 control grid over the screen with one off-centre control height of ``peak_mm``
        (row 1, column 3: at 3/4 of the width and 1/4 of the height). The 3 × 3 model cannot
        represent it; the 5 × 5 model can exactly, and so can 9 × 9 (its not-a-knot spline
        space contains the 5 × 5 one: the 5-point spline's only interior knot is the centre,
        which is also a knot of the 9-point spline).
    ``"random"``
        A seeded random smooth shape on a 17 × 17 grid: Σ_{m,n=1..4} a_mn·sin(mπu)·sin(nπv),
        u, v ∈ [0, 1] across the screen, a_mn ~ N(0, 1)/(m² + n²), scaled so that the largest
        control height magnitude is ``peak_mm``. No model grid represents it exactly.
    """
    scr = setup.screen
    x0, x1 = scr.grid_x_mm[0], scr.grid_x_mm[-1]
    y0, y1 = scr.grid_y_mm[0], scr.grid_y_mm[-1]
    if kind == "offcentre":
        gx, gy = np.linspace(x0, x1, 5), np.linspace(y0, y1, 5)
        z = np.zeros((5, 5))
        z[1, 3] = peak_mm
    elif kind == "random":
        gx, gy = np.linspace(x0, x1, 17), np.linspace(y0, y1, 17)
        u = (gx - x0) / (x1 - x0)
        v = (gy - y0) / (y1 - y0)
        rng = np.random.default_rng([seed, 17])
        z = np.zeros((17, 17))
        for m in range(1, 5):
            for n in range(1, 5):
                z += rng.normal() / (m * m + n * n) * np.outer(np.sin(n * np.pi * v), np.sin(m * np.pi * u))
        z *= peak_mm / np.abs(z).max()
    else:
        raise ValueError(f"unknown screen deformation {kind!r}; expected one of {SCREEN_DEFORMATIONS}")
    return setup.with_screen_heights(gx, gy, z)


@dataclass(frozen=True, eq=False)
class Experiment3Scenario:
    """One true setup of Experiment 3: the paper's bulge, a mismatch deformation, or a sagged
    calibration mirror (with the paper's bulge ``bulge_mm``)."""

    name: str  # "bulge", "offcentre", "random" or "mirror_sag"
    bulge_mm: float
    mirror_sag_um: float
    truth: Setup

    @property
    def label(self) -> str:
        if self.name == "bulge":
            return f"bulge {self.bulge_mm:g} mm"
        if self.name == "mirror_sag":
            return f"mirror sag {self.mirror_sag_um:g} µm, bulge {self.bulge_mm:g} mm"
        return f"{self.name} deformation"

    @property
    def start_seed(self) -> list[int]:
        """Seed of the calibration's start values: Experiment 2's for the bulge scenarios."""
        if self.name == "bulge":
            return [0, int(round(self.bulge_mm * 1000))]
        kind = {"offcentre": 1, "random": 2, "mirror_sag": 3}[self.name]
        return [0, 1_000_000 * kind + int(round(self.mirror_sag_um * 1000))]


def experiment3_scenarios(base: Setup, *, downsample: int = 1, bulges: Iterable[float] = (0.0, 1.0, 2.0, 3.0),
                          deformations: Iterable[str] = SCREEN_DEFORMATIONS,
                          mirror_sags_um: Iterable[float] = (1.0, 5.0), sag_bulge_mm: float = 3.0,
                          peak_mm: float = 3.0) -> list[Experiment3Scenario]:
    """The true setups of Experiment 3, binned by ``downsample``."""
    b = base.binned(downsample)
    out = [Experiment3Scenario("bulge", float(dh), 0.0, b.with_bulge(dh)) for dh in bulges]
    for kind in deformations:
        t = screen_deformation(b, kind, peak_mm=peak_mm)
        z = t.screen.control_heights()
        out.append(Experiment3Scenario(kind, float(z[z.shape[0] // 2, z.shape[1] // 2]), 0.0, t))
    for s in mirror_sags_um:
        out.append(Experiment3Scenario("mirror_sag", float(sag_bulge_mm), float(s),
                                       b.with_bulge(sag_bulge_mm).with_mirror_sag(s)))
    return out


def screen_shape_error_um(truth: Setup, model: Setup, observations) -> tuple[float, float]:
    """(max, RMS) of calibrated − true screen height (µm) over the screen points the calibration
    observed (the decoded (x_q, y_q) of all ``observations``): how well the model found the
    screen's shape where the data can tell. Both share the gauge (border/frame plane at 0)."""
    q = np.concatenate([o.q_screen_mm[:, :2] for o in observations])
    d = model.screen.surface.height(q[:, 0], q[:, 1]) - truth.screen.surface.height(q[:, 0], q[:, 1])
    d = d[np.isfinite(d)]
    return float(np.abs(d).max() * 1e3), float(np.sqrt(np.mean(d * d)) * 1e3)


def experiment3_records(scenario: Experiment3Scenario, screen_model: str, e: Experiment2Bulge, observations) -> list[dict]:
    """results.json objects of one scenario and screen model: the Experiment 1 keys, then
    ``screen_model`` and ``free_parameters`` (the contract), then diagnostics."""
    sm = e.result.screen_model
    shape_max, shape_rms = screen_shape_error_um(scenario.truth, e.model, observations)
    out = []
    for c in e.cases:
        rec = c.as_record()
        rec = {"bulge_mm": rec.pop("bulge_mm"), "camera": rec.pop("camera"),
               "max_height_diff_um": rec.pop("max_height_diff_um"), "max_dev_plane_um": rec.pop("max_dev_plane_um"),
               "tilt_urad": rec.pop("tilt_urad"),
               "screen_model": screen_model, "free_parameters": 0 if sm is None else int(sm.n_free),
               "scenario": scenario.name, "mirror_sag_um": scenario.mirror_sag_um,
               "calibration_rms_px": float(e.result.rms_px), "calibration_converged": bool(e.result.converged),
               "calibration_condition_number": float(e.result.condition_number),
               "frame_turn_deg": float(e.deviation["table_turn_deg"]),
               "screen_shape_max_error_um": shape_max, "screen_shape_rms_error_um": shape_rms, **rec}
        if sm is not None:
            cx = 0.5 * (sm.grid_x_mm[0] + sm.grid_x_mm[-1])
            cy = 0.5 * (sm.grid_y_mm[0] + sm.grid_y_mm[-1])
            rec["screen_central_height_mm"] = float(np.ravel(sm.height(cx, cy))[0])
        out.append(rec)
    return out


def run_experiment3(scenarios: Iterable[Experiment3Scenario], grids: Iterable[int] = (3, 5, 9), *,
                    method: str = "stepwise", progress: Progress | None = None):
    """Experiment 3 (beyond the paper, §5): for every scenario, simulate the calibration data
    once, then calibrate and reconstruct with the planar model and each n × n free-form model.

    Yields
    ------
    (scenario, screen_model label, Experiment2Bulge, records) per scenario and model, in order.
    Where the calibration data cannot determine a model (e.g. control heights that no mirror
    pose's reflection reaches), the third item is the :class:`~pmdsim.calibration.CalibrationDataError`
    that says which parameters and why, and ``records`` is empty: the other models still run.
    """
    from ..calibration import CalibrationDataError

    grids = list(grids)
    for sc in scenarios:
        if progress is not None:
            progress(f"{sc.label}: simulating the calibration poses")
        obs = simulate_calibration_observations(sc.truth)
        for g in [None, *grids]:
            label = "planar" if g is None else f"{g}x{g}"
            if progress is not None:
                progress(f"{sc.label}: {label} screen model")
            try:
                e = calibrate_and_reconstruct(sc.truth, bulge_mm=sc.bulge_mm, method=method,
                                              start_seed=sc.start_seed, screen_grid=g, observations=obs,
                                              uncertainty=True)
            except CalibrationDataError as err:
                yield sc, label, err, []
                continue
            yield sc, label, e, experiment3_records(sc, label, e, obs)
