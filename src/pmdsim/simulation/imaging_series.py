"""The render kernel of :mod:`.imaging`: the displayed fringe's harmonic series per pixel, each term
through the camera's transfer, truncated where a bound of the rest is below a tolerance.

Per pixel and harmonic n of period p (docs/conventions.md, "Image formation: truncation of the
series") the recorded mean is g·Σ_n c_n·Σ_a w_{n,a}·T(ν_{n,a})·cos(n(φ − δ_k) + 2πa·x/P): the
display response's cosine coefficients c_n, the screen's sample-and-hold aliases a (ν = (r + a)/P,
r = nP/p, weight sin(πr)/(π(r + a)); only a = 0 with weight 1 without screen pixels), and the
camera transfer T(ν) = 2·J₁(4πσν)/(4πσν)·sinc(J_u ν)·sinc(J_v ν) (defocus footprint std σ along
the fringe axis, pixel footprint J). g = radiance × the sensor's DN scale.

Every term is bounded by |c_n|·min(1, |sin πr|/(π|z|))·E(|z|/P), z = r + a, with the envelope

    E(ν) = min(1, C·(4πσν)^(−3/2)) · min(1, 1/(π|J_u|ν)) · min(1, 1/(π|J_v|ν)),

C = :data:`JINC_ENVELOPE`: sup_x x^(3/2)·|2·J₁(x)/x| = 1.6501, reached in the main lobe at
x = 2.166; the later lobes' maxima decrease towards the asymptotic amplitude 2·√(2/π) = 1.5958 of
J₁(x) ~ √(2/(πx))·cos(x − 3π/4) (DLMF 10.17.3); checked against scipy.special.j1 on [10⁻³, 10⁵]
in tests/test_imaging_series.py. 1.66 also covers the renderer's table interpolation. Per pixel the
dropped terms' sum is kept below ``tol_dn`` grey levels: half for the harmonics n ≥ n₀ (suffix sum
S_{n₀} = Σ_{n ≥ n₀}|c_n| times a bound of one harmonic's terms: E(n₀/p) without screen pixels,
Λ = 1 + G(½) + 2·Σ_{k=1}^{A} G(k) with them, G(z) = min(1, 1/(πz))·E(z/P) — the aliases of a high
harmonic reach low frequencies, so with screen pixels Λ ≥ 1 whatever n), half for the aliases of
each kept harmonic (share ∝ √|c_n|): only |z| ≤ Z is summed, where the tail beyond Z, a power
law κ·z^(−1−β) on both sides of the lattice, is ≤ 2·G_n(Z)·(1 + Z/β). Without any transfer
factor (β = 0) the alias series has no such bound and all 2A + 1 terms are summed.
"""

from __future__ import annotations

import numba
import numpy as np

from .optics import jinc
from .sensor_code import sensor_code

__all__ = ["JINC_ENVELOPE", "TRUNCATION_TOLERANCE_DN", "series_kernel"]

#: C in |2·J₁(x)/x| ≤ C·x^(−3/2) for all x > 0 (1.6501 for the exact function, at x = 2.166; the
#: table's linear interpolation adds at most a factor (1 − h/x)^(−3/2) ≤ 1.0011 where the
#: envelope is below 1).
JINC_ENVELOPE = 1.66
#: Default truncation tolerance (grey levels of the recorded image, on the mean before noise and
#: rounding): 1e-3 DN, 1/1000 of the quantisation step at any bit depth.
TRUNCATION_TOLERANCE_DN = 1e-3


@numba.njit(cache=True, error_model="numpy")
def _envelope(nu, sig4pi, ju, jv):
    """E(ν) ≥ |T(ν)| (module docstring); ``sig4pi`` = 4πσ, ``ju``, ``jv`` = π|J_u|, π|J_v|."""
    e = 1.0
    x = sig4pi * nu
    if x > 0.0:
        b = JINC_ENVELOPE / (x * np.sqrt(x))
        if b < 1.0:
            e = b
    x = ju * nu
    if x > 1.0:
        e /= x
    x = jv * nu
    if x > 1.0:
        e /= x
    return e


@numba.njit(cache=True, error_model="numpy")
def _family_bound(hold, sig4pi, ju, jv, n_alias):
    """Λ ≥ Σ_a min(1, |sin πr|/(π|r + a|))·E(|r + a|/P) over |a| ≤ A, for any r."""
    g_half = min(1.0, 2.0 / np.pi) * _envelope(0.5 / hold, sig4pi, ju, jv)
    s = 1.0 + g_half
    for k in range(1, n_alias + 1):
        s += 2.0 * _envelope(k / hold, sig4pi, ju, jv) / (np.pi * k)
    return s


