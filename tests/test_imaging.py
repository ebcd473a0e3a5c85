"""Image-formation effects (issue 13): each against something they did not produce.

Truths: the existing ideal renderer (everything off, bit for bit), the TOML reader (round trip),
rays traced through points of the entrance pupil to the pixel's point on the focal plane
(defocus footprint, its centroid, the blur of every harmonic — with the tracer, or with a plane
mirror written here in numpy for the lens transfer and its contrast reversals), numpy.gradient
(pixel Jacobian), the binomial series of (A + B·cos θ)^γ (gamma ripple), and Monte Carlo over
seeds (noise model).
All on the Table 1 setup binned 8 × 8 (240 × 150 px).
"""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest
from scipy.special import binom

from pmdsim.errors import SetupError
from pmdsim.simulation.imaging import decoder_response
from pmdsim.evaluation.pipeline import decode_images
from pmdsim.evaluation.phase import wrapped_phase
from pmdsim.geometry.transform import RigidTransform
from pmdsim.setup import ImagingSetup, default_setup, parse_setup
from pmdsim.simulation.imaging import imaging_maps, render_period_imaging
from pmdsim.simulation.optics import pixel_jacobian
from pmdsim.simulation.patterns import render_period
from pmdsim.simulation.render import render_images, trace_setup_camera
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.trace import trace_rays

CAM = "left"


@pytest.fixture(scope="module")
def base():
    return default_setup().binned(8).with_bulge(3.0)


@pytest.fixture(scope="module")
def mapping(base):
    return trace_setup_camera(base, CAM, store_points=True)


def _images(setup, mapping, **kw):
    out = {}
    for spec, img in render_images(setup, CAM, mapping, **kw):
        out.setdefault((spec.frame.direction, spec.frame.period_mm), []).append(img)
    return out


# ------------------------------------------------------------------ setup
def test_imaging_toml_round_trip_and_errors(base):
    s = base.with_imaging(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, display_gamma=2.2, linearise=True,
                          emission_exponent=1.5, screen_pixel_pitch_mm=0.27, screen_fill_factor=0.8, f_number=8.0,
                          pixel_area=True)
    assert parse_setup(tomllib.loads(s.to_toml())) == s
    doc = tomllib.loads(s.to_toml())
    doc["imaging"]["bit_depth"] = 14
    with pytest.raises(SetupError, match=r"imaging\.bit_depth must be one of \[8, 10, 12, 16\], got 14"):
        parse_setup(doc)
    doc["imaging"]["bit_depth"] = 12
    doc["imaging"]["f_numbr"] = 8.0
    with pytest.raises(SetupError, match=r"unknown key imaging\.f_numbr \(did you mean imaging\.f_number\?"):
        parse_setup(doc)
    del doc["imaging"]["f_numbr"]
    doc["imaging"]["screen_fill_factor"] = 1.5
    with pytest.raises(SetupError, match=r"imaging\.screen_fill_factor must be ≤ 1, got 1\.5"):
        parse_setup(doc)


# ------------------------------------------------------------------ everything off
@pytest.mark.parametrize("imaging", [None, ImagingSetup()])
def test_everything_off_is_the_ideal_renderer_bit_for_bit(base, mapping, imaging):
    s = base.with_patterns(noise_std=1.5, seed=7)
    s = s if imaging is None else s.with_imaging(imaging)
    got = _images(s, mapping)
    rng = np.random.default_rng([7, 0])
    seq = s.patterns.sequence
    for d in ("x", "y"):
        for p in seq.periods(d):
            ref = render_period(mapping.screen_xy_mm, mapping.valid, d, p, seq, bit_depth=8, noise_std=1.5, rng=rng)
            np.testing.assert_array_equal(np.stack(got[(d, p)]), ref)


# ------------------------------------------------------------------ optics
def _pupil_quadrature(D, n_r=8, n_phi=16):
    """Quadrature of the uniform disc of diameter D: Gauss–Legendre in u = r² (uniform on the
    disc), equally spaced angles; exact for the low-order moments the tests take."""
    x, w = np.polynomial.legendre.leggauss(n_r)
    u = (x + 1) / 2 * (D / 2) ** 2
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    r = np.sqrt(u)[:, None]
    pts = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros((n_r, n_phi))], -1).reshape(-1, 3)
    wts = np.repeat(w / 2 / n_phi, n_phi)
    return pts, wts


def _trace_pupil(s, m, v, u, pts, focus_mm=None):
    """Screen points of the rays from pupil points ``pts`` (camera frame) through the pixel's
    point on the focal plane z_cam = ``focus_mm`` (None: its own sample point), by the tracer."""
    cs = s.cameras[CAM]
    p_cam = (cs.T_world_cam.inv() @ s.sample.T_world_sample).apply(m.p_sample_mm[v, u])
    if focus_mm is not None:
        p_cam = p_cam * (focus_mm / p_cam[2])
    T_screen_sample = s.screen.T_world_screen.inv() @ s.sample.T_world_sample
    return np.array([trace_rays((p_cam - ak)[None], np.ones(1, bool),
                                s.sample.T_world_sample.inv() @ cs.T_world_cam @ RigidTransform(np.eye(3), ak),
                                T_screen_sample, s.sample.surface, s.screen.surface).screen_xy_mm[0] for ak in pts])


