"""Virtual calibration: check the predicted accuracy by simulating the whole calibration.

For a plan ``{(q_i, F_i)}, i = 1..m`` the design step predicts the RMS error after
compensation at each test pose, ``sqrt(rho_j)`` with ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``
(m^2, ../shared/paper/MATH.md sections 1-3). That prediction rests on the linearised model
``y = B X``. Here every step of a real calibration is simulated ``N`` times on the problem's
own nonlinear measurement model (:class:`casadi_design.models.CalibrationModel`: markers,
load-point moment, joint deflection fixed point and noise model included):

1. a true robot (:mod:`.simulate`): random errors of the identified geometric parameters
   (normal, std :class:`ErrorSpreads`) and random true compliances (log-normal around a
   nominal value);
2. the plan's measurements (:mod:`.simulate`): ``model.measurement`` of the true robot, whose
   values are whitened, plus noise ``sigma`` per value;
3. identification (:mod:`.identify`): linear least squares ``X = (S^T S)^-1 S^T y`` in the
   elasto-static case, Levenberg-Marquardt on ``model.measurement`` otherwise;
4. compensation (:mod:`.compensate`): at each test pose ``(q0_j, F0_j)`` the command ``q_c`` for
   which the identified robot puts the frame on the nominal target (``model.accuracy`` = 0,
   machining wrench included; Newton-chord iterations); the residual error is
   ``model.accuracy`` of the true robot at ``q_c``;
5. the empirical RMS of the residual error over the trials, next to ``sqrt(rho_j)`` (from
   ``model.B_stack`` and :func:`casadi_design.measures.score_plan`), with a chi-square
   confidence interval (:mod:`.statistics`).

Every trial of a plan runs at once (CasADi functions mapped over the stacked trials, numpy for
the batched linear algebra). Plans with the same m share their true robots and noise draws
(common random numbers, generator ``default_rng([seed, m])``), which sharpens the comparison
between criteria.

Command line (:func:`add_arguments`, :func:`run`)::

    casadi-design validate problems/<case>.toml [--results DIR/results.json] [--trials N]
        [--seed S] [--out DIR] [--scales 1,10,100] [--length-mm ...] [--angle-deg ...] [--k ...]

Without ``--results`` the plans are solved first (every criterion and m of the problem file).
Writes ``DIR/validation.json`` and ``DIR/validation.png`` / ``.pdf``; the folder is created only
once the simulation has succeeded. Bad input or a failed simulation raises
:class:`~casadi_design.errors.ProblemError` / :class:`~casadi_design.errors.DesignError`.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import DesignError, ProblemError
from ..measures import information_matrix, score_plan
from ..nlp import B0_at_test_poses
from .compensate import compensate as _compensate  # the name `compensate` stays the module
from .identify import Identification, identify_linear, identify_nonlinear
from .simulate import (
    ErrorSpreads,
    Plan,
    draw_true_parameters,
    evaluate,
    nominal_poses,
    simulate_measurements,
    true_values,
)
from .statistics import CONFIDENCE, effective_dof, rankings, rms_interval

if TYPE_CHECKING:
    from ..build import Problem
    from ..solve import Design

__all__ = [
    "CONFIDENCE", "HELP", "DESCRIPTION", "ErrorSpreads", "Identification", "Plan", "PlanValidation",
    "Validation", "add_arguments", "evaluate", "format_report", "linearisation_study",
    "plans_from_designs", "plans_from_results", "rankings", "run", "simulate_plan", "validate",
    "validation_record", "write_validation",
]

#: One-line help and description of the ``validate`` subcommand.
HELP = ("check the predicted accuracy by simulating the whole calibration "
        "(casadi-design validate --help)")
DESCRIPTION = ("Virtual calibration: draw true robots (geometric errors of given spreads, "
               "log-normal compliances), simulate the measurements of each plan on the problem's "
               "nonlinear model with noise sigma, identify, compensate every test pose and compare "
               "the simulated RMS error with the predicted sqrt(rho), with a 95 % chi-square "
               "interval per test pose. Prints max errors (mm) and rankings; with --out writes "
               "validation.json (SI units) and validation.png/pdf.")


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


def _check_plan(problem: Problem, plan: Plan) -> None:
    model = problem.model
    if np.shape(plan.Q) != (plan.m, model.n) or np.shape(plan.F) != (plan.m, model.nF):
        raise ProblemError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: Q has shape "
            f"{np.shape(plan.Q)} and F {np.shape(plan.F)}, {problem.path} needs ({plan.m}, {model.n}) "
            f"and ({plan.m}, {model.nF}); give a plan of this problem"
        )


def simulate_plan(problem: Problem, plan: Plan, spreads: ErrorSpreads, trials: int,
                  rng: np.random.Generator, B0: np.ndarray | None = None) -> PlanValidation:
    """Simulate ``trials`` calibrations of ``plan`` and compare with ``sqrt(rho)`` (module doc).

    ``B0``: :func:`~casadi_design.nlp.B0_at_test_poses`, shape (s, r, L), computed when not
    given. The empirical mean square at test pose j is ``mean_t |e_tj|^2`` (m^2) over the
    trials whose compensation converged there; its interval uses ``nu_j`` of
    ``C_j = sigma^2 B0_j M^-1 B0_j^T``.
    """
    t0 = time.perf_counter()
    _check_plan(problem, plan)
    model, tp, sigma = problem.model, problem.test_poses, problem.sigma_m
    s = tp.s
    B = model.B_stack(plan.Q, plan.F)
    B0 = B0_at_test_poses(problem) if B0 is None else B0
    scores = score_plan(B, B0, sigma)
    if not scores.identifiable:
        raise DesignError(
            f"virtual calibration of the {plan.criterion} plan, m = {plan.m}: its information "
            "matrix M is singular, the parameters cannot be identified; give a solved plan"
        )
    X_true = draw_true_parameters(model, spreads, trials, rng)
    ref, y = simulate_measurements(model, plan, X_true, sigma, spreads, rng)
    if model.case == "elastostatic":
        X_hat, ident = identify_linear(B, y, model.column_scale)
    else:
        X_hat, ident = identify_nonlinear(model, plan.Q, plan.F, ref, y, sigma)

    target = nominal_poses(model, tp.q, tp.F)
    qc, done, miss = _compensate(model, tp.q, tp.F, target, np.repeat(X_hat, s, axis=0), sigma)
    err = true_values(model.accuracy, spreads, qc, np.tile(tp.F, (trials, 1)),
                      np.repeat(X_true, s, axis=0), np.tile(target, (trials, 1)), where=done)
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


def _check_trials(trials: int) -> None:
    if trials < 2:
        raise ProblemError(f"virtual calibration: trials = {trials}; give at least 2 (e.g. 2000)")


def validate(problem: Problem, plans: list[Plan], trials: int = 2000, seed: int = 0,
             spreads: ErrorSpreads = ErrorSpreads(), source: str = "") -> Validation:
    """Virtual calibration of each plan: ``trials`` simulated calibrations (module doc).

    Raises
    ------
    ProblemError
        When ``trials`` is below 2 or a plan does not fit the problem.
    DesignError
        When a plan is singular, or the deflection or the compensation of the simulated robots
        does not converge.
    """
    _check_trials(trials)
    t0 = time.perf_counter()
    B0 = B0_at_test_poses(problem)
    results = tuple(simulate_plan(problem, p, spreads, trials, plan_rng(seed, p.m), B0) for p in plans)
    return Validation(problem, source, trials, seed, spreads, results, time.perf_counter() - t0)


def linearisation_study(problem: Problem, plans: list[Plan], scales: list[float], trials: int,
                        seed: int = 0, spreads: ErrorSpreads = ErrorSpreads(),
                        source: str = "") -> list[tuple[float, Validation]]:
    """Where the linearised prediction breaks down: validate with every spread times ``scale``.

    The ratio of simulated to predicted error stays near 1 while the true robots are close to
    the nominal one (B evaluated at ``X = 0`` still describes them) and drifts as they move away.
    """
    return [(scale, validate(problem, plans, trials, seed, spreads.scaled(scale), source)) for scale in scales]


# --------------------------------------------------------------------------- plans

def plans_from_designs(designs: list[Design]) -> list[Plan]:
    """The plans of solved designs."""
    return [Plan(d.criterion, d.m, np.asarray(d.Q, float), np.asarray(d.F, float)) for d in designs]


def plans_from_results(problem: Problem, path: str | Path) -> list[Plan]:
    """The plans of a ``results.json`` (or ``sweep.json``) written by ``casadi-design solve``
    (``sweep``) for ``problem``.

    Raises
    ------
    ProblemError
        When the file is missing, unreadable or malformed, or was written for another model.
    """
    from ..results import OutputError, read_json

    path = Path(path)
    if not path.exists():
        raise ProblemError(f"--results: no such file {path}; solve first: "
                           f"casadi-design solve {problem.path} --out DIR")
    try:
        record = read_json(path)
    except OutputError as exc:
        raise ProblemError(f"--results: {exc}") from None
    model = problem.model
    wanted = {"calibration.parameters": list(model.parameter_names), "sigma_m": problem.sigma_m}
    calibration = record.get("calibration")
    parameters = calibration.get("parameters") if isinstance(calibration, dict) else None
    found = {"calibration.parameters": parameters, "sigma_m": record.get("sigma_m")}
    for key, value in wanted.items():
        if found[key] != value:
            raise ProblemError(
                f"--results: {path} has {key} = {found[key]!r} but {problem.path} has {value!r}; "
                f"give the results of this problem (casadi-design solve {problem.path} --out DIR)"
            )
    plans = []
    for i, d in enumerate(record["designs"]):
        Q = np.array([e["q_rad"] for e in d["experiments"]], dtype=float).reshape(d["m"], -1)
        F = np.array([e["force"] for e in d["experiments"]], dtype=float).reshape(d["m"], -1)
        if Q.shape[1] != model.n or F.shape[1] != model.nF:
            raise ProblemError(
                f"--results: {path} designs[{i}] has {Q.shape[1]} joints and {F.shape[1]} force "
                f"components per experiment, {problem.path} has {model.n} and {model.nF}; give the "
                "results of this problem"
            )
        plans.append(Plan(d["criterion"], int(d["m"]), Q, F))
    return plans


# --------------------------------------------------------------------------- records and report

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
        "rankings": {str(m): r for m, r in rankings(validation.plans).items()},
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


def write_validation(path: Path, validation: Validation,
                     study: list[tuple[float, Validation]] = ()) -> dict:
    """Write ``validation.json`` atomically; returns the record."""
    from ..results import write_atomic

    record = validation_record(validation, study)
    write_atomic(Path(path), (json.dumps(record, indent=2) + "\n").encode())
    return record


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
    for m, r in rankings(v.plans).items():
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


# --------------------------------------------------------------------------- command line

def _positive_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--scales takes numbers separated by commas, got '{text}'")
    if any(not (math.isfinite(v) and v > 0) for v in values):
        raise argparse.ArgumentTypeError(f"--scales takes positive numbers, got '{text}'")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``casadi-design validate`` (see :data:`HELP`, :data:`DESCRIPTION`)."""
    d = ErrorSpreads()
    parser.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    parser.add_argument("--results", metavar="JSON",
                        help="results.json (or sweep.json) of casadi-design solve (sweep) for this "
                             "problem (default: solve every criterion and m of the problem now)")
    parser.add_argument("--starts", type=int, metavar="N",
                        help="seeded IPOPT starts per design when solving first (default: "
                             "[solver].starts of the problem)")
    parser.add_argument("--trials", type=int, default=2000, metavar="N",
                        help="simulated calibrations per plan (default 2000)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the simulation (default 0)")
    parser.add_argument("--out", metavar="DIR",
                        help="folder for validation.json and validation.png/.pdf (created, if "
                             "missing, once the simulation has succeeded)")
    parser.add_argument("--length-mm", type=float, default=d.length_m * 1e3, metavar="MM",
                        help=f"std of the translation errors, mm (default {d.length_m * 1e3:g})")
    parser.add_argument("--angle-deg", type=float, default=math.degrees(d.angle_rad), metavar="DEG",
                        help=f"std of the rotation errors, deg (default {math.degrees(d.angle_rad):g})")
    parser.add_argument("--k", type=float, default=d.k_nominal, metavar="K",
                        help=f"median true compliance, rad/(N m) or m/N (default {d.k_nominal:g})")
    parser.add_argument("--k-log-spread", type=float, default=d.k_log_spread, metavar="S",
                        help=f"std of log k (default {d.k_log_spread:g})")
    parser.add_argument("--scales", type=_positive_list, metavar="LIST",
                        help="also validate with every spread times each scale, e.g. 1,10,100, "
                             "to see where the linearised prediction breaks down")


