"""The ``[imaging]`` keys of the LCD's viewing-angle model (issue 20): names, defaults, validation
and their TOML reading.

``lcd_mode = "ips"`` switches the model on (docs/conventions.md, "Display: viewing-angle
response"; :mod:`pmdsim.simulation.display_angle`): an in-plane-switching liquid-crystal cell
between crossed polarisers whose transmittance depends on the direction of the light leaving the
screen. The cell is described by

* ``lcd_retardation_nm`` — d·Δn of the cell (nm, > 0; default 275: the first-minimum design
  λ/2 at λ = 550 nm, full transmission at normal incidence);
* ``lcd_indices`` — (n_o, n_e) of the liquid crystal (1 ≤ n_o < n_e; default (1.48, 1.58),
  Δn = 0.1, a typical nematic mixture for IPS; the cell gap is d = retardation / Δn);
* ``lcd_rubbing_deg`` — the rubbing direction (the director's direction at black, also the
  entrance polariser's transmission axis; the analyser is crossed), degrees from the screen's
  x axis (default 0);
* ``lcd_wavelength_nm`` — the wavelength the cell is evaluated at (nm, > 0; default 550).
"""

from __future__ import annotations

import math
from typing import Any

from ..errors import SetupError

__all__ = ["LCD_MODES", "LCD_KEYS", "LCD_DEFAULTS", "validate_lcd", "read_lcd_keys"]

#: The cell types modelled.
LCD_MODES = ("ips",)
#: The TOML keys of the model (in ``[imaging]``).
LCD_KEYS = ("lcd_mode", "lcd_retardation_nm", "lcd_indices", "lcd_rubbing_deg", "lcd_wavelength_nm")
#: Their defaults (``lcd_mode`` None: the model is off).
LCD_DEFAULTS: dict[str, Any] = dict(lcd_mode=None, lcd_retardation_nm=275.0, lcd_indices=(1.48, 1.58),
                                    lcd_rubbing_deg=0.0, lcd_wavelength_nm=550.0)


def _finite(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def validate_lcd(im: Any) -> None:
    """Check the ``lcd_*`` values of an :class:`~pmdsim.setup.ImagingSetup` (one-line
    :class:`~pmdsim.errors.SetupError` naming the key)."""
    if im.lcd_mode is not None and im.lcd_mode not in LCD_MODES:
        raise SetupError(f"imaging.lcd_mode must be one of {list(LCD_MODES)} (or absent: off), got {im.lcd_mode!r}")
    for name in ("lcd_retardation_nm", "lcd_wavelength_nm"):
        v = getattr(im, name)
        if not _finite(v) or v <= 0:
            raise SetupError(f"imaging.{name} must be a finite number > 0, got {v!r}")
    if not _finite(im.lcd_rubbing_deg):
        raise SetupError(f"imaging.lcd_rubbing_deg must be a finite number (degrees), got {im.lcd_rubbing_deg!r}")
    n = im.lcd_indices
    if (not isinstance(n, (tuple, list)) or len(n) != 2 or not all(_finite(x) for x in n)
            or not 1.0 <= n[0] < n[1]):
        raise SetupError(f"imaging.lcd_indices must be [n_o, n_e] with 1 ≤ n_o < n_e, got {n!r}")
    object.__setattr__(im, "lcd_indices", (float(n[0]), float(n[1])))  # hashable, plain floats


def read_lcd_keys(r: Any, kw: dict[str, Any]) -> None:
    """Read the ``lcd_*`` keys present in the ``[imaging]`` table reader ``r`` into ``kw``."""
    if r.has("lcd_mode"):
        v = r.raw("lcd_mode")
        if not isinstance(v, str):
            raise SetupError(f"{r.key('lcd_mode')} must be a string, one of {list(LCD_MODES)}, got {v!r}")
        kw["lcd_mode"] = v
    for k in ("lcd_retardation_nm", "lcd_wavelength_nm"):
        if r.has(k):
            kw[k] = r.number(k, positive=True)
    if r.has("lcd_rubbing_deg"):
        kw["lcd_rubbing_deg"] = r.number("lcd_rubbing_deg")
    if r.has("lcd_indices"):
        kw["lcd_indices"] = r.vector("lcd_indices", 2)
