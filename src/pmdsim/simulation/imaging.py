"""Realistic image formation (issue 13): display, optics and sensor composed per camera.

For one camera the slowly varying per-pixel factors are computed once from the traced mapping
(:func:`imaging_maps`: the defocus covariance and pixel Jacobian of :mod:`.optics`, the angular
emission and black-matrix factor of :mod:`.display`); every fringe image is then rendered by one
numba kernel that sums the display response's cosine harmonics, each multiplied by its transfer

    T_n = 2·J₁(4πnσ_a/p)/(4πnσ_a/p) · sinc(n·J_a,u/p)·sinc(n·J_a,v/p) · sinc(n·P/p)

(defocus by a thin lens with a uniform-disc pupil and one focal plane — the uniform-ellipse
footprint's transfer, :mod:`.optics`; pixel area; screen sample-and-hold; a the fringe axis, σ_a
the footprint's std along it), evaluated at the defocus footprint's centroid (offset from the
chief ray's screen point by O(D²)), scales by the emission factor and passes the result through
the sensor (:class:`.sensor.SensorModel`). A harmonic's transfer is real: it scales the modulation
and, where it is negative (defocus beyond the first zero of J₁), reverses the contrast — a π phase
flip that the decoder flags (UNWRAP_INCONSISTENT against the coarser periods; issue 20). The
kernel (:mod:`.imaging_series`) sums only the terms a bound of whose remainder exceeds the
truncation tolerance (default 1e-3 grey levels per pixel and image). With screen pixels each
harmonic also carries its aliases (the staircase); :func:`render_direction_imaging` (used by
``render_images``) then renders the held pattern in position instead (:mod:`.imaging_held`: the
exact displayed values weighted by the footprint kernel's integral over each screen pixel, the
same model summed to infinity), once per direction for all its periods and shifts. Display levels
seen by a sharp camera (no defocus, pixel area or screen pixels) are the displayed staircase
sampled at each pixel's point (:mod:`.imaging_point`, exact). With the LCD's viewing-angle model
(``lcd_mode``, :mod:`.display_angle`) every pixel has its own response, R functions of the level
mixed with the pixel's weights in each of these paths.

The noise is drawn from ``numpy.random.default_rng`` seeded by the setup's seed, the camera's
index and the stream (:func:`pmdsim.simulation.render.render_images`): the same inputs give the
same images.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..setup import ImagingSetup, Setup
from ..setup.fringes import DIRECTIONS, FringeSequence
from .display import black_matrix_factor, display_response, emission_falloff, harmonic_coefficients
from .display_angle import AngularBasis, angular_basis, view_directions
from .imaging_series import TRUNCATION_TOLERANCE_DN, series_kernel
from .optics import JINC_TABLE, default_focus_distance, defocus_moments, focus_path, jinc, pixel_jacobian
from ..setup.sensor import SensorModel
from .trace import Mapping

#: The screen's sample-and-hold staircase: aliases ν = n/p + a/P of each harmonic are rendered
#: for |a| ≤ HOLD_ALIASES (the model's cap: without any camera transfer — a sharp, point-sampling
#: camera — the alias series of the held pattern converges only conditionally), of which only
#: those not bounded below the truncation tolerance are summed (:mod:`.imaging_series`).
HOLD_ALIASES = 32

__all__ = ["HOLD_ALIASES", "TRUNCATION_TOLERANCE_DN", "ImagingMaps", "needs_points", "imaging_maps", "render_period_imaging",
           "render_direction_imaging", "grey_level_response",
           "decoder_response"]


def needs_points(setup: Setup) -> bool:
    """True if the setup's effects need the traced sample and screen points (defocus, emission, the
    LCD's viewing angle)."""
    im = setup.imaging
    return im is not None and (im.f_number is not None or im.emission_exponent is not None
                               or im.lcd_mode is not None)


