"""Consistency checks of decoded fringe images: per image, per period and per pixel (issue 11).

The N-step decoder (:mod:`.phase`) turns any N ≥ 3 images into a phase; it cannot tell a good
measurement from a dropped frame or a mis-stated period. These checks test what the data must
satisfy if the fringe model of docs/conventions.md holds, each against the noise the images
themselves show, and mark the pixels that fail with :class:`~.phase.PhaseFlag` bits:

``FIT_RESIDUAL`` — per image.
    For N ≥ 4 equally spaced shifts the least-squares fit of I_k = A + B·cos(φ − δ_k) leaves
    N − 3 residual degrees of freedom; with Gaussian intensity noise σ_I the residual sum of
    squares is σ_I²·χ²(N − 3) (the hat matrix of the design [1, cos δ_k, sin δ_k] is
    3/N·I on its diagonal). A pixel is flagged if RSS/σ_I² exceeds the χ²(N − 3) quantile of
    the false-alarm probability α. A black, duplicated or foreign frame adds a residual of the
    order of A or B (≫ σ_I). The image with the largest |residual| is recorded (which frame).
``PERIOD_MISMATCH`` — per period.
    Hierarchical unwrapping refines the coordinate c_{k−1} of the coarser period with the finer
    period's phase, c_k = p_k·(φ_k/2π + round((c_{k−1} − p_k·φ_k/2π)/p_k)). If both are right,
    c_{k−1} − c_k is noise with σ² = σ_{k−1}² + σ_k², σ_j = p_j/(2π)·√(2/N_j)·σ_I/B_j (the
    decoder's σ model). A pixel is flagged if |c_{k−1} − c_k| > z_{α/2}·σ. A wrong period, a
    period's images shifted against the others, a missing shift (N taken as 3 for 4 displayed)
    make the periods disagree by far more than their noise. Where the decoder corrected a
    period's reversed contrast by π (``decoded.reversed``, :mod:`.unwrapping`), the same
    correction is applied here first, so a corrected pixel is not flagged for its π flip.
``GEOMETRY`` — per pixel.
    The coordinate lies outside the screen by more than 1 % of its extent, or the local
    orientation of the pixel → screen mapping disagrees with the nominal one: with J the
    Jacobian ∂(x_q, y_q)/∂(u, v) of the decoded map and J₀ that of the map predicted for the
    nominal sample plane (:func:`nominal_screen_xy`), M = J₀⁻¹·J is close to a positive
    multiple of the identity for any gently curved sample; det M < 0 (one direction mirrored: a
    reversed shift order, x and y swapped) or trace M < 0 (both mirrored) is flagged. A rough
    or strongly concave sample seen beyond a caustic folds the mapping locally: those pixels are
    flagged too (their coordinates are right, but the surface cannot be integrated across a
    fold); only more than 90 % flipped pixels are taken as a direction mirrored as a whole.

The noise σ_I is the larger of the given ``noise_std`` and the noise the images show: the
per-pixel residual variances RSS/(N − 3) of each stack are binned by the offset A, each bin's
mean of the lower 90 % corrected to the mean of χ², and the photon-transfer line σ_I² = a + b·A (EMVA 1288:
read noise + shot noise) fitted by non-negative least squares; σ_I²(A) is the lowest of the
stacks' lines (each a median over many pixels, so precise to a few per cent), so that bad stacks
— up to all but one — do not inflate it.

Only pixels the decoder found photometrically fine (no DARK, SATURATED, LOW_MODULATION,
NONFINITE) are tested. Everything here is a pure function of arrays; nothing is printed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numba
import numpy as np

from ..geometry.camera import Camera
from ..geometry.transform import RigidTransform
from .phase import (
    QUANTISATION_NOISE_STD,
    PhaseDecodingError,
    PhaseFlag,
    ScreenCoordinates,
    equal_shifts,
)
from .consistency_levels import check_stacks, fit_row, stack_images
from .distributions import chi2_cdf, chi2_isf, chi2_ppf, nnls, norm_isf
from .fast_atan import _phase_0_2pi

__all__ = [
    "DEFAULT_FALSE_ALARM",
    "DEFAULT_DEFECT_FRACTION",
    "OUTSIDE_SCREEN_FRACTION",
    "ImageLabel",
    "ConsistencyResult",
    "check_consistency",
    "with_consistency",
    "nominal_screen_xy",
]

#: Default per-test false-alarm probability α of the residual and period checks (per pixel and
#: stack): at α = 1e-6 a clean 1920×1200 image set with 6 stacks expects ≈ 14 flagged pixels.
DEFAULT_FALSE_ALARM = 1e-6
#: Default ``defect_fraction`` of :func:`check_consistency`.
DEFAULT_DEFECT_FRACTION = 0.2
#: A coordinate more than this fraction of the screen extent outside the screen is GEOMETRY.
OUTSIDE_SCREEN_FRACTION = 0.01
#: Bits set by this module.
CONSISTENCY_BITS = np.uint8(PhaseFlag.FIT_RESIDUAL | PhaseFlag.PERIOD_MISMATCH | PhaseFlag.GEOMETRY)
_PHOTOMETRIC = np.uint8(PhaseFlag.DARK | PhaseFlag.SATURATED | PhaseFlag.LOW_MODULATION | PhaseFlag.NONFINITE)
_N_BINS = 12
_TRIM = 0.9
_MAX_NOISE_SAMPLES = 60_000
_MIN_NOISE_PIXELS = 200


@dataclass(frozen=True)
class ImageLabel:
    """One image of a camera's set: fringe direction, period (mm), shift index k."""

    direction: str
    period_mm: float
    shift_index: int | None  # None: one of the period's images, not identifiable (N = 4)

    def __str__(self) -> str:
        if self.shift_index is None:
            return f"direction {self.direction}, period {self.period_mm:g} mm, one of the 4 shifts (N = 4 cannot tell which)"
        return f"direction {self.direction}, period {self.period_mm:g} mm, shift {self.shift_index}"


