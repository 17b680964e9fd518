"""The design NLP: choose the plan ``{(q_i, F_i)}, i = 1..m`` that optimises a criterion.

Decision variables: ``Q`` (n x m, rad), the normalised loads ``f = F / |F|_max`` (nF x m,
absent for fixed loads and geometric cases), and the criterion's own auxiliary variables. The
test-pose criterion is the min-max of the paper (eq. 15) in epigraph form:

    minimise t  subject to  trace(B0_j M^-1 B0_j^T) <= t,  j = 1..s

(``rho_j = sigma^2`` times the left side, so sigma does not change the plan). ``M^-1`` enters
through the Cholesky factor ``M = R^T R``: ``trace(B0 M^-1 B0^T) = |R^-T B0^T|_F^2``.

E-optimality and the condition number are non-smooth in the plan (an eigenvalue may be
repeated at the optimum); they are posed smoothly with semidefinite constraints written as
Cholesky-factor equalities: ``M - s I = C C^T`` (C lower triangular, free) holds iff
``M - s I`` is positive semidefinite, so ``max s`` gives ``s = lambda_min(M)``.

Constraints: joint limits (bounds), loads (``|f_i| = 1`` or ``<= 1``), and the workspace of the
measured point (box and half-spaces).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import casadi as ca
import numpy as np

from .problem import Problem


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


def _test_pose(M: ca.SX, B0: np.ndarray) -> Objective:
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


def _D(M: ca.SX, B0: np.ndarray) -> Objective:
    return _no_aux(-2 * ca.sum1(ca.log(ca.diag(ca.chol(M)))))


def _A(M: ca.SX, B0: np.ndarray) -> Objective:
    Rinv_T = ca.solve(ca.chol(M).T, ca.DM.eye(M.shape[0]))
    return _no_aux(ca.sumsqr(Rinv_T))


def _T(M: ca.SX, B0: np.ndarray) -> Objective:
    return _no_aux(-ca.trace(M))


def _E(M: ca.SX, B0: np.ndarray) -> Objective:
    L = M.shape[0]
    s = ca.SX.sym("s")
    c, g, init_c = _psd_factor("C", M - s * ca.SX.eye(L))

    def init(M0: np.ndarray) -> np.ndarray:
        s0 = 0.5 * np.linalg.eigvalsh(M0)[0]
        return np.concatenate([[s0], init_c(M0 - s0 * np.eye(L))])

    n = c.numel()
    return Objective(-s, ca.vertcat(s, c), np.r_[0.0, np.full(n, -np.inf)], np.full(n + 1, np.inf),
                     g, np.zeros(n), np.zeros(n), init)


def _condition(M: ca.SX, B0: np.ndarray) -> Objective:
    """min kappa s.t. s I <= M <= kappa s I: kappa = lambda_max / lambda_min = (s_1/s_L)^2."""
    L = M.shape[0]
    s, kappa = ca.SX.sym("s"), ca.SX.sym("kappa")
    c1, g1, init1 = _psd_factor("C1", M - s * ca.SX.eye(L))
    c2, g2, init2 = _psd_factor("C2", kappa * s * ca.SX.eye(L) - M)

    def init(M0: np.ndarray) -> np.ndarray:
        lam = np.linalg.eigvalsh(M0)
        s0, k0 = 0.5 * lam[0], 2.0 * lam[-1] / (0.5 * lam[0])
        return np.concatenate([[s0, k0], init1(M0 - s0 * np.eye(L)), init2(k0 * s0 * np.eye(L) - M0)])

    n = c1.numel()
    return Objective(kappa, ca.vertcat(s, kappa, c1, c2),
                     np.r_[1e-12, 1.0, np.full(2 * n, -np.inf)], np.full(2 * n + 2, np.inf),
                     ca.vertcat(g1, g2), np.zeros(2 * n), np.zeros(2 * n), init)


def _no_aux(f: ca.SX) -> Objective:
    empty = np.zeros(0)
    return Objective(f, ca.SX(0, 1), empty, empty, ca.SX(0, 1), empty, empty, lambda M0: empty)


#: Symbolic objective of each criterion (the names of :data:`casadi_design.measures.CRITERIA`).
OBJECTIVES: dict[str, Callable[[ca.SX, np.ndarray], Objective]] = {
    "test-pose": _test_pose,
    "D": _D,
    "A": _A,
    "E": _E,
    "T": _T,
    "condition": _condition,
}


@functools.cache
def pose_constraints(problem: Problem) -> tuple[ca.Function, np.ndarray, np.ndarray]:
    """Workspace constraints of one configuration: ``lb <= g(q) <= ub`` (m).

    Every measured point in the box, the half-spaces (``n.p >= b``, n normalised) and the
    tracker's sphere; every moving joint origin and measured point above the floor.
    """
    ws, model = problem.workspace, problem.model
    q = ca.SX.sym("q", problem.robot.n)
    P = model.points(q)
    g, lb, ub = [], [], []
    for j in range(P.shape[1]):
        p = P[:, j]
        if ws.box_min_m is not None:
            g.append(p)
            lb += list(ws.box_min_m)
            ub += list(ws.box_max_m)
        for hs in ws.half_spaces:
            n = np.array(hs.normal) / np.linalg.norm(hs.normal)
            g.append(ca.dot(ca.DM(n), p))
            lb.append(hs.offset_m / np.linalg.norm(hs.normal))
            ub.append(np.inf)
        if ws.sphere_center_m is not None:
            g.append(ca.sqrt(ca.sumsqr(p - ca.DM(ws.sphere_center_m)) + 1e-12))
            lb.append(-np.inf)
            ub.append(ws.sphere_radius_m)
    if ws.floor_z_m is not None:
        # origins fixed to the base (not depending on q) are where the robot stands: not constrained
        z = ca.horzcat(model.kinematics.joint_origins(q), P)[2, :].T
        z = ca.vertcat(*[z[k] for k in range(z.numel()) if ca.depends_on(z[k], q)])
        g.append(z)
        lb += [ws.floor_z_m] * z.numel()
        ub += [np.inf] * z.numel()
    return ca.Function("workspace", [q], [ca.vertcat(*g) if g else ca.SX(0, 1)]), np.array(lb), np.array(ub)


def B0_at_test_poses(problem: Problem) -> np.ndarray:
    """``B0_j`` at every test pose, shape (s, r, L)."""
    tp = problem.test_poses
    return np.array([problem.model.B_numeric(q, F, accuracy=True) for q, F in zip(tp.q, tp.F)])


def build_nlp(problem: Problem, criterion: str, m: int, B0: np.ndarray | None = None) -> DesignNLP:
    """Build the NLP of ``criterion`` for ``m`` experiments (a pure function of the problem)."""
    model, robot, force = problem.model, problem.robot, problem.force
    B0 = B0_at_test_poses(problem) if B0 is None else B0
    n, nF = robot.n, model.nF
    Q = ca.SX.sym("Q", n, m)
    free_force = nF > 0 and force is not None and force.mode != "fixed"
    if free_force and force.mode == "direction":
        f = ca.SX.sym("a", 1, m)  # F = a |F|max u, 0 <= a <= 1
        F = force.magnitude_N * ca.DM(force.direction) @ f
    elif free_force:
        f = ca.SX.sym("f", nF, m)
        F = force.magnitude_N * f
    else:
        f = ca.SX(0, 1)
        F = ca.repmat(ca.DM(force.vector_N if force else np.zeros(0)), 1, m) if nF else ca.SX(0, m)
    # M (and B0) enter the NLP scaled to O(1) per experiment: a constant factor leaves every
    # criterion's optimal plans and trace(B0 M^-1 B0^T) unchanged and keeps IPOPT's steps
    # well scaled.
    scale = model.L / max(np.einsum("sij,sij->", B0, B0) / B0.shape[0], np.finfo(float).tiny)
    M = ca.SX.zeros(model.L, model.L)
    for i in range(m):
        Bi = model.B(Q[:, i], F[:, i])
        M += scale * (Bi.T @ Bi)
    obj = OBJECTIVES[criterion](M, np.sqrt(scale) * B0)

    g, lbg, ubg = [obj.g], [obj.lbg], [obj.ubg]
    if free_force and force.mode != "direction":
        norms = ca.sum1(f**2).T
        g.append(norms)
        lbg.append(np.ones(m) if force.mode == "equal" else np.zeros(m))
        ubg.append(np.ones(m))
    g_pose, lb_pose, ub_pose = pose_constraints(problem)
    for i in range(m):
        g.append(g_pose(Q[:, i]))
        lbg.append(lb_pose)
        ubg.append(ub_pose)
    dmin = problem.workspace.min_joint_distance_rad
    if dmin > 0:
        pairs = [ca.sumsqr(Q[:, i] - Q[:, j]) for i in range(m) for j in range(i + 1, m)]
        g.append(ca.vertcat(*pairs) if pairs else ca.SX(0, 1))
        lbg.append(np.full(len(pairs), dmin**2))
        ubg.append(np.full(len(pairs), np.inf))

    qv, fv = ca.vec(Q), ca.vec(f)
    x = ca.vertcat(qv, fv, obj.w)
    f_lb = 0.0 if free_force and force.mode == "direction" else -1.0
    lbx = np.concatenate([np.tile(robot.q_min, m), np.full(fv.numel(), f_lb), obj.lbw])
    ubx = np.concatenate([np.tile(robot.q_max, m), np.ones(fv.numel()), obj.ubw])
    plan = ca.Function("plan", [x], [Q, F], ["x"], ["Q", "F"])
    information = ca.Function("M", [x], [M], ["x"], ["M"])
    n_plan = qv.numel() + fv.numel()

    def start(Q0: np.ndarray, F0: np.ndarray) -> np.ndarray:
        if not free_force:
            f0 = np.zeros(0)
        elif force.mode == "direction":
            f0 = np.array(force.direction) @ F0 / force.magnitude_N
        else:
            f0 = (F0 / force.magnitude_N).ravel(order="F")
        x_plan = np.concatenate([np.asarray(Q0).ravel(order="F"), f0])
        M0 = np.asarray(information(np.concatenate([x_plan, np.zeros(x.numel() - n_plan)])))
        return np.concatenate([x_plan, obj.init(M0)])

    return DesignNLP(criterion, m, scale, x, obj.f, ca.vertcat(*g), lbx, ubx,
                     np.concatenate(lbg), np.concatenate(ubg), plan, information, start)
