"""The NLP of a plan of configurations seated at an artefact's points: the exchange's plan moved
along the seated configurations by IPOPT.

Each experiment i keeps its socket ``c_i = t_g + R_g a_k`` (point k of placement g of the problem
file, :func:`~casadi_design.plan.seated.socket_positions`) and moves its joints ``q_i``
(rad) within the joint limits and within :data:`SEATED_NLP_BOX` of the exchange's plan, its
nominal ball held in its socket and its hand within the tilt:

    minimise  (mean_j rho_j^r)^(1/r),   rho_j = tr(B0_j M(Q)^-1 B0_j^T)   (j = 1..s)
              (test-pose; any other criterion: its phi(M(Q)) / k)
    subject to  p(q_i) = c_i,   z(q_i) . (-R_g e_z) >= cos(tilt_max),

with ``M(Q) = sum_i [B_i(q_i), -G_i]^T [B_i(q_i), -G_i]`` the information of X (the base set the
exchange's pool tells) and every placement's pose, ``B0`` the test poses' registered rows
(:func:`~casadi_design.calibration.artefact.artefact_rows`,
:func:`~casadi_design.calibration.artefact.registered`): the test-pose measure of the pool engine,
here a CasADi graph of the plan (its values equal the engine's, a test checks them to 1e-7), so
IPOPT gets its exact gradient; a limited-memory Hessian. The r-mean is the test-pose criterion's
smooth surrogate, the max as r grows (:data:`SEATED_NLP_POWERS`). The other criteria are their
own ``phi(M)`` of :mod:`~casadi_design.measures.objectives` (D ``-log det M``, A ``log tr M^-1``, E
and condition their spectral surrogates for each power of the criterion's ``powers``), with
its gradient ``dphi/dM`` (:class:`CriterionOfM`), divided by k, the number of parameters of X
(IPOPT diverges on D's sum). The plan is kept where IPOPT converges to a
plan that keeps every rule and scores better by the criterion itself
(:func:`~.artefact_pool.artefact_scores`).
"""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np

from ..calibration.artefact import placement_columns
from ..measures.criteria import CRITERIA
from ..measures.objectives import Objective
from ..plan.design import Design, StartRecord
from ..plan.seated import socket_positions
from ..plan.rules import plan_violations
from ..problem.build import Problem
from .artefact_pool import artefact_pool, artefact_scores
from .ipopt import QUIET, ipopt_call

#: The powers of the smooth surrogate IPOPT minimises in turn, each from the last's plan: the
#: p-mean of rho (the exchange's surrogate, :data:`~.pool.POOL_POWER`, then a sharper one). The
#: epigraph of the max with a limited-memory Hessian stalls on these equality rows (the Panda of
#: problems/panda_ball_socket.toml, m = 16: 200 iterations, worse than its start; the exact
#: Hessian takes 45 s); the 8- then 32-mean converge in about 1 s each (0.0919 -> 0.0548 mm).
SEATED_NLP_POWERS = (8.0, 32.0)
#: Each joint moves at most this far (rad) from the exchange's plan: without the box, D's NLP
#: left for near-singular plans and ended there (problems/panda_ball_socket.toml without its
#: joint margin, m = 24, at front_center: log det M 16.0 -> -32 after 500 iterations; within
#: 1 rad: 25.6 in 133); the test-pose plans lost 1 to 2 % to it there (m = 16: 0.0526 -> 0.0535 mm).
SEATED_NLP_BOX = 1.0
SEATED_NLP_ITERATIONS = 500
SEATED_NLP_OPTIONS = {"ipopt.hessian_approximation": "limited-memory"}
#: How far (m) a refined plan's nominal ball may be from its socket, and its hand past the tilt
#: (in the cosine: IPOPT holds a row to its tolerance, 1e-8).
SEATED_TOL_M = 1e-7
TILT_TOL = 1e-6
SEATED_NLP = "NLP along the seated configurations, from the exchange's plan"