@dataclass(frozen=True)
class ConsistencyResult:
    """Result of :func:`check_consistency` for one camera.

    Attributes
    ----------
    flags : ndarray (H, W) uint8
        :class:`~.phase.PhaseFlag` bits FIT_RESIDUAL, PERIOD_MISMATCH, GEOMETRY (0: consistent
        or not tested).
    fit_residual_ratio : ndarray (H, W) float32
        max over stacks of (RSS/σ_I²) / χ²-threshold; > 1 is FIT_RESIDUAL. NaN: not tested.
    period_mismatch_ratio : ndarray (H, W) float32
        max over period pairs of |c_{k−1} − c_k| / (z·σ); > 1 is PERIOD_MISMATCH. NaN: not tested.
    worst_image : ndarray (H, W) int16
        Index into :attr:`images` of the image with the largest standardised residual, where
        FIT_RESIDUAL is set; −1 elsewhere.
    images : tuple[ImageLabel, ...]
        x stacks then y stacks in the order given, shifts 0 … N−1 (for N = 4 followed by a label
        with ``shift_index`` None: with 4 shifts the residual ∝ (1, −1, 1, −1) does not tell
        which frame is bad).
    image_counts : dict[ImageLabel, int]
        FIT_RESIDUAL pixels per worst image (only images with a count > 0).
    period_counts : dict[(str, float), int]
        PERIOD_MISMATCH pixels per (direction, finer period mm) of the worst-disagreeing pair.
    geometry_counts : dict[str, int]
        GEOMETRY pixels by reason: "outside_screen", "orientation".
    defects : tuple[str, ...]
        Images, periods or directions found defective as a whole (all their pixels flagged).
    tested : ndarray (H, W) bool
        Pixels the checks were applied to (photometrically valid).
    noise_model : (float, float)
        The (a, b) of σ_I² = a + b·A (grey levels², grey levels) of the stack with the lowest
        noise at the median offset; NaN if not fitted (no stack with N ≥ 4).
    noise_std_max : float
        Largest σ_I (grey levels) the checks used.
    false_alarm : float
        α of the checks.
    """

    flags: np.ndarray
    fit_residual_ratio: np.ndarray
    period_mismatch_ratio: np.ndarray
    worst_image: np.ndarray
    images: tuple
    image_counts: dict
    period_counts: dict
    geometry_counts: dict
    defects: tuple
    tested: np.ndarray
    noise_model: tuple
    noise_std_max: float
    false_alarm: float
    noise_lines: np.ndarray | None = None
    given_noise_std: object = QUANTISATION_NOISE_STD

    def noise_std_at(self, offset) -> np.ndarray:
        """σ_I (grey levels) the checks use at offset A (array): max(given, estimated)."""
        a = np.clip(np.nan_to_num(np.asarray(offset, dtype=np.float64)), 0.0, None)
        given2 = np.broadcast_to(np.asarray(self.given_noise_std, dtype=np.float64) ** 2, a.shape)
        if self.noise_lines is None:
            return np.sqrt(given2)
        est = np.min(self.noise_lines[:, 0, None, None] + self.noise_lines[:, 1, None, None] * a, axis=0)
        return np.sqrt(np.maximum(est, given2))

    def counts(self) -> dict[str, int]:
        """Pixels per consistency flag (a pixel may count under several)."""
        return {f.name: int(np.count_nonzero(self.flags & np.uint8(f)))
                for f in (PhaseFlag.FIT_RESIDUAL, PhaseFlag.PERIOD_MISMATCH, PhaseFlag.GEOMETRY)}

    def reasons(self, limit: int = 3) -> list[str]:
        """Short, human-readable reasons (e.g. for a warning): the whole-stack/period/direction
        defects if any, else the largest per-pixel counts."""
        out = list(self.defects)
        if out:
            return out[:limit]
        for lab, n in sorted(self.image_counts.items(), key=lambda kv: -kv[1])[:limit]:
            out.append(f"FIT_RESIDUAL: image ({lab}) deviates from its period's sinusoid in {n} px")
        for (d, p), n in sorted(self.period_counts.items(), key=lambda kv: -kv[1])[:limit]:
            out.append(f"PERIOD_MISMATCH: direction {d}, period {p:g} mm disagrees with the next coarser "
                       f"period in {n} px")
        for why, n in self.geometry_counts.items():
            if n:
                text = ("decoded coordinate outside the screen" if why == "outside_screen" else
                        "the pixel → screen mapping folds (orientation flipped against the nominal sample: "
                        "beyond a caustic of a rough or strongly curved sample)")
                out.append(f"GEOMETRY: {text} in {n} px")
        return out


