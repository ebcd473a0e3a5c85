"""Numba typed lists of arrays built in cached compiled code (issue 25 item 3).

:class:`pmdsim.evaluation.multigrid._Multigrid` hands its levels to the compiled cycle as
numba typed lists. ``numba.typed.List([...])`` called from Python compiles numba's own
typed-list helpers (``_make_list``, ``_append``: not cached) on its first use in a process —
0.25 s of CPU, paid inside the first least-squares integration of every ``pmdsim evaluate
--method least_squares`` (its coarse-to-fine start solves the 150×240 level with multigrid), on
the command's critical path (docs/benchmarks.md, "The least-squares integration's first call
(rc26)"). :func:`array_list` builds the same list (same type, the same arrays, not copies)
with two small kernels of this module, which numba's cache keeps: ≈ 7 ms on their first call.
``_Multigrid`` builds its lists so, for every caller of the multigrid-preconditioned CG (the
least-squares integration's coarse levels and masked frames, the anchored stereo integration,
the σ solves).
"""

from __future__ import annotations

import numba
from numba.typed import List

__all__ = ["array_list"]


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

