"""Time of the Table 2/3 figures of merit at full resolution (issue 15): the plane fit.

A synthetic 1920 × 1200 error field (a tilted plane plus noise, 5 % NaN, 2.19 M finite points)
through :func:`pmdsim.evaluation.metrics.surface_error_metrics` (normal-equation sums), and the
former ``numpy.linalg.lstsq`` of the (n, 3) design matrix on the same points, best of
``--repeat``.

    python benchmarks/bench_metrics.py [--repeat 5] [--json]
"""

from __future__ import annotations

import argparse

import numpy as np

from _common import best_of, dump_json
from pmdsim.evaluation.metrics import surface_error_metrics


def lstsq_metrics(x, y, e):
    """The former implementation (pmdsim ≤ 2b3039d): lstsq of the centred design matrix."""
    x, y, e = (np.asarray(v, dtype=float).ravel() for v in (x, y, e))
    m = np.isfinite(x) & np.isfinite(y) & np.isfinite(e)
    x, y, e = x[m], y[m], e[m]
    xc, yc = x - x.mean(), y - y.mean()
    A = np.column_stack([xc, yc, np.ones_like(xc)])
    (a, b, c), *_ = np.linalg.lstsq(A, e, rcond=None)
    resid = e - A @ np.array([a, b, c])
    return {"max_dev_plane_um": float(np.abs(resid).max() * 1e3), "tilt_x_urad": a * 1e6, "tilt_y_urad": b * 1e6,
            "max_height_diff_um": float((e.max() - e.min()) * 1e3), "rms_um": float(np.sqrt(np.mean(e**2)) * 1e3)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:1200, 0:1920] * 0.1
    x, y = x - 50.0, y + 20.0
    e = 1e-3 * (0.3 * x - 0.2 * y) + 1e-4 * rng.normal(size=x.shape)
    e[rng.random(e.shape) < 0.05] = np.nan
    t_new, m_new = best_of(lambda: surface_error_metrics(x, y, e), a.repeat)
    t_old, m_old = best_of(lambda: lstsq_metrics(x, y, e), a.repeat)
    res = {"n_points": m_new["n_pixels"], "normal_equations_s": t_new, "lstsq_s": t_old, "speedup": t_old / t_new,
           "max_dev_rel_diff": abs(m_new["max_dev_plane_um"] / m_old["max_dev_plane_um"] - 1),
           "load": open("/proc/loadavg").read().split()[:3]}
    if a.json:
        dump_json(res)
        return
    print(f"{res['n_points']} points (load {res['load']}), best of {a.repeat}:")
    print(f"  lstsq (before)          {t_old:.3f} s")
    print(f"  normal equations (now)  {t_new:.3f} s   ({res['speedup']:.1f}×; max_dev_plane differs by "
          f"{res['max_dev_rel_diff']:.1e} relative)")


if __name__ == "__main__":
    main()