@numba.njit(parallel=True, cache=True, nogil=True, fastmath=False, error_model="numpy")
def _stack_kernel(images, cos_d, sin_d, a_out, b_out, phi_out, rss_out, worst_out):
    """Per pixel of one stack (its N images as one read-only (N, H, W) array) with equal shifts: A, B,
    φ ∈ [0, 2π), RSS of the N-step fit and argmax_k |r_k| (docs/conventions.md, "Fringe
    patterns").

    Row by row, image by image along the row (contiguous, vectorised across pixels; per pixel
    the sums run over k in order, so A, B, RSS and the worst image are those of the pixel-by-
    pixel loop bit for bit), φ by the decoder's branch-free atan2 (:mod:`.fast_atan`, within
    1e-15 rad of libm's)."""
    n = len(images)
    h, w = a_out.shape
    for v in numba.prange(0, h):
        sa, sc, ss, rss, best = np.empty(w), np.empty(w), np.empty(w), np.empty(w), np.empty(w)
        worst = np.empty(w, np.int64)
        fit_row(images, 0, n, v, cos_d, sin_d, sa, sc, ss, rss, best, worst, 2)
        for u in range(w):
            a_out[v, u] = sa[u]
            b_out[v, u] = math.sqrt(sc[u] * sc[u] + ss[u] * ss[u])
            phi_out[v, u] = _phase_0_2pi(ss[u], sc[u])
            rss_out[v, u] = rss[u]
            worst_out[v, u] = worst[u]


def _stack_stats(stack):
    """A, B, φ, RSS and argmax_k |r_k| of one (N, H, W) stack (equal shifts), each (H, W)."""
    n, h, w = np.shape(stack)
    d = equal_shifts(n)
    out = [np.empty((h, w)) for _ in range(4)]
    worst = np.empty((h, w), np.int16)
    _stack_kernel(stack_images([stack]), np.cos(d), np.sin(d), *out, worst)
    if n <= 3:
        out[3][:] = 0.0  # an exact fit: no residual
    return (*out, worst)


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _grad(xy, v, u, d, axis):
    """np.gradient of component d along ``axis`` (1: u, 0: v) at (v, u): central inside,
    one-sided at the border."""
    h, w = xy.shape[0], xy.shape[1]
    if axis == 1:
        if u == 0:
            return (xy[v, 1, d] - xy[v, 0, d]) / 1.0
        if u == w - 1:
            return (xy[v, w - 1, d] - xy[v, w - 2, d]) / 1.0
        return (xy[v, u + 1, d] - xy[v, u - 1, d]) / 2.0
    if v == 0:
        return (xy[1, u, d] - xy[0, u, d]) / 1.0
    if v == h - 1:
        return (xy[h - 1, u, d] - xy[h - 2, u, d]) / 1.0
    return (xy[v + 1, u, d] - xy[v - 1, u, d]) / 2.0


