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

import warnings
from collections.abc import Mapping as _AbcMapping
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
from .errors import ConsistencyWarning, ImageSetError, InputError, InputTypeError, UnknownCameraError
from .evaluation.consistency import ConsistencyResult
from .evaluation.phase import ScreenCoordinates
from .evaluation.pipeline import consistency_checked, decode_images, evaluate_decoded
from .geometry.compact import compact_repr
from .evaluation.reconstruction import Reconstruction, reconstruct
from .evaluation.registration import Registration
from .evaluation.uncertainty import SurfaceUncertainty
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

    __repr__ = compact_repr  # one line: arrays by shape and dtype

    camera: str
    mapping: Mapping
    images: dict


# ---------------------------------------------------------------- argument checks (shared)
def _check_setup(setup) -> Setup:
    if not isinstance(setup, Setup):
        raise InputTypeError(f"setup must be a pmdsim Setup (pmdsim.default_setup(), pmdsim.load_setup(path)), got "
                             f"{type(setup).__name__}")
    return setup


def _check_camera(setup: Setup, camera) -> str:
    if not isinstance(camera, str):
        raise InputTypeError(f"camera must be a camera name (one of {', '.join(setup.cameras)}), got "
                             f"{type(camera).__name__}")
    if camera not in setup.cameras:
        raise UnknownCameraError(f"no camera {camera!r} in the setup (cameras: {', '.join(setup.cameras)})")
    return camera


def _frozen(obj):
    """``obj`` with its ndarray fields read-only (results are values: issue 23); arrays shared
    with another result are the same read-only object."""
    for name in getattr(obj, "__dataclass_fields__", {}):
        v = getattr(obj, name, None)
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return obj


def simulate(setup: Setup, camera: str, *, stream: int | None = None) -> Measurement:
    """Simulate what ``camera`` of ``setup`` records: trace every pixel camera → sample → screen
    (paper §2.4, eq. 17) and render the setup's fringe sequence (quantised to its bit depth,
    with its noise, seeded by ``patterns.seed`` and ``stream``). The result's arrays are read-only.

    Raises
    ------
    InputTypeError, UnknownCameraError
        ``setup`` is not a Setup, ``camera`` not one of its cameras.
    """
    _check_camera(_check_setup(setup), camera)
    mapping = trace_setup_camera(setup, camera, store_points=True)
    frames: dict = {}
    for spec, img in render_images(setup, camera, mapping, stream=stream):
        frames.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    stacks = {k: np.stack(v) for k, v in frames.items()}
    for v in stacks.values():
        v.flags.writeable = False
    return Measurement(camera, _frozen(mapping), stacks)


def _full_scale(setup: Setup) -> tuple[int, float]:
    """(bit depth, full-scale grey level) the decoder assumes for ``setup``'s images."""
    bits = setup.patterns.bit_depth
    if setup.imaging is not None and setup.imaging.bit_depth is not None:
        bits = setup.imaging.bit_depth
    return int(bits), float(2**int(bits) - 1)


