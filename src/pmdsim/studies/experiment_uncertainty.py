"""Per-pixel height uncertainty in the experiments' ``results.json`` (issue 22, item 2).

Experiments 2, 3 and 5 add, per case and camera (docs/experiments.md, "Height uncertainty in
the experiments"):

``height_std_um``
    {rms, max, median, noise_rms, calibration_rms, pixels}: statistics of the combined standard
    uncertainty (k = 1) of the height over the reconstructed pixels that carry one, µm, and the
    RMS of its noise and calibration contributions
    (:func:`pmdsim.evaluation.uncertainty.surface_uncertainty`).
``coverage_k2``
    The fraction of those pixels with |error| ≤ 2σ. The error is the experiment's own height
    error with *nothing removed* (reconstructed minus true height; the seed pixel has its true
    height, so the error is 0 there), and σ is the standard uncertainty relative to the same
    seed — the two are referred to the same point, so they are comparable. For Gaussian errors
    with the stated σ the expected fraction is erf(√2) = 0.9545; a single realisation of a
    correlated error field (one calibration draw moves every pixel together) scatters about it.
``height_std_notes`` and ``height_std_ignores``
    What σ covers, and the known model errors it does not (a bias, not a scatter): a coverage
    far below 0.95 is then explained by a listed item, not by a wrong σ.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..errors import PmdsimError
from ..evaluation.uncertainty import NO_COVARIANCE_NOTE

__all__ = ["COVERAGE_GAUSSIAN_K2", "coverage_k2", "case_uncertainty", "case_uncertainty_record", "height_std_summary", "uncertainty_record",
           "reconstruction_uncertainty", "model_error_labels", "screen_representation_error_mm",
           "stereo_uncertainty_record", "STEREO_NO_SIGMA_NOTE", "IGNORES_PLANAR_BULGE", "IGNORES_IDEAL_IMAGES", "IGNORES_MIRROR_SAG",
           "IGNORES_COVER_GLASS", "IGNORES_SCREEN_SHAPE", "IGNORES_LATERAL"]

#: P(|e| ≤ 2σ) of a Gaussian error: erf(2/√2).
COVERAGE_GAUSSIAN_K2 = math.erf(math.sqrt(2.0))

#: Labels of ``height_std_ignores`` (the known model errors σ does not cover).
IGNORES_PLANAR_BULGE = "planar screen model's bias under a bulge"
IGNORES_SCREEN_SHAPE = "free-form screen model cannot represent the true screen shape"
IGNORES_IDEAL_IMAGES = "ideal images: σ covers quantisation only"
IGNORES_MIRROR_SAG = "mirror sag"
IGNORES_COVER_GLASS = "unmodelled cover glass"
IGNORES_LATERAL = "lateral error × sample slope"
#: A stereo σ without the calibration's part (the setup carries no covariance): the absolute
#: level rests on the calibrated cameras' poses, whose uncertainty σ then ignores.
IGNORES_STEREO_CALIBRATION = "the calibration's uncertainty (stereo σ: the images' noise only)"

#: A screen model whose best representation of the true screen misses it by more than this
#: (mm) is labelled: 1 µm of screen height moves a slope by ≈ 1e-3 µrad per mm of lever — far
#: below every σ here, while the labelled cases miss by tens of µm or more.
SCREEN_REPRESENTATION_TOL_MM = 1e-3


def coverage_k2(error, sigma, k: float = 2.0) -> float | None:
    """Fraction of the pixels where both ``error`` and ``sigma`` are finite with
    |error| ≤ k·sigma (same units); None when there is no such pixel."""
    e = np.asarray(error, dtype=float)
    s = np.asarray(sigma, dtype=float)
    ok = np.isfinite(e) & np.isfinite(s)
    if not ok.any():
        return None
    return float(np.mean(np.abs(e[ok]) <= k * s[ok]))


def _rms(a) -> float:
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def height_std_summary(height_std_um, noise_um, calibration_um) -> dict | None:
    """``height_std_um`` of results.json: {rms, max, median, noise_rms, calibration_rms, pixels}
    over the pixels with a finite combined σ (µm); None when no pixel has one."""
    h = np.asarray(height_std_um, dtype=float)
    ok = np.isfinite(h)
    if not ok.any():
        return None
    v = h[ok]
    n = np.nan_to_num(np.asarray(noise_um, dtype=float)[ok])
    c = np.nan_to_num(np.asarray(calibration_um, dtype=float)[ok])
    return {"rms": _rms(v), "max": float(v.max()), "median": float(np.median(v)), "noise_rms": _rms(n),
            "calibration_rms": _rms(c), "pixels": int(ok.sum())}


def uncertainty_record(maps: dict | None, error_mm, *, notes=(), ignores=()) -> dict:
    """The results.json keys of one case: ``height_std_um`` (:func:`height_std_summary`),
    ``coverage_k2`` (error in mm against the combined σ), ``height_std_notes`` (text; the notes
    joined by "; ") and ``height_std_ignores`` (list). ``maps``: {"height_std_um",
    "height_std_noise_um", "height_std_calibration_um"} (H, W) µm, or None when σ could not be
    computed (then the statistics and the coverage are null and the notes say why)."""
    if maps is None:
        summary, cov = None, None
    else:
        h = np.asarray(maps["height_std_um"], dtype=float)
        summary = height_std_summary(h, maps["height_std_noise_um"], maps["height_std_calibration_um"])
        cov = coverage_k2(np.asarray(error_mm, dtype=float) * 1e3, h)
    return {"height_std_um": summary, "coverage_k2": cov, "height_std_notes": "; ".join(dict.fromkeys(notes)),
            "height_std_ignores": list(dict.fromkeys(ignores))}


#: Why a stereo evaluation's keys are null.
STEREO_NO_SIGMA_NOTE = ("stereo evaluation: no per-pixel σ (the stereo reconstruction carries none); "
                        "height_std_um and coverage_k2 are null")


def stereo_uncertainty_record(truth, camera_result, error_mm, *, screen_grid: int | None,
                              curved_sample: bool = False) -> dict:
    """The keys of one camera of a stereo evaluation: from its σ maps if the stereo result carries
    them (an ``uncertainty`` attribute with ``height_std_um``, ``height_std_noise_um`` and
    ``height_std_calibration_um``, µm: the σ of the absolute heights the stereo anchors fix),
    else nulls with :data:`STEREO_NO_SIGMA_NOTE`; labelled as the mono evaluations."""
    ignores, label_notes = model_error_labels(truth, screen_grid=screen_grid, curved_sample=curved_sample)
    u = getattr(camera_result, "uncertainty", None)
    names = ("height_std_um", "height_std_noise_um", "height_std_calibration_um")
    if u is None or not all(hasattr(u, n) for n in names):
        return uncertainty_record(None, None, notes=(STEREO_NO_SIGMA_NOTE, *label_notes), ignores=ignores)
    maps = {n: np.asarray(getattr(u, n), dtype=float) for n in names}
    u_notes = tuple(getattr(u, "notes", ()) or ())
    if NO_COVARIANCE_NOTE in u_notes:  # the absolute level rests on the calibrated poses, σ without them
        ignores = (*ignores, IGNORES_STEREO_CALIBRATION)
    return uncertainty_record(maps, error_mm, notes=(*u_notes, *label_notes), ignores=ignores)


def reconstruction_uncertainty(model, camera: str, decoded, reg, rec, parts, *, method: str,
                               screen_model=None) -> tuple[dict | None, list[str]]:
    """The σ maps of one camera's reconstruction made of one or more independently seeded
    regions, each relative to its own seed.

    Parameters
    ----------
    model : Setup
        The evaluating (calibrated) setup; its ``calibration_covariance``, if any, gives the
        calibration contribution.
    camera : str
    decoded : ScreenCoordinates
    reg : Registration
    rec : Reconstruction
        All regions' heights (``reconstructed`` their union).
    parts : list of (seed_pixel (v, u), seed_height_mm, mask (H, W) bool)
        The regions: each region's pixels were reconstructed from its seed at that height.
    method : {"stepwise", "least_squares"}
    screen_model : surface, optional
        The evaluation's screen model (None: the plane).

    Returns
    -------
    (maps, notes)
        maps: {"height_std_um", "height_std_noise_um", "height_std_calibration_um"} (H, W) µm,
        NaN off the regions and in a region whose σ failed; None when no region has σ. notes:
        the σ's own notes and every failure's reason.
    """
    from ..evaluation.anchor import HeightAnchor
    from ..evaluation.uncertainty import surface_uncertainty

    shape = rec.reconstructed.shape
    out = {k: np.full(shape, np.nan) for k in ("height_std_um", "height_std_noise_um", "height_std_calibration_um")}
    notes: list[str] = []
    done = False
    for seed, z0, mask in parts:
        mask = np.asarray(mask, dtype=bool) & rec.reconstructed
        if not mask.any():
            continue
        seed = (int(seed[0]), int(seed[1]))
        r = replace(rec, reconstructed=mask, seed_pixel=seed)
        try:
            # A HeightAnchor at the seed pixel itself: the calibration part holds the same seed.
            u = surface_uncertainty(model, camera, decoded, reg, r, method=method, screen_model=screen_model,
                                    anchor=HeightAnchor(seed, float(z0)))
        except (PmdsimError, ArithmeticError, ValueError) as exc:
            notes.append(f"no σ for the {int(mask.sum())} pixels seeded at {list(seed)}: {exc}")
            continue
        for k in out:
            out[k][mask] = np.asarray(getattr(u, k), dtype=float)[mask]
        notes.extend(u.notes)
        done = True
    if len(parts) > 1:
        notes.append(f"{len(parts)} independently seeded regions, each σ relative to its own seed")
    return (out if done else None), notes


def _dense(surface, bounds, n: int = 41):
    x0, x1, y0, y1 = bounds
    gx, gy = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    return np.asarray(surface.height(gx, gy), dtype=float), gx, gy


def screen_representation_error_mm(truth, grid: int | None) -> float:
    """How far the screen model's space misses the true screen: the largest |difference| (mm)
    between the true screen surface and its interpolant on the model's grid (planar: 0 heights;
    n × n: the n × n not-a-knot spline through the true heights at its nodes) over the screen.
    Zero (to rounding) when the model contains the true shape (e.g. a 3 × 3 bulge in any
    n × n model)."""
    from ..geometry.surface import SplineSurface

    scr = truth.screen
    bounds = (scr.grid_x_mm[0], scr.grid_x_mm[-1], scr.grid_y_mm[0], scr.grid_y_mm[-1])
    z_true, _, _ = _dense(scr.surface, bounds)
    if grid is None:
        return float(np.abs(z_true).max())
    gx = np.linspace(bounds[0], bounds[1], int(grid))
    gy = np.linspace(bounds[2], bounds[3], int(grid))
    X, Y = np.meshgrid(gx, gy)
    fit = SplineSurface(gx, gy, np.asarray(scr.surface.height(X, Y), dtype=float))
    z_fit, _, _ = _dense(fit, bounds)
    return float(np.abs(z_fit - z_true).max())


def model_error_labels(truth, *, screen_grid: int | None, screen_glass_modelled: bool = False,
                       curved_sample: bool = False) -> tuple[list[str], list[str]]:
    """(ignores, notes): the known model errors of an evaluation of ``truth`` that σ ignores.

    Parameters
    ----------
    truth : Setup
        The simulated truth.
    screen_grid : int or None
        The calibration's screen model (None: planar; n: n × n free form).
    screen_glass_modelled : bool
        Whether the calibration and evaluation model the screen's cover glass.
    curved_sample : bool
        The error is the height minus the true height at the *reconstructed* (x, y) of a curved
        sample: a lateral error times the sample's slope enters the error but not σ (which is
        the height's at a pixel).
    """
    ignores, notes = [], []
    miss = screen_representation_error_mm(truth, screen_grid)
    if miss > SCREEN_REPRESENTATION_TOL_MM:
        bulge = truth.screen.bulge_mm is not None and truth.screen.heights_mm is None
        if screen_grid is None:
            ignores.append(IGNORES_PLANAR_BULGE if bulge else "planar screen model's bias under the screen's deformation")
            notes.append(f"the true screen deviates from the planar model by up to {miss * 1e3:.4g} µm")
        else:
            ignores.append(IGNORES_SCREEN_SHAPE)
            notes.append(f"the {screen_grid}×{screen_grid} screen model misses the true screen by up to "
                         f"{miss * 1e3:.4g} µm (its best interpolant)")
    im = truth.imaging
    sensor_noise = im is not None and getattr(im, "any_on", False) and (im.full_well_e is not None)
    if truth.patterns.noise_std == 0 and not sensor_noise:
        ignores.append(IGNORES_IDEAL_IMAGES)
        notes.append("noise-free images: the decoder's σ is the 8-bit rounding's (1/√12 grey levels), whose errors "
                     "are deterministic and correlated between pixels")
    if truth.calibration.mirror_sag_um:
        ignores.append(IGNORES_MIRROR_SAG)
        notes.append(f"the calibration mirror sags by {truth.calibration.mirror_sag_um:g} µm; the calibration takes "
                     f"it flat")
    if truth.screen.cover_glass.present and not screen_glass_modelled:
        ignores.append(IGNORES_COVER_GLASS)
        notes.append(f"the screen's {truth.screen.cover_glass.thickness_mm:g} mm cover glass is not modelled")
    if curved_sample:
        ignores.append(IGNORES_LATERAL)
        notes.append("σ is the height's at a pixel; the error compares with the true height at the reconstructed "
                     "(x, y), so a lateral error times the sample's slope is in the error, not in σ")
    return ignores, notes


def case_uncertainty(truth, model, camera: str, decoded, reg, rec, parts, error_mm, *, method: str,
                     screen_grid: int | None, glass_modelled: bool = False,
                     curved_sample: bool = False) -> tuple[dict, np.ndarray | None]:
    """(results.json keys, combined σ map (H, W) µm or None) of one camera of Experiment 2's
    chain (also Experiments 3 and 5 mono): σ of the reconstruction with the calibrated ``model``
    (its covariance gives the calibration part; :func:`reconstruction_uncertainty`) against
    ``error_mm`` (nothing removed; :func:`uncertainty_record`), labelled by
    :func:`model_error_labels`."""
    screen_model = None if screen_grid is None else model.screen.surface
    maps, notes = reconstruction_uncertainty(model, camera, decoded, reg, rec, parts, method=method,
                                             screen_model=screen_model)
    ignores, label_notes = model_error_labels(truth, screen_grid=screen_grid, screen_glass_modelled=glass_modelled,
                                              curved_sample=curved_sample)
    record = uncertainty_record(maps, error_mm, notes=[*notes, *label_notes], ignores=ignores)
    return record, (None if maps is None else maps["height_std_um"])


def case_uncertainty_record(truth, model, camera: str, decoded, reg, rec, parts, error_mm, *, method: str,
                            screen_grid: int | None, glass_modelled: bool = False, curved_sample: bool = False) -> dict:
    """The results.json keys of :func:`case_uncertainty`."""
    return case_uncertainty(truth, model, camera, decoded, reg, rec, parts, error_mm, method=method,
                            screen_grid=screen_grid, glass_modelled=glass_modelled, curved_sample=curved_sample)[0]
