"""Figures of the studies (matplotlib).

Every function returns the :class:`matplotlib.figure.Figure` and saves it only when ``path`` is
given. Figures are built without pyplot, so importing pmdsim never switches matplotlib's
backend (inline plots in a notebook keep working) and no figure lingers in pyplot's registry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .map_png import write_height_map_png  # noqa: F401 - public here too (lives in map_png: no matplotlib figure)

__all__ = ["height_map_figure", "write_height_map_png", "height_grid_figure", "error_vs_free_parameters_figure"]


def _panel(fig, ax, x_mm, y_mm, z, title, label, *, signed: bool = True):
    """One map over its points' x, y (mm): the values binned on a raster of the axes' device
    pixels when drawn (:class:`~pmdsim.studies.map_raster.MapImage`: each cell the mean of the
    values whose points fall in it, cells without a value transparent; never a scatter of
    points). ``signed``: a diverging colour map centred on zero (errors, heights about a
    reference), else viridis; the colour limits span every finite value. ``label`` names the
    quantity and its unit, e.g. ``"height error (µm)"``."""
    from matplotlib.colors import CenteredNorm, Normalize

    from .map_raster import MapImage, map_points

    if "(" not in label or not label.rstrip().endswith(")"):
        raise ValueError(f"colour-bar label {label!r} must end with its unit in parentheses, e.g. 'height (µm)'")
    pts = map_points(x_mm, y_mm, z)
    if pts.n < 6:
        ax.set_title(title + " (no data)")
        return
    z0, z1 = pts.z_range
    if signed:
        norm, cmap = CenteredNorm(vcenter=0.0, halfrange=max(abs(z0), abs(z1)) or 1.0), "RdBu_r"
    else:
        norm, cmap = Normalize(vmin=z0, vmax=z1 if z1 > z0 else z0 + 1.0), "viridis"
    im = MapImage(ax, pts, cmap=cmap, norm=norm)
    ax.add_image(im)
    x0, x1, y0, y1 = pts.extent_mm
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title, fontsize=9)
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label(label)
    cb.formatter.set_useOffset(False)
    cb.update_ticks()


# zlib level of the PNG files: 1 encodes the evaluation's figures in about half the time of
# level 6 (Pillow's default) for 10-45 % larger files (docs/benchmarks.md, "PNG figures")
PNG_COMPRESS_LEVEL = 1


def _save(fig: Figure, path: str | Path | None) -> Figure:
    fig.tight_layout()
    if path is not None:
        png = str(path).lower().endswith(".png")
        fig.savefig(path, metadata={"Software": None}, **({"pil_kwargs": {"compress_level": PNG_COMPRESS_LEVEL}} if png else {}))
    return fig


def height_map_figure(x_mm, y_mm, z_um, *, title: str, label: str = "height (µm)",
                      path: str | Path | None = None, signed: bool = True) -> Figure:
    """One height map over its points' x, y (mm, each (H, W)) with a colour bar; ``z_um`` (H, W).

    Drawn on the pixel grid (masked where there is no value), a diverging colour map centred on
    zero unless ``signed`` is False. Saved as PNG to ``path`` when given; returns the figure.
    """
    fig = Figure(figsize=(6.4, 4.8), dpi=120)
    ax = fig.subplots()
    _panel(fig, ax, np.asarray(x_mm), np.asarray(y_mm), np.asarray(z_um), title, label, signed=signed)
    return _save(fig, path)


def height_grid_figure(panels, *, suptitle: str, label: str = "height error (µm)",
                       path: str | Path | None = None) -> Figure:
    """A grid of height maps, each with its own colour scale centred on zero (like the paper's
    Figs. 4 and 5), drawn on the pixel grid.

    ``panels`` is a list of rows; each entry is (x_mm, y_mm, z_um, title) with (H, W) arrays.
    Saved as PNG to ``path`` when given; returns the figure.
    """
    rows = len(panels)
    cols = max(len(r) for r in panels)
    fig = Figure(figsize=(5.6 * cols, 4.2 * rows), dpi=110)
    axes = fig.subplots(rows, cols, squeeze=False)
    for i, row in enumerate(panels):
        for j, (x, y, z, title) in enumerate(row):
            _panel(fig, axes[i, j], np.asarray(x), np.asarray(y), np.asarray(z), title, label)
    fig.suptitle(suptitle, fontsize=10)
    return _save(fig, path)


def error_vs_free_parameters_figure(series, model_labels, *, suptitle: str, floor_um: float | None = None,
                                    path: str | Path | None = None) -> Figure:
    """Experiment 3: reconstruction error and calibration residual against the screen model.

    Parameters
    ----------
    series : list of (label, errors_um, rms_px)
        One line per scenario; ``errors_um[i]`` (maximum height difference, the larger of the
        cameras) and ``rms_px[i]`` belong to ``model_labels[i]`` (NaN where not run).
    model_labels : list of str
        x-axis categories, e.g. "planar (0)", "3×3 (1)", ….
    floor_um : float, optional
        The 8-bit floor (Δh = 0, planar model), drawn as a dashed line.
    """
    fig = Figure(figsize=(12.0, 4.6), dpi=110)
    axes = fig.subplots(1, 2)
    x = np.arange(len(model_labels))
    for label, err, rms in series:
        axes[0].plot(x, err, marker="o", label=label)
        axes[1].plot(x, rms, marker="o", label=label)
    if floor_um is not None:
        axes[0].axhline(floor_um, color="k", ls="--", lw=0.8, label="8-bit floor (Δh = 0, planar)")
    for ax, ylabel in zip(axes, ("max. height difference (µm)", "calibration residual RMS (px)")):
        ax.set_yscale("log")
        ax.set_xticks(x, model_labels)
        ax.set_xlabel("screen model (free control heights)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", lw=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(suptitle, fontsize=10)
    return _save(fig, path)
