"""The screen's cover glass: a plate of thickness t and index n over the emitting surface.

Every LCD/OLED screen emits through a glass plate. pmdsim models it as a plate of thickness
``thickness_mm`` (t) and refractive index ``index`` (n) on the **sample side** of the emitting
surface (the surface that carries the pattern, :class:`~pmdsim.geometry.surface.SplineSurface`
z = h(x, y) of the screen frame, whose +z points away from the sample). The plate follows the
(possibly deformed) emitting surface: its outer surface is the emitting surface offset by t
along the local unit normal towards the sample, m(u) = (h_x, h_y, −1)/√(1 + h_x² + h_y²):

    A(u) = (u_x, u_y, h(u)) + t·m(u),

and the outer surface's normal at A(u) is m(u) (a property of offset surfaces). A ray coming
from the sample meets the outer surface at A, is refracted there (Snell's law in vector form,
air index 1), and travels inside the glass to the emitting surface, which it meets at Q: the
pattern point that the ray sees (docs/conventions.md, "Cover glass"). For a flat screen the
lateral shift of Q against the point that the unrefracted ray would meet is the plate shift
t·sinθ·(1 − cosθ/√(n² − sin²θ)) (θ the angle of incidence).

Kernels (numba, per ray): :func:`through_glass_kernel` (the forward trace: outer-surface hit,
refraction, emitting-surface hit, warm started from the unrefracted hit) and its vectorised
wrappers :meth:`CoverGlass.trace` and :meth:`CoverGlass.apparent_points` (the inverse problem of
registration: the straight line from a sample point that, refracted, reaches a given emitting
point).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .surface import (
    _NEEDS_SOLVE, FIXED_POINT_MAX_ITER, INTERSECT_TOL_MM, eval_kernel, intersect_kernel, intersect_solve,
)

__all__ = ["CoverGlass", "DEFAULT_GLASS_INDEX", "plate_shift_mm"]

#: The index used when a thickness is given without one (soda-lime/borosilicate ≈ 1.5).
DEFAULT_GLASS_INDEX = 1.5
#: Foot-point iterations of the outer-surface intersection (converges in 2–4 on real screens).
_FOOT_MAX_ITER = 30
#: Convergence of the foot point (mm).
_FOOT_TOL_MM = 1e-9
#: Newton steps of the emitting-surface hit before the safeguarded solver.
_NEWTON_STEPS = 4
#: Fixed-point iteration of the inverse problem (the error shrinks ≈ t/(n·distance) per step):
#: converged when the correction moves the exit point by less than this (mm), at most so many steps.
INVERSE_TOL_MM = 1e-9
INVERSE_MAX_ITER = 30


def plate_shift_mm(thickness_mm, index, theta_rad):
    """Lateral shift of the apparent point behind a flat plate (textbook plate shift).

    t·sinθ·(1 − cosθ/√(n² − sin²θ)), the displacement of the emerging ray parallel to the
    plate's surface. Shapes broadcast.
    """
    s = np.sin(theta_rad)
    return thickness_mm * s * (1.0 - np.cos(theta_rad) / np.sqrt(index * index - s * s))


# As the tracer's kernels (pmdsim.simulation.trace): inlined, no reference counting (the arrays
# handed to the surface kernels are not incref'd per ray), fastmath only for FMA contraction.
_JIT = dict(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})


@numba.njit(**_JIT, inline="always")
def through_glass_kernel(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, dx, dy, dz, x0, y0, z0,
                         tol, max_iter):
    """:func:`through_glass_full` without the outer-surface values: ``(x, y, z, status)``."""
    x, y, z, st, _az, _mx, _my = through_glass_full(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz,
                                                    dx, dy, dz, x0, y0, z0, tol, max_iter)
    return x, y, z, st


@numba.njit(**_JIT, inline="always")
def through_glass_full(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, ox, oy, oz, dx, dy, dz, x0, y0, z0,
                       tol, max_iter):
    """One ray o + s·d (screen frame, towards the screen) through the cover glass.

    ``(x0, y0, z0)``: the ray's hit of the bare emitting surface (the start of the foot-point
    iteration and the warm start of the final intersection). Returns ``(x, y, z, status, a_z,
    m_x, m_y)``: the point Q on the emitting surface, an
    :class:`~pmdsim.geometry.surface.IntersectStatus` code (1 PARALLEL where the ray does not
    enter the outer surface from the sample side, 3 NO_CONVERGENCE where the foot point does
    not converge), and the height of the outer-surface hit A and the plate normal m used there
    (the tracer's warm starts of the neighbouring pixels; NaN where the status is not 0).

    Outer-surface hit: with the foot point u, the outer surface is replaced by its tangent plane
    at A(u) (normal m(u)), the ray's point X on it is taken, and u ← (X − t·m(u))_xy, until u
    moves less than 1e-9 mm (Newton's method on the offset surface, whose tangent plane at
    A(u) has normal m(u)).
    """
    nan = np.nan
    ux = x0
    uy = y0
    mx = 0.0
    my = 0.0
    mz = -1.0
    ax = nan
    ay = nan
    az = nan
    converged = False
    for _ in range(_FOOT_MAX_ITER):
        h, hx, hy = eval_kernel(kind, gx, gy, coef, ux, uy)
        g = 1.0 / math.sqrt(1.0 + hx * hx + hy * hy)
        mx = hx * g
        my = hy * g
        mz = -g
        px = ux + t * mx
        py = uy + t * my
        pz = h + t * mz
        dm = dx * mx + dy * my + dz * mz
        if not dm < 0.0:  # the ray must meet the outer surface from the sample side
            return nan, nan, nan, 1, nan, nan, nan
        s = ((px - ox) * mx + (py - oy) * my + (pz - oz) * mz) / dm
        ax = ox + s * dx
        ay = oy + s * dy
        az = oz + s * dz
        nx = ax - t * mx
        ny = ay - t * my
        moved = abs(nx - ux) + abs(ny - uy)
        ux = nx
        uy = ny
        if moved <= _FOOT_TOL_MM:
            converged = True
            break
    if not converged:
        return nan, nan, nan, 3, nan, nan, nan
    # Refraction at A (Snell's law in vector form), normal m facing the incident ray.
    inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
    ex = dx * inv
    ey = dy * inv
    ez = dz * inv
    eta = 1.0 / n_idx
    cos_i = -(ex * mx + ey * my + ez * mz)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    f = eta * cos_i - math.sqrt(k)
    rx = eta * ex + f * mx
    ry = eta * ey + f * my
    rz = eta * ez + f * mz
    # The emitting-surface hit: Newton steps from the foot point's height (Q lies ≈ t·tanθ_g from
    # the foot), each accepted by its error bound (intersect_kernel); the safeguarded solver only
    # if they do not settle.
    # Start: the refracted ray's point on the emitting surface's tangent plane at the foot point.
    h = eval_kernel(kind, gx, gy, coef, ux, uy)[0]
    rm = rx * mx + ry * my + rz * mz
    s_plane = ((ux - ax) * mx + (uy - ay) * my + (h - az) * mz) / rm
    z = az + s_plane * rz
    if not np.isfinite(z):
        z = h
    st = _NEEDS_SOLVE
    for _ in range(_NEWTON_STEPS):
        _s, x, y, z, _hx, _hy, st = intersect_kernel(kind, gx, gy, coef, dmax, ax, ay, az, rx, ry, rz, tol, z, False)
        if st != _NEEDS_SOLVE:
            break
    if st == _NEEDS_SOLVE:
        _s, x, y, z, _hx, _hy, st = intersect_solve(kind, gx, gy, coef, z_min, z_max, dmax, ax, ay, az, rx, ry, rz,
                                                    tol, max_iter, z)
    if st != 0:
        return nan, nan, nan, st, nan, nan, nan
    return x, y, z, 0, az, mx, my


@numba.njit(**_JIT)
def _trace_range(start, end, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, o, d, q, tol, max_iter, out, status):
    for i in range(start, end):
        if status[i] != 0:
            out[i, 0] = np.nan
            out[i, 1] = np.nan
            out[i, 2] = np.nan
            continue
        x, y, z, st = through_glass_kernel(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, o[i, 0], o[i, 1], o[i, 2],
                                           d[i, 0], d[i, 1], d[i, 2], q[i, 0], q[i, 1], q[i, 2], tol, max_iter)
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z
        status[i] = st


_CHUNK = 2048


@numba.njit(cache=True, parallel=True)
def _trace_many(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, o, d, q, tol, max_iter, out, status):
    n = o.shape[0]
    for c in numba.prange(0, (n + _CHUNK - 1) // _CHUNK):
        _trace_range(c * _CHUNK, min(n, (c + 1) * _CHUNK), kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, o, d, q,
                     tol, max_iter, out, status)


@numba.njit(**_JIT)
def _apparent_range(start, end, kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, p, q, ok, tol_inv, max_iter_inv,
                    tol, max_iter, out, converged):
    """:meth:`CoverGlass.apparent_points` for the points ``start:end`` (its fixed point per point,
    then the straight line's hit of the emitting surface)."""
    nan = np.nan
    for i in range(start, end):
        converged[i] = True
        if not ok[i]:
            out[i, 0] = nan
            out[i, 1] = nan
            out[i, 2] = nan
            continue
        px = p[i, 0]
        py = p[i, 1]
        pz = p[i, 2]
        qx = q[i, 0]
        qy = q[i, 1]
        qz = q[i, 2]
        _h, hx, hy = eval_kernel(kind, gx, gy, coef, qx, qy)
        nrm = math.sqrt(hx * hx + hy * hy + 1.0)
        ax = qx + t * (hx / nrm)
        ay = qy + t * (hy / nrm)
        az = qz + t * (-1.0 / nrm)
        failed = False
        todo = True
        # The foot point of A (where the offset normal through A meets the emitting surface):
        # Q for the first trace, then A − t·m with the plate normal of the previous trace.
        ux = qx
        uy = qy
        for _ in range(max_iter_inv):
            x, y, z, st, _az, mx, my = through_glass_full(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, px, py, pz,
                                                          ax - px, ay - py, az - pz, ux, uy, qz, tol, max_iter)
            if st != 0:
                failed = True
                todo = False
                break
            sx = qx - x
            sy = qy - y
            sz = qz - z
            ax += sx
            ay += sy
            az += sz
            ux = ax - t * mx
            uy = ay - t * my
            if max(abs(sx), abs(sy), abs(sz)) < tol_inv:
                todo = False
                break
        converged[i] = not todo
        if failed or todo:
            out[i, 0] = nan
            out[i, 1] = nan
            out[i, 2] = nan
            continue
        # The straight line P → A meets the emitting surface near Q: Newton steps from Q's height,
        # the safeguarded solver if they do not settle (as in through_glass_full).
        z = qz
        st = _NEEDS_SOLVE
        for _ in range(_NEWTON_STEPS):
            _s, x, y, z, _hx, _hy, st = intersect_kernel(kind, gx, gy, coef, dmax, px, py, pz, ax - px, ay - py,
                                                         az - pz, tol, z, False)
            if st != _NEEDS_SOLVE:
                break
        if st == _NEEDS_SOLVE:
            _s, x, y, z, _hx, _hy, st = intersect_solve(kind, gx, gy, coef, z_min, z_max, dmax, px, py, pz, ax - px,
                                                        ay - py, az - pz, tol, max_iter, z)
        if st != 0:
            x = nan
            y = nan
            z = nan
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z


@numba.njit(cache=True, parallel=True)
def _apparent_many(kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, p, q, ok, tol_inv, max_iter_inv, tol, max_iter,
                   out, converged):
    n = p.shape[0]
    for c in numba.prange(0, (n + _CHUNK - 1) // _CHUNK):
        _apparent_range(c * _CHUNK, min(n, (c + 1) * _CHUNK), kind, gx, gy, coef, z_min, z_max, dmax, t, n_idx, p, q,
                        ok, tol_inv, max_iter_inv, tol, max_iter, out, converged)


@dataclass(frozen=True)
class CoverGlass:
    """A cover-glass plate of ``thickness_mm`` and refractive ``index`` (module docstring).

    ``thickness_mm`` = 0 is no glass (:attr:`present` False): the tracer and the registration
    then skip it entirely.
    """

    thickness_mm: float = 0.0
    index: float = DEFAULT_GLASS_INDEX

    def __post_init__(self) -> None:
        t = float(self.thickness_mm)
        n = float(self.index)
        if not (math.isfinite(t) and t >= 0.0):
            raise ValueError(f"cover glass thickness must be a finite number ≥ 0 mm, got {self.thickness_mm!r}")
        if not (math.isfinite(n) and n > 1.0):
            raise ValueError(f"cover glass index must be a finite number > 1, got {self.index!r}")
        object.__setattr__(self, "thickness_mm", t)
        object.__setattr__(self, "index", n)

    @property
    def present(self) -> bool:
        """True when the plate has a thickness."""
        return self.thickness_mm > 0.0

    def with_(self, *, thickness_mm: float | None = None, index: float | None = None) -> "CoverGlass":
        return CoverGlass(self.thickness_mm if thickness_mm is None else thickness_mm,
                          self.index if index is None else index)

    def trace(self, surface, origin, direction, start=None, *, status=None, tol_mm: float = INTERSECT_TOL_MM):
        """Trace rays through the glass to the emitting ``surface`` (screen frame).

        Parameters
        ----------
        surface : SplineSurface or PlaneSurface
            The emitting surface.
        origin, direction : ndarray (..., 3)
            Rays towards the screen, in the screen frame.
        start : ndarray (..., 3), optional
            The rays' hits of the bare emitting surface (warm starts); computed when None.
        status : ndarray of uint8 (...), optional
            Non-zero: skip the ray (its result is NaN and its status kept).

        Returns
        -------
        q : ndarray (..., 3)
            The emitting-surface points Q (NaN where the status is not 0).
        status : ndarray of uint8 (...)
            :class:`~pmdsim.geometry.surface.IntersectStatus` codes.
        """
        o, d = np.broadcast_arrays(np.asarray(origin, dtype=float), np.asarray(direction, dtype=float))
        shape = o.shape[:-1]
        of = np.ascontiguousarray(o.reshape(-1, 3))
        df = np.ascontiguousarray(d.reshape(-1, 3))
        if start is None:
            _t, start, st0 = surface.intersect(of, df, tol_mm)
        else:
            st0 = np.zeros(of.shape[0], dtype=np.uint8)
        qf = np.ascontiguousarray(np.broadcast_to(np.asarray(start, dtype=float), o.shape).reshape(-1, 3))
        st = np.ascontiguousarray(st0.reshape(-1).astype(np.uint8))
        if status is not None:
            st = np.where(np.asarray(status).reshape(-1) != 0, np.asarray(status).reshape(-1), st).astype(np.uint8)
        out = np.empty_like(of)
        k = surface.kernel
        _trace_many(k.kind, k.grid_x, k.grid_y, k.coef, k.z_min, k.z_max, k.dmax, self.thickness_mm, self.index,
                    of, df, qf, tol_mm, FIXED_POINT_MAX_ITER, out, st)
        return out.reshape(shape + (3,)), st.reshape(shape)

    def apparent_points(self, surface, p_mm, q_mm, *, tol_mm: float = INVERSE_TOL_MM,
                        max_iter: int = INVERSE_MAX_ITER, return_converged: bool = False):
        """The inverse problem of registration: the line from a sample point to an emitting point.

        For a sample point P and the emitting-surface point Q that it sees through the glass
        (both (..., 3), screen frame), find the exit point A on the outer surface such that the
        ray P → A, refracted, reaches Q. Method: A ← A + (Q − Q′), where Q′ is the forward trace
        (:meth:`trace`) of the ray P → A, starting from A = Q + t·m(Q); the error shrinks by
        ≈ t/(n·|PQ|) per step (< 1 % for t ≤ 3 mm at ≥ 300 mm). A point has converged when the
        correction |Q − Q′| (largest component) is below ``tol_mm`` (1e-9 mm; 4–6 steps); the
        iteration stops when all have, or after ``max_iter`` steps.

        Returns
        -------
        ndarray (..., 3)
            The *apparent* point: where the straight line P → A meets the emitting surface (the
            point a glass-free screen would have to show for that line). NaN where P or Q is
            not finite, a trace fails or the iteration did not converge.
        ndarray of bool (...), with ``return_converged``
            False where P and Q are finite and every trace succeeded but the iteration did not
            converge within ``max_iter`` steps.
        """
        p, q = np.broadcast_arrays(np.asarray(p_mm, dtype=float), np.asarray(q_mm, dtype=float))
        if not self.present:
            return (q.copy(), np.ones(q.shape[:-1], dtype=bool)) if return_converged else q.copy()
        shape = q.shape[:-1]
        pf = np.ascontiguousarray(p.reshape(-1, 3))
        qf = np.ascontiguousarray(q.reshape(-1, 3))
        ok = np.isfinite(pf).all(axis=-1) & np.isfinite(qf).all(axis=-1)
        out = np.empty_like(qf)
        conv = np.empty(qf.shape[0], dtype=np.bool_)
        k = surface.kernel
        _apparent_many(k.kind, k.grid_x, k.grid_y, k.coef, k.z_min, k.z_max, k.dmax, self.thickness_mm, self.index,
                       pf, qf, ok, float(tol_mm), int(max_iter), INTERSECT_TOL_MM, FIXED_POINT_MAX_ITER, out, conv)
        out = out.reshape(shape + (3,))
        return (out, conv.reshape(shape)) if return_converged else out
