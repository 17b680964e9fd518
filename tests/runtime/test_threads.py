"""Every process computes with the same BLAS: one thread, one set of OpenBLAS kernels."""

import os
import subprocess
import sys

import pytest

from casadi_design.errors import DesignError
from casadi_design.execution.parallel import DaskExecutor
from casadi_design.records.results import results_dict
from casadi_design.runtime.threads import KERNEL, KERNEL_VARIABLE, _cpu_runs_kernel, blas_kernels


def _python(code: str) -> str:
    """``code`` run by a fresh interpreter whose environment leaves the BLAS to the package."""
    env = {k: v for k, v in os.environ.items()
           if k not in (KERNEL_VARIABLE, "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


@pytest.mark.skipif(not _cpu_runs_kernel(), reason=f"this CPU does not run the {KERNEL} kernels")
def test_the_kernels_are_fixed_before_numpy_loads():
    # OpenBLAS picks its kernels by CPU, and they round differently: fixed where the CPU runs them
    out = _python("from casadi_design.runtime.threads import fixed_blas, blas_kernels; fixed_blas(); "
                  "import numpy, scipy.linalg; print(blas_kernels())")
    assert out == KERNEL
    assert blas_kernels() == KERNEL  # this test process too (tests/conftest.py, as the command)


def test_a_library_caller_s_workers_get_the_kernels_it_loaded():
    # numpy loaded before the package: too late to choose, so the workers get the same kernels
    out = _python("import os, numpy; from casadi_design.runtime.threads import fixed_blas, blas_kernels; "
                  f"fixed_blas(); print(os.environ.get('{KERNEL_VARIABLE}') == blas_kernels() != 'none')")
    assert out == "True"


def _loaded_openblas_corenames() -> set[str]:
    """The kernels numpy's and scipy's OpenBLAS libraries mapped into this process report
    themselves, asked through their own C function ``*_get_corename`` (the libraries found in
    /proc/self/maps, not through threadpoolctl as :func:`blas_kernels` finds them). CasADi's
    ``libcasadi-tp-openblas``, built for one core type, has no choice of kernels to record."""
    import ctypes

    with open("/proc/self/maps") as fh:
        files = {line.split()[-1] for line in fh if "/" in line}
    prefixes = ("libopenblas", "libscipy_openblas")
    paths = {f for f in files if f.rsplit("/", 1)[-1].startswith(prefixes)}
    names = set()
    for path in paths:
        lib = ctypes.CDLL(path)  # loaded already: the same handle
        symbols = [s for s in ("openblas_get_corename", "scipy_openblas_get_corename",
                               "scipy_openblas_get_corename64_", "openblas_get_corename64_")
                   if hasattr(lib, s)]
        assert symbols, f"{path}: no *_get_corename"
        get = getattr(lib, symbols[0])
        get.restype = ctypes.c_char_p
        names.add(get().decode())
    return names


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
def test_results_record_the_kernels(paper):
    import numpy  # noqa: F401  (loaded by the package already: its OpenBLAS, and scipy's)
    import scipy.linalg  # noqa: F401

    recorded = results_dict(paper, [])["blas_kernels"]
    assert recorded == (",".join(sorted(_loaded_openblas_corenames())) or "none")
    if _cpu_runs_kernel():
        assert recorded == KERNEL  # fixed before numpy loaded (tests/conftest.py, as the command)


def test_dask_workers_with_other_kernels_are_refused_with_the_fix(monkeypatch):
    distributed = pytest.importorskip("distributed")
    monkeypatch.setenv(KERNEL_VARIABLE, "Prescott")  # the workers' (SSE3: every x86-64 runs it)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        if client.run(blas_kernels) == {w: blas_kernels() for w in client.scheduler_info()["workers"]}:
            pytest.skip("this BLAS has no choice of kernels")
        with pytest.raises(DesignError, match=f"{KERNEL_VARIABLE}={blas_kernels()} .*dask worker tcp://"):
            DaskExecutor(client)
        assert client.status == "running"  # a client given by the caller stays open


def test_results_name_the_numerical_libraries(paper):
    from importlib.metadata import version

    import numpy

    versions = results_dict(paper, [])["versions"]
    assert versions["numpy"] == numpy.__version__ and versions["casadi"] == version("casadi")
