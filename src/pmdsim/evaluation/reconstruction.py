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
from numba.typed import List
from scipy import ndimage

from ..errors import PmdsimError

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
        ``"least_squares"``: the last iteration changed no height by ``tol_mm`` or more (and
        its sparse solve converged).
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


@numba.njit(cache=True)
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
def _solve_pixel(o, d, q, state, vb, ub, tol, max_iter, nb_dv, nb_du):
    """One integration step: the height of pixel (vb, ub) from all its 4-neighbours a_i whose
    flag in ``state`` (see :func:`_expand_kernel`) is 1 (reconstructed):

        Σ_i [z_b − z_ai − G_i·(xy_b − xy_ai)] = 0,  G_i = ½(g_ai + g_b) (trapezoidal rule),

    linear in t_b for fixed G_i; predictor G_i = g_ai, then correctors until |Δz| < ``tol``
    (at most ``max_iter``). Returns (ok, t_b, g_b,x, g_b,y, correctors used, last |Δz|); not
    ok if the ray misses the plane in front of the camera or the normal is unusable."""
    H = state.shape[0]
    W = state.shape[1]
    ox = o[0]
    oy = o[1]
    oz = o[2]
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
        for k in range(4):
            va = vb + nb_dv[k]
            ua = ub + nb_du[k]
            if va < 0 or va >= H or ua < 0 or ua >= W:
                continue
            if state[va, ua, 3] != 1.0:
                continue
            Gx = state[va, ua, 1] if not have_gb else 0.5 * (state[va, ua, 1] + gbx)
            Gy = state[va, ua, 2] if not have_gb else 0.5 * (state[va, ua, 2] + gby)
            ta = state[va, ua, 0]
            rax = ta * d[va, ua, 0]
            ray = ta * d[va, ua, 1]
            raz = ta * d[va, ua, 2]
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
    return ok, tb, gbx, gby, used, change


@numba.njit(cache=True, error_model="numpy")
def _expand_kernel(o, d, q, state, cur, n_cur, tol, max_iter, nb_dv, nb_du):
    """Layered (wavefront) stepwise integration from the reconstructed pixels ``cur[:n_cur]``.

    ``state`` (H, W, 4) holds per pixel [t, g_x, g_y, flag] with flag −1 = not valid,
    0 = valid and not yet reached, 2 = in the wavefront being solved, 1 = reconstructed
    (t: ray parameter of the point, g: slopes there). ``cur`` (H·W,) int64 lists the flat
    indices v·W + u of the wavefront to start from (flag 1, t and g set); it is used as
    workspace. The wavefront k + 1 is every valid, unreached 4-neighbour of wavefront k; each
    of its pixels is solved from *all* its reconstructed 4-neighbours at once (the pixels of
    one wavefront are never 4-adjacent when the start is a single pixel, as the pixel grid is
    bipartite; in general they are solved from the neighbours reconstructed before the
    wavefront, so the order within a wavefront does not matter). Returns (largest corrector
    count, largest final |Δz|, number of pixels that missed ``tol``)."""
    H = state.shape[0]
    W = state.shape[1]
    nxt = np.empty(H * W, dtype=np.int64)
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
        # Solve each pixel of the wavefront from all its reconstructed neighbours.
        n_solved = 0
        for i in range(n_nxt):
            idx = nxt[i]
            vb = idx // W
            ub = idx - vb * W
            ok, tb, gbx, gby, used, change = _solve_pixel(o, d, q, state, vb, ub, tol, max_iter, nb_dv, nb_du)
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


@numba.njit(cache=True, error_model="numpy")
def _stepwise_kernel(o, d, q, state, sv, su, z0, tol, max_iter, nb_dv, nb_du):
    """Stepwise integration from the seed (sv, su) at height z0: :func:`_expand_kernel` from
    the seed alone. Returns its statistics; the corrector count is −1 if the seed's normal is
    unusable."""
    H = state.shape[0]
    W = state.shape[1]
    t = (z0 - o[2]) / d[sv, su, 2]
    px = o[0] + t * d[sv, su, 0]
    py = o[1] + t * d[sv, su, 1]
    gx, gy = _bisector_slopes(px, py, z0, o[0], o[1], o[2], q[sv, su, 0], q[sv, su, 1], q[sv, su, 2])
    if not (np.isfinite(gx) and np.isfinite(gy)):
        return -1, 0.0, 0
    state[sv, su, 0] = t
    state[sv, su, 1] = gx
    state[sv, su, 2] = gy
    state[sv, su, 3] = 1.0
    cur = np.empty(H * W, dtype=np.int64)
    cur[0] = sv * W + su
    return _expand_kernel(o, d, q, state, cur, 1, tol, max_iter, nb_dv, nb_du)


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


@numba.njit(cache=True, inline="always")
def _between(z0, z1, z2, z3):
    """Height of a pixel from the heights two apart along a row or column: z1, z2 on either
    side (z0 beyond z1, z3 beyond z2, at distance 3): linear interpolation, or linear
    extrapolation from one side if the other is unknown; NaN if neither works."""
    if np.isfinite(z1) and np.isfinite(z2):
        return 0.5 * (z1 + z2)
    if np.isfinite(z1) and np.isfinite(z0):
        return 1.5 * z1 - 0.5 * z0
    if np.isfinite(z2) and np.isfinite(z3):
        return 1.5 * z2 - 0.5 * z3
    return np.nan


