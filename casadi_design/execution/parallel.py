"""Run the starts of a multi-start on local processes or on a Dask cluster.

An executor sends each start to a worker as plain data: the problem's checked data
(:class:`~casadi_design.problem_file.read.ProblemSpec`), the criterion, ``m`` and the start plan
``(Q0, F0)`` (Q0 (m, n), rad; F0 (m, nF), N). The worker builds the problem and the design NLP once (cached per process) and runs
:func:`casadi_design.optimisation.solve.solve_start`, the same code the serial loop runs, so a start gives
the same numbers wherever it runs. The seeded start plans are drawn by the caller
(:func:`casadi_design.optimisation.solve.seeded_plans`), never by a worker, so results do not depend on
the number of workers.

An executor runs tasks (:class:`Task`) at most one per worker at a time, the most urgent ready
one first (:meth:`_Workers.run`): a campaign hands it the approximate designs and the starts
of all its designs (:mod:`casadi_design.execution.campaign`), so no worker waits for another to finish
a design.

Executors (context managers; ``None`` means serial, in this process):

* :class:`ProcessExecutor` -- ``jobs`` local processes (``spawn``: no fork of a process that
  already runs CasADi threads);
* :class:`DaskExecutor` -- a ``dask.distributed`` scheduler (``pip install
  casadi-design[dask]``). Workers need this package and must see the problem's relative URDF
  paths from their working folder. Each worker process runs one start at a time; start
  workers with ``--nthreads 1`` and as many processes as cores.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, InvalidStateError, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Protocol, Self

import numpy as np

from ..errors import DesignError
from ..optimisation.approximate import approximate_one, maximise_d
from ..optimisation.bound import ApproximateDesign
from ..optimisation.solve import StartPlan, StartResult, make_design_solver, solve_start
from ..problem.build import Problem, build_problem
from ..problem_file.read import ProblemSpec
from ..runtime.cache import Memo
from ..runtime.interrupt import pressed
from ..runtime.threads import KERNEL_VARIABLE, THREAD_VARIABLES, blas_setup, cpu_count, fixed_blas

#: Seconds to wait for a Dask scheduler before giving up.
DASK_CONNECT_TIMEOUT_S = 5.0
#: Problems (and their solvers) kept per worker process.
CACHE_PROBLEMS = 4


class WorkerLost(DesignError):
    """A worker process died (killed by a signal, out of memory, a crashed native library)
    again after its starts were run once more; the message names the design."""


def _signal_name(code: int | None) -> str:
    """What an exit code of a worker process says (negative: the signal that killed it)."""
    if code is None or code >= 0:
        return "ended abruptly" if code is None else f"exited with code {code}"
    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = f"signal {-code}"
    memory = " (the kernel's out-of-memory killer sends it when memory runs out)" if -code == signal.SIGKILL else ""
    return f"was killed by {name}{memory}"


def _lost(what: str, how: str) -> WorkerLost:
    return WorkerLost(f"{what}: a worker process {how} while running it; give the workers more "
                      "memory or fewer --jobs")

@dataclass(frozen=True)
class ProblemRef:
    """What a worker needs to build a problem: its checked plain data, and a key."""

    spec: ProblemSpec
    key: str

    @classmethod
    def of(cls, problem: Problem) -> ProblemRef:
        return cls(problem.spec, problem.digest)


# Worker-side state. One lock per process: CasADi building and IPOPT (MUMPS) are not safe to
# run from several threads at once, and Dask may run tasks in threads.
_LOCK = threading.Lock()
_PROBLEMS: Memo[tuple[Problem, dict]] = Memo(CACHE_PROBLEMS)


def _cached(ref: ProblemRef) -> tuple[Problem, dict]:
    """The problem of ``ref`` (from build_problem's own memo when built in this process) and
    its design solvers, by (criterion, m, verbose)."""
    return _PROBLEMS.get(ref.key, lambda: (build_problem(ref.spec), {}))


def run_approximate(ref: ProblemRef, criterion: str, m: int, steps: int, pool: int) -> ApproximateDesign:
    """One approximate design, in a worker (:func:`casadi_design.optimisation.approximate.approximate_one`)."""
    with _LOCK:
        return approximate_one(_cached(ref)[0], criterion, steps, pool, m=m)


def run_searches(ref: ProblemRef, scale: float, G: np.ndarray, Q: np.ndarray, F: np.ndarray,
                 duals: list) -> tuple:
    """Searches of an approximate design's step, in a worker (:func:`casadi_design.optimisation.approximate.maximise_d`)."""
    with _LOCK:
        return maximise_d(_cached(ref)[0], scale, G, Q, F, duals)


def run_start(ref: ProblemRef, criterion: str, m: int, Q0: np.ndarray,
              F0: np.ndarray, verbose: bool = False) -> StartResult:
    """One start, in a worker: rebuild (or reuse) the problem and NLP, then solve."""
    with _LOCK:
        problem, solvers = _cached(ref)
        key = (criterion, m, verbose)
        if key not in solvers:
            solvers[key] = make_design_solver(problem, criterion, m, verbose)
        return solve_start(problem, solvers[key], Q0, F0)


#: prctl(2) option: the signal the kernel sends a process when its parent dies (Linux).
PR_SET_PDEATHSIG = 1


def _worker_setup(parent: int) -> None:
    """In each worker process. Ctrl-C reaches every process of the terminal's group: only the
    parent (pid ``parent``) reacts, so it can keep the finished cases and shut the pool down
    cleanly. And a worker ends with its parent: on Linux the kernel sends it SIGKILL when the
    parent dies (``kill``, a batch system's time limit, the out-of-memory killer), so no start
    goes on computing for nobody."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


@dataclass(frozen=True, eq=False)
class Task:
    """One call for a worker, ``fn(*args)``; ``what`` names the work in the message of a lost
    worker (e.g. "criterion D, m = 2")."""

    fn: Callable
    args: tuple
    what: str


class TaskSource(Protocol):
    """What :meth:`_Workers.run` runs: ``take(k)`` hands over up to k of the tasks that can
    run now, the most urgent first (none: nothing is ready until a running task returns)."""

    def take(self, k: int) -> list[Task]: ...


@dataclass(eq=False)
class _Queue:
    """A :class:`TaskSource` of tasks known in advance, in their order."""

    tasks: list[Task]

    def take(self, k: int) -> list[Task]:
        out, self.tasks = self.tasks[:k], self.tasks[k:]
        return out


class _Workers:
    """What an executor runs on its workers: :meth:`run` keeps each worker busy with the most
    urgent task that is ready; :meth:`_map` runs calls known in advance, results in their
    order. A subclass gives ``slots`` (tasks at once), ``_submit(task) -> handle``,
    ``_finished(handles) -> the handles done`` and ``_result(handle, task)`` (both raise
    :class:`BrokenProcessPool` when a local worker process died), ``_restart()`` and
    ``_cancel(handles)``."""

    slots: int = 1

    def run(self, source: TaskSource) -> Iterator[tuple[Task, Any]]:
        """Run the tasks of ``source``, at most ``slots`` at a time, and yield ``(task,
        result)`` as each returns; ``source`` is asked for more whenever a worker is free (a
        task whose inputs just returned goes before less urgent ones). Ends when nothing is
        ready and nothing runs.

        When a local worker process dies, the tasks that ran then run once more, one at a time
        on fresh workers (a task is a pure function of its arguments: the result is the same),
        so that the one that kills its worker is known: a task lost again raises
        :class:`WorkerLost` naming its ``what``. (A Dask scheduler reschedules a lost task
        itself.)"""
        running: dict[Any, Task] = {}
        unsent: list[Task] = []  # taken, but the pool broke before they could be sent
        slots = self.slots
        try:
            while True:
                free = slots - len(running) - len(unsent)
                tasks, unsent = unsent + (list(source.take(free)) if free > 0 else []), []
                for task in tasks:
                    try:
                        running[self._submit(task)] = task
                    except BrokenProcessPool:  # a worker died since the last results came back
                        unsent.append(task)
                if not running:
                    if not unsent:
                        return
                    self._restart()  # the worker died idle: nothing ran that must run alone
                    continue
                broken = False
                for handle in self._finished(list(running)):
                    try:
                        result = self._result(handle, running[handle])
                    except BrokenProcessPool:
                        broken = True
                        continue
                    yield running.pop(handle), result
                if broken:  # every task that ran, again, alone: which one kills its worker?
                    again, running = list(running.values()), {}
                    self._restart()
                    for task in again:
                        yield task, self._alone(task)
        finally:
            self._cancel(list(running))

    def _alone(self, task: Task) -> Any:
        """``task`` run again on fresh workers, alone (after a lost worker)."""
        raise NotImplementedError

    def _map(self, fn: Callable, calls: Sequence[tuple], what: str) -> Iterator[Any]:
        """``fn(*args)`` for each of ``calls``, results in their order as soon as they are
        (:meth:`run`)."""
        tasks = [Task(fn, args, what) for args in calls]
        index = {t: k for k, t in enumerate(tasks)}
        done: dict[int, Any] = {}
        first = 0
        for task, result in self.run(_Queue(list(tasks))):
            done[index[task]] = result
            while first in done:
                yield done.pop(first)
                first += 1

    def map_starts(self, problem: Problem, criterion: str, m: int,
                   plans: Sequence[StartPlan], verbose: bool) -> Iterator[StartResult]:
        """The starts' results in the order of ``plans``."""
        ref = ProblemRef.of(problem)
        yield from self._map(run_start, [(ref, criterion, m, Q0, F0, verbose) for Q0, F0 in plans],
                             f"criterion {criterion}, m = {m}")

    def maximise(self, problem: Problem, scale: float, G: np.ndarray, Q: np.ndarray, F: np.ndarray,
                 duals: list) -> tuple:
        """The searches of one exchange step (:data:`casadi_design.optimisation.bound.Maximise`) split in
        ``slots`` consecutive batches, one per worker; the maxima in their order."""
        ref = ProblemRef.of(problem)
        parts = [p for p in np.array_split(np.arange(len(Q)), self.slots) if p.size]
        found = list(self._map(run_searches, [(ref, scale, G, Q[p], F[p], [duals[i] for i in p])
                                              for p in parts], "the searches of an approximate design"))
        k = sum(len(q) for q, _, _ in found)
        return (np.concatenate([q for q, _, _ in found] or [Q[:0]]).reshape(k, Q.shape[1]),
                np.concatenate([f for _, f, _ in found] or [F[:0]]).reshape(k, F.shape[1]),
                [u for _, _, us in found for u in us])

    def map_approximate(self, problem: Problem, wanted: Sequence[tuple[str, int]], steps: int,
                        pool: int) -> Iterator[ApproximateDesign]:
        """The approximate designs ``wanted``, ``(criterion, m)`` (m = 0: for every m), one per
        worker at the same time."""
        ref = ProblemRef.of(problem)
        yield from self._map(run_approximate, [(ref, c, m, steps, pool) for c, m in wanted],
                             f"the approximate designs of {', '.join(c for c, _ in wanted)}")


class ProcessExecutor(_Workers):
    """Starts on ``jobs`` local worker processes (spawned, single-threaded BLAS)."""

    def __init__(self, jobs: int):
        if jobs < 1:
            raise ValueError(f"--jobs: expected a positive number of processes, got {jobs}")
        self.jobs = jobs
        # Workers are spawned on demand and inherit os.environ then: keep the setting until close
        # (the command set it already: casadi_design.launch; a library caller may not have).
        self._saved_env = fixed_blas()
        self._pool = self._new_pool()

    def _new_pool(self) -> ProcessPoolExecutor:
        pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_worker_setup, initargs=(os.getpid(),))
        # Start the workers now (each imports this package, ~0.5 s) while the caller loads
        # the problem: one submit spawns one process. Ctrl-C waits until every worker is the
        # pool's (one caught half-started would be left behind, printing a traceback).
        blocked = threading.current_thread() is threading.main_thread()
        if blocked:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            for _ in range(self.jobs):
                pool.submit(int)
        finally:
            if blocked:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        return pool

    def _processes(self) -> list:
        """The pool's worker processes (``multiprocessing.Process``), to read how one ended."""
        return list((getattr(self._pool, "_processes", None) or {}).values())

    @property
    def slots(self) -> int:
        return self.jobs

    def _submit(self, task: Task) -> Any:
        return self._pool.submit(task.fn, *task.args)

    def _finished(self, handles: list) -> list:
        done = wait(handles, return_when=FIRST_COMPLETED)[0]
        return [h for h in handles if h in done]  # in the order they were sent

    def _result(self, handle: Any, task: Task) -> Any:
        return handle.result()

    def _restart(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._pool = self._new_pool()

    def _cancel(self, handles: list) -> None:
        for f in handles:
            f.cancel()

    def _alone(self, task: Task) -> Any:
        workers = self._processes()
        try:
            return self._pool.submit(task.fn, *task.args).result()
        except BrokenProcessPool:
            self._restart()  # the old workers are joined: their exit codes are known
            # the pool ends the other workers with SIGTERM once one is lost: name the first cause
            codes = sorted((p.exitcode for p in workers if p.exitcode not in (None, 0)),
                           key=lambda c: c == -signal.SIGTERM)
            raise _lost(task.what, _signal_name(codes[0] if codes else None) + ", twice") from None

    def close(self, interrupted: bool = False) -> None:
        """Shut the pool down; after Ctrl-C, end the workers at once (their starts are lost
        anyway) instead of waiting for the starts they run."""
        if not interrupted:
            self._pool.shutdown(wait=True, cancel_futures=True)
        else:
            # the pool's manager thread then finds its workers gone and fails to mark the
            # cancelled futures (InvalidStateError, printed as a traceback): expected, hidden
            hook = threading.excepthook
            threading.excepthook = lambda args: (None if issubclass(args.exc_type, InvalidStateError)
                                                 else hook(args))
            try:
                workers = self._processes()
                for proc in workers:  # ended before the pool's queues go (a worker still
                    proc.kill()       # starting would read them and print a traceback)
                for proc in workers:
                    proc.join(timeout=5)
                self._pool.shutdown(wait=True, cancel_futures=True)
            finally:
                threading.excepthook = hook
        for k, v in self._saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type | None, *exc: object) -> None:
        # Ctrl-C: a KeyboardInterrupt, or the one-line error a command made of it
        self.close(interrupted=exc_type is not None and (issubclass(exc_type, KeyboardInterrupt) or pressed()))


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message says what to install."""


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError as e:
        raise MissingExtraError(
            "--dask-scheduler needs dask.distributed, which is not installed: "
            "pip install casadi-design[dask]  (or: pip install \"dask[distributed]\")"
        ) from e
    return distributed


def _connect(distributed, address: str):
    """``distributed.Client(address)``, given up a second after ``DASK_CONNECT_TIMEOUT_S``: the
    client's timeout covers the TCP connection, not Dask's handshake (dask/distributed #7698),
    so a service that is no scheduler and never answers would hold the command for ever."""
    found: list = []

    def connect() -> None:
        try:
            found.append(distributed.Client(address, timeout=DASK_CONNECT_TIMEOUT_S))
        except BaseException as exc:  # handed to the caller's thread
            found.append(exc)

    thread = threading.Thread(target=connect, name="dask-connect", daemon=True)
    thread.start()
    thread.join(DASK_CONNECT_TIMEOUT_S + 1.0)
    if not found:
        raise TimeoutError("connected, but no Dask handshake came back: not a Dask scheduler")
    if isinstance(found[0], BaseException):
        raise found[0]
    return found[0]


class DaskExecutor(_Workers):
    """Starts on a Dask cluster: ``address`` of its scheduler (``tcp://host:8786``) or a
    ``distributed.Client`` (left open on close when given)."""

    def __init__(self, address: str | Any):
        distributed = _import_distributed()
        if isinstance(address, distributed.Client):
            self.client, self._own = address, False
        else:
            try:
                self.client = _connect(distributed, address)
            except (OSError, TimeoutError, ValueError, TypeError, MemoryError) as exc:
                # (MemoryError: another service's bytes read as the length of Dask's handshake)
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise DesignError(
                    f"--dask-scheduler {address}: no Dask scheduler answered within "
                    f"{DASK_CONNECT_TIMEOUT_S:g} s ({reason}); check the address (tcp://host:8786) "
                    "or start one with `dask scheduler`") from None
            self._own = True
        self._check_blas()

    def _check_blas(self) -> None:
        """The workers compute with this process's OpenBLAS kernels and BLAS threads
        (:mod:`casadi_design.runtime.threads`), or their starts would give other numbers than ``--jobs``
        (and an approximate design computed there would be kept under this process's name,
        :attr:`casadi_design.problem.build.Problem.fingerprint`): a clear error otherwise."""
        here = blas_setup()
        other = {w: k for w, k in self.client.run(blas_setup).items() if tuple(k) != here}
        kernels_here, threads_here = here
        if other:
            worker, (kernels, threads) = next(iter(other.items()))
            if self._own:
                self.client.close()
            raise DesignError(
                f"--dask-scheduler: {len(other)} worker(s) compute with other OpenBLAS kernels or "
                f"BLAS threads than this command ({worker}: {kernels}, {threads} thread(s); here: "
                f"{kernels_here}, {threads_here} thread(s)), so their starts would end elsewhere; start the "
                f"workers with {KERNEL_VARIABLE}={kernels_here} "
                f"{' '.join(f'{v}={threads_here}' for v in THREAD_VARIABLES)} "
                f"dask worker {self.client.scheduler.address} --nthreads 1")

    @property
    def slots(self) -> int:
        """The cluster's worker threads (one task each), when the work is handed out."""
        return max(1, sum(self.client.nthreads().values()))

    def _submit(self, task: Task) -> Any:
        return self.client.submit(task.fn, *task.args, pure=False)

    def _finished(self, handles: list) -> list:
        from distributed import wait as dask_wait

        done = dask_wait(handles, return_when="FIRST_COMPLETED").done
        return [h for h in handles if h in done]

    def _result(self, handle: Any, task: Task) -> Any:
        from distributed import KilledWorker

        try:
            return handle.result()
        except KilledWorker:  # the scheduler gave the task to workers that died, each time
            raise _lost(task.what, "went away each time the Dask scheduler gave it this work") from None

    def _restart(self) -> None:
        pass

    def _cancel(self, handles: list) -> None:
        self.client.cancel([f for f in handles if not f.done()])

    def close(self) -> None:
        if self._own:
            self.client.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Serial:
    """No executor: :func:`casadi_design.optimisation.solve.solve_design` runs the starts itself."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        pass


def make_executor(jobs: int | None = None, dask_scheduler: str | None = None) -> Any:
    """Context manager giving the executor for ``--jobs`` / ``--dask-scheduler``.

    ``dask_scheduler`` wins over ``jobs``; ``jobs`` None means :func:`cpu_count`; 1 means
    serial (the context gives None).
    """
    if dask_scheduler:
        return DaskExecutor(dask_scheduler)
    jobs = cpu_count() if jobs is None else jobs
    if jobs < 1:
        raise ValueError(f"--jobs: expected a positive number of processes, got {jobs}")
    return _Serial() if jobs == 1 else ProcessExecutor(jobs)
