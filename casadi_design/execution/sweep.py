"""Sweeps over the number of experiments ``m`` and the criteria: how accuracy grows with m.

A sweep is a campaign (:func:`casadi_design.execution.campaign.run_campaign`: the same seeded and rounded
starts and bounds as a single solve) plus, for every m after the first, one *warm start*: the
sweep's plan for the previous m (``m_prev``) completed with ``m - m_prev`` random
experiments drawn from their own generator (:func:`warm_start_rng`). The warm start runs
after the seeded starts and wins only when strictly better, so a sweep's design equals the
solve's design when the warm start does not win, and is better when it does; each row says
which happened (``warm_start_won``) and keeps the best result of the solve's own starts
(seeded and rounded: ``seeded_best_max_error_mm``).

Reference line "repeat the best single pose": repeating a plan k times multiplies M by k, so
``sqrt(rho)`` is divided by ``sqrt(k)``. From the best test-pose plan of ``m_ref`` experiments
(``m_ref`` = the smallest identifiable m, 1 for the paper) the line is
``e(m_ref) sqrt(m_ref / m)``; a plan that beats it gains from *different* poses, not from
repetition (the paper: factor 2.5 from 1 to 5 experiments against sqrt(5) = 2.24).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from ..measures.criteria import CRITERIA
from ..optimisation.bound import ApproximateDesign
from ..optimisation.solve import StartExecutor
from ..plan.design import WARM_ORIGIN, Design
from ..plan.sampling import random_plan
from ..problem.build import Problem
from ..records.results import design_from_record, design_record, results_dict
from .campaign import Settings, check_m_values, run_campaign, total_starts

#: The 4th entry of the warm-start generator's seed (start_rng uses 3 entries).
WARM_STREAM = 1


def warm_start_rng(seed: int, criterion: str, m: int) -> np.random.Generator:
    """Generator of the experiments added to the previous plan; not the seeded starts' one."""
    return np.random.default_rng([seed, m, CRITERIA[criterion].seed_id, WARM_STREAM])


