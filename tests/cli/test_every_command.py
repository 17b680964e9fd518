"""Every subcommand on every file in problems/, with tiny settings: exit code 0 and nothing on
stderr; a bug raises out of main(), and the command as a process of its own (``python -m
casadi_design``, where a bug's traceback would reach stderr) runs clean.

Tiny settings (identify: the solved plan measured on the nominal robot; program: its first
experiments; validate: two trials): the D criterion, one start, IPOPT with a limited-memory
Hessian, the smallest m, one exchange step of the approximate design on 12 candidates in the
bound command (none in solve and sweep); the sweep runs a range that does not start at the
smallest m. The bound command is a test of its own (on the 6-axis cells it is the longest
command: the ABB's runs with the slow tests).
"""

import json
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.cli import main
from casadi_design.execution.campaign import approximate_designs
from casadi_design.identification.fit import model_points
from casadi_design.calibrated.urdf import MEASURED_POINT
from casadi_design.measures.measures import information_matrix
from casadi_design.optimisation.bound import bound
from casadi_design.optimisation.seated_nlp import SEATED_TOL_M
from casadi_design.plan.rules import FEASIBILITY_TOL
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_robot, load_problem
from casadi_design.problem_file.read import read_problem
from casadi_design.records.export import read_plan_table
from casadi_design.reports.viewer import read_viewer_data
from casadi_design.robot.robots import frame_placement, make_robot
from tests.conftest import PAPER, PROBLEM_FILES, ROOT
from tests.identify_data import measurement_csv

#: Criterion of the tiny runs: cheap on every problem; an IPOPT option through --ipopt (a
#: limited-memory Hessian: as fast as the exact one here, and it exercises the pass-through).
CRITERION = "D"
QUICK = "hessian_approximation=limited-memory"
#: One exchange step of the approximate design on a pool of POOL candidates (the UR10 and ABB
#: identify their 27 and 30 parameters with it; the polish searches from every candidate: the
#: UR10's bound command takes 5.6 s in the virtual machine instead of 9.5 s with 30).
POOL = 12
BOUND = ["--bound-steps", "1", "--bound-pool", str(POOL), "--jobs", "1"]
NO_BOUND = ["--bound-steps", "0"]
#: Virtual calibrations of validate (each a nonlinear identification: half a second for the ABB; the
#: statistics of a few trials are tested in tests/virtual/test_validate.py).
TRIALS = 2
#: Experiments of the solved plan the robot program visits (a program's cost grows with its
#: moves: 9 experiments of the UR10 take 8 s in the virtual machine, 3 take 5 s, 2 take 2.5 s).
PROGRAM_EXPERIMENTS = 2


def _on_one_worker(path, *marks):
    """The runs of one problem file in this module on one test worker (``--dist loadgroup``):
    the second reuses what the first built and kept in the process (the problem, its CasADi
    functions, a Panda's seated configurations: about a second each)."""
    return pytest.param(path, marks=[pytest.mark.xdist_group(f"every_command_{path.stem}"), *marks], id=path.stem)


