"""Camera sensor model: exposure, shot and read noise, dark offset, gain, bit depth, saturation.

Model (docs/conventions.md, "Image formation"), per sample with relative screen radiance s
(1 = a full-white, normally viewed screen):

    e = exposure · FW · s                             photo-electrons
    DN = dark + g · e + √(g²·(e + σ_read²) + σ_extra²) · z,   z ~ N(0, 1)
    recorded = clip(round(DN), 0, 2^bits − 1)      if e < FW
    recorded = 2^bits − 1                           if e ≥ FW (saturated: pinned, no noise)

with g the conversion gain (DN per electron; default (2^bits − 1)/FW, the full well fills the
range), σ_read the read noise in electrons and σ_extra the setup's additive grey-level noise
(``patterns.noise_std``). Photon shot noise is Poisson (variance e); it is drawn as a normal of
the same variance (EMVA 1288's linear model; the normal's shape error is irrelevant above a few
tens of electrons, and it lets one standard normal per sample carry all noise sources). A pixel
whose well is full records the saturation code 2^bits − 1 exactly — it carries no noise, and the
decoder flags it SATURATED (issue 20; before, noise was added to the clipped mean, so a saturated
pixel still fluctuated below full scale).
Without a full well (sensor off) the camera is ideal: DN = (2^bits − 1)·s + σ_extra·z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


__all__ = ["SensorModel"]


@dataclass(frozen=True)
class SensorModel:
    """The sensor of a setup as the renderer uses it (all values in DN unless named).

    Attributes
    ----------
    bit_depth : int
        8, 10, 12 or 16.
    scale_dn : float
        Mean DN above the dark offset for s = 1 (unsaturated).
    dark_dn : float
        Dark offset (DN).
    clip_dn : float
        Mean DN above the dark offset at which the full well saturates (inf: no full well).
    shot_dn : float
        Shot-noise variance per DN of signal (the gain g; 0 when the sensor is off).
    const_var_dn2 : float
        Signal-independent variance (g·σ_read)² + σ_extra² in DN².
    """

    bit_depth: int
    scale_dn: float
    dark_dn: float
    clip_dn: float
    shot_dn: float
    const_var_dn2: float

    @property
    def full_scale(self) -> float:
        """Largest grey level 2^bits − 1."""
        return float(2**self.bit_depth - 1)

    @property
    def dtype(self):
        return np.uint8 if self.bit_depth == 8 else np.uint16

    @property
    def noisy(self) -> bool:
        return self.shot_dn > 0 or self.const_var_dn2 > 0

    @classmethod
    def from_setup(cls, setup) -> "SensorModel":
        """The sensor of ``setup.imaging`` with ``setup.patterns``' bit depth and noise."""
        return cls.from_values(setup.imaging, setup.patterns.bit_depth, setup.patterns.noise_std)

    @classmethod
    def from_values(cls, im, pattern_bit_depth: int, noise_std: float) -> "SensorModel":
        """From an :class:`~pmdsim.setup.ImagingSetup` (or None) and the pattern values."""
        bits = pattern_bit_depth if im is None or im.bit_depth is None else im.bit_depth
        full = float(2**bits - 1)
        extra = float(noise_std) ** 2
        if im is None or im.full_well_e is None:
            return cls(bits, full, 0.0, math.inf, 0.0, extra)
        g = full / im.full_well_e if im.gain_dn_per_e is None else im.gain_dn_per_e
        return cls(bits, g * im.exposure * im.full_well_e, im.dark_offset_dn, g * im.full_well_e, g,
                   (g * im.read_noise_e) ** 2 + extra)

    def noise_std_dn(self, mean_dn) -> np.ndarray:
        """Predicted σ (DN) of a recorded sample of mean ``mean_dn`` (any shape), including the
        rounding error 1/√12: √(g·(mean − dark) + const + 1/12)."""
        m = np.asarray(mean_dn, dtype=float)
        return np.sqrt(self.shot_dn * np.clip(m - self.dark_dn, 0.0, None) + self.const_var_dn2 + 1.0 / 12.0)
