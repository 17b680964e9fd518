"""Simulated calibrations of a plan of configurations seated at an artefact's points.

A trial draws a true robot ``X*`` (:func:`~.simulate.draw_true_parameters`) and records the
plan as a user does: each configuration hand-guided until the true robot's ball sits in its
socket within the seating repeatability,

    p(q_i*, X*) = c_i + e_i,    e_i ~ N(0, sigma^2 I_3),

from the planned ``q_i`` (Newton steps of least norm in q: the hand moves the joints least);
``c_i`` is the point ``t_g + R_g a_k`` of the placement the nominal robot's plan puts the
ball at (:meth:`~casadi_design.calibration.artefact.Artefact.placed`, as the pool engine's).
The recordings ``q_i*`` are identified by identify's own fit
(:func:`~casadi_design.identification.artefact_fit.fit_artefact`: X, the base set the plan
tells, and every placement's pose), and the test poses' error is the one a user sees after
registering the work by the calibrated robot: ``p(q0_j, X^) - p(q0_j, X*)`` with the test
points' rigid motion projected out (:func:`~casadi_design.calibration.artefact.registered`'s
:func:`~casadi_design.calibration.artefact.projected_out`). Its RMS over the trials is compared
with the predicted ``sqrt(rho_j)`` of the plan's rows
(:func:`~casadi_design.optimisation.artefact_pool.artefact_pool`).
"""

from __future__ import annotations

import time

import numpy as np

from ..calibration.artefact import projected_out, rigid_columns
from ..errors import DesignError
from ..identification.artefact_fit import ball_points, fit_artefact
from ..identification.fit import fit_model, model_points
from ..identification.lsq import Identification
from ..identification.recordings import Recordings
from ..measures.measures import information_matrix
from ..optimisation.artefact_pool import artefact_pool, artefact_scores
from ..plan.design import Design
from ..problem.build import Problem
from ..robot.robots import frame_jacobian
from .simulate import ErrorSpreads, Plan, draw_true_parameters
from .statistics import effective_dof, rms_interval
from .validation import PlanValidation, Validation, plan_rng

#: Newton steps of a simulated recording (the seating equation to a nanometre: 3 at most for
#: errors of a few mm).
SEATING_STEPS = 8
SEATING_TOL_M = 1e-9


