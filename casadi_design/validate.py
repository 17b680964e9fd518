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

import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from statistics import NormalDist

import casadi as ca
import numpy as np

from .errors import DesignError, ProblemError
from .measures import information_matrix, score_plan
from .models import CalibrationModel
from .problem import Problem
from .results import write_atomic
from .solve import Design
from .symbolic import twist_jacobian

#: Fixed-point iterations of the joint deflection ``dq = diag(k) J(q + dq)^T W``.
DEFLECTION_ITERATIONS = 10
#: Largest last fixed-point update (rad, or m for prismatic joints) accepted for the true robot.
DEFLECTION_TOL = 1e-9
#: Levenberg-Marquardt: converged when the Gauss-Newton correction moves the model's
#: prediction of the measurements by less than this fraction of sigma.
LM_TOL = 1e-6
LM_MAX_ITERATIONS = 100
LM_LAMBDA0 = 1e-3
#: Newton iterations of the compensation: converged when every joint step is below this (rad, m).
COMPENSATION_STEP_TOL = 1e-13
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
    column-major rotation and the position, m, of the reference pose).

    Attributes
    ----------
    pose : casadi.Function
        ``(q, F, X) -> (ref, step)``: the deflected frame pose as a reference vector, and the
        largest last update of the deflection fixed point (rad or m).
    deviation : casadi.Function
        ``(q, F, X, ref) -> (dev, step)``: the 6 deviation rows (m, rad) from ``ref``.
    jacobians : casadi.Function
        ``(q, F, X, ref) -> (dev, d dev / d X, d dev / d q)``: shapes 6, 6 x L, 6 x n.
    """

    model: CalibrationModel
    pose: ca.Function
    deviation: ca.Function
    jacobians: ca.Function


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
    R_ref = ca.reshape(ref[0:9], 3, 3)
    A = R @ R_ref.T
    S = (A - A.T) / 2
    dev = ca.vertcat(p - ref[9:12], S[2, 1], S[0, 2], S[1, 0])
    return NonlinearModel(
        model=model,
        pose=ca.Function("pose", [q, F, X], [ca.vertcat(ca.vec(R), p), step]),
        deviation=ca.Function("deviation", [q, F, X, ref], [dev, step]),
        jacobians=ca.Function("jacobians", [q, F, X, ref],
                              [dev, ca.jacobian(dev, X), ca.jacobian(dev, q)]),
    )


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
    out = fn.map(N)(*[np.ascontiguousarray(np.asarray(a, dtype=float).T) for a in rows])
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


def _true_deviation(nl: NonlinearModel, q, F, X, ref, spreads: ErrorSpreads) -> np.ndarray:
    """Deviation rows (N, 6) of true robots, checking that their deflection has converged."""
    dev, step = evaluate(nl.deviation, q, F, X, ref)
    worst = float(np.max(step, initial=0.0))
    if worst > DEFLECTION_TOL:
        raise DesignError(
            f"virtual calibration: the joint deflection of the true robots did not converge in "
            f"{DEFLECTION_ITERATIONS} fixed-point iterations (last update {worst:.2e}); the nominal "
            f"compliance k_nominal = {spreads.k_nominal:g} is too large for the loads, lower it"
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

    Minimises ``|y - h(X)|^2`` with ``h`` the measured rows of ``nl.deviation`` at the plan's
    ``Q`` (m, n), ``F`` (m, nF) and nominal references ``ref`` (m, 12). Step:
    ``(H + lambda diag H) dX = J^T r`` with ``H = J^T J``. A trial has converged when its
    Gauss-Newton correction changes the predicted measurements by at most ``LM_TOL sigma``
    (``sqrt(g^T H^-1 g) <= LM_TOL sigma``, ``g = J^T r``).

    Returns
    -------
    X : ndarray, shape (trials, L)
    report : :class:`Identification` (trials still not converged after ``max_iterations``)
    """
    rows = list(nl.model.measured_rows)
    trials, m = y.shape[0], Q.shape[0]

    def residual(X: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = len(which)
        dev, dX, _ = evaluate(nl.jacobians, np.tile(Q, (t, 1)), np.tile(F, (t, 1)),
                              np.repeat(X, m, axis=0), np.tile(ref, (t, 1)))
        r = y[which] - dev[:, rows, 0].reshape(t, -1)
        return r, dX[:, rows, :].reshape(t, -1, nl.model.L)

    X = np.zeros((trials, nl.model.L))
    everyone = np.arange(trials)
    r, J = residual(X, everyone)
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
        X[ok], r[ok], J[ok], cost[ok] = trial_X[better], r_new[better], J_new[better], np.sum(r_new[better] ** 2, axis=1)
        lam[ok] /= 10.0
        lam[a[~better]] *= 10.0
    return X, Identification("Levenberg-Marquardt", iterations, int(active.sum()))


def compensate(nl: NonlinearModel, q0: np.ndarray, F0: np.ndarray, target: np.ndarray,
               X: np.ndarray) -> tuple[np.ndarray, float]:
    """Corrected commands: the identified model ``X`` puts the frame on ``target``.

    Newton (minimum-norm steps) on ``dev(q_c, F0, X, target) = 0`` in the required rows
    (``[test_poses].components``), from ``q_c = q0``, for N stacked cases at once.

    Parameters
    ----------
    q0 : ndarray, shape (N, n), rad;  F0 : ndarray, shape (N, nF), N (machining wrench)
    target : ndarray, shape (N, 12): nominal poses at ``q0`` (see :class:`NonlinearModel`)
    X : ndarray, shape (N, L): identified parameters

    Returns
    -------
    q_c : ndarray, shape (N, n)
    model_residual : float, m (rad): largest remaining ``|dev|`` of the identified model,
        zero unless the required rows cannot all be met with n joints.
    """
    rows = list(nl.model.accuracy_rows)
    qc = np.array(q0, dtype=float)
    for _ in range(COMPENSATION_MAX_ITERATIONS):
        dev, _, dq = evaluate(nl.jacobians, qc, F0, X, target)
        step = -np.linalg.pinv(dq[:, rows, :]) @ dev[:, rows, :]
        qc = qc + step[..., 0]
        if np.max(np.abs(step)) < COMPENSATION_STEP_TOL:
            break
    else:
        raise DesignError(
            f"virtual calibration: compensation did not converge in {COMPENSATION_MAX_ITERATIONS} "
            "Newton steps; the identified errors are too large for the test poses (reduce the "
            "error spreads) or a test pose is singular"
        )
    dev, _ = evaluate(nl.deviation, qc, F0, X, target)
    return qc, float(np.max(np.linalg.norm(dev[:, rows, 0], axis=1)))


def chi2_quantile(p: float, dof: np.ndarray) -> np.ndarray:
    """Quantile of the chi-square law (Wilson-Hilferty): ``k (1 - 2/(9k) + z_p sqrt(2/(9k)))^3``.

    Relative error below 1e-3 for ``k >= 10``; the intervals here use ``k`` of several hundred.
    """
    k = np.asarray(dof, dtype=float)
    z = NormalDist().inv_cdf(p)
    return k * (1 - 2 / (9 * k) + z * np.sqrt(2 / (9 * k))) ** 3


def effective_dof(C: np.ndarray) -> np.ndarray:
    """Degrees of freedom ``nu = trace(C)^2 / trace(C^2)`` of ``|e|^2``, ``e ~ N(0, C)``.

    ``|e|^2`` has mean ``trace C = rho`` and is approximated by ``rho / nu chi2(nu)``
    (Satterthwaite); ``C`` of shape (s, r, r).
    """
    return np.trace(C, axis1=1, axis2=2) ** 2 / np.einsum("sij,sji->s", C, C)


def rms_interval(mean_square: np.ndarray, dof: np.ndarray, trials: int,
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
    wall_s: float

    @property
    def ratio(self) -> np.ndarray:
        """Empirical over predicted RMS error at each test pose."""
        return self.empirical_rms_m / self.predicted_rms_m

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


def plan_matrices(model: CalibrationModel, plan: Plan, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``B_i`` of the plan, shape (m, d, L), and ``B0_j`` at the test poses, shape (s, r, L)."""
    tp = problem.test_poses
    B = np.array([model.B_numeric(q, F) for q, F in zip(plan.Q, plan.F)])
    B0 = np.array([model.B_numeric(q, F, accuracy=True) for q, F in zip(tp.q, tp.F)])
    return B, B0


def simulate_plan(problem: Problem, nl: NonlinearModel, plan: Plan, spreads: ErrorSpreads,
                  trials: int, rng: np.random.Generator) -> PlanValidation:
    """Simulate ``trials`` calibrations of ``plan`` and compare with ``sqrt(rho)`` (module doc)."""
    t0 = time.perf_counter()
    model, tp, sigma = problem.model, problem.test_poses, problem.sigma_m
    m, d, s = plan.m, len(model.measured_rows), tp.s
    B, B0 = plan_matrices(model, plan, problem)
    X_true = draw_true_parameters(model, spreads, trials, rng)

    zeros_m = np.zeros((m, model.L))
    ref, _ = evaluate(nl.pose, plan.Q, plan.F, zeros_m)
    ref = ref[:, :, 0]
    dev = _true_deviation(nl, np.tile(plan.Q, (trials, 1)), np.tile(plan.F, (trials, 1)),
                          np.repeat(X_true, m, axis=0), np.tile(ref, (trials, 1)), spreads)
    y = dev[:, list(model.measured_rows)].reshape(trials, m * d)
    y = y + sigma * rng.standard_normal(y.shape)
    if model.case == "elastostatic":
        X_hat, ident = identify_linear(B.reshape(m * d, model.L), y)
    else:
        X_hat, ident = identify_nonlinear(nl, plan.Q, plan.F, ref, y, sigma)

    target, _ = evaluate(nl.pose, tp.q, tp.F, np.zeros((s, model.L)))
    target = np.tile(target[:, :, 0], (trials, 1))
    q0, F0 = np.tile(tp.q, (trials, 1)), np.tile(tp.F, (trials, 1))
    qc, miss = compensate(nl, q0, F0, target, np.repeat(X_hat, s, axis=0))
    err = _true_deviation(nl, qc, F0, np.repeat(X_true, s, axis=0), target, spreads)
    err = err[:, list(model.accuracy_rows)].reshape(trials, s, -1)
    mean_square = np.mean(np.sum(err**2, axis=2), axis=0)

    predicted = score_plan(B, B0, sigma).rms_error_m
    M_inv = np.linalg.inv(information_matrix(B))
    C = sigma**2 * np.einsum("sil,lk,sjk->sij", B0, M_inv, B0)
    dof = effective_dof(C)
    low, high = rms_interval(mean_square, dof, trials)
    return PlanValidation(plan, predicted, np.sqrt(mean_square), low, high, dof, ident, miss,
                          time.perf_counter() - t0)


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
                           f"python scripts/solve_case.py {problem.path} --out DIR")
    except json.JSONDecodeError as exc:
        raise ProblemError(f"--results: {path} is not valid JSON ({exc}); solve the case again")
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
    out: dict[int, dict[str, list[str]]] = {}
    for m in sorted({p.plan.m for p in validation.plans}):
        group = [p for p in validation.plans if p.plan.m == m]
        out[m] = {
            "by_measure": [p.plan.criterion for p in sorted(group, key=lambda p: np.max(p.predicted_rms_m))],
            "by_simulation": [p.plan.criterion for p in sorted(group, key=lambda p: np.max(p.empirical_rms_m))],
        }
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
                        "non_converged": p.identification.non_converged} for p in v.plans]}
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
    """Per plan: max predicted and simulated RMS error (mm) with the interval, node agreement."""
    v = validation
    pct = round(100 * CONFIDENCE)
    lines = [
        f"virtual calibration of {v.problem.name} ({v.problem.model.case}): {v.trials} trials, seed {v.seed}, "
        f"{v.problem.test_poses.s} test poses; errors: length {v.spreads.length_m * 1e3:g} mm, "
        f"angle {math.degrees(v.spreads.angle_rad):g} deg, k {v.spreads.k_nominal:g} (log-std {v.spreads.k_log_spread:g})",
        f"{'criterion':<10} {'m':>3} {'max sqrt(rho)':>14} {'max simulated':>14} {f'{pct}% interval':>18} "
        f"{'worst node':>11} {'covered':>8}  identification",
    ]
    for p in v.plans:
        rec = plan_record(p)
        mx, ident = rec["max"], p.identification
        conv = "" if not ident.non_converged else f", {ident.non_converged} NOT CONVERGED"
        lines.append(
            f"{p.plan.criterion:<10} {p.plan.m:>3} {mx['predicted_m'] * 1e3:>11.4f} mm {mx['empirical_m'] * 1e3:>11.4f} mm "
            f"{mx['ci_low_m'] * 1e3:>8.4f}..{mx['ci_high_m'] * 1e3:.4f} {100 * p.worst_relative_error:>10.2f}% "
            f"{100 * p.coverage:>7.0f}%  {ident.method}, {ident.iterations} it.{conv}"
        )
    for m, r in rankings(v).items():
        same = "same" if r["by_measure"] == r["by_simulation"] else "DIFFERENT"
        lines.append(f"m = {m}: ranking by the measure {r['by_measure']}, by simulation {r['by_simulation']} ({same})")
    lines.append(f"wall time {v.wall_s:.2f} s for {len(v.plans)} plans x {v.trials} trials")
    if study:
        lines.append("linearisation: max simulated / max predicted error when the spreads are scaled")
        lines.append(f"{'scale':>8}  " + "  ".join(f"{p.plan.criterion + ' m=' + str(p.plan.m):>14}" for p in study[0][1].plans))
        for scale, s in study:
            lines.append(f"{scale:>8g}  " + "  ".join(f"{p.max_ratio:>14.3f}" for p in s.plans))
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
        for p in (p for p in validation.plans if p.plan.m == m):
            style = STYLES[p.plan.criterion]
            e = p.empirical_rms_m * 1e3
            ax.plot(x, p.predicted_rms_m * 1e3, label=f"{LABELS[p.plan.criterion]}: predicted", **style)
            ax.errorbar(x[::every], e[::every],
                        yerr=np.abs(np.vstack([p.ci_low_m, p.ci_high_m]) * 1e3 - e)[:, ::every],
                        fmt="o", ms=3, capsize=2, color=style["color"], label="simulated")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("RMS error after compensation (mm)")
        ax.set_ylim(bottom=0)
        ax.set_title(f"m = {m}: {validation.trials} virtual calibrations, {round(100 * CONFIDENCE)}% intervals")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    return fig