def _check_images(images, setup: Setup, scale, size_px=None) -> dict:
    """Validate one camera's image stacks against the setup's fringe sequence and bit depth;
    returns ``{(direction, period_mm): (N, H, W) array}`` (floats × ``scale`` where given)."""
    if not isinstance(images, _AbcMapping):
        raise InputTypeError(f"images must be a dict {{(direction, period_mm): (N, H, W) stack}} or a Measurement, "
                             f"got {type(images).__name__}")
    seq = setup.patterns.sequence
    want = [("x", float(p)) for p in seq.periods_x_mm] + [("y", float(p)) for p in seq.periods_y_mm]
    missing = [k for k in want if k not in images]
    if missing:
        raise ImageSetError(f"images: no stack for {missing} (the setup's fringe sequence; keys given: "
                            f"{sorted(images, key=str)[:8]})")
    bits, full = _full_scale(setup)
    out, shape = {}, None
    for key in want:
        a = np.asarray(images[key])
        name = f"images[{key!r}]"
        if a.ndim != 3 or a.shape[0] != seq.n_shifts:
            raise ImageSetError(f"{name}: shape {a.shape}; expected ({seq.n_shifts}, H, W) — "
                                f"patterns.n_shifts = {seq.n_shifts} images of one size")
        if shape is None:
            shape = a.shape[1:]
        elif a.shape[1:] != shape:
            raise ImageSetError(f"{name}: image size {a.shape[1:]} differs from the first stack's {shape}")
        if np.issubdtype(a.dtype, np.floating):
            if scale is None:
                raise InputError(f"{name}: {a.dtype} images need an explicit scale — decode(images, setup, scale=S) "
                                 f"with S the grey level that 1.0 stands for (e.g. scale={full:g} for images in "
                                 f"[0, 1] and the setup's {bits}-bit depth)")
            a = a.astype(np.float64) * float(scale)
        elif a.dtype in (np.uint8, np.uint16):
            if scale is not None:
                raise InputError(f"{name}: scale is for float images; {a.dtype} images are grey levels already")
            if a.dtype == np.uint16 and bits == 8:
                raise InputError(f"{name}: uint16 images but the setup declares 8-bit images (patterns.bit_depth = "
                                 f"8); declare the camera's bit depth: setup.with_patterns(bit_depth=16) or "
                                 f"[imaging] bit_depth = 10/12/16 in the setup file")
            if a.size and int(a.max()) > full:
                raise InputError(f"{name}: grey level {int(a.max())} above the {bits}-bit full scale {full:g}; "
                                 f"declare the camera's bit depth in the setup")
        else:
            raise InputTypeError(f"{name}: dtype {a.dtype}; expected uint8 or uint16 grey levels, or floats with "
                                 f"an explicit scale")
        out[key] = a
    if size_px is not None and shape != size_px:
        raise ImageSetError(f"images are {shape[1]}×{shape[0]} px but the camera is {size_px[1]}×{size_px[0]} px "
                            f"(cameras.<name>.image_size_px)")
    return out


def _warn_consistency(camera: str, cons: ConsistencyResult) -> None:
    n = int(np.count_nonzero(cons.flags))
    if n:
        warnings.warn(f"{camera}: {n} pixels failed the consistency checks (flagged in the result's flags): "
                      f"{'; '.join(cons.reasons())}", ConsistencyWarning, stacklevel=3)


