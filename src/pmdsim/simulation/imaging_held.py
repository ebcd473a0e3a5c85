"""The screen's held pattern rendered in position: every image of one fringe direction from one
set of per-pixel screen-pixel weights (issue 20, speed).

With screen pixels of pitch P (``[imaging] screen_pixel_pitch_mm``) the screen shows the pattern
held constant over each pixel j, x ∈ [jP, (j + 1)P): the value R_j = r(Q(A + B·cos(2π(j + ½)P/p −
δ_k))) (the display response r of the commanded level rounded to the display's levels Q,
docs/conventions.md "Image formation"). A camera pixel records this staircase averaged over its
footprint on the screen: along the fringe axis the marginal of the lens's uniform-ellipse blur (a
semicircle of radius R = 2σ_a, :mod:`.optics`) convolved with the pixel's own footprint (boxes of
widths |J_a,u| and |J_a,v|, the pixel Jacobian's row a). With F_K the CDF of that kernel K,

    mean = Σ_j R_j·[F_K((j + 1)P − x) − F_K(jP − x)] = R_{j₁} + Σ_{i = j₀+1}^{j₁} F_K(iP − x)·(R_{i−1} − R_i),

x the footprint centroid's screen coordinate and j₀ … j₁ the screen pixels under the kernel's
support |y − x| ≤ R + (|J_a,u| + |J_a,v|)/2. This is the harmonic × alias series of
:mod:`.imaging_series` summed to infinity (Poisson summation of the same staircase), with the
displayed values exact: no harmonic of the rounded response is dropped (the series keeps 48), no
alias beyond a cap. F_K is closed form: with G₁, G₂ the first and second antiderivatives of the
semicircle's CDF,

    F_K(e) = [G₂(e + (a + b)/2) − G₂(e + (a − b)/2) − G₂(e − (a − b)/2) + G₂(e − (a + b)/2)]/(a·b)

(a ≥ b the two box widths), (G₁(e + c/2) − G₁(e − c/2))/c with c = √(a² + b²) when a·b < 1e-7·s²
(s = max(R, a): the second difference would lose more digits than the narrow box changes; the
trapezoid and the box of equal variance differ in F by ≤ b/(8a) ≤ 1.25e-8 there), the semicircle's
own CDF without pixel area. For the unit semicircle (density (2/π)√(1 − t²) on [−1, 1]; s = √(1 − t²)):

    F(t)  = ½ + (t·s + asin t)/π
    G₁(t) = (t + 1)/2 + (t·asin t + s − s³/3 − π/2)/π                       (= t for t ≥ 1)
    G₂(t) = (t + 1)²/4 + ((t²/2 + 1/8)·asin t + 5t·s/8 − t·s³/12 − πt/2)/π − 3/16   (= t²/2 + 1/8)

scaled to radius R as F(x/R), R·G₁(x/R), R²·G₂(x/R) (R = 0: a step, x₊, x₊²/2). asin is fdlibm's
rational approximation (a few ulp; libm's asin costs ≈ 50 ns here, the render's budget per pixel
is ≈ 2 µs for all images).

Per pixel the kernel evaluates F_K at the ≈ (2R + |J|)/P + 1 screen-pixel edges under its support
once per direction (the geometry is shared by every period and shift of that direction) and then
each of the direction's images is a dot product of those values with the tabulated differences
R_{i−1} − R_i of its held pattern, followed by the sensor (:class:`~pmdsim.setup.sensor.SensorModel`,
the same code as the series kernel).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.fast_trig import ASIN_PIO2_HI, ASIN_PIO2_LO, asin_ratio, fast_asin
from .sensor_code import sensor_code

__all__ = ["semicircle_cdf", "semicircle_g1", "semicircle_g2", "kernel_cdf", "held_values",
           "render_direction_held", "held_kernel"]

#: a·b below this × max(R, a)² merges the two boxes into one of equal variance (module docstring).
MERGE_RATIO = 1e-7


@numba.njit(cache=True, error_model="numpy")
def semicircle_cdf(x, radius):
    """CDF at ``x`` of the semicircle (Wigner) density of ``radius`` (≥ 0; 0: a step at 0)."""
    if x >= radius:
        return 1.0
    if x <= -radius:
        return 0.0
    t = x / radius
    s = np.sqrt((1.0 - t) * (1.0 + t))
    return 0.5 + (t * s + fast_asin(t)) / np.pi


@numba.njit(cache=True, error_model="numpy")
def semicircle_g1(x, radius):
    """∫_{−∞}^x of :func:`semicircle_cdf` (x for x ≥ radius, 0 below −radius)."""
    if x >= radius:
        return x
    if x <= -radius:
        return 0.0
    t = x / radius
    s = np.sqrt((1.0 - t) * (1.0 + t))
    return radius * (0.5 * (t + 1.0) + (t * fast_asin(t) + s - s * s * s / 3.0 - 0.5 * np.pi) / np.pi)


@numba.njit(cache=True, error_model="numpy")
def semicircle_g2(x, radius):
    """∫_{−∞}^x of :func:`semicircle_g1` (x²/2 + radius²/8 for x ≥ radius, 0 below −radius)."""
    if x >= radius:
        return 0.5 * x * x + 0.125 * radius * radius
    if x <= -radius:
        return 0.0
    t = x / radius
    s = np.sqrt((1.0 - t) * (1.0 + t))
    u = t + 1.0
    g = (0.25 * u * u + ((0.5 * t * t + 0.125) * fast_asin(t) + 0.625 * t * s - t * s * s * s / 12.0
                          - 0.5 * np.pi * t) / np.pi - 0.1875)
    return radius * radius * g


@numba.njit(cache=True, error_model="numpy")
def kernel_cdf(e, radius, a, b):
    """CDF at ``e`` of semicircle(``radius``) ⊛ box(``a``) ⊛ box(``b``), a ≥ b ≥ 0 the full widths
    (module docstring)."""
    if a == 0.0:
        return semicircle_cdf(e, radius)
    s = max(radius, a)
    if a * b < MERGE_RATIO * s * s:
        c = np.sqrt(a * a + b * b)
        h = 0.5 * c
        return (semicircle_g1(e + h, radius) - semicircle_g1(e - h, radius)) / c
    hp = 0.5 * (a + b)
    hm = 0.5 * (a - b)
    return (semicircle_g2(e + hp, radius) - semicircle_g2(e + hm, radius) - semicircle_g2(e - hm, radius)
            + semicircle_g2(e - hp, radius)) / (a * b)


@numba.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _g2_many(xs, m, radius, out):
    """out[i] = :func:`semicircle_g2` (xs[i], radius) for i < m, radius > 0: the same closed form,
    branch-free (selects), so that the loop vectorises."""
    r2 = radius * radius
    inv = 1.0 / radius
    for i in range(m):
        x = xs[i]
        t = min(1.0, max(-1.0, x * inv))
        ax = abs(t)
        small = ax < 0.5
        z = t * t if small else 0.5 * (1.0 - ax)
        r = asin_ratio(z)
        q = np.sqrt(z)
        big = ASIN_PIO2_HI - (2.0 * (q + q * r) - ASIN_PIO2_LO)
        asn = t + t * r if small else (big if t > 0.0 else -big)
        s = np.sqrt((1.0 - t) * (1.0 + t))
        u = t + 1.0
        g = (0.25 * u * u + ((0.5 * t * t + 0.125) * asn + 0.625 * t * s - t * s * s * s / 12.0 - 0.5 * np.pi * t)
             / np.pi - 0.1875) * r2
        hi = 0.5 * x * x + 0.125 * r2
        out[i] = hi if x >= radius else (0.0 if x <= -radius else g)


@numba.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _held_rows(v0, v1, coord, valid, radius, box_a, box_b, pitch, j0, levels, dlevels, pw, use_pw, radiance, scale,
               dark, clip, shot, const_var, full, noise, use_noise, out, means, fbuf, args, vals, acc):
    w = valid.shape[1]
    n_per, n = out.shape[0], out.shape[1]
    nc = levels.shape[1]  # R·P·N columns: R response functions (1 without the viewing-angle model)
    nim = n_per * n
    nr = nc // nim
    keep_means = means.shape[0] > 0
    for v in range(v0, v1):
        for u in range(w):
            x = coord[v, u]
            if not valid[v, u] or not np.isfinite(x):
                for p in range(n_per):
                    for k in range(n):
                        out[p, k, v, u] = 0
                        if keep_means:
                            means[p, k, v, u] = 0.0
                continue
            rad = radius[v, u]
            a = box_a[v, u]
            b = box_b[v, u]
            if b > a:
                a, b = b, a
            hw = rad + 0.5 * (a + b)
            jlo = int(np.floor((x - hw) / pitch)) - j0
            jhi = int(np.floor((x + hw) / pitch)) - j0
            ne = jhi - jlo  # interior edges i = jlo + 1 … jhi
            sc = max(rad, a)
            if rad > 0.0 and a > 0.0 and a * b >= MERGE_RATIO * sc * sc:
                # the common case, F_K by the second difference of G₂: its 4·ne values in one loop
                hp = 0.5 * (a + b)
                hm = 0.5 * (a - b)
                for i in range(ne):
                    e = (jlo + 1 + i + j0) * pitch - x
                    args[4 * i] = e + hp
                    args[4 * i + 1] = e + hm
                    args[4 * i + 2] = e - hm
                    args[4 * i + 3] = e - hp
                _g2_many(args, 4 * ne, rad, vals)
                ab = a * b
                for i in range(ne):
                    fbuf[i] = (vals[4 * i] - vals[4 * i + 1] - vals[4 * i + 2] + vals[4 * i + 3]) / ab
            else:
                for i in range(ne):
                    fbuf[i] = kernel_cdf((jlo + 1 + i + j0) * pitch - x, rad, a, b)
            for c in range(nc):
                acc[c] = levels[jhi, c]
            for i in range(ne):
                f = fbuf[i]
                for c in range(nc):
                    acc[c] += f * dlevels[jlo + 1 + i, c]
            g = radiance[v, u] * scale
            if use_pw:  # the pixel's mix of the response functions
                for c in range(nim):
                    s = 0.0
                    for r in range(nr):
                        s += pw[v, u, r] * acc[r * nim + c]
                    acc[c] = s
            for p in range(n_per):
                for k in range(n):
                    mean = g * acc[p * n + k]
                    if keep_means:
                        means[p, k, v, u] = mean
                    out[p, k, v, u] = sensor_code(mean, dark, clip, shot, const_var, full, use_noise,
                                                  noise[p, k, v, u] if use_noise else 0.0)


@numba.njit(cache=True, parallel=True)
def held_kernel(coord, valid, radius, box_a, box_b, pitch, j0, levels, dlevels, pw, use_pw, radiance, scale, dark,
                clip, shot, const_var, full, noise, use_noise, n_edges, out, means):
    """Every image (period p, shift k) of one direction, rows in parallel blocks: ``levels``
    (M, R·P·N) the held relative radiance of screen pixel j0 + m in image p·N + k (of response
    function r, column r·P·N + p·N + k; mixed per pixel with ``pw`` (H, W, R) when ``use_pw``,
    else R = 1), ``dlevels`` its differences levels[m − 1] − levels[m]; ``out`` (P, N, H, W) uint16, ``means`` (P, N, H, W)
    float64 (or empty) the mean grey levels above the dark offset; ``n_edges`` bounds the edges per
    pixel."""
    h = valid.shape[0]
    rows = 8
    for blk in numba.prange(0, (h + rows - 1) // rows):
        fbuf = np.empty(n_edges)
        args = np.empty(4 * n_edges)
        vals = np.empty(4 * n_edges)
        acc = np.empty(levels.shape[1])
        _held_rows(blk * rows, min(h, (blk + 1) * rows), coord, valid, radius, box_a, box_b, pitch, j0, levels,
                   dlevels, pw, use_pw, radiance, scale, dark, clip, shot, const_var, full, noise, use_noise, out, means, fbuf,
                   args, vals, acc)


def held_values(theta: np.ndarray, coefficients: np.ndarray, response=None, levels: int | None = None,
                mean_level: float | None = None, amplitude: float | None = None) -> np.ndarray:
    """Relative radiance the screen holds at fringe phases ``theta`` (radians, any shape).

    With ``mean_level`` and ``amplitude`` given: r(Q(A + B·cos θ)) exactly (``response`` r or
    linear, ``levels`` Q or none; :func:`.display.quantise_levels`). Otherwise the cosine series
    Σ_n c_n·cos(nθ) of ``coefficients`` (a pattern defined by its harmonics)."""
    from .display import quantise_levels

    theta = np.asarray(theta, dtype=float)
    if mean_level is not None and amplitude is not None:
        d = quantise_levels(mean_level + amplitude * np.cos(theta), levels)
        return d if response is None else np.asarray(response.forward(d), dtype=float)
    c = np.asarray(coefficients, dtype=float)
    out = np.full(theta.shape, c[0])
    for m in range(1, c.size):
        out += c[m] * np.cos(m * theta)
    return out


def render_direction_held(coord: np.ndarray, valid: np.ndarray, radius_mm: np.ndarray, box_a_mm: np.ndarray,
                          box_b_mm: np.ndarray, pitch_mm: float, periods, n_shifts: int, pattern, radiance: np.ndarray,
                          sensor, noise: np.ndarray | None, *, means: np.ndarray | None = None,
                          weights: np.ndarray | None = None) -> np.ndarray:
    """All images of one direction through the held-pattern kernel.

    Parameters
    ----------
    coord : ndarray (H, W)
        Screen coordinate along the fringe axis of each pixel's footprint centroid (mm).
    valid : ndarray of bool (H, W)
    radius_mm, box_a_mm, box_b_mm : ndarray (H, W)
        The blur semicircle's radius 2σ_a and the pixel footprint's box widths |J_a,u|, |J_a,v|.
    pitch_mm : float
        Screen pixel pitch P (> 0).
    periods : sequence of float; n_shifts : int
    pattern : callable
        θ (radians, any shape) → held relative radiance (:func:`held_values` bound to the display);
        with ``weights``: shape (R,) + θ's, R response functions.
    radiance : ndarray (H, W)
        Per-pixel relative radiance factor (emission × black matrix).
    sensor : SensorModel
    noise : ndarray (P, N, H, W) float32 or None
        Standard-normal draws (required when the sensor is noisy).
    means : ndarray (P, N, H, W) float64, optional
        Receives the mean grey levels above the dark offset before clipping, noise and rounding.
    weights : ndarray (H, W, R), optional
        Each pixel's weights of the R functions ``pattern`` returns (the LCD's viewing-angle
        response, :mod:`.display_angle`).

    Returns
    -------
    ndarray (P, N, H, W) of the sensor's dtype.
    """
    ok = np.ascontiguousarray(valid, dtype=bool)
    x = np.ascontiguousarray(coord, dtype=float)
    rad = np.ascontiguousarray(radius_mm, dtype=float)
    ba = np.ascontiguousarray(np.abs(box_a_mm), dtype=float)
    bb = np.ascontiguousarray(np.abs(box_b_mm), dtype=float)
    use = ok & np.isfinite(x)
    n_per = len(periods)
    shape = ok.shape
    if use.any():
        hw = rad[use] + 0.5 * (ba[use] + bb[use])
        lo = int(np.floor(np.min((x[use] - hw) / pitch_mm))) - 2
        hi = int(np.floor(np.max((x[use] + hw) / pitch_mm))) + 2
        n_edges = int(np.max(np.floor((x[use] + hw) / pitch_mm) - np.floor((x[use] - hw) / pitch_mm))) + 2
    else:
        lo, hi, n_edges = 0, 1, 1
    j = np.arange(lo, hi + 1)
    delta = 2.0 * np.pi * np.arange(n_shifts) / n_shifts
    n_fn = 1 if weights is None else int(weights.shape[-1])
    levels = np.empty((j.size, n_fn, n_per, n_shifts))
    for pi, p in enumerate(periods):
        theta = 2.0 * np.pi * (j + 0.5) * pitch_mm / float(p)
        vals = pattern(theta[:, None] - delta[None, :])
        levels[:, :, pi, :] = vals[:, None, :] if weights is None else np.moveaxis(vals, 0, 1)
    levels = levels.reshape(j.size, n_fn * n_per * n_shifts)
    dlevels = np.zeros_like(levels)
    dlevels[1:] = levels[:-1] - levels[1:]
    out = np.empty((n_per, n_shifts) + shape, dtype=np.uint16)
    if means is not None and (means.shape != out.shape or means.dtype != np.float64):
        raise ValueError(f"means must be a float64 array of shape {out.shape}")
    m_out = np.empty((0, 0, 0, 0)) if means is None else means
    if sensor.noisy and noise is None:
        raise ValueError("a noisy sensor needs the noise draws")
    nz = noise if sensor.noisy else np.empty((0, 0, 0, 0), dtype=np.float32)
    pw = np.zeros((1, 1, 1)) if weights is None else np.ascontiguousarray(weights, dtype=float)
    held_kernel(x, ok, rad, ba, bb, float(pitch_mm), lo, levels, dlevels, pw, weights is not None,
                np.ascontiguousarray(radiance, dtype=float),
                sensor.scale_dn, sensor.dark_dn, sensor.clip_dn, sensor.shot_dn, sensor.const_var_dn2,
                sensor.full_scale, nz, sensor.noisy, n_edges, out, m_out)
    return out if sensor.dtype == np.uint16 else out.astype(sensor.dtype)
