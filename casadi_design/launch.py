"""The ``casadi-design`` command's first instructions: from here on Ctrl-C ends the command
with exit code 130 and one line, also while the package is still being imported (about a
second: CasADi, Pinocchio, numpy)."""

from __future__ import annotations

import atexit
import os
import sys
from typing import NoReturn

from .runtime import interrupt
from .runtime.interrupt import EXIT_INTERRUPTED
from .runtime.threads import fixed_blas


def _exit_interrupted() -> NoReturn:
    """End the process now with code 130, after the exit functions (multiprocessing's
    clean-up of its semaphores, logging) and with its output flushed.

    A plain return would let ``python -m casadi_design`` end by SIGINT (status -2) instead:
    when the ``KeyboardInterrupt`` passed through Python code that a native library ran with
    ``PyRun_String``, CPython marks the interrupt unhandled (``_Py_UnhandledKeyboardInterrupt``,
    set in 2 of 60 solves interrupted during their first second) though the command caught it,
    and kills itself with SIGINT after finalisation.
    """
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)


def _interrupted() -> NoReturn:
    print("interrupted", file=sys.stderr)
    _exit_interrupted()


class ReaderSafeOutput:
    """The command's standard output, kept working when its reader stops reading (``| head``):
    what is printed after that goes nowhere, and the command goes on to write its files and
    ends as it would (a closed pipe is no reason to lose a solve)."""

    def __init__(self, stream):
        self._stream, self.reader_gone = stream, False

    def _gone(self) -> None:
        self.reader_gone = True
        os.dup2(os.open(os.devnull, os.O_WRONLY), self._stream.fileno())  # the flush at exit has nowhere to fail

    def write(self, text: str) -> int:
        if not self.reader_gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._gone()
        return len(text)

    def flush(self) -> None:
        if not self.reader_gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._gone()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    """Import the command line and run it (:func:`casadi_design.cli.main`)."""
    if not isinstance(sys.stdout, ReaderSafeOutput):  # main may run again in one process
        sys.stdout = ReaderSafeOutput(sys.stdout)
    interrupt.install()  # records Ctrl-C: Python drops the KeyboardInterrupt of some import hooks
    fixed_blas()  # before numpy, CasADi and IPOPT load: the same numbers for any --jobs and CPU
    try:
        from .cli import main as run
    except KeyboardInterrupt:
        _interrupted()
    except Exception:
        # Ctrl-C inside an import can come out as another error: a native module whose
        # initialisation it broke says "initialization failed" (scipy's HiGHS through pybind11),
        # a dataclass field's __set_name__ a RuntimeError; the interrupt, not a broken install
        if interrupt.pressed():
            _interrupted()
        raise
    if interrupt.pressed():
        _interrupted()
    code = run(argv)
    sys.stdout.flush()  # here, where a reader gone is caught, not at the interpreter's exit
    if code == EXIT_INTERRUPTED:
        _exit_interrupted()  # the command said what it kept
    return code
