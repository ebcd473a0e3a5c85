"""The multigrid hierarchy's typed lists built by compiled code (evaluation/multigrid_lists.py):
the same lists as ``numba.typed.List`` and the same preconditioner as a hierarchy whose lists
numba.typed.List built, without compiling numba's typed-list helpers in a fresh process."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numba
import numpy as np
import pytest
from numba.typed import List

import pmdsim
from pmdsim.evaluation.multigrid import _Multigrid, _pcg
from pmdsim.evaluation.multigrid_lists import array_list


def test_array_list_is_numbas_typed_list_of_the_same_arrays():
    arrays = [np.arange(12.0).reshape(3, 4), np.zeros((1, 1)), np.ones((5, 2))]
    got = array_list(arrays)
    ref = List(arrays)
    assert numba.typeof(got) == numba.typeof(ref)
    assert len(got) == len(arrays)
    for a, g in zip(arrays, got):
        assert np.shares_memory(a, g) and g.shape == a.shape  # the array itself, not a copy
        assert np.array_equal(g, a)
    arrays[1][0, 0] = 7.0
    assert got[1][0, 0] == 7.0
    with pytest.raises(ValueError, match="at least one"):
        array_list([])


def _operator(H, W, rng):
    """A padded SPD 5-point operator with random positive couplings and a few holes."""
    Hp, Wp = H + 2, W + 2
    Ex = np.zeros((Hp, Wp))
    Ey = np.zeros((Hp, Wp))
    Ex[1:-1, 1:-2] = rng.uniform(0.5, 1.5, (H, W - 1))
    Ey[1:-2, 1:-1] = rng.uniform(0.5, 1.5, (H - 1, W))
    active = np.zeros((Hp, Wp), dtype=bool)
    active[1:-1, 1:-1] = rng.random((H, W)) > 0.05
    Ex[~active] = 0.0
    Ex[:, :-1][~active[:, 1:]] = 0.0
    Ey[~active] = 0.0
    Ey[:-1][~active[1:]] = 0.0
    D = np.zeros((Hp, Wp))
    D[1:-1, 1:-1] = (Ex[1:-1, 1:-1] + Ex[1:-1, :-2] + Ey[1:-1, 1:-1] + Ey[:-2, 1:-1]) + 0.01
    D[~active] = 0.0
    iD = np.where(D > 0.0, 1.0 / np.where(D > 0.0, D, 1.0), 0.0)
    b = np.where(active, rng.standard_normal((Hp, Wp)), 0.0)
    return D, iD, Ex, Ey, b


_LISTS = ("Ds", "iDs", "Exs", "Eys", "xs", "rcs", "r2s", "accs")


def _with_numba_lists(mg):
    """mg with every typed list rebuilt by numba.typed.List from copies of its arrays (the
    reference: the lists as numba builds them from Python)."""
    for name in _LISTS:
        setattr(mg, name, List([np.array(a) for a in getattr(mg, name)]))
    return mg


def test_multigrid_is_the_reference_hierarchy_bit_for_bit():
    D, iD, Ex, Ey, b = _operator(45, 70, np.random.default_rng(3))
    mine, ref = _Multigrid(D, iD, Ex, Ey), _with_numba_lists(_Multigrid(D, iD, Ex, Ey))
    assert mine.n_levels == ref.n_levels > 2
    for name in _LISTS:
        assert numba.typeof(getattr(mine, name)) == numba.typeof(getattr(ref, name))
        assert all(np.array_equal(m, r) for m, r in zip(getattr(mine, name), getattr(ref, name)))
    assert mine.coarse_kind == ref.coarse_kind
    assert np.array_equal(mine.coarse_factor, ref.coarse_factor)
    out_m, out_r = np.zeros_like(b), np.zeros_like(b)
    assert mine.apply(b, out_m, 2.0, 1.5) == ref.apply(b, out_r, 2.0, 1.5)
    assert np.array_equal(out_m, out_r)
    x_m, it_m, ok_m = _pcg(D, iD, Ex, Ey, b, 1e-10, 1e-8, 100)
    x_m = x_m.copy()
    x_r, it_r, ok_r = _pcg(D, iD, Ex, Ey, b, 1e-10, 1e-8, 100, mg=_with_numba_lists(_Multigrid(D, iD, Ex, Ey)))
    assert ok_m and ok_r and it_m == it_r
    assert np.array_equal(x_m, x_r)
    resid = b[1:-1, 1:-1] - (D * x_r - Ex * np.roll(x_r, -1, 1) - np.roll(Ex * x_r, 1, 1)
                             - Ey * np.roll(x_r, -1, 0) - np.roll(Ey * x_r, 1, 0))[1:-1, 1:-1]
    assert np.max(np.abs(resid)) < 1e-6 * np.max(np.abs(b))  # it solves N x = b (numpy product)


def test_first_list_in_a_fresh_process_compiles_no_typed_list_helper():
    script = textwrap.dedent("""
        import numpy as np
        from numba.typed import typedlist
        from pmdsim.evaluation.multigrid_lists import array_list
        array_list([np.zeros((3, 3)), np.ones((2, 2))])
        print("COMPILED", len(typedlist._make_list.signatures) + len(typedlist._append.signatures))
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(pmdsim.__file__).parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "COMPILED 0" in r.stdout
