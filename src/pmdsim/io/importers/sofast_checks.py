"""Checks of SOFAST files that the importer (:mod:`.sofast`) runs before it writes anything
(issue 24): an import that ``pmdsim evaluate`` cannot use, or whose geometry is wrong, fails at
import with one line naming the input file and the key — an image calibration with fewer than
two levels, reversed levels or on another scale than the fringes, a display orientation that
does not face the optic (a rotation vector in degrees, a negated one).
"""

from __future__ import annotations

import numpy as np

from ...errors import PmdsimError
from ...geometry.transform import RigidTransform

__all__ = ["MAX_SCREEN_VIEW_ANGLE_DEG", "MIN_LIT_PIXELS", "check_calibration", "check_screen_faces_optic"]


#: The largest angle (deg) between the display's normal and its line of sight to the optic that an
#: import accepts: a deflectometry screen faces the sample (the SOFAST facet: 5.7°); an orientation
#: whose display faces elsewhere is a mistake (a rotation vector in degrees: 68°; negated: 45°).
MAX_SCREEN_VIEW_ANGLE_DEG = 30.0


def _screen_view_angle_deg(r_cs: np.ndarray, s_world: np.ndarray, p_opt: np.ndarray) -> float:
    """Angle (deg) between the display's normal towards the sample — SOFAST's display +z,
    ``R(r_cam_screen)ᵀ·e_z`` in the camera frame — and the direction from the display origin
    ``s_world`` to the optic ``p_opt`` (both mm, camera frame)."""
    n = RigidTransform.from_rotvec(r_cs, np.zeros(3)).rotation.T @ np.array([0.0, 0.0, 1.0])
    u = (p_opt - s_world) / np.linalg.norm(p_opt - s_world)
    return float(np.degrees(np.arccos(np.clip(n @ u, -1.0, 1.0))))


def check_screen_faces_optic(r_cs: np.ndarray, s_world: np.ndarray, p_opt: np.ndarray, orientation) -> None:
    """Refuse an orientation whose display does not face the optic (the likely mistakes named:
    a rotation vector in degrees, a negated one, the inverse rotation)."""
    angle = _screen_view_angle_deg(r_cs, s_world, p_opt)
    if angle <= MAX_SCREEN_VIEW_ANGLE_DEG:
        return
    guesses = {"written in degrees (radians expected)": np.radians(r_cs), "negated (the inverse rotation)": -r_cs}
    a_best, what = min((_screen_view_angle_deg(r, s_world, p_opt), what) for what, r in guesses.items())
    fits = [f"{what}: read so, it would face the optic at {a_best:.1f}°"] if a_best <= 0.5 * MAX_SCREEN_VIEW_ANGLE_DEG else []
    raise _error()(
        f"{str(orientation)!r}: SpatialOrientation/r_cam_screen = {r_cs.tolist()} turns the display "
        f"{angle:.1f}° away from its line of sight to the optic (at most {MAX_SCREEN_VIEW_ANGLE_DEG:g}° expected: a "
        f"deflectometry screen faces the sample); "
        + (f"the rotation vector looks {fits[0]}" if fits else
           "is it a rotation vector in radians mapping camera to display coordinates (SOFAST's convention)?"))


#: The fewest lit pixels a measurement's mask may have (a surface fit needs a region, not a point).
MIN_LIT_PIXELS = 16


def check_calibration(calibration, dv: np.ndarray, cv: np.ndarray, fringes: np.ndarray, measurement) -> None:
    """Refuse an image calibration ``evaluate`` cannot use, naming the file and the key: fewer
    than two levels, levels that decrease (reversed), display values outside 0…255, or camera
    values on another scale than the fringe images (an 8-bit calibration for 16-bit fringes, or
    one scaled ×256: the fringes' lit level far beyond or far below its brightest camera value)."""
    src = f"{str(calibration)!r}"
    if dv.size != cv.size:
        raise _error()(f"{src}: ImageCalibration/display_values has {dv.size} levels but camera_values "
                                f"{cv.size}; one camera value per display value expected")
    if dv.size < 2 or not (np.all(np.isfinite(dv)) and np.all(np.isfinite(cv))):
        raise _error()(f"{src}: ImageCalibration/display_values, camera_values hold {dv.size} finite "
                                f"level(s); at least two expected (the display → camera response is interpolated "
                                f"between them)")
    if np.all(np.diff(dv) < 0) or (np.all(np.diff(cv) < 0) and np.all(np.diff(dv) <= 0)):
        raise _error()(f"{src}: ImageCalibration/display_values and camera_values decrease "
                                f"({dv[0]:g} … {dv[-1]:g}, {cv[0]:g} … {cv[-1]:g}); SOFAST writes them in increasing "
                                f"order — are they reversed?")
    if np.any(np.diff(dv) <= 0):
        raise _error()(f"{src}: ImageCalibration/display_values must increase, got {dv.tolist()}")
    if np.count_nonzero(np.diff(cv) > 0) < 1:
        raise _error()(f"{src}: ImageCalibration/camera_values do not increase with the display value "
                                f"({cv.tolist()}); a camera that does not respond to the display cannot be linearised")
    if dv.min() < 0 or dv.max() > 255:
        raise _error()(f"{src}: ImageCalibration/display_values span {dv.min():g} … {dv.max():g}; SOFAST's "
                                f"display levels are 0 … 255")
    full = 255.0 if fringes.dtype == np.uint8 else 65535.0
    if cv.max() > full:
        raise _error()(f"{src}: ImageCalibration/camera_values reach {cv.max():g}, beyond the "
                                f"{'8' if full == 255 else '16'}-bit fringe images' full scale {full:g}: a calibration "
                                f"of another camera setting, or scaled (×256)?")
    lit_level = float(np.percentile(fringes.max(axis=-1), 99))  # the brightest fringe samples
    top = float(cv.max())
    if lit_level > 4.0 * top and lit_level > 255:
        raise _error()(
            f"{src}: ImageCalibration/camera_values reach {top:g}, but the fringe images of "
            f"{str(measurement)!r} (MeasurementSofastFringe/fringe_images) reach {lit_level:g} ({fringes.dtype}): the calibration is on another scale (an 8-bit calibration "
            f"for 16-bit images?); every fringe sample would be above its brightest level (saturated)")
    if top > 4.0 * max(lit_level, 1.0):
        raise _error()(
            f"{src}: ImageCalibration/camera_values reach {top:g}, but the fringe images of "
            f"{str(measurement)!r} (MeasurementSofastFringe/fringe_images) reach only {lit_level:g}: the calibration is on another scale (scaled ×256, or for 16-bit images?)")


def _error() -> type[PmdsimError]:
    """:class:`.sofast.SofastImportError` (imported here late: :mod:`.sofast` imports this module)."""
    from .sofast import SofastImportError

    return SofastImportError
