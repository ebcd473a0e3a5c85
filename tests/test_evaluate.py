"""`pmdsim evaluate` end to end: simulate → images on disk → evaluate, against the truth."""

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from pmdsim.cli import main




def _run(args):
    r = CliRunner().invoke(main, args)
    return r


def test_evaluate_simulated_images(tmp_path, small_setup_file, small_bulge3_evaluated):
    # `simulate --bulge-mm 3`, then `evaluate` with the planar screen model (the paper's
    # assumption; tests/conftest.py, both exit 0): a tilted plane of the Experiment 1 magnitude.
    sim, out = small_bulge3_evaluated
    with h5py.File(out / "evaluation.h5") as f, h5py.File(sim / "mapping.h5") as m:
        assert set(f) == {"left", "right"}
        for cam in ("left", "right"):
            g = f[cam]
            h = g["height_mm"][()]
            rec = g["reconstructed"][()]
            assert rec.all()
            # Decoded coordinates agree with the simulator's mapping within the 8-bit bound
            # (finest period 4 mm in the small setup, B = 0.45·255).
            err = np.abs(g["screen_xy_mm"][()] - m[cam]["screen_xy_mm"][()])
            assert err.max() < 4.0 / (2 * np.pi) * np.arcsin(1 / (0.45 * 255)) * 1.01
            ptp = np.ptp(h[rec]) * 1e3
            assert 100 < ptp < 400  # µm: Experiment 1 at Δh = 3 mm gives ≈ 220 µm
            n = g["normals"][()]
            np.testing.assert_allclose(np.linalg.norm(n[rec], axis=-1), 1.0, atol=1e-12)
    assert (out / "height_left.png").stat().st_size > 5000
    # With the true (setup's, bulged) screen model the plane is recovered to the 8-bit floor.
    out2 = tmp_path / "ev2"
    setup3 = tmp_path / "setup3.toml"
    text = small_setup_file.read_text()
    assert text.count("bulge_mm = 0.0") == 1
    setup3.write_text(text.replace("bulge_mm = 0.0", "bulge_mm = 3.0"))
    r = _run(["evaluate", str(sim), "--setup", str(setup3), "--screen-model", "setup", "--out", str(out2),
              "--method", "least_squares", "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(out2 / "evaluation.h5") as f:
        for cam in ("left", "right"):
            h = f[cam]["height_mm"][()]
            assert np.nanmax(np.abs(h)) * 1e3 < 0.5  # µm (binned camera: coarser integration steps)


def test_evaluate_errors(tmp_path, small_setup_file):
    r = _run(["evaluate", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "manifest" in r.output
    assert not (tmp_path / "o").exists()
