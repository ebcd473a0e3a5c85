"""Experiment 4 across ``--downsample K``: the rows of several runs side by side (issue 20 item 4).

Reads ``DIR/k{K}_{effect}/results.json`` (one ``pmdsim experiment 4 --downsample K --effects
effect`` run each) and prints, per effect and camera, the height RMS, the RMS after the best-fit
plane, the tilt, the slope RMS and the decoded pixels at every K, then issue 20's criterion for
the systematic rows — K = 4 agrees with K = 1 within 10 % or 0.01 µm RMS, whichever is larger —
and for the noise rows the noise part √(RMS² − RMS_ideal²) against the σ model's √K growth.

    python benchmarks/exp4_compare_k.py DIR --ks 1,4,8
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

NOISE_ROWS = ("sensor",)


def load(root: Path, k: int, effect: str) -> dict:
    f = root / f"k{k}_{effect}" / "results.json"
    if not f.exists():
        return {}
    return {r["camera"]: r for r in json.loads(f.read_text())}


def fmt(v, spec):
    return "—" if v is None else format(v, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--ks", default="1,4,8")
    ap.add_argument("--effects", default="ideal,sensor,gamma_uncorrected,screen_pixels,defocus_f8,all_systematic")
    a = ap.parse_args()
    ks = [int(k) for k in a.ks.split(",")]
    effects = a.effects.split(",")
    runs = {(k, e): load(a.root, k, e) for k in ks for e in effects}
    print("| effect | camera | K | RMS µm | RMS after plane µm | tilt µrad | slope RMS µrad | pixels |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for e in effects:
        for cam in ("left", "right"):
            for k in ks:
                r = runs[(k, e)].get(cam)
                if r is None:
                    continue
                if r.get("rms_um") is None:
                    print(f"| {e} | {cam} | {k} | failed: {r.get('error', '')[:80]} | | | | |")
                    continue
                print(f"| {e} | {cam} | {k} | {r['rms_um']:.4f} | {fmt(r.get('rms_plane_removed_um'), '.4f')} | "
                      f"{r['tilt_urad']:.2f} | {r['slope_rms_urad']:.2f} | {r['n_pixels']} |")
    if 1 in ks and 4 in ks:
        print("\nK = 4 against K = 1 (issue 20: within max(10 %, 0.01 µm) of the height RMS):")
        for e in effects:
            for cam in ("left", "right"):
                r1, r4 = runs[(1, e)].get(cam), runs[(4, e)].get(cam)
                if not r1 or not r4 or r1.get("rms_um") is None or r4.get("rms_um") is None:
                    continue
                tol = max(0.1 * r1["rms_um"], 0.01)
                d = r4["rms_um"] - r1["rms_um"]
                ds = r4["slope_rms_urad"] / r1["slope_rms_urad"] - 1
                print(f"  {e:<18} {cam:<5} RMS {r1['rms_um']:.4f} → {r4['rms_um']:.4f} µm (Δ {d:+.4f}, allowed ±{tol:.4f}): "
                      f"{'met' if abs(d) <= tol else 'NOT met'}; slope RMS {ds:+.1%}")
    for e in NOISE_ROWS:
        if e not in effects or "ideal" not in effects:
            continue
        print(f"\nnoise part of {e} (√(RMS² − RMS_ideal²), µm) and the σ model's √K:")
        for cam in ("left", "right"):
            parts = {}
            for k in ks:
                r, r0 = runs[(k, e)].get(cam), runs[(k, "ideal")].get(cam)
                if r and r0 and r.get("rms_um") is not None and r0.get("rms_um") is not None:
                    parts[k] = max(r["rms_um"] ** 2 - r0["rms_um"] ** 2, 0.0) ** 0.5
            if not parts:
                continue
            k0 = min(parts)
            line = ", ".join(f"K={k}: {v:.4f} (√K from K={k0}: {parts[k0] * (k / k0) ** 0.5:.4f})"
                             for k, v in sorted(parts.items()))
            print(f"  {cam}: {line}")


if __name__ == "__main__":
    main()
