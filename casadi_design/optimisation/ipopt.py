"""How the package runs IPOPT: silent options, warm starts, and the guarded call.

Every IPOPT solve (the design starts, the approximate designs' searches, the check of the
options) runs inside :func:`ipopt_call` with options built from :data:`QUIET`, so a failure is a
status, Ctrl-C stops the command, and BLAS runs on one thread.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from threadpoolctl import ThreadpoolController

from ..runtime.cache import memoised
from ..runtime import interrupt

#: nlpsol options of a silent IPOPT whose failures are statuses, not exceptions.
QUIET = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "error_on_fail": False,
         "show_eval_warnings": False}
#: nlpsol options of a run that continues from the primal and dual point of the previous one.
WARM_START = {"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-6}


@memoised(1)
def _blas() -> ThreadpoolController:
    """The BLAS libraries loaded in this process (found once: a search costs ~2 ms)."""
    return ThreadpoolController()


@contextlib.contextmanager
def ipopt_call() -> Iterator[None]:
    """Run an IPOPT solve: Ctrl-C stops it (:func:`casadi_design.runtime.interrupt.solver_call`), and BLAS
    runs on one thread. The reduced-space derivatives multiply small matrices (L x L): BLAS
    threads cost more than they give there (10x slower on a busy 2-core machine), and the
    rounding, hence a start's outcome, would depend on the thread count (and so on ``--jobs``)."""
    with interrupt.solver_call(), _blas().limit(limits=1, user_api="blas"):
        yield
