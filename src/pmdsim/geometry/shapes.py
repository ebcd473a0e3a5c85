"""Analytic sample shapes as surfaces: sphere, paraboloid, cylinder (closed forms).

A :class:`QuadricSurface` is a height field z = h(x, y) over a rectangle of its frame, like a
:class:`~pmdsim.geometry.surface.SplineSurface`, with the same interface (``height``,
``gradient``, ``normal``, ``intersect``, ``kernel``); the tracer does not know which it is.
Height, gradient and ray intersection are closed forms (:mod:`pmdsim.geometry.shape_kernels`),
exact to rounding — which a spline on a grid is not (docs/conventions.md, "Curved samples":
a 1 m sphere on a 2.5 mm grid is still off by 1e-8 mm in height and 1e-8 rad in slope).

Sign convention (docs/conventions.md, "Curved samples"): heights are along the surface
frame's +z; the vertex (v_x, v_y) has height 0. A **positive** radius or focal length puts
the centre of curvature (the focus) on the +z side: for the sample, whose +z points away from
the cameras, that is **convex as seen from the cameras** (the vertex is the point nearest to
them), the same sign as a positive ``calibration.mirror_sag_um``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kernel_args import readonly
from .surface import _KIND_QUADRIC, KernelSurface, _SurfaceBase, _validate_grid

__all__ = ["QuadricSurface"]


@dataclass(frozen=True, eq=False)
class QuadricSurface(_SurfaceBase):
    """A quadric height field F(p') = p'ᵀ Q p' − z = 0, p' = (x − v_x, y − v_y, z).

    Build it with :meth:`sphere`, :meth:`paraboloid` or :meth:`cylinder`.

    Parameters
    ----------
    grid_x_mm, grid_y_mm : array_like, shape (n,)
        Bounds of the surface (only the first and last values are used: the rectangle over
        which the height field exists, as for a spline surface).
    vertex_xy_mm : (float, float)
        (v_x, v_y), where h = 0 and ∇h = 0.
    q : array_like, shape (3, 3)
        The symmetric matrix Q (1/mm).

    Raises
    ------
    ValueError
        If the branch ∂F/∂z < 0 of the height field does not cover the whole rectangle (a
        sphere or cylinder whose radius is too small for the grid).
    """

    grid_x_mm: np.ndarray
    grid_y_mm: np.ndarray
    vertex_xy_mm: tuple[float, float]
    q: np.ndarray

    def __post_init__(self) -> None:
        gx = _validate_grid("grid_x_mm", self.grid_x_mm)
        gy = _validate_grid("grid_y_mm", self.grid_y_mm)
        gx = np.array([gx[0], gx[-1]])
        gy = np.array([gy[0], gy[-1]])
        gx.setflags(write=False)
        gy.setflags(write=False)
        q = np.array(self.q, dtype=float)
        if q.shape != (3, 3) or not np.all(np.isfinite(q)) or not np.allclose(q, q.T, rtol=0, atol=0):
            raise ValueError(f"q must be a finite symmetric 3 × 3 matrix, got {q!r}")
        vx, vy = (float(v) for v in self.vertex_xy_mm)
        if not (math.isfinite(vx) and math.isfinite(vy)):
            raise ValueError(f"vertex_xy_mm must be finite, got {self.vertex_xy_mm!r}")
        q.setflags(write=False)
        object.__setattr__(self, "grid_x_mm", gx)
        object.__setattr__(self, "grid_y_mm", gy)
        object.__setattr__(self, "vertex_xy_mm", (vx, vy))
        object.__setattr__(self, "q", q)
        coef = np.array([vx, vy, q[0, 0], q[0, 1], q[0, 2], q[1, 1], q[1, 2], q[2, 2]])
        coef.setflags(write=False)
        # The height field must exist over the whole rectangle: check its corners, its edge
        # points nearest to the vertex and the vertex (the extremes of these shapes' heights).
        xs = np.array([gx[0], gx[1], np.clip(vx, gx[0], gx[1])])
        ys = np.array([gy[0], gy[1], np.clip(vy, gy[0], gy[1])])
        X, Y = np.meshgrid(xs, ys)
        probe = KernelSurface(_KIND_QUADRIC, gx, gy, coef, 0.0, 0.0, readonly(np.zeros(2)))
        object.__setattr__(self, "kernel", probe)
        h = self.height(X, Y)
        if not np.all(np.isfinite(h)):
            raise ValueError(
                f"the shape does not cover the grid [{gx[0]:g}, {gx[1]:g}] × [{gy[0]:g}, {gy[1]:g}] mm around its "
                f"vertex ({vx:g}, {vy:g}) mm: its radius is too small (a sphere or cylinder must reach every corner)")
        # Height bounds of the kernel description (the spline fallback's search interval; the
        # closed-form intersection does not use them): the probed corners, edge points and
        # vertex, where these shapes take their extremes unless a cylinder's axis crosses the
        # rectangle away from the vertex (bounds widened to include 0).
        pad = 1e-9 + 1e-9 * float(np.max(np.abs(h)))
        kernel = KernelSurface(_KIND_QUADRIC, gx, gy, coef, min(float(np.min(h)), 0.0) - pad,
                               max(float(np.max(h)), 0.0) + pad,
                               readonly(np.zeros(2)))
        object.__setattr__(self, "kernel", kernel)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def sphere(cls, grid_x_mm, grid_y_mm, radius_mm: float, vertex_xy_mm=None) -> "QuadricSurface":
        """Sphere of signed radius R: h = R − sgn(R)·√(R² − r²), r the distance from the vertex
        (centre of curvature at (v_x, v_y, R); R > 0: convex as seen from −z)."""
        r = _nonzero("radius_mm", radius_mm)
        return cls(grid_x_mm, grid_y_mm, _vertex(grid_x_mm, grid_y_mm, vertex_xy_mm), np.eye(3) / (2.0 * r))

    @classmethod
    def paraboloid(cls, grid_x_mm, grid_y_mm, focal_length_x_mm: float, focal_length_y_mm: float,
                   vertex_xy_mm=None) -> "QuadricSurface":
        """Paraboloid h = x'²/(4 f_x) + y'²/(4 f_y) (signed focal lengths; opposite signs: a
        saddle; ``math.inf``: no curvature along that axis)."""
        fx = _nonzero("focal_length_x_mm", focal_length_x_mm, allow_inf=True)
        fy = _nonzero("focal_length_y_mm", focal_length_y_mm, allow_inf=True)
        q = np.diag([1.0 / (4.0 * fx), 1.0 / (4.0 * fy), 0.0])
        return cls(grid_x_mm, grid_y_mm, _vertex(grid_x_mm, grid_y_mm, vertex_xy_mm), q)

    @classmethod
    def cylinder(cls, grid_x_mm, grid_y_mm, radius_mm: float, axis_angle_deg: float = 0.0,
                 vertex_xy_mm=None) -> "QuadricSurface":
        """Cylinder of signed radius R whose axis lies parallel to the x–y plane at z = R, through
        the vertex, at ``axis_angle_deg`` from the x axis (towards +y): h = R − sgn(R)·√(R² − s²),
        s the distance from the axis in the x–y plane."""
        r = _nonzero("radius_mm", radius_mm)
        th = math.radians(float(axis_angle_deg))
        if not math.isfinite(th):
            raise ValueError(f"axis_angle_deg must be finite, got {axis_angle_deg!r}")
        w = np.array([-math.sin(th), math.cos(th), 0.0])
        q = (np.outer(w, w) + np.diag([0.0, 0.0, 1.0])) / (2.0 * r)
        q = 0.5 * (q + q.T)
        return cls(grid_x_mm, grid_y_mm, _vertex(grid_x_mm, grid_y_mm, vertex_xy_mm), q)

    is_planar = False


def _nonzero(name: str, v, allow_inf: bool = False) -> float:
    if isinstance(v, bool):
        raise ValueError(f"{name} must be a number, got {v!r}")
    f = float(v)
    if f == 0.0 or math.isnan(f) or (math.isinf(f) and not allow_inf):
        raise ValueError(f"{name} must be a non-zero finite number, got {v!r}")
    return f


def _vertex(gx, gy, vertex_xy_mm) -> tuple[float, float]:
    """The given vertex, or the centre of the grid rectangle."""
    if vertex_xy_mm is not None:
        v = tuple(float(c) for c in vertex_xy_mm)
        if len(v) != 2:
            raise ValueError(f"vertex_xy_mm must be (x, y), got {vertex_xy_mm!r}")
        return v
    gx = np.asarray(gx, dtype=float)
    gy = np.asarray(gy, dtype=float)
    return 0.5 * float(gx[0] + gx[-1]), 0.5 * float(gy[0] + gy[-1])
