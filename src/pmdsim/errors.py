"""Exception types of pmdsim.

Every error that a user can cause (a bad setup file, a bad image set, a calibration that does
not converge) raises one of these, with a message that names the offending key, file or array
and what was expected.
"""

from __future__ import annotations

__all__ = [
    "PmdsimError",
    "SetupError",
    "OutputExistsError",
    "ImageSetError",
    "ComputationError",
    "OutputPathError",
    "OutputLockedError",
]


class PmdsimError(Exception):
    """Base class of all pmdsim errors."""


class SetupError(PmdsimError, ValueError):
    """A measurement setup (TOML file or Python values) is invalid.

    The message names the key (for example ``cameras.left.focal_length_px``) and the problem.
    """


class OutputExistsError(PmdsimError, FileExistsError):
    """An output file or directory exists and ``force`` was not given."""


class ImageSetError(PmdsimError, ValueError):
    """An image set (manifest plus image files) is missing, inconsistent or unreadable."""


class ComputationError(PmdsimError, RuntimeError):
    """The inputs were valid but the computation failed (e.g. a calibration did not converge).

    The CLI exits with code 1 for these and 2 for bad input.
    """


class OutputPathError(PmdsimError, OSError):
    """An output cannot be written where it was asked for (under a regular file, in a read-only
    or unwritable directory); raised before the computation."""


class OutputLockedError(PmdsimError):
    """Another pmdsim run is writing the same output (its lock file is held); the message names it."""
