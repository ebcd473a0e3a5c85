"""Experiment 1 (paper §3, Table 2, Fig. 4), end to end through 8-bit images.

Simulate the Table 1 setup with a screen bulge Δh, render the fringe images, decode them, and
reconstruct the planar sample with *perfect setup knowledge* — the true cameras and poses — but
a *planar* screen model, as the paper's evaluation assumes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from ..simulation.imaging import decoder_response
from ..evaluation.metrics import surface_error_metrics
from ..evaluation.pipeline import decode_images, evaluate_decoded
from ..evaluation.reconstruction import Reconstruction
from ..setup import Setup, default_setup
from ..simulation.render import render_images, trace_setup_camera

__all__ = ["PAPER_TABLE2", "CaseResult", "run_experiment1_case", "experiment1", "Progress"]


#: The paper's Table 2 (Experiment 1): (Δh mm, camera) → (max height difference µm,
#: max deviation from best-fit plane µm, best-fit plane tilt µrad).
PAPER_TABLE2 = {
    (0.0, "left"): (0.0, 0.0, 0.0),
    (0.0, "right"): (0.0, 0.0, 0.1),
    (1.0, "left"): (49.7, 14.6, 278.5),
    (1.0, "right"): (57.8, 10.8, 259.8),
    (2.0, "left"): (99.6, 29.1, 557.4),
    (2.0, "right"): (115.8, 21.7, 520.3),
    (3.0, "left"): (149.5, 43.7, 836.6),
    (3.0, "right"): (174.1, 32.6, 781.5),
}


Progress = Callable[[str], None]


@dataclass(frozen=True, eq=False)
class CaseResult:
    """One reconstruction of one camera's data, with its error metrics.

    Only the maps needed for outputs are kept (a full-resolution experiment holds many cases).

    Attributes
    ----------
    height_mm : ndarray (H, W)
        Reconstructed height (sample frame), NaN outside the reconstructed FOV.
    height_error_mm : ndarray (H, W)
        z_reconstructed − z_true at the reconstructed points, NaN outside.
    p_sample_mm : ndarray (H, W, 3), float32
        Reconstructed points (sample frame), mm; NaN outside.
    reconstructed : ndarray (H, W) bool
        Reconstructed pixels.
    """

    bulge_mm: float
    camera: str
    metrics: dict
    method: str
    seed_pixel: tuple[int, int]
    converged: bool
    iterations: int
    height_mm: np.ndarray
    height_error_mm: np.ndarray
    p_sample_mm: np.ndarray
    reconstructed: np.ndarray
    n_sample: np.ndarray | None = None  # (H, W, 3) float32 reconstructed unit normals (sample frame)
    uncertainty: dict | None = None  # results.json's height σ keys (studies.experiment_uncertainty), if computed
    height_std_um: np.ndarray | None = None  # (H, W) combined height standard uncertainty, µm, if computed

    @classmethod
    def from_reconstruction(cls, bulge_mm, camera, rec: Reconstruction, height_error_mm, metrics) -> "CaseResult":
        return cls(float(bulge_mm), camera, metrics, rec.method, tuple(int(v) for v in rec.seed_pixel),
                   bool(rec.converged), int(rec.iterations), rec.height_mm, height_error_mm,
                   rec.p_sample_mm.astype(np.float32), rec.reconstructed, rec.n_sample.astype(np.float32))

    def as_record(self) -> dict:
        """The results.json object: the contract keys first, then the rest of the metrics."""
        m = self.metrics
        rec = {
            "bulge_mm": self.bulge_mm,
            "camera": self.camera,
            "max_height_diff_um": m["max_height_diff_um"],
            "max_dev_plane_um": m["max_dev_plane_um"],
            "tilt_urad": m["tilt_urad"],
        }
        rec.update({k: v for k, v in m.items() if k not in rec})
        rec["method"] = self.method
        rec["seed_pixel"] = list(self.seed_pixel)
        rec["converged"] = self.converged
        rec.update(self.uncertainty or {})
        return rec


def run_experiment1_case(bulge_mm: float, camera: str, *, base: Setup | None = None, downsample: int = 1,
                         method: str = "stepwise", image_sink=None) -> CaseResult:
    """One cell of Table 2: simulate with Δh = ``bulge_mm``, decode the 8-bit images and
    reconstruct with the true cameras and a planar screen model.

    The seed (initial point) of the reconstruction is the camera's central pixel with its true
    height (perfect knowledge). ``image_sink(spec, image)`` receives every rendered image.
    """
    base = default_setup() if base is None else base
    truth = base.binned(downsample).with_bulge(bulge_mm)
    mapping = trace_setup_camera(truth, camera, store_points=True)
    images: dict = {}
    for spec, img in render_images(truth, camera, mapping):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        if image_sink is not None:
            image_sink(spec, img)
    decoded = decode_images(truth, images, response=decoder_response(truth))
    del images
    model = truth.with_bulge(0.0)  # perfect knowledge, except for the screen: a plane
    cam = truth.cameras[camera].camera
    seed = (cam.height_px // 2, cam.width_px // 2)
    seed_height = float(mapping.p_sample_mm[seed][2])
    if not np.isfinite(seed_height):
        raise RuntimeError(f"the central pixel of camera {camera!r} does not see the sample; cannot seed")
    reg, rec = evaluate_decoded(model, camera, decoded, method=method, seed_pixel=seed, seed_height_mm=seed_height)
    p = rec.p_sample_mm
    true_h = truth.sample.surface.height(p[..., 0], p[..., 1])
    err = np.where(rec.reconstructed, rec.height_mm - true_h, np.nan)
    metrics = surface_error_metrics(p[..., 0], p[..., 1], err)
    return CaseResult.from_reconstruction(bulge_mm, camera, rec, err, metrics)


def experiment1(bulges: Iterable[float] = (0.0, 1.0, 2.0, 3.0), cameras: Iterable[str] | None = None, *,
                base: Setup | None = None, downsample: int = 1, method: str = "stepwise",
                progress: Progress | None = None, image_sink=None) -> list[CaseResult]:
    """Experiment 1 (paper §3): every Δh and camera; see :func:`run_experiment1_case`."""
    base = default_setup() if base is None else base
    cams = list(base.cameras) if cameras is None else list(cameras)
    out = []
    for dh in bulges:
        for cam in cams:
            if progress is not None:
                progress(f"Δh = {dh:g} mm, camera {cam}")
            out.append(run_experiment1_case(dh, cam, base=base, downsample=downsample, method=method,
                                            image_sink=image_sink))
    return out
