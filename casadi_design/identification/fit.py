"""Identify a robot from measured points: the tracker frame, then the iterated weighted fit.

The measurement model is the problem's one ``y(q, F, X)`` (:mod:`casadi_design.calibration.models`). With
``frame = "tracker"`` the measured coordinates ``P`` are in the tracker's frame, an unknown
rigid motion ``T`` of the base frame: ``P = T p``. ``T = T0 E(delta)``:

1. ``T0`` in closed form (:func:`~.registration.rigid_fit`) from the nominal model's points;
2. ``delta`` (tx, ty, tz m, rx, ry, rz rad) is the model's base error ``base.*``
   (``E(delta) = (Rx Ry Rz, t)`` left-multiplies the chain, :mod:`casadi_design.robot.symbolic`), so
   the fit's parameters are ``(delta, X)`` of one measurement model; the robot parameters the
   frame absorbs (a combination of ``delta`` and the parameters before them, tested on the
   column-normalised Jacobian stacked over random poses) are dropped and reported;
3. weighted least squares ``min |W (y - h(delta, X))|^2`` (or a robust loss) by scipy's trust
   region with the exact Jacobian (:func:`~.lsq.identify_nonlinear`, the solver of every
   simulated calibration of ``validate``),
   with ``y = Wh (T0^-1 P - p_ref)`` the whitened deviations of the measured points from the
   nominal ones and ``W`` the mask of the markers seen.

With ``frame = "base"`` the coordinates are in the base frame: ``T0 = I`` and the fit's
parameters are the problem's own X. Units: SI (m, rad, rad/(N m)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..calibration.held import prior_std
from ..calibration.identifiability import RANK_RTOL, stacked_jacobian, unit_columns
from ..calibration.models import CalibrationModel, calibration_model
from ..errors import DesignError, ProblemError
from ..measures.measures import SINGULAR_RTOL, information_matrix
from ..problem.build import Problem, model_arguments
from ..robot.mapped import evaluate
from ..robot.symbolic import PLACEMENT_ERRORS
from ..runtime.cache import Memo
from .lsq import (
    Identification,
    expanded,
    frame_poses,
    identify_nonlinear,
    measurement_jacobian,
    nominal_poses,
    pose_parts,
)
from .measurements import Measurements, measured_axes
from .registration import rigid_fit

FRAMES = ("tracker", "base")
#: The parameters of the tracker frame's correction ``delta``: the model's base error.
FRAME_PARAMETERS = tuple(f"base.{e}" for e in PLACEMENT_ERRORS)
#: Measurements whose best rigid fit to the nominal model leaves a larger RMS (m) are not of
#: this robot (or not in mm, or the joint columns are in another order).
REGISTRATION_TOL_M = 0.02
#: Why a robot parameter is left out of the fit in the tracker frame.
ABSORBED = "acts as a combination of the tracker frame's placement and the parameters kept"
#: The same in the robot's base frame (``--frame base``): nothing absorbs, a parameter depends.
DEPENDENT = "acts as a combination of the parameters kept"
#: Seed of the random poses that decide what the frame absorbs (a property of the model).
ABSORB_SEED = 0


@dataclass(frozen=True, eq=False)
class FitModel:
    """The measurement model of the fit and how its parameters relate to the problem's.

    ``model.parameter_names`` are the frame's kept parameters (``frame_names``, tracker frame
    only), then the robot's (``robot_names``); ``absorbed``: (name, why) of the problem's
    parameters the frame absorbs or that have no effect; ``prior_std`` (L,), physical units:
    the prior's standard deviation of each parameter (inf: none) of a MAP fit, None for least
    squares.
    """

    model: CalibrationModel
    frame: str
    frame_names: tuple[str, ...]
    robot_names: tuple[str, ...]
    absorbed: tuple[tuple[str, str], ...]
    prior_std: np.ndarray | None = None

    @property
    def robot_columns(self) -> np.ndarray:
        """Indices of the robot parameters in the fit's X."""
        return np.arange(len(self.frame_names), self.model.L)


