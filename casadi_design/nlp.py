"""The design NLP: choose the plan ``{(q_i, F_i)}, i = 1..m`` that optimises a criterion.

Decision variables: ``Q`` (n x m, rad), the normalised loads ``Fbar = F / |F|_max`` (nF x m; a
1 x m magnitude ``a`` for a load of fixed direction; absent for fixed loads and geometric
cases), and the criterion's own auxiliary variables (:mod:`casadi_design.criteria`). The
test-pose criterion is the min-max of the paper (eq. 15) in epigraph form:

    minimise t  subject to  trace(B0_j M^-1 B0_j^T) <= t,  j = 1..s

(``rho_j = sigma^2`` times the left side, so sigma does not change the plan).

Constraints, the rules of :mod:`casadi_design.rules`: joint limits (bounds), loads
(``|Fbar_i| = 1`` or ``<= 1``, ``0 <= a_i <= 1``), the workspace rows of every experiment
(:func:`~casadi_design.rules.pose_constraints`) and the joint distance between experiments.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .build import Problem
from .criteria import CRITERIA
from .rules import pose_constraints


@dataclass(frozen=True, eq=False)
class DesignNLP:
    """The NLP of one (criterion, m), ready for ``casadi.nlpsol``.

    ``plan(x) -> (Q, F)`` gives the joint values (n x m, rad) and loads (nF x m, N).
    ``start(Q, F) -> x0`` completes a start point with the auxiliary variables.
    ``scale`` is the constant factor of M inside the NLP (``information`` returns ``scale M``).
    """

    criterion: str
    m: int
    scale: float
    x: ca.SX
    f: ca.SX
    g: ca.SX
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    plan: ca.Function
    information: ca.Function
    start: Callable[[np.ndarray, np.ndarray], np.ndarray]


def B0_at_test_poses(problem: Problem) -> np.ndarray:
    """``B0_j`` at every test pose, shape (s, r, L)."""
    tp = problem.test_poses
    return problem.model.B_stack(tp.q, tp.F, accuracy=True)


def build_nlp(problem: Problem, criterion: str, m: int, B0: np.ndarray | None = None) -> DesignNLP:
    """Build the NLP of ``criterion`` for ``m`` experiments (a pure function of the problem)."""
    model, robot, force = problem.model, problem.robot, problem.force
    B0 = B0_at_test_poses(problem) if B0 is None else B0
    n, nF = robot.n, model.nF
    Q = ca.SX.sym("Q", n, m)
    free_force = nF > 0 and force is not None and force.mode != "fixed"
    if free_force and force.mode == "direction":
        Fbar = ca.SX.sym("a", 1, m)  # F = a |F|max u, 0 <= a <= 1
        F = force.magnitude_N * ca.DM(force.direction) @ Fbar
    elif free_force:
        Fbar = ca.SX.sym("Fbar", nF, m)
        F = force.magnitude_N * Fbar
    else:
        Fbar = ca.SX(0, 1)
        F = ca.repmat(ca.DM(force.vector_N if force else np.zeros(0)), 1, m) if nF else ca.SX(0, m)
    # M (and B0) enter the NLP scaled to O(1) per experiment: a constant factor leaves every
    # criterion's optimal plans and trace(B0 M^-1 B0^T) unchanged and keeps IPOPT's steps
    # well scaled.
    scale = model.L / max(np.einsum("sij,sij->", B0, B0) / B0.shape[0], np.finfo(float).tiny)
    M = ca.SX.zeros(model.L, model.L)
    for i in range(m):
        Bi = model.B(Q[:, i], F[:, i])
        M += scale * (Bi.T @ Bi)
    obj = CRITERIA[criterion].objective(M, np.sqrt(scale) * B0)

    g, lbg, ubg = [obj.g], [obj.lbg], [obj.ubg]
    if free_force and force.mode != "direction":
        norms = ca.sum1(Fbar**2).T
        g.append(norms)
        lbg.append(np.ones(m) if force.mode == "equal" else np.zeros(m))
        ubg.append(np.ones(m))
    rules = pose_constraints(problem)
    for i in range(m):
        g.append(rules.g(Q[:, i]))
        lbg.append(rules.lb)
        ubg.append(rules.ub)
    dmin = problem.workspace.min_joint_distance_rad
    if dmin > 0:
        pairs = [ca.sumsqr(Q[:, i] - Q[:, j]) for i in range(m) for j in range(i + 1, m)]
        g.append(ca.vertcat(*pairs) if pairs else ca.SX(0, 1))
        lbg.append(np.full(len(pairs), dmin**2))
        ubg.append(np.full(len(pairs), np.inf))

    qv, fv = ca.vec(Q), ca.vec(Fbar)
    x = ca.vertcat(qv, fv, obj.w)
    f_lb = 0.0 if free_force and force.mode == "direction" else -1.0
    lbx = np.concatenate([np.tile(robot.q_min, m), np.full(fv.numel(), f_lb), obj.lbw])
    ubx = np.concatenate([np.tile(robot.q_max, m), np.ones(fv.numel()), obj.ubw])
    plan = ca.Function("plan", [x], [Q, F], ["x"], ["Q", "F"])
    information = ca.Function("M", [x], [M], ["x"], ["M"])
    n_plan = qv.numel() + fv.numel()

    def start(Q0: np.ndarray, F0: np.ndarray) -> np.ndarray:
        if not free_force:
            Fbar0 = np.zeros(0)
        elif force.mode == "direction":
            Fbar0 = np.array(force.direction) @ F0 / force.magnitude_N
        else:
            Fbar0 = (F0 / force.magnitude_N).ravel(order="F")
        x_plan = np.concatenate([np.asarray(Q0).ravel(order="F"), Fbar0])
        M0 = np.asarray(information(np.concatenate([x_plan, np.zeros(x.numel() - n_plan)])))
        return np.concatenate([x_plan, obj.init(M0)])

    return DesignNLP(criterion, m, scale, x, obj.f, ca.vertcat(*g), lbx, ubx,
                     np.concatenate(lbg), np.concatenate(ubg), plan, information, start)
