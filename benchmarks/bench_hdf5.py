"""Benchmark writing a full-resolution ``evaluation.h5`` (issue 25 item 1) with several HDF5
chunking / compression choices, and reading it back with h5py and xarray.

The data: two 1920×1200 cameras with the dtypes and shapes ``pmdsim evaluate`` writes
(:func:`pmdsim.io.hdf5.write_evaluation_h5` + :func:`~pmdsim.io.hdf5.write_consistency_h5`),
filled with smooth maps plus the noise a decoded measurement has (screen coordinates ±5 µm,
heights ±10 nm, normals ±10 µrad), NaN outside an elliptical field of view (≈ 70 % of the
pixels valid) — float noise in the low mantissa bits is what limits the compression of real maps.

    PYTHONPATH=src python benchmarks/bench_hdf5.py [--repeat 3] [--only "lzf + shuffle|gzip 1"]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from types import SimpleNamespace

import h5py
import numpy as np

from pmdsim.io import hdf5

GZ1S = dict(compression="gzip", compression_opts=1, shuffle=True)
LZFS = dict(compression="lzf", shuffle=True)
#: name → (float-map filters, bool/int-map filters, rows per chunk; None: contiguous, no filters)
FILTERS = {
    "none (contiguous)": ({}, {}, None),
    "none (64-row chunks)": ({}, {}, 64),
    "gzip 1": (dict(compression="gzip", compression_opts=1), dict(compression="gzip", compression_opts=1), 64),
    "gzip 1 + shuffle": (GZ1S, GZ1S, 64),
    "gzip 4 + shuffle": (dict(GZ1S, compression_opts=4), dict(GZ1S, compression_opts=4), 64),
    "lzf": (dict(compression="lzf"), dict(compression="lzf"), 64),
    "lzf + shuffle": (LZFS, LZFS, 64),
    "gzip 1 + shuffle, 256-row chunks": (GZ1S, GZ1S, 256),
    "floats none, ints gzip 1 + shuffle": ({}, GZ1S, 64),
}


def camera(rng, H=1200, W=1920):
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    inside = ((u - W / 2) / (0.48 * W)) ** 2 + ((v - H / 2) / (0.48 * H)) ** 2 < 1.0
    nan = np.where(inside, 1.0, np.nan)
    xy = np.stack([0.17 * u - 160 + 1e-6 * u * v, 0.17 * v - 100 + 1e-6 * u * u], -1)
    xy = (xy + rng.normal(0, 5e-3, xy.shape)) * nan[..., None]
    std = (np.full(xy.shape, 3e-3) + rng.normal(0, 2e-4, xy.shape)) * nan[..., None]
    x, y = 0.11 * (u - W / 2), 0.11 * (v - H / 2)
    h = (-(x**2 + y**2) / 4e5 + rng.normal(0, 1e-5, x.shape)) * nan
    n = np.stack([x / 2e5, y / 2e5, np.ones_like(x)], -1) + rng.normal(0, 1e-5, (H, W, 3))
    n = n / np.linalg.norm(n, axis=-1, keepdims=True) * nan[..., None]
    p = np.stack([x, y, h], -1) * nan[..., None]
    flags = np.where(inside, 0, 1).astype(np.uint8)
    dec = SimpleNamespace(screen_xy_mm=xy, std_xy_mm=std, valid=inside, flags=flags)
    reg = SimpleNamespace(status=np.where(inside, 0, 2).astype(np.uint8))
    rec = SimpleNamespace(n_sample=n, p_sample_mm=p, height_mm=h, reconstructed=inside, method="least_squares",
                          seed_pixel=(600, 960), converged=True, iterations=12)
    slopes = n[..., :2] / n[..., 2:]
    extras = {"slopes": slopes, "height_detrended_mm": h - np.nanmean(h),
              "residual_slopes": slopes - np.stack([x / 2e5, y / 2e5], -1)}
    cons = SimpleNamespace(flags=np.zeros((H, W), np.uint8),
                           fit_residual_ratio=(rng.gamma(2, 0.1, (H, W)) * nan).astype(np.float32),
                           period_mismatch_ratio=(np.abs(rng.normal(0, 0.2, (H, W))) * nan).astype(np.float32),
                           worst_image=np.where(inside, rng.integers(0, 24, (H, W)), -1).astype(np.int16),
                           false_alarm=1e-6, noise_model=(0.5, 0.01), reasons=lambda: [])
    return (dec, reg, rec), extras, cons


def write(path, data, filters, rows, int_filters=None):
    hdf5.FLOAT_FILTERS = filters
    hdf5.INT_FILTERS = filters if int_filters is None else int_filters
    hdf5.CHUNK_ROWS = rows if rows else 10**9
    results = {c: d[0] for c, d in data.items()}
    extras = {c: d[1] for c, d in data.items()}
    t0 = time.perf_counter()
    hdf5.write_evaluation_h5(path, results, {"pmdsim_version": "bench"}, extras=extras)
    hdf5.write_consistency_h5(path, {c: d[2] for c, d in data.items()}, {c: ["a.png"] for c in data})
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default=None, help="variant names separated by | (default: all)")
    args = ap.parse_args()
    rng = np.random.default_rng(1)
    data = {"left": camera(rng), "right": camera(rng)}
    nbytes = sum(a.nbytes for d in data.values() for a in (
        *[getattr(o, k) for o in d[0] for k in vars(o) if isinstance(getattr(o, k), np.ndarray)],
        *d[1].values(), *[v for v in vars(d[2]).values() if isinstance(v, np.ndarray)]))
    print(f"raw data {nbytes / 1e6:.0f} MB (two 1920×1200 cameras); load {os.getloadavg()[0]:.2f}")
    print(f"{'filters':36s} {'write s':>8s} {'MB':>7s} {'MB/s':>6s} {'read h5py s':>11s} {'xarray s':>8s}")
    orig = (hdf5.FLOAT_FILTERS, hdf5.INT_FILTERS, hdf5.CHUNK_ROWS)
    with tempfile.TemporaryDirectory() as d:
        try:  # imported before the first timing, so that no row pays for it
            import xarray  # noqa: F401
        except ImportError:
            pass
        chosen = FILTERS if args.only is None else {k: FILTERS[k] for k in args.only.split("|")}
        for name, (filters, int_filters, rows) in chosen.items():
            path = os.path.join(d, "evaluation.h5")
            times = []
            for _ in range(args.repeat):
                if os.path.exists(path):
                    os.unlink(path)
                times.append(write(path, data, filters, rows, int_filters) if rows else _write_contiguous(path, data))
            size = os.path.getsize(path)
            t0 = time.perf_counter()
            with h5py.File(path) as f:
                for c in f.values():
                    for v in c.values():
                        v[()]
            t_read = time.perf_counter() - t0
            t_xr = float("nan")
            try:
                import xarray as xr

                t0 = time.perf_counter()
                dt = xr.open_datatree(path, engine="h5netcdf")
                dt.load()
                t_xr = time.perf_counter() - t0
            except ImportError:
                pass
            best = min(times)
            print(f"{name:36s} {best:8.2f} {size / 1e6:7.1f} {nbytes / 1e6 / best:6.0f} {t_read:11.2f} {t_xr:8.2f}")
    hdf5.FLOAT_FILTERS, hdf5.INT_FILTERS, hdf5.CHUNK_ROWS = orig
    print(f"load {os.getloadavg()[0]:.2f}")


def _write_contiguous(path, data):
    """No filters, no chunks (what h5py writes by default)."""
    put = hdf5._put

    def unchunked(g, name, arr, *, compress=True, **kw):
        return put(g, name, arr, compress=False, **kw)

    hdf5._put = unchunked
    try:
        return write(path, data, {}, 64)
    finally:
        hdf5._put = put


if __name__ == "__main__":
    main()
