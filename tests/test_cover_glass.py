"""The screen's cover glass (issue 21): tracer against the closed-form plate shift and against an
independent refraction trace written here; setup keys; registration round trip."""

import numpy as np
import pytest
from scipy.optimize import brentq, fsolve

from pmdsim.errors import SetupError
from pmdsim.geometry.camera import Camera
from pmdsim.geometry.cover_glass import CoverGlass
from pmdsim.geometry.surface import PlaneSurface, SplineSurface
from pmdsim.geometry.transform import RigidTransform
from pmdsim.setup import default_setup
from pmdsim.setup.toml import parse_setup
from pmdsim.simulation.trace import Status, trace_camera

# A small camera with the Table 1 field of view, looking at a planar mirror and the screen.
SMALL = Camera(96, 60, 220.0, 220.0, 48.0, 30.0)
T_WORLD_CAM = RigidTransform.from_origin_angles([-90.0, 295.0, -295.0], [45.0, 10.0, 10.0])
T_WORLD_SCREEN = RigidTransform.from_origin_angles([-354.0, -78.0, -400.0], [135.0, 0.0, 0.0])
T_WORLD_SAMPLE = RigidTransform.from_origin_angles([-210.0, -190.0, 0.0], [0.0, 0.0, 0.0])
SAMPLE = PlaneSurface((0.0, 420.0), (0.0, 400.0))
GX = np.linspace(0.0, 708.0, 5)
GY = np.linspace(0.0, 398.0, 5)


def _reflected_rays_screen():
    """The reflected rays of SMALL off the planar mirror z = 0, in the screen frame (written
    here: ray ∩ plane, mirror reflection)."""
    d_cam, ok = SMALL.sensor_rays()
    o = T_WORLD_CAM.translation
    d = T_WORLD_CAM.apply_vector(d_cam)
    T_sample_world = T_WORLD_SAMPLE.inv()
    o_s = T_sample_world.apply(o)
    d_s = T_sample_world.apply_vector(d)
    p_s = o_s + (-o_s[2] / d_s[..., 2])[..., None] * d_s
    r_s = d_s * np.array([1.0, 1.0, -1.0])
    T_screen_sample = T_WORLD_SCREEN.inv() @ T_WORLD_SAMPLE
    return T_screen_sample.apply(p_s), T_screen_sample.apply_vector(r_s)


def _trace(screen, glass, store_points=False):
    return trace_camera(SMALL, T_WORLD_CAM, T_WORLD_SAMPLE, SAMPLE, T_WORLD_SCREEN, screen, glass=glass,
                        store_points=store_points)


def test_zero_thickness_is_the_glass_free_trace_bit_for_bit():
    screen = SplineSurface.from_bulge(GX, GY, 3.0)
    a = _trace(screen, None, store_points=True)
    b = _trace(screen, CoverGlass(0.0, 1.52), store_points=True)
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.screen_xy_mm, b.screen_xy_mm)
    np.testing.assert_array_equal(a.q_screen_mm, b.q_screen_mm)


@pytest.mark.parametrize("t, n", [(3.0, 1.52), (0.7, 1.8)])
def test_flat_screen_closed_form_plate_shift(t, n):
    """Flat screen: the pattern point seen through the glass lies off the unrefracted ray line by
    the plate shift t·sinθ·(1 − cosθ/√(n² − sin²θ)); in the screen plane by that / cosθ,
    towards the foot of the normal."""
    screen = PlaneSurface((0.0, 708.0), (0.0, 398.0))
    bare = _trace(screen, None)
    m = _trace(screen, CoverGlass(t, n))
    o, r = _reflected_rays_screen()
    ok = m.valid & bare.valid
    assert ok.sum() > 0.9 * ok.size
    r = r / np.linalg.norm(r, axis=-1, keepdims=True)
    cos = r[..., 2]  # the screen's +z points away from the sample: rays towards it have r_z > 0
    sin = np.sqrt(1.0 - cos**2)
    expect = t * sin * (1.0 - cos / np.sqrt(n * n - sin**2))
    q = np.concatenate([m.screen_xy_mm, np.zeros(m.status.shape + (1,))], axis=-1)
    v = q - o
    perp = np.linalg.norm(v - np.sum(v * r, axis=-1, keepdims=True) * r, axis=-1)
    np.testing.assert_allclose(perp[ok], expect[ok], rtol=0, atol=1e-9)
    shift = np.linalg.norm(m.screen_xy_mm - bare.screen_xy_mm, axis=-1)
    np.testing.assert_allclose(shift[ok], (expect / cos)[ok], rtol=0, atol=1e-9)
    # Towards the foot of the normal: the ray is steeper in the glass.
    lateral = r[..., :2] / np.linalg.norm(r[..., :2], axis=-1, keepdims=True)
    assert (np.sum((m.screen_xy_mm - bare.screen_xy_mm) * lateral, axis=-1)[ok] < 0).all()
    assert 0.3 < np.degrees(np.arccos(cos[ok])).min() and np.degrees(np.arccos(cos[ok])).max() > 20


