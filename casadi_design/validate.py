"""Virtual calibration: check the predicted accuracy by simulating the whole calibration.

For a plan ``{(q_i, F_i)}, i = 1..m`` the design step predicts the RMS error after
compensation at each test pose, ``sqrt(rho_j)`` with ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``
(m^2, ../shared/paper/MATH.md sections 1-3). That prediction rests on the linearised model
``dp = B X``. Here every step of a real calibration is simulated on the *nonlinear* model,
``N`` times:

1. a true robot: nominal geometry plus random errors of the identified geometric parameters
   ``Pi`` (normal, std :class:`ErrorSpreads`), and random true compliances ``k`` (log-normal
   around a nominal value);
2. the plan's measurements: the full forward kinematics ``placement(q + dq, Pi)`` with the
   compliant joint deflection ``dq = diag(k) J(q + dq, Pi)^T W`` (a fixed point; ``W`` the
   6-D wrench of ``F`` at the frame origin, world-aligned), plus noise ``N(0, sigma^2)``;
3. identification: linear least squares ``k = (S^T S)^-1 S^T y`` (elasto-static case),
   Levenberg-Marquardt on the nonlinear model otherwise;
4. compensation: at each test pose ``(q0_j, F0_j)`` the command ``q_c`` for which the
   identified model puts the frame on the nominal target, deflection under ``F0_j`` included;
   the residual error is the true robot's deviation from the target at ``q_c`` (the
   ``[test_poses].components`` rows);
5. the empirical RMS of the residual error over the trials, next to ``sqrt(rho_j)``, with a
   chi-square confidence interval.

The deviation of a pose ``(R, p)`` from a reference ``(R_r, p_r)`` is
``(p - p_r, vee(R R_r^T - R_r R^T) / 2)`` (m, rad): to first order the world-aligned twist
of :mod:`casadi_design.symbolic`, so ``d deviation / d X = B`` at ``X = 0``.

Every trial of a plan runs at once: CasADi functions mapped over the stacked trials, numpy
for the batched linear algebra. Plans with the same m share their true robots and noise draws
(common random numbers), which sharpens the comparison between criteria.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from statistics import NormalDist

import casadi as ca
import numpy as np

from .errors import DesignError, ProblemError
from .measures import information_matrix, score_plan
from .models import CalibrationModel
from .problem import Problem, load_problem
from .results import write_atomic
from .solve import Design
from .symbolic import twist_jacobian

#: Fixed-point iterations of the joint deflection ``dq = diag(k) J(q + dq)^T W``: the update
#: shrinks by ~``k |W| reach`` per iteration, so 5 reach DEFLECTION_TOL up to ``k |W| reach``
#: ~ 0.01 (k = 1e-4 rad/(N m) under 100 N at 1 m: 100 times a stiff industrial joint).
DEFLECTION_ITERATIONS = 5
#: Largest last fixed-point update (rad, or m for prismatic joints) accepted for the true robot.
DEFLECTION_TOL = 1e-9
#: Levenberg-Marquardt: converged when the Gauss-Newton correction moves the model's
#: prediction of the measurements by less than this fraction of sigma (1e-3: changes the
#: error variance by ~1e-6 relative, and stays above the rounding floor of the cost,
#: ~sqrt(|r| 1e-16 m) ~ 1e-6 sigma at sigma = 0.1 mm).
LM_TOL = 1e-3
LM_MAX_ITERATIONS = 100
LM_LAMBDA0 = 1e-3
#: Compensation (Newton): converged when the identified model misses the target by at most
#: this fraction of sigma, or when the joint step falls below COMPENSATION_STEP_TOL (rad, m).
COMPENSATION_TOL = 1e-6
COMPENSATION_STEP_TOL = 1e-12
COMPENSATION_MAX_ITERATIONS = 20
#: Level of the confidence intervals of the empirical RMS errors.
CONFIDENCE = 0.95


@dataclass(frozen=True)
class ErrorSpreads:
    """How far the simulated true robots lie from the nominal one.

    Attributes
    ----------
    length_m : float, m
        Std of the translation errors (``.tx``, ``.ty``, ``.tz``, prismatic offsets).
    angle_rad : float, rad
        Std of the rotation errors (``.rx``, ``.ry``, ``.rz``, revolute offsets).
    k_nominal : float, rad/(N m) (m/N for prismatic joints)
        Median of the true joint compliances.
    k_log_spread : float
        Std of ``log k``: ``k = k_nominal exp(k_log_spread z)``, ``z ~ N(0, 1)``.
    """

    length_m: float = 0.5e-3
    angle_rad: float = math.radians(0.05)
    k_nominal: float = 1e-6
    k_log_spread: float = 0.2

    def __post_init__(self):
        for name, value in self.as_dict().items():
            if not (math.isfinite(value) and value >= 0):
                raise ProblemError(
                    f"virtual calibration: error spread {name} = {value}; give a finite value >= 0")

    def scaled(self, factor: float) -> ErrorSpreads:
        """Spreads with the lengths, angles and nominal compliance multiplied by ``factor``."""
        return replace(self, length_m=self.length_m * factor, angle_rad=self.angle_rad * factor,
                       k_nominal=self.k_nominal * factor)

    def as_dict(self) -> dict:
        return {"length_m": self.length_m, "angle_rad": self.angle_rad,
                "k_nominal": self.k_nominal, "k_log_spread": self.k_log_spread}


@dataclass(frozen=True, eq=False)
class Plan:
    """The experiments of one design.

    Attributes
    ----------
    Q : ndarray, shape (m, n), rad (m for prismatic joints)
    F : ndarray, shape (m, nF), N (N m)
    """

    criterion: str
    m: int
    Q: np.ndarray
    F: np.ndarray


@dataclass(frozen=True, eq=False)
class NonlinearModel:
    """The nonlinear twin of a :class:`~casadi_design.models.CalibrationModel`.

    Inputs of every function: ``q`` (n, rad), ``F`` (nF, N), ``X`` (L, the model's parameter
    vector: geometric errors in m and rad, compliances) and, for deviations, ``ref`` (12: the
    column-major rotation and the position, m, of the reference pose). ``step`` is the largest
    last update of the deflection fixed point (rad, or m for prismatic joints).

    Attributes
    ----------
    pose : casadi.Function
        ``(q, F, X) -> ref``: the deflected frame pose as a reference vector.
    measurement : casadi.Function
        ``(q, F, X, ref) -> (y, step)``: the measured deviation rows (d) from ``ref``.
    measurement_jacobian : casadi.Function
        ``(q, F, X, ref) -> (y, dy/dX)``: shapes d and d x L.
    accuracy : casadi.Function
        ``(q, F, X, ref) -> (e, step)``: the required deviation rows (r) from ``ref``.
    accuracy_jacobian : casadi.Function
        ``(q, F, X, ref) -> (e, de/dq)``: shapes r and r x n.
    """

    model: CalibrationModel
    pose: ca.Function
    measurement: ca.Function
    measurement_jacobian: ca.Function
    accuracy: ca.Function
    accuracy_jacobian: ca.Function


def nonlinear_model(model: CalibrationModel) -> NonlinearModel:
    """Build the nonlinear measurement model of ``model`` (see :class:`NonlinearModel`)."""
    kin = model.kinematics
    robot = kin.robot
    q = ca.SX.sym("q", robot.n)
    F = ca.SX.sym("F", model.nF)
    X = ca.SX.sym("X", model.L)
    ref = ca.SX.sym("ref", 12)
    Pi = ca.SX.zeros(len(kin.parameter_names))
    k = ca.SX.zeros(robot.n)
    for i, name in enumerate(model.parameter_names):
        if name in kin.parameter_names:
            Pi[kin.parameter_names.index(name)] = X[i]
        else:  # "k.<joint>"
            k[robot.joints.index(name[2:])] = X[i]
    W = ca.SX.zeros(6)
    for i, r in enumerate(model.force_rows):
        W[r] = F[i]

    qs, Pis = ca.SX.sym("qs", robot.n), ca.SX.sym("Pis", Pi.numel())
    Rs, ps = kin.placement(qs, Pis)
    jacobian = ca.Function("J", [qs, Pis], [twist_jacobian(Rs, ps, qs)])
    dq, step = ca.SX.zeros(robot.n), ca.SX(0)
    if model.nF:
        for _ in range(DEFLECTION_ITERATIONS):
            new = k * (jacobian(q + dq, Pi).T @ W)
            dq, step = new, ca.mmax(ca.fabs(new - dq))
    R, p = kin.placement(q + dq, Pi)
    A = R @ ca.reshape(ref[0:9], 3, 3).T
    S = (A - A.T) / 2
    dev = ca.vertcat(p - ref[9:12], S[2, 1], S[0, 2], S[1, 0])
    y, e = dev[list(model.measured_rows)], dev[list(model.accuracy_rows)]
    args, names = [q, F, X, ref], ["q", "F", "X", "ref"]
    return NonlinearModel(
        model=model,
        pose=ca.Function("pose", [q, F, X], [ca.vertcat(ca.vec(R), p)], names[:3], ["ref"]),
        measurement=ca.Function("y", args, [y, step], names, ["y", "step"]),
        measurement_jacobian=ca.Function("dy", args, [y, ca.jacobian(y, X)], names, ["y", "dy_dX"]),
        accuracy=ca.Function("e", args, [e, step], names, ["e", "step"]),
        accuracy_jacobian=ca.Function("de", args, [e, ca.jacobian(e, q)], names, ["e", "de_dq"]),
    )


@functools.lru_cache(maxsize=32)
def _mapped(fn: ca.Function, N: int) -> ca.Function:
    return fn.map(N)


def evaluate(fn: ca.Function, *rows: np.ndarray) -> list[np.ndarray]:
    """Evaluate ``fn`` on N stacked inputs at once (CasADi map).

    Parameters
    ----------
    rows : ndarray, shape (N, size of input a), one per input of ``fn``

    Returns
    -------
    list of ndarray, shape (N, rows of output b, columns of output b), one per output
    """
    N = rows[0].shape[0]
    out = _mapped(fn, N)(*[np.ascontiguousarray(np.asarray(a, dtype=float).T) for a in rows])
    out = out if isinstance(out, (list, tuple)) else [out]
    return [np.asarray(o).reshape(fn.size1_out(b), N, fn.size2_out(b)).transpose(1, 0, 2)
            for b, o in enumerate(out)]


def draw_true_parameters(model: CalibrationModel, spreads: ErrorSpreads, trials: int,
                         rng: np.random.Generator) -> np.ndarray:
    """True parameter vectors ``X`` of ``trials`` robots, shape (trials, L).

    Geometric errors: ``N(0, std^2)`` with std ``spreads.length_m`` (m) for translations and
    prismatic offsets, ``spreads.angle_rad`` (rad) for rotations and revolute offsets.
    Compliances: ``k_nominal exp(k_log_spread z)``, ``z ~ N(0, 1)``.
    """
    robot = model.kinematics.robot
    z = rng.standard_normal((trials, model.L))
    X = np.empty_like(z)
    for i, name in enumerate(model.parameter_names):
        owner, what = name.split(".", 1)
        if name not in model.kinematics.parameter_names:  # "k.<joint>"
            X[:, i] = spreads.k_nominal * np.exp(spreads.k_log_spread * z[:, i])
            continue
        prismatic = what == "offset" and robot.model.joints[
            robot.model.getJointId(owner)].shortname().startswith("JointModelP")
        linear = what in ("tx", "ty", "tz") or prismatic
        X[:, i] = (spreads.length_m if linear else spreads.angle_rad) * z[:, i]
    return X


def true_deviation(fn: ca.Function, spreads: ErrorSpreads, *rows: np.ndarray) -> np.ndarray:
    """Deviation rows of N true robots, shape (N, rows of ``fn``), by ``nl.measurement`` or
    ``nl.accuracy``; checks that their deflection fixed point has converged."""
    dev, step = evaluate(fn, *rows)
    worst = float(np.max(step, initial=0.0))
    if worst > DEFLECTION_TOL:
        raise DesignError(
            f"virtual calibration: the joint deflection of the true robots did not converge in "
            f"{DEFLECTION_ITERATIONS} fixed-point iterations (last update {worst:.2e}); the nominal "
            f"compliance k_nominal = {spreads.k_nominal:g} is too large for the loads; lower it "
            "(--k, --scales)"
        )
    return dev[:, :, 0]


@dataclass(frozen=True)
class Identification:
    """How the parameters were identified: method, iterations used, trials not converged."""

    method: str
    iterations: int
    non_converged: int

    def as_dict(self) -> dict:
        return {"method": self.method, "iterations": self.iterations,
                "non_converged": self.non_converged}


def identify_linear(S: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, Identification]:
    """Least squares ``X = (S^T S)^-1 S^T y`` of every trial at once.

    Parameters
    ----------
    S : ndarray, shape (m d, L): the stacked ``B_i`` of the plan.
    y : ndarray, shape (trials, m d): measured deviations from the nominal model (m, rad).
    """
    return y @ np.linalg.pinv(S).T, Identification("linear least squares", 1, 0)


def identify_nonlinear(nl: NonlinearModel, Q: np.ndarray, F: np.ndarray, ref: np.ndarray,
                       y: np.ndarray, sigma: float,
                       max_iterations: int = LM_MAX_ITERATIONS) -> tuple[np.ndarray, Identification]:
    """Levenberg-Marquardt on the nonlinear model, every trial at once, from ``X = 0``.

    Minimises ``|y - h(X)|^2`` with ``h = nl.measurement`` at the plan's
    ``Q`` (m, n), ``F`` (m, nF) and nominal references ``ref`` (m, 12). Step:
    ``(H + lambda diag H) dX = J^T r`` with ``H = J^T J``. A trial has converged when its
    Gauss-Newton correction changes the predicted measurements by at most ``LM_TOL sigma``
    (``sqrt(g^T H^-1 g) <= LM_TOL sigma``, ``g = J^T r``).

    Returns
    -------
    X : ndarray, shape (trials, L)
    report : :class:`Identification` (trials still not converged after ``max_iterations``)
    """
    trials, m = y.shape[0], Q.shape[0]

    def residual(X: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = len(which)
        h, dh = evaluate(nl.measurement_jacobian, np.tile(Q, (t, 1)), np.tile(F, (t, 1)),
                         np.repeat(X, m, axis=0), np.tile(ref, (t, 1)))
        return y[which] - h.reshape(t, -1), dh.reshape(t, -1, nl.model.L)

    X = np.zeros((trials, nl.model.L))
    r, J = residual(X, np.arange(trials))
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
        damped = H + lam[a, None, None] * (np.eye(H.shape[1]) * np.diagonal(H, axis1=1, axis2=2)[:, None, :])
        trial_X = X[a] + np.linalg.solve(damped, g[..., None])[..., 0]
        r_new, J_new = residual(trial_X, a)
        better = np.sum(r_new**2, axis=1) < cost[a]
        ok = a[better]
        X[ok], r[ok], J[ok] = trial_X[better], r_new[better], J_new[better]
        cost[ok] = np.sum(r[ok] ** 2, axis=1)
        lam[ok] /= 10.0
        lam[a[~better]] *= 10.0
    return X, Identification("Levenberg-Marquardt", iterations, int(active.sum()))


def compensate(nl: NonlinearModel, q0: np.ndarray, F0: np.ndarray, target: np.ndarray,
               X: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Corrected commands: the identified model ``X`` puts the frame on ``target``.

    Newton (minimum-norm steps) on ``e(q_c, F0, X, target) = 0`` with ``e = nl.accuracy`` (the
    ``[test_poses].components`` rows), from ``q_c = q0``, for N stacked cases at once. A case is
    done when ``|e| <= COMPENSATION_TOL sigma`` or its step is below ``COMPENSATION_STEP_TOL``.

    Parameters
    ----------
    q0 : ndarray, shape (N, n), rad;  F0 : ndarray, shape (N, nF), N (machining wrench)
    target : ndarray, shape (N, 12): nominal poses at ``q0`` (see :class:`NonlinearModel`)
    X : ndarray, shape (N, L): identified parameters
    sigma : float, m: measurement noise, the scale of the tolerance

    Returns
    -------
    q_c : ndarray, shape (N, n)
    done : ndarray of bool, shape (N,): False where Newton did not converge in
        ``COMPENSATION_MAX_ITERATIONS`` steps (the identified model cannot reach the target).
    model_residual : float, m (rad): largest remaining ``|e|`` of the identified model over
        the converged cases, below the tolerance unless the required rows cannot all be met
        with n joints.
    """
    qc = np.array(q0, dtype=float)
    done = np.zeros(len(qc), dtype=bool)
    miss = np.zeros(len(qc))
    for _ in range(COMPENSATION_MAX_ITERATIONS):
        a = np.flatnonzero(~done)
        e, de = evaluate(nl.accuracy_jacobian, qc[a], F0[a], X[a], target[a])
        miss[a] = np.linalg.norm(e[..., 0], axis=1)
        step = -(np.linalg.pinv(de) @ e)[..., 0]
        stop = (miss[a] <= COMPENSATION_TOL * sigma) | (np.max(np.abs(step), axis=1) <= COMPENSATION_STEP_TOL)
        done[a[stop]] = True
        qc[a[~stop]] += step[~stop]
        if done.all():
            break
    return qc, done, float(np.max(miss[done], initial=0.0))


