"""The orientation plausibility check on a full-resolution camera (issue 25 item 1): its medians
over a sub-grid of pixels against the same medians over every pixel (np.gradient + nanmedian,
the check as it was), on a mapping made by an independent closed form (the nominal plane's,
:func:`pmdsim.evaluation.consistency.nominal_screen_xy`) with noise, a bulge and holes."""

from __future__ import annotations

import numpy as np

from pmdsim.evaluation.consistency import nominal_screen_xy
from pmdsim.evaluation.plausibility import _orientation_jacobians, check_orientation, orientation_stride
from pmdsim.setup import default_setup


def test_subgrid_medians_match_every_pixel_and_flag_the_same_flips():
    setup = default_setup()
    cs = setup.cameras["left"]
    xy = nominal_screen_xy(cs.camera, cs.T_world_cam, setup.sample.T_world_sample, setup.screen.T_world_screen)
    h, w = xy.shape[:2]
    assert orientation_stride((h, w)) == 8
    v, u = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(3)
    xy = xy + 2.0 * np.stack([np.sin(u / 300.0), np.cos(v / 200.0)], -1) + rng.normal(0, 0.005, xy.shape)
    ok = np.isfinite(xy).all(-1) & ((u - 900) ** 2 + (v - 500) ** 2 > 150 ** 2)
    xy[~ok] = np.nan
    for flip in (None, 0, 1):
        m = xy.copy()
        if flip is not None:
            m[..., flip] = -m[..., flip]  # a display axis flipped
        if flip is None:  # the sub-grid medians against every pixel's (the full grid: ~1 s)
            Jd8, Jp8 = _orientation_jacobians(setup, "left", m, ok, 8)
            Jd1, Jp1 = _orientation_jacobians(setup, "left", m, ok, 1)
            np.testing.assert_allclose(Jp8, Jp1, rtol=0, atol=1e-3 * np.abs(Jp1).max())  # relative to |J|
            np.testing.assert_allclose(Jd8, Jd1, rtol=0, atol=1e-3 * np.abs(Jd1).max())
            M8, M1 = Jd8 @ np.linalg.inv(Jp8), Jd1 @ np.linalg.inv(Jp1)
            np.testing.assert_allclose(np.diag(M8), np.diag(M1), rtol=1e-3)
        warn = check_orientation(setup, "left", m, ok)
        if flip is None:
            assert warn == []
        else:
            assert len(warn) == 1 and f"screen {'xy'[flip]} coordinates run opposite" in warn[0]
