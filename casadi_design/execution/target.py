"""How many experiments a tolerance needs: the smallest m whose test-pose plan reaches it.

For a target T (m) on the max error ``max_j sqrt(rho_j)`` along the test poses, the answer is
the smallest m, from the smallest identifiable one up to a limit, whose test-pose design
reaches ``max_j sqrt(rho_j) <= T``. The certified bound of the test-pose criterion
(:mod:`casadi_design.optimisation.bound`) is a lower bound of the error of every plan of m
experiments and falls with m, so no m whose bound exceeds T can reach it: the search finds the
smallest m whose bound is at most T (one approximate design serves every m; with information
held, one per m, found by bisection), and designs from there up until a plan reaches T. The
answer says whether m - 1 is excluded by its bound ("cannot") or was only not reached by its
design ("might"). Without a bound (``bound_steps`` 0, or a field of unmodelled error, whose
experiments are correlated) the designs start at the smallest m.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ..measures.field import field_measure
from ..optimisation.bound import bound
from ..plan.design import Design
from ..problem.build import Problem
from .campaign import Campaign, Settings, aim, approximate_designs, has_bound, run_campaign

#: The criterion whose plans the target is met with.
TARGET_CRITERION = "test-pose"
#: The largest m a search tries by default: this many times the largest m of the problem file.
LIMIT_FACTOR = 3


def default_limit(problem: Problem) -> int:
    """The largest m a search tries without ``--m``: ``LIMIT_FACTOR`` times the largest m of
    the problem file, at least 10 more than the smallest identifiable."""
    return max(LIMIT_FACTOR * max(problem.m_values), problem.m_min + 10)


@dataclass(frozen=True)
class TargetAnswer:
    """The smallest m that reaches ``target_m`` (module docstring).

    Attributes
    ----------
    target_m : the tolerance on the max error along the test poses, m.
    m : the smallest m whose test-pose plan reaches it; None when no m up to ``limit`` does.
    limit : the largest m searched.
    errors_m : the max error of the test-pose design of every m designed, m.
    bounds_m : the certified lower bound of the max error at every m looked at, m.
    m_held : experiments already measured (the campaign is m_held + m).
    """

    target_m: float
    m: int | None
    limit: int
    errors_m: dict[int, float]
    bounds_m: dict[int, float]
    m_min: int
    m_held: int = 0

    @property
    def fewer_excluded(self) -> bool | None:
        """Whether m - 1 experiments cannot reach the target: by their bound (True), or not
        known (False: the bound allows it, the design did not reach it); None when m is the
        smallest identifiable (fewer identify nothing) or there is no answer."""
        if self.m is None or self.m <= self.m_min:
            return None
        b = self.bounds_m.get(self.m - 1)
        return b is not None and b > self.target_m

    def line(self) -> str:
        """The answer for people (mm)."""
        T = f"{self.target_m * 1e3:.4g} mm"
        held = f" new (with the {self.m_held} measured: {{}} in all)" if self.m_held else ""
        if self.m is None:
            worst = self.bounds_m.get(self.limit)
            reached = self.errors_m.get(self.limit)
            return (f"target {T}: no plan of up to {self.limit} experiments reaches it"
                    + (f" (the bound at m = {self.limit} is {worst * 1e3:.4g} mm)" if worst is not None else "")
                    + (f"; the plan of {self.limit} reaches {reached * 1e3:.4g} mm" if reached is not None else "")
                    + "; relax the target, raise the limit with --m, or measure more precisely")
        head = (f"target {T}: m = {self.m}" + held.format(self.m_held + self.m)
                + f", its plan {self.errors_m[self.m] * 1e3:.4g} mm")
        fewer = self.fewer_excluded
        if fewer is None:
            return head + f"; {self.m} is the fewest that identify the parameters"
        b = self.bounds_m.get(self.m - 1)
        if fewer:
            return head + f"; {self.m - 1} cannot reach {T} (bound {b * 1e3:.4g} mm)"
        return (head + f"; {self.m - 1} might" + (f" (bound {b * 1e3:.4g} mm" if b is not None else " (no bound")
                + (f", its plan {self.errors_m[self.m - 1] * 1e3:.4g} mm)" if self.m - 1 in self.errors_m else ")"))

    def as_dict(self) -> dict:
        return {"target_m": self.target_m, "m": self.m, "limit": self.limit,
                "fewer_excluded_by_bound": self.fewer_excluded, "m_measured": self.m_held,
                "max_rms_error_m": {str(m): v for m, v in sorted(self.errors_m.items())},
                "bound_m": {str(m): v for m, v in sorted(self.bounds_m.items())}, "answer": self.line()}


def answer_from(problem: Problem, target_m: float, designs: dict[tuple[str, int], Design],
                limit: int, bounds: dict[int, float] | None = None) -> TargetAnswer:
    """The answer read from designs already solved (a sweep, a search): the smallest m of
    their test-pose designs that reaches the target, with their bounds and ``bounds`` (m: the
    bound of m experiments, m) of m not designed."""
    ours = {m: d for (c, m), d in designs.items() if c == TARGET_CRITERION}
    errors = {m: d.scores.max_rms_error_m for m, d in ours.items()}
    bounds = {**(bounds or {}), **{m: d.bound.value for m, d in ours.items() if d.bound is not None}}
    m = min((m for m, e in errors.items() if e <= target_m), default=None)
    return TargetAnswer(target_m, m, limit, errors, bounds, problem.m_min, problem.m_held)


def run_target(problem: Problem, criteria: tuple[str, ...], first: int, limit: int, settings: Settings,
               target_m: float, *,
               executor=None, done: dict | None = None, on_design: Callable[[Design], object] | None = None,
               progress: Callable[[int], object] | None = None) -> tuple[Campaign, TargetAnswer]:
    """The smallest m from ``first`` to ``limit`` whose test-pose plan reaches ``target_m`` (m;
    module docstring), and the designs on the way: test-pose at every m designed, the other
    ``criteria`` at the answer (or at ``limit`` without one). ``done``, ``on_design`` and
    ``progress`` as for :func:`~casadi_design.execution.campaign.run_campaign`."""
    designs: dict[tuple[str, int], Design] = dict(done or {})
    approx: dict = {}
    bounds: dict[int, float] = {}

    def bound_at(m: int) -> float:
        if m not in bounds:
            wanted = aim(problem, TARGET_CRITERION, m)
            approx.update(approximate_designs(problem, [wanted], settings.bound_steps, settings.bound_pool, executor))
            bounds[m] = bound(problem, m, approx[wanted]).value
        return bounds[m]

    def design(criteria: tuple[str, ...], m: int) -> None:
        found = run_campaign(problem, criteria, (m,), settings, approx=approx, executor=executor,
                             done=designs, on_design=on_design, progress=progress)
        designs.update(found.designs)
        approx.update(found.approx)

    lo, hi = first, limit
    m = first
    bounded = has_bound(TARGET_CRITERION, settings) and not field_measure(problem, TARGET_CRITERION)  # (a field: none)
    if bounded and bound_at(hi) > target_m:
        m = limit + 1  # no m up to the limit: only the limit is designed, to show how close it comes
    elif bounded and bound_at(lo) > target_m:  # bound(lo) > T >= bound(hi): the smallest m with bound <= T
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if bound_at(mid) > target_m else (lo, mid)
        m = hi
    reached = None
    while m <= limit and reached is None:
        design((TARGET_CRITERION,), m)
        reached = m if designs[TARGET_CRITERION, m].scores.max_rms_error_m <= target_m else None
        m += 1
    if bounded and reached is not None and reached - 1 >= problem.m_min:
        bound_at(reached - 1)  # whether fewer could: the answer's statement
    final = limit if reached is None else reached
    if (TARGET_CRITERION, final) not in designs:
        design((TARGET_CRITERION,), final)
    others = tuple(c for c in criteria if c != TARGET_CRITERION)
    if others:
        design(others, final)
    ms = tuple(sorted({m for _, m in designs}))
    order = (TARGET_CRITERION, *others)
    answer = answer_from(problem, target_m, designs, limit, bounds)
    campaign = Campaign(order, ms, settings,
                        {(c, m): designs[c, m] for m in ms for c in order if (c, m) in designs}, approx, answer)
    return campaign, answer

