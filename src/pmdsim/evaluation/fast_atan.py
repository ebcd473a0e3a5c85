"""Fast atan2 onto [0, 2π) for the per-pixel decoding loops (numba).

A rational approximation (Cephes ``atan``) in place of libm's ``atan2``, which called per pixel
was 2–7× slower and dominated the decoding time (:mod:`pmdsim.evaluation.decoding`).
"""

from __future__ import annotations

import math

import numba

from .phase_flags import _TWO_PI

__all__ = ["_phase_0_2pi"]

# atan2 as a rational approximation (Cephes ``atan``, accurate to ~1 ulp, max. deviation from
# libm's atan2 8.9e-16 rad over 4e6 random inputs): libm's atan2 called per pixel was 2–7×
# slower and dominated the decoding time.
_ATAN_P0 = -8.750608600031904122785e-1
_ATAN_P1 = -1.615753718733365076637e1
_ATAN_P2 = -7.500855792314704667340e1
_ATAN_P3 = -1.228866684490136173410e2
_ATAN_P4 = -6.485021904942025371773e1
_ATAN_Q0 = 2.485846490142306297962e1
_ATAN_Q1 = 1.650270098316988542046e2
_ATAN_Q2 = 4.328810604912902668951e2
_ATAN_Q3 = 4.853903996359136964868e2
_ATAN_Q4 = 1.945506571482613964425e2
_ATAN_MOREBITS = 6.123233995736765886130e-17  # π/2 − fl(π/2)
_TAN_3PI_8 = 2.41421356237309504880
_PI = math.pi


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _phase_0_2pi(s, c):
    """atan2(s, c) mapped to [0, 2π); 0 for s = c = 0. NaN in, NaN out.

    Branch-free (selects only) so that loops calling it vectorise."""
    ay = abs(s)
    ax = abs(c)
    big = ay > _TAN_3PI_8 * ax  # atan(ay/ax) = π/2 + atan(−ax/ay)
    mid = ay > 0.66 * ax  # atan(ay/ax) = π/4 + atan((ay − ax)/(ay + ax))
    num = -ax if big else (ay - ax if mid else ay)
    den = ay if big else (ay + ax if mid else ax)
    den = den if den != 0.0 else 1.0  # s = c = 0: num = 0, result 0
    base = 0.5 * _PI if big else (0.25 * _PI if mid else 0.0)
    extra = _ATAN_MOREBITS if big else (0.5 * _ATAN_MOREBITS if mid else 0.0)
    x = num / den
    z = x * x
    p = (((_ATAN_P0 * z + _ATAN_P1) * z + _ATAN_P2) * z + _ATAN_P3) * z + _ATAN_P4
    q = ((((z + _ATAN_Q0) * z + _ATAN_Q1) * z + _ATAN_Q2) * z + _ATAN_Q3) * z + _ATAN_Q4
    t = base + (x + x * (z * p / q) + extra)  # atan(ay / ax) in [0, π/2]
    left = _PI + t if s < 0.0 else _PI - t
    right = _TWO_PI - t if s < 0.0 else t
    r = left if c < 0.0 else right
    return 0.0 if r >= _TWO_PI else r  # 2π − tiny rounds to 2π
