"""Why Experiment 4's heights change with ``--downsample K`` while its slopes do not (issue 20).

For one effect of Experiment 4 this script runs the budget's chain (calibration with the 3 × 3
free screen, reconstruction, :func:`pmdsim.studies.experiment4.effect_truth`) at every K of
``--ks`` and separates the candidate causes:

1. **Calibration** (K² fewer correspondences → another calibrated geometry): the measurement at
   the coarsest K is reconstructed with the calibration of every finer K (its cameras binned to
   the coarse K) — if the heights follow the calibration, it is the calibration.
2. **Gauge** (seed pixel, table plane): the height RMS with and without the best-fit plane.
3. **Sampling of the slope field** (aliasing): the slope-error map of the finest K is
   subsampled here with numpy at steps s (every offset of the s × s cell), integrated with an
   independent least-squares integrator written here (scipy.sparse, trapezoidal rule between
   4-neighbours, the seed pixel nearest the centre at height 0), and compared with the
   pipeline's own heights at K·s; the same slopes box-averaged over s × s before sampling (an
   anti-aliased sampling) are integrated too. The slope error's 1-D spectra along the rows and
   columns give the share of its variance above each step's Nyquist frequency.

Run (the chain at K = 1 takes minutes: under the heavy-job lock)::

    flock /tmp/pmdsim_heavy.lock nice python benchmarks/diag_exp4_heights_k.py \
        --effect all_systematic --ks 1,4,8
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pmdsim.evaluation.metrics import surface_error_metrics
from pmdsim.evaluation.pipeline import evaluate_decoded
from pmdsim.setup import default_setup
from pmdsim.simulation.imaging import needs_points
from pmdsim.simulation.render import trace_setup_camera
from pmdsim.studies.calibration_data import simulate_decoded
from pmdsim.studies.experiment2 import _with_other_regions, calibrate_and_reconstruct
from pmdsim.studies.experiment4 import BULGE_MM, effect_truth, slope_error_metrics


#: Largest grid (valid pixels) integrated here by the sparse direct solve (memory, time).
MAX_DIRECT = 700_000


def plane_removed_rms_um(x, y, z):
    """RMS (µm) of z (mm) after a least-squares plane a·x + b·y + c."""
    m = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    A = np.column_stack([x[m], y[m], np.ones(m.sum())])
    coef, *_ = np.linalg.lstsq(A, z[m], rcond=None)
    return float(np.sqrt(np.mean((z[m] - A @ coef) ** 2)) * 1e3)


def integrate_ls(gx, gy, x, y, valid):
    """Least-squares heights from slopes on a pixel grid (trapezoidal rule between 4-neighbours).

    Independent of pmdsim's integrators: each valid neighbour pair (a, b) gives the equation
    z_b − z_a = ½(g_a + g_b)·(xy_b − xy_a); the normal equations (a graph Laplacian) are solved
    by a sparse direct solve with the valid pixel nearest the grid's centre held at 0 (one
    connected component: the largest).
    """
    from scipy import ndimage

    lab, n = ndimage.label(valid)
    if n == 0:
        raise ValueError("no valid pixel")
    sizes = np.bincount(lab.ravel())[1:]
    valid = lab == (1 + int(np.argmax(sizes)))
    H, W = valid.shape
    idx = -np.ones((H, W), dtype=np.int64)
    idx[valid] = np.arange(valid.sum())
    rows, cols, rhs = [], [], []
    for dv, du in ((0, 1), (1, 0)):
        a = valid[: H - dv, : W - du] & valid[dv:, du:]
        ia = idx[: H - dv, : W - du][a]
        ib = idx[dv:, du:][a]
        sl_a = (slice(0, H - dv), slice(0, W - du))
        sl_b = (slice(dv, H), slice(du, W))
        dx = x[sl_b][a] - x[sl_a][a]
        dy = y[sl_b][a] - y[sl_a][a]
        rhs.append(0.5 * ((gx[sl_a][a] + gx[sl_b][a]) * dx + (gy[sl_a][a] + gy[sl_b][a]) * dy))
        rows.append(ia)
        cols.append(ib)
    ia, ib, r = np.concatenate(rows), np.concatenate(cols), np.concatenate(rhs)
    m = len(r)
    nv = int(valid.sum())
    D = sp.csr_matrix((np.r_[-np.ones(m), np.ones(m)], (np.r_[np.arange(m), np.arange(m)], np.r_[ia, ib])),
                      shape=(m, nv))
    vv, uu = np.nonzero(valid)
    seed = int(np.argmin((vv - H / 2) ** 2 + (uu - W / 2) ** 2))
    keep = np.ones(nv, bool)
    keep[seed] = False
    Dk = D[:, keep]
    z = np.zeros(nv)
    z[keep] = spla.spsolve((Dk.T @ Dk).tocsc(), Dk.T @ r)
    out = np.full((H, W), np.nan)
    out[valid] = z
    return out


def slopes(n):
    """(gx, gy) = (−n_x/n_z, −n_y/n_z): the slope error against the true plane z = 0."""
    n = np.asarray(n, dtype=float)
    return -n[..., 0] / n[..., 2], -n[..., 1] / n[..., 2]


def height_stats(x, y, z):
    m = np.isfinite(z)
    return {"rms_um": float(np.sqrt(np.nanmean(z[m] ** 2)) * 1e3), "rms_plane_removed_um": plane_removed_rms_um(x, y, z),
            "n": int(m.sum())}


def run_chain(base, effect, k, method):
    truth = effect_truth(base, effect, k)
    t0 = time.perf_counter()
    e2 = calibrate_and_reconstruct(truth, bulge_mm=BULGE_MM, method=method, start_seed=[0, 3000], screen_grid=3)
    return truth, e2, time.perf_counter() - t0


def reconstruct_with(model, truth, cam, method):
    """The measurement of ``truth`` (camera ``cam``) reconstructed with the calibrated ``model``
    (as :func:`calibrate_and_reconstruct` does, seed: the decoded pixel nearest the centre)."""
    m = trace_setup_camera(truth, cam, store_points=needs_points(truth))
    decoded = simulate_decoded(truth, cam, m)
    c = model.cameras[cam].camera
    rows, cols = np.nonzero(decoded.valid)
    k = int(np.argmin((rows - c.height_px // 2) ** 2 + (cols - c.width_px // 2) ** 2))
    reg, rec = evaluate_decoded(model, cam, decoded, method=method, seed_pixel=(int(rows[k]), int(cols[k])),
                                seed_height_mm=0.0, screen_model=model.screen.surface)
    rec, _ = _with_other_regions(reg, rec, method)
    err = np.where(rec.reconstructed, rec.height_mm, np.nan)
    p = rec.p_sample_mm
    return {**{k: surface_error_metrics(p[..., 0], p[..., 1], err)[k] for k in ("rms_um", "tilt_urad")},
            "rms_plane_removed_um": plane_removed_rms_um(p[..., 0], p[..., 1], err),
            **slope_error_metrics(rec.n_sample)}


def spectrum_shares(g, valid, steps):
    """Share of the slope error's variance above the Nyquist frequency 1/(2s) (cycles per pixel of
    this grid) of each step s, from 1-D periodograms along the rows and the columns of the
    largest all-valid rectangle's rows/columns (mean removed per line)."""
    out = {}
    for axis, name in ((1, "along_rows"), (0, "along_cols")):
        lines = []
        gg = g if axis == 1 else g.T
        vv = valid if axis == 1 else valid.T
        for i in range(gg.shape[0]):
            ok = vv[i]
            if ok.sum() < 64:
                continue
            # the longest valid run of the line
            d = np.diff(np.r_[0, ok.astype(int), 0])
            s0, s1 = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
            j = int(np.argmax(s1 - s0))
            seg = gg[i, s0[j]:s1[j]]
            if seg.size >= 64:
                lines.append(seg[:256] - seg[:256].mean())
        L = min(len(s) for s in lines)
        P = np.mean([np.abs(np.fft.rfft(s[:L])) ** 2 for s in lines], axis=0)
        f = np.fft.rfftfreq(L)
        tot = P[1:].sum()
        out[name] = {f"above_nyquist_step{s}": float(P[1:][f[1:] > 0.5 / s].sum() / tot) for s in steps}
        top = np.argsort(P[1:])[::-1][:3] + 1
        out[name]["peaks_cycles_per_px"] = [float(f[t]) for t in top]
        out[name]["peaks_share"] = [float(P[t] / tot) for t in top]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--effect", default="all_systematic")
    ap.add_argument("--ks", default="2,4,8", help="comma-separated K (the first is the fine map)")
    ap.add_argument("--method", default="stepwise")
    ap.add_argument("--steps", default=None, help="subsampling steps of the fine map (default: K / K_fine)")
    ap.add_argument("--maps", default=None, help="npz prefix of saved maps: subsample those (no chain run)")
    ap.add_argument("--save", default=None, help="npz prefix for the maps")
    a = ap.parse_args()
    ks = [int(v) for v in a.ks.split(",")]
    report = {"effect": a.effect, "ks": ks, "pipeline": {}, "swap": {}, "subsampled": {}, "spectrum": {}}
    if a.maps:  # only step 3, from the maps a previous run saved (--save): no chain is run
        maps = []
        for cam in ("left", "right"):
            d = np.load(f"{a.maps}_{a.effect}_k{ks[0]}_{cam}.npz")
            maps.append((cam, d["n"], d["valid"], d["p"]))
        subsample_and_integrate(a, ks, maps, report)
        return
    base = default_setup()
    runs = {}
    for k in ks:
        truth, e2, sec = run_chain(base, a.effect, k, a.method)
        runs[k] = (truth, e2)
        for c in e2.cases:
            p = c.p_sample_mm.astype(float)
            rec = {"seconds": round(sec, 1), "rms_um": c.metrics["rms_um"], "tilt_urad": c.metrics["tilt_urad"],
                   "rms_plane_removed_um": plane_removed_rms_um(p[..., 0], p[..., 1], c.height_error_mm),
                   "n": c.metrics["n_pixels"], **slope_error_metrics(c.n_sample),
                   "table_turn_urad": e2.deviation["table_turn_deg"] * np.pi / 180 * 1e6}
            report["pipeline"][f"K{k}_{c.camera}"] = rec
            if a.save:
                np.savez_compressed(f"{a.save}_{a.effect}_k{k}_{c.camera}.npz", n=c.n_sample, p=c.p_sample_mm,
                                    h=c.height_error_mm, valid=c.reconstructed)
        print(json.dumps(report["pipeline"], indent=1), flush=True)
    # 1. calibration swap: the coarsest measurement with every finer calibration.
    kc = ks[-1]
    for k in ks[:-1]:
        if kc % k:
            continue
        model = runs[k][1].model.binned(kc // k)
        for cam in runs[kc][0].cameras:
            report["swap"][f"meas K{kc}, calib K{k}, {cam}"] = reconstruct_with(model, runs[kc][0], cam, a.method)
    print(json.dumps(report["swap"], indent=1), flush=True)
    subsample_and_integrate(a, ks, [(c.camera, c.n_sample, c.reconstructed, c.p_sample_mm) for c in runs[ks[0]][1].cases],
                            report)


def subsample_and_integrate(a, ks, maps, report):
    """3. the finest slope map (``maps``: (camera, n, reconstructed, p) of K = ks[0]) subsampled
    and integrated here, and its spectrum."""
    kf = ks[0]
    for camera, n_sample, reconstructed, p_sample_mm in maps:
        gx, gy = slopes(n_sample)
        valid = reconstructed & np.isfinite(gx)
        x, y = p_sample_mm[..., 0].astype(float), p_sample_mm[..., 1].astype(float)
        steps = [int(v) for v in a.steps.split(",")] if a.steps else [k // kf for k in ks if k % kf == 0]
        res = {}
        for s in steps:
            per_off = []
            if s == 1 and valid.sum() > MAX_DIRECT:
                print(f"{camera}: step 1 has {int(valid.sum())} pixels, over the direct solve's "
                      f"{MAX_DIRECT}: not integrated here (the pipeline's figure is above)", flush=True)
                continue
            for off in range(s):  # diagonal offsets (off, off) of the s × s cell
                sl = (slice(off, None, s), slice(off, None, s))
                z = integrate_ls(gx[sl], gy[sl], x[sl], y[sl], valid[sl])
                per_off.append(height_stats(x[sl], y[sl], z))
            # anti-aliased: box-average the slopes over the s × s cell, then sample
            H, W = (valid.shape[0] // s) * s, (valid.shape[1] // s) * s

            def box(a):
                return a[:H, :W].reshape(H // s, s, W // s, s).mean(axis=(1, 3))
            vb = valid[:H, :W].reshape(H // s, s, W // s, s).all(axis=(1, 3))
            gxb, gyb = box(np.where(valid, gx, 0)), box(np.where(valid, gy, 0))
            xb, yb = box(np.nan_to_num(x)), box(np.nan_to_num(y))
            zb = integrate_ls(gxb, gyb, xb, yb, vb)
            res[f"step{s}"] = {"sampled_per_offset": per_off, "box_averaged": height_stats(xb, yb, zb)}
            print(camera, s, json.dumps(res[f"step{s}"]), flush=True)
        report["subsampled"][camera] = res
        report["spectrum"][camera] = {"gx": spectrum_shares(gx, valid, steps), "gy": spectrum_shares(gy, valid, steps)}
    print(json.dumps({"spectrum": report["spectrum"]}, indent=1))
    if a.save:
        with open(f"{a.save}_{a.effect}_report.json", "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
