"""Ray tracing (paper §2.4) against closed forms: planar mirrors, paraboloids, the default FOV."""

import numpy as np
import pytest

from pmdsim.geometry.camera import Camera
from pmdsim.setup import default_setup
from pmdsim.simulation import trace_setup_camera
from pmdsim.geometry.surface import PlaneSurface, SplineSurface
from pmdsim.simulation.trace import Status, trace_camera
from pmdsim.geometry.transform import RigidTransform

# A small camera with the Table 1 field of view (focal length scaled with the sensor).
SMALL = Camera(192, 120, 440.0, 440.0, 96.0, 60.0, k1=-0.05, k2=0.01, p1=2e-4, p2=-1e-4)
T_WORLD_CAM = RigidTransform.from_origin_angles([-90.0, 295.0, -295.0], [45.0, 10.0, 10.0])
T_WORLD_SCREEN = RigidTransform.from_origin_angles([-354.0, -78.0, -400.0], [135.0, 0.0, 0.0])
SCREEN_PLANE = PlaneSurface((0.0, 708.0), (0.0, 398.0))


def _world_rays(camera, T_world_cam):
    d_cam, ok = camera.sensor_rays()
    assert ok.all()
    o = T_world_cam.translation
    d = T_world_cam.apply_vector(d_cam)
    return o, d


def _reflect(d, n):
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return d - 2 * np.sum(d * n, axis=-1, keepdims=True) * n


def _ray_plane(o, d, p0, n):
    t = np.sum((p0 - o) * n, axis=-1) / np.sum(d * n, axis=-1)
    return o + t[..., None] * d


def _ray_paraboloid_local(o, d, a, b, c):
    """First positive root of o_z + t d_z = c + a x(t)² + b y(t)² (frame of the paraboloid)."""
    A = a * d[..., 0] ** 2 + b * d[..., 1] ** 2
    B = 2 * a * o[..., 0] * d[..., 0] + 2 * b * o[..., 1] * d[..., 1] - d[..., 2]
    C = a * o[..., 0] ** 2 + b * o[..., 1] ** 2 + c - o[..., 2]
    disc = np.sqrt(B**2 - 4 * A * C)
    q = -0.5 * (B + np.where(B >= 0, 1.0, -1.0) * disc)
    t1, t2 = q / A, C / q
    t = np.where((t1 > 0) & ((t1 < t2) | (t2 <= 0)), t1, t2)
    return o + t[..., None] * d


def _screen_xy_plane(p_world, r_world):
    """Closed form: reflected ray ∩ planar screen, in screen coordinates."""
    n_screen = T_WORLD_SCREEN.rotation[:, 2]
    q_world = _ray_plane(p_world, r_world, T_WORLD_SCREEN.translation, n_screen)
    return T_WORLD_SCREEN.inv().apply(q_world)[..., :2]


def test_tilted_planar_mirror_closed_form():
    T_world_sample = RigidTransform.from_origin_angles([-210.0, -190.0, 3.0], [1.5, -2.0, 7.0])
    sample = PlaneSurface((0.0, 420.0), (0.0, 400.0))
    m = trace_camera(SMALL, T_WORLD_CAM, T_world_sample, sample, T_WORLD_SCREEN, SCREEN_PLANE, store_points=True)
    assert m.valid.all()
    o, d = _world_rays(SMALL, T_WORLD_CAM)
    n = T_world_sample.rotation[:, 2]
    p = _ray_plane(o, d, T_world_sample.translation, n)
    ref = _screen_xy_plane(p, _reflect(d, n))
    np.testing.assert_allclose(m.screen_xy_mm, ref, atol=1e-9, rtol=0)
    np.testing.assert_allclose(T_world_sample.apply(m.p_sample_mm), p, atol=1e-9, rtol=0)