@dataclass(frozen=True, eq=False)
class ImagingMaps:
    """Per-pixel factors of one camera's image formation.

    Attributes
    ----------
    var_xy_mm2 : ndarray (H, W, 2)
        Defocus footprint variance along screen x and y (mm²); 0 without defocus.
    jacobian : ndarray (H, W, 2, 2) or None
        ∂(x_q, y_q)/∂(u, v) (mm/px) for pixel-area integration; None when off.
    radiance : ndarray (H, W)
        Relative radiance factor (angular emission × black matrix); 1 when off.
    hold_pitch_mm : float
        Screen pixel pitch for the sample-and-hold transfer; 0 when off.
    coefficients : ndarray (K + 1,)
        Cosine-series coefficients of the displayed (response-distorted) fringe.
    centroid_xy_mm : ndarray (H, W, 2) or None
        Offset of the defocus footprint's centroid from the chief ray's screen point (mm);
        None without defocus.
    focus_distance_mm : float or None
        The camera's focus distance used (``imaging.focus_distance_mm`` or the default); None
        without defocus.
    display : tuple or None
        ``(response, levels)`` of the display (:func:`.display.display_response`, ``display_levels``):
        with screen pixels the held values are r(Q(A + B·cos θ)) exactly (:mod:`.imaging_held`);
        None: the displayed pattern is the cosine series of ``coefficients``.
    angular : AngularBasis or None
        The LCD's viewing-angle response (``lcd_mode``, :mod:`.display_angle`): R response
        functions of the commanded level and their weights per pixel; None: the same response
        (``display``) for every pixel.
    angular_coefficients : ndarray (R, K + 1) or None
        The cosine coefficients of each of those functions (rows zero-padded to one length).
    sharp : bool
        No camera transfer (no defocus, pixel area or screen pixels): with ``display_levels``
        the images are the displayed pattern sampled at each pixel's point (:mod:`.imaging_point`).
    """

    var_xy_mm2: np.ndarray
    jacobian: np.ndarray | None
    radiance: np.ndarray
    hold_pitch_mm: float
    coefficients: np.ndarray
    centroid_xy_mm: np.ndarray | None = None
    focus_distance_mm: float | None = None
    display: tuple | None = None
    angular: AngularBasis | None = None
    angular_coefficients: np.ndarray | None = None
    sharp: bool = False


def imaging_maps(setup: Setup, camera: str, mapping: Mapping, *, T_world_sample=None) -> ImagingMaps:
    """The per-pixel factors of ``camera`` for the traced ``mapping`` (see :class:`ImagingMaps`).

    ``T_world_sample`` is the pose of the surface the mapping was traced with (default: the
    setup's sample; a calibration mirror pose otherwise). Defocus and angular emission need the
    mapping's points (``store_points=True``). The default focus distance (``imaging.
    focus_distance_mm`` unset) is taken from this mapping: the axial distance of the surface point
    seen by the principal point.
    """
    im = setup.imaging if setup.imaging is not None else ImagingSetup()
    xy = mapping.screen_xy_mm
    shape = xy.shape[:2]
    T_ws = setup.sample.T_world_sample if T_world_sample is None else T_world_sample
    cs = setup.cameras[camera]
    var = np.zeros(shape + (2,))
    centroid = None
    radiance = np.ones(shape)
    if needs_points(setup):
        if mapping.p_sample_mm is None or mapping.q_screen_mm is None:
            raise ValueError("defocus and angular emission need a mapping traced with store_points=True")
        aperture = 0.0 if im.f_number is None else im.focal_length_mm / im.f_number
        fpath = None
        if im.f_number is not None:
            focus = im.focus_distance_mm
            if focus is None:
                focus = default_focus_distance(cs.T_world_cam, T_ws, mapping.p_sample_mm,
                                               (cs.camera.ppx_px, cs.camera.ppy_px))
            fpath = focus_path(cs.T_world_cam, T_ws, mapping.p_sample_mm, focus)
        cov, centroid, cos_view = defocus_moments(cs.T_world_cam, T_ws, setup.screen.T_world_screen,
                                                  mapping.p_sample_mm, mapping.q_screen_mm, aperture,
                                                  setup.screen.surface, fpath)
        if im.f_number is not None:
            var = np.stack([cov[..., 0, 0], cov[..., 1, 1]], axis=-1)
            centroid = np.ascontiguousarray(np.where(np.isfinite(centroid), centroid, 0.0))
        else:
            centroid = None
        if im.emission_exponent is not None:
            radiance = radiance * emission_falloff(cos_view, im.emission_exponent)
    var = np.where(np.isfinite(var), var, 0.0)
    # The real pixel's footprint: 1/K of the sampling step of a camera sampled every K-th pixel.
    jac = pixel_jacobian(xy) / im.sampling_step_px if im.pixel_area else None
    if im.screen_pixel_pitch_mm is not None:
        radiance = radiance * black_matrix_factor(xy, im.screen_pixel_pitch_mm, im.screen_fill_factor, var, jac)
    radiance = np.where(np.isfinite(radiance), radiance, 0.0)
    seq = setup.patterns.sequence
    resp = display_response(im.display_gamma, im.display_black_level)
    coef = harmonic_coefficients(resp, seq.mean_level, seq.amplitude, levels=im.display_levels)
    basis = acoef = None
    if im.lcd_mode is not None:
        dirs = view_directions(setup.screen.T_world_screen, T_ws, mapping.p_sample_mm, mapping.q_screen_mm)
        dirs[~np.asarray(mapping.valid, dtype=bool)] = np.nan
        basis = angular_basis(im, dirs)
        rows = [harmonic_coefficients(_Curve(basis, r), seq.mean_level, seq.amplitude, levels=im.display_levels)
                for r in range(basis.rank)]
        acoef = np.zeros((len(rows), max(len(c) for c in rows)))
        for r, c in enumerate(rows):
            acoef[r, :len(c)] = c
    sharp = im.f_number is None and not im.pixel_area and im.screen_pixel_pitch_mm is None
    return ImagingMaps(np.ascontiguousarray(var), None if jac is None else np.ascontiguousarray(jac),
                       np.ascontiguousarray(radiance), float(im.screen_pixel_pitch_mm or 0.0), coef, centroid,
                       None if im.f_number is None else float(focus), (resp, im.display_levels), basis, acoef, sharp)


