"""Simulated calibrations of a plan against the predicted accuracy (the package's docstring).

Every trial of a plan runs at once (CasADi functions mapped over the stacked trials, numpy for
the batched linear algebra). Plans with the same m share their true robots and noise draws
(common random numbers, generator ``default_rng([seed, m])``), which sharpens the comparison
between criteria.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import DesignError, ProblemError
from ..measures.measures import information_matrix, score_plan
from ..problem.build import Problem
from .compensate import compensate as _compensate  # the name `compensate` stays the module
from .identify import Identification, identify_nonlinear
from .simulate import (
    ErrorSpreads,
    Plan,
    draw_true_parameters,
    nominal_poses,
    simulate_measurements,
    true_values,
)
from .statistics import effective_dof, rms_interval


@dataclass(frozen=True, eq=False)
class PlanValidation:
    """Predicted and simulated accuracy of one plan at the s test poses.

    Attributes
    ----------
    predicted_rms_m : ndarray, shape (s,), m: ``sqrt(rho_j)``.
    empirical_rms_m : ndarray, shape (s,), m: RMS over the trials of the residual error.
    ci_low_m, ci_high_m : ndarray, shape (s,), m: ``CONFIDENCE`` interval of the true RMS.
    dof : ndarray, shape (s,): effective degrees of freedom of one squared error.
    identification : how X was identified, and its convergence.
    compensation_residual_m : float, m: largest miss of the target by the identified model.
    compensation_failed : int
        (trial, test pose) cases the identified model could not reach; left out of the RMS.
    wall_s : float, s.
    """

    plan: Plan
    predicted_rms_m: np.ndarray
    empirical_rms_m: np.ndarray
    ci_low_m: np.ndarray
    ci_high_m: np.ndarray
    dof: np.ndarray
    identification: Identification
    compensation_residual_m: float
    compensation_failed: int
    wall_s: float

    @property
    def ratio(self) -> np.ndarray:
        """Empirical over predicted RMS error at each test pose (1 where both are 0)."""
        return np.divide(self.empirical_rms_m, self.predicted_rms_m,
                         out=np.ones_like(self.predicted_rms_m), where=self.predicted_rms_m > 0)

    @property
    def worst_relative_error(self) -> float:
        """``max_j |empirical_j / predicted_j - 1|``."""
        return float(np.max(np.abs(self.ratio - 1)))

    @property
    def coverage(self) -> float:
        """Fraction of test poses whose interval holds the predicted ``sqrt(rho_j)``."""
        inside = (self.ci_low_m <= self.predicted_rms_m) & (self.predicted_rms_m <= self.ci_high_m)
        return float(np.mean(inside))

    @property
    def max_ratio(self) -> float:
        """Max over the path of the empirical RMS over max of ``sqrt(rho)``."""
        return float(np.max(self.empirical_rms_m) / np.max(self.predicted_rms_m))


@dataclass(frozen=True, eq=False)
class Validation:
    """A virtual calibration of every plan of a problem."""

    problem: Problem
    source: str
    trials: int
    seed: int
    spreads: ErrorSpreads
    plans: tuple[PlanValidation, ...]
    wall_s: float


def plan_rng(seed: int, m: int) -> np.random.Generator:
    """Generator of a plan's trials: depends on ``seed`` and ``m`` only (common random numbers)."""
    return np.random.default_rng([seed, m])


def _check_plan(problem: Problem, plan: Plan) -> None:
    model = problem.model
    if np.shape(plan.Q) != (plan.m, model.n) or np.shape(plan.F) != (plan.m, model.nF):
        raise ProblemError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: Q has shape "
            f"{np.shape(plan.Q)} and F {np.shape(plan.F)}, {problem.path} needs ({plan.m}, {model.n}) "
            f"and ({plan.m}, {model.nF}); give a plan of this problem"
        )


