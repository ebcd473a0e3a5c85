"""Experiment 4 (issue 13, beyond the paper): the error budget of realistic image formation.

The Table 1 setup with Δh = 3 mm is calibrated with the free 3 × 3 screen model (so that the
screen's shape is not the dominant error; :func:`~.experiment2.calibrate_and_reconstruct`) and
the planar sample reconstructed — once with the ideal camera and display of the paper, once per
image-formation effect alone at realistic values, and with all effects together (display
uncorrected and linearised). Each case records the Experiment 1 figures of merit (height
peak-to-valley, deviation from the best-fit plane, tilt, RMS) plus the slope error, so that the
dominant effect and the remedy can be read off.

At ``downsample`` K > 1 the cameras sample every K-th pixel of the same sensor (issue 20): the
pixel area, full well and noise are the real pixel's (``imaging.sampling_step_px`` = K), so the
slope figures of every row do not change with K and the noise rows change as the σ model predicts
for the coarser sampling. The heights of the systematic rows do change where the fringe-locked
slope ripple lies above the coarser sampling's Nyquist frequency: it aliases into long waves that
integrate to larger heights (``rms_plane_removed_um`` shows it; docs/experiments.md, "Experiment 4
at full resolution (K = 1)", says how to choose K).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from matplotlib.figure import Figure

from ..errors import PmdsimError
from ..geometry.cover_glass import CoverGlass
from ..io import atomic_output_dir, provenance, write_json
from ..setup import ImagingSetup, Setup
from .experiment2 import calibrate_and_reconstruct
from .report import json_ready

__all__ = ["EFFECTS", "Effect", "effect_truth", "slope_error_metrics", "run_experiment4", "write_experiment4", "experiment4_steps",
           "experiment4_table", "experiment4_figure", "BULGE_MM"]

Progress = Callable[[str], None]

#: The screen bulge of the budget (Table 1's largest Δh).
BULGE_MM = 3.0

#: A 12-bit industrial camera (full well ≈ 10.5 ke⁻, read noise 6 e⁻, dark offset 16 DN, the
#: white screen at 80 % of the full well).
_SENSOR = dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=16.0, exposure=0.8)
#: An LCD: gamma 2.2, contrast 1000:1, radiance ∝ cos²θ, 0.27 mm pixels with 80 % fill factor.
_DISPLAY = dict(display_gamma=2.2, display_black_level=0.001)
_EMISSION = dict(emission_exponent=2.0)
_PIXELS = dict(screen_pixel_pitch_mm=0.27, screen_fill_factor=0.8, pixel_area=True)
#: A 25 mm lens at f/8, one focal plane through the sample point of the principal point.
_DEFOCUS = dict(f_number=8.0, focal_length_mm=25.0)
#: An 8-bit display: the commanded pattern rounded to 256 levels.
_LEVELS = dict(display_levels=256)
#: A typical LCD cover glass (issue 21): 1.1 mm, n = 1.52; the modelled case fits t from 1 mm.
GLASS_MM = 1.1
GLASS_INDEX = 1.52
GLASS_START_MM = 1.0


@dataclass(frozen=True)
class Effect:
    """One case of the budget: its name, the ``[imaging]`` values, what it is, the remedy."""

    name: str
    imaging: dict
    description: str
    remedy: str
    #: The finest fringe period (mm, both directions) when the case changes it (a remedy), else
    #: None: the setup's periods.
    finest_period_mm: float | None = None
    #: The true screen's cover-glass thickness (mm, n = :data:`GLASS_INDEX`), else None: none.
    glass_mm: float | None = None
    #: Whether the calibration models the glass (thickness fitted from :data:`GLASS_START_MM`).
    model_glass: bool = False

    def as_imaging(self) -> ImagingSetup | None:
        return ImagingSetup(**self.imaging) if self.imaging else None


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("ideal", {}, "the paper's ideal 8-bit camera and linear display", "—"),
    Effect("sensor", _SENSOR, "12-bit camera: shot and read noise, dark offset",
           "more phase shifts or averaged frames (σ ∝ 1/√N), a longer exposure, a finer period"),
    Effect("gamma_uncorrected", _DISPLAY, "LCD response: gamma 2.2, contrast 1000:1, not corrected",
           "linearise with a grey-level calibration series, or more phase shifts (N ≥ 6 rejects "
           "the 3rd and 4th harmonics: harmonic n leaks into the phase iff n ≡ ±1 mod N)"),
    Effect("gamma_corrected", {**_DISPLAY, "linearise": True}, "LCD response, linearised from a simulated "
           "grey-level series", "—"),
    Effect("emission", _EMISSION, "screen radiance falling off as cos²θ with the viewing angle",
           "nothing needed (offset and modulation scale alike); keep the exposure below saturation"),
    Effect("screen_pixels", _PIXELS, "0.27 mm screen pixels, 80 % fill factor (with camera pixel-area "
           "integration)", "periods ≫ the pixel pitch; defocus averages the black matrix"),
    Effect("pixel_area", {"pixel_area": True}, "camera pixel-area integration",
           "longer periods (transfer sinc(footprint/p))"),
    Effect("defocus_f8", _DEFOCUS, "f/8, one focal plane on the sample: the screen is out of focus "
           "(uniform-disc pupil; contrast reversed where σ > 0.305·p: the decoder corrects the π flip, "
           "pixels near a zero of the transfer are flagged)",
           "a smaller aperture (higher f-number), longer periods (transfer 2·J₁(x)/x, x = 4πσ/p: reversed "
           "and weak where σ > 0.305·p, zero at σ = 0.305·p and 0.558·p)"),
    Effect("display_levels", _LEVELS, "8-bit display: the commanded fringe rounded to 256 levels",
           "more phase shifts (the rounding's harmonics n ≡ ±1 mod N fold into the phase), or a "
           "display with more levels"),
    Effect("viewing_angle", {**_DISPLAY, "lcd_mode": "ips"}, "gamma 2.2 uncorrected, seen through an IPS cell "
           "between crossed polarisers: luminance and gamma change with each pixel's viewing angle",
           "N ≥ 6 shifts (rejects the 3rd and 4th harmonics of every pixel's curve); a normally viewed "
           "grey-level series cannot linearise the oblique curves"),
    Effect("viewing_angle_corrected", {**_DISPLAY, "lcd_mode": "ips", "linearise": True}, "the same, "
           "linearised from a normally viewed grey-level series: what linearisation leaves",
           "N ≥ 6 shifts; view the screen closer to its normal"),
    Effect("glass_ignored", {}, f"{GLASS_MM:g} mm cover glass (n = {GLASS_INDEX:g}) over the screen, not modelled",
           "model the glass: declare [screen] cover_glass_thickness_mm and fit it ([calibration] "
           "fit_glass_thickness = true)", glass_mm=GLASS_MM),
    Effect("glass_modelled", {}, f"{GLASS_MM:g} mm cover glass, thickness fitted by the calibration "
           f"(start {GLASS_START_MM:g} mm)", "—", glass_mm=GLASS_MM, model_glass=True),
    Effect("all_uncorrected", {**_SENSOR, **_DISPLAY, **_EMISSION, **_PIXELS, **_DEFOCUS},
           "every effect, display not corrected", "linearise; then the remaining budget"),
    Effect("all_corrected", {**_SENSOR, **_DISPLAY, **_EMISSION, **_PIXELS, **_DEFOCUS, "linearise": True},
           "every effect, display linearised", "—"),
    # Every effect but the sensor's noise (a noiseless 12-bit camera): the row that must not change
    # with --downsample K (issue 20).
    Effect("all_systematic", {"bit_depth": 12, **_DISPLAY, **_EMISSION, **_PIXELS, **_DEFOCUS, **_LEVELS},
           "every effect but sensor noise (noiseless 12-bit camera), display not corrected",
           "N ≥ 6 shifts (rejects the 3rd and 4th harmonics of the gamma), longer periods or a smaller aperture"),
    # The remedy for the defocus that dominates at the Table 1 periods: a finest period of 8 mm,
    # whose transfer 2·J₁(x)/x (x = 4πσ/p) at the f/8 blur spot (σ ≈ 0.5–0.9 mm) is 0.77–0.93
    # instead of a reversed or vanishing contrast at 2 mm (docs/experiments.md).
    Effect("all_uncorrected_p8mm", {**_SENSOR, **_DISPLAY, **_EMISSION, **_PIXELS, **_DEFOCUS},
           "every effect, display not corrected, finest period 8 mm", "linearise; then the remaining budget",
           finest_period_mm=8.0),
    Effect("all_corrected_p8mm", {**_SENSOR, **_DISPLAY, **_EMISSION, **_PIXELS, **_DEFOCUS, "linearise": True},
           "every effect, display linearised, finest period 8 mm", "—", finest_period_mm=8.0),
)}


def _with_finest_period(setup: Setup, period_mm: float) -> Setup:
    """``setup`` with the finest period of both directions replaced by ``period_mm`` (the coarser
    periods kept: the hierarchical unwrapping ratio stays ≤ their ratio)."""
    seq = setup.patterns.sequence
    px = tuple(seq.periods_x_mm[:-1]) + (period_mm,)
    py = tuple(seq.periods_y_mm[:-1]) + (period_mm,)
    return setup.with_patterns(periods_x_mm=px, periods_y_mm=py)


def slope_error_metrics(normals: np.ndarray, true_normal=(0.0, 0.0, 1.0)) -> dict[str, float]:
    """Slope error of reconstructed normals against the true one (the sample plane's), in µrad.

    The slope error of a pixel is the angle between its reconstructed normal and the true
    normal (orientation ignored): what deflectometry measures, before any integration (the
    integrated heights average neighbouring slopes and hide pixel-to-pixel slope noise).

    Parameters
    ----------
    normals : ndarray (H, W, 3)
        Reconstructed normals (NaN outside the reconstruction).
    true_normal : array_like (3,)
        The true normal in the same frame (default: the frame's z axis).

    Returns
    -------
    dict
        ``slope_rms_urad`` (RMS of the angle) and ``slope_max_urad`` (its maximum).
    """
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    t = np.asarray(true_normal, dtype=float)
    t = t / np.linalg.norm(t)
    ok = np.isfinite(n).all(-1)
    if ok.sum() < 1:
        return {"slope_rms_urad": float("nan"), "slope_max_urad": float("nan")}
    n = n[ok] / np.linalg.norm(n[ok], axis=-1, keepdims=True)
    # atan2(|n × t|, |n · t|): accurate for the µrad angles involved.
    ang = np.arctan2(np.linalg.norm(np.cross(n, t), axis=-1), np.abs(n @ t)) * 1e6
    return {"slope_rms_urad": float(np.sqrt(np.mean(ang**2))), "slope_max_urad": float(ang.max())}


def _plane_removed_rms_um(p_mm: np.ndarray, err_mm: np.ndarray) -> float:
    """RMS (µm) of the height error ``err_mm`` (H, W) after its least-squares plane over the
    points ``p_mm`` (H, W, 3): the part of the error that no tilt or offset (the calibrated table
    plane's, the seed's) explains (docs/experiments.md, "Experiment 4 at full resolution")."""
    x, y, e = (np.asarray(a, dtype=float).ravel() for a in (p_mm[..., 0], p_mm[..., 1], err_mm))
    m = np.isfinite(x) & np.isfinite(y) & np.isfinite(e)
    A = np.column_stack([x[m], y[m], np.ones(int(m.sum()))])
    coef, *_ = np.linalg.lstsq(A, e[m], rcond=None)
    return float(np.sqrt(np.mean((e[m] - A @ coef) ** 2)) * 1e3)


def effect_truth(base: Setup, name: str, downsample: int = 1) -> Setup:
    """The true setup of effect ``name`` (Δh = :data:`BULGE_MM`) sampled at every ``downsample``-th
    pixel of the same camera (the real pixel's area, full well and noise: issue 20)."""
    eff = EFFECTS[name]
    truth = base.binned(downsample).with_bulge(BULGE_MM)
    if eff.imaging:
        truth = truth.with_imaging(eff.as_imaging().with_(sampling_step_px=downsample))
    if eff.finest_period_mm is not None:
        truth = _with_finest_period(truth, eff.finest_period_mm)
    if eff.glass_mm is not None:
        truth = truth.with_cover_glass(eff.glass_mm, GLASS_INDEX)
    return truth


def experiment4_steps(base: Setup, effects: Sequence[str]) -> int:
    """How many ``progress`` calls :func:`write_experiment4` makes."""
    n_poses = len(base.calibration.mirror_poses(base.sample))
    return len(effects) * (n_poses * len(base.cameras) + 1 + len(base.cameras))


def run_experiment4(base: Setup, effects: Sequence[str], *, downsample: int = 1, method: str = "stepwise",
                    seed: int = 0, progress: Progress | None = None) -> tuple[list[dict], list]:
    """Calibrate (3 × 3 free screen) and reconstruct with every effect of ``effects``.

    Returns
    -------
    records : list of dict
        One per effect and camera: the Experiment 1 keys, ``effect``, slope metrics, the
        calibration RMS; metrics None and ``error`` set where the case failed (e.g. no valid
        seed pixel: the fringes washed out).
    cases : list of (effect, CaseResult)
    """
    bad = [e for e in effects if e not in EFFECTS]
    if bad:
        raise ValueError(f"unknown effect(s) {bad}; expected some of {list(EFFECTS)}")
    records, cases = [], []
    for name in effects:
        eff = EFFECTS[name]
        truth = effect_truth(base, name, downsample)
        glass = CoverGlass(GLASS_START_MM, GLASS_INDEX) if eff.model_glass else None
        try:
            e2 = calibrate_and_reconstruct(truth, bulge_mm=BULGE_MM, method=method, start_seed=[seed, 3000],
                                           progress=progress, screen_grid=3, glass=glass)
        except (PmdsimError, ValueError, np.linalg.LinAlgError) as exc:
            for cam in truth.cameras:
                records.append({"bulge_mm": BULGE_MM, "camera": cam, "effect": name, "max_height_diff_um": None,
                                "max_dev_plane_um": None, "tilt_urad": None, "rms_um": None,
                                "error": f"{type(exc).__name__}: {exc}", "imaging": eff.imaging})
            continue
        for c in e2.cases:
            rec = {**c.as_record(), "effect": name, **slope_error_metrics(c.n_sample),
                   "rms_plane_removed_um": _plane_removed_rms_um(c.p_sample_mm, c.height_error_mm),
                   "calibration_rms_px": float(e2.result.rms_px), "calibration_converged": bool(e2.result.converged),
                   "imaging": eff.imaging}
            records.append(rec)
            cases.append((name, c))
    return records, cases


def _dominant(records: list[dict]) -> dict | None:
    """The single effect with the largest RMS height error beyond the ideal case."""
    ideal = max((r["rms_um"] for r in records if r["effect"] == "ideal" and r.get("rms_um") is not None), default=0.0)
    single = [r for r in records if r["effect"] != "ideal" and not r["effect"].startswith("all_")
              and r.get("rms_um") is not None]
    if not single:
        return None
    worst = max(single, key=lambda r: r["rms_um"])
    excess = float(np.sqrt(max(worst["rms_um"] ** 2 - ideal**2, 0.0)))
    return {"effect": worst["effect"], "camera": worst["camera"], "rms_um": worst["rms_um"],
            "excess_over_ideal_um": excess, "remedy": EFFECTS[worst["effect"]].remedy}


def experiment4_table(records: list[dict], title: str) -> str:
    """The budget as text: one row per effect and camera, then the dominant effect and remedies."""
    head = f"{'effect':<22} {'camera':<7} {'PV µm':>9} {'plane dev µm':>12} {'tilt µrad':>10} {'RMS µm':>8} " \
           f"{'slope RMS µrad':>15} {'pixels':>7}"
    lines = [title, head, "-" * len(head)]
    for r in records:
        if r.get("rms_um") is None:
            lines.append(f"{r['effect']:<22} {r['camera']:<7} failed: {r.get('error', '')[:120]}")
            continue
        lines.append(f"{r['effect']:<22} {r['camera']:<7} {r['max_height_diff_um']:9.3f} {r['max_dev_plane_um']:12.3f} "
                     f"{r['tilt_urad']:10.2f} {r['rms_um']:8.3f} {r['slope_rms_urad']:15.2f} {r['n_pixels']:7d}")
    dom = _dominant(records)
    if dom is not None:
        lines.append("")
        lines.append(f"dominant single effect: {dom['effect']} ({dom['camera']} camera, RMS {dom['rms_um']:.3f} µm, "
                     f"{dom['excess_over_ideal_um']:.3f} µm beyond the ideal case in quadrature)")
        lines.append(f"what to do: {dom['remedy']}")
    lines.append("")
    lines.append("remedies:")
    for name in dict.fromkeys(r["effect"] for r in records):
        if EFFECTS[name].remedy != "—":
            lines.append(f"  {name}: {EFFECTS[name].remedy}")
    return "\n".join(lines)


def experiment4_figure(records: list[dict], *, suptitle: str, path: str | Path | None = None) -> Figure:
    """Bars of height PV, RMS and slope RMS per effect and camera (returns the Figure)."""
    effects = list(dict.fromkeys(r["effect"] for r in records))
    cams = list(dict.fromkeys(r["camera"] for r in records))
    fig = Figure(figsize=(11.0, 4.2), dpi=120)
    axes = fig.subplots(1, 3)
    x = np.arange(len(effects))
    width = 0.8 / max(len(cams), 1)
    for ax, key, label in zip(axes, ("max_height_diff_um", "rms_um", "slope_rms_urad"),
                              ("height PV (µm)", "height RMS (µm)", "slope RMS (µrad)")):
        for i, cam in enumerate(cams):
            vals = [next((r.get(key) for r in records if r["effect"] == e and r["camera"] == cam), None)
                    for e in effects]
            ax.bar(x + i * width, [np.nan if v is None else v for v in vals], width, label=cam)
        ax.set_xticks(x + 0.4 - width / 2, effects, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(label)
        ax.set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, metadata={"Software": None})
    return fig


@dataclass(frozen=True)
class Experiment4Output:
    table: str
    files: tuple[str, ...]
    seconds: float

    def summary(self, out_dir) -> str:
        return f"wrote {', '.join(self.files)} to {out_dir} in {self.seconds:.1f} s"


def write_experiment4(out_dir: str | Path, base: Setup, *, effects: Sequence[str] | None = None,
                      downsample: int = 1, method: str = "stepwise", seed: int = 0, force: bool = False,
                      command: str | None = None, progress: Progress | None = None) -> Experiment4Output:
    """Experiment 4 written to ``out_dir``: ``results.json`` (one object per effect and camera:
    the Experiment 1 keys plus ``effect``), ``run.json`` (provenance, options, the dominant
    effect and remedies), ``table.txt`` and ``error_budget.png``."""
    effects = list(EFFECTS) if effects is None else list(effects)
    bad = [e for e in effects if e not in EFFECTS]
    if bad:
        raise ValueError(f"unknown effect(s) {bad}; expected some of {list(EFFECTS)}")
    prov = provenance(command, base.to_toml())
    t0 = time.perf_counter()
    with atomic_output_dir(out_dir, force=force) as tmp:
        records, _ = run_experiment4(base, effects, downsample=downsample, method=method, seed=seed,
                                     progress=progress)
        cam0 = next(iter(base.cameras.values())).camera.binned(downsample)
        title = (f"Experiment 4 — error budget of image formation; Δh = {BULGE_MM:g} mm, 3 × 3 free screen model, "
                 f"{method} integration, {cam0.width_px}×{cam0.height_px} px per camera")
        table = experiment4_table(records, title)
        write_json(tmp / "results.json", json_ready(records))
        write_json(tmp / "run.json", json_ready({
            **prov, "experiment": 4, "downsample": downsample, "method": method, "seed": seed, "bulge_mm": BULGE_MM,
            "screen_grid": 3, "image_size_px": [cam0.width_px, cam0.height_px],
            "effects": {e: {"imaging": EFFECTS[e].imaging, "description": EFFECTS[e].description,
                            "remedy": EFFECTS[e].remedy, "finest_period_mm": EFFECTS[e].finest_period_mm}
                        for e in effects},
            "dominant": _dominant(records)}))
        (tmp / "table.txt").write_text(table + "\n", encoding="utf-8")
        experiment4_figure(records, suptitle=title, path=tmp / "error_budget.png")
    return Experiment4Output(table, ("results.json", "run.json", "table.txt", "error_budget.png"),
                             time.perf_counter() - t0)
