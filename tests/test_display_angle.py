"""The LCD's viewing-angle response (issue 20 item 2): an IPS cell between crossed polarisers.

References written here, not by the code under test: the gamma curve at normal incidence; a
Jones-matrix computation whose every mode (polariser, liquid crystal, analyser) comes from solving
the wave equation det(k kᵀ − |k|² I + ε) = 0 numerically for k_z (the Fresnel equation: a quartic
fitted through five determinants and solved by numpy.roots, the fields its null vectors); the
N-step phase of a response's Fourier series in closed form; scipy's cubic-spline interpolation.
"""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.errors import SetupError
from pmdsim.setup import ImagingSetup, default_setup, parse_setup
from pmdsim.setup.fringes import FringeSequence
from pmdsim.setup.sensor import SensorModel
from pmdsim.simulation.display_angle import angular_basis, angular_response, ips_transmittance, view_directions
from pmdsim.simulation.imaging import ImagingMaps, render_direction_imaging, render_period_imaging

IM = ImagingSetup(lcd_mode="ips", display_gamma=2.2, display_black_level=0.002)


def _fresnel_modes(eps, ux, uy):
    """The two forward plane-wave modes (k_z, unit E) of a medium of dielectric tensor ``eps`` with
    transverse wave vector (ux, uy) (units of k₀)."""
    def m(kz):
        k = np.array([ux, uy, kz], dtype=complex)
        return np.outer(k, k) - (k @ k) * np.eye(3) + eps

    z = np.linspace(-2.0, 2.0, 5)
    poly = np.linalg.solve(np.vander(z, 5), [np.linalg.det(m(t)) for t in z])
    roots = [r for r in np.roots(poly) if r.real > 0]
    assert len(roots) == 2
    modes = []
    for r in roots:
        e = np.linalg.svd(m(r))[2][-1].conj()
        modes.append((r, e / np.linalg.norm(e)))
    return modes


def _split(field, a, b):
    return np.linalg.solve(np.array([a[:2], b[:2]]).T, field[:2])


def _jones_reference(psi, ux, uy, *, retardation_nm, indices, rubbing_deg, wavelength_nm, n_pol=1.5, kappa=1.0):
    """T at each director angle of ``psi`` (sequence) for the direction (ux, uy)."""
    rho = np.radians(rubbing_deg)
    no, ne = indices
    # dichroic polarisers: uniaxial absorbers (ε = n² + iκ along the absorption axis); the mode
    # that passes is the least absorbed one
    a1 = np.array([-np.sin(rho), np.cos(rho), 0.0])
    a2 = np.array([np.cos(rho), np.sin(rho), 0.0])
    pol = sorted(_fresnel_modes(n_pol**2 * np.eye(3) + 1j * kappa * np.outer(a1, a1), ux, uy), key=lambda q: q[0].imag)
    ana = sorted(_fresnel_modes(n_pol**2 * np.eye(3) + 1j * kappa * np.outer(a2, a2), ux, uy), key=lambda q: q[0].imag)
    k0d = 2 * np.pi * retardation_nm / (ne - no) / wavelength_nm
    out = []
    for p in np.atleast_1d(psi):
        c = np.array([np.cos(rho + p), np.sin(rho + p), 0.0])
        lc = _fresnel_modes(no**2 * np.eye(3) + (ne**2 - no**2) * np.outer(c, c), ux, uy)
        coef = _split(pol[0][1], lc[0][1], lc[1][1])
        field = sum(coef[i] * np.exp(1j * k0d * lc[i][0]) * lc[i][1] for i in range(2))
        out.append(abs(_split(field, ana[0][1], ana[1][1])[0]) ** 2)
    return np.array(out)