def _independent_glass_hit(screen, t, n, o, d):
    """Reference trace of one ray through the glass on a curved screen, written independently:
    the foot point u of the outer-surface hit A = S(u) + t·m(u) by fsolve on the two
    components of (A − o) × d that do not vanish, refraction by conservation of the tangential
    component (|e_t′| = |e_t|/n), the emitting-surface hit by brentq along the refracted ray."""
    d = d / np.linalg.norm(d)

    def unit_normal(x, y):  # towards the sample (−z side)
        hx, hy = screen.gradient(x, y)
        m = np.array([hx, hy, -1.0])
        return m / np.linalg.norm(m)

    def outer(u):
        m = unit_normal(*u)
        return np.array([u[0], u[1], float(screen.height(*u))]) + t * m

    def residual(u):
        c = np.cross(outer(u) - o, d)
        return c[:2]

    # Start: the bare hit, by brentq on the ray's height above the surface.
    f0 = lambda s: (o + s * d)[2] - float(screen.height(*(o + s * d)[:2]))
    s_plane = -o[2] / d[2]
    s0 = brentq(f0, 0.5 * s_plane, 1.5 * s_plane, xtol=1e-14)
    u = fsolve(residual, (o + s0 * d)[:2], xtol=1e-12)
    a = outer(u)
    m = unit_normal(*u)
    e_n = np.dot(d, m) * m
    e_t = d - e_n
    e_t2 = e_t / n
    r = e_t2 + np.sqrt(1.0 - np.dot(e_t2, e_t2)) * (-m)
    f1 = lambda s: (a + s * r)[2] - float(screen.height(*(a + s * r)[:2]))
    s1 = brentq(f1, 0.0, 10.0 * t, xtol=1e-14)
    return (a + s1 * r)[:2]


def test_deformed_screen_independent_refraction_trace():
    z = np.zeros((5, 5))
    z[2, 2] = 3.0
    z[1, 3] = -2.0
    z[3, 1] = 1.5
    screen = SplineSurface(GX, GY, z)
    t, n = 3.0, 1.52
    m = _trace(screen, CoverGlass(t, n))
    o, r = _reflected_rays_screen()
    rng = np.random.default_rng(21)
    valid = np.argwhere(m.valid)
    assert len(valid) > 0.9 * m.status.size
    for j, i in valid[rng.choice(len(valid), 25, replace=False)]:
        ref = _independent_glass_hit(screen, t, n, o[j, i], r[j, i])
        np.testing.assert_allclose(m.screen_xy_mm[j, i], ref, rtol=0, atol=1e-8)


def test_setup_keys_round_trip_and_bad_values():
    s = default_setup().with_cover_glass(1.1, 1.52)
    assert s.screen.cover_glass == CoverGlass(1.1, 1.52)
    doc = s.to_dict()
    assert doc["screen"]["cover_glass_thickness_mm"] == 1.1 and doc["screen"]["cover_glass_index"] == 1.52
    back = parse_setup(doc)
    assert back.screen.cover_glass == CoverGlass(1.1, 1.52)
    doc["screen"].pop("cover_glass_index")
    assert parse_setup(doc).screen.cover_glass.index == 1.5  # the default when t > 0
    assert default_setup().screen.cover_glass.present is False
    assert "cover_glass" not in str(default_setup().to_dict()["screen"])
    for key, value, msg in (("cover_glass_thickness_mm", -0.5, "screen.cover_glass_thickness_mm must be ≥ 0"),
                            ("cover_glass_index", 1.0, "screen.cover_glass_index must be > 1"),
                            ("cover_glass_index", "1.5", "screen.cover_glass_index must be a number")):
        bad = default_setup().to_dict()
        bad["screen"][key] = value
        with pytest.raises(SetupError, match=msg.replace("(", r"\(")):
            parse_setup(bad)


