"""What every command shares: option types, the output folder, the problem, the study the
arguments ask for, the panels of Fig. 1.

A command handler reads its arguments, calls the package once (:func:`design` turns them into
a :class:`~casadi_design.execution.study.Study` and runs it), prints and writes. Nothing here computes.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from ..errors import OutputError, ProblemError
from ..execution.campaign import Campaign, Settings
from ..execution.study import Study, run_study
from ..execution.sweep import Sweep
from ..measures.criteria import BOUND_CRITERIA, CRITERIA
from ..problem.build import Problem
from ..problem_file.fields import MAX_EXPERIMENTS
from ..problem_file.read import ProblemSpec
from ..records.files import prepare_out
from ..runtime import interrupt
from ..runtime.threads import cpu_count

#: A design's better plans are printed once its starts have run this long (s), or when its
#: approximate design comes after them (a one-start solve): a long design says its best plan
#: so far, a quick one only its result.
BETTER_AFTER_S = 5.0
#: Figure formats ``plot --format`` writes.
FIGURE_FORMATS = ("png", "pdf", "svg")


# --------------------------------------------------------------------------- option types

def integer(what: str, minimum: int = 1):
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


def number(what: str, kind: str, strict: bool = True):
    """An option's finite number ``> 0`` (``strict``) or ``>= 0``; ``kind`` says it for people
    ("a positive number", "a time in s >= 0")."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = math.nan
        if not (math.isfinite(v) and (v > 0 if strict else v >= 0)):
            raise argparse.ArgumentTypeError(f"{what} takes {kind}, got '{text}'")
        return v
    return parse


def parse_m_values(text: str) -> list[int]:
    """``"1:10"`` (inclusive range), ``"1:10:3"`` (with a step) or ``"1,2,5"``; sorted, unique.

    Raises ``ValueError`` with a message for people.
    """
    text = text.strip()
    try:
        if ":" in text:
            parts = [int(p) for p in text.split(":")]
            if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] < 1):
                raise ValueError
            ends = parts[:2]
        else:
            parts = ends = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(
            f"--m takes a range first:last[:step] (e.g. 1:10) or integers separated by commas "
            f"(e.g. 1,2,5), got '{text}'") from None
    if ends and max(ends) > MAX_EXPERIMENTS:  # before a range of that length is made
        raise ValueError(f"--m {max(ends)} is above {MAX_EXPERIMENTS}, the most experiments a plan "
                         f"may have; give fewer, e.g. --m 1:20")
    values = list(range(parts[0], parts[1] + 1, parts[2] if len(parts) == 3 else 1)) if ":" in text else parts
    if not values or any(v < 1 for v in values):
        raise ValueError(f"--m takes positive numbers of experiments, got '{text}'")
    return sorted(set(values))


