"""Decoding one camera of a loaded image set (manifest → stacks → screen coordinates).

Split from :mod:`pmdsim.io.imageset` (which re-exports both functions): the manifest and its
stacks are read there, the fringe decoding itself is :mod:`pmdsim.evaluation.phase`'s; this
module checks the periods against the screen, linearises images with a declared display
response (:mod:`pmdsim.io.imageset_instrument`) and applies a declared mask and screen map.
"""

from __future__ import annotations

from ..errors import ImageSetError
from ..evaluation.phase import ScreenCoordinates, decode_screen_coordinates
from .imageset import DIRECTIONS, CameraImages, ImageSetManifest, _screen_size, load_camera_stacks
from .imageset_instrument import apply_mask_and_map, linearise_camera, linearised_noise_std

__all__ = ["decode_camera", "decode_camera_images"]


def decode_camera_images(images: CameraImages, screen_size_mm, noise_std=None, *, response=None,
                         **decoder_kw) -> ScreenCoordinates:
    """Decode the pixel → screen mapping (x_q, y_q) of one camera's image stacks.

    Parameters
    ----------
    images : CameraImages
        From :func:`load_camera_stacks` or :func:`camera_images_from_arrays`.
    screen_size_mm : (float, float)
        Screen (width along x_q, height along y_q) in mm; the unwrapping extent.
    noise_std : float or array_like broadcastable to (H, W), optional
        Intensity noise σ_I in grey levels for the predicted σ (default: quantisation noise).
    response : IntensityResponse or LinearResponse, optional
        The display → camera response: the images are linearised (c → d(c), fractions of full
        scale) before decoding; samples at full scale or above the response's brightest level
        flag the pixel SATURATED (:mod:`pmdsim.io.imageset_instrument`).
    **decoder_kw
        Further keyword arguments of :func:`pmdsim.evaluation.phase.decode_screen_coordinates`
        (``screen_origin_mm``, thresholds, ``tolerance``, ``margin_mm``, ``check_saturation``).

    Returns
    -------
    pmdsim.evaluation.phase.ScreenCoordinates
        ``screen_xy_mm`` (H, W, 2) in mm (NaN where invalid), ``valid`` (H, W), ``flags``, …

    Raises
    ------
    ImageSetError
        If the screen size is invalid or a direction's coarsest period is shorter than the
        screen extent (hierarchical unwrapping needs it to be at least the extent).
    pmdsim.evaluation.phase.PhaseDecodingError
        For invalid decoder arguments.
    """
    size = _screen_size(screen_size_mm, "screen_size_mm")
    for i, direction in enumerate(DIRECTIONS):
        p0 = images.periods_mm(direction)[0]
        if p0 < size[i]:
            other = images.periods_mm(DIRECTIONS[1 - i])[0]
            swapped = p0 >= size[1 - i] and other >= size[i]  # each would cover the other extent
            raise ImageSetError(
                f"camera {images.camera!r}, direction {direction!r}: the coarsest period {p0:g} mm is shorter "
                f"than the screen's {'width' if i == 0 else 'height'} {size[i]:g} mm; absolute (hierarchical) "
                f"unwrapping needs a coarsest period of at least the screen extent"
                + (f" — the x and y directions look swapped: the {direction} periods fit the screen's "
                   f"{'height' if i == 0 else 'width'} and the {DIRECTIONS[1 - i]} periods ({other:g} mm coarsest) its "
                   f"{'width' if i == 0 else 'height'}; check each image's direction in the manifest" if swapped else "")
            )
    if response is None:
        return decode_screen_coordinates(
            list(images.x_stacks), list(images.x_periods_mm), list(images.y_stacks), list(images.y_periods_mm),
            size, images.max_value, noise_std, **decoder_kw,
        )
    full = float(images.max_value)
    xs, ys, saturated = linearise_camera(images, full, response)
    # σ_I (grey levels; default quantisation noise) → display-level units through the inverse
    # response's slope at each pixel's mean level of the finest x period.
    sigma = linearised_noise_std(images, response, noise_std)
    kw = dict(decoder_kw)
    kw["check_saturation"] = False
    dec = decode_screen_coordinates(xs, list(images.x_periods_mm), ys, list(images.y_periods_mm), size, 1.0,
                                    sigma, **kw)
    if decoder_kw.get("check_saturation", True):
        return apply_mask_and_map(dec, saturated=saturated)
    return dec


def decode_camera(manifest: ImageSetManifest, camera: str, screen_size_mm=None, noise_std=None, *,
                  expected_size_px: tuple[int, int] | None = None, **decoder_kw) -> ScreenCoordinates:
    """Read and decode one camera of an image set: the pixel → screen mapping (x_q, y_q).

    Parameters
    ----------
    manifest : ImageSetManifest
        From :func:`load_manifest`.
    camera : str
        One of ``manifest.cameras``.
    screen_size_mm : (float, float), optional
        Screen (width, height) in mm; default the manifest's ``screen_size_mm``.
    noise_std : float or array_like broadcastable to (H, W), optional
        Intensity noise σ_I in grey levels (default: quantisation noise 1/√12).
    expected_size_px : (int, int), optional
        ``[width, height]`` the images must have (the setup camera's ``image_size_px``).
    **decoder_kw
        Passed to :func:`pmdsim.evaluation.phase.decode_screen_coordinates`.

    Returns
    -------
    pmdsim.evaluation.phase.ScreenCoordinates
        ``screen_xy_mm`` (H, W, 2) in mm of the screen frame, NaN where invalid; ``valid``,
        ``flags``, ``std_xy_mm``, ``modulation``, ``offset``.

    Raises
    ------
    ImageSetError
        If neither the argument nor the manifest gives the screen size, or as
        :func:`load_camera_stacks` and :func:`decode_camera_images`.
    """
    size = screen_size_mm if screen_size_mm is not None else manifest.screen_size_mm
    if size is None:
        raise ImageSetError(f"{manifest.path}: the screen size is unknown: the manifest has no 'screen_size_mm'; "
                            f"pass screen_size_mm (width, height) in mm, e.g. from the setup")
    inst = manifest.instrument
    stacks = load_camera_stacks(manifest, camera, expected_size_px=expected_size_px)
    dec = decode_camera_images(stacks, size, noise_std, response=inst.response, **decoder_kw)
    if inst.mask is None and inst.screen_map is None:
        return dec
    return apply_mask_and_map(dec, mask=inst.mask, screen_map=inst.screen_map, source=str(manifest.path))
