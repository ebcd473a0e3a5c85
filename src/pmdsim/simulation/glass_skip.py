"""The cover glass's foot-point Newton step skipped where the prediction is provably good enough.

The row kernel's glass stage (:mod:`pmdsim.simulation.glass_rows`) predicts each pixel's foot
point u_lin from the outer-surface height A_z and plate normal m of the two rows above,
extrapolated linearly, and takes one Newton step s = u* − u_lin on F(u) = A(u)_xy − (a + b·A(u)_z)
(A(u) = (u, h(u)) + t·m(u), the ray x = a + b·z). That step is ≈ 1.3e-6 mm on Table 1's
bulged screen and varies smoothly down a column: its first difference between rows is ≈ 1e-9 mm,
its second ≈ 1e-13 mm (rounding; docs/benchmarks.md "Cover glass (issue 21): the foot step skipped
where bounded"). So the steps s₁, s₂ of the two rows above, extrapolated (2·s₁ − s₂), predict
this row's to ≈ 1e-13 mm: the foot point v = u_lin + 2·s₁ − s₂ needs no Newton step, only a proof
that it is within the foot tolerance τ = 1e-9 mm of the root (the convergence threshold of
:func:`~pmdsim.geometry.cover_glass.through_glass_full` and of the Newton step's own bound).

**The bound** (from the residual F(v) alone: one bicubic evaluation of h and ∇h at v, without
the Hessian). Write F's Jacobian J = I + E with E = t·∂m_xy/∂u − b ⊗ ∇A_z, ∇A_z = ∇h + t·∇m_z,
m = (h_x·g, h_y·g, −g), g = 1/√(1 + |∇h|²). Let D₂ bound every second partial derivative of h
(:attr:`~pmdsim.geometry.surface.KernelSurface.dmax`) and σ = |h_x(v)| + |h_y(v)| + 4·D₂·τ, which
bounds |h_x| + |h_y| on the ball B = {u: ‖u − v‖_∞ ≤ τ}; require σ ≤ 1. On B, with
p_j = h_x·∂_j h_x + h_y·∂_j h_y (|p_j| ≤ σ·D₂ ≤ D₂),

* ∂_j(h_i·g) = g·∂_j h_i − h_i·g³·p_j, so |∂_j m_i| ≤ D₂·(1 + σ²) ≤ 2·D₂ (g ≤ 1);
* ∂_j m_z = g³·p_j, so |∂_j m_z| ≤ D₂;

and the row sums of |E| are at most ε = 4·t·D₂ + max(|b_x|, |b_y|)·(σ + 2·t·D₂). If ε < 1 and
‖F(v)‖_∞ ≤ (1 − ε)·τ, let ρ = ‖F(v)‖_∞ / (1 − ε) ≤ τ. The map G(u) = u − F(u) has
‖G′‖_∞ = ‖E‖_∞ ≤ ε on B(v, ρ) ⊆ B and ‖G(u) − v‖ ≤ ‖G(u) − G(v)‖ + ‖F(v)‖ ≤ ε·ρ + (1 − ε)·ρ = ρ:
G maps B(v, ρ) into itself and contracts, so F has exactly one root u* there and
‖v − u*‖_∞ ≤ ρ ≤ τ — the same guarantee as an accepted Newton step's (whose own bound is also
τ), with h, ∇h and g evaluated at v itself rather than carried there by Taylor's theorem. The
residual's rounding (≈ 1e-13 mm for foot points of a few 100 mm) is far below τ and, as in the
Newton step's bound, not counted. v must also lie strictly inside the patch of u_lin (the run's
patch; edge patches open outwards), where that patch's polynomial is h.

A block run takes the skip only if every pixel of it passes (one vectorised loop,
:func:`skip_check_run`), else the run takes the Newton step (:func:`glass_rows._foot_run`'s loop,
unchanged). The steps s of the rows above (``zr[10:14]``) are those taken (u* − u_lin after the
Newton step), or where skipped v − F(v) − u_lin (the root to first order: |J⁻¹ − I| ≤ ε/(1 − ε)
keeps the stored step within ε·|F|/(1 − ε) ≈ 1e-15 mm of the root's, so the prediction does not
drift from row to row); NaN where the pixel is not valid, went to the scalar path, or had no
linear prediction (the first two rows of a band): the next two rows take the Newton step there.
"""

from __future__ import annotations

import math

import numba

from ..geometry.cover_glass import _FOOT_TOL_MM
from .trace_rows import _AX, _AY, _BLK, _BX, _BY, _CONV, _HX, _HY, _JIT, _UX, _UY, _VX, _VY, _X, _Y, _Z, patch_rows

