"""Study metrics of the evaluation's per-pixel height σ (issue 22, item 6: design questions).

A ``simulate+evaluate`` case that asks for one of :data:`UNCERTAINTY_METRICS` also computes
the evaluation's standard uncertainties (:func:`pmdsim.evaluation.uncertainty.surface_uncertainty`,
the σ that ``pmdsim evaluate`` writes as ``height_std_um``; k = 1, relative to the seed pixel,
whose height the case knows) and records statistics of that map — nothing is recomputed:

* ``height_std_rms_um``, ``height_std_max_um`` — RMS and maximum of ``height_std_um`` over the
  reconstructed pixels (the figures ``pmdsim evaluate`` prints,
  :func:`~.uncertainty_job.uncertainty_stats`);
* ``height_std_edge_um`` — σ at the field's edge: the :data:`EDGE_PERCENTILE` th percentile
  (numpy's linear interpolation) of ``height_std_um`` over the reconstructed pixels. σ grows
  with the distance from the seed, so this is σ of the outermost 5 % of the field, robust to
  the few pixels of a ragged border;
* ``coverage_k2`` — the fraction of reconstructed pixels with |height error| ≤ 2σ (expanded
  uncertainty with coverage factor k = 2), the error taken against the simulated truth. About
  0.95 when σ covers the error and the error is Gaussian; lower when errors that σ does not
  model (model errors, e.g. a planar screen model of a bulged screen) dominate.
"""

from __future__ import annotations

import numpy as np

from .experiment_uncertainty import coverage_k2 as _coverage

__all__ = ["UNCERTAINTY_METRICS", "EDGE_PERCENTILE", "height_std_edge_um", "coverage_k2", "uncertainty_metrics"]

#: The σ metrics a ``simulate+evaluate`` study may record (per camera).
UNCERTAINTY_METRICS = ("height_std_rms_um", "height_std_max_um", "height_std_edge_um", "coverage_k2")

#: Percentile of ``height_std_um`` over the reconstructed pixels that defines σ at the field's edge.
EDGE_PERCENTILE = 95.0


def height_std_edge_um(height_std_um) -> float:
    """σ at the field's edge, µm: the :data:`EDGE_PERCENTILE` th percentile of the finite
    entries of ``height_std_um`` (H, W) (NaN if there are none)."""
    h = np.asarray(height_std_um, dtype=float)
    h = h[np.isfinite(h)]
    return float(np.percentile(h, EDGE_PERCENTILE)) if h.size else float("nan")


def coverage_k2(height_std_um, error_mm) -> float:
    """Fraction of pixels where both are finite with |error| ≤ 2σ (σ in µm, error in mm; NaN
    if there are none): :func:`~.experiment_uncertainty.coverage_k2` in the study tables'
    units, NaN where that gives None."""
    c = _coverage(np.asarray(error_mm, dtype=float) * 1e3, height_std_um)
    return float("nan") if c is None else c


def uncertainty_metrics(model, camera: str, decoded, reg, rec, error_mm, *, method: str, screen_model) -> dict:
    """The :data:`UNCERTAINTY_METRICS` of one camera's evaluation.

    Parameters
    ----------
    model : Setup
        The evaluating setup (its calibration covariance, if any, is part of σ).
    camera : str
    decoded : ScreenCoordinates
        The decoded images (with ``std_xy_mm``).
    reg, rec : Registration, Reconstruction
        The evaluation (:func:`pmdsim.evaluation.pipeline.evaluate_decoded`).
    error_mm : ndarray (H, W)
        Reconstructed height minus the truth (NaN where not reconstructed).
    method : {"stepwise", "least_squares"}
    screen_model : surface or None
        The evaluation's screen model (None: the plane).

    Returns
    -------
    dict
        Metric name → value.

    Raises
    ------
    UncertaintyError
        σ cannot be computed (the study records the case as failed, with this reason).
    """
    from ..evaluation.uncertainty import surface_uncertainty
    from .uncertainty_job import uncertainty_stats

    unc = surface_uncertainty(model, camera, decoded, reg, rec, method=method, screen_model=screen_model)
    st = uncertainty_stats(unc)
    return {"height_std_rms_um": st.get("height_std_rms_um", float("nan")),
            "height_std_max_um": st.get("height_std_max_um", float("nan")),
            "height_std_edge_um": height_std_edge_um(unc.height_std_um),
            "coverage_k2": coverage_k2(unc.height_std_um, error_mm)}
