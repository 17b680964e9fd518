"""``casadi-design identify``: identify the robot from measured tracker coordinates
(:mod:`casadi_design.identification`), compensate the test poses, export the calibrated model."""

from __future__ import annotations

import argparse
import math
import time

from ..errors import ProblemError
from ..records.files import prepare_out, write_atomic, write_json
from .common import number, say

HELP = "identify the robot from tracker measurements, export the calibrated model (casadi-design identify --help)"
DESCRIPTION = (
    "Identify the robot from measured points: MEAS.csv is a plan CSV of casadi-design solve (joint "
    "and load columns) with the measured coordinates appended: meas_x_mm, meas_y_mm, meas_z_mm "
    "for one measured point, meas1_x_mm ... measK_z_mm for the markers of markers_m (_m for "
    "metres; an empty cell: a marker not seen); FIGAROH's layout (x1, y1, z1 ... in m, bare "
    "joint names) is read as it is. The tracker frame is registered in closed form (the "
    "measured points located when they are far off), candidate models (registration only, + "
    "joint offsets, + the most significant parameters, the problem's own) are cross-validated "
    "on the rows and one is chosen (--model), and its parameters and the frame are fitted "
    "together by weighted nonlinear least squares (scipy's trust region, exact Jacobian); "
    "outliers are excluded one at a time. Writes to --out: identification.json (SI units), "
    "identification.md and identification.png, compensated_test_poses.csv, calibrated.urdf, "
    "calibrated.toml (a problem file of the calibrated robot), for a DH robot calibrated_dh.toml "
    "(the same with the corrected DH table, Hayati's beta for nearly parallel axes), with "
    "compliances identified_compliances.toml, and viewer.html (measured and model points, residuals).")