@numba.njit(cache=True, error_model="numpy")
def _alias_reach(cm, sr, hold, sig4pi, ju, jv, tau, zcap):
    """Z such that the aliases with |z| > Z sum to at most ``tau`` (relative radiance); ``zcap``
    when no power-law tail is available (no transfer factor, or ``tau`` ≤ 0).

    Each transfer factor k_i·z^(−β_i) bounds its own min(1, ·) beyond its threshold z_i; using
    the factors whose thresholds are ≤ z_s (a prefix of them sorted by threshold) the terms beyond
    Z ≥ z_s are ≤ κ·z^(−1−β), their tail ≤ 2κZ^(−1−β)(1 + Z/β) ≤ 2κZ^(−β)(1/z_s + 1/β). The
    smallest Z over the prefixes is returned (each is a valid bound)."""
    if tau <= 0.0:
        return zcap
    if sr == 0.0 or cm == 0.0:
        return 0.5
    inf = np.inf
    # The factors (threshold, coefficient, exponent): defocus C·(4πσz/P)^(−3/2), pixel (P/(π|J|))/z.
    t0, k0, b0 = inf, 1.0, 0.0
    if sig4pi > 0.0:
        t0, k0, b0 = hold * JINC_ENVELOPE ** (2.0 / 3.0) / sig4pi, JINC_ENVELOPE * (hold / sig4pi) ** 1.5, 1.5
    t1, k1, b1 = (hold / ju, hold / ju, 1.0) if ju > 0.0 else (inf, 1.0, 0.0)
    t2, k2, b2 = (hold / jv, hold / jv, 1.0) if jv > 0.0 else (inf, 1.0, 0.0)
    # sorted by threshold (three compare-exchanges)
    if t1 < t0:
        t0, k0, b0, t1, k1, b1 = t1, k1, b1, t0, k0, b0
    if t2 < t1:
        t1, k1, b1, t2, k2, b2 = t2, k2, b2, t1, k1, b1
    if t1 < t0:
        t0, k0, b0, t1, k1, b1 = t1, k1, b1, t0, k0, b0
    best = zcap
    kappa = cm * sr / np.pi
    zs = max(0.5, sr / np.pi)
    beta = 0.0
    for i in range(3):
        th, kf, bf = (t0, k0, b0) if i == 0 else ((t1, k1, b1) if i == 1 else (t2, k2, b2))
        if bf == 0.0 or th >= best:
            break
        zs = max(zs, th)
        kappa *= kf
        beta += bf
        z = max(zs, (2.0 * kappa * (1.0 / zs + 1.0 / beta) / tau) ** (1.0 / beta))
        if z < best:
            best = z
    return best