__all__ = ["foot_skip_bound", "skip_check_run"]


@numba.njit(**_JIT, inline="always")
def foot_skip_bound(vx, vy, hx, hy, g, h, ax, ay, bx, by, t, d2):
    """The residual F(v) = (f_x, f_y) at the foot point v (height ``h``, gradient ``hx``, ``hy``,
    g = 1/√(1 + h_x² + h_y²)) of the ray x = a_x + b_x·z, y = a_y + b_y·z through a glass of
    thickness ``t`` on a surface whose second derivatives are bounded by ``d2``, and whether v is
    provably within the foot tolerance of the root (module docstring). Returns ``(f_x, f_y, ok)``;
    NaN anywhere gives ``ok`` False."""
    azu = h - t * g
    fx = vx + t * (hx * g) - ax - bx * azu
    fy = vy + t * (hy * g) - ay - by * azu
    sig = abs(hx) + abs(hy) + 4.0 * d2 * _FOOT_TOL_MM
    eps = 4.0 * t * d2 + max(abs(bx), abs(by)) * (sig + 2.0 * t * d2)
    ok = (max(abs(fx), abs(fy)) <= (1.0 - eps) * _FOOT_TOL_MM) & (sig <= 1.0) & (eps < 1.0)
    return fx, fy, ok


@numba.njit(**_JIT, inline="always")
def _in_box(x, y, x_lo, x_hi, y_lo, y_hi):
    """Whether (x, y) lies strictly inside the open box (x_lo, x_hi) × (y_lo, y_hi) (NaN: False)."""
    return (x > x_lo) & (x < x_hi) & (y > y_lo) & (y < y_hi)


@numba.njit(**_JIT)
def skip_check_run(n, c, gxi, gyj, x_lo, x_hi, y_lo, y_hi, t, d2, s1x, s1y, s2x, s2y, S):
    """The skip's check for pixels 0 … n − 1 of ``S`` (a view from the run's first pixel), all on
    one bicubic patch (coefficients ``c[0:16]``, origin (gxi, gyj), open interval
    (x_lo, x_hi) × (y_lo, y_hi)): at each pixel's predicted foot point v = u_lin + 2·s₁ − s₂
    (u_lin in _UX, _UY; the steps of the two rows above in ``s1x`` … ``s2y``; v stored in _X,
    _Y) the height, gradient and g (stored in _Z, _HX, _HY, _CONV), the residual's bound
    (:func:`foot_skip_bound`), and the step estimate v − F(v) − u_lin (stored in _VX, _VY, where
    :func:`.glass_rows._foot_run` keeps the step for the rows below; u_lin in _UX, _UY). Returns
    the number of pixels that pass. One loop without branches (vectorised)."""
    c0, c1, c2, c3, c4, c5, c6, c7 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
    c8, c9, c10, c11, c12, c13, c14, c15 = c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15]
    B = _BLK
    n_ok = 0
    for i in range(n):
        vx = S[_UX * B + i] + (2.0 * s1x[i] - s2x[i])
        vy = S[_UY * B + i] + (2.0 * s1y[i] - s2y[i])
        sx = vx - gxi
        sy = vy - gyj
        r0, r1, r2, r3, e1d0, e1d1, e1d2, e1d3 = patch_rows(c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12,
                                                            c13, c14, c15, sx)
        h = r0 + sy * (r1 + sy * (r2 + sy * r3))
        hx = e1d0 + sy * (e1d1 + sy * (e1d2 + sy * e1d3))
        hy = r1 + sy * (2.0 * r2 + sy * 3.0 * r3)
        g = 1.0 / math.sqrt(1.0 + hx * hx + hy * hy)
        fx, fy, ok = foot_skip_bound(vx, vy, hx, hy, g, h, S[_AX * B + i], S[_AY * B + i], S[_BX * B + i],
                                     S[_BY * B + i], t, d2)
        inside = _in_box(vx, vy, x_lo, x_hi, y_lo, y_hi)
        S[_X * B + i] = vx
        S[_Y * B + i] = vy
        S[_Z * B + i] = h
        S[_HX * B + i] = hx
        S[_HY * B + i] = hy
        S[_CONV * B + i] = g
        S[_VX * B + i] = (vx - fx) - S[_UX * B + i]
        S[_VY * B + i] = (vy - fy) - S[_UY * B + i]
        n_ok += ok & inside
    return n_ok
