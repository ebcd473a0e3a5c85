"""The fused render-and-decode path (evaluation/synthetic_decode.py) against the two-step path it
replaces: render every image with simulation.render.render_images (uint8/uint16 arrays), decode
them with evaluation.pipeline.decode_images. Every output array must agree bit for bit (NaN in
the same places), with and without noise, for 8 and 16 bits, for periods not given coarsest first,
and for pixels that miss the screen (black)."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation.pipeline import decode_images, decode_simulated
from pmdsim.evaluation.synthetic_decode import decode_rendered_fringes
from pmdsim.setup import default_setup
from pmdsim.simulation.render import noise_generator, render_images, trace_setup_camera


def _two_step(setup, camera, mapping, stream=None):
    images: dict = {}
    for spec, img in render_images(setup, camera, mapping, stream=stream):
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    return decode_images(setup, images)


def _assert_identical(a, b):
    for name in ("screen_xy_mm", "valid", "flags", "std_xy_mm", "modulation", "offset"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and x.dtype == y.dtype, name
        # bit for bit: the same bytes (NaN patterns included), not a tolerance
        assert np.array_equal(x.view(np.uint8), y.view(np.uint8)), f"{name} differs in {np.sum(x != y)} entries"


@pytest.fixture(scope="module")
def traced():
    from pmdsim.simulation.trace import Mapping, Status

    s = default_setup().binned(8).with_bulge(3.0)
    maps = {}
    for cam in s.cameras:
        m = trace_setup_camera(s, cam)
        # every pixel of this setup sees the screen: a corner block misses the sample instead
        status, xy = m.status.copy(), m.screen_xy_mm.copy()
        status[:20, :30] = Status.SAMPLE_OUTSIDE
        xy[:20, :30] = np.nan
        maps[cam] = Mapping(xy, status)
    return s, maps


@pytest.mark.parametrize("changes", [
    {},
    {"noise_std": 2.5, "seed": 7},
    {"bit_depth": 16, "noise_std": 40.0},
    # display order not coarsest first: the noise is drawn in display order, decoded coarse → fine
    {"periods_x_mm": (48.0, 720.0, 2.0), "periods_y_mm": (28.0, 2.0, 420.0), "noise_std": 1.0, "n_shifts": 5},
])
def test_fused_path_equals_render_then_decode(traced, changes):
    s0, maps = traced
    s = s0.with_patterns(**changes) if changes else s0
    for stream in (None, 3):
        for cam, m in maps.items():
            ref = _two_step(s, cam, m, stream=stream)
            got = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, cam, stream=stream))
            _assert_identical(got, ref)
            # the same with every pixel sent through the libm fallback (tie guard 0.5 grey levels)
            p = s.patterns
            exact = decode_rendered_fringes(m.screen_xy_mm, m.valid, p.sequence, s.screen.size_mm,
                                            bit_depth=p.bit_depth, noise_std=p.noise_std,
                                            rng=noise_generator(s, cam, stream=stream), tie_guard=0.5,
                                            decoder_noise_std=float(np.hypot(p.noise_std, 1 / np.sqrt(12))))
            _assert_identical(exact, ref)
            # only every 3rd pixel: the same values as the full decode there (noise fields drawn in full)
            sub = decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, cam, stream=stream),
                                   pixel_stride=3)
            _assert_identical(sub, type(ref)(**{k: v[::3, ::3] for k, v in vars(ref).items()}))
            assert 0 < ref.valid.sum() < ref.valid.size  # both decoded and black/flagged pixels are exercised


def test_black_and_saturated_pixels_are_flagged_as_by_the_decoder(traced):
    s, maps = traced
    m = maps["left"]
    valid = m.valid.copy()
    valid[::3] = False  # a third of the rows see no screen: black, DARK
    s2 = s.with_patterns(mean_level=0.6, amplitude=0.45)  # peaks at 1.05·F: clipped, SATURATED
    images: dict = {}
    from pmdsim.simulation.patterns import render_period
    for d, periods in (("x", s2.patterns.sequence.periods_x_mm), ("y", s2.patterns.sequence.periods_y_mm)):
        for p in periods:
            images[(d, p)] = list(render_period(m.screen_xy_mm, valid, d, p, s2.patterns.sequence))
    ref = decode_images(s2, images)
    got = decode_simulated(s2, m.screen_xy_mm, valid)
    _assert_identical(got, ref)
    assert not got.valid[::3].any()
    from pmdsim.evaluation.phase import PhaseFlag
    assert np.any(got.flags & np.uint8(PhaseFlag.SATURATED))


def test_noise_needs_a_generator_and_imaging_is_refused(traced):
    s, maps = traced
    m = maps["left"]
    with pytest.raises(ValueError, match="rng"):
        decode_rendered_fringes(m.screen_xy_mm, m.valid, s.patterns.sequence, s.screen.size_mm, noise_std=1.0)
    with pytest.raises(ValueError, match="imaging"):
        decode_simulated(s.with_imaging(f_number=4.0), m.screen_xy_mm, m.valid)


def test_fast_sincos_matches_libm():
    """The vectorised sin/cos of the renderer against numpy's (libm) over the phases it gets
    (|φ| ≤ 1e5 rad: 2π·x/p for x within ±16 m at p = 1 mm), including the quadrant edges."""
    from pmdsim.geometry.fast_trig import sincos_into

    rng = np.random.default_rng(1)
    k = np.arange(-4, 5)
    phi = np.concatenate([rng.uniform(-1e5, 1e5, 400_000), rng.uniform(-10, 10, 400_000),
                          (k[:, None] * np.pi / 4 + np.array([-1e-12, 0, 1e-12])).ravel(), [0.0, -0.0]])
    s, c = np.empty_like(phi), np.empty_like(phi)
    sincos_into(phi, s, c)
    # 4e-16 absolute (≈ 2 ulp of 1): moves a 16-bit grey level by < 65535·2·4e-16 ≈ 5e-11, far
    # inside the renderer's tie guard of 1e-7 grey levels
    assert np.max(np.abs(s - np.sin(phi))) < 4e-16
    assert np.max(np.abs(c - np.cos(phi))) < 4e-16


def _observations_reference(truth):
    """The calibration observations as computed before the fused path: every pose traced, its
    full images rendered and decoded, every stride-th pixel kept by observations_from_mapping."""
    from pmdsim.calibration import observations_from_mapping
    from pmdsim.simulation.trace import trace_camera

    cal = truth.calibration
    out = []
    for k, (_, T) in enumerate(cal.mirror_poses(truth.sample)):
        for cam, cs in truth.cameras.items():
            m = trace_camera(cs.camera, cs.T_world_cam, T, cal.mirror_surface(), truth.screen.T_world_screen,
                             truth.screen.surface)
            dec = _two_step(truth, cam, m, stream=k + 1)
            out.append(observations_from_mapping(cam, k, dec.screen_xy_mm, dec.valid, stride=cal.observation_stride_px,
                                                 screen_std_xy_mm=dec.std_xy_mm))
    return out


def test_calibration_observations_decode_only_the_used_pixels_bit_for_bit():
    """simulate_calibration_observations decodes only the stride-th pixels (fused path) and, with
    an image sink, renders and decodes full images (two-step path): both equal the reference."""
    from pmdsim.studies.calibration_data import simulate_calibration_observations

    truth = default_setup().binned(8).with_bulge(2.0).with_patterns(noise_std=1.5, seed=11)
    ref = _observations_reference(truth)
    sunk = []
    for got in (simulate_calibration_observations(truth),
                simulate_calibration_observations(truth, image_sink=lambda k, spec, img: sunk.append(k))):
        assert len(got) == len(ref)
        for g, r in zip(got, ref):
            assert (g.camera, g.pose_index) == (r.camera, r.pose_index)
            for name in ("uv_px", "q_screen_mm", "q_std_mm"):
                a, b = getattr(g, name), getattr(r, name)
                assert a.shape == b.shape and a.shape[0] > 100, name
                assert np.array_equal(a, b), name
    n_images = len(truth.patterns.sequence.frames())
    assert len(sunk) == len(ref) * n_images  # the sink saw every image of every pose and camera


def test_parallel_and_serial_kernels_agree(traced, monkeypatch):
    """Images of ≥ _SERIAL_BELOW_PX pixels go through the parallel kernel: force it here."""
    import pmdsim.evaluation.synthetic_decode as sd

    s0, maps = traced
    s = s0.with_patterns(noise_std=2.0)
    m = maps["right"]
    ref = _two_step(s, "right", m, stream=2)
    monkeypatch.setattr(sd, "_SERIAL_BELOW_PX", 0)
    _assert_identical(decode_simulated(s, m.screen_xy_mm, m.valid, rng=noise_generator(s, "right", stream=2)), ref)