@pytest.mark.parametrize("path", [_on_one_worker(p) for p in PROBLEM_FILES])
def test_every_subcommand_runs_on_every_problem(path, tmp_path, capsys):
    problem = load_problem(path)
    m = problem.m_min
    tiny = ["--starts", "1", "--jobs", "1", "--criteria", CRITERION, "--quiet", "--ipopt", QUICK]
    solved, swept = tmp_path / "solve", tmp_path / "sweep"

    assert main(["solve", str(path), "--m", str(m), *tiny, *NO_BOUND, "--out", str(solved)]) == 0
    assert main(["sweep", str(path), "--m", f"{m + 1}:{m + 1}", *tiny, *NO_BOUND,
                 "--out", str(swept)]) == 0
    plan = solved / "plans" / f"{CRITERION}_m{m}.csv"
    assert main(["evaluate", str(path), "--plan", str(plan), "--moves", "--quiet"]) == 0
    assert main(["evaluate", str(path), "--plan", str(plan), "--compare", str(solved),
                 "--out", str(tmp_path / "evaluate"), "--quiet"]) == 0
    assert main(["validate", str(path), "--results", str(solved / "results.json"), "--trials", str(TRIALS),
                 "--out", str(tmp_path / "validate")]) == 0
    assert main(["plot", str(swept), "--out", str(tmp_path / "figures"), "--format", "png"]) == 0
    if problem.artefact is not None:  # recordings: the plan CSV itself (its rows seated by the nominal robot)
        assert main(["identify", str(path), "--measurements", str(plan), "--model", "identifiable",
                     "--out", str(tmp_path / "identify"), "--quiet"]) == 0
        # a second round is refused in one line (its held recordings are not built for an artefact)
        assert main(["solve", str(path), "--m", "1", *tiny, "--measured", str(plan), "--prior",
                     str(tmp_path / "identify" / "identification.json")]) == 2
        assert "a second round" in capsys.readouterr().err
    else:
        measured = tmp_path / "measured.csv"  # the solved plan measured on the nominal robot, base frame
        Q, F, _, _ = read_plan_table(problem, plan)
        P = model_points(problem.model, Q, F, np.zeros(problem.model.L))
        hidden = ((0, 1),) if P.shape[1] > 1 else ()  # a marker the tracker did not see
        measured.write_text(measurement_csv(problem, Q, F, P + 1e-6 * np.random.default_rng(0).standard_normal(P.shape),
                                            hidden))
        assert main(["identify", str(path), "--measurements", str(measured), "--frame", "base",
                     "--model", "identifiable",  # auto's candidates: tests/identification
                     "--out", str(tmp_path / "identify")]) == 0
        # the second round: the plan measured, the identification as a prior, one more experiment
        second = tmp_path / "second"
        held = ["--measured", str(plan), "--prior", str(tmp_path / "identify" / "identification.json")]
        assert main(["solve", str(path), "--m", "1", *tiny, *NO_BOUND, *held, "--out", str(second)]) == 0
        campaign = second / "plans" / f"{CRITERION}_m1.csv"
        assert main(["evaluate", str(path), "--plan", str(campaign), *held, "--quiet"]) == 0
        assert main(["validate", str(path), "--results", str(second / "results.json"), "--trials", "2", *held,
                     "--quiet"]) == 0
    rows = [line for line in plan.read_text().splitlines() if not line.startswith("#")]
    first = tmp_path / "first.csv"  # the program of the plan's first PROGRAM_EXPERIMENTS experiments
    first.write_text("\n".join(rows[:1 + PROGRAM_EXPERIMENTS]) + "\n")
    assert main(["program", str(path), "--plan", str(first), "--format", "json", "--measure-s", "1",
                 "--out", str(tmp_path / "program"), "--quiet"]) == 0
    # main() returns 2 after one line "error: ..." on stderr and raises on a bug (its traceback
    # is the report, test_a_bug_raises_and_the_command_as_a_process_runs_clean): the codes above
    # and an empty stderr are what no error looks like
    assert capsys.readouterr().err == ""

    design = json.loads((solved / "results.json").read_text())["designs"][0]
    report = (solved / "report.md").read_text()  # the one page a person reads: the plan and its figure of results.json
    assert f"### {CRITERION} plan, m = {m}: max error {design['max_rms_error_m'] * 1e3:.4f} mm" in report
    assert ("| placement_name |" in report) == (problem.artefact is not None)
    if problem.artefact is not None:  # each experiment seated at a point of a placement of the problem file
        names = [p.name for p in problem.spec.measurement.artefact.placements]
        assert all(e["point"] in (0, 1) and e["placement"] in names for e in design["experiments"])
    evaluation = json.loads((tmp_path / "evaluate" / "evaluation.json").read_text())
    assert evaluation["violations"] == []  # an optimal plan obeys every rule of its problem
    if problem.cell is not None:  # ... and keeps the clearance on the real geometry
        assert all(e["clearance_m"] >= problem.cell.spec.clearance_m - FEASIBILITY_TOL for e in design["experiments"])
        assert [e["clearance_m"] for e in evaluation["experiments"]] == [e["clearance_m"] for e in design["experiments"]]
    assert (tmp_path / "figures" / "sweep_max_error.png").stat().st_size > 0
    for folder in (solved, tmp_path / "figures", tmp_path / "program", tmp_path / "identify",
                   *([second] if problem.artefact is None else [])):
        assert (folder / "viewer.html").stat().st_size > 0  # tests/reports/test_viewer.py opens them
        # the measured point named as what it is, in the legend and the pose's panel, and each pose's load
        data = read_viewer_data(folder / "viewer.html")
        assert data["point"] == ("reflector" if problem.artefact is None else "ball centre")
        assert all(p["load_text"] for v in data["views"] for p in v["poses"])
    assert json.loads((tmp_path / "validate" / "validation.json").read_text())["trials"] == TRIALS
    identified = json.loads((tmp_path / "identify" / "identification.json").read_text())
    assert (tmp_path / "identify" / "calibrated.urdf").stat().st_size > 0
    # the nominal robot's own plan: nothing left to fit (an artefact's recordings: the seating the NLP holds to;
    # a tracker's: its noise)
    assert identified["residual_rms_m"] < (SEATED_TOL_M if problem.artefact is not None else 1e-5)
    if problem.spec.robot.source == "dh":  # the calibrated table reads and is calibrated.urdf's robot
        table = build_robot(read_problem(tmp_path / "identify" / "calibrated_dh.toml").robot)
        urdf = make_robot(pin.buildModelFromUrdf(str(tmp_path / "identify" / "calibrated.urdf")), MEASURED_POINT)
        for q in Q:
            assert np.abs(frame_placement(table, q).homogeneous - frame_placement(urdf, q).homogeneous).max() < 1e-9
    if problem.artefact is None:
        again = json.loads((second / "results.json").read_text())["designs"][0]
        assert [e.get("measured", False) for e in again["experiments"]] == [True] * m + [False]
    program = json.loads((tmp_path / "program" / "program.json").read_text())
    assert sorted(p["experiment"] for p in program["points"] if p["experiment"]) == \
        list(range(1, min(m, PROGRAM_EXPERIMENTS) + 1))
    if problem.artefact is not None:  # the program stops at each approach for the ball to be seated by hand,
        points = program["points"]    # then comes back out to it: the moves checked start there
        for p, after in zip(points, points[1:]):
            if p["kind"] == "experiment":
                e = design["experiments"][p["experiment"] - 1]
                assert f"hand-guide the ball into point {e['point']} of the tool at '{e['placement']}'" in p["stop_before"]
                assert after["kind"] == "via" and after["positions"] == p["positions"]


