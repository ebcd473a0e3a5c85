"""Issue 12: where is the SOFAST facet's measure point seen? pmdsim's pixel vs SOFAST's, decomposed.

    python benchmarks/sofast_anchor.py [--data DIR] [--no-synthetic]

A. Real data (OpenCSP's facet measurement and SOFAST's own evaluation of it):
   1. SOFAST's measure-point pixel reproduced from its stored refined corners
      (``loop_facet_image_refine``) by a pose fit with pmdsim's camera model and the projection of
      the facet centre; the pose against SOFAST's stored ``r_optic_cam_refine_1`` /
      ``v_cam_optic_cam_refine_1``.
   2. SOFAST's mask and corners reproduced from the images by an independent re-implementation
      of its method (tests/sofast_reference.py).
   3. The 0.13 px (pmdsim before this change vs SOFAST) decomposed: corners from SOFAST's mask and pixel-boundary edges with its RANSAC
      perimeter fit / with pmdsim's side selection / from pmdsim's half-level mask / with
      pmdsim's sub-pixel edges; each located by the homography (pmdsim) and by the pose fit
      (SOFAST); the pose's reprojection RMS and the distance it implies vs the measured one.
   4. Edge widths per side (erf fits of the light − dark profile), SOFAST's threshold as a
      fraction of the local step, the inward shift a threshold τ predicts for a Gaussian edge
      (σ·Φ⁻¹(τ)) and the centre shift that follows, vs the observed side offsets.
C. (printed before B) A replica of the real facet: the same, rendered at the pose pmdsim fits to
   the real outline, with the real levels; SOFAST − pmdsim on the replica vs on the real data.
B. Synthetic truth: the facet rendered at SOFAST's pose through the same camera, with the real
   edges' measured blur per side, at 16 sub-pixel positions; each method's error vs the true
   projected centre.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import h5py
import numpy as np
from scipy.special import ndtri
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import sofast_reference as ref  # noqa: E402

from pmdsim.io.importers.outline import outline_point_pixel, outline_pose  # noqa: E402
from pmdsim.io.importers.sofast import _mask, facet_outline_corners, read_sofast_camera  # noqa: E402

DATA = Path(os.environ.get("PMDSIM_SOFAST_DATA", "/work/shared/data/sofast"))
OBJ_M = np.array([[0.606, -0.606, 0], [-0.606, -0.606, 0], [-0.606, 0.606, 0], [0.606, 0.606, 0]])
G = "DataSofastCalculation/general/"
GF = "DataSofastCalculation/facet/facet_000/"


def locate(cam, corners, obj, screen_cam_m=None, dist_m=None):
    """(homography pixel (u, v), pose pixel (u, v), pose RMS px, distance error m)."""
    h = outline_point_pixel(cam, corners, obj, [0, 0, 0])
    pose = outline_pose(cam, corners, obj)
    p = pose.pixel_of(cam, [0, 0, 0])
    derr = np.nan
    if screen_cam_m is not None:
        derr = dist_m - float(np.linalg.norm(screen_cam_m - pose.T_cam_obj.translation))
    return h, p, pose.rms_px, derr


def real(D: Path):
    e = h5py.File(D / "expected_facet_distorted_2d.h5")
    cam, _ = read_sofast_camera(D / "camera_sofast_downsampled.h5")
    loop = e[GF + "CalculationImageProcessingFacet/loop_facet_image_refine"][()].T
    exp = e[G + "CalculationImageProcessingGeneral/loop_optic_image_exp"][()].T
    mraw = e[G + "CalculationImageProcessingGeneral/mask_raw"][()]
    r1 = e[G + "CalculationDataGeometryGeneral/r_optic_cam_refine_1"][()]
    v1 = e[G + "CalculationDataGeometryGeneral/v_cam_optic_cam_refine_1"][()].ravel()
    v2 = e[G + "CalculationDataGeometryGeneral/v_cam_optic_cam_refine_2"][()].ravel()
    meas = h5py.File(D / "measurement_facet.h5")["MeasurementSofastFringe"]
    mimg = meas["mask_images"][()]
    dist_m = float(meas["dist_optic_screen"][()])
    v_screen = h5py.File(D / "spatial_orientation.h5")["SpatialOrientation/v_cam_screen_cam"][()].ravel()
    dark, light = mimg[..., 0], mimg[..., 1]
    delta = light.astype(float) - dark.astype(float)

    print("A1. SOFAST's measure-point pixel from its own intermediates")
    sofast_uv = cam.project(v2[None])[0]
    pose = outline_pose(cam, loop, OBJ_M)
    print(f"    projection of v_cam_optic_cam_refine_2 (SOFAST's pixel): (u, v) = ({sofast_uv[0]:.4f}, {sofast_uv[1]:.4f})")
    print(f"    pose fit of its refined corners (pmdsim camera): translation off the stored one by "
          f"{np.linalg.norm(pose.T_cam_obj.translation - v1) * 1e6:.2f} µm, rotation by "
          f"{np.degrees((Rotation.from_matrix(pose.T_cam_obj.rotation) * Rotation.from_rotvec(r1).inv()).magnitude()) * 3600:.3f}″; "
          f"centre at ({pose.pixel_of(cam, [0, 0, 0])[0]:.4f}, {pose.pixel_of(cam, [0, 0, 0])[1]:.4f}); "
          f"reprojection RMS {pose.rms_px:.3f} px (SOFAST's error_reprojection_1: "
          f"{e[G + 'CalculationError/error_reprojection_1'][()]:.3f})")

    print("A2. SOFAST's mask and corners re-implemented (tests/sofast_reference.py)")
    d32 = light.astype(np.float32) - dark.astype(np.float32)
    ths = []
    for tie in range(6):
        try:
            ths.append((tie, ref.mask_threshold(d32, tie), int((ref.mask_raw(dark, light, tie) ^ mraw).sum())))
        except IndexError:
            break
    print("    equally empty histogram bins between the peaks → possible thresholds (pixels differing from "
          "SOFAST's mask_raw): " + ", ".join(f"{t:.1f} ({n})" for _, t, n in ths))
    tie_sofast = min(ths, key=lambda r: r[2])[0]
    corners_ref = ref.perimeter(ref.pixel_edges(mraw), exp)
    print(f"    corners from SOFAST's mask_raw: max |Δ| vs loop_facet_image_refine = {np.abs(corners_ref - loop).max():.1e} px")

    print("A3. decomposition: corner sets × centre step (u, v px; SOFAST's pixel "
          f"({sofast_uv[0]:.3f}, {sofast_uv[1]:.3f}))")
    print("    | corners | homography (pmdsim's step) | pose fit (SOFAST's step) | pose RMS px | implied distance − measured, mm |")
    mask_half = _mask(dark, light)
    sets = [("SOFAST: its mask (threshold %.1f), pixel-boundary edges, RANSAC perimeter" % ths[tie_sofast][1], loop)]
    for tie, thr, _ in ths:
        if tie != tie_sofast:
            sets.append((f"  same, threshold {thr:.1f} (another empty bin)",
                         ref.perimeter(ref.pixel_edges(ref.mask_raw(dark, light, tie)), exp)))
    sets += [("SOFAST's mask, pmdsim's side selection (binary edges)", facet_outline_corners(mraw)),
             ("pmdsim's half-level mask, SOFAST's RANSAC perimeter", ref.perimeter(ref.pixel_edges(mask_half), exp)),
             ("pmdsim's half-level mask, pmdsim's side selection (binary edges)", facet_outline_corners(mask_half)),
             ("pmdsim: area sub-pixel edges, local levels (the importer's corners)", facet_outline_corners(mask_half, delta))]
    out = {}
    for name, c in sets:
        h, p, rms, derr = locate(cam, c, OBJ_M, v_screen, dist_m)
        out[name] = (h, p)
        print(f"    | {name} | ({h[0]:.3f}, {h[1]:.3f}) | ({p[0]:.3f}, {p[1]:.3f}) | {rms:.3f} | {derr * 1e3:+.1f} |")

    print("A4. edges per side (light − dark profiles, erf fits on 40 lines each)")
    ours = facet_outline_corners(mask_half, delta)
    prof = ref.edge_profiles(delta, ours)
    thr = ths[tie_sofast][1]
    cen = ours.mean(axis=0)
    shift = {}
    names = ref.SIDES
    for i, nm in enumerate(names):
        a, b = ours[i], ours[(i + 1) % 4]
        d = b - a
        n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        n = n if n @ (cen - a) > 0 else -n
        mid_s = 0.5 * (loop[i] + loop[(i + 1) % 4])
        off = float((mid_s - 0.5 * (a + b)) @ n)  # SOFAST's side inward of pmdsim's, px
        r = prof[nm]
        dk, st, sg = np.median(r[:, 0]), np.median(r[:, 1]), np.median(r[:, 3])
        tau = (thr - dk) / st
        pred = sg * ndtri(tau) - sg * ndtri((0.5 * (np.median(delta[mask_half]) + np.median(delta[~mask_half])) - dk) / st)
        shift[nm] = (off, pred)
        print(f"    {nm:6s}: σ {sg:.3f} px (IQR {np.percentile(r[:, 3], 25):.3f}–{np.percentile(r[:, 3], 75):.3f}), "
              f"outside {dk:.1f}, step {st:.1f}; SOFAST's threshold = {tau:.2f} of the local step → predicted "
              f"inward shift vs the half level {pred:+.3f} px; observed (SOFAST's side vs pmdsim's) {off:+.3f} px")
    du_pred = 0.5 * (shift["left"][1] - shift["right"][1])
    du_obs = 0.5 * (shift["left"][0] - shift["right"][0])
    dv_pred = 0.5 * (shift["top"][1] - shift["bottom"][1])
    dv_obs = 0.5 * (shift["top"][0] - shift["bottom"][0])
    print(f"    centre shift SOFAST − pmdsim from the side offsets: predicted by the threshold on Gaussian edges "
          f"(Δu, Δv) = ({du_pred:+.3f}, {dv_pred:+.3f}) px; from the observed sides ({du_obs:+.3f}, {dv_obs:+.3f}) px")
    real_data = dict(delta=delta, mask=mask_half, loop=loop, threshold=ths[tie_sofast][1], sofast_uv=sofast_uv,
                     ours=out["pmdsim: area sub-pixel edges, local levels (the importer's corners)"],
                     ours_rms=outline_pose(cam, facet_outline_corners(mask_half, delta), OBJ_M).rms_px)
    return cam, prof, (Rotation.from_rotvec(r1).as_matrix(), 1e3 * v1), exp, real_data


def calibrated_blur(cam, R, t, prof, dark=0.0, lit=216.0):
    """Optical σ per side such that the rendered edges re-measure (erf fits) as the real ones."""
    target = {k: float(np.median(v[:, 3])) for k, v in prof.items()}
    sig = {k: float(np.sqrt(max(v**2 - 1.0 / 12.0, 0.0))) for k, v in target.items()}
    for _ in range(4):
        img = ref.render_facet(cam, R, t, 606.0, sig, dark, lit)
        got = ref.edge_profiles(img, facet_outline_corners(_mask(np.zeros_like(img), img), img))
        sig = {k: max(0.0, sig[k] + target[k] - float(np.median(got[k][:, 3]))) for k in sig}
    return sig


def replica(cam, prof, exp, real_data, n_seeds=9):
    """C. The real facet re-rendered: at the pose pmdsim fits to its outline, with the real
    outside/inside levels (quadratic fields near the outline) and the measured blur per side,
    8-bit; SOFAST's method at SOFAST's threshold and pmdsim's, each vs the replica's true centre,
    and their difference vs the real one."""
    from pmdsim.io.importers.sofast import measure_point_pixel

    obj = 1e3 * OBJ_M
    loc = measure_point_pixel(real_data["mask"], cam, obj, [0, 0, 0], real_data["delta"])
    R, t = loc.T_cam_obj.rotation, loc.T_cam_obj.translation
    B, L = ref.level_fields(real_data["delta"], real_data["mask"])
    sig = calibrated_blur(cam, R, t, prof)
    img = ref.render_facet(cam, R, t, 606.0, sig, B, L)
    truth = cam.project(t[None])[0]
    rows = []
    for seed in range(n_seeds):
        # 8-bit dark and light images; seed 0 without noise, the others with 1 DN per image.
        rng = np.random.default_rng(seed)
        sd = 0.0 if seed == 0 else 1.0
        dark = np.clip(np.round(14.0 + sd * rng.normal(size=img.shape)), 0, 255).astype(np.uint8)
        light = np.clip(np.round(14.0 + img + sd * rng.normal(size=img.shape)), 0, 255).astype(np.uint8)
        delta = light.astype(float) - dark
        ours = measure_point_pixel(_mask(dark, light), cam, obj, [0, 0, 0], delta)
        uv_p = np.array([ours.pixel_vu[1], ours.pixel_vu[0]])
        mr = ref.mask_raw(dark, light, threshold=real_data["threshold"])
        c_s = ref.perimeter(ref.pixel_edges(mr), exp)
        uv_s = outline_pose(cam, c_s, obj).pixel_of(cam, [0, 0, 0])
        rows.append(np.r_[uv_p - truth, uv_s - truth, np.abs(c_s - real_data["loop"]).max(),
                          np.abs(ours.corners_px - loc.corners_px).max()])
    rows = np.array(rows)
    e_p, e_s = rows[:, 0:2], rows[:, 2:4]
    real_diff = real_data["sofast_uv"] - real_data["ours"][1]
    print("C. replica of the real facet (pose of pmdsim's outline fit, real levels, blur " +
          ", ".join(f"{k} {v:.3f}" for k, v in sig.items()) + " px, 8 bit), SOFAST's threshold "
          f"{real_data['threshold']:.1f}")
    print(f"    replica's corners vs the real ones (noise-free): SOFAST's method max |Δ| {rows[0, 4]:.3f} px, "
          f"pmdsim's {rows[0, 5]:.3f} px")
    print(f"    pmdsim (pose fit) − truth: noise-free ({e_p[0, 0]:+.3f}, {e_p[0, 1]:+.3f}) px, with noise "
          f"({e_p[1:, 0].mean():+.3f} ± {e_p[1:, 0].std():.3f}, {e_p[1:, 1].mean():+.3f} ± {e_p[1:, 1].std():.3f}) px")
    print(f"    SOFAST's method − truth: noise-free ({e_s[0, 0]:+.3f}, {e_s[0, 1]:+.3f}) px, with noise "
          f"({e_s[1:, 0].mean():+.3f} ± {e_s[1:, 0].std():.3f}, {e_s[1:, 1].mean():+.3f} ± {e_s[1:, 1].std():.3f}) px "
          f"[{n_seeds - 1} seeds]")
    d = e_s - e_p
    print(f"    SOFAST − pmdsim: replica noise-free ({d[0, 0]:+.3f}, {d[0, 1]:+.3f}), with noise ({d[1:, 0].mean():+.3f} ± "
          f"{d[1:, 0].std():.3f}, {d[1:, 1].mean():+.3f} ± {d[1:, 1].std():.3f}) px; real data "
          f"({real_diff[0]:+.3f}, {real_diff[1]:+.3f}) px")


def synthetic(cam, prof, pose, exp, n_shift=4, noise=1.0, seed=12, real_rms=float("nan")):
    R, t0 = pose
    rng = np.random.default_rng(seed)
    sig = calibrated_blur(cam, R, t0, prof)
    blur = ", ".join(f"{k} {v:.3f}" for k, v in sig.items())
    print("B. synthetic facet at SOFAST's pose, optical blur per side (adjusted until the rendered edges "
          f"re-measure as the real ones): {blur} px; dark 14, lit 230 DN, noise {noise:g} DN per image, 8 bit; "
          f"{n_shift}×{n_shift} sub-pixel positions")
    obj = 1e3 * OBJ_M
    errs = {k: [] for k in ("pmdsim edges + homography", "pmdsim edges + pose fit (the importer)",
                            "SOFAST-like (threshold, pixel edges, RANSAC) + pose fit (SOFAST)",
                            "SOFAST-like + homography")}
    check = None
    rms = []
    for i in range(n_shift):
        for j in range(n_shift):
            du, dv = i / n_shift, j / n_shift
            t = t0 + np.array([du * t0[2] / cam.fx_px, dv * t0[2] / cam.fy_px, 0.0])
            img = ref.render_facet(cam, R, t, 606.0, sig, 0.0, 216.0)
            truth = cam.project(t[None])[0]
            # 8-bit dark and light images with the camera's noise (seeded).
            dark = np.clip(np.round(14.0 + rng.normal(0.0, noise, img.shape)), 0, 255).astype(np.uint8)
            light = np.clip(np.round(14.0 + img + rng.normal(0.0, noise, img.shape)), 0, 255).astype(np.uint8)
            delta = light.astype(float) - dark.astype(float)
            m = _mask(dark, light)
            c_p = facet_outline_corners(m, delta)
            mr = ref.mask_raw(dark, light)
            c_s = ref.perimeter(ref.pixel_edges(mr), exp + [du, dv])
            errs["pmdsim edges + homography"].append(outline_point_pixel(cam, c_p, obj, [0, 0, 0]) - truth)
            pp = outline_pose(cam, c_p, obj)
            rms.append(pp.rms_px)
            errs["pmdsim edges + pose fit (the importer)"].append(pp.pixel_of(cam, [0, 0, 0]) - truth)
            errs["SOFAST-like (threshold, pixel edges, RANSAC) + pose fit (SOFAST)"].append(
                outline_pose(cam, c_s, obj).pixel_of(cam, [0, 0, 0]) - truth)
            errs["SOFAST-like + homography"].append(outline_point_pixel(cam, c_s, obj, [0, 0, 0]) - truth)
            if check is None:
                check = ref.edge_profiles(delta, c_p)
    print("    rendered edges re-measured (σ px): " + ", ".join(f"{k} {np.median(v[:, 3]):.3f}" for k, v in check.items())
          + " (real: " + ", ".join(f"{k} {np.median(v[:, 3]):.3f}" for k, v in prof.items()) + ")")
    print(f"    pose fit of pmdsim's corners: reprojection RMS {np.mean(rms):.3f} px (max {np.max(rms):.3f}; real data {real_rms:.3f})")
    print("    | method | error u: mean ± sd, max | | error v: mean ± sd, max | |")
    for k, v in errs.items():
        v = np.array(v)
        print(f"    | {k} | {v[:, 0].mean():+.3f} ± {v[:, 0].std():.3f} | {np.abs(v[:, 0]).max():.3f} | "
              f"{v[:, 1].mean():+.3f} ± {v[:, 1].std():.3f} | {np.abs(v[:, 1]).max():.3f} |")
    return errs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--shifts", type=int, default=4)
    a = ap.parse_args()
    cam, prof, pose, exp, real_data = real(a.data)
    replica(cam, prof, exp, real_data)
    if not a.no_synthetic:
        synthetic(cam, prof, pose, exp, a.shifts, real_rms=real_data["ours_rms"])


if __name__ == "__main__":
    main()
