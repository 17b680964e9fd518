"""A study: what a user asks of the package, built once, and the one call that runs it.

A :class:`Study` holds the problem, the criteria, the numbers of experiments, the campaign's
settings, whether it is a sweep (with warm starts from the previous m), where the starts run
(``jobs`` processes or a Dask scheduler) and where each finished design is kept (``partial``,
a JSON file that ``resume`` continues from). :func:`run_study` runs it with callbacks for the
progress (one call per start) and for each finished design, and owns what a long run needs:
the designs kept as they finish, a resumed run, Ctrl-C (:class:`Interrupted`, whose message
says what was kept) and a lost worker. The command line turns its arguments into a Study
(:mod:`casadi_design.cli.common`); a script builds one directly::

    study = Study(load_problem("problems/ur10_drilling.toml"), ("test-pose",), (9, 12), Settings(4))
    campaign = run_study(study, on_design=lambda d: print(d.criterion, d.m))
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DesignError, OutputError, ProblemError
from ..plan.design import Design
from ..problem.build import Problem
from ..records.files import load_partial, partial_record
from ..runtime import interrupt
from ..runtime.cache import digest
from .campaign import (
    Campaign,
    Interim,
    Settings,
    campaign_key,
    check_criteria,
    check_m_values,
    choose_campaign,
    run_campaign,
    total_starts,
)
from .parallel import WorkerLost, make_executor
from .sweep import RESUME_KEYS, Sweep, run_sweep, sweep_total_starts
from .target import TARGET_CRITERION, run_target


class Interrupted(Exception):
    """Ctrl-C stopped a study; the message says what was kept (a command exits with 130)."""


@dataclass(frozen=True, eq=False)
class Study:
    """What to design (module docstring).

    problem : the built problem.
    criteria : criteria names (:data:`casadi_design.measures.criteria.CRITERIA`), in solve order.
    m_values : numbers of experiments, each at least ``problem.m_min``.
    settings : seeded starts, exchange steps and pool of the bound, IPOPT's output.
    sweep : a sweep (:func:`casadi_design.execution.sweep.run_sweep`: the reference line, and with
        ``warm_start`` one more start from the previous m's plan) rather than a campaign.
    jobs : worker processes (None: one per core; 1: in this process).
    dask_scheduler : address of a Dask scheduler to run the starts on instead.
    partial : the file each finished design is saved to at once (None: not kept).
    resume : continue from the designs saved in ``partial``'s folder by an interrupted run.
    target_m : a tolerance on the max error along the test poses, m: a campaign searches the
        smallest m that reaches it from ``problem.m_min`` to the last of ``m_values``
        (:mod:`casadi_design.execution.target`); a sweep says which of its m does.
    pool : the postures ``(Q, F)`` the plans are chosen from (``--candidates``;
        :func:`~casadi_design.execution.campaign.choose_campaign`), None: designed freely.
    """

    problem: Problem
    criteria: tuple[str, ...]
    m_values: tuple[int, ...]
    settings: Settings
    sweep: bool = False
    warm_start: bool = True
    jobs: int | None = None
    dask_scheduler: str | None = None
    partial: Path | None = None
    resume: bool = False
    target_m: float | None = None
    pool: tuple[np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        check_criteria(self.problem, self.criteria)
        check_m_values(self.problem, self.m_values)
        if self.pool is not None and (self.sweep or self.target_m is not None):
            raise ProblemError("--candidates chooses the plans of solve; give it without --target-mm, "
                               "and run solve instead of sweep")
        if self.target_m is not None and TARGET_CRITERION not in self.criteria:
            raise ProblemError(f"--target-mm is met by the {TARGET_CRITERION} plans; add {TARGET_CRITERION} "
                               "to --criteria")

    @property
    def key(self) -> dict:
        """What its designs depend on (:func:`casadi_design.execution.campaign.campaign_key`): a resumed
        study must match it."""
        key = campaign_key(self.problem, self.criteria, self.m_values, self.settings,
                           self.sweep and self.warm_start)
        if self.target_m is not None:
            key["target_m"] = self.target_m
        if self.pool is not None:
            key["candidates_sha256"] = digest(*(np.ascontiguousarray(a, dtype=float).tobytes() for a in self.pool))
        return key

    @property
    def searches(self) -> bool:
        """Whether the campaign searches the m of ``target_m`` (not every m of ``m_values``)."""
        return self.target_m is not None and not self.sweep

    @property
    def designs(self) -> int:
        """Designs in all (a search: those of its first two m, a guess)."""
        if self.searches:
            return len(self.criteria) + 1
        return len(self.criteria) * len(self.m_values)

    @property
    def starts(self) -> int:
        """IPOPT starts in all (for a progress bar)."""
        if self.sweep:
            return sweep_total_starts(self.problem, self.criteria, self.m_values, self.settings, self.warm_start)
        if self.searches:
            return total_starts(self.criteria + (TARGET_CRITERION,), self.m_values[:1], self.settings)
        if self.pool is not None:  # greedy, the pool's approximate design and the seeded subsets
            return len(self.m_values) * sum(self.settings.seeded(c) + 2 for c in self.criteria)
        return total_starts(self.criteria, self.m_values, self.settings)

    @property
    def where(self) -> str:
        """Where the starts run, for people."""
        from ..runtime.threads import cpu_count

        if self.dask_scheduler:
            return f"on the Dask cluster at {self.dask_scheduler}"
        jobs = self.jobs or cpu_count()
        return "in this process" if jobs == 1 else f"on {jobs} processes"

    def resumed(self) -> dict[tuple[str, int], Design]:
        """The designs an interrupted run saved (``resume``), else none."""
        if self.partial is None or not self.resume:
            return {}
        sources = RESUME_KEYS if self.sweep else ((self.partial.name, ("key",)),)
        return load_partial(self.partial.parent, self.key, sources)


def executor_of(study: Study):
    """The executor of ``study.jobs`` / ``study.dask_scheduler`` (a context manager), for a
    caller that starts the workers before the problem is built."""
    return make_executor(study.jobs, study.dask_scheduler)


def run_study(study: Study, *, progress: Callable[[int], object] | None = None,
              on_design: Callable[[Design], object] | None = None,
              on_resume: Callable[[int], object] | None = None, executor=None,
              on_better: Callable[[Interim], object] | None = None) -> Campaign | Sweep:
    """Run ``study``: its designs (a :class:`~casadi_design.execution.campaign.Campaign`, or a
    :class:`~casadi_design.execution.sweep.Sweep`), each saved in ``study.partial`` as it finishes and
    passed to ``on_design``; ``progress(n)`` after each start; ``on_resume(n)`` with the number
    of designs a resumed study read back; ``executor``: one already started
    (:func:`executor_of`), else one is started here; ``on_better``: the best plan of a design
    so far, each time it improves (a campaign on workers: :class:`~casadi_design.execution.campaign.Interim`).

    Raises
    ------
    Interrupted
        Ctrl-C, with how many designs are kept and how to continue.
    DesignError
        A lost worker (with what is kept), or a design no start can make (the partial file
        is removed: the same settings fail again).
    """
    done = study.resumed()
    if study.resume and on_resume is not None:
        on_resume(len(done))
    designs = dict(done)

    def save(design: Design) -> None:
        designs[design.criterion, design.m] = design
        if study.partial is not None:
            partial_record(study.partial, study.problem, study.key, list(designs.values()))
        if on_design is not None:
            on_design(design)

    def checked(n: int = 1) -> None:
        interrupt.check()  # a Ctrl-C that CasADi swallowed in this process stops the study here
        if progress is not None:
            progress(n)

    with _keeping(study.partial, lambda: len(designs), study.designs), \
            (contextlib.nullcontext(executor) if executor is not None else executor_of(study)) as ex:
        if study.sweep:
            return run_sweep(study.problem, study.criteria, study.m_values, study.settings,
                             warm_start=study.warm_start, done=done, executor=ex, progress=checked,
                             on_design=save)
        if study.pool is not None:
            return choose_campaign(study.problem, study.criteria, study.m_values, study.settings, *study.pool,
                                   done=done, on_design=save, progress=checked)
        if study.searches:
            return run_target(study.problem, study.criteria, study.problem.m_min, max(study.m_values), study.settings,
                              study.target_m, executor=ex, done=done, on_design=save, progress=checked)[0]
        return run_campaign(study.problem, study.criteria, study.m_values, study.settings, executor=ex,
                            done=done, on_design=save, progress=checked, on_better=on_better)


@contextlib.contextmanager
def _keeping(partial: Path | None, finished: Callable[[], int], total: int) -> Iterator[None]:
    """Run a study whose finished designs are saved in ``partial``: Ctrl-C and a lost worker
    end it with one line saying how many of ``total`` designs are kept there and how to
    continue; a design no start can make removes ``partial`` (and its folder when empty)."""
    def kept() -> str:
        n = finished()
        if not n:
            return f"none of the {total} designs had finished; nothing is kept"
        where = (f"kept in {partial}; continue with the same command and --resume" if partial
                 else "not kept (no --out)")
        return f"{n} of {total} design{'s' if total > 1 else ''} {where}"

    try:
        yield
    except KeyboardInterrupt:
        raise Interrupted(f"interrupted: {kept()}") from None
    except WorkerLost as exc:
        if interrupt.pressed():
            raise Interrupted(f"interrupted: {kept()}") from None
        raise DesignError(f"{exc}; {kept()}") from None
    except DesignError:
        if interrupt.pressed():
            raise Interrupted(f"interrupted: {kept()}") from None
        if partial is not None:
            partial.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                partial.parent.rmdir()  # only when empty: the folder this run created
        raise
    except Exception:
        if not interrupt.pressed():
            raise
        # Ctrl-C while CasADi built a solver: its callbacks' KeyboardInterrupt became a RuntimeError
        raise Interrupted(f"interrupted: {kept()}") from None


@contextlib.contextmanager
def writing(study: Study) -> Iterator[None]:
    """Write a study's files: then its partial file is removed; when a file cannot be
    written, the error also says that the designs are kept and how to continue."""
    try:
        yield
    except OutputError as exc:
        raise OutputError(f"{exc}; the designs are kept in {study.partial}: once fixed, run the same "
                          "command with --resume to write the files without solving again") from None
    if study.partial is not None:
        study.partial.unlink(missing_ok=True)
