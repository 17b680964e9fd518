"""The ``casadi-design`` command's first instructions: from here on Ctrl-C ends the command
with exit code 130 and one line, also while the package is still being imported (about a
second: CasADi, Pinocchio, numpy)."""

from __future__ import annotations

import os
import sys

from .runtime import interrupt
from .runtime.interrupt import EXIT_INTERRUPTED
from .runtime.threads import fixed_blas


def _interrupted() -> None:
    print("interrupted", file=sys.stderr, flush=True)
    sys.stdout.flush()
    # Ctrl-C inside a native library's import can leave Python believing the signal went
    # unhandled, and it would then end the process by SIGINT (status -2), not 130: nothing
    # is open yet, so end here.
    os._exit(EXIT_INTERRUPTED)


def main(argv: list[str] | None = None) -> int:
    """Import the command line and run it (:func:`casadi_design.cli.main`)."""
    interrupt.install()  # records Ctrl-C: Python drops the KeyboardInterrupt of some import hooks
    fixed_blas()  # before numpy, CasADi and IPOPT load: the same numbers for any --jobs and CPU
    try:
        from .cli import main as run
    except KeyboardInterrupt:
        _interrupted()
    except ImportError:
        # a native module whose initialisation Ctrl-C broke says "initialization failed"
        # (scipy's HiGHS through pybind11): the interrupt, not a broken install
        if interrupt.pressed():
            _interrupted()
        raise
    if interrupt.pressed():
        _interrupted()
    code = run(argv)
    if code == EXIT_INTERRUPTED:
        # the command said what it kept: a SIGINT still pending now would raise a
        # KeyboardInterrupt in the interpreter's exit, which ends the process by SIGINT
        # (status -2, about once in 30 on a loaded machine) instead of 130
        interrupt.ignore()
    return code
