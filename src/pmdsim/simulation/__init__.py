"""Simulation (layer 2): what a deflectometry instrument records.

* :mod:`.trace` — the per-pixel ray tracer camera → sample → screen (§2.4, eq. 17), giving the
  pixel → screen-point :class:`~.trace.Mapping` with a status code per invalid pixel;
* :mod:`.patterns` — rendering of phase-shifted fringes at 8/16 bit (numba kernels);
* :mod:`.render` — a setup's camera traced and its fringe images rendered (the measurement).

* :mod:`.sensor`, :mod:`.display`, :mod:`.optics`, :mod:`.imaging` — realistic image formation
  (issue 13: sensor noise and bit depth, display response and emission, screen pixels, defocus
  and pixel-area blur applied analytically per harmonic), switched on by ``[imaging]``.
May import: :mod:`pmdsim.errors`, :mod:`pmdsim.geometry`, :mod:`pmdsim.setup`.
"""

from .render import ImageSpec, image_specs, render_images, trace_setup_camera
from .trace import Mapping, Status, trace_camera, trace_rays

__all__ = ["ImageSpec", "image_specs", "render_images", "trace_setup_camera", "Mapping", "Status", "trace_camera",
           "trace_rays"]
