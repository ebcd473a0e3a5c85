"""Both fringe directions of :func:`~pmdsim.evaluation.decoding.decode_screen_coordinates` in
one parallel pass over image rows (issue 25, item 3).

The images are handed over as one read-only (N, H, W) array, the levels' images one after the
other (:func:`common_image_stack`): a view of the camera's array when the stacks are consecutive
slices of one (as :func:`pmdsim.io.imageset.load_camera_stacks` and the linearised stacks are), else
one copy — no numba typed list (its helpers compiled in every process: 0.55–0.59 s of each
``pmdsim evaluate``, they cannot be cached). Each row is decoded coarse → fine for direction x, then y, in row buffers, with the
per-pixel arithmetic of ``decoding._finish_row`` expression for expression (bit for bit
:func:`~pmdsim.evaluation.decoding.decode_direction`'s values) written as branch-free loops that
vectorise, and the sums of four images per pass over the row; the row's results are combined
into the (H, W, 2) outputs at once, so there are no per-direction (H, W) temporaries and no
serial combine pass.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..geometry.kernel_args import readonly
from .decoding import (
    _KERNEL_DTYPES,
    ScreenCoordinates,
    _add_image_row,
    _clear_row_sums,
    _as_image_stack,
    _modulation_phase_row,
    _quality,
    _shift_weights,
)
from .phase_flags import _NONFINITE, _UNWRAP_INCONSISTENT
from .phase_noise import coordinate_std_scale
from .unwrapping import REVERSAL_PHASE_TOLERANCE, _coarse_coord, _refine

__all__ = ["ImageList", "as_image_list", "common_image_stack", "decode_both_directions"]


class ImageList(list):
    """A list of N ≥ 3 C-contiguous (H, W) images of one kernel dtype, with the ``shape``
    (N, H, W) and ``dtype`` of the stack they stand for (not stacked)."""

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self),) + self[0].shape

    @property
    def dtype(self) -> np.dtype:
        return self[0].dtype


def _plain_images(images) -> bool:
    """``images`` is a sequence of ≥ 3 (H, W) numpy images, all of one shape and one native
    kernel dtype: usable as they are (only non-contiguous ones are copied)."""
    if not isinstance(images, (list, tuple)) or len(images) < 3:
        return False
    first = images[0]
    if not isinstance(first, np.ndarray) or first.ndim != 2 or first.size == 0:
        return False
    dt = first.dtype
    if dt not in _KERNEL_DTYPES or not dt.isnative:
        return False
    return all(isinstance(im, np.ndarray) and im.shape == first.shape and im.dtype == dt for im in images)


def as_image_list(images, name: str) -> ImageList:
    """The images of one period as an :class:`ImageList`, with the checks, messages and
    conversions of ``decoding._as_image_stack``.

    Parameters
    ----------
    images : array_like (N, H, W) or sequence of N (H, W) images
    name : str
        The argument's name for error messages.

    Returns
    -------
    ImageList
        A sequence of (H, W) images is used as it is (views, no copy); anything else goes through
        ``_as_image_stack`` and is split into views of its images.
    """
    if _plain_images(images):
        return ImageList(np.ascontiguousarray(im) for im in images)
    return ImageList(_as_image_stack(images, name))


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _accumulate_images_row(images, first, n, v, w_a, w_c, w_s, sa, sc, ss, mx):
    """``decoding._accumulate_row`` for images ``first`` … ``first + n − 1`` of the (N, H, W) array
    ``images`` and weights ``w_*[first:first + n]``: per pixel the same sums in the same order,
    four images per pass over the row (one load and store of the sums per four images)."""
    w = sa.shape[0]
    _clear_row_sums(sa, sc, ss, mx)
    k = first
    end = first + n
    while k + 4 <= end:
        r0, r1, r2, r3 = images[k, v], images[k + 1, v], images[k + 2, v], images[k + 3, v]
        a0, a1, a2, a3 = w_a[k], w_a[k + 1], w_a[k + 2], w_a[k + 3]
        c0, c1, c2, c3 = w_c[k], w_c[k + 1], w_c[k + 2], w_c[k + 3]
        s0, s1, s2, s3 = w_s[k], w_s[k + 1], w_s[k + 2], w_s[k + 3]
        for u in range(w):
            x0 = np.float64(r0[u])
            x1 = np.float64(r1[u])
            x2 = np.float64(r2[u])
            x3 = np.float64(r3[u])
            sa[u] = (((sa[u] + a0 * x0) + a1 * x1) + a2 * x2) + a3 * x3
            sc[u] = (((sc[u] + c0 * x0) + c1 * x1) + c2 * x2) + c3 * x3
            ss[u] = (((ss[u] + s0 * x0) + s1 * x1) + s2 * x2) + s3 * x3
            mx[u] = max(max(max(max(mx[u], x0), x1), x2), x3)
        k += 4
    while k < end:
        _add_image_row(images[k, v], w_a[k], w_c[k], w_s[k], sa, sc, ss, mx)
        k += 1


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _finish_level_row(sa, sc, ss, mx, coarse, last, check_saturation, max_value, dark_level, min_modulation,
                      min_ratio, period, origin, upper, tolerance, rev_ratio, std_scale, noise_row, coord, f_row,
                      contrast, rev, mod, off, sd):
    """One level of one direction on a row, from the accumulated sums: ``decoding._finish_row``'s
    arithmetic, expression for expression, as branch-free loops (selects only, both unwrapping
    candidates computed) so that they vectorise. Row buffers (W,): ``coord`` (in: the coarser
    level's coordinate; out: this level's), ``f_row`` (flags, OR-ed), ``contrast`` (B/A, in:
    the coarser level's), ``rev``; at the ``last`` level ``mod``, ``off``, ``sd`` (σ, NaN where
    flagged) and ``coord`` NaN where flagged. ``noise_row`` (1|W,): σ_I of the row."""
    w = sa.shape[0]
    su = 1 if noise_row.shape[0] > 1 else 0
    inv_period = 1.0 / period
    _modulation_phase_row(sc, ss)
    for u in range(w):
        a = sa[u]
        b = sc[u]
        phi = ss[u]
        fin = np.isfinite(a) & np.isfinite(b)
        f = _quality(a, b, mx[u], check_saturation, max_value, dark_level, min_modulation, min_ratio)
        f = f if fin else _NONFINITE
        a = a if fin else np.nan
        b = b if fin else np.nan
        phi = phi if fin else np.nan
        ratio = b / a
        if coarse:
            val = _coarse_coord(phi, period, origin, upper)
        else:
            c = coord[u]
            ck, bad = _refine(c, phi, period, inv_period, tolerance)
            ck_r, bad_r = _refine(c, phi + math.pi, period, inv_period, tolerance)
            r = ((abs(c - ck) >= (0.5 - REVERSAL_PHASE_TOLERANCE) * period) & (ratio <= rev_ratio * contrast[u])
                 & (rev_ratio >= 0.0))
            val = ck_r if r else ck
            f |= _UNWRAP_INCONSISTENT if (bad_r if r else bad) else np.uint8(0)
            rev[u] |= r
        contrast[u] = ratio
        f |= f_row[u]
        f_row[u] = f
        if last:
            mod[u] = b
            off[u] = a
            ok = f == 0
            coord[u] = val if ok else np.nan
            sd[u] = std_scale * noise_row[u * su] / b if ok else np.nan
        else:
            coord[u] = val


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _decode_row(images, v, level_start, level_period, dir_level, origin, upper, std_scale, w_a, w_c, w_s,
                check_saturation, max_value, dark_level, min_modulation, min_ratio, tolerance, rev_ratio,
                noise, xy, flags, std, modulation, offset, valid, rev):
    """Row v of :func:`_fused_kernel`: both directions into row buffers, then combined as
    ``decoding._combine_kernel`` does."""
    w = xy.shape[1]
    sa = np.empty(w)
    sc = np.empty(w)
    ss = np.empty(w)
    mx = np.empty(w)
    noise_row = noise[v if noise.shape[0] > 1 else 0]  # σ_I of row v, (1|W,)
    coord = np.empty((2, w))
    f_dir = np.zeros((2, w), np.uint8)
    mod = np.empty((2, w))
    off = np.empty((2, w))
    sd = np.empty((2, w))
    contrast = np.empty(w)
    r_dir = np.zeros((2, w), np.bool_)
    for d in range(2):
        for level in range(dir_level[d], dir_level[d + 1]):
            first = level_start[level]
            _accumulate_images_row(images, first, level_start[level + 1] - first, v, w_a, w_c, w_s,
                                   sa, sc, ss, mx)
            _finish_level_row(sa, sc, ss, mx, level == dir_level[d], level == dir_level[d + 1] - 1,
                              check_saturation, max_value, dark_level, min_modulation, min_ratio,
                              level_period[level], origin[d], upper[d], tolerance, rev_ratio, std_scale[d],
                              noise_row, coord[d], f_dir[d], contrast, r_dir[d], mod[d], off[d], sd[d])
    for u in range(w):
        f = f_dir[0, u] | f_dir[1, u]
        flags[v, u] = f
        valid[v, u] = f == 0
        for d in range(2):
            modulation[v, u, d] = mod[d, u]
            offset[v, u, d] = off[d, u]
            rev[v, u, d] = r_dir[d, u]
            if f == 0:
                xy[v, u, d] = coord[d, u]
                std[v, u, d] = sd[d, u]
            else:
                xy[v, u, d] = np.nan
                std[v, u, d] = np.nan


@numba.njit(parallel=True, cache=True, nogil=True, fastmath=False, error_model="numpy")
def _fused_kernel(images, level_start, level_period, dir_level, origin, upper, std_scale, w_a, w_c, w_s,
                  check_saturation, max_value, dark_level, min_modulation, min_ratio, tolerance, rev_ratio,
                  noise, xy, flags, std, modulation, offset, valid, rev):
    """Decode both directions; one parallel pass over image rows.

    ``images``: (N, H, W) read-only C-contiguous array, the levels' images one after the other (x coarse → fine,
    then y coarse → fine); level l has images ``level_start[l]`` … ``level_start[l + 1] − 1``,
    period ``level_period[l]`` mm; direction d has levels ``dir_level[d]`` … ``dir_level[d + 1] − 1``
    and ``origin[d]``, ``upper[d]``, ``std_scale[d]``. ``w_*``: per image. ``noise`` (1|H, 1|W).
    Outputs: ``xy``, ``std``, ``modulation``, ``offset`` (H, W, 2) float64, ``flags`` (H, W)
    uint8, ``valid`` (H, W) bool, ``rev`` (H, W, 2) bool.
    """
    for v in numba.prange(0, flags.shape[0]):
        _decode_row(images, np.int64(v), level_start, level_period, dir_level, origin, upper, std_scale, w_a,
                    w_c, w_s, check_saturation, max_value, dark_level, min_modulation, min_ratio, tolerance,
                    rev_ratio, noise, xy, flags, std, modulation, offset, valid, rev)


def _consecutive_view(images):
    """The (N, H, W) array whose images are ``images`` (N ≥ 1 C-contiguous (H, W) arrays of one
    shape and dtype) if they lie one after the other in one array's memory — the slices of a
    camera's (N, H, W) array, in order — else None. A view: nothing is copied."""
    first = images[0]
    base = first.base
    if base is None or not first.flags.c_contiguous:
        return None
    nbytes = first.nbytes
    start = first.__array_interface__["data"][0]
    for k, im in enumerate(images):
        if (im.base is not base or im.shape != first.shape or im.dtype != first.dtype or not im.flags.c_contiguous
                or im.__array_interface__["data"][0] != start + k * nbytes):
            return None
    isz = first.dtype.itemsize
    h, w = first.shape
    # every image is inside ``base``'s memory and they are adjacent: the strided view spans them exactly
    return np.lib.stride_tricks.as_strided(first, (len(images), h, w), (nbytes, w * isz, isz), writeable=False)


