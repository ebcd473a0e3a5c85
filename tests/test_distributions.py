"""pmdsim.evaluation.distributions against scipy (test-only), closed forms and exact arithmetic;
and that the evaluate path imports neither scipy.stats nor dask (issue 25, item 1)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from pmdsim.evaluation import distributions as dist

SRC = str(Path(__file__).resolve().parents[1] / "src")

#: Relative tolerance against scipy: scipy's own chi2.cdf/sf are off by up to 1.6e-13 at
#: ν ≈ 200 (against a 60-digit series, docs/benchmarks.md), ours by < 1e-15 there.
RTOL_SCIPY = 1e-12
_TAILS = np.logspace(-12, math.log10(0.49), 25)
PROBS = np.concatenate([_TAILS, [0.5, 0.9], 1.0 - _TAILS])


def _rel(a, b):
    return abs(a - b) / abs(b) if b != 0 else abs(a)


def test_chi2_quantiles_match_scipy():
    stats = pytest.importorskip("scipy.stats")
    dofs = list(range(1, 16)) + list(range(20, 201, 20)) + [199]
    worst = 0.0
    for nu in dofs:
        ppf = stats.chi2.ppf(PROBS, nu)
        isf = stats.chi2.isf(PROBS, nu)
        for p, ref_ppf, ref_isf in zip(PROBS, ppf, isf):
            worst = max(worst, _rel(dist.chi2_ppf(p, nu), ref_ppf), _rel(dist.chi2_isf(p, nu), ref_isf))
    assert worst <= RTOL_SCIPY, worst


def test_chi2_cdf_sf_match_scipy():
    stats = pytest.importorskip("scipy.stats")
    worst = 0.0
    for nu in list(range(1, 31)) + list(range(35, 201, 15)) + [200]:
        xs = stats.chi2.ppf(PROBS, nu)
        cdf, sf = stats.chi2.cdf(xs, nu), stats.chi2.sf(xs, nu)
        for x, c, s in zip(xs, cdf, sf):
            worst = max(worst, _rel(dist.chi2_cdf(x, nu), c), _rel(dist.chi2_sf(x, nu), s))
    assert worst <= RTOL_SCIPY, worst


def test_chi2_closed_forms():
    # ν = 1: P(χ² > x) = erfc(√(x/2)); ν = 2: e^(−x/2); ν = 3: erfc(√(x/2)) + √(2x/π)·e^(−x/2).
    for x in (1e-8, 0.3, 2.7, 10.0, 60.0, 300.0):
        assert _rel(dist.chi2_sf(x, 1), math.erfc(math.sqrt(x / 2))) <= 4e-16
        assert _rel(dist.chi2_sf(x, 2), math.exp(-x / 2)) <= 4e-16
        assert _rel(dist.chi2_sf(x, 3), math.erfc(math.sqrt(x / 2)) + math.sqrt(2 * x / math.pi) * math.exp(-x / 2)) <= 1e-15
        assert _rel(dist.chi2_cdf(x, 2), -math.expm1(-x / 2)) <= 1e-15
    # The quantile inverts the tail it was asked for, to the tail's precision.
    for nu in (1, 2, 5, 40, 200):
        for q in (1e-12, 1e-6, 0.05, 0.4):
            assert _rel(dist.chi2_sf(dist.chi2_isf(q, nu), nu), q) <= 1e-13
            assert _rel(dist.chi2_cdf(dist.chi2_ppf(q, nu), nu), q) <= 1e-13
    # ν = 2: x = −2 ln q exactly invertible.
    for q in (1e-12, 1e-3, 0.3):
        assert _rel(dist.chi2_isf(q, 2), -2.0 * math.log(q)) <= 1e-15
    assert dist.chi2_isf(0.0, 3) == math.inf and dist.chi2_isf(1.0, 3) == 0.0
    assert dist.chi2_ppf(0.0, 3) == 0.0 and dist.chi2_ppf(1.0, 3) == math.inf


def test_norm_isf_matches_scipy_and_erfc():
    stats = pytest.importorskip("scipy.stats")
    qs = np.concatenate([np.logspace(-300, -1, 40), [0.3, 0.5], 1.0 - _TAILS])
    ref = stats.norm.isf(qs)
    worst = max(_rel(dist.norm_isf(q), r) for q, r in zip(qs, ref) if r != 0)
    assert worst <= RTOL_SCIPY, worst
    assert dist.norm_isf(0.5) == 0.0
    for q in (1e-12, 5e-7, 0.025):  # P(Z > z) = erfc(z/√2)/2
        assert _rel(0.5 * math.erfc(dist.norm_isf(q) / math.sqrt(2.0)), q) <= 1e-14


@pytest.mark.parametrize("bad", [0, -1, 2.5])
def test_bad_arguments(bad):
    with pytest.raises(ValueError):
        dist.chi2_ppf(0.5, bad)
    with pytest.raises(ValueError):
        dist.chi2_isf(1.5, 3)
    with pytest.raises(ValueError):
        dist.nnls(np.ones((3, 7)), np.ones(3))
    with pytest.raises(ValueError):
        dist.nnls(np.ones((3, 2)), np.ones(4))


def _exact_lstsq(a, b):
    """The least-squares solution of a full-column-rank (m, n) problem in exact rationals."""
    cols = [[Fraction(float(v)) for v in a[:, j]] for j in range(a.shape[1])]
    bq = [Fraction(float(v)) for v in b]
    return dist._solve_exact(cols, bq)


def test_nnls_matches_scipy_on_random_problems():
    opt = pytest.importorskip("scipy.optimize")
    rng = np.random.default_rng(25)
    worst = 0.0
    for trial in range(400):
        n = int(rng.integers(1, 4))
        m = int(rng.integers(n + 2, 13))
        a = rng.normal(size=(m, n))
        if trial % 2:  # the noise model's design: [1, A] with A the offsets (grey levels)
            a = np.column_stack([np.ones(m), rng.uniform(10.0, 250.0, m)])[:, :n] if n <= 2 else a
        b = rng.normal(size=m) * 10.0 ** rng.integers(-3, 4)
        x, rnorm = dist.nnls(a, b)
        ref, ref_rnorm = opt.nnls(a, b)
        # Backward-stable solvers agree to ε·cond(A)·‖A⁺‖·‖b‖ (scipy is the less accurate here:
        # with cancellation in Aᵀb it is off by up to 1.5e-13 of x, ours is exact).
        sv = np.linalg.svd(a, compute_uv=False)
        worst = max(worst, np.abs(x - ref).max() / (sv[0] / sv[-1] ** 2 * np.linalg.norm(b)))
        assert np.all(x >= 0.0)
        assert rnorm <= ref_rnorm * (1 + 1e-12) + 1e-300
    assert worst <= 1e-14, worst


def test_nnls_is_the_correctly_rounded_kkt_solution():
    # Feasible unconstrained solution: nnls returns the exact least-squares solution, rounded once.
    rng = np.random.default_rng(3)
    centres = np.sort(rng.uniform(20.0, 220.0, 12))
    a = np.column_stack([np.ones(12), centres])
    b = 0.4 + 0.012 * centres + rng.normal(scale=0.01, size=12)
    x, _ = dist.nnls(a, b)
    exact = _exact_lstsq(a, b)
    assert [float(v) for v in exact] == list(x)
    # A negative slope is clamped to 0: then the intercept is the mean of b (the 1-column solution).
    b2 = 3.0 - 0.01 * centres
    x2, _ = dist.nnls(a, b2)
    assert x2[1] == 0.0 and x2[0] == float(sum(Fraction(float(v)) for v in b2) / 12)
    # All-negative right-hand side with positive design: x = 0.
    x3, r3 = dist.nnls(np.abs(a), -np.ones(12))
    assert np.array_equal(x3, [0.0, 0.0]) and r3 == pytest.approx(math.sqrt(12.0), rel=1e-15)


_FRESH = """
import sys
import numpy as np
import pmdsim.cli, pmdsim.studies.jobs, pmdsim.evaluation.consistency as c
rng = np.random.default_rng(0)
a = rng.uniform(20, 200, 3000)
lines = c._noise_model([(a, (0.5 + 0.01 * a) * rng.chisquare(1, a.size), 1)])
assert lines is not None and lines.shape == (1, 2), lines
c.norm_isf(1e-6), c.chi2_isf(1e-6, 1)
print(sorted(m for m in sys.modules if m.startswith(("scipy.stats", "scipy.optimize", "dask"))))
"""


def test_evaluate_path_imports_no_scipy_stats_or_dask():
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-c", _FRESH], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", out.stdout
