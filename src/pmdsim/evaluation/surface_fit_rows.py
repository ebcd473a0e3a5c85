"""The points of a joint surface fit gathered from several cameras' maps, and its residuals
scattered back (issue 25 item 1: :func:`pmdsim.evaluation.surface_fit.surface_fit_summary`
without numpy's boolean-mask copies).

Compiled single passes over each camera's (H, W) maps: the slopes (−n_x/n_z, −n_y/n_z) of the
unit normals and the mask of the fitted pixels (reconstructed, finite slopes), then x, y, the
slopes and their σ of those pixels copied into (2, M) rows (cameras in order, pixels in C order
— what numpy's ``a[ok]`` gives), and per camera the (H, W, 2) residual map filled from the
fit's (M, 2) residuals (NaN elsewhere). Pure copies and the same two divisions per pixel as
:func:`~pmdsim.evaluation.surface_fit.sample_slopes`: bit-identical to the numpy expressions.
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.kernel_args import readonly

__all__ = ["slopes_and_mask", "slopes_and_rows", "gather_rows", "gather_sigma", "scatter_residuals"]


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _slopes_kernel(n, rec, g, ok):  # pragma: no cover - compiled
    h, w = rec.shape
    m = 0
    for v in range(0, h):
        for u in range(0, w):
            m += _slope_at(n, rec, g, ok, v, u)[2]
    return m


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")
def _slope_at(n, rec, g, ok, v, u):  # pragma: no cover - compiled
    """Pixel (v, u): its slopes (−n_x/n_z, −n_y/n_z) written to ``g``, whether it is fitted
    (reconstructed, finite slopes) to ``ok``; returns (g_x, g_y, fitted)."""
    nz = n[v, u, 2]
    gx = -n[v, u, 0] / nz
    gy = -n[v, u, 1] / nz
    g[v, u, 0] = gx
    g[v, u, 1] = gy
    good = rec[v, u] and np.isfinite(gx) and np.isfinite(gy)
    ok[v, u] = good
    return gx, gy, good


def slopes_and_mask(n_sample, reconstructed) -> tuple[np.ndarray, np.ndarray, int]:
    """Slopes (H, W, 2) of unit normals (H, W, 3) (as :func:`~.surface_fit.sample_slopes`), the
    fitted pixels (reconstructed and finite slopes) and their number."""
    n = readonly(np.ascontiguousarray(n_sample, dtype=np.float64))
    rec = readonly(np.ascontiguousarray(reconstructed, dtype=np.bool_))
    g = np.empty(rec.shape + (2,))
    ok = np.empty(rec.shape, dtype=np.bool_)
    m = _slopes_kernel(n, rec, g, ok)
    return g, ok, int(m)


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _slopes_rows_kernel(n, rec, p, start, g, ok, x, y, gx, gy, ext):  # pragma: no cover - compiled
    h, w = rec.shape
    j = start
    xlo, xhi, ylo, yhi, gmax = ext[0], ext[1], ext[2], ext[3], ext[4]
    for v in range(0, h):
        for u in range(0, w):
            sx, sy, good = _slope_at(n, rec, g, ok, v, u)
            # written at the next free index, which only a fitted pixel advances (no branch)
            px = p[v, u, 0]
            py = p[v, u, 1]
            x[j] = px
            y[j] = py
            gx[j] = sx
            gy[j] = sy
            j += good
            if good:
                xlo = min(xlo, px)
                xhi = max(xhi, px)
                ylo = min(ylo, py)
                yhi = max(yhi, py)
                gmax = max(gmax, max(abs(sx), abs(sy)))
    ext[0], ext[1], ext[2], ext[3], ext[4] = xlo, xhi, ylo, yhi, gmax
    return j


def slopes_and_rows(n_sample, reconstructed, p_sample_mm, start: int, rows, extents=None
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`slopes_and_mask` and :func:`gather_rows` in one pass: the slopes (H, W, 2), the
    fitted pixels (H, W) and the next free index; x, y (of ``p_sample_mm`` (H, W, 3)) and the
    slopes of the fitted pixels written to ``rows`` = (x, y, g_x, g_y) ((N,) each, C order) from
    ``start`` on. Each row needs room for ``start`` + H·W values (every pixel is written at the
    next free index, which only a fitted one advances). ``extents`` ((5,) float64, optional):
    (min x, max x, min y, max y, max(|g_x|, |g_y|)) of the fitted pixels, continued (start from
    (inf, −inf, inf, −inf, 0))."""
    n = readonly(np.ascontiguousarray(n_sample, dtype=np.float64))
    rec = readonly(np.ascontiguousarray(reconstructed, dtype=np.bool_))
    if any(r.size < start + rec.size for r in rows):
        raise ValueError("slopes_and_rows: rows too short for the camera's pixels")
    g = np.empty(rec.shape + (2,))
    ok = np.empty(rec.shape, dtype=np.bool_)
    ext = np.array([np.inf, -np.inf, np.inf, -np.inf, 0.0]) if extents is None else extents
    j = _slopes_rows_kernel(n, rec, readonly(np.ascontiguousarray(p_sample_mm, dtype=np.float64)), np.int64(start), g,
                            ok, *rows, ext)
    return g, ok, int(j)


