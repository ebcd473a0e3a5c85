"""Residual diagnostics of a calibration: is the fit as good as the images' noise allows? (issue 11)

A calibration's residuals r_k (px) come from the noise of the decoded screen points q_k
(σ = the decoder's ``q_std_mm``, propagated through the model) and from anything the model does
not describe — a camera or the mirror that moved during one pose, a wrong pose order, a bent
mirror. The noise part is predicted per correspondence by the linear propagation

    E‖r_k‖² = Σ_j ‖∂r_k/∂q_j‖² σ_j²,   j ∈ {x_q, y_q},

(∂r/∂q by forward differences of the model's residuals, :func:`~.solver.residuals_and_jacobian`),
so the ratio of the observed RMS to the predicted one is ≈ 1 for a model that fits and much larger
for one that does not. It is computed per (camera, pose) block, which names the pose and camera
where the model breaks down — the common real-world mistake being one bad pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .model import Observations
from .result import CalibrationResult
from .solver import residuals_and_jacobian

__all__ = ["RATIO_WARN", "OUTLIER_FACTOR", "BlockResidual", "ResidualReport", "residual_report"]

#: The residual RMS may exceed the predicted noise by this factor before it is reported.
RATIO_WARN = 3.0
#: A block stands out if its ratio exceeds this multiple of the median block's (and RATIO_WARN).
OUTLIER_FACTOR = 1.5
_MAX_SAMPLES = 400
_EPS_MM = 1e-3


@dataclass(frozen=True)
class BlockResidual:
    """One (camera, pose) block: observed RMS, predicted noise RMS (px) and their ratio."""

    camera: str
    pose_index: int
    rms_px: float
    predicted_rms_px: float

    @property
    def ratio(self) -> float:
        return self.rms_px / self.predicted_rms_px if self.predicted_rms_px > 0 else math.inf


@dataclass(frozen=True)
class ResidualReport:
    """Result of :func:`residual_report`.

    Attributes
    ----------
    blocks : tuple[BlockResidual, ...]
        Per (camera, pose), in the observations' order.
    rms_px, predicted_rms_px : float
        Overall observed and predicted RMS (px).
    outliers : tuple[BlockResidual, ...]
        Blocks whose ratio exceeds both :data:`RATIO_WARN` and :data:`OUTLIER_FACTOR` × the median
        ratio, worst first.
    """

    blocks: tuple
    rms_px: float
    predicted_rms_px: float
    outliers: tuple

    @property
    def ratio(self) -> float:
        return self.rms_px / self.predicted_rms_px if self.predicted_rms_px > 0 else math.inf

    def warning(self, pose_labels=None) -> str | None:
        """One line if the residuals exceed the predicted noise (overall or in some blocks), else None."""
        if not (self.ratio > RATIO_WARN or self.outliers):
            return None
        label = (lambda k: f"pose {k} ({pose_labels[k]})") if pose_labels else (lambda k: f"pose {k}")
        text = (f"calibration RMS {self.rms_px:.4g} px is {self.ratio:.0f}× the {self.predicted_rms_px:.3g} px "
                f"the images' noise predicts")
        if self.outliers:
            worst = ", ".join(f"{label(b.pose_index)} camera {b.camera!r} ({b.ratio:.0f}×)" for b in self.outliers[:6])
            text += (f"; residuals stand out in {worst}: check these poses (camera or mirror moved, wrong pose "
                     f"order?) and calibrate without them")
        else:
            text += "; the model does not fit all poses alike (setup, mirror flatness, screen shape?)"
        return text


def _predicted_ms(o: Observations, state, rng: np.random.Generator) -> tuple[float, int]:
    """Mean predicted ‖r_k‖² (px²) over up to _MAX_SAMPLES correspondences of ``o``, and their count."""
    if o.q_std_mm is None or o.n == 0:
        return math.nan, 0
    idx = np.arange(o.n) if o.n <= _MAX_SAMPLES else np.sort(rng.choice(o.n, _MAX_SAMPLES, replace=False))
    uv, q, sd = o.uv_px[idx], o.q_screen_mm[idx], o.q_std_mm[idx]
    r0 = residuals_and_jacobian([Observations(o.camera, o.pose_index, uv, q, sd)], state)[0].reshape(-1, 2)
    total = np.zeros(idx.size)
    for j in range(2):
        qj = q.copy()
        qj[:, j] += _EPS_MM
        rj = residuals_and_jacobian([Observations(o.camera, o.pose_index, uv, qj, sd)], state)[0].reshape(-1, 2)
        total += np.sum(((rj - r0) / _EPS_MM) ** 2, axis=1) * sd[:, j] ** 2
    ok = np.isfinite(total)
    return (float(np.mean(total[ok])) if ok.any() else math.nan), int(ok.sum())


def residual_report(observations, result: CalibrationResult, *, seed: int = 0) -> ResidualReport:
    """Compare a calibration's residuals with the noise predicted from the observations' ``q_std_mm``.

    Parameters
    ----------
    observations : iterable of Observations
        What :func:`~.solver.calibrate` was given (with ``q_std_mm``: the decoder's σ).
    result : CalibrationResult
        Its result (residual RMS per block, the estimated state).
    seed : int
        Seed of the subsample (≤ 400 correspondences per block) for the prediction.

    Returns
    -------
    ResidualReport
        Per-block observed / predicted RMS (px), the overall ratio and the blocks that stand out.
        Predictions are NaN (and nothing is reported) for observations without ``q_std_mm``.
    """
    rng = np.random.default_rng(seed)
    state = result.state
    merged: dict = {}
    for o in observations:
        merged.setdefault((o.camera, o.pose_index), []).append(o)
    blocks = []
    ssr_obs = 0.0
    n_obs = 0
    ms_sum = 0.0
    for key, obs in merged.items():
        rms = result.rms_px_by_camera_pose.get(key, math.nan)
        preds = [_predicted_ms(o, state, rng) for o in obs]
        n = sum(o.n for o in obs)
        w = sum(c for _, c in preds)
        ms = sum(m * c for m, c in preds if c) / w if w else math.nan
        blocks.append(BlockResidual(key[0], key[1], float(rms), math.sqrt(ms / 2.0) if ms == ms else math.nan))
        if math.isfinite(rms) and ms == ms:
            ssr_obs += rms ** 2 * n
            ms_sum += ms / 2.0 * n
            n_obs += n
    rms_all = math.sqrt(ssr_obs / n_obs) if n_obs else math.nan
    pred_all = math.sqrt(ms_sum / n_obs) if n_obs else math.nan
    ratios = np.array([b.ratio for b in blocks if math.isfinite(b.predicted_rms_px)])
    med = float(np.median(ratios)) if ratios.size else math.nan
    outliers = sorted((b for b in blocks if math.isfinite(b.predicted_rms_px)
                       and b.ratio > max(RATIO_WARN, OUTLIER_FACTOR * med)), key=lambda b: -b.ratio)
    return ResidualReport(tuple(blocks), rms_all, pred_all, tuple(outliers))
