"""Simulated calibrations: true robots and the measurements of a plan, from the one model.

Every value here comes from the problem's :class:`~casadi_design.calibration.models.CalibrationModel`:
``model.pose`` gives the nominal references, ``model.measurement`` the whitened measured
values of a true robot (markers, load-point moment and joint deflection included), to which
the noise ``sigma`` per value is added. Nothing here rebuilds kinematics, markers, loads or
the noise model.

Every trial runs at once: :func:`casadi_design.robot.mapped.evaluate` maps a CasADi function over N
stacked inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from ..calibration.models import DEFLECTION_ITERATIONS, CalibrationModel
from ..errors import DesignError, ProblemError
from ..identification.lsq import nominal_poses
from ..robot.mapped import evaluate

#: Largest last fixed-point update of the joint deflection (rad, or m for prismatic joints)
#: accepted for a true robot.
DEFLECTION_TOL = 1e-9


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
    criterion : str, the criterion it was designed for (a key of ``CRITERIA``).
    m : int, number of experiments.
    Q : ndarray, shape (m, n), rad (m for prismatic joints)
    F : ndarray, shape (m, nF), N (N m): calibration loads.
    """

    criterion: str
    m: int
    Q: np.ndarray
    F: np.ndarray


def draw_true_parameters(model: CalibrationModel, spreads: ErrorSpreads, trials: int,
                         rng: np.random.Generator) -> np.ndarray:
    """True parameter vectors ``X`` (physical units) of ``trials`` robots, shape (trials, L).

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


def true_values(fn: ca.Function, spreads: ErrorSpreads, *rows: np.ndarray,
                where: np.ndarray | None = None) -> np.ndarray:
    """Values of N true robots, shape (N, rows of ``fn``), by ``model.measurement`` or
    ``model.accuracy``; checks that their deflection fixed point has converged (in the cases
    ``where``, bool of shape (N,), when given).

    Raises
    ------
    DesignError
        When the last fixed-point update exceeds ``DEFLECTION_TOL`` (compliance too large).
    """
    values, step = evaluate(fn, *rows)
    step = step.reshape(-1) if where is None else step.reshape(-1)[where]
    worst = float(np.max(step, initial=0.0))
    if not worst <= DEFLECTION_TOL:
        raise DesignError(
            f"virtual calibration: the joint deflection of the true robots did not converge in "
            f"{DEFLECTION_ITERATIONS} fixed-point iterations (last update {worst:.2e}); the nominal "
            f"compliance k_nominal = {spreads.k_nominal:g} is too large for the loads; lower it "
            "(--k, --scales)"
        )
    return values[:, :, 0]


def simulate_measurements(model: CalibrationModel, plan: Plan, X_true: np.ndarray, sigma: float,
                          spreads: ErrorSpreads, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The plan's measurements of every true robot, with noise.

    ``y = model.measurement(q_i, F_i, X_true, ref_i) + sigma z`` (``z ~ N(0, I)``): the whitened
    values have noise ``sigma`` per value whatever the noise model.

    Parameters
    ----------
    X_true : ndarray, shape (trials, L), physical parameters of the true robots.
    sigma : float, m: the problem's reference noise ``sigma_m``.

    Returns
    -------
    ref : ndarray, shape (m, 12): nominal poses of the plan's experiments.
    y : ndarray, shape (trials, m d): measured values, experiment after experiment.
    """
    trials, m = X_true.shape[0], plan.m
    ref = nominal_poses(model, plan.Q, plan.F)
    y = true_values(model.measurement, spreads, np.tile(plan.Q, (trials, 1)),
                    np.tile(plan.F, (trials, 1)), np.repeat(X_true, m, axis=0),
                    np.tile(ref, (trials, 1)))
    y = y.reshape(trials, m * model.d)
    return ref, y + sigma * rng.standard_normal(y.shape)
