"""``casadi-design validate``: the virtual calibration (:mod:`casadi_design.virtual`) of the
plans of a results file, or of the plans ``solve`` designs with the same options."""

from __future__ import annotations

import argparse
import math

from ..errors import ProblemError

from ..records.files import prepare_out
from ..virtual import (
    ErrorSpreads,
    format_report,
    linearisation_study,
    plans_from_designs,
    plans_from_results,
    validate,
    write_validation,
)
from ..virtual.validation import check_trials
from . import common

HELP = ("check the predicted accuracy by simulating the whole calibration "
        "(casadi-design validate --help)")
DESCRIPTION = ("Virtual calibration: draw true robots (geometric errors of given spreads, "
               "log-normal compliances), simulate the measurements of each plan on the problem's "
               "nonlinear model with noise sigma, identify, compensate every test pose and compare "
               "the simulated RMS error with the predicted sqrt(rho), with a 95 % chi-square "
               "interval per test pose. Prints max errors (mm) and rankings; with --out writes "
               "validation.json (SI units) and validation.png/pdf. Without --results the plans are "
               "those `casadi-design solve` designs with the same options.")


def _positive_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--scales takes numbers separated by commas, got '{text}'")
    if any(not (math.isfinite(v) and v > 0) for v in values):
        raise argparse.ArgumentTypeError(f"--scales takes positive numbers, got '{text}'")
    return values


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help=HELP, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(run=run)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``casadi-design validate``: those of ``solve`` (for the plans solved when
    no ``--results`` is given) and the simulation's."""
    d = ErrorSpreads()
    common.add_campaign(p, "numbers of experiments of the plans solved first: 1,5 or a range 1:10 "
                           "(default: [experiments].m)")
    p.add_argument("--results", metavar="JSON",
                   help="results.json (or sweep.json) of casadi-design solve (sweep) for this "
                        "problem (default: solve now, as casadi-design solve does with these options)")
    p.add_argument("--trials", type=int, default=2000, metavar="N",
                   help="simulated calibrations per plan (default 2000)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the simulation (default 0)")
    p.add_argument("--out", metavar="DIR",
                   help="folder for validation.json and validation.png/.pdf (created, if "
                        "missing, once the simulation has succeeded)")
    p.add_argument("--length-mm", type=common.number("--length-mm", "a length in mm >= 0", strict=False), default=d.length_m * 1e3, metavar="MM",
                   help=f"std of the translation errors, mm (default {d.length_m * 1e3:g})")
    p.add_argument("--angle-deg", type=common.number("--angle-deg", "an angle in deg >= 0", strict=False), default=math.degrees(d.angle_rad), metavar="DEG",
                   help=f"std of the rotation errors, deg (default {math.degrees(d.angle_rad):g})")
    p.add_argument("--k", type=common.number("--k", "a compliance >= 0", strict=False), default=d.k_nominal, metavar="K",
                   help=f"median true compliance, rad/(N m) or m/N (default {d.k_nominal:g})")
    p.add_argument("--k-log-spread", type=common.number("--k-log-spread", "a number >= 0", strict=False), default=d.k_log_spread, metavar="S",
                   help=f"std of log k (default {d.k_log_spread:g})")
    p.add_argument("--scales", type=_positive_list, metavar="LIST",
                   help="also validate with every spread times each scale, e.g. 1,10,100, "
                        "to see where the linearised prediction breaks down")


def run(args: argparse.Namespace) -> int:
    """Run ``casadi-design validate``; returns 0.

    Raises
    ------
    ProblemError, DesignError, casadi_design.errors.OutputError
        Bad input, a failed simulation, or an ``--out`` that is not a folder (before anything
        is simulated or written).
    """
    check_trials(args.trials)
    spreads = ErrorSpreads(args.length_mm * 1e-3, math.radians(args.angle_deg), args.k, args.k_log_spread)
    # our files in --out are replaced (as `plot` does); its other files are left alone
    out = None if args.out is None else prepare_out(args.out, force=True)
    spec = common.read_spec(args, artefact=True)
    if spec.measurement.artefact is not None:
        validation, study = _artefact(args, spec, spreads)
    else:
        validation, study = _tracker(args, spreads)
    print(format_report(validation, study))
    print(f"total simulation time {validation.wall_s + sum(v.wall_s for _, v in study):.2f} s")
    if out is not None:
        from ..reports.plotting import save_figures, validation_figure

        write_validation(out / "validation.json", validation, study)
        save_figures(validation_figure(validation), [out / f"validation.{suffix}" for suffix in ("png", "pdf")])
        print(f"wrote {out / 'validation.json'}, {out / 'validation.png'}, {out / 'validation.pdf'}")
    return 0


def _artefact(args: argparse.Namespace, spec, spreads: ErrorSpreads) -> tuple:
    """The virtual calibration of an artefact's plans (:mod:`casadi_design.virtual.artefact`):
    those of ``--results`` or solved now as ``solve`` does."""
    from ..virtual.artefact import validate_artefact
    from .solve import artefact_designs

    if args.scales:
        raise ProblemError(f"{spec.path}: --scales: the linearisation study of an artefact's plans is not built; "
                           "run validate with --length-mm and --angle-deg at each scale instead")
    problem = common.load(args, check_solver=False, spec=spec)
    if args.results:
        designs, source = common.seated_designs(problem, args.results, "--results"), str(args.results)
    else:
        designs, source = [ch.design for ch in artefact_designs(args, problem)[4].values()], "solved as casadi-design solve does"
    return validate_artefact(problem, designs, args.trials, args.seed, spreads, source), []


def _tracker(args: argparse.Namespace, spreads: ErrorSpreads) -> tuple:
    """The virtual calibration of a tracker's plans (:func:`casadi_design.virtual.validate`)."""
    if args.results:
        problem = common.load(args, check_solver=False)
        plans, source = plans_from_results(problem, args.results), str(args.results)
    else:
        study, done, _ = common.design(args, "validate")
        problem = study.problem
        plans, source = plans_from_designs(problem, list(done.designs.values())), "solved as casadi-design solve does"
    if problem.M_held is not None and (problem.spec.calibration.prior is not None or (
            problem.spec.held is not None and problem.spec.held.prior_covariance is not None)):
        common.say(args, "note: the prior is not simulated: each trial identifies the campaign's experiments "
                         "by least squares alone, and sqrt(rho) is predicted for them alone")
    if problem.field is not None:
        common.say(args, "note: the field of unmodelled error is not simulated: each trial's robot differs from its "
                         "model by the parameters and the tracker's noise alone, and sqrt(rho) is the paper's measure")
    validation = validate(problem, plans, args.trials, args.seed, spreads, source)
    study = (linearisation_study(problem, plans, args.scales, args.trials, args.seed, spreads, source)
             if args.scales else [])
    return validation, study
