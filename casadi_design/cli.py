"""Command line: design, sweep, score and plot calibration plans.

    casadi-design solve    problems/<case>.toml --out DIR      optimal plans, Table 4, Fig. 1
    casadi-design sweep    problems/<case>.toml --m 1:10 --out DIR   accuracy vs m per criterion
    casadi-design evaluate problems/<case>.toml --plan plan.csv      score your own plan
    casadi-design plot     DIR/sweep.json                       redraw the figures
    casadi-design validate problems/<case>.toml --results DIR   simulate the calibration
    casadi-design bound    problems/<case>.toml --m 1:10        what no plan can beat

Errors in the input or a design that cannot be produced print one line ``error: ...`` and exit
with code 2; files are written only once the work they describe is done (a sweep also keeps
each finished design in ``sweep.partial.json``; Ctrl-C exits with code 130 and ``--resume``
continues).
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from functools import partial
from pathlib import Path

from . import interrupt
from .criteria import CRITERIA
from .errors import DesignError, ProblemError
from .parallel import MissingExtraError, cpu_count
from .results import OutputError, write_atomic

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


# --------------------------------------------------------------------------- option types

def _integer(what: str, minimum: int = 1):
    """An option's integer ``>= minimum`` (1: "a positive integer")."""
    kind = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = minimum - 1
        if v < minimum:
            raise argparse.ArgumentTypeError(f"{what} takes {kind}, got '{text}'")
        return v
    return parse


