"""The multigrid hierarchy's typed lists built in cached compiled code (issue 25 item 3).

:class:`pmdsim.evaluation.multigrid._Multigrid` hands its levels to the compiled cycle as
numba typed lists. ``numba.typed.List([...])`` called from Python compiles numba's own
typed-list helpers (``_make_list``, ``_append``: not cached) on its first use in a process —
0.25 s of CPU, paid inside the first least-squares integration of every ``pmdsim evaluate
--method least_squares`` (its coarse-to-fine start solves the 150×240 level with multigrid), on
the command's critical path (docs/benchmarks.md, "The least-squares integration's first call
(rc26)"). :func:`array_list` builds the same list (same type, the same arrays, not copies)
with two small kernels of this module, which numba's cache keeps: ≈ 7 ms on their first call.
:class:`Multigrid` is ``_Multigrid`` with its lists built so (the same hierarchy and cycle).
"""

from __future__ import annotations

import numba
import numpy as np
from numba.typed import List

from .multigrid import _MG_COARSEST_CELLS, _coarsen, _Multigrid

__all__ = ["Multigrid", "array_list"]


@numba.njit(cache=True)
def _list_of(a):
    """A new typed list holding the array a."""
    out = List()
    out.append(a)
    return out


@numba.njit(cache=True)
def _list_append(lst, a):
    """lst.append(a) (the array itself, not a copy)."""
    lst.append(a)


def array_list(arrays) -> List:
    """``numba.typed.List(arrays)`` for a non-empty sequence of numpy arrays of one type (e.g.
    2-D C-contiguous float64), built by cached compiled code: the items are the arrays
    themselves (views of the same memory). Raises ValueError if ``arrays`` is empty."""
    it = iter(arrays)
    try:
        out = _list_of(next(it))
    except StopIteration:
        raise ValueError("array_list needs at least one array (the list's item type)") from None
    for a in it:
        _list_append(out, a)
    return out


class Multigrid(_Multigrid):
    """:class:`~pmdsim.evaluation.multigrid._Multigrid` (aggregation multigrid of a padded
    5-point SPD operator; the same levels, coarsest factor and :meth:`apply`) with its typed
    lists built by :func:`array_list`. Pass it to :func:`~pmdsim.evaluation.multigrid._pcg`
    as ``mg``."""

    def __init__(self, D, iD, Ex, Ey):  # noqa: D107 — the levels as _Multigrid.__init__
        levels = [(D, iD, Ex, Ey)]
        while (D.shape[0] - 2) * (D.shape[1] - 2) > _MG_COARSEST_CELLS:
            D, iD, Ex, Ey = _coarsen(D, Ex, Ey)
            levels.append((D, iD, Ex, Ey))
        self.n_levels = len(levels)
        self.Ds, self.iDs, self.Exs, self.Eys = (array_list([lv[k] for lv in levels]) for k in range(4))
        # Work arrays per level: result, restricted residual, second cycle's residual, sum of the cycles.
        self.xs, self.rcs, self.r2s, self.accs = (array_list([np.zeros(lv[0].shape) for lv in levels])
                                                  for _ in range(4))
        self._factor_coarsest(*levels[-1])