class _Curve:
    """Basis function ``r`` of an :class:`AngularBasis` as a response (``forward``)."""

    def __init__(self, basis: AngularBasis, r: int):
        self.basis, self.r = basis, r

    def forward(self, d):
        return self.basis.at_levels(d)[self.r]


def render_period_imaging(maps: ImagingMaps, screen_xy_mm: np.ndarray, valid: np.ndarray, direction: str,
                          period_mm: float, sequence: FringeSequence, sensor: SensorModel,
                          rng: np.random.Generator | None, *, tolerance_dn: float = TRUNCATION_TOLERANCE_DN,
                          means: np.ndarray | None = None, counts: np.ndarray | None = None) -> np.ndarray:
    """All N phase-shifted images of one direction and period with the image-formation effects.

    Parameters
    ----------
    maps : ImagingMaps
        The camera's per-pixel factors (:func:`imaging_maps`).
    screen_xy_mm : ndarray (H, W, 2); valid : ndarray of bool (H, W)
        The traced mapping.
    direction, period_mm, sequence
        The fringe (``sequence`` gives N).
    sensor : SensorModel
    rng : numpy.random.Generator or None
        Source of the N standard-normal noise fields (float32, drawn in shift order); required
        when the sensor is noisy.
    tolerance_dn : float
        Truncation tolerance of the series (grey levels): per pixel and image, the terms left out
        sum to at most this on the mean grey level before noise and rounding
        (:mod:`.imaging_series`; docs/conventions.md, "Truncation of the series"). 0: every
        harmonic and every alias up to :data:`HOLD_ALIASES` (the uncut series).
    means : ndarray (N, H, W) float64, optional
        Receives the mean grey levels above the dark offset before clipping, noise and rounding.
    counts : ndarray (H, W) int64, optional
        Receives the number of series terms summed per pixel (1 where the displayed value is
        sampled directly, :mod:`.imaging_point`).

    Returns
    -------
    ndarray (N, H, W), uint8 (8 bit) or uint16 (10, 12, 16 bit)
    """
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be 'x' or 'y', got {direction!r}")
    tol = float(tolerance_dn)
    if not (np.isfinite(tol) and tol >= 0.0):
        raise ValueError(f"tolerance_dn must be a finite number of grey levels ≥ 0, got {tolerance_dn!r}")
    axis = DIRECTIONS.index(direction)
    n = sequence.n_shifts
    delta = 2.0 * np.pi * np.arange(n) / n
    ok = np.ascontiguousarray(valid, dtype=bool)
    coord = screen_xy_mm[..., axis]
    if maps.centroid_xy_mm is not None:  # the footprint's centroid, not the chief ray, is its centre
        coord = coord + maps.centroid_xy_mm[..., axis]
    coord = np.ascontiguousarray(coord)
    if sensor.noisy:
        if rng is None:
            raise ValueError("a noisy sensor needs a seeded rng for reproducible images")
        noise = rng.standard_normal(size=(n,) + ok.shape, dtype=np.float32)
    else:
        noise = np.empty((0, 0, 0), dtype=np.float32)
    if means is not None and (means.shape != (n,) + ok.shape or means.dtype != np.float64):
        raise ValueError(f"means must be a float64 array of shape {(n,) + ok.shape}")
    if counts is not None and (counts.shape != ok.shape or counts.dtype != np.int64):
        raise ValueError(f"counts must be an int64 array of shape {ok.shape}")
    levels = maps.display[1] if maps.display is not None else None
    if maps.sharp and levels is not None:  # the staircase sampled at each pixel's point, exactly
        from .imaging_point import render_period_point

        d = np.arange(levels) / (levels - 1)
        if maps.angular is not None:
            lut = maps.angular.at_levels(d)
        else:
            lut = (d if maps.display[0] is None else np.asarray(maps.display[0].forward(d), dtype=float))[None]
        out16 = np.empty((n,) + ok.shape, dtype=np.uint16)
        render_period_point(coord, ok, period_mm, n, sequence.mean_level, sequence.amplitude, lut,
                            None if maps.angular is None else maps.angular.weights, maps.radiance, sensor,
                            noise if sensor.noisy else None, out16, means)
        if counts is not None:
            counts[...] = 1  # one term per pixel and image: the displayed value
        return out16 if sensor.dtype == np.uint16 else out16.astype(sensor.dtype)
    jac = maps.jacobian[..., axis, :] if maps.jacobian is not None else np.zeros((1, 1, 2))
    out = np.empty((n,) + ok.shape, dtype=sensor.dtype)
    if maps.angular is not None:
        coefs = np.ascontiguousarray(maps.angular_coefficients, dtype=float)
        pw, use_pw = maps.angular.weights, True
        mag = np.sum(maps.angular.weights_max[:, None] * np.abs(coefs), axis=0)  # ≥ every pixel's |c_n|
        coef = coefs[0]
    else:
        coef = np.ascontiguousarray(maps.coefficients, dtype=float)
        coefs, pw, use_pw = coef[None], np.zeros((1, 1, 1)), False
        mag = np.abs(coef)
    suffix = np.concatenate([np.cumsum(mag[::-1])[::-1], [0.0]])  # S_m = Σ_{j ≥ m} |c_j|
    # Alias budget of harmonic m ∝ √(|c_m|·|sin(πmP/p)|) (its aliases' weight), summing to 1.
    m_idx = np.arange(1, coef.size)
    root = np.sqrt(mag[1:] * (np.abs(np.sin(np.pi * m_idx * maps.hold_pitch_mm / period_mm))
                              if maps.hold_pitch_mm > 0 else 1.0))
    share = np.concatenate([[0.0], root / root.sum() if root.sum() > 0 else root])
    m_out = np.empty((0, 0, 0)) if means is None else means
    c_out = np.empty((0, 0), dtype=np.int64) if counts is None else counts
    series_kernel(coord, ok, float(period_mm), np.cos(delta), np.sin(delta), coefs, pw, use_pw, suffix, share,
                  np.ascontiguousarray(maps.var_xy_mm2[..., axis]), np.ascontiguousarray(jac),
                  maps.jacobian is not None, maps.hold_pitch_mm, maps.radiance, sensor.scale_dn,
                  sensor.dark_dn, sensor.clip_dn, sensor.shot_dn, sensor.const_var_dn2, sensor.full_scale,
                  noise, sensor.noisy, JINC_TABLE, HOLD_ALIASES, tol, out, m_out, c_out)
    return out