@numba.njit(cache=True, nogil=True, fastmath=False)
def _gather_kernel(p, g, sig, ok, start, use_xy, use_sig, xy, gxy, sg):  # pragma: no cover - compiled
    h, w = ok.shape
    j = start
    for v in range(0, h):
        for u in range(0, w):
            if ok[v, u]:
                if use_xy:
                    xy[0, j] = p[v, u, 0]
                    xy[1, j] = p[v, u, 1]
                    gxy[0, j] = g[v, u, 0]
                    gxy[1, j] = g[v, u, 1]
                if use_sig:
                    sg[j, 0] = sig[v, u, 0]
                    sg[j, 1] = sig[v, u, 1]
                j += 1
    return j


def gather_rows(p_sample_mm, slopes, ok, start: int, xy, gxy) -> int:
    """Copy x, y (of ``p_sample_mm`` (H, W, 3)) and the slopes (H, W, 2) of the pixels ``ok``
    into ``xy[:, start:]`` and ``gxy[:, start:]`` ((2, M)); returns the next free index."""
    none = readonly(np.zeros((1, 1, 2)))
    return int(_gather_kernel(readonly(np.ascontiguousarray(p_sample_mm, dtype=np.float64)),
                              readonly(np.ascontiguousarray(slopes, dtype=np.float64)), none,
                              readonly(np.ascontiguousarray(ok, dtype=np.bool_)), int(start), True, False, xy, gxy,
                              np.zeros((1, 2))))


def gather_sigma(sig, ok, start: int, sg) -> int:
    """Copy the σ (H, W, 2) of the pixels ``ok`` into ``sg[start:]`` ((M, 2)); returns the next
    free index."""
    s = readonly(np.ascontiguousarray(sig, dtype=np.float64))
    none3, none2 = readonly(np.zeros((1, 1, 3))), readonly(np.zeros((1, 1, 2)))
    return int(_gather_kernel(none3, none2, s, readonly(np.ascontiguousarray(ok, dtype=np.bool_)), int(start), False,
                              True, np.zeros((2, 1)), np.zeros((2, 1)), sg))


@numba.njit(cache=True, nogil=True, fastmath=False)
def _scatter_kernel(res, ok, start, out):  # pragma: no cover - compiled
    h, w = ok.shape
    j = start
    for v in range(0, h):
        for u in range(0, w):
            if ok[v, u]:
                out[v, u, 0] = res[j, 0]
                out[v, u, 1] = res[j, 1]
                j += 1
            else:
                out[v, u, 0] = np.nan
                out[v, u, 1] = np.nan
    return j


def scatter_residuals(residuals, ok, start: int) -> tuple[np.ndarray, int]:
    """The (H, W, 2) map of the rows ``residuals[start:]`` ((M, 2)) at the pixels ``ok`` (C
    order), NaN elsewhere, and the next row index."""
    ok = readonly(np.ascontiguousarray(ok, dtype=np.bool_))
    out = np.empty(ok.shape + (2,))
    # Fortran order: the fit's (2, M) rows transposed (no copy), the kernel's one argument type
    j = _scatter_kernel(readonly(np.asfortranarray(residuals, dtype=np.float64)), ok, int(start), out)
    return out, int(j)
