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
    "OptionalDependencyError",
    "ConsistencyWarning",
    "InputError",
    "InputTypeError",
    "UnknownCameraError",
    "require_extra",
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


class OptionalDependencyError(PmdsimError, ImportError):
    """A feature needs a package of an optional extra (``pmdsim[study]``, ``pmdsim[xarray]``)
    that is not installed; the message names the extra to install."""


class ConsistencyWarning(UserWarning):
    """Pixels failed the fringe-consistency checks (dropped, duplicated or foreign frames, wrong
    periods or shift orders; :mod:`pmdsim.evaluation.consistency`): issued by
    :func:`pmdsim.evaluate` with the reasons, as the CLI prints them; the pixels are flagged in
    the result's ``flags``."""


def require_extra(extra: str, *modules: str, feature: str) -> None:
    """Check that the packages of an optional extra import; raise
    :class:`OptionalDependencyError` naming ``pip install 'pmdsim[extra]'`` otherwise.

    ``pmdsim[study]``: distributed, pyarrow (``pmdsim study``, :func:`pmdsim.studies.run_study`);
    ``pmdsim[xarray]``: xarray, h5netcdf (:func:`pmdsim.open_evaluation`).
    """
    import importlib.util

    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        raise OptionalDependencyError(f"{feature} needs {', '.join(missing)} (optional extra {extra!r}); install it "
                                      f"with: pip install 'pmdsim[{extra}]'")


class InputError(PmdsimError, ValueError):
    """An argument of a pmdsim function is invalid (a shape, a dtype, an option, a pixel outside
    the image); the message names the argument, what was given and what was expected."""


class InputTypeError(InputError, TypeError):
    """An argument of a pmdsim function has the wrong type (e.g. a path where a Setup is expected)."""


class UnknownCameraError(InputError, KeyError):
    """A camera name that the setup does not have; the message lists the setup's cameras."""

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0]) if self.args else ""
