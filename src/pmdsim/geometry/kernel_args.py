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

import numpy as np

__all__ = ["readonly"]


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