def warm_start_plan(problem: Problem, previous: Design, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The plan of ``previous`` (m_prev experiments) plus ``m - m_prev`` random experiments.

    Returns ``Q0`` (m, n), rad, and ``F0`` (m, nF), N: a start of the design of m.
    """
    k = m - previous.m
    if k < 1:
        raise ValueError(f"warm start for m = {m} from a plan of {previous.m} experiments")
    Q_new, F_new = random_plan(problem, k, warm_start_rng(problem.solver.seed, previous.criterion, m))
    return np.vstack([previous.Q, Q_new]), np.vstack([previous.F, F_new])


@dataclass(frozen=True, eq=False)
class Sweep:
    """The designs of a sweep and how they were obtained.

    Attributes
    ----------
    designs : {(criterion, m): Design}
    seeded_starts : seeded starts per design.
    criterion_starts : (criterion, starts) pairs that replace ``seeded_starts`` for those criteria.
    reference : the best test-pose design at ``problem.m_min``, for the "repeat" line (None when
        the sweep has no test-pose criterion).
    approx : the approximate designs behind its bounds and rounded starts (empty for a sweep
        read back from its record).
    """

    m_values: tuple[int, ...]
    criteria: tuple[str, ...]
    designs: dict[tuple[str, int], Design]
    seeded_starts: int
    warm_start: bool
    reference: Design | None = None
    approx: dict[tuple[str, int], ApproximateDesign] = field(default_factory=dict)
    criterion_starts: tuple[tuple[str, int], ...] = ()

    def warm_start_won(self, criterion: str, m: int) -> bool:
        """True when the warm start is strictly better than every seeded start."""
        winner = self.designs[criterion, m].winner
        return winner is not None and winner.origin == WARM_ORIGIN

    def repeat_reference_m(self, m: int) -> float:
        """``e(m_ref) sqrt(m_ref / m)`` (m): the best m_ref-experiment plan repeated."""
        if self.reference is None:
            return math.nan
        return self.reference.scores.max_rms_error_m * math.sqrt(self.reference.m / m)


def run_sweep(
    problem: Problem,
    criteria: Iterable[str],
    m_values: Iterable[int],
    settings: Settings,
    *,
    warm_start: bool = True,
    done: dict[tuple[str, int], Design] | None = None,
    executor: StartExecutor | None = None,
    progress: Callable[[int], object] | None = None,
    on_design: Callable[[Design], object] | None = None,
    approx: dict[tuple[str, int], ApproximateDesign] | None = None,
) -> Sweep:
    """The campaign of every (criterion, m), m ascending, with the warm starts; ``done``
    designs (a resumed sweep) are kept. ``on_design`` is called with each design as soon as it
    is solved (to save it); ``approx``: the approximate designs
    (:func:`casadi_design.execution.campaign.approximate`), computed when None."""
    criteria, ms = tuple(criteria), tuple(sorted(set(m_values)))
    check_m_values(problem, ms)

    def warm(c: str, m: int, designs: dict) -> list[tuple]:
        i = ms.index(m)
        return [(*warm_start_plan(problem, designs[c, ms[i - 1]], m), WARM_ORIGIN)] if warm_start and i else []

    campaign = run_campaign(problem, criteria, ms, settings, approx=approx, executor=executor,
                            done=done, extra_starts=warm, on_design=on_design, progress=progress)
    reference = campaign.designs.get(("test-pose", problem.m_min))
    if reference is None and "test-pose" in criteria:
        reference = run_campaign(problem, ("test-pose",), (problem.m_min,), settings, approx=campaign.approx,
                                 executor=executor, progress=progress).designs["test-pose", problem.m_min]
    return Sweep(ms, criteria, campaign.designs, settings.starts, warm_start, reference, campaign.approx,
                 settings.criterion_starts)


def sweep_total_starts(problem: Problem, criteria: Iterable[str], m_values: Iterable[int],
                       settings: Settings, warm_start: bool = True) -> int:
    """Number of IPOPT starts a sweep runs (for progress bars), reference design included."""
    criteria, ms = tuple(criteria), sorted(set(m_values))
    total = total_starts(criteria, ms, settings) + (len(ms) - 1) * len(criteria) * warm_start
    if "test-pose" in criteria and problem.m_min not in ms:
        total += total_starts(("test-pose",), (problem.m_min,), settings)
    return total


#: Columns of the sweep table (CSV and JSON), in order, with units: one per criterion (its
#: :attr:`~casadi_design.measures.criteria.Criterion.column`, mm for errors) after the repeat line.
COLUMNS = (
    "criterion", "m", CRITERIA["test-pose"].column, "repeat_best_single_pose_mm",
    *(c.column for c in CRITERIA.values() if c.name != "test-pose"),
    "O1", "O2", "O3", "O4", "O5", "identifiable", "status",
    "starts", "converged", "iterations", "wall_s", "warm_start_won", "seeded_best_max_error_mm",
    "starts_at_optimum", "bound", "gap_percent", "won_by",
)


def sweep_rows(sweep: Sweep) -> list[dict]:
    """One row per (criterion, m): the plan's measures and its solve statistics.

    Errors in mm; the other measures in the SI units of B (see :mod:`casadi_design.measures.measures`);
    ``bound`` in the units of the criterion's column.
    """
    rows = []
    for (c, m), d in sweep.designs.items():
        scores, crit = d.scores, CRITERIA[c]
        seeded = d.best_of_solve()
        rows.append({
            "criterion": c,
            "m": m,
            **{k.column: scores.value(k.name) * k.per_mm for k in CRITERIA.values()},
            "repeat_best_single_pose_mm": sweep.repeat_reference_m(m) * 1e3,
            **{k: scores.observability.get(k, math.nan) for k in ("O1", "O2", "O3", "O4", "O5")},
            "identifiable": scores.identifiable,
            "status": d.status,
            "starts": len(d.starts),
            "converged": d.converged_starts,
            "iterations": d.iterations,
            "wall_s": d.wall_s,
            "warm_start_won": sweep.warm_start_won(c, m),
            "seeded_best_max_error_mm": seeded.max_rms_error_m * 1e3 if seeded else math.nan,
            "starts_at_optimum": d.optimum_spread()["starts_at_optimum"],
            "bound": None if d.bound is None else d.bound.value * crit.per_mm,
            "gap_percent": None if d.bound is None else d.gap_percent,
            "won_by": "" if d.winner is None else d.winner.origin,
        })
    return rows


# --------------------------------------------------------------------------- files

#: Name of the file that keeps the finished designs of an unfinished sweep, and the files a
#: sweep resumes from (:func:`casadi_design.records.files.load_partial`: where their key is).
PARTIAL_NAME = "sweep.partial.json"
RESUME_KEYS = ((PARTIAL_NAME, ("key",)), ("sweep.json", ("sweep", "key")))
RESUME_FILES = tuple(name for name, _ in RESUME_KEYS)


def sweep_record(problem: Problem, sweep: Sweep, key: dict,
                 approx: dict[tuple[str, int], ApproximateDesign] | None = None) -> dict:
    """``sweep.json``: the results record of every design (and the approximate designs of
    the bounds) plus the sweep's table and settings (``key``: :func:`casadi_design.execution.campaign.campaign_key`)."""
    record = results_dict(problem, list(sweep.designs.values()), approx)
    record["sweep"] = {
        "key": key,
        "m": list(sweep.m_values),
        "criteria": list(sweep.criteria),
        "seeded_starts": sweep.seeded_starts,
        "criterion_starts": dict(sweep.criterion_starts),
        "warm_start": sweep.warm_start,
        "units": {"max_error_mm": "mm", "repeat_best_single_pose_mm": "mm",
                  "bound": "in the unit of the criterion's column: mm for test-pose and I (lower "
                           "bounds), log det M for D (upper), trace M^-1 for A (lower)",
                  "seeded_best_max_error_mm": "mm", "wall_s": "s",
                  "other measures": "SI units of B (lengths in m)"},
        "columns": list(COLUMNS),
        "rows": sweep_rows(sweep),
        "reference": None if sweep.reference is None else design_record(sweep.reference, problem),
    }
    return record


def sweep_from_record(record: dict) -> Sweep:
    """The :class:`Sweep` of a ``sweep.json`` record (for redrawing its figures)."""
    saved = record["sweep"]
    designs = {(d["criterion"], d["m"]): design_from_record(d) for d in record["designs"]}
    reference = None if saved["reference"] is None else design_from_record(saved["reference"])
    return Sweep(tuple(saved["m"]), tuple(saved["criteria"]), designs, saved["seeded_starts"], saved["warm_start"],
                 reference, criterion_starts=tuple(saved.get("criterion_starts", {}).items()))
