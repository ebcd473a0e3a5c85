"""The simulated measurement (paper §2): trace every camera once, render its fringe images.

This layer combines the numeric core (camera, surfaces, tracer, patterns) for a
:class:`~pmdsim.setup.Setup`; it neither prints nor writes files.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .patterns import PatternFrame, render_period
from ..setup import Setup
from .trace import Mapping, trace_camera

__all__ = ["trace_setup_camera", "ImageSpec", "image_specs", "render_images", "noise_generator"]


def trace_setup_camera(setup: Setup, camera: str, *, store_points: bool = False) -> Mapping:
    """Pixel → screen mapping of one camera of ``setup`` (paper §2.4)."""
    if camera not in setup.cameras:
        raise KeyError(f"camera {camera!r} is not in the setup (cameras: {list(setup.cameras)})")
    cs = setup.cameras[camera]
    return trace_camera(
        cs.camera,
        cs.T_world_cam,
        setup.sample.T_world_sample,
        setup.sample.surface,
        setup.screen.T_world_screen,
        setup.screen.surface,
        store_points=store_points,
        glass=setup.screen.cover_glass,
    )


@dataclass(frozen=True)
class ImageSpec:
    """One image of a simulated image set: camera, pattern frame and file name."""

    camera: str
    frame: PatternFrame
    period_index: int
    file: str

    def as_manifest_entry(self) -> dict:
        return {
            "file": self.file,
            "camera": self.camera,
            "direction": self.frame.direction,
            "period_mm": self.frame.period_mm,
            "period_index": self.period_index,
            "shift_index": self.frame.shift_index,
            "n_shifts": self.frame.n_shifts,
        }


def image_specs(setup: Setup, camera: str, *, extension: str = "png") -> list[ImageSpec]:
    """The images of one camera in display order, with their file names
    ``{camera}_{direction}_p{period index}_s{shift index}.{extension}``."""
    seq = setup.patterns.sequence
    out = []
    for frame in seq.frames():
        pi = seq.periods(frame.direction).index(frame.period_mm)
        out.append(ImageSpec(camera, frame, pi,
                             f"{camera}_{frame.direction}_p{pi}_s{frame.shift_index}.{extension}"))
    return out


def render_images(setup: Setup, camera: str, mapping: Mapping, *,
                  stream: int | None = None, T_world_sample=None) -> Iterator[tuple[ImageSpec, np.ndarray]]:
    """Yield ``(spec, image)`` for every image of ``camera``; noise (if any) is seeded from
    the setup's seed and the camera's index, so the same setup gives the same images.

    ``stream`` (≥ 0) selects an independent noise stream for the same camera, e.g. one per
    calibration mirror pose, so that the noise of different image sets is uncorrelated.

    With image-formation effects (``setup.imaging``, :mod:`.imaging`) the images are rendered
    by :func:`~.imaging.render_direction_imaging` (all images of a direction at once);
    ``T_world_sample`` is then the pose of the surface ``mapping`` was traced with (default: the
    setup's sample), and defocus or angular emission need ``mapping`` traced with
    ``store_points=True``.
    """
    p = setup.patterns
    key = _noise_key(setup, camera, stream)
    if setup.imaging is not None and setup.imaging.any_on:
        yield from _render_images_imaging(setup, camera, mapping, key, T_world_sample)
        return
    rng = np.random.default_rng(key) if p.noise_std > 0 else None
    stack = None
    for spec in image_specs(setup, camera):
        f = spec.frame
        if f.shift_index == 0:  # frames come in display order: all shifts of a period together
            stack = render_period(mapping.screen_xy_mm, mapping.valid, f.direction, f.period_mm, p.sequence,
                                  bit_depth=p.bit_depth, noise_std=p.noise_std, rng=rng)
        yield spec, stack[f.shift_index]


def _noise_key(setup: Setup, camera: str, stream: int | None) -> list:
    """The documented seed contract: ``[seed, camera index]`` or ``[seed, camera index, stream]``."""
    cam_index = list(setup.cameras).index(camera)
    return [setup.patterns.seed, cam_index] if stream is None else [setup.patterns.seed, cam_index, int(stream)]


def noise_generator(setup: Setup, camera: str, *, stream: int | None = None) -> np.random.Generator | None:
    """The generator :func:`render_images` draws the ideal renderer's noise from (None without
    noise): seeded by ``[seed, camera index]`` or ``[seed, camera index, stream]``, so that
    :func:`pmdsim.evaluation.synthetic_decode.decode_rendered_fringes` reproduces its images."""
    return np.random.default_rng(_noise_key(setup, camera, stream)) if setup.patterns.noise_std > 0 else None


def _render_images_imaging(setup, camera, mapping, key, T_world_sample):
    from .imaging import imaging_maps, render_direction_imaging
    from ..setup.sensor import SensorModel

    sensor = SensorModel.from_setup(setup)
    maps = imaging_maps(setup, camera, mapping, T_world_sample=T_world_sample)
    rng = np.random.default_rng(key) if sensor.noisy else None
    seq = setup.patterns.sequence
    stacks, direction = None, None
    for spec in image_specs(setup, camera):  # display order: one direction's periods together
        f = spec.frame
        if f.direction != direction:  # the direction's images share the per-pixel geometry
            direction = f.direction
            stacks = render_direction_imaging(maps, mapping.screen_xy_mm, mapping.valid, direction, seq, sensor, rng)
        yield spec, stacks[spec.period_index, f.shift_index]
