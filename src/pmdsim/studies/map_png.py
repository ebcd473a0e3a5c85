"""Map figures written straight to PNG with Pillow (issue 25 item 1: the figures of
``pmdsim evaluate`` in milliseconds instead of a matplotlib draw each).

The same figure as :func:`pmdsim.studies.figures.height_map_figure` — per panel a map over
its points' x, y (mm) binned at the axes' pixel resolution (:mod:`.map_raster`), pixels
without a value white, the axes framed with ticks and tick labels in mm, a title, and a colour
bar with ticks and the quantity's label — drawn with Pillow: matplotlib supplies only the
colour map, the norm, the tick positions (``MaxNLocator``, its default steps) and their
labels (``ScalarFormatter``), the font is matplotlib's DejaVu Sans. matplotlib laid out and
drew the text of every axis at each save (0.1–0.3 s per figure on this machine); here a panel
costs a few milliseconds besides binning its map.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

__all__ = ["MapPanel", "PanelLayout", "write_map_png", "write_height_map_png", "warm_up"]

#: zlib level of the PNG files (see :data:`pmdsim.studies.figures.PNG_COMPRESS_LEVEL`).
PNG_COMPRESS_LEVEL = 1


@dataclass(frozen=True)
class MapPanel:
    """One map: (H, W) x, y (mm) and values z (NaN: no value), its title (lines split at
    ``\\n``), the colour bar's label with its unit in parentheses, diverging (``signed``) or not."""

    x_mm: np.ndarray
    y_mm: np.ndarray
    z: np.ndarray
    title: str
    label: str
    signed: bool = True


@dataclass(frozen=True)
class PanelLayout:
    """Where a panel was drawn: the axes box (left, top, right, bottom) in PNG pixels (right,
    bottom exclusive), its data extent (x0, x1, y0, y1) in mm, the norm's limits and the colour map's name."""

    box_px: tuple
    extent_mm: tuple
    vmin: float
    vmax: float
    cmap: str

    def pixel_of(self, x_mm: float, y_mm: float) -> tuple[int, int]:
        """(row, column) of the PNG pixel showing data point (x, y)."""
        l, t, r, b = self.box_px
        x0, x1, y0, y1 = self.extent_mm
        col = l + int((x_mm - x0) / (x1 - x0) * (r - l))
        row = b - 1 - int((y_mm - y0) / (y1 - y0) * (b - t))
        return min(max(row, t), b - 1), min(max(col, l), r - 1)


@lru_cache(maxsize=8)
def _font(size_px: int):
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont(font_manager.FontProperties(family="DejaVu Sans")), size_px)


def _text_size(font, text: str) -> tuple[int, int]:
    l, t, r, b = font.getbbox(text)
    return r - l, b - t


def _ticks(lo: float, hi: float, length_px: int, font_px: int):
    """Tick positions in [lo, hi] and their labels, as matplotlib's default axis would pick them."""
    from matplotlib.ticker import MaxNLocator, ScalarFormatter

    nbins = max(3, min(9, int(length_px / (2.6 * font_px))))
    loc = MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10])
    ticks = [t for t in loc.tick_values(lo, hi) if lo - 1e-9 * (hi - lo) <= t <= hi + 1e-9 * (hi - lo)]
    fmt = ScalarFormatter(useOffset=False)
    fmt.create_dummy_axis()
    fmt.axis.set_view_interval(lo, hi)
    fmt.axis.set_data_interval(lo, hi)
    return ticks, fmt.format_ticks(ticks)


def _vtext(img, xy, text: str, font, fill=(0, 0, 0)):
    """Text rotated by 90° (reading upwards), its box's top-left corner at ``xy``."""
    from PIL import Image, ImageDraw

    w, h = _text_size(font, text)
    l, t, _, _ = font.getbbox(text)
    tmp = Image.new("L", (w + 2, h + 2), 0)
    ImageDraw.Draw(tmp).text((1 - l, 1 - t), text, font=font, fill=255)
    rot = tmp.rotate(90, expand=True)
    img.paste(Image.new("RGB", rot.size, fill), (int(xy[0]), int(xy[1])), rot)
    return rot.size


def _norm(pts, signed: bool):
    from matplotlib.colors import CenteredNorm, Normalize

    z0, z1 = pts.z_range
    if signed:
        return CenteredNorm(vcenter=0.0, halfrange=max(abs(z0), abs(z1)) or 1.0), "RdBu_r"
    return Normalize(vmin=z0, vmax=z1 if z1 > z0 else z0 + 1.0), "viridis"


