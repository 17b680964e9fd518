"""Identify a robot from measured points: the tracker frame, then the iterated weighted fit.

The measurement model is the problem's one ``y(q, F, X)`` (:mod:`casadi_design.models`). With
``frame = "tracker"`` the measured coordinates ``P`` are in the tracker's frame, an unknown
rigid motion ``T`` of the base frame: ``P = T p``. ``T = T0 E(delta)``:

1. ``T0`` in closed form (:func:`~.registration.rigid_fit`) from the nominal model's points;
2. ``delta`` (tx, ty, tz m, rx, ry, rz rad) is the model's base error ``base.*``
   (``E(delta) = (Rx Ry Rz, t)`` left-multiplies the chain, :mod:`casadi_design.symbolic`), so
   the fit's parameters are ``(delta, X)`` of one measurement model; the robot parameters the
   frame absorbs (a combination of ``delta`` and the parameters before them, tested on the
   column-normalised Jacobian stacked over random poses) are dropped and reported;
3. weighted least squares ``min |W (y - h(delta, X))|^2`` by Levenberg-Marquardt
   (:func:`~.lsq.identify_nonlinear`, the code of every simulated calibration of ``validate``),
   with ``y = Wh (T0^-1 P - p_ref)`` the whitened deviations of the measured points from the
   nominal ones and ``W`` the mask of the markers seen.

With ``frame = "base"`` the coordinates are in the base frame: ``T0 = I`` and the fit's
parameters are the problem's own X. Units: SI (m, rad, rad/(N m)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..build import Problem, model_arguments
from ..errors import DesignError, ProblemError
from ..identifiability import RANK_RTOL, stacked_jacobian
from ..mapped import evaluate
from ..measures import SINGULAR_RTOL, information_matrix
from ..models import CalibrationModel, calibration_model
from ..symbolic import PLACEMENT_ERRORS
from .lsq import Identification, identify_nonlinear, measurement_slopes, nominal_poses
from .measurements import Measurements, measured_axes
from .registration import rigid_fit

FRAMES = ("tracker", "base")
#: The parameters of the tracker frame's correction ``delta``: the model's base error.
FRAME_PARAMETERS = tuple(f"base.{e}" for e in PLACEMENT_ERRORS)
#: Measurements whose best rigid fit to the nominal model leaves a larger RMS (m) are not of
#: this robot (or not in mm, or the joint columns are in another order).
REGISTRATION_TOL_M = 0.02
#: Why a robot parameter is left out of the fit in the tracker frame.
ABSORBED = "absorbed by the tracker frame (acts as a combination of its placement and the parameters kept)"
#: Seed of the random poses that decide what the frame absorbs (a property of the model).
ABSORB_SEED = 0


@dataclass(frozen=True, eq=False)
class FitModel:
    """The measurement model of the fit and how its parameters relate to the problem's.

    ``model.parameter_names`` are the frame's kept parameters (``frame_names``, tracker frame
    only), then the robot's (``robot_names``); ``absorbed``: (name, why) of the problem's
    parameters the frame absorbs or that have no effect.
    """

    model: CalibrationModel
    frame: str
    frame_names: tuple[str, ...]
    robot_names: tuple[str, ...]
    absorbed: tuple[tuple[str, str], ...]

    @property
    def robot_columns(self) -> np.ndarray:
        """Indices of the robot parameters in the fit's X."""
        return np.arange(len(self.frame_names), self.model.L)


def fit_model(problem: Problem, frame: str) -> FitModel:
    """The fit's measurement model for measurements in the ``frame`` (module docstring)."""
    if frame not in FRAMES:
        raise ProblemError(f"--frame {frame}: allowed: {', '.join(FRAMES)}")
    model = problem.model
    if frame == "base":
        return FitModel(model, frame, (), model.parameter_names, ())
    kin = model.kinematics
    compliant = tuple(p for p in model.parameter_names if p.startswith("k."))
    geometric = tuple(p for p in model.parameter_names if p not in compliant and p not in FRAME_PARAMETERS)
    absorbed = [(p, "the tracker frame's placement") for p in model.parameter_names if p in FRAME_PARAMETERS]
    case = "both" if compliant else "geometric"

    def build(names: tuple[str, ...]) -> CalibrationModel:
        """The model of the parameters ``names`` (geometric errors and ``k.<joint>``)."""
        args = model_arguments(problem.spec, tuple(p for p in names if not p.startswith("k.")))
        args["compliant"] = tuple(p[2:] for p in names if p.startswith("k.")) or None
        return calibration_model(kin, case, **args)

    candidates = build(FRAME_PARAMETERS + geometric + compliant)
    S = stacked_jacobian(candidates, np.random.default_rng(ABSORB_SEED))
    norms = np.linalg.norm(S, axis=0)
    live = norms > RANK_RTOL * norms.max()
    Sn = S / np.where(live, norms, 1.0)
    kept: list[int] = []
    for i, name in enumerate(candidates.parameter_names):
        if not live[i]:
            if name not in FRAME_PARAMETERS:
                absorbed.append((name, "no effect on the measured values"))
            continue
        sv = np.linalg.svd(Sn[:, kept + [i]], compute_uv=False)
        if sv[-1] > RANK_RTOL * sv[0]:
            kept.append(i)
        elif name not in FRAME_PARAMETERS:
            absorbed.append((name, ABSORBED))
    names = tuple(candidates.parameter_names[i] for i in kept)
    frame_names = tuple(p for p in names if p in FRAME_PARAMETERS)
    return FitModel(build(names), frame, frame_names, names[len(frame_names):], tuple(absorbed))