def test_paraboloid_sample_closed_form():
    # z = c + a x² + b y² in a sample frame centred under the FOV: exact on a 3×3 grid.
    a, b, c = 3e-4, -2e-4, 0.4
    gx = np.array([-150.0, 0.0, 150.0])
    gy = np.array([-120.0, 0.0, 120.0])
    X, Y = np.meshgrid(gx, gy)
    sample = SplineSurface(gx, gy, c + a * X**2 + b * Y**2)
    T_world_sample = RigidTransform.from_origin_angles([30.0, -5.0, 0.0], [0.0, 0.0, 0.0])
    m = trace_camera(SMALL, T_WORLD_CAM, T_world_sample, sample, T_WORLD_SCREEN, SCREEN_PLANE)
    assert m.valid.all()
    o, d = _world_rays(SMALL, T_WORLD_CAM)
    o_s = T_world_sample.inv().apply(o)
    d_s = T_world_sample.inv().apply_vector(d)
    p_s = _ray_paraboloid_local(o_s, d_s, a, b, c)
    n_s = np.stack([-2 * a * p_s[..., 0], -2 * b * p_s[..., 1], np.ones(p_s.shape[:-1])], -1)
    r_s = _reflect(d_s, n_s)
    ref = _screen_xy_plane(T_world_sample.apply(p_s), T_world_sample.apply_vector(r_s))
    np.testing.assert_allclose(m.screen_xy_mm, ref, atol=1e-9, rtol=0)


