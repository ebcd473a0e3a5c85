"""The notebook API: a handful of functions over the layers (docs/api.md walks through them).

Each function is a thin composition of the library's layers, with the shapes and units stated:

* :func:`simulate` — trace one camera of a setup and render its fringe images (paper §2.4);
* :func:`decode` — N-step phase decoding and hierarchical unwrapping → screen coordinates;
* :func:`evaluate` — registration with a setup's cameras and screen model, then reconstruction
  (§2.5), seeded at a pixel of known height;
* :func:`calibrate` — holistic calibration with a planar mirror (§4), from a nominal setup;
* :func:`reconstruct` — the integrators themselves, on view rays and screen points.

Setups are built with :func:`default_setup` (the paper's Table 1) or :func:`load_setup`, and
changed with one call (``setup.with_bulge(3)``, ``setup.with_camera("left",
focal_length_px=(4410, 4410))``, ``setup.binned(4)``). Conventions: docs/conventions.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import (
    CalibrationResult,
    CalibrationState,
    Observations,
    calibrated_setup,
    free_screen_model,
    nominal_state,
)
from .calibration import calibrate as _calibrate
from .evaluation.phase import ScreenCoordinates
from .evaluation.pipeline import decode_images, evaluate_decoded
from .evaluation.reconstruction import Reconstruction, reconstruct
from .evaluation.registration import Registration
from .setup import Setup
from .simulation.imaging import decoder_response
from .simulation.render import render_images, trace_setup_camera
from .simulation.trace import Mapping

__all__ = ["Measurement", "simulate", "decode", "Evaluation", "evaluate", "calibrate", "reconstruct"]


@dataclass(frozen=True, eq=False)
class Measurement:
    """One camera's simulated measurement.

    Attributes
    ----------
    camera : str
        The camera's name in the setup.
    mapping : Mapping
        The true pixel → screen mapping: ``screen_xy_mm`` (H, W, 2, screen frame, mm, NaN where
        invalid), ``valid`` (H, W), ``status`` (H, W) and ``p_sample_mm`` (H, W, 3, the true
        surface points in the sample frame, mm).
    images : dict
        ``{(direction, period_mm): stack}`` with ``stack`` (N, H, W) uint8/uint16 fringe
        images, shift index k along the first axis (docs/conventions.md, "Fringe patterns").
    """

    camera: str
    mapping: Mapping
    images: dict


def simulate(setup: Setup, camera: str, *, stream: int | None = None) -> Measurement:
    """Simulate what ``camera`` of ``setup`` records: trace every pixel camera → sample → screen
    (paper §2.4, eq. 17) and render the setup's fringe sequence (quantised to its bit depth,
    with its noise, seeded by ``patterns.seed`` and ``stream``)."""
    if camera not in setup.cameras:
        raise KeyError(f"no camera {camera!r} in the setup (cameras: {', '.join(setup.cameras)})")
    mapping = trace_setup_camera(setup, camera, store_points=True)
    frames: dict = {}
    for spec, img in render_images(setup, camera, mapping, stream=stream):
        frames.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    return Measurement(camera, mapping, {k: np.stack(v) for k, v in frames.items()})


def decode(images: dict, setup: Setup) -> ScreenCoordinates:
    """Decode one camera's fringe images ``{(direction, period_mm): (N, H, W) stack}`` with
    ``setup``'s fringe sequence and bit depth → screen coordinates.

    Returns
    -------
    ScreenCoordinates
        ``screen_xy_mm`` (H, W, 2, screen frame, mm, NaN where not decoded), ``valid`` (H, W),
        ``flags`` (H, W, :class:`~pmdsim.evaluation.phase.PhaseFlag`), ``std_xy_mm`` (H, W, 2,
        the predicted σ), ``modulation``, ``offset``.
    """
    if isinstance(images, Measurement):
        images = images.images
    return decode_images(setup, images, response=decoder_response(setup))


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Registration and reconstruction of one camera (sample frame of the evaluating setup).

    Attributes
    ----------
    camera : str
    registration : Registration
        View rays and screen points per pixel in the sample frame, with a status per pixel.
    reconstruction : Reconstruction
        ``height_mm`` (H, W), points, normals and ``reconstructed`` (H, W) bool.
    """

    camera: str
    registration: Registration
    reconstruction: Reconstruction

    @property
    def height_mm(self) -> np.ndarray:
        """(H, W) reconstructed height along the sample frame's +z, mm; NaN where not reconstructed."""
        return self.reconstruction.height_mm

    @property
    def reconstructed(self) -> np.ndarray:
        """(H, W) bool: pixels with a reconstructed height."""
        return self.reconstruction.reconstructed