@numba.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _series_rows(v0, v1, coord, valid, period, cos_d, sin_d, coefs, pw, use_pw, suffix, share, var, jac, use_jac,
                 hold, radiance, scale, dark, clip, shot, const_var, full, noise, use_noise, table, n_alias, tol_dn,
                 out, means, counts):
    w = valid.shape[1]
    n = cos_d.shape[0]
    kmax = coefs.shape[1] - 1
    nr = coefs.shape[0]
    coef = np.empty(kmax + 1)  # this pixel's coefficients Σ_r w_r·c_r,n (the response's basis mixed)
    for m in range(kmax + 1):
        coef[m] = coefs[0, m]
    k1 = 2.0 * np.pi / period
    aliasing = hold > 0.0 and n_alias > 0
    na = n_alias if aliasing else 0
    keep_means = means.shape[0] > 0
    keep_counts = counts.shape[0] > 0
    ncol = max(n, 1)
    ck = np.empty((n, ncol))  # cos(ρδ_k), sin(ρδ_k) for the residues ρ = m mod N
    sk = np.empty((n, ncol))
    for k in range(n):
        for rho in range(ncol):
            ck[k, rho] = np.cos(rho * 2.0 * np.pi * k / n) if rho > 0 else 1.0
            sk[k, rho] = np.sin(rho * 2.0 * np.pi * k / n) if rho > 0 else 0.0
    acc_c = np.empty(ncol)
    acc_s = np.empty(ncol)
    cpa = np.empty(na + 1)  # cos, sin of a·2πx/P, a·πJ_u/P, a·πJ_v/P for a = 0 … A
    spa = np.empty(na + 1)
    cua = np.empty(na + 1)
    sua = np.empty(na + 1)
    cva = np.empty(na + 1)
    sva = np.empty(na + 1)
    for v in range(v0, v1):
        for u in range(w):
            if not valid[v, u]:
                for k in range(n):
                    out[k, v, u] = 0
                    if keep_means:
                        means[k, v, u] = 0.0
                continue
            if use_pw:
                for m in range(kmax + 1):
                    c = 0.0
                    for r_ in range(nr):
                        c += pw[v, u, r_] * coefs[r_, m]
                    coef[m] = c
            g = radiance[v, u] * scale
            tau = tol_dn / g if g > 0.0 else np.inf  # the budget in relative radiance
            phi = k1 * coord[v, u]
            c1 = np.cos(phi)
            s1 = np.sin(phi)
            sigma = np.sqrt(var[v, u])
            xj = 2.0 * k1 * sigma  # 4πσ/p: the first harmonic's jinc argument
            sig4pi = 4.0 * np.pi * sigma
            xa = np.pi * jac[v, u, 0] / period if use_jac else 0.0
            xb = np.pi * jac[v, u, 1] / period if use_jac else 0.0
            ju = np.pi * abs(jac[v, u, 0]) if use_jac else 0.0
            jv = np.pi * abs(jac[v, u, 1]) if use_jac else 0.0
            xh = np.pi * hold / period
            ca, sa, sa0 = np.cos(xa), np.sin(xa), 0.0  # sin(m·x) by the Chebyshev recurrence
            cb, sb, sb0 = np.cos(xb), np.sin(xb), 0.0
            cam_a, cam_a0 = ca, 1.0  # cos(m·x) likewise
            cam_b, cam_b0 = cb, 1.0
            ch, sh, sh0 = np.cos(xh), np.sin(xh), 0.0
            if aliasing:
                xq = coord[v, u] / hold  # screen position in pixel pitches
                yu = np.pi * jac[v, u, 0] / hold if use_jac else 0.0
                yv = np.pi * jac[v, u, 1] / hold if use_jac else 0.0
                c_p, s_p = np.cos(2.0 * np.pi * xq), np.sin(2.0 * np.pi * xq)
                c_u, s_u, c_v, s_v = np.cos(yu), np.sin(yu), np.cos(yv), np.sin(yv)
                cpa[0], spa[0], cua[0], sua[0], cva[0], sva[0] = 1.0, 0.0, 1.0, 0.0, 1.0, 0.0
                for a in range(1, na + 1):
                    cpa[a] = cpa[a - 1] * c_p - spa[a - 1] * s_p
                    spa[a] = spa[a - 1] * c_p + cpa[a - 1] * s_p
                    cua[a] = cua[a - 1] * c_u - sua[a - 1] * s_u
                    sua[a] = sua[a - 1] * c_u + cua[a - 1] * s_u
                    cva[a] = cva[a - 1] * c_v - sva[a - 1] * s_v
                    sva[a] = sva[a - 1] * c_v + cva[a - 1] * s_v
            for rho in range(ncol):
                acc_c[rho] = 0.0
                acc_s[rho] = 0.0
            cn, sn = 1.0, 0.0
            lam = -1.0  # Λ, computed when first needed
            terms = 0
            for m in range(1, kmax + 1):
                cn, sn = cn * c1 - sn * s1, sn * c1 + cn * s1
                # Harmonics m … K dropped when their bound is within half the budget: S_m·E(m/p)
                # without screen pixels (E is non-increasing in ν), S_m·Λ with them (Λ ≥ 1, so
                # S_m ≤ τ/2 is necessary and tested first).
                if not aliasing:
                    if suffix[m] * _envelope(m / period, sig4pi, ju, jv) <= 0.5 * tau:
                        break
                elif suffix[m] <= 0.5 * tau:
                    if lam < 0.0:
                        lam = _family_bound(hold, sig4pi, ju, jv, na)
                    if suffix[m] * lam <= 0.5 * tau:
                        break
                if not aliasing:
                    tm = coef[m]
                    if xj != 0.0:
                        tm *= jinc(m * xj, table)
                    if xa != 0.0:
                        tm *= sa / (m * xa)
                    if xb != 0.0:
                        tm *= sb / (m * xb)
                    if xh != 0.0:
                        tm *= sh / (m * xh)
                    t, ts = tm, 0.0
                    terms += 1
                else:
                    # Aliases a with |r + a| ≤ Z: weight sin(πr)/(π(r + a)), phase 2πa·x/P, transfer
                    # at ν = (r + a)/P; sin(πJ_u ν) = sin(m·x_a + a·y_u) by angle addition.
                    r = m * hold / period
                    zcap = n_alias + r + 1.0
                    z_reach = _alias_reach(abs(coef[m]), abs(sh), hold, sig4pi, ju, jv,
                                           0.5 * tau * share[m], zcap)
                    a_lo = max(-na, int(np.ceil(-r - z_reach)))
                    a_hi = min(na, int(np.floor(-r + z_reach)))
                    t, ts = 0.0, 0.0
                    for a in range(a_lo, a_hi + 1):
                        ia = abs(a)
                        sg = 1.0 if a >= 0 else -1.0
                        z = r + a
                        # sin(πr)/(πz) = (−1)^a·sin(πz)/(πz). Where z is within rounding of 0 (a
                        # period that is a whole number of screen pixels: r = −a exactly, but
                        # m·P/p is not) the recurrence's sin(πr) and z are both rounding noise:
                        # the limit (−1)^a·(1 − (πz)²/6) is used for |z| < 1e-6 (its error there
                        # < 1e-22; sh/(πz) elsewhere, relative error ≲ m·1e-16/|πz| ≤ m·3e-11).
                        if abs(z) < 1e-6:
                            ta = coef[m] * (1.0 - 2.0 * (ia % 2)) * (1.0 - (np.pi * z) ** 2 / 6.0)
                        else:
                            ta = coef[m] * sh / (np.pi * z)
                        if xj != 0.0:
                            ta *= jinc(xj * period / hold * abs(z), table)
                        if use_jac:
                            nu = z / hold
                            za = np.pi * jac[v, u, 0] * nu
                            zb = np.pi * jac[v, u, 1] * nu
                            # sinc factors sin(ζ)/ζ; near ζ = 0 the angle-addition numerator is
                            # rounding noise of the size of ζ itself: the limit 1 − ζ²/6 there.
                            if abs(za) >= 1e-6:
                                ta *= (sa * cua[ia] + cam_a * sg * sua[ia]) / za
                            else:
                                ta *= 1.0 - za * za / 6.0
                            if abs(zb) >= 1e-6:
                                ta *= (sb * cva[ia] + cam_b * sg * sva[ia]) / zb
                            else:
                                ta *= 1.0 - zb * zb / 6.0
                        t += ta * cpa[ia]
                        ts += ta * sg * spa[ia]
                    terms += max(0, a_hi - a_lo + 1)
                # Σ_k: cos(m(φ − δ_k) + ψ) through the residue ρ = m mod N (cos mδ_k = cos ρδ_k).
                rho = m % n
                acc_c[rho] += t * cn - ts * sn
                acc_s[rho] += t * sn + ts * cn
                cam_a, cam_a0 = 2.0 * ca * cam_a - cam_a0, cam_a
                cam_b, cam_b0 = 2.0 * cb * cam_b - cam_b0, cam_b
                sa, sa0 = 2.0 * ca * sa - sa0, sa
                sb, sb0 = 2.0 * cb * sb - sb0, sb
                sh, sh0 = 2.0 * ch * sh - sh0, sh
            if keep_counts:
                counts[v, u] = terms
            for k in range(n):
                s = coef[0]
                for rho in range(ncol):
                    s += acc_c[rho] * ck[k, rho] + acc_s[rho] * sk[k, rho]
                mean = g * s
                if keep_means:
                    means[k, v, u] = mean
                out[k, v, u] = sensor_code(mean, dark, clip, shot, const_var, full, use_noise,
                                           noise[k, v, u] if use_noise else 0.0)


