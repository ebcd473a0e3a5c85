"""The sensor's last step, one pixel and image: a mean signal to its recorded code (issue 20, item 3).

Shared by the image-formation kernels (:mod:`.imaging_point`, :mod:`.imaging_series`,
:mod:`.imaging_held`); the sensor's parameters come from :class:`~pmdsim.setup.sensor.SensorModel`
(docs/conventions.md, "Sensor"). A mean at or above the full well's code (``clip``) is pinned at
the saturation code ``full`` with no noise; otherwise the code is round-half-up of dark offset +
mean + √(shot·mean + const_var)·ξ (ξ standard normal), clipped to [0, full].

Inlined into its callers at numba's IR level (``inline="always"``), so each caller's floating-point
flags (e.g. ``fastmath={"contract"}``) apply as they did to the inline code it replaces: the
recorded codes are bit-identical to the per-kernel copies this module replaced.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["sensor_code"]


@numba.njit(cache=True, error_model="numpy", inline="always")
def sensor_code(mean, dark, clip, shot, const_var, full, use_noise, noise_value):
    """Recorded code (float, an integer value in [0, full]) of a pixel whose mean signal above the
    dark offset is ``mean`` (DN, before clipping, noise and rounding).

    Parameters
    ----------
    mean, dark, clip, shot, const_var, full : float
        Mean signal, dark offset, the full well's code, shot-noise variance per DN, signal-independent
        variance (DN²) and the saturation code (:class:`~pmdsim.setup.sensor.SensorModel`).
    use_noise : bool
        Add noise; ``noise_value`` (a standard-normal draw) is read only then.
    """
    if mean >= clip:  # the full well is reached: the saturation code, no noise
        return full
    if mean < 0.0:
        mean = 0.0
    val = dark + mean
    if use_noise:
        val += np.sqrt(shot * mean + const_var) * noise_value
    q = np.floor(val + 0.5)
    if q < 0.0:
        q = 0.0
    elif q > full:
        q = full
    return q
