"""The NLP of test-pose and I with the robot's unmodelled error as a field: the kriging variance in IPOPT.

The reduced NLP (:mod:`casadi_design.optimisation.reduced`) is a function of M; with a field the
error at a test pose is the universal kriging variance of the whole campaign
(:mod:`casadi_design.measures.field`), which M does not hold. Here IPOPT's variables, bounds and
rule rows are the reduced NLP's (the same rulebook, :func:`~casadi_design.optimisation.nlp.build_nlp`
with ``field``), and the criterion's part is the kriging variance instead: test-pose's rows
``rho_j / sigma^2 - t <= 0``, I's objective ``mean_j rho_j / sigma^2`` (``rho / sigma^2`` is
``trace(B0 M^-1 B0^T)``, the reduced NLP's rows, in the limit of no field).

``rho`` is a CasADi graph of the plan's variables ``Z`` (p x m, each experiment's ``z = (q,
v)``): each experiment's rows ``B(z)`` and loads ``G(z)`` (``dy/dq`` for an error of the joint
angles; ``Wh C`` for the base axes), mapped; the kernels of the campaign (the held poses, then
the plan's) and of the test poses; ``V = sum_c (K_c (x) 1) * (g_c g_c^T) + nugget^2 I (x) A +
sigma^2 I`` and the cross covariance ``k0``; two linear solves (LDL); then, as
:func:`~casadi_design.measures.field.kriging_rho`,

    rho_j = tr(T00_j) - tr(k0_j^T V^-1 k0_j) + tr(R_j H^-1 R_j^T),
    H = P + S^T V^-1 S,  R = B0 - k0^T V^-1 S,

its gradient by CasADi in reverse mode. The Hessian is IPOPT's limited-memory approximation: an
exact one (forward over reverse through the solves) costs more an iteration than it saves in
iterations (IPA's UR10, 100 poses held, m = 10: 87 s against 36 s for the same plan).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import casadi as ca
import numpy as np

from ..calibration.models import joint_jacobians
from ..measures.field import coupling, held_part, noise, own_variance
from ..problem.build import Problem
from .reduced import ReducedNLP, callbacks

#: IPOPT's Hessian of the NLP with the field.
LIMITED_MEMORY = {"ipopt.hessian_approximation": "limited-memory"}


def kriging_graph(problem: Problem, m: int) -> ca.Function:
    """``Z -> (rows, d rows / d vec(Z))``: ``rho_j / sigma^2`` (s,) at the test poses of the
    campaign of the held poses and the plan of variables ``Z`` (n + nv x m) with the problem's
    field (module docstring), and its Jacobian (s x (n + nv) m, ``vec`` column-major: experiment
    i's variable a at ``i (n + nv) + a``); p below is the field's number of components.

    The held poses do not move: their part is numbers, eliminated once
    (:func:`~casadi_design.measures.field.held_part`), and the graph's solves are of the plan's m
    d values alone (``D = V_pp - T T^T``, ``T = V_ph C_h^-T``)."""
    fld, model, loads = problem.field, problem.model, problem.rules.loads
    n, nv, d, L = model.n, loads.nv, model.d, model.L
    axes = problem.field_axes[0]
    Wh, sigma = problem.whitening, problem.sigma_m
    q, v = ca.SX.sym("q", n), ca.SX.sym("v", nv)
    F = loads.load(v)
    G = joint_jacobians(model)[0](q, F) if fld.through_joints else ca.DM(Wh @ coupling(axes, np.arange(3)))
    one = ca.Function("one", [ca.vertcat(q, v)], [model.B(q, F), G])
    Z = ca.MX.sym("Z", n + nv, m)
    Bm, Gm = one.map(m)(Z)  # (d, L m), (d, p m)
    p = Gm.shape[1] // m
    S = ca.vertcat(*(Bm[:, i * L:(i + 1) * L] for i in range(m)))  # the plan's rows (m d, L)
    g = [ca.vertcat(*(Gm[:, i * p + c] for i in range(m))) for c in range(p)]  # its loads (m d,) per component
    Qp = Z[:n, :].T  # (m, n)
    S0 = problem.field_test_sites
    s, r = S0.G.shape[:2]
    ones = ca.DM.ones(d, d)
    Kc, K0c = _components(fld, Qp, Qp), _components(fld, Qp, ca.DM(S0.Q))
    Bh, Sh = problem.field_held_rows  # (its sites' A, the nugget's coupling, with no held pose too)
    D = sum(ca.kron(Kc[c], ones) * (g[c] @ g[c].T) for c in range(p)) + ca.DM(np.kron(np.eye(m), noise(fld, Sh, sigma)))
    k0 = sum((g[c] * ca.kron(K0c[c], ca.DM.ones(d, 1))) @ ca.DM(_spread(S0.G[:, :, c])) for c in range(p))
    held = held_part(fld, sigma, Bh, Sh, problem.B0, S0, problem.field_prior)
    H, R, KK = ca.DM(held.G), ca.DM(held.R.reshape(s * r, L)), ca.DM(held.KK)
    if len(Sh):  # the held poses, eliminated (docstring)
        Kh = _components(fld, Qp, ca.DM(Sh.Q))
        Vph = sum(ca.kron(Kh[c], ones) * (g[c] @ ca.DM(Sh.G[:, :, c].reshape(1, -1))) for c in range(p))
        T = Vph @ ca.DM(np.linalg.inv(held.Ch).T)
        D, S, k0 = D - T @ T.T, S - T @ ca.DM(held.UB), k0 - T @ ca.DM(held.Uk)
    W = ca.solve(D, ca.horzcat(S, k0), "ldl")
    WS, Wk = W[:, :L], W[:, L:]
    H = H + S.T @ WS
    R = R - k0.T @ WS
    Y = ca.solve(H, R.T, "ldl")
    KK = KK + ca.sum1(ca.reshape(ca.sum1(k0 * Wk), r, s)).T
    RR = ca.sum1(ca.reshape(ca.sum2(R * Y.T).T, r, s))
    rows = (ca.DM(own_variance(fld, S0)) - KK + RR.T) / sigma**2
    return ca.Function("kriging", [Z], [rows, ca.jacobian(rows, ca.vec(Z))], ["Z"], ["rows", "drows"])


def _components(fld, Qa: ca.MX, Qb: ca.MX | ca.DM) -> tuple[list, list]:
    """The components' kernels ``k_c`` (MX, len(Qa) x len(Qb)) between the poses ``Qa`` and
    ``Qb`` (rows), as :meth:`~casadi_design.measures.field.Field.components`."""
    ma, mb = Qa.shape[0], Qb.shape[0]
    D2 = [((ca.repmat(Qa[:, l], 1, mb) - ca.repmat(Qb[:, l].T, ma, 1)) / ell) ** 2 for l, ell in enumerate(fld.lengths)]
    if fld.through_joints:
        return [a**2 * ca.exp(-0.5 * D) for a, D in zip(fld.angles_rad, D2)]
    if fld.shares:
        return [fld.scale_m**2 * sum(w * ca.exp(-0.5 * D) for w, D in zip(fld.shares, D2))] * 3
    return [fld.scale_m**2 * ca.exp(-0.5 * sum(D2))] * 3


def _spread(G0c: np.ndarray) -> np.ndarray:
    """``P`` (s, s r) with ``P[j, j r + w] = G0c[j, w]``: test pose j's loads of one component
    on its r components."""
    s, r = G0c.shape
    P = np.zeros((s, s * r))
    for j in range(s):
        P[j, j * r:(j + 1) * r] = G0c[j]
    return P


class _FieldValues(NamedTuple):
    """f, g and M at one x (M: the reduced NLP's, for :attr:`DesignNLP.information`)."""

    f: float
    g: np.ndarray
    M: np.ndarray


@dataclass(frozen=True, eq=False)
class FieldNLP:
    """The reduced NLP ``base`` of test-pose or I with its criterion's part replaced by the
    kriging variance (module docstring): its rules, bounds and layout; ``kriging`` the graph of
    :func:`kriging_graph`."""

    base: ReducedNLP
    kriging: ca.Function
    last: list = field(default_factory=list)

    @property
    def n_rows(self) -> int:
        return self.base.n_rows

    @property
    def nx(self) -> int:
        return self.base.nx

    @property
    def active(self) -> np.ndarray:
        return self.base.active

    @property
    def active_rows(self) -> np.ndarray:
        return self.base.active_rows

    @property
    def pairs(self) -> np.ndarray:
        return self.base.pairs

    def _rows(self, x: np.ndarray, slopes: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """``rho_j / sigma^2`` (s,) at x and, with ``slopes``, their gradient by x (s, nx); those
        of the last x kept (its gradient costs some 40 times its values)."""
        x = np.asarray(x, dtype=float).ravel()
        key = x.tobytes()
        base = self.base
        if not self.last or self.last[0] != key:
            self.last[:] = [key, np.asarray(self.values(x[base.cols].T), dtype=float).ravel(), None]
        if slopes and self.last[2] is None:
            J = np.zeros((len(base.B0s), base.nx))
            J[:, base.cols.ravel()] = np.asarray(self.kriging(x[base.cols].T)[1], dtype=float)
            self.last[2] = J
        return self.last[1], self.last[2]

    @cached_property
    def values(self) -> ca.Function:
        """``Z -> rows`` alone."""
        Z = self.kriging.mx_in(0)
        return ca.Function("rows", [Z], [self.kriging(Z)[0]])

    def at(self, x: np.ndarray) -> _FieldValues:
        v = self.base.at(x)
        rows, _ = self._rows(x)
        g = v.g.copy()
        if self.n_rows:  # f = t
            t = float(np.asarray(x, dtype=float).ravel()[-1])
            g[:self.n_rows] = rows - t
            return _FieldValues(t, g, v.M)
        return _FieldValues(float(np.mean(rows)), g, v.M)

    def f_g(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = self.at(x)
        return np.array([v.f]), v.g

    def grad_f(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = self.at(x)
        if self.n_rows:
            return np.array([v.f]), np.eye(self.nx)[-1]
        return np.array([v.f]), np.mean(self._rows(x, slopes=True)[1], axis=0)

    def jac_g(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        base, v = self.base, self.at(x)
        J = base.slopes(x).jac_g.copy()
        if self.n_rows:
            J[:self.n_rows] = self._rows(x, slopes=True)[1]
            J[:self.n_rows, -1] = -1.0
        return v.g, J.ravel()[base.jacobian_nonzeros]

    def functions(self) -> tuple[ca.Function, dict]:
        """The NLP ``(x, p) -> (f, g)`` and the nlpsol options: its first derivatives and IPOPT's
        limited-memory Hessian."""
        base = self.base
        oracle, options = callbacks(self, base.nx, base.ng, base.jacobian_pattern)
        return oracle, {**options, **LIMITED_MEMORY}
