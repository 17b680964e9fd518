"""``casadi-design program``: a plan as a robot program, in the order that saves time, with
moves checked against the cell."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from ..errors import DesignError, ProblemError
from ..records.files import write_atomic
from . import common

HELP = "order a plan, check its moves against the cell and write a robot program"
DESCRIPTION = ("Order the experiments of a plan CSV to save time (load changes first, then the time of "
               "synchronous joint moves from and back to home), check every move against the cell along its "
               "whole path (capsule rows, the meshes where they come closest, the tracker's beam), give "
               "blocked moves via points, and write the program: URScript (program.script), ABB RAPID "
               "(program.mod), KUKA KRL (program.src), the ROS robot_calibration poses YAML (program.yaml) "
               "or a JSON joint trajectory (program.json), and viewer.html (the route in the cell).")
#: Measuring time per experiment (s) when not given: the tracker settles and averages.
MEASURE_S = 3.0


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..program.formats import FILES

    p = sub.add_parser("program", help=HELP, description=DESCRIPTION)
    p.add_argument("problem", help="problem file (TOML) the plan is for")
    p.add_argument("--plan", required=True, metavar="CSV", help="the plan, one row per experiment (as for evaluate)")
    p.add_argument("--format", required=True, metavar="FORMAT", help=f"one of {', '.join(FILES)}")
    p.add_argument("--home", metavar="DEG,...",
                   help="home pose, one joint value per joint in deg (mm for prismatic joints); default: the test "
                        "poses' seed_q_deg, else the middle of the joint limits")
    p.add_argument("--measure-s", type=common.number("--measure-s", "a time in s >= 0", strict=False), default=MEASURE_S, metavar="S",
                   help=f"measuring time per experiment, s (default {MEASURE_S:g})")
    p.add_argument("--out", metavar="DIR", help="folder for the program file and viewer.html (created if missing)")
    p.add_argument("--force", action="store_true", help="write into --out even if it is not empty")
    common.add_common(p)
    p.set_defaults(run=run)


def home_pose(problem, text: str | None) -> np.ndarray:
    """The home pose (n,), rad: ``--home`` (deg, mm) or the default of ``--help``, checked
    (inside the limits, clear of the cell: :func:`~casadi_design.program.moves.pose_problems`)."""
    from ..program.moves import pose_problems
    from ..records.export import joint_scales

    n = problem.robot.n
    if text is None:
        seed = problem.spec.test_poses.seed_q_rad
        home = np.array(seed) if seed is not None else problem.rules.limits.middle
    else:
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            values = []
        if len(values) != n or not all(map(math.isfinite, values)):
            raise ProblemError(f"--home: '{text}' is not {n} joint values; give one value in deg (mm for prismatic "
                               f"joints) per joint of the chain ({', '.join(problem.robot.joints)}), e.g. --home "
                               + ",".join(["0"] * n))
        home = np.array(values) * joint_scales(problem)
    why = pose_problems(problem, home)
    if why:
        raise ProblemError(f"--home: {why}; give a home pose inside the limits and clear of the cell" if text else
                           f"the default home ([test_poses].seed_q_deg, else the middle of the limits): {why}; give "
                           "a home pose inside the limits and clear of the cell with --home")
    return home


def run(args: argparse.Namespace) -> int:
    from ..identification.measurements import read_experiments
    from ..program.formats import FILES, check_format, program_text
    from ..program.sequence import make_program

    out = common.output_folder(args, "program")
    problem = common.load(args, check_solver=False, spec=common.read_spec(args, artefact=True))
    notes = []  # said once the program is made: nothing is printed before an error
    if problem.artefact is not None:  # seated configurations: the program visits their approaches
        from ..identification.recordings import read_recordings
        from ..plan.seated import APPROACH_M, approaches

        plan = read_recordings(problem, [args.plan], "--plan")
        Q = approaches(problem, plan.Q)
        F = np.zeros((len(Q), problem.model.nF))
        steps = [f"hand-guide the ball into point {k} of the tool at {plan.names[g]!r} (the plan's configuration), "
                 "record the joints, then continue" for k, g in zip(plan.point, plan.placement)]
        notes.append(f"note: each experiment is programmed {APPROACH_M * 1e3:g} mm back along the hand's axis from "
                     "its seated configuration; the program stops there for the operator to hand-guide the ball into "
                     "its socket and record, then comes back out")
    else:
        steps = None
        Q, F, plan = read_experiments(problem, args.plan)  # a plan of another robot names the plan
        new = ~plan.measured  # a campaign's measured experiments are not measured again
        Q, F = Q[new], F[new]
    robot = problem.robot
    past = int(np.sum((Q < robot.q_min) | (Q > robot.q_max)))  # within the reading's tolerance
    if past:  # a controller refuses a target past a limit, however little
        Q = np.clip(Q, robot.q_min, robot.q_max)
        notes.append(f"note: {common.count(past, 'joint value')} of the plan past {'their' if past > 1 else 'its'} "
                     "limit (within the reading's tolerance) programmed at the limit")
    check_format(problem, args.format)  # after the plan: a plan of another robot is the first thing to say
    home = home_pose(problem, args.home)
    t0 = time.perf_counter()
    program = make_program(problem, Q, F, home, args.measure_s, steps)
    text = program_text(problem, program, args.format, str(args.plan))
    wall = time.perf_counter() - t0
    if notes:
        common.say(args, *notes)
    print(report(problem, program, args.plan))
    common.say(args, f"ordered, checked and written in {wall:.2f} s")
    if out:
        from ..reports.viewer import write_program_viewer

        write_atomic(out / FILES[args.format], text.encode())
        shown = write_program_viewer(out, problem, Q, F, program, str(args.plan))  # the route in the cell
        common.say(args, f"wrote {out / FILES[args.format]}, {out / shown[0]}")
    return 0


def report(problem, program, plan: str | Path) -> str:
    """The order, the times and every move's time, via points, clearances and beam, for people."""
    m = len(program.order)
    moving = program.time_s - m * program.measure_s
    lines = [f"plan {plan}: {m} experiments; joint speeds: {program.times.source}",
             f"order: {', '.join(map(str, program.order))}",
             (f"time {program.time_s:.1f} s ({moving:.1f} s of moves, {m} x {program.measure_s:g} s measuring); "
             f"file order {program.file_time_s:.1f} s (as straight moves {program.file_straight_s:.1f} s"
             + ("" if problem.cell is None else f", but {program.file_blocked} of its {m + 1} moves break the clearance"
                if program.file_blocked else ", all clear") + ")"),
             f"load changes: {program.load_changes} (file order {program.file_load_changes})"]
    if problem.cell is None:
        return "\n".join(lines + ["no [cell]: the moves are not checked for collisions"])
    lines.append(f"{'move':<32}{'time_s':>8}{'vias':>6}{'clearance_mm':>14}{'mesh_mm':>9}  beam")
    names = ["home", *(f"experiment {k}" for k in program.order), "home"]
    for a, b, path in zip(names[:-1], names[1:], program.paths):
        lines.append(f"{a + ' -> ' + b:<32}{path.time_s:>8.2f}{path.vias:>6}{path.clearance_m * 1e3:>14.1f}"
                     f"{path.mesh_m * 1e3:>9.1f}  {'broken: ' + path.beam if path.beam else 'kept'}")
    lines.append(f"clearance: capsules along the whole move (at least half the cell's "
                 f"{problem.cell.spec.clearance_m * 1e3:g} mm between samples), meshes at the closest samples")
    return "\n".join(lines)


def write_programs(out: Path, problem, designs, fmt: str, programs: dict | None = None) -> list[str]:
    """Each design's plan as ``out/programs/<criterion>_m<m>.<ext>`` in format ``fmt``, from
    the default home with the default measuring time; returns the file names (``programs``:
    filled with each (criterion, m)'s program, for the viewer)."""
    from ..program.formats import FILES, check_format, program_text
    from ..program.sequence import make_program

    check_format(problem, fmt)
    names = []
    for d in designs:
        name = f"programs/{d.criterion}_m{d.m}{Path(FILES[fmt]).suffix}"
        try:
            program = make_program(problem, d.Q, d.F, home_pose(problem, None), MEASURE_S)
        except (ProblemError, DesignError) as exc:  # a pose or load it cannot run, a pose it cannot reach
            raise DesignError(f"{exc} (the {d.criterion} plan of m = {d.m}); the results and plans are written "
                              f"in {out}: casadi-design program takes plans/{d.criterion}_m{d.m}.csv with another "
                              "--home") from None
        write_atomic(out / name, program_text(problem, program, fmt, f"plans/{d.criterion}_m{d.m}.csv", name).encode())
        names.append(name)
        if programs is not None:
            programs[d.criterion, d.m] = program
    return names
