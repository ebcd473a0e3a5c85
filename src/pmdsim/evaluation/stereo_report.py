"""The agreement report of a stereo reconstruction (:mod:`pmdsim.evaluation.stereo`, step 3).

Per pixel of a camera A with a height, and a partner camera B that sees the point: the angle
between the normals A's and B's registered screen points imply at A's reconstructed point, and
the height discrepancy z_A − z_B along A's view ray, z_B from B's reconstruction interpolated at
the point's projection into B and iterated to the intersection with A's ray (a contraction for
slopes ≪ 1, to :data:`~pmdsim.evaluation.stereo._REPORT_TOL_MM`).

The work per pixel (issue 25, st25h): one projection into B serves both the normals and the
first step of the intersection (it is the same point), and the "all 16 samples valid" test of
the cubic convolution (:func:`pmdsim.evaluation.stereo._interp`) is one look-up in a mask of
valid 4 × 4 windows computed once per map (:func:`ok_windows`) instead of 16 per
interpolation. The results are bit-identical to the per-sample tests and a second projection
(the same operations in the same order).
"""

from __future__ import annotations

import numba
import numpy as np

from .integration import _bisector_slopes
from .stereo import _REPORT_MAX_ITER, _REPORT_TOL_MM, _cell, _interp_at, _partners, _project

__all__ = ["agreement", "ok_windows"]


def ok_windows(ok: np.ndarray) -> np.ndarray:
    """(H, W) bool: ``out[j, i]`` is True where every sample of the 4 × 4 neighbourhood
    ``ok[j − 1 : j + 3, i − 1 : i + 3]`` of :func:`pmdsim.evaluation.stereo._interp` is True
    (False where that neighbourhood leaves the (H, W) map ``ok``)."""
    ok = np.asarray(ok, dtype=bool)
    H, W = ok.shape
    out = np.zeros((H, W), dtype=bool)
    if H >= 4 and W >= 4:
        h = ok[:, :-3] & ok[:, 1:-2] & ok[:, 2:-1] & ok[:, 3:]  # columns i − 1 … i + 2, i = 1 … W − 3
        out[1:H - 2, 1:W - 2] = h[:-3] & h[1:-2] & h[2:-1] & h[3:]
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _interp_window(arr, win, u, v, out):
    """:func:`pmdsim.evaluation.stereo._interp` with its 16 validity tests replaced by one
    look-up of ``win`` (:func:`ok_windows` of its ``ok``): the same result."""
    inside, iu, iv = _cell(arr, u, v)
    if not inside or not win[iv, iu]:
        return False
    _interp_at(arr, iu, iv, u, v, out)
    return True


@numba.njit(cache=True, nogil=True, parallel=True)
def _report_kernel(oA, d, q, zA, oB, qB, winB, zB, winzB, RB, tB, camB, ang_out, dz_out):
    """Per pixel of A with a height zA (H, W): the angle between A's and B's implied normals
    (rad) and z_A − z_B along A's ray (mm); NaN where B does not see the point. ``qB`` (H', W', 3)
    B's screen points, ``winB`` their valid 4 × 4 windows; ``zB`` (H', W', 1) B's heights (0 where
    none), ``winzB`` their valid windows (:func:`ok_windows`); RB, tB: T_cam_ref of B, camB its
    intrinsics (:func:`pmdsim.evaluation.stereo._project`)."""
    H, W = zA.shape
    for v in numba.prange(0, H):
        buf = np.empty(3)
        hb = np.empty(1)
        for u in range(W):
            ang_out[v, u] = np.nan
            dz_out[v, u] = np.nan
            z = zA[v, u]
            if not np.isfinite(z):
                continue
            dx = d[v, u, 0]
            dy = d[v, u, 1]
            dz = d[v, u, 2]
            t = (z - oA[2]) / dz
            px = oA[0] + t * dx
            py = oA[1] + t * dy
            ok, uu, vv = _project(RB, tB, camB, px, py, z)
            if not ok or not _interp_window(qB, winB, uu, vv, buf):
                continue
            gax, gay = _bisector_slopes(px, py, z, oA[0], oA[1], oA[2], q[v, u, 0], q[v, u, 1], q[v, u, 2])
            gbx, gby = _bisector_slopes(px, py, z, oB[0], oB[1], oB[2], buf[0], buf[1], buf[2])
            if not (np.isfinite(gax - gbx) and np.isfinite(gay - gby)):
                continue
            ax, ay, az = -gax, -gay, 1.0
            bx, by, bz = -gbx, -gby, 1.0
            cx = ay * bz - az * by
            cy = az * bx - ax * bz
            cz = ax * by - ay * bx
            ang_out[v, u] = np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)
            # B's surface along A's ray: z ← z_B(projection of p(z)); the first projection is the one above
            zz = z
            good = False
            for it in range(_REPORT_MAX_ITER):
                if it > 0:
                    t = (zz - oA[2]) / dz
                    ok, uu, vv = _project(RB, tB, camB, oA[0] + t * dx, oA[1] + t * dy, zz)
                if not ok or not _interp_window(zB, winzB, uu, vv, hb):
                    good = False
                    break
                good = True
                change = hb[0] - zz
                zz = hb[0]
                if abs(change) < _REPORT_TOL_MM:
                    break
            if good:
                dz_out[v, u] = z - zz


def agreement(arrays: dict, cams: dict, heights: dict) -> dict:
    """The agreement maps of every camera against every other (with several partners: the
    largest angle, the discrepancy largest in magnitude).

    ``arrays``: name → (o, d, q, valid) (:func:`pmdsim.evaluation.stereo._view_arrays`),
    ``cams``: name → (R, t, intrinsics) (:func:`pmdsim.evaluation.stereo._camera_arrays`),
    ``heights``: name → (H, W) reconstructed heights (NaN where none), mm. Returns name →
    (angle (H, W) rad, z_this − z_partner (H, W) mm), NaN where no partner sees the point."""
    win = {n: ok_windows(a[3]) for n, a in arrays.items()}
    zwin = {n: ok_windows(np.isfinite(z)) for n, z in heights.items()}
    zpad = {n: np.ascontiguousarray(np.nan_to_num(z)[..., None]) for n, z in heights.items()}
    out = {}
    for name, (o, d, q, _) in arrays.items():
        zA = heights[name]
        ang = np.full(zA.shape, np.nan)
        dzm = np.full(zA.shape, np.nan)
        for partner, oB, qB, _, RB, tB, camB in _partners(arrays, cams, name):
            a = np.empty(zA.shape)
            dz = np.empty(zA.shape)
            _report_kernel(o, d, q, zA, oB, qB, win[partner], zpad[partner], zwin[partner], RB, tB, camB, a, dz)
            ang = np.fmax(ang, a)
            dzm = np.where(np.isnan(dzm) | (np.abs(dz) > np.abs(dzm)), dz, dzm)
        out[name] = (ang, dzm)
    return out