def test_normal_incidence_is_the_gamma_curve_and_keys_are_validated():
    d = np.linspace(0.0, 1.0, 257)
    for rub in (0.0, 17.0, 90.0):
        im = IM.with_(lcd_rubbing_deg=rub)
        np.testing.assert_allclose(angular_response(d, 0.0, 0.0, im), 0.002 + 0.998 * d**2.2, rtol=1e-12, atol=1e-15)
    t = ips_transmittance(np.linspace(0, np.pi / 4, 9), 0.0, 0.0, retardation_nm=200.0, indices=(1.5, 1.6),
                          rubbing_deg=30.0, wavelength_nm=550.0)
    np.testing.assert_allclose(t, np.sin(2 * np.linspace(0, np.pi / 4, 9))**2 * np.sin(np.pi * 200 / 550)**2,
                               rtol=1e-12, atol=1e-15)
    s = parse_setup({**default_setup().to_dict(), "imaging": {"lcd_mode": "ips", "lcd_indices": [1.5, 1.62],
                                                              "lcd_rubbing_deg": 15, "lcd_retardation_nm": 300}})
    assert s.imaging.lcd_indices == (1.5, 1.62) and s.imaging.lcd_rubbing_deg == 15.0
    import tomllib
    assert parse_setup(tomllib.loads(s.to_toml())).imaging == s.imaging
    for bad, key in (({"lcd_mode": "tn"}, "lcd_mode"), ({"lcd_mode": "ips", "lcd_indices": [1.6, 1.5]}, "lcd_indices"),
                     ({"lcd_retardation_nm": 0}, "lcd_retardation_nm"), ({"lcd_indices": [1.5]}, "lcd_indices")):
        with pytest.raises(SetupError, match=key):
            parse_setup({**default_setup().to_dict(), "imaging": bad})


def test_transmittance_matches_a_jones_computation_with_the_fresnel_modes():
    rng = np.random.default_rng(3)
    for _ in range(40):
        psi = rng.uniform(0, np.pi / 4)
        th, ph = np.radians(rng.uniform(0, 50)), rng.uniform(0, 2 * np.pi)
        kw = dict(retardation_nm=rng.uniform(200, 400), indices=(1.48, 1.48 + rng.uniform(0.05, 0.2)),
                  rubbing_deg=rng.uniform(-90, 90), wavelength_nm=550.0)
        ux, uy = np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph)
        ref = _jones_reference(psi, ux, uy, **kw)
        assert ips_transmittance(psi, ux, uy, **kw) == pytest.approx(ref[0], rel=1e-8, abs=1e-12)


def _row_maps(n_px, period, u, im, *, hold=0.0, levels=None):
    """One row of ``n_px`` pixels over one period, all seen from direction ``u`` (ux, uy)."""
    shape = (1, n_px)
    xy = np.zeros(shape + (2,))
    xy[0, :, 0] = np.arange(n_px) * period / n_px
    basis = angular_basis(im, np.broadcast_to(np.asarray(u, float), shape + (2,)).copy())
    return xy, basis


def _closed_form_phase(r_of_d, x, period, n=4, A=0.5, B=0.45):
    """N-step phase of the pattern r(A + B·cos(2πx/p − δ)) from its Fourier series: the harmonics
    n ≡ ±1 (mod N) fold into Σ_k I_k e^{iδ_k} = (N/2)·Σ (c_n e^{inφ}[n ≡ 1] + c_n e^{−inφ}[n ≡ −1])."""
    m = 4096
    th = 2 * np.pi * np.arange(m) / m
    c = np.fft.rfft(r_of_d(A + B * np.cos(th))).real / m
    c[1:] *= 2
    phi = 2 * np.pi * x / period
    k = np.arange(c.size)
    s = (c[None, k % n == 1] * np.exp(1j * k[k % n == 1] * phi[:, None])).sum(1) \
        + (c[None, k % n == n - 1] * np.exp(-1j * k[k % n == n - 1] * phi[:, None])).sum(1)
    return np.angle(s)


