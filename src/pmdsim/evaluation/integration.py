"""What both surface integrators share (paper §2.5): the result type, input checks, the seed,
and the bisector normals and slopes (the law of reflection).

The method and its notation: :mod:`pmdsim.evaluation.reconstruction`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..errors import PmdsimError
from ..geometry.compact import compact_repr

__all__ = ["ReconstructionError", "Reconstruction", "normals_from_registration"]


class ReconstructionError(PmdsimError, ValueError):
    """The inputs of a surface reconstruction are inconsistent or unusable.

    The message names the offending argument (``o``, ``d``, ``q``, ``valid``, ``seed_pixel``,
    ``seed_height_mm``, ``method``, …) and what was expected.
    """


@dataclass(frozen=True)
class Reconstruction:
    """Result of a surface reconstruction (paper §2.5), in the reconstruction frame.

    Attributes
    ----------
    height_mm : ndarray, shape (H, W)
        Surface height z (along the frame's +z) per pixel, mm; NaN where not reconstructed.
    p_sample_mm : ndarray, shape (H, W, 3)
        Reconstructed surface points p = o + t·d in the reconstruction frame (the sample frame
        in pmdsim's pipeline), mm; NaN where not reconstructed.
    n_sample : ndarray, shape (H, W, 3)
        Unit surface normals at ``p_sample_mm`` (bisector of the directions to the camera and to the
        screen point), oriented towards the camera: n·(o − p) > 0; NaN where not reconstructed.
    reconstructed : ndarray of bool, shape (H, W)
        True where a height was reconstructed.
    method : str
        ``"stepwise"`` or ``"least_squares"``.
    iterations : int
        ``"least_squares"``: number of Gauss–Newton iterations (points → slopes → sparse
        solve for the height update).
        ``"stepwise"``: the largest number of corrector iterations that any single integration
        step needed.
    converged : bool
        ``"least_squares"``: the last iteration changed no height by ``tol_mm`` or more (and
        its sparse solve converged).
        ``"stepwise"``: every step's corrector met |Δz| < :data:`STEP_TOL_MM`.
    seed_pixel : tuple of int
        (row, column) of the initial point whose height was given.
    final_change_mm : float
        The largest height change of the last iteration (outer iteration for
        ``"least_squares"``, last corrector update of any step for ``"stepwise"``), mm.
    """

    __repr__ = compact_repr  # one line: arrays by shape and dtype (issue 23)

    height_mm: np.ndarray
    p_sample_mm: np.ndarray
    n_sample: np.ndarray
    reconstructed: np.ndarray
    method: str
    iterations: int
    converged: bool
    seed_pixel: tuple[int, int]
    final_change_mm: float = 0.0


def normals_from_registration(p, o, q) -> np.ndarray:
    """Surface normals from the law of reflection (paper §2.5).

    The normal at a surface point bisects the directions to the camera centre and to the
    screen point that the pixel sees:

        n = ((o − p)/|o − p| + (q − p)/|q − p|) / |…|

    Parameters
    ----------
    p : array_like, shape (..., 3)
        Surface points, mm.
    o : array_like, shape (..., 3)
        Camera projection centre(s), mm; broadcasts against ``p`` (typically shape (3,)).
    q : array_like, shape (..., 3)
        Screen points of the deflectometric registration, mm; broadcasts against ``p``.

    Returns
    -------
    ndarray, shape (..., 3)
        Unit normals, oriented towards the camera and screen side of the surface (the side the
        light comes from): n·(o − p) > 0 and n·(q − p) > 0. NaN where undefined (p coincides
        with o or q, or the two directions are opposite).
    """
    p = np.asarray(p, dtype=np.float64)
    o = np.asarray(o, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    for name, a in (("p", p), ("o", o), ("q", q)):
        if a.ndim < 1 or a.shape[-1] != 3:
            raise ReconstructionError(f"{name} must have shape (..., 3), got {a.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        a = o - p
        b = q - p
        n = a / np.linalg.norm(a, axis=-1, keepdims=True) + b / np.linalg.norm(b, axis=-1, keepdims=True)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    n[~np.all(np.isfinite(n), axis=-1)] = np.nan
    return n


@numba.njit(cache=True, nogil=True)
def _scan_inputs(d, q, valid):
    """One pass over the valid pixels: counts and first flat indices (row-major) of
    [non-finite d, d_z == 0 (among finite d), non-finite q]."""
    H, W = valid.shape
    count = np.zeros(3, dtype=np.int64)
    first = np.full(3, -1, dtype=np.int64)
    for v in range(H):
        for u in range(W):
            if not valid[v, u]:
                continue
            k = v * W + u
            if not (np.isfinite(d[v, u, 0]) and np.isfinite(d[v, u, 1]) and np.isfinite(d[v, u, 2])):
                c = 0
            elif d[v, u, 2] == 0.0:
                c = 1
            else:
                c = -1
            if c >= 0:
                if count[c] == 0:
                    first[c] = k
                count[c] += 1
            if not (np.isfinite(q[v, u, 0]) and np.isfinite(q[v, u, 1]) and np.isfinite(q[v, u, 2])):
                if count[2] == 0:
                    first[2] = k
                count[2] += 1
    return count, first


def _check_inputs(o, d, q, valid):
    o = np.asarray(o, dtype=np.float64)
    if o.shape != (3,):
        raise ReconstructionError(f"o (camera centre) must have shape (3,), got {o.shape}")
    if not np.all(np.isfinite(o)):
        raise ReconstructionError(f"o (camera centre) must be finite, got {o.tolist()}")
    d = np.asarray(d, dtype=np.float64)
    if d.ndim != 3 or d.shape[2] != 3:
        raise ReconstructionError(f"d (view-ray directions) must have shape (H, W, 3), got {d.shape}")
    H, W = d.shape[:2]
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (H, W, 3):
        raise ReconstructionError(
            f"q (registered screen points) must have shape (H, W, 3) = {(H, W, 3)} like d, got {q.shape}")
    valid_arr = np.asarray(valid)
    if valid_arr.shape != (H, W):
        raise ReconstructionError(
            f"valid must have shape (H, W) = {(H, W)} like d[..., 0], got {valid_arr.shape}")
    if valid_arr.dtype != np.bool_:
        if not np.issubdtype(valid_arr.dtype, np.integer):
            raise ReconstructionError(f"valid must be a boolean mask, got dtype {valid_arr.dtype}")
        valid_arr = valid_arr != 0
    if not valid_arr.any():
        raise ReconstructionError("valid has no True pixel: there is nothing to reconstruct")
    d = np.ascontiguousarray(d)
    q = np.ascontiguousarray(q)
    valid_arr = np.ascontiguousarray(valid_arr)
    count, first = _scan_inputs(d, q, valid_arr)
    if count[0]:
        v, u = divmod(int(first[0]), W)
        raise ReconstructionError(
            f"d has non-finite directions at {int(count[0])} valid pixels (first at row {v}, column {u}); "
            "mark them invalid in valid")
    if count[1]:
        v, u = divmod(int(first[1]), W)
        raise ReconstructionError(
            f"d has {int(count[1])} valid view rays with d_z == 0 (first at row {v}, column {u}): such a ray "
            "runs parallel to the x–y plane, perpendicular to the height axis, and its height cannot "
            "be solved for; mark these pixels invalid in valid or choose a frame whose +z is not "
            "perpendicular to them")
    if count[2]:
        v, u = divmod(int(first[2]), W)
        raise ReconstructionError(
            f"q has non-finite screen points at {int(count[2])} valid pixels (first at row {v}, column {u}); "
            "mark them invalid in valid")
    return o, d, q, valid_arr


def _default_seed(valid):
    vv, uu = np.nonzero(valid)
    cv = vv.mean()
    cu = uu.mean()
    k = int(np.argmin((vv - cv) ** 2 + (uu - cu) ** 2))  # first in row-major order on ties
    return int(vv[k]), int(uu[k])


def _check_seed(seed_pixel, seed_height_mm, o, d, valid):
    H, W = valid.shape
    if seed_pixel is None:
        seed = _default_seed(valid)
    else:
        try:
            sv, su = seed_pixel
            if isinstance(sv, (bool, np.bool_)) or isinstance(su, (bool, np.bool_)):
                raise TypeError
            if int(sv) != sv or int(su) != su:
                raise TypeError
            seed = (int(sv), int(su))
        except (TypeError, ValueError):
            raise ReconstructionError(
                f"seed_pixel must be a (row, column) pair of integers, got {seed_pixel!r}") from None
        if not (0 <= seed[0] < H and 0 <= seed[1] < W):
            raise ReconstructionError(
                f"seed_pixel {seed} is outside the image: rows 0…{H - 1}, columns 0…{W - 1}")
        if not valid[seed]:
            raise ReconstructionError(
                f"seed_pixel {seed} is not a valid pixel (valid[{seed[0]}, {seed[1]}] is False); "
                "choose a valid pixel or pass seed_pixel=None for the valid pixel nearest to the "
                "centroid of the mask")
    try:
        z0 = float(seed_height_mm)
    except (TypeError, ValueError):
        raise ReconstructionError(f"seed_height_mm must be a number, got {seed_height_mm!r}") from None
    if not np.isfinite(z0):
        raise ReconstructionError(f"seed_height_mm must be finite, got {z0}")
    t0 = (z0 - o[2]) / d[seed][2]
    if not t0 > 0.0:
        raise ReconstructionError(
            f"seed_height_mm = {z0} puts the seed pixel {seed}'s surface point behind the camera "
            f"(ray parameter t = {t0:.6g} ≤ 0; camera centre at z = {o[2]:.6g} mm, ray direction "
            f"d_z = {d[seed][2]:.6g}); give the seed's height on the visible side of the camera")
    return seed, z0


@numba.njit(cache=True, nogil=True, inline="always")
def _bisector(px, py, pz, ox, oy, oz, qx, qy, qz):
    ax = ox - px
    ay = oy - py
    az = oz - pz
    la = np.sqrt(ax * ax + ay * ay + az * az)
    bx = qx - px
    by = qy - py
    bz = qz - pz
    lb = np.sqrt(bx * bx + by * by + bz * bz)
    nx = ax / la + bx / lb
    ny = ay / la + by / lb
    nz = az / la + bz / lb
    ln = np.sqrt(nx * nx + ny * ny + nz * nz)
    return nx / ln, ny / ln, nz / ln


@numba.njit(cache=True, nogil=True, inline="always")
def _bisector_slopes(px, py, pz, ox, oy, oz, qx, qy, qz):
    """Slopes (−m_x/m_z, −m_y/m_z) of the bisector m = â + b̂ (its length does not matter)."""
    ax = ox - px
    ay = oy - py
    az = oz - pz
    ia = 1.0 / np.sqrt(ax * ax + ay * ay + az * az)
    bx = qx - px
    by = qy - py
    bz = qz - pz
    ib = 1.0 / np.sqrt(bx * bx + by * by + bz * bz)
    imz = -1.0 / (az * ia + bz * ib)
    return (ax * ia + bx * ib) * imz, (ay * ia + by * ib) * imz


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _points_normals(o, d, q, z, points, normals):
    """Points (H, W, 3) on the view rays at heights z (H, W) and their bisector normals
    (:func:`_bisector`); NaN where z is NaN.

    One loop per row over the (W, 3) rows of d, q and the outputs, without branches (a NaN
    height gives NaN everywhere by itself): the divisions and square roots, which bound the
    loop, overlap with its memory traffic (a row gathered into contiguous rows first, then
    computed, then scattered, took twice as long on one thread: the passes ran one after the
    other). The same operations per pixel as :func:`_bisector`, bit for bit."""
    H, W = z.shape
    ox = o[0]
    oy = o[1]
    oz = o[2]
    for v in numba.prange(0, H):
        zr = z[v]
        dr = d[v].reshape(3 * W)  # contiguous rows (views)
        qr = q[v].reshape(3 * W)
        pr = points[v].reshape(3 * W)
        nr = normals[v].reshape(3 * W)
        for u in range(W):
            zz = zr[u]
            t = (zz - oz) / dr[3 * u + 2]
            px = ox + t * dr[3 * u]
            py = oy + t * dr[3 * u + 1]
            pr[3 * u] = px
            pr[3 * u + 1] = py
            pr[3 * u + 2] = zz
            nr[3 * u], nr[3 * u + 1], nr[3 * u + 2] = _bisector(
                px, py, zz, ox, oy, oz, qr[3 * u], qr[3 * u + 1], qr[3 * u + 2])


def _points_and_normals(o, d, q, z):
    """Points (H, W, 3) on the view rays at heights z and their unit bisector normals."""
    points = np.empty(d.shape)
    normals = np.empty(d.shape)
    _points_normals(o, d, q, z, points, normals)
    return points, normals