def test_defocus_footprint_matches_rays_traced_through_the_pupil(base, mapping):
    f_number, focal = 8.0, 25.0
    s = base.with_imaging(f_number=f_number, focal_length_mm=focal)
    from pmdsim.simulation.optics import defocus_covariance

    cs = s.cameras[CAM]
    cov = defocus_covariance(cs.T_world_cam, s.sample.T_world_sample, s.screen.T_world_screen,
                             mapping.p_sample_mm, mapping.q_screen_mm, focal / f_number, s.screen.surface)
    pts, wts = _pupil_quadrature(focal / f_number)
    for v, u in [(20, 30), (75, 120), (130, 200)]:
        assert mapping.valid[v, u]
        hits = _trace_pupil(s, mapping, v, u, pts)
        mean = wts @ hits
        ref = np.einsum("k,ki,kj->ij", wts, hits - mean, hits - mean)
        # First-order model: relative error O((D/s)²) ≈ 1e-4; the quadrature is exact to ≈ 1e-6.
        np.testing.assert_allclose(cov[v, u], ref, rtol=1e-3, atol=1e-3 * np.abs(ref).max())
        np.testing.assert_allclose(mean, mapping.screen_xy_mm[v, u], atol=0.01 * np.sqrt(ref.max()))


def test_pixel_jacobian_is_numpy_gradient_in_the_interior(mapping):
    J = pixel_jacobian(mapping.screen_xy_mm)
    gy, gx = np.gradient(mapping.screen_xy_mm, axis=(0, 1))
    ok = np.isfinite(gx).all(-1) & np.isfinite(gy).all(-1)
    np.testing.assert_allclose(J[..., :, 0][ok], gx[ok], rtol=1e-12)
    np.testing.assert_allclose(J[..., :, 1][ok], gy[ok], rtol=1e-12)


def _sharp(coord, period, A, B, shifts, response=None):
    d = A + B * np.cos(2 * np.pi * coord[..., None] / period - shifts)
    return d if response is None else response.forward(d)


def test_blur_of_every_harmonic_matches_rays_through_the_pupil_and_the_pixel(base, mapping):
    """Display gamma 2.2 (harmonics up to the 6th), f/8 with the default focal plane, and pixel
    area: the kernel's noise-free 16-bit values against the displayed pattern averaged over rays
    traced through the pupil disc (24 × 48 points) to the pixel's point on the focal plane and
    over the pixel box (Gauss–Legendre), with the tracer — nothing of the code's footprint maps.
    The first-order footprint neglects terms O((D/s)²) ≈ 6e-5 relative; measured error ≤ 2e-4."""
    from pmdsim.simulation.display import display_response

    s = base.with_patterns(bit_depth=16).with_imaging(display_gamma=2.2, f_number=8.0, pixel_area=True)
    maps = imaging_maps(s, CAM, mapping)
    seq = s.patterns.sequence
    period = 8.0
    stack = render_period_imaging(maps, mapping.screen_xy_mm, mapping.valid, "x", period, seq,
                                  SensorModel.from_setup(s), None).astype(float) / 65535.0
    resp = display_response(2.2)
    pts, wts = _pupil_quadrature(s.imaging.focal_length_mm / 8.0, n_r=24, n_phi=48)
    box, bw = np.polynomial.legendre.leggauss(8)
    box, bw = box / 2, bw / 2  # Gauss–Legendre on [−½, ½]
    shifts = 2 * np.pi * np.arange(4) / 4
    J = np.stack(np.gradient(mapping.screen_xy_mm[..., 0], axis=(1, 0)), -1)  # d x_q / d(u, v)
    for v, u in [(20, 30), (75, 120), (130, 200)]:
        xq = _trace_pupil(s, mapping, v, u, pts, maps.focus_distance_mm)[:, 0]
        ju, jv = J[v, u]
        c = xq[None, None, :] + box[:, None, None] * ju + box[None, :, None] * jv
        ref = np.einsum("abzk,a,b,z->k", _sharp(c, period, seq.mean_level, seq.amplitude, shifts, resp), bw, bw, wts)
        np.testing.assert_allclose(stack[:, v, u], ref, atol=3e-4)


def _plane_mirror_pupil_hits(s, m, focus_mm, pix, n_r=24, n_phi=64):
    """Screen x of rays from a uniform pupil disc (camera x–y plane, diameter f/N) through each
    pixel's point on the focal plane z_cam = focus_mm, reflected at the planar sample and
    intersected with the planar screen — numpy, this test's own geometry. Returns the hits
    (len(pix), K) and the quadrature weights (K,)."""
    cs = s.cameras[CAM]
    R, O = cs.T_world_cam.rotation, cs.T_world_cam.translation
    D = s.imaging.focal_length_mm / s.imaging.f_number
    Ts, Tq = s.sample.T_world_sample, s.screen.T_world_screen
    ns, ps0, nq, pq0 = Ts.rotation[:, 2], Ts.translation, Tq.rotation[:, 2], Tq.translation
    pts, wts = _pupil_quadrature(D, n_r, n_phi)
    A = O + pts[:, :1] * R[:, 0] + pts[:, 1:2] * R[:, 1]
    out = []
    for v, u in pix:
        P = Ts.apply(m.p_sample_mm[v, u])
        d = (P - O) / np.linalg.norm(P - O)
        F = O + focus_mm / (d @ R[:, 2]) * d
        dirs = F - A
        X = A + (((ps0 - A) @ ns) / (dirs @ ns))[:, None] * dirs
        r = dirs - 2 * (dirs @ ns)[:, None] * ns
        Q = X + (((pq0 - X) @ nq) / (r @ nq))[:, None] * r
        out.append(((Q - pq0) @ Tq.rotation)[:, 0])
    return np.array(out), wts