def fit_model(problem: Problem, frame: str, names: tuple[str, ...] | None = None,
              prior: bool = False, gravity: bool = False, seating: bool = False) -> FitModel:
    """The fit's measurement model for measurements in the ``frame`` (module docstring), of the
    robot parameters ``names`` (default the problem's own); with ``prior`` a MAP fit under the
    problem's ``[calibration.prior]``; with ``gravity`` the compliances ``k.<joint>`` of
    ``names`` deflect the joints under the robot's own weight too (the URDF's inertias); with
    ``seating`` under :data:`SEATING_N` at the measured point in every measured experiment (the
    push seating a ball in an artefact's point).

    The model is derived once per problem model, frame, names and loads in a process
    (:data:`_FITS`): a virtual calibration fits the same model in every trial, and the choice
    of a model fits each candidate in every fold."""
    if frame not in FRAMES:
        raise ProblemError(f"--frame {frame}: allowed: {', '.join(FRAMES)}")
    names = problem.model.parameter_names if names is None else tuple(names)
    fm = _FITS.get((problem.model, frame, names, gravity, seating),
                   lambda: _fit_model(problem, frame, names, gravity, seating))
    return replace(fm, prior_std=prior_std(problem.robot, problem.spec.calibration.prior,
                                             fm.frame_names + fm.robot_names)) if prior else fm


#: The push seating a ball in an artefact's point (N, base frame): 1 N down. Its size is not
#: known, so a compliance under it, ``k.<joint>`` of a seating model, is rad per N m of torque
#: per newton of push: the joints' deflection is what the recordings tell.
SEATING_N = (0.0, 0.0, -1.0)
#: The fit models derived in this process, by problem model, frame, names and loads: as many
#: as the candidates of a model choice (:mod:`casadi_design.identification.choice`) and a few.
KEEP_FITS = 32
_FITS: Memo[FitModel] = Memo(KEEP_FITS)


def _fit_model(problem: Problem, frame: str, names: tuple[str, ...], gravity: bool, seating: bool) -> FitModel:
    """:func:`fit_model` without a prior, derived anew."""
    model = problem.model
    kin = model.kinematics
    compliant = tuple(p for p in names if p.startswith("k."))

    def build(names: tuple[str, ...]) -> CalibrationModel:
        """The model of the parameters ``names`` (geometric errors and ``k.<joint>``; its case
        from what they hold)."""
        geometric = tuple(p for p in names if not p.startswith("k."))
        args = model_arguments(problem.spec, geometric)
        args["compliant"] = tuple(p[2:] for p in names if p.startswith("k.")) or None
        case = "geometric" if args["compliant"] is None else "both" if geometric else "elastostatic"
        return calibration_model(kin, case, **args, gravity=gravity, seating_N=SEATING_N if seating else None)

    if frame == "base" and names == model.parameter_names and not (gravity or seating):
        return FitModel(model, frame, (), names, ())  # the problem's own: identifiable as it is
    frame_parameters = () if frame == "base" else FRAME_PARAMETERS
    dependent = DEPENDENT if frame == "base" else ABSORBED
    geometric = tuple(p for p in names if p not in compliant and p not in frame_parameters)
    absorbed = [(p, "the tracker frame's placement") for p in names if p in frame_parameters]
    candidates = build(frame_parameters + geometric + compliant)
    Sn, live = unit_columns(stacked_jacobian(candidates, np.random.default_rng(ABSORB_SEED)), RANK_RTOL)
    kept: list[int] = []
    for i, name in enumerate(candidates.parameter_names):
        if not live[i]:
            if name not in frame_parameters:
                absorbed.append((name, "no effect on the measured values"))
            continue
        sv = np.linalg.svd(Sn[:, kept + [i]], compute_uv=False)
        if sv[-1] > RANK_RTOL * sv[0]:
            kept.append(i)
        elif name not in frame_parameters:
            absorbed.append((name, dependent))
    names = tuple(candidates.parameter_names[i] for i in kept)
    frame_names = tuple(p for p in names if p in frame_parameters)
    return FitModel(build(names), frame, frame_names, names[len(frame_names):], tuple(absorbed))


