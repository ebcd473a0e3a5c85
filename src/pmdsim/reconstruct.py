"""Surface reconstruction from a deflectometric registration (paper §2.5).

Everything here works in one *reconstruction frame* (for example the sample frame) whose +z is
the height direction. The inputs are

* ``o`` (3,): the camera's projection centre (the pinhole), mm;
* ``d`` (H, W, 3): the view-ray direction of every pixel (any length, not necessarily unit);
  the surface point seen by pixel (v, u) is p = o + t·d[v, u] with an unknown t > 0, its height
  is z = p_z;
* ``q`` (H, W, 3): the deflectometric registration — the point on the pattern screen whose light
  reaches pixel (v, u) via the surface, mm. It does not depend on the surface;
* ``valid`` (H, W) bool: usable pixels.

The surface normal at p bisects the direction to the camera and the direction to the screen
point (law of reflection, paper §2.5),

    n ∝ (o − p)/|o − p| + (q − p)/|q − p|,

and the slopes follow as g = (∂z/∂x, ∂z/∂y) = (−n_x/n_z, −n_y/n_z). Between two 4-neighbouring
pixels a and b the height difference is integrated with the trapezoidal rule

    z_b − z_a = ½ (g_a + g_b) · (xy_b − xy_a),                                   (*)

which is exact for height functions of degree ≤ 2 (planes, paraboloids), whose slopes are
linear in x and y. Note that xy_b depends on z_b (the point slides along its view ray) and g_b
depends on the point.

Two integrators are provided:

* :func:`reconstruct_stepwise` — the paper's stepwise integration: breadth-first expansion
  from an initial point, each new pixel solved from (*) with a predictor–corrector iteration;
* :func:`reconstruct_least_squares` — zonal (Southwell-type) least-squares integration of (*)
  over all valid neighbour pairs of the seed's component (Gauss–Newton iterations, each a
  sparse solve by multigrid-preconditioned conjugate gradients).

Neither assumes on which side of the surface the camera is (o_z may be above or below).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage

from .errors import PmdsimError

__all__ = [
    "ReconstructionError",
    "Reconstruction",
    "normals_from_registration",
    "reconstruct_stepwise",
    "reconstruct_least_squares",
    "reconstruct",
    "STEP_TOL_MM",
    "STEP_MAX_ITER",
]

#: Convergence tolerance of the corrector iteration of one integration step (|Δz|), in mm.
STEP_TOL_MM = 1e-12
#: Maximum number of corrector iterations of one integration step.
STEP_MAX_ITER = 50

# Neighbour offsets in the order in which the stepwise integration visits them.
_NB_DV = np.array([-1, 1, 0, 0], dtype=np.int64)
_NB_DU = np.array([0, 0, -1, 1], dtype=np.int64)

_METHODS = ("stepwise", "least_squares")


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
    points : ndarray, shape (H, W, 3)
        Reconstructed surface points p = o + t·d, mm; NaN where not reconstructed.
    normals : ndarray, shape (H, W, 3)
        Unit surface normals at ``points`` (bisector of the directions to the camera and to the
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
        ``"least_squares"``: the last iteration changed no height by ``tol_mm`` or more.
        ``"stepwise"``: every step's corrector met |Δz| < :data:`STEP_TOL_MM`.
    seed_pixel : tuple of int
        (row, column) of the initial point whose height was given.
    final_change_mm : float
        The largest height change of the last iteration (outer iteration for
        ``"least_squares"``, last corrector update of any step for ``"stepwise"``), mm.
    """

    height_mm: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    reconstructed: np.ndarray
    method: str
    iterations: int
    converged: bool
    seed_pixel: tuple[int, int]
    final_change_mm: float = 0.0


