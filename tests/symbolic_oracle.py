"""Test oracle: the symbolic formulation of test-pose, D, A and T (one CasADi graph of M).

The product solves these criteria in the reduced space (:mod:`casadi_design.reduced`); here
they are posed on the lifted builder of E and condition (:func:`casadi_design.nlp.lifted_nlp`)
with CasADi's own exact derivatives, to check the reduced space's values and derivatives.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from casadi_design.criteria import Objective
from casadi_design.nlp import B0_at_test_poses, DesignNLP, lifted_nlp


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


def t_objective(M: ca.SX, B0: np.ndarray) -> Objective:
    """``min -trace M``."""
    return _no_aux(-ca.trace(M))


OBJECTIVES = {"test-pose": test_pose_objective, "D": d_objective, "A": a_objective, "T": t_objective}


def symbolic_nlp(problem, criterion: str, m: int, B0: np.ndarray | None = None) -> DesignNLP:
    """The symbolic NLP of a reduced-space criterion (same x, g, bounds and scale)."""
    B0 = B0_at_test_poses(problem) if B0 is None else B0
    return lifted_nlp(problem, criterion, OBJECTIVES[criterion], m, B0)
