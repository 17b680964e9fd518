"""The campaign: every (criterion, m) of a study solved the one way.

For each m (ascending) and each criterion (in the order given), a design is the multi-start
solve (:func:`casadi_design.solve.solve_design`) from

1. the seeded random starts (``settings.starts``, drawn from ``(seed, m, criterion)``),
2. the caller's extra starts (a sweep's warm start from the previous m),
3. the starts rounded from the criterion's approximate design, when it has one
   (:func:`casadi_design.bound.rounded_plans`),

and it carries the certified bound of its criterion for m experiments
(:func:`casadi_design.bound.bound`). Every command that designs plans (``solve``, ``sweep``,
``validate`` without ``--results``, and what comes) calls :func:`run_campaign`, so the same
problem and settings give the same plans whichever command solved them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

from .bound import (
    BOUND_STEPS,
    POOL_SIZE,
    ROUNDED,
    ROUNDED_PLANS,
    ApproximateDesign,
    approximate_designs,
    bound,
    rounded_plans,
)
from .build import Problem
from .criteria import CRITERIA
from .design import Design
from .errors import ProblemError
from .nlp import B0_at_test_poses
from .solve import StartExecutor, solve_design

#: Extra starts of a design: ``(criterion, m, designs so far) -> [(Q0, F0, origin), ...]``.
ExtraStarts = Callable[[str, int, dict[tuple[str, int], Design]], list[tuple]]


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
    """

    starts: int
    bound_steps: int = BOUND_STEPS
    bound_pool: int = POOL_SIZE
    verbose: bool = False

    def __post_init__(self) -> None:
        if self.starts < 1 or self.bound_steps < 0 or self.bound_pool < 1:
            raise ValueError(f"campaign settings: starts >= 1, bound_steps >= 0 and bound_pool >= 1, "
                             f"got {self.starts}, {self.bound_steps}, {self.bound_pool}")


@dataclass(frozen=True, eq=False)
class Campaign:
    """The designs of a campaign, ``{(criterion, m): Design}`` in solve order, and the
    approximate designs their bounds and rounded starts came from."""

    criteria: tuple[str, ...]
    m_values: tuple[int, ...]
    settings: Settings
    designs: dict[tuple[str, int], Design]
    approx: dict[str, ApproximateDesign]


def campaign_key(problem: Problem, criteria: Iterable[str], m_values: Iterable[int],
                 settings: Settings, warm_start: bool = False) -> dict:
    """What a campaign's designs depend on (a resumed command must match it): the problem's
    checked data, seed, starts, the sweep's warm start, m, criteria and the bound's steps and
    pool."""
    return {"problem_sha256": problem.digest, "seed": problem.solver.seed,
            "starts": settings.starts, "warm_start": warm_start, "m": sorted(set(m_values)),
            "criteria": list(criteria), "bound_steps_pool": [settings.bound_steps, settings.bound_pool]}


def check_criteria(problem: Problem, criteria: Iterable[str]) -> None:
    for c in criteria:
        if c not in CRITERIA:
            raise ProblemError(f"{problem.path}: --criteria has '{c}'; allowed: {', '.join(CRITERIA)}")


def check_m_values(problem: Problem, m_values: Iterable[int]) -> None:
    small = [m for m in m_values if m < problem.m_min]
    if small:
        raise ProblemError(
            f"{problem.path}: --m {small[0]} is too small: {problem.model.L} parameters need "
            f"m >= {problem.m_min} experiments; start the range at {problem.m_min}")


def approximate(problem: Problem, criteria: Iterable[str], settings: Settings,
                executor: StartExecutor | None = None) -> dict[str, ApproximateDesign]:
    """The approximate designs of the criteria that have a bound (none when
    ``settings.bound_steps`` is 0), one per worker of ``executor`` at the same time."""
    return approximate_designs(problem, criteria, settings.bound_steps, settings.bound_pool, executor)


def total_starts(criteria: Sequence[str], m_values: Sequence[int], settings: Settings,
                 approx: dict[str, ApproximateDesign]) -> int:
    """IPOPT starts of a campaign (for progress bars), the caller's extra starts left out."""
    per_m = sum(settings.starts + (ROUNDED_PLANS if c in approx else 0) for c in criteria)
    return len(m_values) * per_m


def run_campaign(
    problem: Problem,
    criteria: Sequence[str],
    m_values: Iterable[int],
    settings: Settings,
    *,
    approx: dict[str, ApproximateDesign] | None = None,
    executor: StartExecutor | None = None,
    done: dict[tuple[str, int], Design] | None = None,
    extra_starts: ExtraStarts | None = None,
    on_design: Callable[[Design], object] | None = None,
    progress: Callable[[int], object] | None = None,
) -> Campaign:
    """Solve every (criterion, m), m ascending (module docstring).

    Parameters
    ----------
    approx : the approximate designs (:func:`approximate`); computed when None.
    executor : where the starts run (:mod:`casadi_design.parallel`); None: here, one by one.
    done : designs already solved (a resumed sweep): kept, not solved again.
    extra_starts : the caller's extra starts of each design (they run after the seeded ones
        and win only when strictly better).
    on_design : called with each design as soon as it is solved (to save it).
    progress : called with the number of starts after each start (``tqdm.update``).
    """
    criteria, ms = tuple(criteria), tuple(sorted(set(m_values)))
    check_criteria(problem, criteria)
    check_m_values(problem, ms)
    approx = approximate(problem, criteria, settings, executor) if approx is None else approx
    designs: dict[tuple[str, int], Design] = dict(done or {})
    B0 = B0_at_test_poses(problem)
    for m in ms:
        for c in criteria:
            if (c, m) in designs:
                if progress is not None:
                    progress(len(designs[c, m].starts))
                continue
            extra = extra_starts(c, m, designs) if extra_starts is not None else []
            rounded = [(Q, F, ROUNDED) for Q, F in rounded_plans(problem, approx[c], m)] if c in approx else []
            d = solve_design(problem, c, m, B0, starts=settings.starts, verbose=settings.verbose,
                             initial_plans=extra + rounded, executor=executor, progress=progress)
            if c in approx:
                d = replace(d, bound=bound(problem, m, approx[c]))
            designs[c, m] = d
            if on_design is not None:
                on_design(d)
    return Campaign(criteria, ms, settings, {(c, m): designs[c, m] for m in ms for c in criteria}, approx)
