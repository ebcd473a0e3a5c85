"""Curved samples (issue 14): analytic shapes against closed forms computed here, independently
of pmdsim's quadric kernels (geometric ray–sphere and ray–cylinder intersection, the paraboloid's
own quadratic, reflection about the normal, the screen plane); setup files and height maps as
round trips and refusals; grazing rays; a 1 m sphere reconstructed through 8-bit images."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.interpolate import RectBivariateSpline

import pmdsim
from pmdsim.errors import SetupError
from pmdsim.evaluation.metrics import surface_error_metrics
from pmdsim.geometry.shapes import QuadricSurface
from pmdsim.geometry.surface import PlaneSurface
from pmdsim.geometry.transform import RigidTransform
from pmdsim.io.heightmap import load_setup, read_height_map, write_height_map
from pmdsim.setup import SampleShape, parse_setup
from pmdsim.setup.sample_shape import spline_report
from pmdsim.simulation.render import trace_setup_camera
from pmdsim.simulation.trace import MAX_INCIDENCE_DEG, Status, trace_rays

R_MM = 1000.0


def _sphere_height(x, y, r=R_MM, vx=200.0, vy=200.0):
    r2 = (x - vx) ** 2 + (y - vy) ** 2
    return r - np.sign(r) * np.sqrt(r * r - r2)


# ----------------------------------------------------------------------------- closed forms
def _world_rays(setup, camera):
    cs = setup.cameras[camera]
    d_cam, ok = cs.camera.sensor_rays()
    T = cs.T_world_cam
    d = d_cam @ T.rotation.T
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(T.translation, d.shape), d, ok


def _reflect_to_screen(setup, p_w, n_w, d_w):
    """Reflect d about the (any-sign) normal at p and intersect the screen's plane z_screen = 0."""
    n = n_w / np.linalg.norm(n_w, axis=-1, keepdims=True)
    r = d_w - 2.0 * np.sum(d_w * n, axis=-1, keepdims=True) * n
    T_sw = setup.screen.T_world_screen.inv()
    o_s = p_w @ T_sw.rotation.T + T_sw.translation
    r_s = r @ T_sw.rotation.T
    t = -o_s[..., 2] / r_s[..., 2]
    return o_s + t[..., None] * r_s, t


def _sphere_closed_form(setup, camera, radius):
    """World-frame geometric ray–sphere intersection (near cap), reflection, screen plane."""
    o, d, _ = _world_rays(setup, camera)
    T_ws = setup.sample.T_world_sample
    c = T_ws.apply(np.array([200.0, 200.0, radius]))  # vertex at the grid centre, centre at +R
    oc = o - c
    b = np.sum(oc * d, axis=-1)
    disc = b * b - (np.sum(oc * oc, axis=-1) - radius * radius)
    t = -b - np.sign(radius) * np.sqrt(disc)  # the cap nearer to the cameras (vertex side)
    p = o + t[..., None] * d
    q, _ = _reflect_to_screen(setup, p, p - c, d)
    p_s = T_ws.inv().apply(p)
    return p_s, q


def _paraboloid_closed_form(setup, camera, fx, fy):
    """Sample-frame quadratic of the ray in z = x'²/(4fx) + y'²/(4fy), normal (−h_x, −h_y, 1)."""
    o_w, d_w, _ = _world_rays(setup, camera)
    T_sw = setup.sample.T_world_sample.inv()
    o = o_w @ T_sw.rotation.T + T_sw.translation - np.array([200.0, 200.0, 0.0])
    d = d_w @ T_sw.rotation.T
    a = d[..., 0] ** 2 / (4 * fx) + d[..., 1] ** 2 / (4 * fy)
    b = 2 * o[..., 0] * d[..., 0] / (4 * fx) + 2 * o[..., 1] * d[..., 1] / (4 * fy) - d[..., 2]
    c = o[..., 0] ** 2 / (4 * fx) + o[..., 1] ** 2 / (4 * fy) - o[..., 2]
    roots = np.stack([(-b - np.sqrt(b * b - 4 * a * c)) / (2 * a), (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)])
    roots = np.where(roots > 0, roots, np.inf)
    t = roots.min(axis=0)
    p = o + t[..., None] * d
    n = np.stack([-p[..., 0] / (2 * fx), -p[..., 1] / (2 * fy), np.ones_like(t)], axis=-1)
    p_s = p + np.array([200.0, 200.0, 0.0])
    T_ws = setup.sample.T_world_sample
    q, _ = _reflect_to_screen(setup, T_ws.apply(p_s), n @ T_ws.rotation.T, d_w)
    return p_s, q


