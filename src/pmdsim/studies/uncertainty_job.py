"""The uncertainty part of ``pmdsim evaluate`` (issue 22): per camera, the standard
uncertainties of :mod:`pmdsim.evaluation.uncertainty`, their datasets in ``evaluation.h5``,
``height_std_{camera}.png`` and the summary lines. A σ that cannot be computed does not stop
the evaluation: the heights are written, σ is omitted and a warning says why."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..evaluation.uncertainty import SurfaceUncertainty, UncertaintyError, surface_uncertainty
from .map_png import write_height_map_png

__all__ = ["camera_uncertainty", "uncertainty_datasets", "uncertainty_attribute", "uncertainty_stats",
           "height_std_figure", "stereo_uncertainty", "stereo_figures", "stereo_attribute"]

_NAMES = ("slope_std_urad", "height_std_um", "height_std_noise_um", "height_std_calibration_um",
          "slope_std_noise_urad", "slope_std_calibration_urad")


def anchor_std_mm(anchor, override: float | None) -> float:
    """The anchor's own standard uncertainty, mm: ``override`` (the CLI option) if given, else
    the anchor's ``distance_std_mm`` / ``height_std_mm`` (manifest), else 0."""
    if override is not None:
        return float(override)
    return float(getattr(anchor, "distance_std_mm", 0.0) or getattr(anchor, "height_std_mm", 0.0) or 0.0)


def camera_uncertainty(setup, cam: str, decoded, reg, rec, *, method: str, screen_model, anchor,
                       anchor_std: float = 0.0) -> tuple[SurfaceUncertainty | None, list[str]]:
    """:func:`~pmdsim.evaluation.uncertainty.surface_uncertainty` for one camera; on
    :class:`UncertaintyError` (None, [warning]) — the caller keeps the heights."""
    from ..evaluation.anchor import DistanceAnchor, HeightAnchor

    a = anchor if isinstance(anchor, (DistanceAnchor, HeightAnchor)) else None
    try:
        return surface_uncertainty(setup, cam, decoded, reg, rec, method=method, screen_model=screen_model,
                                   anchor=a, anchor_std_mm=anchor_std), []
    except UncertaintyError as exc:
        return None, [f"{cam}: no uncertainty (σ datasets omitted, heights written): {exc}"]


def uncertainty_datasets(unc: SurfaceUncertainty | None) -> dict:
    """The σ maps of evaluation.h5 by dataset name (empty without σ)."""
    return {} if unc is None else {n: getattr(unc, n) for n in _NAMES}


def uncertainty_attribute(uncs: dict, skipped: str | None = None) -> str:
    """The ``uncertainty`` file attribute (JSON): per camera what σ is and covers, or why there is none."""
    doc = {cam: (u.describe() if u is not None else {"omitted": True}) for cam, u in uncs.items()}
    if skipped:
        doc = {"omitted": True, "reason": skipped}
    return json.dumps(doc)


def _finite_values(a: np.ndarray) -> np.ndarray:
    """The finite values of ``a`` in C order, 1-D: ``a[np.isfinite(a)]``, but without that copy
    when every value is finite (a σ map usually is)."""
    a = np.asarray(a)
    ok = np.isfinite(a)
    return a.ravel() if ok.all() else a[ok]


def _rms(values: np.ndarray) -> float:
    """RMS of 1-D values, 0 without any: the same operations as ``SurfaceUncertainty.dominant``'s."""
    return float(np.sqrt(np.mean(values * values))) if values.size else 0.0