def _draw_panel(img, draw, cell, panel: MapPanel, dpi: float):
    """One panel in ``cell`` = (left, top, width, height) px; returns its :class:`PanelLayout`
    (None without data)."""
    from matplotlib import colormaps

    from .map_raster import map_points

    if "(" not in panel.label or not panel.label.rstrip().endswith(")"):
        raise ValueError(f"colour-bar label {panel.label!r} must end with its unit in parentheses, e.g. 'height (µm)'")
    cl, ct, cw, ch = cell
    px = dpi / 72.0
    f10, f9 = _font(max(6, int(round(10 * px)))), _font(max(6, int(round(9 * px))))
    tick, pad = int(round(3.5 * px)), int(round(3.5 * px))
    line_h = _text_size(f10, "0123456789−")[1]
    pts = map_points(panel.x_mm, panel.y_mm, panel.z)
    title = panel.title + (" (no data)" if pts.n < 6 else "")
    lines = title.split("\n")
    title_h = sum(_text_size(f9, s or " ")[1] + 3 for s in lines)

    def put_title(bottom: int, centre: int) -> None:
        y = bottom - title_h
        for s in lines:
            tw, th = _text_size(f9, s or " ")
            draw.text((centre - tw // 2, y), s, font=f9, fill=(0, 0, 0), anchor="lt")
            y += th + 3

    top = ct + int(0.04 * ch) + title_h + pad
    if pts.n < 6:
        put_title(top - pad, cl + cw // 2)
        return None
    norm, cmap_name = _norm(pts, panel.signed)
    cmap = colormaps[cmap_name]
    x0, x1, y0, y1 = pts.extent_mm
    label_w = _text_size(f10, "x (mm)")[1]
    # first guess of the box for the tick density, then the margins from the labels
    bottom = ct + ch - int(0.03 * ch) - label_w - pad - line_h - tick - pad
    yt, ylab = _ticks(y0, y1, max(bottom - top, 10), line_h)
    left = cl + int(0.03 * cw) + label_w + pad + max(_text_size(f10, s)[0] for s in ylab) + tick + pad
    cticks, clab = _ticks(norm.vmin, norm.vmax, max(bottom - top, 10), line_h)
    cbar_w = max(6, int(0.035 * cw))
    right_block = (int(0.05 * cw) + cbar_w + tick + pad + max(_text_size(f10, s)[0] for s in clab) + pad + label_w
                   + int(0.03 * cw))
    right = cl + cw - right_block
    aw, ah = max(right - left, 10), max(bottom - top, 10)
    # equal aspect: the box shrinks to the data's aspect, centred in the available space
    aspect = (y1 - y0) / max(x1 - x0, 1e-12)
    bw, bh = (aw, int(round(aw * aspect))) if aw * aspect <= ah else (int(round(ah / aspect)), ah)
    bw, bh = max(bw, 1), max(bh, 1)
    bl, bt = left + (aw - bw) // 2, top + (ah - bh) // 2
    xt, xlab = _ticks(x0, x1, bw, line_h)
    yt, ylab = _ticks(y0, y1, bh, line_h)
    # the map: binned at the box's pixels, coloured, masked cells white; row 0 at the top
    vals = pts.raster(bw, bh)
    rgba = cmap(norm(vals.filled(np.nan)), bytes=True)
    rgb = rgba[..., :3].copy()
    rgb[np.ma.getmaskarray(vals)] = 255
    from PIL import Image

    tile = Image.fromarray(np.ascontiguousarray(rgb[::-1]), "RGB")
    if tile.size != (bw, bh):  # fewer cells than pixels (sparse points): nearest-neighbour upscale
        tile = tile.resize((bw, bh), Image.NEAREST)
    img.paste(tile, (bl, bt))
    put_title(bt - 1 - int(round(6 * px)), bl + bw // 2)  # 6 pt above the axes, centred on them
    black = (0, 0, 0)
    draw.rectangle((bl - 1, bt - 1, bl + bw, bt + bh), outline=black, width=1)
    for t, s in zip(xt, xlab):
        u = bl + int(round((t - x0) / (x1 - x0) * (bw - 1))) if x1 > x0 else bl
        draw.line((u, bt + bh, u, bt + bh + tick), fill=black)
        draw.text((u, bt + bh + tick + pad), s, font=f10, fill=black, anchor="mt")
    for t, s in zip(yt, ylab):
        v = bt + bh - 1 - int(round((t - y0) / (y1 - y0) * (bh - 1))) if y1 > y0 else bt
        draw.line((bl - 1 - tick, v, bl - 1, v), fill=black)
        draw.text((bl - 1 - tick - pad, v), s, font=f10, fill=black, anchor="rm")
    xw, _ = _text_size(f10, "x (mm)")
    draw.text((bl + bw // 2, bt + bh + tick + pad + line_h + pad), "x (mm)", font=f10, fill=black, anchor="mt")
    yl_w = max(_text_size(f10, s)[0] for s in ylab)
    sz = _text_size(f10, "y (mm)")
    _vtext(img, (bl - 1 - tick - pad - yl_w - pad - sz[1] - 2, bt + bh // 2 - sz[0] // 2), "y (mm)", f10)
    # the colour bar: 85 % of the axes' slot height, centred on it
    cbh = max(int(0.85 * ah), 10)
    cbl, cbt = right + int(0.05 * cw), top + (ah - cbh) // 2
    levels = norm.vmin + (norm.vmax - norm.vmin) * (np.arange(cbh)[::-1] + 0.5) / cbh
    bar = cmap(norm(levels), bytes=True)[:, :3]
    img.paste(Image.fromarray(np.ascontiguousarray(np.repeat(bar[:, None], cbar_w, axis=1)), "RGB"), (cbl, cbt))
    draw.rectangle((cbl - 1, cbt - 1, cbl + cbar_w, cbt + cbh), outline=black, width=1)
    for t, s in zip(cticks, clab):
        v = cbt + cbh - 1 - int(round((t - norm.vmin) / (norm.vmax - norm.vmin) * (cbh - 1)))
        draw.line((cbl + cbar_w, v, cbl + cbar_w + tick, v), fill=black)
        draw.text((cbl + cbar_w + tick + pad, v), s, font=f10, fill=black, anchor="lm")
    cl_w = max(_text_size(f10, s)[0] for s in clab)
    sz = _text_size(f10, panel.label)
    _vtext(img, (cbl + cbar_w + tick + pad + cl_w + pad, cbt + cbh // 2 - sz[0] // 2), panel.label, f10)
    return PanelLayout((bl, bt, bl + bw, bt + bh), (x0, x1, y0, y1), float(norm.vmin), float(norm.vmax), cmap_name)


def write_map_png(path: str | Path, panels, *, ncols: int = 1, figsize=(6.4, 4.8), dpi: float = 120.0) -> list:
    """Write ``panels`` (:class:`MapPanel`, row by row, ``ncols`` per row) as one PNG of
    ``figsize`` inches at ``dpi``; returns each panel's :class:`PanelLayout` (None for a panel
    without data). The map figures of :func:`pmdsim.studies.figures.height_map_figure` (one
    panel, 6.4 × 4.8 in at 120 dpi) and of the slope error (two per row, 10 × 4.2 in per row
    at 110 dpi), drawn with Pillow (module docstring)."""
    from PIL import Image, ImageDraw

    panels = list(panels)
    nrows = max(1, -(-len(panels) // ncols))
    W, H = int(round(figsize[0] * dpi)), int(round(figsize[1] * dpi))
    img = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    cw, ch = W // ncols, H // nrows
    out = [_draw_panel(img, draw, ((i % ncols) * cw, (i // ncols) * ch, cw, ch), p, dpi) for i, p in enumerate(panels)]
    img.save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return out


def write_height_map_png(x_mm, y_mm, z_um, *, title: str, path: str | Path, label: str = "height (µm)",
                         signed: bool = True) -> list:
    """:func:`~pmdsim.studies.figures.height_map_figure` written to the PNG ``path`` with Pillow
    (the same map, title, axes and colour bar; a few milliseconds instead of a matplotlib draw,
    and no matplotlib figure imported). Returns the panel's :class:`PanelLayout` in a list."""
    return write_map_png(path, [MapPanel(np.asarray(x_mm), np.asarray(y_mm), np.asarray(z_um), title, label, signed)])


def warm_up() -> None:
    """Draw a tiny map into memory: imports matplotlib's colours, ticks and fonts and Pillow's
    drawing and loads the binning kernels, so that ``pmdsim evaluate``'s figure thread does it
    while the images are read (start-up) instead of at the first figure."""
    import io

    v, u = np.mgrid[0:8, 0:8].astype(np.float64)
    write_map_png(io.BytesIO(), [MapPanel(u, v, u * v, "warm-up", "z (1)", True)])