def frame_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4 x 4 homogeneous matrix of ``p -> R p + t`` (m)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def error_placement(delta: np.ndarray) -> np.ndarray:
    """``E(delta)`` (4 x 4) of a placement error (tx, ty, tz m, rx, ry, rz rad): the rotation
    ``Rx(rx) Ry(ry) Rz(rz)`` and the translation (as in :mod:`casadi_design.symbolic`)."""
    tx, ty, tz, rx, ry, rz = delta
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return frame_matrix(Rx @ Ry @ Rz, np.array([tx, ty, tz]))


@dataclass(frozen=True, eq=False)
class Fit:
    """One weighted least-squares fit of the rows ``used`` of some measurements.

    Attributes
    ----------
    X : ndarray, shape (L,): the fit's parameters (``fit.model.parameter_names``; SI units).
    T0 : ndarray, shape (4, 4), m: the closed-form registration (identity in the base frame).
    ref : ndarray, shape (m, 12): nominal poses of the rows.
    y : ndarray, shape (m, d): whitened measured deviations (0 where not measured), m.
    mask : ndarray of bool, shape (m, d): the values measured.
    used : ndarray of bool, shape (m,): the rows in the fit.
    r : ndarray, shape (m, d), m: whitened residuals ``y - h(X)`` (0 where not measured).
    J : ndarray, shape (m, d, L): ``dh/dX`` at ``X`` (masked).
    identification : iterations and convergence of Levenberg-Marquardt.
    """

    fit: FitModel
    X: np.ndarray
    T0: np.ndarray
    ref: np.ndarray
    y: np.ndarray
    mask: np.ndarray
    used: np.ndarray
    r: np.ndarray
    J: np.ndarray
    identification: Identification

    @property
    def tracker_from_base(self) -> np.ndarray:
        """``T = T0 E(delta)`` (4 x 4, m): base-frame points to tracker-frame points."""
        delta = np.zeros(6)
        for name, value in zip(self.fit.frame_names, self.X):
            delta[FRAME_PARAMETERS.index(name)] = value
        return self.T0 @ error_placement(delta)

    @property
    def robot_X(self) -> np.ndarray:
        """The fit's X with the frame's parameters at 0: the identified robot in its base frame."""
        X = self.X.copy()
        X[: len(self.fit.frame_names)] = 0.0
        return X

    @property
    def information(self) -> np.ndarray:
        """``M = J^T J`` of the rows used (whitened, m^2 per parameter unit^2)."""
        return information_matrix(self.J[self.used])


def whitening(problem: Problem) -> np.ndarray:
    """``Wh = sigma Sigma^-1/2`` of one experiment's values (identity by default)."""
    wh = problem.spec.measurement.whitening
    return np.eye(problem.model.d) if wh is None else np.asarray(wh, dtype=float)


