"""Weighted nonlinear least squares on the one measurement model: scipy's trust region.

The identification of a robot, from measured data (:mod:`casadi_design.identification`) and
in every simulated calibration of ``casadi-design validate`` (:mod:`casadi_design.virtual`):
minimise ``sum_k rho(|r_k / sigma|^2)`` with ``r = W (y - h(X))``, ``h(X) =
model.measurement(q_i, F_i, X, ref_i)`` stacked over the experiments (whitened values, noise
``sigma`` per value, so ordinary least squares is the weighted least squares of the noise
model), ``W`` an optional 0/1 mask of the values that were measured (a marker the tracker did
not see) and ``rho`` the loss: ``linear`` (least squares) or a robust loss of
``scipy.optimize.least_squares`` (``soft_l1``, ``huber``, ``cauchy``) that down-weights
residuals beyond ``LOSS_SCALE_SIGMA`` sigma (a bad shot).

The solver is ``scipy.optimize.least_squares`` (MINPACK's Levenberg-Marquardt for least squares,
trust-region reflective for a robust loss) on the scaled problem:
residuals in sigma, parameters in the metres they move the measurements by at X = 0 (the
column norms of ``J``), so that lengths, angles and compliances share one scale and the
standard tests (``ftol``, ``xtol``, ``gtol`` = ``LSQ_TOL``) mean the same for every robot. The
residuals are always the exact model's. The Jacobian is

* ``"exact"``: ``dh/dX`` at each iterate (CasADi, :func:`measurement_jacobian`), for measured
  data, whatever the size of the errors;
* ``"taylor"``: its expansion ``J0 + sum_l X_l dJ/dX_l`` at X = 0 (:func:`taylor_jacobian`),
  exact to ``O(|X|^2)``, derived once per plan: for the thousands of simulated calibrations of
  ``validate`` (a model with deflections costs 15x its residuals for the exact ``dh/dX``). The
  stop tests hold with it too (the cost stops falling); the estimate differs from the exact
  least squares by ``O(|X|^2)`` of the Jacobian, 1e-7 relative at the default spreads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import casadi as ca
import numpy as np

from ..calibration.models import CalibrationModel
from ..errors import ProblemError
from ..robot.mapped import EXACT, Stacked, evaluate
from ..runtime.cache import memoised

T = TypeVar("T")
#: Losses of ``--loss``: scipy.optimize.least_squares's names.
LOSSES = ("linear", "soft_l1", "huber", "cauchy")
#: A robust loss treats residuals beyond this many sigma as bad shots (scipy's ``f_scale``).
LOSS_SCALE_SIGMA = 3.0
#: ``ftol``, ``xtol`` and ``gtol`` of the scaled problem: the cost's relative change, the
#: step relative to the parameters (in sigma) and the gradient (sigma^2) at which the fit stops.
LSQ_TOL = 1e-10
#: Largest number of model evaluations of one fit (a fit from X = 0 takes 3 to 10).
LSQ_MAX_EVALUATIONS = 100
#: The Jacobians of :func:`identify_nonlinear` (module docstring).
JACOBIANS = ("exact", "taylor")


def pose_parts(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotations ``R`` (N, 3, 3) and positions ``p`` (N, 3), m, of poses (N, 12) as
    :attr:`CalibrationModel.pose` gives them (``vec(R)`` column-major, then ``p``)."""
    return poses[:, :9].reshape(-1, 3, 3).transpose(0, 2, 1), poses[:, 9:12]


