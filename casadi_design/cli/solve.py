"""``casadi-design solve``: the optimal plans of a problem file, Table 4 and Fig. 1."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..errors import OutputError, ProblemError
from ..execution.campaign import Campaign
from ..execution.study import writing
from ..problem.build import Problem
from ..records.files import write_atomic
from ..reports.tables import format_solver_lines, format_table
from . import common

HELP = "optimal plans for each criterion and m, and how accurate each is"
#: The file that keeps the finished designs of an unfinished solve (``--resume``).
PARTIAL_NAME = "solve.partial.json"
DESCRIPTION = ("Design the optimal plans of a problem file for each criterion and number of "
               "experiments m; print the max error along the test poses (mm, Table 4) and solve "
               "statistics; with --out write results.json (SI units), fig1.png/pdf, "
               "plans/<criterion>_m<m>.csv (joint values in deg and rad, load in N, measured point "
               "in mm), viewer.html (every plan in its cell, one pose at a time, offline) and report.md.")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("solve", help=HELP, description=DESCRIPTION)
    common.add_target(common.add_campaign(p, "numbers of experiments: 1,5 or a range 1:10 (default: [experiments].m)"))
    common.add_output(p, "folder for results.json, fig1.png/pdf, plans/*.csv, report.md (created if missing)")
    p.add_argument("--program", metavar="FORMAT",
                   help="also write each plan as a robot program, programs/<criterion>_m<m>.<ext> (as "
                        "casadi-design program with its defaults; FORMAT: urscript, rapid, krl, yaml, json)")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted solve saved in --out (solve.partial.json; same "
                        "problem and options)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    out = common.output_folder(args, "solve", (PARTIAL_NAME,))
    if args.program and not out:
        raise OutputError("--program writes into the --out folder; add --out DIR")

    def check(problem: Problem) -> None:  # the program's format, before anything is solved
        if args.program:
            from ..program.formats import check_format

            check_format(problem, args.program, "--program")

    spec = common.read_spec(args, artefact=True)
    if spec.measurement.artefact is not None:
        if args.program:
            raise ProblemError(f"{spec.path}: --program: not written by solve for an artefact's configurations yet; "
                               "run casadi-design program --plan <out>/plans/<criterion>_m<m>.csv (its moves stop "
                               "back from each socket)")
        return run_artefact(args, spec, out, t0)
    study, done, fig_m = common.design(args, "solve", out / PARTIAL_NAME if out else None, check=check)
    problem = study.problem
    designs = list(done.designs.values())
    wall = time.perf_counter() - t0
    print(common.case_line(problem, args.quiet))
    print(format_table(designs))
    if done.target is not None:
        print(done.target.line())
    common.say(args, "", format_solver_lines(designs),
               f"total {wall:.2f} s for {common.count(len(designs), 'design')} {study.where} (after imports)")
    if out:
        with writing(study):
            files = write_solve(out, problem, done, fig_m)
        if args.program:  # (the results are written: a plan that cannot be programmed says so)
            from ..reports.viewer import write_viewer
            from .program import write_programs

            programs: dict = {}
            files += write_programs(out, problem, designs, args.program, programs)
            write_viewer(out, problem, designs, programs)  # viewer.html again, with the routes
        common.say(args, f"wrote {', '.join(str(out / f) for f in files if not f.startswith('plans/'))} "
                         f"and {common.count(len(designs), 'plan')} in {out / 'plans'}")
    return 0


def write_solve(out: Path, problem: Problem, done: Campaign, fig_m: list[int]) -> list[str]:
    """results.json, fig1, the poses figure (with a [cell]), the plans, viewer.html and report.md."""
    from ..records.export import report_markdown, write_plans
    from ..records.files import write_results
    from ..reports.plotting import fig1, poses_figure, write_figures
    from ..reports.viewer import write_viewer

    designs, first = list(done.designs.values()), done.criteria[0]
    target = None if done.target is None else done.target.as_dict()
    write_results(out / "results.json", problem, designs, done.approx, target)
    files = ["results.json"]
    files += write_figures(out, "fig1", fig1(problem.test_poses.position_m, designs, fig_m))
    figures = [("Fig. 1: +/- sqrt(rho) along the test poses", "fig1.png")]
    if problem.cell is not None:  # the robot in the cell, in each experiment of the first criterion's plans
        shown = [d for d in designs if d.criterion == first and d.m in fig_m]
        files += write_figures(out, "poses", poses_figure(problem, shown), ("png",))  # 3-D: no PDF
        figures.append((f"The robot in the cell in every experiment ({first} plans), the "
                        "tracker's beams and the test poses", "poses.png"))
    files += write_plans(out, problem, designs)
    files += write_viewer(out, problem, designs)  # every plan in its cell, one pose at a time
    report = report_markdown(problem, designs, table=format_table(designs), figures=figures,
                             plans_for=fig_m, files=files, starts=done.settings.starts_text(),
                             notes=[] if target is None else [target["answer"]])
    write_atomic(out / "report.md", report.encode())
    return files + ["report.md"]


def run_artefact(args: argparse.Namespace, spec, out: Path | None, t0: float) -> int:
    """``solve`` of a problem measured at points fixed in an artefact
    (:mod:`casadi_design.optimisation.artefact_pool`): the m configurations best by each
    criterion among the recordings of ``--candidates`` (a placement's folder of
    ``hole_<k>.csv``, or a CSV with point and placement columns), or, without it, among
    configurations seated by the nominal robot at the problem file's placements
    (:mod:`casadi_design.plan.seated`), recorded at the best ``clamps`` of them (where to clamp
    the tool). Prints Table 4's table and each set of placements' max error; writes
    results.json, fig1, ``plans/<criterion>_m<m>.csv`` (with point and placement columns: what
    ``identify`` reads), ``viewer.html`` and report.md (:func:`write_artefact`)."""
    problem = common.load(args, check_solver=False, spec=spec)
    pool, names, sources, where, choices = artefact_designs(args, problem)
    designs = [ch.design for ch in choices.values()]
    print(f"{problem.name}: {where}; {problem.test_poses.s} test poses, registered; sigma = "
          f"{problem.sigma_m * 1e3:g} mm; seed {problem.solver.seed}")
    print(format_table(designs))
    clamping = clamp_table(choices, names)
    if clamping:
        print(clamping)
    common.say(args, f"total {time.perf_counter() - t0:.2f} s for {common.count(len(designs), 'design')} (after imports)")
    if out:
        from ..optimisation.artefact_pool import artefact_pool
        from ..problem_file.solver import starts_text

        starts = str(args.starts) if args.starts else starts_text(problem.solver.starts, problem.solver.criterion_starts)
        told = artefact_pool(problem, pool.Q, pool.point, pool.placement).names
        absorbed = [n for n in problem.model.parameter_names if n not in told]
        rows = {"solver": (f"the pool exchange from {starts} seeded starts per design"
                           + ("" if args.candidates else ", then IPOPT along the seated configurations")
                           + f"; seed {problem.solver.seed}"),
                "identified": (f"{problem.model.case}: the {len(told)} parameters the configurations tell "
                               f"({', '.join(told)}); absorbed by the placements' poses (no fixed point tells them): "
                               f"{', '.join(absorbed) or 'none'}")}
        files = write_artefact(out, problem, choices, names, sources, where, rows)
        common.say(args, f"wrote {', '.join(str(out / f) for f in files if not f.startswith('plans/'))} and "
                         f"{common.count(len(designs), 'plan')} in {out / 'plans'}")
    return 0


def write_artefact(out: Path, problem: Problem, choices: dict, names: tuple[str, ...], sources: tuple[str, ...],
                   where: str, rows: dict[str, str]) -> list[str]:
    """results.json (the designs, each experiment with its point and placement, and where to
    clamp: each set of placements' best plan), fig1, the plans (with their point and placement
    columns, as identify reads them), viewer.html and report.md (``rows``: the case's rows said
    for this kind, :func:`~casadi_design.records.export.report_markdown`)."""
    from ..records.export import report_markdown, write_plans
    from ..records.files import write_json
    from ..records.results import results_dict
    from ..reports.plotting import fig1, write_figures
    from ..reports.viewer import write_viewer

    designs = [ch.design for ch in choices.values()]
    record = artefact_record(choices, names, sources, where)
    write_json(out / "results.json", results_dict(problem, designs) | {"artefact": record})
    files = ["results.json"]
    shown = sorted({d.m for d in designs})[-1:]
    files += write_figures(out, "fig1", fig1(problem.test_poses.position_m, designs, shown))
    files += write_plans(out, problem, designs)
    files += write_viewer(out, problem, designs)
    tables = [format_table(designs), clamp_table(choices, names)]
    report = report_markdown(
        problem, designs, table="\n\n".join(t for t in tables if t), plans_for=shown, files=files, starts="",
        figures=[("Fig. 1: +/- sqrt(rho) along the test poses, after registering the work", "fig1.png")],
        notes=[f"candidates: {where}", f"the test-pose measure: {record['test_pose_measure']}"],
        rows=rows)
    write_atomic(out / "report.md", report.encode())
    return files + ["report.md"]


def artefact_record(choices: dict, names: tuple[str, ...], sources: tuple[str, ...], where: str) -> dict:
    """The ``artefact`` section of results.json and sweep.json: where the pool came from, the
    placements, what the test-pose measure is, and per design the placements used, the
    recordings chosen and each set of placements' best plan (where to clamp)."""
    return {
        "pool": where, "placements": list(names),
        "test_pose_measure": "sqrt(rho) of the test poses' positions after registering the work (their rigid "
                             "motion projected out), every placement's pose unknown",
        "designs": [{"criterion": c, "m": m, "placements_used": [names[g] for g in ch.placements],
                     "recordings": [sources[i] for i in ch.rows],
                     "by_placements": [{"placements": [names[g] for g in S],
                                        "max_rms_error_m": None if d is None else d.scores.max_rms_error_m,
                                        "value": None if d is None else d.scores.value(c)} for S, d in ch.by_set]}
                    for (c, m), ch in choices.items()]}


