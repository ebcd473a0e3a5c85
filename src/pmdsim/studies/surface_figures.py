"""The slope-error figure of an evaluation (issue 12, item 4): the residual slopes after the
best-fit paraboloid, x and y component, in mrad over the sample frame's x, y (mm)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # matplotlib's figure only where one is drawn (pmdsim evaluate writes PNGs with Pillow)
    from matplotlib.figure import Figure

__all__ = ["slope_error_figure", "write_slope_error_png"]


def slope_error_figure(per_camera: dict, fit, *, path: str | Path | None = None) -> Figure:
    """``per_camera[name] = (p_sample_mm (H, W, 3), residual_slopes (H, W, 2) rad)``; ``fit`` a
    :class:`~pmdsim.evaluation.surface_fit.ParaboloidFit`. One row per camera, x and y residuals."""
    from matplotlib.figure import Figure

    from .figures import _panel, _save

    n = max(1, len(per_camera))
    fig = Figure(figsize=(10.0, 4.2 * n), dpi=110)
    axes = np.atleast_2d(fig.subplots(n, 2))
    for row, (name, (p, res)) in enumerate(per_camera.items()):
        for k, comp in enumerate("xy"):
            _panel(fig, axes[row, k], p[..., 0], p[..., 1], res[..., k] * 1e3,
                   f"{name}: slope error {comp} after the best-fit paraboloid\n"
                   f"(f_x {fit.focal_length_x_mm:.6g} mm, f_y {fit.focal_length_y_mm:.6g} mm, "
                   f"RMS {fit.slope_residual_rms_mrad:.3g} mrad)", "slope error (mrad)")
    return _save(fig, path)


def write_slope_error_png(per_camera: dict, fit, *, path: str | Path) -> list:
    """:func:`slope_error_figure` written to the PNG ``path`` with Pillow (the same panels,
    :mod:`.map_png`); returns the panels' :class:`~pmdsim.studies.map_png.PanelLayout`."""
    from .map_png import MapPanel, write_map_png

    panels = [MapPanel(p[..., 0], p[..., 1], res[..., k] * 1e3,
                       f"{name}: slope error {comp} after the best-fit paraboloid\n"
                       f"(f_x {fit.focal_length_x_mm:.6g} mm, f_y {fit.focal_length_y_mm:.6g} mm, "
                       f"RMS {fit.slope_residual_rms_mrad:.3g} mrad)", "slope error (mrad)")
              for name, (p, res) in per_camera.items() for k, comp in enumerate("xy")]
    return write_map_png(path, panels, ncols=2, figsize=(10.0, 4.2 * max(1, len(per_camera))), dpi=110)
