"""The campaign: every (criterion, m) of a study solved the one way.

For each m (ascending) and each criterion (in the order given), a design is the multi-start
solve (:func:`casadi_design.optimisation.solve.solve_design`) from

1. the seeded random starts (``settings.seeded(criterion)``, drawn from ``(seed, m, criterion)``),
2. the caller's extra starts (a sweep's warm start from the previous m),
3. the starts rounded from an approximate design (:func:`casadi_design.optimisation.approximate.rounded_plans`):
   the criterion's own when it has a bound, A's for E and condition
   (:attr:`~casadi_design.measures.criteria.Criterion.approximate`),

and it carries the certified bound of its criterion for m experiments, when it has one
(:func:`casadi_design.optimisation.bound.bound`). Every command that designs plans (``solve``, ``sweep``,
``validate`` without ``--results``, and what comes) calls :func:`run_campaign`, so the same
problem and settings give the same plans whichever command solved them.

On workers (:mod:`casadi_design.execution.parallel`) the campaign is a pipeline (:class:`_Pipeline`):
the approximate designs and the starts of every design are tasks, handed out as workers free
up, so the seeded starts of later designs fill the time in which a design waits for its
approximate design, its last start or the design before it. Serially, the designs are solved
one after the other. Both give the same designs: each start and each approximate design is a
pure function of its arguments, and a design is judged on its starts in their order.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import DesignError, ProblemError
from ..measures.criteria import BOUND_CRITERIA, CRITERIA
from ..measures.field import field_measure
from ..optimisation.approximate import (
    BOUND_STEPS,
    POOL_SIZE,
    ROUNDED,
    Maximise,
    approximate_one,
    rounded_plans,
)
from ..optimisation.bound import ApproximateDesign, bound
from ..optimisation.solve import (
    StartExecutor,
    StartPlan,
    StartResult,
    best_design,
    initial_starts,
    seeded_plans,
    solve_design,
)
from ..plan.design import SEEDED, Bound, Design
from ..problem.build import Problem
from ..problem_file.solver import seeded_starts, starts_text
from ..runtime.cache import Memo, digest
from . import parallel

#: Extra starts of a design: ``(criterion, m, designs so far) -> [(Q0, F0, origin), ...]``.
ExtraStarts = Callable[[str, int, dict[tuple[str, int], Design]], list[tuple]]
#: The name of an approximate design in a campaign: ``(criterion, m)``, m = 0 when one design
#: serves every m (nothing held; :class:`~casadi_design.optimisation.bound.ApproximateDesign`).
Aim = tuple[str, int]


def aim(problem: Problem, criterion: str, m: int) -> Aim:
    """The approximate design of ``criterion`` for the designs of m experiments: the one that
    bounds them when the criterion has a bound."""
    return (criterion, m if problem.M_held is not None else 0)


def start_aim(problem: Problem, criterion: str, m: int) -> Aim | None:
    """The approximate design that rounds the starts of the design (criterion, m)
    (:attr:`~casadi_design.measures.criteria.Criterion.approximate`); None: it has no rounded starts."""
    source = CRITERIA[criterion].approximate
    return None if source is None else aim(problem, source, m)


def aims(problem: Problem, criteria: Iterable[str], m_values: Iterable[int]) -> list[Aim]:
    """The approximate designs that bound or start the designs of ``criteria`` for
    ``m_values``, in campaign order."""
    out: list[Aim] = []
    for m in m_values:
        for c in criteria:
            a = start_aim(problem, c, m)
            if a is not None and a not in out:
                out.append(a)
    return out


@dataclass(frozen=True)
class Settings:
    """How a campaign solves, beside the problem file.

    Attributes
    ----------
    starts : seeded IPOPT starts per design.
    bound_steps : exchange steps of the approximate designs behind the bounds and the rounded
        starts (0: no bound, no rounded starts).
    bound_pool : random feasible experiments in the approximate design's first pool.
    verbose : IPOPT prints its iterations.
    criterion_starts : (criterion, starts) pairs that replace ``starts`` for the designs of
        those criteria (``[solver.criterion_starts]``).
    """

    starts: int
    bound_steps: int = BOUND_STEPS
    bound_pool: int = POOL_SIZE
    verbose: bool = False
    criterion_starts: tuple[tuple[str, int], ...] = ()

    def __post_init__(self) -> None:
        starts = [self.starts, *dict(self.criterion_starts).values()]
        if min(starts) < 1 or self.bound_steps < 0 or self.bound_pool < 1:
            raise ValueError(f"campaign settings: starts >= 1, bound_steps >= 0 and bound_pool >= 1, "
                             f"got {starts}, {self.bound_steps}, {self.bound_pool}")

    @classmethod
    def of(cls, problem: Problem, starts: int | None = None, **kw) -> Settings:
        """The settings of ``problem``'s ``[solver]`` (its starts and criterion starts), or
        ``starts`` for every design."""
        solver = problem.solver
        return cls(starts or solver.starts, criterion_starts=() if starts else solver.criterion_starts, **kw)

    def seeded(self, criterion: str) -> int:
        """The seeded starts of a design of ``criterion``."""
        return seeded_starts(self.starts, self.criterion_starts, criterion)

    def starts_text(self) -> str:
        """The seeded starts per design, for people (``16 (test-pose: 4)``)."""
        return starts_text(self.starts, self.criterion_starts)


@dataclass(frozen=True)
class Interim:
    """The best plan of a design so far, while its starts run (:func:`run_campaign`'s
    ``on_better``): its criterion's score and max error (m), how many of its starts returned
    (of ``total``; None while its rounded and extra starts are not known yet), the bound when
    its approximate design is done, what is still running, the time since its first start was
    handed out (s), and what runs once these starts have returned (a one-start solve's
    approximate design, :func:`_to_spread`)."""

    criterion: str
    m: int
    value: float
    max_rms_error_m: float
    returned: int
    total: int | None
    bound: Bound | None
    running: tuple[str, ...]
    elapsed_s: float = 0.0
    later: tuple[str, ...] = ()

    def line(self) -> str:
        """For people: the score (mm for errors), the starts, the gap, what still runs."""
        crit = CRITERIA[self.criterion]
        score = (f"{self.value * crit.per_mm:{crit.fmt}} mm" if crit.per_mm != 1 else
                 f"{crit.row.split(': ', 1)[-1]} {self.value:{crit.fmt}} (max error {self.max_rms_error_m * 1e3:.4f} mm)")
        gap = ("" if self.bound is None else
               f", {self.bound.gap_percent(self.value):.1f} % from the bound")
        of = "" if self.total is None else f" of {self.total}"
        running = f"; running: {', '.join(self.running)}" if self.running else ""
        later = f"; next: {', '.join(self.later)}" if self.later else ""
        return (f"best so far: {self.criterion}, m = {self.m}: {score} after {self.returned}{of} "
                f"starts{gap}{running}{later}")


@dataclass(frozen=True, eq=False)
class Campaign:
    """The designs of a campaign, ``{(criterion, m): Design}`` in solve order, the
    approximate designs their bounds and rounded starts came from and, for a campaign that
    searched the m of a tolerance, its answer (:class:`~casadi_design.execution.target.TargetAnswer`)."""

    criteria: tuple[str, ...]
    m_values: tuple[int, ...]
    settings: Settings
    designs: dict[tuple[str, int], Design]
    approx: dict[Aim, ApproximateDesign]
    target: object | None = None


#: Approximate designs, a pure function of (the problem, criterion, steps, pool): the ones
#: used last in this process, and on disk (:mod:`casadi_design.runtime.cache`, named by the problem's
#: :attr:`~casadi_design.problem.build.Problem.fingerprint`, the criterion, steps and pool), so that a
#: later run of any command on the same problem reads them back, to the bit, marked ``kept``;
#: not when :data:`casadi_design.runtime.cache.KEEP_DESIGNS` is 0.
APPROXIMATE: Memo[ApproximateDesign] = Memo(32, kind="approximate-design",
                                            on_read=lambda a: replace(a, kept=True))


def approximate_key(problem: Problem, wanted: Aim, steps: int, pool: int) -> str:
    """The name of an approximate design in :data:`APPROXIMATE` (:func:`~casadi_design.runtime.cache.digest`)."""
    c, m = wanted
    return digest(*(str(v).encode() for v in (problem.fingerprint, c, steps, pool, *((m,) if m else ()))))


def computed(problem: Problem, wanted: Iterable[Aim], steps: int = BOUND_STEPS, pool: int = POOL_SIZE
             ) -> tuple[dict[Aim, ApproximateDesign], list[Aim]]:
    """Of the approximate designs ``wanted`` (:func:`aims`; none when ``steps`` is 0): those
    computed in this process already or kept on disk by an earlier run (these marked
    ``kept``), and those still to compute."""
    wanted = [a for a in wanted if steps > 0]
    have = {w: a for w in wanted for a in [APPROXIMATE.lookup(approximate_key(problem, w, steps, pool))]
            if isinstance(a, ApproximateDesign)}
    return have, [w for w in wanted if w not in have]


def keep(problem: Problem, steps: int, pool: int, approx: ApproximateDesign) -> None:
    """Keep ``approx`` (of ``problem`` with ``steps`` and ``pool``) for the commands that run
    after this one in this process and on this machine (:func:`computed`)."""
    APPROXIMATE.keep(approximate_key(problem, (approx.criterion, approx.m), steps, pool), approx)


def approximate_designs(problem: Problem, wanted: Iterable[Aim], steps: int = BOUND_STEPS, pool: int = POOL_SIZE,
                        executor=None, maximise: Maximise | None = None) -> dict[Aim, ApproximateDesign]:
    """The approximate designs ``wanted`` (:func:`aims`, each by :func:`approximate_one`);
    none when ``steps`` is 0. ``executor`` (:mod:`casadi_design.execution.parallel`) computes
    those not computed yet in this process at the same time, one per worker; None: here, one
    after the other, their searches run by ``maximise`` (:func:`approximate_design`'s). The
    result is the same either way."""
    wanted = list(wanted)
    have, missing = computed(problem, wanted, steps, pool)
    if missing:
        found = (executor.map_approximate(problem, missing, steps, pool) if executor is not None
                 else (approximate_one(problem, c, steps, pool, maximise, m) for c, m in missing))
        for a in found:
            keep(problem, steps, pool, a)
            have[a.criterion, a.m] = a
    return {w: have[w] for w in wanted if w in have}


def campaign_key(problem: Problem, criteria: Iterable[str], m_values: Iterable[int],
                 settings: Settings, warm_start: bool = False) -> dict:
    """What a campaign's designs depend on (a resumed command must match it): the problem's
    checked data, seed, starts, the sweep's warm start, m, criteria and the bound's steps and
    pool."""
    return {"problem_sha256": problem.digest, "seed": problem.solver.seed,
            "starts": settings.starts, "criterion_starts": [list(p) for p in settings.criterion_starts],
            "warm_start": warm_start, "m": sorted(set(m_values)),
            "criteria": list(criteria), "bound_steps_pool": [settings.bound_steps, settings.bound_pool]}


def check_criteria(problem: Problem, criteria: Iterable[str]) -> None:
    for c in criteria:
        if c not in CRITERIA:
            raise ProblemError(f"{problem.path}: --criteria has '{c}'; allowed: {', '.join(CRITERIA)}")


def check_m_values(problem: Problem, m_values: Iterable[int]) -> None:
    small = [m for m in m_values if m < problem.m_min]
    if small:
        held = "" if problem.M_held is None else " with what is held before the plan (--measured, --prior)"
        raise ProblemError(
            f"{problem.path}: --m {small[0]} is too small: {problem.model.L} parameters need "
            f"m >= {problem.m_min} experiments{held}; start the range at {problem.m_min}")


def approximate(problem: Problem, criteria: Iterable[str], m_values: Iterable[int], settings: Settings,
                executor: StartExecutor | None = None) -> dict[Aim, ApproximateDesign]:
    """The approximate designs of the criteria that have a bound for ``m_values`` (none when
    ``settings.bound_steps`` is 0), one per worker of ``executor`` at the same time."""
    return approximate_designs(problem, aims(problem, criteria, m_values), settings.bound_steps,
                               settings.bound_pool, executor)


def has_bound(criterion: str, settings: Settings) -> bool:
    """Whether the designs of ``criterion`` carry a bound."""
    return criterion in BOUND_CRITERIA and settings.bound_steps > 0


def has_rounded(criterion: str, settings: Settings) -> bool:
    """Whether the designs of ``criterion`` have starts rounded from an approximate design."""
    return CRITERIA[criterion].approximate is not None and settings.bound_steps > 0


def total_starts(criteria: Sequence[str], m_values: Sequence[int], settings: Settings) -> int:
    """IPOPT starts of a campaign (for progress bars), the caller's extra starts left out."""
    per_m = sum(settings.seeded(c) + (CRITERIA[c].rounded if has_rounded(c, settings) else 0) for c in criteria)
    return len(m_values) * per_m


def run_campaign(
    problem: Problem,
    criteria: Sequence[str],
    m_values: Iterable[int],
    settings: Settings,
    *,
    approx: dict[Aim, ApproximateDesign] | None = None,
    executor: StartExecutor | None = None,
    done: dict[tuple[str, int], Design] | None = None,
    extra_starts: ExtraStarts | None = None,
    on_design: Callable[[Design], object] | None = None,
    progress: Callable[[int], object] | None = None,
    on_better: Callable[[Interim], object] | None = None,
) -> Campaign:
    """Solve every (criterion, m), m ascending (module docstring).

    Parameters
    ----------
    approx : approximate designs already made (:func:`approximate`); the others are computed.
    executor : where the starts run (:mod:`casadi_design.execution.parallel`); None: here, one by one.
    done : designs already solved (a resumed sweep): kept, not solved again.
    extra_starts : the caller's extra starts of each design (they run after the seeded ones
        and win only when strictly better).
    on_design : called with each design as soon as it is solved (to save it).
    progress : called with the number of starts after each start (``tqdm.update``).
    on_better : on workers, called with the design's :class:`Interim` each time a start
        returns a better plan than its design had (the first answer comes before the bound).
    """
    criteria, ms = tuple(criteria), tuple(sorted(set(m_values)))
    check_criteria(problem, criteria)
    check_m_values(problem, ms)
    designs: dict[tuple[str, int], Design] = dict(done or {})
    if executor is not None and hasattr(executor, "run"):
        approx = dict(approx or {})
        kept, missing = computed(problem, [a for a in aims(problem, criteria, ms) if a not in approx],
                                 settings.bound_steps, settings.bound_pool)
        spread = _to_spread(missing, criteria, ms, settings, designs, executor.slots)
        pipeline = _Pipeline(problem, criteria, ms, settings, designs, {**kept, **approx},
                             [a for a in missing if a not in spread], extra_starts, on_design, progress,
                             on_better, later=spread)
        for task, result in executor.run(pipeline):  # with ``spread``: the seeded starts alone
            pipeline.returned(task, result)
        if spread:  # then the approximate designs, each step's searches over every worker
            pipeline.approx.update(approximate_designs(problem, spread, settings.bound_steps, settings.bound_pool,
                                                       maximise=executor.maximise))
            pipeline.later = []
            for task, result in executor.run(pipeline):
                pipeline.returned(task, result)
        return Campaign(criteria, ms, settings, {(c, m): designs[c, m] for m in ms for c in criteria},
                        {a: pipeline.approx[a] for a in aims(problem, criteria, ms) if a in pipeline.approx})
    given = dict(approx or {})
    approx = {**approximate_designs(problem, [a for a in aims(problem, criteria, ms) if a not in given],
                                    settings.bound_steps, settings.bound_pool, executor), **given}
    _one_by_one(criteria, ms, designs, lambda c, m: _with_field(problem, _bounded(problem, solve_design(
        problem, c, m, starts=settings.seeded(c), verbose=settings.verbose,
        initial_plans=_later_starts(problem, c, m, designs, approx, extra_starts),
        executor=executor, progress=progress), approx), designs, settings), on_design, progress)
    return Campaign(criteria, ms, settings, {(c, m): designs[c, m] for m in ms for c in criteria}, approx)


def _one_by_one(criteria: tuple[str, ...], ms: tuple[int, ...], designs: dict[tuple[str, int], Design],
                make: Callable[[str, int], Design], on_design: Callable[[Design], object] | None,
                progress: Callable[[int], object] | None) -> None:
    """Make every design (c, m) not in ``designs`` yet, m ascending, in criteria order, into
    ``designs`` and ``on_design``; ``progress`` is told the starts of those already there
    (``make`` tells it its own)."""
    for m in ms:
        for c in criteria:
            if (c, m) in designs:
                if progress is not None:
                    progress(len(designs[c, m].starts))
                continue
            designs[c, m] = d = make(c, m)
            if on_design is not None:
                on_design(d)


def choose_campaign(problem: Problem, criteria: Sequence[str], m_values: Iterable[int], settings: Settings,
                    Q: np.ndarray, F: np.ndarray, *, done: dict[tuple[str, int], Design] | None = None,
                    on_design: Callable[[Design], object] | None = None,
                    progress: Callable[[int], object] | None = None) -> Campaign:
    """Every (criterion, m) chosen from the postures ``Q`` (k, n), ``F`` (k, nF) of a pool
    (:func:`casadi_design.optimisation.pool.choose_design`: greedy, the pool's approximate
    design and ``settings.seeded(c)`` random subsets, each exchanged), with the pool's bound
    when ``settings.bound_steps`` > 0; ``done``, ``on_design``, ``progress`` as for
    :func:`run_campaign`."""
    from ..optimisation.pool import choose_design

    criteria, ms = tuple(criteria), tuple(sorted(set(m_values)))
    check_criteria(problem, criteria)
    check_m_values(problem, ms)
    designs: dict[tuple[str, int], Design] = dict(done or {})

    def make(c: str, m: int) -> Design:
        d = choose_design(problem, c, m, Q, F, settings.seeded(c), settings.bound_steps > 0)
        if progress is not None:
            progress(len(d.starts))
        return d

    _one_by_one(criteria, ms, designs, make, on_design, progress)
    return Campaign(criteria, ms, settings, {(c, m): designs[c, m] for m in ms for c in criteria}, {})


def _later_starts(problem: Problem, c: str, m: int, designs: dict, approx: dict,
                  extra_starts: ExtraStarts | None) -> list[tuple]:
    """The starts of design (c, m) after its seeded ones, ``(Q0, F0, origin)``: the caller's
    extra starts (from the designs so far), then those rounded from its approximate design
    (:func:`start_aim`)."""
    extra = extra_starts(c, m, designs) if extra_starts is not None else []
    a = approx.get(start_aim(problem, c, m))
    return extra + ([(Q, F, ROUNDED) for Q, F in rounded_plans(problem, a, m, CRITERIA[c].rounded)]
                    if a is not None else [])


def _with_field(problem: Problem, design: Design, designs: dict, settings: Settings) -> Design:
    """``design``, of a criterion that weighs the problem's field, exchanged with the field over
    its own and the other ``designs``' experiments and sampled ones
    (:func:`casadi_design.optimisation.pool.field_design`); else itself."""
    if not field_measure(problem, design.criterion):
        return design
    from ..optimisation.pool import field_design

    others = [d for key, d in designs.items() if key != (design.criterion, design.m)]
    return field_design(problem, design, others, settings.seeded(design.criterion))


def _bounded(problem: Problem, design: Design, approx: dict) -> Design:
    """``design`` with the bound of its criterion for its m, when it has an approximate design."""
    a = approx.get(aim(problem, design.criterion, design.m))
    return design if a is None or field_measure(problem, design.criterion) else replace(
        design, bound=bound(problem, design.m, a))


def _to_spread(missing: list[Aim], criteria: tuple[str, ...], ms: tuple[int, ...], settings: Settings,
               designs: dict, slots: int) -> list[Aim]:
    """Of the approximate designs ``missing`` (to compute), those to compute after the seeded
    starts, one after the other, each exchange step's IPOPT searches split over the ``slots``
    workers (:meth:`casadi_design.execution.parallel._Workers.maximise`), when the campaign has
    too little else to keep the workers busy meanwhile: fewer approximate designs to compute
    than workers, and no more seeded starts than workers (a one-start solve, whose seeded plan
    is then told before the approximate design). Otherwise none: the pipeline runs each on one
    worker beside the starts. The same designs either way (each search and each start is a pure
    function of its inputs)."""
    seeded = sum(settings.seeded(c) for m in ms for c in criteria if (c, m) not in designs)
    if not missing or len(missing) >= slots or seeded > slots:
        return []
    return missing


def _named(wanted: Iterable[Aim]) -> tuple[str, ...]:
    """Approximate designs for people: "the approximate design of C (m = M)"."""
    return tuple(f"the approximate design of {c}" + (f" (m = {m})" if m else "") for c, m in wanted)


@dataclass(eq=False)
class _Starts:
    """The starts of one design of a pipelined campaign: its plans and their origins (the
    seeded ones first; the extra and rounded ones once ``complete``), how many were handed
    out, their results by index, when the first was handed out, whether it is judged
    (``done``) and, when no start converged, the error to raise."""

    criterion: str
    m: int
    plans: list[StartPlan]
    origins: list[str]
    complete: bool = False
    given: int = 0
    done: bool = False
    error: DesignError | None = None
    results: dict[int, StartResult] = field(default_factory=dict)
    t0: float | None = None
    best: float | None = None


class _Pipeline:
    """The campaign's work as tasks for the workers (:meth:`casadi_design.execution.parallel._Workers.run`),
    so that no worker waits while another finishes a design: the approximate designs first
    (they take longest and the rounded starts wait for them), then the starts of the designs.
    Without extra starts the designs are independent and the largest m go first (their starts
    cost most: a long start handed out last would keep one worker busy alone); with them (a
    sweep's warm start from the design of the previous m) in campaign order, and a design's
    extra starts are asked for once every design before it is finished. The seeded starts of
    other designs run while a design waits for its rounded starts (its approximate design) or
    for its extra starts. A design is judged (:func:`casadi_design.optimisation.solve.best_design`), bounded
    and passed to ``on_design`` as soon as its every start has returned: the same designs as
    one after the other, since each start and approximate design is a pure function of its
    arguments. A design none of whose starts converged raises its error once every design
    before it is judged: the same error, and the same designs kept, as serially."""

    def __init__(self, problem: Problem, criteria: tuple[str, ...], ms: tuple[int, ...],
                 settings: Settings, designs: dict, approx: dict, missing: Sequence[Aim],
                 extra_starts: ExtraStarts | None, on_design: Callable | None, progress: Callable | None,
                 on_better: Callable | None = None, later: Sequence[Aim] = ()):
        self.problem, self.settings, self.designs = problem, settings, designs
        self.later = list(later)  # approximate designs the caller computes after these starts
        self.extra_starts, self.on_design, self.progress = extra_starts, on_design, progress
        self.on_better = on_better
        self.ref = parallel.ProblemRef.of(problem)
        steps, pool = settings.bound_steps, settings.bound_pool
        self.approx = dict(approx)  # made already; ``missing``: computed on the workers
        self.todo = [_Starts(c, m, plans, [SEEDED] * len(plans))
                     for m in ms for c in criteria if (c, m) not in designs
                     for plans in [seeded_plans(problem, c, m, settings.seeded(c))]]
        for m in ms:
            for c in criteria:
                if (c, m) in designs and progress is not None:
                    progress(len(designs[c, m].starts))
        self.pending = [parallel.Task(parallel.run_approximate, (self.ref, c, m, steps, pool),
                                      f"the approximate design of {c}" + (f" for m = {m}" if m else ""))
                        for c, m in missing]
        self.waiting = dict(zip(self.pending, missing))
        self.starts: dict = {}  # task -> (its design, the index of its plan)
        self.order = (list(range(len(self.todo))) if extra_starts is not None else
                      sorted(range(len(self.todo)), key=lambda i: (-self.todo[i].m, i)))

    def _completed(self, k: int, d: _Starts) -> bool:
        """Append the extra and rounded starts of design ``k`` once their inputs are there."""
        if d.complete:
            return True
        c, m = d.criterion, d.m
        if has_rounded(c, self.settings) and start_aim(self.problem, c, m) not in self.approx:
            return False
        if self.extra_starts is not None and not all(e.done and e.error is None for e in self.todo[:k]):
            return False
        plans, origins = initial_starts(self.problem, m, _later_starts(self.problem, c, m, self.designs,
                                                                      self.approx, self.extra_starts))
        d.plans += plans
        d.origins += origins
        d.complete = True
        return True

    def take(self, k: int) -> list:
        out, self.pending = self.pending[:k], self.pending[k:]
        for i in self.order:
            d = self.todo[i]
            if len(out) >= k:
                break
            if d.done:
                continue
            self._completed(i, d)  # its extra and rounded starts, once their inputs are there
            while d.given < len(d.plans) and len(out) < k:
                Q0, F0 = d.plans[d.given]
                task = parallel.Task(parallel.run_start, (self.ref, d.criterion, d.m, Q0, F0,
                                                    self.settings.verbose),
                                  f"criterion {d.criterion}, m = {d.m}")
                self.starts[task] = (d, d.given)
                d.t0 = time.perf_counter() if d.t0 is None else d.t0
                d.given += 1
                out.append(task)
        return out

    def _better(self, d: _Starts, result: StartResult) -> None:
        """Tell ``on_better`` when the start ``result`` of design ``d`` beats its best so far."""
        rec, _, _, scores = result
        crit = CRITERIA[d.criterion]
        if self.on_better is None or not rec.converged or (d.best is not None and (
                not crit.better(rec.value, d.best) or crit.same_optimum(rec.value, d.best))):
            return
        d.best = rec.value
        a = self.approx.get(aim(self.problem, d.criterion, d.m))
        self.on_better(Interim(d.criterion, d.m, rec.value, scores.max_rms_error_m, len(d.results),
                               len(d.plans) if d.complete else None,
                               None if a is None or field_measure(self.problem, d.criterion) else bound(self.problem, d.m, a),
                               _named(self.waiting.values()),
                               time.perf_counter() - d.t0, _named(self.later)))

    def returned(self, task, result) -> None:
        """Take the result of ``task``; finish the designs whose every start returned."""
        if task in self.waiting:
            wanted = self.waiting.pop(task)
            keep(self.problem, self.settings.bound_steps, self.settings.bound_pool, result)
            self.approx[wanted] = result
        else:
            d, i = self.starts.pop(task)
            d.results[i] = result
            if self.progress is not None:
                self.progress(1)
            self._better(d, result)
        for k, d in enumerate(self.todo):  # in campaign order: a finished one may complete the next
            if d.done or not (self._completed(k, d) and len(d.results) == len(d.plans)):
                continue
            d.done = True
            try:
                design = best_design(self.problem, d.criterion, d.m,
                                     (d.results[i] for i in range(len(d.plans))), d.origins, d.t0)
            except DesignError as exc:  # raised once every design before it is judged, as serially
                d.error = exc
                continue
            self.designs[d.criterion, d.m] = design = _with_field(
                self.problem, _bounded(self.problem, design, self.approx), self.designs, self.settings)
            if self.on_design is not None:
                self.on_design(design)
        failed = next((k for k, d in enumerate(self.todo) if d.error is not None), None)
        if failed is not None and all(d.done for d in self.todo[:failed]):
            raise self.todo[failed].error
