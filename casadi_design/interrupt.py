"""Ctrl-C that stops at once, even inside IPOPT.

CasADi checks for Ctrl-C between IPOPT iterations, runs Python's handler, and then reports the
start as failed (a ``KeyboardInterruptException`` warning) instead of raising. The command line
installs :func:`install`: the handler records the signal before raising, and :func:`check`,
called after every solver call, turns the recorded signal back into ``KeyboardInterrupt``.
"""

from __future__ import annotations

import signal
import threading

_HIT = threading.Event()


def _handler(signum: int, frame: object) -> None:
    _HIT.set()
    raise KeyboardInterrupt


def install() -> None:
    """Record Ctrl-C (SIGINT) for :func:`check`; call from the main thread."""
    _HIT.clear()
    signal.signal(signal.SIGINT, _handler)


def check() -> None:
    """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed since :func:`install`."""
    if _HIT.is_set():
        raise KeyboardInterrupt


def interrupted() -> bool:
    """Whether Ctrl-C was pressed since :func:`install`."""
    return _HIT.is_set()