def _m_values(text: str) -> list[int]:
    from .sweep import parse_m_values

    try:
        return parse_m_values(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


#: Figure formats ``plot --format`` writes.
FIGURE_FORMATS = ("png", "pdf", "svg")


def _formats(text: str) -> list[str]:
    formats = _names(text)
    unknown = [f for f in formats if f not in FIGURE_FORMATS]
    if unknown or not formats:
        raise argparse.ArgumentTypeError(f"unknown figure format '{unknown[0] if unknown else text}'; "
                                         f"allowed: {', '.join(FIGURE_FORMATS)}")
    return formats


# --------------------------------------------------------------------------- shared steps

def _executor(args: argparse.Namespace):
    from .parallel import make_executor

    return make_executor(args.jobs, args.dask_scheduler)


def _where(args: argparse.Namespace) -> str:
    if args.dask_scheduler:
        return f"on the Dask cluster at {args.dask_scheduler}"
    jobs = args.jobs or cpu_count()
    return "in this process" if jobs == 1 else f"on {jobs} processes"


def _ipopt_option(text: str) -> tuple[str, int | float | str]:
    """``KEY=VALUE`` of ``--ipopt``: the value as an int, a float or a string."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or not value.strip():
        raise argparse.ArgumentTypeError(f"--ipopt takes KEY=VALUE (e.g. max_cpu_time=60), got '{text}'")
    for kind in (int, float):
        try:
            return key.strip(), kind(value)
        except ValueError:
            pass
    return key.strip(), value.strip()


def _load(args: argparse.Namespace, check_solver: bool = True):
    """Read and build the problem file of ``args``, with the ``--ipopt`` options over its
    [solver.ipopt]; with ``check_solver``, also try the IPOPT options."""
    from dataclasses import replace

    from .build import build_problem
    from .problem import read_problem
    from .solve import check_ipopt_options

    spec = read_problem(args.problem)
    if getattr(args, "ipopt", None):
        options = {**dict(spec.solver.ipopt), **dict(args.ipopt)}
        spec = replace(spec, solver=replace(spec.solver, ipopt=tuple(sorted(options.items()))))
    problem = build_problem(spec)
    if check_solver:
        check_ipopt_options(problem)
    return problem


def _say(args: argparse.Namespace, *lines: str) -> None:
    if not args.quiet:
        print(*lines, sep="\n")


def _case_line(problem) -> str:
    line = (f"{problem.name}: {problem.model.case} calibration of "
            f"{', '.join(problem.model.parameter_names)}; {problem.test_poses.s} test poses; "
            f"sigma = {problem.sigma_m * 1e3:g} mm; seed {problem.solver.seed}")
    return line if problem.base_set is None else line + "\n" + problem.base_set.report()


def _fig_m(requested: list[int] | None, available: list[int], preferred: tuple[int, ...]) -> list[int]:
    """m values of the Fig. 1 panels: requested, else the problem's m that were solved, else
    the first and last m (at most two panels by default)."""
    if requested:
        missing = [m for m in requested if m not in available]
        if missing:
            raise OutputError(f"--fig-m {missing[0]} was not solved; choose among {available}")
        return requested
    chosen = [m for m in preferred if m in available][:2]
    return chosen or sorted({available[0], available[-1]})


def _write_figures(out: Path, stem: str, fig, formats: tuple[str, ...] = ("png", "pdf")) -> list[str]:
    from .plotting import save_figures

    save_figures(fig, [out / f"{stem}.{suffix}" for suffix in formats])
    return [f"{stem}.{suffix}" for suffix in formats]


def _write_plans(out: Path, problem, designs) -> list[str]:
    from .export import write_plan_csv

    (out / "plans").mkdir(exist_ok=True)
    names = []
    for d in designs:
        name = f"plans/{d.criterion}_m{d.m}.csv"
        write_plan_csv(out / name, problem, d)
        names.append(name)
    return names


# --------------------------------------------------------------------------- solve

def _approximate(args: argparse.Namespace, problem, criteria) -> dict:
    """The approximate designs of the criteria that have a bound (``--bound-steps``)."""
    from .bound import approximate_designs

    t0 = time.perf_counter()
    approx = approximate_designs(problem, criteria, args.bound_steps, args.bound_pool)
    if approx:
        _say(args, f"approximate designs of {', '.join(approx)}: {time.perf_counter() - t0:.1f} s "
                   f"({', '.join(f'{len(a.history)} exchange steps' for a in approx.values())})")
    return approx


def _solve(args: argparse.Namespace) -> int:
    from .bound import ROUNDED_PLANS, rounded_starts, with_bound
    from .export import report_markdown
    from .nlp import B0_at_test_poses
    from .plotting import fig1, poses_figure
    from .progress import progress_bar
    from .results import format_solver_lines, format_table, prepare_out, write_results
    from .solve import solve_design
    from .sweep import check_criteria, check_m_values

    t0 = time.perf_counter()
    out = prepare_out(args.out, args.force) if args.out is not None else None
    with _executor(args) as executor:  # first: worker processes start while the problem loads
        problem = _load(args)
        m_values = args.m or sorted(problem.m_values)
        criteria = args.criteria or list(problem.criteria)
        check_criteria(problem, criteria)
        check_m_values(problem, m_values)
        fig_m = _fig_m(args.fig_m, m_values, problem.m_values)
        starts = args.starts or problem.solver.starts
        B0 = B0_at_test_poses(problem)
        approx = _approximate(args, problem, criteria)
        bar = progress_bar(len(m_values) * sum(starts + (ROUNDED_PLANS if c in approx else 0)
                                               for c in criteria), "solve", args.quiet)
        designs = []
        try:
            for m in m_values:
                for c in criteria:
                    bar.set_postfix_str(f"{c}, m = {m}")
                    d = solve_design(problem, c, m, B0, starts=starts, verbose=args.verbose,
                                     initial_plans=rounded_starts(problem, approx, c, m),
                                     executor=executor, progress=bar.update)
                    designs.append(with_bound(problem, d, approx))
        finally:
            bar.close()
    wall = time.perf_counter() - t0
    print(_case_line(problem))
    print(format_table(designs))
    _say(args, "", format_solver_lines(designs),
         f"total {wall:.2f} s for {len(designs)} designs {_where(args)} (after imports)")
    if out:
        out.mkdir(parents=True, exist_ok=True)
        write_results(out / "results.json", problem, designs, approx)
        files = ["results.json"]
        files += _write_figures(out, "fig1", fig1(problem.test_poses.position_m, designs, fig_m))
        figures = [("Fig. 1: +/- sqrt(rho) along the test poses", "fig1.png")]
        if problem.cell is not None:  # the robot in the cell, in each experiment of the first criterion's plans
            shown = [d for d in designs if d.criterion == criteria[0] and d.m in fig_m]
            files += _write_figures(out, "poses", poses_figure(problem, shown), ("png",))  # 3-D: no PDF
            figures.append((f"The robot in the cell in every experiment ({criteria[0]} plans), the "
                            "tracker's beams and the test poses", "poses.png"))
        files += _write_plans(out, problem, designs)
        report = report_markdown(problem, designs, table=format_table(designs), figures=figures,
                                 plans_for=fig_m, files=files, starts=starts)
        write_atomic(out / "report.md", report.encode())
        _say(args, f"wrote {', '.join(str(out / f) for f in files if not f.startswith('plans/'))}, "
                   f"{out / 'report.md'} and {len(designs)} plans in {out / 'plans'}")
    return 0


# --------------------------------------------------------------------------- sweep

def _sweep(args: argparse.Namespace) -> int:
    from .progress import progress_bar
    from .results import prepare_out
    from .sweep import (
        check_criteria,
        check_m_values,
        format_sweep_table,
        load_partial,
        partial_record,
        run_sweep,
        sweep_key,
        sweep_total_starts,
    )

    t0 = time.perf_counter()
    if args.resume and args.out is None:
        raise OutputError("--resume needs the --out folder of the interrupted sweep; add --out DIR")
    out = prepare_out(args.out, args.force, args.resume) if args.out is not None else None
    problem = _load(args)
    criteria = args.criteria or list(problem.criteria)
    ms = args.m or list(range(problem.m_min, max(problem.m_values) + 1))
    check_criteria(problem, criteria)
    check_m_values(problem, ms)
    starts = args.starts or problem.solver.starts
    warm = not args.no_warm_start
    fig_m = _fig_m(args.fig_m, ms, problem.m_values)
    key = sweep_key(problem, criteria, ms, starts, warm, (args.bound_steps, args.bound_pool))
    done = load_partial(out, key) if args.resume else {}
    if args.resume:
        _say(args, f"resuming: {len(done)} of {len(ms) * len(criteria)} designs already in {out}")
    saved = dict(done)
    partial = out / "sweep.partial.json" if out else None

    def save(design) -> None:
        saved[design.criterion, design.m] = design
        bar.set_postfix_str(f"done: {design.criterion}, m = {design.m}")
        if partial is not None:
            out.mkdir(parents=True, exist_ok=True)
            partial_record(partial, problem, key, list(saved.values()))

    approx = _approximate(args, problem, criteria)
    total = sweep_total_starts(problem, criteria, ms, starts, warm, approx)
    bar = progress_bar(total, "sweep", args.quiet)
    try:
        with _executor(args) as executor:
            sweep = run_sweep(problem, criteria, ms, starts, warm_start=warm, done=done,
                              executor=executor, progress=bar.update, on_design=save,
                              verbose=args.verbose, approx=approx)
    except KeyboardInterrupt:
        bar.close()
        where = (f"kept in {partial}; continue with the same command and --resume" if partial
                 else "not kept (no --out)")
        print(f"interrupted: {len(saved)} of {len(ms) * len(criteria)} designs {where}", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    print(_case_line(problem))
    print(format_sweep_table(sweep))
    _say(args, f"total {wall:.2f} s for {len(sweep.designs)} designs ({starts} seeded starts each"
               f"{', plus one warm start for m after the first' if warm else ''}) {_where(args)}")
    if out:
        files = _write_sweep(out, problem, sweep, fig_m, args.log, starts, key, approx)
        if partial.exists():
            partial.unlink()
        _say(args, f"wrote {', '.join(str(out / f) for f in files if not f.startswith('plans/'))} "
                   f"and {sum(f.startswith('plans/') for f in files)} plans in {out / 'plans'}")
    return 0


def _write_sweep(out: Path, problem, sweep, fig_m: list[int], log: bool, starts: int, key: dict,
                 approx: dict) -> list[str]:
    from .export import report_markdown, write_table_csv
    from .plotting import fig1, sweep_figure
    from .results import write_json
    from .sweep import COLUMNS, format_sweep_table, sweep_record, sweep_rows

    out.mkdir(parents=True, exist_ok=True)
    designs = list(sweep.designs.values())
    write_json(out / "sweep.json", sweep_record(problem, sweep, key, approx))
    write_table_csv(out / "sweep.csv", COLUMNS, sweep_rows(sweep))
    files = ["sweep.json", "sweep.csv"]
    files += _write_figures(out, "sweep_max_error", sweep_figure(sweep, log))
    files += _write_figures(out, "fig1", fig1(problem.test_poses.position_m, designs, fig_m))
    files += _write_plans(out, problem, designs)
    notes = [
        ("Each design uses the seeded starts of `casadi-design solve` (same seed, same plans); "
         "for every m after the first, one more start begins from the previous m's plan plus "
         "new random poses. It wins only when strictly better, so a row can be better than "
         "`solve`, never worse (`warm_start_won` in sweep.csv)."),
    ]
    if sweep.reference is not None:
        e_ref = sweep.reference.scores.max_rms_error_m
        notes.append(f"Repeat line: the best test-pose plan of {sweep.reference.m} experiment(s) "
                     f"({e_ref * 1e3:.4f} mm) repeated, e / sqrt(m / {sweep.reference.m}).")
        if "test-pose" in sweep.criteria:
            m_last = sweep.m_values[-1]
            e_last = sweep.designs["test-pose", m_last].scores.max_rms_error_m
            notes.append(f"Test-pose plans: {e_ref / e_last:.2f} times more accurate at m = {m_last} "
                         f"than at m = {sweep.reference.m}; repetition alone gives "
                         f"{math.sqrt(m_last / sweep.reference.m):.2f}.")
    report = report_markdown(
        problem, designs, table=format_sweep_table(sweep), starts=starts,
        figures=[("Max error along the test poses vs m", "sweep_max_error.png"),
                 (f"Fig. 1: +/- sqrt(rho) along the test poses, m = {', '.join(map(str, fig_m))}",
                  "fig1.png")],
        plans_for=fig_m, files=files, title="Calibration sweep", notes=notes)
    write_atomic(out / "report.md", report.encode())
    return files + ["report.md"]


# --------------------------------------------------------------------------- evaluate

def _observability(k: str, scores) -> float:
    return scores.observability.get(k, math.nan)


#: Rows of the evaluate table: label, Scores -> value, format.
MEASURE_ROWS = (
    ("max over test poses of sqrt(rho), mm", lambda sc: sc.max_rms_error_m * 1e3, ".4f"),
    ("mean over test poses of sqrt(rho), mm", lambda sc: float(sc.rms_error_m.mean()) * 1e3, ".4f"),
    ("D: log det M", lambda sc: sc.log_det_M, ".6g"),
    ("A: trace M^-1", lambda sc: sc.trace_M_inv, ".6g"),
    ("E: smallest singular value s_L", lambda sc: sc.s_min, ".6g"),
    ("T: trace M", lambda sc: sc.trace_M, ".6g"),
    ("condition number s_1/s_L", lambda sc: sc.condition, ".6g"),
    *((k, partial(_observability, k), ".6g") for k in ("O1", "O2", "O3", "O4", "O5")),
)


def _evaluate(args: argparse.Namespace) -> int:
    from .export import read_plan_csv
    from .nlp import B0_at_test_poses
    from .results import design_from_record, prepare_out, read_json, write_json
    from .cell import clearances
    from .rules import plan_violations
    from .solve import plan_scores

    out = prepare_out(args.out, args.force) if args.out is not None else None
    problem = _load(args, check_solver=False)
    Q, F = read_plan_csv(problem, args.plan)
    m = Q.shape[1]
    others = []
    if args.compare:
        record = read_json(Path(args.compare))
        if record.get("problem") != problem.name:
            raise OutputError(f"{record['_path']}: results of problem '{record.get('problem')}', "
                              f"not '{problem.name}'; compare with results of the same problem")
        others = [design_from_record(d) for d in record["designs"] if d["m"] == m]
        if not others:
            raise OutputError(f"{record['_path']}: no design with m = {m} experiments (the plan's "
                              f"rows); solve or sweep that m first")
    scores = plan_scores(problem, Q, F, B0_at_test_poses(problem))
    violations = plan_violations(problem, Q, F)
    print(_case_line(problem))
    print(f"plan {args.plan}: {m} experiment{'s' if m > 1 else ''}"
          + ("" if scores.identifiable else "; M is singular: the parameters are NOT identifiable"))
    names = ["your plan"] + [f"{d.criterion} m={d.m}" for d in others]
    width = max(len(r[0]) for r in MEASURE_ROWS) + 2
    print(f"{'measure (SI units of B unless stated)':<{width}}" + "".join(f"{n:>16}" for n in names))
    print("-" * (width + 16 * len(names)))
    for label, get, fmt in MEASURE_ROWS:
        print(f"{label:<{width}}" + "".join(f"{get(sc):>16{fmt}}" for sc in [scores] + [d.scores for d in others]))
    if violations:
        print(f"the plan breaks {len(violations)} constraint(s) of the problem:")
        for v in violations:
            print(f"  {v}")
    else:
        print("the plan satisfies the problem's joint limits, load"
              + (", workspace and cell" if problem.cell else " and workspace"))
    near = clearances(problem.cell, Q) if problem.cell else []
    if near:
        print(f"clearance on the {problem.cell.check.source} (mm), per experiment: "
              + ", ".join(f"{c.distance_m * 1e3:.0f}" for c in near)
              + f"; smallest {min(c.distance_m for c in near) * 1e3:.1f} mm between "
              + " and ".join(min(near, key=lambda c: c.distance_m).between))
    if out:
        from .plotting import USER_STYLE, Band, bands_figure

        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "evaluation.json", {
            "problem": problem.name, "problem_file": problem.path, "plan_file": str(args.plan),
            "m": m, "units": {"q": "rad", "force": "N (N m for moments)", "errors": "m"},
            "experiments": [{"q_rad": q.tolist(), "force": f.tolist()}
                            | ({"clearance_m": c.distance_m, "closest_bodies": list(c.between)} if c else {})
                            for q, f, c in zip(Q.T, F.T, near or [None] * m)],
            "max_rms_error_m": scores.max_rms_error_m, **scores.as_dict(),
            "violations": violations,
        })
        # a singular plan has no finite error band: draw the others, or no figure at all
        bands = ([Band(f"Your plan ({Path(args.plan).name})", USER_STYLE, scores.rms_error_m)]
                 if scores.identifiable else []) + others
        files = [out / "evaluation.json"]
        if bands:
            _write_figures(out, "evaluation", bands_figure(problem.test_poses.position_m, bands,
                                                             f"{m} calibration experiment{'s' if m > 1 else ''}"))
            files += [out / "evaluation.png", out / "evaluation.pdf"]
        _say(args, "wrote " + ", ".join(map(str, files))
             + ("" if scores.identifiable else " (no error band of your plan: M is singular)"))
    return 0


# --------------------------------------------------------------------------- plot

def _plot(args: argparse.Namespace) -> int:
    import numpy as np

    from .plotting import fig1, save_figures, sweep_figure
    from .results import design_from_record, read_json
    from .sweep import sweep_from_record

    if args.out is not None and not args.out.strip():
        raise OutputError("--out is empty; give a folder name (or leave --out out to write beside the results)")
    record = read_json(Path(args.results))
    src = Path(record["_path"])
    out = Path(args.out) if args.out is not None else src.parent
    designs = [design_from_record(d) for d in record["designs"]]
    available = sorted({d.m for d in designs})
    figures = {"fig1": fig1(np.array([t["position_m"] for t in record["test_poses"]]), designs,
                            _fig_m(args.m, available, ()))}
    if "sweep" in record:
        figures["sweep_max_error"] = sweep_figure(sweep_from_record(record), args.log)
    targets = [out / f"{stem}.{fmt}" for stem in figures for fmt in args.format]
    existing = [t for t in targets if t.exists()]
    if existing and not args.force:
        raise OutputError(f"{existing[0]}: exists; add --force to overwrite it (or choose another --out)")
    out.mkdir(parents=True, exist_ok=True)
    for stem, fig in figures.items():
        save_figures(fig, [out / f"{stem}.{fmt}" for fmt in args.format])
    _say(args, "wrote " + ", ".join(str(t) for t in targets))
    return 0


# --------------------------------------------------------------------------- validate

def _validate(args: argparse.Namespace) -> int:
    """``casadi-design validate``: the virtual calibration (:mod:`casadi_design.virtual`)."""
    from .virtual import run

    return run(args)


# --------------------------------------------------------------------------- bound

def _bound(args: argparse.Namespace) -> int:
    from .bound import approximate_designs, bound
    from .sweep import check_m_values

    problem = _load(args, check_solver=False)
    ms = args.m or list(range(problem.m_min, max(problem.m_values) + 1))
    check_m_values(problem, ms)
    approx = approximate_designs(problem, ("test-pose", "D"), args.bound_steps, args.bound_pool)
    print(_case_line(problem))
    print(f"{'m':>4}{'test-pose error >= (mm)':>26}{'relaxation (mm)':>18}{'log det M <=':>15}")
    for m in ms:
        tp, d = bound(problem, m, approx["test-pose"]), bound(problem, m, approx["D"])
        print(f"{m:>4}{tp.value * 1e3:>26.5f}{tp.relaxation * 1e3:>18.5f}{d.value:>15.4f}")
    for a in approx.values():
        _say(args, f"{a.criterion}: {len(a.weights)} support points, pool {a.pool_size}, "
                   f"{len(a.history)} exchange steps, {a.wall_s:.2f} s")
    return 0


# --------------------------------------------------------------------------- parser

def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bars and no per-design lines; tables and errors still print")
    p.add_argument("--verbose", action="store_true",
                   help="show IPOPT's own output for every start (hidden by default)")


def _compute(p: argparse.ArgumentParser, out_help: str) -> None:
    p.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    p.add_argument("--out", metavar="DIR", help=out_help)
    p.add_argument("--force", action="store_true",
                   help="write into --out even if it exists and is not empty (overwrites our files)")
    p.add_argument("--ipopt", type=_ipopt_option, action="append", metavar="KEY=VALUE",
                   help="an IPOPT option over [solver.ipopt] of the problem, e.g. --ipopt "
                        "hessian_approximation=limited-memory (quick trials on large cases); repeatable")
    p.add_argument("--criteria", type=_names, metavar="LIST",
                   help=f"criteria, comma separated, among {', '.join(CRITERIA)} "
                        "(default: [design].criteria of the problem)")
    p.add_argument("--starts", type=_integer("--starts"), metavar="N",
                   help="seeded IPOPT starts per design (default: [solver].starts of the problem)")
    p.add_argument("--jobs", "-j", type=_integer("--jobs"), metavar="N",
                   help=f"local worker processes for the starts (default: the number of CPUs, "
                        f"here {cpu_count()}; 1 = serial in this process). Results do not depend on it")
    p.add_argument("--dask-scheduler", metavar="ADDRESS",
                   help="run the starts on a Dask cluster, e.g. tcp://10.0.0.1:8786 (overrides "
                        "--jobs; needs pip install casadi-design[dask]; start workers with "
                        "--nthreads 1)")
    p.add_argument("--fig-m", type=_m_values, metavar="LIST",
                   help="m of the Fig. 1 panels, e.g. 1,5 (default: [experiments].m of the problem "
                        "when solved, else the first and last m)")
    _bound_steps(p)
    _common(p)


def _bound_steps(p: argparse.ArgumentParser, minimum: int = 0) -> None:
    """``--bound-steps`` (at least ``minimum``; 0 turns the bound off) and ``--bound-pool``."""
    from .bound import BOUND_CRITERIA, BOUND_STEPS, POOL_SIZE, SAMPLE_SIZE

    p.add_argument("--bound-steps", type=_integer("--bound-steps", minimum), default=BOUND_STEPS,
                   metavar="K",
                   help=f"exchange steps of the approximate design behind the certified bound of "
                        f"{', '.join(BOUND_CRITERIA)} and their rounded starts (default {BOUND_STEPS}: "
                        "more steps tighten the bound"
                        + ("; 0: no bound, no rounded starts)" if minimum == 0 else ")"))
    p.add_argument("--bound-pool", type=_integer("--bound-pool"), default=POOL_SIZE, metavar="N",
                   help=f"random feasible experiments in the approximate design's first pool (default "
                        f"{POOL_SIZE}; {SAMPLE_SIZE // POOL_SIZE}x as many are searched for the bound's "
                        "certificate): fewer is faster and looser")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="casadi-design", formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1],
        epilog="Units: lengths and errors in mm for people (tables, CSV plans), SI (m, rad, N) "
               "in the JSON files. `casadi-design COMMAND --help` explains each option.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    solve = sub.add_parser(
        "solve", help="optimal plans for each criterion and m, and how accurate each is",
        description="Design the optimal plans of a problem file for each criterion and number "
                    "of experiments m; print the max error along the test poses (mm, Table 4) and "
                    "solve statistics; with --out write results.json (SI units), fig1.png/pdf, "
                    "plans/<criterion>_m<m>.csv (joint values in deg and rad, load in N, measured "
                    "point in mm) and report.md.")
    _compute(solve, "folder for results.json, fig1.png/pdf, plans/*.csv, report.md (created if missing)")
    solve.add_argument("--m", type=_m_values, metavar="LIST",
                       help="numbers of experiments: 1,5 or a range 1:10 (default: [experiments].m)")
    solve.set_defaults(run=_solve)

    sweep = sub.add_parser(
        "sweep", help="accuracy vs number of experiments m for each criterion",
        description="Solve every (criterion, m) of a range of m with the seeded starts of `solve` "
                    "plus a warm start from the previous m's plan; print max error (mm) vs m with "
                    "the reference 'best single pose repeated m times' (e1/sqrt(m)); with --out "
                    "write sweep.csv/json, sweep_max_error.png/pdf, fig1.png/pdf, plans/*.csv, "
                    "report.md. Each finished design is saved at once in sweep.partial.json: after "
                    "Ctrl-C, run the same command with --resume.")
    _compute(sweep, "folder for sweep.csv/json, figures, plans/*.csv, report.md (created if missing)")
    sweep.add_argument("--m", type=_m_values, metavar="RANGE",
                       help="numbers of experiments: a range first:last[:step], e.g. 1:10, or a "
                            "list 1,2,5 (default: the smallest identifiable m to the largest "
                            "[experiments].m)")
    sweep.add_argument("--log", action="store_true",
                       help="logarithmic axes in sweep_max_error (the repeat line is then straight)")
    sweep.add_argument("--no-warm-start", action="store_true",
                       help="only the seeded starts: every row then equals `solve` exactly")
    sweep.add_argument("--resume", action="store_true",
                       help="continue the interrupted sweep saved in --out (same problem and options)")
    sweep.set_defaults(run=_sweep)

    ev = sub.add_parser(
        "evaluate", help="score your own plan with every measure",
        description="Score a plan given as CSV (one row per experiment) with every measure: max "
                    "and mean error along the test poses (mm), D, A, E, T, condition, O1..O5 (SI "
                    "units of B), and check it against the problem's joint limits, load and "
                    "workspace. Columns: q1_deg or q1_rad ... (or joint names, e.g. joint1_deg; "
                    "prismatic joints _mm or _m), the load fx_N, fy_N ... (mx_Nm ...; optional for "
                    "a fixed load); experiment, x_mm, y_mm, z_mm are ignored, so the plans/*.csv "
                    "files of solve and sweep can be read back.")
    ev.add_argument("problem", help="problem file (TOML) the plan is for")
    ev.add_argument("--plan", required=True, metavar="CSV", help="the plan, one row per experiment")
    ev.add_argument("--compare", metavar="RESULTS",
                    help="results.json or sweep.json (or its folder): add the optimal plans with the "
                         "same m as columns")
    ev.add_argument("--out", metavar="DIR",
                    help="folder for evaluation.json (SI units) and evaluation.png/pdf (error bands)")
    ev.add_argument("--force", action="store_true", help="write into --out even if it is not empty")
    _common(ev)
    ev.set_defaults(run=_evaluate)

    plot = sub.add_parser(
        "plot", help="redraw the figures from results.json or sweep.json",
        description="Redraw fig1 (error bands along the test poses, mm) and, for a sweep, "
                    "sweep_max_error (max error in mm vs m) from a results file, without solving.")
    plot.add_argument("results", help="results.json, sweep.json, or the folder holding one")
    plot.add_argument("--out", metavar="DIR", help="folder for the figures (default: the results' folder)")
    plot.add_argument("--m", type=_m_values, metavar="LIST",
                      help="m of the fig1 panels, e.g. 1,5 (default: the first and last m)")
    plot.add_argument("--log", action="store_true", help="logarithmic axes in sweep_max_error")
    plot.add_argument("--format", type=_formats, default=["png", "pdf"], metavar="LIST",
                      help="file formats, comma separated: png, pdf, svg (default: png,pdf)")
    plot.add_argument("--force", action="store_true", help="overwrite figures that exist")
    _common(plot)
    plot.set_defaults(run=_plot)

    bnd = sub.add_parser(
        "bound", help="certified lower bound of the test-pose error (and upper bound of log det M)",
        description="From the approximate design over single experiments, print per m the "
                    "certified lower bound of the max error along the test poses (mm) that no "
                    "plan of m experiments can beat, the relaxation's value, and the upper bound "
                    "of log det M. No design NLP is solved.")
    bnd.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    bnd.add_argument("--m", type=_m_values, metavar="RANGE",
                     help="numbers of experiments, e.g. 1:10 or 1,5 (default: the smallest "
                          "identifiable m to the largest [experiments].m)")
    _bound_steps(bnd, minimum=1)
    _common(bnd)
    bnd.set_defaults(run=_bound)

    from .virtual import DESCRIPTION, HELP, add_arguments

    val = sub.add_parser("validate", help=HELP, description=DESCRIPTION)
    add_arguments(val)
    val.set_defaults(run=_validate)
    return parser


class ArgumentError(ValueError):
    """A command-line option is wrong (raised instead of argparse's usage block)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse with errors as one line ``error: <command>: <what>; <what to do>``."""

    def error(self, message: str) -> None:
        raise ArgumentError(f"{self.prog}: {message}; see {self.prog} --help")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if threading.current_thread() is threading.main_thread():
        interrupt.install()
    try:
        args = build_parser().parse_args(argv)
        return args.run(args)
    except (ArgumentError, ProblemError, DesignError, OutputError, MissingExtraError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
