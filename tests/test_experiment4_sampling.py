"""Experiment 4 across ``--downsample K`` (issue 20 item 4): a slope ripple above the coarser
sampling's Nyquist frequency aliases, and the integration turns the alias into heights.

docs/experiments.md ("Experiment 4 at full resolution (K = 1)") explains the heights' change with K
by this mechanism; here it is checked on synthetic registrations against the closed form of the
trapezoidal rule: a slope g(x) = a·sin(2πx/λ) sampled at step Δ and integrated from the seed
(x = 0, height 0) gives the heights

    z_n = (Δ·a/2)·cot(ω/2)·(1 − cos ωn),  ω = 2πΔ/λ,

whatever the aliasing (cot has period π: the sampled ripple is the alias's) — so the height
ripple's peak-to-valley is a·Δ·|cot(ω/2)|, small where λ is resolved (Δ ≪ λ) and large where
ω is near a multiple of 2π (the alias's wavelength long).
"""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation.reconstruction import reconstruct

A_RAD = 10e-6       # slope ripple amplitude, 10 µrad
STEP_MM = 0.08      # the fine sampling step on the sample (≈ a Table 1 pixel)
# Fine step / wavelength 0.2625: resolved; at a 4-times coarser step 1.05 cycles per sample,
# i.e. an alias of 0.05 cycles per sample (20 samples long).
LAMBDA_MM = STEP_MM / 0.2625
O_MM = np.array([3.0, -2.0, 500.0])  # the camera's pinhole above the plane z = 0
SCREEN_Z_MM = 300.0


def _registration(step: int):
    """Pixels on a regular grid of the plane z = 0 (every ``step``-th of the fine grid), the
    screen points a surface with normals tilted by g(x) = a·sin(2π(x − x_seed)/λ) reflects them
    to (the screen: the plane z = 300 mm). Returns o, d, q, valid, the seed pixel, x (mm)."""
    nu, nv = 321, 9
    x = (np.arange(nu)[::step] - 160) * STEP_MM
    y = (np.arange(nv)[::step] - 4) * STEP_MM
    X, Y = np.meshgrid(x, y)
    p = np.stack([X, Y, np.zeros_like(X)], axis=-1)
    g = A_RAD * np.sin(2 * np.pi * X / LAMBDA_MM)
    n = np.stack([-g, np.zeros_like(g), np.ones_like(g)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    v = p - O_MM
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    r = v - 2 * np.sum(v * n, axis=-1, keepdims=True) * n
    q = p + r * (SCREEN_Z_MM / r[..., 2:3])
    seed = (len(y) // 2, len(x) // 2)
    assert X[seed] == 0.0
    return O_MM, p - O_MM, q, np.ones(X.shape, bool), seed, x


def _closed_form(x_mm, delta_mm):
    omega = 2 * np.pi * delta_mm / LAMBDA_MM
    n = np.rint(x_mm / delta_mm)
    return 0.5 * delta_mm * A_RAD / np.tan(omega / 2) * (1 - np.cos(omega * n))


@pytest.mark.parametrize("method", ["stepwise", "least_squares"])
def test_a_slope_ripple_sampled_coarser_integrates_to_the_aliased_heights(method):
    pv = {}
    for step in (1, 4):
        o, d, q, valid, seed, x = _registration(step)
        rec = reconstruct(o, d, q, valid, method=method, seed_pixel=seed, seed_height_mm=0.0)
        assert rec.reconstructed.all()
        want = _closed_form(x, step * STEP_MM)
        got = rec.height_mm  # every row alike (the ripple varies along x only)
        # The integration of the sampled slopes is exact (no bias at any step): ≤ 1 % of the
        # ripple's peak-to-valley (second order: the points slide along their rays by ≈ nm).
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), rtol=0,
                                   atol=0.01 * np.ptp(want))
        pv[step] = np.ptp(got)
    # Resolved (fine): a·Δ·cot(π·0.2625) = 0.74 nm; 4× coarser: a·4Δ·cot(π·1.05) = 20.2 nm —
    # the same slope error (RMS a/√2 at both steps) gives 27× the height ripple.
    assert pv[1] * 1e6 == pytest.approx(A_RAD * STEP_MM / np.tan(np.pi * 0.2625) * 1e6, rel=0.01)
    assert pv[4] * 1e6 == pytest.approx(A_RAD * 4 * STEP_MM / np.tan(np.pi * 1.05) * 1e6, rel=0.01)
    assert pv[4] / pv[1] > 20


def test_plane_removed_rms_of_a_tilted_checkerboard_is_the_checkerboard():
    """results.json's ``rms_plane_removed_um``: a tilt and an offset (any) plus a ±δ checkerboard
    on an even grid (orthogonal to every plane over it: each of 1, x, y sums to 0 against it)
    leaves exactly δ; NaN pixels are ignored."""
    from pmdsim.studies.experiment4 import _plane_removed_rms_um

    v, u = np.mgrid[0:40, 0:60].astype(float)
    p = np.stack([0.1 * u + 3.0, 0.13 * v - 2.0, np.zeros_like(u)], axis=-1)
    delta_mm = 2e-6
    err = 1e-3 * (0.7 * p[..., 0] - 0.4 * p[..., 1] + 5.0) + delta_mm * (-1.0) ** (u + v)
    assert _plane_removed_rms_um(p, err) == pytest.approx(delta_mm * 1e3, rel=1e-6)
    err[:2, :] = np.nan  # two full rows out: the rest is still an even grid
    assert _plane_removed_rms_um(p, err) == pytest.approx(delta_mm * 1e3, rel=1e-6)
