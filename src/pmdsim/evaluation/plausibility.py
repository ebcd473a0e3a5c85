"""Plausibility checks of an evaluation: the mistakes that otherwise give silently wrong results
when a real instrument's data are converted (issue 12, item 5). Each check returns warning
texts (empty when plausible) that name the likely cause; the evaluation reports them.

* :func:`check_scale` — lengths that look like metres in a setup that pmdsim reads as mm;
* :func:`check_screen_coverage` — most decoded pixels outside the screen model (e.g. a screen
  grid centred on the screen although pattern coordinates start at its corner);
* :func:`check_orientation` — the decoded pixel → screen mapping mirrored against the one the
  setup's geometry predicts for a flat sample (a display axis flipped).
"""

from __future__ import annotations

import numpy as np

from .registration import RegistrationStatus

__all__ = ["check_scale", "check_screen_coverage", "check_orientation"]

#: Screens smaller than this (mm) are implausible (a phone display is ~60 mm wide).
MIN_SCREEN_MM = 20.0
#: Camera–screen distances below this (mm) are implausible.
MIN_DISTANCE_MM = 20.0


def check_scale(setup) -> list[str]:
    """Lengths of ``setup`` that look like metres (pmdsim reads every length in mm)."""
    out = []
    w, h = setup.screen.size_mm
    if max(w, h) < MIN_SCREEN_MM:
        out.append(f"the screen grid is only {w:g} × {h:g} mm: implausibly small — are the lengths in metres? "
                   f"pmdsim reads every length (screen grid, origins) in millimetres")
    o_screen = np.asarray(setup.screen.T_world_screen.translation)
    for name, cs in setup.cameras.items():
        dist = float(np.linalg.norm(np.asarray(cs.T_world_cam.translation) - o_screen))
        if dist < MIN_DISTANCE_MM:
            out.append(f"camera {name!r} is {dist:.4g} mm from the screen origin: implausibly close — are the "
                       f"origins in metres? pmdsim reads them in millimetres")
    return out


def check_screen_coverage(decoded_valid, status, screen_xy_mm, bounds_mm, camera: str) -> list[str]:
    """Warn when more than half of the decoded pixels fall outside the screen model's grid.

    ``decoded_valid`` (H, W), ``status`` (H, W) registration status, ``screen_xy_mm`` (H, W, 2)
    decoded coordinates, ``bounds_mm`` (x0, x1, y0, y1) of the screen model."""
    n_dec = int(np.count_nonzero(decoded_valid))
    n_out = int(np.count_nonzero(status == RegistrationStatus.OUTSIDE_SCREEN_MODEL))
    if n_dec == 0 or n_out <= 0.5 * n_dec:
        return []
    x0, x1, y0, y1 = bounds_mm
    xy = screen_xy_mm[np.asarray(decoded_valid, bool)]
    lo = np.nanpercentile(xy, 1, axis=0)
    hi = np.nanpercentile(xy, 99, axis=0)
    msg = (f"camera {camera!r}: {n_out} of {n_dec} decoded pixels lie outside the screen model "
           f"(grid x {x0:g} … {x1:g}, y {y0:g} … {y1:g} mm; decoded x {lo[0]:.4g} … {hi[0]:.4g}, "
           f"y {lo[1]:.4g} … {hi[1]:.4g} mm)")
    w, h = x1 - x0, y1 - y0
    centred = abs(x0 + x1) < 0.05 * w and abs(y0 + y1) < 0.05 * h
    if centred and lo[0] >= x0 - 0.05 * w and lo[1] >= y0 - 0.05 * h and (hi[0] > x1 or hi[1] > y1):
        msg += ("; the screen grid is centred on the screen, but pattern coordinates start at the screen's corner "
                "(0 … width, 0 … height): start screen.grid_x_mm and grid_y_mm at 0")
    elif max(hi[0] - lo[0], hi[1] - lo[1]) > 20 * max(w, h) or max(hi[0] - lo[0], hi[1] - lo[1]) < max(w, h) / 50:
        msg += "; the decoded and the model's extents differ by orders of magnitude: metres vs millimetres?"
    else:
        msg += "; check the screen size (the image set's periods) against the setup's screen grid"
    return [msg]


def _jacobian_median(xy, ok):
    """Median ∂(x, y)/∂(u, v) (2 × 2, columns u, v) over pixels where the central differences
    are defined."""
    gx_v, gx_u = np.gradient(np.where(ok, xy[..., 0], np.nan))
    gy_v, gy_u = np.gradient(np.where(ok, xy[..., 1], np.nan))
    J = np.array([[np.nanmedian(gx_u), np.nanmedian(gx_v)], [np.nanmedian(gy_u), np.nanmedian(gy_v)]])
    return J


#: Images with more pixels than this take the orientation check's medians on a sub-grid.
ORIENTATION_FULL_GRID_PX = 262_144
#: Samples of the sub-grid (about): its stride is √(H·W / this).
ORIENTATION_SAMPLES = 36_000


def orientation_stride(shape) -> int:
    """Pixel stride of :func:`check_orientation`'s medians: 1 (every pixel) up to
    :data:`ORIENTATION_FULL_GRID_PX` pixels, else about √(H·W / :data:`ORIENTATION_SAMPLES`)
    (8 for 1920×1200: 36 000 samples; a median of a smooth Jacobian from them differs from the
    full one by far less than the sign test needs)."""
    h, w = int(shape[0]), int(shape[1])
    if h * w <= ORIENTATION_FULL_GRID_PX or h < 3 or w < 3:
        return 1
    return max(1, int(np.sqrt(h * w / ORIENTATION_SAMPLES)))