def _cylinder_closed_form(setup, camera, radius, angle_deg):
    """Ray–cylinder in the cylinder's own frame: the 2-D ray–circle problem across the axis."""
    o_w, d_w, _ = _world_rays(setup, camera)
    T_ws = setup.sample.T_world_sample
    th = math.radians(angle_deg)
    axis = np.array([math.cos(th), math.sin(th), 0.0])
    w = np.array([-math.sin(th), math.cos(th), 0.0])
    c = np.array([200.0, 200.0, radius])  # a point on the axis (sample frame)
    T_sw = T_ws.inv()
    o = o_w @ T_sw.rotation.T + T_sw.translation - c
    d = d_w @ T_sw.rotation.T
    e = np.array([0.0, 0.0, 1.0])
    o2 = np.stack([o @ w, o @ e], axis=-1)
    d2 = np.stack([d @ w, d @ e], axis=-1)
    a = np.sum(d2 * d2, axis=-1)
    b = np.sum(o2 * d2, axis=-1)
    disc = b * b - a * (np.sum(o2 * o2, axis=-1) - radius * radius)
    t = (-b - np.sign(radius) * np.sqrt(disc)) / a
    p = o + t[..., None] * d
    n = p - np.sum(p * axis, axis=-1, keepdims=True) * axis  # radial direction from the axis
    p_s = p + c
    q, _ = _reflect_to_screen(setup, T_ws.apply(p_s), n @ T_ws.rotation.T, d_w)
    return p_s, q


@pytest.fixture(scope="module")
def small():
    return pmdsim.default_setup().binned(8)


@pytest.mark.parametrize("shape, closed", [
    (SampleShape.sphere(R_MM), lambda s: _sphere_closed_form(s, "left", R_MM)),
    (SampleShape.sphere(-R_MM), lambda s: _sphere_closed_form(s, "left", -R_MM)),
    (SampleShape.paraboloid(500.0, -800.0), lambda s: _paraboloid_closed_form(s, "left", 500.0, -800.0)),
    (SampleShape.cylinder(600.0, 30.0), lambda s: _cylinder_closed_form(s, "left", 600.0, 30.0)),
    (SampleShape.cylinder(-700.0, -75.0), lambda s: _cylinder_closed_form(s, "left", -700.0, -75.0)),
], ids=["sphere+", "sphere-", "saddle-paraboloid", "cylinder+", "cylinder-"])
def test_tracer_matches_closed_form(small, shape, closed):
    """Sample point and screen hit of every pixel to 1e-9 mm; the masked pixels are exactly those
    whose closed-form screen hit lies outside the screen."""
    setup = small.with_sample_shape(shape)
    m = trace_setup_camera(setup, "left", store_points=True)
    p_true, q_true = closed(setup)
    gx, gy = setup.screen.grid_x_mm, setup.screen.grid_y_mm
    on_screen = (q_true[..., 0] >= gx[0]) & (q_true[..., 0] <= gx[-1]) & (q_true[..., 1] >= gy[0]) & (
        q_true[..., 1] <= gy[-1])
    ok = m.valid
    assert ok.sum() > 0.5 * ok.size
    np.testing.assert_array_equal(ok, on_screen)
    assert set(np.unique(m.status[~ok])) <= {Status.SCREEN_OUTSIDE}
    assert np.max(np.abs(m.p_sample_mm[ok] - p_true[ok])) < 1e-9
    assert np.max(np.abs(m.screen_xy_mm[ok] - q_true[ok][:, :2])) < 1e-9


