"""Which model to identify: nested candidates judged by k-fold cross-validation on the training rows.

A real robot differs from its model in ways no parameter set captures (compliance, backlash, the
tracker's own errors), and the richest identifiable set fits those too: it fits the training
rows best and can predict new poses worst. The candidates, nested:

* ``registration``: the tracker frame and the measured point (``tool.tx, ty, tz``; with
  markers also ``tool.rx, ry, rz``): the nominal robot, placed;
* ``offsets``: + every joint's zero offset (those the frame does not absorb);
* ``offsets + k``: + the k most significant other parameters of the problem's own set, in the
  order of ``|X_j| / std_j`` of its fit to every training row;
* ``identifiable``: the problem's own parameters (``[calibration].parameters``, e.g. its
  identifiable base set);
* ``... + gravity`` (a robot whose URDF gives the links' masses): ``offsets``, the nested
  candidate of smallest cross-validated error and ``identifiable``, each with every joint's compliance
  ``k.<joint>`` deflecting it under the robot's own weight (the usual next term on a real arm;
  compliances without effect, e.g. of a vertical first axis, left out);
* ``prior`` (with ``[calibration.prior]``): the problem's own parameters, regularised: the MAP
  estimate ``min |r / sigma|^2 + |X / std|^2``, whose ``H = J^T J + diag((sigma / std)^2)``
  (ridge regression); its size is its effective number of parameters ``tr(J^T J H^-1)``.

Each is judged by leave-one-out cross-validation: the error at each row of the fit to all the
other rows, which predicts the row with the frame it fitted (the use: a frame measured once,
the robot then used). For a least-squares fit it has a closed form at the estimate (linearised,
no refit): with the row's whitened residuals ``r_i`` and Jacobian ``J_i`` and ``H = J^T J``,
the row left out is off by ``(I - J_i H^-1 J_i^T)^-1 r_i`` (the PRESS residual of a block of
values; Cook and Weisberg, Residuals and Influence in Regression, 1982). A row that the model
needs to be identified (``I - J_i H^-1 J_i^T`` singular) makes it not cross-validated. The
cross-validated error is the RMS over the rows of each row's RMS point error (m), with its
standard error ``se = std(e_i^2) / (2 cv sqrt(N))`` (delta method).
``auto`` takes the fewest (effective) parameters whose error is within one
standard error of the smallest (the one-standard-error rule of Hastie, Tibshirani and Friedman,
The Elements of Statistical Learning, 7.10): the best error is itself noisy, and of models
that predict as well the smaller one holds further from the training poses. The robot's weight
(or, for an artefact's recordings on a robot without masses, the push seating the ball) is a
load known beforehand, not one more term of a ladder: the chosen geometry with the compliances
under it (``... + gravity``, ``identifiable + seating``; not refused) is taken when it is better by more than
one standard error of the difference on the same rows, ``std(e_i^2 / (2 cv) - b_i^2 / (2 cv_b))
/ sqrt(N)`` (paired: what the rows share, a row hard for both, is not noise of the comparison).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import DesignError, ProblemError
from ..problem.build import Problem
from ..robot.symbolic import carried_weights
from .fit import Fit, FitModel, fit, fit_model, row_errors
from .measurements import Measurements, measured_axes
from .residuals import leverages, press

MODELS = ("auto", "registration", "offsets", "identifiable", "prior")
#: A compliance below minus this many standard deviations is negative (a stiff joint's estimate
#: falls below 0 half the time within its noise): a loaded candidate with one is not chosen.
NEGATIVE_STD = 2.0
#: A model predicts worse than registration only when its cross-validated error is larger by
#: more than this fraction.
TIE_RTOL = 1e-3


@dataclass(frozen=True, eq=False)
class Candidate:
    """One candidate model: its fit model, the RMS of its fit to all training rows (m) and
    its cross-validated error (m; NaN when it could not be cross-validated, ``why``), each
    row's (``cv_errors_m``, m); a candidate ``auto`` may not choose says why in ``refused``
    (:func:`negative_compliances`); ``fitted`` its :class:`~.fit.Fit` (None when it failed):
    the chosen one is not fitted again."""

    name: str
    fit_model: FitModel
    training_rms_m: float
    cv_rms_m: float
    cv_se_m: float = math.nan
    why: str = ""
    dof: float = math.nan
    refused: str = ""
    fitted: Fit | None = field(default=None, repr=False)
    cv_errors_m: np.ndarray | None = field(default=None, repr=False)

    @property
    def L(self) -> int:
        return self.fit_model.model.L

    @property
    def loaded(self) -> bool:
        """Whether the joints deflect under a load known beforehand in this model: the robot's
        own weight, or an artefact's seating push."""
        return self.fit_model is not None and bool(self.fit_model.model.loaded)

    @property
    def size(self) -> float:
        """The effective number of parameters (``L`` of a least-squares fit)."""
        return self.L if math.isnan(self.dof) else self.dof

    def as_dict(self) -> dict:
        return {"model": self.name, "parameters": self.L, "effective_parameters": self.size,
                "training_rms_m": self.training_rms_m,
                "cross_validated_rms_m": None if math.isnan(self.cv_rms_m) else self.cv_rms_m,
                "cross_validated_se_m": None if math.isnan(self.cv_se_m) else self.cv_se_m,
                "not_cross_validated_because": self.why or None,
                "not_chosen_because": self.refused or None}


