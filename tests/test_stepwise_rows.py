"""The stepwise integration in bands of image rows (issue 25, :mod:`pmdsim.evaluation.stepwise_rows`)
against the pixel-by-pixel Python reference of tests/test_stepwise_wavefront.py (the paper's step,
wavefront by wavefront): heights, mask and statistics bit for bit where the row pass runs (full
masks, masks with holes that do not bend the L1 diamonds, random masks), and the row pass's own
verdict checked where it must hand over to the wavefront pass (holes that bend the diamonds:
−1; a failed step: −2), whose result must then be the reference's too."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_stepwise_wavefront import _reference, _scene

from pmdsim.evaluation.stepwise import (
    _NB_DU,
    _NB_DV,
    STEP_MAX_ITER,
    _init_state,
    _seed_values,
    _stepwise_kernel,
    reconstruct_stepwise,
    step_tolerance_mm,
)
from pmdsim.evaluation.stepwise_rows import l1_layered, rows_stepwise_kernel


def _l1_layered_py(S, seed):
    """l1_layered written out with numpy: every pixel but the seed has an upstream neighbour."""
    H, W = S.shape
    v, u = np.mgrid[0:H, 0:W]
    dist = np.abs(v - seed[0]) + np.abs(u - seed[1])
    up = np.zeros((H, W), bool)
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        sh = np.zeros((H, W), bool)
        dsh = np.full((H, W), -10)
        vs, us = slice(max(0, -dv), H - max(0, dv)), slice(max(0, -du), W - max(0, du))
        vt, ut = slice(max(0, dv), H - max(0, -dv)), slice(max(0, du), W - max(0, -du))
        sh[vs, us] = S[vt, ut]
        dsh[vs, us] = dist[vt, ut]
        up |= sh & (dsh == dist - 1)
    up[seed] = True
    return bool(S[seed] and np.all(up[S]))


def _smooth_scene(H=23, W=31):
    """_scene's camera and wavy surface with every view ray towards the surface (no step fails)."""
    o, d, q, _, _ = _scene(H, W)
    d[..., 2] = -np.abs(d[..., 2])
    v, u = np.mgrid[0:H, 0:W].astype(float)
    t = (0.3 * np.sin(u / 4) + 0.2 * np.cos(v / 3) - o[2]) / d[..., 2]
    p = o + t[..., None] * d
    q = p + np.stack([0.1 * np.sin(v / 5), 0.2 * np.cos(u / 6), 400.0 + u], axis=-1)
    return o, d, q


def _rows(o, d, q, valid, seed, z0, band):
    """The row pass alone: (its code, its statistics, the heights where it finished)."""
    tol = step_tolerance_mm(o, q, valid)
    z = np.full(valid.shape, -7.0)
    t0, gx0, gy0 = _seed_values(o, d, q, seed[0], seed[1], z0)
    used, change, unconv, code = rows_stepwise_kernel(o, d, q, valid, z, seed[0], seed[1], t0, gx0, gy0, tol,
                                                      STEP_MAX_ITER, np.int64(band))
    z[seed] = z0
    return code, (used, change, unconv), z, tol


def _wavefront_stats(o, d, q, valid, seed, z0, tol):
    state = np.empty(valid.shape + (4,))
    _init_state(valid, state)
    return _stepwise_kernel(o, d, q, state, seed[0], seed[1], z0, tol, STEP_MAX_ITER, _NB_DV, _NB_DU)


@pytest.mark.parametrize("seed", [(11, 15), (0, 0), (22, 30), (5, 29), (17, 0)])
@pytest.mark.parametrize("band", [1, 3, 16])
def test_full_mask_rows_equal_the_reference(seed, band):
    o, d, q = _smooth_scene()
    valid = np.ones((23, 31), bool)
    code, stats, z, tol = _rows(o, d, q, valid, seed, 0.1, band)
    assert code == 0
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.1, tol)
    assert np.isfinite(ref).all()
    assert np.array_equal(z, ref) and np.array_equal(np.signbit(z), np.signbit(ref))
    assert stats == _wavefront_stats(o, d, q, valid, seed, 0.1, tol)
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.1)
    assert np.array_equal(rec.height_mm, ref) and rec.reconstructed.all()
    assert (rec.iterations, rec.final_change_mm) == stats[:2]


def test_holes_that_keep_the_diamonds_run_in_rows_and_those_that_bend_them_do_not():
    o, d, q = _smooth_scene()
    valid = np.ones((23, 31), bool)
    valid[0:3, 0:4] = False  # corner cut and a notch in the outer border: the diamonds stay
    valid[22, 10:20] = False
    valid[15:19, 25:31] = False
    seed = (11, 15)
    assert l1_layered(valid, *seed) and _l1_layered_py(valid, seed)
    code, stats, z, tol = _rows(o, d, q, valid, seed, 0.0, 4)
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.0, tol)
    assert code == 0 and np.array_equal(z, ref, equal_nan=True)
    assert stats == _wavefront_stats(o, d, q, valid, seed, 0.0, tol)
    valid[5:8, 12:18] = False  # a hole between the seed and the rows above: they are reached around it
    assert not l1_layered(valid, *seed) and not _l1_layered_py(valid, seed)
    code, _, z, _ = _rows(o, d, q, valid, seed, 0.0, 4)
    z[seed] = -7.0
    assert code == -1 and np.all(z == -7.0)  # nothing written: the wavefront pass runs instead
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.0)
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.0, tol)
    assert np.array_equal(rec.height_mm, ref, equal_nan=True)


def test_a_failed_step_hands_over_to_the_wavefront_pass():
    o, d, q = _smooth_scene()
    valid = np.ones((23, 31), bool)
    seed = (11, 15)
    d[3, 20, 2] = 0.5  # a ray pointing away from the surface: its step fails from every side
    code, _, _, tol = _rows(o, d, q, valid, seed, 0.0, 16)
    assert code == -2
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.0)
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.0, tol)
    assert np.isnan(ref[3, 20]) and np.isfinite(np.delete(ref.ravel(), 3 * 31 + 20)).all()
    assert np.array_equal(rec.height_mm, ref, equal_nan=True)
    o, d, q, valid, seed = _scene()  # holes and failed steps together
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.25)
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.25, step_tolerance_mm(o, q, valid))
    assert np.array_equal(rec.height_mm, ref, equal_nan=True)


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 0.08), st.integers(1, 9))
def test_random_masks_equal_the_reference(mask_seed, hole_fraction, band):
    H, W = 13, 17
    o, d, q = _smooth_scene(H, W)
    rng = np.random.default_rng(mask_seed)
    valid = rng.random((H, W)) >= hole_fraction
    seed = (int(rng.integers(H)), int(rng.integers(W)))
    valid[seed] = True
    layered = _l1_layered_py(valid, seed)
    assert bool(l1_layered(valid, *seed)) == layered
    code, stats, z, tol = _rows(o, d, q, valid, seed, 0.05, band)
    assert code == (0 if layered else -1)
    rec = reconstruct_stepwise(o, d, q, valid, seed_pixel=seed, seed_height_mm=0.05)
    with np.errstate(all="ignore"):
        ref = _reference(o, d, q, valid, seed, 0.05, tol)
    assert np.array_equal(rec.height_mm, ref, equal_nan=True)
    assert np.array_equal(np.signbit(rec.height_mm), np.signbit(ref))
    if layered:
        assert np.array_equal(z, ref, equal_nan=True)
        assert stats == _wavefront_stats(o, d, q, valid, seed, 0.05, tol)
