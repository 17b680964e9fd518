"""Weighted nonlinear least squares on the one measurement model: Levenberg-Marquardt.

The identification of a robot, from measured data (:mod:`casadi_design.identification`) and
in every simulated calibration of ``casadi-design validate`` (:mod:`casadi_design.virtual`):
minimise ``|W (y - h(X))|^2`` with ``h(X) = model.measurement(q_i, F_i, X, ref_i)`` stacked over
the experiments (whitened values, noise ``sigma`` per value, so ordinary least squares is the
weighted least squares of the noise model) and ``W`` an optional 0/1 mask of the values that
were measured (a marker the tracker did not see). The Jacobian of each trial is the Taylor
expansion ``J(X) = J0 + sum_l X_l dJ/dX_l`` at X = 0 (:func:`taylor_jacobian`), exact to
``O(|X|^2)``; the residuals are the exact model's, so the iterations converge to the exact
least-squares estimate.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..mapped import evaluate
from ..models import CalibrationModel

#: Levenberg-Marquardt: converged when the Gauss-Newton correction moves the model's
#: prediction of the measurements by less than this fraction of sigma (1e-3: changes the
#: error variance by ~1e-6 relative, and stays above the rounding floor of the cost,
#: ~sqrt(|r| 1e-16 m) ~ 1e-6 sigma at sigma = 0.1 mm).
LM_TOL = 1e-3
LM_MAX_ITERATIONS = 100
LM_LAMBDA0 = 1e-3


def nominal_poses(model: CalibrationModel, Q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """References of the nominal robot (``X = 0``, no deflection), shape (N, 12): the
    measurement references of a plan ``(Q, F)`` and the targets of the test poses."""
    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    return evaluate(model.pose, Q, np.asarray(F, float).reshape(len(Q), model.nF),
                    np.zeros((len(Q), model.L)))[0][:, :, 0]


@dataclass(frozen=True)
class Identification:
    """How the parameters were identified: method, iterations used, trials not converged."""

    method: str
    iterations: int
    non_converged: int

    def as_dict(self) -> dict:
        return {"method": self.method, "iterations": self.iterations,
                "non_converged": self.non_converged}


@functools.lru_cache(maxsize=8)
def measurement_slopes(model: CalibrationModel) -> ca.Function:
    """``(q, F, X, ref, u) -> (J, dJ u)``: ``J = dy/dX`` of ``model.measurement`` (d x L,
    physical X) and its derivative in the direction u (d x L), derived once per model."""
    q, F = ca.SX.sym("q", model.n), ca.SX.sym("F", model.nF)
    X, ref, u = ca.SX.sym("X", model.L), ca.SX.sym("ref", 12), ca.SX.sym("u", model.L)
    y, _ = model.measurement(q, F, X, ref)
    J = ca.jacobian(y, X)
    return ca.Function("slopes", [q, F, X, ref, u], [J, ca.jtimes(J, X, u)],
                       ["q", "F", "X", "ref", "u"], ["J", "dJ_u"])


def taylor_jacobian(model: CalibrationModel, Q: np.ndarray, F: np.ndarray,
                    ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``J0`` (m d, L) and ``T`` (m d, L, L), ``T[k, i, l] = dJ0[k, i] / dX_l``, of a plan at
    X = 0: ``J(X) = J0 + T X + O(|X|^2)``."""
    m, L = Q.shape[0], model.L
    fn = measurement_slopes(model)
    J, dJ = evaluate(fn, np.repeat(Q, L, axis=0), np.repeat(F, L, axis=0), np.zeros((m * L, L)),
                     np.repeat(ref, L, axis=0), np.tile(np.eye(L), (m, 1)))
    d = J.shape[1]
    J0 = J.reshape(m, L, d, L)[:, 0].reshape(m * d, L)
    return J0, dJ.reshape(m, L, d, L).transpose(0, 2, 3, 1).reshape(m * d, L, L)


