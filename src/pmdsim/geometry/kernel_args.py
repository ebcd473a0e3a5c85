"""Array arguments of the numba kernels in one type (issue 25 items 2 and 4: fewer compiles).

numba compiles a kernel once per distinct argument *type*, and a read-only array is another type
than a writable one (``readonly array(float64, 1d, C)`` vs ``array(float64, 1d, C)``). The value
objects hand their arrays over read-only (a :class:`~pmdsim.geometry.surface.SplineSurface`'s
coefficients, a camera's cached view rays, the images of :func:`pmdsim.simulate`), while arrays
built on the fly (a plane's zero coefficients, rays made by hand, images read from disk) are
writable: the same kernel then compiled twice — the tracer's band kernel five times in the test
suite, minutes each on a cold cache. The kernels' wrappers pass their *input* arrays through
:func:`readonly` (a view, no copy), so that every caller reaches the one compiled signature.
"""

from __future__ import annotations

from contextlib import contextmanager

import numba
import numpy as np

__all__ = ["SERIAL_BELOW_PX", "numba_threads", "readonly"]

#: Below this many pixels a parallel kernel runs on one numba thread (:func:`numba_threads`):
#: its work is shorter than the wait at the threading layer's barrier, which under load (the
#: second vCPU busy) can last a scheduler slice — measured 7.5 ms per call of two small
#: parallel kernels, 20–66 s for one test's 8 352 calls at load 2–3 against 2.1 s on one
#: thread (docs/benchmarks.md, "A load amplifier"). The same bound as
#: ``evaluation.synthetic_decode``'s serial kernel.
SERIAL_BELOW_PX = 200_000


def readonly(a: np.ndarray) -> np.ndarray:
    """``a`` itself if it is read-only, else a read-only view of it (no copy; ``a`` stays
    writable).

    Parameters
    ----------
    a : ndarray, any shape and dtype

    Returns
    -------
    ndarray
        Same shape, dtype, memory and layout as ``a``, ``flags.writeable`` False.
    """
    if not a.flags.writeable:
        return a
    v = a.view()
    v.flags.writeable = False
    return v


@contextmanager
def numba_threads(n: int):
    """Run the block with at most ``n`` numba threads (this thread's setting, restored after).

    ``numba.set_num_threads`` applies to parallel kernels launched from the calling thread.
    Per-pixel kernels give the same values with any thread count; a ``prange`` reduction (e.g.
    the conjugate-gradient dot products of ``evaluation.poisson``) adds its per-thread partial
    sums, so its last bits follow the thread count — one thread makes them independent of
    ``NUMBA_NUM_THREADS``.

    Parameters
    ----------
    n : int
        Thread limit, ≥ 1 (values above the current setting leave it unchanged).
    """
    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(int(n), before)))
    try:
        yield
    finally:
        numba.set_num_threads(before)