def frame_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4 x 4 homogeneous matrix of ``p -> R p + t`` (m)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def error_placement(delta: np.ndarray) -> np.ndarray:
    """``E(delta)`` (4 x 4) of a placement error (tx, ty, tz m, rx, ry, rz rad): the rotation
    ``Rx(rx) Ry(ry) Rz(rz)`` and the translation (as in :mod:`casadi_design.robot.symbolic`)."""
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
    X : ndarray, shape (L,): the fit's parameters (``fit.model.parameter_names``; SI units),
        the tracker frame's those of the first round.
    T0s : ndarray, shape (R, 4, 4), m: the closed-form registration of each tracker frame
        (identity in the base frame); ``T0`` the first.
    ref : ndarray, shape (m, 12): nominal poses of the rows.
    y : ndarray, shape (m, d): whitened measured deviations (0 where not measured), m.
    mask : ndarray of bool, shape (m, d): the values measured.
    used : ndarray of bool, shape (m,): the rows in the fit.
    r : ndarray, shape (m, d), m: whitened residuals ``y - h(X)`` (0 where not measured).
    J : ndarray, shape (m, d, L): ``dh/dX`` at ``X`` (masked); with several tracker frames,
        each later round's rows with its frame's parameters projected out, so that ``J^T J``
        is the information on X with those frames unknown (their Schur complement).
    frames : ndarray, shape (R - 1, nf): the frame parameters of the later rounds (one tracker
        frame per round), and ``frame_of`` (m,) the frame of each row.
    identification : evaluations and convergence of the least squares.
    prior_information : ndarray, shape (L,), m^2 per parameter unit^2: ``(sigma / std)^2`` of a
        MAP fit's prior (0: none), None for least squares.
    """

    fit: FitModel
    X: np.ndarray
    T0s: np.ndarray
    ref: np.ndarray
    y: np.ndarray
    mask: np.ndarray
    used: np.ndarray
    r: np.ndarray
    J: np.ndarray
    identification: Identification
    prior_information: np.ndarray | None = None
    frames: np.ndarray | None = None
    frame_of: np.ndarray | None = None

    @property
    def T0(self) -> np.ndarray:
        """The closed-form registration of the first round's tracker frame (4 x 4, m)."""
        return self.T0s[0]

    def rows_X(self, frame_of: np.ndarray) -> np.ndarray:
        """The model parameters of rows measured in the frames ``frame_of`` (k,): shape (k, L)."""
        nf = len(self.fit.frame_names)
        if self.frames is None or not nf:
            return np.tile(self.X, (len(frame_of), 1))
        return expanded(np.concatenate([self.X, self.frames.ravel()]), np.asarray(frame_of), nf, len(self.X))

    def tracker_points(self, Q: np.ndarray, F: np.ndarray, frame_of: np.ndarray | None = None) -> np.ndarray:
        """The model's points (k, p, 3), m, of the rows ``Q``, ``F`` in their tracker frames
        (``frame_of``; None: the first round's)."""
        frame_of = np.zeros(len(Q), dtype=int) if frame_of is None else np.asarray(frame_of)
        return in_tracker(self.T0s[frame_of], model_points(self.fit.model, Q, F, self.rows_X(frame_of)))

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
        """``M = J^T J`` of the rows used (whitened, m^2 per parameter unit^2), plus
        ``diag((sigma / std)^2)`` of a MAP fit's prior: ``sigma^2 M^-1`` is the covariance."""
        return self.with_prior(information_matrix(self.J[self.used]))

    def with_prior(self, M: np.ndarray) -> np.ndarray:
        """``M`` (L x L, whitened, m^2 per parameter unit^2) plus a MAP fit's prior information
        ``diag((sigma / std)^2)``; ``M`` itself for least squares."""
        return M if self.prior_information is None else M + np.diag(self.prior_information)


