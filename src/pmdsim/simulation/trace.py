"""Ray tracing: camera pixel → sample → screen (paper §2.4).

For every pixel the view ray (paper §2.2) is intersected with the sample surface (eqs. 9–16),
reflected (eq. 17) and intersected with the screen surface; the result is the pixel → pattern
coordinate mapping (x_q, y_q) in mm of the screen frame, with a status code per pixel
(:class:`Status`, docs/conventions.md "Validity codes"). The mapping is computed once per
camera and reused for a whole pattern sequence.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numba
import numpy as np

from ..geometry.camera import Camera
from ..geometry.cover_glass import CoverGlass
from ..geometry.kernel_args import readonly
from ..geometry.surface import FIXED_POINT_MAX_ITER, INTERSECT_TOL_MM
from ..geometry.transform import RigidTransform
from .glass_rows import glass_band_rows
from .glass_switch import glass_pixel_if
from .trace_rows import _BLK, _NF, _NI, intersect_ray, trace_row
from ..geometry.compact import compact_repr

__all__ = ["Status", "Mapping", "trace_rays", "trace_camera"]


class Status(enum.IntEnum):
    """Per-pixel status of the tracer (docs/conventions.md, "Validity codes")."""

    VALID = 0
    UNDISTORT_FAILED = 1
    SAMPLE_PARALLEL = 2
    SAMPLE_OUTSIDE = 3
    SAMPLE_NO_CONVERGENCE = 4
    SCREEN_PARALLEL = 5
    SCREEN_OUTSIDE = 6
    SCREEN_NO_CONVERGENCE = 7
    SAMPLE_GRAZING = 8

    @property
    def description(self) -> str:
        return _DESCRIPTIONS[self]


_DESCRIPTIONS = {
    Status.VALID: "the pixel sees the screen via the sample",
    Status.UNDISTORT_FAILED: "the lens distortion could not be inverted for this pixel",
    Status.SAMPLE_PARALLEL: "the view ray is parallel to the sample plane or the sample is behind the camera",
    Status.SAMPLE_OUTSIDE: "the view ray meets the sample outside its grid bounds",
    Status.SAMPLE_NO_CONVERGENCE: "no intersection with the sample surface was found",
    Status.SCREEN_PARALLEL: "the reflected ray is parallel to the screen or points away from it",
    Status.SCREEN_OUTSIDE: "the reflected ray meets the screen outside its grid bounds",
    Status.SCREEN_NO_CONVERGENCE: "no intersection with the screen surface was found",
    Status.SAMPLE_GRAZING: "the view ray meets the sample at grazing incidence (more than MAX_INCIDENCE_DEG from "
                           "its normal) or from behind",
}

#: Largest angle of incidence on the sample (between the view ray and the surface normal) that
#: the tracer accepts; beyond it the pixel is SAMPLE_GRAZING (docs/conventions.md, "Curved samples").
MAX_INCIDENCE_DEG = 85.0
_COS_MAX_INCIDENCE = float(np.cos(np.radians(MAX_INCIDENCE_DEG)))

# Map intersection codes to tracer codes, per surface.
# (index 4 is the surface kernels' internal _NEEDS_SOLVE, never mapped; 5 is the tracer's grazing check)
_SAMPLE_CODES = np.array([Status.VALID, Status.SAMPLE_PARALLEL, Status.SAMPLE_OUTSIDE, Status.SAMPLE_NO_CONVERGENCE,
                          Status.SAMPLE_NO_CONVERGENCE, Status.SAMPLE_GRAZING], dtype=np.uint8)
_SCREEN_CODES = np.array([Status.VALID, Status.SCREEN_PARALLEL, Status.SCREEN_OUTSIDE, Status.SCREEN_NO_CONVERGENCE], dtype=np.uint8)


#: Image rows per band of the tracer (bands are traced in parallel; each row of a band after the
#: first is warm started from the rows above and traced by the vectorised row kernel,
#: :mod:`pmdsim.simulation.trace_rows`; the first row pixel by pixel). Fixed: the results depend
#: on it, not on threads. 32 (was 16): half as many pixel-by-pixel rows, still 38 bands for the
#: threads at 1200 rows.
_BAND_ROWS = 32


# _nrt=False: the function allocates nothing, and without numba's reference counting the
# arrays handed to the inlined surface kernels are not incref'd and decref'd on every pixel
# (atomic calls that also force register spills: ~40 % of the time). fastmath={"contract"}
# only lets LLVM fuse a·b + c into FMAs (one rounding instead of two); it assumes nothing
# about NaN or infinity, so the validity checks are unaffected.
@numba.njit(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})
def _trace_run(
    band, d_cam, ok, run_length, band_rows, z_rows, scratch, pscratch, r_sc, t_sc, r_ps, t_ps,
    s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
    p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
    tol, max_iter, sample_codes, screen_codes,
    screen_xy, status, p_sample, q_screen, store, glass_t, glass_n, with_glass,
):
    """Trace one band of ``band_rows`` runs of ``run_length`` rays (image rows).

    Each intersection is warm started from neighbouring pixels' heights (one Newton step,
    :func:`pmdsim.geometry.surface.intersect_kernel`); any pixel whose fast path does not
    converge is solved by :func:`pmdsim.geometry.surface.intersect_solve`.

    Warm starts: in the first row of a band from the pixels to the left (the first pixel of
    the row has none); in every further row from the **rows above**, extrapolated linearly
    (2·z[row − 1] − z[row − 2], else z[row − 1]), read from ``z_rows[band]`` (4, run_length):
    sample and screen heights of the previous two rows. Within such a row the pixels do not
    depend on each other, so the processor overlaps their computations instead of waiting for
    the left neighbour's result. Bands are independent and fixed by ``band_rows`` (not by the
    number of threads), so results do not depend on the thread count.

    With a cover glass (``glass_t`` > 0 mm, index ``glass_n``) every reflected ray is traced
    through it (:mod:`pmdsim.simulation.glass_rows`, warm started from the pixels two and
    three to the left in the first row of a band, from the rows above in the others:
    ``z_rows[band]`` has 14 rows then, the screen heights being those of the emitting-surface
    points seen through the glass; the glass's rows 4–13 are two slots per value, written
    alternately, the first row of a band in slot 0: :func:`.trace_rows._glass_rows_update`).
    ``with_glass`` is a boolean literal: the glass-free entry kernel :func:`_trace_kernel` passes
    ``False`` and does not compile the glass stage (:mod:`pmdsim.simulation.glass_switch`);
    :func:`_trace_kernel_glass` passes ``True``.
    """
    n = d_cam.shape[0]
    nan = np.nan
    # Ray origin: the pinhole, in the sample frame.
    ox = t_sc[0]
    oy = t_sc[1]
    oz = t_sc[2]
    # The transforms as local scalars: the compiler cannot hoist array loads past the stores
    # into the output arrays (it cannot prove they do not alias).
    a00, a01, a02 = r_sc[0, 0], r_sc[0, 1], r_sc[0, 2]
    a10, a11, a12 = r_sc[1, 0], r_sc[1, 1], r_sc[1, 2]
    a20, a21, a22 = r_sc[2, 0], r_sc[2, 1], r_sc[2, 2]
    b00, b01, b02 = r_ps[0, 0], r_ps[0, 1], r_ps[0, 2]
    b10, b11, b12 = r_ps[1, 0], r_ps[1, 1], r_ps[1, 2]
    b20, b21, b22 = r_ps[2, 0], r_ps[2, 1], r_ps[2, 2]
    c0, c1, c2 = t_ps[0], t_ps[1], t_ps[2]
    zr = z_rows[band]
    row0 = band * band_rows
    row_end = min(row0 + band_rows, (n + run_length - 1) // run_length)
    for row in range(row0, row_end):
        kb = np.uint64(row * run_length)
        above = row > row0  # not the first row of the band
        if above:
            # The pixels do not depend on each other: the vectorised row kernel.
            trace_row(
                kb, min(run_length, n - row * run_length), d_cam, ok, zr, scratch[band], pscratch[band],
                r_sc, t_sc, r_ps, t_ps, _COS_MAX_INCIDENCE * _COS_MAX_INCIDENCE,
                s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
                p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
                tol, max_iter, sample_codes, screen_codes,
                screen_xy, status, p_sample, q_screen, store, glass_t, glass_n, with_glass, (row - row0) % 2,
            )
            continue
        zs_prev = nan  # sample height of the previous pixel
        # Screen heights of the previous three pixels (NaN where not valid).
        zp1 = nan
        zp2 = nan
        zp3 = nan
        # With a glass: the outer-surface heights and plate normals of the previous three pixels.
        ga1 = nan
        ga2 = nan
        ga3 = nan
        gx1 = nan
        gx2 = nan
        gx3 = nan
        gy1 = nan
        gy2 = nan
        gy3 = nan
        for col in range(np.uint64(min(run_length, n - row * run_length))):  # unsigned: no wrap-around
            k = kb + col
            if above:
                zs_guess = 2.0 * zr[0, col] - zr[1, col]
                if not np.isfinite(zs_guess):
                    zs_guess = zr[0, col]
                zq_guess = 2.0 * zr[2, col] - zr[3, col]
                if not np.isfinite(zq_guess):
                    zq_guess = zr[2, col]
            else:
                zs_guess = zs_prev
                # The screen height extrapolated linearly from the pixels two and three back (not
                # from the previous one: two independent chains of dependent computations, which
                # the processor overlaps), else the previous one's.
                zq_guess = 3.0 * zp2 - 2.0 * zp3
                if not np.isfinite(zq_guess):
                    zq_guess = zp1
            qx = nan
            qy = nan
            qz = nan
            gaz = nan
            gmx = nan
            gmy = nan
            if store:
                for c in range(3):
                    p_sample[k, c] = nan
                    q_screen[k, c] = nan
            if not ok[k]:
                status[k] = 1  # UNDISTORT_FAILED
                zs_prev = nan
            else:
                a = d_cam[k, 0]
                b = d_cam[k, 1]
                c = d_cam[k, 2]
                # Direction in the sample frame.
                vx = a00 * a + a01 * b + a02 * c
                vy = a10 * a + a11 * b + a12 * c
                vz = a20 * a + a21 * b + a22 * c
                t, px, py, pz, hx, hy, st = intersect_ray(
                    s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax, ox, oy, oz, vx, vy, vz, tol, max_iter,
                    zs_guess, np.bool_(True)
                )
                # Grazing or back-side incidence: |v·n| ≤ cos(MAX_INCIDENCE_DEG)·|v||n|, n = (−h_x, −h_y, 1),
                # or v·n of the other sign than v_z (the ray meets the side of the height field it did not
                # start on).
                vn = vz - hx * vx - hy * vy
                if st == 0 and not (vn * vz > 0.0 and vn * vn > (_COS_MAX_INCIDENCE * _COS_MAX_INCIDENCE) * (
                        (vx * vx + vy * vy + vz * vz) * (hx * hx + hy * hy + 1.0))):
                    st = 5  # -> SAMPLE_GRAZING
                if st != 0:
                    status[k] = sample_codes[st]
                    zs_prev = nan
                else:
                    zs_prev = pz
                    # Reflection, eq. (17), with n = (−h_x, −h_y, 1).
                    nx = -hx
                    ny = -hy
                    f = 2.0 * (vx * nx + vy * ny + vz) / (nx * nx + ny * ny + 1.0)
                    rx = vx - f * nx
                    ry = vy - f * ny
                    rz = vz - f
                    # Origin and direction of the reflected ray in the screen frame.
                    qox = b00 * px + b01 * py + b02 * pz + c0
                    qoy = b10 * px + b11 * py + b12 * pz + c1
                    qoz = b20 * px + b21 * py + b22 * pz + c2
                    wx = b00 * rx + b01 * ry + b02 * rz
                    wy = b10 * rx + b11 * ry + b12 * rz
                    wz = b20 * rx + b21 * ry + b22 * rz
                    if glass_t > 0.0:
                        az_g = 3.0 * ga2 - 2.0 * ga3
                        mx_g = 3.0 * gx2 - 2.0 * gx3
                        my_g = 3.0 * gy2 - 2.0 * gy3
                        if not np.isfinite(az_g + mx_g + my_g):
                            az_g = ga1
                            mx_g = gx1
                            my_g = gy1
                        qx, qy, qz, st2, gaz, gmx, gmy = glass_pixel_if(
                            with_glass, p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax, glass_t, glass_n,
                            qox, qoy, qoz, wx, wy, wz, az_g, mx_g, my_g, zq_guess, tol, max_iter
                        )
                    else:
                        t2, qx, qy, qz, _sgx, _sgy, st2 = intersect_ray(
                            p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax, qox, qoy, qoz, wx, wy, wz, tol,
                            max_iter, zq_guess, np.bool_(False)
                        )
                    if store:
                        p_sample[k, 0] = px
                        p_sample[k, 1] = py
                        p_sample[k, 2] = pz
                    if st2 != 0:
                        status[k] = screen_codes[st2]
                        qx = nan
                        qy = nan
                        qz = nan
                        gaz = nan
                        gmx = nan
                        gmy = nan
                    else:
                        status[k] = 0
                        if store:
                            q_screen[k, 0] = qx
                            q_screen[k, 1] = qy
                            q_screen[k, 2] = qz
            screen_xy[k, 0] = qx
            screen_xy[k, 1] = qy
            zp3 = zp2
            zp2 = zp1
            zp1 = qz
            zr[1, col] = zr[0, col]  # row − 1 becomes row − 2
            zr[0, col] = zs_prev
            zr[3, col] = zr[2, col]
            zr[2, col] = qz
            if glass_t > 0.0:
                ga3 = ga2
                ga2 = ga1
                ga1 = gaz
                gx3 = gx2
                gx2 = gx1
                gx1 = gmx
                gy3 = gy2
                gy2 = gy1
                gy1 = gmy
                # The glass's rows are a ring of two slots per value (trace_rows._glass_rows_update):
                # the first row of a band writes slot 0; slot 1 (row − 2) is still NaN.
                zr[4, col] = gaz
                zr[6, col] = gmx
                zr[8, col] = gmy


@numba.njit(cache=True, parallel=True)
def _trace_kernel(
    d_cam, ok, run_length, band_rows, z_rows, scratch, pscratch, r_sc, t_sc, r_ps, t_ps,
    s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
    p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
    tol, max_iter, sample_codes, screen_codes,
    screen_xy, status, p_sample, q_screen, store, glass_t, glass_n,
):
    for band in numba.prange(0, z_rows.shape[0]):
        _trace_run(
            band, d_cam, ok, run_length, band_rows, z_rows, scratch, pscratch, r_sc, t_sc, r_ps, t_ps,
            s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
            p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
            tol, max_iter, sample_codes, screen_codes,
            screen_xy, status, p_sample, q_screen, store, glass_t, glass_n, False,
        )


# The same band loop as _trace_kernel, on purpose: the glass flag must be a literal constant at
# the call of _trace_run (simulation/glass_switch.py), so that the glass-free kernel neither types
# nor compiles the glass stage (docs/benchmarks.md, "The glass stage compiled only where used").
@numba.njit(cache=True, parallel=True)
def _trace_kernel_glass(
    d_cam, ok, run_length, band_rows, z_rows, scratch, pscratch, r_sc, t_sc, r_ps, t_ps,
    s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
    p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
    tol, max_iter, sample_codes, screen_codes,
    screen_xy, status, p_sample, q_screen, store, glass_t, glass_n,
):
    for band in numba.prange(0, z_rows.shape[0]):
        _trace_run(
            band, d_cam, ok, run_length, band_rows, z_rows, scratch, pscratch, r_sc, t_sc, r_ps, t_ps,
            s_kind, s_gx, s_gy, s_coef, s_zmin, s_zmax, s_dmax,
            p_kind, p_gx, p_gy, p_coef, p_zmin, p_zmax, p_dmax,
            tol, max_iter, sample_codes, screen_codes,
            screen_xy, status, p_sample, q_screen, store, glass_t, glass_n, True,
        )


@dataclass(frozen=True, eq=False)
class Mapping:
    """Result of tracing one camera: the pixel → pattern-coordinate mapping (paper §2.4).

    Attributes
    ----------
    screen_xy_mm : ndarray (H, W, 2)
        Pattern coordinates (x_q, y_q) in the screen frame, NaN where ``status != VALID``.
    status : ndarray of uint8 (H, W)
        :class:`Status` code per pixel.
    p_sample_mm : ndarray (H, W, 3) or None
        The sample intersection point (sample frame), if requested.
    q_screen_mm : ndarray (H, W, 3) or None
        The screen intersection point (screen frame, z = screen height), if requested.
    """

    __repr__ = compact_repr  # one line: arrays by shape and dtype (issue 23)

    screen_xy_mm: np.ndarray
    status: np.ndarray
    p_sample_mm: np.ndarray | None = None
    q_screen_mm: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: status == VALID."""
        return self.status == Status.VALID

    def status_counts(self) -> dict[str, int]:
        """Number of pixels per status name (only non-zero counts)."""
        counts = np.bincount(self.status.ravel(), minlength=len(Status))
        return {Status(i).name: int(c) for i, c in enumerate(counts) if c}


