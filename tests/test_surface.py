"""Spline surfaces (paper §2.3, eq. 8) against scipy's splines and closed forms."""

import numpy as np
import pytest
from scipy.interpolate import CubicSpline, RectBivariateSpline
from scipy.optimize import brentq

from pmdsim.geometry.surface import IntersectStatus, PlaneSurface, SplineSurface, cardinal_spline_coefficients


def _spline_1d(knots, values):
    """scipy's 1-D interpolant with the paper's end condition (2 points: the line)."""
    if len(knots) == 2:
        slope = (values[1] - values[0]) / (knots[1] - knots[0])
        class _Line:
            def __call__(self, x, nu=0):
                return values[0] + slope * (x - knots[0]) if nu == 0 else slope + 0 * x
        return _Line()
    return CubicSpline(knots, values, bc_type="not-a-knot")


def _two_step_scipy(gx, gy, z, xq, yq):
    """The paper's two-step scheme (eq. 8) with scipy: h, ∂h/∂x, ∂h/∂y at each query point."""
    out = []
    for x, y in zip(xq, yq):
        col = [_spline_1d(gy, z[:, i])(y) for i in range(len(gx))]  # s_{x_i}(y_q)
        s_yq = _spline_1d(gx, np.array(col))
        row = [_spline_1d(gx, z[j, :])(x) for j in range(len(gy))]  # s_{y_j}(x_q)
        s_xq = _spline_1d(gy, np.array(row))
        out.append((s_yq(x), s_yq(x, 1), s_xq(y, 1)))
    return np.array(out, dtype=float)


@pytest.mark.parametrize("nx,ny", [(2, 2), (3, 3), (2, 3), (4, 4), (5, 3), (7, 6), (9, 9), (40, 25)])
def test_two_step_scheme_matches_scipy(nx, ny):
    rng = np.random.default_rng(nx * 10 + ny)
    gx = np.cumsum(rng.uniform(20, 120, nx))
    gy = np.cumsum(rng.uniform(20, 80, ny))
    z = rng.normal(scale=3.0, size=(ny, nx))
    s = SplineSurface(gx, gy, z)
    xq = np.concatenate([rng.uniform(gx[0], gx[-1], 150), gx, [gx[0], gx[-1]]])
    yq = np.concatenate([rng.uniform(gy[0], gy[-1], 150), rng.uniform(gy[0], gy[-1], nx), [gy[0], gy[-1]]])
    ref = _two_step_scipy(gx, gy, z, xq, yq)
    np.testing.assert_allclose(s.height(xq, yq), ref[:, 0], atol=1e-10, rtol=0)
    np.testing.assert_allclose(s.gradient(xq, yq), ref[:, 1:], atol=1e-10, rtol=0)
    # Control points are interpolated.
    X, Y = np.meshgrid(gx, gy)
    np.testing.assert_allclose(s.height(X, Y), z, atol=1e-12)


def test_matches_fitpack_interpolating_spline():
    # FITPACK's interpolating bicubic spline (s=0) has the not-a-knot knot placement too.
    rng = np.random.default_rng(5)
    gx = np.linspace(0, 400, 8)
    gy = np.sort(rng.uniform(0, 300, 6))
    z = rng.normal(size=(6, 8))
    ref = RectBivariateSpline(gy, gx, z, kx=3, ky=3, s=0)
    s = SplineSurface(gx, gy, z)
    xq, yq = rng.uniform(0, 400, 300), rng.uniform(gy[0], gy[-1], 300)
    np.testing.assert_allclose(s.height(xq, yq), ref.ev(yq, xq), atol=1e-10)
    np.testing.assert_allclose(s.gradient(xq, yq)[:, 0], ref.ev(yq, xq, dy=1), atol=1e-10)
    np.testing.assert_allclose(s.gradient(xq, yq)[:, 1], ref.ev(yq, xq, dx=1), atol=1e-10)