def point_errors(problem: Problem, P: np.ndarray, model_P: np.ndarray) -> np.ndarray:
    """Per point ``|P - model_P|`` over the measured axes (m, k), NaN where not seen."""
    axes = list(measured_axes(problem))
    return np.sqrt(np.sum((P - model_P)[:, :, axes] ** 2, axis=2))


def pose_rms(e: np.ndarray) -> np.ndarray:
    """RMS over each row's seen points, shape (m,)."""
    return np.sqrt(np.nanmean(e**2, axis=1))


def in_tracker(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points ``p`` (k, q, 3) moved by ``T``: one 4 x 4 for every row, or one per row (k, 4, 4)."""
    T = np.asarray(T)
    if T.ndim == 2:
        return p @ T[:3, :3].T + T[:3, 3]
    return np.einsum("kij,kqj->kqi", T[:, :3, :3], p) + T[:, None, :3, 3]


def model_points(model: CalibrationModel, Q: np.ndarray, F: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Points (m, k, 3), m, of the markers of robot ``X`` (fit parameters; one row per
    experiment, shape (m, L), or one for all) under the loads ``F``, in the base frame (the
    frame's ``delta`` included when ``X`` holds it)."""
    R, p = frame_poses(model, Q, F, X)
    return p[:, None, :] + np.einsum("tij,kj->tki", R, model.markers_m)


def registration(problem: Problem, fm: FitModel, meas: Measurements) -> tuple[np.ndarray, float, int]:
    """``T0s`` (R, 4, 4): the closed-form tracker frame of the nominal model in each round's
    frame (identity in the base frame), the RMS distance (m) of the measured points from the
    nominal ones they leave, and the row (index) of the worst.

    Raises
    ------
    ProblemError
        When the points do not determine a frame.
    """
    axes = measured_axes(problem)
    nominal = model_points(fm.model, meas.Q, meas.F, np.zeros(fm.model.L))
    frame_of = meas.frame_of
    T0s = np.tile(np.eye(4), (meas.frames, 1, 1))
    for k in range(meas.frames):
        seen = meas.seen & (frame_of == k)[:, None]
        A, B = nominal[seen], meas.P_m[seen]
        if fm.frame == "tracker":
            found = rigid_fit(A, B, axes)
            if found is None:
                where = meas.paths[k] if meas.frames > 1 else meas.path
                raise ProblemError(
                    f"{where}: the {len(B)} measured points do not determine the tracker frame (they "
                    f"lie on a line, or fewer than {len(axes)}); measure more varied poses, or give "
                    "base-frame coordinates with --frame base")
            T0s[k] = frame_matrix(*found)
    seen = meas.seen
    off = (meas.P_m - in_tracker(T0s[frame_of], nominal))[seen][:, list(axes)]
    rows = np.nonzero(seen)[0]
    return T0s, float(np.sqrt(np.mean(np.sum(off**2, axis=1)))), int(rows[np.argmax(np.sum(off**2, axis=1))])


def with_points(problem: Problem, d: np.ndarray, build: bool = True):
    """``problem`` with its measured points moved by ``d`` (k x 3, m, in the measured frame):
    ``[robot].tool_xyz_m`` for one point, ``[measurement].markers_m`` for markers; its spec
    only when not ``build``."""
    from dataclasses import replace

    from ..problem.build import build_problem
    from ..robot.robots import placement_from_xyz_rpy

    spec = problem.spec
    if spec.measurement.markers_m is not None:
        markers = tuple(tuple(float(v) for v in np.add(m, dm)) for m, dm in zip(spec.measurement.markers_m, d))
        moved = replace(spec, measurement=replace(spec.measurement, markers_m=markers))
        return build_problem(moved) if build else moved
    r = spec.robot
    xyz = np.zeros(3) if r.tool_xyz_m is None else np.asarray(r.tool_xyz_m, float)
    rot = np.eye(3) if r.tool_rpy_rad is None else placement_from_xyz_rpy(xyz, r.tool_rpy_rad).rotation
    tool = tuple(float(v) for v in xyz + rot @ d[0])
    moved = replace(spec, robot=replace(r, tool_xyz_m=tool))
    return build_problem(moved) if build else moved


def point_keys(problem: Problem) -> str:
    return "[measurement].markers_m" if problem.spec.measurement.markers_m is not None else "[robot].tool_xyz_m"


def point_values(problem) -> str:
    """The measured points of a problem (or its spec) as its file would give them (m)."""
    spec = getattr(problem, "spec", problem)
    pts = spec.measurement.markers_m if spec.measurement.markers_m is not None else [spec.robot.tool_xyz_m or (0.0, 0.0, 0.0)]
    text = ", ".join("[" + ", ".join(f"{v:.5f}" for v in pt) + "]" for pt in pts)
    return f"[{text}]" if spec.measurement.markers_m is not None else text


def register(problem: Problem, frame: str, meas: Measurements) -> tuple[Problem, FitModel, np.ndarray, list[str]]:
    """The problem to fit (its measured points located when they are far off), its fit model,
    ``T0`` of :func:`registration`, and a note when the points were located.

    The measurements must lie within ``REGISTRATION_TOL_M`` RMS of the nominal model after the
    closed-form frame. When they do not and x, y, z are measured in the tracker frame, the
    measured points are located with the frame (:func:`locate_points`); if that leaves them
    within the gate, the problem with the located points is fitted.

    Raises
    ------
    ProblemError
        When the points do not determine the frame, or lie too far from the nominal robot even
        with the points located (the message names the keys and the located points).
    """
    fm = fit_model(problem, frame)
    T0, rms, worst = registration(problem, fm, meas)
    if rms <= REGISTRATION_TOL_M:
        return problem, fm, T0, []
    located = ""
    if frame == "tracker" and len(measured_axes(problem)) == 3:
        d, left = locate_points(fm, meas)
        where = f"{point_keys(problem)} = {point_values(with_points(problem, d, build=False))} m"
        if not left <= REGISTRATION_TOL_M:  # (NaN: a round whose points fix no frame)
            located = f"; with the measured points located at {where} they are still {left * 1e3:.1f} mm RMS off"
        else:
            try:
                moved = with_points(problem, d)
            except ProblemError as e:  # e.g. test poses the moved tool cannot reach
                located = f"; with the measured points located at {where} ({left * 1e3:.2f} mm RMS left) {e}"
            else:
                fm = fit_model(moved, frame)
                T0, _, _ = registration(moved, fm, meas)
                return moved, fm, T0, [
                    f"the measured points of {problem.path} lie {rms_of(d) * 1e3:.1f} mm off "
                    f"{point_keys(problem)} (the nominal robot {rms * 1e3:.1f} mm RMS off the "
                    f"measurements): located with the tracker frame at {where} ({left * 1e3:.2f} mm "
                    "RMS left) and fitted from there"]
    how = "after the best rigid fit" if fm.frame == "tracker" else "in the base frame (--frame base)"
    raise ProblemError(
        f"{meas.path}: cannot be registered to the nominal robot of {problem.path}: {how} the "
        f"measured points are {rms * 1e3:.1f} mm RMS off it ({meas.row(worst)} the "
        f"worst){located}; check {point_keys(problem)}, that the file belongs to this case file, "
        "the order and units of the joint and coordinate columns" + ("" if fm.frame == "tracker" else ", and the --frame"))


def rms_of(d: np.ndarray) -> float:
    """RMS length (m) of the rows of ``d``."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(d) ** 2, axis=-1))))


#: The alternating registration with the points free stops when no point moves by more than
#: this (m), or after ``LOCATE_ITERATIONS`` rounds.
LOCATE_TOL_M = 1e-9
LOCATE_ITERATIONS = 2000


def locate_points(fm: FitModel, meas: Measurements) -> tuple[np.ndarray, float]:
    """The measured points' offsets from their nominal place, in the measured frame, found
    with the tracker frame (one per round of ``meas``): ``min over T, d_c of sum_ic
    |T (R_i (m_c + d_c) + p_i) - P_ic|^2`` (nominal robot, poses ``(R_i, p_i)`` of the measured
    frame, nominal points ``m_c``).

    Alternating closed forms: for the frame ``T`` the Kabsch fit (:func:`rigid_fit`); for the
    points ``d_c = mean_i R_i^T (T^-1 P_ic - p_i) - m_c``. Three measured components only.

    Returns
    -------
    d : ndarray, shape (k, 3), m.  rms_m : float, the RMS distance left, m.
    """
    model = fm.model
    ref = nominal_poses(model, meas.Q, meas.F)
    R, p = pose_parts(ref)
    seen, P = meas.seen, meas.P_m
    rounds = [meas.frame_of == k for k in range(meas.frames)]  # one tracker frame per round
    seen_in = [seen & r[:, None] for r in rounds]  # each round's seen points
    markers = np.asarray(model.markers_m, float)
    d = np.zeros_like(markers)

    def frames(d: np.ndarray) -> tuple[np.ndarray, list | None]:
        points = p[:, None, :] + np.einsum("tij,kj->tki", R, markers + d)
        found = [rigid_fit(points[s], P[s], (0, 1, 2)) for s in seen_in]
        return points, None if any(f is None for f in found) else found

    for _ in range(LOCATE_ITERATIONS):
        _, found = frames(d)
        if found is None:
            break
        local = np.empty_like(P)
        for r, (Rt, t) in zip(rounds, found):  # R_i^T (T^-1 P - p_i)
            local[r] = np.einsum("tji,tkj->tki", R[r], (P[r] - t) @ Rt - p[r, None, :]) - markers
        new = np.array([np.mean(local[seen[:, c], c], axis=0) for c in range(len(markers))])
        moved = float(np.max(np.abs(new - d)))
        d = new
        if moved < LOCATE_TOL_M:
            break
    points, found = frames(d)
    if found is None:
        return d, math.nan
    off = np.concatenate([P[s] - (points[s] @ Rt.T + t) for s, (Rt, t) in zip(seen_in, found)])
    return d, float(np.sqrt(np.mean(np.sum(off**2, axis=-1))))


def measured_values(problem: Problem, fm: FitModel, meas: Measurements,
                    T0s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``ref`` (m, 12), ``y`` (m, d) and ``mask`` (m, d) of :class:`Fit` for the rows of
    ``meas``, each row's points taken out of its round's frame ``T0s[k]`` (R, 4, 4)."""
    model, axes = fm.model, list(measured_axes(problem))
    ref = nominal_poses(model, meas.Q, meas.F)
    R, p = pose_parts(ref)
    nominal = p[:, None, :] + np.einsum("tij,kj->tki", R, model.markers_m)
    P = meas.P_m.copy()
    P[:, :, [a for a in range(3) if a not in axes]] = 0.0  # not measured: left alone by T0
    T0 = np.asarray(T0s).reshape(-1, 4, 4)[meas.frame_of]
    base = np.einsum("tpj,tji->tpi", P - T0[:, None, :3, 3], T0[:, :3, :3])  # T0^-1 P
    dev = (base - nominal)[:, :, axes].reshape(meas.m, -1)  # the order of model.measurement
    mask = np.isfinite(dev)
    Wh = problem.whitening
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
    L, values, rows = fm.model.L + (meas.frames - 1) * len(fm.frame_names), int(mask[used].sum()), int(used.sum())
    frame = (f" ({L - fm.model.L + len(fm.frame_names)} of them the tracker frames')" if fm.frame_names else "")
    per_row = max(1, values // max(rows, 1))
    which = f"{rows} rows" if rows == meas.m else f"{rows} of the {meas.m} rows (the others left out as outliers)"
    if values < L:
        raise ProblemError(
            f"{meas.path}: {which} give {values} measured values, fewer than the {L} parameters "
            f"to identify{frame}; measure at least {math.ceil(L / per_row)} rows"
            + ("" if rows == meas.m else " that fit the model"))
    B = fm.model.B_stack(meas.Q[used], meas.F[used]) * mask[used][:, :, None]
    lam = np.linalg.eigvalsh(information_matrix(B))
    if not lam[0] > SINGULAR_RTOL * max(lam[-1], np.finfo(float).tiny):
        raise ProblemError(
            f"{meas.path}: {'the ' * (rows == meas.m)}{which} do not identify the {L} parameters{frame} (their "
            f"information matrix is singular: rank {int(np.sum(lam > SINGULAR_RTOL * lam[-1]))} of "
            f"{L}); measure more, and more varied, poses (a plan of casadi-design solve)")


def fit(problem: Problem, fm: FitModel, meas: Measurements, T0s: np.ndarray, used: np.ndarray,
        loss: str = "linear") -> Fit:
    """Least squares (``loss``: :data:`~.lsq.LOSSES`) on the rows ``used`` of ``meas`` (module
    docstring); the MAP estimate when ``fm`` has a prior. Rows of several rounds each in a
    tracker frame of its own (``meas.frames``) share the robot's parameters and fit a frame per
    round (:func:`~.lsq.identify_nonlinear`'s ``frames``).

    Raises
    ------
    ProblemError
        Too few rows or values (:func:`check_identifiable`).
    DesignError
        When the fit does not converge.
    """
    T0s = np.asarray(T0s).reshape(-1, 4, 4)
    ref, y, mask = measured_values(problem, fm, meas, T0s)
    check_identifiable(problem, fm, meas, used, mask)
    model, sigma = fm.model, problem.sigma_m
    nf, frame_of = len(fm.frame_names), meas.frame_of
    several = meas.frames > 1 and nf > 0
    Z, ident = identify_nonlinear(model, meas.Q[used], meas.F[used], ref[used], y[used].reshape(1, -1),
                                  sigma, mask=mask[used].reshape(-1), loss=loss,
                                  prior_std=fm.prior_std, frames=(frame_of[used], nf) if several else None)
    if ident.non_converged:
        raise DesignError(
            f"{meas.path}: the fit did not meet its tolerances in {ident.iterations} evaluations "
            "of the model; the robot is far from its nominal model or the rows disagree: check the "
            "file, or fit fewer parameters first (--model offsets)")
    X, frames = Z[0, :model.L], Z[0, model.L:].reshape(-1, nf) if several else None
    h, J = evaluate(measurement_jacobian(model), meas.Q, meas.F, expanded(Z[0], frame_of, nf, model.L), ref)
    h, J = h[:, :, 0], J * mask[:, :, None]
    if several:
        J = frames_projected(J, frame_of, used, nf)
    prior = None if fm.prior_std is None else (sigma / fm.prior_std) ** 2
    return Fit(fm, X, T0s, ref, y, mask, used, np.where(mask, y - h, 0.0), J, ident, prior,
               frames, frame_of if several else None)


def frames_projected(J: np.ndarray, frame_of: np.ndarray, used: np.ndarray, nf: int) -> np.ndarray:
    """``J`` (m, d, L) with, for the rows ``used`` of each later round (``frame_of`` > 0), the
    directions of their frame's ``nf`` parameters (the first) projected out: ``J^T J`` is then
    the information on X with those frames unknown (the Schur complement of their block)."""
    J = J.copy()
    for k in range(1, int(frame_of.max(initial=0)) + 1):
        rows = np.flatnonzero((frame_of == k) & used)
        Jk = J[rows].reshape(-1, J.shape[2])
        G = Jk[:, :nf]
        J[rows] = (Jk - G @ np.linalg.lstsq(G, Jk, rcond=None)[0]).reshape(len(rows), -1, J.shape[2])
    return J


def row_errors(problem: Problem, f: Fit, meas: Measurements, rows: np.ndarray | None = None) -> np.ndarray:
    """RMS over each row's points of ``|P - T0 p(X)|`` (m) of the fit ``f`` at the rows ``rows``
    (indices or mask, default all) of ``meas``, in the frame the fit identified."""
    sub = meas if rows is None else meas.subset(rows)
    return pose_rms(point_errors(problem, sub.P_m, f.tracker_points(sub.Q, sub.F, sub.frame_of)))
