"""Issue 12's end-to-end check on the shared SOFAST measurement: ``pmdsim import sofast`` +
``pmdsim evaluate`` (run as subprocesses, exactly as a user would), then pmdsim's results against
SOFAST's own evaluation (``expected_facet_distorted_2d.h5``):

1. decoded screen points vs SOFAST's ``v_screen_points_fractional_screens`` (µm on the screen);
2. slopes vs SOFAST's ``slopes_facet_xy`` after SOFAST's alignment (pmdsim's normals rotated into
   SOFAST's aligned facet frame: r_cam_optic, v_cam_optic_cam, trans_alignment about the align
   point);
3. focal lengths of the paraboloid over the slopes vs SOFAST's ``surf_coefs_facet``;
4. heights after piston/tilt removal vs an independent integration of SOFAST's slopes (scipy
   sparse least squares of the trapezoidal rule on the pixel grid), p95.

    python benchmarks/sofast_check.py [--display distorted_2d|distorted_3d|rectangular] [--data DIR]

Prints one line per figure with its target. Needs only the shared files.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import lsqr
from scipy.spatial.transform import Rotation

DATA = Path(os.environ.get("PMDSIM_SOFAST_DATA", "/work/shared/data/sofast"))


def run(args):
    r = subprocess.run([sys.executable, "-m", "pmdsim.cli", *args], capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"pmdsim {' '.join(args)} failed ({r.returncode}):\n{r.stderr}")
    return r


def integrate_slopes(mask, xy, g):
    """Heights z on the mask's pixels from slopes g (M, 2) at points xy (M, 2) by least squares of
    z_b − z_a = ½(g_a + g_b)·(xy_b − xy_a) over 4-neighbour pairs, plus Σz = 0."""
    H, W = mask.shape
    idx = -np.ones((H, W), int)
    idx[mask] = np.arange(mask.sum())
    rows, cols, vals, rhs = [], [], [], []
    r = 0
    for dv, du in ((0, 1), (1, 0)):
        a = idx[: H - dv, : W - du]
        b = idx[dv:, du:]
        ok = (a >= 0) & (b >= 0)
        ia, ib = a[ok], b[ok]
        n = ia.size
        rr = r + np.arange(n)
        rows += [rr, rr]
        cols += [ib, ia]
        vals += [np.ones(n), -np.ones(n)]
        rhs.append(0.5 * ((g[ia] + g[ib]) * (xy[ib] - xy[ia])).sum(axis=1))
        r += n
    rows.append(np.full(mask.sum(), r))
    cols.append(np.arange(mask.sum()))
    vals.append(np.ones(mask.sum()))
    rhs.append(np.zeros(1))
    A = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                   shape=(r + 1, mask.sum())).tocsr()
    return lsqr(A, np.concatenate(rhs), atol=1e-14, btol=1e-14, iter_lim=20000)[0]


def detrend(x, y, z):
    A = np.stack([np.ones_like(x), x, y], axis=-1)
    c, *_ = np.linalg.lstsq(A, z, rcond=None)
    return z - A @ c


def paraboloid_focal(x, y, gx, gy):
    z0, one = np.zeros_like(x), np.ones_like(x)
    A = np.concatenate([np.stack([2 * x, y, z0, one, z0], -1), np.stack([z0, x, 2 * y, z0, one], -1)])
    c, *_ = np.linalg.lstsq(A, np.concatenate([gx, gy]), rcond=None)
    return 1 / (4 * c[0]), 1 / (4 * c[2])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--display", default="distorted_2d", choices=["distorted_2d", "distorted_3d", "rectangular"])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--method", default=None, choices=["stepwise", "least_squares"],
                    help="default: the image set's (least_squares, as the importer declares)")
    ap.add_argument("--anchor-pixel", type=float, nargs=2, default=None,
                    help="control: override the imported anchor's pixel (row, column), e.g. SOFAST's refined "
                         "measure-point pixel 98.0868 111.8048")
    a = ap.parse_args()
    D = a.data
    work = a.work or Path(tempfile.mkdtemp(prefix="sofast_check_"))
    imp, ev = work / "import", work / "eval"
    run(["import", "sofast", "--measurement", str(D / "measurement_facet.h5"),
         "--camera", str(D / "camera_sofast_downsampled.h5"), "--display", str(D / f"display_{a.display}.h5"),
         "--orientation", str(D / "spatial_orientation.h5"), "--calibration", str(D / "image_calibration.h5"),
         "--facet", str(D / "Facet_NSTTF.json"), "--out", str(imp), "--force"])
    extra = []
    if a.anchor_pixel is not None:
        anc = json.loads((imp / "images" / "manifest.json").read_text())["anchor"]
        extra = ["--anchor-distance-mm", str(anc["distance_mm"]), "--anchor-pixel", *map(str, a.anchor_pixel),
                 "--anchor-point-mm", *map(str, anc["point_world_mm"])]
    r = run(["evaluate", str(imp / "images"), "--setup", str(imp / "setup.toml"), "--out", str(ev), "--force",
             "--quiet", *(["--method", a.method] if a.method else []), *extra])
    print(r.stdout.strip())
    fit = json.loads((ev / "surface_fit.json").read_text())

    from pmdsim.io.importers import pattern_mm_to_fraction
    from pmdsim.io.imageset import load_manifest
    from pmdsim.setup import load_setup

    setup = load_setup(imp / "setup.toml")
    size = load_manifest(imp / "images").screen_size_mm
    with h5py.File(ev / "evaluation.h5") as f:
        g = f["camera"]
        n_sample = g["normals"][()]
        p_sample = g["points_mm"][()]
        rec = g["reconstructed"][()]
    # Pattern coordinates before the screen map: decode again without it (same code path).
    from pmdsim.io.imageset import decode_camera_images, load_camera_stacks

    m = load_manifest(imp / "images")
    dec = decode_camera_images(load_camera_stacks(m, "camera"), m.screen_size_mm, response=m.instrument.response)

    e = h5py.File(D / "expected_facet_distorted_2d.h5")
    gf = "DataSofastCalculation/facet/facet_000/"
    mask = e[gf + "CalculationImageProcessingFacet/mask_processed"][()]
    frac = e[gf + "CalculationDataGeometryFacet/v_screen_points_fractional_screens"][()].T
    slopes_s = e[gf + "SlopeSolverData/slopes_facet_xy"][()].T
    surf_s = e[gf + "SlopeSolverData/v_surf_points_facet"][()].T
    coefs = e[gf + "SlopeSolverData/surf_coefs_facet"][()]
    trans = e[gf + "SlopeSolverData/trans_alignment"][()]
    so = gf + "CalculationDataGeometryFacet/SpatialOrientation/"
    r_cam_optic = Rotation.from_rotvec(e[so + "r_cam_optic"][()])
    v_cam_optic = e[so + "v_cam_optic_cam"][()].ravel()
    align = e[gf + "CalculationDataGeometryFacet/v_align_point_facet"][()].ravel()

    # 1. decoded points.
    ours = pattern_mm_to_fraction(dec.screen_xy_mm[mask], size)
    both = np.isfinite(ours).all(axis=1)
    du = np.abs(ours[both] - frac[both]) * np.array(size) * 1e3
    dist_um = np.hypot(du[:, 0], du[:, 1])
    print(f"decoded screen points vs SOFAST: median {np.median(dist_um):.3f} µm, p95 {np.percentile(dist_um, 95):.3f} µm "
          f"(x median {np.median(du[:, 0]):.3f}, y {np.median(du[:, 1]):.3f} µm) over {both.sum()} of {mask.sum()} "
          f"SOFAST pixels; target ≤ 2 µm median")

    # 2. slopes in SOFAST's aligned facet frame: optic ← camera, then the alignment about the align point.
    T_w_s = setup.sample.T_world_sample  # world = camera frame (mm)
    n_cam = T_w_s.apply_vector(n_sample[mask])
    p_cam_m = T_w_s.apply(p_sample[mask]) / 1e3
    R_al = trans[:3, :3]
    n_f = (R_al @ r_cam_optic.apply(n_cam).T).T
    p_opt = r_cam_optic.apply(p_cam_m - v_cam_optic)
    p_f = (R_al @ (p_opt - align).T).T + align + trans[:3, 3]
    # SOFAST's facet normal points towards the camera (+z); pmdsim's towards the camera as well.
    g_ours = -n_f[:, :2] / n_f[:, 2:3]
    ok = rec[mask] & np.isfinite(g_ours).all(axis=1)
    dg = (g_ours[ok] - slopes_s[ok]) * 1e3
    print(f"slopes vs SOFAST (aligned facet frame): x mean {dg[:, 0].mean():+.4f} median {np.median(dg[:, 0]):+.4f}, "
          f"y mean {dg[:, 1].mean():+.4f} median {np.median(dg[:, 1]):+.4f} mrad; RMS {np.sqrt((dg**2).mean()):.4f} mrad "
          f"over {ok.sum()} pixels; target ≤ 0.005 mrad mean/median")

    # 3. focal lengths.
    fx_s, fy_s = 1 / (4 * coefs[2]), 1 / (4 * coefs[5])
    fx_o, fy_o = paraboloid_focal(p_f[ok, 0], p_f[ok, 1], g_ours[ok, 0], g_ours[ok, 1])
    print(f"focal lengths: SOFAST {fx_s * 1e3:.0f} / {fy_s * 1e3:.0f} mm; pmdsim surface_fit.json "
          f"{fit['focal_length_x_mm']:.0f} / {fit['focal_length_y_mm']:.0f} mm "
          f"({100 * (fit['focal_length_x_mm'] / (fx_s * 1e3) - 1):+.2f} %, {100 * (fit['focal_length_y_mm'] / (fy_s * 1e3) - 1):+.2f} %); "
          f"pmdsim slopes fitted in SOFAST's frame {fx_o * 1e3:.0f} / {fy_o * 1e3:.0f} mm "
          f"({100 * (fx_o / fx_s - 1):+.2f} %, {100 * (fy_o / fy_s - 1):+.2f} %); target within 2 %")

    # 4. heights after piston/tilt vs an independent integration of SOFAST's slopes.
    z_ref = integrate_slopes(mask, surf_s[:, :2], slopes_s)
    z_ref = detrend(surf_s[:, 0], surf_s[:, 1], z_ref)
    z_o = detrend(p_f[ok, 0], p_f[ok, 1], p_f[ok, 2])
    dz = np.abs(z_o - detrend(surf_s[ok, 0], surf_s[ok, 1], z_ref[ok])) * 1e6
    print(f"heights after piston/tilt vs integrated SOFAST slopes: p95 {np.percentile(dz, 95):.3f} µm, "
          f"median {np.median(dz):.3f} µm, max {dz.max():.3f} µm; target ≤ 1 µm p95")


if __name__ == "__main__":
    main()