def seated_graph(problem: Problem, design: Design) -> tuple[ca.Function, ca.Function, ca.Function, np.ndarray,
                                                             np.ndarray, np.ndarray]:
    """The CasADi functions of the plan ``Q`` (n x m, rad) of ``design`` (its seating fixed):
    ``rho(Q)`` (s,), ``tr(B0_j M^-1 B0_j^T)``; ``information(Q)``, M (L x L); and ``seat(Q)``
    (4m,): each experiment's ball minus its socket (m) then the cosine of its tilt; with the
    sockets (m, 3), the pool's parameters' columns in the problem's model and the test poses'
    registered rows ``B0`` (s, 3, L)."""
    model, A = problem.model, problem.artefact
    s = design.seated
    pool = artefact_pool(problem, design.Q, s.point, s.placement)
    kept = [model.parameter_names.index(n) for n in pool.names]
    at = np.searchsorted(np.unique(s.placement), s.placement)
    G = -placement_columns(A, pool.R, s.point, at)  # (m, 3, P nP), constant
    # the sockets and their axes where the problem file clamps the tool (the plan's placements by name)
    Rs, cs = socket_positions(problem)
    names = [p.name for p in problem.spec.measurement.artefact.placements]
    g = np.array([names.index(s.names[j]) for j in s.placement])
    sockets, into = cs[g, s.point], -Rs[g][:, :, 2]  # the artefact's -z: into the socket
    m, n = design.Q.shape
    Q = ca.MX.sym("Q", n, m)
    F0 = ca.DM.zeros(model.nF)
    rows, seat, tilt = [], [], []
    for i in range(m):
        B = model.B(Q[:, i], F0)[:, kept]
        rows.append(ca.horzcat(B, ca.DM(G[i])))
        R, p = model.kinematics.placement(Q[:, i], ca.DM.zeros(len(model.kinematics.parameter_names)))
        seat.append(p - ca.DM(sockets[i]))
        tilt.append(ca.dot(R[:, 2], ca.DM(into[i])))
    J = ca.vertcat(*rows)
    B0 = pool.B0.reshape(-1, pool.B0.shape[2])  # (3s, L'), the registered test poses' rows
    M = J.T @ J
    X = ca.solve(M, ca.DM(B0.T))
    rho = ca.reshape(ca.sum1(ca.DM(B0.T) * X), 3, -1)  # each row's B0_r M^-1 B0_r^T, three a pose
    return (ca.Function("rho", [Q], [ca.sum1(rho).T]), ca.Function("information", [Q], [M]),
            ca.Function("seat", [Q], [ca.vertcat(*seat, *tilt)]), sockets, np.array(kept), pool.B0)