def frame_poses(model: CalibrationModel, Q: np.ndarray, F: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The measured frame's rotation ``R`` (N, 3, 3) and position ``p`` (N, 3), m, of robot
    ``X`` (fit parameters; one row per configuration, (N, L), or one for all) at the
    configurations ``Q`` under the loads ``F`` (deflected, under the robot's weight too where
    the model has it)."""
    X = np.asarray(X, dtype=float)
    rows = X if X.ndim == 2 else np.tile(X, (len(Q), 1))
    return pose_parts(evaluate(model.pose, Q, np.asarray(F, float).reshape(len(Q), model.nF), rows)[0][:, :, 0])


def nominal_poses(model: CalibrationModel, Q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """References of the nominal robot (``X = 0``, no deflection), shape (N, 12): the
    measurement references of a plan ``(Q, F)`` and the targets of the test poses."""
    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    return evaluate(model.pose, Q, np.asarray(F, float).reshape(len(Q), model.nF),
                    np.zeros((len(Q), model.L)))[0][:, :, 0]


@dataclass(frozen=True)
class Identification:
    """How the parameters were identified: method and loss, the largest number of model
    evaluations of a trial, the trials that stopped without meeting a tolerance."""

    method: str
    iterations: int
    non_converged: int
    loss: str = "linear"

    def as_dict(self) -> dict:
        return {"method": self.method, "loss": self.loss, "evaluations": self.iterations,
                "non_converged": self.non_converged}


@memoised(8)
def measurement_jacobian(model: CalibrationModel) -> ca.Function:
    """``(q, F, X, ref) -> (y, J)``: ``model.measurement`` and ``J = dy/dX`` (d x L, physical
    X), derived once per model."""
    q, F = ca.SX.sym("q", model.n), ca.SX.sym("F", model.nF)
    X, ref = ca.SX.sym("X", model.L), ca.SX.sym("ref", 12)
    y, _ = model.measurement(q, F, X, ref)
    return ca.Function("measurement_jacobian", [q, F, X, ref], [y, ca.jacobian(y, X)],
                       ["q", "F", "X", "ref"], ["y", "J"])


@memoised(8)
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
    J, dJ = evaluate(measurement_slopes(model), np.repeat(Q, L, axis=0), np.repeat(F, L, axis=0),
                     np.zeros((m * L, L)), np.repeat(ref, L, axis=0), np.tile(np.eye(L), (m, 1)))
    d = J.shape[1]
    J0 = J.reshape(m, L, d, L)[:, 0].reshape(m * d, L)
    return J0, dJ.reshape(m, L, d, L).transpose(0, 2, 3, 1).reshape(m * d, L, L)


def expanded(X: np.ndarray, rounds: np.ndarray, nf: int, L: int) -> np.ndarray:
    """Each row's model parameters (m, L) from a fit's parameters ``X`` (L + (R - 1) nf: the
    model's, then the ``nf`` frame parameters of rounds 1..R-1): row i takes the frame of its
    ``rounds[i]`` as its first ``nf``."""
    rows = np.tile(X[:L], (len(rounds), 1))
    later = rounds > 0
    if later.any():
        rows[later, :nf] = X[L:].reshape(-1, nf)[rounds[later] - 1]
    return rows


def contracted(J: np.ndarray, rounds: np.ndarray, nf: int, P: int) -> np.ndarray:
    """``dh/dX`` of the fit's parameters (m, d, P) from each row's ``dh/dX`` of its model
    parameters ``J`` (m, d, L) (:func:`expanded`'s transpose)."""
    m, d, L = J.shape
    out = np.zeros((m, d, P))
    out[:, :, :L] = J
    later = np.flatnonzero(rounds > 0)
    for i in later:
        k = L + (rounds[i] - 1) * nf
        out[i, :, k:k + nf] = J[i, :, :nf]
        out[i, :, :nf] = 0.0
    return out


def remembered(f: Callable[[np.ndarray], T]) -> Callable[[np.ndarray], T]:
    """``f`` keeping its last value: scipy's least squares asks for the residuals and the
    Jacobian at the same x one after the other, and one evaluation gives both."""
    last: dict = {}

    def at(x: np.ndarray) -> T:
        key = x.tobytes()
        if key not in last:
            last.clear()
            last[key] = f(x)
        return last[key]

    return at


def check_loss(loss: str) -> str:
    if loss not in LOSSES:
        raise ProblemError(f"--loss {loss}: allowed: {', '.join(LOSSES)}")
    return loss


def identify_nonlinear(model: CalibrationModel, Q: np.ndarray, F: np.ndarray, ref: np.ndarray,
                       y: np.ndarray, sigma: float, max_iterations: int = LSQ_MAX_EVALUATIONS,
                       mask: np.ndarray | None = None, loss: str = "linear",
                       X0: np.ndarray | None = None, jacobian: str = "exact",
                       prior_std: np.ndarray | None = None,
                       frames: tuple[np.ndarray, int] | None = None) -> tuple[np.ndarray, Identification]:
    """Fit X to each row of ``y`` (module docstring), from ``X0`` (default 0), with the
    ``jacobian`` of ``JACOBIANS``.

    Parameters
    ----------
    Q : ndarray, shape (m, n), rad (m);  F : ndarray, shape (m, nF), N (N m);
    ref : ndarray, shape (m, 12): nominal references of the rows.
    y : ndarray, shape (trials, m d): whitened measured values (m), one fit per row.
    sigma : float, m: noise per value (> 0; the scale of the tests and of a robust loss).
    mask : ndarray of bool, shape (m d,): the values that were measured (default all); the
        others (NaN allowed in ``y``) leave the residuals and the Jacobian.
    max_iterations : largest number of model evaluations of one fit.
    prior_std : ndarray, shape (L,), physical units: the standard deviation of a zero-mean
        normal prior on each parameter (inf: none); the fit is then the MAP estimate,
        ``min |r / sigma|^2 + |X / prior_std|^2``.
    frames : ``(round, nf)``: the rows were measured in several frames, row i in frame
        ``round[i]`` (0..R-1), whose parameters are the first ``nf`` of X; the fit's
        parameters are then X followed by the ``nf`` frame parameters of rounds 1..R-1
        (:func:`expanded`).

    Returns
    -------
    X : ndarray, shape (trials, L + (R - 1) nf), physical parameters.
    report : :class:`Identification`.
    """
    from scipy.optimize import least_squares  # imported here: scipy.optimize takes ~0.3 s

    check_loss(loss)
    y = np.atleast_2d(np.asarray(y, dtype=float))
    trials, m, L = y.shape[0], Q.shape[0], model.L
    rounds, nf = (np.zeros(m, dtype=int), 0) if frames is None else (np.asarray(frames[0]), frames[1])
    P = L + (int(rounds.max(initial=0))) * nf  # the fit's parameters
    w = np.ones(y.shape[1]) if mask is None else np.asarray(mask, dtype=float)
    y = np.where(w > 0, y, 0.0)
    if jacobian not in JACOBIANS:
        raise ValueError(f"identify_nonlinear: jacobian {jacobian!r}; allowed: {', '.join(JACOBIANS)}")
    X0 = np.zeros((trials, P)) if X0 is None else np.broadcast_to(np.asarray(X0, float), (trials, P))
    s = max(float(sigma), np.finfo(float).tiny)
    if jacobian == "exact":
        fn = measurement_jacobian(model)

        def model_at(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            h, J = evaluate(fn, Q, F, expanded(X, rounds, nf, L), ref, threads=1)
            return h.reshape(-1) * w / s, contracted(J, rounds, nf, P).reshape(-1, P) * w[:, None] / s

        _, J0 = model_at(np.zeros(P))
    else:
        Ja, T = taylor_jacobian(model, Q, F, ref)
        J0, T = Ja * w[:, None] / s, T * w[:, None, None] / s

        # the same m rows at every evaluation of every trial: one kept buffer (the same bits)
        measure = Stacked(model.measurement, m) if m <= EXACT else \
            (lambda *rows: evaluate(model.measurement, *rows, threads=1))

        def model_at(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            h = measure(Q, F, np.tile(X, (m, 1)), ref)[0]
            return h.reshape(-1) * w / s, J0 + T @ X
    norms = np.linalg.norm(J0, axis=0)
    x_scale = 1.0 / (s * np.where(norms > 0, norms, 1.0))  # parameter units per m of the values
    if prior_std is not None:
        weight = np.concatenate([1.0 / np.asarray(prior_std, dtype=float), np.zeros(P - L)])  # 0: no prior
        plain = model_at

        def model_at(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            h, J = plain(X)
            return np.concatenate([h, -weight * X]), np.vstack([J, -np.diag(weight)])

        y = np.hstack([y, np.zeros((trials, P))])
    # MINPACK's Levenberg-Marquardt (a trust region in C) for least squares, 1.4x faster than
    # the trust-region reflective method at the same optimum; trf for the robust losses and
    # for fewer values than parameters, which MINPACK refuses
    method = "lm" if loss == "linear" and J0.shape[0] >= L else "trf"
    X = np.empty((trials, P))
    evaluations, stopped = 0, 0
    for t in range(trials):
        target, at = y[t] / s, remembered(model_at)

        found = least_squares(lambda x: at(x)[0] - target, X0[t], jac=lambda x: at(x)[1],
                              method=method, x_scale=x_scale, loss=loss, f_scale=LOSS_SCALE_SIGMA,
                              ftol=LSQ_TOL, xtol=LSQ_TOL, gtol=LSQ_TOL, max_nfev=max_iterations)
        X[t] = found.x
        evaluations = max(evaluations, int(found.nfev))
        stopped += int(found.status <= 0)
    return X, Identification(f"trust-region least squares (scipy {method}, {jacobian} Jacobian)",
                             evaluations, stopped, loss)
