"""sin and cos as a branch-free polynomial, for loops that numba/LLVM should vectorise (issue 15).

libm's ``sin`` and ``cos`` are calls: a loop containing them does not vectorise, and at
≈ 47 ns per (sin, cos) pair they were half of the fringe renderer's time. :func:`sincos` is
Cody–Waite reduction by π/2 (fdlibm's three-part π/2; k·PIO2_1 and k·PIO2_2 are exact for
|k| < 2^20) followed by fdlibm's ``__kernel_sin``/``__kernel_cos`` polynomials on [−π/4, π/4]:
≈ 1.3 ns per pair when vectorised, within 4·10⁻¹⁶ of libm for |φ| ≤ :data:`MAX_FAST_PHASE`
(tests/test_synthetic_decode.py). It is not bit-identical to libm; callers that must reproduce
libm-based results (the quantised fringe images) recompute with libm every value that lies
within :data:`TIE_GUARD` of a rounding boundary.

:func:`fast_asin` is fdlibm's ``e_asin.c`` rational approximation as an inlinable numba function
(libm's ``asin`` is a call, too; used by the screen pixels' staircase, :mod:`pmdsim.simulation.imaging_held`).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["sincos", "sincos_into", "libm_grey_level", "fast_asin", "asin_ratio", "ASIN_PIO2_HI", "ASIN_PIO2_LO", "MAX_FAST_PHASE", "TIE_GUARD"]

_TWO_OVER_PI = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624871116645580e-21
_S1 = -1.66666666666666324348e-01
_S2 = 8.33333333332248946124e-03
_S3 = -1.98412698298579493134e-04
_S4 = 2.75573137070700676789e-06
_S5 = -2.50507602534068634195e-08
_S6 = 1.58969099521155010221e-10
_C1 = 4.16666666666666019037e-02
_C2 = -1.38888888888741095749e-03
_C3 = 2.48015872894767294178e-05
_C4 = -2.75573143513906633035e-07
_C5 = 2.08757232129817482790e-09
_C6 = -1.13596475577881948265e-11
_ROUND_MAGIC = 6755399441055744.0  # 1.5·2^52: x + M − M rounds x to the nearest integer
MAX_FAST_PHASE = 1.0e5  # |φ| above this (or not finite): use libm
# Grey levels. The fast sin/cos (≤ 4e-16 from libm) move the value being rounded by at most
# F·2·4e-16 plus a few of its ulps: < 1e-10 even at 16 bits (F = 65535).
TIE_GUARD = 1.0e-7


@numba.njit(cache=True, fastmath=False, error_model="numpy")
def sincos(phi):
    """(sin φ, cos φ), branch-free (selects only, so that loops calling it vectorise); for
    |φ| ≤ :data:`MAX_FAST_PHASE`."""
    k = (phi * _TWO_OVER_PI + _ROUND_MAGIC) - _ROUND_MAGIC  # nearest integer (|k| < 2^51)
    r = ((phi - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
    z = r * r
    sr = r + r * z * (_S1 + z * (_S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))))
    cr = 1.0 - 0.5 * z + z * z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6)))))
    q = k - 4.0 * np.floor(k * 0.25)  # quadrant 0, 1, 2, 3
    swap = (q == 1.0) | (q == 3.0)
    s = cr if swap else sr
    c = sr if swap else cr
    s = -s if q >= 2.0 else s
    c = -c if (q == 1.0) | (q == 2.0) else c
    return s, c


@numba.njit(cache=True, fastmath=False, error_model="numpy")
def sincos_into(phi, s, c):
    """Element-wise :func:`sincos` of the 1-D array ``phi`` into ``s`` and ``c``."""
    for i in range(phi.shape[0]):
        s[i], c[i] = sincos(phi[i])


@numba.njit(cache=True, error_model="numpy")
def libm_grey_level(c, s, cos_dk, sin_dk, mean, amp, full_scale, has_noise, noise_value):
    """The fringe renderer's quantised grey level with libm's cos φ = ``c`` and sin φ = ``s``:
    round half up of F·(mean + amp·(cos φ·cos δ_k + sin φ·sin δ_k)) (+ noise), clipped to [0, F]
    (F = ``full_scale``; docs/conventions.md, "Fringe patterns"). The exact reference that callers
    of :func:`sincos` fall back to within :data:`TIE_GUARD` of a rounding boundary; one
    definition for the renderer (:mod:`pmdsim.simulation.patterns`) and the fused
    render-and-decode (:mod:`pmdsim.evaluation.synthetic_decode`), which must agree bit for bit."""
    val = full_scale * (mean + amp * (c * cos_dk + s * sin_dk))
    if has_noise:
        val += noise_value
    q = np.floor(val + 0.5)
    if q < 0.0:
        q = 0.0
    elif q > full_scale:
        q = full_scale
    return q


# fdlibm e_asin.c (Sun Microsystems 1993) coefficients: asin x = x + x·R(x²), R = P/Q.
ASIN_PIO2_HI = 1.57079632679489655800e00
ASIN_PIO2_LO = 6.12323399573676603587e-17
_PS0 = 1.66666666666666657415e-01
_PS1 = -3.25565818622400915405e-01
_PS2 = 2.01212532134862925881e-01
_PS3 = -4.00555345006794114027e-02
_PS4 = 7.91534994289814532176e-04
_PS5 = 3.47933107596021167570e-05
_QS1 = -2.40339491173441421878e00
_QS2 = 2.02094576023350569471e00
_QS3 = -6.88283971605453293030e-01
_QS4 = 7.70381505559019352791e-02


@numba.njit(cache=True, error_model="numpy")
def asin_ratio(t):
    """fdlibm's R(t) = P(t)/Q(t) of ``e_asin.c``: asin x = x + x·R(x²) for |x| < ½, and
    π/2 − 2·(s + s·R(t)) with t = (1 − |x|)/2, s = √t, above (:func:`fast_asin`; branch-free
    callers evaluate both)."""
    p = t * (_PS0 + t * (_PS1 + t * (_PS2 + t * (_PS3 + t * (_PS4 + t * _PS5)))))
    q = 1.0 + t * (_QS1 + t * (_QS2 + t * (_QS3 + t * _QS4)))
    return p / q


@numba.njit(cache=True, error_model="numpy")
def fast_asin(x):
    """asin x for |x| ≤ 1 (fdlibm's e_asin.c rational approximation, Sun Microsystems 1993,
    without its extra-precision split: within a few ulp of libm; tests/test_imaging_held.py)."""
    ax = abs(x)
    if ax < 0.5:
        return x + x * asin_ratio(x * x)
    t = 0.5 * (1.0 - ax)
    s = np.sqrt(t)
    r = ASIN_PIO2_HI - (2.0 * (s + s * asin_ratio(t)) - ASIN_PIO2_LO)
    return r if x > 0.0 else -r