def decode(images: dict, setup: Setup, *, camera: str | None = None, scale: float | None = None,
           consistency: bool = True) -> ScreenCoordinates:
    """Decode one camera's fringe images ``{(direction, period_mm): (N, H, W) stack}`` with
    ``setup``'s fringe sequence and bit depth → screen coordinates, with the consistency checks
    of ``pmdsim evaluate``.

    Parameters
    ----------
    images : dict or Measurement
        uint8 / uint16 grey levels of the setup's bit depth (``patterns.bit_depth``, or
        ``imaging.bit_depth``), or floats with ``scale``.
    setup : Setup
    camera : str, optional
        The camera that took them (default: a Measurement's camera); adds the check of the
        image size and the orientation check.
    scale : float, optional
        For float images: the grey level that 1.0 stands for (e.g. 255 for [0, 1] images and
        an 8-bit setup). Required for floats, an error for integer images.
    consistency : bool
        Run the consistency checks (docs/reliability.md; not with image-formation effects on).
        Pixels that fail are flagged in ``flags`` and invalid; a
        :class:`~pmdsim.errors.ConsistencyWarning` names the reasons.

    Returns
    -------
    ScreenCoordinates
        ``screen_xy_mm`` (H, W, 2, screen frame, mm, NaN where not decoded), ``valid`` (H, W),
        ``flags`` (H, W, :class:`~pmdsim.evaluation.phase.PhaseFlag`), ``std_xy_mm`` (H, W, 2,
        the predicted σ), ``modulation``, ``offset``; read-only arrays.

    Raises
    ------
    InputError, InputTypeError, ImageSetError, UnknownCameraError
        Wrong types, missing stacks, wrong shapes, a dtype that does not match the bit depth.
    """
    _check_setup(setup)
    if isinstance(images, Measurement):
        camera = images.camera if camera is None else camera
        images = images.images
    size = None
    if camera is not None:
        c = setup.cameras[_check_camera(setup, camera)].camera
        size = (c.height_px, c.width_px)
    stacks = _check_images(images, setup, scale, size)
    decoded = decode_images(setup, stacks, response=decoder_response(setup))
    if consistency and not (setup.imaging is not None and setup.imaging.any_on):
        seq = setup.patterns.sequence
        noise = float(np.hypot(setup.patterns.noise_std, 1.0 / np.sqrt(12.0)))
        # a curved sample's orientation reference is the mapping traced through it, as in the CLI
        expected = (trace_setup_camera(setup, camera).screen_xy_mm
                    if camera is not None and setup.sample.curved else None)
        decoded, cons = consistency_checked(setup, camera, [stacks[("x", float(p))] for p in seq.periods_x_mm],
                                            seq.periods_x_mm, [stacks[("y", float(p))] for p in seq.periods_y_mm],
                                            seq.periods_y_mm, decoded, noise, expected_xy_mm=expected)
        _warn_consistency(camera or "images", cons)
    return _frozen(decoded)


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
    decoded : ScreenCoordinates
        What was registered, with the per-pixel ``flags`` (also :attr:`flags`).
    warnings : tuple of str
        The plausibility and consistency warnings (also issued as
        :class:`~pmdsim.errors.ConsistencyWarning`).
    uncertainty : SurfaceUncertainty or None
        Per-pixel standard uncertainties (k = 1) of heights and slopes with their noise and
        calibration contributions (:mod:`pmdsim.evaluation.uncertainty`; arrays read-only);
        None with ``evaluate(..., uncertainty=False)`` or when σ could not be computed (a
        warning says why).
    """

    __repr__ = compact_repr  # one line: arrays by shape and dtype

    camera: str
    registration: Registration
    reconstruction: Reconstruction
    decoded: ScreenCoordinates | None = None
    warnings: tuple = ()
    uncertainty: SurfaceUncertainty | None = None

    @property
    def height_std_um(self) -> np.ndarray | None:
        """(H, W) combined height standard uncertainty, µm (None without :attr:`uncertainty`)."""
        return None if self.uncertainty is None else self.uncertainty.height_std_um

    @property
    def slope_std_urad(self) -> np.ndarray | None:
        """(H, W, 2) combined slope standard uncertainty, µrad (None without :attr:`uncertainty`)."""
        return None if self.uncertainty is None else self.uncertainty.slope_std_urad

    @property
    def flags(self) -> np.ndarray:
        """(H, W) uint8 :class:`~pmdsim.evaluation.phase.PhaseFlag` bits per pixel: the
        decoder's and the consistency checks' (read-only)."""
        return self.decoded.flags

    @property
    def height_mm(self) -> np.ndarray:
        """(H, W) reconstructed height along the sample frame's +z, mm; NaN where not reconstructed."""
        return self.reconstruction.height_mm

    @property
    def reconstructed(self) -> np.ndarray:
        """(H, W) bool: pixels with a reconstructed height."""
        return self.reconstruction.reconstructed


