"""The calibration's contribution to the standard uncertainty of stereo heights and slopes (issue 22).

A stereo evaluation (:mod:`pmdsim.evaluation.stereo`) fixes its heights by normal-consistency
anchors between calibrated cameras: the cameras' intrinsics and poses, the table plane (the
sample frame) and, with a free-form screen model, the screen heights all move the absolute
heights. To first order (GUM) their covariance is J C Jᵀ, C the calibration covariance the
setup carries (:class:`~pmdsim.setup.covariance.CalibrationCovariance`); as for mono
(:mod:`pmdsim.evaluation.uncertainty_calibration`) C is decomposed into principal axes in
correlation units (:func:`~pmdsim.evaluation.uncertainty_calibration.principal_axes`) — here of
the parameters acting on *any* camera (every camera's own, the table, the glass, the screen
heights when the evaluation uses the screen surface), since each anchor joins two cameras —
and for each axis k, with the setup moved by ε·δ_k (ε = 0.01 σ, forward difference):

1. every camera's decoded coordinates are registered again (:func:`~pmdsim.evaluation.stereo.stereo_views`);
2. every anchor's height is re-solved on its moved ray with its partner by the search's own
   Gauss–Newton (:func:`~pmdsim.evaluation.stereo.refine_anchors`) from its height: δa_k;
3. each camera's anchored least-squares integration is linearised at its solution: the moved
   geometry changes the right-hand side of the Gauss–Newton normal equations at the unchanged
   heights z, b_k = b(p + εδ_k; z) − b(p; z) (the slope equations and the anchors' w²(a − z)),
   and δz_k = N⁻¹ b_k/ε, N the Gauss–Newton matrix of the evaluation (anchor weight on its
   diagonal), solved by the multigrid-preconditioned CG — exactly the first-order change of the
   solution;
4. the slopes δg_k: the bisector slopes of the moved rays and screen points at z + εδz_k minus
   the evaluation's, over ε.

Var z = Σ_k δz_k², Var g = Σ_k δg_k². As for mono, on large images steps 1–4 run on a pixel
subgrid of stride s (default :func:`default_stereo_stride`: a subgrid of at least 150 px on the
shorter side; every camera as the camera of focal length f/s),
each anchor moved to its nearest subgrid pixel with its anchor weight (w² times the anchors
there, so that the anchors keep their total weight; the slope equations' stiffness of a smooth
field does not depend on the grid spacing), and each axis's changes are interpolated bilinearly
to every pixel before squaring (Σ_k through each cell's Gram matrix over the axes,
:mod:`pmdsim.evaluation.uncertainty_gram`: equal to the per-axis sum up to rounding).
The subgrid underestimates σ, more than mono's, the more the coarser it is (measured: about 2 %
with a 120 × 75 px subgrid, 5 % with 60 × 38, 15 % with 30 × 19; its cause is not identified),
hence the default's minimum subgrid of 150 px. The heights are absolute, as the stereo heights: nothing
is held. What it does not cover: parameters the calibration held (k3, the screen pose: the
gauge), the images' noise (:mod:`pmdsim.evaluation.uncertainty_stereo`), model errors.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numba
import numpy as np

from ..geometry.kernel_args import numba_threads
from ..setup.covariance import perturbed_setup
from .integration import _points_and_normals
from .least_squares import _assemble_gauss_newton
from .multigrid import _CGWork, _Multigrid, _pcg
from .stereo import ANCHOR_WEIGHT, StereoReconstruction, _view_arrays, refine_anchors, stereo_views
from .surface_fit import sample_slopes
from .uncertainty_calibration import (DEFAULT_STEP, CalibrationContribution, CalibrationUncertaintyError,
                                      _interpolated_squares, _strided, calibration_parameters,
                                      principal_axes)
from .uncertainty_gram import interpolated_std_maps

__all__ = ["StereoCalibrationContribution", "StereoLinearisation", "stereo_calibration_contribution",
           "stereo_calibration_parameters", "default_stereo_stride", "MIN_SUBGRID_PX"]

#: Relative tolerance of each axis's solve (a few dozen solves: tight).
_RTOL = 1e-6

#: Numba threads of the calibration part (:func:`stereo_calibration_contribution`). Its work is
#: a few hundred small kernel calls (a 240 × 150 px subgrid, ≈ 1 ms each on one thread); with
#: more threads each call's parallel region costs more than it saves, and the OpenMP layer's
#: waiting threads spin: measured at 240 × 150 px, load 4, 2 vCPUs, 3.82 s CPU with 2 threads
#: against 1.27 s with one (wall 3.87 s against 1.39 s; docs/benchmarks.md "Uncertainty: stereo
#: calibration part at full resolution").
THREADS = 1


@numba.njit(cache=True, nogil=True, parallel=True)
def _std_maps(var, S, h_um, g_urad):
    """From the variances var (H, W, 3) (height mm², slopes): h_um (H, W) = sqrt(var₀)·1e3 and
    g_urad (H, W, 2) = sqrt(var₁,₂)·1e6 on S, NaN off it — numpy's ``np.sqrt(var[..., 0]) * 1e3``
    after ``var[~S] = nan`` bit for bit, in one pass without its temporaries."""
    H, W = S.shape
    for v in numba.prange(0, H):
        for u in range(W):
            if S[v, u]:
                h_um[v, u] = np.sqrt(var[v, u, 0]) * 1e3
                g_urad[v, u, 0] = np.sqrt(var[v, u, 1]) * 1e6
                g_urad[v, u, 1] = np.sqrt(var[v, u, 2]) * 1e6
            else:
                h_um[v, u] = np.nan
                g_urad[v, u, 0] = np.nan
                g_urad[v, u, 1] = np.nan


@dataclass(frozen=True, eq=False)
class StereoCalibrationContribution:
    """The calibration's contribution to a stereo evaluation's standard uncertainties (k = 1).

    Attributes
    ----------
    cameras : dict name → CalibrationContribution
        Per camera ``height_std_um`` (H, W, absolute) and ``slope_std_urad`` (H, W, 2); NaN
        where not reconstructed; ``stride_px`` the subgrid's stride.
    anchor_height_std_um : dict name → ndarray (n,)
        The calibration's standard uncertainty of each anchor height, µm (its subgrid
        anchor's; NaN for an anchor off the reconstruction).
    parameters : tuple of str
        The calibrated parameters propagated.
    n_axes : int
        Principal axes evaluated.
    notes : tuple of str
        E.g. anchors or pixels that a moved setup lost (their change taken as 0).
    seconds : float
        Wall time.
    """

    cameras: dict
    anchor_height_std_um: dict
    parameters: tuple
    n_axes: int
    notes: tuple = ()
    seconds: float = 0.0


#: The shortest subgrid side the default stride keeps (pixels): the subgrid underestimates σ
#: by about 2 % at 75 px, 5 % at 38 px (docs/benchmarks.md).
MIN_SUBGRID_PX = 150


def default_stereo_stride(shape) -> int:
    """The calibration part's default subgrid stride: min(H, W) // :data:`MIN_SUBGRID_PX`, at
    least 1 (every pixel below 300 px; 8 at 1920 × 1200, a 240 × 150 subgrid)."""
    return max(1, min(int(shape[0]), int(shape[1])) // MIN_SUBGRID_PX)


def stereo_calibration_parameters(setup, cameras, *, screen_model=None) -> tuple:
    """The covariance's parameters acting on a stereo evaluation of ``cameras``: the union of
    :func:`~pmdsim.evaluation.uncertainty_calibration.calibration_parameters`, in the
    covariance's order."""
    used = set()
    for c in cameras:
        used.update(calibration_parameters(setup, c, screen_model=screen_model))
    return tuple(n for n in setup.calibration_covariance.parameters if n in used)