@numba.njit(parallel=True, cache=True, nogil=True, fastmath=False, error_model="numpy")
def _orientation_kernel(measured, expected, out):
    """det(J₀⁻¹J) < 0 or trace(J₀⁻¹J) < 0 per pixel (see :func:`_orientation_flipped`); rows in parallel."""
    h, w = measured.shape[0], measured.shape[1]
    nan = np.nan
    for v in numba.prange(0, h):
        for u in range(w):
            # J[i, k] = ∂xy_i/∂(u, v)_k (k = 0: along u, 1: along v); NaN where an axis has one pixel.
            j00 = _grad(measured, v, u, 0, 1) if w >= 2 else nan
            j10 = _grad(measured, v, u, 1, 1) if w >= 2 else nan
            j01 = _grad(measured, v, u, 0, 0) if h >= 2 else nan
            j11 = _grad(measured, v, u, 1, 0) if h >= 2 else nan
            e00 = _grad(expected, v, u, 0, 1) if w >= 2 else nan
            e10 = _grad(expected, v, u, 1, 1) if w >= 2 else nan
            e01 = _grad(expected, v, u, 0, 0) if h >= 2 else nan
            e11 = _grad(expected, v, u, 1, 0) if h >= 2 else nan
            det0 = e00 * e11 - e01 * e10
            a00, a11, a01, a10 = e11, e00, -e01, -e10
            m00 = (a00 * j00 + a01 * j10) / det0
            m01 = (a00 * j01 + a01 * j11) / det0
            m10 = (a10 * j00 + a11 * j10) / det0
            m11 = (a10 * j01 + a11 * j11) / det0
            det_m = m00 * m11 - m01 * m10
            tr_m = m00 + m11
            out[v, u] = (det_m < 0) or (tr_m < 0)


def _noise_idx(mask) -> np.ndarray:
    """The pixels (flat indices into (H, W)) the noise model samples: all of ``mask``, or a
    seeded subsample of at most ``_MAX_NOISE_SAMPLES`` (the medians/means need no more)."""
    idx = np.flatnonzero(mask)
    if idx.size > _MAX_NOISE_SAMPLES:
        idx = np.sort(np.random.default_rng(0).choice(idx, _MAX_NOISE_SAMPLES, replace=False))
    return idx


def _noise_model(sampled):
    """Fit σ_I² = a + b·A to the residual variances (see the module docstring): ``sampled`` per
    stack with more than 3 images (A, RSS, ν) at the pixels of :func:`_noise_idx`."""
    lines = []
    for av, rv, nu in sampled:
        vv = rv / nu  # RSS/ν at the sampled pixels only (no full-size quotient)
        # Mean of the lower 90 % of RSS/ν (robust to a few bad pixels, and smooth for the discrete
        # residuals of quantised images, unlike a median), corrected by its value for χ²(ν)/ν:
        # E[χ²_ν; χ²_ν < Q] = ν·F_{ν+2}(Q).
        trim = chi2_cdf(chi2_ppf(_TRIM, nu), nu + 2) / _TRIM
        edges = np.unique(np.quantile(av, np.linspace(0.0, 1.0, _N_BINS + 1)))
        centres, values = [], []
        for i in range(max(edges.size - 1, 1)):
            sel = (av >= edges[i]) & (av <= edges[min(i + 1, edges.size - 1)])
            if np.count_nonzero(sel) >= 20:
                v = vv[sel]
                centres.append(float(np.median(av[sel])))
                values.append(float(np.mean(v[v <= np.quantile(v, _TRIM)])) / trim)
        if centres:
            design = np.column_stack([np.ones(len(centres)), np.asarray(centres)])
            coef, _ = nnls(design, np.asarray(values))
            if np.ptp(centres) < 0.5 * np.median(centres):  # too narrow a range of A for a slope: a constant
                coef = np.array([float(np.median(values)), 0.0])
            lines.append(coef)
    if not lines:
        return None
    return np.asarray(lines)  # (S, 2): one (a, b) per stack


def _item_stats(it):
    """A, B, φ, RSS and the worst image of one stack of :func:`check_consistency` (see there)."""
    st_a, st_b, st_phi, st_rss, st_worst = _stack_stats(it["stack"])
    if it["n"] == 4:  # r ∝ (1, −1, 1, −1): every frame has the same |residual|
        st_worst = np.full(st_worst.shape, it["n"], np.int16)
    return st_a, st_b, st_phi, st_rss, st_worst