def evaluate(decoded: ScreenCoordinates, setup: Setup, camera: str, *, screen: str = "planar",
             method: str = "stepwise", seed_pixel=None, seed_height_mm: float = 0.0, uncertainty: bool = True,
             seed_height_std_mm: float = 0.0) -> Evaluation:
    """Register ``decoded`` with ``setup``'s ``camera`` and screen, then reconstruct (§2.5).

    Parameters
    ----------
    decoded : ScreenCoordinates, Measurement or dict of image stacks
        From :func:`decode` (or :func:`pmdsim.io.imageset.decode_camera` for images on disk);
        images are decoded here with :func:`decode` (its consistency checks included).
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
    uncertainty : bool
        Compute the per-pixel standard uncertainties (:attr:`Evaluation.uncertainty`); False
        skips them when speed matters (they add about a third to the evaluation).
    seed_height_std_mm : float
        Standard uncertainty of ``seed_height_mm`` (mm), added to the height σ.

    Warns
    -----
    ConsistencyWarning
        The checks of ``pmdsim evaluate``: lengths that look like metres, a flipped mapping,
        decoded pixels outside the screen model (and, for images, the consistency checks).

    Raises
    ------
    InputError, InputTypeError, UnknownCameraError
        Wrong camera, types, shapes, options or seed pixel.
    """
    from .evaluation.plausibility import check_orientation, check_scale, check_screen_coverage

    _check_camera(_check_setup(setup), camera)
    if screen not in ("planar", "setup"):
        raise InputError(f"screen must be 'planar' or 'setup', got {screen!r}")
    if method not in ("stepwise", "least_squares"):
        raise InputError(f"method must be 'stepwise' or 'least_squares', got {method!r}")
    if not np.isfinite(seed_height_mm):
        raise InputError(f"seed_height_mm must be finite, got {seed_height_mm!r}")
    if not (np.isfinite(seed_height_std_mm) and seed_height_std_mm >= 0):
        raise InputError(f"seed_height_std_mm must be finite and ≥ 0, got {seed_height_std_mm!r}")
    if isinstance(decoded, (Measurement, _AbcMapping)):  # images: decode them with the checks
        decoded = decode(decoded, setup, camera=camera)
    if not isinstance(decoded, ScreenCoordinates):
        raise InputTypeError(f"decoded must be the ScreenCoordinates of pmdsim.decode (or the images), got "
                             f"{type(decoded).__name__}")
    c = setup.cameras[camera].camera
    if decoded.valid.shape != (c.height_px, c.width_px):
        raise InputError(f"decoded maps are {decoded.valid.shape[1]}×{decoded.valid.shape[0]} px but camera "
                         f"{camera!r} is {c.width_px}×{c.height_px} px")
    if seed_pixel is not None:
        try:
            v, u = (float(x) for x in seed_pixel)
        except (TypeError, ValueError):
            raise InputError(f"seed_pixel must be (row, column), got {seed_pixel!r}") from None
        if not (0 <= v <= c.height_px - 1 and 0 <= u <= c.width_px - 1):
            raise InputError(f"seed_pixel {tuple(seed_pixel)} is outside camera {camera!r}'s "
                             f"{c.width_px}×{c.height_px} image (row, column)")
    # the CLI's plausibility checks (pmdsim.studies.jobs evaluate), reported as warnings
    found = list(check_scale(setup)) + check_orientation(setup, camera, decoded.screen_xy_mm, decoded.valid)
    model = None if screen == "planar" else setup.screen.surface
    reg, rec = evaluate_decoded(setup, camera, decoded, screen_model=model, method=method, seed_pixel=seed_pixel,
                                seed_height_mm=seed_height_mm)
    scr = setup.screen
    bounds = (model.bounds_mm if model is not None else
              (scr.grid_x_mm[0], scr.grid_x_mm[-1], scr.grid_y_mm[0], scr.grid_y_mm[-1]))
    found += check_screen_coverage(decoded.valid, reg.status, decoded.screen_xy_mm, bounds, camera)
    unc = None
    if uncertainty:
        from .evaluation.anchor import HeightAnchor
        from .evaluation.uncertainty import UncertaintyError, surface_uncertainty

        try:
            unc = _frozen(surface_uncertainty(setup, camera, decoded, reg, rec, method=method, screen_model=model,
                                              anchor=HeightAnchor(tuple(map(float, rec.seed_pixel)), seed_height_mm),
                                              anchor_std_mm=float(seed_height_std_mm)))
        except UncertaintyError as exc:
            found.append(f"{camera}: no uncertainty (heights stand): {exc}")
    for w in found:
        warnings.warn(w, ConsistencyWarning, stacklevel=2)
    return Evaluation(camera, _frozen(reg), _frozen(rec), decoded, tuple(found), unc)


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
        Start values: a setup (its cameras and its calibration mirror poses) or a state. A
        setup's screen cover glass (``[screen] cover_glass_thickness_mm`` > 0) is part of the
        model, held or, with ``[calibration] fit_glass_thickness`` / ``fit_glass_index``, fitted
        (:func:`pmdsim.calibration.glass.calibrate_with_glass`; the result's ``glass`` and
        ``glass_std()``); a state's ``glass`` and ``glass_free`` are used as given.
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
    if not isinstance(nominal, (Setup, CalibrationState)):
        raise InputTypeError(f"nominal must be a Setup or a CalibrationState, got {type(nominal).__name__}")
    if not observations:
        raise InputError("observations is empty: give the correspondences of at least one camera and mirror pose")
    if isinstance(nominal, Setup):
        poses = [T for _, T in nominal.calibration.mirror_poses(nominal.sample)]
        screen_model = None if screen_grid is None else free_screen_model(nominal, screen_grid)
        start = nominal_state(nominal, poses)
        glass, cal = nominal.screen.cover_glass, nominal.calibration
        if glass.present or cal.fit_glass_thickness or cal.fit_glass_index:
            from .calibration.glass import calibrate_with_glass

            return calibrate_with_glass(observations, start, glass, screen_model=screen_model,
                                        fit_thickness=cal.fit_glass_thickness, fit_index=cal.fit_glass_index, **options)
    else:
        if screen_grid is not None:
            raise InputError("screen_grid needs the nominal Setup (for the screen's extent), not a state")
        screen_model, start = None, nominal
    return _calibrate(observations, start, screen_model=screen_model, **options)