def test_paper_screen_is_the_closed_form_bulge():
    dh = 3.0
    s = SplineSurface.from_bulge([0, 354, 708], [0, 199, 398], dh)
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 708, 1000), rng.uniform(0, 398, 1000)
    u, v = (x - 354) / 354, (y - 199) / 199
    np.testing.assert_allclose(s.height(x, y), dh * (1 - u**2) * (1 - v**2), atol=1e-12)
    gx = dh * (-2 * u / 354) * (1 - v**2)
    gy = dh * (1 - u**2) * (-2 * v / 199)
    np.testing.assert_allclose(s.gradient(x, y), np.stack([gx, gy], -1), atol=1e-14)


def test_cardinal_basis_partition_of_unity_and_reproduces_cubics():
    knots = np.array([0.0, 1.0, 2.5, 3.0, 5.0, 7.5])
    c = cardinal_spline_coefficients(knots)
    # Σ_j w_j = 1 and not-a-knot splines reproduce cubic polynomials exactly.
    f = lambda x: 0.3 - 1.2 * x + 0.5 * x**2 - 0.07 * x**3
    s = SplineSurface(knots, [0.0, 1.0], np.vstack([f(knots), f(knots)]))
    xq = np.linspace(0, 7.5, 101)
    np.testing.assert_allclose(s.height(xq, 0.5), f(xq), atol=1e-12)
    np.testing.assert_allclose(c[:, 0, :].sum(axis=1), 1.0)