def test_quadric_height_and_gradient_are_the_closed_form():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 400, 500), rng.uniform(0, 400, 500)
    s = QuadricSurface.sphere([0, 400], [0, 400], -R_MM)
    np.testing.assert_allclose(s.height(x, y), _sphere_height(x, y, -R_MM), rtol=0, atol=1e-12)
    # Gradient against central differences of the closed form.
    e = 1e-4
    gx_fd = (_sphere_height(x + e, y, -R_MM) - _sphere_height(x - e, y, -R_MM)) / (2 * e)
    gy_fd = (_sphere_height(x, y + e, -R_MM) - _sphere_height(x, y - e, -R_MM)) / (2 * e)
    np.testing.assert_allclose(s.gradient(x, y), np.stack([gx_fd, gy_fd], -1), rtol=0, atol=1e-8)
    c = QuadricSurface.cylinder([0, 400], [0, 400], 700.0, 90.0)  # axis along y: h depends on x only
    np.testing.assert_allclose(c.height(x, y), _sphere_height(x, 200.0 + 0 * y, 700.0), rtol=0, atol=1e-12)


def test_grazing_and_missing_rays_are_masked_with_a_reason():
    """Rays aimed at a point of a sphere at incidence 1° below / above MAX_INCIDENCE_DEG, a ray
    that misses the sphere, a ray that meets it only outside the grid."""
    sphere = QuadricSurface.sphere([-300, 300], [-300, 300], R_MM, (0.0, 0.0))
    screen = PlaneSurface((-1e5, 1e5), (-1e5, 1e5))
    # Screen plane 500 mm towards the cameras (sample −z), its +z pointing away from the sample.
    T_screen_sample = RigidTransform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, -500.0]).inv()
    x0 = 250.0
    p = np.array([x0, 0.0, _sphere_height(x0, 0.0, R_MM, 0.0, 0.0)])
    n_out = np.array([x0, 0.0, p[2] - R_MM]) / R_MM  # from the centre (0, 0, R) out: towards −z
    t = np.array([0.0, 1.0, 0.0])  # tangent: the rays come in sideways, the reflection leaves towards −z
    rays = []
    for inc in (MAX_INCIDENCE_DEG - 1.0, MAX_INCIDENCE_DEG + 1.0):
        a = math.radians(inc)
        d = -math.cos(a) * n_out + math.sin(a) * t  # arriving: d·n_out = −cos(incidence)
        rays.append((p - 50.0 * d, d))
    rays.append((np.array([0.0, 0.0, -100.0]), np.array([1.0, 0.0, 1e-4])))  # misses the sphere
    rays.append((np.array([0.0, 0.0, -100.0]), np.array([0.9, 0.0, 0.3])))  # meets it beyond x = 300
    statuses = []
    for o, d in rays:  # the tracer's rays start at the pinhole, the origin of T_sample_cam
        m = trace_rays(d[None], np.ones(1, bool), RigidTransform(np.eye(3), o), T_screen_sample, sphere, screen,
                       store_points=True)
        statuses.append(Status(int(m.status[0])))
        if statuses[-1] == Status.VALID:
            np.testing.assert_allclose(m.p_sample_mm[0], p, rtol=0, atol=1e-9)
    assert statuses == [Status.VALID, Status.SAMPLE_GRAZING, Status.SAMPLE_OUTSIDE, Status.SAMPLE_OUTSIDE]


# ----------------------------------------------------------------------------- setups
def test_shape_round_trips_through_toml_and_refuses_bad_values(small):
    for shape in (SampleShape.sphere(R_MM), SampleShape.paraboloid(700.0, 2000.0),
                  SampleShape.cylinder(-900.0, 20.0, (150.0, 210.0))):
        s = small.with_sample_shape(shape)
        back = parse_setup(__import__("tomllib").loads(s.to_toml()))
        assert back.sample == s.sample
    doc = small.with_sample_shape("sphere", radius_mm=R_MM).to_dict()
    bad = [({"radius_mm": 250.0}, "radius is too small"), ({"shape": "ellipsoid"}, "sample.shape must be one of"),
           ({"radius_mm": 0.0}, "sample.radius_mm must be non-zero"),
           ({"focal_length_x_mm": 3.0}, "does not apply"),
           ({"heights_mm": [[0.0, 0.0], [0.0, 0.0]]}, "not both")]
    for change, msg in bad:
        d = {**doc, "sample": {**doc["sample"], **change}}
        with pytest.raises(SetupError, match=msg):
            parse_setup(d)
    d = {**doc, "sample": {k: v for k, v in doc["sample"].items() if k != "shape"}}
    with pytest.raises(SetupError, match="needs sample.shape"):
        parse_setup(d)