@dataclass(frozen=True, eq=False)
class _Sampled:
    """A camera's decoded coordinates on the subgrid (what :func:`stereo_views` reads)."""

    screen_xy_mm: np.ndarray
    valid: np.ndarray


class _Camera:
    """One camera's linearised anchored integration (module docstring, step 3) on its (sub)grid:
    reconstructed pixels S, heights z, anchors at the pixels ``nodes`` (m, 2) of weight² ``w2``
    (m,) with heights ``a_base``."""

    def __init__(self, view, S, z, nodes, w2, a_base):
        o, d, q, _ = _view_arrays(view)
        self.S = S = np.ascontiguousarray(S)
        self.z = np.ascontiguousarray(np.where(S, z, 0.0))
        self.nodes, self.w2 = nodes, w2
        self.av, self.au = nodes[:, 0] + 1, nodes[:, 1] + 1
        H, W = S.shape
        shape = (H + 2, W + 2)
        self.D, self.iD, self.Ex, self.Ey = (np.zeros(shape) for _ in range(4))
        self.rhs0 = self._rhs(o, d, q, a_base, self.D, self.iD, self.Ex, self.Ey)
        self.D[self.av, self.au] += w2
        self.iD[self.av, self.au] = 1.0 / self.D[self.av, self.au]
        self.mg = _Multigrid(self.D, self.iD, self.Ex, self.Ey)
        self.work = _CGWork(shape)
        self.scratch = tuple(np.zeros(shape) for _ in range(4))
        self.q0 = q
        self.g0 = self._slopes(o, d, q, self.z)

    def _rhs(self, o, d, q, a, D, iD, Ex, Ey) -> np.ndarray:
        rhs = np.zeros_like(D)
        _assemble_gauss_newton(o, d, q, self.S, self.z, -1, -1, D, iD, Ex, Ey, rhs)
        rhs[self.av, self.au] += self.w2 * (a - self.z[self.nodes[:, 0], self.nodes[:, 1]])
        return rhs

    def _slopes(self, o, d, q, z) -> np.ndarray:
        _, n = _points_and_normals(o, d, q, np.where(self.S, z, np.nan))
        return sample_slopes(n)

    def change(self, view, a):
        """(δz (H, W) mm, δg (H, W, 2), pixels whose moved screen point was lost) of the moved
        view and anchor heights ``a``: one Gauss–Newton step from the evaluation's solution."""
        o, d, q, ok = _view_arrays(view)
        lost = self.S & ~ok
        if lost.any():  # a moved registration lost a pixel: its screen point taken as unmoved
            q = np.where(lost[..., None], self.q0, q)
        b = self._rhs(o, d, q, a, *self.scratch) - self.rhs0
        scale = float(np.max(np.abs(b)))
        if scale == 0.0:
            dz = np.zeros(self.S.shape)
        else:  # solved for b / scale: the tolerances are relative
            x, _, conv = _pcg(self.D, self.iD, self.Ex, self.Ey, b / scale, 0.0, _RTOL, 500, work=self.work,
                              mg=self.mg)
            if not conv or not np.isfinite(x[1:-1, 1:-1][self.S]).all():
                raise CalibrationUncertaintyError("the linearised anchored least-squares system did not converge")
            dz = np.array(x[1:-1, 1:-1]) * scale
        g = self._slopes(o, d, q, self.z + dz)
        return np.where(self.S, dz, np.nan), g - self.g0, int(lost.sum())


