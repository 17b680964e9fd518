"""Test oracle: the symbolic formulation of every criterion (one CasADi graph of M).

The product solves the criteria in the reduced space (:mod:`casadi_design.optimisation.reduced`); here they
are posed as one symbolic CasADi graph with CasADi's own exact derivatives, to check the
reduced space's values and derivatives, and E and condition exactly (without surrogate) with
semidefinite constraints written as Cholesky-factor equalities: ``M - lam I = C C^T`` (C lower
triangular, free) holds iff ``M - lam I`` is positive semidefinite, so ``max lam`` gives
``lam = lambda_min(M)``. Their graph grows as L^4: small cases only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from casadi_design.optimisation import nlp as nlp_module
from casadi_design.optimisation.nlp import DesignNLP, information_scale
from casadi_design.plan.rules import joint_distance_sq
from casadi_design.problem.build import Problem


@dataclass(frozen=True, eq=False)
class Objective:
    """A criterion's part of the NLP: ``f`` to minimise, auxiliary variables ``w``, constraints."""

    f: ca.SX
    w: ca.SX
    lbw: np.ndarray
    ubw: np.ndarray
    g: ca.SX
    lbg: np.ndarray
    ubg: np.ndarray
    init: Callable[[np.ndarray], np.ndarray]  # M at the start point -> w0


def _lower(C: ca.SX) -> ca.SX:
    """Entries of the lower triangle of a square matrix, column by column."""
    n = C.shape[0]
    return ca.vertcat(*[C[i, j] for j in range(n) for i in range(j, n)])