def test_spline_of_a_sphere_misses_by_what_the_report_says():
    """The spline report's figure against an independent evaluation (scipy's not-a-knot spline)."""
    g = np.linspace(0.0, 400.0, 21)
    heights, rep = spline_report(SampleShape.sphere(R_MM), g, g)
    np.testing.assert_allclose(heights, _sphere_height(*np.meshgrid(g, g)), rtol=0, atol=1e-12)
    f = np.linspace(0, 400, 81)
    fine = RectBivariateSpline(g, g, heights, kx=3, ky=3, s=0)(f, f)
    X, Y = np.meshgrid(f, f)
    off = ~(np.isin(X, g) & np.isin(Y, g))
    err = (fine - _sphere_height(X, Y))[off]
    assert rep.max_error_mm == pytest.approx(np.max(np.abs(err)), rel=1e-6)
    assert rep.rms_error_mm == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-6)


# ----------------------------------------------------------------------------- height maps
def _sample_toml(small, tmp_path, keys: str, grid_n: int = 21) -> str:
    doc = small.to_dict()
    g = np.linspace(0.0, 400.0, grid_n).tolist()
    doc["sample"]["grid_x_mm"] = g
    doc["sample"]["grid_y_mm"] = g
    text = pmdsim.setup.toml.dump_toml(doc)
    path = tmp_path / "setup.toml"
    path.write_text(text.replace("[sample]\n", "[sample]\n" + keys + "\n", 1), encoding="utf-8")
    return str(path)


@pytest.mark.parametrize("fmt, units, extra", [
    ("h5", "mm", 'height_map_dataset = "height"'),
    ("h5", "um", ""),
    ("npy", "m", "height_map_x_mm = [0.0, 400.0]\nheight_map_y_mm = [0.0, 400.0]"),
    ("csv", "um", ""),
])
def test_height_map_round_trip_matches_the_analytic_sphere(small, tmp_path, fmt, units, extra):
    xd = np.linspace(0.0, 400.0, 81)  # the file: 5 mm grid; the sample's spline grid: 20 mm
    zd = _sphere_height(*np.meshgrid(xd, xd))
    write_height_map(tmp_path / f"sphere.{fmt}", xd, xd, zd, units=units)
    path = _sample_toml(small, tmp_path, f'height_map = "sphere.{fmt}"\nheight_map_units = "{units}"\n{extra}')
    setup = load_setup(path)
    g = np.asarray(setup.sample.grid_x_mm)
    # Nodes of the spline are nodes of the file: the heights are the sphere's there.
    np.testing.assert_allclose(np.array(setup.sample.heights_mm), _sphere_height(*np.meshgrid(g, g)),
                               rtol=0, atol=1e-9)
    # The report: the spline against the file at the file's points (independently: scipy).
    rep = setup.sample.interpolation_report
    spl = RectBivariateSpline(g, g, np.array(setup.sample.heights_mm), kx=3, ky=3, s=0)(xd, xd)
    err = spl - zd
    assert rep.n_points == zd.size
    assert rep.max_error_mm == pytest.approx(np.max(np.abs(err)), rel=1e-6, abs=1e-12)
    assert rep.rms_error_mm == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-6, abs=1e-12)
    assert 0 < rep.max_error_mm < 1e-3  # 20 mm grid on a 1 m sphere: ~0.1 µm (measured by spline_report)
    # A setup pmdsim writes carries the resampled heights and the record: it reads back equal
    # without the file.
    (tmp_path / f"sphere.{fmt}").unlink()
    assert parse_setup(__import__("tomllib").loads(setup.to_toml())).sample == setup.sample