def load_without_cell(path: str):
    """The problem of ``path`` built without its ``[cell]``: the identification does not check
    plans, and fitting the cell's capsules takes seconds (``calibrated.toml`` keeps the cell)."""
    from dataclasses import replace

    from ..problem.build import build_problem
    from ..problem_file.read import read_problem

    return build_problem(replace(read_problem(path), cell=None))


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("identify", help=HELP, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(run=run)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ..identification.calibrate import OUTLIER_SIGMA
    from ..identification.artefact_fit import ARTEFACT_MODELS
    from ..identification.choice import MODELS
    from ..identification.fit import FRAMES
    from ..identification.lsq import LOSS_SCALE_SIGMA, LOSSES
    from ..identification.measurements import COORDINATE_UNITS, LIMIT_TOLERANCE

    p.add_argument("problem", help="problem file (TOML) of the measured robot, e.g. problems/ur10_drilling.toml")
    p.add_argument("--measurements", required=True, metavar="CSV", action="append",
                   help="measured plan: the plan CSV with meas_x_mm, meas_y_mm, meas_z_mm (or meas1_x_mm ...) "
                        "appended; repeat it for the rounds of a campaign, each in a tracker frame of its own "
                        "(the tracker moved between them) unless --same-frame")
    p.add_argument("--same-frame", action="store_true",
                   help="the --measurements files share one tracker frame (the tracker did not move)")
    p.add_argument("--validation", metavar="CSV", action="append",
                   help="poses measured for validation only (same format), not used in the fit; with an artefact "
                        "([measurement.artefact]) a placement's folder or CSV, repeatable: placements held out")
    p.add_argument("--frame", choices=FRAMES, default="tracker",
                   help="frame of the coordinates: tracker (default: its placement is identified) or base")
    p.add_argument("--outlier-sigma", type=number("--outlier-sigma", "a positive number"), default=OUTLIER_SIGMA, metavar="S",
                   help=f"a row whose residual exceeds S sigma is excluded and the rest refitted "
                        f"(default {OUTLIER_SIGMA:g})")
    p.add_argument("--model", choices=tuple(dict.fromkeys(MODELS + ARTEFACT_MODELS)), default="auto",
                   help="the model identified: registration (frame and measured point), offsets (+ joint "
                        "offsets), identifiable (the problem's parameters), prior (those, MAP under the "
                        "problem's [calibration.prior]) or auto (default: chosen by cross-validation on the rows); "
                        "of an artefact's recordings: ball (the ball located), offsets, identifiable (the base set "
                        "they tell), 'identifiable + gravity' (+ the joints' compliances under the robot's weight; "
                        "'... + tilt' the bearings' too), 'identifiable + seating' (under the push seating the "
                        "ball) or auto")
    p.add_argument("--loss", choices=LOSSES, default="linear",
                   help=f"least-squares loss: linear (default) or a robust loss that down-weights residuals "
                        f"beyond {LOSS_SCALE_SIGMA:g} sigma (bad shots)")
    p.add_argument("--units", choices=tuple(COORDINATE_UNITS), default=None,
                   help="unit of coordinate columns without a unit suffix (FIGAROH's layout: m)")
    p.add_argument("--joint-units", default="rad,m", metavar="U[,U]",
                   help="units of joint columns named without a unit (bare joint names): rad or deg for "
                        "revolute joints, m or mm for prismatic ones (default rad,m)")
    p.add_argument("--columns", default="", metavar="FILE=OURS,...",
                   help="read the file's columns under our names, e.g. x1=meas1_x,y1=meas1_y,z1=meas1_z")
    p.add_argument("--limit-tolerance", type=number("--limit-tolerance", "a number >= 0 (rad or m)", strict=False), default=LIMIT_TOLERANCE, metavar="TOL",
                   help=f"joint readings up to TOL (rad or m) past a joint limit are accepted with a note "
                        f"(default {LIMIT_TOLERANCE:g})")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the files (created if missing)")
    p.add_argument("--force", action="store_true",
                   help="write into --out even if it exists and is not empty (overwrites our files)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no time and no list of the files written; the notes, tables and errors still print")
    p.set_defaults(tracker_defaults={d: p.get_default(d) for d in TRACKER_OPTIONS})


#: The options of a tracker's measurements: refused with an artefact's recordings (:func:`run_artefact`).
TRACKER_OPTIONS = ("same_frame", "frame", "loss", "units", "joint_units", "columns")


def run(args: argparse.Namespace) -> int:
    """Run ``casadi-design identify``; returns 0.

    Raises
    ------
    ProblemError, DesignError, casadi_design.errors.OutputError
        Bad input (one line naming the file, row and column), a fit that does not converge,
        an ``--out`` that cannot be written (before anything is computed).
    """
    from ..identification.calibrate import calibrate
    from ..calibrated.calibrated_toml import (
        calibrated_problem,
        toml_text,
    )
    from ..identification.measurements import (
        FileFormat,
        parse_columns,
        read_measurements,
        rounds_of,
    )
    from ..calibrated.report import (
        compensated_csv,
        identification_record,
        parameter_unit,
        report_markdown,
        summary_lines,
    )
    from ..calibrated.urdf import calibrated_chain, urdf_text

    out = prepare_out(args.out, args.force)
    t0 = time.perf_counter()
    fmt = FileFormat(args.units, tuple(u.strip() for u in args.joint_units.split(",") if u.strip()),
                     parse_columns(args.columns), args.limit_tolerance)
    problem = load_without_cell(args.problem)
    if problem.artefact is not None:
        return run_artefact(args, problem, out, t0)
    if args.validation is not None and len(args.validation) > 1:
        raise ProblemError(f"--validation: given {len(args.validation)} times; tracker measurements are validated "
                           "by one file (join the rows of the others into it)")
    args.validation = None if args.validation is None else args.validation[0]
    meas = rounds_of([read_measurements(problem, path, fmt) for path in args.measurements], args.same_frame)
    valid = None if args.validation is None else read_measurements(problem, args.validation, fmt)
    if valid is not None and valid.path in (meas.paths or (meas.path,)):
        raise ProblemError(f"--validation {valid.path}: is the file of the fit; give poses not used in the fit")
    cal = calibrate(problem, meas, args.frame, valid, args.outlier_sigma, args.loss, args.model)
    problem = cal.problem  # with the measured points located when they were far off
    print("\n".join(summary_lines(cal)))
    say(args, f"identification time {time.perf_counter() - t0:.2f} s")

    from ..reports.plotting import identification_figure, write_figures

    f = cal.fit
    chain = calibrated_chain(problem, f.fit.model.parameter_names, f.robot_X)
    header = (f"calibrated by casadi-design identify from {meas.path} ({problem.path}, frame "
              f"{args.frame}, {cal.model} model)")
    # every text first, the figure (the slow part) next, then the texts at once: Ctrl-C leaves
    # the folder as it was, or the figure alone
    texts = {"calibrated.urdf": urdf_text(problem, chain),
             "calibrated.toml": toml_text(calibrated_problem(problem, out / "calibrated.urdf"), header),
             "compensated_test_poses.csv": compensated_csv(cal)}
    texts.update(dh_texts(problem, chain, out, header))
    compliances = [(n, x, s) for n, x, s in zip(cal.names, f.X, cal.std) if n.startswith("k.")]
    if compliances:
        record = {"compliances": {n[2:]: {"value": float(x), "std": float(s), "unit": parameter_unit(cal, n)}
                                  for n, x, s in compliances}}
        texts["identified_compliances.toml"] = toml_text(
            record, header + "\nidentified joint compliances (a URDF cannot hold them)")
    figure = identification_figure(cal)
    names = ["identification.json", "identification.md", "identification.png", *texts, "viewer.html"]
    texts["identification.md"] = report_markdown(cal, ["identification.png"], names)
    files = {"urdf": "calibrated.urdf", "problem": "calibrated.toml",
             "compensated_test_poses": "compensated_test_poses.csv", "report": "identification.md",
             "figures": ["identification.png"]}
    if "calibrated_dh.toml" in texts:
        files["dh_problem"] = "calibrated_dh.toml"
    if compliances:
        files["compliances"] = "identified_compliances.toml"
    record_text = identification_record(cal, files)
    write_figures(out, "identification", figure, ("png",))  # a pdf too would take 1 s more
    for name, text in texts.items():
        write_atomic(out / name, text.encode())
    write_json(out / "identification.json", record_text)
    from ..reports.viewer import write_identification_viewer

    write_identification_viewer(out, cal)  # the measured points and the model's, in the cell
    say(args, f"wrote {', '.join(names)} in {out}")
    return 0


def dh_texts(problem, chain, out, header: str) -> dict[str, str]:
    """``calibrated_dh.toml``'s text for a DH robot measured at its flange (the calibrated DH
    table of ``chain``), else none (a DH robot measured elsewhere is said so)."""
    from ..calibrated.calibrated_toml import calibrated_dh_problem, toml_text
    from ..calibrated.dh_table import calibrated_dh, has_dh_table

    robot = problem.spec.robot
    if has_dh_table(robot):
        return {"calibrated_dh.toml": toml_text(calibrated_dh_problem(problem, calibrated_dh(robot, chain), out), header + (
            "\nthe calibrated DH table: beta_deg is Hayati's rotation about y for nearly parallel axes"))}
    if robot.source == "dh":
        print(f"no calibrated_dh.toml: the robot is measured at '{robot.frame}', not at its flange "
              "(calibrated.urdf and calibrated.toml hold the calibration)")
    return {}


def run_artefact(args: argparse.Namespace, problem, out, t0: float) -> int:
    """``identify`` of recordings of an artefact's points (:mod:`casadi_design.identification.artefact_fit`):
    each ``--measurements`` a placement's folder (``hole_<k>.csv``) or a CSV with ``point`` and
    ``placement`` columns, each ``--validation`` a placement held out. Writes identification.json,
    calibrated.urdf (``measured_point``: the calibrated ball centre) and calibrated.toml."""
    from ..identification.artefact_fit import calibrate_artefact
    from ..calibrated.artefact_report import artefact_record, artefact_summary
    from ..calibrated.calibrated_toml import calibrated_problem, toml_text
    from ..identification.recordings import read_recordings
    from ..calibrated.urdf import calibrated_chain, urdf_text

    for option, default in args.tracker_defaults.items():
        if getattr(args, option) != default:
            raise ProblemError(f"--{option.replace('_', '-')}: not used with an artefact's recordings (joints in rad "
                               "in the chain's order, a point and a placement each: docs/ball-socket.md); leave it out")
    if not (math.isfinite(args.limit_tolerance) and args.limit_tolerance >= 0):
        raise ProblemError(f"--limit-tolerance {args.limit_tolerance:g}: give a number >= 0 (rad or m)")
    rec = read_recordings(problem, args.measurements, "--measurements", args.limit_tolerance)
    valid = None if not args.validation else read_recordings(problem, args.validation, "--validation",
                                                             args.limit_tolerance)
    if valid is not None and set(valid.names) & set(rec.names):
        raise ProblemError(f"--validation: placement '{sorted(set(valid.names) & set(rec.names))[0]}' is in the fit; "
                           "give placements not used in the fit")
    cal = calibrate_artefact(problem, rec, valid, args.model, args.outlier_sigma)
    print("\n".join(artefact_summary(cal)))
    say(args, f"identification time {time.perf_counter() - t0:.2f} s")
    kept = cal.in_urdf  # the chosen model, or the best one without its compliances (a URDF cannot hold them)
    chain = calibrated_chain(problem, kept.names, kept.fit.X)
    header = (f"calibrated by casadi-design identify from {', '.join(rec.names)} ({problem.path}, the artefact's "
              f"points, {kept.model} model)")
    texts = {"calibrated.urdf": urdf_text(problem, chain),
             "calibrated.toml": toml_text(calibrated_problem(problem, out / "calibrated.urdf"), header),
             **dh_texts(problem, chain, out, header)}
    names = ["identification.json", "identification.md", *texts, "viewer.html"]
    texts["identification.md"] = "\n".join([f"# Identification of {problem.name} from an artefact's recordings", "",
                                            header, "", "```", *artefact_summary(cal), "```", "",
                                            "Files: " + ", ".join(f"`{n}`" for n in names), ""])
    files = {"urdf": "calibrated.urdf", "problem": "calibrated.toml", "report": "identification.md"}
    if "calibrated_dh.toml" in texts:
        files["dh_problem"] = "calibrated_dh.toml"
    record = artefact_record(cal, files)  # made before any file is written
    for name, text in texts.items():
        write_atomic(out / name, text.encode())
    write_json(out / "identification.json", record)
    from ..reports.viewer import write_identification_viewer

    write_identification_viewer(out, cal)  # the recordings, the sockets and the calibrated ball centres
    say(args, f"wrote {', '.join(names)} in {out}")
    return 0
