"""The whole identification of measured data: fit, outliers, statistics, validation, compensation.

Statistics of a fit with N measured values and L parameters (whitened residuals ``r``, the
tracker's noise ``sigma`` per value, ``J = dh/dX`` at the estimate):

* ``sigma_hat = sqrt(|r|^2 / (N - L))``, and ``|r|^2 / sigma^2 ~ chi2(N - L)``: the residuals
  are consistent with the tracker's noise when it lies within the central ``CONFIDENCE``
  interval; above its ``UNMODELLED_CONFIDENCE`` quantile the robot's unmodelled error ``tau``
  is estimated from the cross-validated residuals, and
  the fit's error per value is ``s^2 = sigma^2 + tau^2`` (:mod:`.residuals`; ``s = sigma``
  when the residuals are the noise). The problem's sigma stays the designs' and the tracker's
  share;
* ``cov(X) = s^2 (J^T J)^-1``, standard deviations its diagonal's roots, correlations
  ``C_ab / (std_a std_b)`` (pairs beyond ``CORRELATION_LIMIT`` reported);
* outliers (:func:`fit_without_outliers`): a row whose externally studentized residual
  exceeds ``threshold`` (default 4) times the error of the other rows (at least sigma) is
  excluded, the worst first, and the rest refitted; at most ``MAX_OUTLIER_SHARE`` of the rows;
* predicted accuracy at the test poses of the plan that was measured:
  ``sqrt(rho_j) = sqrt(s^2 trace(B0_j M^-1 B0_j^T) + d tau^2)`` with ``M`` and ``B0`` at X = 0
  (the design's measure with ``s`` for ``sigma``, :func:`design_information`, plus the
  unmodelled error at the pose, which compensation cannot remove), the error of the
  compensated robot in the frame of the measurements (where the workpiece is registered: the
  frame's uncertainty included, as the design's base errors are);
* validation rows (not in the fit), judged as the robot is used: every model with the tracker
  frame fitted on the training rows: the nominal robot (the closed-form frame), registration
  only (frame and measured point fitted), the calibrated robot; and, for the shape error alone,
  each re-registered on the validation rows themselves. Rows in another tracker frame (the
  tracker moved: ``MOVED_RATIO``) are judged re-registered only. The error per pose is the RMS
  over its points of ``|P - T p(X)|`` (mm for people), predicted ``sqrt((s^2 trace(B_v M^-1
  B_v^T) + d_v s^2) / k)`` (the parameters' error and the pose's own unmodelled error and
  noise, d_v values of k points); a measured error beyond ``PREDICTION_RATIO`` times the
  prediction, or a calibrated robot worse than the nominal one or registration only, is
  reported. A validation pose with a joint outside the range of the training rows is out of
  range (extrapolation), marked and summarised apart.
* the model (:mod:`.choice`): registration only, + joint offsets, + the most significant of
  the problem's parameters, or all of them, + the joints' compliance under the robot's own
  weight, or a MAP fit under ``[calibration.prior]``, given or chosen by cross-validation on the
  training rows less the outliers of the richest model (the problem's own, with the
  compliances under its weight for a robot with masses: a smaller model would take what it
  misses for bad shots); the chosen model is fitted on those rows. A gravity model whose
  compliances come out negative beyond ``NEGATIVE_STD`` is not chosen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import DesignError, ProblemError
from ..measures.measures import information_matrix, rho_at_test_poses
from ..problem.build import Problem
from .choice import (
    MODELS,
    NEGATIVE_STD,
    Candidate,
    candidates,
    choose,
    has_weight,
    negative_compliances,
)
from .compensate import compensate
from .field_fit import FIELD_SEED, TrainedField, estimate_field
from .fit import (
    REGISTRATION_TOL_M,
    Fit,
    FitModel,
    fit,
    fit_model,
    frame_matrix,
    frames_projected,
    in_tracker,
    model_points,
    point_errors,
    pose_rms,
    register,
    row_errors,
)
from .lsq import check_loss, nominal_poses, pose_parts
from .measurements import Measurements, measured_axes
from .registration import rigid_fit
from .residuals import ErrorScale, chi2_quantile, deleted_scores, error_scale, leverages, without_outliers

#: A row whose externally studentized residual exceeds this many times the other rows' error
#: (at least sigma) is an outlier (default of ``--outlier-sigma``; :func:`row_scores`).
OUTLIER_SIGMA = 4.0
#: At most this share of the rows (at least one) is excluded as outliers: bad shots are rare.
MAX_OUTLIER_SHARE = 0.05
#: Parameter pairs correlated beyond this are reported.
CORRELATION_LIMIT = 0.9
#: A validation pose is a test pose when their joints agree within this (rad or m).
SAME_POSE_RAD = 1e-6
#: Level of the chi-square test of the noise.
CONFIDENCE = 0.95
#: The residuals hold an unmodelled error when ``|r|^2 / sigma^2`` exceeds this quantile of its
#: chi-square law (one-sided): a robot measured with the tracker's noise alone is taken for one
#: with an unmodelled error once in a thousand identifications.
UNMODELLED_CONFIDENCE = 0.999
#: A validation RMS beyond this times its prediction is reported as what the model misses.
PREDICTION_RATIO = 1.5
#: The unmodelled error's field compensates only when its leave-one-out error on the training
#: rows is below this times least squares' alone (its lengths were fitted on the same rows).
FIELD_GAIN = 0.97
#: The field's kriging uses at most this many training rows (seeded: FIELD_SEED).
KRIGING_ROWS = 1000
#: Validation rows on which the nominal robot, in the training rows' tracker frame, is beyond
#: this times its error on the training rows and on the rows re-registered are in another
#: tracker frame (the tracker moved between the series).
MOVED_RATIO = 3.0
#: A calibrated robot whose validation RMS is beyond this times the nominal robot's (or
#: registration only's) is reported as not to be used (a few percent: the rows' spread).
WORSE_RATIO = 1.05


@dataclass(frozen=True, eq=False)
class PoseErrors:
    """Errors per validation pose (m): RMS over each pose's points of ``|measured - model|``
    (module docstring), the predicted RMS of the calibrated model's error (with the noise and
    the unmodelled error), which poses lie outside the training rows' joint ranges, and
    whether the rows are in another tracker frame than the training rows (``moved``: the
    nominal robot beyond ``MOVED_RATIO`` times its error on the training rows and on the
    validation rows re-registered)."""

    lines: tuple[int, ...]
    nominal_m: np.ndarray
    registration_m: np.ndarray
    calibrated_m: np.ndarray
    nominal_reregistered_m: np.ndarray
    registration_reregistered_m: np.ndarray
    calibrated_reregistered_m: np.ndarray
    predicted_m: np.ndarray
    out_of_range: np.ndarray
    moved: bool = False
    field_m: np.ndarray | None = None
    field_reregistered_m: np.ndarray | None = None
    predicted_field_m: np.ndarray | None = None

    @property
    def counted(self) -> tuple[str, str, str]:
        """The errors that count, nominal, registration only and calibrated: in the training
        frame, or re-registered when the rows are in another tracker frame (``moved``)."""
        if self.moved:
            return "nominal_reregistered", "registration_reregistered", "calibrated_reregistered"
        return "nominal", "registration", "calibrated"

    def rms(self, name: str, where: np.ndarray | None = None) -> float:
        e = getattr(self, f"{name}_m")
        e = e if where is None else e[where]
        return float(np.sqrt(np.mean(e**2))) if e.size else math.nan


@dataclass(frozen=True, eq=False)
class Calibration:
    """What ``casadi-design identify`` found (module docstring). SI units.

    Attributes
    ----------
    fit : the final fit (outliers excluded).
    outliers : tuple of (line, the row's score when it was excluded, the residual scale (m) it
        was judged against): :func:`row_scores`.
    std : ndarray, shape (L,): standard deviations with the fit's error per value ``s``
        (``scale``: the tracker's sigma and the robot's unmodelled error, :mod:`.residuals`).
    correlation : ndarray, shape (L, L).
    sigma_hat_m, chi2, dof, chi2_interval : the noise estimated from the residuals and its test.
    residual_rms_m, residual_max_m : ndarray, shape (m,): per row, over its points (NaN: excluded
        rows get the calibrated model's error too, as the other rows).
    residual_axes_m : ndarray, shape (m, k, 3): per row, point and axis (NaN where not measured).
    predicted_rms_m : ndarray, shape (s,): ``sqrt(rho_j)`` at the test poses,
        ``sqrt(s^2 trace(B0_j M^-1 B0_j^T) + d tau^2)``; ``predicted_parameters_m`` its first
        term alone (the parameters' error).
    q_compensated : ndarray, shape (s, n): commands that put the calibrated robot's measured
        frame on the nominal targets of the test poses (machining wrench included).
    validation : :class:`PoseErrors` of the validation rows, or None.
    model : the model identified (:data:`~.choice.MODELS`), ``candidates`` every candidate with
        its cross-validated error; ``loss`` the loss of the fit.
    notes : what a person should read (measured points located, a refit refused, a model
        worse than registration only, a validation beyond its prediction, a tracker that moved).
    scale : the :class:`~.residuals.ErrorScale` of the fit.
    field : the unmodelled error's field estimated from the fit's residuals
        (:class:`~.field_fit.TrainedField`), None when the residuals are the tracker's noise;
        when it predicts the training rows left out better (``field_compensates``,
        :func:`field_notes`) ``q_compensated`` corrects with its kriging mean too, and
        ``predicted_field_m`` (s,) is ``sqrt(rho_j)`` after that compensation (the kriging
        variance). Designs of a second round take it either way (``--prior``).
    """

    problem: Problem
    measurements: Measurements
    fit: Fit
    outliers: tuple[tuple[int, float, float], ...]
    std: np.ndarray
    correlation: np.ndarray
    sigma_hat_m: float
    chi2: float
    dof: int
    chi2_interval: tuple[float, float]
    residual_rms_m: np.ndarray
    residual_max_m: np.ndarray
    residual_axes_m: np.ndarray
    predicted_rms_m: np.ndarray
    q_compensated: np.ndarray
    compensation_converged: np.ndarray
    validation: PoseErrors | None
    validation_path: str | None
    validation_Q: np.ndarray | None
    model: str = "identifiable"
    candidates: tuple[Candidate, ...] = ()
    loss: str = "linear"
    notes: tuple[str, ...] = ()
    model_request: str = "auto"
    scale: ErrorScale | None = None
    predicted_parameters_m: np.ndarray | None = None
    field: TrainedField | None = None
    predicted_field_m: np.ndarray | None = None
    field_compensates: bool = False

    @property
    def model_chosen(self) -> bool:
        """Whether the model was chosen by cross-validation (``--model auto``)."""
        return self.model_request == "auto"

    @property
    def names(self) -> tuple[str, ...]:
        return self.fit.fit.model.parameter_names

    @property
    def noise_consistent(self) -> bool:
        low, high = self.chi2_interval
        return low <= self.chi2 <= high

    @property
    def test_pose_errors_m(self) -> np.ndarray | None:
        """The calibrated model's validation error (as counted: re-registered when the tracker
        moved) at each test pose that is also a validation pose (joints within
        ``SAME_POSE_RAD``), NaN at the others; None when there are none."""
        if self.validation is None:
            return None
        q0, qv = self.problem.test_poses.q, self.validation_Q
        same = np.all(np.abs(q0[:, None, :] - qv[None, :, :]) <= SAME_POSE_RAD, axis=2)
        if not same.any():
            return None
        e = np.full(len(q0), np.nan)
        j, i = np.nonzero(same)
        e[j] = getattr(self.validation, f"{self.validation.counted[2]}_m")[i]
        return e

    def correlated_pairs(self) -> list[tuple[str, str, float]]:
        C, out = self.correlation, []
        for a in range(len(C)):
            for b in range(a + 1, len(C)):
                if abs(C[a, b]) > CORRELATION_LIMIT:
                    out.append((self.names[a], self.names[b], float(C[a, b])))
        return out


def row_scores(f: Fit, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Each row's outlier score (m,) and the scale (m,), m, it is judged against: its
    externally studentized residual among the fit's rows used (:func:`~.residuals.deleted_scores`);
    rows not used score -inf."""
    used = f.used
    L = f.fit.model.L + (0 if f.frames is None else f.frames.size)
    score, s = np.full(len(used), -np.inf), np.full(len(used), np.nan)
    score[used], s[used] = deleted_scores(f.r[used], f.mask[used], leverages(f.J[used], f.information), sigma,
                                          int(f.mask[used].sum()) - L)
    return score, s


def fit_without_outliers(problem: Problem, fm: FitModel, meas: Measurements, T0: np.ndarray,
                         threshold: float, loss: str = "linear",
                         ) -> tuple[Fit, list[tuple[int, float, float]], list[str]]:
    """Fit, then exclude the rows whose score (:func:`row_scores`) exceeds ``threshold`` and
    half the worst row's, the worst first, and refit, while rows exceed the threshold; at most
    ``MAX_OUTLIER_SHARE`` of the rows (at least one) are excluded. A bad shot stands out
    against the residual scale; what many rows share is the model's error, not bad shots (a
    note says so when the cap stops the exclusion). A refit that fails (the rest do not
    identify X, or it does not converge) keeps the last good fit, and the notes say so.

    Returns the fit, the outliers (line, score, scale m) and the notes."""
    f, excluded, stopped = without_outliers(lambda used: fit(problem, fm, meas, T0, used, loss),
                                            lambda f: row_scores(f, problem.sigma_m), meas.m, threshold,
                                            MAX_OUTLIER_SHARE)
    outliers = [(meas.lines[i], score, scale) for i, score, scale in excluded]
    if stopped is None:
        return f, outliers, []
    if stopped.error is None:
        return f, outliers, [
            f"{stopped.beyond} more row{'s' * (stopped.beyond > 1)} lie beyond {threshold:g} x the other rows' "
            f"error (about {stopped.scale_m * 1e3:.4g} mm per value); at most {MAX_OUTLIER_SHARE:.0%} of the rows are excluded as bad "
            "shots: so many far out is the robot's error the model misses, not bad shots (their "
            "residuals: identification.png)"]
    why = str(stopped.error).split(": ", 1)[-1]
    return f, outliers, [f"row {meas.lines[stopped.row]} ({stopped.score:.1f} x the other rows' error) kept: "
                         f"the fit without it failed ({why}); the fit with it is reported"]


def design_rows(f: Fit, meas: Measurements) -> np.ndarray:
    """``B`` (m, d, L) at X = 0 of the rows of ``meas`` for the fit's physical parameters, the
    values not measured zero and, with several tracker frames, the later rounds' frames
    projected out (unknown): the design's rows of the plan that was measured."""
    model = f.fit.model
    B = model.B_stack(meas.Q, meas.F) * model.column_scale * f.mask[:, :, None]
    if f.frames is not None:  # the later rounds' frames unknown
        B = frames_projected(B, f.frame_of, f.used, len(f.fit.frame_names))
    return B


def design_information(f: Fit, meas: Measurements) -> np.ndarray:
    """``M = sum B_i^T B_i`` of the rows and values of ``meas`` the fit used
    (:func:`design_rows`): the information matrix of the design's measure for the plan that
    was measured (the standard deviations use ``J`` at the estimate), plus a MAP fit's prior
    ``diag((sigma / std)^2)``."""
    return f.with_prior(information_matrix(design_rows(f, meas)[f.used]))


def train_field(problem: Problem, f: Fit, meas: Measurements) -> TrainedField:
    """The unmodelled error's field of the fit's rows used (:func:`~.field_fit.estimate_field`),
    with what predicts and corrects it at other poses: their residuals and their rows ``B`` at
    X = 0 (:func:`design_rows`)."""
    used = f.used
    axes, Wh, model = problem.field_axes[0], problem.whitening, f.fit.model
    B = design_rows(f, meas)
    dq = model.dq_stack(meas.Q, meas.F) * f.mask[:, :, None]
    estimate = estimate_field(f.r[used], f.J[used], meas.Q[used], axes, Wh, problem.sigma_m, dq[used])
    rows = np.flatnonzero(used)
    if len(rows) > KRIGING_ROWS:  # the kriging's cost is cubic in the rows
        rows = np.sort(np.random.default_rng(FIELD_SEED).choice(rows, KRIGING_ROWS, replace=False))
    sites = estimate.field.sites(meas.Q[rows], axes, Wh, dq[rows])
    return TrainedField(estimate, sites, f.r[rows], B[rows], Wh, problem.sigma_m, model)


def field_notes(trained: TrainedField, rows: int) -> tuple[bool, list[str]]:
    """Whether the field is used to compensate: its leave-one-out error on the training rows
    (kriging with least squares) is below ``FIELD_GAIN`` times least squares' alone; and the
    notes that say what it does."""
    with_field, alone = trained.loo_rms(), trained.loo_rms(with_field=False)
    notes = [] if len(trained.Q) == rows else [
        f"the field's kriging uses {len(trained.Q)} of the {rows} rows (seeded; its cost is cubic in the rows)"]
    if with_field < FIELD_GAIN * alone:
        return True, notes
    return False, notes + [
        f"the field of the unmodelled error does not compensate: it does not predict the training rows left out "
        f"better ({with_field * 1e3:.4f} against {alone * 1e3:.4f} mm per value by least squares alone; the poses "
        "are too far apart for their errors to tell one another); identification.json keeps it for the design of "
        "a second round, which can measure nearer"]


def corrected_commands(model, X: np.ndarray, Q: np.ndarray, F: np.ndarray, sigma: float,
                       field: TrainedField | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The commands (k, n) that put the identified robot ``X`` (physical, the fit's) on the
    nominal targets of the poses ``Q`` (k, n), rad, under the wrenches ``F`` (k, nF), N, and
    which converged (k,): :func:`~.compensate.compensate`; with a ``field`` the target's
    position is moved against the field's kriging mean at the pose (the robot will be off by
    it there) and, with an error of the joint angles, its orientation turned back by the
    field's turn ``w`` (``R <- exp(-[w]) R``; the required orientation components), so the robot
    with its unmodelled error lands on the target."""
    target = nominal_poses(model, Q, F)
    if field is not None:
        target = target.copy()
        target[:, 9:] -= field.shift(Q)
        w = field.turn(Q, F)
        if np.any(w):
            from scipy.spatial.transform import Rotation

            R = pose_parts(target)[0]
            R = Rotation.from_rotvec(-w).as_matrix() @ R
            target[:, :9] = R.transpose(0, 2, 1).reshape(-1, 9)
    qc, done, _ = compensate(model, Q, F, target, np.tile(X, (len(Q), 1)), sigma)
    return qc, done


def compensated(calibration: Calibration, Q: np.ndarray, F: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The commands (k, n), rad (m), that put the identified robot on the nominal targets of a
    user's poses ``Q`` (k, n) under the wrenches ``F`` (k, nF), N (default none): the calibrated
    model, and its field's kriging mean where the field compensates
    (:attr:`Calibration.field_compensates`); and which converged (k,). What
    ``compensated_test_poses.csv`` holds for the test poses (:func:`corrected_commands`)::

        cal = calibrate(problem, read_measurements(problem, "meas.csv"))
        q_commands, ok = compensated(cal, q_targets)
    """
    model = calibration.fit.fit.model
    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    F = np.zeros((len(Q), model.nF)) if F is None else np.asarray(F, dtype=float).reshape(len(Q), model.nF)
    if Q.shape[1] != model.n:
        raise ProblemError(f"compensated: poses of {Q.shape[1]} joints for a robot of {model.n} "
                           f"({', '.join(calibration.problem.robot.joints)}); give one value per joint, rad (m)")
    return corrected_commands(model, calibration.fit.robot_X, Q, F, calibration.problem.sigma_m,
                              calibration.field if calibration.field_compensates else None)


def validate_rows(problem: Problem, f: Fit, valid: Measurements, M: np.ndarray,
                  registered: Fit | None, training: Measurements, s_m: float,
                  field: TrainedField | None = None) -> PoseErrors:
    """Errors at the validation rows of the nominal, registration-only (``registered``; None:
    the nominal's) and calibrated models in the training frame and each re-registered on the
    rows, and the predicted RMS with ``s_m`` the error per value (module docstring); with a
    ``field`` the calibrated model corrected by its kriging mean too, and its prediction (the
    kriging variance and the validation's own noise)."""
    fm, axes = f.fit, measured_axes(problem)
    model = fm.model
    seen = valid.seen

    def reregistered(points: np.ndarray) -> np.ndarray:
        found = rigid_fit(points[seen], valid.P_m[seen], axes) if fm.frame == "tracker" else None
        return pose_rms(point_errors(problem, valid.P_m, in_tracker(
            f.T0 if found is None and fm.frame == "tracker" else np.eye(4) if found is None else frame_matrix(*found), points)))

    nominal = model_points(model, valid.Q, valid.F, np.zeros(model.L))
    calibrated = model_points(model, valid.Q, valid.F, f.robot_X)
    placed = nominal if registered is None else model_points(registered.fit.model, valid.Q, valid.F, registered.robot_X)
    e_nominal = pose_rms(point_errors(problem, valid.P_m, in_tracker(f.T0, nominal)))
    Bv = model.B_stack(valid.Q, valid.F) * model.column_scale  # for the physical X of the fit
    per = len(axes)
    mask = np.repeat(seen, per, axis=1)
    Bv = Bv * mask[:, :, None]
    k = seen.sum(axis=1)
    model_var = rho_at_test_poses(M, Bv, s_m)  # s^2 trace(B_v M^-1 B_v^T)
    predicted = np.sqrt((model_var + mask.sum(axis=1) * s_m**2) / k)
    Qt = training.Q[f.used]
    outside = np.any((valid.Q < Qt.min(axis=0) - SAME_POSE_RAD) | (valid.Q > Qt.max(axis=0) + SAME_POSE_RAD), axis=1)
    nominal_training = pose_rms(point_errors(problem, training.P_m, in_tracker(
        f.T0s[training.frame_of], model_points(model, training.Q, training.F, np.zeros(model.L)))))[f.used]
    e_nominal_re = reregistered(nominal)
    moved = bool(fm.frame == "tracker" and np.sqrt(np.mean(e_nominal**2)) > MOVED_RATIO * max(
        float(np.sqrt(np.mean(nominal_training**2))), float(np.sqrt(np.mean(e_nominal_re**2)))))
    errors = PoseErrors(valid.lines, e_nominal,
                        e_nominal if registered is None else row_errors(problem, registered, valid),
                        row_errors(problem, f, valid), e_nominal_re, reregistered(placed), reregistered(calibrated),
                        predicted, outside, moved)
    if field is None:
        return errors
    corrected = calibrated + field.marker_shift(valid.Q, valid.F)
    seen_share = mask.sum(axis=1) / mask.shape[1]  # (a marker not seen: its share of the field's error)
    rho = field.rho(Bv, field.at(valid.Q, valid.F, "measured")) * seen_share
    return replace(errors, field_m=pose_rms(point_errors(problem, valid.P_m, in_tracker(f.tracker_from_base, corrected))),
                   field_reregistered_m=reregistered(corrected),
                   predicted_field_m=np.sqrt((rho + mask.sum(axis=1) * problem.sigma_m**2) / k))


def calibrate(problem: Problem, meas: Measurements, frame: str = "tracker",
              validation: Measurements | None = None, threshold: float = OUTLIER_SIGMA,
              loss: str = "linear", model: str = "auto") -> Calibration:
    """Identify the robot of ``problem`` from ``meas`` (module docstring).

    The measured points are located first when they are far off (:func:`~.fit.register`:
    ``Calibration.problem`` is then the problem with the located points); the model is
    ``model`` of :data:`~.choice.MODELS`.

    Raises
    ------
    ProblemError
        Measurements that cannot be registered or do not identify the parameters.
    DesignError
        A fit that does not converge.
    """
    if model not in MODELS:
        raise ProblemError(f"--model {model}: allowed for tracker measurements: {', '.join(MODELS)}")
    if not threshold > 0:
        raise ProblemError(f"--outlier-sigma {threshold:g}: give a positive number of sigma, e.g. 4")
    check_loss(loss)
    if model == "prior" and problem.spec.calibration.prior is None:
        raise ProblemError("--model prior: the problem file has no [calibration.prior]; add one "
                           "(a standard deviation per group, e.g. length_m = 1e-3, angle_rad = 1e-3)")
    problem, own, T0, notes = register(problem, frame, meas)
    if has_weight(problem):  # a model that misses the sag would take the sagging rows for outliers
        own = fit_model(problem, frame, problem.model.parameter_names + tuple(
            f"k.{j}" for j in problem.robot.joints if f"k.{j}" not in problem.model.parameter_names),
            gravity=True)
    try:  # the outliers are the richest model's: a smaller one takes what it misses for bad shots
        rich, outliers, refused = fit_without_outliers(problem, own, meas, T0, threshold, loss)
        rows = rich.used
    except (ProblemError, DesignError):
        rows, outliers, refused = None, [], []
    found = candidates(problem, frame, meas, T0, loss, np.ones(meas.m, dtype=bool) if rows is None else rows,
                       model)
    chosen, warnings = choose(found, model)
    fm = chosen.fit_model
    # the chosen model on the rows without the outliers: the candidate's fit (to those rows; None
    # when it failed)
    f = chosen.fitted if rows is not None else None
    if f is None:
        f, outliers, refused = fit_without_outliers(problem, fm, meas, T0, threshold, loss)
    notes += refused + warnings
    if frame == "tracker" and problem.model.case == "elastostatic" and np.all(np.any(meas.F != 0, axis=1)):
        notes.append("an elasto-static plan is designed for points measured in the robot's base frame (the "
                     "deflections); here the tracker frame is fitted from the same rows, which costs accuracy: "
                     "measure the poses unloaded too, or give points registered in the base frame with --frame base")
    sigma, L = problem.sigma_m, fm.model.L
    N = int(f.mask[f.used].sum())
    dof = N - L - (0 if f.frames is None else f.frames.size)  # the later rounds' frames too
    ssr = float(np.sum(f.r[f.used] ** 2))
    interval = ((float(chi2_quantile((1 - CONFIDENCE) / 2, dof)), float(chi2_quantile((1 + CONFIDENCE) / 2, dof)))
                if dof > 0 else (0.0, float("inf")))
    sigma_hat = float(np.sqrt(ssr / dof)) if dof > 0 else float("nan")
    rejected = dof > 0 and ssr / sigma**2 > float(chi2_quantile(UNMODELLED_CONFIDENCE, dof))
    scale = error_scale(f.r[f.used], leverages(f.J[f.used], f.information), sigma, sigma_hat, rejected)
    s_m = scale.s_m
    C = s_m**2 * np.linalg.inv(f.information)
    std = np.sqrt(np.diagonal(C))
    correlation = C / np.outer(std, std)
    trained = train_field(problem, f, meas) if scale.tau_m > 0 else None
    compensating = None
    if trained is not None:
        use, said = field_notes(trained, int(f.used.sum()))
        notes += said
        compensating = trained if use else None
    negative = negative_compliances(f, std)
    if negative:  # a joint that yields against its load: what the model misses
        notes.append(f"negative compliance beyond {NEGATIVE_STD:g} std: "
                     f"{', '.join(f'{n} = {x:.3g} (std {s:.2g})' for n, x, s in negative)}; no joint yields against "
                     "its load: the model misses what moves the robot (geometric errors, the load point)")
    model_P = f.tracker_points(meas.Q, meas.F, meas.frame_of)
    e = point_errors(problem, meas.P_m, model_P)
    if fm.model.gravity:  # the robot files hold the kinematics: without the sag they are off
        rigid = replace(f, X=np.where([n.startswith("k.") for n in fm.model.parameter_names], 0.0, f.X))
        off = pose_rms(point_errors(problem, meas.P_m, rigid.tracker_points(meas.Q, meas.F, meas.frame_of)))[f.used]
        notes.append(f"the {chosen.name} model holds the joints' compliance under the robot's own weight; "
                     "calibrated.urdf and calibrated.toml hold its kinematics only, "
                     f"{np.sqrt(np.mean(off**2)) * 1e3:.3f} mm RMS off the training rows without the sag "
                     f"({np.sqrt(np.mean(pose_rms(e)[f.used] ** 2)) * 1e3:.3f} mm with it): use them with the "
                     "compliances of identification.json, or choose a model without gravity (--model)")
    axes_m = meas.P_m - model_P
    axes_m[:, :, [a for a in range(3) if a not in measured_axes(problem)]] = np.nan

    tp = problem.test_poses
    B0 = fm.model.B_stack(tp.q, tp.F, accuracy=True) * fm.model.column_scale  # physical X, as M
    M0 = design_information(f, meas)
    parameters_var = rho_at_test_poses(M0, B0, s_m)  # s^2 trace(B0 M^-1 B0^T)
    predicted = np.sqrt(parameters_var + B0.shape[1] * scale.tau_m**2)  # + the pose's own unmodelled error
    predicted_field = None if compensating is None else np.sqrt(compensating.rho(B0, compensating.at(tp.q, tp.F)))
    qc, done = corrected_commands(fm.model, f.robot_X, tp.q, tp.F, sigma, compensating)
    valid = None
    if validation is not None:
        base = found[0]
        registered = None if math.isnan(base.training_rms_m) else (
            f if base is chosen else base.fitted if np.array_equal(base.fitted.used, f.used)
            else fit(problem, base.fit_model, meas, T0, f.used, loss))
        valid = validate_rows(problem, f, validation, M0, registered, meas, s_m, compensating)
        if valid.rms("nominal_reregistered") > REGISTRATION_TOL_M:  # the rows of another robot, or units
            raise ProblemError(
                f"--validation {validation.path}: after the best rigid fit the nominal robot is "
                f"{valid.rms('nominal_reregistered') * 1e3:.1f} mm RMS off its points, more than "
                f"{REGISTRATION_TOL_M * 1e3:g} mm: not this robot's rows, or not in the measurements' units (--units, "
                "--joint-units and --columns read every file alike)")
        notes += validation_notes(valid)
    return Calibration(
        problem, meas, f, tuple(outliers), std, correlation, sigma_hat, ssr / sigma**2, dof, interval,
        pose_rms(e), np.nanmax(e, axis=1), axes_m, predicted, qc, done, valid,
        None if validation is None else validation.path, None if validation is None else validation.Q,
        chosen.name, tuple(found), loss, tuple(notes), model, scale, np.sqrt(parameters_var), trained, predicted_field,
        compensating is not None)


def validation_notes(valid: PoseErrors) -> list[str]:
    """What a person should read about the validation rows: a tracker frame that moved, a
    measured error beyond ``PREDICTION_RATIO`` times its prediction, a calibrated robot worse
    than the nominal one or registration only; judged in the frame that counts
    (:attr:`PoseErrors.counted`)."""
    nominal, registration, calibrated = valid.counted
    notes = []
    if valid.moved:
        notes.append(
            f"the validation rows are in another tracker frame than the training rows (the tracker moved): "
            f"in the training rows' frame the nominal robot is {valid.rms('nominal') * 1e3:.1f} mm RMS off them, "
            f"after its own rigid fit {valid.rms('nominal_reregistered') * 1e3:.3f} mm; the re-registered "
            "figures count (each model fitted rigidly to the validation rows)")
    measured, predicted = valid.rms(calibrated), valid.rms("predicted")
    if measured > PREDICTION_RATIO * predicted:
        notes.append(f"the validation RMS {measured * 1e3:.3f} mm{' (re-registered)' * valid.moved} is "
                     f"{measured / predicted:.1f}x its prediction {predicted * 1e3:.3f} mm: the robot's error "
                     "differs from the training rows' (other poses, another day or temperature, the tracker)")
    name, before = min((("the nominal robot", valid.rms(nominal)), ("registration only", valid.rms(registration))),
                       key=lambda b: b[1])
    if measured > WORSE_RATIO * before:
        notes.append(f"the calibrated robot is farther from the validation rows than {name}"
                     f"{' (re-registered)' * valid.moved} ({measured * 1e3:.3f} against {before * 1e3:.3f} mm RMS): "
                     "do not use its files; measure more rows, or choose a model that holds what the robot does")
    return notes