@pytest.fixture(scope="module")
def flat():
    s = default_setup().binned(8).with_patterns(bit_depth=16).with_imaging(f_number=8.0)
    return s, trace_setup_camera(s, CAM, store_points=True)


def test_lens_transfer_matches_a_pupil_sampled_plane_mirror_with_its_contrast_reversals(flat):
    """f/8, one focal plane (default: the principal point's sample point), planar sample and
    screen: the decoded complex first harmonic B·e^{iφ}/B₀ of noise-free 16-bit images against the
    pupil average of exp(2πi·x_q/p) over rays traced here (:func:`_plane_mirror_pupil_hits`).
    At p = 2 mm the reference reverses the contrast on most pixels (Re T·e^{−iφ_chief} < 0): the
    model must agree in sign and size. Bound 4e-3: the footprint's neglected second-order terms,
    O(D/s₁) = 3.1/420 relative in σ, times max|x·T'(x)| ≈ 0.6 (measured ≤ 7e-4)."""
    from pmdsim.evaluation.phase import wrapped_phase as wp

    s, m = flat
    maps = imaging_maps(s, CAM, m)
    cs = s.cameras[CAM]
    # The default focus distance: the principal ray meets the sample plane (numpy, here).
    R, O = cs.T_world_cam.rotation, cs.T_world_cam.translation
    ray = R @ np.array([0.0, 0.0, 1.0])
    Ts = s.sample.T_world_sample
    t = ((Ts.translation - O) @ Ts.rotation[:, 2]) / (ray @ Ts.rotation[:, 2])
    step = np.abs(np.diff(((cs.T_world_cam.inv() @ Ts).apply(m.p_sample_mm))[..., 2], axis=1))
    assert abs(maps.focus_distance_mm - t) <= np.nanmax(step)  # the nearest traced pixel's
    pix = [(v, u) for v in range(5, 150, 20) for u in range(5, 240, 20) if m.valid[v, u]]
    hits, wts = _plane_mirror_pupil_hits(s, m, maps.focus_distance_mm, pix)
    vv, uu = np.array(pix).T
    seq = s.patterns.sequence
    for p in (2.0, 4.0):
        st = render_period_imaging(maps, m.screen_xy_mm, m.valid, "x", p, seq, SensorModel.from_setup(s), None)
        res = wp(st, max_value=65535)
        model = (res.modulation * np.exp(1j * res.phase))[vv, uu] / (seq.amplitude * 65535)
        ref = np.exp(2j * np.pi * hits / p) @ wts
        assert np.abs(model - ref).max() < 4e-3
        if p == 2.0:
            assert ((ref * np.exp(-2j * np.pi * m.screen_xy_mm[vv, uu, 0] / p)).real < 0).mean() > 0.3


def test_decoder_corrects_or_flags_the_pixels_whose_contrast_the_lens_reversed(flat):
    """Finest period 2 mm at f/8: every pixel whose pupil-sampled transfer (numpy plane mirror) is
    reversed (Re T·e^{−iφ_chief} < −0.05) in x is corrected by π and marked ``reversed`` by the
    decoder, or flagged LOW_MODULATION (near a zero); with ``correct_reversal=False`` it is
    flagged with a reason, never decoded half a period off; at 4 mm, where nothing is reversed,
    every pixel decodes. (The corrected coordinates against the reference:
    tests/test_reversal.py.)"""
    from pmdsim.evaluation.phase import PhaseFlag, decode_direction

    s, m = flat
    imgs = _images(s, m)
    periods = s.patterns.sequence.periods_x_mm
    stacks = [np.stack(imgs[("x", p)]) for p in periods]
    dec = decode_direction(stacks, periods, s.screen.size_mm[0], 65535, correct_reversal=False)
    fixed = decode_direction(stacks, periods, s.screen.size_mm[0], 65535)
    pix = [(v, u) for v in range(2, 150, 4) for u in range(2, 240, 4) if m.valid[v, u]]
    hits, wts = _plane_mirror_pupil_hits(s, m, imaging_maps(s, CAM, m).focus_distance_mm, pix, 16, 32)
    vv, uu = np.array(pix).T
    t = (np.exp(2j * np.pi * hits / 2.0) @ wts * np.exp(-2j * np.pi * m.screen_xy_mm[vv, uu, 0] / 2.0)).real
    rev = t < -0.05
    assert rev.sum() > 100
    # Flagged with a reason: half a period off the coarser periods, or (near the zero) too little
    # modulation.
    reason = dec.flags[vv[rev], uu[rev]] & (PhaseFlag.UNWRAP_INCONSISTENT | PhaseFlag.LOW_MODULATION)
    assert np.all(reason != 0)
    low = (fixed.flags[vv[rev], uu[rev]] & PhaseFlag.LOW_MODULATION) != 0
    assert np.all(fixed.reversed[vv[rev], uu[rev]] | low)
    assert np.all(fixed.valid[vv[rev], uu[rev]] | low) and not low.all()
    assert not fixed.reversed[vv[t > 0.05], uu[t > 0.05]].any()
    # Not indiscriminate: with a 4 mm finest period (transfer ≈ 0.4–0.8, nowhere reversed) every
    # traced pixel decodes.
    s4 = s.with_patterns(periods_x_mm=(720.0, 48.0, 4.0))
    imgs4 = _images(s4, m)
    dec4 = decode_direction([np.stack(imgs4[("x", p)]) for p in (720.0, 48.0, 4.0)], (720.0, 48.0, 4.0),
                            s.screen.size_mm[0], 65535)
    assert dec4.valid[m.valid].all()