def seated_recordings(problem: Problem, Q: np.ndarray, X: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The configurations (N, n), rad, of robots ``X`` (N, L) with their measured point at
    ``target`` (N, 3), m, each from ``Q`` (N, n) by Newton steps of least norm in q
    (:data:`SEATING_STEPS`; the nominal robot's Jacobian).

    Raises
    ------
    DesignError
        A recording whose point stays farther than :data:`SEATING_TOL_M` from its target.
    """
    model, robot = problem.model, problem.robot
    F = np.zeros((len(Q), model.nF))
    Q = np.array(Q, dtype=float)
    for _ in range(SEATING_STEPS):
        r = target - model_points(model, Q, F, X)[:, 0]
        if np.max(np.linalg.norm(r, axis=1)) < SEATING_TOL_M:
            return Q
        Q += np.stack([np.linalg.lstsq(frame_jacobian(robot, q)[:3], e, rcond=None)[0] for q, e in zip(Q, r)])
    worst = float(np.max(np.linalg.norm(target - model_points(model, Q, F, X)[:, 0], axis=1)))
    if worst > SEATING_TOL_M:
        raise DesignError(f"virtual calibration: a simulated robot's ball stays {worst * 1e3:.3g} mm from its socket "
                          f"after {SEATING_STEPS} steps; lower the error spreads (--length-mm, --angle-deg)")
    return Q


def simulate_artefact_plan(problem: Problem, plan: Plan, point: np.ndarray, placement: np.ndarray,
                           spreads: ErrorSpreads, trials: int, rng: np.random.Generator) -> PlanValidation:
    """Simulate ``trials`` calibrations of ``plan`` (its configurations seated at ``point`` of
    ``placement``, (m,)) and compare with ``sqrt(rho)`` (module docstring).

    Raises
    ------
    DesignError
        A plan whose rows do not identify X with the placements unknown.
    """
    t0 = time.perf_counter()
    model, A, sigma, tp = problem.model, problem.artefact, problem.sigma_m, problem.test_poses
    m, s = plan.m, tp.s
    pool = artefact_pool(problem, plan.Q, point, placement)
    scores = artefact_scores(problem, plan.Q, point, placement)
    if not scores.identifiable:
        raise DesignError(f"virtual calibration of the {plan.criterion} plan, m = {m}: its configurations do not "
                          "identify the parameters with the placements unknown; give a solved plan")
    at = np.searchsorted(np.unique(placement), placement)
    R, t = A.placed(ball_points(model, plan.Q, np.zeros(model.L))[0], point, at)
    sockets = t[at] + np.einsum("kab,kb->ka", R[at], A.points_m[point])
    X_true = draw_true_parameters(model, spreads, trials, rng)
    target = sockets[None] + sigma * rng.standard_normal((trials, m, 3))
    Qr = seated_recordings(problem, np.tile(plan.Q, (trials, 1)), np.repeat(X_true, m, axis=0),
                           target.reshape(-1, 3)).reshape(trials, m, -1)
    fm = fit_model(problem, "base", pool.names)
    columns = [model.parameter_names.index(n) for n in fm.model.parameter_names]
    X_hat, evaluations, failed = np.zeros_like(X_true), 0, 0
    names = tuple(str(g) for g in range(int(at.max()) + 1))
    for i in range(trials):
        rec = Recordings(Qr[i], np.asarray(point), at, names, tuple(f"row {j + 1}" for j in range(m)))
        try:
            f = fit_artefact(problem, fm, rec)
        except DesignError:
            failed += 1
            X_hat[i] = np.nan
            continue
        X_hat[i, columns], evaluations = f.X, max(evaluations, f.evaluations)
    done = np.all(np.isfinite(X_hat), axis=1)
    if not done.any():
        raise DesignError(f"virtual calibration of the {plan.criterion} plan, m = {m}: no simulated recording was "
                          "identified; lower the error spreads")
    F0 = np.zeros((s * int(done.sum()), model.nF))
    q0 = np.tile(tp.q, (int(done.sum()), 1))
    e = (model_points(model, q0, F0, np.repeat(X_hat[done], s, axis=0))[:, 0]
         - model_points(model, q0, F0, np.repeat(X_true[done], s, axis=0))[:, 0]).reshape(-1, s, 3)
    p0 = tp.position_m
    e = np.stack([projected_out(ei[:, :, None], rigid_columns(p0))[:, :, 0] for ei in e])
    mean_square = np.mean(np.sum(e**2, axis=2), axis=0)
    C = sigma**2 * np.einsum("sil,lk,sjk->sij", pool.B0, np.linalg.inv(information_matrix(pool.B)), pool.B0)
    dof = effective_dof(C)
    low, high = rms_interval(mean_square, dof, int(done.sum()))
    ident = Identification("identify's artefact fit (X and the placements' poses)", evaluations, failed)
    return PlanValidation(plan, scores.rms_error_m, np.sqrt(mean_square), low, high, dof, ident, 0.0, 0,
                          time.perf_counter() - t0)


def validate_artefact(problem: Problem, designs: list[Design], trials: int, seed: int,
                      spreads: ErrorSpreads, source: str) -> Validation:
    """Virtual calibration of each design's plan (its configurations and their
    :attr:`~casadi_design.plan.design.Design.seated`): :func:`simulate_artefact_plan` with the
    generator of its m (common random numbers, :func:`~.validation.plan_rng`)."""
    t0 = time.perf_counter()
    results = tuple(simulate_artefact_plan(problem, Plan(d.criterion, d.m, d.Q, d.F), d.seated.point,
                                           d.seated.placement, spreads, trials, plan_rng(seed, d.m))
                    for d in designs)
    return Validation(problem, source, trials, seed, spreads, results, time.perf_counter() - t0)
