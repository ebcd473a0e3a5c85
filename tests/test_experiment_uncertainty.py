"""The height σ keys of Experiments 2, 3 and 5 (issue 22, item 2): ``height_std_um``,
``coverage_k2``, ``height_std_notes``, ``height_std_ignores``.

Truths: the Gaussian closed form P(|e| ≤ kσ) = erf(k/√2) for seeded errors of known σ; the
root-sum-square of the contributions; the decoder's noise model σ_I² = noise_std² + 1/12
(a closed-form ratio of the noise part with and without image noise); the spline spaces the
screen models span (a 3 × 3 bulge is a parabola; the planar model misses it by its peak); the
experiment's own maps for the pixel count and the seed (σ = 0 where the height is given).
"""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from pmdsim.setup import default_setup
from pmdsim.studies import run_experiment2_bulge, screen_deformation
from pmdsim.studies.experiment_uncertainty import (
    COVERAGE_GAUSSIAN_K2, IGNORES_COVER_GLASS, IGNORES_IDEAL_IMAGES, IGNORES_LATERAL, IGNORES_MIRROR_SAG, IGNORES_PLANAR_BULGE,
    IGNORES_SCREEN_SHAPE, STEREO_NO_SIGMA_NOTE, coverage_k2, height_std_summary, model_error_labels,
    screen_representation_error_mm, stereo_uncertainty_record)

KEYS = {"height_std_um", "coverage_k2", "height_std_notes", "height_std_ignores"}
STATS = {"rms", "max", "median", "noise_rms", "calibration_rms", "pixels"}


def test_coverage_k2_of_gaussian_errors_with_known_sigma():
    rng = np.random.default_rng(22)
    sigma = rng.uniform(0.05, 5.0, (300, 400))
    err = rng.normal(size=sigma.shape) * sigma
    err[0, :50] = np.nan  # not reconstructed: not counted
    n = np.isfinite(err).sum()
    assert COVERAGE_GAUSSIAN_K2 == pytest.approx(0.9545, abs=1e-4)
    for k in (1.0, 2.0, 3.0):
        p = math.erf(k / math.sqrt(2))
        assert abs(coverage_k2(err, sigma, k) - p) < 4 * math.sqrt(p * (1 - p) / n)
    # A σ stated half as large as the errors' covers erf(1/√2) of them at k = 2.
    assert abs(coverage_k2(err, 0.5 * sigma) - math.erf(1 / math.sqrt(2))) < 0.01
    assert coverage_k2(np.full(3, np.nan), np.ones(3)) is None


def test_height_std_summary_statistics():
    h = np.array([[3.0, 4.0], [np.nan, np.nan]])
    s = height_std_summary(h, np.array([[3.0, 0.0], [np.nan, np.nan]]), np.array([[0.0, 4.0], [np.nan, np.nan]]))
    assert s == pytest.approx({"rms": math.sqrt(12.5), "max": 4.0, "median": 3.5, "noise_rms": math.sqrt(4.5),
                               "calibration_rms": math.sqrt(8.0), "pixels": 2})
    assert height_std_summary(np.full((2, 2), np.nan), h, h) is None


def test_screen_model_representation_and_labels():
    s = default_setup().binned(16)
    bulged = s.with_bulge(3.0)
    # A 3-point not-a-knot spline is one parabola: its peak is the central control height.
    assert screen_representation_error_mm(bulged, None) == pytest.approx(3.0, abs=1e-9)
    assert screen_representation_error_mm(bulged, 3) < 1e-9
    assert screen_representation_error_mm(bulged, 5) < 1e-9
    off = screen_deformation(s, "offcentre")  # a 5 × 5 shape: not in the 3 × 3 space, in the 9 × 9 one
    assert screen_representation_error_mm(off, 3) > 0.1
    assert screen_representation_error_mm(off, 9) < 1e-9
    ign, notes = model_error_labels(bulged, screen_grid=None)
    assert ign == [IGNORES_PLANAR_BULGE, IGNORES_IDEAL_IMAGES] and len(notes) == 2
    assert model_error_labels(bulged, screen_grid=3)[0] == [IGNORES_IDEAL_IMAGES]
    assert model_error_labels(off, screen_grid=3)[0][0] == IGNORES_SCREEN_SHAPE
    noisy = bulged.with_patterns(noise_std=2.0).with_mirror_sag(5.0).with_cover_glass(1.0)
    assert model_error_labels(noisy, screen_grid=3)[0] == [IGNORES_MIRROR_SAG, IGNORES_COVER_GLASS]
    assert model_error_labels(noisy, screen_grid=3, screen_glass_modelled=True)[0] == [IGNORES_MIRROR_SAG]
    assert model_error_labels(noisy, screen_grid=3, screen_glass_modelled=True, curved_sample=True)[0] == [
        IGNORES_MIRROR_SAG, IGNORES_LATERAL]


