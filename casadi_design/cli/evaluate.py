"""``casadi-design evaluate``: score a user's plan with every measure and check its rules."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import OutputError
from ..records.files import read_results, write_json
from ..reports.tables import format_measures
from . import common

HELP = "score your own plan with every measure"
DESCRIPTION = ("Score a plan given as CSV (one row per experiment) with every measure: max and mean "
               "error along the test poses (mm), the score of every criterion, O1..O5 (SI units of "
               "B), and check it against the problem's joint limits, load and workspace. Columns: "
               "q1_deg or q1_rad ... (or joint names, e.g. joint1_deg; prismatic joints _mm or _m), "
               "the load fx_N, fy_N ... (mx_Nm ...; optional for a fixed load); experiment, x_mm, "
               "y_mm, z_mm are ignored, so the plans/*.csv files of solve and sweep can be read back.")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help=HELP, description=DESCRIPTION)
    p.add_argument("problem", help="problem file (TOML) the plan is for")
    p.add_argument("--plan", required=True, metavar="CSV",
                   help="the plan, one row per experiment: a plan CSV, a measurement CSV (its joint and "
                        "load columns; FIGAROH's layout as identify reads it) or bare joint columns "
                        "in rad and m (a controller's log)")
    p.add_argument("--compare", metavar="RESULTS",
                   help="results.json or sweep.json (or its folder): add the optimal plans with the "
                        "same m as columns")
    p.add_argument("--out", metavar="DIR",
                   help="folder for evaluation.json (SI units) and evaluation.png/pdf (error bands)")
    p.add_argument("--force", action="store_true", help="write into --out even if it is not empty")
    p.add_argument("--moves", action="store_true",
                   help="also check the moves of the plan as it runs: straight joint moves from home through "
                        "the rows in file order and back (as casadi-design program checks them)")
    p.add_argument("--home", metavar="DEG,...", help="home pose of --moves (default: as casadi-design program)")
    common.add_held(p)
    common.add_common(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..identification.measurements import read_experiments
    from ..optimisation.solve import plan_scores
    from ..records.results import design_from_record
    from ..reports.plotting import Band

    out = common.output_folder(args, "evaluate")
    spec = common.read_spec(args, artefact=True)
    if spec.measurement.artefact is not None:
        return run_artefact(args, spec, out)
    problem = common.load(args, check_solver=False, spec=spec)
    Q, F, plan = read_experiments(problem, args.plan, limits=False)  # outside the limits: told below
    if problem.m_held:  # a campaign's plan CSV: its measured rows are those of --measured
        new = ~plan.measured
        Q, F = Q[new], F[new]
    m = len(Q)
    others = []
    if args.compare:
        record = read_results(Path(args.compare))
        if record.get("problem") != problem.name:
            raise OutputError(f"{record['_path']}: results of problem '{record.get('problem')}', "
                              f"not '{problem.name}'; compare with results of the same problem")
        differs = [what for what, same in (
            ("sigma_m", np.isclose(record.get("sigma_m", np.nan), problem.sigma_m, rtol=1e-12, atol=0)),
            ("the parameters", record.get("calibration", {}).get("parameters") == list(problem.model.parameter_names)),
            ("the test poses", np.allclose([t["position_m"] for t in record.get("test_poses", [])],
                                           problem.test_poses.position_m, rtol=0, atol=1e-9)
             if len(record.get("test_poses", [])) == problem.test_poses.s else False)) if not same]
        if differs:  # a copy of the file edited under the same name: its errors are another problem's
            raise OutputError(f"{record['_path']}: results of '{problem.name}' with other {' and '.join(differs)} than "
                              f"{problem.path}; compare with results of this problem file")
        others = [design_from_record(d) for d in record["designs"] if d["m"] == m]
        if not others:
            raise OutputError(f"{record['_path']}: no design with m = {m} experiments (the plan's "
                              f"rows); solve or sweep that m first")
    from .program import home_pose

    home = home_pose(problem, args.home) if args.moves else None  # refused before anything is printed
    scores = plan_scores(problem, Q, F)
    print(common.case_line(problem, args.quiet))
    report(args, problem, out, Q, F, scores, [(f"{d.criterion} m={d.m}", Band.of(d), d.scores) for d in others], home)
    return 0


def run_artefact(args: argparse.Namespace, spec, out: Path | None) -> int:
    """``evaluate`` of a plan of configurations seated at an artefact's points (a CSV with point
    and placement columns, as ``solve`` writes and ``identify`` reads): its measures with the
    placements' poses beside X
    (:func:`~casadi_design.optimisation.artefact_pool.artefact_scores`); ``--compare`` an
    ``artefact_design.json``."""
    from ..identification.recordings import read_recordings
    from ..optimisation.artefact_pool import artefact_scores
    from ..reports.plotting import Band
    from .program import home_pose

    problem = common.load(args, check_solver=False, spec=spec)
    rec = read_recordings(problem, [args.plan], "--plan")
    others = []
    if args.compare:
        others = [(f"{d.criterion} m={d.m}", Band.of(d), d.scores)
                  for d in common.seated_designs(problem, args.compare, "--compare") if d.m == rec.N]
        if not others:
            raise OutputError(f"--compare {args.compare}: no design with m = {rec.N} configurations (the plan's rows); "
                              "solve that m first")
    home = home_pose(problem, args.home) if args.moves else None
    scores = artefact_scores(problem, rec.Q, rec.point, rec.placement)
    print(f"{problem.name}: configurations seated at {', '.join(rec.names)}; {problem.test_poses.s} test poses, "
          f"registered; sigma = {problem.sigma_m * 1e3:g} mm")
    report(args, problem, out, rec.Q, np.zeros((rec.N, problem.model.nF)), scores, others, home,
           {"point": rec.point.tolist(), "placement": [rec.names[g] for g in rec.placement]})
    return 0


def report(args: argparse.Namespace, problem, out: Path | None, Q: np.ndarray, F: np.ndarray, scores, others: list,
           home: np.ndarray | None, seated: dict | None = None) -> None:
    """Print a plan's measures beside ``others`` ((label, band, scores) each), the rules it
    breaks, its moves (``home``: with ``--moves``) and clearances; with ``out`` write
    evaluation.json (``seated``: each experiment's artefact point and placement) and the error
    bands."""
    from ..cell.cell import clearances
    from ..plan.rules import plan_violations
    from ..records.results import experiment_records
    from ..reports.plotting import USER_STYLE, Band, bands_figure, write_figures

    m = len(Q)
    violations = plan_violations(problem, Q, F)
    print(f"plan {args.plan}: {m} experiment{'s' if m > 1 else ''}"
          + ("" if scores.identifiable else "; M is singular: the parameters are NOT identifiable"))
    print(format_measures(["your plan"] + [label for label, _, _ in others], [scores] + [s for _, _, s in others]))
    if violations:
        print(f"the plan breaks {len(violations)} constraint(s) of the problem:")
        for v in violations:
            print(f"  {v}")
    else:
        print("the plan satisfies the problem's joint limits, load"
              + (", workspace and cell" if problem.cell else " and workspace"))
    moves = checked_moves(problem, Q, home)
    near = clearances(problem.cell, Q) if problem.cell else []
    if near:
        print(f"clearance on the {problem.cell.check.source} (mm), per experiment: "
              + ", ".join(f"{c.distance_m * 1e3:.0f}" for c in near)
              + f"; smallest {min(c.distance_m for c in near) * 1e3:.1f} mm between "
              + " and ".join(min(near, key=lambda c: c.distance_m).between))
    if out:
        write_json(out / "evaluation.json", {
            "problem": problem.name, "problem_file": problem.path, "plan_file": str(args.plan),
            "m": m, "units": {"q": "rad", "force": "N (N m for moments)", "errors": "m"},
            "experiments": experiment_records(Q, F, near), **({"seated": seated} if seated else {}),
            **scores.as_dict(), "violations": violations,
            **({"moves": moves} if args.moves else {}),
        })
        # a singular plan has no finite error band: draw the others, or no figure at all
        bands = ([Band(f"Your plan ({Path(args.plan).name})", USER_STYLE, scores.rms_error_m)]
                 if scores.identifiable else []) + [band for _, band, _ in others]
        files = [out / "evaluation.json"]
        if bands:
            write_figures(out, "evaluation", bands_figure(
                problem.test_poses.position_m, bands, f"{m} calibration experiment{'s' if m > 1 else ''}"))
            files += [out / "evaluation.png", out / "evaluation.pdf"]
        common.say(args, "wrote " + ", ".join(map(str, files))
                   + ("" if scores.identifiable else " (no error band of your plan: M is singular)"))


def checked_moves(problem, Q, home) -> list[dict]:
    """With ``--moves`` (``home``, rad; None without): each move of the plan in file order,
    from and back to home, checked as :func:`casadi_design.program.moves.check_move` checks a
    program's; printed, and returned for evaluation.json (m, SI)."""
    if home is None:
        return []
    from ..program.moves import check_move

    names = ["home", *(f"experiment {k}" for k in range(1, len(Q) + 1)), "home"]
    points = np.vstack([home, Q, home])
    out = []
    for a, b, qa, qb in zip(names[:-1], names[1:], points[:-1], points[1:]):
        mv = check_move(problem, qa, qb)
        out.append({"from": a, "to": b, "blocked": mv.blocked, "clearance_m": mv.clearance_m, "closest": mv.closest,
                    "mesh_clearance_m": mv.mesh_m, "beam_broken": mv.beam})
    if problem.cell is None:
        print("moves: no [cell], nothing to collide with")
        return out
    blocked = [m for m in out if m["blocked"]]
    print(f"moves in file order from and back to home: {len(blocked)} of {len(out)} break the "
          f"{problem.cell.spec.clearance_m * 1e3:g} mm clearance")
    for m in out:
        short = (problem.cell.spec.clearance_m - m["clearance_m"]) * 1e3
        print(f"  {m['from'] + ' -> ' + m['to']:<30} clearance {m['clearance_m'] * 1e3:7.1f} mm"
              + (f" BLOCKED by {short:.3g} mm ({m['closest']})" if m["blocked"] else "")
              + (f"; beam broken: {m['beam_broken']}" if m["beam_broken"] else ""))
    return out