class StereoLinearisation:
    """A stereo evaluation's heights, slopes and anchors linearised in the calibrated
    parameters ``names`` (module docstring, steps 1–4), on every ``stride``-th pixel.

    Parameters
    ----------
    setup, decoded, stereo, screen_model
        As :func:`stereo_calibration_contribution`.
    names : sequence of str
        The parameters of the steps given to :meth:`change`.
    stride : int
        Subgrid stride s: every camera is taken as the camera of focal length f/s whose pixel
        (v', u') is pixel (o + s·v', o + s·u'), o = (the search's stride // 2) mod s (so that the
        anchors lie on the subgrid when s divides the search's stride); each anchor moves to its
        nearest subgrid pixel, whose anchor weight² is w² times the anchors there. 1: every pixel.

    Attributes
    ----------
    offset : int
        o above (the subgrid's first row and column).
    cameras : dict name → _Camera
    anchor_node : dict name → ndarray (n,) of int
        Each anchor's subgrid anchor (index into that camera's subgrid anchors; −1: not on the
        reconstruction).
    """

    def __init__(self, setup, decoded: dict, stereo: StereoReconstruction, names, *, screen_model=None,
                 stride: int = 1):
        cams = list(stereo.cameras)
        missing = [c for c in cams if c not in decoded]
        if missing:
            raise CalibrationUncertaintyError(f"camera(s) {missing} have a stereo reconstruction but no decoded images")
        s = int(stride)
        if s < 1:
            raise CalibrationUncertaintyError(f"stride must be ≥ 1, got {stride!r}")
        self.setup, self.stereo, self.names, self.stride = setup, stereo, tuple(names), s
        self.offset = o = (int(stereo.stride_px) // 2) % s
        self.decoded = {c: _Sampled(np.ascontiguousarray(np.asarray(decoded[c].screen_xy_mm, dtype=float)[o::s, o::s]),
                                    np.ascontiguousarray(np.asarray(decoded[c].valid, dtype=bool)[o::s, o::s]))
                        for c in cams}
        self.screen_model = screen_model
        views = stereo_views(self._sampled(setup), self.decoded, screen_model=screen_model)
        self.cameras, self.partners, self.a_base, self.anchor_node = {}, {}, {}, {}
        for c in cams:
            sc = stereo.cameras[c]
            S = np.asarray(sc.reconstructed)[o::s, o::s]
            z = np.asarray(sc.height_mm)[o::s, o::s]
            h, w = S.shape
            vu = np.asarray(sc.anchor_pixels, dtype=np.int64).reshape(-1, 2)
            nv = np.clip(np.rint((vu[:, 0] - o) / s), 0, h - 1).astype(np.int64)
            nu = np.clip(np.rint((vu[:, 1] - o) / s), 0, w - 1).astype(np.int64)
            on = S[nv, nu]
            if not on.any():
                raise CalibrationUncertaintyError(f"camera {c!r}: no anchor lies on the reconstructed pixels")
            nodes, inv, counts = np.unique(np.stack([nv[on], nu[on]], axis=-1), axis=0, return_inverse=True,
                                           return_counts=True)
            node = np.full(vu.shape[0], -1, dtype=np.int64)
            node[on] = inv.reshape(-1)
            self.anchor_node[c] = node
            start = z[nodes[:, 0], nodes[:, 1]]
            a, _, self.partners[c] = refine_anchors(views, c, nodes, start)
            self.a_base[c] = np.where(np.isfinite(a), a, start)  # the search's roots, re-solved on the subgrid
            self.cameras[c] = _Camera(views[c], S, z, nodes, ANCHOR_WEIGHT ** 2 * counts.astype(float), self.a_base[c])
        self.lost_px = 0
        self.lost_anchors = 0

    def _sampled(self, setup):
        """``setup`` with its cameras on the subgrid."""
        if self.stride == 1:
            return setup
        cams = dict(setup.cameras)
        for c, dec in self.decoded.items():
            cams[c] = replace(cams[c], camera=_strided(setup, c, self.stride, self.offset, self.offset,
                                                        dec.valid.shape))
        return setup.with_cameras(cams)

    def _moved(self, delta) -> dict:
        m = perturbed_setup(self.setup, delta, self.names)
        sm = None if self.screen_model is None else m.screen.surface
        v = stereo_views(self._sampled(m), self.decoded, screen_model=sm)
        out = {}
        for c, lin in self.cameras.items():
            a, _, _ = refine_anchors(v, c, lin.nodes, self.a_base[c], partners=self.partners[c])
            bad = ~np.isfinite(a)
            a = np.where(bad, self.a_base[c], a)  # an anchor lost by the move: taken as unmoved
            dz, dg, lost = lin.change(v[c], a)
            out[c] = (dz, dg, a - self.a_base[c])
            self.lost_px, self.lost_anchors = max(self.lost_px, lost), max(self.lost_anchors, int(bad.sum()))
        return out

    def change(self, delta, *, central: bool = False) -> dict:
        """The first-order change of every camera's (heights (h, w) mm, slopes (h, w, 2) on the
        subgrid, subgrid anchor heights (m,) mm) for the parameter step ``delta`` (natural units,
        in ``names``' order): the moved setup's (forward), or half the difference of the setups
        moved by ±delta (``central``)."""
        delta = np.asarray(delta, dtype=float)
        fwd = self._moved(delta)
        if not central:
            return fwd
        bwd = self._moved(-delta)
        return {c: tuple(0.5 * (f - b) for f, b in zip(fwd[c], bwd[c])) for c in fwd}


def stereo_calibration_contribution(setup, decoded: dict, stereo: StereoReconstruction, *, screen_model=None,
                                    stride: int | None = None, step: float = DEFAULT_STEP,
                                    central: bool = False, threads: int = THREADS) -> StereoCalibrationContribution:
    """Per-pixel standard uncertainty of a stereo evaluation's heights and slopes from the
    calibration covariance ``setup`` carries (module docstring).

    Parameters
    ----------
    setup : Setup
        The evaluating (calibrated) setup, with ``calibration_covariance``.
    decoded : dict name → ScreenCoordinates
        Every camera's decoded coordinates, as evaluated.
    stereo : StereoReconstruction
        The evaluation (:func:`~pmdsim.evaluation.stereo.reconstruct_stereo` of the views
        :func:`~pmdsim.evaluation.stereo.stereo_views` gives for ``setup`` and ``decoded``).
    screen_model : surface, optional
        The evaluation's screen model: None for the plane, else the setup's screen surface (then
        the moved setups' surfaces are used, and the screen heights' covariance acts).
    stride : int, optional
        Subgrid stride of the linearisation (:class:`StereoLinearisation`); default
        :func:`default_stereo_stride` (every pixel up to 299 px in the shorter image side).
    step : float
        Finite-difference step along each principal axis, in standard deviations.
    central : bool
        Central instead of forward differences (twice the work; for checks).
    threads : int
        Numba threads of the linearisation (default :data:`THREADS`: one; at most the
        caller's). The result does not depend on it beyond the solves' rounding (measured:
        docs/benchmarks.md).

    Returns
    -------
    StereoCalibrationContribution

    Raises
    ------
    CalibrationUncertaintyError
        No covariance, no anchor on the reconstruction, or a solve that does not converge.
    """
    t0 = time.perf_counter()
    cov = setup.calibration_covariance
    if cov is None:
        raise CalibrationUncertaintyError("the setup carries no calibration covariance (calibrate it with "
                                          "`pmdsim calibrate`, or give [calibration_report] covariance)")
    if not (step > 0 and math.isfinite(step)):
        raise CalibrationUncertaintyError(f"step must be positive and finite, got {step!r}")
    cams = list(stereo.cameras)
    s = default_stereo_stride(stereo.cameras[cams[0]].reconstructed.shape) if stride is None else int(stride)
    names = stereo_calibration_parameters(setup, cams, screen_model=screen_model)
    axes = principal_axes(cov.subset(names))
    with numba_threads(threads):
        lin = StereoLinearisation(setup, decoded, stereo, names, screen_model=screen_model, stride=s)
        fields = {c: [] for c in cams}
        var_a = {c: np.zeros(lin.a_base[c].size) for c in cams}
        for delta in axes:
            ch = lin.change(step * delta, central=central)
            for c in cams:
                dz, dg, da = (x / step for x in ch[c])
                fields[c].append(np.concatenate([dz[..., None], dg], axis=-1))
                var_a[c] += da * da
    notes = []
    if lin.lost_px:
        notes.append(f"calibration part: up to {lin.lost_px} pixel(s) lost their screen point in a moved setup (taken as "
                     f"unmoved)")
    if lin.lost_anchors:
        notes.append(f"calibration part: up to {lin.lost_anchors} anchor(s) not re-solved in a moved setup (taken as "
                     f"unmoved)")
    out, anchors = {}, {}
    o = lin.offset
    for c in cams:
        S = np.asarray(stereo.cameras[c].reconstructed)
        H, W = S.shape
        if axes and s > 1:  # per-cell Gram matrices, straight to the σ maps (no (H, W, 3) variances)
            h_um, g_urad = interpolated_std_maps(np.stack(fields[c]), o, o, s, S)
        else:
            var = _interpolated_squares(np.stack(fields[c]), o, o, s, H, W) if axes else np.zeros((H, W, 3))
            h_um, g_urad = np.empty((H, W)), np.empty((H, W, 2))
            _std_maps(np.ascontiguousarray(var), np.ascontiguousarray(S, dtype=np.bool_), h_um, g_urad)
        out[c] = CalibrationContribution(h_um, g_urad, names, len(axes), s)
        node = lin.anchor_node[c]
        anchors[c] = np.where(node >= 0, np.sqrt(var_a[c][np.maximum(node, 0)]) * 1e3, np.nan)
    return StereoCalibrationContribution(out, anchors, names, len(axes), tuple(notes), time.perf_counter() - t0)
