"""Ctrl-C that stops at once, even inside IPOPT.

CasADi checks for Ctrl-C between IPOPT iterations, runs Python's handler, and then reports the
start as failed (a ``KeyboardInterruptException`` warning) instead of raising. The command line
installs :func:`install`: the handler records the signal before raising, and every solver
call runs inside :func:`solver_call`, which turns the recorded signal back into
``KeyboardInterrupt`` (and drops CasADi's warning about it).
"""

from __future__ import annotations

import contextlib
import io
import signal
import sys
import threading
from collections.abc import Iterator

#: Exit code of a command stopped by Ctrl-C (128 + SIGINT).
EXIT_INTERRUPTED = 130

_HIT = threading.Event()
#: What CasADi writes to ``sys.stderr`` when a ``KeyboardInterrupt`` stopped its solver.
_CASADI_INTERRUPTED = "KeyboardInterruptException"


def _handler(signum: int, frame: object) -> None:
    _HIT.set()
    raise KeyboardInterrupt


def _unraisable(unraisable: object) -> None:
    """Python's hook for an exception it cannot raise (in a weakref callback of the import
    machinery, a ``__del__``): the ``KeyboardInterrupt`` of :func:`_handler` raised there is
    recorded already (:func:`check` raises it again), so nothing is printed; any other
    exception goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and _HIT.is_set():
        return
    sys.__unraisablehook__(unraisable)


def install() -> None:
    """Record Ctrl-C (SIGINT) for :func:`check`; call from the main thread. A Ctrl-C that lands
    where Python cannot raise it (a weakref callback while the package is imported) prints no
    "Exception ignored" traceback (:func:`_unraisable`)."""
    _HIT.clear()
    signal.signal(signal.SIGINT, _handler)
    sys.unraisablehook = _unraisable


def pressed() -> bool:
    """Whether Ctrl-C was pressed since :func:`install` (CasADi may have turned the
    ``KeyboardInterrupt`` of a Python callback into its own ``RuntimeError``)."""
    return _HIT.is_set()


def check() -> None:
    """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed since :func:`install`: a
    ``KeyboardInterrupt`` raised inside CasADi's argument conversion is swallowed by SWIG's
    overload dispatch (it tries the next overload), so the command checks after building a
    problem and whenever a start comes back."""
    if _HIT.is_set():
        raise KeyboardInterrupt


@contextlib.contextmanager
def solver_call() -> Iterator[None]:
    """Run a CasADi solver call; raise ``KeyboardInterrupt`` after it if Ctrl-C was pressed.

    What CasADi writes to ``sys.stderr`` meanwhile is passed on, unless the call was
    interrupted (then it is CasADi's ``KeyboardInterruptException`` warning). Without
    :func:`install` (the package used as a library) that warning is how the interrupt shows:
    CasADi ends the run early and returns, and the start would go on from a cut-short run (a
    result no uninterrupted run gives, kept on disk by
    :func:`casadi_design.optimisation.solve.solve_start`); it is raised as ``KeyboardInterrupt`` too.
    """
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            yield
    finally:
        if _HIT.is_set() or _CASADI_INTERRUPTED in said.getvalue():
            raise KeyboardInterrupt
        sys.stderr.write(said.getvalue())
