"""Tables of the design studies' height σ, and the check against the decoder's closed-form scaling.

Reads ``results.parquet`` of ``pmdsim study examples/study_height_sigma_design.toml`` (or of the
``_sensor`` variant) and prints, per camera, ``height_std_edge_um`` in nm for every case (rows:
shifts × finest period; columns: bit depth), the observed σ ratio of every case to the Table 1
point (N = 4, p = 2 mm, 8 bits) against the law σ ∝ p/(√N·(2^b − 1)), and ``coverage_k2``.

    PYTHONPATH=src python3 benchmarks/design_sigma_table.py design-out [--law]

``--law`` adds the scaling check (valid for noise fixed in grey levels, the ideal camera of
examples/study_height_sigma_design.toml; not for the shot-noise-limited sensor variant).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pyarrow.parquet as pq

REF = (4, 2.0, 8)


def law(n: int, p: float, b: int) -> float:
    """σ_height ∝ p/(√N·(2^b − 1)) at fixed noise in grey levels (σ_c = p/(2π)·√(2/N)·σ_I/B,
    B = amplitude·(2^b − 1))."""
    return p / math.sqrt(n) / (2**b - 1)


def main(out: str, with_law: bool) -> None:
    rows = pq.read_table(Path(out) / "results.parquet").to_pylist()
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        print(f"{len(bad)} rows not ok: {sorted({r['error'] for r in bad})}")
    rows = [r for r in rows if r["status"] == "ok"]
    key = lambda r: (int(r["n_shifts"]), float(r.get("finest_period_mm", 2.0)), int(r["camera_bit_depth"]))
    bits = sorted({key(r)[2] for r in rows})
    for cam in sorted({r["camera"] for r in rows}):
        by = {key(r): r for r in rows if r["camera"] == cam}
        print(f"\n{cam}: height_std_edge_um in nm (coverage_k2 in brackets)")
        print("| N | finest period (mm) | " + " | ".join(f"{b} bit" for b in bits) + " |")
        print("|---|---|" + "---|" * len(bits))
        for n, p in sorted({k[:2] for k in by}):
            cells = [f"{by[(n, p, b)]['height_std_edge_um'] * 1e3:.4g} ({by[(n, p, b)]['coverage_k2']:.2f})"
                     if (n, p, b) in by else "—" for b in bits]
            print(f"| {n} | {p:g} | " + " | ".join(cells) + " |")
        if with_law and REF in by:
            dev = {m: max(abs(by[k][m] / by[REF][m] / (law(*k) / law(*REF)) - 1) for k in by)
                   for m in ("height_std_edge_um", "height_std_rms_um", "height_std_max_um")}
            print(f"{cam}: max |observed ratio / law − 1| over {len(by)} cases: "
                  + ", ".join(f"{m} {v:.2e}" for m, v in dev.items()))
        cov = [r["coverage_k2"] for r in by.values()]
        print(f"{cam}: coverage_k2 min {min(cov):.3f}, max {max(cov):.3f}")


if __name__ == "__main__":
    main(sys.argv[1], "--law" in sys.argv[2:])