def simulate_plan(problem: Problem, plan: Plan, spreads: ErrorSpreads, trials: int,
                  rng: np.random.Generator) -> PlanValidation:
    """Simulate ``trials`` calibrations of ``plan`` and compare with ``sqrt(rho)`` (module doc).

    The empirical mean square at test pose j is ``mean_t |e_tj|^2`` (m^2) over the
    trials whose compensation converged there; its interval uses ``nu_j`` of
    ``C_j = sigma^2 B0_j M^-1 B0_j^T``.
    """
    t0 = time.perf_counter()
    _check_plan(problem, plan)
    model, tp, sigma = problem.model, problem.test_poses, problem.sigma_m
    s = tp.s
    B = model.B_stack(plan.Q, plan.F)
    B0 = problem.B0
    scores = score_plan(B, B0, sigma)
    if not scores.identifiable:
        raise DesignError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: its information "
            "matrix M is singular, the parameters cannot be identified; give a solved plan"
        )
    X_true = draw_true_parameters(model, spreads, trials, rng)
    ref, y = simulate_measurements(model, plan, X_true, sigma, spreads, rng)
    X_hat, ident = identify_nonlinear(model, plan.Q, plan.F, ref, y, sigma, jacobian="taylor")

    target = nominal_poses(model, tp.q, tp.F)
    qc, done, miss = _compensate(model, tp.q, tp.F, target, np.repeat(X_hat, s, axis=0), sigma)
    err = true_values(model.accuracy, spreads, qc, np.tile(tp.F, (trials, 1)),
                      np.repeat(X_true, s, axis=0), np.tile(target, (trials, 1)), where=done)
    done = done.reshape(trials, s)
    count = done.sum(axis=0)
    if not count.all():
        j = int(np.argmin(count))
        raise DesignError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: no simulated robot "
            f"could be compensated at test pose {j} (its target is out of the identified robots' "
            "reach); reduce the error spreads"
        )
    square = np.sum(err.reshape(trials, s, -1) ** 2, axis=2)
    mean_square = np.sum(np.where(done, square, 0.0), axis=0) / count

    C = sigma**2 * np.einsum("sil,lk,sjk->sij", B0, np.linalg.inv(information_matrix(B)), B0)
    dof = effective_dof(C)
    low, high = rms_interval(mean_square, dof, count)
    return PlanValidation(plan, scores.rms_error_m, np.sqrt(mean_square), low, high, dof, ident, miss,
                          int(done.size - count.sum()), time.perf_counter() - t0)


def check_trials(trials: int) -> None:
    if trials < 2:
        raise ProblemError(f"virtual calibration: trials = {trials}; give at least 2 (e.g. 2000)")


def validate(problem: Problem, plans: list[Plan], trials: int = 2000, seed: int = 0,
             spreads: ErrorSpreads = ErrorSpreads(), source: str = "") -> Validation:
    """Virtual calibration of each plan: ``trials`` simulated calibrations (module doc).

    Raises
    ------
    ProblemError
        When ``trials`` is below 2 or a plan does not fit the problem.
    DesignError
        When a plan is singular, or the deflection or the compensation of the simulated robots
        does not converge.
    """
    check_trials(trials)
    t0 = time.perf_counter()
    results = tuple(simulate_plan(problem, p, spreads, trials, plan_rng(seed, p.m)) for p in plans)
    return Validation(problem, source, trials, seed, spreads, results, time.perf_counter() - t0)


def linearisation_study(problem: Problem, plans: list[Plan], scales: list[float], trials: int,
                        seed: int = 0, spreads: ErrorSpreads = ErrorSpreads(),
                        source: str = "") -> list[tuple[float, Validation]]:
    """Where the linearised prediction breaks down: validate with every spread times ``scale``.

    The ratio of simulated to predicted error stays near 1 while the true robots are close to
    the nominal one (B evaluated at ``X = 0`` still describes them) and drifts as they move away.
    """
    return [(scale, validate(problem, plans, trials, seed, spreads.scaled(scale), source)) for scale in scales]