def _noise_pass(items, tested):
    """The noise model's pixels (``tested`` where every stack's RSS is finite) and lines
    (:func:`_noise_model`, None if there are too few pixels or no stack of more than 3 images).
    One stack's maps alive at a time for integer images (their RSS is finite: the pixels are
    known before); for float images A and RSS of every stack until the pixels are known."""
    usable = [it for it in items if it["n"] > 3]
    integer = all(np.asarray(it["stack"]).dtype.kind in "ui" for it in items)
    kept = []
    if integer:
        mask = tested
    else:
        mask = tested.copy()
        for it in items:
            st = _item_stats(it)
            mask &= np.isfinite(st[3])
            if it["n"] > 3:
                kept.append((st[0], st[3], it["n"] - 3))
    if not usable or np.count_nonzero(mask) < _MIN_NOISE_PIXELS:
        return mask, None
    idx = _noise_idx(mask)
    if integer:  # A and RSS at the sampled pixels only (bit for bit the maps' values there)
        from .consistency_sample import stack_at_pixels

        for it in usable:
            kept.append((*stack_at_pixels(it["stack"], idx), it["n"] - 3))
    else:
        kept = [(a.ravel()[idx], r.ravel()[idx], nu) for a, r, nu in kept]
    return mask, _noise_model(kept)


