"""Geometry (layer 0): rigid transforms and Givens-angle poses, the camera model, surfaces.

* :mod:`.transform` — :class:`RigidTransform` and the paper's Givens angles (§2.1, eq. 1);
* :mod:`.camera` — pinhole + Brown distortion (OpenCV's full model), numerically inverted (§2.2,
  eqs. 2–4); :mod:`.camera_checks` — plausibility checks of camera models;
* :mod:`.surface` — not-a-knot spline and plane surfaces: height, gradient and ray
  intersection (§2.3, eqs. 8–16), with the numba kernels the tracer and calibration use;
* :mod:`.shapes` — sphere, paraboloid and cylinder as quadric height fields in closed form
  (same interface and kernels; :mod:`.shape_kernels`), for curved samples.

A surface knows its shape; it does not know where it is sampled or who traces it.
Conventions: docs/conventions.md. May import: :mod:`pmdsim.errors` only.
"""

from .camera import Camera
from .shapes import QuadricSurface
from .surface import IntersectStatus, PlaneSurface, SplineSurface
from .transform import RigidTransform, givens_angles, givens_rotation

__all__ = ["Camera", "IntersectStatus", "PlaneSurface", "QuadricSurface", "SplineSurface", "RigidTransform", "givens_angles",
           "givens_rotation"]