def evaluate(decoded: ScreenCoordinates, setup: Setup, camera: str, *, screen: str = "planar",
             method: str = "stepwise", seed_pixel=None, seed_height_mm: float = 0.0) -> Evaluation:
    """Register ``decoded`` with ``setup``'s ``camera`` and screen, then reconstruct (§2.5).

    Parameters
    ----------
    decoded : ScreenCoordinates
        From :func:`decode` (or :func:`pmdsim.io.imageset.decode_camera` for images on disk).
    setup : Setup
        What the evaluation knows: cameras, screen pose and grid, sample frame.
    screen : {"planar", "setup"}
        "planar": the screen frame's x–y plane (the paper's assumption); "setup": the setup's
        screen surface (e.g. a calibrated free-form screen).
    method : {"stepwise", "least_squares"}
    seed_pixel : (row, column), optional
        Pixel whose height is known; default the registered pixel nearest the centroid of the
        registered pixels (:func:`pmdsim.evaluation.anchor.default_seed_pixel`), height 0.
    seed_height_mm : float
        Its height in the sample frame (mm).
    """
    if screen not in ("planar", "setup"):
        raise ValueError(f"screen must be 'planar' or 'setup', got {screen!r}")
    reg, rec = evaluate_decoded(setup, camera, decoded, screen_model=None if screen == "planar" else setup.screen.surface,
                                method=method, seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
    return Evaluation(camera, reg, rec)


def calibrate(observations: list[Observations], nominal: Setup | CalibrationState, *, screen_grid: int | None = None,
              **options) -> CalibrationResult:
    """Holistic calibration with a planar mirror (paper §4; free-form screen, §5).

    Parameters
    ----------
    observations : list of Observations
        Pixel ↔ decoded screen point correspondences per camera and mirror pose (e.g.
        :func:`pmdsim.studies.simulate_calibration_observations` or
        :func:`pmdsim.calibration.observations_from_mapping` of decoded images).
    nominal : Setup or CalibrationState
        Start values: a setup (its cameras and its calibration mirror poses) or a state.
    screen_grid : int, optional
        n ≥ 3: calibrate the screen as an n × n free-form spline grid (border held, interior
        heights free); None: planar screen.
    **options
        Passed to :func:`pmdsim.calibration.calibrate` (``max_iter``, ``ftol``, …).

    Returns
    -------
    CalibrationResult
        Cameras, mirror planes, (screen model), covariance and fit report;
        :func:`pmdsim.calibration.calibrated_setup` turns it into a :class:`Setup`.
    """
    if isinstance(nominal, Setup):
        poses = [T for _, T in nominal.calibration.mirror_poses(nominal.sample)]
        screen_model = None if screen_grid is None else free_screen_model(nominal, screen_grid)
        start = nominal_state(nominal, poses)
    else:
        if screen_grid is not None:
            raise ValueError("screen_grid needs the nominal Setup (for the screen's extent), not a state")
        screen_model, start = None, nominal
    return _calibrate(observations, start, screen_model=screen_model, **options)


def evaluate_stereo(decoded: dict, setup: Setup, *, screen: str = "planar",
                    search_range_mm=(-20.0, 20.0), **options):
    """Stereo evaluation (issue 14, docs/stereo.md): absolute heights from two or more
    calibrated cameras without a seed — normal consistency on sparse pixels, then each camera's
    slopes integrated from those absolute points, with a per-pixel agreement report.

    Parameters
    ----------
    decoded : dict camera → ScreenCoordinates
        Every camera's decoded screen coordinates (from :func:`decode`), at least two.
    setup : Setup
        What the evaluation knows (cameras, screen); heights in its sample frame.
    screen : {"planar", "setup"}
        As :func:`evaluate`.
    search_range_mm : (float, float)
        Heights searched along the view rays (sample frame, mm).
    **options
        ``search_step_mm``, ``stride_px``, ``max_iter``, ``tol_mm`` of
        :func:`pmdsim.evaluation.stereo.reconstruct_stereo`.

    Returns
    -------
    StereoReconstruction
        ``cameras[name]``: ``height_mm`` (H, W), ``reconstruction``, ``overlap``,
        ``normal_disagreement_urad``, ``height_discrepancy_um``, the anchors; ``summary()``.
    """
    from .evaluation.stereo import evaluate_stereo_decoded

    if screen not in ("planar", "setup"):
        raise ValueError(f"screen must be 'planar' or 'setup', got {screen!r}")
    decoded = {c: (decode(d, setup) if isinstance(d, Measurement) else d) for c, d in decoded.items()}
    _, result = evaluate_stereo_decoded(setup, decoded, screen_model=None if screen == "planar" else setup.screen.surface,
                                        search_range_mm=search_range_mm, **options)
    return result


__all__.append("evaluate_stereo")


# calibrated_setup is part of the notebook API too (result → Setup).
__all__.append("calibrated_setup")