def evaluate_stereo(decoded: dict, setup: Setup, *, screen: str = "planar",
                    search_range_mm=(-20.0, 20.0), uncertainty: bool = True, **options):
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
    uncertainty : bool
        Compute every camera's per-pixel standard uncertainties (absolute: the stereo anchors'
        σ included; :mod:`pmdsim.evaluation.uncertainty_stereo`) into ``cameras[name].uncertainty``
        and ``anchor_height_std_um``; False skips them when speed matters. If σ cannot be
        computed, a :class:`~pmdsim.errors.ConsistencyWarning` says why and they stay None.
    **options
        ``search_step_mm``, ``stride_px``, ``max_iter``, ``tol_mm`` of
        :func:`pmdsim.evaluation.stereo.reconstruct_stereo`.

    Returns
    -------
    StereoReconstruction
        ``cameras[name]``: ``height_mm`` (H, W), ``reconstruction``, ``overlap``,
        ``normal_disagreement_urad``, ``height_discrepancy_um``, the anchors, ``uncertainty``
        (a :class:`~pmdsim.evaluation.uncertainty.SurfaceUncertainty` or None); ``summary()``.
        Its arrays are read-only.
    """
    from .evaluation.stereo import evaluate_stereo_decoded

    _check_setup(setup)
    if screen not in ("planar", "setup"):
        raise InputError(f"screen must be 'planar' or 'setup', got {screen!r}")
    if not isinstance(decoded, _AbcMapping) or len(decoded) < 2:
        raise InputError(f"decoded must map at least two camera names to their decoded images, got "
                         f"{type(decoded).__name__}{' of ' + str(len(decoded)) if isinstance(decoded, _AbcMapping) else ''}")
    for c in decoded:
        _check_camera(setup, c)
    decoded = {c: (decode(d, setup) if isinstance(d, Measurement) else d) for c, d in decoded.items()}
    model = None if screen == "planar" else setup.screen.surface
    views, result = evaluate_stereo_decoded(setup, decoded, screen_model=model, search_range_mm=search_range_mm,
                                            **options)
    if uncertainty:
        from .evaluation.uncertainty_stereo import stereo_with_uncertainty

        result, _, why = stereo_with_uncertainty(setup, views, decoded, result, screen_model=model)
        for w in why:
            warnings.warn(w, ConsistencyWarning, stacklevel=2)
    for cam in result.cameras.values():  # read-only results, as evaluate's (issue 23)
        _frozen(cam)
        _frozen(cam.reconstruction)
        if cam.uncertainty is not None:
            _frozen(cam.uncertainty)
    return result


__all__.append("evaluate_stereo")


# calibrated_setup is part of the notebook API too (result → Setup).
__all__.append("calibrated_setup")