def uncertainty_stats(unc: SurfaceUncertainty | None) -> dict:
    """RMS and maximum of ``height_std_um`` and the dominant contribution (for the summary).

    The values and the choice of :meth:`SurfaceUncertainty.dominant`, each map's RMS taken once:
    the combined map is the noise map itself when the calibration part is zero
    (``surface_uncertainty``), and an all-zero calibration map has RMS 0 (issue 25: three RMS
    passes per camera were ≈ 0.15 s of the command's rest)."""
    if unc is None:
        return {}
    h = _finite_values(unc.height_std_um)
    if not h.size:
        return {}
    rms = _rms(h)
    noise = rms if unc.height_std_noise_um is unc.height_std_um else _rms(_finite_values(unc.height_std_noise_um))
    cal = unc.height_std_calibration_um
    cal_rms = _rms(_finite_values(cal)) if np.asarray(cal).any() else 0.0  # every value ±0: RMS 0
    return {"height_std_rms_um": rms, "height_std_max_um": float(h.max()),
            "uncertainty_dominant": "calibration" if cal_rms > noise else "noise", "uncertainty_notes": list(unc.notes)}


def uncertainty_line(cam: str, c: dict) -> str | None:
    """The summary line of one camera (None without σ)."""
    if "height_std_rms_um" not in c:
        return None
    return (f"{cam}: height standard uncertainty (k = 1) RMS {c['height_std_rms_um']:.4g} µm, max "
            f"{c['height_std_max_um']:.4g} µm; dominated by {c['uncertainty_dominant']}"
            + (f" ({'; '.join(c['uncertainty_notes'])})" if c.get("uncertainty_notes") else ""))


def height_std_figure(rec, unc: SurfaceUncertainty, cam: str, path: str | Path, *,
                      relative_to: str = "relative to the anchor") -> None:
    """``height_std_{camera}.png``: the combined height σ over the sample frame, µm."""
    p = rec.p_sample_mm
    write_height_map_png(p[..., 0], p[..., 1], unc.height_std_um,
                         title=f"{cam}: height standard uncertainty (k = 1, {relative_to})",
                         label="height σ (µm)", path=path, signed=False)


def stereo_uncertainty(setup, views: dict, decoded: dict, st, *, screen: str = "planar", enabled: bool = True):
    """The σ of a stereo evaluation (:func:`pmdsim.evaluation.uncertainty_stereo.stereo_with_uncertainty`).

    ``screen``: the evaluation's screen model, "planar" or "setup" (the setup's surface).
    Returns (the StereoReconstruction with each camera's ``uncertainty`` and
    ``anchor_height_std_um``, {camera: SurfaceUncertainty or None}, warnings); on
    :class:`UncertaintyError` the heights stand, σ is None and a warning says why."""
    from ..evaluation.uncertainty_stereo import stereo_with_uncertainty

    if not enabled:
        return st, {}, []
    return stereo_with_uncertainty(setup, views, decoded, st,
                                   screen_model=None if screen == "planar" else setup.screen.surface)


def stereo_figures(tmp: Path, results: dict, uncs: dict) -> None:
    """``height_std_{camera}.png`` of a stereo evaluation (absolute σ)."""
    for cam, (_, _, rec) in results.items():
        if uncs.get(cam) is not None:
            height_std_figure(rec, uncs[cam], cam, Path(tmp) / f"height_std_{cam}.png",
                              relative_to="absolute, stereo")


def stereo_attribute(uncs: dict, enabled: bool) -> str:
    """The ``uncertainty`` attribute of a stereo evaluation: as :func:`uncertainty_attribute`,
    the heights' σ absolute (gauged by the stereo anchors)."""
    doc = json.loads(uncertainty_attribute(uncs, None if enabled else "not requested"))
    for cam, u in uncs.items():
        if u is not None:
            doc[cam]["heights_relative_to"] = ("nothing: absolute, gauged by the stereo anchors (their σ included; "
                                               "anchor_height_std_um)")
    return json.dumps(doc)


def fit_slope_std(uncs: dict, cameras) -> list | None:
    """Per camera the slopes' noise σ (H, W, 2) in rad for the surface fit, or None when a
    camera has none (the fit then carries no σ)."""
    if not uncs or any(uncs.get(c) is None for c in cameras):
        return None
    return [uncs[c].slope_std_noise_urad * 1e-6 for c in cameras]
