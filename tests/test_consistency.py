"""Consistency checks of decoded fringe images (issue 11): every bad-data case of the issue is
reproduced on simulated images, as a user would (files on disk, `pmdsim evaluate`), and must be
flagged with a reason; a clean set must not be.

Truths: the simulator's own mapping (mapping.h5, computed by ray tracing, not by the decoder),
the χ² and normal distributions (scipy.stats) for the false-alarm rates of synthetic Gaussian
data, and closed-form synthetic coordinate maps for the geometric check.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image
from scipy import stats

from pmdsim.cli import main
from pmdsim.evaluation.consistency import check_consistency, nominal_screen_xy, with_consistency
from pmdsim.evaluation.phase import PhaseFlag, decode_screen_coordinates
from pmdsim.io.imageset import decode_camera_images, load_camera_stacks, load_manifest
from pmdsim.setup import load_setup

from conftest import replace_exactly

NOISE = 1.0  # grey levels of the simulated sets


def _run(args):
    return CliRunner().invoke(main, args)


@pytest.fixture(scope="module")
def noisy_setup_file(tmp_path_factory, small_toml):
    p = tmp_path_factory.mktemp("setup") / "noisy.toml"
    p.write_text(replace_exactly(small_toml, "noise_std = 0.0", f"noise_std = {NOISE}", 1))
    return p


@pytest.fixture(scope="module")
def clean_set(tmp_path_factory, noisy_setup_file):
    d = tmp_path_factory.mktemp("sets") / "clean"
    r = _run(["simulate", "--setup", str(noisy_setup_file), "--out", str(d), "--quiet"])
    assert r.exit_code == 0, r.output
    return d


def _variant(clean: Path, dst: Path, fn) -> Path:
    shutil.copytree(clean, dst)
    man = json.loads((dst / "manifest.json").read_text())
    fn(dst, man)
    (dst / "manifest.json").write_text(json.dumps(man))
    return dst


def _img(d, f):
    return np.array(Image.open(d / f))


def _put(d, f, a):
    Image.fromarray(a).save(d / f)


# The cases (small setup: periods x 720/60/4 mm, y 420/35/4 mm, N = 4), left camera.
def _drop(d, man):  # one black frame in the finest period
    _put(d, "left_x_p2_s1.png", np.zeros_like(_img(d, "left_x_p2_s1.png")))


def _duplicate(d, man):  # shift 2 recorded twice as shift 1
    _put(d, "left_x_p2_s2.png", _img(d, "left_x_p2_s1.png"))


def _reverse(d, man):  # shift order reversed in direction x
    for e in man["images"]:
        if e["camera"] == "left" and e["direction"] == "x":
            e["shift_index"] = (-e["shift_index"]) % e["n_shifts"]


def _wrong_period(d, man):  # 60 mm stated as 62.5 mm (the issue: 48 stated as 50)
    for e in man["images"]:
        if e["period_mm"] == 60.0:
            e["period_mm"] = 62.5


def _misregistered(d, man):  # one period's images shifted by 2 px (the issue: 10 px of 480)
    for k in range(4):
        f = f"left_x_p1_s{k}.png"
        _put(d, f, np.roll(_img(d, f), 2, axis=1))


def _missing_shift(d, man):  # the last shift of a period missing, no n_shifts in the manifest
    man["images"] = [e for e in man["images"] if not (e["camera"] == "left" and e["direction"] == "x"
                                                      and e["period_index"] == 1 and e["shift_index"] == 3)]
    for e in man["images"]:
        e.pop("n_shifts")


def _three_periods(d, man):  # found by test_properties: every x period corrupted at once
    a, b = _img(d, "left_x_p0_s0.png"), _img(d, "left_x_p2_s0.png")
    _put(d, "left_x_p0_s0.png", b)
    _put(d, "left_x_p2_s0.png", a)
    _put(d, "left_x_p1_s0.png", np.zeros_like(a))


CASES = {
    "dropped frame": (_drop, "sinusoid"),
    "duplicated frame": (_duplicate, "sinusoid"),
    "reversed shift order": (_reverse, "orientation"),
    "wrong period": (_wrong_period, "period 62.5 mm disagrees"),
    "misregistered period": (_misregistered, "period 60 mm disagrees"),
    "missing shift": (_missing_shift, "period 60 mm disagrees"),
    "all x periods corrupted": (_three_periods, "sinusoid"),
}


def test_clean_set_not_flagged(tmp_path, clean_set, noisy_setup_file):
    out = tmp_path / "ev"
    r = _run(["evaluate", str(clean_set), "--setup", str(noisy_setup_file), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    assert "warning" not in r.output
    with h5py.File(out / "evaluation.h5") as f:
        for cam in ("left", "right"):
            g = f[cam]
            assert not g["consistency_flags"][()].any()
            assert g["reconstructed"][()].all()
            assert np.nanmax(g["fit_residual_ratio"][()]) < 1 and np.nanmax(g["period_mismatch_ratio"][()]) < 1
            names = json.loads(f.attrs["phase_flags"])
            assert names["FIT_RESIDUAL"] == 32 and names["PERIOD_MISMATCH"] == 64 and names["GEOMETRY"] == 128


@pytest.mark.parametrize("case", list(CASES))
def test_bad_data_is_refused_with_reason(tmp_path, clean_set, noisy_setup_file, case):
    fn, reason = CASES[case]
    d = _variant(clean_set, tmp_path / "set", fn)
    out = tmp_path / "ev"
    r = _run(["evaluate", str(d), "--setup", str(noisy_setup_file), "--out", str(out), "--quiet"])
    assert r.exit_code == 1, r.output
    err = [line for line in r.output.splitlines() if line.startswith("pmdsim: error:")]
    assert len(err) == 1 and "left" in err[0] and reason in err[0], r.output
    assert "Traceback" not in r.output


@pytest.mark.parametrize("case", list(CASES))
def test_no_unflagged_pixel_is_wrong(clean_set, noisy_setup_file, case, tmp_path):
    """API level: whatever the consistency checks leave valid agrees with the traced truth
    within 6 σ of the coordinate noise (σ from the noise the check estimated)."""
    setup = load_setup(noisy_setup_file)
    d = _variant(clean_set, tmp_path / "set", CASES[case][0])
    man = load_manifest(d, screen_size_mm=setup.screen.size_mm)
    im = load_camera_stacks(man, "left")
    dec = decode_camera_images(im, setup.screen.size_mm)
    cs = setup.cameras["left"]
    exp = nominal_screen_xy(cs.camera, cs.T_world_cam, setup.sample.T_world_sample, setup.screen.T_world_screen)
    cons = check_consistency(im.x_stacks, im.x_periods_mm, im.y_stacks, im.y_periods_mm, dec, setup.screen.size_mm,
                             expected_xy_mm=exp)
    checked = with_consistency(dec, cons)
    with h5py.File(clean_set / "mapping.h5") as m:
        truth = m["left"]["screen_xy_mm"][()]
    before = np.abs(dec.screen_xy_mm - truth)[dec.valid]
    assert before.size and np.nanmax(before) > 0.1, "the case must corrupt the decoding (mm)"
    ok = checked.valid
    sigma_scale = cons.noise_std_max / math.sqrt(1 / 12)  # decoder σ assumed quantisation noise only
    err = np.abs(checked.screen_xy_mm - truth)[ok] / (checked.std_xy_mm[ok] * sigma_scale)
    assert err.size == 0 or err.max() < 6.0, f"{case}: {np.count_nonzero(err >= 6)} wrong pixels left valid"
    # Every newly invalid pixel carries a consistency reason.
    newly = dec.valid & ~checked.valid
    assert np.all(checked.flags[newly] & (PhaseFlag.FIT_RESIDUAL | PhaseFlag.PERIOD_MISMATCH | PhaseFlag.GEOMETRY))


def test_local_defect_is_flagged_locally(tmp_path, clean_set, noisy_setup_file):
    """A 12×12 px patch of one finest-period frame overwritten (a reflection, dust): exactly the
    patch is FIT_RESIDUAL, the command warns and succeeds, the rest is reconstructed."""
    def patch(d, man):
        a = _img(d, "left_x_p2_s1.png")
        a[20:32, 40:52] = 200
        _put(d, "left_x_p2_s1.png", a)

    d = _variant(clean_set, tmp_path / "set", patch)
    out = tmp_path / "ev"
    r = _run(["evaluate", str(d), "--setup", str(noisy_setup_file), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    assert "pmdsim: warning: left:" in r.output and "FIT_RESIDUAL" in r.output
    with h5py.File(out / "evaluation.h5") as f:
        fl = f["left"]["consistency_flags"][()]
        files = json.loads(f["left"].attrs["consistency_images"])
        worst = f["left"]["worst_image"][()]
    flagged = (fl & PhaseFlag.FIT_RESIDUAL) != 0
    inside = np.zeros_like(flagged)
    inside[20:32, 40:52] = True
    assert not flagged[~inside].any()
    # The patch is detectable wherever it changes the sample by more than the noise allows.
    assert flagged[inside].mean() > 0.8
    assert {files[i] for i in np.unique(worst[flagged])} == {"left_x_p2_s0.png|left_x_p2_s1.png|left_x_p2_s2.png|"
                                                             "left_x_p2_s3.png"}


# ----------------------------------------------------------------------------- synthetic truths
def _synthetic(rng, sigma, h=160, w=200, n=5, ext=(100.0, 80.0), px=(120.0, 12.0, 1.5), py=(90.0, 9.0, 1.5),
               a=120.0, b=100.0, mirror_x=False):
    v, u = np.mgrid[0:h, 0:w].astype(float)
    x = 5 + u * (ext[0] - 10) / (w - 1)
    y = 5 + v * (ext[1] - 10) / (h - 1)
    xs = (ext[0] - x) if mirror_x else x

    def stacks(c, periods):
        return [np.stack([a + b * np.cos(2 * np.pi * c / p - 2 * np.pi * k / n) + rng.normal(0, sigma, c.shape)
                          for k in range(n)]) for p in periods]

    sx, sy = stacks(xs, px), stacks(y, py)
    dec = decode_screen_coordinates(sx, px, sy, py, ext, 255.0, sigma)
    return sx, sy, dec, np.stack([x, y], axis=-1)


@pytest.mark.parametrize("alpha", [1e-2, 1e-3])
def test_false_alarm_rates_match_chi2_and_normal(alpha):
    """Gaussian noise of known σ, N = 5: FIT_RESIDUAL per stack ~ Binomial(α) (RSS/σ² ~ χ²(2));
    PERIOD_MISMATCH per period pair ~ Binomial(α) (difference/σ ~ N(0, 1))."""
    rng = np.random.default_rng(7)
    sigma = 2.0
    px, py = (120.0, 12.0, 1.5), (90.0, 9.0, 1.5)
    sx, sy, dec, _ = _synthetic(rng, sigma, px=px, py=py)
    cons = check_consistency(sx, px, sy, py, dec, (100.0, 80.0), sigma, false_alarm=alpha, defect_fraction=1.0)
    n_px = cons.tested.sum()
    # Per pixel: 6 independent residual tests, 4 period tests (2 per direction).
    p_fit = 1 - (1 - alpha) ** 6
    p_mis = 1 - (1 - alpha) ** 4
    for flag, p in ((PhaseFlag.FIT_RESIDUAL, p_fit), (PhaseFlag.PERIOD_MISMATCH, p_mis)):
        k = np.count_nonzero(cons.flags & flag)
        lo, hi = stats.binom.interval(1 - 1e-4, n_px, p)
        assert lo <= k <= hi, (flag, k, n_px * p)
    # The noise the check estimated from the images agrees with the truth (σ² = 4).
    a, b = cons.noise_model
    assert abs(a + b * 120 - sigma ** 2) < 0.1 * sigma ** 2


def test_noise_estimate_protects_against_underestimated_noise():
    """The decoder is told σ = quantisation only, the images have σ = 2: the checks use the noise
    they see in the images, not the stated one, so the clean set is not flagged."""
    rng = np.random.default_rng(3)
    px, py = (120.0, 12.0, 1.5), (90.0, 9.0, 1.5)
    sx, sy, dec, _ = _synthetic(rng, 2.0, px=px, py=py)
    cons = check_consistency(sx, px, sy, py, dec, (100.0, 80.0), None)
    expected = cons.tested.sum() * 10 * 1e-6
    assert np.count_nonzero(cons.flags) <= max(2, 10 * expected)


def test_orientation_check_closed_form():
    rng = np.random.default_rng(5)
    px, py = (120.0, 12.0, 1.5), (90.0, 9.0, 1.5)
    sx, sy, dec, truth = _synthetic(rng, 1.0, px=px, py=py)
    cons = check_consistency(sx, px, sy, py, dec, (100.0, 80.0), 1.0, expected_xy_mm=truth)
    assert not np.any(cons.flags & PhaseFlag.GEOMETRY)
    sx, sy, dec, _ = _synthetic(rng, 1.0, px=px, py=py, mirror_x=True)
    cons = check_consistency(sx, px, sy, py, dec, (100.0, 80.0), 1.0, expected_xy_mm=truth)
    assert np.all(cons.flags[cons.tested] & PhaseFlag.GEOMETRY)
    assert cons.geometry_counts["orientation"] == cons.tested.sum()


def test_five_shifts_name_the_dropped_frame(tmp_path, small_toml):
    """With N = 5 the residual has 2 degrees of freedom and points at the bad frame: the error
    names its file."""
    setup = tmp_path / "n5.toml"
    t = replace_exactly(small_toml, "n_shifts = 4", "n_shifts = 5", 1)
    setup.write_text(replace_exactly(t, "noise_std = 0.0", f"noise_std = {NOISE}", 1))
    d = tmp_path / "set"
    r = _run(["simulate", "--setup", str(setup), "--out", str(d), "--quiet"])
    assert r.exit_code == 0, r.output
    _put(d, "left_y_p2_s3.png", np.zeros_like(_img(d, "left_y_p2_s3.png")))
    r = _run(["evaluate", str(d), "--setup", str(setup), "--out", str(tmp_path / "ev"), "--quiet"])
    assert r.exit_code == 1, r.output
    (err,) = [line for line in r.output.splitlines() if line.startswith("pmdsim: error:")]
    assert "image left_y_p2_s3.png deviates from its period's sinusoid" in err
