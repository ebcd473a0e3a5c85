"""Quick checks of a setup before any work: what will not work, and whether it fits in memory.

:func:`setup_findings` is what ``pmdsim setup --setup FILE`` runs (issue 11): it traces every
camera on a coarse pixel grid (binned so that at most ≈ 20 000 rays are traced) and reports

* the fraction of each camera's pixels that see the screen via the sample (none: the camera
  cannot measure; below 10 %: little can be measured);
* fringes that clip: mean_level + amplitude > 1 (saturation) or mean_level − amplitude < 0
  (black);
* a fringe modulation below the decoder's threshold (1 % of full scale, LOW_MODULATION);
* a coarsest period shorter than the screen in its direction (absolute unwrapping impossible);
* successive periods too far apart for the noise: the coarser period's coordinate noise
  σ_c = p_c/(2π)·√(2/N)·σ_I/B (the decoder's σ model) must stay below the unwrapping tolerance
  0.25·p_f of the finer period with a margin of 5σ, else unwrapping fails in a noticeable
  fraction of the pixels.

:func:`check_memory` estimates the memory a job needs from the pixel count and refuses, with one
line, what cannot fit (instead of a 149 GiB allocation that fails with a traceback).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from ..errors import PmdsimError
from ..setup import Setup

__all__ = ["Finding", "setup_findings", "InsufficientMemoryError", "check_memory", "available_memory_bytes",
           "estimate_bytes"]

#: Coverage below this fraction of a camera's pixels is a warning.
LOW_COVERAGE = 0.10
#: At most this many rays are traced per camera by the coverage check.
MAX_COVERAGE_RAYS = 20_000

# Bytes per camera pixel a job holds at its peak (measured orders of magnitude: rays, mappings,
# per-pixel maps of decoding, registration and reconstruction), plus per image (stacks and the
# float copies of the consistency checks).
_BYTES_PER_PIXEL = {"simulate": 400, "evaluate": 1200, "calibrate": 1200}
_BYTES_PER_IMAGE_PIXEL = 28


class InsufficientMemoryError(PmdsimError, MemoryError):
    """A job would need more memory than the machine has available."""


@dataclass(frozen=True)
class Finding:
    """One result of :func:`setup_findings`: ``level`` "fatal" (nothing can work), "warning" or
    "info"; ``message`` one line naming the key and value."""

    level: str
    message: str


def setup_findings(setup: Setup) -> list[Finding]:
    """What will not work with ``setup`` (see the module docstring); fatal findings first."""
    from ..evaluation.phase import DEFAULT_MIN_MODULATION_FRACTION, DEFAULT_UNWRAP_TOLERANCE, QUANTISATION_NOISE_STD
    from ..simulation.render import trace_setup_camera

    out: list[Finding] = []
    seq = setup.patterns.sequence
    a, b = seq.mean_level, seq.amplitude
    if a + b > 1.0:
        out.append(Finding("warning", f"patterns: mean_level + amplitude = {a + b:g} > 1: the bright fringe crests "
                                      f"clip (saturate) and the phase is biased; keep mean_level + amplitude ≤ 1"))
    if a - b < 0.0:
        out.append(Finding("warning", f"patterns: mean_level − amplitude = {a - b:g} < 0: the dark fringe troughs "
                                      f"clip at black and the phase is biased; keep amplitude ≤ mean_level"))
    if b < DEFAULT_MIN_MODULATION_FRACTION:
        out.append(Finding("fatal", f"patterns: amplitude {b:g} is below the decoder's minimum modulation "
                                    f"({DEFAULT_MIN_MODULATION_FRACTION:g} of full scale): every pixel is LOW_MODULATION"))
    full = 2 ** setup.patterns.bit_depth - 1
    sigma_i = math.hypot(setup.patterns.noise_std, QUANTISATION_NOISE_STD)
    b_dn = b * full
    n = seq.n_shifts
    for i, direction in enumerate(("x", "y")):
        extent = setup.screen.size_mm[i]
        periods = seq.periods(direction)
        key = f"patterns.periods_{direction}_mm"
        if max(periods) < extent:
            out.append(Finding("fatal", f"{key}: the coarsest period {max(periods):g} mm is shorter than the screen's "
                                        f"{'width' if i == 0 else 'height'} {extent:g} mm: absolute (hierarchical) "
                                        f"unwrapping is impossible; make the coarsest period ≥ {extent:g} mm"))
        ps = sorted(periods, reverse=True)
        for pc, pf in zip(ps, ps[1:]):
            sigma_c = pc / (2 * math.pi) * math.sqrt(2.0 / n) * sigma_i / b_dn
            if 5.0 * sigma_c > DEFAULT_UNWRAP_TOLERANCE * pf:
                out.append(Finding("warning", f"{key}: the step {pc:g} → {pf:g} mm is too large for the noise: the "
                                              f"{pc:g} mm period's coordinate noise {sigma_c:.3g} mm (σ_I = "
                                              f"{sigma_i:.3g} grey levels) × 5 exceeds the unwrapping tolerance "
                                              f"{DEFAULT_UNWRAP_TOLERANCE * pf:.3g} mm; add an intermediate period"))
    seen_any = False
    for cam, cs in setup.cameras.items():
        c = cs.camera
        k = max(1, math.ceil(math.sqrt(c.width_px * c.height_px / MAX_COVERAGE_RAYS)))
        k = min(k, c.width_px, c.height_px)
        m = trace_setup_camera(setup.binned(k), cam)
        frac = float(m.valid.mean())
        if frac == 0.0:
            out.append(Finding("warning", f"cameras.{cam}: no pixel sees the screen via the sample (checked on a "
                                          f"{k}×{k}-binned grid); this camera cannot measure — check its pose "
                                          f"(origin_world_mm, angles_deg) and the screen's"))
        else:
            seen_any = True
            level = "warning" if frac < LOW_COVERAGE else "info"
            out.append(Finding(level, f"cameras.{cam}: {frac:.1%} of the pixels see the screen via the sample"
                                      + (f" (below {LOW_COVERAGE:.0%}: little can be measured)" if level == "warning"
                                         else "")))
    if setup.cameras and not seen_any:
        out.append(Finding("fatal", "no camera sees the screen via the sample: nothing can be measured"))
    order = {"fatal": 0, "warning": 1, "info": 2}
    return sorted(out, key=lambda f: order[f.level])


def available_memory_bytes() -> int | None:
    """MemAvailable of /proc/meminfo (Linux), else physical memory; None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def estimate_bytes(setup: Setup, kind: str, cameras=None, n_images: int = 0) -> int:
    """Peak memory (bytes) of ``kind`` ("simulate", "evaluate", "calibrate") for the largest camera
    (cameras are processed one at a time) with ``n_images`` images in all."""
    names = list(setup.cameras) if cameras is None else [c for c in cameras if c in setup.cameras]
    if not names:
        return 0
    n_cam = max(1, len(names))
    px = max(setup.cameras[c].camera.width_px * setup.cameras[c].camera.height_px for c in names)
    per_cam_images = n_images / n_cam if n_images else 2 * (len(setup.patterns.sequence.periods_x_mm)
                                                             + len(setup.patterns.sequence.periods_y_mm)) * \
        setup.patterns.sequence.n_shifts
    return int(px * (_BYTES_PER_PIXEL[kind] + _BYTES_PER_IMAGE_PIXEL * per_cam_images))


def check_memory(setup: Setup, kind: str, *, cameras=None, n_images: int = 0, available: int | None = None) -> int:
    """Refuse a job whose estimated memory exceeds the available memory; returns the estimate.

    Raises
    ------
    InsufficientMemoryError
        One line with the estimate, the available memory and the camera size.
    """
    need = estimate_bytes(setup, kind, cameras, n_images)
    have = available_memory_bytes() if available is None else available
    if have is not None and need > have:
        cam = max(setup.cameras.values(), key=lambda cs: cs.camera.width_px * cs.camera.height_px).camera
        raise InsufficientMemoryError(
            f"{kind} of {cam.width_px}×{cam.height_px}-px cameras needs ≈ {need / 2**30:.1f} GiB, but only "
            f"{have / 2**30:.1f} GiB of memory are available; use smaller images (bin the cameras: image_size_px, "
            f"focal_length_px and principal_point_px divided by the same factor)")
    return need