def test_height_map_refusals_name_the_file(small, tmp_path):
    xd = np.linspace(0.0, 400.0, 41)
    zd = _sphere_height(*np.meshgrid(xd, xd))
    zn = zd.copy()
    zn[3, 5] = np.nan
    write_height_map(tmp_path / "nan.h5", xd, xd, zn)
    with pytest.raises(SetupError, match=r"nan\.h5.*1 heights are NaN.*x = 50 mm, y = 30 mm"):
        load_setup(_sample_toml(small, tmp_path, 'height_map = "nan.h5"'))
    write_height_map(tmp_path / "coarse.h5", xd, xd, zd)  # 10 mm spacing; the spline grid: 5 mm
    with pytest.raises(SetupError, match=r"coarse\.h5.*too coarse.*10 mm.*5 mm"):
        load_setup(_sample_toml(small, tmp_path, 'height_map = "coarse.h5"', grid_n=81))
    # A spline grid too coarse for the map's curvature: 100 mm on a 1 m sphere misses it by ~16 µm
    # (bench_curved.py --spline-table), more than the default 1 µm — accepted with a tolerance.
    write_height_map(tmp_path / "fine.h5", xd, xd, zd)
    with pytest.raises(SetupError, match=r"grid \(spacing 100 × 100 mm\) is too coarse for height map .*fine\.h5.*"
                                         r"height_map_max_error_um = 1 µm"):
        load_setup(_sample_toml(small, tmp_path, 'height_map = "fine.h5"', grid_n=5))
    loose = load_setup(_sample_toml(small, tmp_path, 'height_map = "fine.h5"\nheight_map_max_error_um = 50.0',
                                    grid_n=5))
    assert 1e-3 < loose.sample.interpolation_report.max_error_mm < 50e-3
    write_height_map(tmp_path / "small.h5", xd[:21], xd, zd[:, :21])  # covers x ≤ 200 only
    with pytest.raises(SetupError, match=r"small\.h5' covers x ∈ \[0, 200\]"):
        load_setup(_sample_toml(small, tmp_path, 'height_map = "small.h5"'))
    with pytest.raises(SetupError, match=r"missing\.npy.*does not exist"):
        load_setup(_sample_toml(small, tmp_path, 'height_map = "missing.npy"'))
    np.save(tmp_path / "nogrid.npy", zd)
    with pytest.raises(SetupError, match="height_map_x_mm"):
        load_setup(_sample_toml(small, tmp_path, 'height_map = "nogrid.npy"'))
    (tmp_path / "holes.csv").write_text("x_mm,y_mm,z\n0,0,0\n1,0,0\n0,1,0\n", encoding="utf-8")
    with pytest.raises(SetupError, match=r"holes\.csv.*complete grid"):
        read_height_map(tmp_path / "holes.csv")
    # The setup layer alone reads no files, and says how to.
    with pytest.raises(SetupError, match="needs pmdsim.io"):
        pmdsim.setup.load_setup(_sample_toml(small, tmp_path, 'height_map = "coarse.h5"'))