def test_stereo_without_sigma_is_null_with_a_note():
    r = stereo_uncertainty_record(default_setup().binned(16).with_bulge(3.0), SimpleNamespace(), None, screen_grid=None)
    assert r["height_std_um"] is None and r["coverage_k2"] is None
    assert STEREO_NO_SIGMA_NOTE in r["height_std_notes"] and IGNORES_PLANAR_BULGE in r["height_std_ignores"]
    maps = {"height_std_um": np.array([1.0, 2.0]), "height_std_noise_um": np.array([1.0, 0.0]),
            "height_std_calibration_um": np.array([0.0, 2.0])}
    r = stereo_uncertainty_record(default_setup().binned(16), SimpleNamespace(uncertainty=SimpleNamespace(**maps)),
                                  np.array([1.5e-3, 5e-3]), screen_grid=None)
    assert r["coverage_k2"] == 0.5 and r["height_std_um"]["pixels"] == 2


@pytest.fixture(scope="module")
def exp2_3mm(binned8_bulge3_experiment2):
    """Experiment 2 at Δh = 3 mm, downsample 8, planar (None) and 3 × 3 screen models on the same
    calibration observations (tests/conftest.py: shared with tests/test_experiment3.py)."""
    return binned8_bulge3_experiment2


def test_experiment2_cases_carry_sigma_keys(exp2_3mm):
    for grid, e in exp2_3mm.items():
        assert e.model.calibration_covariance is not None  # the calibration part is used
        for c in e.cases:
            rec = json.loads(json.dumps(c.as_record()))
            assert KEYS <= set(rec) and set(rec["height_std_um"]) == STATS
            st = rec["height_std_um"]
            h = c.height_std_um
            assert st["pixels"] == int(c.reconstructed.sum())
            assert np.isnan(h[~c.reconstructed]).all() and np.isfinite(h[c.reconstructed]).all()
            # Relative to the seed: 0 where the height is given, > 0 everywhere else.
            assert h[c.seed_pixel] == 0.0
            others = c.reconstructed.copy()
            others[c.seed_pixel] = False
            assert (h[others] > 0).all()
            assert st["noise_rms"] > 0 and st["calibration_rms"] > 0
            assert st["rms"] ** 2 == pytest.approx(st["noise_rms"] ** 2 + st["calibration_rms"] ** 2, rel=1e-9)
            assert st["max"] >= st["rms"] >= 0
            e_um = c.height_error_mm[c.reconstructed] * 1e3
            assert rec["coverage_k2"] == pytest.approx(np.mean(np.abs(e_um) <= 2 * h[c.reconstructed]))
            assert IGNORES_IDEAL_IMAGES in rec["height_std_ignores"]
            assert (IGNORES_PLANAR_BULGE in rec["height_std_ignores"]) == (grid is None)
            assert IGNORES_SCREEN_SHAPE not in rec["height_std_ignores"]
            assert rec["height_std_notes"]
    # The planar model's bias (labelled) lies far outside its σ; the 3 × 3 model's errors do not.
    for cp, cf in zip(exp2_3mm[None].cases, exp2_3mm[3].cases):
        assert cp.uncertainty["coverage_k2"] < 0.5 < cf.uncertainty["coverage_k2"]


def test_noise_part_follows_the_decoders_noise_model():
    """σ_I² = noise_std² + 1/12 grey levels² (the rounding): 2 grey levels of noise scale the
    noise part by √(4 + 1/12)/√(1/12) = 7 (up to the decoded modulation's own noise)."""
    truth = default_setup().binned(16).with_bulge(3.0)
    quiet = run_experiment2_bulge(3.0, base=default_setup(), downsample=16, screen_grid=3)
    noisy = run_experiment2_bulge(3.0, base=default_setup().with_patterns(noise_std=2.0, seed=3), downsample=16,
                                  screen_grid=3)
    assert truth.patterns.noise_std == 0
    for a, b in zip(quiet.cases, noisy.cases):
        ratio = b.uncertainty["height_std_um"]["noise_rms"] / a.uncertainty["height_std_um"]["noise_rms"]
        assert ratio == pytest.approx(7.0, rel=0.05)
        assert IGNORES_IDEAL_IMAGES not in b.uncertainty["height_std_ignores"]