# ------------------------------------------------------------------ noise model
def test_monte_carlo_scatter_matches_the_sensor_noise_model(base, mapping):
    """40 seeds × ~8000 pixels: each pixel's sample σ has a relative standard error
    1/√(2·39) ≈ 11 %, the RMS over the pixels ≈ 0.1 %: a 10 % disagreement is resolved ~100×."""
    # Emission falloff cos³θ makes the modulation, hence σ, vary over the image (≈ ±15 %).
    s = base.with_imaging(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, dark_offset_dn=20.0,
                          emission_exponent=3.0)
    draws, sig = [], None
    for seed in range(40):
        dec = decode_images(s.with_patterns(seed=seed), response=decoder_response(s.with_patterns(seed=seed)), images=_images(s.with_patterns(seed=seed), mapping))
        draws.append(dec.screen_xy_mm)
        sig = dec.std_xy_mm if sig is None else sig
    draws = np.array(draws)
    ok = np.isfinite(draws).all(axis=(0, 3)) & np.isfinite(sig).all(-1)
    ok[::2] = False  # every other row: keep it quick and the pixels independent
    mc = draws.std(axis=0, ddof=1)
    for a in range(2):
        # In the lower and upper third of predicted σ separately: the prediction follows the
        # per-pixel modulation, not only the mean (≈ 2600 pixels each: ≈ 1.4 % standard error).
        lo, hi = np.quantile(sig[ok, a], [1 / 3, 2 / 3])
        assert sig[ok, a].max() / sig[ok, a].min() > 1.2
        for sel in (ok & (sig[..., a] <= lo), ok & (sig[..., a] >= hi)):
            ratio = np.sqrt(np.mean(mc[sel, a] ** 2) / np.mean(sig[sel, a] ** 2))
            assert abs(ratio - 1) < 0.10, ratio


# ------------------------------------------------------------------ display response
def _gamma_harmonic(n, A, B, gamma, terms=4000):
    """c_n of (A + B cos θ)^γ by the binomial series A^γ Σ_j C(γ, j) m^j cos^j θ (m = B/A) and
    cos^j θ = 2^{1−j} Σ C(j, (j−n)/2) cos nθ."""
    m = B / A
    j = np.arange(n, terms, 2)
    # log-space products avoid overflow of C(j, k) and underflow of 2^{1−j}·m^j.
    from scipy.special import gammaln
    log_bin = gammaln(j + 1) - gammaln((j - n) / 2 + 1) - gammaln((j + n) / 2 + 1)
    vals = binom(gamma, j) * np.exp(log_bin + j * np.log(m / 2) + np.log(2.0))
    return A**gamma * vals.sum()