def _psd_factor(name: str, S: ca.SX) -> tuple[ca.SX, ca.SX, Callable[[np.ndarray], np.ndarray]]:
    """Variables ``C`` (lower triangular) and equalities ``lower(S - C C^T) = 0``: S is PSD.

    Returns the variables, the equality constraints and ``init(S0) -> C0`` (Cholesky of S0).
    """
    L = S.shape[0]
    c = ca.SX.sym(name, L * (L + 1) // 2)
    C = ca.SX.zeros(L, L)
    k = 0
    for j in range(L):
        for i in range(j, L):
            C[i, j] = c[k]
            k += 1

    def init(S0: np.ndarray) -> np.ndarray:
        C0 = np.linalg.cholesky(S0 + 1e-12 * np.trace(S0) * np.eye(L))
        return np.array([C0[i, j] for j in range(L) for i in range(j, L)])

    return c, _lower(S - C @ C.T), init


def e_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``max lam`` s.t. ``M - lam I = C C^T``: lam = lambda_min(M) = s_L^2."""
    L = M.shape[0]
    lam = ca.SX.sym("lam")
    c, g, init_c = _psd_factor("C", M - lam * ca.SX.eye(L))

    def init(M0: np.ndarray) -> np.ndarray:
        lam0 = 0.5 * np.linalg.eigvalsh(M0)[0]
        return np.concatenate([[lam0], init_c(M0 - lam0 * np.eye(L))])

    n = c.numel()
    return Objective(-lam, ca.vertcat(lam, c), np.r_[0.0, np.full(n, -np.inf)], np.full(n + 1, np.inf),
                     g, np.zeros(n), np.zeros(n), init)


def condition_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min kappa`` s.t. ``lam I <= M <= kappa lam I``: kappa = lambda_max / lambda_min = (s_1/s_L)^2."""
    L = M.shape[0]
    lam, kappa = ca.SX.sym("lam"), ca.SX.sym("kappa")
    c1, g1, init1 = _psd_factor("C1", M - lam * ca.SX.eye(L))
    c2, g2, init2 = _psd_factor("C2", kappa * lam * ca.SX.eye(L) - M)

    def init(M0: np.ndarray) -> np.ndarray:
        eig = np.linalg.eigvalsh(M0)
        lam0, k0 = 0.5 * eig[0], 2.0 * eig[-1] / (0.5 * eig[0])
        return np.concatenate([[lam0, k0], init1(M0 - lam0 * np.eye(L)), init2(k0 * lam0 * np.eye(L) - M0)])

    n = c1.numel()
    return Objective(kappa, ca.vertcat(lam, kappa, c1, c2),
                     np.r_[1e-12, 1.0, np.full(2 * n, -np.inf)], np.full(2 * n + 2, np.inf),
                     ca.vertcat(g1, g2), np.zeros(2 * n), np.zeros(2 * n), init)


def lifted_nlp(problem: Problem, criterion: str,
               objective: Callable[[ca.SX, np.ndarray], Objective], m: int,
               B0: np.ndarray) -> DesignNLP:
    """The NLP as one symbolic CasADi graph of ``M = scale sum_i B_i^T B_i`` and ``objective``
    (its exact Hessian from CasADi)."""
    model, robot = problem.model, problem.robot
    loads = problem.rules.loads
    Q = ca.SX.sym("Q", robot.n, m)
    V = ca.SX.sym("V", loads.nv, m)
    F = ca.horzcat(*[loads.load(V[:, i]) for i in range(m)])
    scale = information_scale(model.L, B0)
    M = ca.SX.zeros(model.L, model.L)
    for i in range(m):
        Bi = model.B(Q[:, i], F[:, i])
        M += scale * (Bi.T @ Bi)
    obj = objective(M, np.sqrt(scale) * B0)

    rules = problem.rules.pose
    g = [obj.g, ca.sum1(V**2).T if loads.norm_lb is not None else ca.SX(0, 1)]
    if rules.collision is None:
        g += [rules.g(Q[:, i]) for i in range(m)]
    else:  # the capsule rows come after the other rows of every experiment
        held = rules.collision.first
        g += [rules.g(Q[:, i])[:held] for i in range(m)] + [rules.g(Q[:, i])[held:] for i in range(m)]
    if problem.workspace.min_joint_distance_rad > 0:
        limits = problem.rules.limits
        g += [joint_distance_sq(limits, Q[:, i], Q[:, j]) for i in range(m) for j in range(i + 1, m)]
    lb_rules, ub_rules = nlp_module.rule_bounds(problem, m, loads)
    lb_plan, ub_plan = nlp_module.plan_bounds(problem, m, loads)

    x = ca.vertcat(ca.vec(Q), ca.vec(V), obj.w)
    oracle = ca.Function("nlp", [x, ca.SX(0, 1)], [obj.f, ca.vertcat(*g)], ["x", "p"],
                         ["f", "g"])
    plan = ca.Function("plan", [x], [Q.T, F.T], ["x"], ["Q", "F"])  # one experiment per row
    information = ca.Function("M", [x], [M], ["x"], ["M"])
    n_aux = obj.w.numel()

    def start(Q0: np.ndarray, F0: np.ndarray) -> np.ndarray:
        x_plan = np.concatenate([np.asarray(Q0).ravel(), loads.variables(F0).ravel()])
        M0 = np.asarray(information(np.concatenate([x_plan, np.zeros(n_aux)])))
        return np.concatenate([x_plan, obj.init(M0)])

    return DesignNLP(criterion, m, scale, oracle,
                     np.concatenate([lb_plan, obj.lbw]), np.concatenate([ub_plan, obj.ubw]),
                     np.concatenate([obj.lbg, lb_rules]), np.concatenate([obj.ubg, ub_rules]),
                     plan, information, start)




def _no_aux(f: ca.SX) -> Objective:
    empty = np.zeros(0)
    return Objective(f, ca.SX(0, 1), empty, empty, ca.SX(0, 1), empty, empty, lambda M0: empty)


def test_pose_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min t`` s.t. ``trace(B0_j M^-1 B0_j^T) <= t``, with ``M = R^T R``:
    ``trace(B0 M^-1 B0^T) = |R^-T B0^T|_F^2``."""
    s, r, L = B0.shape
    R = ca.chol(M)
    Y = ca.solve(R.T, ca.DM(B0.transpose(2, 0, 1).reshape(L, s * r)))
    trace = ca.sum1(ca.reshape(ca.sum1(Y**2), r, s)).T
    t = ca.SX.sym("t")

    def init(M0: np.ndarray) -> np.ndarray:
        Z = np.linalg.solve(np.linalg.cholesky(M0), B0.transpose(2, 0, 1).reshape(L, s * r))
        return np.array([1.01 * np.max(np.sum(Z**2, axis=0).reshape(s, r).sum(axis=1))])

    return Objective(t, t, np.array([0.0]), np.array([np.inf]), trace - t,
                     np.full(s, -np.inf), np.zeros(s), init)


def d_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min -log det M = -2 sum log diag(chol M)``."""
    return _no_aux(-2 * ca.sum1(ca.log(ca.diag(ca.chol(M)))))


def a_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min trace M^-1 = |R^-T|_F^2``."""
    Rinv_T = ca.solve(ca.chol(M).T, ca.DM.eye(M.shape[0]))
    return _no_aux(ca.sumsqr(Rinv_T))


def i_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min mean_j trace(B0_j M^-1 B0_j^T) = mean_j |R^-T B0_j^T|_F^2`` (I-optimality)."""
    s, r, L = B0.shape
    Y = ca.solve(ca.chol(M).T, ca.DM(B0.transpose(2, 0, 1).reshape(L, s * r)))
    return _no_aux(ca.sumsqr(Y) / s)


def t_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min -trace M``."""
    return _no_aux(-ca.trace(M))


OBJECTIVES = {"test-pose": test_pose_objective, "D": d_objective, "A": a_objective,
              "T": t_objective, "E": e_objective, "condition": condition_objective,
              "I": i_objective}


def symbolic_nlp(problem, criterion: str, m: int, B0: np.ndarray | None = None) -> DesignNLP:
    """The symbolic NLP of a reduced-space criterion (same x, g, bounds and scale)."""
    B0 = problem.B0 if B0 is None else B0
    return lifted_nlp(problem, criterion, OBJECTIVES[criterion], m, B0)
