"""Intensity response and linearisation (pmdsim.evaluation.response) against closed forms and
against a measured grey-level series (SOFAST's image_calibration.h5 values)."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.errors import PmdsimError
from pmdsim.evaluation.response import IntensityResponse, ResponseError

# SOFAST's ImageCalibration of the shared measurement (OpenCSP, Apache-2.0; shared/data/sofast):
# display grey levels and the camera's mean response to each.
SOFAST_DISPLAY = [0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 130, 140, 150, 160, 170, 180, 190, 200, 210,
                  220, 230, 240, 250, 255]
SOFAST_CAMERA = [1.47232824, 1.5529329, 2.25688027, 3.71936521, 5.79108076, 8.80328445, 12.77892728, 17.57970068,
                 23.24015669, 29.65965247, 36.80574528, 44.56091804, 53.08728405, 62.62871635, 72.9020691,
                 83.45013057, 94.77506027, 106.82844516, 119.39604259, 132.46941543, 145.89338088, 159.84898554,
                 174.4750904, 189.64985938, 206.01285657, 223.15985335, 234.40769385]


def test_gamma_forward_matches_the_law_between_knots():
    r = IntensityResponse.from_gamma(2.2, black_level=0.02, white_level=0.9, n_levels=257)
    d = np.random.default_rng(1).uniform(0.0, 1.0, 10_000)
    np.testing.assert_allclose(r.forward(d), 0.02 + 0.88 * d**2.2, atol=2e-6)


def test_linearise_inverts_forward():
    r = IntensityResponse.from_gamma(1.95, black_level=0.01, n_levels=65)
    d = np.linspace(0.0, 1.0, 1001)
    back, out = r.linearise(r.forward(d))
    assert not out.any()
    np.testing.assert_allclose(back, d, atol=1e-12)  # the exact inverse, between the samples too
    # and the inverse of the sampled law is within the interpolation error of the law's inverse:
    c = np.linspace(0.01, 1.0, 997)
    lin, _ = r.linearise(c)
    np.testing.assert_allclose(lin, ((c - 0.01) / 0.99) ** (1 / 1.95), atol=2e-3)


def test_measured_series_is_monotone_and_flags_out_of_range():
    r = IntensityResponse.from_samples(SOFAST_DISPLAY, SOFAST_CAMERA, display_full_scale=255, camera_full_scale=255)
    d, out = r.linearise(np.array([0.0, 100.0 / 255, 250.0 / 255]))
    assert out.tolist() == [True, False, True]  # below the darkest and above the brightest measured level
    assert 0 < d[1] < 1
    dd = np.linspace(0, 1, 500)
    assert (np.diff(r.forward(dd)) >= 0).all()


@pytest.mark.parametrize("display, camera, what", [
    ([0, 0.5, 1], [0.1, 0.3, 0.2], "camera_levels must be strictly increasing"),
    ([0, 0.5, 0.5], [0.1, 0.2, 0.3], "display_levels must be strictly increasing"),
    ([0, 1.5], [0.1, 0.2], "must lie in [0, 1]"),
    ([0], [0.1], "at least 2 levels"),
    ([0, 1], [0.1, 0.2, 0.3], "equal lengths"),
])
def test_invalid_responses_are_refused_naming_the_problem(display, camera, what):
    with pytest.raises(ResponseError, match=what.replace("[", r"\[").replace("]", r"\]")):
        IntensityResponse(tuple(display), tuple(camera))
    assert issubclass(ResponseError, PmdsimError)


def test_dict_round_trip():
    r = IntensityResponse.from_gamma(2.2, n_levels=9)
    assert IntensityResponse.from_dict(r.as_dict()) == r
    with pytest.raises(ResponseError, match="manifest.response"):
        IntensityResponse.from_dict({"display_levels": [0, 1]}, source="manifest.response")
