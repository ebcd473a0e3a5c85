"""The intensity response and linearisation, as the evaluation uses them.

:class:`IntensityResponse` describes the instrument (display → camera), so it lives in the
setup layer (:mod:`pmdsim.setup.response`); it is re-exported here, where the evaluation
applies :meth:`IntensityResponse.linearise` before decoding.
"""

from ..setup.response import IntensityResponse, ResponseError

__all__ = ["IntensityResponse", "ResponseError"]