def _predicted_xy(setup, cs, d_cam):
    """Screen (x, y) (…, 2) where view rays ``d_cam`` (…, 3, camera frame) reflected at the
    sample frame's plane z = 0 meet the screen plane, and whether both hits lie ahead."""
    T_s_c = setup.sample.T_world_sample.inv() @ cs.T_world_cam
    o = np.asarray(T_s_c.translation, dtype=float)
    d = T_s_c.apply_vector(d_cam)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / d[..., 2]
        p = o + t[..., None] * d
        r = d * np.array([1.0, 1.0, -1.0])  # reflected at the plane z = 0 (normal ±z)
        T_scr_s = setup.screen.T_world_screen.inv() @ setup.sample.T_world_sample
        p_scr = T_scr_s.apply(p)
        r_scr = T_scr_s.apply_vector(r)
        s = -p_scr[..., 2] / r_scr[..., 2]
        pred = p_scr[..., :2] + s[..., None] * r_scr[..., :2]
    return pred, (t > 0) & (s > 0) & np.isfinite(pred).all(axis=-1)


def _stencil_median(f, good):
    """Median Jacobian from 5-point stencils: ``f`` (5, …, 2) at (centre, u−1, u+1, v−1, v+1),
    central differences (np.gradient's interior formula) where both neighbours are ``good``."""
    with np.errstate(invalid="ignore"):
        du = np.where((good[1] & good[2])[..., None], (f[2] - f[1]) / 2.0, np.nan)
        dv = np.where((good[3] & good[4])[..., None], (f[4] - f[3]) / 2.0, np.nan)
    return np.array([[np.nanmedian(du[..., 0]), np.nanmedian(dv[..., 0])],
                     [np.nanmedian(du[..., 1]), np.nanmedian(dv[..., 1])]])


def _orientation_jacobians(setup, camera: str, decoded_xy_mm, ok, stride: int):
    """(J_dec, J_pred) of :func:`check_orientation`, or None with fewer than 16 usable pixels;
    ``stride`` > 1: central differences at every stride-th interior pixel (v, u ≡ 1 mod stride)."""
    cs = setup.cameras[camera]
    d_cam, conv = cs.camera.sensor_rays()
    xy = np.asarray(decoded_xy_mm, float)
    if stride == 1:
        pred, ahead = _predicted_xy(setup, cs, d_cam)
        good = ok & conv & ahead
        if good.sum() < 16:
            return None
        return _jacobian_median(xy, good), _jacobian_median(pred, good)
    h, w = ok.shape
    V, U = np.meshgrid(np.arange(1, h - 1, stride), np.arange(1, w - 1, stride), indexing="ij")
    sv = np.stack([V, V, V, V - 1, V + 1])
    su = np.stack([U, U - 1, U + 1, U, U])
    pred, ahead = _predicted_xy(setup, cs, d_cam[sv, su])
    good = ok[sv, su] & conv[sv, su] & ahead
    if good[0].sum() < 16:
        return None
    return _stencil_median(xy[sv, su], good), _stencil_median(pred, good)


def check_orientation(setup, camera: str, decoded_xy_mm, decoded_valid) -> list[str]:
    """Compare the decoded mapping's orientation with the flat-sample prediction.

    The sample frame's plane z = 0 is taken as a mirror; each decoded pixel's view ray is
    reflected there and meets the screen frame's plane z = 0 at the predicted (x, y). With
    J_dec, J_pred the median Jacobians ∂(x, y)/∂(u, v), M = J_dec·J_pred⁻¹ is close to the
    identity for a mirror that is not strongly curved; a negative diagonal entry means that
    screen axis runs the other way in the data than in the setup (a flipped display axis). A
    concave mirror beyond its centre of curvature inverts the image as well, hence a warning,
    not an error. Images above :data:`ORIENTATION_FULL_GRID_PX` pixels take the medians over
    a regular sub-grid (:func:`orientation_stride`), the central differences still between
    neighbouring pixels."""
    ok = np.asarray(decoded_valid, bool)
    if ok.sum() < 16:
        return []
    J = _orientation_jacobians(setup, camera, decoded_xy_mm, ok, orientation_stride(ok.shape))
    if J is None:
        return []
    Jd, Jp = J
    if not (np.isfinite(Jd).all() and np.isfinite(Jp).all()) or abs(np.linalg.det(Jp)) < 1e-300:
        return []
    M = Jd @ np.linalg.inv(Jp)
    flipped = [ax for i, ax in enumerate("xy") if M[i, i] < 0 and abs(M[i, i]) > abs(M[i, 1 - i])]
    if not flipped:
        return []
    axes = " and ".join(flipped)
    return [f"camera {camera!r}: the decoded screen {axes} coordinates run opposite to what the setup's geometry "
            f"predicts for a flat sample (J_dec·J_pred⁻¹ diagonal {M[0, 0]:.3g}, {M[1, 1]:.3g}): the display's "
            f"{axes} axis is likely flipped between the images and the setup's screen frame (e.g. pattern y counted "
            f"from the top row while the screen frame's y points up)"]