class CriterionOfM(ca.Callback):
    """A criterion's ``phi(M) / k`` (:class:`~casadi_design.measures.objectives.Objective`; ``P``
    its weights, ``power`` r of a surrogate; ``log phi(M) / k`` where phi is positive: A's
    ``tr M^-1`` is 1e6 on a Panda's plans) of a symmetric L x L matrix M, for IPOPT: the value,
    and its gradient in M as CasADi's Jacobian (no second derivative: the NLP's Hessian is
    limited-memory). Not a number where M is not positive definite: IPOPT then cuts its step.
    The caller keeps the object alive as long as a solver calls it."""

    def __init__(self, objective: Objective, P: np.ndarray | None, power: float, L: int, k: int,
                 gradient: bool = False):
        ca.Callback.__init__(self)
        self.objective, self.P, self.power, self.L, self.k, self.gradient = objective, P, power, L, k, gradient
        self._jacobians: list[CriterionOfM] = []
        self.construct("dphi" if gradient else "phi", {})

    def get_n_in(self) -> int:
        return 2 if self.gradient else 1  # a Jacobian's inputs: M and phi at M

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self.L, self.L) if i == 0 else ca.Sparsity.dense(1, 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(1, self.L**2 if self.gradient else 1)

    def eval(self, arg):
        M = np.asarray(arg[0], dtype=float)
        M = 0.5 * (M + M.T)
        try:
            C = np.linalg.cholesky(M)
        except np.linalg.LinAlgError:
            return [ca.DM.nan(*self.get_sparsity_out(0).shape)]
        Cinv = np.linalg.inv(C)
        local = self.objective.at(M, C, Cinv, self.P, self.power)
        log = self.objective.positive
        if not self.gradient:
            return [(np.log(local.value) if log else local.value) / self.k]
        G = self.objective.gradient(local, Cinv.T @ Cinv, self.P) / (local.value if log else 1.0)
        return [ca.DM(np.ravel(0.5 * (G + G.T), order="F")[None] / self.k)]

    def has_jacobian(self) -> bool:
        return not self.gradient

    def get_jacobian(self, name, inames, onames, opts):
        jacobian = CriterionOfM(self.objective, self.P, self.power, self.L, self.k, gradient=True)
        self._jacobians.append(jacobian)  # each one CasADi asks for lives as long as this one
        return jacobian


def seated_nlp(problem: Problem, design: Design) -> Design:
    """IPOPT on the NLP of the module docstring from ``design``'s plan: for the test-pose
    criterion on the p-mean of rho for each power of :data:`SEATED_NLP_POWERS` in turn, for
    another criterion on its ``phi(M)`` (each power of its surrogate in turn); the design with the
    best refined plan that is seated, keeps every rule and scores better by the criterion itself,
    and with the NLP's records among its starts either way."""
    m, n = design.Q.shape
    rho, information, seat, _, kept, B0 = seated_graph(problem, design)
    x = ca.MX.sym("x", n * m)
    r, seated = rho(ca.reshape(x, n, m)), seat(ca.reshape(x, n, m))
    crit = CRITERIA[design.criterion]
    if design.criterion == "test-pose":
        stages = [(f"{p:g}-mean", ca.log(ca.sum1(r**p) / r.numel()) / p) for p in SEATED_NLP_POWERS]
    else:
        P, M = crit.objective.weights(B0), information(ca.reshape(x, n, m))
        phis = [(f"{crit.row}, r = {p:g}" if crit.powers else crit.row, CriterionOfM(crit.objective, P, p, len(B0[0, 0]), len(kept)))
                for p in (crit.powers or (0.0,))]
        stages = [(name, phi(M)) for name, phi in phis]
    cos_max = float(np.cos(problem.spec.measurement.artefact.tilt_max_rad))
    lower, upper = problem.rules.limits.bounds()
    x0 = design.Q.ravel()
    bounds = {"lbx": np.maximum(np.tile(lower, m), x0 - SEATED_NLP_BOX), "ubx": np.minimum(np.tile(upper, m), x0 + SEATED_NLP_BOX),
              "lbg": np.concatenate([np.zeros(3 * m), np.full(m, cos_max)]),
              "ubg": np.concatenate([np.zeros(3 * m), np.full(m, np.inf)])}
    best, Q0, better = design, design.Q, crit.better
    for stage, f in stages:
        solver = ca.nlpsol("seated", "ipopt", {"x": x, "f": f, "g": seated},
                           {**QUIET, **SEATED_NLP_OPTIONS, "ipopt.max_iter": SEATED_NLP_ITERATIONS,
                            "ipopt.tol": problem.solver.tol})
        with ipopt_call():
            sol = solver(x0=Q0.ravel(), **bounds)
        Q = np.clip(np.asarray(sol["x"], dtype=float).ravel().reshape(m, n), lower, upper)
        values = np.asarray(seat(Q.T), dtype=float).ravel()
        feasible = (float(np.max(np.abs(values[:3 * m]))) <= SEATED_TOL_M and bool(np.all(values[3 * m:] >= cos_max - TILT_TOL))
                    and not plan_violations(problem, Q, design.F))
        scores = artefact_scores(problem, Q, design.seated.point, design.seated.placement)
        stats = solver.stats()
        rec = StartRecord(str(stats["return_status"]), int(stats.get("iter_count", 0)), scores.value(design.criterion),
                          scores.max_rms_error_m, feasible and scores.identifiable, f"{SEATED_NLP} ({stage})")
        if rec.converged and better(scores.value(design.criterion), best.scores.value(design.criterion)):
            best = replace(best, Q=Q, scores=scores, status=rec.status)
        best = replace(best, starts=best.starts + (rec,))
        Q0 = Q if rec.feasible else Q0
    return best