def common_image_stack(images) -> np.ndarray:
    """(H, W) images of the kernels as one read-only C-contiguous (N, H, W) array.

    Parameters
    ----------
    images : sequence of N ≥ 1 ndarray (H, W)
        One shape; numeric kernel dtypes (``decoding._KERNEL_DTYPES``), native byte order. Images
        of mixed dtypes (rare) are promoted to their common type (it keeps every grey level's
        float64 value).

    Returns
    -------
    ndarray (N, H, W)
        A view when the images are consecutive in one array's memory (:func:`_consecutive_view`:
        the stacks of :func:`pmdsim.io.imageset.load_camera_stacks`), else one copy
        (``np.stack``). Its numba type — read-only C array of the dtype, 3 dimensions — holds
        neither the number of images nor of stacks: the kernels compile once per dtype.
    """
    dtypes = {im.dtype for im in images}
    if len(dtypes) > 1:
        common = np.result_type(*dtypes)
        images = [im.astype(common) for im in images]
    view = _consecutive_view(images)
    return view if view is not None else readonly(np.stack(images))



def decode_both_directions(preps, check_saturation: bool) -> ScreenCoordinates:
    """:func:`~pmdsim.evaluation.decoding.decode_screen_coordinates` from the validated inputs
    of both directions (``decoding._DirectionInput``, stacks as :class:`ImageList`) in one kernel
    pass.

    Parameters
    ----------
    preps : (x, y) pair of ``decoding._DirectionInput``
        Equal image size (H, W), equal thresholds and noise map (one call's arguments).
    check_saturation : bool

    Returns
    -------
    ScreenCoordinates
        (H, W, 2) coordinates, σ, modulation, offset and reversal; (H, W) flags and valid.
    """
    px, py = preps
    counts = [len(stack) for p in preps for stack in p.stacks]
    level_start = np.zeros(len(counts) + 1, np.int64)
    level_start[1:] = np.cumsum(counts)
    weights = [_shift_weights(n, None) for n in counts]
    w_a, w_c, w_s = (np.ascontiguousarray(np.concatenate([wt[i] for wt in weights])) for i in range(3))
    h, w = px.shape
    xy = np.empty((h, w, 2))
    std = np.empty((h, w, 2))
    modulation = np.empty((h, w, 2))
    offset = np.empty((h, w, 2))
    flags = np.empty((h, w), np.uint8)
    valid = np.empty((h, w), np.bool_)
    rev = np.empty((h, w, 2), np.bool_)
    _fused_kernel(
        common_image_stack([im for p in preps for stack in p.stacks for im in stack]), level_start,
        np.concatenate([px.periods, py.periods]).astype(np.float64),
        np.array([0, len(px.stacks), len(px.stacks) + len(py.stacks)], np.int64),
        np.array([px.origin, py.origin]), np.array([px.upper, py.upper]),
        np.array([coordinate_std_scale(p.periods[-1], len(p.stacks[-1])) for p in preps]),
        w_a, w_c, w_s, bool(check_saturation), px.max_value, px.dark_level, px.min_modulation, px.min_ratio,
        px.tolerance, px.rev_ratio, px.noise, xy, flags, std, modulation, offset, valid, rev,
    )
    return ScreenCoordinates(screen_xy_mm=xy, valid=valid, flags=flags, std_xy_mm=std,
                             modulation=modulation, offset=offset, reversed=rev)
