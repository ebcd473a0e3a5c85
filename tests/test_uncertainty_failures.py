"""σ that real inputs make impossible (issue 22, "Bad input"): the evaluation says why, per
camera, and still writes the heights — reproduced with real inputs, not patched exceptions."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from pmdsim.cli import main
from pmdsim.setup.covariance import CalibrationCovariance
from pmdsim.setup.toml import load_setup
from pmdsim.studies.jobs import evaluate_image_set


@pytest.fixture(scope="module")
def sim(tmp_path_factory, small_setup_file):
    out = tmp_path_factory.mktemp("sim") / "sim"
    r = CliRunner().invoke(main, ["simulate", "--setup", str(small_setup_file), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    return out


def test_a_covariance_that_moves_the_camera_out_of_sight(tmp_path, sim, small_setup_file):
    """The setup's covariance gives the left camera's rotation a standard deviation of 200 rad
    (a wrong unit, say): the calibration part's finite-difference step (a hundredth of σ, 2 rad)
    turns the camera away from the sample, and no surface can be reconstructed there. The left
    camera's σ is omitted with one warning naming the camera and the cause; its heights are
    written. The covariance holds no parameter of the right camera, so its calibration part is
    exactly zero (and its σ is the noise part alone), with the file's shapes: (H, W) and (H, W, 2)."""
    setup = load_setup(small_setup_file).with_calibration_covariance(
        CalibrationCovariance(("left.rotvec_x",), [[200.0 ** 2]]))
    summary = evaluate_image_set(sim, setup, tmp_path / "ev")
    lines = [w for w in summary.warnings if "no uncertainty" in w]
    assert len(lines) == 1 and lines[0].startswith("left: no uncertainty (σ datasets omitted, heights written): ")
    assert "camera 'left': the surface cannot be reconstructed when the setup moves" in lines[0]
    with h5py.File(tmp_path / "ev" / "evaluation.h5") as f:
        left, right = f["left"], f["right"]
        rec = left["reconstructed"][()]
        assert rec.sum() > 1000 and np.isfinite(left["height_mm"][()][rec]).all()
        assert not any(k.startswith(("height_std", "slope_std")) for k in left)
        assert json.loads(f.attrs["uncertainty"])["left"] == {"omitted": True}
        r = right["reconstructed"][()]
        h, w = r.shape
        assert right["height_std_calibration_um"].shape == (h, w)
        assert right["slope_std_calibration_urad"].shape == (h, w, 2)
        assert (right["height_std_calibration_um"][()][r] == 0).all()
        assert (right["slope_std_calibration_urad"][()][r] == 0).all()
        np.testing.assert_array_equal(right["height_std_um"][()][r], right["height_std_noise_um"][()][r])
    assert not (tmp_path / "ev" / "height_std_left.png").exists()
    assert (tmp_path / "ev" / "height_std_right.png").exists()