def check_consistency(
    x_stacks: Sequence,
    x_periods_mm,
    y_stacks: Sequence,
    y_periods_mm,
    decoded: ScreenCoordinates,
    screen_size_mm,
    noise_std=None,
    *,
    screen_origin_mm=(0.0, 0.0),
    margin_mm: float | None = None,
    expected_xy_mm: np.ndarray | None = None,
    false_alarm: float = DEFAULT_FALSE_ALARM,
    defect_fraction: float = DEFAULT_DEFECT_FRACTION,
) -> ConsistencyResult:
    """Per-image, per-period and geometric consistency of one camera's decoded fringe images.

    Parameters
    ----------
    x_stacks, y_stacks : sequence of array_like, each (N_i, H, W)
        The image stacks the decoder was given (equally spaced shifts δ_k = 2πk/N), grey levels.
    x_periods_mm, y_periods_mm : array_like (P_x,), (P_y,)
        Their periods in mm (as stated: a wrong period is what is tested).
    decoded : ScreenCoordinates
        The decoder's result for these stacks (its photometric flags select the tested pixels).
    screen_size_mm : (float, float)
        Screen width and height (mm): the unwrapping extent.
    noise_std : float or array_like broadcastable to (H, W), optional
        Intensity noise σ_I (grey levels) the decoder was given; default quantisation 1/√12.
        The checks use the larger of it and the noise estimated from the images.
    screen_origin_mm : (float, float)
        Lowest (x_q, y_q) on the screen (mm), as for the decoder.
    margin_mm : float, optional
        The decoder's unwrapping margin (default half the unused part of the coarsest period).
    expected_xy_mm : ndarray (H, W, 2), optional
        Screen coordinates predicted for the nominal sample (:func:`nominal_screen_xy`); enables
        the orientation check.
    false_alarm : float
        Per-test false-alarm probability α in (0, 0.5) of the residual and period checks.
    defect_fraction : float
        A stack, period or direction that fails a check in more than this fraction of the tested
        pixels is taken as defective as a whole and all its tested pixels are flagged (its other
        pixels pass by chance: e.g. a wrong period agrees wherever the error happens to be near
        a multiple of the finer period).

    Returns
    -------
    ConsistencyResult

    Raises
    ------
    PhaseDecodingError
        If the stacks, periods or ``decoded`` do not fit together.
    """
    if not (0.0 < float(false_alarm) < 0.5):
        raise PhaseDecodingError(f"false_alarm must be in (0, 0.5), got {false_alarm!r}")
    if not (0.0 < float(defect_fraction) <= 1.0):
        raise PhaseDecodingError(f"defect_fraction must be in (0, 1], got {defect_fraction!r}")
    h, w = decoded.flags.shape
    size = np.asarray(screen_size_mm, dtype=np.float64).reshape(2)
    origin = np.asarray(screen_origin_mm, dtype=np.float64).reshape(2)
    tested = (decoded.flags & _PHOTOMETRIC) == 0
    if noise_std is None:
        noise_std = QUANTISATION_NOISE_STD
    if np.any(np.asarray(noise_std) <= 0):
        raise PhaseDecodingError(f"noise_std must be > 0 grey levels, got {noise_std!r}")
    given2 = np.broadcast_to(np.asarray(noise_std, dtype=np.float64) ** 2, (h, w))

    # The stacks, directions in order, sorted coarse → fine within a direction. A stack's (H, W)
    # maps (A, B, φ, RSS, worst image: 78 MB at 1920×1200) are computed where they are used, not
    # kept for all stacks at once (issue 25: memory): once for the noise model's samples, once in
    # the checks below.
    labels: list[ImageLabel] = []
    per_dir = []
    for direction, stacks, periods in (("x", x_stacks, x_periods_mm), ("y", y_stacks, y_periods_mm)):
        periods = np.asarray(periods, dtype=np.float64).reshape(-1)
        stacks = list(stacks)
        if len(stacks) != periods.size:
            raise PhaseDecodingError(f"direction {direction!r}: {len(stacks)} stacks but {periods.size} periods")
        items = []
        for stack, p in zip(stacks, periods):
            shape = np.shape(stack)
            if len(shape) != 3 or shape[1:] != (h, w):
                raise PhaseDecodingError(f"direction {direction!r}, period {p:g} mm: image size {shape[1:]} "
                                         f"differs from the decoded map's {(h, w)}")
            n = shape[0]
            items.append(dict(p=float(p), n=n, stack=stack, first=len(labels)))
            labels.extend(ImageLabel(direction, float(p), k) for k in range(n))
            if n == 4:
                labels.append(ImageLabel(direction, float(p), None))
        items.sort(key=lambda it: -it["p"])
        per_dir.append((direction, items))

    all_items = [it for _, items in per_dir for it in items]
    mask, lines = _noise_pass(all_items, tested)

    period_counts: dict = {}
    geometry_counts = {"outside_screen": 0, "orientation": 0}
    defects: list[str] = []
    z = norm_isf(float(false_alarm) / 2.0)
    n_tested = int(np.count_nonzero(tested))
    limit = float(defect_fraction) * n_tested

    # One pass over image rows for every stack of both directions (:mod:`.consistency_levels`):
    # the N-step fit, σ_I², both tests, the coordinates, the outside-screen test; per stack the
    # tests' pixels as bits, their counts, and the largest σ_I².
    bounds = []
    for axis, (direction, items) in enumerate(per_dir):
        ext = float(size[axis])
        margin = 0.5 * (items[0]["p"] - ext) if margin_mm is None else float(margin_mm)
        tol = OUTSIDE_SCREEN_FRACTION * ext
        bounds.append((float(origin[axis]), float(origin[axis] + ext + margin), origin[axis] - tol,
                       origin[axis] + ext + tol))
        for it in items:
            it["thr"] = chi2_isf(float(false_alarm), it["n"] - 3) if it["n"] > 3 else 0.0
    typical = lines is not None and mask.any()  # A of all_items[0] at the noise pixels
    with np.errstate(invalid="ignore", divide="ignore"):
        rows = check_stacks([items for _, items in per_dir], lines=lines, given2=given2, tested=tested,
                            rev=np.ascontiguousarray(decoded.reversed), z=z, origin=[b[0] for b in bounds],
                            upper=[b[1] for b in bounds], lo=[b[2] for b in bounds], hi=[b[3] for b in bounds],
                            a_stack=0 if typical else -1, mask=mask if typical else None)
    if typical:
        a_typical = np.nanmedian(rows.a_at_mask)
    top_given = float(np.nanmax(np.where(tested, given2, 0.0))) if lines is None else 0.0
    noise_max = max(float(np.sqrt(top_given if lines is None else t)) for t in rows.top)
    flags = rows.flags  # GEOMETRY outside the screen
    geometry_counts["outside_screen"] = int(rows.n_outside.sum())
    fit_ratio, mis_ratio, final = rows.fit_ratio, rows.mis_ratio, rows.final
    # The whole-stack rules, stack by stack in the pass's order (x then y, coarse → fine).
    fit_stacks, escalated, fit_defect = [], None, False
    s = 0
    for axis, (direction, items) in enumerate(per_dir):
        dir_stacks, dir_bad = [], None
        for level, it in enumerate(items):
            if it["n"] > 3:
                fit_stacks.append(s)
                n_fit = int(rows.n_fit[s])
                if n_tested and n_fit > limit:
                    # A frame of this stack is bad as a whole: its other pixels agree by chance.
                    bad = rows.bad_fit(s)
                    k = int(np.bincount(_item_stats(it)[4][bad], minlength=it["n"] + 1).argmax())
                    defects.append(f"image ({labels[it['first'] + k]}) deviates from its period's "
                                   f"sinusoid in {n_fit / n_tested:.0%} of the pixels")
                    if escalated is None:
                        escalated = np.full((h, w), -1, np.int16)  # the defective stack's label, where only it flags
                    escalated[tested & ~bad & (escalated < 0)] = it["first"] + k
                    fit_defect = True
            if level > 0:
                n_per = int(rows.n_per[s])
                whole = bool(n_tested and n_per > limit)
                if whole:
                    # The period disagrees as a whole (wrong period, shifted images, wrong shifts):
                    # where it agrees, it does so by chance.
                    defects.append(f"direction {direction}, period {it['p']:g} mm disagrees with the "
                                   f"{items[level - 1]['p']:g} mm period in "
                                   f"{n_per / n_tested:.0%} of the pixels")
                if whole or dir_bad is not None:  # the pixels new to this level, counted anew
                    if dir_bad is None:
                        dir_bad = rows.any_bit(rows.bits_per, dir_stacks)
                    bad = tested.copy() if whole else rows.bad_per(s)
                    new = int(np.count_nonzero(bad & ~dir_bad))
                    dir_bad |= bad
                else:  # counted in the pass
                    new = int(rows.n_new[s])
                    dir_stacks.append(s)
                if new:
                    period_counts[(direction, it["p"])] = new
            s += 1
        if dir_bad is None:
            dir_bad = rows.any_bit(rows.bits_per, dir_stacks)
        flags[dir_bad] |= np.uint8(PhaseFlag.PERIOD_MISMATCH)

    fit_bad = tested.copy() if fit_defect else rows.any_bit(rows.bits_fit, fit_stacks)
    flags[fit_bad] |= np.uint8(PhaseFlag.FIT_RESIDUAL)
    worst_image = rows.worst_image
    if escalated is None:
        worst_image[~(fit_bad & (fit_ratio > 1.0))] = -1
    else:
        worst_image = np.where(fit_ratio > 1.0, worst_image, escalated).astype(np.int16)
        worst_image[~fit_bad] = -1
    with np.errstate(invalid="ignore", divide="ignore"):
        if expected_xy_mm is not None:
            flipped = tested & _orientation_flipped(final, np.asarray(expected_xy_mm, dtype=np.float64))
            if n_tested and np.count_nonzero(flipped) > 0.9 * n_tested:  # mirrored as a whole
                defects.append(f"the mapping's orientation is flipped against the nominal sample in "
                               f"{np.count_nonzero(flipped) / n_tested:.0%} of the pixels (a reversed shift "
                               f"order or swapped x/y directions?)")
                flipped = tested
            flags[flipped] |= np.uint8(PhaseFlag.GEOMETRY)
            geometry_counts["orientation"] = int(np.count_nonzero(flipped))
    idx, cnt = np.unique(worst_image[worst_image >= 0], return_counts=True)
    image_counts = {labels[int(i)]: int(n) for i, n in zip(idx, cnt)}
    return ConsistencyResult(
        flags=flags, fit_residual_ratio=fit_ratio, period_mismatch_ratio=mis_ratio, worst_image=worst_image,
        images=tuple(labels), image_counts=image_counts, period_counts=period_counts,
        geometry_counts=geometry_counts, defects=tuple(defects), tested=tested,
        noise_model=(math.nan, math.nan) if lines is None else tuple(float(v) for v in lines[np.argmin(lines[:, 0] + lines[:, 1] * a_typical if mask.any() else lines[:, 0])]),
        noise_std_max=noise_max,
        false_alarm=float(false_alarm), noise_lines=lines, given_noise_std=noise_std,
    )