def trace_rays(
    d_cam: np.ndarray,
    converged: np.ndarray,
    T_sample_cam: RigidTransform,
    T_screen_sample: RigidTransform,
    sample,
    screen,
    *,
    store_points: bool = False,
    tol_mm: float = INTERSECT_TOL_MM,
    glass: CoverGlass | None = None,
) -> Mapping:
    """Trace view rays through sample and screen (paper §2.4).

    Parameters
    ----------
    d_cam : ndarray (..., 3)
        View-ray directions in the camera frame (rays start at the pinhole).
    converged : ndarray of bool (...)
        False where the view ray could not be computed (marked UNDISTORT_FAILED).
    T_sample_cam, T_screen_sample : RigidTransform
        Camera → sample and sample → screen transforms (eq. 1).
    sample, screen : SplineSurface or PlaneSurface
        Surfaces in their own frames.
    store_points : bool
        Also return the sample and screen intersection points.
    tol_mm : float
        Intersection convergence tolerance (mm).
    glass : CoverGlass, optional
        The screen's cover glass (docs/conventions.md, "Cover glass"). When present, every
        reflected ray is refracted through it and the mapping holds the point on the emitting
        surface that the ray reaches (:mod:`pmdsim.simulation.glass_rows`: a stage of the
        tracer, warm started from the neighbouring pixels); None or zero thickness: the
        glass-free trace, unchanged.

    Returns
    -------
    Mapping
        Arrays shaped like ``d_cam.shape[:-1]``.
    """
    d = np.asarray(d_cam, dtype=float)
    if d.shape[-1] != 3:
        raise ValueError(f"d_cam must have shape (..., 3), got {d.shape}")
    ok = np.asarray(converged, dtype=bool)
    if ok.shape != d.shape[:-1]:
        raise ValueError(f"converged must have shape {d.shape[:-1]}, got {ok.shape}")
    shape = d.shape[:-1]
    df = readonly(np.ascontiguousarray(d.reshape(-1, 3)))  # one compiled signature for every caller
    okf = readonly(np.ascontiguousarray(ok.reshape(-1)))
    n = df.shape[0]
    screen_xy = np.empty((n, 2))
    status = np.empty(n, dtype=np.uint8)
    with_glass = glass is not None and glass.present
    if store_points:
        p_s = np.empty((n, 3))
        q_p = np.empty((n, 3))
    else:
        p_s = np.empty((0, 3))
        q_p = np.empty((0, 3))
    s = sample.kernel
    p = screen.kernel
    run_length = max(int(shape[-1] if len(shape) >= 2 else min(max(n, 1), 1024)), 1)
    # Image rows are traced in bands of _BAND_ROWS, each row warm started from the rows above;
    # runs of a flat list of rays are not neighbours: one run per band (left neighbours only).
    band_rows = _BAND_ROWS if len(shape) >= 2 else 1
    n_runs = (n + run_length - 1) // run_length
    if with_glass and len(shape) >= 2:  # longer bands: fewer first rows, the costly ones with a glass
        band_rows = glass_band_rows(n_runs, band_rows)
    z_rows = np.full(((n_runs + band_rows - 1) // band_rows, 14 if with_glass else 4, run_length), np.nan)
    scratch = np.empty((z_rows.shape[0], _NF * _BLK))
    pscratch = np.empty((z_rows.shape[0], _NI * _BLK), dtype=np.int64)
    # Bands are handed to the threads one at a time: on a shared machine a thread that is
    # descheduled for a while does not hold up the others.
    old_chunksize = numba.set_parallel_chunksize(1)
    try:
        (_trace_kernel_glass if with_glass else _trace_kernel)(
            df, okf, run_length, band_rows, z_rows, scratch, pscratch,
            readonly(np.ascontiguousarray(T_sample_cam.rotation)),
            readonly(np.ascontiguousarray(T_sample_cam.translation)),
            readonly(np.ascontiguousarray(T_screen_sample.rotation)),
            readonly(np.ascontiguousarray(T_screen_sample.translation)),
            s.kind, s.grid_x, s.grid_y, s.coef, s.z_min, s.z_max, s.dmax,
            p.kind, p.grid_x, p.grid_y, p.coef, p.z_min, p.z_max, p.dmax,
            tol_mm, FIXED_POINT_MAX_ITER, _SAMPLE_CODES, _SCREEN_CODES,
            screen_xy, status, p_s, q_p, store_points,
            float(glass.thickness_mm) if with_glass else 0.0, float(glass.index) if with_glass else 1.5,
        )
    finally:
        numba.set_parallel_chunksize(old_chunksize)
    return Mapping(
        screen_xy.reshape(shape + (2,)),
        status.reshape(shape),
        p_s.reshape(shape + (3,)) if store_points else None,
        q_p.reshape(shape + (3,)) if store_points else None,
    )


def trace_camera(
    camera: Camera,
    T_world_cam: RigidTransform,
    T_world_sample: RigidTransform,
    sample,
    T_world_screen: RigidTransform,
    screen,
    *,
    store_points: bool = False,
    rays: tuple[np.ndarray, np.ndarray] | None = None,
    glass: CoverGlass | None = None,
) -> Mapping:
    """Trace every pixel of ``camera`` (H, W) through sample and screen (and the screen's cover
    ``glass``, if any: :func:`trace_rays`).

    ``rays`` may pass precomputed ``camera.sensor_rays()`` to reuse them across setups.
    """
    d_cam, ok = camera.sensor_rays() if rays is None else rays
    T_sample_cam = T_world_sample.inv() @ T_world_cam
    T_screen_sample = T_world_screen.inv() @ T_world_sample
    return trace_rays(d_cam, ok, T_sample_cam, T_screen_sample, sample, screen, store_points=store_points,
                      glass=glass)
