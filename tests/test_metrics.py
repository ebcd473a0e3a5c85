"""Table 2/3 figures of merit: the normal-equation plane fit against scipy's least squares.

References: ``scipy.linalg.lstsq`` (SVD) of the (n, 3) design matrix — the computation the
normal-equation sums replaced — and a closed form (an exact plane has zero deviation and its
known tilt).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from pmdsim.evaluation.metrics import surface_error_metrics


def _lstsq_reference(x, y, e):
    m = np.isfinite(x) & np.isfinite(y) & np.isfinite(e)
    x, y, e = x[m], y[m], e[m]
    A = np.column_stack([x, y, np.ones_like(x)])
    (a, b, c), *_ = scipy.linalg.lstsq(A, e, lapack_driver="gelsd")
    resid = e - A @ np.array([a, b, c])
    return a, b, np.abs(resid).max(), np.linalg.cond(A.T @ A)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plane_fit_equals_lstsq(seed):
    rng = np.random.default_rng(seed)
    n = 20_000
    # A camera footprint: an off-centre, rotated and sheared patch (correlated x, y), mm.
    u, v = rng.uniform(-60, 60, n), rng.uniform(-40, 40, n)
    x = 120.0 + 0.9 * u + 0.3 * v
    y = -75.0 + 0.2 * u + 1.1 * v
    e = 1e-3 * (0.4 * x - 0.25 * y + 3.0) + 1e-4 * rng.normal(size=n) + 2e-6 * (x - 120) ** 2
    e[rng.random(n) < 0.05] = np.nan
    x[rng.random(n) < 0.01] = np.nan
    m = surface_error_metrics(x, y, e)
    a, b, max_dev, cond = _lstsq_reference(x, y, e)
    # Normal equations lose accuracy as cond(AᵀA)·ε (Golub & Van Loan §5.3.7); a few hundred ulps of headroom.
    tol = 1e3 * np.finfo(float).eps * cond
    assert m["tilt_x_urad"] == pytest.approx(a * 1e6, rel=tol)
    assert m["tilt_y_urad"] == pytest.approx(b * 1e6, rel=tol)
    assert m["max_dev_plane_um"] == pytest.approx(max_dev * 1e3, rel=tol)
    assert m["tilt_urad"] == pytest.approx(np.arctan(np.hypot(a, b)) * 1e6, rel=tol)


def test_exact_plane_has_zero_deviation_and_its_tilt():
    y, x = np.mgrid[0:50, 0:80] * 0.5
    e = 2e-4 * x - 5e-5 * y + 0.01  # mm
    m = surface_error_metrics(x, y, e)
    assert m["tilt_x_urad"] == pytest.approx(200.0, rel=1e-12)
    assert m["tilt_y_urad"] == pytest.approx(-50.0, rel=1e-12)
    assert m["tilt_urad"] == pytest.approx(np.arctan(np.hypot(2e-4, 5e-5)) * 1e6, rel=1e-12)
    assert m["max_dev_plane_um"] < 1e-9
    assert m["max_height_diff_um"] == pytest.approx((e.max() - e.min()) * 1e3, rel=1e-12)


def test_collinear_points_refused():
    x = np.linspace(0, 1, 10)
    with pytest.raises(ValueError, match="collinear"):
        surface_error_metrics(x, 2 * x, x)