def _orientation_flipped(measured_xy: np.ndarray, expected_xy: np.ndarray) -> np.ndarray:
    """det(J₀⁻¹J) < 0 or trace(J₀⁻¹J) < 0 (see the module docstring), (H, W) bool."""
    if expected_xy.shape != measured_xy.shape:
        raise PhaseDecodingError(f"expected_xy_mm: shape {expected_xy.shape}, expected {measured_xy.shape}")
    # J (and J₀) = ∂(x, y)/∂(u, v) by np.gradient's differences (central; one-sided at the border), M = adj(J₀)·J/det J₀,
    # per pixel in one pass; NaN compares False: untested.
    out = np.empty(measured_xy.shape[:2], bool)
    _orientation_kernel(np.ascontiguousarray(measured_xy, dtype=np.float64),
                        np.ascontiguousarray(expected_xy, dtype=np.float64), out)
    return out


def with_consistency(decoded: ScreenCoordinates, result: ConsistencyResult, *,
                     rescale_std: bool = False, in_place: bool = False) -> ScreenCoordinates:
    """``decoded`` with the consistency flags OR-ed in; newly flagged pixels become invalid (NaN).

    ``rescale_std``: scale ``std_xy_mm`` (∝ σ_I, :func:`.phase.decode_direction`) from the noise
    the decoder was given to the noise the checks found in the images
    (:meth:`ConsistencyResult.noise_std_at` of the finest periods' offsets).
    ``in_place``: write the NaN into ``decoded``'s ``screen_xy_mm`` and ``std_xy_mm`` (no (H, W, 2)
    copies; for a caller that drops ``decoded``, issue 25).
    """
    flags = decoded.flags | result.flags
    valid = flags == 0
    xy, std = decoded.screen_xy_mm, decoded.std_xy_mm
    if in_place and xy.flags.writeable and std.flags.writeable and not np.may_share_memory(xy, std):
        invalid = ~valid
        xy[invalid] = np.nan
        std[invalid] = np.nan
    else:
        xy = np.where(valid[..., None], xy, np.nan)
        std = np.where(valid[..., None], std, np.nan)
    if rescale_std:
        given = np.broadcast_to(np.asarray(result.given_noise_std, dtype=np.float64), valid.shape)
        for d in range(2):
            std[..., d] *= result.noise_std_at(decoded.offset[..., d]) / given
    return ScreenCoordinates(screen_xy_mm=xy, valid=valid, flags=flags, std_xy_mm=std,
                             modulation=decoded.modulation, offset=decoded.offset, reversed=decoded.reversed)