def render_direction_imaging(maps: ImagingMaps, screen_xy_mm: np.ndarray, valid: np.ndarray, direction: str,
                             sequence: FringeSequence, sensor: SensorModel, rng: np.random.Generator | None, *,
                             tolerance_dn: float = TRUNCATION_TOLERANCE_DN,
                             means: np.ndarray | None = None) -> np.ndarray:
    """All images of one direction, every period coarsest first: (P, N, H, W).

    With screen pixels (``maps.hold_pitch_mm`` > 0) the held pattern is rendered in position
    (:mod:`.imaging_held`): the per-pixel weights of the screen pixels under the footprint are
    computed once and shared by every period and shift; the displayed values are exact
    (``maps.display``). Without, each period is the harmonic series of
    :func:`render_period_imaging` (truncated at ``tolerance_dn``). The noise is drawn from ``rng``
    period by period exactly as :func:`render_period_imaging` draws it (the same images for the
    same seed).
    """
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be 'x' or 'y', got {direction!r}")
    periods = sequence.periods(direction)
    n = sequence.n_shifts
    ok = np.ascontiguousarray(valid, dtype=bool)
    if means is not None and (means.shape != (len(periods), n) + ok.shape or means.dtype != np.float64):
        raise ValueError(f"means must be a float64 array of shape {(len(periods), n) + ok.shape}")
    if maps.hold_pitch_mm <= 0.0:
        return np.stack([render_period_imaging(maps, screen_xy_mm, ok, direction, p, sequence, sensor, rng,
                                               tolerance_dn=tolerance_dn, means=None if means is None else means[i])
                         for i, p in enumerate(periods)])
    from .imaging_held import held_values, render_direction_held

    axis = DIRECTIONS.index(direction)
    coord = screen_xy_mm[..., axis]
    if maps.centroid_xy_mm is not None:
        coord = coord + maps.centroid_xy_mm[..., axis]
    noise = None
    if sensor.noisy:
        if rng is None:
            raise ValueError("a noisy sensor needs a seeded rng for reproducible images")
        noise = np.empty((len(periods), n) + ok.shape, dtype=np.float32)
        for i in range(len(periods)):
            rng.standard_normal(dtype=np.float32, out=noise[i])
    radius = 2.0 * np.sqrt(maps.var_xy_mm2[..., axis])
    if maps.jacobian is not None:
        box_a, box_b = maps.jacobian[..., axis, 0], maps.jacobian[..., axis, 1]
    else:
        box_a = box_b = np.zeros(ok.shape)
    if maps.angular is not None:  # R functions of the level (the viewing-angle model), mixed per pixel
        from .display import quantise_levels

        def pattern(theta):
            d = quantise_levels(sequence.mean_level + sequence.amplitude * np.cos(theta), maps.display[1])
            return maps.angular.at_levels(d)
    elif maps.display is not None:
        resp, levels = maps.display

        def pattern(theta):
            return held_values(theta, maps.coefficients, resp, levels, sequence.mean_level, sequence.amplitude)
    else:
        def pattern(theta):
            return held_values(theta, maps.coefficients)
    return render_direction_held(coord, ok, radius, box_a, box_b, maps.hold_pitch_mm, periods, n, pattern,
                                 maps.radiance, sensor, noise, means=means,
                                 weights=None if maps.angular is None else maps.angular.weights)