def candidate_parameters(problem: Problem, name: str) -> tuple[str, ...]:
    """The robot parameters of the candidate ``name`` (module docstring); the problem's
    compliances ``k.<joint>`` are in every candidate (what an elasto-static case identifies)."""
    own = problem.model.parameter_names
    if name == "identifiable":
        return own
    rotations = problem.spec.measurement.markers_m is not None
    tool = tuple(f"tool.{e}" for e in ("tx", "ty", "tz") + (("rx", "ry", "rz") if rotations else ()))
    compliances = tuple(p for p in own if p.startswith("k."))
    if name == "registration":
        return tool + compliances
    return tool + tuple(f"{j}.offset" for j in problem.robot.joints) + compliances


def has_weight(problem: Problem) -> bool:
    """Whether the robot's own weight loads its joints: the chain carries a mass (the URDF's
    inertias) and the model has gravity."""
    robot = problem.robot
    return bool(np.any(robot.model.gravity.linear)) and any(carried_weights(robot))


def cv_error(e: np.ndarray, best: np.ndarray | None = None) -> tuple[float, float]:
    """The cross-validated RMS error (m) of the rows' errors ``e`` (N, m) and its standard error
    (delta method), of ``e`` alone or, beside the ``best`` candidate's errors on the same rows,
    of the paired differences (module docstring)."""
    cv = float(np.sqrt(np.mean(e**2)))
    if cv == 0:
        return cv, 0.0
    g = e**2 / (2 * cv)  # cv's linearisation in the rows' squared errors
    if best is not None:
        b = float(np.sqrt(np.mean(best**2)))
        g = g - (best**2 / (2 * b) if b > 0 else 0.0)
    return cv, float(np.std(g) / math.sqrt(len(e)))


def cross_validate(problem: Problem, f: Fit, meas: Measurements) -> tuple[np.ndarray | None, str]:
    """Each row's leave-one-out RMS point error (m) of the fit ``f`` over its rows of ``meas``
    (module docstring), or None and why not."""
    used = np.flatnonzero(f.used)
    # with a MAP fit's prior in H: the PRESS of ridge regression
    e, _, needed = press(f.r[used], leverages(f.J[used], f.information))
    if e is None:
        return None, f"row {meas.lines[used[needed]]} is needed to identify it"
    left_out = e @ np.linalg.inv(problem.whitening).T
    points = f.mask[used].sum(axis=1) / len(measured_axes(problem))
    return np.sqrt(np.sum(left_out**2, axis=1) / points), ""


