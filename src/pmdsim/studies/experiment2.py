"""Experiment 2 (paper §4, Table 3, Fig. 5): holistic calibration with a planar mirror, then
reconstruction with the calibrated setup, heights relative to the calibrated table plane."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..calibration.setup_bridge import calibrated_setup, calibration_deviation, free_screen_model, nominal_setup
from ..evaluation.metrics import surface_error_metrics
from ..evaluation.pipeline import evaluate_decoded
from ..evaluation.reconstruction import ReconstructionError
from ..setup import Setup, default_setup
from ..simulation.imaging import needs_points
from ..simulation.render import trace_setup_camera
from .calibration_data import simulate_calibration_observations, simulate_decoded
from .experiment1 import CaseResult, Progress
from .experiment_uncertainty import case_uncertainty

__all__ = ["PAPER_TABLE3", "INITIAL_ERRORS", "Experiment2Bulge", "run_experiment2_bulge", "calibrate_and_reconstruct"]


#: The paper's Table 3 (Experiment 2): (Δh mm, camera) → (max height difference µm,
#: max deviation from best-fit plane µm, best-fit plane tilt µrad).
PAPER_TABLE3 = {
    (0.0, "left"): (0.0, 0.0, 0.0),
    (0.0, "right"): (0.0, 0.0, 0.1),
    (1.0, "left"): (2.6, 1.6, 6.3),
    (1.0, "right"): (2.6, 1.6, 6.5),
    (2.0, "left"): (7.6, 4.3, 20.1),
    (2.0, "right"): (7.2, 4.3, 16.7),
    (3.0, "left"): (8.5, 5.3, 10.5),
    (3.0, "right"): (8.6, 5.2, 11.0),
}


#: Errors of the nominal start values of the calibration (never the true values): camera and
#: mirror positions, angles, focal lengths (fraction), principal points.
INITIAL_ERRORS = dict(position_mm=5.0, angle_deg=2.0, focal_frac=0.03, pp_px=20.0, mirror_mm=3.0, mirror_deg=1.0)


@dataclass(frozen=True, eq=False)
class Experiment2Bulge:
    """Experiment 2 at one Δh: the calibration and both cameras' reconstructions."""

    bulge_mm: float
    result: object  # CalibrationResult
    model: Setup
    deviation: dict
    cases: list


def run_experiment2_bulge(bulge_mm: float, *, base: Setup | None = None, downsample: int = 1,
                          method: str = "stepwise", seed: int = 0, progress: Progress | None = None,
                          image_sink=None, screen_grid: int | None = None,
                          observations=None, uncertainty: bool = True) -> Experiment2Bulge:
    """Experiment 2 (paper §4) at one Δh: simulate the calibration poses → calibrate (planar
    screen model, nominal start values with :data:`INITIAL_ERRORS`) → simulate the planar
    sample → reconstruct with the calibrated parameters, heights relative to the calibrated
    table plane (the base mirror pose), seeded at the central pixel with height 0.

    ``screen_grid`` = n (odd, ≥ 3) calibrates the screen as a free-form n × n spline grid
    (border heights held: the rigid frame's plane is the gauge; interior heights free) and
    reconstructs with the calibrated screen — the paper's future work (§5); None: planar.
    ``uncertainty``: the cases carry results.json's height σ keys (docs/experiments.md).
    """
    base = default_setup() if base is None else base
    truth = base.binned(downsample).with_bulge(bulge_mm)
    return calibrate_and_reconstruct(truth, bulge_mm=bulge_mm, method=method,
                                     start_seed=[seed, int(round(bulge_mm * 1000))], progress=progress,
                                     image_sink=image_sink, screen_grid=screen_grid, observations=observations,
                                     uncertainty=uncertainty)


#: Decoded regions smaller than this (pixels) are not reconstructed on their own.
MIN_REGION_PX = 16
#: At most this many further regions are reconstructed (largest first).
MAX_REGIONS = 64


def _with_other_regions(reg, rec, method: str):
    """``rec`` plus every further 4-connected region of registered pixels it did not reach (e.g.
    where the lens reversed the finest fringes' contrast and those pixels were flagged, issue 20),
    each reconstructed from its own seed — the pixel nearest its centroid — at height 0 (returned
    with ``rec``: the list of (seed pixel, seed height, pixels) of every region): the
    regions' heights are *not* tied by the measurement; each is anchored to the table plane the
    budget's planar sample lies on, as the first region is. Regions under :data:`MIN_REGION_PX`
    pixels are left out; at most :data:`MAX_REGIONS` (largest first)."""
    from scipy import ndimage

    from ..evaluation.anchor import default_seed_pixel
    from ..evaluation.reconstruction import reconstruct

    parts = [(tuple(rec.seed_pixel), float(rec.height_mm[tuple(rec.seed_pixel)]), rec.reconstructed)]
    rest = reg.valid & ~rec.reconstructed
    labels, n = ndimage.label(rest)
    if n == 0:
        return rec, parts
    sizes = np.bincount(labels.ravel())[1:]
    order = [i + 1 for i in np.argsort(-sizes, kind="stable") if sizes[i] >= MIN_REGION_PX][:MAX_REGIONS]
    h, p, nrm, done = rec.height_mm.copy(), rec.p_sample_mm.copy(), rec.n_sample.copy(), rec.reconstructed.copy()
    for lab in order:
        region = labels == lab
        try:
            r = reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, region, method=method,
                            seed_pixel=default_seed_pixel(region), seed_height_mm=0.0)
        except ReconstructionError:
            continue
        m = r.reconstructed & ~done
        h[m], p[m], nrm[m] = r.height_mm[m], r.p_sample_mm[m], r.n_sample[m]
        done |= m
        parts.append((tuple(r.seed_pixel), 0.0, m))
    return replace(rec, height_mm=h, p_sample_mm=p, n_sample=nrm, reconstructed=done), parts