def nominal_screen_xy(camera: Camera, T_world_cam: RigidTransform, T_world_sample: RigidTransform,
                      T_world_screen: RigidTransform) -> np.ndarray:
    """Screen coordinates (x_q, y_q) each pixel would see via a mirror in the sample's x–y plane.

    The view ray (paper §2.2) is reflected at the plane z = 0 of the sample frame and
    intersected with the plane z = 0 of the screen frame (the planar screen model).

    Returns
    -------
    ndarray (H, W, 2), mm, screen frame; NaN where the ray misses either plane (or the
    distortion cannot be inverted).
    """
    d_cam, ok = camera.sensor_rays()
    n = T_world_sample.apply_vector(np.array([0.0, 0.0, 1.0]))
    m = T_world_screen.apply_vector(np.array([0.0, 0.0, 1.0]))
    inv = T_world_screen.inv()
    xy = np.empty(d_cam.shape[:-1] + (2,))
    _nominal_kernel(np.ascontiguousarray(d_cam), np.ascontiguousarray(ok), np.ascontiguousarray(T_world_cam.rotation),
                    np.ascontiguousarray(T_world_cam.translation), n, np.ascontiguousarray(T_world_sample.translation),
                    m, np.ascontiguousarray(T_world_screen.translation), np.ascontiguousarray(inv.rotation),
                    np.ascontiguousarray(inv.translation), xy)
    return xy


@numba.njit(parallel=True, cache=True, nogil=True, fastmath=False, error_model="numpy")
def _nominal_kernel(d_cam, ok, r_wc, o, n, p0, m, t_scr, r_sw, t_sw, out):
    """Per pixel of :func:`nominal_screen_xy`: the view ray d = R·d_cam from o, reflected at the
    plane (p0, n), intersected with the plane (t_scr, m), in the screen frame (R_sw·q + t_sw); rows
    in parallel."""
    h, w = d_cam.shape[0], d_cam.shape[1]
    for v in numba.prange(0, h):
        for u in range(w):
            dc0, dc1, dc2 = d_cam[v, u, 0], d_cam[v, u, 1], d_cam[v, u, 2]
            d0 = dc0 * r_wc[0, 0] + dc1 * r_wc[0, 1] + dc2 * r_wc[0, 2]
            d1 = dc0 * r_wc[1, 0] + dc1 * r_wc[1, 1] + dc2 * r_wc[1, 2]
            d2 = dc0 * r_wc[2, 0] + dc1 * r_wc[2, 1] + dc2 * r_wc[2, 2]
            dn = d0 * n[0] + d1 * n[1] + d2 * n[2]
            t = ((p0[0] - o[0]) * n[0] + (p0[1] - o[1]) * n[1] + (p0[2] - o[2]) * n[2]) / dn
            h0, h1, h2 = o[0] + t * d0, o[1] + t * d1, o[2] + t * d2
            r0, r1, r2 = d0 - 2.0 * dn * n[0], d1 - 2.0 * dn * n[1], d2 - 2.0 * dn * n[2]
            t2 = (((t_scr[0] - h0) * m[0] + (t_scr[1] - h1) * m[1] + (t_scr[2] - h2) * m[2])
                  / (r0 * m[0] + r1 * m[1] + r2 * m[2]))
            q0, q1, q2 = h0 + t2 * r0, h1 + t2 * r1, h2 + t2 * r2
            if ok[v, u] and t > 0 and t2 > 0:
                out[v, u, 0] = q0 * r_sw[0, 0] + q1 * r_sw[0, 1] + q2 * r_sw[0, 2] + t_sw[0]
                out[v, u, 1] = q0 * r_sw[1, 0] + q1 * r_sw[1, 1] + q2 * r_sw[1, 2] + t_sw[1]
            else:
                out[v, u, 0] = np.nan
                out[v, u, 1] = np.nan