def test_paraboloid_screen_closed_form():
    # A deformed screen (paraboloid over its 3×3 grid) seen via a planar sample.
    a, b, c = -2e-5, -3e-5, 1.0
    gx = np.array([0.0, 354.0, 708.0])
    gy = np.array([0.0, 199.0, 398.0])
    X, Y = np.meshgrid(gx, gy)
    # Heights relative to the centre so the bulge is a few mm.
    Z = c + a * (X - 354) ** 2 + b * (Y - 199) ** 2
    screen = SplineSurface(gx, gy, Z)
    T_world_sample = RigidTransform.from_origin_angles([-200.0, -200.0, 0.0], [0.0, 0.0, 0.0])
    sample = PlaneSurface((0.0, 400.0), (0.0, 400.0))
    m = trace_camera(SMALL, T_WORLD_CAM, T_world_sample, sample, T_WORLD_SCREEN, screen)
    assert m.valid.all()
    o, d = _world_rays(SMALL, T_WORLD_CAM)
    p = _ray_plane(o, d, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    r = _reflect(d, np.array([0.0, 0.0, 1.0]))
    # In a screen frame shifted to the paraboloid's apex.
    T_apex = T_WORLD_SCREEN @ RigidTransform(np.eye(3), [354.0, 199.0, 0.0])
    o_p = T_apex.inv().apply(p)
    r_p = T_apex.inv().apply_vector(r)
    q = _ray_paraboloid_local(o_p, r_p, a, b, c)
    np.testing.assert_allclose(m.screen_xy_mm, q[..., :2] + [354.0, 199.0], atol=1e-9, rtol=0)


def test_default_setup_field_of_view():
    """Table 1 with R = Rz(γ)Ry(β)Rx(α): each sensor's footprint on the sample plane spans
    ≈ 227 × 174 mm in world x and y (paper: "approximately 225 mm by 172 mm") and its
    reflected rays land on the 708 × 398 mm screen."""
    setup = default_setup().with_bulge(3.0)
    for name in ("left", "right"):
        m = trace_setup_camera(setup, name, store_points=True)
        assert m.valid.all(), m.status_counts()
        p_world = setup.sample.T_world_sample.apply(m.p_sample_mm)
        span_x = np.ptp(p_world[..., 0])
        span_y = np.ptp(p_world[..., 1])
        assert abs(span_x - 227.0) < 1.0 and abs(span_y - 174.0) < 1.0, (span_x, span_y)
        xy = m.screen_xy_mm
        assert xy[..., 0].min() > 0 and xy[..., 0].max() < 708
        assert xy[..., 1].min() > 0 and xy[..., 1].max() < 398
    # The two cameras are mirror images in x, but the pixel centres (0 … 1919) are not
    # symmetric about ppx = 960: the footprints mirror about x = 0 up to half a pixel (≈ 0.08 mm).
    pl = setup.sample.T_world_sample.apply(trace_setup_camera(setup, "left", store_points=True).p_sample_mm)
    pr = setup.sample.T_world_sample.apply(trace_setup_camera(setup, "right", store_points=True).p_sample_mm)
    assert abs(pl[..., 0].min() + pr[..., 0].max()) < 0.1


def test_invalid_pixels_are_masked_with_reasons():
    T_world_sample = RigidTransform.from_origin_angles([-200.0, -200.0, 0.0], [0.0, 0.0, 0.0])
    # A sample that covers only part of the field of view, a screen that catches only part.
    small_sample = PlaneSurface((150.0, 260.0), (0.0, 400.0))
    small_screen = PlaneSurface((0.0, 400.0), (0.0, 398.0))
    m = trace_camera(SMALL, T_WORLD_CAM, T_world_sample, small_sample, T_WORLD_SCREEN, small_screen)
    counts = m.status_counts()
    assert counts.get("SAMPLE_OUTSIDE", 0) > 0
    assert counts.get("SCREEN_OUTSIDE", 0) > 0
    assert counts.get("VALID", 0) > 0
    assert np.isnan(m.screen_xy_mm[~m.valid]).all()
    assert np.isfinite(m.screen_xy_mm[m.valid]).all()
    # Looking away from the sample: the sample is behind the camera.
    T_away = RigidTransform.from_origin_angles([-90.0, 295.0, -295.0], [-135.0, 0.0, 0.0])
    m2 = trace_camera(SMALL, T_away, T_world_sample, small_sample, T_WORLD_SCREEN, SCREEN_PLANE)
    assert m2.status_counts() == {"SAMPLE_PARALLEL": SMALL.width_px * SMALL.height_px}
    # Distortion that cannot be inverted at the corners.
    folded = Camera(192, 120, 40.0, 40.0, 96.0, 60.0, k1=-0.5)
    m3 = trace_camera(folded, T_WORLD_CAM, T_world_sample, small_sample, T_WORLD_SCREEN, SCREEN_PLANE)
    assert m3.status_counts().get("UNDISTORT_FAILED", 0) > 0
    assert {Status(s).description for s in np.unique(m3.status)}  # every code has a description


def test_mapping_is_independent_of_thread_count():
    import numba

    setup = default_setup().with_bulge(3.0)
    cam = Camera(192, 120, 440.0, 440.0, 96.0, 60.0)
    args = (cam, setup.cameras["left"].T_world_cam, setup.sample.T_world_sample, setup.sample.surface,
            setup.screen.T_world_screen, setup.screen.surface)
    m1 = trace_camera(*args)
    n = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        m2 = trace_camera(*args)
    finally:
        numba.set_num_threads(n)
    np.testing.assert_array_equal(m1.screen_xy_mm, m2.screen_xy_mm)


def test_partial_paraboloid_screen_closed_form():
    """Warm starts restart after pixels that miss a deformed screen (SCREEN_OUTSIDE inside rows)."""
    a, b, c = -2e-5, -3e-5, 1.0
    gx = np.array([150.0, 300.0, 450.0])  # a strip of the screen: rows leave and re-enter it
    gy = np.array([0.0, 199.0, 398.0])
    X, Y = np.meshgrid(gx, gy)
    screen = SplineSurface(gx, gy, c + a * (X - 354) ** 2 + b * (Y - 199) ** 2)
    T_world_sample = RigidTransform.from_origin_angles([-200.0, -200.0, 0.0], [0.0, 0.0, 0.0])
    sample = PlaneSurface((0.0, 400.0), (0.0, 400.0))
    m = trace_camera(SMALL, T_WORLD_CAM, T_world_sample, sample, T_WORLD_SCREEN, screen)
    counts = m.status_counts()
    assert counts.get("VALID", 0) > 1000 and counts.get("SCREEN_OUTSIDE", 0) > 1000, counts
    o, d = _world_rays(SMALL, T_WORLD_CAM)
    p = _ray_plane(o, d, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    r = _reflect(d, np.array([0.0, 0.0, 1.0]))
    T_apex = T_WORLD_SCREEN @ RigidTransform(np.eye(3), [354.0, 199.0, 0.0])
    q = _ray_paraboloid_local(T_apex.inv().apply(p), T_apex.inv().apply_vector(r), a, b, c)[..., :2] + [354.0, 199.0]
    inside = (q[..., 0] >= 150.0) & (q[..., 0] <= 450.0)
    np.testing.assert_array_equal(m.valid, inside)
    np.testing.assert_allclose(m.screen_xy_mm[inside], q[inside], atol=1e-9, rtol=0)


# ----------------------------------------------------------------------------- issue 15: row kernel
# Rows after the first of each band are traced by the vectorised row kernel
# (pmdsim.simulation.trace_rows); a flat list of rays (1-D d_cam) by the pixel-by-pixel loop.


def _biquadratic(gx, gy, Z):
    """Coefficients a[i, j] of h = Σ a_ij (x − gx[1])^i (y − gy[1])^j through a 3 × 3 grid: on
    3 grid lines the not-a-knot spline is the parabola through them (an independent fit)."""
    V = lambda g: np.vander(g - g[1], 3, increasing=True)  # noqa: E731
    return np.linalg.solve(V(gx), np.linalg.solve(V(gy), Z).T)  # a[i, j]: x^i y^j


def _first_root(o, w, height, t0):
    """Ray o + t·w ∩ z = height(x, y) by Newton's method on g(t) = o_z + t w_z − h, the
    derivative by central differences, iterated to a fixed point (a reference independent of
    pmdsim's kernels)."""
    t = t0
    for _ in range(60):
        p = o + t[..., None] * w
        g = p[..., 2] - height(p[..., 0], p[..., 1])
        dt = 1e-3
        pp = o + (t + dt)[..., None] * w
        pm = o + (t - dt)[..., None] * w
        dg = ((pp[..., 2] - height(pp[..., 0], pp[..., 1])) - (pm[..., 2] - height(pm[..., 0], pm[..., 1]))) / (2 * dt)
        t_new = t - g / dg
        if np.array_equal(t_new, t):
            break
        t = t_new
    return o + t[..., None] * w


def test_row_kernel_screen_points_within_intersection_tolerance():
    """Table 1, Δh = 3 mm, camera binned 8 × 8: screen points of the row kernel against an
    independent intersection with the biquadratic the 3 × 3 spline screen equals, in the
    screen frame, to the intersection tolerance 1e-11 mm (in z; x, y move by |b|·Δz)."""
    setup = default_setup().with_bulge(3.0).binned(8)
    cs = setup.cameras["left"]
    m = trace_camera(cs.camera, cs.T_world_cam, setup.sample.T_world_sample, setup.sample.surface,
                     setup.screen.T_world_screen, setup.screen.surface, store_points=True)
    assert m.valid.all()
    scr = setup.screen.surface
    a = _biquadratic(scr.grid_x_mm, scr.grid_y_mm, scr.heights_mm)
    height = lambda x, y: np.polynomial.polynomial.polyval2d(x - scr.grid_x_mm[1], y - scr.grid_y_mm[1], a)  # noqa: E731
    # The view rays and the planar sample in closed form (world frame), then the screen frame.
    o, d = _world_rays(cs.camera, cs.T_world_cam)
    Ts = setup.sample.T_world_sample
    n = Ts.rotation[:, 2]
    p = _ray_plane(o, d, Ts.translation, n)
    r = _reflect(d, n)
    Tq = setup.screen.T_world_screen.inv()
    o_q = Tq.apply(p)
    w_q = Tq.apply_vector(r)
    q = _first_root(o_q, w_q, height, -o_q[..., 2] / w_q[..., 2])
    assert np.abs(q[..., 2]).max() > 2.0  # the bulge is seen
    dz = np.abs(m.q_screen_mm[..., 2] - q[..., 2])
    b = np.hypot(w_q[..., 0], w_q[..., 1]) / np.abs(w_q[..., 2])
    dxy = np.linalg.norm(m.screen_xy_mm - q[..., :2], axis=-1)
    assert dz.max() <= 1e-11, dz.max()
    assert (dxy <= 1e-11 * (1.0 + b) + 1e-12).all(), dxy.max()


@pytest.mark.parametrize("n_lines", [5, 14])  # 8 intervals: patches by counting; 26: by bisection
def test_row_kernel_fine_spline_sample_and_screen_closed_form(n_lines):
    """Cubic not-a-knot splines reproduce quadratics exactly: a paraboloid sample and a
    paraboloid screen on fine, unevenly spaced grids against the closed forms (sample points,
    gradient via the reflection, screen points), through the row kernel's Newton steps,
    patch runs and scalar fallbacks."""
    rng = np.random.default_rng(15)

    def grid(lo, hi):
        g = np.linspace(lo, hi, n_lines)
        g[1:-1] += rng.uniform(-0.2, 0.2, n_lines - 2) * (g[1] - g[0])
        return g

    a_s, b_s, c_s = 3e-4, -2e-4, 0.4
    gx, gy = grid(-150.0, 150.0), grid(-120.0, 120.0)
    X, Y = np.meshgrid(gx, gy)
    sample = SplineSurface(gx, gy, c_s + a_s * X**2 + b_s * Y**2)
    T_world_sample = RigidTransform.from_origin_angles([30.0, -5.0, 0.0], [0.0, 0.0, 0.0])
    a_q, b_q, c_q = -2e-5, -3e-5, 1.0
    hx_, hy_ = grid(0.0, 708.0), grid(0.0, 398.0)
    X, Y = np.meshgrid(hx_, hy_)
    screen = SplineSurface(hx_, hy_, c_q + a_q * (X - 354) ** 2 + b_q * (Y - 199) ** 2)
    m = trace_camera(SMALL, T_WORLD_CAM, T_world_sample, sample, T_WORLD_SCREEN, screen, store_points=True)
    assert m.valid.all(), m.status_counts()
    o, d = _world_rays(SMALL, T_WORLD_CAM)
    o_s = T_world_sample.inv().apply(o)
    d_s = T_world_sample.inv().apply_vector(d)
    p_s = _ray_paraboloid_local(o_s, d_s, a_s, b_s, c_s)
    np.testing.assert_allclose(m.p_sample_mm, p_s, atol=1e-9, rtol=0)
    n_s = np.stack([-2 * a_s * p_s[..., 0], -2 * b_s * p_s[..., 1], np.ones(p_s.shape[:-1])], -1)
    r_s = _reflect(d_s, n_s)
    T_apex = T_WORLD_SCREEN @ RigidTransform(np.eye(3), [354.0, 199.0, 0.0])
    q = _ray_paraboloid_local(T_apex.inv().apply(T_world_sample.apply(p_s)),
                              T_apex.inv().apply_vector(T_world_sample.apply_vector(r_s)), a_q, b_q, c_q)
    np.testing.assert_allclose(m.screen_xy_mm, q[..., :2] + [354.0, 199.0], atol=1e-9, rtol=0)


def test_row_kernel_matches_pixel_loop_status_and_points():
    """The same rays as an image (row kernel for all rows after a band's first) and as a flat
    list (the pixel-by-pixel loop): identical status codes, several kinds in one image
    (undistortion failures, rays missing sample and screen), and both against the closed
    forms of a paraboloid sample (exact on its 5 × 3 spline grid) and a paraboloid strip of
    screen. (Where an intersection has no converging fixed point the two warm-start orders
    may end in different failure codes, SAMPLE_OUTSIDE or SAMPLE_NO_CONVERGENCE — as before
    this kernel; this sample has none.)"""
    from pmdsim.simulation.trace import trace_rays

    folded = Camera(192, 120, 150.0, 150.0, 96.0, 60.0, k1=-1.2)  # outer part: UNDISTORT_FAILED
    d_cam, ok = folded.sensor_rays()
    a, b, c = -2e-5, -3e-5, 1.0
    gx = np.array([150.0, 300.0, 450.0])
    gy = np.array([0.0, 199.0, 398.0])
    X, Y = np.meshgrid(gx, gy)
    screen = SplineSurface(gx, gy, c + a * (X - 354) ** 2 + b * (Y - 199) ** 2)
    a_s, b_s, c_s = 3e-4, -2e-4, 0.4
    sgx = np.array([-150.0, -40.0, 0.0, 60.0, 150.0])
    sgy = np.array([-120.0, 0.0, 120.0])
    Xs, Ys = np.meshgrid(sgx, sgy)
    sample = SplineSurface(sgx, sgy, c_s + a_s * Xs**2 + b_s * Ys**2)
    T_world_sample = RigidTransform.from_origin_angles([30.0, -5.0, 0.0], [0.0, 0.0, 0.0])
    T_sample_cam = T_world_sample.inv() @ T_WORLD_CAM
    T_screen_sample = T_WORLD_SCREEN.inv() @ T_world_sample
    img = trace_rays(d_cam, ok, T_sample_cam, T_screen_sample, sample, screen, store_points=True)
    flat = trace_rays(d_cam.reshape(-1, 3), ok.reshape(-1), T_sample_cam, T_screen_sample, sample, screen,
                      store_points=True)
    counts = img.status_counts()
    for name in ("VALID", "UNDISTORT_FAILED", "SAMPLE_OUTSIDE", "SCREEN_OUTSIDE"):
        assert counts.get(name, 0) > 1000, counts
    np.testing.assert_array_equal(img.status.reshape(-1), flat.status)
    # Closed forms (in the sample frame, then the paraboloid screen's apex frame).
    d_s = T_sample_cam.apply_vector(d_cam[ok])
    o_s = np.broadcast_to(T_sample_cam.translation, d_s.shape)
    p_s = _ray_paraboloid_local(o_s, d_s, a_s, b_s, c_s)
    n_s = np.stack([-2 * a_s * p_s[..., 0], -2 * b_s * p_s[..., 1], np.ones(p_s.shape[:-1])], -1)
    T_apex_sample = RigidTransform(np.eye(3), [-354.0, -199.0, 0.0]) @ T_screen_sample
    q = _ray_paraboloid_local(T_apex_sample.apply(p_s), T_apex_sample.apply_vector(_reflect(d_s, n_s)), a, b, c)
    q_xy = q[..., :2] + [354.0, 199.0]
    for m in (img, flat):
        st = m.status.reshape(-1)[ok.reshape(-1)]
        hit = st != Status.SAMPLE_OUTSIDE
        np.testing.assert_allclose(m.p_sample_mm.reshape(-1, 3)[ok.reshape(-1)][hit], p_s[hit], atol=1e-9, rtol=0)
        v = st == Status.VALID
        np.testing.assert_allclose(m.screen_xy_mm.reshape(-1, 2)[ok.reshape(-1)][v], q_xy[v], atol=1e-9, rtol=0)
        assert np.isnan(m.screen_xy_mm.reshape(-1, 2)[m.status.reshape(-1) != Status.VALID]).all()