def run(args: argparse.Namespace) -> int:
    """Run ``casadi-design validate`` with the options of :func:`add_arguments`; returns 0.

    Raises
    ------
    ProblemError, DesignError, casadi_design.results.OutputError
        Bad input, a failed simulation, or an ``--out`` that is not a folder (before anything
        is simulated or written).
    """
    from ..build import load_problem
    from ..results import prepare_out

    _check_trials(args.trials)
    if args.starts is not None and args.starts < 1:
        raise ProblemError(f"--starts {args.starts}: give a positive number of IPOPT starts")
    spreads = ErrorSpreads(args.length_mm * 1e-3, math.radians(args.angle_deg), args.k,
                           args.k_log_spread)
    # our files in --out are replaced (as `plot` does); its other files are left alone
    out = None if args.out is None else prepare_out(args.out, force=True)
    problem = load_problem(args.problem)
    if args.results:
        plans, source = plans_from_results(problem, args.results), str(args.results)
    else:
        from ..solve import check_ipopt_options, solve_design

        check_ipopt_options(problem)
        designs = [solve_design(problem, c, m, starts=args.starts)
                   for m in problem.m_values for c in problem.criteria]
        plans, source = plans_from_designs(designs), "solved by casadi-design validate"
    t0 = time.perf_counter()
    validation = validate(problem, plans, args.trials, args.seed, spreads, source)
    study = (linearisation_study(problem, plans, args.scales, args.trials, args.seed, spreads, source)
             if args.scales else [])
    print(format_report(validation, study))
    print(f"total simulation time {time.perf_counter() - t0:.2f} s")
    if out is not None:
        from ..plotting import save_figures, validation_figure

        out.mkdir(parents=True, exist_ok=True)
        write_validation(out / "validation.json", validation, study)
        fig = validation_figure(validation)
        save_figures(fig, [out / f"validation.{suffix}" for suffix in ("png", "pdf")])
        print(f"wrote {out / 'validation.json'}, {out / 'validation.png'}, {out / 'validation.pdf'}")
    return 0
