"""The sensor's last step (:mod:`pmdsim.simulation.sensor_code`) against the sensor model written
out in numpy here: saturation pinned without noise, shot + constant noise, round half up, clip."""

from __future__ import annotations

import numpy as np

from pmdsim.simulation.sensor_code import sensor_code


def _reference(mean, dark, clip, shot, const_var, full, noise):
    m = np.maximum(mean, 0.0)
    val = dark + m + np.sqrt(shot * m + const_var) * noise
    q = np.clip(np.floor(val + 0.5), 0.0, full)
    return np.where(mean >= clip, full, q)


def test_sensor_code_matches_the_model_written_out():
    rng = np.random.default_rng(7)
    full, clip, dark, shot, const_var = 4095.0, 3980.0, 16.0, 0.39, 2.5
    mean = np.concatenate([rng.uniform(-50.0, 4200.0, 4000), [clip, clip - 1e-9, -1.0, 0.0]])
    noise = rng.standard_normal(mean.size)
    got = np.array([sensor_code(m, dark, clip, shot, const_var, full, True, z) for m, z in zip(mean, noise)])
    np.testing.assert_array_equal(got, _reference(mean, dark, clip, shot, const_var, full, noise))
    # at or above the full well's code: the saturation code, whatever the noise draw
    assert all(sensor_code(clip + d, dark, clip, shot, const_var, full, True, z) == full
               for d in (0.0, 1.0, 500.0) for z in (-40.0, 0.0, 40.0))


def test_noise_free_codes_round_half_up_and_clip():
    full, clip = 255.0, 1e9  # no saturation: the clip to [0, full] alone
    cases = {(10.0, 2.5): 13.0, (10.0, 2.4999): 12.0, (0.0, -0.6): 0.0, (250.0, 10.0): 255.0, (0.0, -5.0): 0.0}
    for (dark, mean), want in cases.items():
        assert sensor_code(mean, dark, clip, 1.0, 1.0, full, False, np.nan) == want