def test_the_angle_changes_the_decoded_coordinate_as_the_folded_harmonics_predict():
    """N = 4, γ = 2.2: the response's 3rd and 5th harmonics fold into the phase (a 4φ ripple).
    Off the normal the cell's curve r(d; θ, φ) has other harmonics; the decoder's phase on the
    rendered images (means, no noise) equals the closed form computed from the Jones reference's
    curve at that direction, and differs from the normal one. A luminance scale alone (the
    emission factor) changes nothing."""
    period, n_px = 4.0, 64
    seq = FringeSequence((period,), (period,), n_shifts=4, mean_level=0.5, amplitude=0.45)
    sensor = SensorModel.from_values(None, 16, 0.0)
    cell = dict(retardation_nm=IM.lcd_retardation_nm, indices=IM.lcd_indices, rubbing_deg=IM.lcd_rubbing_deg,
                wavelength_nm=IM.lcd_wavelength_nm)
    d4 = 2 * np.pi * np.arange(4) / 4
    for th_deg, ph_deg in ((0.0, 0.0), (25.0, 40.0), (35.0, 110.0)):
        th, ph = np.radians(th_deg), np.radians(ph_deg)
        u = (np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph))
        xy, basis = _row_maps(n_px, period, u, IM)
        x = xy[0, :, 0]

        def r_ref(d):
            psi = 0.5 * np.arcsin(np.sqrt(d**2.2))
            t = _jones_reference(psi.ravel(), *u, **cell).reshape(psi.shape)
            return 0.002 + 0.998 * t / np.sin(np.pi * cell["retardation_nm"] / cell["wavelength_nm"])**2

        # the curve at 512 levels by the reference, interpolated (smooth in d away from d = 0)
        dd = np.linspace(0.0, 1.0, 257)
        rr = r_ref(dd)
        want = _closed_form_phase(lambda d: np.interp(d, dd, rr), x, period)
        phases = []
        for scale in (1.0, 0.6):
            from pmdsim.simulation.imaging import _Curve
            from pmdsim.simulation.display import harmonic_coefficients
            rows = [harmonic_coefficients(_Curve(basis, r), 0.5, 0.45) for r in range(basis.rank)]
            acoef = np.zeros((basis.rank, max(map(len, rows))))
            for r, c in enumerate(rows):
                acoef[r, :len(c)] = c
            maps = ImagingMaps(np.zeros((1, n_px, 2)), None, np.full((1, n_px), scale), 0.0, acoef[0],
                               display=(None, None), angular=basis, angular_coefficients=acoef)
            means = np.empty((4, 1, n_px))
            render_period_imaging(maps, xy, np.ones((1, n_px), bool), "x", period, seq, sensor, None, means=means)
            I = means[:, 0]
            phases.append(np.arctan2(np.sin(d4) @ I, np.cos(d4) @ I))
        err = np.angle(np.exp(1j * (phases[0] - want)))
        # the interpolated reference curve (d step 1/256: ≈ h²/8·|r"| ≈ 1e-5) and the 1e-3 DN truncation
        assert np.abs(err).max() < 5e-5
        np.testing.assert_allclose(phases[1], phases[0], atol=1e-12)  # a luminance scale: nothing
        if th_deg == 0.0:
            normal = want
        else:
            ripple = np.angle(np.exp(1j * (want - normal)))
            assert np.abs(ripple).max() > 20 * 5e-5  # the angle's change is resolved


@pytest.mark.parametrize("path", ["series", "held", "point"])
def test_every_renderer_mixes_the_basis_as_the_single_response_at_that_direction(path):
    """A row seen from one direction: the renderer with the viewing-angle model equals the same
    renderer given the response r(·; u) itself (the display-response path, tested on its own)."""
    from pmdsim.simulation.display import harmonic_coefficients

    period, n_px = 2.0, 200
    u = (-0.35, 0.12)
    levels = 256 if path != "series" else None
    hold = 0.27 if path == "held" else 0.0
    im = IM.with_(display_levels=levels)
    xy, basis = _row_maps(n_px, period, u, im)
    d = np.linspace(0, 1, 4097)
    rd = angular_response(d, *u, im)

    class resp:  # the response r(·; u) (linear interpolation, step 1/4096)
        forward = staticmethod(lambda x: np.interp(x, d, rd))

    seq = FringeSequence((period, 8.0), (period,), n_shifts=4, mean_level=0.5, amplitude=0.45)
    sensor = SensorModel.from_values(None, 16, 0.0)
    from pmdsim.simulation.imaging import _Curve
    rows = [harmonic_coefficients(_Curve(basis, r), 0.5, 0.45, levels=levels) for r in range(basis.rank)]
    acoef = np.zeros((basis.rank, max(map(len, rows))))
    for r, c in enumerate(rows):
        acoef[r, :len(c)] = c
    one = np.ones((1, n_px))
    zero = np.zeros((1, n_px, 2))
    sharp = path == "point"
    with_model = ImagingMaps(zero, None, one, hold, acoef[0], display=(None, levels), angular=basis,
                             angular_coefficients=acoef, sharp=sharp)
    plain = ImagingMaps(zero, None, one, hold, harmonic_coefficients(resp, 0.5, 0.45, levels=levels),
                        display=(resp, levels), sharp=sharp)
    got = np.empty((2, 4, 1, n_px))
    ref = np.empty((2, 4, 1, n_px))
    ok = np.ones((1, n_px), bool)
    render_direction_imaging(with_model, xy, ok, "x", seq, sensor, None, means=got)
    render_direction_imaging(plain, xy, ok, "x", seq, sensor, None, means=ref)
    # the basis' fit (1e-6) and the reference response's interpolation (step 1/4096)
    np.testing.assert_allclose(got, ref, atol=65535 * 2e-6, rtol=0)


