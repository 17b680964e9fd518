"""The design criteria: one registry entry each, the only place a criterion is described.

For a plan with information matrix ``M = sum_i B_i^T B_i`` (``cov(X) = sigma^2 M^-1``) and the
test-pose measure ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)`` (m^2, paper eq. 12):

* test-pose (paper eq. 15): minimise ``max_j rho_j`` (score: ``max_j sqrt(rho_j)``, m);
* D: maximise ``log det M``; A: minimise ``trace M^-1``; E (the paper's "SVD approach"):
  maximise ``s_L``, the smallest singular value of the stacked B; T: maximise ``trace M``;
  condition: minimise ``s_1 / s_L``;
* I: minimise the *mean* of ``rho_j`` over the test poses, the average accuracy along the
  path (score: ``sqrt(mean_j rho_j)``, m, the RMS error over the test poses).

An entry holds everything the package does with its criterion: the sense and the score (a
function of the plan's spectrum and rho), its names, labels, column and line style, a fixed
seed id (adding a criterion never changes the starts of another), its reduced-space objective
(:mod:`casadi_design.measures.objectives`: value, gradient, curvature, or epigraph rows) and, when it
has one, its bound form (:mod:`casadi_design.optimisation.bound`). The scores, the results' fields, the
tables, the sweep columns and the command-line choices are all generated from here.

E and condition are not smooth in the plan (a repeated eigenvalue at the optimum): they are
solved through the log power means of the eigenvalues of M for the rising powers r of
``powers``, each run starting where the last stopped; their scores stay the exact ``s_L`` and
``s_1 / s_L``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .objectives import (
    EpigraphRows,
    LogDet,
    MeanTestPose,
    Objective,
    SpectralSurrogate,
    Trace,
    TraceInverse,
)

#: Relative tolerance within which two starts count as reaching the same optimum (on the
#: criterion's value; for D on det M, i.e. absolute on log det M).
SAME_OPTIMUM_RTOL = 1e-6
#: Powers r of the surrogates of E and condition: ``l_{-r}`` is within ``log(L) / r`` of
#: ``log lambda_min``.
SURROGATE_POWERS = (4.0, 16.0, 64.0, 256.0)


class PlanSpectrum(NamedTuple):
    """What the scores are computed from: the eigenvalues ``lam`` of M (descending, >= 0),
    the singular values ``sv = sqrt(lam)`` of the stacked B, ``rho`` (s,), m^2 (inf when M
    is singular), ``trace_M``, whether M is regular, ``log_det = log det M`` and ``trace_inv =
    tr M^-1`` (for a regular M). A criterion's score reads only the fields its
    :attr:`Criterion.reads` names: the pool engine (:mod:`casadi_design.optimisation.engine`)
    fills only those, from low-rank updates, the others None."""

    lam: np.ndarray | None
    sv: np.ndarray | None
    rho: np.ndarray | None
    trace_M: float | None
    identifiable: bool
    log_det: float | None = None
    trace_inv: float | None = None


@dataclass(frozen=True)
class BoundForm:
    """How a criterion is bounded from the approximate design (:mod:`casadi_design.optimisation.bound`).

    Attributes
    ----------
    rows : ``B0 (s, r, L) -> Hj (k, L, L)``: the matrices of the trace form
        ``t* = min_W max_k tr(Hj_k W^-1)`` (a lower bound: :func:`bound_trace`); None for the
        log-det form (D: an upper bound).
    score : ``(constant, m, sigma_m, L) -> bound of the score`` for m experiments.
    meaning : what ``bound.value`` of a results record bounds, with units.
    moves : exchange steps between two moves of the heavy support points
        (:func:`casadi_design.optimisation.approximate._moved`); 0: the support moves only through the maxima of
        d. On the UR10 cell (README, Speed), moves every 6 steps narrow the test-pose
        certificate's gap from 0.58 % to 0.05 % for 1.17x the time (ABB: 0.85 % to 0.02 %,
        1.42x), so test-pose has 6. For D they tighten the bound by only 0.008 in log det at
        m = 9 and change its rounded starts, and the study's D plan at m = 9 is worse with
        them, so D has none; A's support is spread (77 to 105 points carry 95 % of the weight)
        and its moves take 1.7x the time for no better bound, so A and I (not measured) have
        none either.
    """

    rows: Callable[[np.ndarray], np.ndarray] | None
    score: Callable[[float, int, float, int], float]
    meaning: str
    moves: int = 0

    @property
    def log_det(self) -> bool:
        return self.rows is None

    def gap_percent(self, bound_value: float, achieved: float, L: int) -> float:
        """How far a plan's score ``achieved`` is from the bound, %: the excess of the score
        over its lower bound; for the log-det form, of ``det M^(-1/L)``."""
        if self.log_det:
            return float(100.0 * np.expm1((bound_value - achieved) / L))
        return float(100.0 * (achieved / bound_value - 1.0))


def _outer(B0: np.ndarray) -> np.ndarray:
    """``B0_j^T B0_j`` per test pose, shape (s, L, L)."""
    return np.einsum("jri,jrl->jil", B0, B0)


def _rms_bound(t: float, m: int, sigma: float, L: int) -> float:
    return float(np.sqrt(sigma**2 * t / m))


@dataclass(frozen=True, eq=False)
class Criterion:
    """One design criterion (module docstring).

    Attributes
    ----------
    name : the name used in problem files, options and results.
    sense : "min" or "max", the better direction of the score.
    score : the key of its value in :class:`~casadi_design.measures.measures.Scores` and results files.
    score_of : ``PlanSpectrum -> score`` (SI units of B; errors in m), of one plan or of many
        at once (the spectrum's fields with a leading axis of plans: the pool engine's).
    label : description for figures, with units.
    legend : name in figure legends.
    style : matplotlib line style of its curves.
    seed_id : third entry of the seed of its starts (fixed forever).
    objective : its part of the reduced-space NLP.
    column : its column in sweep tables (``_mm``: the score in mm).
    row : its row label in the measure tables of ``evaluate``.
    per_mm : factor from the score to the tables' unit (1e3 for errors in m, else 1).
    fmt : format of the tables' numbers.
    polished : nearly singular starts first get a few D-optimal iterations (see solve.py).
    log_value : the value is a logarithm (same optimum: absolute tolerance on it).
    powers : the powers r of the surrogate of a non-smooth criterion, one NLP run each.
    bound : its bound form, None if it has none.
    rounded_from : a criterion with a bound whose approximate design rounds this one's starts,
        for a criterion without a bound of its own (E and condition: A's, whose plans the
        A-optimal support spreads over every direction of M; on the ABB study the rounded A
        plans end at a condition number 6 % below the best of 16 seeded starts at m = 8, and
        improve E at m = 8 and the UR10's condition number at m = 12; D's do not); None: its
        own approximate design, or none.
    reads : what of the plan its score reads (a field of :class:`PlanSpectrum`): ``rho``,
        ``log_det``, ``trace_inv``, ``trace_M`` or ``lam`` (the spectrum: E and condition).
    smoothed : ``(PlanSpectrum, p) -> `` a smooth surrogate of a max score whose limit for p ->
        infinity is the score (test-pose: the p-mean of rho, :func:`_p_mean_rms`), or None. The
        pool's exchange climbs it before the score itself: a swap that lowers one of several
        test poses at the max does not lower the max, and the exchange would stop there.
    rounded : starts rounded from that approximate design per design
        (:func:`casadi_design.optimisation.approximate.rounded_plans`: the apportioned support, then jittered
        copies; the first four the same whatever the count). Of 12 on the UR10 study, the best
        is the 8th (test-pose, m = 9), 6th (test-pose, m = 12), 6th (D, m = 9: 0.3 higher in
        log det than the best of the first 4) and 4th (A, m = 9). D's and A's rounded starts
        cost what a seeded one does (50 to 250 IPOPT iterations), so D and A have 8;
        test-pose's from m = 12 on cost 3 to 10 seeded ones (1000 to 2800 iterations, some
        stall), and 8 make the UR10 sweep 1.4x slower, so the others have 4.
    """

    name: str
    sense: str
    score: str
    score_of: Callable[[PlanSpectrum], np.ndarray]
    label: str
    legend: str
    style: dict
    seed_id: int
    objective: Objective
    column: str
    row: str
    reads: str
    per_mm: float = 1.0
    fmt: str = ".6g"
    polished: bool = False
    log_value: bool = False
    powers: tuple[float, ...] = ()
    bound: BoundForm | None = None
    rounded_from: str | None = None
    rounded: int = 4
    smoothed: Callable[[PlanSpectrum, float], np.ndarray] | None = None

    @property
    def approximate(self) -> str | None:
        """The criterion whose approximate design rounds this one's starts: its own when it has a
        bound, ``rounded_from`` otherwise (None: no rounded starts)."""
        return self.name if self.bound is not None else self.rounded_from

    def better(self, a: float, b: float) -> bool:
        """Whether value ``a`` is strictly better than ``b``."""
        return a < b if self.sense == "min" else a > b

    def same_optimum(self, value: float, best: float) -> bool:
        """Whether ``value`` reaches the optimum ``best`` within ``SAME_OPTIMUM_RTOL`` relative."""
        scale = 1.0 if self.log_value else abs(best)
        return abs(value - best) <= SAME_OPTIMUM_RTOL * scale

    def worst(self, values: list[float]) -> float:
        """The worst of ``values`` in the criterion's sense."""
        return max(values) if self.sense == "min" else min(values)