def identify_nonlinear(model: CalibrationModel, Q: np.ndarray, F: np.ndarray, ref: np.ndarray,
                       y: np.ndarray, sigma: float, max_iterations: int = LM_MAX_ITERATIONS,
                       mask: np.ndarray | None = None) -> tuple[np.ndarray, Identification]:
    """Levenberg-Marquardt on ``model.measurement``, every trial at once, from ``X = 0``.

    Minimises ``|y - h(X)|^2`` with ``h(X) = model.measurement(q_i, F_i, X, ref_i)`` stacked over
    the plan's ``Q`` (m, n), ``F`` (m, nF) and nominal references ``ref`` (m, 12), with the
    Jacobian ``J0 + T X`` of :func:`taylor_jacobian`. Step:
    ``(H + lambda diag H) dX = J^T r`` with ``H = J^T J``, solved with the parameters scaled by
    the column norms of ``J`` at ``X = 0`` (the same for every trial), so that lengths, angles
    and compliances share one scale. A trial has converged when its Gauss-Newton correction
    changes the predicted measurements by at most ``LM_TOL sigma`` (``sqrt(g^T H^-1 g) <= LM_TOL
    sigma``, ``g = J^T r``).

    ``mask`` : ndarray of bool, shape (m d,): the values that were measured (default all); the
    others (NaN allowed in ``y``) leave the residuals and the Jacobian.

    Returns
    -------
    X : ndarray, shape (trials, L), physical parameters.
    report : :class:`Identification` (trials still not converged after ``max_iterations``)
    """
    trials, m, L = y.shape[0], Q.shape[0], model.L
    J0, T = taylor_jacobian(model, Q, F, ref)
    w = None if mask is None else np.asarray(mask, dtype=float)
    if w is not None:
        y, J0, T = np.where(w > 0, y, 0.0), J0 * w[:, None], T * w[:, None, None]

    def residual(X: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = len(which)
        h = evaluate(model.measurement, np.tile(Q, (t, 1)), np.tile(F, (t, 1)),
                     np.repeat(X, m, axis=0), np.tile(ref, (t, 1)))[0]
        h = h.reshape(t, -1) if w is None else h.reshape(t, -1) * w
        return y[which] - h, J0 + np.einsum("kil,tl->tki", T, X)

    X = np.zeros((trials, L))
    r, J = residual(X, np.arange(trials))
    norms = np.linalg.norm(J0, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    J = J / scale  # J is now d h / d (scale X): unit columns at X = 0
    cost = np.sum(r**2, axis=1)
    lam = np.full(trials, LM_LAMBDA0)
    active = np.ones(trials, dtype=bool)
    iterations = 0
    while active.any() and iterations < max_iterations:
        iterations += 1
        a = np.flatnonzero(active)
        H = np.einsum("tki,tkj->tij", J[a], J[a])
        g = np.einsum("tki,tk->ti", J[a], r[a])
        gn = np.linalg.solve(H, g[..., None])[..., 0]
        done = np.sqrt(np.maximum(np.einsum("ti,ti->t", g, gn), 0.0)) <= LM_TOL * sigma
        active[a[done]] = False
        a, H, g = a[~done], H[~done], g[~done]
        if not a.size:
            break
        damped = H + lam[a, None, None] * (np.eye(L) * np.diagonal(H, axis1=1, axis2=2)[:, None, :])
        trial_X = X[a] + np.linalg.solve(damped, g[..., None])[..., 0] / scale
        r_new, J_new = residual(trial_X, a)
        J_new /= scale
        better = np.sum(r_new**2, axis=1) < cost[a]
        ok = a[better]
        X[ok], r[ok], J[ok] = trial_X[better], r_new[better], J_new[better]
        cost[ok] = np.sum(r[ok] ** 2, axis=1)
        lam[ok] /= 10.0
        lam[a[~better]] *= 10.0
    return X, Identification("Levenberg-Marquardt", iterations, int(active.sum()))