def chi2_quantile(p: float, dof: np.ndarray) -> np.ndarray:
    """Quantile of the chi-square law (Wilson-Hilferty): ``k (1 - 2/(9k) + z_p sqrt(2/(9k)))^3``.

    Relative error below 1e-3 at the 2.5 % and 97.5 % points for ``k >= 100`` (1e-2 for
    ``k >= 10``); the intervals here use ``k`` = trials times nu, in the thousands.
    """
    k = np.asarray(dof, dtype=float)
    z = NormalDist().inv_cdf(p)
    return k * (1 - 2 / (9 * k) + z * np.sqrt(2 / (9 * k))) ** 3


def effective_dof(C: np.ndarray) -> np.ndarray:
    """Degrees of freedom ``nu = trace(C)^2 / trace(C^2)`` of ``|e|^2``, ``e ~ N(0, C)``.

    ``|e|^2`` has mean ``trace C = rho`` and is approximated by ``rho / nu chi2(nu)``
    (Satterthwaite); ``C`` of shape (s, r, r). ``nu = 1`` where ``C = 0``.
    """
    square = np.einsum("sij,sji->s", C, C)
    return np.trace(C, axis1=1, axis2=2) ** 2 / np.where(square > 0, square, 1.0) + (square == 0)


def rms_interval(mean_square: np.ndarray, dof: np.ndarray, trials: np.ndarray | int,
                 confidence: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Confidence interval of the RMS error from the mean square of ``trials`` errors (m).

    With ``T = trials nu``, ``T mean_square / rho ~ chi2(T)``, so
    ``sqrt(rho) in [sqrt(T ms / chi2_{(1+c)/2}(T)), sqrt(T ms / chi2_{(1-c)/2}(T))]``.
    """
    T = trials * np.asarray(dof, dtype=float)
    return (np.sqrt(T * mean_square / chi2_quantile((1 + confidence) / 2, T)),
            np.sqrt(T * mean_square / chi2_quantile((1 - confidence) / 2, T)))


@dataclass(frozen=True, eq=False)
class PlanValidation:
    """Predicted and simulated accuracy of one plan at the s test poses.

    Attributes
    ----------
    predicted_rms_m : ndarray, shape (s,), m: ``sqrt(rho_j)``.
    empirical_rms_m : ndarray, shape (s,), m: RMS over the trials of the residual error.
    ci_low_m, ci_high_m : ndarray, shape (s,), m: ``CONFIDENCE`` interval of the true RMS.
    dof : ndarray, shape (s,): effective degrees of freedom of one squared error.
    identification : how X was identified, and its convergence.
    compensation_residual_m : float, m: largest miss of the target by the identified model.
    compensation_failed : int
        (trial, test pose) cases the identified model could not reach; left out of the RMS.
    wall_s : float, s.
    """

    plan: Plan
    predicted_rms_m: np.ndarray
    empirical_rms_m: np.ndarray
    ci_low_m: np.ndarray
    ci_high_m: np.ndarray
    dof: np.ndarray
    identification: Identification
    compensation_residual_m: float
    compensation_failed: int
    wall_s: float

    @property
    def ratio(self) -> np.ndarray:
        """Empirical over predicted RMS error at each test pose (1 where both are 0)."""
        return np.divide(self.empirical_rms_m, self.predicted_rms_m,
                         out=np.ones_like(self.predicted_rms_m), where=self.predicted_rms_m > 0)

    @property
    def worst_relative_error(self) -> float:
        """``max_j |empirical_j / predicted_j - 1|``."""
        return float(np.max(np.abs(self.ratio - 1)))

    @property
    def coverage(self) -> float:
        """Fraction of test poses whose interval holds the predicted ``sqrt(rho_j)``."""
        inside = (self.ci_low_m <= self.predicted_rms_m) & (self.predicted_rms_m <= self.ci_high_m)
        return float(np.mean(inside))

    @property
    def max_ratio(self) -> float:
        """Max over the path of the empirical RMS over max of ``sqrt(rho)``."""
        return float(np.max(self.empirical_rms_m) / np.max(self.predicted_rms_m))


def plan_matrices(problem: Problem, plan: Plan) -> tuple[np.ndarray, np.ndarray]:
    """``B_i`` of the plan, shape (m, d, L), and ``B0_j`` at the test poses, shape (s, r, L)."""
    model, tp = problem.model, problem.test_poses
    B = np.array([model.B_numeric(q, F) for q, F in zip(plan.Q, plan.F)])
    B0 = np.array([model.B_numeric(q, F, accuracy=True) for q, F in zip(tp.q, tp.F)])
    return B, B0


def simulate_plan(problem: Problem, nl: NonlinearModel, plan: Plan, spreads: ErrorSpreads,
                  trials: int, rng: np.random.Generator) -> PlanValidation:
    """Simulate ``trials`` calibrations of ``plan`` and compare with ``sqrt(rho)`` (module doc).

    The empirical mean square at test pose j is ``mean_t |e_tj|^2`` (m^2) over the trials whose
    compensation converged there; its interval uses ``nu_j`` of ``C_j = sigma^2 B0_j M^-1 B0_j^T``.
    """
    t0 = time.perf_counter()
    model, tp, sigma = problem.model, problem.test_poses, problem.sigma_m
    m, d, s = plan.m, len(model.measured_rows), tp.s
    B, B0 = plan_matrices(problem, plan)
    scores = score_plan(B, B0, sigma)
    if not scores.identifiable:
        raise DesignError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: its information "
            "matrix M is singular, the parameters cannot be identified; give a solved plan"
        )
    X_true = draw_true_parameters(model, spreads, trials, rng)

    ref = evaluate(nl.pose, plan.Q, plan.F, np.zeros((m, model.L)))[0][:, :, 0]
    y = true_deviation(nl.measurement, spreads, np.tile(plan.Q, (trials, 1)),
                       np.tile(plan.F, (trials, 1)), np.repeat(X_true, m, axis=0), np.tile(ref, (trials, 1)))
    y = y.reshape(trials, m * d) + sigma * rng.standard_normal((trials, m * d))
    if model.case == "elastostatic":
        X_hat, ident = identify_linear(B.reshape(m * d, model.L), y)
        X_hat = X_hat / model.column_scale  # B is written for the scaled parameters c * X
    else:
        X_hat, ident = identify_nonlinear(nl, plan.Q, plan.F, ref, y, sigma)

    target = np.tile(evaluate(nl.pose, tp.q, tp.F, np.zeros((s, model.L)))[0][:, :, 0], (trials, 1))
    F0 = np.tile(tp.F, (trials, 1))
    qc, done, miss = compensate(nl, np.tile(tp.q, (trials, 1)), F0, target,
                                np.repeat(X_hat, s, axis=0), sigma)
    err = true_deviation(nl.accuracy, spreads, qc, F0, np.repeat(X_true, s, axis=0), target)
    done = done.reshape(trials, s)
    count = done.sum(axis=0)
    if not count.all():
        j = int(np.argmin(count))
        raise DesignError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: no simulated robot "
            f"could be compensated at test pose {j} (its target is out of the identified robots' "
            "reach); reduce the error spreads"
        )
    square = np.sum(err.reshape(trials, s, -1) ** 2, axis=2)
    mean_square = np.sum(np.where(done, square, 0.0), axis=0) / count

    C = sigma**2 * np.einsum("sil,lk,sjk->sij", B0, np.linalg.inv(information_matrix(B)), B0)
    dof = effective_dof(C)
    low, high = rms_interval(mean_square, dof, count)
    return PlanValidation(plan, scores.rms_error_m, np.sqrt(mean_square), low, high, dof, ident, miss,
                          int(done.size - count.sum()), time.perf_counter() - t0)


@dataclass(frozen=True, eq=False)
class Validation:
    """A virtual calibration of every plan of a problem."""

    problem: Problem
    source: str
    trials: int
    seed: int
    spreads: ErrorSpreads
    plans: tuple[PlanValidation, ...]
    wall_s: float


def plan_rng(seed: int, m: int) -> np.random.Generator:
    """Generator of a plan's trials: depends on ``seed`` and ``m`` only (common random numbers)."""
    return np.random.default_rng([seed, m])


def validate(problem: Problem, plans: list[Plan], trials: int = 2000, seed: int = 0,
             spreads: ErrorSpreads = ErrorSpreads(), source: str = "") -> Validation:
    """Virtual calibration of each plan: ``trials`` simulated calibrations (module doc).

    Raises
    ------
    ProblemError
        When ``trials`` is below 2.
    DesignError
        When the deflection or the compensation of the simulated robots does not converge.
    """
    if trials < 2:
        raise ProblemError(f"virtual calibration: trials = {trials}; give at least 2 (e.g. 2000)")
    t0 = time.perf_counter()
    nl = nonlinear_model(problem.model)
    results = tuple(simulate_plan(problem, nl, p, spreads, trials, plan_rng(seed, p.m)) for p in plans)
    return Validation(problem, source, trials, seed, spreads, results, time.perf_counter() - t0)


def plans_from_designs(designs: list[Design]) -> list[Plan]:
    """The plans of solved designs."""
    return [Plan(d.criterion, d.m, np.asarray(d.Q, float), np.asarray(d.F, float)) for d in designs]


def plans_from_results(problem: Problem, path: str | Path) -> list[Plan]:
    """The plans of a ``results.json`` written by ``solve_case.py`` for ``problem``.

    Raises
    ------
    ProblemError
        When the file is missing or unreadable, or was written for another model.
    """
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise ProblemError(f"--results: no such file {path}; solve first: "
                           f"python scripts/solve_case.py {problem.path} --out DIR") from None
    except json.JSONDecodeError as exc:
        raise ProblemError(f"--results: {path} is not valid JSON ({exc}); solve the case again") from None
    model = problem.model
    wanted = {"calibration.parameters": list(model.parameter_names), "sigma_m": problem.sigma_m}
    found = {"calibration.parameters": record.get("calibration", {}).get("parameters"),
             "sigma_m": record.get("sigma_m")}
    for key, value in wanted.items():
        if found[key] != value:
            raise ProblemError(
                f"--results: {path} has {key} = {found[key]!r} but {problem.path} has {value!r}; "
                f"give the results of this problem (python scripts/solve_case.py {problem.path} --out DIR)"
            )
    plans = []
    for i, d in enumerate(record.get("designs", [])):
        Q = np.array([e["q_rad"] for e in d["experiments"]], dtype=float).reshape(d["m"], -1)
        F = np.array([e["force"] for e in d["experiments"]], dtype=float).reshape(d["m"], -1)
        if Q.shape[1] != model.n or F.shape[1] != model.nF:
            raise ProblemError(
                f"--results: {path} designs[{i}] has {Q.shape[1]} joints and {F.shape[1]} force "
                f"components per experiment, {problem.path} has {model.n} and {model.nF}; give the "
                "results of this problem"
            )
        plans.append(Plan(d["criterion"], int(d["m"]), Q, F))
    if not plans:
        raise ProblemError(f"--results: {path} holds no designs; solve the case again")
    return plans


def rankings(validation: Validation) -> dict[int, dict[str, list[str]]]:
    """Per m, the criteria from best to worst by max ``sqrt(rho)`` and by max simulated RMS."""
    def order(group: list[PlanValidation], field: str) -> list[str]:
        return [p.plan.criterion for p in sorted(group, key=lambda p: np.max(getattr(p, field)))]

    out: dict[int, dict[str, list[str]]] = {}
    for m in sorted({p.plan.m for p in validation.plans}):
        group = [p for p in validation.plans if p.plan.m == m]
        out[m] = {"by_measure": order(group, "predicted_rms_m"),
                  "by_simulation": order(group, "empirical_rms_m")}
    return out


def plan_record(pv: PlanValidation) -> dict:
    """One plan's validation as plain data (m)."""
    j = int(np.argmax(pv.empirical_rms_m))
    return {
        "criterion": pv.plan.criterion,
        "m": pv.plan.m,
        "predicted_rms_m": pv.predicted_rms_m.tolist(),
        "empirical_rms_m": pv.empirical_rms_m.tolist(),
        "ci_low_m": pv.ci_low_m.tolist(),
        "ci_high_m": pv.ci_high_m.tolist(),
        "dof": pv.dof.tolist(),
        "max": {"predicted_m": float(np.max(pv.predicted_rms_m)),
                "empirical_m": float(pv.empirical_rms_m[j]), "node": j,
                "ci_low_m": float(pv.ci_low_m[j]), "ci_high_m": float(pv.ci_high_m[j]),
                "ratio": pv.max_ratio},
        "worst_relative_error": pv.worst_relative_error,
        "coverage": pv.coverage,
        "identification": pv.identification.as_dict(),
        "compensation_residual_m": pv.compensation_residual_m,
        "compensation_failed": pv.compensation_failed,
        "wall_s": pv.wall_s,
    }


def validation_record(validation: Validation, study: list[tuple[float, Validation]] = ()) -> dict:
    """The whole ``validation.json`` record (SI units); ``study`` from :func:`linearisation_study`."""
    problem = validation.problem
    return {
        "problem": problem.name,
        "problem_file": problem.path,
        "plans_from": validation.source,
        "case": problem.model.case,
        "parameters": list(problem.model.parameter_names),
        "sigma_m": problem.sigma_m,
        "seed": validation.seed,
        "trials": validation.trials,
        "confidence": CONFIDENCE,
        "spreads": validation.spreads.as_dict(),
        "test_pose_positions_m": problem.test_poses.position_m.tolist(),
        "plans": [plan_record(p) for p in validation.plans],
        "rankings": {str(m): r for m, r in rankings(validation).items()},
        "wall_s": validation.wall_s,
        "linearisation": [
            {"scale": scale, "spreads": v.spreads.as_dict(), "wall_s": v.wall_s,
             "plans": [{"criterion": p.plan.criterion, "m": p.plan.m, "max_ratio": p.max_ratio,
                        "worst_relative_error": p.worst_relative_error,
                        "non_converged": p.identification.non_converged,
                        "compensation_failed": p.compensation_failed} for p in v.plans]}
            for scale, v in study
        ],
    }


def write_validation(path: Path, validation: Validation, study: list[tuple[float, Validation]] = ()) -> dict:
    """Write ``validation.json`` atomically; returns the record."""
    record = validation_record(validation, study)
    write_atomic(Path(path), (json.dumps(record, indent=2) + "\n").encode())
    return record


def linearisation_study(problem: Problem, plans: list[Plan], scales: list[float], trials: int,
                        seed: int = 0, spreads: ErrorSpreads = ErrorSpreads(),
                        source: str = "") -> list[tuple[float, Validation]]:
    """Where the linearised prediction breaks down: validate with every spread times ``scale``.

    The ratio of simulated to predicted error stays near 1 while the true robots are close to
    the nominal one (B evaluated at ``X = 0`` still describes them) and drifts as they move away.
    """
    return [(s, validate(problem, plans, trials, seed, spreads.scaled(s), source)) for s in scales]


def format_report(validation: Validation, study: list[tuple[float, Validation]] = ()) -> str:
    """Per plan: max predicted and simulated RMS error (mm) with the interval, node agreement;
    the rankings; the wall time; and the linearisation study when given."""
    v, sp = validation, validation.spreads
    lines = [
        (f"virtual calibration of {v.problem.name} ({v.problem.model.case}): {v.trials} trials, "
         f"seed {v.seed}, {v.problem.test_poses.s} test poses; errors: length {sp.length_m * 1e3:g} mm, "
         f"angle {math.degrees(sp.angle_rad):g} deg, k {sp.k_nominal:g} (log-std {sp.k_log_spread:g})"),
        (f"{'criterion':<10} {'m':>3} {'max sqrt(rho)':>14} {'max simulated':>14} "
         f"{f'{round(100 * CONFIDENCE)}% interval':>18} {'worst node':>11} {'covered':>8}  identification"),
    ]
    for p in v.plans:
        mx, ident = plan_record(p)["max"], p.identification
        notes = "" if not ident.non_converged else f", {ident.non_converged} trials NOT CONVERGED"
        if p.compensation_failed:
            notes += f"; {p.compensation_failed} (trial, pose) cases NOT COMPENSATED, left out"
        lines.append(
            f"{p.plan.criterion:<10} {p.plan.m:>3} {mx['predicted_m'] * 1e3:>11.4f} mm "
            f"{mx['empirical_m'] * 1e3:>11.4f} mm {mx['ci_low_m'] * 1e3:>8.4f}..{mx['ci_high_m'] * 1e3:.4f} "
            f"{100 * p.worst_relative_error:>10.2f}% {100 * p.coverage:>7.0f}%  "
            f"{ident.method}, {ident.iterations} it.{notes}"
        )
    for m, r in rankings(v).items():
        same = "same" if r["by_measure"] == r["by_simulation"] else "DIFFERENT"
        lines.append(f"m = {m}: ranking by the measure {r['by_measure']}, "
                     f"by simulation {r['by_simulation']} ({same})")
    lines.append(f"wall time {v.wall_s:.2f} s for {len(v.plans)} plans x {v.trials} trials")
    if study:
        lines.append("linearisation, every spread times scale: max simulated / max sqrt(rho), "
                     "worst node |simulated / sqrt(rho) - 1|, (trial, pose) cases not compensated")
        names = [f"{p.plan.criterion} m={p.plan.m}" for p in study[0][1].plans]
        lines.append(f"{'scale':>8}" + "".join(f"{n:>20}" for n in names))
        for scale, s in study:
            cells = [f"{p.max_ratio:.3f} {100 * p.worst_relative_error:4.1f}% {p.compensation_failed}"
                     for p in s.plans]
            lines.append(f"{scale:>8g}" + "".join(f"{c:>20}" for c in cells))
    return "\n".join(lines)


def validation_figure(validation: Validation):
    """Predicted ``sqrt(rho)`` (lines) and simulated RMS error with its interval (markers), mm,
    along the test poses: one panel per m. Returns a ``matplotlib.figure.Figure``."""
    from matplotlib.figure import Figure

    from .plotting import LABELS, STYLES, path_coordinate

    x, xlabel = path_coordinate(validation.problem.test_poses.position_m)
    ms = sorted({p.plan.m for p in validation.plans})
    fig = Figure(figsize=(5.5 * len(ms), 4.5), layout="constrained")
    axes = fig.subplots(1, len(ms), squeeze=False)[0]
    every = max(1, len(x) // 20)
    for ax, m in zip(axes, ms):
        for i, p in enumerate(p for p in validation.plans if p.plan.m == m):
            style = STYLES[p.plan.criterion]
            e = p.empirical_rms_m * 1e3
            ax.plot(x, p.predicted_rms_m * 1e3, label=f"{LABELS[p.plan.criterion]}: sqrt(rho)", **style)
            ax.errorbar(x[::every], e[::every],
                        yerr=np.abs(np.vstack([p.ci_low_m, p.ci_high_m]) * 1e3 - e)[:, ::every],
                        fmt="o", ms=3, capsize=2, color=style["color"],
                        label="simulated RMS and interval" if i == 0 else "_nolegend_")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("RMS error after compensation (mm)")
        ax.set_ylim(bottom=0)
        ax.set_title(f"m = {m}: {validation.trials} virtual calibrations, "
                     f"{round(100 * CONFIDENCE)}% intervals")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    return fig

# --------------------------------------------------------------------------- command line
# casadi-design validate problems/<case>.toml [--results DIR/results.json] [--trials N]
#     [--seed S] [--out DIR] [--scales 1,10,100]
# Without --results the plans are solved first (every criterion and m of the problem file).
# Writes DIR/validation.json and DIR/validation.png / .pdf. Bad input or a failed simulation
# prints one line and exits with code 2.

def _positive_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--scales takes numbers separated by commas, got '{text}'")
    if any(not v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"--scales takes positive numbers, got '{text}'")
    return values


def build_parser() -> argparse.ArgumentParser:
    d = ErrorSpreads()
    parser = argparse.ArgumentParser(prog="casadi-design validate", description=__doc__.splitlines()[0])
    parser.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    parser.add_argument("--results",
                        help="results.json of solve_case.py for this problem (default: solve now)")
    parser.add_argument("--trials", type=int, default=2000,
                        help="simulated calibrations per plan (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulation (default 0)")
    parser.add_argument("--out",
                        help="folder for validation.json and validation.png/.pdf (created if missing)")
    parser.add_argument("--length-mm", type=float, default=d.length_m * 1e3,
                        help=f"std of the translation errors, mm (default {d.length_m * 1e3:g})")
    parser.add_argument("--angle-deg", type=float, default=math.degrees(d.angle_rad),
                        help=f"std of the rotation errors, deg (default {math.degrees(d.angle_rad):g})")
    parser.add_argument("--k", type=float, default=d.k_nominal,
                        help=f"median true compliance, rad/(N m) or m/N (default {d.k_nominal:g})")
    parser.add_argument("--k-log-spread", type=float, default=d.k_log_spread,
                        help=f"std of log k (default {d.k_log_spread:g})")
    parser.add_argument("--scales", type=_positive_list,
                        help="also validate with every spread times each scale, e.g. 1,10,100, "
                             "to see where the linearised prediction breaks down")
    return parser


def run(args: argparse.Namespace) -> int:
    problem = load_problem(args.problem)
    if args.results:
        plans, source = plans_from_results(problem, args.results), str(args.results)
    else:
        from .solve import solve_design

        designs = [solve_design(problem, c, m) for m in problem.m_values for c in problem.criteria]
        plans, source = plans_from_designs(designs), "solved by casadi-design validate"
    spreads = ErrorSpreads(args.length_mm * 1e-3, math.radians(args.angle_deg), args.k, args.k_log_spread)
    t0 = time.perf_counter()
    validation = validate(problem, plans, args.trials, args.seed, spreads, source)
    study = (linearisation_study(problem, plans, args.scales, args.trials, args.seed, spreads, source)
             if args.scales else [])
    print(format_report(validation, study))
    print(f"total simulation time {time.perf_counter() - t0:.2f} s")
    if args.out:
        from .plotting import save_figure

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_validation(out / "validation.json", validation, study)
        fig = validation_figure(validation)
        for suffix in ("png", "pdf"):
            save_figure(fig, out / f"validation.{suffix}")
        print(f"wrote {out / 'validation.json'}, {out / 'validation.png'}, {out / 'validation.pdf'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except (ProblemError, DesignError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