def test_per_pixel_weights_follow_the_model_over_a_camera_and_the_spline_is_scipys():
    """Over the default setup's left camera (θ up to 27°): Σ w_m(u)·B_m against the model at
    each pixel's own direction, and the per-pixel spline against scipy.ndimage.map_coordinates."""
    from scipy.ndimage import map_coordinates, spline_filter

    from pmdsim.simulation import display_angle as da
    from pmdsim.simulation.render import trace_setup_camera

    s = default_setup().binned(8)
    m = trace_setup_camera(s, "left", store_points=True)
    u = view_directions(s.screen.T_world_screen, s.sample.T_world_sample, m.p_sample_mm, m.q_screen_mm)
    u[~m.valid] = np.nan
    # θ of each direction against the emission's cos θ_v (optics.defocus_moments, its own kernel)
    from pmdsim.simulation.optics import defocus_moments

    cs = s.cameras["left"]
    _, _, cos_view = defocus_moments(cs.T_world_cam, s.sample.T_world_sample, s.screen.T_world_screen,
                                     m.p_sample_mm, m.q_screen_mm, 0.0, s.screen.surface)
    np.testing.assert_allclose(np.hypot(u[..., 0], u[..., 1])[m.valid],
                               np.sqrt(1.0 - cos_view[m.valid] ** 2), atol=1e-9)
    basis = angular_basis(IM, u)
    assert 1 <= basis.rank <= 12 and basis.residual <= da.BASIS_TOLERANCE
    v, c = np.nonzero(m.valid)
    pick = np.random.default_rng(0).choice(v.size, 300, replace=False)
    v, c = v[pick], c[pick]
    d = np.linspace(0, 1, 65)
    want = angular_response(d[None, :], u[v, c, 0][:, None], u[v, c, 1][:, None], IM)
    got = basis.weights[v, c] @ basis.at_levels(d)
    assert np.abs(got - want).max() < 5e-5  # 0.2 DN at 12 bit, full scale
    # the kernel's spline is scipy's (prefilter 'mirror', pixels ≥ 3 nodes inside the grid)
    coef = np.random.default_rng(1).normal(size=(12, 10, 2))
    pts = np.random.default_rng(2).uniform([3.0, 3.0], [8.0, 6.0], size=(50, 2))  # (y, x) in nodes, ≥ 3 inside
    out = np.zeros((1, 50, 2))
    da._spline_weights(np.stack([pts[:, 1], pts[:, 0]], -1)[None].copy(),
                       np.stack([spline_filter(coef[..., k], order=3, mode="mirror") for k in range(2)], -1),
                       0.0, 0.0, 1.0, 1.0, out)
    for k in range(2):
        np.testing.assert_allclose(out[0, :, k], map_coordinates(coef[..., k], pts.T, order=3, mode="mirror"),
                                   atol=1e-12)


def test_display_levels_seen_by_a_sharp_camera_are_the_rounded_pattern_at_the_pixel():
    """No camera transfer: the images are r(Q(A + B·cos(2πx/p − δ_k))) at each pixel's x, Q the
    rounding to L levels (closed form here, γ = 2.2, b = 0.01), scaled to 16 bit and rounded (the
    route of ``display_levels`` without lens, pixel area or screen pixels: :mod:`.imaging_point`)."""
    s = default_setup().with_imaging(display_levels=64, display_gamma=2.2, display_black_level=0.01, bit_depth=16)
    from pmdsim.simulation.imaging import imaging_maps
    from pmdsim.simulation.trace import Mapping

    n_px, p = 997, 3.0
    xy = np.zeros((1, n_px, 2))
    xy[0, :, 0] = np.linspace(-40.0, 40.0, n_px)
    m = Mapping(xy, np.zeros((1, n_px), np.uint8))  # every pixel valid (status 0)
    maps = imaging_maps(s, "left", m)
    assert maps.sharp
    seq = FringeSequence((p,), (p,), n_shifts=5, mean_level=0.5, amplitude=0.45)
    sensor = SensorModel.from_setup(s)
    means = np.empty((5, 1, n_px))
    img = render_period_imaging(maps, xy, np.ones((1, n_px), bool), "x", p, seq, sensor, None, means=means)
    d = 0.5 + 0.45 * np.cos(2 * np.pi * xy[0, :, 0] / p - 2 * np.pi * np.arange(5)[:, None] / 5)
    q = np.floor(d * 63 + 0.5) / 63
    want = (0.01 + 0.99 * q**2.2) * sensor.scale_dn
    # the display response is the gamma law's 1025-level pchip table (setup.response): 1e-6 of it
    np.testing.assert_allclose(means[:, 0], want, rtol=1e-6)
    np.testing.assert_array_equal(img[:, 0], np.floor(sensor.dark_dn + means[:, 0] + 0.5))