def model_points(model: CalibrationModel, Q: np.ndarray, F: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Points (m, k, 3), m, of the markers of robot ``X`` (fit parameters) under the loads
    ``F``, in the base frame (the frame's ``delta`` included when ``X`` holds it)."""
    poses = evaluate(model.pose, Q, F.reshape(len(Q), model.nF), np.tile(X, (len(Q), 1)))[0][:, :, 0]
    R, p = poses[:, :9].reshape(-1, 3, 3).transpose(0, 2, 1), poses[:, 9:]
    return p[:, None, :] + np.einsum("tij,kj->tki", R, model.markers_m)


def registration(problem: Problem, fm: FitModel, meas: Measurements) -> np.ndarray:
    """``T0`` (4 x 4): the closed-form tracker frame of the nominal model, identity in the base
    frame; the measurements must lie within ``REGISTRATION_TOL_M`` RMS of the nominal model.

    Raises
    ------
    ProblemError
        When the points do not determine the frame, or lie too far from the nominal robot.
    """
    axes = measured_axes(problem)
    nominal = model_points(fm.model, meas.Q, meas.F, np.zeros(fm.model.L))
    seen = meas.seen
    A, B = nominal[seen], meas.P_m[seen]
    if fm.frame == "base":
        T0 = np.eye(4)
    else:
        found = rigid_fit(A, B, axes)
        if found is None:
            raise ProblemError(
                f"{meas.path}: the {len(B)} measured points do not determine the tracker frame (they "
                f"lie on a line, or fewer than {len(axes)}); measure more varied poses, or give "
                "base-frame coordinates with --frame base")
        T0 = frame_matrix(*found)
    off = (B - (A @ T0[:3, :3].T + T0[:3, 3]))[:, list(axes)]
    rms = float(np.sqrt(np.mean(np.sum(off**2, axis=1))))
    if rms > REGISTRATION_TOL_M:
        rows = np.nonzero(seen)[0]
        worst = int(rows[np.argmax(np.sum(off**2, axis=1))])
        how = "after the best rigid fit" if fm.frame == "tracker" else "in the base frame (--frame base)"
        raise ProblemError(
            f"{meas.path}: cannot be registered to the nominal robot of {problem.path}: {how} the "
            f"measured points are {rms * 1e3:.1f} mm RMS off it (row {meas.lines[worst]} the "
            f"worst); check that the file belongs to this case file, the order and units of the "
            "joint columns, the coordinates in mm" + ("" if fm.frame == "tracker" else ", and the --frame"))
    return T0


def measured_values(problem: Problem, fm: FitModel, meas: Measurements,
                    T0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``ref`` (m, 12), ``y`` (m, d) and ``mask`` (m, d) of :class:`Fit` for the rows of ``meas``."""
    model, axes = fm.model, list(measured_axes(problem))
    ref = nominal_poses(model, meas.Q, meas.F)
    R, p = ref[:, :9].reshape(-1, 3, 3).transpose(0, 2, 1), ref[:, 9:]
    nominal = p[:, None, :] + np.einsum("tij,kj->tki", R, model.markers_m)
    P = meas.P_m.copy()
    P[:, :, [a for a in range(3) if a not in axes]] = 0.0  # not measured: left alone by T0
    base = (P - T0[:3, 3]) @ T0[:3, :3]  # T0^-1 P
    dev = (base - nominal)[:, :, axes].reshape(meas.m, -1)  # the order of model.measurement
    mask = np.isfinite(dev)
    Wh = whitening(problem)
    if not mask.all() and np.count_nonzero(Wh - np.diag(np.diagonal(Wh))):
        i = int(np.flatnonzero(~mask.all(axis=1))[0])
        raise ProblemError(f"{meas.row(i)}: a marker is not measured, and the noise model of "
                           f"{problem.path} correlates the markers' values; give every marker in "
                           "every row, or per-axis sigmas")
    return ref, np.where(mask, np.nan_to_num(dev) @ Wh.T, 0.0), mask


def check_identifiable(problem: Problem, fm: FitModel, meas: Measurements, used: np.ndarray,
                       mask: np.ndarray) -> None:
    """The rows ``used`` must identify the fit's parameters: enough values, M non-singular.

    Raises
    ------
    ProblemError
        Naming the numbers of rows, values and parameters.
    """
    L, values, rows = fm.model.L, int(mask[used].sum()), int(used.sum())
    names = ", ".join(fm.model.parameter_names)
    frame = f" ({len(fm.frame_names)} of them the tracker frame's)" if fm.frame_names else ""
    per_row = max(1, values // max(rows, 1))
    if values < L:
        raise ProblemError(
            f"{meas.path}: {rows} rows give {values} measured values, fewer than the {L} parameters "
            f"to identify{frame}: {names}; measure at least {math.ceil(L / per_row)} rows")
    B = fm.model.B_stack(meas.Q[used], meas.F[used]) * mask[used][:, :, None]
    lam = np.linalg.eigvalsh(information_matrix(B))
    if not lam[0] > SINGULAR_RTOL * max(lam[-1], np.finfo(float).tiny):
        raise ProblemError(
            f"{meas.path}: the {rows} rows do not identify the {L} parameters{frame} (their "
            f"information matrix is singular: rank {int(np.sum(lam > SINGULAR_RTOL * lam[-1]))} of "
            f"{L}); measure more, and more varied, poses (a plan of casadi-design solve)")


def fit(problem: Problem, fm: FitModel, meas: Measurements, T0: np.ndarray, used: np.ndarray) -> Fit:
    """Levenberg-Marquardt on the rows ``used`` of ``meas`` (module docstring).

    Raises
    ------
    ProblemError
        Too few rows or values (:func:`check_identifiable`).
    DesignError
        When the fit does not converge.
    """
    ref, y, mask = measured_values(problem, fm, meas, T0)
    check_identifiable(problem, fm, meas, used, mask)
    model, sigma = fm.model, problem.sigma_m
    m = len(y)
    X, ident = identify_nonlinear(model, meas.Q[used], meas.F[used], ref[used], y[used].reshape(1, -1),
                                  sigma, mask=mask[used].reshape(-1))
    if ident.non_converged:
        raise DesignError(
            f"{meas.path}: the fit did not converge in {ident.iterations} Levenberg-Marquardt "
            "iterations; the robot is far from its nominal model or the rows disagree: check the "
            "file, or calibrate in two steps (fewer parameters first)")
    X = X[0]
    h = evaluate(model.measurement, meas.Q, meas.F, np.tile(X, (m, 1)), ref)[0][:, :, 0]
    J = evaluate(measurement_slopes(model), meas.Q, meas.F, np.tile(X, (m, 1)), ref,
                 np.zeros((m, model.L)))[0]
    return Fit(fm, X, T0, ref, y, mask, used, np.where(mask, y - h, 0.0), J * mask[:, :, None], ident)