def test_gamma_ripple_matches_closed_form_and_linearisation_returns_to_the_noise_floor(base, mapping):
    seq = base.patterns.sequence
    A, B, g = seq.mean_level, seq.amplitude, 2.2
    c1, c3, c5 = (_gamma_harmonic(n, A, B, g) for n in (1, 3, 5))
    amp_rad = abs(c5 - c3) / c1  # N = 4: harmonics 3 and 5 alias onto a 4φ ripple
    p = min(seq.periods_x_mm)
    sensor = dict(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0)
    s = base.with_imaging(display_gamma=g, **sensor)
    dec = decode_images(s, response=decoder_response(s), images=_images(s, mapping))
    phi = 2 * np.pi * mapping.screen_xy_mm[..., 0] / p
    err = (dec.screen_xy_mm[..., 0] - mapping.screen_xy_mm[..., 0]) * 2 * np.pi / p
    ok = np.isfinite(err)
    X = np.column_stack([np.sin(4 * phi[ok]), np.cos(4 * phi[ok]), np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(X, err[ok], rcond=None)
    assert abs(np.hypot(coef[0], coef[1]) / amp_rad - 1) < 0.10
    # Corrected: linearised with the simulated grey-level series → the decoder's noise floor.
    lin = base.with_imaging(display_gamma=g, linearise=True, **sensor)
    dec2 = decode_images(lin, response=decoder_response(lin), images=_images(lin, mapping))
    e2 = dec2.screen_xy_mm - mapping.screen_xy_mm
    ok2 = np.isfinite(e2).all(-1)
    rms = np.sqrt(np.mean(e2[ok2] ** 2, axis=0))
    floor = np.sqrt(np.mean(dec2.std_xy_mm[ok2] ** 2, axis=0))
    assert np.all(np.abs(rms / floor - 1) < 0.10), rms / floor


# ------------------------------------------------------------------ curved sample
def _dome(base, sag_mm):
    from dataclasses import replace

    from pmdsim.setup.model import SampleSetup

    g = tuple(np.linspace(0.0, 400.0, 5))
    X, Y = np.meshgrid(g, g)
    Z = -sag_mm * (1 - ((X - 200) ** 2 + (Y - 200) ** 2) / 200**2)  # a dome towards the cameras
    return replace(base, sample=SampleSetup(base.sample.pose, g, g, tuple(map(tuple, Z))))


def test_curved_sample_phase_bias_sign_and_scaling(base):
    """With a 2 mm dome the blur spot varies over the image; the footprint's centroid (hence
    the decoded coordinate) is offset from the chief ray's screen point by O(D²): checked
    against rays traced through the pupil (sign and size), ∝ 1/N² (f/4 vs f/8), and found in
    the decoded noise-free 16-bit images."""
    s = _dome(base.with_patterns(bit_depth=16, periods_x_mm=(720.0, 48.0, 8.0), periods_y_mm=(420.0, 28.0, 8.0)), 2.0)
    m = trace_setup_camera(s, CAM, store_points=True)
    pix = [(20, 30), (75, 120), (130, 200)]
    biases, traced_bias = {}, {}
    for fn in (4.0, 8.0):
        si = s.with_imaging(f_number=fn)
        maps = imaging_maps(si, CAM, m)
        sig = np.sqrt(maps.var_xy_mm2[..., 0][m.valid])
        assert sig.max() / sig.min() > 1.3  # the blur spot varies over the image
        pts, wts = _pupil_quadrature(si.imaging.focal_length_mm / fn)
        for v, u in pix:
            traced = wts @ _trace_pupil(s, m, v, u, pts, maps.focus_distance_mm) - m.screen_xy_mm[v, u]
            # The footprint model takes the sample as locally flat; with one focal plane the rays
            # meet this dome off P (the sample-side blur), which it neglects: 2.7 % measured at
            # f/4 (issue 20; pupil sampling for curved samples is not implemented). Bound 5 %.
            np.testing.assert_allclose(maps.centroid_xy_mm[v, u, 0], traced[0], rtol=0.05)
            traced_bias[fn, v, u] = traced[0]
        biases[fn] = maps.centroid_xy_mm[..., 0]
        # The decoded coordinate carries the bias (noise-free 16 bit: rounding ≤ p/(2π·B)).
        dec = decode_images(si, response=decoder_response(si), images=_images(si, m))
        ok = dec.valid
        got = dec.screen_xy_mm[..., 0] - m.screen_xy_mm[..., 0]
        bound = 8.0 / (2 * np.pi * dec.modulation[..., 0])  # finest period 8 mm: |Δφ| ≤ 1/B
        assert np.all(np.abs(got[ok] - maps.centroid_xy_mm[..., 0][ok]) <= bound[ok])
        assert np.median(maps.centroid_xy_mm[..., 0][ok]) > 5 * np.median(bound[ok])  # resolved
    ok = m.valid
    assert np.all(biases[4.0][ok] > 0)  # sign: along +x of the screen for this geometry
    # ∝ D² = (f/N)² in the traced rays themselves (the model is compared with them above).
    for v, u in pix:
        np.testing.assert_allclose(traced_bias[4.0, v, u], 4.0 * traced_bias[8.0, v, u], rtol=0.05)


def test_monte_carlo_slope_scatter_matches_the_decoder_sigma_propagated_to_the_normals(base, mapping):
    """The reconstructed normal is the bisector of −d and r = (q − p)/|q − p|: a screen error δq
    (screen x, y axes) turns r by (I − rrᵀ)·δq/s₂ and the normal by (I − nnᵀ)·δr/|r − d|
    (first order; the reconstructed point's own error, ~0.1 µm over s₂ ≈ 500 mm, is negligible).
    The decoder's σ of x_q and y_q propagated so (independent in x and y) against the scatter of
    the reconstructed normals over 40 seeds (perfect setup knowledge, 12-bit sensor); every
    other row, ≈ 17 000 pixels: a 10 % disagreement is resolved ≈ 50×."""
    from pmdsim.evaluation.pipeline import evaluate_decoded

    s = base.with_imaging(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0)
    normals, sig = [], None
    seed_px = (75, 120)
    for seed in range(40):
        sk = s.with_patterns(seed=seed)
        dec = decode_images(sk, response=decoder_response(sk), images=_images(sk, mapping))
        sig = dec.std_xy_mm if sig is None else sig
        _, rec = evaluate_decoded(sk, CAM, dec, screen_model=sk.screen.surface, seed_pixel=seed_px,
                                  seed_height_mm=float(mapping.p_sample_mm[seed_px][2]))
        normals.append(rec.n_sample)
    normals = np.array(normals)
    # Prediction from the true geometry (world frame; the sample frame is world-aligned here).
    T_ws, T_wp = s.sample.T_world_sample, s.screen.T_world_screen
    p = T_ws.apply(mapping.p_sample_mm)
    q = T_wp.apply(mapping.q_screen_mm)
    o = s.cameras[CAM].T_world_cam.translation
    d = (p - o) / np.linalg.norm(p - o, axis=-1, keepdims=True)
    s2 = np.linalg.norm(q - p, axis=-1)
    r = (q - p) / s2[..., None]
    n = r - d
    bis = np.linalg.norm(n, axis=-1)
    n = n / bis[..., None]
    eye = np.eye(3)
    Pr = eye - r[..., :, None] * r[..., None, :]
    Pn = eye - n[..., :, None] * n[..., None, :]
    G = np.einsum("...ij,...jk->...ik", Pn, Pr) / (bis * s2)[..., None, None]
    cov = np.zeros(p.shape[:2] + (3, 3))
    for a in range(2):
        col = G @ T_wp.rotation[:, a]
        cov += sig[..., a, None, None] ** 2 * col[..., :, None] * col[..., None, :]
    ok = np.isfinite(normals).all(axis=(0, 3)) & np.isfinite(cov).all(axis=(-1, -2))
    ok[::2] = False
    mc = normals.var(axis=0, ddof=1)
    for a in range(2):  # the normal's x and y components: the slopes
        ratio = np.sqrt(np.mean(mc[ok, a]) / np.mean(cov[ok, a, a]))
        assert abs(ratio - 1) < 0.10, ratio


def test_saturation_is_flagged_where_the_full_well_is_reached(base, mapping):
    """Exposure 1.06 (white at 106 % of the full well), shot noise negligible (full well 1e12 e⁻):
    a pixel saturates iff 1.06·(A + B·cos(φ − δ_k)) ≥ 1 for one of its samples (closed form
    from the traced phase), and the decoder flags exactly those pixels SATURATED."""
    from pmdsim.evaluation.phase import PhaseFlag

    s = base.with_imaging(bit_depth=12, full_well_e=1e12, exposure=1.06)
    dec = decode_images(s, response=decoder_response(s), images=_images(s, mapping))
    seq = s.patterns.sequence
    shifts = 2 * np.pi * np.arange(seq.n_shifts) / seq.n_shifts
    level = np.zeros(mapping.valid.shape)
    for d, a in (("x", 0), ("y", 1)):
        for p in seq.periods(d):
            phi = 2 * np.pi * mapping.screen_xy_mm[..., a] / p
            level = np.maximum(level, (1.06 * (seq.mean_level + seq.amplitude * np.cos(phi[..., None] - shifts))).max(-1))
    sat = (dec.flags & PhaseFlag.SATURATED) != 0
    margin = 1.0 / 4095  # rounding: levels within a grey level of full scale may go either way
    ok = mapping.valid & (np.abs(level - 1.0) > margin)
    assert sat[ok].sum() > 1000 and (~sat[ok]).sum() > 1000
    np.testing.assert_array_equal(sat[ok], level[ok] >= 1.0)
    assert not dec.valid[sat].any()


def test_effects_are_reproducible_and_streams_independent(base, mapping):
    s = base.with_imaging(bit_depth=12, full_well_e=10500.0, read_noise_e=6.0, display_gamma=2.2, f_number=8.0,
                          pixel_area=True)
    a = [img for _, img in render_images(s, CAM, mapping)]
    b = [img for _, img in render_images(s, CAM, mapping)]
    c = [img for _, img in render_images(s, CAM, mapping, stream=1)]
    assert all(x.dtype == np.uint16 and x.max() <= 4095 for x in a)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not any(np.array_equal(x, y) for x, y in zip(a, c))  # another stream, other noise


def test_simulate_writes_12_bit_images_in_16_bit_pngs(tmp_path, small_toml):
    """`pmdsim simulate` with `[imaging] bit_depth = 12`: 16-bit PNG files whose values stay
    within 0 … 4095, a manifest saying 16 (the files' depth), read back by `pmdsim evaluate`."""
    from click.testing import CliRunner
    from PIL import Image

    from pmdsim.cli import main

    setup = tmp_path / "s12.toml"
    setup.write_text(small_toml + "\n[imaging]\nbit_depth = 12\nfull_well_e = 10500.0\nread_noise_e = 6.0\n",
                     encoding="utf-8")
    r = CliRunner().invoke(main, ["simulate", "--setup", str(setup), "--out", str(tmp_path / "sim"), "--quiet"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "sim" / "manifest.json").read_text())
    assert doc["bit_depth"] == 16
    imgs = [np.asarray(Image.open(tmp_path / "sim" / e["file"])) for e in doc["images"]]
    assert all(a.dtype == np.uint16 for a in imgs) and max(int(a.max()) for a in imgs) <= 4095
    assert max(int(a.max()) for a in imgs) > 255
    r = CliRunner().invoke(main, ["evaluate", str(tmp_path / "sim"), "--setup", str(setup), "--out",
                                  str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output


def test_a_saturated_sample_is_pinned_at_full_scale_without_noise_and_flagged():
    """Closed form: a sample saturates iff exposure·(A + B·cos(2πc/p − δ_k)) ≥ 1 (its mean
    reaches the full well); it must then record exactly 2^bits − 1 in every noise draw, and the
    decoder flags the pixel SATURATED. Shot and read noise (≈ 44 DN) would otherwise scatter it."""
    from pmdsim.evaluation.phase import PhaseFlag
    from pmdsim.setup.fringes import FringeSequence
    from pmdsim.simulation.imaging import ImagingMaps

    im = ImagingSetup(bit_depth=12, full_well_e=10000.0, read_noise_e=40.0, exposure=1.25)
    sensor = SensorModel.from_values(im, 8, 0.0)
    shape = (40, 50)
    coord = np.zeros(shape + (2,))
    coord[..., 0] = np.linspace(0.0, 8.0, shape[0] * shape[1]).reshape(shape)
    A, B, period = 0.5, 0.45, 8.0
    maps = ImagingMaps(np.zeros(shape + (2,)), None, np.ones(shape), 0.0, np.array([A, B]))
    seq = FringeSequence((period,), (period,), n_shifts=4, mean_level=A, amplitude=B)
    shifts = 2 * np.pi * np.arange(4) / 4
    level = 1.25 * (A + B * np.cos(2 * np.pi * coord[..., 0, None] / period - shifts))  # (H, W, N)
    sat = np.moveaxis(level >= 1.0, -1, 0)
    # 6 σ below: σ² = g·mean + (g·σ_read)², g = 4095/FW → √(1677 + 268) ≈ 44.1 DN near full scale
    clear = np.moveaxis(level < 1.0 - 6 * 44.1 / 4095, -1, 0)
    assert sat.sum() > 500 and clear.sum() > 500
    for seed in range(3):
        out = render_period_imaging(maps, coord, np.ones(shape, bool), "x", period, seq, sensor,
                                    np.random.default_rng(seed))
        assert np.all(out[sat] == 4095)
        assert np.all(out[clear] < 4095)
        flags = wrapped_phase(out, max_value=4095).flags
        np.testing.assert_array_equal((flags & PhaseFlag.SATURATED) != 0, sat.any(0) | (out == 4095).any(0))
        assert ((flags & PhaseFlag.SATURATED) != 0)[sat.any(0)].all()


def test_downsampling_keeps_the_real_pixel_footprint():
    """`Setup.binned(K)` samples every K-th pixel of the same camera: the pixel-area footprint is
    the real pixel's. The Jacobian of a K = 8 mapping over its sampling step 8 against the K = 4
    one's (the mean of the 2 × 2 block whose centre is the K = 8 pixel's centre), and the TOML
    round trip of the step and the focus distance."""
    s = default_setup().with_imaging(pixel_area=True, focus_distance_mm=450.0)
    s8, s4 = s.binned(8), s.binned(4)
    assert (s8.imaging.sampling_step_px, s4.imaging.sampling_step_px) == (8, 4)
    assert parse_setup(tomllib.loads(s8.to_toml())) == s8
    j8 = imaging_maps(s8, CAM, trace_setup_camera(s8, CAM)).jacobian
    j4 = imaging_maps(s4, CAM, trace_setup_camera(s4, CAM)).jacobian
    h, w = j8.shape[:2]
    blk = j4[: 2 * h, : 2 * w].reshape(h, 2, w, 2, 2, 2).mean(axis=(1, 3))
    ok = (np.abs(j8).sum((-1, -2)) > 0) & (np.abs(blk).sum((-1, -2)) > 0)
    ok[[0, -1], :] = ok[:, [0, -1]] = False  # one-sided differences at the border
    assert ok.sum() > 10000
    np.testing.assert_allclose(j8[ok], blk[ok], rtol=0.02, atol=0.02 * np.abs(j8[ok]).max())


# ------------------------------------------------------------------ screen pixels (issue 20)
def _render_1d(coord_x, period, *, hold=0.0, jac_u=0.0, sigma=0.0, coefficients=(0.5, 0.45)):
    """Noise-free 16-bit images of one row of pixels at screen x = ``coord_x`` (mm)."""
    from pmdsim.setup.fringes import FringeSequence
    from pmdsim.simulation.imaging import ImagingMaps

    shape = (1, coord_x.size)
    coord = np.zeros(shape + (2,))
    coord[0, :, 0] = coord_x
    jac = None
    if jac_u:
        jac = np.zeros(shape + (2, 2))
        jac[..., 0, 0] = jac_u
    var = np.zeros(shape + (2,))
    var[..., 0] = sigma**2
    maps = ImagingMaps(var, jac, np.ones(shape), hold, np.asarray(coefficients, float))
    seq = FringeSequence((period,), (period,), n_shifts=4, mean_level=0.5, amplitude=0.45)
    sensor = SensorModel.from_values(None, 16, 0.0)
    return render_period_imaging(maps, coord, np.ones(shape, bool), "x", period, seq, sensor, None)[:, 0].astype(float)


def _decoded_x(I, period):
    """N = 4 phase of (N, M) samples → screen coordinate (mm) modulo the period."""
    d = 2 * np.pi * np.arange(I.shape[0]) / I.shape[0]
    return period / (2 * np.pi) * np.arctan2(np.sin(d) @ I, np.cos(d) @ I)


def _wrapped_mm(a, period):
    return (a + period / 2) % period - period / 2


def test_screen_pixel_staircase_moves_the_decoded_coordinate_as_the_box_average_of_the_held_pattern():
    """Closed form: a camera pixel of footprint J (box) over the held pattern
    f((⌊x/P⌋ + ½)·P) records (1/J)·∫ f over the box — a sum over the screen pixels it overlaps,
    computed here exactly (overlap lengths × the held values). The decoded coordinate of the
    renderer's images against the one of these closed-form samples: equal within the 16-bit
    rounding, and the staircase's own error (the closed form against the true x) is resolved."""
    P, p, J = 0.27, 2.0, 0.35
    x = np.linspace(10.0, 14.0, 801)
    got = _decoded_x(_render_1d(x, p, hold=P, jac_u=J), p)
    shifts = 2 * np.pi * np.arange(4) / 4
    lo, hi = x - J / 2, x + J / 2
    ref = np.zeros((4, x.size))
    for j in range(int(np.floor(lo.min() / P)), int(np.floor(hi.max() / P)) + 1):
        overlap = np.clip(np.minimum(hi, (j + 1) * P) - np.maximum(lo, j * P), 0.0, None)
        ref += overlap / J * (0.5 + 0.45 * np.cos(2 * np.pi * (j + 0.5) * P / p - shifts[:, None]))
    want = _decoded_x(ref * 65535, p)
    stair = _wrapped_mm(want - x, p)
    err = _wrapped_mm(got - want, p)
    assert np.sqrt(np.mean((stair - stair.mean()) ** 2)) > 5e-3  # the staircase: > 5 µm RMS
    # 16-bit rounding: |Δφ| ≤ (2/N)·Σ½/B = 1/B rad; B = 0.45·|T|, T = sinc(J/p)·sinc(P/p) > 0.9.
    # The aliases beyond the model's cap A = HOLD_ALIASES (each ≤ K/a², K = 0.45·sin(πP/p)/π ·
    # P/(πJ)): their sum over a > A and both signs ≤ 2K/(A − 1), |Δφ| ≤ 2·sum/B; the terms the
    # truncation leaves out: ≤ TRUNCATION_TOLERANCE_DN grey levels per image, |Δφ| ≤ 2·tol/B.
    from pmdsim.simulation.imaging import HOLD_ALIASES, TRUNCATION_TOLERANCE_DN

    B = 0.45 * 0.9
    K = 0.45 * np.sin(np.pi * P / p) / np.pi * P / (np.pi * J)
    A = HOLD_ALIASES
    dphi = 1.0 / (B * 65535) + 2 * 2 * K / (A - 1) / B + 2 * TRUNCATION_TOLERANCE_DN / (B * 65535)
    assert np.abs(err).max() <= p / (2 * np.pi) * dphi


def test_display_levels_round_the_commanded_pattern_closed_form():
    """L = 16 display levels: the screen shows Q(d) = round(d·(L − 1))/(L − 1) of the commanded
    d = A + B·cos(2πx/p − δ_k), seen through a defocus footprint of std σ = 1 mm (p = 8 mm). The
    reference averages Q over the footprint's marginal, the semicircle of radius 2σ (40 000-point
    quadrature here), and decodes it; the renderer keeps the rounding's harmonics up to the 48th.
    Bound: the dropped harmonics that fold into the N = 4 phase (n > 48, n ≡ ±1 mod 4; |c_n| from a
    2^16-point FFT here) times the envelope 1.6/x^1.5 of 2·J₁(x)/x, |Δφ| ≤ 2·Σ/B, plus the 16-bit
    rounding. The rounding's ripple itself is > 3× that bound (measured 2.6 µm vs 0.73 µm)."""
    from scipy.special import j1

    from pmdsim.simulation.display import harmonic_coefficients

    L, p, sig, A, B = 16, 8.0, 1.0, 0.5, 0.45
    s = default_setup().with_imaging(display_levels=L)
    coef = harmonic_coefficients(None, A, B, levels=s.imaging.display_levels)
    x = np.linspace(0.0, p, 499, endpoint=False)
    got = _decoded_x(_render_1d(x, p, sigma=sig, coefficients=coef), p)
    shifts = 2 * np.pi * np.arange(4) / 4
    R = 2 * sig
    t = np.linspace(-R, R, 40001)[1:-1]
    w = np.sqrt(R * R - t * t)
    w /= w.sum()
    ref = np.stack([(np.floor((A + B * np.cos(2 * np.pi * (x[:, None] + t) / p - dk)) * (L - 1) + 0.5) / (L - 1) * w)
                    .sum(-1) for dk in shifts])
    want = _decoded_x(ref, p)
    theta = 2 * np.pi * np.arange(2**16) / 2**16
    c = 2 * np.abs(np.fft.rfft(np.floor((A + B * np.cos(theta)) * (L - 1) + 0.5) / (L - 1)).real) / 2**16
    n = np.arange(c.size)
    xn = 4 * np.pi * sig * np.maximum(n, 1) / p
    folded = (n > 48) & ((n % 4 == 1) | (n % 4 == 3))
    dropped = (c * np.minimum(1.0, 1.6 / xn**1.5))[folded].sum()
    x1 = 4 * np.pi * sig / p
    b1 = B * 2 * j1(x1) / x1
    bound = p / (2 * np.pi) * (2 * dropped / b1 + 1.0 / (b1 * 65535))
    err = _wrapped_mm(got - want, p)
    ripple = _wrapped_mm(want - x, p)
    assert np.abs(ripple - ripple.mean()).max() > 3 * bound  # the rounding's ripple is resolved
    assert np.abs(err).max() <= bound
