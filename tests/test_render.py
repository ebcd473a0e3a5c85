"""Fringe rendering: render → decode round trip against the traced mapping, determinism."""

import numpy as np
import pytest

from pmdsim.geometry.camera import Camera
from pmdsim.simulation.patterns import FringeSequence, PatternFrame, render
from pmdsim.setup import CameraSetup, default_setup
from pmdsim.simulation import image_specs, render_images, trace_setup_camera


def _small_setup(bulge_mm=3.0, **pattern_kw):
    s = default_setup().with_bulge(bulge_mm)
    cams = {
        name: CameraSetup(Camera(240, 150, 550.0, 550.0, 120.0, 75.0), cs.pose) for name, cs in s.cameras.items()
    }
    from dataclasses import replace

    p = s.patterns
    if pattern_kw:
        seq = replace(p.sequence, **{k: v for k, v in pattern_kw.items() if k in ("n_shifts", "periods_x_mm", "periods_y_mm")})
        p = replace(p, sequence=seq, **{k: v for k, v in pattern_kw.items() if k in ("bit_depth", "noise_std", "seed")})
    return replace(s, cameras=cams, patterns=p)


def _nstep_decode(stack):
    """Independent N-step decoding: φ = atan2(Σ I sin δ, Σ I cos δ) for I_k = A + B cos(φ − δ_k)."""
    n = stack.shape[0]
    delta = 2 * np.pi * np.arange(n) / n
    s = np.tensordot(np.sin(delta), stack.astype(float), axes=1)
    c = np.tensordot(np.cos(delta), stack.astype(float), axes=1)
    return np.mod(np.arctan2(s, c), 2 * np.pi)


def _unwrap(phases, periods):
    coord = periods[0] * phases[0] / (2 * np.pi)
    for phi, p in zip(phases[1:], periods[1:]):
        frac = p * phi / (2 * np.pi)
        coord = frac + p * np.round((coord - frac) / p)
    return coord


def _max_phase_error_per_grey_level(n, amplitude_grey):
    """First-order bound of the N-step phase error from rounding (|ε_k| ≤ ½ grey level):
    δφ = 2/(N·B)·Σ_k ε_k sin(δ_k − φ)  ⇒  |δφ| ≤ 1/(N·B)·max_φ Σ_k |sin(δ_k − φ)|."""
    phi = np.linspace(0, 2 * np.pi, 20001)
    delta = 2 * np.pi * np.arange(n) / n
    worst = np.max(np.sum(np.abs(np.sin(delta[:, None] - phi[None, :])), axis=0))
    return worst / (n * amplitude_grey)


@pytest.mark.parametrize("n_shifts,bit_depth", [(4, 8), (3, 8), (8, 8), (4, 16)])
def test_render_decode_round_trip_within_quantisation_bound(n_shifts, bit_depth):
    setup = _small_setup(n_shifts=n_shifts, bit_depth=bit_depth)
    m = trace_setup_camera(setup, "left")
    assert m.valid.all()
    images = {}
    for spec, img in render_images(setup, "left", m):
        assert img.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
        images.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    seq = setup.patterns.sequence
    amp_grey = seq.amplitude * (2**bit_depth - 1)
    # 1 % slack for the second-order term of the error expansion.
    dphi = 1.01 * _max_phase_error_per_grey_level(n_shifts, amp_grey)
    for axis, direction in enumerate("xy"):
        periods = seq.periods(direction)
        phases = [_nstep_decode(np.array(images[(direction, p)])) for p in periods]
        coord = _unwrap(phases, periods)
        err = np.abs(coord - m.screen_xy_mm[..., axis])
        bound = periods[-1] * dphi / (2 * np.pi)
        assert err.max() <= bound, (direction, err.max(), bound)
        # And the error is really quantisation: unquantised rendering is exact.
    frame = PatternFrame("x", seq.periods_x_mm[-1], 1, n_shifts)
    assert frame.shift_rad == pytest.approx(2 * np.pi / n_shifts)


def test_phase_convention():
    # I_k = A + B cos(2π c/p − δ_k): at c = 0 shift 0 is maximal; at c = p/4 shift k = N/4 is
    # maximal; at c = p/2 shift 0 is minimal.
    seq = FringeSequence((100.0,), (100.0,), n_shifts=4, mean_level=0.5, amplitude=0.5)
    xy = np.array([[[0.0, 0.0], [25.0, 0.0], [50.0, 0.0]]])
    ok = np.ones((1, 3), bool)
    i0 = render(xy, ok, PatternFrame("x", 100.0, 0, 4), seq)
    i1 = render(xy, ok, PatternFrame("x", 100.0, 1, 4), seq)
    assert i0[0, 0] == 255 and i1[0, 1] == 255 and i0[0, 2] == 0
    # Direction y reads the screen's y coordinate.
    iy = render(xy[..., ::-1].copy(), ok, PatternFrame("y", 100.0, 0, 4), seq)
    np.testing.assert_array_equal(iy, i0)


def test_invalid_pixels_are_black_and_images_deterministic():
    setup = _small_setup()
    m = trace_setup_camera(setup, "right")
    valid = m.valid.copy()
    valid[:10] = False
    frame = PatternFrame("y", 35.0, 2, 4)
    a = render(m.screen_xy_mm, valid, frame, setup.patterns.sequence)
    b = render(m.screen_xy_mm, valid, frame, setup.patterns.sequence)
    assert (a[:10] == 0).all() and (a[10:] > 0).all()
    np.testing.assert_array_equal(a, b)


