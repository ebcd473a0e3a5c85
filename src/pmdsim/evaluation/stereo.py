"""Stereo deflectometry: the absolute surface without a known point (issue 14).

One camera's deflectometric data fix the surface normal at every point of a view ray, but not
where along the ray the surface is: the mono reconstruction needs a seed of known height
(:mod:`pmdsim.evaluation.reconstruction`). A second calibrated camera removes that ambiguity
(Knauer, Kaminski and Häusler 2004, "Phase measuring deflectometry: a new approach to measure
specular free-form surfaces", Proc. SPIE 5457; the paper's "requirement to conform to the
measurement of a second camera", §1): only at the true surface do the normals that the two
cameras imply agree.

Method (all in one reconstruction frame, e.g. the sample frame; heights along its +z):

1. **Normal consistency on sparse pixels.** For a pixel of camera A and a candidate height z,
   the point p(z) = o_A + t·d_A lies on A's view ray; A's registered screen point q_A implies the
   normal n_A(z) = bisector(o_A − p, q_A − p) (law of reflection, paper §2.5). p(z) is projected
   into camera B (its calibrated pinhole + distortion model, §2.2); B's registered screen
   points are interpolated there (cubic convolution, Keys 1981, over a 4 × 4 neighbourhood of
   registered pixels) to q_B, which implies n_B(z) = bisector(o_B − p, q_B − p). The residual
   r(z) = g_A(z) − g_B(z) of the slopes g = (−n_x/n_z, −n_y/n_z) vanishes at the true height.
   It is scanned over the search range (``search_range_mm``, in steps of ``search_step_mm``),
   every local minimum of |r| is refined by Gauss–Newton on the 2-vector r (one unknown),
   and the refined minimum with the smallest |r| is the pixel's absolute height (an *anchor*).
   Pixels with a second refined minimum of comparable |r| elsewhere in the range are
   ambiguous and not used.
2. **Anchored integration of each camera's slopes.** Each camera's slope field is integrated
   by the zonal least-squares integration of :mod:`pmdsim.evaluation.least_squares` (the same
   Gauss–Newton assembly; on full frames CG preconditioned by the DCT with an exact level,
   :mod:`pmdsim.evaluation.stereo_solve`, else by multigrid), without a fixed seed: the gauge
   comes from the anchor equations w·(z_i − a_i) = 0 added to the normal equations (weight
   :data:`ANCHOR_WEIGHT`: small, so that the anchors set the absolute level, which the slopes
   cannot, and the slopes set the shape). A camera's anchors are those found along its own
   rays with the other camera(s) as partner — both cameras' slope fields enter every anchor.
   Heights outside the overlap follow from the camera's own slopes.
3. **Agreement report** per pixel of each camera where a partner sees the same point: the
   angle between the two implied normals at the reconstructed point (µrad) and the height
   discrepancy z_A − z_B along A's view ray, z_B from the partner's reconstruction
   (interpolated at the projection, iterated to the intersection with A's ray), in µm.

Assumptions and limits: docs/stereo.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage

from ..geometry.camera import Camera
from ..geometry.transform import RigidTransform
from .integration import (
    Reconstruction,
    ReconstructionError,
    _bisector_slopes,
    _check_inputs,
    _points_and_normals,
)
from .least_squares import (_INNER_CAP, _INNER_MAX_ITER, _INNER_RTOL, _apply_update, _assemble_gauss_newton, _Fields,
                            _start_heights)
from . import poisson
from .multigrid import _CGWork, _pcg
from .registration import Registration
from .stereo_solve import level_dct_pcg
from ..geometry.compact import compact_repr

__all__ = ["StereoView", "StereoCamera", "StereoReconstruction", "reconstruct_stereo", "evaluate_stereo_decoded",
           "stereo_views", "refine_anchors",
           "stereo_residual",
           "ANCHOR_WEIGHT", "DEFAULT_SEARCH_RANGE_MM", "DEFAULT_SEARCH_STEP_MM"]


#: Weight w of an anchor equation w·(z − a) relative to the slope equations (weight 1). A
#: slope equation between neighbours is known to about 1 nm (µrad slopes over ≤ 1 mm), an
#: anchor to about 1 µm; w² = 1e-4 lets the anchors fix the absolute level (which the slopes
#: leave free) while their noise barely bends the surface locally.
ANCHOR_WEIGHT = 1e-2

#: Default height range searched along the view rays (reconstruction frame, mm).
DEFAULT_SEARCH_RANGE_MM = (-20.0, 20.0)

#: Default scan step of the search (mm).
DEFAULT_SEARCH_STEP_MM = 0.25

#: Default number of anchors aimed at per camera (sets the sparse pixel stride).
DEFAULT_ANCHORS = 4000

_GN_TOL_MM = 1e-9
_REPORT_TOL_MM = 1e-7
_REPORT_MAX_ITER = 6
_GN_MAX_ITER = 30
_FD_STEP_MM = 1e-3


# ============================================================================ kernels
@numba.njit(cache=True, nogil=True, inline="always")
def _project(R, t, cam, px, py, pz):
    """Reference-frame point → pixel (u, v) of a camera (eqs. 2–4). ``R``, ``t``: T_cam_ref;
    ``cam`` = (fx, fy, ppx, ppy, k1, k2, k3, p1, p2). Returns (ok, u, v)."""
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    if not z > 0.0:
        return False, 0.0, 0.0
    xn = x / z
    yn = y / z
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (cam[4] + r2 * (cam[5] + r2 * cam[6]))
    xd = xn * radial + 2.0 * cam[7] * xn * yn + cam[8] * (r2 + 2.0 * xn * xn)
    yd = yn * radial + cam[7] * (r2 + 2.0 * yn * yn) + 2.0 * cam[8] * xn * yn
    return True, cam[0] * xd + cam[2], cam[1] * yd + cam[3]


@numba.njit(cache=True, nogil=True, inline="always")
def _keys(s):
    """Cubic-convolution weights (Keys 1981, a = −1/2) of the 4 samples at −1, 0, 1, 2 for
    the fractional position s ∈ [0, 1): C¹, exact for quadratics."""
    s2 = s * s
    s3 = s2 * s
    return (-0.5 * s3 + s2 - 0.5 * s, 1.5 * s3 - 2.5 * s2 + 1.0, -1.5 * s3 + 2.0 * s2 + 0.5 * s, 0.5 * s3 - 0.5 * s2)


@numba.njit(cache=True, nogil=True)
def _interp(arr, ok, u, v, out):
    """Cubic convolution of ``arr`` (H, W, C) at pixel (u, v) into ``out`` (C,); False (out
    untouched) unless all 16 samples of the 4 × 4 neighbourhood are inside and ``ok``."""
    inside, iu, iv = _cell(arr, u, v)
    if not inside:
        return False
    for j in range(iv - 1, iv + 3):
        for i in range(iu - 1, iu + 3):
            if not ok[j, i]:
                return False
    _interp_at(arr, iu, iv, u, v, out)
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _cell(arr, u, v):
    """(inside, ⌊u⌋, ⌊v⌋): whether the 4 × 4 neighbourhood of the cubic convolution at pixel
    (u, v) lies inside ``arr`` (H, W, …), and its cell."""
    H = arr.shape[0]
    W = arr.shape[1]
    if not (u >= 1.0 and v >= 1.0 and u < W - 2.0 and v < H - 2.0):
        return False, 0, 0
    return True, int(np.floor(u)), int(np.floor(v))


@numba.njit(cache=True, nogil=True, inline="always")
def _interp_at(arr, iu, iv, u, v, out):
    """The cubic convolution of :func:`_interp` at (u, v) from the 4 × 4 samples around
    (iu, iv) = (⌊u⌋, ⌊v⌋), which the caller checked."""
    wu = _keys(u - iu)
    wv = _keys(v - iv)
    C = arr.shape[2]
    for c in range(C):
        s = 0.0
        for a in range(4):
            row = 0.0
            for b in range(4):
                row += wu[b] * arr[iv - 1 + a, iu - 1 + b, c]
            s += wv[a] * row
        out[c] = s


@numba.njit(cache=True, nogil=True)
def _residual(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, out):
    """r(z) = g_A − g_B at height z on A's view ray (d) with A's screen point q; partner B
    (centre oB, screen points qB (H, W, 3) registered where okB, T_cam_ref = RB, tB, intrinsics
    camB). Writes r to out[0:2], g_A to out[2:4], g_B to out[4:6]. Returns ok."""
    t = (z - oA[2]) / dz
    px = oA[0] + t * dx
    py = oA[1] + t * dy
    ok, u, v = _project(RB, tB, camB, px, py, z)
    if not ok:
        return False
    if not _interp(qB, okB, u, v, buf):
        return False
    gax, gay = _bisector_slopes(px, py, z, oA[0], oA[1], oA[2], qx, qy, qz)
    gbx, gby = _bisector_slopes(px, py, z, oB[0], oB[1], oB[2], buf[0], buf[1], buf[2])
    out[0] = gax - gbx
    out[1] = gay - gby
    out[2] = gax
    out[3] = gay
    out[4] = gbx
    out[5] = gby
    return np.isfinite(out[0]) and np.isfinite(out[1])


@numba.njit(cache=True, nogil=True, inline="always")
def _residual_jacobian(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, r0, r1, r2):
    """r(z) into r0 (as :func:`_residual`; ``buf`` then holds the partner's q_B at z) and
    J = ∂r/∂z by a central difference of step :data:`_FD_STEP_MM` (r1, r2: work). Returns
    (ok, J_x, J_y). The one derivative of the search's Gauss–Newton and of the anchors' σ."""
    h = _FD_STEP_MM
    if not (_residual(oA, dx, dy, dz, qx, qy, qz, z + h, oB, qB, okB, RB, tB, camB, buf, r1)
            and _residual(oA, dx, dy, dz, qx, qy, qz, z - h, oB, qB, okB, RB, tB, camB, buf, r2)
            and _residual(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, r0)):
        return False, 0.0, 0.0
    return True, (r1[0] - r2[0]) / (2.0 * h), (r1[1] - r2[1]) / (2.0 * h)


@numba.njit(cache=True, nogil=True)
def _refine(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, r0, r1, r2, step_max):
    """Gauss–Newton on the 2-vector r(z) from z (central-difference derivative). Returns
    (ok, z, |r|)."""
    for _ in range(_GN_MAX_ITER):
        ok, jx, jy = _residual_jacobian(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, r0, r1, r2)
        if not ok:
            return False, z, np.inf
        jj = jx * jx + jy * jy
        if not jj > 0.0:
            return False, z, np.inf
        delta = -(jx * r0[0] + jy * r0[1]) / jj
        if delta > step_max:
            delta = step_max
        elif delta < -step_max:
            delta = -step_max
        z += delta
        if abs(delta) < _GN_TOL_MM:
            break
    if not _residual(oA, dx, dy, dz, qx, qy, qz, z, oB, qB, okB, RB, tB, camB, buf, r0):
        return False, z, np.inf
    return True, z, np.sqrt(r0[0] * r0[0] + r0[1] * r0[1])


@numba.njit(cache=True, nogil=True, parallel=True)
def _search_kernel(oA, d, q, rows, cols, oB, qB, okB, RB, tB, camB, z_lo, step, n_steps, out_z, out_r, out_n):
    """Normal-consistency search (module docstring, step 1) for the pixels (rows[k], cols[k]).
    out_z: height (NaN if none), out_r: |r| at it (rad), out_n: number of distinct refined
    minima with |r| ≤ max(2·best, best + 20 µrad)."""
    n = rows.size
    for k in numba.prange(0, n):
        v = rows[k]
        u = cols[k]
        dx = d[v, u, 0]
        dy = d[v, u, 1]
        dz = d[v, u, 2]
        qx = q[v, u, 0]
        qy = q[v, u, 1]
        qz = q[v, u, 2]
        buf = np.empty(3)
        r0 = np.empty(6)
        r1 = np.empty(6)
        r2 = np.empty(6)
        f = np.full(n_steps, np.inf)
        for i in range(n_steps):
            if _residual(oA, dx, dy, dz, qx, qy, qz, z_lo + i * step, oB, qB, okB, RB, tB, camB, buf, r0):
                f[i] = r0[0] * r0[0] + r0[1] * r0[1]
        # Local minima of |r|² along the scan (a plateau's first sample), refined.
        zs = np.full(8, np.nan)
        rs = np.full(8, np.inf)
        m = 0
        for i in range(n_steps):
            if not np.isfinite(f[i]):
                continue
            left = f[i - 1] if i > 0 else np.inf
            right = f[i + 1] if i + 1 < n_steps else np.inf
            if f[i] < left and f[i] <= right:
                ok, zz, rr = _refine(oA, dx, dy, dz, qx, qy, qz, z_lo + i * step, oB, qB, okB, RB, tB, camB,
                                     buf, r0, r1, r2, step)
                if ok and z_lo <= zz <= z_lo + (n_steps - 1) * step:  # roots outside the range do not count
                    if m < 8:
                        zs[m] = zz
                        rs[m] = rr
                        m += 1
                    else:  # keep the 8 best
                        worst = 0
                        for j in range(8):
                            if rs[j] > rs[worst]:
                                worst = j
                        if rr < rs[worst]:
                            zs[worst] = zz
                            rs[worst] = rr
        best = -1
        for j in range(m):
            if best < 0 or rs[j] < rs[best]:
                best = j
        if best < 0:
            out_z[k] = np.nan
            out_r[k] = np.nan
            out_n[k] = 0
            continue
        out_z[k] = zs[best]
        out_r[k] = rs[best]
        cnt = 1
        lim = max(2.0 * rs[best], rs[best] + 20e-6)
        for j in range(m):
            if j != best and rs[j] <= lim and abs(zs[j] - zs[best]) > 10.0 * step:
                cnt += 1
        out_n[k] = cnt


@numba.njit(cache=True, nogil=True, parallel=True)
def _refine_kernel(oA, d, q, rows, cols, z0, oB, qB, okB, RB, tB, camB, step_max, out_z, out_r):
    """Gauss–Newton (:func:`_refine`) of the heights on A's rays through the pixels (rows[k],
    cols[k]) from z0[k] with partner B; out_z NaN and out_r inf where it fails."""
    for k in numba.prange(0, rows.size):
        v = rows[k]
        u = cols[k]
        buf = np.empty(3)
        r0 = np.empty(6)
        r1 = np.empty(6)
        r2 = np.empty(6)
        ok, z, r = _refine(oA, d[v, u, 0], d[v, u, 1], d[v, u, 2], q[v, u, 0], q[v, u, 1], q[v, u, 2], z0[k], oB,
                           qB, okB, RB, tB, camB, buf, r0, r1, r2, step_max)
        out_z[k] = z if ok else np.nan
        out_r[k] = r if ok else np.inf


# ============================================================================ data
@dataclass(frozen=True, eq=False)
class StereoView:
    """One calibrated camera's data for stereo: its intrinsic model, its pose in the
    reconstruction frame and its registration (view rays and screen points in that frame)."""

    camera: Camera
    T_ref_cam: RigidTransform
    registration: Registration


@dataclass(frozen=True, eq=False)
class StereoCamera:
    """One camera's result of :func:`reconstruct_stereo` (reconstruction frame, mm).

    Attributes
    ----------
    reconstruction : Reconstruction
        The anchored least-squares reconstruction (``method`` = ``"stereo"``); ``seed_pixel``
        is the anchor nearest the anchors' centroid (its height is *not* fixed).
    overlap : ndarray of bool (H, W)
        Reconstructed pixels whose point a partner camera sees (the report is defined there).
    normal_disagreement_urad : ndarray (H, W)
        Angle between this camera's and the partner's implied normals at the reconstructed
        point, µrad; NaN outside ``overlap``. With several partners: the largest.
    height_discrepancy_um : ndarray (H, W)
        z_this − z_partner along this camera's view ray (partner's reconstruction), µm; NaN
        where the partner has no height there. With several partners: the largest in magnitude.
    anchor_pixels : ndarray of int (n, 2)
        (row, column) of the anchors found along this camera's rays.
    anchor_height_mm : ndarray (n,)
        Their absolute heights from normal consistency.
    anchor_residual_urad : ndarray (n,)
        |g_this − g_partner| at each anchor (slope units, µrad).
    anchor_fit_um : ndarray (n,)
        Reconstructed minus anchor height at the anchors, µm.
    searched : int
        Sparse pixels searched; ``ambiguous``: those with more than one consistent height.
    uncertainty : SurfaceUncertainty or None
        Per-pixel standard uncertainties (k = 1, absolute) of heights and slopes
        (:mod:`pmdsim.evaluation.uncertainty_stereo`); None when not computed.
    anchor_height_std_um : ndarray (n,) or None
        Standard uncertainty of each anchor height, µm (None when not computed).
    """

    __repr__ = compact_repr  # one line: arrays by shape and dtype (issue 23)

    reconstruction: Reconstruction
    overlap: np.ndarray
    normal_disagreement_urad: np.ndarray
    height_discrepancy_um: np.ndarray
    anchor_pixels: np.ndarray
    anchor_height_mm: np.ndarray
    anchor_residual_urad: np.ndarray
    anchor_fit_um: np.ndarray
    searched: int
    ambiguous: int
    uncertainty: object = None
    anchor_height_std_um: np.ndarray | None = None

    @property
    def height_mm(self) -> np.ndarray:
        return self.reconstruction.height_mm

    @property
    def reconstructed(self) -> np.ndarray:
        return self.reconstruction.reconstructed


@dataclass(frozen=True, eq=False)
class StereoReconstruction:
    """Result of :func:`reconstruct_stereo`: per camera a :class:`StereoCamera`, and the
    search settings used."""

    __repr__ = compact_repr  # one line: arrays by shape and dtype (issue 23)

    cameras: dict
    search_range_mm: tuple[float, float]
    search_step_mm: float
    stride_px: int
    timings_s: dict = None  # seconds of the stages: "search", "integration", "report" (wall), "…_cpu" (CPU, all threads)

    def summary(self) -> dict:
        """Per camera: anchors, overlap pixels, median/max normal disagreement (µrad) and
        median/max |height discrepancy| (µm) over the overlap (JSON-ready)."""
        out = {}
        for name, c in self.cameras.items():
            ang = c.normal_disagreement_urad[np.isfinite(c.normal_disagreement_urad)]
            dz = np.abs(c.height_discrepancy_um[np.isfinite(c.height_discrepancy_um)])
            out[name] = {
                "anchors": int(c.anchor_height_mm.size), "searched": int(c.searched), "ambiguous": int(c.ambiguous),
                "reconstructed": int(c.reconstructed.sum()), "overlap": int(c.overlap.sum()),
                "normal_disagreement_median_urad": float(np.median(ang)) if ang.size else float("nan"),
                "normal_disagreement_max_urad": float(np.max(ang)) if ang.size else float("nan"),
                "height_discrepancy_median_um": float(np.median(dz)) if dz.size else float("nan"),
                "height_discrepancy_max_um": float(np.max(dz)) if dz.size else float("nan"),
                "converged": bool(c.reconstruction.converged),
            }
        return out


def _camera_arrays(view: StereoView):
    T_cam_ref = view.T_ref_cam.inv()
    c = view.camera
    cam = np.array([c.fx_px, c.fy_px, c.ppx_px, c.ppy_px, c.k1, c.k2, c.k3, c.p1, c.p2], dtype=np.float64)
    return (np.ascontiguousarray(T_cam_ref.rotation, dtype=np.float64),
            np.ascontiguousarray(T_cam_ref.translation, dtype=np.float64), cam)


def _view_arrays(view: StereoView):
    reg = view.registration
    o, d, q, valid = _check_inputs(reg.o_ref_mm, reg.d_ref, reg.q_ref_mm, reg.valid)
    q_filled = np.where(valid[..., None], q, 0.0)
    return o, d, np.ascontiguousarray(q_filled), valid


def _partners(arrays: dict, cams: dict, name: str):
    """Every camera but ``name`` as a partner: (partner, o, q, valid, R, t, intrinsics) from
    ``arrays`` (:func:`_view_arrays`) and ``cams`` (:func:`_camera_arrays`)."""
    for partner, (oB, _, qB, okB) in arrays.items():
        if partner != name:
            yield (partner, oB, qB, okB, *cams[partner])


def stereo_residual(views: dict, camera: str, partner: str, pixel, z_mm):
    """The normal-consistency residual r(z) = g_camera − g_partner (slopes, 2-vector) at heights
    ``z_mm`` (array) on ``camera``'s view ray through ``pixel`` (row, column); NaN where the
    partner does not see the point. For plots and checks of the criterion."""
    o, d, q, valid = _view_arrays(views[camera])
    oB, _, qB, okB = _view_arrays(views[partner])
    RB, tB, camB = _camera_arrays(views[partner])
    v, u = pixel
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    out = np.full(z.shape + (2,), np.nan)
    buf = np.empty(3)
    r = np.empty(6)
    for i, zz in enumerate(z.ravel()):
        if valid[v, u] and _residual(o, d[v, u, 0], d[v, u, 1], d[v, u, 2], q[v, u, 0], q[v, u, 1], q[v, u, 2],
                                     float(zz), oB, qB, okB, RB, tB, camB, buf, r):
            out.reshape(-1, 2)[i] = r[:2]
    return out


def refine_anchors(views: dict, camera: str, pixels_vu, z_mm, partners=None):
    """The normal-consistency heights on ``camera``'s rays through ``pixels_vu`` (n, 2) refined
    by the search's Gauss–Newton from ``z_mm`` (n,) (step at most :data:`DEFAULT_SEARCH_STEP_MM`).

    ``partners`` (n,) of int, optional: each pixel's partner (index into ``views``); default the
    partner whose refined root has the smallest |r|. Returns (z (n,) NaN where it fails, |r|
    (n,) rad, partners (n,) int, −1 where none)."""
    names = list(views)
    o, d, q, _ = _view_arrays(views[camera])
    px = np.asarray(pixels_vu, dtype=np.int64).reshape(-1, 2)
    rows, cols = np.ascontiguousarray(px[:, 0]), np.ascontiguousarray(px[:, 1])
    z0 = np.ascontiguousarray(z_mm, dtype=np.float64)
    best_z, best_r = np.full(rows.size, np.nan), np.full(rows.size, np.inf)
    best_p = np.full(rows.size, -1, dtype=np.int64)
    for j, partner in enumerate(names):
        if partner == camera or (partners is not None and not np.any(np.asarray(partners) == j)):
            continue
        oB, _, qB, okB = _view_arrays(views[partner])
        RB, tB, camB = _camera_arrays(views[partner])
        z, r = np.empty(rows.size), np.empty(rows.size)
        _refine_kernel(o, d, q, rows, cols, z0, oB, qB, okB, RB, tB, camB, DEFAULT_SEARCH_STEP_MM, z, r)
        take = (r < best_r) if partners is None else (np.asarray(partners) == j)
        best_z[take], best_r[take], best_p[take] = z[take], r[take], j
    return best_z, best_r, np.where(np.isfinite(best_z), best_p, -1)


def stereo_views(model, decoded: dict, *, screen_model=None) -> dict:
    """Every camera's :class:`StereoView`: its decoded screen coordinates registered with
    ``model`` (cameras, screen pose) in the model's sample frame, as :func:`evaluate_stereo_decoded`
    does (``screen_model`` None: the plane z = 0 of the screen frame over its grid)."""
    from ..geometry.surface import SplineSurface
    from .registration import register

    if screen_model is None:
        scr = model.screen
        screen_model = SplineSurface(scr.grid_x_mm, scr.grid_y_mm, np.zeros((len(scr.grid_y_mm), len(scr.grid_x_mm))))
    unknown = [c for c in decoded if c not in model.cameras]
    if unknown:
        raise ReconstructionError(f"camera(s) {unknown} are not in the setup (cameras: {list(model.cameras)})")
    T_world_ref = model.sample.T_world_sample
    T_ref_world = T_world_ref.inv()
    views = {}
    for cam, dec in decoded.items():
        cs = model.cameras[cam]
        reg = register(cs.camera, cs.T_world_cam, screen_model, model.screen.T_world_screen, dec.screen_xy_mm,
                       dec.valid, T_world_ref)
        views[cam] = StereoView(cs.camera, T_ref_world @ cs.T_world_cam, reg)
    return views


# ============================================================================ integration
def _anchor_level(z, anchors_vu, anchors_z):
    """The level c minimising Σ (z_i + c − a_i)² over the anchors (equal weights: the mean misfit
    a_i − z_i) for heights z (H, W), anchors at ``anchors_vu`` (n, 2) with heights ``anchors_z`` (n,)."""
    return float(np.mean(anchors_z - z[anchors_vu[:, 0], anchors_vu[:, 1]]))


def _integrate_anchored(o, d, q, valid, anchors_vu, anchors_z, tol_mm, max_iter, fields=None):
    """Zonal least-squares integration (:func:`~pmdsim.evaluation.least_squares.reconstruct_least_squares`'s
    equations) of the valid pixels' components that hold an anchor, gauged by the anchor
    equations (weight :data:`ANCHOR_WEIGHT`) instead of a fixed seed. ``fields`` (a
    :class:`~pmdsim.evaluation.least_squares._Fields` of at least (H + 2)(W + 2) elements): the
    work arrays of the start and of the iteration, reused (by the cameras of one reconstruction:
    no page faults of fresh arrays); a new one if not given. Returns
    (z (H, W), S, seed, iterations, converged, last change).

    The start is :func:`~pmdsim.evaluation.least_squares._start_heights` from the anchor nearest
    the anchors' centre, shifted to the anchors' level (:func:`_anchor_level`; the seed anchor
    alone is off by its own error, 0.34 mm on Table 1 with the unmodelled 3 mm bulge, and the
    first update would be that level: a larger second-order remainder and one more Gauss–Newton
    iteration). Only the level: the slopes, not the anchors, set the tilt (a tilt fitted to the
    anchors' misfits is 8× too large there and costs an iteration). On a single component that
    fills the frame (:func:`~pmdsim.evaluation.poisson.prefers_dct`) the updates are solved by
    CG with the DCT preconditioner and an exact level (:mod:`pmdsim.evaluation.stereo_solve`),
    otherwise by the multigrid-preconditioned CG; the first update only to the relative
    accuracy :data:`~pmdsim.evaluation.least_squares._INNER_RTOL` (it is ≈ 0.1 mm, and the next
    update, solved to ``tol_mm``/10, removes its error with the second-order remainder), and it
    never decides convergence."""
    labels, _ = ndimage.label(valid)
    lab = labels[anchors_vu[:, 0], anchors_vu[:, 1]]
    held = np.unique(lab[lab > 0])
    S = np.ascontiguousarray(np.isin(labels, held))
    cv, cu = anchors_vu.mean(axis=0)
    k = int(np.argmin((anchors_vu[:, 0] - cv) ** 2 + (anchors_vu[:, 1] - cu) ** 2))
    seed = (int(anchors_vu[k, 0]), int(anchors_vu[k, 1]))
    H, W = S.shape
    if fields is None:
        fields = _Fields((H + 2) * (W + 2))
    fields.reset()
    z = _start_heights(o, d, q, S, seed, float(anchors_z[k]), tol_mm, max_iter, fields)
    z += _anchor_level(z, anchors_vu, anchors_z)
    fields.reset()  # the start's arrays are dead: the iteration's are carved from the same buffers
    D, iD, Ex, Ey, rhs = (fields.zeros((H + 2, W + 2)) for _ in range(5))
    lap = None
    if held.size == 1 and poisson.prefers_dct(np.count_nonzero(S), S.shape):
        lap = poisson.DCTLaplacian(S.shape, seed, dtype=np.float32)
        work = poisson._DCTWork(1, D.shape, zeros=fields.zeros)
    else:
        work = _CGWork(D.shape, zeros=fields.zeros)
    av = anchors_vu[:, 0] + 1
    au = anchors_vu[:, 1] + 1
    w2 = ANCHOR_WEIGHT ** 2
    converged, change, it = False, np.inf, 0
    for it in range(1, max_iter + 1):
        _assemble_gauss_newton(o, d, q, S, z, -1, -1, D, iD, Ex, Ey, rhs)
        np.add.at(D, (av, au), w2)
        np.add.at(rhs, (av, au), w2 * (anchors_z - z[anchors_vu[:, 0], anchors_vu[:, 1]]))
        iD[av, au] = 1.0 / D[av, au]
        loose = it == 1 and max_iter > 1  # the first update: relative accuracy only
        cap = np.inf if loose else _INNER_CAP * tol_mm
        if lap is not None:
            delta, _, solved = level_dct_pcg(D, Ex, Ey, rhs, 0.01 * tol_mm, _INNER_RTOL, _INNER_MAX_ITER, cap=cap,
                                             lap=lap, work=work)
        else:
            delta, _, solved = _pcg(D, iD, Ex, Ey, rhs, 0.01 * tol_mm, _INNER_RTOL, _INNER_MAX_ITER, cap=cap, work=work)
        change = _apply_update(z, delta, D)
        if not np.isfinite(change):
            raise ReconstructionError("the anchored least-squares integration diverged (non-finite heights); "
                                      "check that the registrations and camera poses belong together")
        if change < tol_mm and solved and not loose:
            converged = True
            break
    return z, S, seed, it, converged, change


def warm_up() -> np.ndarray:
    """Run the anchored integration once on a small synthetic full frame (the flat mirror z = 0
    seen from 500 mm, 320 × 320 pixels, anchors at height 0: the DCT path with a coarse-to-fine
    start): loads the numba kernels of the integration and of its start from the cache (≈ 0.5 s
    on this machine), so that ``pmdsim evaluate --stereo`` does it in a background thread while
    the images are decoded instead of in its first camera's integration. Returns the heights
    (320, 320) (0 up to round-off)."""
    n = 320
    o = np.array([0.0, 0.0, 500.0])
    v, u = np.mgrid[0:n, 0:n].astype(np.float64)
    p = np.stack([(u - n / 2) * 0.1, (v - n / 2) * 0.1, np.zeros_like(u)], axis=-1)
    d = p - o
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    q = p + d * np.array([1.0, 1.0, -1.0]) * (300.0 / -d[..., 2:3])  # reflected to the plane z = 300 mm
    vu = np.stack(np.mgrid[8:n:16, 8:n:16], axis=-1).reshape(-1, 2)
    z, S, *_ = _integrate_anchored(o, np.ascontiguousarray(d), np.ascontiguousarray(q), np.ones((n, n), dtype=bool),
                                   vu, np.zeros(len(vu)), 1e-9, 20)
    _points_and_normals(o, d, q, np.where(S, z, np.nan))
    return z


# ============================================================================ main
def reconstruct_stereo(views: dict, *, search_range_mm=DEFAULT_SEARCH_RANGE_MM,
                       search_step_mm: float = DEFAULT_SEARCH_STEP_MM, stride_px: int | None = None,
                       max_iter: int = 20, tol_mm: float = 1e-9, on_reconstruction=None) -> StereoReconstruction:
    """Absolute surface from two or more calibrated cameras, without a seed (module docstring).

    Parameters
    ----------
    views : dict name → StereoView
        At least two cameras, all registered in the same reconstruction frame.
    search_range_mm : (float, float)
        Heights (reconstruction frame, mm) searched along the view rays; the surface must lie
        inside in the overlap.
    search_step_mm : float
        Scan step (mm); refined roots closer than 10 steps count as one.
    stride_px : int, optional
        Every stride-th pixel (rows and columns) is searched; default so that about
        :data:`DEFAULT_ANCHORS` pixels of each camera are.
    max_iter, tol_mm
        Gauss–Newton iterations and tolerance of the anchored integration
        (as :func:`~pmdsim.evaluation.least_squares.reconstruct_least_squares`).
    on_reconstruction : callable, optional
        Called as ``on_reconstruction(name, reconstruction)`` (a
        :class:`~pmdsim.evaluation.integration.Reconstruction`, the one the result holds) as soon
        as each camera's integration ends, in camera order, before the next camera integrates
        and before the agreement report (e.g. to write the camera's maps meanwhile).

    Returns
    -------
    StereoReconstruction

    Raises
    ------
    ReconstructionError
        Fewer than two cameras, a bad search range, or a camera with no anchor (no overlap or
        no consistent height in the range) — the message names the camera.
    """
    if len(views) < 2:
        raise ReconstructionError(f"stereo needs at least two cameras, got {len(views)} ({list(views)})")
    lo, hi = (float(v) for v in search_range_mm)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ReconstructionError(f"search_range_mm must be an increasing pair of finite heights, got {search_range_mm!r}")
    step = float(search_step_mm)
    if not (np.isfinite(step) and 0 < step <= hi - lo):
        raise ReconstructionError(f"search_step_mm must be in (0, {hi - lo:g}] mm, got {search_step_mm!r}")
    n_steps = int(np.floor((hi - lo) / step)) + 1
    if isinstance(max_iter, (bool, np.bool_)) or int(max_iter) != max_iter or max_iter < 1:
        raise ReconstructionError(f"max_iter must be an integer ≥ 1, got {max_iter!r}")
    if not (np.isfinite(tol_mm) and tol_mm > 0):
        raise ReconstructionError(f"tol_mm must be a positive, finite number of mm, got {tol_mm!r}")
    max_iter, tol_mm = int(max_iter), float(tol_mm)
    arrays = {}
    for n, v in views.items():
        try:
            arrays[n] = _view_arrays(v)
        except ReconstructionError as e:
            raise ReconstructionError(f"camera {n!r}: {e}") from None
    cams = {n: _camera_arrays(v) for n, v in views.items()}
    if stride_px is None:
        n_valid = min(int(a[3].sum()) for a in arrays.values())
        stride_px = max(1, int(round(np.sqrt(max(n_valid, 1) / DEFAULT_ANCHORS))))
    stride = int(stride_px)
    if stride < 1:
        raise ReconstructionError(f"stride_px must be an integer ≥ 1, got {stride_px!r}")

    # 1. anchors along each camera's rays, each partner in turn
    timings = {}
    t0, c0 = time.perf_counter(), time.process_time()
    anchors = {}
    for name, (o, d, q, valid) in arrays.items():
        H, W = valid.shape
        sub = np.zeros_like(valid)
        sub[stride // 2::stride, stride // 2::stride] = True
        rows, cols = np.nonzero(valid & sub)
        best_z = np.full(rows.size, np.nan)
        best_r = np.full(rows.size, np.inf)
        amb = np.zeros(rows.size, dtype=bool)
        for _, oB, qB, okB, RB, tB, camB in _partners(arrays, cams, name):
            z = np.empty(rows.size)
            r = np.empty(rows.size)
            cnt = np.empty(rows.size, dtype=np.int64)
            _search_kernel(o, d, q, rows.astype(np.int64), cols.astype(np.int64), oB, qB, okB, RB, tB, camB,
                           lo, step, n_steps, z, r, cnt)
            better = np.isfinite(z) & (r < best_r)
            best_z[better], best_r[better] = z[better], r[better]
            amb |= cnt > 1
        keep = np.isfinite(best_z) & ~amb
        if not keep.any():
            raise ReconstructionError(
                f"camera {name!r}: no pixel has a unique consistent height in {lo:g} … {hi:g} mm (searched "
                f"{rows.size} pixels, {int(amb.sum())} ambiguous): the cameras' fields of view do not overlap on the "
                f"surface, or the surface is outside search_range_mm")
        anchors[name] = (np.stack([rows[keep], cols[keep]], axis=-1), best_z[keep], best_r[keep], rows.size,
                         int(amb.sum()))

    # 2. anchored integration of each camera's slopes
    t1, c1 = time.perf_counter(), time.process_time()
    timings["search"], timings["search_cpu"] = t1 - t0, c1 - c0
    recs = {}
    fields = _Fields(max((a[3].shape[0] + 2) * (a[3].shape[1] + 2) for a in arrays.values()))  # shared work arrays
    for name, (o, d, q, valid) in arrays.items():
        vu, az, ar, _, _ = anchors[name]
        z, S, seed, it, conv, change = _integrate_anchored(o, d, q, valid, vu, az, tol_mm, max_iter, fields)
        recon = S & np.isfinite(z)
        z = np.where(recon, z, np.nan)
        pts, nrm = _points_and_normals(o, d, q, z)
        recs[name] = Reconstruction(z, pts, nrm, recon, "stereo", int(it), bool(conv), seed, float(change))
        if on_reconstruction is not None:
            on_reconstruction(name, recs[name])
    del fields  # the integration's work arrays (≈ 0.2 GB at 1920 × 1200): freed before the report

    # 3. agreement report
    t2, c2 = time.perf_counter(), time.process_time()
    timings["integration"], timings["integration_cpu"] = t2 - t1, c2 - c1
    from .stereo_report import agreement  # here: it imports this module's kernels

    report = agreement(arrays, cams, {n: r.height_mm for n, r in recs.items()})
    out = {}
    for name in arrays:
        zA = recs[name].height_mm
        ang, dzm = report[name]
        vu, az, ar, searched, n_amb = anchors[name]
        fit = (zA[vu[:, 0], vu[:, 1]] - az) * 1e3
        out[name] = StereoCamera(recs[name], np.isfinite(ang), ang * 1e6, dzm * 1e3, vu, az, ar * 1e6, fit,
                                 searched, n_amb)
    timings["report"], timings["report_cpu"] = time.perf_counter() - t2, time.process_time() - c2
    return StereoReconstruction(out, (lo, hi), step, stride, timings)


def evaluate_stereo_decoded(model, decoded: dict, *, screen_model=None, **options) -> tuple[dict, StereoReconstruction]:
    """Register every camera's decoded screen coordinates with ``model`` (a
    :class:`~pmdsim.setup.Setup`: cameras, screen pose; heights in its sample frame), then
    :func:`reconstruct_stereo`. ``screen_model`` defaults to the plane z = 0 of the screen frame
    over the model's screen grid (the paper's planar-screen assumption); pass
    ``model.screen.surface`` for a calibrated free-form screen. Returns (views, result)."""
    views = stereo_views(model, decoded, screen_model=screen_model)
    return views, reconstruct_stereo(views, **options)
