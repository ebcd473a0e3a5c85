"""The stepwise σ's per-pixel samples (``uncertainty_stepwise._pixel_samples``, issue 25) against the
recursion written out with numpy here: δz_k = (Σ_edges (±vx ± vy − J_a δz_a,k) ± ux ± uy) / Σ J_b,
the signs from the counter-based draws' bits, in the kernel's order of operations — equal bit for
bit for 0 to 4 upstream edges (the one-pass loop for ≤ 2 edges, the edge-by-edge loops beyond),
and δz = 0 with −1 returned when Σ J_b vanishes."""

from __future__ import annotations

import numpy as np
import pytest

from pmdsim.evaluation.uncertainty_stepwise import _draw_word, _pixel_samples, _seed_key


def _signs(word, K):
    bits = np.array([(int(word) >> k) & 1 for k in range(2 * K)], dtype=bool)
    return bits[0::2], bits[1::2]


@pytest.mark.parametrize("m", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("K", [64, 40, 7])
def test_pixel_samples_equal_the_recursion_written_out(m, K):
    rng = np.random.default_rng(10 * m + K)
    n_chunks = (K + 31) // 32
    key = _seed_key(12345)
    prev = rng.normal(size=(6, K))
    w_prev = np.array([[_draw_word(key, 100 + r, c, n_chunks) for c in range(n_chunks)] for r in range(6)],
                      dtype=np.uint64)
    e_pos = rng.permutation(6)[:4].astype(np.int64)
    e_c = rng.normal(size=(4, 3))
    ux, uy, den = rng.normal(size=3)
    cur = np.full((3, K), np.nan)
    w_cur = np.zeros((3, n_chunks), dtype=np.uint64)
    kb = 777
    s = _pixel_samples(kb, key, K, m, e_pos, e_c, ux, uy, den, prev, cur, 1, w_prev, w_cur)
    z = np.zeros(K)
    for j in range(m):
        vx, vy, Ja = e_c[j]
        for c in range(n_chunks):
            k = slice(32 * c, min(K, 32 * c + 32))
            sx, sy = _signs(w_prev[e_pos[j], c], k.stop - k.start)
            z[k] += np.where(sx, -vx, vx) + np.where(sy, -vy, vy) - Ja * prev[e_pos[j], k]
    for c in range(n_chunks):
        k = slice(32 * c, min(K, 32 * c + 32))
        sx, sy = _signs(_draw_word(key, kb, c, n_chunks), k.stop - k.start)
        z[k] = (z[k] + np.where(sx, -ux, ux) + np.where(sy, -uy, uy)) / den
    assert np.array_equal(cur[1], z) and np.array_equal(np.signbit(cur[1]), np.signbit(z))
    assert np.isnan(cur[0]).all() and np.isnan(cur[2]).all()
    np.testing.assert_allclose(s, np.sum(z * z), rtol=K * 1e-16)
    cur[1] = np.nan
    assert _pixel_samples(kb, key, K, m, e_pos, e_c, ux, uy, 0.0, prev, cur, 1, w_prev, w_cur) == -1.0
    assert np.all(cur[1] == 0.0)
