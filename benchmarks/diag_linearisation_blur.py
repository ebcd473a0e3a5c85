"""Why linearising does not help when the display's non-linear output is blurred (Experiment 4).

For the Table 1 setup binned 8×8, Δh = 3 mm, finest period 8 mm, left camera: the decoded
screen-coordinate error (RMS against the traced truth) and the decoder's predicted σ, for the
LCD response (gamma 2.2) alone and combined with each effect that blurs or scales the emitted
radiance, with and without the grey-level linearisation.

    cd benchmarks && PYTHONPATH=../src python3 diag_linearisation_blur.py

Linearisation inverts the response pixel by pixel, r⁻¹(c). A radiance scale L (emission
falloff) keeps it exact for a power law (r⁻¹(L·r(d)) = L^{1/γ}·d is still linear in d), but an
average over a blur spot or a pixel footprint does not commute with r: r⁻¹(⟨r(d)⟩) ≠ ⟨d⟩, so the
harmonics the blur left behind are not removed and the linearisation's noise penalty remains.
"""

from __future__ import annotations

import numpy as np

import pmdsim
from pmdsim.setup import ImagingSetup
from pmdsim.studies.experiment4 import _DEFOCUS, _DISPLAY, _EMISSION, _PIXELS, _with_finest_period


def main() -> None:
    base = _with_finest_period(pmdsim.default_setup().binned(8).with_bulge(3.0), 8.0)
    cases = {"gamma": _DISPLAY, "gamma+emission": {**_DISPLAY, **_EMISSION},
             "gamma+screen_pixels": {**_DISPLAY, **_PIXELS}, "gamma+defocus": {**_DISPLAY, **_DEFOCUS}}
    print(f"{'case':22s} {'linearised':>10s} {'predicted σ µm':>15s} {'actual RMS µm':>14s}")
    for name, im in cases.items():
        for lin in (False, True):
            s = base.with_imaging(ImagingSetup(**im, linearise=lin))
            m = pmdsim.simulate(s, "left")
            d = pmdsim.decode(m.images, s)
            err = (d.screen_xy_mm - m.mapping.screen_xy_mm)[d.valid]
            print(f"{name:22s} {str(lin):>10s} {np.nanmedian(d.std_xy_mm[d.valid]) * 1e3:15.2f} "
                  f"{np.sqrt(np.mean(err**2)) * 1e3:14.2f}")


if __name__ == "__main__":
    main()