# --------------------------------------------------------------------------------------------
# Normals
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


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
    bad = valid_arr & ~np.all(np.isfinite(d), axis=-1)
    if bad.any():
        v, u = np.argwhere(bad)[0]
        raise ReconstructionError(
            f"d has non-finite directions at {int(bad.sum())} valid pixels (first at row {v}, column {u}); "
            "mark them invalid in valid")
    bad = valid_arr & (d[..., 2] == 0.0)
    if bad.any():
        v, u = np.argwhere(bad)[0]
        raise ReconstructionError(
            f"d has {int(bad.sum())} valid view rays with d_z == 0 (first at row {v}, column {u}): such a ray "
            "runs parallel to the x–y plane, perpendicular to the height axis, and its height cannot "
            "be solved for; mark these pixels invalid in valid or choose a frame whose +z is not "
            "perpendicular to them")
    bad = valid_arr & ~np.all(np.isfinite(q), axis=-1)
    if bad.any():
        v, u = np.argwhere(bad)[0]
        raise ReconstructionError(
            f"q has non-finite screen points at {int(bad.sum())} valid pixels (first at row {v}, column {u}); "
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


# --------------------------------------------------------------------------------------------
# Stepwise integration (numba)
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
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


@numba.njit(cache=True, inline="always")
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


@numba.njit(cache=True, error_model="numpy")
def _stepwise_kernel(o, d, q, state, sv, su, z0, tol, max_iter, nb_dv, nb_du):
    """Layered (wavefront) stepwise integration.

    ``state`` (H, W, 4) holds per pixel [t, g_x, g_y, flag] with flag −1 = not valid,
    0 = valid and not yet reached, 2 = in the wavefront being solved, 1 = reconstructed
    (t: ray parameter of the point, g: slopes there). The wavefront k + 1 is every valid,
    unreached 4-neighbour of wavefront k; each of its pixels is solved from *all* its
    reconstructed 4-neighbours at once (the pixels of one wavefront are never 4-adjacent, as
    the pixel grid is bipartite, so the order within a wavefront does not matter). Returns
    (largest corrector count, largest final |Δz|, number of pixels that missed ``tol``); the
    count is −1 if the seed's normal is unusable."""
    H = state.shape[0]
    W = state.shape[1]
    ox = o[0]
    oy = o[1]
    oz = o[2]
    cur = np.empty(H * W, dtype=np.int64)
    nxt = np.empty(H * W, dtype=np.int64)
    nbr_t = np.empty(4)
    nbr_gx = np.empty(4)
    nbr_gy = np.empty(4)
    nbr_v = np.empty(4, dtype=np.int64)
    nbr_u = np.empty(4, dtype=np.int64)
    # Seed.
    t = (z0 - oz) / d[sv, su, 2]
    px = ox + t * d[sv, su, 0]
    py = oy + t * d[sv, su, 1]
    gx, gy = _bisector_slopes(px, py, z0, ox, oy, oz, q[sv, su, 0], q[sv, su, 1], q[sv, su, 2])
    if not (np.isfinite(gx) and np.isfinite(gy)):
        return -1, 0.0, 0
    state[sv, su, 0] = t
    state[sv, su, 1] = gx
    state[sv, su, 2] = gy
    state[sv, su, 3] = 1.0
    cur[0] = sv * W + su
    n_cur = 1
    max_used = 0
    max_change = 0.0
    n_unconverged = 0
    while n_cur > 0:
        # The next wavefront: valid, unreached neighbours of the current one.
        n_nxt = 0
        for i in range(n_cur):
            idx = cur[i]
            va = idx // W
            ua = idx - va * W
            for k in range(4):
                vb = va + nb_dv[k]
                ub = ua + nb_du[k]
                if vb < 0 or vb >= H or ub < 0 or ub >= W:
                    continue
                if state[vb, ub, 3] != 0.0:
                    continue
                state[vb, ub, 3] = 2.0
                nxt[n_nxt] = vb * W + ub
                n_nxt += 1
        # Solve each pixel b of the wavefront from all its reconstructed neighbours a_i:
        # Σ_i [z_b − z_ai − G_i·(xy_b − xy_ai)] = 0, G_i = ½(g_ai + g_b) (trapezoidal rule),
        # linear in t_b for fixed G_i; predictor G_i = g_ai, then correctors.
        n_solved = 0
        for i in range(n_nxt):
            idx = nxt[i]
            vb = idx // W
            ub = idx - vb * W
            m = 0
            for k in range(4):
                va = vb + nb_dv[k]
                ua = ub + nb_du[k]
                if va < 0 or va >= H or ua < 0 or ua >= W:
                    continue
                if state[va, ua, 3] != 1.0:
                    continue
                nbr_v[m] = va
                nbr_u[m] = ua
                nbr_t[m] = state[va, ua, 0]
                nbr_gx[m] = state[va, ua, 1]
                nbr_gy[m] = state[va, ua, 2]
                m += 1
            dx = d[vb, ub, 0]
            dy = d[vb, ub, 1]
            dz = d[vb, ub, 2]
            qx = q[vb, ub, 0]
            qy = q[vb, ub, 1]
            qz = q[vb, ub, 2]
            ok = False
            z_prev = 0.0
            change = np.inf
            used = 0
            tb = 0.0
            gbx = 0.0
            gby = 0.0
            have_gb = False
            for it in range(max_iter + 1):
                num = 0.0
                den = 0.0
                for j in range(m):
                    Gx = nbr_gx[j] if not have_gb else 0.5 * (nbr_gx[j] + gbx)
                    Gy = nbr_gy[j] if not have_gb else 0.5 * (nbr_gy[j] + gby)
                    ta = nbr_t[j]
                    rax = ta * d[nbr_v[j], nbr_u[j], 0]
                    ray = ta * d[nbr_v[j], nbr_u[j], 1]
                    raz = ta * d[nbr_v[j], nbr_u[j], 2]
                    # (t_b d_z − r_a,z) − G·(t_b d_xy − r_a,xy) = 0 summed over the neighbours.
                    num += raz - (Gx * rax + Gy * ray)
                    den += dz - (Gx * dx + Gy * dy)
                tb = num / den
                if not (tb > 0.0) or not np.isfinite(tb):
                    ok = False
                    break
                bz = oz + tb * dz
                gbx, gby = _bisector_slopes(ox + tb * dx, oy + tb * dy, bz, ox, oy, oz, qx, qy, qz)
                if not (np.isfinite(gbx) and np.isfinite(gby)):
                    ok = False
                    break
                ok = True
                have_gb = True
                if it > 0:
                    change = abs(bz - z_prev)
                    used = it
                    if change < tol:
                        break
                z_prev = bz
            if not ok:
                state[vb, ub, 3] = 0.0  # may be reached again from a later wavefront
                continue
            if change >= tol:
                n_unconverged += 1
            if used > max_used:
                max_used = used
            if change > max_change:
                max_change = change
            state[vb, ub, 0] = tb
            state[vb, ub, 1] = gbx
            state[vb, ub, 2] = gby
            cur[n_solved] = idx  # reuse cur as the list of solved pixels of this wavefront
            n_solved += 1
        for i in range(n_solved):
            idx = cur[i]
            vb = idx // W
            ub = idx - vb * W
            state[vb, ub, 3] = 1.0
        n_cur = n_solved
    return max_used, max_change, n_unconverged


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _points_normals(o, d, q, z, points, normals):
    """Points on the view rays at heights z (NaN stays NaN) and their bisector normals."""
    H, W = z.shape
    ox = o[0]
    oy = o[1]
    oz = o[2]
    for v in numba.prange(H):
        for u in range(W):
            zz = z[v, u]
            if np.isnan(zz):
                for c in range(3):
                    points[v, u, c] = np.nan
                    normals[v, u, c] = np.nan
                continue
            t = (zz - oz) / d[v, u, 2]
            px = ox + t * d[v, u, 0]
            py = oy + t * d[v, u, 1]
            points[v, u, 0] = px
            points[v, u, 1] = py
            points[v, u, 2] = zz
            nx, ny, nz = _bisector(px, py, zz, ox, oy, oz, q[v, u, 0], q[v, u, 1], q[v, u, 2])
            normals[v, u, 0] = nx
            normals[v, u, 1] = ny
            normals[v, u, 2] = nz


def _points_and_normals(o, d, q, z):
    """Points (H, W, 3) on the view rays at heights z and their unit bisector normals."""
    points = np.empty(d.shape)
    normals = np.empty(d.shape)
    _points_normals(o, d, q, z, points, normals)
    return points, normals


def _run_stepwise(o, d, q, valid, seed, z0, tol=STEP_TOL_MM):
    """Heights (H, W) (NaN where not reached) and the kernel's statistics."""
    H, W = valid.shape
    state = np.full((H, W, 4), np.nan)
    state[..., 3] = np.where(valid, 0.0, -1.0)
    max_used, max_change, n_unconv = _stepwise_kernel(
        o, d, q, state, seed[0], seed[1], z0, tol, STEP_MAX_ITER, _NB_DV, _NB_DU)
    if max_used < 0:
        raise ReconstructionError(
            f"the normal at seed_pixel {seed} is undefined or perpendicular to the height axis "
            f"(camera centre, seed point and q[{seed[0]}, {seed[1]}] = {q[seed].tolist()} are degenerate); "
            "choose another seed_pixel or check q")
    done = state[..., 3] == 1.0
    z = np.where(done, o[2] + state[..., 0] * d[..., 2], np.nan)
    z[seed] = z0
    return z, done, max_used, max_change, n_unconv


def reconstruct_stepwise(o, d, q, valid, seed_pixel=None, seed_height_mm=0.0) -> Reconstruction:
    """Stepwise integration of the surface from an initial point (paper §2.5).

    Starting from the seed pixel, whose height is given, the reconstruction expands over valid
    4-connected neighbours, driven by the normals at the border of the current reconstruction.

    **Expansion order.** In wavefronts from the seed: wavefront k + 1 is every valid,
    not yet reconstructed 4-neighbour of wavefront k (so wavefront k holds the pixels at
    4-connected distance k from the seed). Each pixel of a wavefront is solved from *all* its
    reconstructed 4-neighbours together (one or two for a full grid: those of the previous
    wavefront), so the result does not depend on the order in which neighbours are visited,
    and where the measured slope field is not exactly a gradient (a wrong screen model, noise)
    the errors of the different paths are averaged instead of following one arbitrary path.
    A pixel whose step fails (see below) stays unreconstructed in its wavefront and may be
    reached again from a later one.

    **One step.** The height of b solves the trapezoidal rule for its reconstructed
    neighbours a_i, summed:

        Σ_i [ z_b − z_ai − ½ (g_ai + g_b) · (xy_b − xy_ai) ] = 0

    with p_b = o + t_b·d_b on b's view ray and g = (−n_x/n_z, −n_y/n_z) the slopes of the
    bisector normal (see :func:`normals_from_registration`). For fixed mean slopes G_i the
    equation is linear in t_b (for one neighbour: p_b is the intersection of b's ray with the
    plane through p_a of slope G). The predictor uses G_i = g_ai; each corrector recomputes g_b
    at the new p_b and uses G_i = ½(g_ai + g_b), until the height changes by less than
    :data:`STEP_TOL_MM` (at most :data:`STEP_MAX_ITER` correctors; the last iterate is kept
    either way). The rule is exact for height functions of degree ≤ 2 (planes, paraboloids).
    A step that fails (the ray misses the plane in front of the camera, or the normal is
    undefined or perpendicular to z) is skipped and b may be reached from a later wavefront.

    Parameters
    ----------
    o : array_like, shape (3,)
        Camera projection centre in the reconstruction frame, mm.
    d : array_like, shape (H, W, 3)
        View-ray direction per pixel (any non-zero length), reconstruction frame.
        Valid pixels need d_z ≠ 0.
    q : array_like, shape (H, W, 3)
        Screen point per pixel from the deflectometric registration, reconstruction frame, mm.
    valid : array_like of bool, shape (H, W)
        Pixels that may be reconstructed.
    seed_pixel : tuple of int, optional
        (row, column) of the initial point. Default: the valid pixel nearest (Euclidean, in
        pixels) to the centroid of ``valid``; ties go to the first in row-major order.
    seed_height_mm : float
        Height z of the initial point, mm (the integration constant).

    Returns
    -------
    Reconstruction
        Pixels not 4-connected to the seed through valid pixels stay NaN / not reconstructed.

    Raises
    ------
    ReconstructionError
        Shape mismatches, no valid pixels, a seed pixel out of range or invalid, a seed height
        behind the camera, or valid rays with d_z = 0.
    """
    o, d, q, valid = _check_inputs(o, d, q, valid)
    seed, z0 = _check_seed(seed_pixel, seed_height_mm, o, d, valid)
    z, done, max_used, max_change, n_unconv = _run_stepwise(o, d, q, valid, seed, z0)
    points, normals = _points_and_normals(o, d, q, z)
    return Reconstruction(
        height_mm=z,
        points=points,
        normals=normals,
        reconstructed=done,
        method="stepwise",
        iterations=int(max_used),
        converged=bool(n_unconv == 0),
        seed_pixel=seed,
        final_change_mm=float(max_change),
    )


# --------------------------------------------------------------------------------------------
# Least squares: 5-point operators on the pixel grid, aggregation multigrid, PCG (numba)
# --------------------------------------------------------------------------------------------
#
# A symmetric positive definite operator N with 4-neighbour couplings is stored on the pixel
# grid, padded by one zero pixel on every side (shape (H + 2, W + 2)), as
#   D  : the diagonal; D == 0 marks a pixel that is not an unknown (inactive),
#   iD : 1/D on active pixels, 0 on inactive ones,
#   Ex : (N x)[v,u] contains −Ex[v,u]·x[v,u+1], and (N x)[v,u+1] contains −Ex[v,u]·x[v,u],
#   Ey : the same for the pixel below, (v+1, u).
# Couplings that touch an inactive pixel are 0 and vectors are 0 on inactive pixels, so the
# kernels need no branches. Coarse levels aggregate 2×2 pixels; with piecewise-constant
# interpolation the Galerkin operator Pᵀ N P is again such a 5-point operator.

#: Over-correction factor of the multigrid coarse-grid correction (plain aggregation
#: underestimates smooth corrections by about a factor of two).
_MG_OVERCORRECTION = 1.5
#: Relative tolerance (max-norm of the preconditioned residual) of one inner solve.
_INNER_RTOL = 1e-4
_INNER_MAX_ITER = 200


@numba.njit(cache=True)
def _matvec_dot(D, Ex, Ey, x, out):
    """out = N x; returns x·out."""
    Hp, Wp = D.shape
    s = 0.0
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            y = (D[v, u] * x[v, u] - Ex[v, u - 1] * x[v, u - 1] - Ex[v, u] * x[v, u + 1]
                 - Ey[v - 1, u] * x[v - 1, u] - Ey[v, u] * x[v + 1, u])
            out[v, u] = y
            s += x[v, u] * y
    return s


@numba.njit(cache=True)
def _residual(D, Ex, Ey, r, x, out):
    """out = r − N x."""
    Hp, Wp = D.shape
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            out[v, u] = (r[v, u] - D[v, u] * x[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * x[v, u + 1]
                         + Ey[v - 1, u] * x[v - 1, u] + Ey[v, u] * x[v + 1, u])


@numba.njit(cache=True)
def _presmooth_restrict(iD, Ex, Ey, r, x, rc):
    """One forward (lexicographic) Gauss–Seidel sweep for N x = r from x = 0, then the residual
    r − N x summed over 2×2 aggregates into rc (padded coarse grid).

    After a forward sweep from zero the residual at a pixel is Ex·x(right) + Ey·x(below)
    (the equation was satisfied with the right and lower neighbours still 0); it is
    accumulated one row behind the sweep."""
    Hp, Wp = iD.shape
    rc[:, :] = 0.0
    for v in range(1, Hp - 1):
        xl = 0.0
        for u in range(1, Wp - 1):
            xl = (r[v, u] + Ex[v, u - 1] * xl + Ey[v - 1, u] * x[v - 1, u]) * iD[v, u]
            x[v, u] = xl
        x[v, Wp - 1] = 0.0
        if v > 1:
            w = v - 1
            V = ((w - 1) >> 1) + 1
            for u in range(1, Wp - 1):
                rc[V, ((u - 1) >> 1) + 1] += Ex[w, u] * x[w, u + 1] + Ey[w, u] * x[v, u]
    w = Hp - 2
    V = ((w - 1) >> 1) + 1
    for u in range(1, Wp - 1):
        rc[V, ((u - 1) >> 1) + 1] += Ex[w, u] * x[w, u + 1]


@numba.njit(cache=True)
def _prolong_postsmooth(iD, Ex, Ey, r, x, xc, alpha):
    """x += alpha·P xc (piecewise-constant interpolation from 2×2 aggregates), then one
    backward Gauss–Seidel sweep for N x = r. The interpolation of row v − 1 is added just
    before row v is swept. Inactive pixels receive the interpolation too (no branch), but
    their couplings are 0 and the sweep resets them to 0 (iD = 0)."""
    Hp, Wp = iD.shape

    def _add_row(w):
        V = ((w - 1) >> 1) + 1
        for u in range(1, Wp - 1):
            x[w, u] += alpha * xc[V, ((u - 1) >> 1) + 1]

    _add_row(Hp - 2)
    for v in range(Hp - 2, 0, -1):
        if v > 1:
            _add_row(v - 1)
        xr = x[v, Wp - 1]
        for u in range(Wp - 2, 0, -1):
            xr = (r[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * xr
                  + Ey[v - 1, u] * x[v - 1, u] + Ey[v, u] * x[v + 1, u]) * iD[v, u]
            x[v, u] = xr


@numba.njit(cache=True)
def _coarsen(D, Ex, Ey):
    """Galerkin coarse operator Pᵀ N P for 2×2 aggregation (padded arrays in and out)."""
    Hp, Wp = D.shape
    H = Hp - 2
    W = Wp - 2
    Hc = (H + 1) // 2
    Wc = (W + 1) // 2
    Dc = np.zeros((Hc + 2, Wc + 2))
    Exc = np.zeros((Hc + 2, Wc + 2))
    Eyc = np.zeros((Hc + 2, Wc + 2))
    for v in range(1, Hp - 1):
        V = ((v - 1) >> 1) + 1
        v_internal = ((v - 1) & 1) == 0  # the edge to v + 1 stays inside the aggregate
        for u in range(1, Wp - 1):
            if D[v, u] == 0.0:
                continue
            U = ((u - 1) >> 1) + 1
            Dc[V, U] += D[v, u]
            e = Ex[v, u]
            if ((u - 1) & 1) == 0:
                Dc[V, U] -= 2.0 * e  # both off-diagonal entries fall on the aggregate's diagonal
            else:
                Exc[V, U] += e
            e = Ey[v, u]
            if v_internal:
                Dc[V, U] -= 2.0 * e
            else:
                Eyc[V, U] += e
    iDc = np.zeros((Hc + 2, Wc + 2))
    for V in range(1, Hc + 1):
        for U in range(1, Wc + 1):
            if Dc[V, U] > 0.0:
                iDc[V, U] = 1.0 / Dc[V, U]
            else:  # no active pixel (or round-off): not an unknown
                Dc[V, U] = 0.0
                Exc[V, U] = 0.0
                Eyc[V, U] = 0.0
                Exc[V, U - 1] = 0.0
                Eyc[V - 1, U] = 0.0
    return Dc, iDc, Exc, Eyc


@numba.njit(cache=True)
def _cg_update(x, r, p, Ap, alpha):
    """x += αp, r −= αAp."""
    Hp, Wp = x.shape
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            x[v, u] += alpha * p[v, u]
            r[v, u] -= alpha * Ap[v, u]


@numba.njit(cache=True)
def _dot_maxabs(a, b):
    """Returns (a·b, max|b|)."""
    Hp, Wp = a.shape
    s = 0.0
    m = 0.0
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            s += a[v, u] * b[v, u]
            m = max(m, abs(b[v, u]))
    return s, m


@numba.njit(cache=True)
def _cg_direction(p, z, beta):
    """p = z + βp."""
    Hp, Wp = p.shape
    for v in range(1, Hp - 1):
        for u in range(1, Wp - 1):
            p[v, u] = z[v, u] + beta * p[v, u]


#: The multigrid hierarchy stops coarsening once a level has at most this many cells; that
#: level is solved exactly (dense Cholesky factorisation).
_MG_COARSEST_CELLS = 256


@numba.njit(cache=True)
def _cholesky_inplace(A):
    """Lower Cholesky factor of the SPD matrix A, in place. Returns False if a pivot is not
    positive (A not numerically positive definite)."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        ljj = np.sqrt(s)
        A[j, j] = ljj
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / ljj
    return True


@numba.njit(cache=True)
def _cholesky_solve(L, index, r, x):
    """x[index] = (L Lᵀ)⁻¹ r[index] on flattened padded grids; x is 0 elsewhere."""
    n = L.shape[0]
    rf = r.ravel()
    xf = x.ravel()
    xf[:] = 0.0
    y = np.empty(n)
    for i in range(n):
        s = rf[index[i]]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * y[k]
        y[i] = s / L[i, i]
    for i in range(n):
        xf[index[i]] = y[i]


class _Multigrid:
    """Aggregation multigrid preconditioner for a padded 5-point SPD operator (see above).

    Levels aggregate 2×2 pixels, with Galerkin coarse operators, so any mask works; the
    coarsest level (≤ ``_MG_COARSEST_CELLS`` cells) is solved exactly. One application is a
    W-cycle: forward Gauss–Seidel before and backward Gauss–Seidel after the coarse-grid
    correction (a symmetric pair), the correction being two coarse cycles scaled by ``alpha``
    (over-correction; plain aggregation underestimates smooth corrections)."""

    def __init__(self, D, iD, Ex, Ey, alpha):
        self.alpha = float(alpha)
        self.levels = [(D, iD, Ex, Ey)]
        while (D.shape[0] - 2) * (D.shape[1] - 2) > _MG_COARSEST_CELLS:
            D, iD, Ex, Ey = _coarsen(D, Ex, Ey)
            self.levels.append((D, iD, Ex, Ey))
        shapes = [lv[0].shape for lv in self.levels]
        self.x = [np.zeros(s) for s in shapes]
        coarse = [None] + [np.zeros(s) for s in shapes[1:]]
        self.rc = coarse                                      # restricted residual (level input)
        self.r2 = [None] + [np.zeros(s) for s in shapes[1:]]  # residual for the second cycle
        self.acc = [None] + [np.zeros(s) for s in shapes[1:]]  # sum of the two coarse cycles
        self._factor_coarsest()

    def _factor_coarsest(self):
        D, _, Ex, Ey = self.levels[-1]
        Wp = D.shape[1]
        flat = np.flatnonzero(D.ravel() > 0.0)
        self.coarse_index = flat
        n = flat.size
        if n == 0:
            self.coarse_factor = None
            return
        pos = np.full(D.size, -1, dtype=np.int64)
        pos[flat] = np.arange(n)
        A = np.zeros((n, n))
        A[np.arange(n), np.arange(n)] = D.ravel()[flat]
        for E, step in ((Ex.ravel(), 1), (Ey.ravel(), Wp)):
            src = np.flatnonzero(E != 0.0)
            i = pos[src]
            j = pos[src + step]
            keep = (i >= 0) & (j >= 0)
            A[i[keep], j[keep]] = -E[src[keep]]
            A[j[keep], i[keep]] = -E[src[keep]]
        L = A.copy()
        if _cholesky_inplace(L):
            self.coarse_factor = ("chol", L)
        else:  # numerically semi-definite: pseudo-inverse
            self.coarse_factor = ("pinv", np.linalg.pinv(A, hermitian=True))

    def _solve_coarsest(self, r, x):
        if self.coarse_factor is None:
            x[:] = 0.0
            return x
        kind, f = self.coarse_factor
        if kind == "chol":
            _cholesky_solve(f, self.coarse_index, r, x)
        else:
            x[:] = 0.0
            x.ravel()[self.coarse_index] = f @ r.ravel()[self.coarse_index]
        return x

    def _cycle(self, lvl, r):
        D, iD, Ex, Ey = self.levels[lvl]
        x = self.x[lvl]
        if lvl == len(self.levels) - 1:
            return self._solve_coarsest(r, x)
        nxt = lvl + 1
        _presmooth_restrict(iD, Ex, Ey, r, x, self.rc[nxt])
        e = self._cycle(nxt, self.rc[nxt])
        acc = self.acc[nxt]
        acc[:] = e
        Dn, _, Exn, Eyn = self.levels[nxt]
        _residual(Dn, Exn, Eyn, self.rc[nxt], acc, self.r2[nxt])
        e = self._cycle(nxt, self.r2[nxt])
        acc += e
        _prolong_postsmooth(iD, Ex, Ey, r, x, acc, self.alpha)
        return x

    def apply(self, r, out):
        if len(self.levels) == 1:
            self._solve_coarsest(r, out)
            return
        out[:] = self._cycle(0, r)


def _pcg(D, iD, Ex, Ey, b, atol, rtol, max_iter):
    """Conjugate gradients for N x = b, preconditioned by :class:`_Multigrid`.

    Stops when the max-norm of the preconditioned residual (an estimate of the error of x) is
    below ``max(atol, rtol · its initial value)``; that last preconditioned residual is added
    to x. The over-corrected W-cycle is not guaranteed to be positive definite; should CG
    break down or not converge in ``max_iter`` steps with it, the solve is repeated with the
    plain W-cycle (alpha = 1), which is a symmetric positive definite preconditioner.
    Returns (x, total CG iterations, converged)."""
    total = 0
    x = np.zeros_like(b)
    r = np.empty_like(b)
    z = np.zeros_like(b)
    p = np.empty_like(b)
    Ap = np.zeros_like(b)
    for alpha in (_MG_OVERCORRECTION, 1.0):
        mg = _Multigrid(D, iD, Ex, Ey, alpha)
        x[:] = 0.0
        r[:] = b
        mg.apply(r, z)
        rz, zmax = _dot_maxabs(r, z)
        if zmax <= atol:
            x += z  # the solution is below the tolerance anyway
            return x, total, True
        tol = max(atol, rtol * zmax)
        p[:] = z
        for k in range(1, max_iter + 1):
            total += 1
            pAp = _matvec_dot(D, Ex, Ey, p, Ap)
            if not (pAp > 0.0 and rz > 0.0):
                break  # breakdown: the preconditioner is not positive definite here
            a = rz / pAp
            _cg_update(x, r, p, Ap, a)
            mg.apply(r, z)
            rz_new, zmax = _dot_maxabs(r, z)
            if not np.isfinite(rz_new):
                break
            if zmax <= tol:
                x += z
                return x, total, True
            _cg_direction(p, z, rz_new / rz)
            rz = rz_new
    return x, total, False


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _pixel_geometry(o, d, q, S, z, xy, g, dg):
    """Per pixel of S at height z: the point's x, y, the slopes g of the bisector normal and
    their derivative dg/dz along the view ray."""
    H, W = S.shape
    ox = o[0]
    oy = o[1]
    oz = o[2]
    for v in numba.prange(H):
        for u in range(W):
            if not S[v, u]:
                continue
            ex = d[v, u, 0] / d[v, u, 2]  # dp/dz = (ex, ey, 1)
            ey = d[v, u, 1] / d[v, u, 2]
            w = z[v, u] - oz
            px = ox + w * ex
            py = oy + w * ey
            pz = z[v, u]
            ax = ox - px
            ay = oy - py
            az = oz - pz
            la = np.sqrt(ax * ax + ay * ay + az * az)
            ax /= la
            ay /= la
            az /= la
            bx = q[v, u, 0] - px
            by = q[v, u, 1] - py
            bz = q[v, u, 2] - pz
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            bx /= lb
            by /= lb
            bz /= lb
            mx = ax + bx
            my = ay + by
            mz = az + bz
            # d(â)/dz = −(e − (â·e) â)/|a|, the same for b̂.
            ae = ax * ex + ay * ey + az
            be = bx * ex + by * ey + bz
            dmx = -(ex - ae * ax) / la - (ex - be * bx) / lb
            dmy = -(ey - ae * ay) / la - (ey - be * by) / lb
            dmz = -(1.0 - ae * az) / la - (1.0 - be * bz) / lb
            xy[v, u, 0] = px
            xy[v, u, 1] = py
            g[v, u, 0] = -mx / mz
            g[v, u, 1] = -my / mz
            dg[v, u, 0] = -(dmx * mz - mx * dmz) / (mz * mz)
            dg[v, u, 1] = -(dmy * mz - my * dmz) / (mz * mz)


@numba.njit(cache=True, error_model="numpy")
def _edge(z, d, xy, g, dg, v, u, vb, ub):
    """Residual of the trapezoidal equation of the edge a = (v, u) → b = (vb, ub) and its
    derivatives with respect to z_a and z_b (xy moves along the rays, dxy/dz = d_xy/d_z; the
    slopes change by dg/dz)."""
    Gx = 0.5 * (g[v, u, 0] + g[vb, ub, 0])
    Gy = 0.5 * (g[v, u, 1] + g[vb, ub, 1])
    dx = xy[vb, ub, 0] - xy[v, u, 0]
    dy = xy[vb, ub, 1] - xy[v, u, 1]
    res = z[vb, ub] - z[v, u] - (Gx * dx + Gy * dy)
    ka = (Gx * d[v, u, 0] + Gy * d[v, u, 1]) / d[v, u, 2]
    kb = (Gx * d[vb, ub, 0] + Gy * d[vb, ub, 1]) / d[vb, ub, 2]
    Ja = -1.0 + ka - 0.5 * (dg[v, u, 0] * dx + dg[v, u, 1] * dy)
    Jb = 1.0 - kb - 0.5 * (dg[vb, ub, 0] * dx + dg[vb, ub, 1] * dy)
    ok = np.isfinite(res) and np.isfinite(Ja) and np.isfinite(Jb)
    return ok, res, Ja, Jb


@numba.njit(cache=True, error_model="numpy")
def _gauss_newton_system(S, z, d, xy, g, dg, sv, su, D, iD, Ex, Ey, rhs, rowsum):
    """Gauss–Newton normal equations Jᵀ J δ = −Jᵀ res of the trapezoidal equations
    res = z_b − z_a − ½(g_a + g_b)·(xy_b − xy_a) of all 4-neighbour pairs in S, written to the
    padded 5-point arrays. The seed (sv, su) is not an unknown (gauge). rowsum[v] receives the
    sum of res² of the edges owned by row v (right and lower edges). Edges whose residual is
    not finite are dropped (evaluated identically from both ends)."""
    H, W = S.shape
    for v in range(H):
        acc = 0.0
        for u in range(W):
            dd = 0.0
            rr = 0.0
            exo = 0.0
            eyo = 0.0
            if S[v, u] and not (v == sv and u == su):
                if u + 1 < W and S[v, u + 1]:  # right
                    ok, res, Ja, Jb = _edge(z, d, xy, g, dg, v, u, v, u + 1)
                    if ok:
                        dd += Ja * Ja
                        rr -= Ja * res
                        acc += res * res
                        if not (v == sv and u + 1 == su):
                            exo = -Ja * Jb
                if v + 1 < H and S[v + 1, u]:  # below
                    ok, res, Ja, Jb = _edge(z, d, xy, g, dg, v, u, v + 1, u)
                    if ok:
                        dd += Ja * Ja
                        rr -= Ja * res
                        acc += res * res
                        if not (v + 1 == sv and u == su):
                            eyo = -Ja * Jb
                if u > 0 and S[v, u - 1]:  # left: this pixel is b
                    ok, res, Ja, Jb = _edge(z, d, xy, g, dg, v, u - 1, v, u)
                    if ok:
                        dd += Jb * Jb
                        rr -= Jb * res
                if v > 0 and S[v - 1, u]:  # above: this pixel is b
                    ok, res, Ja, Jb = _edge(z, d, xy, g, dg, v - 1, u, v, u)
                    if ok:
                        dd += Jb * Jb
                        rr -= Jb * res
            elif v == sv and u == su:
                # The seed is no unknown, but its edges' residuals count.
                if u + 1 < W and S[v, u + 1]:
                    ok, res, Ja, Jb = _edge(z, d, xy, g, dg, v, u, v, u + 1)
                    if ok:
                        acc += res * res
                if v + 1 < H and S[v + 1, u]:
                    ok, res, Ja, Jb = _edge(z, d, xy, g, dg, v, u, v + 1, u)
                    if ok:
                        acc += res * res
            D[v + 1, u + 1] = dd
            iD[v + 1, u + 1] = 1.0 / dd if dd > 0.0 else 0.0
            rhs[v + 1, u + 1] = rr if dd > 0.0 else 0.0
            Ex[v + 1, u + 1] = exo
            Ey[v + 1, u + 1] = eyo
        rowsum[v] = acc


def reconstruct_least_squares(o, d, q, valid, seed_pixel=None, seed_height_mm=0.0, max_iter=20,
                              tol_mm=1e-9) -> Reconstruction:
    """Zonal least-squares integration of the deflectometric slopes (paper §2.5).

    The unknowns are the heights z of all valid pixels that are 4-connected to the seed pixel
    through valid pixels (the seed's component). Every pair of such 4-neighbours a, b (a left
    of or above b) contributes one equation of the Southwell type,

        z_b − z_a = ½ (g_a + g_b) · (xy_b − xy_a),

    with xy of a pixel the x–y position of its point p = o + t·d, t = (z − o_z)/d_z, and g the
    slopes of the bisector normal at p (:func:`normals_from_registration`). All equations have
    weight 1, and the result minimises the sum of their squared residuals over the heights.
    Because the points, and with them the slopes, depend on the heights, the problem is
    nonlinear and is solved by Gauss–Newton iteration:

    1. points from the current heights (along the fixed view rays), then normals and slopes
       at the points;
    2. linearise every residual in the two heights it involves — the movement of xy along the
       rays and the change of the slopes with the height (both exact derivatives) — and solve
       the sparse normal equations Jᵀ J δ = −Jᵀ res for the update δ (a 5-point operator on
       the pixel grid, like a graph Laplacian);
    3. z ← z + δ; repeat until max |δ| < ``tol_mm``.

    Each residual involves two heights only, so including the slope derivative costs nothing
    and gives fast convergence: the slopes' dependence on the heights couples all pixels
    weakly but coherently (a tilt of the whole surface changes all normals), and freezing it
    would make the iteration converge only linearly. The iteration starts from the stepwise
    solution (:func:`reconstruct_stepwise`), which already satisfies the equations exactly
    for consistent data (one iteration then suffices); with noisy data 2–4 iterations are
    typical.

    **Gauge.** The seed pixel's height is fixed at ``seed_height_mm`` exactly (it is removed
    from the unknowns). **Components.** Valid pixels not 4-connected to the seed are not tied
    to the gauge and are left NaN (as in the stepwise integration). **Solver.** Conjugate
    gradients preconditioned by an aggregation multigrid W-cycle (2×2 aggregates with
    Galerkin coarse operators, symmetric Gauss–Seidel smoothing, over-corrected coarse-grid
    correction, dense Cholesky on the coarsest level), which copes with arbitrary masks; each
    update is solved to a relative accuracy of about 1e-4 or an absolute one of
    ``tol_mm``/100, whichever is reached first (inexact Gauss–Newton: the next iteration
    corrects the rest).

    Parameters
    ----------
    o : array_like, shape (3,)
        Camera projection centre in the reconstruction frame, mm.
    d : array_like, shape (H, W, 3)
        View-ray direction per pixel (any non-zero length); valid pixels need d_z ≠ 0.
    q : array_like, shape (H, W, 3)
        Screen point per pixel from the deflectometric registration, mm.
    valid : array_like of bool, shape (H, W)
        Pixels that may be reconstructed.
    seed_pixel : tuple of int, optional
        (row, column) of the pixel whose height is given. Default: the valid pixel nearest to
        the centroid of ``valid`` (ties: first in row-major order).
    seed_height_mm : float
        Height of the seed pixel, mm.
    max_iter : int
        Maximum number of outer iterations (≥ 1).
    tol_mm : float
        Convergence tolerance on the largest height update of an outer iteration, mm (> 0).

    Returns
    -------
    Reconstruction
        ``iterations`` is the number of outer iterations, ``converged`` whether the last one
        changed no height by ``tol_mm`` or more.

    Raises
    ------
    ReconstructionError
        As :func:`reconstruct_stepwise`, and for ``max_iter`` < 1 or ``tol_mm`` ≤ 0.
    """
    try:
        ok = not isinstance(max_iter, (bool, np.bool_)) and int(max_iter) == max_iter and max_iter >= 1
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ReconstructionError(f"max_iter must be an integer ≥ 1, got {max_iter!r}")
    max_iter = int(max_iter)
    try:
        ok = bool(np.isfinite(tol_mm) and tol_mm > 0)
    except TypeError:
        ok = False
    if not ok:
        raise ReconstructionError(f"tol_mm must be a positive, finite number of mm, got {tol_mm!r}")
    tol_mm = float(tol_mm)
    o, d, q, valid = _check_inputs(o, d, q, valid)
    seed, z0 = _check_seed(seed_pixel, seed_height_mm, o, d, valid)

    labels, _ = ndimage.label(valid)  # 4-connectivity
    S = np.ascontiguousarray(labels == labels[seed])
    H, W = valid.shape

    # Start from the stepwise solution; pixels it could not reach start at the seed height.
    # The stepwise solution is only the start of the Gauss–Newton iteration: its correctors
    # need not converge far below the final tolerance.
    z, done, _, _, _ = _run_stepwise(o, d, q, valid, seed, z0, tol=max(tol_mm, 1e-9))
    z = np.where(S, z, np.nan)
    z[S & ~done] = z0
    z[seed] = z0

    xy = np.zeros((H, W, 2))
    g = np.zeros((H, W, 2))
    dg = np.zeros((H, W, 2))
    D = np.zeros((H + 2, W + 2))
    iD = np.zeros_like(D)
    Ex = np.zeros_like(D)
    Ey = np.zeros_like(D)
    rhs = np.zeros_like(D)
    rowsum = np.zeros(H)
    converged = False
    change = np.inf
    it = 0
    for it in range(1, max_iter + 1):
        _pixel_geometry(o, d, q, S, z, xy, g, dg)
        _gauss_newton_system(S, z, d, xy, g, dg, seed[0], seed[1], D, iD, Ex, Ey, rhs, rowsum)
        delta, _, _ = _pcg(D, iD, Ex, Ey, rhs, 0.01 * tol_mm, _INNER_RTOL, _INNER_MAX_ITER)
        delta = delta[1:-1, 1:-1]
        active = D[1:-1, 1:-1] > 0.0
        z[active] += delta[active]
        change = float(np.max(np.abs(delta[active]))) if active.any() else 0.0
        if not np.isfinite(change):
            raise ReconstructionError(
                "the least-squares iteration diverged (non-finite heights); check that q and d are "
                "consistent (q must be the screen points seen via the surface along d)")
        if change < tol_mm:
            converged = True
            break

    recon = S & np.isfinite(z)
    z = np.where(recon, z, np.nan)
    pts, nrm = _points_and_normals(o, d, q, z)
    return Reconstruction(
        height_mm=z,
        points=pts,
        normals=nrm,
        reconstructed=recon,
        method="least_squares",
        iterations=int(it),
        converged=bool(converged),
        seed_pixel=seed,
        final_change_mm=float(change),
    )


def reconstruct(o, d, q, valid, method="stepwise", seed_pixel=None, seed_height_mm=0.0, **kwargs) -> Reconstruction:
    """Reconstruct a surface with the chosen integrator (paper §2.5).

    Parameters
    ----------
    o, d, q, valid, seed_pixel, seed_height_mm
        See :func:`reconstruct_stepwise`.
    method : {"stepwise", "least_squares"}
        :func:`reconstruct_stepwise` or :func:`reconstruct_least_squares`.
    **kwargs
        ``max_iter`` and ``tol_mm`` for ``"least_squares"``.

    Returns
    -------
    Reconstruction
    """
    if method == "stepwise":
        if kwargs:
            raise ReconstructionError(
                f"method 'stepwise' takes no options, got {sorted(kwargs)}")
        return reconstruct_stepwise(o, d, q, valid, seed_pixel=seed_pixel, seed_height_mm=seed_height_mm)
    if method == "least_squares":
        unknown = set(kwargs) - {"max_iter", "tol_mm"}
        if unknown:
            raise ReconstructionError(
                f"method 'least_squares' accepts max_iter and tol_mm, got unknown {sorted(unknown)}")
        return reconstruct_least_squares(o, d, q, valid, seed_pixel=seed_pixel,
                                         seed_height_mm=seed_height_mm, **kwargs)
    raise ReconstructionError(f"method must be one of {_METHODS}, got {method!r}")
