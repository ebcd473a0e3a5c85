"""From decoded images to a surface: registration, then reconstruction (paper §2.5).

:func:`decode_images` decodes one camera's in-memory fringe images with a setup's fringe
sequence; :func:`evaluate_decoded` registers the decoded screen points with a setup's camera and
screen model and reconstructs the sample, heights in the setup's sample frame.
"""

from __future__ import annotations

import numpy as np

from ..geometry.surface import SplineSurface
from ..setup import Setup
from .phase import ScreenCoordinates, decode_screen_coordinates
from .synthetic_decode import decode_rendered_fringes
from .anchor import default_seed_pixel
from .reconstruction import Reconstruction, ReconstructionError, reconstruct
from .registration import Registration, register

__all__ = ["decode_images", "decode_simulated", "evaluate_decoded"]


def decode_images(setup: Setup, images: dict, *, response=None) -> ScreenCoordinates:
    """Decode one camera's in-memory images ``{(direction, period_mm): [image per shift]}``
    with the setup's fringe sequence (N-step phase + hierarchical unwrapping).

    With ``setup.imaging`` effects on, the sensor-matched noise model is used and, if
    ``imaging.linearise`` is set, the images are linearised with ``response`` (an
    :class:`~pmdsim.setup.response.IntensityResponse`: a real instrument's measured grey-level
    series, or :func:`pmdsim.simulation.imaging.decoder_response` for a simulated one).
    """
    if setup.imaging is not None and setup.imaging.any_on:
        from .imaging_decode import decode_images_imaging  # sensor-matched noise model (issue 13)

        return decode_images_imaging(setup, images, response=response)
    seq = setup.patterns.sequence
    full = float(2**setup.patterns.bit_depth - 1)
    # the per-image lists as they are: the decoder takes a view where they already lie in one array, else stacks them once
    xs = [images[("x", p)] for p in seq.periods_x_mm]
    ys = [images[("y", p)] for p in seq.periods_y_mm]
    noise = np.hypot(setup.patterns.noise_std, 1.0 / np.sqrt(12.0))
    return decode_screen_coordinates(xs, seq.periods_x_mm, ys, seq.periods_y_mm, setup.screen.size_mm, full,
                                     noise_std=noise)


def consistency_checked(setup: Setup, camera: str | None, x_stacks, x_periods_mm, y_stacks, y_periods_mm,
                        decoded: ScreenCoordinates, noise_std=None, *, expected_xy_mm=None):
    """The consistency checks of ``pmdsim evaluate`` (docs/reliability.md) for one camera's
    decoded images, with the orientation check (when ``camera`` is given) against
    ``expected_xy_mm`` (H, W, 2), the screen coordinates the setup predicts — default: the
    nominal flat sample's, in closed form; for a curved sample (``setup.sample.curved``) pass the
    mapping traced through it, as the CLI's evaluate job and :func:`pmdsim.decode` do.

    Returns ``(decoded, result)``: the decoded coordinates with the consistency bits OR-ed into
    ``flags`` (and those pixels invalid), and the
    :class:`~pmdsim.evaluation.consistency.ConsistencyResult`.
    """
    from .consistency import check_consistency, nominal_screen_xy, with_consistency

    expected = expected_xy_mm
    if camera is not None and expected is None:  # the orientation check needs the camera's nominal mapping
        cs = setup.cameras[camera]
        expected = nominal_screen_xy(cs.camera, cs.T_world_cam, setup.sample.T_world_sample,
                                     setup.screen.T_world_screen)
    elif camera is None:
        expected = None
    cons = check_consistency(x_stacks, x_periods_mm, y_stacks, y_periods_mm, decoded, setup.screen.size_mm, noise_std,
                             expected_xy_mm=expected)
    return with_consistency(decoded, cons), cons


def decode_simulated(setup: Setup, screen_xy_mm: np.ndarray, valid: np.ndarray, *, rng=None,
                     pixel_stride: int = 1) -> ScreenCoordinates:
    """What :func:`decode_images` returns for the ideal renderer's images of a traced mapping
    (:func:`pmdsim.simulation.render.render_images` with ``rng`` =
    :func:`~pmdsim.simulation.render.noise_generator`), bit for bit, without rendering them
    (:func:`~.synthetic_decode.decode_rendered_fringes`). Only for setups without image-formation
    effects (``setup.imaging`` off): those images come from another renderer. ``pixel_stride``
    s: only the pixels (v, u) ≡ (0, 0) mod s, i.e. the full result's ``[::s, ::s]``.
    """
    if setup.imaging is not None and setup.imaging.any_on:
        raise ValueError("decode_simulated covers the ideal renderer only; with setup.imaging effects on, "
                         "render the images (render_images) and decode them (decode_images)")
    p = setup.patterns
    return decode_rendered_fringes(screen_xy_mm, valid, p.sequence, setup.screen.size_mm, bit_depth=p.bit_depth,
                                   noise_std=p.noise_std, rng=rng, pixel_stride=pixel_stride,
                                   decoder_noise_std=float(np.hypot(p.noise_std, 1.0 / np.sqrt(12.0))))


def evaluate_decoded(model: Setup, camera: str, decoded: ScreenCoordinates, *, screen_model=None,
                     method: str = "stepwise", seed_pixel=None, seed_height_mm: float = 0.0) -> tuple[Registration, Reconstruction]:
    """Registration with the model's camera and screen pose, then reconstruction (paper §2.5).

    Heights are in the model's sample frame. ``screen_model`` defaults to the plane z = 0 of the
    screen frame over the model's screen grid: the paper's planar-screen assumption. With a cover
    glass in the model (``model.screen.cover_glass``), registration and reconstruction run twice,
    the second registration at the first reconstruction's points (registration.py).
    """
    cs = model.cameras[camera]
    if screen_model is None:
        scr = model.screen
        screen_model = SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
    glass = model.screen.cover_glass
    reg = register(cs.camera, cs.T_world_cam, screen_model, model.screen.T_world_screen,
                   decoded.screen_xy_mm, decoded.valid, model.sample.T_world_sample, glass=glass,
                   sample_height_mm=seed_height_mm)
    if seed_pixel is None:
        # The documented default shared with the CLI: the registered pixel nearest the centroid
        # of the registered pixels (pmdsim.evaluation.anchor.default_seed_pixel).
        if not reg.valid.any():
            raise ReconstructionError(f"camera {camera!r}: no pixel was decoded and registered; nothing to reconstruct")
        seed_pixel = default_seed_pixel(reg.valid)
    rec = reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, method=method,
                      seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
    if glass.present:
        # The glass's apparent points depend on the sample point (registration.py): register
        # again at the reconstructed points and reconstruct again.
        reg = register(cs.camera, cs.T_world_cam, screen_model, model.screen.T_world_screen,
                       decoded.screen_xy_mm, decoded.valid, model.sample.T_world_sample, glass=glass,
                       sample_points_ref_mm=rec.p_sample_mm, sample_height_mm=seed_height_mm)
        rec = reconstruct(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid, method=method,
                          seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
    return reg, rec
