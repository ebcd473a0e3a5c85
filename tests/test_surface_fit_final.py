"""The joint surface fit's parallel passes (issue 25, item 1): the σ sandwich and the residual maps
of ``surface_fit_summary`` against numpy on the explicit design, and the weighted sums and the
last pass the same bits on one numba thread as on two."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pmdsim.evaluation.surface_fit import surface_fit_summary
from pmdsim.geometry.kernel_args import numba_threads
from test_surface_fit_summary import _recs


def _design(x, y):
    """The (2M, 5) design of the slope rows [2x, y, 0, 1, 0] and [0, x, 2y, 0, 1]."""
    z, one = np.zeros_like(x), np.ones_like(x)
    return np.concatenate([np.stack([2 * x, y, z, one, z], -1), np.stack([z, x, 2 * y, z, one], -1)])


def test_summary_sigma_and_residual_maps_match_numpy():
    """σ of the coefficients and focal lengths = the sandwich (AᵀWA)⁻¹AᵀW²Σ²A(AᵀWA)⁻¹ by numpy
    matmul at the fit's coefficients and scale (1e-9 relative); the residual maps = g − A·c (1e-15
    rad), NaN off the fitted pixels."""
    recs, sig = _recs()
    fit, extras = surface_fit_summary(recs, -900.0, sig)
    xs, ys, gs, ss = [], [], [], []
    for r, s, ex in zip(recs, sig, extras):
        g = ex["slopes"]
        ok = r.reconstructed & np.isfinite(g).all(-1)
        xs.append(r.p_sample_mm[..., 0][ok]), ys.append(r.p_sample_mm[..., 1][ok]), gs.append(g[ok]), ss.append(s[ok])
        a, b, c, d, e = fit.coefficients
        x, y = r.p_sample_mm[..., 0], r.p_sample_mm[..., 1]
        ref = np.stack([g[..., 0] - (2 * a * x + b * y + d), g[..., 1] - (b * x + 2 * c * y + e)], -1)
        np.testing.assert_allclose(ex["residual_slopes"][ok], ref[ok], rtol=0, atol=1e-15)
        assert np.isnan(ex["residual_slopes"][~ok]).all()
    x, y, g, s = np.concatenate(xs), np.concatenate(ys), np.concatenate(gs), np.concatenate(ss)
    xc, yc = x.mean(), y.mean()
    A = _design(x - xc, y - yc)
    r = np.concatenate([g[:, 0], g[:, 1]]) - _design(x, y) @ np.array(fit.coefficients)
    u = r / fit.scale
    w = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
    assert fit.scale > 0 and (w == 0).sum() > 10  # the outliers are weighted out
    N = A.T @ (w[:, None] * A)
    B = A.T @ (((w * np.concatenate([s[:, 0], s[:, 1]])) ** 2)[:, None] * A)
    cov = np.linalg.solve(N, np.linalg.solve(N, B).T)
    T = np.eye(5)
    T[3, :3] = (-2 * xc, -yc, 0.0)
    T[4, :3] = (0.0, -xc, -2 * yc)
    std = np.sqrt(np.diag(T @ cov @ T.T))
    np.testing.assert_allclose(fit.coefficients_std, std, rtol=1e-9, atol=0)
    fx, fy = fit.focal_length_x_mm, fit.focal_length_y_mm
    a, c = fit.coefficients[0], fit.coefficients[2]
    np.testing.assert_allclose((fit.focal_length_x_std_mm, fit.focal_length_y_std_mm),
                               (abs(fx) * std[0] / abs(a), abs(fy) * std[2] / abs(c)), rtol=1e-9)


_CHILD = textwrap.dedent("""
    import json
    import numpy as np
    from pmdsim.evaluation.surface_fit_final import final_pass
    from pmdsim.evaluation.surface_fit_sums import weighted_sums
    from pmdsim.geometry.kernel_args import readonly
    import numba
    rng = np.random.default_rng(5)
    h, w = 320, 640  # above SERIAL_BELOW_PX pixels: the parallel path
    p = rng.uniform(-50, 50, (h, w, 3))
    g = rng.normal(0, 1e-3, (h, w, 2))
    sig = rng.uniform(1e-6, 2e-6, (h, w, 2))
    ok = rng.random((h, w)) > 0.1
    m = int(ok.sum())
    rows = np.empty((2, m))
    x, y, gx, gy = (readonly(np.ascontiguousarray(a[ok])) for a in (p[..., 0], p[..., 1], g[..., 0], g[..., 1]))
    coef = np.array([1e-5, -2e-6, 3e-5, 1e-4, -2e-4])
    s = weighted_sums(x, y, gx, gy, 0.5, -0.25, coef, 2e-3, True)
    sums = np.zeros(24)
    res, n = final_pass(p, g, sig, ok, 0, (0.5, -0.25), coef, 2e-3, (rows[0], rows[1]), sums)
    print(json.dumps({"threads": numba.get_num_threads(), "n": n, "sums": [v.hex() for v in s],
                      "final": [v.hex() for v in sums], "res": res.tobytes().hex(), "rows": rows.tobytes().hex()}))
""")


def test_sums_are_the_same_bits_on_one_and_two_threads():
    """The blocks' partial sums are added in block (row) order: the weighted sums, the sandwich
    sums and the residuals are the same bits on one numba thread (a subprocess with
    NUMBA_NUM_THREADS=1) as on two (this process)."""
    import contextlib
    import io

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one numba thread here: nothing to compare")
    with numba_threads(2):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            exec(compile(_CHILD, "<child>", "exec"), {})
    mine = json.loads(buf.getvalue().strip().splitlines()[-1])
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    one = json.loads(done.stdout.strip().splitlines()[-1])
    assert (one.pop("threads"), mine.pop("threads")) == (1, 2)
    assert one == mine