@numba.njit(cache=True)
def _interpolate_coarse(S, z, a, b):
    """Heights z (H, W) known on some pixels (a + 2i, b + 2j) (NaN elsewhere): linear
    interpolation to the pixels of S between, first along the rows, at (a + 2i, b + 2j + 1),
    then along the columns, at (a + 2i + 1, ·) — bilinear between four known pixels —, with
    linear extrapolation from one side where the other side is unknown or outside the image
    (:func:`_between`). Returns the number of pixels of S that are still NaN."""
    H, W = S.shape
    ua = (b + 1) % 2  # first column between known ones (or before the first)
    for i in range((H - a + 1) // 2):
        v = a + 2 * i
        for u in range(ua, W, 2):
            if S[v, u]:
                z[v, u] = _between(z[v, u - 3] if u >= 3 else np.nan, z[v, u - 1] if u >= 1 else np.nan,
                                   z[v, u + 1] if u + 1 < W else np.nan,
                                   z[v, u + 3] if u + 3 < W else np.nan)
    va = (a + 1) % 2
    for i in range((H - va + 1) // 2):
        v = va + 2 * i
        for u in range(W):
            if S[v, u]:
                z[v, u] = _between(z[v - 3, u] if v >= 3 else np.nan, z[v - 1, u] if v >= 1 else np.nan,
                                   z[v + 1, u] if v + 1 < H else np.nan,
                                   z[v + 3, u] if v + 3 < H else np.nan)
    n_left = 0
    for v in range(H):
        for u in range(W):
            if S[v, u] and np.isnan(z[v, u]):
                n_left += 1
    return n_left


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _fill_kernel(o, d, q, S, z, tol, max_iter, nb_dv, nb_du):
    """Complete the heights z (H, W) on the pixels of S by stepwise integration
    (:func:`_expand_kernel`) from all pixels of S whose height is finite. Filled heights are
    written to z; pixels that cannot be reached stay NaN. Returns the number of pixels that
    are still NaN.

    Only the known pixels with an unknown 4-neighbour in S (the frontier) are ever used, so
    only their slopes are computed; a known pixel whose normal is unusable becomes unknown
    (and is solved again from its neighbours). The wavefronts start from the frontier in
    row-major order."""
    H, W = S.shape
    ox = o[0]
    oy = o[1]
    oz = o[2]
    state = np.empty((H, W, 4))
    for v in numba.prange(H):
        for u in range(W):
            state[v, u, 1] = np.nan  # slopes not computed
            if not S[v, u]:
                state[v, u, 3] = -1.0
            elif np.isfinite(z[v, u]):
                state[v, u, 3] = 1.0
            else:
                state[v, u, 3] = 0.0
    n_invalidated = 1
    while n_invalidated > 0:  # until no known pixel next to an unknown one is unusable
        n_invalidated = 0
        for v in numba.prange(H):
            for u in range(W):
                if state[v, u, 3] != 1.0 or np.isfinite(state[v, u, 1]):
                    continue
                frontier = False
                for k in range(4):
                    va = v + nb_dv[k]
                    ua = u + nb_du[k]
                    if 0 <= va < H and 0 <= ua < W and state[va, ua, 3] == 0.0:
                        frontier = True
                if not frontier:
                    continue
                zz = z[v, u]
                t = (zz - oz) / d[v, u, 2]
                gx, gy = _bisector_slopes(ox + t * d[v, u, 0], oy + t * d[v, u, 1], zz, ox, oy, oz,
                                          q[v, u, 0], q[v, u, 1], q[v, u, 2])
                if np.isfinite(gx) and np.isfinite(gy) and t > 0.0:
                    state[v, u, 0] = t
                    state[v, u, 1] = gx
                    state[v, u, 2] = gy
                else:
                    z[v, u] = np.nan
                    state[v, u, 3] = 0.0
                    n_invalidated += 1
    cur = np.empty(H * W, dtype=np.int64)
    n_cur = 0
    for v in range(H):
        for u in range(W):
            if state[v, u, 3] == 1.0 and np.isfinite(state[v, u, 1]):
                cur[n_cur] = v * W + u
                n_cur += 1
    if n_cur > 0:
        _expand_kernel(o, d, q, state, cur, n_cur, tol, max_iter, nb_dv, nb_du)
    n_missing = 0
    for v in range(H):
        for u in range(W):
            if S[v, u] and not np.isfinite(z[v, u]):
                if state[v, u, 3] == 1.0:
                    z[v, u] = oz + state[v, u, 0] * d[v, u, 2]
                else:
                    n_missing += 1
    return n_missing


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

#: Over-correction factors of the multigrid coarse-grid correction (plain aggregation
#: underestimates smooth corrections by about a factor of two): on the finest level, whose
#: correction is a single coarse cycle, and on the coarser levels, whose correction is the sum
#: of two coarse cycles (more accurate, so less over-correction is needed and tolerated).
_MG_TOP_OVERCORRECTION = 2.0
_MG_OVERCORRECTION = 1.5
#: Relative tolerance (max-norm of the preconditioned residual) of one inner solve.
_INNER_RTOL = 1e-4
_INNER_MAX_ITER = 200
#: Each Gauss–Newton update is solved at least to this fraction of the convergence tolerance.
_INNER_CAP = 0.1
#: The least-squares integration starts coarse to fine (see :func:`_start_heights`) when the
#: seed's component has at least this many pixels; smaller problems start stepwise.
_COARSE_START_MIN_PIXELS = 50_000
#: Convergence tolerance of the Gauss–Newton iteration on the coarse levels of the start, mm.
#: The start need not be more accurate than the coarse and fine solutions agree (about 1e-4 mm
#: for the full-frame benchmark); after an update of at most this size the coarse heights are
#: already far closer to the coarse solution than that (the remaining error is of second
#: order in the update plus the inner solve's error, ≤ 1e-5 mm), so a typical coarse level
#: stops after one iteration. The final convergence test is the one on the full grid.
_COARSE_TOL_MM = 1e-3


@numba.njit(cache=True)
def _direction_matvec_dot(D, Ex, Ey, z, p, beta, Ap):
    """The CG direction p = z + βp (p = z for β = 0), then Ap = N p; returns p·Ap. The
    direction is updated one row ahead of the product, which needs the rows above and below."""
    Hp, Wp = D.shape

    def _direction_row(v):
        if beta == 0.0:
            for u in range(1, Wp - 1):
                p[v, u] = z[v, u]
        else:
            for u in range(1, Wp - 1):
                p[v, u] = z[v, u] + beta * p[v, u]

    _direction_row(1)
    s = 0.0
    for v in range(1, Hp - 1):
        if v + 1 < Hp - 1:
            _direction_row(v + 1)
        for u in range(1, Wp - 1):
            y = (D[v, u] * p[v, u] - Ex[v, u - 1] * p[v, u - 1] - Ex[v, u] * p[v, u + 1]
                 - Ey[v - 1, u] * p[v - 1, u] - Ey[v, u] * p[v + 1, u])
            Ap[v, u] = y
            s += p[v, u] * y
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

    Rows are swept in pairs, the second row one column behind the first (it needs the new
    value above it): the result is that of the row-by-row sweep, but the two rows are two
    independent dependency chains, which the processor overlaps. After a forward sweep from
    zero the residual at a pixel is Ex·x(right) + Ey·x(below) (the equation was satisfied with
    the right and lower neighbours still 0); it is accumulated once the row below is swept."""
    Hp, Wp = iD.shape
    rc[:, :] = 0.0

    def _restrict_row(w):
        V = ((w - 1) >> 1) + 1
        for u in range(1, Wp - 1):
            rc[V, ((u - 1) >> 1) + 1] += Ex[w, u] * x[w, u + 1] + Ey[w, u] * x[w + 1, u]

    v = 1
    while v < Hp - 1:
        if v + 1 < Hp - 1:
            w = v + 1
            x0 = (r[v, 1] + Ey[v - 1, 1] * x[v - 1, 1]) * iD[v, 1]
            x[v, 1] = x0
            x1 = 0.0
            for u in range(2, Wp - 1):
                x0 = (r[v, u] + Ex[v, u - 1] * x0 + Ey[v - 1, u] * x[v - 1, u]) * iD[v, u]
                x[v, u] = x0
                t = u - 1
                x1 = (r[w, t] + Ex[w, t - 1] * x1 + Ey[v, t] * x[v, t]) * iD[w, t]
                x[w, t] = x1
            t = Wp - 2
            x1 = (r[w, t] + Ex[w, t - 1] * x1 + Ey[v, t] * x[v, t]) * iD[w, t]
            x[w, t] = x1
            x[v, Wp - 1] = 0.0
            x[w, Wp - 1] = 0.0
            if v > 1:
                _restrict_row(v - 1)
            _restrict_row(v)
            v += 2
        else:
            x0 = 0.0
            for u in range(1, Wp - 1):
                x0 = (r[v, u] + Ex[v, u - 1] * x0 + Ey[v - 1, u] * x[v - 1, u]) * iD[v, u]
                x[v, u] = x0
            x[v, Wp - 1] = 0.0
            if v > 1:
                _restrict_row(v - 1)
            v += 1
    _restrict_row(Hp - 2)  # the row below it is the zero padding


@numba.njit(cache=True)
def _prolong_postsmooth(iD, Ex, Ey, r, x, xc, alpha):
    """x += alpha·P xc (piecewise-constant interpolation from 2×2 aggregates), then one
    backward Gauss–Seidel sweep for N x = r. Rows are swept in pairs from the bottom, the
    upper row one column behind (as in :func:`_presmooth_restrict`; the result is that of the
    row-by-row sweep); the interpolation is added to a row just before it is needed. Inactive
    pixels receive the interpolation too (no branch), but their couplings are 0 and the sweep
    resets them to 0 (iD = 0). Returns (r·x, max |x|) of the result (for CG)."""
    Hp, Wp = iD.shape
    s = 0.0
    m = 0.0

    def _add_row(w):
        V = ((w - 1) >> 1) + 1
        for u in range(1, Wp - 1):
            x[w, u] += alpha * xc[V, ((u - 1) >> 1) + 1]

    _add_row(Hp - 2)
    v = Hp - 2
    while v >= 1:
        if v - 1 >= 1:
            w = v - 1
            _add_row(w)
            if w > 1:
                _add_row(w - 1)
            t = Wp - 2
            x0 = (r[v, t] + Ex[v, t - 1] * x[v, t - 1] + Ex[v, t] * x[v, t + 1]
                  + Ey[w, t] * x[w, t] + Ey[v, t] * x[v + 1, t]) * iD[v, t]
            x[v, t] = x0
            s += r[v, t] * x0
            m = max(m, abs(x0))
            x1 = x[w, Wp - 1]
            for u in range(Wp - 3, 0, -1):
                x0 = (r[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * x0
                      + Ey[w, u] * x[w, u] + Ey[v, u] * x[v + 1, u]) * iD[v, u]
                x[v, u] = x0
                s += r[v, u] * x0
                m = max(m, abs(x0))
                t = u + 1
                x1 = (r[w, t] + Ex[w, t - 1] * x[w, t - 1] + Ex[w, t] * x1
                      + Ey[w - 1, t] * x[w - 1, t] + Ey[w, t] * x[v, t]) * iD[w, t]
                x[w, t] = x1
                s += r[w, t] * x1
                m = max(m, abs(x1))
            x1 = (r[w, 1] + Ex[w, 0] * x[w, 0] + Ex[w, 1] * x1
                  + Ey[w - 1, 1] * x[w - 1, 1] + Ey[w, 1] * x[v, 1]) * iD[w, 1]
            x[w, 1] = x1
            s += r[w, 1] * x1
            m = max(m, abs(x1))
            v -= 2
        else:
            xr = x[v, Wp - 1]
            for u in range(Wp - 2, 0, -1):
                xr = (r[v, u] + Ex[v, u - 1] * x[v, u - 1] + Ex[v, u] * xr
                      + Ey[v - 1, u] * x[v - 1, u] + Ey[v, u] * x[v + 1, u]) * iD[v, u]
                x[v, u] = xr
                s += r[v, u] * xr
                m = max(m, abs(xr))
            v -= 1
    return s, m


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


@numba.njit(cache=True)
def _coarsest_solve(kind, F, index, r, x):
    """x = exact solution on the coarsest level: ``kind`` 0 = Cholesky factor F
    (:func:`_cholesky_solve`), 1 = pseudo-inverse F of the matrix of the cells ``index``,
    2 = no unknowns (x = 0)."""
    if kind == 0:
        _cholesky_solve(F, index, r, x)
        return
    x[:, :] = 0.0
    if kind == 1:
        n = index.size
        rf = r.ravel()
        xf = x.ravel()
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += F[i, j] * rf[index[j]]
            xf[index[i]] = s


@numba.njit(cache=True)
def _mg_cycle(lvl, r, x, Ds, iDs, Exs, Eys, xs, rcs, r2s, accs, kind, F, index, alpha_top, alpha):
    """x = multigrid cycle for N_lvl x = r on level ``lvl`` of the hierarchy (typed lists of
    the padded level arrays, see :class:`_Multigrid`): forward Gauss–Seidel, coarse-grid
    correction, backward Gauss–Seidel; exact on the coarsest level. The coarse-grid
    correction is, on level 0, one cycle on level 1 scaled by ``alpha_top`` (a V-cycle step:
    the finest level is by far the most expensive) and, below, two cycles (the second for the
    residual the first leaves) whose sum is scaled by ``alpha`` (W-cycle). Returns
    (r·x, max |x|) except on the coarsest level (0, 0)."""
    if lvl == len(Ds) - 1:
        _coarsest_solve(kind, F, index, r, x)
        return 0.0, 0.0
    n = lvl + 1
    _presmooth_restrict(iDs[lvl], Exs[lvl], Eys[lvl], r, x, rcs[n])
    _mg_cycle(n, rcs[n], xs[n], Ds, iDs, Exs, Eys, xs, rcs, r2s, accs, kind, F, index, alpha_top, alpha)
    if lvl == 0:
        return _prolong_postsmooth(iDs[lvl], Exs[lvl], Eys[lvl], r, x, xs[n], alpha_top)
    acc = accs[n]
    acc[:, :] = xs[n]
    _residual(Ds[n], Exs[n], Eys[n], rcs[n], acc, r2s[n])
    _mg_cycle(n, r2s[n], xs[n], Ds, iDs, Exs, Eys, xs, rcs, r2s, accs, kind, F, index, alpha_top, alpha)
    acc += xs[n]
    return _prolong_postsmooth(iDs[lvl], Exs[lvl], Eys[lvl], r, x, acc, alpha)


class _Multigrid:
    """Aggregation multigrid preconditioner for a padded 5-point SPD operator (see above).

    Levels aggregate 2×2 pixels, with Galerkin coarse operators, so any mask works; the
    coarsest level (≤ ``_MG_COARSEST_CELLS`` cells) is solved exactly. One application
    (:meth:`apply`) is a cycle (:func:`_mg_cycle`, entirely in compiled code): forward
    Gauss–Seidel before and backward Gauss–Seidel after the coarse-grid correction (a
    symmetric pair), the correction being one coarse cycle on the finest level and two below
    (a V-cycle step on top of W-cycles), over-corrected (plain aggregation underestimates
    smooth corrections)."""

    def __init__(self, D, iD, Ex, Ey):
        levels = [(D, iD, Ex, Ey)]
        while (D.shape[0] - 2) * (D.shape[1] - 2) > _MG_COARSEST_CELLS:
            D, iD, Ex, Ey = _coarsen(D, Ex, Ey)
            levels.append((D, iD, Ex, Ey))
        self.n_levels = len(levels)
        shapes = [lv[0].shape for lv in levels]
        self.Ds = List([lv[0] for lv in levels])
        self.iDs = List([lv[1] for lv in levels])
        self.Exs = List([lv[2] for lv in levels])
        self.Eys = List([lv[3] for lv in levels])
        # Work arrays per level (level 0's are unused: its input and output are the caller's).
        self.xs = List([np.zeros(s) for s in shapes])     # the level's result
        self.rcs = List([np.zeros(s) for s in shapes])    # restricted residual (level input)
        self.r2s = List([np.zeros(s) for s in shapes])    # residual for the second cycle
        self.accs = List([np.zeros(s) for s in shapes])   # sum of the two coarse cycles
        self._factor_coarsest(*levels[-1])

    def _factor_coarsest(self, D, _iD, Ex, Ey):
        Wp = D.shape[1]
        flat = np.flatnonzero(D.ravel() > 0.0)
        self.coarse_index = flat
        n = flat.size
        if n == 0:
            self.coarse_kind, self.coarse_factor = 2, np.zeros((1, 1))
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
            self.coarse_kind, self.coarse_factor = 0, L
        else:  # numerically semi-definite: pseudo-inverse
            self.coarse_kind, self.coarse_factor = 1, np.ascontiguousarray(np.linalg.pinv(A, hermitian=True))

    def apply(self, r, out, alpha_top, alpha):
        """out = M⁻¹ r (padded level-0 arrays; out's padding must be 0), with the
        over-correction factors ``alpha_top`` (finest level) and ``alpha`` (below). Returns
        (r·out, max |out|)."""
        rz, zmax = _mg_cycle(0, r, out, self.Ds, self.iDs, self.Exs, self.Eys, self.xs, self.rcs,
                             self.r2s, self.accs, self.coarse_kind, self.coarse_factor,
                             self.coarse_index, float(alpha_top), float(alpha))
        if self.n_levels == 1:  # solved exactly, no sweep that could have summed them
            rz, zmax = _dot_maxabs(r, out)
        return rz, zmax


class _CGWork:
    """Work arrays of :func:`_pcg` for padded grids of one shape (zero padding kept)."""

    def __init__(self, shape):
        self.x = np.zeros(shape)
        self.r = np.zeros(shape)
        self.z = np.zeros(shape)
        self.p = np.zeros(shape)
        self.Ap = np.zeros(shape)


def _pcg(D, iD, Ex, Ey, b, atol, rtol, max_iter, cap=np.inf, work=None, mg=None):
    """Conjugate gradients for N x = b, preconditioned by :class:`_Multigrid`.

    Stops when the max-norm of the preconditioned residual (an estimate of the error of x) is
    below ``max(atol, min(rtol · its initial value, cap))``; that last preconditioned residual
    is added to x. The over-corrected cycle is not guaranteed to be positive definite; should
    CG break down with it (non-positive curvature or a non-finite residual), CG restarts from
    the current x with the plain cycle (no over-correction), which is a symmetric positive
    definite preconditioner. After ``max_iter`` iterations in all, the current x is returned
    (not converged; the caller's next Gauss–Newton iteration continues from it).
    ``work`` (:class:`_CGWork`) and ``mg`` (the hierarchy of this operator) are created if not
    given. Returns (x, total CG iterations, converged); x is ``work.x``."""
    if work is None:
        work = _CGWork(D.shape)
    if mg is None:
        mg = _Multigrid(D, iD, Ex, Ey)
    x, r, z, p, Ap = work.x, work.r, work.z, work.p, work.Ap
    x[:] = 0.0
    r[:] = b
    total = 0
    tol = None
    for alpha_top, alpha in ((_MG_TOP_OVERCORRECTION, _MG_OVERCORRECTION), (1.0, 1.0)):
        rz, zmax = mg.apply(r, z, alpha_top, alpha)
        if tol is None:
            if zmax <= atol:
                x += z  # the solution is below the tolerance anyway
                return x, total, True
            tol = max(atol, min(rtol * zmax, cap))
        elif zmax <= tol:
            x += z
            return x, total, True
        beta = 0.0
        breakdown = False
        while total < max_iter:
            total += 1
            pAp = _direction_matvec_dot(D, Ex, Ey, z, p, beta, Ap)
            if not (pAp > 0.0 and rz > 0.0):
                breakdown = True  # the preconditioner is not positive definite here
                break
            a = rz / pAp
            _cg_update(x, r, p, Ap, a)
            rz_new, zmax = mg.apply(r, z, alpha_top, alpha)
            if not np.isfinite(rz_new):
                breakdown = True
                break
            if zmax <= tol:
                x += z
                return x, total, True
            beta = rz_new / rz
            rz = rz_new
        if not breakdown:
            return x, total, False
        # Restart with the plain cycle from the last good x (its residual recomputed).
        if not np.all(np.isfinite(x)):
            x[:] = 0.0
        _residual(D, Ex, Ey, b, x, r)
    return x, total, False


#: Row blocks of :func:`_assemble_gauss_newton` (a constant, so that the result does not
#: depend on the number of threads).
_ASSEMBLY_BLOCKS = 16


@numba.njit(cache=True, error_model="numpy")
def _row_geometry(o, d, q, S, z, v, geo):
    """For every pixel u of S in row v at height z: geo[u] = (x, y, g_x, g_y, dg_x/dz,
    dg_y/dz, d_x/d_z, d_y/d_z) — the point's x, y, the slopes g of the bisector normal there,
    their derivative along the view ray and the ray's dx/dz, dy/dz (geo shape (W, 8))."""
    W = S.shape[1]
    ox = o[0]
    oy = o[1]
    oz = o[2]
    for u in range(W):
        if not S[v, u]:
            continue
        idz = 1.0 / d[v, u, 2]
        ex = d[v, u, 0] * idz  # dp/dz = (ex, ey, 1)
        ey = d[v, u, 1] * idz
        pz = z[v, u]
        w = pz - oz
        px = ox + w * ex
        py = oy + w * ey
        ax = ox - px
        ay = oy - py
        az = oz - pz
        ia = 1.0 / np.sqrt(ax * ax + ay * ay + az * az)
        ax *= ia
        ay *= ia
        az *= ia
        bx = q[v, u, 0] - px
        by = q[v, u, 1] - py
        bz = q[v, u, 2] - pz
        ib = 1.0 / np.sqrt(bx * bx + by * by + bz * bz)
        bx *= ib
        by *= ib
        bz *= ib
        mx = ax + bx
        my = ay + by
        mz = az + bz
        # d(â)/dz = −(e − (â·e) â)/|a|, the same for b̂.
        ae = ax * ex + ay * ey + az
        be = bx * ex + by * ey + bz
        dmx = -(ex - ae * ax) * ia - (ex - be * bx) * ib
        dmy = -(ey - ae * ay) * ia - (ey - be * by) * ib
        dmz = -(1.0 - ae * az) * ia - (1.0 - be * bz) * ib
        imz = 1.0 / mz
        gx = -mx * imz
        gy = -my * imz
        geo[u, 0] = px
        geo[u, 1] = py
        geo[u, 2] = gx
        geo[u, 3] = gy
        geo[u, 4] = -(dmx + gx * dmz) * imz  # d(−m_x/m_z)/dz
        geo[u, 5] = -(dmy + gy * dmz) * imz
        geo[u, 6] = ex
        geo[u, 7] = ey


@numba.njit(cache=True, error_model="numpy")
def _edge(za, zb, ga, ia, gb, ib):
    """Residual of the trapezoidal equation of the edge a → b (heights za, zb; geometry rows
    ga, gb of :func:`_row_geometry` at columns ia, ib) and its derivatives with respect to
    z_a and z_b (xy moves along the rays, dxy/dz = d_xy/d_z; the slopes change by dg/dz).
    Returns (finite, residual, J_a, J_b)."""
    Gx = 0.5 * (ga[ia, 2] + gb[ib, 2])
    Gy = 0.5 * (ga[ia, 3] + gb[ib, 3])
    dx = gb[ib, 0] - ga[ia, 0]
    dy = gb[ib, 1] - ga[ia, 1]
    res = zb - za - (Gx * dx + Gy * dy)
    Ja = -1.0 + (Gx * ga[ia, 6] + Gy * ga[ia, 7]) - 0.5 * (ga[ia, 4] * dx + ga[ia, 5] * dy)
    Jb = 1.0 - (Gx * gb[ib, 6] + Gy * gb[ib, 7]) - 0.5 * (gb[ib, 4] * dx + gb[ib, 5] * dy)
    ok = np.isfinite(res) and np.isfinite(Ja) and np.isfinite(Jb)
    return ok, res, Ja, Jb


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _assemble_gauss_newton(o, d, q, S, z, sv, su, D, iD, Ex, Ey, rhs):
    """Gauss–Newton normal equations Jᵀ J δ = −Jᵀ res of the trapezoidal equations
    res = z_b − z_a − ½(g_a + g_b)·(xy_b − xy_a) of all 4-neighbour pairs in S at the heights
    z, written to the padded 5-point arrays (see above). The seed (sv, su) is not an unknown
    (gauge): it gets no row, and the couplings to it are 0. Edges whose residual or
    derivatives are not finite are dropped.

    Every edge is evaluated once, from its left or upper pixel. The rows are split into
    :data:`_ASSEMBLY_BLOCKS` blocks processed in parallel, each with a rolling two-row buffer
    of the pixel geometry (:func:`_row_geometry`); the contributions of a block's last row to
    the next block's first row go through a buffer that is added afterwards."""
    H, W = S.shape
    nb = min(H, _ASSEMBLY_BLOCKS)
    bD = np.zeros((nb, W))
    brhs = np.zeros((nb, W))
    for blk in numba.prange(nb):
        v0 = blk * H // nb
        v1 = (blk + 1) * H // nb
        geo = np.empty((2, W, 8))
        for v in range(v0, v1):
            for u in range(W):
                D[v + 1, u + 1] = 0.0
                rhs[v + 1, u + 1] = 0.0
        _row_geometry(o, d, q, S, z, v0, geo[0])
        for v in range(v0, v1):
            gc = geo[(v - v0) & 1]
            gn = geo[1 - ((v - v0) & 1)]
            below = v + 1 < H
            if below:
                _row_geometry(o, d, q, S, z, v + 1, gn)
            for u in range(W):
                exo = 0.0
                eyo = 0.0
                if S[v, u]:
                    a_free = not (v == sv and u == su)
                    if u + 1 < W and S[v, u + 1]:  # right
                        ok, res, Ja, Jb = _edge(z[v, u], z[v, u + 1], gc, u, gc, u + 1)
                        if ok:
                            b_free = not (v == sv and u + 1 == su)
                            if a_free:
                                D[v + 1, u + 1] += Ja * Ja
                                rhs[v + 1, u + 1] -= Ja * res
                            if b_free:
                                D[v + 1, u + 2] += Jb * Jb
                                rhs[v + 1, u + 2] -= Jb * res
                            if a_free and b_free:
                                exo = -Ja * Jb
                    if below and S[v + 1, u]:  # below
                        ok, res, Ja, Jb = _edge(z[v, u], z[v + 1, u], gc, u, gn, u)
                        if ok:
                            b_free = not (v + 1 == sv and u == su)
                            if a_free:
                                D[v + 1, u + 1] += Ja * Ja
                                rhs[v + 1, u + 1] -= Ja * res
                            if b_free:
                                if v + 1 < v1:
                                    D[v + 2, u + 1] += Jb * Jb
                                    rhs[v + 2, u + 1] -= Jb * res
                                else:
                                    bD[blk, u] = Jb * Jb
                                    brhs[blk, u] = -Jb * res
                            if a_free and b_free:
                                eyo = -Ja * Jb
                Ex[v + 1, u + 1] = exo
                Ey[v + 1, u + 1] = eyo
    for blk in range(nb - 1):
        v1 = (blk + 1) * H // nb
        for u in range(W):
            D[v1 + 1, u + 1] += bD[blk, u]
            rhs[v1 + 1, u + 1] += brhs[blk, u]
    for v in numba.prange(H):
        for u in range(W):
            dd = D[v + 1, u + 1]
            if dd > 0.0:
                iD[v + 1, u + 1] = 1.0 / dd
            else:
                D[v + 1, u + 1] = 0.0
                iD[v + 1, u + 1] = 0.0
                rhs[v + 1, u + 1] = 0.0


@numba.njit(cache=True)
def _apply_update(z, delta, D):
    """z += delta on the unknowns (D > 0; delta and D padded by one pixel). Returns the
    largest |delta| there (NaN if any is not finite, 0 if there are no unknowns)."""
    H, W = z.shape
    m = 0.0
    for v in range(H):
        for u in range(W):
            if D[v + 1, u + 1] > 0.0:
                dz = delta[v + 1, u + 1]
                z[v, u] += dz
                if not np.isfinite(dz):
                    m = np.nan
                elif abs(dz) > m:
                    m = abs(dz)
    return m


def _gauss_newton(o, d, q, S, seed, z, tol, max_iter):
    """Gauss–Newton iterations of the least-squares integration on the pixels S (H, W),
    updating the heights z (H, W) in place, until the largest update is below ``tol`` (its
    linear solve having converged) or after ``max_iter`` iterations. Returns (iterations,
    converged, largest last update).

    Each update is solved (:func:`_pcg`) until the estimated error of the update is below
    ``max(tol/100, min(1e-4 · |first estimate|, tol/10))`` (max-norm): to a tenth of ``tol``,
    so that after an update that removes all but a second-order remainder the next (checking)
    update is below ``tol`` — with a good start (see :func:`_start_heights`) one full solve
    and one cheap checking solve suffice —, and relatively to 1e-4 when that is finer, but
    never below ``tol/100``, the accuracy to which the last update is known when it is
    compared with ``tol``."""
    H, W = S.shape
    D = np.zeros((H + 2, W + 2))
    iD = np.zeros_like(D)
    Ex = np.zeros_like(D)
    Ey = np.zeros_like(D)
    rhs = np.zeros_like(D)
    work = _CGWork(D.shape)
    converged = False
    change = np.inf
    it = 0
    for it in range(1, max_iter + 1):
        _assemble_gauss_newton(o, d, q, S, z, seed[0], seed[1], D, iD, Ex, Ey, rhs)
        delta, _, solved = _pcg(D, iD, Ex, Ey, rhs, 0.01 * tol, _INNER_RTOL, _INNER_MAX_ITER,
                                cap=_INNER_CAP * tol, work=work)
        change = _apply_update(z, delta, D)
        if not np.isfinite(change):
            raise ReconstructionError(
                "the least-squares iteration diverged (non-finite heights); check that q and d are "
                "consistent (q must be the screen points seen via the surface along d)")
        if change < tol and solved:  # a partial update proves nothing
            converged = True
            break
    return it, converged, change


def _coarse_mask(S, seed):
    """The coarse problem of the coarse-to-fine start: pixels (a + 2i, b + 2j) of S with
    (a, b) = seed mod 2, so that the seed is one of them.

    Two coarse 4-neighbours are coupled through the fine pixel between them, which must be
    in S too: a coarse pixel is kept only if the fine pixels to its right and below are in S
    (or outside the image), so every coarse neighbour pair is a path of two fine pairs and
    the coarse problem never bridges a gap of the mask. The seed is always kept (instead its
    right or lower coarse neighbour is dropped). Returns (a, b, coarse mask restricted to the
    seed's 4-connected component, coarse seed)."""
    H, W = S.shape
    a, b = seed[0] % 2, seed[1] % 2
    Sp = np.ones((H + 1, W + 1), dtype=bool)
    Sp[:H, :W] = S
    right = Sp[a:H:2, b + 1:W + 1:2]
    down = Sp[a + 1:H + 1:2, b:W:2]
    Sc = S[a::2, b::2] & right & down
    Hc, Wc = Sc.shape
    sc = (seed[0] // 2, seed[1] // 2)
    Sc[sc] = True
    if sc[1] + 1 < Wc and not right[sc]:
        Sc[sc[0], sc[1] + 1] = False
    if sc[0] + 1 < Hc and not down[sc]:
        Sc[sc[0] + 1, sc[1]] = False
    labels, _ = ndimage.label(Sc)  # 4-connectivity
    return a, b, np.ascontiguousarray(labels == labels[sc]), sc


def _start_heights(o, d, q, S, seed, z0, tol, max_iter):
    """Start of the Gauss–Newton iteration on the pixels S (heights (H, W), NaN outside S).

    Coarse to fine: if S has at least :data:`_COARSE_START_MIN_PIXELS` pixels, the
    least-squares problem of every second row and column (:func:`_coarse_mask`, the same
    equations between pixels two apart) is solved first — recursively started the same way —
    to :data:`_COARSE_TOL_MM`; the pixels between are interpolated (bilinearly in the pixel
    grid, :func:`_interpolate_coarse`), and those without solved pixels on both sides (at
    borders and holes of the mask) are filled by stepwise integration from their neighbours
    (:func:`_fill_kernel`). The coarse solution differs from the fine one only by the
    discretisation and by how the slope noise averages, so the fine iteration starts close to
    its solution (for the full-frame benchmark within about 1e-4 mm). On
    small problems (and should a coarse solve fail) the start is the stepwise solution
    (:func:`reconstruct_stepwise`). Pixels of S that neither reaches start at the seed
    height."""
    H, W = S.shape
    z = None
    if int(np.count_nonzero(S)) >= _COARSE_START_MIN_PIXELS and min(H, W) >= 4:
        a, b, Sc, sc = _coarse_mask(S, seed)
        dc = np.ascontiguousarray(d[a::2, b::2])
        qc = np.ascontiguousarray(q[a::2, b::2])
        tol_c = max(tol, _COARSE_TOL_MM)
        try:
            zc = _start_heights(o, dc, qc, Sc, sc, z0, tol_c, max_iter)
            _gauss_newton(o, dc, qc, Sc, sc, zc, tol_c, max_iter)
        except ReconstructionError:
            zc = None  # fall back to the stepwise start
        if zc is not None:
            z = np.full((H, W), np.nan)
            z[a::2, b::2] = np.where(Sc, zc, np.nan)
            if _interpolate_coarse(S, z, a, b) > 0:
                _fill_kernel(o, d, q, S, z, max(tol, 1e-9), STEP_MAX_ITER, _NB_DV, _NB_DU)
    if z is None:
        # The stepwise solution is only a start: its correctors need not converge far below
        # the final tolerance.
        z, _, _, _, _ = _run_stepwise(o, d, q, S, seed, z0, tol=max(tol, 1e-9))
    z = np.where(S, z, np.nan)
    z[S & ~np.isfinite(z)] = z0
    z[seed] = z0
    return z


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
    would make the iteration converge only linearly.

    **Start.** Small problems (fewer than :data:`_COARSE_START_MIN_PIXELS` pixels) start from
    the stepwise solution (:func:`reconstruct_stepwise`), which already satisfies the
    equations exactly for consistent data. Larger ones start coarse to fine: the same
    least-squares problem on every second row and column (never bridging a gap of the mask)
    is solved first, recursively started the same way, and interpolated (see
    :func:`_start_heights`); the full-grid iteration then starts within the coarse–fine
    discrepancy of its solution (about 1e-4 mm for a full 1920×1200 frame), and typically two
    iterations on the full grid suffice: one full update and one that confirms convergence.
    The start affects only the run time: the result is the minimum of the full-grid
    equations, and convergence is always decided on the full grid.

    **Gauge.** The seed pixel's height is fixed at ``seed_height_mm`` exactly (it is removed
    from the unknowns). **Components.** Valid pixels not 4-connected to the seed are not tied
    to the gauge and are left NaN (as in the stepwise integration). **Solver.** Conjugate
    gradients preconditioned by aggregation multigrid (2×2 aggregates with Galerkin coarse
    operators, symmetric Gauss–Seidel smoothing, over-corrected coarse-grid correction — one
    coarse cycle from the full grid, W-cycles below —, dense Cholesky on the coarsest level),
    which copes with arbitrary masks. Each update is solved until its estimated error is below
    ``tol_mm``/10 (or 1e-4 relative, if finer, but not below ``tol_mm``/100), so that the
    update that follows, which decides convergence, is accurate to a small fraction of
    ``tol_mm``.

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
        ``iterations`` is the number of outer iterations on the full grid, ``converged``
        whether the last one changed no height by ``tol_mm`` or more (with its sparse solve
        converged).

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

    z = _start_heights(o, d, q, S, seed, z0, tol_mm, max_iter)
    it, converged, change = _gauss_newton(o, d, q, S, seed, z, tol_mm, max_iter)

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
