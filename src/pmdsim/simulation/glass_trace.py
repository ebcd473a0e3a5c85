"""The tracer's refracting pass through the screen's cover glass, as one compiled kernel.

:func:`refract_traced` takes the glass-free trace's per-pixel sample points (sample frame) and
screen hits (screen frame) and, for every valid pixel, traces the reflected ray from its sample
point towards its glass-free hit through the glass
(:func:`pmdsim.geometry.cover_glass.through_glass_kernel`, warm started from that hit), writing
the emitting-surface point, the pattern coordinates and the status in place — the frame change,
the gather and the scatter fused into one numba ``prange`` over pixel chunks (no temporaries).
The same per-ray kernel as :meth:`CoverGlass.trace`, so the result is identical.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.cover_glass import through_glass_kernel
from ..geometry.surface import FIXED_POINT_MAX_ITER

__all__ = ["refract_traced"]

_CHUNK = 4096


@numba.njit(cache=True, parallel=True)
def _refract_kernel(rot, trans, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, p_s, q_p, screen_xy, status,
                    codes, tol, max_iter):
    n = status.shape[0]
    for c in numba.prange(0, (n + _CHUNK - 1) // _CHUNK):
        for i in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
            if status[i] != 0:
                continue
            px, py, pz = p_s[i, 0], p_s[i, 1], p_s[i, 2]
            ox = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
            oy = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
            oz = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
            x0, y0, z0 = q_p[i, 0], q_p[i, 1], q_p[i, 2]
            x, y, z, st = through_glass_kernel(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz,
                                               x0 - ox, y0 - oy, z0 - oz, x0, y0, z0, tol, max_iter)
            if st != 0:
                x = np.nan
                y = np.nan
                z = np.nan
                status[i] = codes[min(st, 3)]
            q_p[i, 0] = x
            q_p[i, 1] = y
            q_p[i, 2] = z
            screen_xy[i, 0] = x
            screen_xy[i, 1] = y


def refract_traced(glass, screen, T_screen_sample, p_s, q_p, screen_xy, status, codes, tol_mm) -> None:
    """Refract every valid pixel's reflected ray through ``glass`` (module docstring).

    Parameters
    ----------
    glass : CoverGlass
        The glass (present).
    screen : surface with ``kernel``
        The emitting surface.
    T_screen_sample : RigidTransform
        Sample frame → screen frame.
    p_s, q_p : ndarray (N, 3)
        Sample points (sample frame) and glass-free screen hits (screen frame); ``q_p`` is
        overwritten with the emitting-surface points (NaN where the glass trace fails).
    screen_xy : ndarray (N, 2), status : ndarray of uint8 (N,)
        Updated in place (status 0 = valid; a failure takes ``codes[min(code, 3)]``).
    codes : ndarray of uint8 (4,)
        The tracer's screen status codes by IntersectStatus.
    tol_mm : float
        Intersection tolerance.
    """
    k = screen.kernel
    _refract_kernel(np.ascontiguousarray(T_screen_sample.rotation), np.ascontiguousarray(T_screen_sample.translation),
                    k.kind, k.grid_x, k.grid_y, k.coef, k.z_min, k.z_max, k.dmax, float(glass.thickness_mm),
                    float(glass.index), p_s, q_p, screen_xy, status, codes, float(tol_mm), FIXED_POINT_MAX_ITER)
