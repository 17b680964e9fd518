"""``casadi-design sweep``: accuracy vs the number of experiments m, for each criterion."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from ..errors import ProblemError
from ..execution.study import writing
from ..execution.sweep import PARTIAL_NAME, RESUME_FILES, Sweep
from ..problem.build import Problem
from ..problem_file.solver import starts_text
from ..records.files import write_atomic
from ..reports.tables import format_sweep_table
from . import common

HELP = "accuracy vs number of experiments m for each criterion"
DESCRIPTION = ("Solve every (criterion, m) of a range of m with the seeded starts of `solve` plus a "
               "warm start from the previous m's plan; print max error (mm) vs m with the reference "
               "'best single pose repeated m times' (e1/sqrt(m)); with --out write sweep.csv/json, "
               "sweep_max_error.png/pdf, fig1.png/pdf, plans/*.csv, report.md. Each finished design "
               "is saved at once in sweep.partial.json: after Ctrl-C, run the same command with --resume.")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help=HELP, description=DESCRIPTION)
    common.add_campaign(p, "numbers of experiments: a range first:last[:step], e.g. 1:10, or a list "
                           "1,2,5 (default: the smallest identifiable m to the largest [experiments].m)",
                        candidates=False)
    common.add_target(p, sweep=True)
    common.add_output(p, "folder for sweep.csv/json, figures, plans/*.csv, report.md (created if missing)")
    p.add_argument("--log", action="store_true",
                   help="logarithmic axes in sweep_max_error (the repeat line is then straight)")
    p.add_argument("--no-warm-start", action="store_true",
                   help="only the seeded starts: every row then equals `solve` exactly")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted sweep saved in --out (same problem and options)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    out = common.output_folder(args, "sweep", RESUME_FILES)
    spec = common.read_spec(args, artefact=True)
    if spec.measurement.artefact is not None:
        return run_artefact(args, spec, out, t0)
    study, sweep, fig_m = common.design(args, "sweep", out / PARTIAL_NAME if out else None, sweep=True)
    problem = study.problem
    wall = time.perf_counter() - t0
    print(common.case_line(problem, args.quiet))
    print(format_sweep_table(sweep))
    target = None
    if study.target_m is not None:
        from ..execution.target import answer_from

        target = answer_from(problem, study.target_m, sweep.designs, max(sweep.m_values))
        print(target.line())
    warm = ", plus one warm start for m after the first" if study.warm_start else ""
    common.say(args, f"total {wall:.2f} s for {len(sweep.designs)} designs "
                     f"({study.settings.starts_text()} seeded starts each{warm}) {study.where}")
    if out:
        with writing(study):
            files = write_sweep(out, problem, sweep, fig_m, args.log, study.key, sweep.approx, target)
        common.say(args, f"wrote {', '.join(str(out / f) for f in files if not f.startswith('plans/'))} "
                         f"and {common.count(sum(f.startswith('plans/') for f in files), 'plan')} in {out / 'plans'}")
    return 0


def run_artefact(args: argparse.Namespace, spec, out: Path | None, t0: float) -> int:
    """``sweep`` of a problem measured at an artefact's points: the designs of ``solve``
    (:func:`~.solve.artefact_designs`: configurations seated at the problem file's placements,
    recorded at the best ``clamps`` of them) for every m of the range, the paper's table of this
    kind (max error along the test poses against m, each criterion) and where to clamp."""
    from .solve import artefact_designs, clamp_table

    if getattr(args, "resume", False) or getattr(args, "target_mm", None) is not None:
        raise ProblemError(f"{spec.path}: --resume and --target-mm are not built for an artefact's points; "
                           "sweep the range of m without them")
    problem = common.load(args, check_solver=False, spec=spec)
    if not args.m:  # the smallest m with as many values as X and one placement's pose, to the largest asked
        args.m = list(range(problem.m_min, max(problem.m_values) + 1))
    pool, names, sources, where, choices = artefact_designs(args, problem)
    criteria = tuple(dict.fromkeys(c for c, _ in choices))
    m_values = tuple(sorted({m for _, m in choices}))
    starts = args.starts or problem.solver.starts
    sweep = Sweep(m_values, criteria, {k: ch.design for k, ch in choices.items()}, starts, False,
                  choices["test-pose", m_values[0]].design if "test-pose" in criteria else None)
    print(f"{problem.name}: {where}; {problem.test_poses.s} test poses, registered; sigma = "
          f"{problem.sigma_m * 1e3:g} mm; seed {problem.solver.seed}")
    print(format_sweep_table(sweep))
    clamping = clamp_table(choices, names)
    if clamping:
        print(clamping)
    common.say(args, f"total {time.perf_counter() - t0:.2f} s for {len(choices)} designs (after imports)")
    if out:
        from .solve import artefact_record

        files = write_sweep(out, problem, sweep, [m_values[0], m_values[-1]], args.log, {"starts": starts}, {},
                            extra={"artefact": artefact_record(choices, names, sources, where)})
        common.say(args, f"wrote {', '.join(str(out / f) for f in files if not f.startswith('plans/'))} "
                         f"and {common.count(sum(f.startswith('plans/') for f in files), 'plan')} in {out / 'plans'}")
    return 0


def write_sweep(out: Path, problem: Problem, sweep: Sweep, fig_m: list[int], log: bool, key: dict,
                approx: dict, target=None, extra: dict | None = None) -> list[str]:
    """sweep.json, sweep.csv, the figures, the plans and report.md (``target``: the
    :class:`~casadi_design.execution.target.TargetAnswer` of ``--target-mm``; ``extra``: more
    keys of sweep.json)."""
    from ..execution.sweep import COLUMNS, sweep_record, sweep_rows
    from ..records.export import report_markdown, write_plans, write_table_csv
    from ..records.files import write_json
    from ..reports.plotting import fig1, sweep_figure, write_figures

    designs = list(sweep.designs.values())
    record = sweep_record(problem, sweep, key, approx)
    if target is not None:
        record["target"] = target.as_dict()
    write_json(out / "sweep.json", record | (extra or {}))
    write_table_csv(out / "sweep.csv", COLUMNS, sweep_rows(sweep))
    files = ["sweep.json", "sweep.csv"]
    files += write_figures(out, "sweep_max_error", sweep_figure(sweep, log))
    files += write_figures(out, "fig1", fig1(problem.test_poses.position_m, designs, fig_m))
    files += write_plans(out, problem, designs)
    notes = [
        ("Each design uses the seeded starts of `casadi-design solve` (same seed, same plans); "
         "for every m after the first, one more start begins from the previous m's plan plus "
         "new random poses. It wins only when strictly better, so a row can be better than "
         "`solve`, never worse (`warm_start_won` in sweep.csv)."),
    ]
    if target is not None:
        notes.append(target.line())
    if sweep.reference is not None:
        e_ref = sweep.reference.scores.max_rms_error_m
        notes.append(f"Repeat line: the best test-pose plan of {sweep.reference.m} experiment(s) "
                     f"({e_ref * 1e3:.4f} mm) repeated, e / sqrt(m / {sweep.reference.m}).")
        m_last = sweep.m_values[-1]
        e_last = sweep.designs["test-pose", m_last].scores.max_rms_error_m
        notes.append(f"Test-pose plans: {e_ref / e_last:.2f} times more accurate at m = {m_last} "
                     f"than at m = {sweep.reference.m}; repetition alone gives "
                     f"{math.sqrt(m_last / sweep.reference.m):.2f}.")
    report = report_markdown(
        problem, designs, table=format_sweep_table(sweep),
        starts=starts_text(sweep.seeded_starts, sweep.criterion_starts),
        figures=[("Max error along the test poses vs m", "sweep_max_error.png"),
                 (f"Fig. 1: +/- sqrt(rho) along the test poses, m = {', '.join(map(str, fig_m))}",
                  "fig1.png")],
        plans_for=fig_m, files=files, title="Calibration sweep", notes=notes)
    write_atomic(out / "report.md", report.encode())
    return files + ["report.md"]
