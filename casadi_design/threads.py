"""One thread per process for BLAS and OpenMP (IPOPT's linear solver), set before they load.

The parallelism is across starts and approximate designs (:mod:`casadi_design.parallel`); BLAS
or OpenMP threads of several processes fighting for the same cores made a 2-process run no
faster than a serial one. And the thread count changes the rounding of IPOPT's linear algebra,
so a result would depend on it: the main process (``--jobs 1``) and every worker run with the
same single thread, set here before numpy, CasADi or IPOPT start (their libraries read the
variables once, when they load or first run in parallel). A value the user set is kept.
"""

from __future__ import annotations

import os

#: The thread counts of the BLAS/OpenMP libraries.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded() -> dict[str, str | None]:
    """Set every variable of :data:`THREAD_VARIABLES` that the user did not set to 1; returns
    the values before."""
    before = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    for k in THREAD_VARIABLES:
        os.environ.setdefault(k, "1")
    return before


def cpu_count() -> int:
    """CPUs this process may use (the default of ``--jobs``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