def test_invalid_grids_rejected():
    with pytest.raises(ValueError, match="strictly increasing"):
        SplineSurface([0, 1, 1], [0, 1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="shape"):
        SplineSurface([0, 1, 2], [0, 1], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        SplineSurface([0, 1], [0, 1], [[0, np.nan], [0, 0]])
    with pytest.raises(ValueError, match="at least 2"):
        SplineSurface([0], [0, 1], np.zeros((2, 1)))


# ----------------------------------------------------------------------------- intersection
def _paraboloid_surface(a, b, c, xr=(-100.0, 100.0), yr=(-80.0, 80.0)):
    """z = c + a x² + b y²: exactly representable on a 3×3 grid (parabola per grid line)."""
    gx = np.array([xr[0], 0.5 * (xr[0] + xr[1]), xr[1]])
    gy = np.array([yr[0], 0.5 * (yr[0] + yr[1]), yr[1]])
    X, Y = np.meshgrid(gx, gy)
    return SplineSurface(gx, gy, c + a * X**2 + b * Y**2)


def _ray_paraboloid(o, d, a, b, c):
    """Smallest positive root of (o_z + t d_z) = c + a (o_x + t d_x)² + b (o_y + t d_y)²."""
    A = a * d[..., 0] ** 2 + b * d[..., 1] ** 2
    B = 2 * a * o[..., 0] * d[..., 0] + 2 * b * o[..., 1] * d[..., 1] - d[..., 2]
    C = a * o[..., 0] ** 2 + b * o[..., 1] ** 2 + c - o[..., 2]
    disc = np.sqrt(B**2 - 4 * A * C)
    # Numerically stable roots.
    q = -0.5 * (B + np.sign(B) * disc)
    t1, t2 = q / A, C / q
    t = np.where((t1 > 0) & ((t1 < t2) | (t2 <= 0)), t1, t2)
    return t


def test_intersection_with_paraboloid_closed_form():
    a, b, c = 2e-4, -1.5e-4, 0.7
    s = _paraboloid_surface(a, b, c)
    rng = np.random.default_rng(3)
    o = np.array([10.0, 250.0, -300.0])
    target = np.column_stack([rng.uniform(-90, 90, 2000), rng.uniform(-70, 70, 2000), np.zeros(2000)])
    d = target - o
    t, p, st = s.intersect(o, d)
    assert (st == IntersectStatus.HIT).all()
    t_ref = _ray_paraboloid(o, d, a, b, c)
    np.testing.assert_allclose(p, o + t_ref[:, None] * d, atol=1e-9, rtol=0)
    np.testing.assert_allclose(p[:, 2], c + a * p[:, 0] ** 2 + b * p[:, 1] ** 2, atol=1e-11)


def test_fallback_where_fixed_point_diverges():
    # Steep slopes along the ray: the fixed point of eqs. 13–16 has a contraction factor > 1,
    # so the safeguarded Newton fallback must find the root; reference: brentq.
    # Here q = |h_x·d_x/d_z| ≈ 1.7 at the first hit (x ≈ −21.5 mm).
    a, b, c = 0.002, 0.0, 0.0
    s = _paraboloid_surface(a, b, c, xr=(-50.0, 50.0), yr=(-50.0, 50.0))
    o = np.array([-60.0, 0.0, -1.0])
    d = np.array([1.0, 0.0, 0.05])  # nearly grazing along x; enters and leaves the bowl
    t, p, st = s.intersect(o, d)
    assert st == IntersectStatus.HIT
    f = lambda tt: o[2] + tt * d[2] - (c + a * (o[0] + tt * d[0]) ** 2)
    # First root along the ray.
    ts = np.linspace(0, 200, 20001)
    k = np.argmax(np.sign(f(ts[1:])) != np.sign(f(ts[0])))
    t_ref = brentq(f, ts[k], ts[k + 1], xtol=1e-15)
    assert abs(t - t_ref) * np.linalg.norm(d) < 1e-9


def test_intersection_status_codes():
    s = _paraboloid_surface(1e-4, 1e-4, 0.0)
    o = np.array([0.0, 0.0, -100.0])
    # Outside the grid bounds, parallel to the plane, pointing away.
    t, p, st = s.intersect(np.array([o, o, o, o]),
                           np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
    assert st.tolist() == [IntersectStatus.HIT, IntersectStatus.OUTSIDE, IntersectStatus.PARALLEL,
                           IntersectStatus.PARALLEL]
    assert np.isnan(p[2]).all()


def test_plane_fast_path_equals_spline_plane():
    plane = PlaneSurface((0.0, 400.0), (0.0, 400.0))
    flat = SplineSurface([0.0, 200.0, 400.0], [0.0, 400.0], np.zeros((2, 3)))
    tilted = SplineSurface([0.0, 400.0], [0.0, 400.0], [[0.0, 0.0], [1e-12, 0.0]])  # not planar
    rng = np.random.default_rng(4)
    o = np.array([200.0, 500.0, -300.0])
    d = np.column_stack([rng.uniform(-1, 1, 100) * 0.3, rng.uniform(-1.2, -0.5, 100), np.ones(100)])
    t1, p1, s1 = plane.intersect(o, d)
    t2, p2, s2 = flat.intersect(o, d)
    t3, p3, s3 = tilted.intersect(o, d)
    assert flat.is_planar and not tilted.is_planar
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_allclose(p1, p2, atol=0)
    np.testing.assert_allclose(p1, p3, atol=1e-9)
    np.testing.assert_allclose(p1[:, 2], 0.0)


def test_second_derivatives_match_fitpack():
    """The intersection carries the gradient to the final point with the second derivatives."""
    from pmdsim.geometry.surface import eval2_kernel

    rng = np.random.default_rng(9)
    gx = np.linspace(0, 300, 6)
    gy = np.linspace(0, 200, 5)
    z = rng.normal(size=(5, 6))
    ref = RectBivariateSpline(gy, gx, z, kx=3, ky=3, s=0)
    k = SplineSurface(gx, gy, z).kernel
    for x, y in rng.uniform([0, 0], [300, 200], size=(50, 2)):
        h, hx, hy, hxx, hxy, hyy = eval2_kernel(k.kind, k.grid_x, k.grid_y, k.coef, x, y)
        np.testing.assert_allclose([h, hx, hy], [ref.ev(y, x), ref.ev(y, x, dy=1), ref.ev(y, x, dx=1)], atol=1e-10)
        np.testing.assert_allclose([hxx, hxy, hyy], [ref.ev(y, x, dy=2), ref.ev(y, x, dx=1, dy=1), ref.ev(y, x, dx=2)],
                                   atol=1e-10)


def test_derivative_bounds_hold():
    """KernelSurface.dmax bounds the second and third partial derivatives (Newton error bounds)."""
    from pmdsim.geometry.surface import eval2_kernel

    rng = np.random.default_rng(11)
    gx = np.array([0.0, 40.0, 100.0, 130.0, 200.0, 300.0])
    gy = np.linspace(0, 200, 5)
    k = SplineSurface(gx, gy, rng.normal(size=(5, 6))).kernel
    pts = rng.uniform([0, 0], [300, 200], size=(3000, 2))
    e = np.array([eval2_kernel(k.kind, k.grid_x, k.grid_y, k.coef, x, y) for x, y in pts])
    second = np.abs(e[:, 3:]).max()
    assert second <= k.dmax[0] and second > 0.02 * k.dmax[0]  # a bound, not absurdly loose
    # Third derivatives by central differences of the (piecewise quadratic) second derivatives,
    # away from the patch borders.
    d = 1e-3
    inner = [(x, y) for x, y in pts if np.min(np.abs(x - gx)) > 2 * d and np.min(np.abs(y - gy)) > 2 * d]
    third = 0.0
    for x, y in inner[:500]:
        ex = [eval2_kernel(k.kind, k.grid_x, k.grid_y, k.coef, x + s * d, y) for s in (-1, 1)]
        ey = [eval2_kernel(k.kind, k.grid_x, k.grid_y, k.coef, x, y + s * d) for s in (-1, 1)]
        third = max(third, *(abs(ex[1][i] - ex[0][i]) / (2 * d) for i in (3, 4, 5)),
                    *(abs(ey[1][i] - ey[0][i]) / (2 * d) for i in (3, 4, 5)))
    assert third <= k.dmax[1]
    assert PlaneSurface((0.0, 1.0), (0.0, 1.0)).kernel.dmax.tolist() == [0.0, 0.0]


def test_warm_started_newton_fast_path():
    """intersect_kernel: one Newton step from a warm start (paper's eq. 13 accelerated) when
    it provably converges to the tolerance; otherwise _NEEDS_SOLVE and intersect_solve."""
    from pmdsim.geometry.surface import _NEEDS_SOLVE, FIXED_POINT_MAX_ITER, intersect_kernel, intersect_solve

    a, b, c = 2e-4, -1.5e-4, 0.7
    s = _paraboloid_surface(a, b, c)
    k = s.kernel
    rng = np.random.default_rng(5)
    o = np.array([10.0, 250.0, -300.0])
    target = np.column_stack([rng.uniform(-90, 90, 300), rng.uniform(-70, 70, 300), np.zeros(300)])
    d = target - o
    p_ref = o + _ray_paraboloid(o, d, a, b, c)[:, None] * d
    tol = 1e-11
    n_fast = 0
    for dz0 in (1e-7, 1e-5, 1e-3, 0.3):
        for i in range(len(d)):
            args = (k.kind, k.grid_x, k.grid_y, k.coef)
            ray = (*o, *d[i])
            for gradient in (True, False):
                t, x, y, z, hx, hy, st = intersect_kernel(*args, k.dmax, *ray, tol, p_ref[i, 2] + dz0, gradient)
                fast = st != _NEEDS_SOLVE
                if not fast:
                    t, x, y, z, hx, hy, st = intersect_solve(*args, k.z_min, k.z_max, k.dmax, *ray, tol,
                                                             FIXED_POINT_MAX_ITER, z)
                n_fast += fast
                assert st == IntersectStatus.HIT
                np.testing.assert_allclose([x, y, z], p_ref[i], atol=1e-9, rtol=0)
                assert abs(z - (c + a * x * x + b * y * y)) <= 2 * tol
                if gradient or not fast:
                    np.testing.assert_allclose([hx, hy], [2 * a * x, 2 * b * y], atol=1e-11, rtol=0)
                else:
                    assert np.isnan(hx) and np.isnan(hy)
    # Close starts take the one-step fast path, a 0.3 mm error does not.
    assert n_fast >= 2 * 2 * len(d)