def m_values(text: str) -> list[int]:
    try:
        return parse_m_values(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def formats(text: str) -> list[str]:
    given = names(text)
    unknown = [f for f in given if f not in FIGURE_FORMATS]
    if unknown or not given:
        raise argparse.ArgumentTypeError(f"unknown figure format '{unknown[0] if unknown else text}'; "
                                         f"allowed: {', '.join(FIGURE_FORMATS)}")
    return given


def ipopt_option(text: str) -> tuple[str, int | float | str]:
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


# --------------------------------------------------------------------------- options

def add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bars and no per-design lines; tables and errors still print")
    p.add_argument("--verbose", action="store_true",
                   help="show IPOPT's own output for every start (hidden by default)")


def add_bound_steps(p: argparse.ArgumentParser, minimum: int = 0) -> None:
    """``--bound-steps`` (at least ``minimum``; 0 turns the bound off) and ``--bound-pool``."""
    from ..optimisation.approximate import BOUND_STEPS, POOL_SIZE, SAMPLE_SIZE

    p.add_argument("--bound-steps", type=integer("--bound-steps", minimum), default=BOUND_STEPS,
                   metavar="K",
                   help=f"exchange steps of the approximate design behind the certified bound of "
                        f"{', '.join(BOUND_CRITERIA)} and their rounded starts (E's and condition's: A's) "
                        f"(default {BOUND_STEPS}: "
                        "more steps tighten the bound"
                        + ("; 0: no bound, no rounded starts)" if minimum == 0 else ")"))
    p.add_argument("--bound-pool", type=integer("--bound-pool"), default=POOL_SIZE, metavar="N",
                   help=f"random feasible experiments in the approximate design's first pool (default "
                        f"{POOL_SIZE}; {SAMPLE_SIZE // POOL_SIZE}x as many are searched for the bound's "
                        "certificate): fewer is faster and looser")


def add_campaign(p: argparse.ArgumentParser, m_help: str, candidates: bool = True):
    """The options of the commands that design plans: what is solved and how (the same
    options give the same plans in every command); ``candidates``: ``--candidates`` too (a
    sweep designs freely). Returns where an option that excludes ``--candidates`` goes (its
    mutually exclusive group; ``p`` without it)."""
    choice = p.add_mutually_exclusive_group() if candidates else p
    p.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    p.add_argument("--m", type=m_values, metavar="LIST", help=m_help)
    p.add_argument("--ipopt", type=ipopt_option, action="append", metavar="KEY=VALUE",
                   help="an IPOPT option over [solver.ipopt] of the problem, e.g. --ipopt "
                        "hessian_approximation=limited-memory (quick trials on large cases); repeatable")
    p.add_argument("--criteria", type=names, metavar="LIST",
                   help=f"criteria, comma separated, among {', '.join(CRITERIA)} "
                        "(default: [design].criteria of the problem)")
    p.add_argument("--starts", type=integer("--starts"), metavar="N",
                   help="seeded IPOPT starts per design (default: [solver].starts of the problem)")
    if candidates:
        choice.add_argument("--candidates", metavar="CSV", action="append",
                       help="choose each plan's experiments from these postures (a plan or measurement CSV: its "
                            "joint and load columns), by exchange from a greedy plan, the pool's approximate "
                            "design and --starts random choices; the bound is the pool's. An artefact's "
                            "recordings: a placement's folder or a CSV, repeatable (one per placement)")
    add_held(p)
    add_workers(p)
    add_bound_steps(p)
    add_common(p)
    return choice


def add_target(p: argparse.ArgumentParser | argparse._MutuallyExclusiveGroup, sweep: bool = False) -> None:
    """``--target-mm``: the tolerance whose smallest m is searched (solve; ``p``: the group of
    :func:`add_campaign`, as it excludes ``--candidates``) or read (sweep)."""
    from ..execution.target import LIMIT_FACTOR

    p.add_argument("--target-mm", type=number("--target-mm", "a positive number of mm"), metavar="T",
                   help="the max error along the test poses to reach, mm: "
                        + ("say the smallest m of the sweep whose test-pose plan reaches it" if sweep else
                           "design test-pose plans for the smallest m that reaches it (searched from the "
                           f"smallest identifiable m to the last of --m, default {LIMIT_FACTOR}x the "
                           "largest [experiments].m), and say whether m - 1 is excluded by the bound"))


def add_held(p: argparse.ArgumentParser) -> None:
    """``--measured`` and ``--prior``: what is known before the plan (a second round)."""
    p.add_argument("--measured", action="append", metavar="CSV",
                   help="experiments already measured (a plan or measurement CSV: its joint and load "
                        "columns): their information is added to every plan's, --m counts the new "
                        "experiments; repeatable")
    p.add_argument("--prior", metavar="JSON",
                   help="an earlier identification (DIR/identification.json of casadi-design identify): "
                        "the inverse of its covariance is added to every plan's information (give "
                        "DIR/calibrated.toml as the problem to design at the identified robot)")


def add_workers(p: argparse.ArgumentParser) -> None:
    """``--jobs`` and ``--dask-scheduler``: where the starts and approximate designs run."""
    p.add_argument("--jobs", "-j", type=integer("--jobs"), metavar="N",
                   help=f"local worker processes for the starts and approximate designs (default: the "
                        f"number of CPUs, here {cpu_count()}; 1 = serial in this process). Results do "
                        "not depend on it")
    p.add_argument("--dask-scheduler", metavar="ADDRESS",
                   help="run them on a Dask cluster, e.g. tcp://10.0.0.1:8786 (overrides "
                        "--jobs; needs pip install casadi-design[dask]; start workers with "
                        "--nthreads 1)")


def add_output(p: argparse.ArgumentParser, out_help: str) -> None:
    p.add_argument("--out", metavar="DIR", help=out_help)
    p.add_argument("--force", action="store_true",
                   help="write into --out even if it exists and is not empty (overwrites our files)")
    p.add_argument("--fig-m", type=m_values, metavar="LIST",
                   help="m of the Fig. 1 panels, e.g. 1,5 (default: [experiments].m of the problem "
                        "when solved, else the first and last m)")


# --------------------------------------------------------------------------- the problem and its campaign

def count(n: int, word: str, plural: str | None = None) -> str:
    """``n`` and ``word`` for people: "1 design", "2 designs" (``plural``: an irregular one)."""
    return f"{n} {word if n == 1 else plural or word + 's'}"


def say(args: argparse.Namespace, *lines: str) -> None:
    if not args.quiet:
        print(*lines, sep="\n")


def read_spec(args: argparse.Namespace, artefact: bool = False) -> ProblemSpec:
    """Read and check the problem file of ``args`` (:func:`casadi_design.problem_file.read.read_problem`,
    no robot built yet), with the ``--ipopt`` options over its [solver.ipopt]. A command that
    starts worker processes reads it first, so a malformed file fails before any worker starts.

    Raises
    ------
    ProblemError
        A problem measured at an artefact's points (``[measurement.artefact]``) for a command
        that does not handle them (not ``artefact``): its plans would be a tracker's."""
    from ..problem_file.read import read_problem

    spec = read_problem(args.problem)
    if spec.measurement.artefact is not None and not artefact:
        raise ProblemError(f"{spec.path}: [measurement.artefact]: this command does not handle an artefact's points "
                           "yet (its plans would be a tracker's); solve --candidates DIR chooses which recordings to "
                           "use and identify identifies the robot from them (docs/ball-socket.md)")
    if getattr(args, "ipopt", None):
        options = {**dict(spec.solver.ipopt), **dict(args.ipopt)}
        spec = replace(spec, solver=replace(spec.solver, ipopt=tuple(sorted(options.items()))))
    return spec


def load(args: argparse.Namespace, check_solver: bool = True, spec: ProblemSpec | None = None) -> Problem:
    """Build the problem of ``args`` (``spec``: as :func:`read_spec` read it; None: read it
    now) with what ``--measured`` and ``--prior`` hold (:mod:`casadi_design.identification.held`);
    with ``check_solver``, also try the IPOPT options."""
    from ..identification.held import read_held
    from ..optimisation.solve import check_ipopt_options
    from ..problem.build import build_problem

    spec = read_spec(args) if spec is None else spec
    problem = build_problem(spec)
    held = read_held(problem, getattr(args, "measured", None), getattr(args, "prior", None))
    if held is not None:
        problem = build_problem(replace(spec, held=held))
    interrupt.check()  # a Ctrl-C that CasADi's argument conversion swallowed while building
    if check_solver:
        check_ipopt_options(problem)
    return problem


def executor(args: argparse.Namespace):
    """The executor of ``--jobs`` / ``--dask-scheduler`` (a context manager)."""
    from ..execution.parallel import make_executor

    return make_executor(args.jobs, args.dask_scheduler)


def case_line(problem: Problem, quiet: bool = False) -> str:
    """The case for people: what is calibrated, the test poses, sigma and the seed, the base
    set (``quiet``: its first line only, not what each parameter left out acts as) and what is
    held before the plan."""
    line = (f"{problem.name}: {problem.model.case} calibration of "
            f"{', '.join(problem.model.parameter_names)}; {problem.test_poses.s} test poses; "
            f"sigma = {problem.sigma_m * 1e3:g} mm; seed {problem.solver.seed}")
    if problem.base_set is not None:
        report = problem.base_set.report()
        line += "\n" + (report.splitlines()[0] if quiet else report)
    line = line if problem.M_held is None else line + "\n" + held_line(problem)
    return line if problem.field is None else line + "\n" + field_line(problem)


def field_line(problem: Problem) -> str:
    """The field of unmodelled error the test-pose and I designs hold, for people."""
    f, (Qh, _) = problem.field, problem.field_held
    source = ("[calibration.model_error]" if problem.spec.calibration.model_error is not None
              else f"the field of {problem.spec.held.prior_file}")
    return (f"model error: test-pose and I weigh the robot's unmodelled error, {source}: {f.describe()}"
            + (f", correlated with the {len(Qh)} poses measured before" if len(Qh) else "")
            + "; their sqrt(rho) is the error after compensation with the field (kriging), no bound: "
            "its experiments are not independent")


def held_line(problem: Problem) -> str:
    """What the designs hold before their plans, for people."""
    held, what = problem.spec.held, []
    if problem.m_held:
        what.append(f"{problem.m_held} experiment{'s' if problem.m_held > 1 else ''} measured "
                    f"({', '.join(held.measured_files)})")
    if held is not None and held.prior_covariance is not None:
        what.append(f"the prior of {held.prior_file} on {len(held.prior_names)} parameters")
    if problem.spec.calibration.prior is not None:
        what.append("the problem's [calibration.prior]")
    return (f"held before the plan: {' and '.join(what)}; m counts the new experiments and the errors "
            f"are the whole campaign's (smallest m: {problem.m_min})")


def study(args: argparse.Namespace, problem: Problem, partial: Path | None = None,
          sweep: bool = False) -> Study:
    """The :class:`~casadi_design.execution.study.Study` the arguments ask for: criteria, m values and
    settings (defaults: the problem file's; a ``sweep``: every m from the smallest identifiable
    to the largest of the file), where the starts run, where the designs are kept
    (``partial``) and whether to resume."""
    from ..execution.target import TARGET_CRITERION, default_limit

    target = getattr(args, "target_mm", None)
    criteria = tuple(args.criteria or ((TARGET_CRITERION,) if target and not sweep else problem.criteria))
    default_m = (range(problem.m_min, max(problem.m_values) + 1) if sweep else
                 range(problem.m_min, default_limit(problem) + 1) if target else sorted(problem.m_values))
    settings = Settings.of(problem, args.starts, bound_steps=args.bound_steps, bound_pool=args.bound_pool,
                           verbose=args.verbose)
    candidates = getattr(args, "candidates", None)
    if candidates and len(candidates) > 1:
        raise ProblemError(f"--candidates is given {len(candidates)} times; give one CSV of postures (join them into "
                           "one file)")
    pool = None if candidates is None else _kept_pool(args, problem, candidates[0])
    return Study(problem, criteria, tuple(args.m or default_m), settings, sweep,
                 not getattr(args, "no_warm_start", False), args.jobs, args.dask_scheduler, partial,
                 getattr(args, "resume", False), None if target is None else target * 1e-3, pool)


def _kept_pool(args: argparse.Namespace, problem: Problem, path: str) -> tuple:
    """The postures of ``--candidates`` a plan may use (:func:`casadi_design.optimisation.pool.kept_postures`),
    with notes on the repeats taken once and the postures left out (why the first)."""
    from ..identification.measurements import read_experiments
    from ..optimisation.pool import kept_postures

    Q, F, _ = read_experiments(problem, path, ignore_unknown=True)
    kept, repeats, why = kept_postures(problem, Q, F)
    say(args, f"--candidates {path}: {count(len(Q), 'posture')}, {int(kept.sum())} kept for the plans")
    if repeats:
        say(args, f"note: --candidates {path}: {count(repeats, 'repeated posture')} taken once (a plan measures "
                  "each posture at most once)")
    if why:
        say(args, f"note: --candidates {path}: {len(why)} of its {len(Q) - repeats} postures break the problem's rules "
                  f"and are left out ({why[0]}{'; ...' if len(why) > 1 else ''})")
    return Q[kept], F[kept]


def say_approximate(args: argparse.Namespace, approx: dict) -> None:
    """A line saying how long each approximate design took (on a worker, beside the starts),
    and which were read back from the disk instead (:func:`casadi_design.execution.campaign.computed`)."""
    if approx:
        names = {w: c + (f" (m = {m})" if m else "") for w in approx for c, m in [w]}
        kept = [names[w] for w, a in approx.items() if a.kept]
        say(args, f"approximate designs of {', '.join(names.values())}: "
                  f"{', '.join(f'{a.wall_s:.1f}' for a in approx.values())} s "
                  f"({', '.join(count(len(a.history), 'exchange step') for a in approx.values())})"
                  + (f"; {', '.join(kept)} read back from the cache (the times are of the run "
                     "that computed them)" if kept else ""))


def output_folder(args: argparse.Namespace, command: str, resume_files: tuple[str, ...] = ()) -> Path | None:
    """``--out`` checked before any work (:func:`casadi_design.records.files.prepare_out`; None
    without it); ``--resume`` needs it and one of ``resume_files`` in it."""
    resume = getattr(args, "resume", False)
    if resume and args.out is None:
        raise OutputError(f"--resume needs the --out folder of the interrupted {command}; add --out DIR")
    return None if args.out is None else prepare_out(args.out, args.force, resume, resume_files)


def design(args: argparse.Namespace, label: str, partial: Path | None = None,
           sweep: bool = False, check: Callable[[Problem], object] | None = None,
           ) -> tuple[Study, Campaign | Sweep, list[int]]:
    """Load the problem of ``args`` and run its study (:func:`casadi_design.execution.study.run_study`)
    with a progress bar; worker processes start while the robot and cell build. With
    ``partial``, each finished design is saved there at once and ``--resume`` continues from it;
    ``check(problem)`` refuses what the command would write from the plans before anything is
    solved. Returns the study, its designs and the m of the Fig. 1 panels (``--fig-m``, checked
    before anything is solved)."""
    from ..runtime.progress import progress_bar

    spec = read_spec(args)  # a malformed file fails before any worker starts
    with executor(args) as ex:
        problem = load(args, spec=spec)
        if check is not None:
            check(problem)
        request = study(args, problem, partial, sweep)
        panels = (None if request.searches else
                  fig_m(getattr(args, "fig_m", None), list(request.m_values), problem.m_values))
        if sweep:
            say(args, f"sweep of {count(request.designs, 'design')} ({count(len(request.criteria), 'criterion', 'criteria')} x "
                      f"{len(request.m_values)} values of m, {request.m_values[0]} to {request.m_values[-1]})")
        with progress_bar(request.starts, label, args.quiet) as bar:
            result = run_study(
                request, progress=bar.update, executor=ex,
                on_design=lambda d: bar.set_postfix_str(f"done: {d.criterion}, m = {d.m}"),
                on_better=lambda i: (bar.write(i.line(), file=sys.stderr)
                                     if not args.quiet and (i.elapsed_s >= BETTER_AFTER_S or i.later) else None,
                                     bar.set_postfix_str(f"running: {', '.join(i.running)}" if i.running else "")),
                on_resume=lambda n: say(args, f"resuming: {n} of {request.designs} designs already in "
                                              f"{partial.parent}"))
    say_approximate(args, result.approx)
    if panels is None:  # a search: the m it designed are known now
        panels = fig_m(getattr(args, "fig_m", None), sorted({m for _, m in result.designs}), problem.m_values)
    return request, result, panels


# --------------------------------------------------------------------------- figures

def fig_m(requested: list[int] | None, available: list[int], preferred: tuple[int, ...],
          option: str = "--fig-m") -> list[int]:
    """m values of the Fig. 1 panels: requested (by ``option``), else the problem's m that
    were solved, else the first and last m (at most two panels by default)."""
    if requested:
        missing = [m for m in requested if m not in available]
        if missing:
            raise OutputError(f"{option} {missing[0]} was not solved; choose among {available}")
        return requested
    chosen = [m for m in preferred if m in available][:2]
    return chosen or sorted({available[0], available[-1]})


def seated_designs(problem: Problem, path: str, option: str) -> list:
    """The designs of a results.json or sweep.json (or its folder) that ``solve`` or ``sweep``
    wrote for ``problem``, a problem measured at an artefact's points: each with its
    experiments' points and placements (:attr:`~casadi_design.plan.design.Design.seated`).

    Raises
    ------
    ProblemError
        An unreadable file, another problem's results, or designs without their points.
    """
    from ..records.files import read_results
    from ..records.results import design_from_record

    try:
        record = read_results(Path(path))
    except OutputError as exc:
        raise ProblemError(f"{option}: {exc}") from None
    designs = [design_from_record(d) for d in record["designs"]]
    if record.get("problem") != problem.name or any(d.seated is None for d in designs):
        why = (f"they are the results of problem {record.get('problem')}"
               if record.get("problem") != problem.name else "its experiments carry no artefact's point and placement")
        raise ProblemError(f"{option}: {record['_path']} is not the results of casadi-design solve {problem.path} "
                           f"({why}); solve this problem first")
    return designs
