"""The summary statistics of ``pmdsim evaluate``'s σ maps (studies/uncertainty_job.uncertainty_stats,
issue 25): equal to the plain numpy definitions (RMS and maximum over the finite values) and to
``SurfaceUncertainty.dominant``, whether the combined map is the noise map itself or not, the
calibration part zero, −0, NaN or larger than the noise."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation.uncertainty import SurfaceUncertainty
from pmdsim.studies.uncertainty_job import uncertainty_stats


def _unc(noise, cal, *, shared: bool):
    total = noise if shared else np.sqrt(noise * noise + cal * cal)
    g = np.zeros(noise.shape + (2,))
    return SurfaceUncertainty(slope_std_urad=g, height_std_um=total, slope_std_noise_urad=g, height_std_noise_um=noise,
                              slope_std_calibration_urad=g, height_std_calibration_um=cal, notes=("a note",))


def _reference(unc):
    h = unc.height_std_um[np.isfinite(unc.height_std_um)]
    return {"height_std_rms_um": float(np.sqrt(np.mean(h * h))), "height_std_max_um": float(h.max()),
            "uncertainty_dominant": unc.dominant(), "uncertainty_notes": ["a note"]}


@pytest.mark.parametrize("case", ["shared", "zero", "minus_zero", "nan_holes", "calibration_dominant", "not_contiguous"])
def test_stats_equal_numpy_definitions(case):
    rng = np.random.default_rng(7)
    noise = rng.uniform(0.5, 2.0, (37, 53))
    cal = np.zeros_like(noise)
    shared = case in ("shared", "zero", "minus_zero", "not_contiguous")
    if case == "minus_zero":
        cal[3, 4] = -0.0
    if case == "nan_holes":
        noise[5:9, 10:20] = np.nan
        cal = rng.uniform(0.0, 0.1, noise.shape)
        cal[0, :] = np.nan
    if case == "calibration_dominant":
        cal = rng.uniform(3.0, 4.0, noise.shape)
    if case == "not_contiguous":
        noise = np.asfortranarray(noise)
    unc = _unc(noise, cal, shared=shared)
    got = uncertainty_stats(unc)
    assert got == _reference(unc)
    assert got["uncertainty_dominant"] == ("calibration" if case == "calibration_dominant" else "noise")


def test_no_finite_value_and_no_uncertainty():
    noise = np.full((4, 5), np.nan)
    assert uncertainty_stats(_unc(noise, np.zeros_like(noise), shared=True)) == {}
    assert uncertainty_stats(None) == {}
