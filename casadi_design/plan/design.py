"""What a design is: the records of a multi-start solve, as plain data.

A plan of m experiments is always stored with one experiment per row: ``Q`` of shape (m, n),
rad (m for prismatic joints), and ``F`` of shape (m, nF), N (N m for moments). The NLP's
variables, the rules, the exports and the simulation all take and give plans in this layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..measures.criteria import CRITERIA
from ..measures.measures import Scores

if TYPE_CHECKING:
    from ..cell.cell import Clearance

#: Status of a start of a plan chosen from a pool whose exchange ended: no swap improves it
#: (:mod:`casadi_design.optimisation.pool`).
EXCHANGE_ENDED = "Exchange_Ended"
#: IPOPT return statuses accepted as converged, and the pool exchange's end.
CONVERGED = ("Solve_Succeeded", "Solved_To_Acceptable_Level", EXCHANGE_ENDED)
#: ``StartRecord.origin`` of the seeded random starts.
SEEDED = "seeded"
#: ``StartRecord.origin`` of the warm start of a sweep (:mod:`casadi_design.execution.sweep`).
WARM_ORIGIN = "warm start"


@dataclass(frozen=True)
class StartRecord:
    """One start: its status, iterations, criterion score and test-pose error (m), and
    where its start plan came from (``origin``: "seeded", or the label of an initial plan, e.g.
    "warm start" or "rounded approximate design"); with a cell, its IPOPT ``runs`` and the
    capsule rows its last run held (``rows_held``, of m times the rows of one experiment;
    :mod:`casadi_design.optimisation.solve`). A start of a plan chosen from a pool
    (status :data:`EXCHANGE_ENDED`) counts the exchange's passes over the plan's positions as
    ``iterations`` and its ``swaps``."""

    status: str
    iterations: int
    value: float
    max_rms_error_m: float
    feasible: bool
    origin: str = SEEDED
    runs: int = 1
    rows_held: int = 0
    swaps: int = 0

    @property
    def converged(self) -> bool:
        return self.status in CONVERGED and self.feasible


@dataclass(frozen=True)
class Bound:
    """The bound of one criterion for m experiments, in the units of its score
    (:class:`casadi_design.measures.measures.Scores`; :mod:`casadi_design.optimisation.bound`).

    ``value``: a lower bound of the score (test-pose, A, I) or an upper bound (D).
    ``relaxation``: the same quantity from the relaxation's value on the pool (not certified).
    ``L``: number of parameters.
    """

    criterion: str
    m: int
    value: float
    relaxation: float
    L: int

    def gap_percent(self, achieved: float) -> float:
        """How far a plan's score ``achieved`` is from the bound, %
        (:meth:`casadi_design.measures.criteria.BoundForm.gap_percent`)."""
        return CRITERIA[self.criterion].bound.gap_percent(self.value, achieved, self.L)


@dataclass(frozen=True, eq=False)
class Seating:
    """Where each experiment of a plan of an artefact's points seats the ball
    (:mod:`casadi_design.calibration.artefact`): its ``point`` (m,) of the artefact and its
    ``placement`` (m,), an index into ``names`` (the placements' names)."""

    point: np.ndarray
    placement: np.ndarray
    names: tuple[str, ...]

    def as_records(self) -> list[dict]:
        """Each experiment's ``{"point": k, "placement": name}``."""
        return [{"point": int(k), "placement": self.names[g]} for k, g in zip(self.point, self.placement)]


@dataclass(frozen=True, eq=False)
class Design:
    """The best plan found for one criterion and number of experiments.

    Attributes
    ----------
    Q : ndarray, shape (m, n), rad
    F : ndarray, shape (m, nF), N (N m)
    scores : every measure of the plan.
    status : IPOPT status of the winning start.
    starts : every start, in the order run.
    wall_s : wall time of the multi-start solve, s: from its first start sent until it is
        judged (on workers, the starts of other designs run in between).
    seed : ``[solver].seed`` of the problem the starts were drawn with.
    bound : the certified bound of the criterion for m experiments, when it was computed.
    clearances : with a ``[cell]``, each experiment's clearance on the real geometry
        (:func:`casadi_design.cell.cell.clearances`), else None.
    kept_starts : how many of ``starts`` were read back from the disk, computed by an earlier
        run (:func:`casadi_design.optimisation.solve.solve_start`; not in results files).
    seated : for a problem measured at an artefact's points, the point and placement of each
        experiment (:class:`Seating`), else None.
    """

    criterion: str
    m: int
    Q: np.ndarray
    F: np.ndarray
    scores: Scores
    status: str
    starts: tuple[StartRecord, ...]
    wall_s: float
    seed: int
    bound: Bound | None = None
    clearances: tuple[Clearance, ...] | None = None
    kept_starts: int = 0
    seated: Seating | None = None

    @property
    def gap_percent(self) -> float | None:
        """How far the plan is from its bound, % (None without a bound)."""
        return None if self.bound is None else self.bound.gap_percent(self.scores.value(self.criterion))

    @property
    def converged_starts(self) -> int:
        return sum(st.converged for st in self.starts)

    @property
    def iterations(self) -> int:
        """IPOPT iterations of the starts that ran IPOPT."""
        return sum(st.iterations for st in self.starts if st.status != EXCHANGE_ENDED)

    @property
    def exchange(self) -> tuple[int, int, int]:
        """The starts exchanged over a pool, their passes and their swaps (zeros: none)."""
        ex = [st for st in self.starts if st.status == EXCHANGE_ENDED]
        return len(ex), sum(st.iterations for st in ex), sum(st.swaps for st in ex)

    @property
    def winner(self) -> StartRecord | None:
        """The start whose plan this is: the first to reach the best value (a later start wins
        only when strictly better); None for a design read without its starts' values."""
        best = self.scores.value(self.criterion)
        return next((st for st in self.starts if st.converged and st.value == best), None)

    def optimum_spread(self) -> dict:
        """Test-pose errors (m) of every converged start that reached the design's optimum.

        Optimal plans need not be unique; when the criterion is not the test-pose measure,
        equally optimal plans may give different accuracy. ``min``/``max`` over those starts.
        """
        crit = CRITERIA[self.criterion]
        best = self.scores.value(self.criterion)
        tied = [st.max_rms_error_m for st in self.starts
                if st.converged and crit.same_optimum(st.value, best)]
        return {"starts_at_optimum": len(tied), "min_max_rms_error_m": min(tied),
                "max_max_rms_error_m": max(tied)}

    def best_of_solve(self) -> StartRecord | None:
        """The record that wins among the starts a solve runs too (the seeded and the rounded
        ones: all but a sweep's :data:`WARM_ORIGIN`), by the rule of the multi-start."""
        crit, best = CRITERIA[self.criterion], None
        for rec in self.starts:
            if rec.origin != WARM_ORIGIN and rec.converged and (best is None or crit.better(rec.value, best.value)):
                best = rec
        return best
