"""Study metrics of the evaluation's height σ (issue 22, item 6) and the design study file.

References: the public API's σ (``pmdsim.simulate`` → ``decode`` → ``evaluate``, its
``Evaluation.uncertainty``) reduced with numpy, the decoder's closed-form σ scaling
σ_c = p/(2π)·√(2/N)·σ_I/B (B = amplitude·(2^b − 1) grey levels, σ_I = 1/√12 at fixed noise in
grey levels), the normal distribution's 2σ probability, and the setup parser (linked keys).
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

import pmdsim
from pmdsim.setup import load_setup, parse_setup
from pmdsim.studies.study import run_case
from pmdsim.studies.study_file import StudyError, load_study, parse_study
from pmdsim.studies.study_results import results_schema
from pmdsim.studies.study_uncertainty import EDGE_PERCENTILE, UNCERTAINTY_METRICS, coverage_k2

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
DESIGN = EXAMPLES / "study_height_sigma_design.toml"
BITS_SETUP = EXAMPLES / "setup_table1_camera_bits.toml"


def _small_study(params: list, downsample: int = 16):
    """A one-camera simulate+evaluate study of the Table 1 setup (+ an explicit camera bit depth),
    binned ``downsample`` × ``downsample``, recording every σ metric."""
    doc = {"format": "pmdsim-study", "setup": str(BITS_SETUP), "action": "simulate+evaluate",
           "downsample": downsample, "cameras": ["left"], "metrics": list(UNCERTAINTY_METRICS) + ["rms_um"],
           "parameters": params}
    return parse_study(doc, source="test")


def _metrics(study) -> list[dict]:
    out = []
    for c in study.iter_cases():
        rec = run_case(c, study.metrics)
        assert rec["status"] == "ok", rec.get("error")
        out.append({**c.params, **{k.split(".", 1)[1]: v for k, v in rec.items() if k.startswith("left.")}})
    return out


# ---------------------------------------------------------------------------- the study files
def test_every_example_parses():
    for p in sorted(EXAMPLES.glob("*.toml")):
        fmt = tomllib.loads(p.read_text(encoding="utf-8")).get("format")
        if fmt == "pmdsim-study":
            load_study(p)
        else:
            assert fmt == "pmdsim-setup", p
            load_setup(p)


def test_design_study_sweeps_shifts_linked_finest_periods_and_bit_depth():
    st = load_study(DESIGN)
    assert st.n_cases == 64
    assert set(UNCERTAINTY_METRICS) <= set(st.metrics)
    seen = set()
    for c in st.iter_cases():
        truth = parse_setup(tomllib.loads(c.truth_toml))
        seq = truth.patterns.sequence
        # the linked parameter sets the finest period of both directions, the coarser ones stay
        assert seq.periods_x_mm == (720.0, 48.0, c.params["finest_period_mm"])
        assert seq.periods_y_mm == (420.0, 28.0, c.params["finest_period_mm"])
        assert seq.n_shifts == c.params["n_shifts"]
        assert truth.imaging.bit_depth == c.params["camera_bit_depth"]
        assert truth.cameras["left"].camera.width_px == 1920 // 8
        seen.add((seq.n_shifts, seq.periods_x_mm[2], truth.imaging.bit_depth))
    assert len(seen) == 64
    f = results_schema(st).field("finest_period_mm")
    assert f.metadata[b"setup_key"] == b"patterns.periods_x_mm[2],patterns.periods_y_mm[2]"
    assert f.metadata[b"units"] == b"mm"
    assert results_schema(st).field("height_std_edge_um").metadata[b"units"] == b"um"
    assert results_schema(st).field("coverage_k2").metadata[b"units"] == b"1"


@pytest.mark.parametrize("param, key", [
    ({"path": ["patterns.periods_x_mm[2]", "patterns.periods_y_mm[2]"], "values": [1.0]}, "parameters[0].name"),
    ({"path": ["patterns.periods_x_mm[2]", "patterns.periods_x_mm"], "name": "p", "values": [1.0]},
     "parameters[0].path[1]"),
    ({"path": ["patterns.periods_x_mm[2]", "seed"], "name": "p", "values": [1.0]}, "parameters[0].path[1]"),
    ({"path": [], "name": "p", "values": [1.0]}, "parameters[0].path"),
    ({"path": ["patterns.periods_x_mm[2]", "patterns.periods_y_mm[7]"], "name": "p", "values": [1.0]},
     "parameters[0].values[0]"),
])
def test_bad_linked_keys_refused_naming_the_key(param, key):
    doc = {"format": "pmdsim-study", "action": "simulate+evaluate", "downsample": 8, "parameters": [param]}
    with pytest.raises(StudyError, match=re.escape(key)):
        parse_study(doc, source="s.toml")


def test_linked_key_may_not_repeat_another_parameters_key():
    doc = {"format": "pmdsim-study", "action": "simulate+evaluate", "downsample": 8, "parameters": [
        {"path": "patterns.periods_y_mm", "values": [[420.0, 28.0, 2.0]]},
        {"path": ["patterns.periods_x_mm[2]", "patterns.periods_y_mm[2]"], "name": "p", "values": [1.0]}]}
    with pytest.raises(StudyError, match=r"parameters\[1\]\.path 'patterns\.periods_y_mm\[2\]'.*parameters\[0\]"):
        parse_study(doc, source="s.toml")


def test_sigma_metrics_only_when_listed():
    doc = {"format": "pmdsim-study", "action": "simulate+evaluate", "downsample": 8,
           "parameters": [{"path": "screen.bulge_mm", "values": [0.0]}]}
    assert not set(UNCERTAINTY_METRICS) & set(parse_study(doc).metrics)


# ---------------------------------------------------------------------------- the metrics
def test_study_metrics_are_the_evaluations_sigma_statistics():
    """A study case's σ metrics equal numpy's statistics of the σ map that the public API's
    evaluation returns for the same images, seed pixel and seed height."""
    st = _small_study([{"path": "patterns.n_shifts", "values": [4]}])
    (m,) = _metrics(st)
    (case,) = st.cases()
    setup = parse_setup(tomllib.loads(case.truth_toml))
    meas = pmdsim.simulate(setup, "left")
    dec = pmdsim.decode(meas, setup, consistency=False)
    c = setup.cameras["left"].camera
    seed = (c.height_px // 2, c.width_px // 2)
    ev = pmdsim.evaluate(dec, setup, "left", seed_pixel=seed, seed_height_mm=float(meas.mapping.p_sample_mm[seed][2]))
    s = np.asarray(ev.uncertainty.height_std_um)
    rec = ev.reconstruction
    s = s[np.asarray(rec.reconstructed)]
    assert s.size > 0.9 * c.height_px * c.width_px
    np.testing.assert_allclose(m["height_std_edge_um"], np.percentile(s, EDGE_PERCENTILE), rtol=1e-12)
    np.testing.assert_allclose(m["height_std_rms_um"], np.sqrt(np.mean(s**2)), rtol=1e-12)
    np.testing.assert_allclose(m["height_std_max_um"], s.max(), rtol=1e-12)
    err_um = (np.asarray(rec.height_mm) - 0.0)[np.asarray(rec.reconstructed)] * 1e3  # the truth: the plane z = 0
    np.testing.assert_allclose(m["coverage_k2"], np.mean(np.abs(err_um) <= 2 * s), rtol=1e-12)
    assert 0.0 < m["height_std_edge_um"] < m["height_std_max_um"]


def test_sigma_scales_as_the_closed_form():
    """σ_height ∝ p/(√N·(2^b − 1)) at fixed noise in grey levels (the rounding): N = 4 → 16
    halves σ, p = 2 → 4 mm doubles it, b = 8 → 10 divides it by 1023/255. The estimator's
    random right-hand sides are the same in every case, so its sampling error cancels in the
    ratios; what remains is each pixel's measured modulation B (from the rounded images, relative
    error ≈ σ_I/B ≈ 0.3 % per pixel at 8 bits, averaging out) and the slightly different
    reconstructions the linearisation is taken at: 0.5 % allowed."""
    st = _small_study([{"path": "patterns.n_shifts", "values": [4, 16]},
                       {"path": ["patterns.periods_x_mm[2]", "patterns.periods_y_mm[2]"], "name": "p",
                        "values": [2.0, 4.0]},
                       {"path": "imaging.bit_depth", "values": [8, 10]}])
    rows = {(r["patterns.n_shifts"], r["p"], r["imaging.bit_depth"]): r for r in _metrics(st)}

    def law(n, p, b):
        return p / math.sqrt(n) / (2**b - 1)

    ref = rows[(4, 2.0, 8)]
    for key, r in rows.items():
        for m in ("height_std_edge_um", "height_std_rms_um"):
            ratio = r[m] / ref[m]
            assert ratio == pytest.approx(law(*key) / law(4, 2.0, 8), rel=5e-3), (key, m)


def test_coverage_k2_of_gaussian_errors():
    """Errors drawn with the stated σ: |e| ≤ 2σ with probability erf(√2) = 0.9545 (binomial
    standard error 0.0009 for 50 000 pixels; 5 of them allowed)."""
    rng = np.random.default_rng(7)
    s_um = rng.uniform(0.5, 3.0, size=(200, 250))
    e_mm = rng.normal(0.0, s_um) * 1e-3
    s_um[0, :10] = np.nan  # not reconstructed: not counted
    assert coverage_k2(s_um, e_mm) == pytest.approx(math.erf(math.sqrt(2.0)), abs=5 * 0.0009)