def test_simulate_and_evaluate_with_glass_round_trip():
    """Simulate with a 3 mm glass on the deformed screen, evaluate with it (true screen model):
    the true (flat) sample comes back; ignoring the glass does not."""
    from pmdsim.evaluation.phase import ScreenCoordinates
    from pmdsim.evaluation.pipeline import evaluate_decoded
    from pmdsim.simulation import trace_setup_camera

    truth = default_setup().binned(10).with_bulge(3.0).with_cover_glass(3.0, 1.52)
    cam = "left"
    m = trace_setup_camera(truth, cam, store_points=True)
    z = np.zeros(m.valid.shape + (2,))
    dec = ScreenCoordinates(m.screen_xy_mm, m.valid, np.zeros(m.valid.shape, np.uint8), z, z, z)
    seed = (m.valid.shape[0] // 2, m.valid.shape[1] // 2)
    errs = {}
    for label, model in (("glass", truth), ("ignored", truth.with_cover_glass(0.0))):
        _, rec = evaluate_decoded(model, cam, dec, screen_model=truth.screen.surface, seed_pixel=seed,
                                  seed_height_mm=float(m.p_sample_mm[seed][2]))
        assert rec.reconstructed.sum() > 0.9 * m.valid.sum()
        errs[label] = np.nanmax(np.abs(rec.height_mm))  # the true sample is the plane z = 0
    assert errs["glass"] < 1e-6, errs
    assert errs["ignored"] > 1e-3, errs


def test_apparent_points_converge_to_tolerance_or_say_so():
    """The registration's inverse problem stops at 1e-9 mm: the ray from P towards the apparent
    point, traced through the glass by the forward tracer, reaches Q; with one step allowed the
    points are reported as not converged (and NaN), which register maps to
    RegistrationStatus.GLASS_NO_CONVERGENCE."""
    from pmdsim.evaluation.registration import RegistrationStatus
    from pmdsim.geometry.surface import SplineSurface

    screen = SplineSurface.from_bulge(np.linspace(0.0, 708.0, 3), np.linspace(0.0, 398.0, 3), 3.0)
    glass = CoverGlass(3.0, 1.52)
    rng = np.random.default_rng(4)
    q = np.column_stack([rng.uniform(50, 650, 40), rng.uniform(50, 350, 40), np.zeros(40)])
    q[:, 2] = screen.height(q[:, 0], q[:, 1])
    p = np.array([354.0, 199.0, -450.0]) + rng.uniform(-80, 80, (40, 3))
    app, conv = glass.apparent_points(screen, p, q, return_converged=True)
    assert conv.all() and np.isfinite(app).all()
    back, st = glass.trace(screen, p, app - p)
    assert (st == 0).all()
    np.testing.assert_allclose(back, q, atol=1e-8, rtol=0)
    one, conv1 = glass.apparent_points(screen, p, q, max_iter=1, return_converged=True)
    assert not conv1.any() and np.isnan(one).all()
    assert RegistrationStatus.GLASS_NO_CONVERGENCE == 4


def _bumps():
    z = np.zeros((5, 5))
    z[2, 2] = 3.0
    z[1, 3] = -2.0
    z[3, 1] = 1.5
    return SplineSurface(GX, GY, z)


@pytest.mark.parametrize("screen", [
    SplineSurface.from_bulge(GX, GY, 3.0),
    _bumps(),
    PlaneSurface((0.0, 708.0), (0.0, 398.0)),
    # A screen that the camera sees only partly: pixels off its edges and next to them (the
    # tracer's scalar fallback and its status codes).
    SplineSurface.from_bulge(np.linspace(150.0, 500.0, 5), np.linspace(60.0, 300.0, 3), 2.0),
], ids=["bulge", "bumps", "plane", "partial"])
def test_tracer_glass_stage_equals_the_per_ray_glass_trace(screen):
    """The tracer's glass stage (warm-started foot-point Newton steps in the row kernel and the
    first rows, simulation.glass_rows) against CoverGlass.trace — the per-ray refraction kernel,
    started from the bare hit — of the glass-free trace's reflected rays (sample point →
    glass-free hit): the same status on every pixel (a failing bare hit keeps its code), the
    same points to 1e-12 mm."""
    glass = CoverGlass(3.0, 1.52)
    bare = _trace(screen, None, store_points=True)
    traced = _trace(screen, glass, store_points=True)
    ok = bare.status == Status.VALID
    T_screen_sample = T_WORLD_SCREEN.inv() @ T_WORLD_SAMPLE
    o = T_screen_sample.apply(bare.p_sample_mm[ok])
    q0 = bare.q_screen_mm[ok]
    q, st = glass.trace(screen, o, q0 - o, q0)
    expect = bare.status.copy()
    expect[ok] = np.where(st == 0, Status.VALID, Status.SCREEN_PARALLEL + np.minimum(st, 3) - 1)
    assert ok.sum() > 1000
    np.testing.assert_array_equal(traced.status, expect)
    good = st == 0
    np.testing.assert_allclose(traced.screen_xy_mm[ok][good], q[good, :2], atol=1e-12, rtol=0)
    np.testing.assert_allclose(traced.q_screen_mm[ok][good], q[good], atol=1e-12, rtol=0)
