"""Identify a robot from recordings of points fixed in an artefact (no tracker).

The measurement model is :mod:`casadi_design.calibration.artefact`'s: each recording puts the
measured point ``p(q_i, X)`` (the problem's one model, :mod:`casadi_design.calibration.models`)
at point ``a_k`` of placement g, ``t_g + R_g a_k``, within the seating repeatability sigma. The
fit is weighted least squares over X and every placement's pose (scipy's Levenberg-Marquardt,
exact Jacobian; the placements start from the rigid fit of the artefact's points to the nominal
robot's mean point of each, :meth:`~casadi_design.calibration.artefact.Artefact.place`).

What the recordings tell: no placement fixes the robot's base, so the parameters a rigid motion
of the whole robot absorbs (``base.*`` and their combinations, :func:`~.fit.fit_model` in the
tracker frame) are left out; of the rest, the base set of the rows is chosen by QR with column
pivoting of the Jacobian with the placements projected out (:func:`artefact_base_set`).
Statistics are those of :mod:`.residuals` on the rows with the placements projected out
(``J^T J`` the information of X with every placement unknown): leverages, the PRESS residuals of
the model choice (:mod:`.choice`'s one-standard-error rule), the outlier scores (a ball that was
not seated), the error scale ``s`` (the seating repeatability and the robot's unmodelled error).

Judged on placements not in the fit, by the figures a user of this setup computes without us
(:func:`judged`): **consistency**, the mean distance of the FK ball centres to their point's mean
(MUKCa's figure), and **spacing**, the error of the distance between two points' means against
the artefact's; each with its prediction from the fit's covariance and scale (:func:`predicted`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..calibration.artefact import Artefact, artefact_rows, identifiable, placement_columns, placement_projected
from ..calibration.identifiability import RANK_RTOL
from ..calibration.models import CalibrationModel
from ..errors import DesignError, ProblemError
from ..problem.build import Problem
from ..robot.mapped import evaluate
from ..measures.field import Field, covariance, value_covariance
from .choice import NEGATIVE_STD, Candidate, choose, cv_error, has_weight, negative_compliances
from .field_fit import FieldFit, estimate_field
from .fit import SEATING_N, FitModel, fit_model
from .lsq import LSQ_TOL, frame_poses, measurement_jacobian, nominal_poses, remembered
from .recordings import Recordings
from .residuals import ErrorScale, chi2_quantile, deleted_scores, error_scale, leverages, press, without_outliers

#: Outlier test: a configuration whose externally studentized residual exceeds this many of the
#: other rows' errors is a ball not seated; at most this share of the rows is excluded.
OUTLIER_SIGMA = 4.0
MAX_OUTLIER_SHARE = 0.05
#: Draws of the Monte Carlo that turns a predicted covariance into a mean distance (seeded).
DISTANCE_DRAWS = 4000
DISTANCE_SEED = 0
#: The base axes of the measured point's values (x, y, z).
AXES = np.arange(3)
#: Model evaluations of one fit at most: a few recordings for many parameters leave directions
#: the trust region crawls along (16 configurations of a Panda's 25 parameters: 40 to 200).
MAX_EVALUATIONS = 1000
#: The chi-square quantile above which the residuals are more than the seating repeatability.
UNMODELLED_CONFIDENCE = 0.999


def ball_points(model: CalibrationModel, Q: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The measured point ``p(q, X)`` (N, 3), m, of configurations ``Q`` (N, n) and ``dp/dX``
    (N, 3, L): the model's measurement plus its nominal reference (one point, x y z, whitening
    the identity: one sigma)."""
    F = np.zeros((len(Q), model.nF))
    ref = nominal_poses(model, Q, F)
    y, J = evaluate(measurement_jacobian(model), Q, F, np.tile(X, (len(Q), 1)), ref, threads=1)
    return y.reshape(len(Q), 3) + ref[:, 9:12], J.reshape(len(Q), 3, model.L)


@dataclass(frozen=True, eq=False)
class ArtefactFit:
    """One least-squares fit of the recordings ``used``.

    Attributes
    ----------
    fit : the fit's model (``fit.model.parameter_names`` are X's).
    X : ndarray, shape (L,), SI units.
    R : ndarray, shape (P, 3, 3); t : ndarray, shape (P, 3), m: each placement's pose.
    r : ndarray, shape (N, 3), m: residuals ``p(q_i, X) - (t_g + R_g a_k)`` of every row.
    J : ndarray, shape (N, 3, L), m per unit: ``dp/dX`` with each placement's columns projected
        out over the rows used (``J[used]^T J[used]`` the information of X).
    used : ndarray of bool, shape (N,).
    evaluations : model evaluations of the least squares.
    placement_parameters : the placements' pose parameters fitted beside X.
    """

    fit: FitModel
    X: np.ndarray
    R: np.ndarray
    t: np.ndarray
    r: np.ndarray
    J: np.ndarray
    used: np.ndarray
    evaluations: int
    placement_parameters: int

    @property
    def information(self) -> np.ndarray:
        """``J^T J`` over the rows used, (L, L): the information of X with the placements unknown."""
        J = self.J[self.used].reshape(-1, self.J.shape[2])
        return J.T @ J

    @property
    def dof(self) -> int:
        """Values less parameters (X and the placements' poses)."""
        return 3 * int(self.used.sum()) - self.J.shape[2] - self.placement_parameters