@numba.njit(cache=True, parallel=True)
def series_kernel(coord, valid, period, cos_d, sin_d, coefs, pw, use_pw, suffix, share, var, jac, use_jac, hold,
                  radiance, scale, dark, clip, shot, const_var, full, noise, use_noise, table, n_alias, tol_dn, out,
                  means, counts):
    """All N images of one period (:func:`.imaging.render_period_imaging`), rows in parallel
    blocks; ``coefs`` (R, K + 1) the cosine coefficients of R response functions, mixed per pixel
    with the weights ``pw`` (H, W, R) when ``use_pw`` (else row 0 alone; the LCD's viewing-angle
    response, :mod:`.display_angle`); ``means`` (N, H, W) float64 receives g·Σ (the mean before
    noise and rounding) and ``counts`` (H, W) int64 the number of terms summed per pixel, unless they are empty."""
    h = valid.shape[0]
    rows = 16
    for b in numba.prange(0, (h + rows - 1) // rows):
        _series_rows(b * rows, min(h, (b + 1) * rows), coord, valid, period, cos_d, sin_d, coefs, pw, use_pw, suffix,
                     share, var, jac, use_jac, hold, radiance, scale, dark, clip, shot, const_var, full, noise,
                     use_noise, table, n_alias, tol_dn, out, means, counts)
