"""Experiment 1 (paper §3, Table 2) end to end through 8-bit images, downsampled 4×4.

Truths: the paper's Table 2 (magnitudes within 0.5–2×, opposite tilts of the two cameras),
linearity in Δh (physics: the error is first order in the screen deformation), and the 8-bit
floor at Δh = 0 (the paper reports ≈ 0.03 µm).
"""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.studies import PAPER_TABLE2
from pmdsim.evaluation import decode_images, evaluate_decoded
from pmdsim.evaluation.metrics import surface_error_metrics
from pmdsim.setup import default_setup
from pmdsim.simulation import render_images, trace_setup_camera

DOWNSAMPLE = 4
KEYS = ("max_height_diff_um", "max_dev_plane_um", "tilt_urad")


@pytest.fixture(scope="module")
def results(experiment1_ds4):
    """Experiment 1 at downsample 4 = DOWNSAMPLE (tests/conftest.py: shared with test_experiment2)."""
    return experiment1_ds4


def test_planar_screen_reaches_the_8bit_floor(results):
    for cam in ("left", "right"):
        m = results[(0.0, cam)].metrics
        assert m["max_height_diff_um"] < 0.1, m
        assert m["n_pixels"] == (1200 // DOWNSAMPLE) * (1920 // DOWNSAMPLE)


def test_errors_grow_linearly_with_the_bulge(results):
    for cam in ("left", "right"):
        for key in KEYS:
            e1 = results[(1.0, cam)].metrics[key]
            e2 = results[(2.0, cam)].metrics[key]
            e3 = results[(3.0, cam)].metrics[key]
            assert 2.8 <= e3 / e1 <= 3.2, (cam, key, e1, e3)
            assert 1.9 <= e2 / e1 <= 2.1, (cam, key, e1, e2)


def test_left_and_right_tilt_in_opposite_x_directions(results):
    for dh in (1.0, 2.0, 3.0):
        tl = results[(dh, "left")].metrics["tilt_x_urad"]
        tr = results[(dh, "right")].metrics["tilt_x_urad"]
        assert tl * tr < 0 and abs(tl) > 100 * dh


def test_magnitudes_match_the_paper_within_a_factor_two(results):
    for dh in (1.0, 2.0, 3.0):
        for cam in ("left", "right"):
            ours = results[(dh, cam)].metrics
            for key, paper in zip(KEYS, PAPER_TABLE2[(dh, cam)]):
                assert 0.5 <= ours[key] / paper <= 2.0, (dh, cam, key, ours[key], paper)


def test_true_screen_model_removes_the_error():
    """Round trip: evaluating with the *true* (bulged) screen as the model recovers the plane
    at the 8-bit floor — the bulge error of Experiment 1 is entirely the planar-screen model."""
    truth = default_setup().binned(DOWNSAMPLE).with_bulge(3.0)
    m = trace_setup_camera(truth, "left", store_points=True)
    images = {}
    for spec, img in render_images(truth, "left", m):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    decoded = decode_images(truth, images)
    seed = (150, 240)
    reg, rec = evaluate_decoded(truth, "left", decoded, screen_model=truth.screen.surface, seed_pixel=seed,
                                seed_height_mm=float(m.p_sample_mm[seed][2]))
    p = rec.p_sample_mm
    metrics = surface_error_metrics(p[..., 0], p[..., 1], rec.height_mm)
    assert metrics["max_height_diff_um"] < 0.1
    # And the reconstructed points lie on the true view rays' sample intersections.
    np.testing.assert_allclose(p[rec.reconstructed], m.p_sample_mm[rec.reconstructed], atol=1e-3)


def test_cli_experiment1_writes_the_contract(tmp_path):
    out = tmp_path / "e1"
    r = CliRunner().invoke(main, ["experiment", "1", "--out", str(out), "--downsample", "8", "--bulges-mm", "0,3",
                                  "--quiet"])
    assert r.exit_code == 0, r.output
    recs = json.loads((out / "results.json").read_text())
    assert len(recs) == 4
    for rec in recs:
        assert {"bulge_mm", "camera", "max_height_diff_um", "max_dev_plane_um", "tilt_urad"} <= set(rec)
        assert rec["camera"] in ("left", "right")
    assert (out / "figure4.png").stat().st_size > 10_000
    assert (out / "heights.h5").exists()
    assert "paper" in r.output and "149.5" in r.output
    # Refuses to overwrite.
    r2 = CliRunner().invoke(main, ["experiment", "1", "--out", str(out), "--downsample", "8", "--quiet"])
    assert r2.exit_code != 0 and "--force" in r2.output
