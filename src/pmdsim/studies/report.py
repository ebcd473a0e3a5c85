"""Tables of the studies as text, and JSON-ready records.

The paper's table layout for Experiments 1 and 2 (ours with the paper's values beneath) and
Experiment 3's table of screen models; :func:`json_ready` turns numpy scalars into numbers.
"""

from __future__ import annotations

import numpy as np

__all__ = ["format_table", "experiment3_table", "scenario_label", "json_ready"]


def scenario_label(r: dict) -> str:
    """The label of an Experiment 3 record's scenario (table rows, figure legend)."""
    if r["scenario"] == "bulge":
        return f"bulge Δh = {r['bulge_mm']:g} mm"
    if r["scenario"] == "mirror_sag":
        return f"mirror sag {r['mirror_sag_um']:g} µm (Δh = {r['bulge_mm']:g} mm)"
    return f"{r['scenario']} deformation"


def experiment3_table(records: list[dict]) -> str:
    """Experiment 3's table: one line per scenario and screen model, cameras L / R."""
    lines = [f"Experiment 3 — calibrated screen models; {len(records)} reconstructions",
             f"{'scenario':34s} {'model':>7s} {'free':>5s} {'max.diff µm L/R':>19s} {'dev µm L/R':>17s} "
             f"{'tilt µrad L/R':>15s} {'calib RMS px':>13s} {'screen err µm':>14s} {'centre h mm':>12s}"]
    keyed = {}
    for r in records:
        keyed.setdefault((scenario_label(r), r["screen_model"]), []).append(r)
    for (sl, model), rs in keyed.items():
        def pair(k, f):
            return "/".join(format(x[k], f) for x in rs)
        ch = rs[0].get("screen_central_height_mm")
        lines.append(f"{sl:34s} {model:>7s} {rs[0]['free_parameters']:5d} {pair('max_height_diff_um', '.4f'):>19s} "
                     f"{pair('max_dev_plane_um', '.4f'):>17s} {pair('tilt_urad', '.2f'):>15s} "
                     f"{rs[0]['calibration_rms_px']:13.5f} {rs[0]['screen_shape_max_error_um']:14.2f} "
                     f"{'' if ch is None else f'{ch:12.6f}'}")
    return "\n".join(lines)


_METRIC_ROWS = (
    ("max_height_diff_um", "Max. height difference [µm]", 0),
    ("max_dev_plane_um", "Max. deviation from best-fit plane [µm]", 1),
    ("tilt_urad", "Best-fit plane tilt angle [µrad]", 2),
)


def format_table(records: list[dict], paper: dict, title: str) -> str:
    """The paper's table layout (Δh across, L/R below), ours with the paper's values beneath."""
    bulges = sorted({r["bulge_mm"] for r in records})
    cams = list(dict.fromkeys(r["camera"] for r in records))
    by = {(r["bulge_mm"], r["camera"]): r for r in records}
    w = 9
    lines = [title]
    head = f"{'Screen bulge height Δh':42s}" + "".join(f"{f'{b:g} mm':^{w * len(cams)}s}" for b in bulges)
    lines.append(head)
    lines.append(f"{'Camera':42s}" + "".join(f"{c[:1].upper():>{w}s}" for b in bulges for c in cams))
    for key, label, idx in _METRIC_ROWS:
        ours = "".join(f"{by[(b, c)][key]:{w}.{3 if key != 'tilt_urad' else 1}f}" if (b, c) in by else " " * w
                       for b in bulges for c in cams)
        lines.append(f"{label:42s}{ours}")
        ref = "".join(f"{paper[(b, c)][idx]:{w}.1f}" if (b, c) in paper else f"{'–':>{w}s}" for b in bulges for c in cams)
        lines.append(f"{'  paper':42s}{ref}")
    return "\n".join(lines)


def json_ready(obj):
    """numpy scalars → Python numbers, recursively (for JSON)."""
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
