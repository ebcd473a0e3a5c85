"""Decoding images recorded with image-formation effects (issue 13): linearisation and a noise
model that matches the sensor.

* Linearisation (``imaging.linearise``): the recorded grey levels are mapped to display levels
  with the response measured from a simulated grey-level series
  (:func:`pmdsim.simulation.imaging.grey_level_response`, the same procedure as a real
  instrument's calibration series) before the N-step formula; samples outside the measured
  range are flagged SATURATED (their linearised value is not measured).
* Noise model: σ_I per pixel from the offset, shot and read noise
  (:func:`pmdsim.evaluation.phase.sensor_noise_std`), converted to linearised units with the
  slope of the inverse response at the offset; the decoder turns it into σ of the screen
  coordinates (σ_c = p_f·√(2/N)·σ_I/(2π·B)), which the calibration uses as weights and the
  outputs report.
* Saturation: any sample at full scale flags the pixel SATURATED (also after linearisation).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..setup import Setup
from .phase import PhaseFlag, ScreenCoordinates, decode_screen_coordinates, sensor_noise_std

__all__ = ["decode_images_imaging"]


def decode_images_imaging(setup: Setup, images: dict, *, response=None) -> ScreenCoordinates:
    """Decode one camera's images ``{(direction, period_mm): [image per shift]}`` recorded with
    ``setup.imaging``'s effects (see the module docstring).

    ``response`` is the :class:`~pmdsim.setup.response.IntensityResponse` to linearise with
    (required when ``setup.imaging.linearise``; a simulated instrument's is
    :func:`pmdsim.simulation.imaging.decoder_response`).

    Returns
    -------
    ScreenCoordinates
        As :func:`~pmdsim.evaluation.phase.decode_screen_coordinates`; ``std_xy_mm`` from the
        sensor-matched σ_I.
    """
    from ..setup.sensor import SensorModel

    seq = setup.patterns.sequence
    sensor = SensorModel.from_setup(setup)
    full = sensor.full_scale
    xs = [np.stack(images[("x", p)]) for p in seq.periods_x_mm]
    ys = [np.stack(images[("y", p)]) for p in seq.periods_y_mm]
    saturated = np.zeros(xs[0].shape[1:], dtype=bool)
    for st in xs + ys:
        saturated |= (st >= full).any(axis=0)
    fine_x = xs[int(np.argmin(seq.periods_x_mm))]
    fine_y = ys[int(np.argmin(seq.periods_y_mm))]
    offset = 0.5 * (fine_x.mean(axis=0, dtype=float) + fine_y.mean(axis=0, dtype=float))
    sigma = sensor_noise_std(offset, sensor.shot_dn, sensor.const_var_dn2, sensor.dark_dn)
    if setup.imaging.linearise:
        if response is None:
            raise ValueError("imaging.linearise is set, but no intensity response was given to linearise with: pass "
                             "response= (a measured grey-level series, or "
                             "pmdsim.simulation.imaging.decoder_response(setup) for a simulated instrument)")
        resp = response

        top = resp.camera_levels[-1]

        def lin(stack):
            c = stack / full
            d, _ = resp.linearise(c)  # below the darkest level: clipped (the noise floor)
            return d * full, (c > top).any(axis=0)

        xs2, ys2 = [], []  # linearised stacks
        for src, dst in ((xs, xs2), (ys, ys2)):
            for st in src:
                d, out = lin(st)
                dst.append(d)
                saturated |= out
        sig_x = _linearised_sigma(fine_x, xs2[int(np.argmin(seq.periods_x_mm))], resp, sensor)
        sig_y = _linearised_sigma(fine_y, ys2[int(np.argmin(seq.periods_y_mm))], resp, sensor)
        dec = decode_screen_coordinates(xs2, seq.periods_x_mm, ys2, seq.periods_y_mm, setup.screen.size_mm, full,
                                        noise_std=sig_x)
        dec_y = decode_screen_coordinates(xs2, seq.periods_x_mm, ys2, seq.periods_y_mm, setup.screen.size_mm, full,
                                          noise_std=sig_y)
        dec = replace(dec, std_xy_mm=np.stack([dec.std_xy_mm[..., 0], dec_y.std_xy_mm[..., 1]], axis=-1))
    else:
        dec = decode_screen_coordinates(xs, seq.periods_x_mm, ys, seq.periods_y_mm, setup.screen.size_mm, full,
                                        noise_std=sigma)
    if not saturated.any():
        return dec
    flags = dec.flags | np.where(saturated, np.uint8(PhaseFlag.SATURATED), np.uint8(0))
    valid = flags == 0
    nan2 = np.where(valid[..., None], 1.0, np.nan)
    return replace(dec, flags=flags, valid=valid, screen_xy_mm=dec.screen_xy_mm * nan2, std_xy_mm=dec.std_xy_mm * nan2)


def _linearised_sigma(raw, lin, resp, sensor) -> np.ndarray:
    """Effective σ_I (linearised grey levels) of one finest-period stack, (H, W).

    After linearisation the noise of sample k is σ_k = σ_I(I_k)·|dd/dI|(I_k), which changes
    with the shift (the inverse response's slope does), so the σ_φ formula's σ_I is replaced by
    the value that gives the N-step estimator's first-order variance exactly:
    σ_eff² = (2/N)·Σ_k σ_k²·sin²(φ − δ_k), φ from the linearised stack.
    """
    full = sensor.full_scale
    n = raw.shape[0]
    delta = 2.0 * np.pi * np.arange(n) / n
    raw_f = raw.astype(float)
    h = 0.5
    lo, _ = resp.linearise((raw_f - h) / full)
    hi, _ = resp.linearise((raw_f + h) / full)
    slope = np.abs(hi - lo) / (2.0 * h) * full
    sig_k = sensor_noise_std(raw_f, sensor.shot_dn, sensor.const_var_dn2, sensor.dark_dn) * slope
    S = np.tensordot(np.sin(delta), lin, axes=1)
    C = np.tensordot(np.cos(delta), lin, axes=1)
    phi = np.arctan2(S, C)
    w = np.sin(phi[None] - delta[:, None, None]) ** 2
    return np.sqrt(np.maximum(2.0 / n * np.sum(sig_k**2 * w, axis=0), 0.0))