def artefact_designs(args: argparse.Namespace, problem: Problem) -> tuple:
    """The designs of ``solve`` for an artefact's points (:func:`run_artefact`): the pool (the
    recordings of ``--candidates`` or the configurations seated at the problem file's
    placements), the placements' names, each configuration's source, a line saying where they
    come from, and the :class:`~casadi_design.optimisation.artefact_pool.ClampChoice` of each
    (criterion, m)."""
    from ..execution.campaign import check_criteria
    from ..identification.recordings import read_recordings
    from ..optimisation.artefact_pool import choose_clamps
    from ..plan.seated import seated_configurations

    criteria = tuple(args.criteria or problem.criteria)
    check_criteria(problem, criteria)
    if getattr(args, "candidates", None):
        pool = read_recordings(problem, args.candidates, "--candidates")
        names, sources, clamps = pool.names, pool.sources, len(pool.names)
        where = f"{pool.N} recorded configurations of {', '.join(names)}"
    else:
        pool = seated_configurations(problem)
        names, clamps = pool.names, problem.spec.measurement.artefact.clamps
        sources = tuple(f"seated at point {k} of {names[g]}" for k, g in zip(pool.point, pool.placement))
        where = (f"{len(pool.Q)} configurations seated by the nominal robot at {', '.join(names)}, "
                 f"recorded at the best {common.count(clamps, 'placement')}")
    seated = not getattr(args, "candidates", None)
    choices = {(c, m): choose_clamps(problem, pool.Q, pool.point, pool.placement, names, c, m,
                                     args.starts or problem.solver.starts_for(c), clamps, seated)
               for m in args.m or sorted(problem.m_values) for c in criteria}
    return pool, names, sources, where, choices


def clamp_table(choices: dict, names: tuple[str, ...]) -> str:
    """Where to clamp: the max error at the test poses (mm) of each set of placements' best
    plan, a column per design; empty when every design had one set to judge."""
    keys = list(choices)
    sets = [S for S, _ in choices[keys[0]].by_set]
    if len(sets) < 2:
        return ""
    head = ["placements"] + [f"{c} m={m}" for c, m in keys]
    rows = [[" + ".join(names[g] for g in S)] + [
        "-" if d is None else f"{d.scores.max_rms_error_m * 1e3:.4f}" + ("*" if S == choices[k].placements else "")
        for k in keys for S2, d in choices[k].by_set if S2 == S] for S in sets]
    width = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    lines = ["where to clamp: max error along the test poses (mm) of each placement's best plan by the criterion "
             "(* where it clamps, by its own measure)"]
    lines += ["  ".join([r[0].ljust(width[0])] + [v.rjust(w) for v, w in zip(r[1:], width[1:])]) for r in [head, *rows]]
    return "\n".join(lines)
