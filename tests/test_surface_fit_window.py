"""The robust fit's medians from a window of its points (issue 25, item 1;
pmdsim.evaluation.surface_fit_window) against numpy: at coefficients near the window's, the
median and MAD of the 2M residuals and their two middle values are numpy's exactly (ties
included); farther away the window declines (None) rather than answer wrongly; and the fit
that uses windows equals, bit for bit, the fit without them."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation import surface_fit as sf
from pmdsim.evaluation import surface_fit_window as sw
from pmdsim.evaluation.surface_fit import fit_paraboloid_slopes


def _points(m, seed, quantise=False):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-150, 150, m)
    y = rng.uniform(-100, 100, m)
    a, b, c, d, e = 2e-6, -3e-7, 1.5e-6, 1e-3, -2e-3
    gx = 2 * a * x + b * y + d + rng.normal(0, 2e-5, m)
    gy = b * x + 2 * c * y + e + rng.normal(0, 2e-5, m)
    bad = rng.random(m) < 0.05
    gx[bad] += rng.normal(0, 1e-3, bad.sum())
    if quantise:
        gx = np.round(gx, 6)  # many equal residuals
    return x, y, gx, gy


def _numpy_medians(x, y, gx, gy, coef):
    """(median, lower, upper middle value) of the residuals and of their deviations, numpy."""
    r = np.concatenate([gx - (2 * coef[0] * x + coef[1] * y + coef[3]), gy - (coef[1] * x + 2 * coef[2] * y + coef[4])])
    n = r.size
    k1, k2 = (n - 1) // 2, n // 2
    srt = np.sort(r)
    med = np.median(r)
    dev = np.sort(np.abs(r - med))
    return (med, srt[k1], srt[k2]), (np.median(dev), dev[k1], dev[k2])


@pytest.mark.parametrize("quantise", [False, True])
def test_window_medians_are_numpys(quantise):
    x, y, gx, gy = _points(40_001, seed=4, quantise=quantise)
    reach = (2 * np.abs(x).max(), np.abs(y).max(), np.abs(x).max(), 2 * np.abs(y).max())
    g_max = max(np.abs(gx).max(), np.abs(gy).max())
    coef = np.array([2e-6, -3e-7, 1.5e-6, 1e-3, -2e-3])
    (med, m1, m2), (mad, d1, d2) = _numpy_medians(x, y, gx, gy, coef)
    w = 2e-7  # the window's reach in residual (rad)
    win = sw.take_window(x, y, gx, gy, coef, (m1 - 2 * w, m2 + 2 * w), (d1 - 2 * w, d2 + 2 * w), 8192, reach, g_max)
    assert win is not None and 0 < win.xs.size < x.size // 4
    rng = np.random.default_rng(1)
    answered = 0

    def drift(dc):
        return max(reach[0] * abs(dc[0]) + reach[1] * abs(dc[1]) + abs(dc[3]),
                   reach[2] * abs(dc[1]) + reach[3] * abs(dc[2]) + abs(dc[4]))

    for f in (0.0, 0.01, 0.1, 0.3, 0.45, 0.8, 1.5, 3.0, 10.0):  # moves of f·w at most
        for kind in ("any", "tilt"):  # a tilt moves the edge points, hardly the medians
            for _ in range(3):
                dc = rng.normal(0, 1, 5) if kind == "any" else np.array([0.0, rng.normal(), 0.0, 0.0, 0.0])
                dc *= f * w / drift(dc)
                got = win.median_and_mad(coef + dc)
                if f < 0.5:
                    assert got is not None  # within its reach the window answers
                if got is not None:
                    answered += 1
                    ref = _numpy_medians(x, y, gx, gy, coef + dc)
                    assert got == ref
                    # narrower brackets (the IRLS's Lipschitz ones): the same answer; brackets
                    # that miss a rank or are empty: the window's own brackets answer
                    (_, r1, r2), (_, e1, e2) = ref
                    for narrow in ((r1, r2, e1, e2), (r1 - 1e-9, r2 + 1e-9, e1 - 1e-9, e2 + 1e-9),
                                   (r2 + 1e-9, r2 + 2e-9, e1, e2), (r1, r2, e2 + 1e-9, e2 + 2e-9), (r2, r1, e2, e1)):
                        assert win.median_and_mad(coef + dc, narrow) == ref
    assert answered >= 20
    # far away: declines
    assert win.median_and_mad(coef + np.array([0, 0, 0, 1e-5, 0])) is None
    # a window holding more points than its capacity is not taken
    assert sw.take_window(x, y, gx, gy, coef, (m1 - 1e-3, m2 + 1e-3), (d1, d2), 100, reach, g_max) is None


def test_fit_with_windows_equals_the_fit_without(monkeypatch):
    """The IRLS takes its medians from windows for most iterations; the fit (coefficients, scale,
    residuals) is bit for bit the fit from full passes."""
    x, y, gx, gy = _points(300_000, seed=9)
    bx, by = x - 20, y + 10  # a bump: structured residuals, an IRLS of many iterations
    bump = 3e-4 * np.exp(-(bx**2 + by**2) / (2 * 40.0**2))
    gx, gy = gx - bx / 40.0**2 * bump, gy - by / 40.0**2 * bump
    p = np.stack([x, y, np.zeros_like(x)], -1)
    g = np.stack([gx, gy], -1)
    calls = {"window": 0, "all": 0}
    orig = sw.WindowedMedians.__call__

    def counted(self, *a):
        got = orig(self, *a)
        calls["all"] += 1
        calls["window"] += got is not None
        return got

    monkeypatch.setattr(sw.WindowedMedians, "__call__", counted)
    fit = fit_paraboloid_slopes(p, g, np.ones(x.size, bool), camera_z_mm=-500.0)
    assert calls["window"] >= 3 and calls["window"] >= calls["all"] // 2
    monkeypatch.setattr(sw.WindowedMedians, "__call__", lambda self, *a: None)
    ref = fit_paraboloid_slopes(p, g, np.ones(x.size, bool), camera_z_mm=-500.0)
    assert fit.coefficients == ref.coefficients and fit.scale == ref.scale
    assert np.array_equal(fit.residual_slopes, ref.residual_slopes)