def test_cli_setup_reports_the_interpolation_error_and_refuses_nan(small, tmp_path):
    xd = np.linspace(0.0, 400.0, 41)
    zd = _sphere_height(*np.meshgrid(xd, xd))
    write_height_map(tmp_path / "s.csv", xd, xd, zd)
    ok = subprocess.run([sys.executable, "-m", "pmdsim.cli", "setup", "--setup",
                         _sample_toml(small, tmp_path, 'height_map = "s.csv"')], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    rep = load_setup(str(tmp_path / "setup.toml")).sample.interpolation_report
    assert f"max {rep.max_error_mm * 1e3:.3g} µm" in ok.stderr and "s.csv" in ok.stderr
    zd[10, 10] = np.nan
    write_height_map(tmp_path / "s.csv", xd, xd, zd)
    bad = subprocess.run([sys.executable, "-m", "pmdsim.cli", "setup", "--setup", str(tmp_path / "setup.toml")],
                         capture_output=True, text=True)
    assert bad.returncode == 2
    assert bad.stderr.startswith("pmdsim: error: ") and "s.csv" in bad.stderr and "NaN" in bad.stderr


# ----------------------------------------------------------------------------- reconstruction
def test_sphere_reconstructed_mono_through_8bit_images(small):
    """A 1 m sphere, true setup and planar screen, seeded at its true height: P-V of the height
    error (docs/benchmarks.md has the full-resolution figure: benchmarks/bench_curved.py)."""
    setup = pmdsim.default_setup().binned(8).with_sample_shape("sphere", radius_mm=R_MM)
    m = pmdsim.simulate(setup, "left")
    decoded = pmdsim.decode(m.images, setup)
    cam = setup.cameras["left"].camera
    seed = (cam.height_px // 2, cam.width_px // 2)
    ev = pmdsim.evaluate(decoded, setup, "left", seed_pixel=seed,
                         seed_height_mm=float(m.mapping.p_sample_mm[seed][2]))
    rec = ev.reconstruction
    p = rec.p_sample_mm
    ok = rec.reconstructed
    err_um = (rec.height_mm[ok] - _sphere_height(p[ok][:, 0], p[ok][:, 1])) * 1e3
    assert ok.sum() > 0.8 * m.mapping.valid.sum()
    assert np.all(np.isfinite(err_um))
    pv = float(err_um.max() - err_um.min())
    print(f"binned 8: P-V {pv:.4f} µm over {ok.sum()} px")
    assert pv < 0.1
    # The masked pixels (reflected rays beyond the screen) leave no NaN in the metrics table.
    assert (m.mapping.status != Status.VALID).any()
    err_full = np.where(ok, rec.height_mm - _sphere_height(p[..., 0], p[..., 1]), np.nan)
    metrics = surface_error_metrics(p[..., 0], p[..., 1], err_full)
    assert all(np.isfinite(v) for v in metrics.values())
    assert metrics["max_height_diff_um"] == pytest.approx(pv, rel=1e-9)


def test_strongly_curved_sphere_grazing_pixels_masked_through_the_pipeline(small):
    """R = 300 mm over the 400 mm grid: the tracer's SAMPLE_GRAZING pixels are exactly those whose
    closed-form incidence exceeds MAX_INCIDENCE_DEG; masked pixels end as NOT_DECODED in the
    registration, are not reconstructed, and leave the metrics finite."""
    from pmdsim.evaluation.registration import RegistrationStatus

    radius = 300.0
    setup = small.with_sample_shape("sphere", radius_mm=radius)
    m = pmdsim.simulate(setup, "left")
    st = m.mapping.status
    grazing = st == Status.SAMPLE_GRAZING
    assert grazing.sum() > 20
    # Independent incidence: world-frame ray–sphere, angle between −d and the outward normal.
    o, d, _ = _world_rays(setup, "left")
    c = setup.sample.T_world_sample.apply(np.array([200.0, 200.0, radius]))
    oc = o - c
    b = np.sum(oc * d, axis=-1)
    disc = b * b - (np.sum(oc * oc, axis=-1) - radius ** 2)
    hit = st != Status.SAMPLE_OUTSIDE
    assert np.all(disc[hit] > 0)
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    n_out = (o + t[..., None] * d - c) / radius
    inc_deg = np.degrees(np.arccos(np.clip(-np.sum(d * n_out, axis=-1), -1, 1)))
    np.testing.assert_array_equal(grazing[hit], inc_deg[hit] > MAX_INCIDENCE_DEG)
    decoded = pmdsim.decode(m.images, setup)
    cam = setup.cameras["left"].camera
    ok_px = np.argwhere(m.mapping.valid)
    seed = tuple(int(v) for v in ok_px[np.argmin(np.sum((ok_px - [cam.height_px // 2, cam.width_px // 2]) ** 2, 1))])
    ev = pmdsim.evaluate(decoded, setup, "left", seed_pixel=seed, seed_height_mm=float(m.mapping.p_sample_mm[seed][2]))
    masked = ~m.mapping.valid
    assert np.all(ev.registration.status[masked] == RegistrationStatus.NOT_DECODED)
    rec = ev.reconstruction
    assert not rec.reconstructed[masked].any()
    p = rec.p_sample_mm
    err = np.where(rec.reconstructed, rec.height_mm - _sphere_height(p[..., 0], p[..., 1], radius), np.nan)
    metrics = surface_error_metrics(p[..., 0], p[..., 1], err)
    assert all(np.isfinite(v) for v in metrics.values())
