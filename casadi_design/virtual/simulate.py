"""Simulated calibrations: true robots and the measurements of a plan, from the one model.

Every value here comes from the problem's :class:`~casadi_design.models.CalibrationModel`:
``model.pose`` gives the nominal references, ``model.measurement`` the whitened measured
values of a true robot (markers, load-point moment and joint deflection included), to which
the noise ``sigma`` per value is added. Nothing here rebuilds kinematics, markers, loads or
the noise model.

Every trial runs at once: :func:`evaluate` maps a CasADi function over N stacked inputs.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from ..errors import DesignError, ProblemError
from ..models import DEFLECTION_ITERATIONS, CalibrationModel
from ..parallel import cpu_count

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


#: Largest number of cases one mapped CasADi call evaluates: longer stacks run in chunks of
#: this size, shorter ones in the next power of two, so that a few mapped functions serve
#: every size (building one takes ~30 ms, as long as evaluating ~20000 cases).
CHUNK = 8192


#: Threads of the mapped evaluations: every core (the cases are independent, so the results do
#: not depend on it).
THREADS = cpu_count()


@functools.lru_cache(maxsize=128)
def _mapped(fn: ca.Function, N: int) -> ca.Function:
    return fn.map(N, "thread", THREADS) if THREADS > 1 else fn.map(N)


def evaluate(fn: ca.Function, *rows: np.ndarray) -> list[np.ndarray]:
    """Evaluate ``fn`` on N stacked inputs at once (CasADi map).

    The arrays are handed to CasADi without conversion (``Function.buffer``): row t of a
    C-ordered (N, size) array is the t-th column of the mapped input, as CasADi stores it.

    Parameters
    ----------
    rows : ndarray, shape (N, size of input a), one per (dense, column-vector) input of ``fn``

    Returns
    -------
    list of ndarray, shape (N, rows of output b, columns of output b), one per output
    """
    N = rows[0].shape[0]
    inputs = [np.ascontiguousarray(a, dtype=float).reshape(N, fn.numel_in(i)) for i, a in enumerate(rows)]
    if any(not fn.sparsity_in(i).is_dense() for i in range(fn.n_in())):
        raise ValueError(f"evaluate: {fn.name()} has sparse inputs; give a function of dense inputs")
    nonzeros = [np.empty((N, fn.nnz_out(b))) for b in range(fn.n_out())]
    K = min(CHUNK, 1 << max(N - 1, 0).bit_length())
    mapped = _mapped(fn, K)
    for start in range(0, N, K):
        stop = min(start + K, N)
        buffer, call = mapped.buffer()
        if stop - start == K:
            args, res = [a[start:stop] for a in inputs], [o[start:stop] for o in nonzeros]
        else:  # the last, short chunk: pad with copies of its last case
            pad = K - (stop - start)
            args = [np.concatenate([a[start:stop], np.repeat(a[stop - 1:stop], pad, axis=0)])
                    for a in inputs]
            res = [np.empty((K, o.shape[1])) for o in nonzeros]
        for i, a in enumerate(args):
            buffer.set_arg(i, memoryview(a))
        for b, o in enumerate(res):
            buffer.set_res(b, memoryview(o))
        call()
        if stop - start < K:
            for o, r in zip(nonzeros, res):
                o[start:stop] = r[:stop - start]
    out = []
    for b, nz in enumerate(nonzeros):
        sp = fn.sparsity_out(b)
        if sp.is_dense():
            full = nz
        else:  # e.g. a Jacobian with structural zeros: scatter its nonzeros (column-major)
            full = np.zeros((N, sp.numel()))
            full[:, sp.find()] = nz
        out.append(full.reshape(N, sp.size2(), sp.size1()).transpose(0, 2, 1))
    return out


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


def nominal_poses(model: CalibrationModel, Q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """References of the nominal robot (``X = 0``, no deflection), shape (N, 12): the
    measurement references of a plan ``(Q, F)`` and the targets of the test poses."""
    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    return evaluate(model.pose, Q, np.asarray(F, float).reshape(len(Q), model.nF),
                    np.zeros((len(Q), model.L)))[0][:, :, 0]


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