def grey_level_series(setup: Setup, *, patch_px: int = 32, n_frames: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A simulated grey-level calibration series: uniform screens at ``imaging.grey_levels``
    equally spaced display levels, recorded through the setup's display and sensor model (a
    ``patch_px`` × ``patch_px`` patch viewed normally, ``n_frames`` frames, its own noise stream)
    and averaged.

    Returns
    -------
    display_levels : ndarray (M,)
        Commanded levels d ∈ [0, 1].
    camera_dn : ndarray (M,)
        Mean recorded grey levels.
    """
    p = setup.patterns
    d, c = _grey_level_series(setup.imaging, p.bit_depth, p.noise_std, p.seed, patch_px, n_frames)
    return d.copy(), c.copy()


@lru_cache(maxsize=32)
def _grey_level_series(im, bit_depth, noise_std, seed, patch_px, n_frames):
    im = im if im is not None else ImagingSetup()
    sensor = SensorModel.from_values(im, bit_depth, noise_std)
    resp = display_response(im.display_gamma, im.display_black_level)
    d = np.linspace(0.0, 1.0, im.grey_levels)
    r = d if resp is None else resp.forward(d)
    rng = np.random.default_rng([seed, 2**31 - 1])  # a stream of its own
    shape = (patch_px, patch_px)
    coord = np.zeros(shape + (2,))
    ok = np.ones(shape, dtype=bool)
    seq = FringeSequence((1.0,), (1.0,), n_shifts=n_frames, mean_level=0.5, amplitude=0.1)
    means = []
    for level in r:
        maps = ImagingMaps(np.zeros(shape + (2,)), None, np.ones(shape), 0.0, np.array([float(level), 0.0]))
        stack = render_period_imaging(maps, coord, ok, "x", 1.0, seq, sensor, rng)
        means.append(stack.astype(float).mean())
    return d, np.array(means)


def decoder_response(setup: Setup):
    """The response the evaluation of ``setup``'s images linearises with: the one measured from
    the simulated grey-level series (:func:`grey_level_response`) when ``imaging.linearise`` is
    set, else None."""
    if setup.imaging is None or not setup.imaging.linearise:
        return None
    return grey_level_response(setup)


def grey_level_response(setup: Setup):
    """The :class:`~pmdsim.evaluation.response.IntensityResponse` measured from
    :func:`grey_level_series` (what the evaluation linearises with)."""
    from ..setup.response import IntensityResponse

    d, c = grey_level_series(setup)
    full = SensorModel.from_setup(setup).full_scale
    return IntensityResponse.from_samples(d, c, display_full_scale=1.0, camera_full_scale=full)