def calibrate_and_reconstruct(truth: Setup, *, bulge_mm: float | None = None, method: str = "stepwise",
                              start_seed=0, progress: Progress | None = None, image_sink=None,
                              screen_grid: int | None = None, observations=None, glass=None,
                              uncertainty: bool = False) -> Experiment2Bulge:
    """The Experiment 2 chain for any true setup (deformed screen, sagged mirror, …).

    Simulate the calibration poses of ``truth`` (or take ``observations`` of it) → calibrate
    from nominal start values (:func:`nominal_setup` perturbed by :data:`INITIAL_ERRORS`,
    seeded by ``start_seed``) with a planar (``screen_grid`` None) or n × n free-form screen
    model and planar mirrors → simulate the planar sample of ``truth`` → reconstruct both
    cameras with the calibrated setup, heights relative to the calibrated table plane (its true
    height is 0, so the reconstructed height is the error). ``bulge_mm`` labels the results
    (default: the truth's central screen control height). ``glass``: the cover glass the
    calibration models (a :class:`~pmdsim.geometry.cover_glass.CoverGlass`, its thickness fitted
    from this start, :func:`pmdsim.calibration.glass.calibrate_with_glass`); None: the truth's
    glass, if any, is ignored. ``uncertainty``: each case carries the height σ keys of
    :func:`~pmdsim.studies.experiment_uncertainty.case_uncertainty_record` (Experiments 2, 3
    and 5 set it; False, the default for other callers such as studies: skip them).
    """
    from ..calibration import calibrate, nominal_state, perturbed_state
    from ..calibration.glass import calibrate_with_glass

    nominal = nominal_setup(truth, glass)
    if bulge_mm is None:
        z = truth.screen.control_heights()
        bulge_mm = float(z[z.shape[0] // 2, z.shape[1] // 2])
    # ``observations`` lets several screen models share one simulated calibration data set.
    obs = observations if observations is not None else simulate_calibration_observations(
        truth, progress=progress, image_sink=image_sink)
    poses = [T for _, T in truth.calibration.mirror_poses(truth.sample)]
    rng = np.random.default_rng(start_seed)
    start = perturbed_state(nominal_state(nominal, poses), rng, **INITIAL_ERRORS)
    if progress is not None:
        progress(f"Δh = {bulge_mm:g} mm: calibrating")
    screen_model = None if screen_grid is None else free_screen_model(nominal, screen_grid)
    if glass is None:
        result = calibrate(obs, start, screen_model=screen_model)
    else:
        result = calibrate_with_glass(obs, start, glass, screen_model=screen_model, fit_thickness=True)
    model = calibrated_setup(nominal, result)
    deviation = calibration_deviation(truth, model)
    cases = []
    for cam in truth.cameras:
        if progress is not None:
            progress(f"Δh = {bulge_mm:g} mm: reconstructing, camera {cam}")
        m = trace_setup_camera(truth, cam, store_points=needs_points(truth))
        decoded = simulate_decoded(truth, cam, m)
        c = model.cameras[cam].camera
        seed_px = (c.height_px // 2, c.width_px // 2)
        if not decoded.valid[seed_px]:  # e.g. washed-out fringes (issue 13): the decoded pixel nearest the centre
            rows, cols = np.nonzero(decoded.valid)
            if rows.size:
                k = int(np.argmin((rows - seed_px[0]) ** 2 + (cols - seed_px[1]) ** 2))
                seed_px = (int(rows[k]), int(cols[k]))
            else:
                seed_px = None
        reg, rec = evaluate_decoded(model, cam, decoded, method=method, seed_pixel=seed_px, seed_height_mm=0.0,
                                    screen_model=None if screen_model is None else model.screen.surface)
        rec, parts = _with_other_regions(reg, rec, method)
        n_rec = int(rec.reconstructed.sum())
        if n_rec < 3:  # nothing to assess: say why instead of failing in the metrics
            n_dec = int(decoded.valid.sum())
            raise ReconstructionError(
                f"camera {cam!r}: the reconstruction reached only {n_rec} pixel(s); {n_dec} of {decoded.valid.size} "
                f"pixels were decoded ({n_dec / decoded.valid.size:.1%}) and they do not form a connected region "
                f"around the seed (fringes washed out: blur, pixel area or noise against the finest period?)")
        p = rec.p_sample_mm
        # The sample is the plane of the base mirror pose: relative to the calibrated table
        # plane its true height is 0, so the reconstructed height is the error.
        err = np.where(rec.reconstructed, rec.height_mm, np.nan)
        metrics = surface_error_metrics(p[..., 0], p[..., 1], err)
        unc, h_std = (None, None) if not uncertainty else case_uncertainty(
            truth, model, cam, decoded, reg, rec, parts, err, method=method, screen_grid=screen_grid,
            glass_modelled=glass is not None)
        cases.append(replace(CaseResult.from_reconstruction(bulge_mm, cam, rec, err, metrics), uncertainty=unc,
                             height_std_um=h_std))
    return Experiment2Bulge(float(bulge_mm), result, model, deviation, cases)