def residual_std(problem: Problem, f: Fit) -> np.ndarray:
    """Standard deviations (L,) of the fit's parameters with the larger of the problem's sigma
    and the residuals' own ``sqrt(|r|^2 / (N - L))``: what the parameters' noise is when the
    rows hold more than the tracker's noise."""
    N, L = int(f.mask[f.used].sum()), f.fit.model.L
    s = problem.sigma_m if N <= L else max(problem.sigma_m, float(np.sqrt(np.sum(f.r[f.used] ** 2) / (N - L))))
    return s * np.sqrt(np.diagonal(np.linalg.inv(f.information)))


def negative_compliances(f: Fit, std: np.ndarray) -> list[tuple[str, float, float]]:
    """(name, value, std) of the fit's compliances below ``-NEGATIVE_STD`` standard deviations:
    a joint that yields against its load, which no joint does (the compliances took up what
    the model misses)."""
    return [(n, float(x), float(s)) for n, x, s in zip(f.fit.model.parameter_names, f.X, std)
            if n.startswith("k.") and x < -NEGATIVE_STD * s]


def candidates(problem: Problem, frame: str, meas: Measurements, T0: np.ndarray,
               loss: str, rows: np.ndarray, model: str = "auto") -> list[Candidate]:
    """The candidates (module docstring) that ``model`` needs, fewest parameters first: every
    one for ``auto``, else registration only and ``model``; fitted to the ``rows`` (bool mask:
    those the richest model does not find outliers) and cross-validated; models equal to a
    smaller one (parameters absorbed) are left out."""
    every = rows

    def candidate(name: str, names: tuple[str, ...], prior: bool = False,
                  gravity: bool = False) -> tuple[Candidate, object]:
        fm = fit_model(problem, frame, names, prior, gravity)
        try:
            f = fit(problem, fm, meas, T0, every, loss)
        except (ProblemError, DesignError) as e:
            return Candidate(name, fm, math.nan, math.nan, math.nan, str(e)), None
        e, why = cross_validate(problem, f, meas)
        cv, se = cv_error(e) if e is not None else (math.nan, math.nan)
        dof = math.nan if f.prior_information is None else float(np.trace(
            np.linalg.solve(f.information, f.information - np.diag(f.prior_information))))
        negative = negative_compliances(f, residual_std(problem, f)) if gravity else []
        refused = (f"negative compliance beyond {NEGATIVE_STD:g} std ({', '.join(n for n, _, _ in negative)}): "
                   "no joint yields against its weight" if negative else "")
        return Candidate(name, fm, float(np.sqrt(np.mean(row_errors(problem, f, meas, rows) ** 2))),
                         cv, se, why, dof, refused, f, e), f

    offsets = candidate_parameters(problem, "offsets")
    found = [candidate("registration", candidate_parameters(problem, "registration"))[0]]
    if model in ("auto", "offsets"):
        found.append(candidate("offsets", offsets)[0])
    if model in ("auto", "identifiable"):
        full, f = candidate("identifiable", candidate_parameters(problem, "identifiable"))
    else:
        full, f = None, None
    if model == "auto" and f is not None:
        names = full.fit_model.model.parameter_names
        std = problem.sigma_m * np.sqrt(np.diagonal(np.linalg.inv(f.information)))
        t = np.abs(f.X) / std
        order = [names[i] for i in np.argsort(-t, kind="stable")
                 if names[i] not in full.fit_model.frame_names and names[i] not in offsets]
        for k in range(1, len(order)):
            found.append(candidate(f"offsets + {k}", offsets + tuple(order[:k]))[0])
    if full is not None:
        found.append(full)
    if model == "auto" and has_weight(problem):  # + every joint's compliance under the robot's own weight
        compliances = tuple(f"k.{j}" for j in problem.robot.joints)
        nested = [c for c in found if not math.isnan(c.cv_rms_m)]
        best = min(nested, key=lambda c: c.cv_rms_m) if nested else found[1]
        for c in dict.fromkeys((found[1], best, full)):
            geometric = tuple(p for p in c.fit_model.model.parameter_names
                              if p not in c.fit_model.frame_names and not p.startswith("k."))
            found.append(candidate(f"{c.name} + gravity", geometric + compliances, gravity=True)[0])
    if problem.spec.calibration.prior is not None and model in ("auto", "prior"):
        found.append(candidate("prior", candidate_parameters(problem, "identifiable"), prior=True)[0])
    kept: list[Candidate] = []
    for c in found:
        if c.name == "prior" or c.fit_model.model.loaded or not any(
                set(c.fit_model.model.parameter_names) == set(k.fit_model.model.parameter_names)
                for k in kept if not k.fit_model.model.loaded):
            kept.append(c)
    return kept


