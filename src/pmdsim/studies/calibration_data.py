"""Simulated calibration measurements (paper §4): the mirror poses traced, rendered and decoded.

The observations these functions return are what :func:`pmdsim.calibration.calibrate` takes
from a real instrument's decoded images.
"""

from __future__ import annotations

from dataclasses import fields

from ..evaluation.phase import ScreenCoordinates
from ..simulation.imaging import decoder_response
from ..evaluation.pipeline import decode_images, decode_simulated
from ..setup import Setup
from ..simulation.imaging import needs_points
from ..simulation.render import noise_generator, render_images
from .experiment1 import Progress

__all__ = ["simulate_calibration_observations", "trace_calibration_poses", "observe_calibration_poses",
           "simulate_decoded"]


def simulate_decoded(truth: Setup, camera: str, mapping, *, stream: int | None = None, T_world_sample=None,
                     image_sink=None, pixel_stride: int = 1) -> ScreenCoordinates:
    """Render ``camera``'s fringe images of a traced ``mapping`` (noise stream ``stream``, see
    :func:`~pmdsim.simulation.render.render_images`) and decode them
    (:func:`~pmdsim.evaluation.pipeline.decode_images`); with ``pixel_stride`` s > 1 only the
    decoded pixels (v, u) ≡ (0, 0) mod s are returned (every array ``[::s, ::s]``).

    Without image-formation effects and without an ``image_sink`` (called as
    ``image_sink(spec, image)`` for every image) the images are never materialised and only the
    returned pixels are decoded: the fused :func:`~pmdsim.evaluation.pipeline.decode_simulated`
    gives the same values bit for bit (tests/test_synthetic_decode.py).
    """
    if image_sink is None and not (truth.imaging is not None and truth.imaging.any_on):
        return decode_simulated(truth, mapping.screen_xy_mm, mapping.valid,
                                rng=noise_generator(truth, camera, stream=stream), pixel_stride=pixel_stride)
    images: dict = {}
    for spec, img in render_images(truth, camera, mapping, stream=stream, T_world_sample=T_world_sample):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
        if image_sink is not None:
            image_sink(spec, img)
    dec = decode_images(truth, images, response=decoder_response(truth))
    if pixel_stride == 1:
        return dec
    s = int(pixel_stride)
    return ScreenCoordinates(**{f.name: getattr(dec, f.name)[::s, ::s] for f in fields(ScreenCoordinates)})


def simulate_calibration_observations(truth: Setup, *, image_sink=None, progress: Progress | None = None,
                                      screen_surface=None):
    """Simulate the calibration poses (paper §4) through 8-bit images and decode them.

    For every mirror pose of ``truth.calibration`` and camera: trace with the mirror as the
    sample, render and quantise the fringe images, decode, and keep every
    ``observation_stride_px``-th pixel's correspondence (pixel ↔ decoded screen point, with the
    screen taken as planar unless ``screen_surface`` is given).

    Returns
    -------
    list of :class:`pmdsim.calibration.Observations`
    """
    from ..calibration import Observations, observations_from_mapping
    from ..simulation.trace import trace_camera

    cal = truth.calibration
    mirror = cal.mirror_surface()
    s = int(cal.observation_stride_px)
    obs = []
    for k, (label, T_world_mirror) in enumerate(cal.mirror_poses(truth.sample)):
        for cam, cs in truth.cameras.items():
            if progress is not None:
                progress(f"pose {k} ({label}), camera {cam}")
            m = trace_camera(cs.camera, cs.T_world_cam, T_world_mirror, mirror, truth.screen.T_world_screen,
                             truth.screen.surface, store_points=needs_points(truth), glass=truth.screen.cover_glass)
            # One independent noise stream per pose (stream 0 is left to the sample's images).
            sink = None if image_sink is None else (lambda spec, img, k=k: image_sink(k, spec, img))
            # Only the pixels the calibration uses are decoded (u, v ≡ 0 mod the stride).
            dec = simulate_decoded(truth, cam, m, stream=k + 1, T_world_sample=T_world_mirror, image_sink=sink,
                                   pixel_stride=s)
            # The decoder's σ per pixel: the covariance's noise model (calibration, "Uncertainties").
            o = observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=1,
                                          screen_surface=screen_surface, screen_std_xy_mm=dec.std_xy_mm)
            obs.append(Observations(cam, k, o.uv_px * s, o.q_screen_mm, o.q_std_mm))
    return obs


def trace_calibration_poses(truth: Setup, stride: int = 1) -> list:
    """Trace every calibration pose of ``truth`` (mirror as the sample) for every camera,
    keeping every ``stride``-th pixel in both directions.

    Returns
    -------
    list of (pose index, camera name, :class:`~pmdsim.simulation.trace.Mapping` of the kept pixels)
    """
    from ..simulation.trace import Mapping, trace_camera

    cal = truth.calibration
    mirror = cal.mirror_surface()
    out = []
    for k, (_, T_world_mirror) in enumerate(cal.mirror_poses(truth.sample)):
        for cam, cs in truth.cameras.items():
            m = trace_camera(cs.camera, cs.T_world_cam, T_world_mirror, mirror, truth.screen.T_world_screen,
                             truth.screen.surface, glass=truth.screen.cover_glass)
            out.append((k, cam, m if stride == 1 else Mapping(m.screen_xy_mm[::stride, ::stride],
                                                               m.status[::stride, ::stride])))
    return out


def observe_calibration_poses(truth: Setup, traced: list, stride: int = 1) -> list:
    """Render (with ``truth``'s bit depth and noise: one independent stream per pose, as in
    :func:`simulate_calibration_observations`) and decode the pixels of
    :func:`trace_calibration_poses`; every decoded pixel becomes a correspondence, in full-image
    pixel coordinates (u, v multiplied by ``stride``), with the decoder's σ as ``q_std_mm``.

    Rendering only the strided pixels gives the same noise *distribution* as rendering the
    full images and subsampling (the decoder works per pixel), not the same noise values: a
    Monte Carlo over many noise draws is then ``stride``² times cheaper.
    """
    from ..calibration import Observations, observations_from_mapping

    obs = []
    for k, cam, m in traced:
        dec = simulate_decoded(truth, cam, m, stream=k + 1)
        o = observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=1, screen_std_xy_mm=dec.std_xy_mm)
        obs.append(Observations(cam, k, o.uv_px * stride, o.q_screen_mm, o.q_std_mm))
    return obs
