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

Two integrators are provided (the modules: :mod:`.integration` — the result type, input
checks and bisector normals both share; :mod:`.stepwise`; :mod:`.least_squares` with its
solver in :mod:`.multigrid`):

* :func:`reconstruct_stepwise` — the paper's stepwise integration: breadth-first expansion
  from an initial point, each new pixel solved from (*) with a predictor–corrector iteration;
* :func:`reconstruct_least_squares` — zonal (Southwell-type) least-squares integration of (*)
  over all valid neighbour pairs of the seed's component (Gauss–Newton iterations, each a
  sparse solve by multigrid-preconditioned conjugate gradients).

Neither assumes on which side of the surface the camera is (o_z may be above or below).
"""

from __future__ import annotations

from .integration import Reconstruction, ReconstructionError, normals_from_registration
from .least_squares import reconstruct_least_squares
from .stepwise import STEP_MAX_ITER, STEP_TOL_MM, reconstruct_stepwise

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


_METHODS = ("stepwise", "least_squares")


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