def _paired_se(c: Candidate, other: Candidate) -> float:
    """The standard error of ``c``'s cross-validated error beside ``other``'s (m): of the paired
    differences when both were judged on the same rows, else ``other``'s own."""
    e, b = c.cv_errors_m, other.cv_errors_m
    return cv_error(e, b)[1] if e is not None and b is not None and e.shape == b.shape else other.cv_se_m


def _geometry(c: Candidate) -> frozenset[str] | None:
    """The candidate's parameters but its compliances (None without a fit model)."""
    if c.fit_model is None:
        return None
    return frozenset(n for n in c.fit_model.model.parameter_names if not n.startswith("k."))


def _own(found: list[Candidate]) -> Candidate:
    """The candidate of the problem's own parameters (the last of the nested ones)."""
    return [c for c in found if c.name != "prior" and not c.fit_model.model.loaded][-1]


def choose(found: list[Candidate], model: str) -> tuple[Candidate, list[str]]:
    """The candidate ``model`` names, or for ``auto`` the one of smallest cross-validated
    error; and the warnings a person should read (a choice worse than registration only)."""
    if model not in MODELS:
        raise ProblemError(f"--model {model}: allowed: {', '.join(MODELS)}")
    valid = [c for c in found if not math.isnan(c.cv_rms_m)]
    warnings = []
    if model == "auto" and not valid:  # too few rows to judge: the problem's own model
        own = _own(found)
        if math.isnan(own.training_rms_m):
            raise ProblemError(own.why)
        return own, [f"no model could be cross-validated ({'; '.join(f'{c.name}: {c.why}' for c in found)}): "
                     "the problem's own parameters are fitted; measure more rows to choose"]
    if model == "auto":
        valid = [c for c in valid if not c.refused] or valid[:1]
        best = min(valid, key=lambda c: c.cv_rms_m)
        chosen = min((c for c in valid if c.cv_rms_m <= best.cv_rms_m + best.cv_se_m), key=lambda c: c.size)
        weighed = [c for c in valid if c.loaded and not chosen.loaded and _geometry(c) == _geometry(chosen)
                   and c.cv_rms_m < chosen.cv_rms_m - _paired_se(c, chosen)]
        chosen = weighed[0] if weighed else chosen
    else:
        chosen = next((c for c in found if c.name == model), None)
        if chosen is None:  # the same parameters as a smaller candidate
            chosen = _own(found) if model == "identifiable" else found[0]
    base = found[0]
    if (chosen is not base and not math.isnan(base.cv_rms_m)
            and not chosen.cv_rms_m <= base.cv_rms_m * (1 + TIE_RTOL)):
        if math.isnan(chosen.cv_rms_m):
            warnings.append(f"the {chosen.name} model could not be cross-validated ({chosen.why}), registration "
                            f"only could ({base.cv_rms_m * 1e3:.3f} mm): whether it predicts new poses "
                            "better is not known; --model auto chooses by cross-validation")
        else:
            warnings.append(f"the {chosen.name} model predicts new poses worse ({chosen.cv_rms_m * 1e3:.3f} mm "
                            f"cross-validated) than registration only ({base.cv_rms_m * 1e3:.3f} mm): it fits "
                            "what the model misses; --model auto chooses by cross-validation")
    return chosen, warnings