def test_noise_is_seeded_and_has_the_requested_spread():
    setup = _small_setup(noise_std=3.0, seed=7)
    m = trace_setup_camera(setup, "left")
    imgs1 = [img for _, img in render_images(setup, "left", m)]
    imgs2 = [img for _, img in render_images(setup, "left", m)]
    for a, b in zip(imgs1, imgs2):
        np.testing.assert_array_equal(a, b)
    clean = [img for _, img in render_images(_small_setup(), "left", m)]
    diff = np.concatenate([(a.astype(float) - c).ravel() for a, c in zip(imgs1, clean)])
    # Var(noise + rounding difference) ≈ σ² + 1/12 ± a few percent.
    assert abs(diff.std() - np.sqrt(9 + 1 / 12)) < 0.1
    # Another seed gives other images.
    other = [img for _, img in render_images(_small_setup(noise_std=3.0, seed=8), "left", m)]
    assert any((a != b).any() for a, b in zip(imgs1, other))


def test_image_specs_cover_the_sequence():
    setup = _small_setup()
    specs = image_specs(setup, "left")
    seq = setup.patterns.sequence
    assert len(specs) == (len(seq.periods_x_mm) + len(seq.periods_y_mm)) * seq.n_shifts
    assert len({s.file for s in specs}) == len(specs)
    assert specs[0].file == "left_x_p0_s0.png"


def test_render_rejects_bad_input():
    seq = FringeSequence((100.0,), (100.0,))
    with pytest.raises(ValueError, match="bit_depth"):
        render(np.zeros((2, 2, 2)), np.ones((2, 2), bool), PatternFrame("x", 100.0, 0, 4), seq, bit_depth=12)
    with pytest.raises(ValueError, match="shape|\\(H, W"):
        render(np.zeros((2, 2)), np.ones((2, 2), bool), PatternFrame("x", 100.0, 0, 4), seq)
    with pytest.raises(ValueError, match="n_shifts"):
        FringeSequence((100.0,), (100.0,), n_shifts=2)


def test_render_period_equals_single_frames():
    """The stacked renderer (one sine/cosine per pixel) gives the single-frame renderer's images
    (up to a grey level where a value falls on a rounding tie within 1e-12)."""
    from pmdsim.simulation.patterns import render_period

    setup = _small_setup()
    m = trace_setup_camera(setup, "left")
    seq = setup.patterns.sequence
    for direction in "xy":
        for p in seq.periods(direction):
            stack = render_period(m.screen_xy_mm, m.valid, direction, p, seq)
            for k in range(seq.n_shifts):
                single = render(m.screen_xy_mm, m.valid, PatternFrame(direction, p, k, seq.n_shifts), seq)
                diff = np.abs(stack[k].astype(int) - single)
                assert diff.max() <= 1 and (diff > 0).mean() < 1e-3


@pytest.mark.parametrize("bit_depth, noise_std", [(8, 0.0), (8, 2.0), (16, 30.0)])
def test_render_period_is_the_closed_form_with_libm_trig(bit_depth, noise_std):
    """render_period (vectorised sin/cos + libm fallback near rounding boundaries) against the
    closed form evaluated in numpy with math.sin/math.cos (libm), the same operation order:
    I_k = clip(floor(F·(A + B·(cos φ cos δ_k + sin φ sin δ_k)) + noise + 0.5), 0, F), 0 where invalid.
    Pixels at x = 0 and x = p/4 put the value on a tie (F·A + ~1e-14), i.e. through the fallback."""
    import math

    from pmdsim.simulation.patterns import render_period

    seq = FringeSequence((720.0, 48.0, 2.0), (420.0, 28.0, 2.0), n_shifts=4, mean_level=0.5, amplitude=0.45)
    rng = np.random.default_rng(4)
    h, w = 64, 96
    xy = rng.uniform(-50.0, 760.0, (h, w, 2))
    ok = rng.random((h, w)) > 0.1
    for p in (720.0, 48.0, 2.0):
        xy[0, :10, 0] = 0.0
        xy[1, :10, 0] = p / 4
        full = float(2**bit_depth - 1)
        delta = 2.0 * np.pi * np.arange(4) / 4
        noise_rng = np.random.default_rng(9) if noise_std > 0 else None
        stack = render_period(xy, ok, "x", p, seq, bit_depth=bit_depth, noise_std=noise_std, rng=noise_rng)
        ref_rng = np.random.default_rng(9)
        fields = [ref_rng.normal(0.0, noise_std, (h, w)) for _ in range(4)] if noise_std > 0 else None
        phi = (2.0 * np.pi / p) * xy[..., 0]
        c = np.vectorize(math.cos)(phi)
        s = np.vectorize(math.sin)(phi)
        for k in range(4):
            # δ's cosines as render_period takes them (np.cos of the array)
            val = full * (seq.mean_level + seq.amplitude * (c * np.cos(delta)[k] + s * np.sin(delta)[k]))
            if fields is not None:
                val = val + fields[k]
            ref = np.where(ok, np.clip(np.floor(val + 0.5), 0.0, full), 0.0)
            assert stack.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
            assert np.array_equal(stack[k], ref.astype(stack.dtype)), (p, k, int(np.sum(stack[k] != ref)))
