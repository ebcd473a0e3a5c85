"""SIGINT, SIGTERM and SIGHUP: a clean abort at any phase of a command (docs/reliability.md).

The command line installs :func:`install` once. From then on the first SIGINT (Ctrl-C),
SIGTERM (``kill``, ``timeout``, a batch scheduler) or SIGHUP (the terminal closed) is
*recorded* and raised as
:class:`Interrupted` (a :class:`KeyboardInterrupt`, so ``except Exception`` does not swallow
it). Python may still swallow that exception when it is raised inside a finaliser
(``Exception ignored in … KeyboardInterrupt``); the record stays, and the output layer
(:mod:`pmdsim.io.outputs`) calls :func:`check` before it commits an output, so a swallowed
interrupt still aborts the run before anything is written; inside a finaliser the handler
does not even raise (it only records). The commit itself runs in :func:`deferred`. Later
signals are only recorded: the cleanup of the first one is not interrupted by a second Ctrl-C.

Where Python reports an exception it cannot raise ("Exception ignored in …", a finaliser or a
callback of C code, e.g. while numba loads its kernels), :func:`install`'s unraisable hook keeps
quiet about an :class:`Interrupted` that was recorded: the command ends with its one line.
C code may also *print* an exception and go on: ``PyErr_Print`` (``PyRun_SimpleString``, and
Cython's unraisable path with a full traceback, which prints before it reports "Exception
ignored") calls ``sys.excepthook``; :func:`install`'s excepthook keeps quiet about a recorded
:class:`Interrupted` too (seen as a bare one-frame traceback of the handler before the command's
line, about 1 run in 60 with Ctrl-C while a command loads its kernels).

The exit codes are the shell's: 128 + signal number (130 for SIGINT, 143 for SIGTERM, 129 for
SIGHUP). Once a
command's output is committed (:func:`output_committed`), a signal no longer aborts: the
output is complete, the command ends normally and says that the signal came too late.

The library does not install anything by itself (a notebook keeps Python's own Ctrl-C);
:func:`check` and :func:`deferred` are harmless without :func:`install`.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Iterator

__all__ = ["SIGNALS", "Interrupted", "install", "installed", "received", "check", "deferred", "output_committed", "exit_code",
           "signal_name", "reset", "finish", "committed"]

#: The signals that abort a command cleanly: Ctrl-C, ``kill``/``timeout``/a batch scheduler, and
#: the terminal closing (SIGHUP: a run in a closed ssh session must not leave partial outputs).
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_SIGNALS = SIGNALS

_state: dict = {"installed": False, "signum": None, "committed": None, "quiet": False, "deferring": 0}


class Interrupted(KeyboardInterrupt):
    """The run was interrupted by a signal (``signum``: SIGINT, SIGTERM or SIGHUP)."""

    def __init__(self, signum: int):
        super().__init__(f"interrupted by {signal_name(signum)}")
        self.signum = int(signum)


def signal_name(signum: int) -> str:
    """``"SIGINT"`` for 2, ``"SIGTERM"`` for 15, ``"SIGHUP"`` for 1, …"""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def exit_code(signum: int) -> int:
    """The shell's exit code of a process ended by ``signum``: 128 + signum (130, 143, 129)."""
    return 128 + int(signum)


def _in_finaliser(frame) -> bool:
    """Whether ``frame`` runs inside a finaliser (``__del__``, a weakref callback), where Python
    would print "Exception ignored" and drop the exception."""
    while frame is not None:
        code = frame.f_code
        if code.co_name == "__del__" or code.co_filename.endswith("weakref.py"):
            return True
        # importlib's module-lock weakref callback (_get_module_lock.<locals>.cb): seen to swallow
        # a SIGINT ("Exception ignored in: <function _get_module_lock.<locals>.cb …>").
        if code.co_name == "cb" and code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _handler(signum, frame) -> None:
    first = _state["signum"] is None
    if first:
        _state["signum"] = signum
    # In a finaliser the exception would be swallowed: only record it there (check() raises it
    # at the next progress step or at the latest before the output is committed).
    if first and not _state["quiet"] and not _state["deferring"] and not _in_finaliser(frame):
        raise Interrupted(signum)


def install() -> None:
    """Record SIGINT and SIGTERM and raise :class:`Interrupted` at the first one (main thread
    only; a signal the parent process set to be ignored stays ignored, as in Python itself)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for s in _SIGNALS:
        if signal.getsignal(s) is not signal.SIG_IGN:  # an ignored signal stays ignored (as Python's own)
            signal.signal(s, _handler)
    if sys.unraisablehook is not _unraisable:
        _state["unraisablehook"] = sys.unraisablehook
        sys.unraisablehook = _unraisable
    if sys.excepthook is not _excepthook:
        _state["excepthook"] = sys.excepthook
        sys.excepthook = _excepthook
    _state["installed"] = True


def _unraisable(info) -> None:
    """``sys.unraisablehook``: an :class:`Interrupted` Python could not raise (in a finaliser or
    a callback) is already recorded — :func:`check` raises it — so it is not printed."""
    if isinstance(info.exc_value, Interrupted) and _state["signum"] is not None:
        return
    (_state.get("unraisablehook") or sys.__unraisablehook__)(info)


def _excepthook(exc_type, exc_value, tb) -> None:
    """``sys.excepthook``, also what C code's ``PyErr_Print`` calls: a recorded
    :class:`Interrupted` is not printed (the command reports it in its one line); anything else
    goes to the previous hook."""
    if isinstance(exc_value, Interrupted) and _state["signum"] is not None:
        return
    (_state.get("excepthook") or sys.__excepthook__)(exc_type, exc_value, tb)


def installed() -> bool:
    """Whether :func:`install` ran in this process."""
    return bool(_state["installed"])


def reset() -> None:
    """Forget a recorded signal and committed output (for a new command in the same process)."""
    _state["signum"] = None
    _state["committed"] = None
    _state["quiet"] = False


def received() -> int | None:
    """The first signal received since :func:`install` (or :func:`reset`), or None."""
    return _state["signum"]


def check() -> None:
    """Raise :class:`Interrupted` if a signal was received (also one whose exception Python
    swallowed) and no output has been committed yet."""
    if _state["signum"] is not None and not _state["quiet"]:
        raise Interrupted(_state["signum"])


def output_committed(path) -> None:
    """An output is complete on disk (``path``): a later signal no longer aborts the command."""
    _state["committed"] = str(path)
    _state["quiet"] = True


def finish(block: bool = False) -> None:
    """The command is over: a later signal is only recorded. ``block``: hold SIGINT and SIGTERM
    back for the rest of the process (its exit code is the command's; Python's shutdown, which
    restores the default handlers and can take a second, is not cut short by a late signal
    into a "killed by signal" exit after a complete output)."""
    _state["quiet"] = True
    if block and _state["installed"] and threading.current_thread() is threading.main_thread():
        # SIG_IGN, not a mask: any thread may receive a process-directed signal, and Python's
        # shutdown resets a Python-level handler to the default action (but keeps SIG_IGN).
        for s in _SIGNALS:
            if signal.getsignal(s) is _handler:
                signal.signal(s, signal.SIG_IGN)


def committed() -> str | None:
    """The output committed by this command, or None."""
    return _state["committed"]


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold a signal's exception back during a short critical section — the commit of an
    output, the removal of a partial one: a signal that arrives meanwhile is recorded, and
    raised (by :func:`check`) when the section ends, unless an output was committed in it."""
    _state["deferring"] += 1
    try:
        yield
    finally:
        _state["deferring"] -= 1
    if not _state["deferring"]:
        check()
