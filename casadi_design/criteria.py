"""The design criteria: one registry entry each, read by the NLP, the scores, plots and the CLI.

For a plan with information matrix ``M = sum_i B_i^T B_i`` (``cov(X) = sigma^2 M^-1``):

* test-pose (paper eq. 12 and 15): minimise ``max_j rho_j``, ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``;
* D: maximise ``log det M``; A: minimise ``trace M^-1``; E (the paper's "SVD approach"):
  maximise ``s_L``, the smallest singular value of the stacked B; T: maximise ``trace M``;
  condition: minimise ``s_1 / s_L``.

Each entry holds the field of :class:`casadi_design.measures.Scores` that holds its numeric
value, its labels and line style, a fixed seed id (adding a criterion never changes the starts
of another) and, for E and condition, the symbolic NLP objective (CasADi, of the scaled ``M``
and ``B0``).

test-pose, D, A and T are smooth in M: their NLP is the reduced-space one of
:mod:`casadi_design.reduced` (test-pose as the epigraph ``min t`` s.t.
``trace(B0_j M^-1 B0_j^T) <= t``). E and condition are non-smooth in the plan (a repeated
eigenvalue at the optimum); they are posed with semidefinite constraints written as
Cholesky-factor equalities: ``M - lam I = C C^T`` (C lower triangular, free) holds iff
``M - lam I`` is positive semidefinite, so ``max lam`` gives ``lam = lambda_min(M)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

#: Relative tolerance within which two starts count as reaching the same optimum (on the
#: criterion's value; for D on det M, i.e. absolute on log det M).
SAME_OPTIMUM_RTOL = 1e-6


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
class Criterion:
    """One design criterion.

    Attributes
    ----------
    name : the name used in problem files, options and results.
    sense : "min" or "max", the better direction of the score.
    score : the field of :class:`~casadi_design.measures.Scores` holding its value.
    label : description for tables, with units.
    legend : name in figure legends.
    style : matplotlib line style of its curves.
    objective : ``(M, B0) -> Objective``, M the (scaled) information matrix, B0 (s, r, L), of
        the lifted NLP; None for the criteria of the reduced-space NLP (:mod:`casadi_design.reduced`).
    seed_id : third entry of the seed of its starts (fixed forever).
    polished : nearly singular starts first get a few D-optimal iterations (see solve.py).
    log_value : the value is a logarithm (same optimum: absolute tolerance on it).
    """

    name: str
    sense: str
    score: str
    label: str
    legend: str
    style: dict
    objective: Callable[[ca.SX, np.ndarray], Objective] | None
    seed_id: int
    polished: bool = False
    log_value: bool = False

    def better(self, a: float, b: float) -> bool:
        """Whether value ``a`` is strictly better than ``b``."""
        return a < b if self.sense == "min" else a > b

    def same_optimum(self, value: float, best: float) -> bool:
        """Whether ``value`` reaches the optimum ``best`` within ``SAME_OPTIMUM_RTOL`` relative."""
        scale = 1.0 if self.log_value else abs(best)
        return abs(value - best) <= SAME_OPTIMUM_RTOL * scale


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


CRITERIA: dict[str, Criterion] = {
    c.name: c
    for c in (
        Criterion("test-pose", "min", "max_rms_error_m", "max over test poses of sqrt(rho) (m)",
                  "Test-pose approach", {"color": "tab:red", "ls": "-", "lw": 2.0}, None, 0),
        Criterion("D", "max", "log_det_M", "log det M (D-optimality)", "D-optimality",
                  {"color": "tab:blue", "ls": "--", "lw": 1.5}, None, 1, log_value=True),
        Criterion("A", "min", "trace_M_inv", "trace M^-1 (A-optimality)", "A-optimality",
                  {"color": "tab:green", "ls": "-.", "lw": 1.5}, None, 2),
        Criterion("E", "max", "s_min", "smallest singular value s_L (E-optimality, SVD approach)",
                  "SVD approach (E-optimality)", {"color": "tab:purple", "ls": ":", "lw": 2.0},
                  e_objective, 3, polished=True),
        Criterion("T", "max", "trace_M", "trace M (T-optimality)", "T-optimality",
                  {"color": "tab:brown", "ls": (0, (5, 1, 1, 1)), "lw": 1.5}, None, 4),
        Criterion("condition", "min", "condition", "condition number s_1/s_L", "Condition number",
                  {"color": "tab:gray", "ls": (0, (3, 1)), "lw": 1.5}, condition_objective, 5, polished=True),
    )
}