def _p_mean_rms(rho: np.ndarray, p: float) -> np.ndarray:
    """``sqrt((mean_j rho_j^p)^(1/p))`` over the last axis (m for rho in m^2): I's score at p =
    1, the test-pose score as p -> infinity (computed relative to the largest rho)."""
    top = np.max(rho, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(top[..., 0] * np.mean((rho / top) ** p, axis=-1) ** (1.0 / p))


def _regular(value: Callable[[PlanSpectrum], np.ndarray], singular: float) -> Callable[[PlanSpectrum], np.ndarray]:
    """A score defined for a regular M, ``singular`` otherwise."""
    def score(sp: PlanSpectrum) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(sp.identifiable, value(sp), singular)
    return score


CRITERIA: dict[str, Criterion] = {
    c.name: c
    for c in (
        Criterion("test-pose", "min", "max_rms_error_m", lambda sp: np.max(np.sqrt(sp.rho), axis=-1),
                  "max over test poses of sqrt(rho) (m)", "Test-pose approach",
                  {"color": "tab:red", "ls": "-", "lw": 2.0}, 0, EpigraphRows(),
                  "max_error_mm", "max over test poses of sqrt(rho), mm", "rho", 1e3, ".4f",
                  bound=BoundForm(_outer, _rms_bound,
                                  "lower bound of max_rms_error_m (m) of any plan of m experiments", moves=6),
                  smoothed=lambda sp, p: _p_mean_rms(sp.rho, p)),
        Criterion("D", "max", "log_det_M", _regular(lambda sp: sp.log_det, -np.inf),
                  "log det M (D-optimality)", "D-optimality",
                  {"color": "tab:blue", "ls": "--", "lw": 1.5}, 1, LogDet(),
                  "log_det_M", "D: log det M", "log_det", log_value=True,
                  bound=BoundForm(None, lambda c, m, sigma, L: L * np.log(m) + c,
                                  "upper bound of log_det_M of any plan of m experiments"), rounded=8),
        Criterion("A", "min", "trace_M_inv", _regular(lambda sp: sp.trace_inv, np.inf),
                  "trace M^-1 (A-optimality)", "A-optimality",
                  {"color": "tab:green", "ls": "-.", "lw": 1.5}, 2, TraceInverse(),
                  "trace_M_inv", "A: trace M^-1", "trace_inv",
                  bound=BoundForm(lambda B0: _outer(np.eye(B0.shape[2])[None]),
                                  lambda c, m, sigma, L: c / m,
                                  "lower bound of trace_M_inv of any plan of m experiments"), rounded=8),
        Criterion("E", "max", "s_min", lambda sp: sp.sv[..., -1],
                  "smallest singular value s_L (E-optimality, SVD approach)", "SVD approach (E-optimality)",
                  {"color": "tab:purple", "ls": ":", "lw": 2.0}, 3,
                  SpectralSurrogate(terms=((-1.0, -1.0),)), "s_min", "E: smallest singular value s_L", "lam",
                  polished=True, powers=SURROGATE_POWERS, rounded_from="A"),
        Criterion("T", "max", "trace_M", lambda sp: sp.trace_M, "trace M (T-optimality)", "T-optimality",
                  {"color": "tab:brown", "ls": (0, (5, 1, 1, 1)), "lw": 1.5}, 4, Trace(),
                  "trace_M", "T: trace M", "trace_M"),
        Criterion("condition", "min", "condition", _regular(lambda sp: sp.sv[..., 0] / sp.sv[..., -1], np.inf),
                  "condition number s_1/s_L", "Condition number",
                  {"color": "tab:gray", "ls": (0, (3, 1)), "lw": 1.5}, 5,
                  SpectralSurrogate(terms=((1.0, 1.0), (-1.0, -1.0))), "condition",
                  "condition number s_1/s_L", "lam", polished=True, powers=SURROGATE_POWERS, rounded_from="A"),
        Criterion("I", "min", "rms_over_test_poses_m", lambda sp: np.sqrt(np.mean(sp.rho, axis=-1)),
                  "RMS over test poses of the error, sqrt(mean rho) (m)", "I-optimality (mean rho)",
                  {"color": "tab:orange", "ls": (0, (1, 1)), "lw": 2.0}, 6, MeanTestPose(),
                  "rms_over_test_poses_mm", "I: sqrt(mean over test poses of rho), mm", "rho", 1e3, ".4f",
                  bound=BoundForm(lambda B0: _outer(B0).mean(axis=0)[None], _rms_bound,
                                  "lower bound of rms_over_test_poses_m (m) of any plan of m experiments")),
    )
}

#: The criteria that have a bound (and an approximate design), in registry order.
BOUND_CRITERIA = tuple(name for name, c in CRITERIA.items() if c.bound is not None)
