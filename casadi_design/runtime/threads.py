"""The same arithmetic in every process: one thread for BLAS and OpenMP (IPOPT's linear solver)
and one set of OpenBLAS kernels, set before the libraries load.

The parallelism is across starts and approximate designs (:mod:`casadi_design.execution.parallel`); BLAS
or OpenMP threads of several processes fighting for the same cores made a 2-process run no
faster than a serial one. And the thread count changes the rounding of IPOPT's linear algebra,
so a result would depend on it: the main process (``--jobs 1``) and every worker run with the
same single thread.

numpy's and scipy's OpenBLAS choose their kernels by CPU (``Haswell`` for AVX2, ``SkylakeX``
for AVX-512 Intel, ...), and kernels round differently: a UR10 start in its cell ends at
another local optimum with the ``SkylakeX`` kernels than with the ``Haswell`` ones, so a table
would depend on the machine that printed it. Where the CPU runs them (x86-64 with AVX2 and FMA,
Linux), the kernels are fixed to :data:`KERNEL`. (CasADi's own OpenBLAS, under MUMPS, is built
for one core type already.) Everything is set here before numpy, CasADi or IPOPT start: their
libraries read the variables once, when they load. A value the user set is kept.
"""

from __future__ import annotations

import os
import platform
import sys

#: The thread counts of the BLAS/OpenMP libraries.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: OpenBLAS's choice of kernels (a build with DYNAMIC_ARCH reads it when it loads).
KERNEL_VARIABLE = "OPENBLAS_CORETYPE"
#: The kernels every process runs where the CPU can (:func:`fixed_blas`).
KERNEL = "Haswell"
#: CPU flags the :data:`KERNEL` kernels need.
KERNEL_FLAGS = ("avx2", "fma")


def _cpu_runs_kernel() -> bool:
    """Whether this machine runs the :data:`KERNEL` kernels: Linux on x86-64 with every flag of
    :data:`KERNEL_FLAGS` in /proc/cpuinfo."""
    if not sys.platform.startswith("linux") or platform.machine() not in ("x86_64", "AMD64"):
        return False
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((line.split(":", 1)[1].split() for line in fh if line.startswith("flags")), [])
    except OSError:
        return False
    return all(f in flags for f in KERNEL_FLAGS)


def fixed_blas() -> dict[str, str | None]:
    """Set every variable of :data:`THREAD_VARIABLES` that the user did not set to 1, and
    :data:`KERNEL_VARIABLE` to :data:`KERNEL` where the CPU runs it; returns the values before.
    Called after numpy has loaded (by a library caller), it sets the kernels already loaded,
    so that the worker processes started next compute as this one does."""
    names = (*THREAD_VARIABLES, KERNEL_VARIABLE)
    before = {k: os.environ.get(k) for k in names}
    for k in THREAD_VARIABLES:
        os.environ.setdefault(k, "1")
    if "numpy" in sys.modules:  # loaded already (a library caller): workers get its kernels
        loaded = blas_kernels()
        if loaded != "none" and "," not in loaded:
            os.environ.setdefault(KERNEL_VARIABLE, loaded)
    elif _cpu_runs_kernel():
        os.environ.setdefault(KERNEL_VARIABLE, KERNEL)
    return before


def blas_kernels() -> str:
    """The kernels of the OpenBLAS libraries loaded in this process, e.g. ``"Haswell"`` (comma
    separated when they differ; ``"none"`` without OpenBLAS): what the results were computed
    with (written into results.json; a Dask worker's must be the command's)."""
    from threadpoolctl import threadpool_info

    kernels = sorted({str(i.get("architecture")) for i in threadpool_info()
                      if i.get("internal_api") == "openblas"})
    return ",".join(kernels) or "none"


def blas_threads() -> int:
    """The most threads any BLAS or OpenMP library loaded in this process runs: 1 wherever
    :func:`fixed_blas` ran first (the commands, their workers, the test suite); a library
    caller that did not call it gets one per core, and other rounding (the approximate designs'
    numpy products: another certificate to the last bits, another plan from some starts), so
    what is kept on disk is named by it too (:attr:`casadi_design.problem.build.Problem.fingerprint`)."""
    from threadpoolctl import threadpool_info

    return max((int(i["num_threads"]) for i in threadpool_info()), default=1)


def blas_setup() -> tuple[str, int]:
    """This process's OpenBLAS kernels and BLAS thread count (:func:`blas_kernels`,
    :func:`blas_threads`): what its numbers are computed with (run on every Dask worker,
    :meth:`casadi_design.execution.parallel.DaskExecutor._check_blas`)."""
    return blas_kernels(), blas_threads()


def cpu_count() -> int:
    """CPUs this process may use (the default of ``--jobs``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