#: The bound command's runs: the ABB's (7 s, the longest of its kind) with the slow tests; the
#: UR10 runs the same path of a 6-axis arm in a cell (capsule rows in the searches) by default.
BOUND_RUNS = [_on_one_worker(p, *([pytest.mark.slow] if p.stem == "abb_irb6640_machining" else []))
              for p in PROBLEM_FILES]


@pytest.mark.parametrize("path", BOUND_RUNS)
def test_the_bound_command_runs_on_every_problem(path, capsys):
    problem = load_problem(path)
    m = problem.m_min
    assert main(["bound", str(path), "--m", f"{m}:{m + 1}", *BOUND, "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert err == ""  # (main() raises on a bug, and returns 2 after an "error: ..." line)
    assert len([line for line in out.splitlines() if line.split()[:1] in ([str(m)], [str(m + 1)])]) == 2
    approx = approximate_designs(problem, [("D", 0)], 1, POOL)  # those of the bound command (kept in this process)
    Q, F = random_plan(problem, m, np.random.default_rng(0))  # a feasible plan: its log det M is below the bound
    assert bound(problem, m, approx["D", 0]).value >= np.linalg.slogdet(information_matrix(problem.model.B_stack(Q, F)))[1]


def test_a_bug_raises_and_the_command_as_a_process_runs_clean(tmp_path, monkeypatch, capsys):
    """A bug is not an input error: main() raises it (no "error: ..." line, no code 2). The
    command run as a process (``python -m casadi_design``: the launch, then main), where a
    bug's traceback would go to stderr, exits 0 with nothing on stderr and prints what main()
    prints."""
    import casadi_design.cli.evaluate as evaluate

    plan = tmp_path / "plan.csv"
    plan.write_text("q1_deg,q2_deg,fx_N,fy_N\n0,90,0,100\n90,-90,100,0\n45,-120,-60,80\n")
    argv = ["evaluate", str(PAPER), "--plan", str(plan)]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert err == "" and "max" in out

    def broken(args):
        raise ZeroDivisionError("a bug in the command")

    with monkeypatch.context() as patch:
        patch.setattr(evaluate, "run", broken)
        with pytest.raises(ZeroDivisionError, match="a bug in the command"):
            main(argv)
    assert capsys.readouterr().err == ""  # raised, not reported as a user's error

    run = subprocess.run([sys.executable, "-m", "casadi_design", *argv], cwd=ROOT,
                         capture_output=True, text=True, check=False, timeout=120)
    assert "Traceback" not in run.stderr, run.stderr
    assert (run.returncode, run.stderr) == (0, "")
    assert run.stdout == out
