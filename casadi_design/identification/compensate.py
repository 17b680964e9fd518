"""Compensation at the test poses: the commands that put the identified robot on its targets.

At test pose ``(q0_j, F0_j)`` the target is the nominal pose ``model.pose(q0_j, F0_j, 0)``;
the corrected command ``q_c`` solves ``model.accuracy(q_c, F0_j, X_hat, target) = 0`` (the
``[test_poses].components`` rows of the identified robot under the machining wrench) by
Newton-chord steps with ``de/dq`` derived once from ``model.accuracy``
(:func:`accuracy_jacobian`). The true robot's residual error is then
``model.accuracy(q_c, F0_j, X_true, target)``. The compensation of a robot identified from
measured data (:mod:`casadi_design.identification`) and of every simulated calibration
(:mod:`casadi_design.virtual`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..calibration.models import CalibrationModel
from ..robot.mapped import evaluate
from ..runtime.cache import memoised

#: Compensation: converged when the identified model misses the target by at most
#: this fraction of sigma, or when the joint step falls below COMPENSATION_STEP_TOL (rad, m).
COMPENSATION_TOL = 1e-6
COMPENSATION_STEP_TOL = 1e-12
COMPENSATION_MAX_ITERATIONS = 20
#: Newton-chord: the Jacobian of a case is refreshed when a step shrinks its error by less
#: than this factor (near the nominal robot a chord step shrinks it a thousandfold).
CHORD_RATE = 0.1


@memoised(8)
def accuracy_jacobian(model: CalibrationModel) -> ca.Function:
    """``(q, F, X, ref) -> (e, de/dq)`` of ``model.accuracy`` (shapes r and r x n), derived once
    per model."""
    q, F = ca.SX.sym("q", model.n), ca.SX.sym("F", model.nF)
    X, ref = ca.SX.sym("X", model.L), ca.SX.sym("ref", 12)
    e, _ = model.accuracy(q, F, X, ref)
    return ca.Function("de", [q, F, X, ref], [e, ca.jacobian(e, q)],
                       ["q", "F", "X", "ref"], ["e", "de_dq"])


def compensate(model: CalibrationModel, q0: np.ndarray, F0: np.ndarray, target: np.ndarray,
               X: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Corrected commands: the identified models ``X`` put the frame on the targets.

    Solves ``e(q_c, F0_j, X, target_j) = 0`` with ``e = model.accuracy`` from ``q_c = q0_j``
    for N = trials x s stacked cases at once (case ``t s + j``: test pose j, parameters
    ``X[t s + j]``), by minimum-norm Newton-chord steps ``q_c -= pinv(J) e``: ``J`` is first
    ``de/dq`` of the nominal robot at test pose j (computed once per pose), and is replaced by
    ``de/dq`` at the current ``(q_c, X)`` (a Newton step) for every case whose ``|e|`` did not
    shrink by ``CHORD_RATE`` in its last step. Near the nominal robot a chord step gains a
    factor ~``1 / (|X| + |q_c - q0|)`` (thousands) for one evaluation of ``model.accuracy``;
    far from it the Newton steps take over. A case is done when ``|e| <= COMPENSATION_TOL
    sigma`` or its step is below ``COMPENSATION_STEP_TOL``.

    Parameters
    ----------
    q0 : ndarray, shape (s, n), rad: the test poses;  F0 : ndarray, shape (s, nF), N: their
        machining wrenches
    target : ndarray, shape (s, 12): nominal poses at ``q0`` (``model.pose(q0, F0, 0)``)
    X : ndarray, shape (N, L), N a multiple of s: identified (physical) parameters per case
    sigma : float, m: measurement noise, the scale of the tolerance

    Returns
    -------
    q_c : ndarray, shape (N, n)
    done : ndarray of bool, shape (N,): False where the iteration did not converge in
        ``COMPENSATION_MAX_ITERATIONS`` steps (the identified model cannot reach the target).
    model_residual : float, m (rad): largest remaining ``|e|`` of the identified model over
        the converged cases, below the tolerance unless the required rows cannot all be met
        with n joints.
    """
    jac = accuracy_jacobian(model)
    q0, F0, target = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (q0, F0, target))
    s, N = len(q0), len(X)
    if N % s:
        raise ValueError(f"compensate: {N} parameter vectors for {s} test poses; give trials x s")
    _, J0 = evaluate(jac, q0, F0.reshape(s, model.nF), np.zeros((s, model.L)), target)
    P = np.tile(np.linalg.pinv(J0), (N // s, 1, 1))
    F0, target = np.tile(F0.reshape(s, model.nF), (N // s, 1)), np.tile(target, (N // s, 1))
    qc = np.tile(q0, (N // s, 1))
    done = np.zeros(N, dtype=bool)
    miss = np.zeros(N)
    last = np.full(N, np.inf)
    for _ in range(COMPENSATION_MAX_ITERATIONS):
        a = np.flatnonzero(~done)
        e = evaluate(model.accuracy, qc[a], F0[a], X[a], target[a])[0]
        miss[a] = np.linalg.norm(e[..., 0], axis=1)
        met = miss[a] <= COMPENSATION_TOL * sigma
        slow = ~met & (miss[a] > CHORD_RATE * last[a])
        if slow.any():  # Newton steps where the chord contracts too slowly
            w = a[slow]
            P[w] = np.linalg.pinv(evaluate(jac, qc[w], F0[w], X[w], target[w])[1])
        last[a] = miss[a]
        step = -(P[a] @ e)[..., 0]
        stop = met | (np.max(np.abs(step), axis=1) <= COMPENSATION_STEP_TOL)
        done[a[stop]] = True
        qc[a[~stop]] += step[~stop]
        if done.all():
            break
    return qc, done, float(np.max(miss[done], initial=0.0))