def fit_artefact(problem: Problem, fm: FitModel, rec: Recordings, used: np.ndarray | None = None) -> ArtefactFit:
    """Fit X and the placements to the recordings ``used`` (module docstring).

    Raises
    ------
    DesignError
        Rows that do not identify X with the placements unknown, or a fit that does not converge.
    """
    from scipy.optimize import least_squares  # imported here: scipy.optimize takes ~0.3 s

    A, model, sigma = problem.artefact, fm.model, problem.sigma_m
    used = np.ones(rec.N, dtype=bool) if used is None else used
    Q, k, g = rec.Q[used], rec.point[used], rec.placement[used]
    places = np.unique(g)
    at = np.searchsorted(places, g)  # each row's placement among those used
    R0, t0 = A.placed(ball_points(model, Q, np.zeros(model.L))[0], k, at)
    L, nP = model.L, A.nP

    def poses(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        moved = [A.moved(R0[i], t0[i], x[L + i * nP:L + (i + 1) * nP]) for i in range(len(places))]
        return np.array([m[0] for m in moved]), np.array([m[1] for m in moved])

    def residuals(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, t = poses(x)
        p, J = ball_points(model, Q, x[:L])
        s = t[at] + np.einsum("kab,kb->ka", R[at], A.points_m[k])
        return (p - s).reshape(-1) / sigma, artefact_rows(A, J, R, k, at).reshape(3 * len(Q), -1) / sigma

    evaluated = remembered(residuals)
    x0 = np.zeros(L + nP * len(places))
    J0 = evaluated(x0)[1]
    if 3 * len(Q) < len(x0) or np.linalg.matrix_rank(J0, tol=RANK_RTOL * np.linalg.norm(J0, 2)) < len(x0):
        raise DesignError(f"the {int(used.sum())} recordings do not identify the {L} parameters with the "
                          f"{len(places)} placement(s) unknown; record more varied configurations")
    norms = np.linalg.norm(J0, axis=0)
    # MINPACK's Levenberg-Marquardt, or the trust-region reflective method where the joints
    # deflect under a load (a Panda under its weight): there LM's first steps reach compliances whose deflection
    # fixed point runs away (a Panda: cost 1e5 sigma^2 after 1000 evaluations; trf: 53)
    found = least_squares(lambda x: evaluated(x)[0], x0, jac=lambda x: evaluated(x)[1], method="trf" if model.loaded else "lm",
                          x_scale=1.0 / np.where(norms > 0, norms, 1.0), ftol=LSQ_TOL, xtol=LSQ_TOL, gtol=LSQ_TOL,
                          max_nfev=MAX_EVALUATIONS)
    if found.status <= 0:
        raise DesignError(f"the fit to the recordings did not converge in {found.nfev} evaluations")
    X = found.x[:L]
    R, t = poses(found.x)
    # every row's residual and Jacobian at the estimate; the placements projected out over the rows used
    Rall = np.zeros((len(rec.names), 3, 3))
    tall = np.full((len(rec.names), 3), np.nan)
    Rall[places], tall[places] = R, t
    p, J = ball_points(model, rec.Q, X)
    s = tall[rec.placement] + np.einsum("kab,kb->ka", Rall[rec.placement], A.points_m[rec.point])
    Jp = np.array(J)
    Jp[used] = placement_projected(J[used], placement_columns(A, R, k, at))
    return ArtefactFit(fm, X, Rall, tall, p - s, Jp, used, int(found.nfev), nP * len(places))


def artefact_base_set(problem: Problem, rec: Recordings, names: tuple[str, ...],
                      load: str = "") -> tuple[tuple[str, ...], list[tuple[str, str]]]:
    """The parameters of ``names`` the recordings identify with every placement and the robot's
    base unknown (:func:`~casadi_design.calibration.artefact.identifiable` at the nominal
    robot; the compliances ``k.<joint>`` of ``names`` deflect the joints under the ``load``:
    ``"gravity"``, the robot's own weight, or ``"seating"``, the push seating the ball), and
    (name, why) of those left out."""
    fm = loaded_model(problem, names, load)
    p, J = ball_points(fm.model, rec.Q, np.zeros(fm.model.L))
    at = np.searchsorted(np.unique(rec.placement), rec.placement)  # the placements recorded, 0..P-1
    R, _ = problem.artefact.placed(p, rec.point, at)
    kept, live = identifiable(J, p, placement_columns(problem.artefact, R, rec.point, at))
    why = {False: "a rigid motion of the whole robot or of a placement (the base, which no fixed point tells)",
           True: "acts as a combination of the parameters kept"}
    return (tuple(n for n, k in zip(fm.model.parameter_names, kept) if k),
            [(n, why[bool(live[i])]) for i, n in enumerate(fm.model.parameter_names) if not kept[i]])


#: Configurations, uniform within the joint limits, of the recordings that tell every parameter
#: an artefact's recordings can tell (:func:`generic_base_set`), and their seed.
GENERIC_CONFIGURATIONS, GENERIC_SEED = 200, 0


def generic_base_set(problem: Problem, names: tuple[str, ...]) -> tuple[str, ...]:
    """The parameters of ``names`` that recordings of varied configurations tell
    (:func:`artefact_base_set` of :data:`GENERIC_CONFIGURATIONS` uniform within the joint limits,
    at the artefact's points in turn, one placement): what the kind can tell, against which the
    recordings' own base set shows configurations that vary too little."""
    robot = problem.robot
    rng = np.random.default_rng(GENERIC_SEED)
    Q = robot.q_min + rng.random((GENERIC_CONFIGURATIONS, robot.n)) * (robot.q_max - robot.q_min)
    k = np.arange(len(Q)) % problem.artefact.K
    rec = Recordings(Q, k, np.zeros(len(Q), dtype=int), ("generic",), (), ())
    return artefact_base_set(problem, rec, names)[0]


def row_scores(f: ArtefactFit, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Each row's outlier score and scale (m): its externally studentized residual among the
    rows used (:func:`~.residuals.deleted_scores`); rows not used score -inf."""
    used = f.used
    score, s = np.full(len(used), -np.inf), np.full(len(used), np.nan)
    score[used], s[used] = deleted_scores(f.r[used], np.ones((int(used.sum()), 3), dtype=bool),
                                          leverages(f.J[used], f.information), sigma, f.dof + 3)
    return score, s


#: A joint is loaded by the robot's own weight (or the seating push) when the RMS of its torque
#: over the recordings is at least this share of the most loaded joint's: under the weight, a
#: Panda's joints 2, 3, 4 and 6 (26, 15, 9.5, 1.5 N m), not 5 and 7 (0.5, 0.01 N m), whose
#: compliances would take up anything.
LOADED_SHARE = 0.05


def loaded_joints(problem: Problem, Q: np.ndarray, load: str) -> tuple[str, ...]:
    """The joints the ``load`` (:func:`artefact_base_set`) loads at the configurations ``Q``
    (:data:`LOADED_SHARE`): the weight's torque ``g(q)``, the seating push's ``(dp/dq)^T f``."""
    if load == "gravity":
        tau = np.stack([np.asarray(problem.model.kinematics.gravity_torque(q), dtype=float).ravel() for q in Q])
    else:
        tau = problem.model.dq_stack(Q, rows="position").transpose(0, 2, 1) @ np.asarray(SEATING_N)
    rms = np.sqrt(np.mean(tau**2, axis=0))
    return tuple(j for j, r in zip(problem.robot.joints, rms) if r > 0 and r >= LOADED_SHARE * rms.max())


def loaded_model(problem: Problem, names: tuple[str, ...], load: str) -> FitModel:
    """The fit model of ``names`` in the base frame whose compliances deflect the joints under
    ``load`` (:func:`artefact_base_set`; ``""``: none)."""
    return fit_model(problem, "base", names, gravity=load == "gravity", seating=load == "seating")


def bent_joints(problem: Problem, Q: np.ndarray) -> tuple[str, ...]:
    """The tilts ``<joint>.<axis>`` (axes across the joint's own) whose bending moment under the
    robot's own weight at the configurations ``Q`` is loaded (:data:`LOADED_SHARE` of the most
    loaded tilt's RMS)."""
    from ..calibration.models import TILT_AXES
    from ..robot.symbolic import joint_axis

    kin, robot = problem.model.kinematics, problem.robot
    names = [f"{j}.{a}" for j, jid in zip(robot.joints, robot.joint_ids) for a, u in zip(TILT_AXES, np.eye(3))
             if abs(joint_axis(robot.model.joints[jid])[0] @ u) < 0.5]
    cols = [kin.parameter_names.index(n) for n in names]
    G = np.stack([np.asarray(kin.gravity_moments(q), dtype=float).ravel()[cols] for q in Q])
    rms = np.sqrt(np.mean(G**2, axis=0))
    return tuple(n for n, r in zip(names, rms) if r > 0 and r >= LOADED_SHARE * rms.max())


def fit_without_outliers(problem: Problem, fm: FitModel, rec: Recordings,
                         threshold: float = OUTLIER_SIGMA) -> tuple[ArtefactFit, list[tuple[str, float]], list[str]]:
    """Fit, then exclude the rows scoring beyond ``threshold`` (and half the worst one's), the
    worst first, and refit, at most :data:`MAX_OUTLIER_SHARE` of the rows: a ball that was not
    seated stands out against the other rows' error. The fit, the outliers (source, score) and
    the notes."""
    f, excluded, stopped = without_outliers(lambda used: fit_artefact(problem, fm, rec, used),
                                            lambda f: row_scores(f, problem.sigma_m), rec.N, threshold,
                                            MAX_OUTLIER_SHARE)
    outliers = [(rec.sources[i], score) for i, score, _ in excluded]
    if stopped is None:
        return f, outliers, []
    if stopped.error is None:
        return f, outliers, [f"{stopped.beyond} more configuration{'s' * (stopped.beyond > 1)} lie beyond {threshold:g} x "
                             f"the other rows' error (about {stopped.scale_m * 1e3:.3g} mm); at most "
                             f"{MAX_OUTLIER_SHARE:.0%} are excluded: so many is the robot's error, not balls unseated"]
    return f, outliers, [f"{rec.sources[stopped.row]} kept: the fit without it failed ({stopped.error})"]


def cross_validate(f: ArtefactFit) -> tuple[np.ndarray | None, str]:
    """Each configuration's leave-one-out point error (m) of the fit (:mod:`.choice`), the
    left-out configuration's placement refitted by the rest; None and why when a row is needed
    to identify the model."""
    used = np.flatnonzero(f.used)
    e, _, needed = press(f.r[used], leverages(f.J[used], f.information))
    if e is None:
        return None, f"configuration {needed + 1} is needed to identify it"
    return np.linalg.norm(e, axis=1), ""


def scale_of(f: ArtefactFit, sigma: float) -> ErrorScale:
    """The error per value (m): the seating repeatability ``sigma`` and the robot's unmodelled
    error, from the PRESS residuals when the chi-square test rejects sigma alone (:mod:`.residuals`)."""
    r = f.r[f.used]
    ssr = float(np.sum(r**2))
    rejected = ssr / sigma**2 > chi2_quantile(UNMODELLED_CONFIDENCE, max(f.dof, 1))
    return error_scale(r, leverages(f.J[f.used], f.information), sigma, math.sqrt(ssr / max(f.dof, 1)), rejected)


@dataclass(frozen=True)
class Judged:
    """Figures of one placement (m): ``consistency`` the mean distance of the FK points to their
    point's mean, averaged over the points (MUKCa's), ``spacing`` the largest error of the
    distance between two points' means against the artefact's; ``predicted_*`` the same
    expected from the fit (:func:`predicted`); ``nominal_*`` of the nominal robot;
    ``moved_m`` (3,) the measured point's move on the hand that these configurations tell, in
    the measured frame, its size in standard deviations ``moved_std`` and the consistency
    with it moved, ``relocated_consistency_m`` (:func:`relocated`); ``beyond`` the
    configurations farther from their point's mean than the prediction allows
    (:func:`beyond_prediction`)."""

    name: str
    rows: int
    consistency_m: float
    spacing_m: float
    predicted_consistency_m: float
    predicted_spacing_m: float
    nominal_consistency_m: float
    nominal_spacing_m: float
    moved_m: tuple[float, float, float] = (math.nan,) * 3
    moved_std: float = math.nan
    relocated_consistency_m: float = math.nan
    beyond: int = 0

    def as_dict(self) -> dict:
        return {"placement": self.name, "configurations": self.rows,
                **{f"{k}_mm": getattr(self, f"{k}_m") * 1e3 for k in
                   ("consistency", "spacing", "predicted_consistency", "predicted_spacing", "nominal_consistency",
                    "nominal_spacing", "relocated_consistency")},
                "measured_point_moved_mm": [x * 1e3 for x in self.moved_m],
                "measured_point_moved_std": self.moved_std, "configurations_beyond_prediction": self.beyond,
                "recorded_badly": self.recorded_badly}

    @property
    def recorded_badly(self) -> bool:
        """More than :data:`UNSEATED_SHARE` of the configurations beyond the prediction: balls not
        seated, or the tool moved while it was recorded; the consistency is not the robot's."""
        return self.beyond > UNSEATED_SHARE * self.rows


#: The measured point moved on the hand when its move is beyond this many standard deviations
#: (its Mahalanobis length under the fit's predicted error at those configurations,
#: :func:`relocated`; chi-square of 3 degrees of freedom: 1e-3 of false alarms).
MOVED_STD = 4.0
#: A held-out placement was not recorded well when more than this share of its configurations
#: are beyond the prediction (:func:`beyond_prediction`; by chance 1e-3 of them). On MUKCa's
#: recordings: 52 of 62 at panda_2's ``high``, at most 7 of 62 at every other placement.
UNSEATED_SHARE = 0.25


def relocated(R: np.ndarray, p: np.ndarray, k: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The move ``delta`` (3,), m, of the measured point in the measured frame that makes the
    configurations of one placement, seated at the points ``k`` (N,), most consistent: with
    ``R_i`` (N, 3, 3) and ``p_i`` (N, 3) the measured frame's rotation and position
    (:func:`~.lsq.frame_poses`), the linear least squares ``min sum_i |d_i + A_i delta|^2``,
    ``d_i = p_i - mean_k p``, ``A_i = R_i - mean_k R``; the consistency (m, :func:`figures`) of ``p_i + R_i delta``; and delta's covariance
    ``A^+ C_d A^+^T`` when the points err by ``cov`` (3N x 3N, m^2: the fit's predicted error,
    :func:`error_covariance`), ``C_d`` that of the ``d_i``: a move the calibrated robot's own
    error would make is not one of the point. A ball held by a gripper's fingers moves between
    placements when grasped again."""
    D = np.kron(np.eye(len(k)) - _point_means(k), np.eye(3))  # each point's mean subtracted
    A = D @ R.reshape(-1, 3)
    Ap = np.linalg.pinv(A)
    delta = -Ap @ (D @ p.reshape(-1))
    return delta, consistency_of(p + R @ delta, k), Ap @ D @ cov @ D.T @ Ap.T


def _point_means(k: np.ndarray) -> np.ndarray:
    """``avg`` (N, N): row i averages the rows seated at i's point."""
    avg = np.zeros((len(k), len(k)))
    for j in np.unique(k):
        rows = k == j
        avg[np.ix_(rows, rows)] = 1.0 / rows.sum()
    return avg


def consistency_of(p: np.ndarray, k: np.ndarray) -> float:
    """MUKCa's consistency (m) of the FK points ``p`` (N, 3) seated at the points ``k`` (N,):
    the mean distance to their point's mean, averaged over the points."""
    return float(np.mean([np.mean(np.linalg.norm(p[k == j] - p[k == j].mean(axis=0), axis=1)) for j in np.unique(k)]))


def figures(A: Artefact, p: np.ndarray, k: np.ndarray) -> tuple[float, float]:
    """Consistency and spacing (m) of the FK points ``p`` (N, 3) of one placement, seated at the
    points ``k`` (N,) (:class:`Judged`)."""
    seen = np.unique(k)
    means = {j: p[k == j].mean(axis=0) for j in seen}
    consistency = consistency_of(p, k)
    spacing = max((abs(float(np.linalg.norm(means[a] - means[b])) - A.spacings_m[a, b])
                   for a in seen for b in seen if a < b), default=math.nan)
    return consistency, spacing


def centred_covariances(k: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The covariances (N, 3, 3), m^2, of ``d_i = e_i - mean_k e``, each point's deviation from
    its point's mean, when the FK points of the configurations seated at ``k`` (N,) err by ``e``
    of covariance ``cov`` (3N x 3N)."""
    N = len(k)
    D = np.kron(np.eye(N) - _point_means(k), np.eye(3))
    return (D @ cov @ D.T).reshape(N, 3, N, 3)[np.arange(N), :, np.arange(N), :]


def beyond_prediction(p: np.ndarray, k: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Which FK points ``p`` (N, 3) seated at ``k`` (N,) are farther from their point's mean
    than :data:`MOVED_STD` standard deviations of the predicted error ``S``
    (:func:`centred_covariances`): ``d_i^T S_i^-1 d_i > MOVED_STD^2``, shape (N,) bool. Where
    many are, the robot's own error is not what the consistency measures: balls not seated, or
    the tool moved while it was recorded. A point of one configuration is its own mean: never
    beyond."""
    avg = _point_means(k)
    alone = np.diagonal(avg) == 1.0  # a point of one configuration: its own mean
    d = p - avg @ p
    S = np.where(alone[:, None, None], np.eye(3), S)
    return ~alone & (np.einsum("na,na->n", d, np.linalg.solve(S, d[:, :, None])[:, :, 0]) > MOVED_STD**2)


def predicted(A: Artefact, k: np.ndarray, cov: np.ndarray, S: np.ndarray) -> tuple[float, float]:
    """The expected consistency and spacing error (m) of one placement's configurations seated
    at ``k`` (N,) whose FK points err by ``e`` of covariance ``cov`` (3N x 3N, m^2; the seating's
    noise included): a point's deviation from its point's mean is ``d_i = e_i - mean_k e``, its
    expected length by a seeded Monte Carlo of its 3 x 3 covariance ``S_i``
    (:func:`centred_covariances`, ``S`` (N, 3, 3)); the spacing error of two
    means is a normal of variance ``u^T cov(mean_b e - mean_a e) u``, ``u`` their direction:
    ``sqrt(2 v / pi)`` its expected size."""
    N = len(k)
    seen = np.unique(k)
    z = np.random.default_rng(DISTANCE_SEED).standard_normal((DISTANCE_DRAWS, 3))
    w, U = np.linalg.eigh((S + S.transpose(0, 2, 1)) / 2)
    lengths = np.linalg.norm(np.einsum("kab,kb,zb->kza", U, np.sqrt(np.clip(w, 0.0, None)), z), axis=2)
    consistency = float(np.mean([lengths[k == j].mean() for j in seen]))
    spacing = math.nan
    for a in seen:
        for b in seen:
            if a < b:
                u = (A.points_m[b] - A.points_m[a]) / A.spacings_m[a, b]
                m = np.zeros(N)
                m[k == b], m[k == a] = 1.0 / np.sum(k == b), -1.0 / np.sum(k == a)
                row = np.kron(m, u)
                spacing = max(0.0 if math.isnan(spacing) else spacing, math.sqrt(2 * float(row @ cov @ row) / math.pi))
    return consistency, spacing


def error_covariance(f: ArtefactFit, Jh: np.ndarray, V: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """The covariance (3N x 3N, m^2) of the errors ``e_h = p(q_h, X_hat) - p_true(q_h) + eps_h``
    at configurations whose ``dp/dX`` are ``Jh`` (N, 3, L), for the least-squares estimate
    ``X_hat - X = H^-1 Jp^T (delta + eps)`` of the fit's rows (``Jp`` with the placements
    projected out): ``W Vtt W^T - W Vth - Vth^T W^T + Vhh``, ``W = Jh H^-1 Jp^T``, with ``V`` the
    covariances of the rows' errors (delta the robot's unmodelled error, eps the seating's
    noise): training-training, training-new, new-new."""
    Vtt, Vth, Vhh = V
    Jp = f.J[f.used].reshape(-1, f.J.shape[2])
    W = Jh.reshape(-1, Jh.shape[2]) @ np.linalg.solve(f.information, Jp.T)
    WV = W @ Vth
    return W @ Vtt @ W.T - WV - WV.T + Vhh


def full_jacobian(problem: Problem, f: ArtefactFit, rec: Recordings) -> np.ndarray:
    """``d r / d(X, poses)`` of the rows used (n, 3, L + P nP), m per unit: ``dp/dX`` and each
    placement's columns ``-G``: the fixed effects of the rows."""
    used = np.flatnonzero(f.used)
    _, J = ball_points(f.fit.model, rec.Q[used], f.X)
    places = np.unique(rec.placement[used])
    return artefact_rows(problem.artefact, J, f.R[places], rec.point[used], np.searchsorted(places, rec.placement[used]))


def unmodelled_field(problem: Problem, f: ArtefactFit, rec: Recordings) -> FieldFit:
    """The robot's unmodelled error as a field over its configurations, estimated from the fit's
    residuals by restricted maximum likelihood with X and the placements' poses as fixed effects
    (:func:`~.field_fit.estimate_field`: the base axes' fields and the joint angles', the lower
    AIC kept); the seating repeatability is the problem's sigma."""
    used = f.used
    Q = rec.Q[used]
    return estimate_field(f.r[used], full_jacobian(problem, f, rec), Q, AXES, np.eye(3), problem.sigma_m,
                          f.fit.model.dq_stack(Q))


def row_covariances(field: Field | None, s: float, sigma: float, Qt: np.ndarray, dqt: np.ndarray,
                    Qh: np.ndarray, dqh: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The covariances of the rows' errors (m^2) between the training configurations ``Qt`` and
    new ones ``Qh`` (their ``dp/dq``: ``dqt``, ``dqh``): with a ``field``, the field's and the
    seating's ``sigma^2`` per value; without, ``s^2`` per value, uncorrelated."""
    if field is None:
        return s**2 * np.eye(3 * len(Qt)), np.zeros((3 * len(Qt), 3 * len(Qh))), s**2 * np.eye(3 * len(Qh))
    St, Sh = field.sites(Qt, AXES, np.eye(3), dqt), field.sites(Qh, AXES, np.eye(3), dqh)
    return (value_covariance(field, St, sigma), covariance(field, St, Sh).reshape(3 * len(Qt), 3 * len(Qh)),
            value_covariance(field, Sh, sigma))


def judged(problem: Problem, f: ArtefactFit, rec: Recordings, field: Field | None, s: float,
           train: Recordings) -> list[Judged]:
    """:class:`Judged` figures of every placement of ``rec`` with the fit ``f`` of ``train``'s
    rows, predicted with the unmodelled error's ``field`` (None: ``s`` per value, uncorrelated)."""
    A, model = problem.artefact, f.fit.model
    p, J = ball_points(model, rec.Q, f.X)
    p0, _ = ball_points(model, rec.Q, np.zeros(model.L))
    Qt = train.Q[f.used]
    dqt, dqh = model.dq_stack(Qt), model.dq_stack(rec.Q)
    out = []
    for g, name in enumerate(rec.names):
        rows = np.flatnonzero(rec.placement == g)
        k = rec.point[rows]
        cov = error_covariance(f, J[rows], row_covariances(field, s, problem.sigma_m, Qt, dqt, rec.Q[rows], dqh[rows]))
        c, sp = figures(A, p[rows], k)
        c0, sp0 = figures(A, p0[rows], k)
        S = centred_covariances(k, cov)
        pc, ps = predicted(A, k, cov, S)
        delta, moved, C = relocated(*frame_poses(model, rec.Q[rows], np.zeros((len(rows), model.nF)), f.X), k, cov)
        out.append(Judged(name, len(rows), c, sp, pc, ps, c0, sp0, tuple(float(x) for x in delta),
                          float(np.sqrt(delta @ np.linalg.pinv(C) @ delta)), moved,
                          int(beyond_prediction(p[rows], k, S).sum())))
    return out


@dataclass(frozen=True, eq=False)
class ArtefactCalibration:
    """What :func:`calibrate_artefact` found: the chosen model's fit, its parameters' names,
    covariance ``C`` (SI units) and standard deviations, the error scale, the candidates judged,
    what the recordings do not tell (``absorbed``), the outliers and notes, the figures of the
    training and held-out placements, and ``urdf``: the calibration calibrated.urdf holds when the
    chosen model's compliances have no place in a URDF (the best model without them, identified
    and judged alike; None: the chosen model itself)."""

    problem: Problem
    recordings: Recordings
    fit: ArtefactFit
    model: str
    candidates: tuple[Candidate, ...]
    absorbed: tuple[tuple[str, str], ...]
    scale: ErrorScale
    C: np.ndarray
    field: Field | None
    outliers: tuple[tuple[str, float], ...]
    notes: tuple[str, ...]
    training: tuple[Judged, ...]
    validation: tuple[Judged, ...]
    validation_recordings: Recordings | None
    urdf: ArtefactCalibration | None = None

    @property
    def in_urdf(self) -> ArtefactCalibration:
        """The calibration calibrated.urdf holds: this one, or without the compliances its
        model has (:attr:`urdf`)."""
        return self.urdf or self

    @property
    def names(self) -> tuple[str, ...]:
        return self.fit.fit.model.parameter_names

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diagonal(self.C))


#: The candidate models of an artefact's recordings (module docstring of :mod:`.choice`): the
#: nominal robot with its ball (the measured point) located, the joint offsets and the ball, the base set the recordings tell, and with a robot whose
#: URDF (or ``inertias_urdf``) gives masses the base set with every joint's compliance under the
#: robot's own weight; without masses, under the push seating the ball (1 N down,
#: :data:`~.fit.SEATING_N`: the compliances take its size; it stands in for the weight too).
#: The base set with the axial compliances and the tilts of the joints' bearings under the robot's
#: weight (:func:`bent_joints`): fitted when named (``--model``), not among ``auto``'s
#: candidates: on MUKCa's Pandas it is chosen on no placement of about 60 configurations, and on
#: 16 (scripts/ball_socket_design.py's random subsets of panda_2) its 35 parameters made auto's
#: choice worse (median held-out consistency 0.537 -> 0.665 mm).
TILT_MODEL = "identifiable + gravity + tilt"
ARTEFACT_MODELS = ("auto", "ball", "offsets", "identifiable", "identifiable + gravity", "identifiable + seating",
                   TILT_MODEL)


def calibrate_artefact(problem: Problem, rec: Recordings, valid: Recordings | None = None,
                       model: str = "auto", threshold: float = OUTLIER_SIGMA,
                       with_field: bool = True) -> ArtefactCalibration:
    """Identify the robot from recordings of an artefact's points (module docstring): the base
    set, candidates judged by cross-validation (``model``: one of :data:`ARTEFACT_MODELS`),
    outliers, error scale, the unmodelled error's field (``with_field``; else ``s`` per value,
    uncorrelated), covariance, and the figures of the training and ``valid`` placements.

    Raises
    ------
    ProblemError, DesignError
        A model name not allowed; recordings that identify no candidate.
    """
    if model not in ARTEFACT_MODELS:
        raise ProblemError(f"--model {model}: allowed for an artefact's recordings: {', '.join(ARTEFACT_MODELS)}")
    names, absorbed = artefact_base_set(problem, rec, problem.model.parameter_names)
    ball = tuple(n for n in names if n.startswith("tool."))
    offsets = tuple(n for n in names if n.endswith(".offset")) + ball
    wanted = [("ball", ball, ""), ("offsets", offsets, ""), ("identifiable", names, "")]
    # auto: the weight where the links' masses are known, else the seating push (it stands in for the weight)
    weight = has_weight(problem)
    load = "gravity" if weight and model != "identifiable + seating" else "seating"
    loaded = loaded_joints(problem, rec.Q, load) if model in ("auto", f"identifiable + {load}", TILT_MODEL) else ()
    if loaded:  # + the compliances of the joints the load loads, those the rows tell
        told = artefact_base_set(problem, rec, names + tuple(f"k.{j}" for j in loaded), load)[0]
        wanted.append((f"identifiable + {load}", told, load))
        if model == TILT_MODEL and load == "gravity":  # + the tilts of the joints' bearings under the moments they carry
            bent = artefact_base_set(problem, rec, told + tuple(f"k.{j}" for j in bent_joints(problem, rec.Q)),
                                     load)[0]
            wanted.append((TILT_MODEL, bent, load))
    if model != "auto" and model not in [n for n, _, _ in wanted]:  # a load's model this robot does not take
        if model == "identifiable + seating" or weight:
            why = f"{'its own weight' if load == 'gravity' else 'the seating push'} loads no joint at these configurations;"
        else:
            why = ("the robot's links carry no masses, so its own weight loads no joint; give [robot] inertias_urdf (a "
                   "URDF with the links' inertias) or")
        raise ProblemError(f"--model {model}: {why} give another model")
    found, signs = [], []
    for name, chosen, loads in wanted:
        same = [c for n, c, _ in wanted if n != name and (n, name) in (("ball", "offsets"), ("identifiable", "offsets"))]
        if not chosen or model not in ("auto", name) or (model == "auto" and chosen in same):  # auto: once each
            continue
        fm = loaded_model(problem, chosen, loads)
        try:
            f = fit_artefact(problem, fm, rec)
        except DesignError as e:
            found.append(Candidate(name, fm, math.nan, math.nan, why=str(e)))
            continue
        e, why = cross_validate(f)
        cv, se = cv_error(e) if e is not None else (math.nan, math.nan)
        if loads:
            signs = negative_compliances(f, np.sqrt(np.sum(f.r**2) / max(f.dof, 1)) *
                                         np.sqrt(np.diagonal(np.linalg.inv(f.information))))
        found.append(Candidate(name, fm, float(np.sqrt(np.mean(np.sum(f.r**2, axis=1)))), cv, se, why,
                               cv_errors_m=e))
    if not found:
        raise ProblemError(f"--model {model}: the recordings tell none of its parameters; give another model")
    chosen, notes = choose(found, "auto")
    notes = [*rec.notes, *(valid.notes if valid is not None else ()), *notes]  # the files' own first
    told = generic_base_set(problem, problem.model.parameter_names)
    if len(names) < len(told):
        missing = [n for n in told if n not in names]
        notes.append(f"the recordings tell {len(names)} of the {len(told)} parameters an artefact's recordings can "
                     f"tell (not {', '.join(missing[:6])}{', ...' * (len(missing) > 6)}): their configurations vary "
                     "too little; record the ball seated in many orientations of the hand and postures")
    if problem.spec.calibration.prior is not None:
        notes.append(f"{problem.path}: [calibration.prior] is not used with an artefact's recordings: the fits are "
                     "least squares")
    if chosen.fit_model.model.loaded and signs:
        why = ("the encoders read the angle after the joint's yield (a Panda's are on the links), so the term takes "
               "up what else moves with the weight, the links' and bearings' bending" if chosen.fit_model.model.gravity
               else "the push is taken 1 N down, so the term takes up a push in another direction and what else "
               "moves with it")
        notes.append(f"negative compliance beyond {NEGATIVE_STD:g} std ({', '.join(n for n, _, _ in signs)}): {why}")
    f, outliers, more = fit_without_outliers(problem, chosen.fit_model, rec, threshold)
    scale = scale_of(f, problem.sigma_m)
    field = unmodelled_field(problem, f, rec).field if with_field else None
    Qt = rec.Q[f.used]
    dqt = f.fit.model.dq_stack(Qt)
    Vtt = row_covariances(field, scale.s_m, problem.sigma_m, Qt, dqt, Qt[:0], dqt[:0])[0]
    Jp = f.J[f.used].reshape(-1, f.J.shape[2])
    Hi = np.linalg.inv(f.information)
    C = Hi @ Jp.T @ Vtt @ Jp @ Hi  # the least squares' covariance under the rows' errors
    training = judged(problem, f, rec, field, scale.s_m, rec)
    validation = judged(problem, f, valid, field, scale.s_m, rec) if valid is not None else []
    unseated = [j for j in validation if j.recorded_badly]
    moved = [j for j in validation if j.moved_std > MOVED_STD and j not in unseated]
    if moved:
        more.append("the measured point sits elsewhere on the hand at " + ", ".join(
            f"{j.name} ({np.linalg.norm(j.moved_m) * 1e3:.2f} mm, {j.moved_std:.0f} std; consistency "
            f"{j.relocated_consistency_m * 1e3:.3f} mm with it moved)" for j in moved) + f" than at "
            f"{', '.join(rec.names)}: it moved on the hand between the recordings (a ball held by the gripper's "
            "fingers moves when grasped again: fix it to the flange); the robot's own error there is the consistency "
            "with it moved")
    if unseated:
        more.append("at " + ", ".join(f"{j.name} ({j.beyond} of {j.rows} configurations, consistency "
                                      f"{j.consistency_m * 1e3:.3f} mm)" for j in unseated)
                    + f" the configurations lie farther from their point's mean than the calibrated robot's "
                    f"predicted error allows ({MOVED_STD:g} std): balls not seated, or the tool moved while it was "
                    "recorded (a tool raised on a stand gives under the push); that consistency is not the robot's: "
                    "record the placement again, the tool clamped on the table")
    worse = [j.name for j in validation if j.predicted_consistency_m > j.nominal_consistency_m]
    if worse:
        more.append(f"at {', '.join(worse)} the predicted consistency is above the nominal robot's: the recordings "
                    f"of {', '.join(rec.names)} do not tell the robot well enough to calibrate it there (their error "
                    f"{scale.s_m * 1e3:.3g} mm per value); record more varied configurations, or check the seating")
    urdf = None
    if any(n.startswith("k.") for n in f.fit.model.parameter_names):  # none in a URDF: the best model without them
        judged_alike = [c for c in found if not c.loaded and not math.isnan(c.cv_rms_m)]
        urdf = calibrate_artefact(problem, rec, valid, choose(judged_alike, "auto")[0].name if judged_alike else
                                  "identifiable", threshold, with_field)
    return ArtefactCalibration(problem, rec, f, chosen.name, tuple(found), tuple(absorbed), scale, C, field,
                               tuple(outliers), tuple(notes + more), tuple(training), tuple(validation), valid, urdf)
