"""From plan to robot program: the time model by hand, the order against brute force, every
move against an independent dense check on the real geometry (coal), a move across the table
that must get a via point, each format read back by a small reader, and the bad inputs."""

from __future__ import annotations

import itertools
import json
import re

import numpy as np
import pinocchio as pin
import pytest
import tomli_w
import yaml

from casadi_design.cli import main
from casadi_design.errors import DesignError, ProblemError
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import load_problem
from casadi_design.program import detours
from casadi_design.program.formats import FILES, controller, program_text
from casadi_design.program.moves import check_move, move_rules
from casadi_design.program.order import (
    TimeModel,
    best_order,
    held_karp,
    load_changes,
    local_search,
    order_cost,
    time_model,
    tour_cost,
)
from casadi_design.program.sequence import make_program
from tests.conftest import PAPER, ROOT, build, paper_raw

ABB = ROOT / "problems" / "abb_irb6640_machining.toml"
UR10 = ROOT / "problems" / "ur10_drilling.toml"
#: Agreement of a program's joint values read back with the plan's (deg, after the mapping).
READ_BACK_TOL_DEG = 1e-6
#: Steps per move of the independent dense check on the meshes.
DENSE_STEPS = 400
#: A pose of the ABB with the spindle low beside the machine table; turning joint 1 to the
#: mirrored pose sweeps the spindle through the table (the constructed blocked move).
ABB_BESIDE_TABLE_DEG = (-50.0, 50.0, 0.0, 0.0, 60.0, 0.0)
#: The UR10's tool pointing down 100 mm above the floor at (0.55, -0.7) m, beside the table
#: (damped least-squares IK from the test poses' seed), turned by joint 1 to (0.55, 0.7) m.
UR10_BESIDE_TABLE_DEG = (-65.4, -61.3, 101.8, -130.5, -90.0, -155.4)


@pytest.fixture(scope="module")
def abb():
    return load_problem(ABB)


def _mirrored(q_deg):
    qa = np.radians(q_deg)
    qb = qa.copy()
    qb[0] = -qa[0]
    return qa, qb


# --------------------------------------------------------------------------- time model and order

def test_move_time_by_hand():
    # joint 1: v = 1 rad/s, a = 2 rad/s^2, d = 0.25 < v^2/a = 0.5: a triangle, 2 sqrt(d/a) = 0.7071 s;
    # joint 2: v = 2, a = 2, d = 3 > v^2/a = 2: d/v + v/a = 1.5 + 1 = 2.5 s, the slowest
    times = TimeModel(np.array([1.0, 2.0]), np.array([2.0, 2.0]), "test")
    np.testing.assert_allclose(times.joint_times(np.array([0.25, -3.0])), [np.sqrt(0.5), 2.5], rtol=1e-15)
    assert times.move_time(np.zeros(2), np.array([0.25, -3.0])) == 2.5
    assert times.lead_joint(np.zeros(2), np.array([0.25, -3.0])) == 1
    # the two profiles meet at d = v^2/a: 2 sqrt(0.5 / 2) = 0.5 / 1 + 1 / 2 = 1 s
    assert times.joint_times(np.array([0.5, 0.0]))[0] == pytest.approx(1.0, rel=1e-15)


def test_time_model_of_the_case_files(abb):
    # the ABB: [robot].joint_speeds_deg_s, reached in acceleration_time_s = 0.5 s
    times = time_model(abb)
    np.testing.assert_allclose(times.speed, np.radians([100, 90, 90, 170, 120, 190]), rtol=1e-15)
    np.testing.assert_allclose(times.acceleration, times.speed / 0.5, rtol=1e-15)
    # joint 1 turns 90 deg: 1.5708 / 1.7453 + 0.5 = 1.4 s
    assert times.move_time(np.zeros(6), np.radians([90, 0, 0, 0, 0, 0])) == pytest.approx(0.9 + 0.5, rel=1e-12)


def _random_costs(rng, N, loads):
    X = rng.normal(size=(N + 1, 6))
    T = np.abs(X[:, None, :] - X[None, :, :]).max(axis=2)  # a metric, as the move times
    F = rng.choice(loads, size=(N, 1))
    return T, load_changes(F, 1e-9)


@pytest.mark.parametrize("N", [1, 2, 5, 7])
def test_order_is_the_brute_force_optimum_with_load_changes_first(N):
    rng = np.random.default_rng(N)
    T, changes = _random_costs(rng, N, [0.0, 100.0, 200.0])
    C = order_cost(T, changes)
    tours = list(itertools.permutations(range(1, N + 1)))
    fewest = min(tour_cost(changes.astype(float), t) for t in tours)
    best = min(tour_cost(T, t) for t in tours if tour_cost(changes.astype(float), t) == fewest)
    order = held_karp(C)
    assert sorted(order) == list(range(1, N + 1))
    assert tour_cost(changes.astype(float), order) == fewest
    assert tour_cost(T, order) == pytest.approx(best, rel=1e-12)
    assert tour_cost(C, order) <= tour_cost(C, tuple(range(1, N + 1))) + 1e-12


def test_local_search_beyond_the_exact_size():
    rng = np.random.default_rng(3)
    T, changes = _random_costs(rng, 16, [0.0, 50.0])
    C = order_cost(T, changes)
    order = best_order(C)  # 16 > EXACT_UP_TO: 2-opt / or-opt
    file_order = tuple(range(1, 17))
    assert sorted(order) == list(file_order)
    assert tour_cost(C, order) < tour_cost(C, file_order)
    # a local optimum: no 2-opt or or-opt move improves it
    assert local_search(C, order) == order
    # on 8 experiments the local search from the file order is within 10 % of the optimum here
    T8, c8 = T[:9, :9], changes[:9, :9]
    C8 = order_cost(T8, c8)
    assert tour_cost(C8, local_search(C8, tuple(range(1, 9)))) <= 1.1 * tour_cost(C8, held_karp(C8))


# --------------------------------------------------------------------------- moves

def _dense_check(problem, points):
    """Independent of the package's move check: the smallest distance on the real geometry (the
    cell's checked collision pairs, coal through Pinocchio) over every move between consecutive
    ``points`` at ``DENSE_STEPS`` steps, and whether any two bodies touch."""
    check = problem.cell.check
    data, gdata = check.model.createData(), check.geometry.createData()
    smallest, touching = np.inf, False
    for qa, qb in itertools.pairwise(points):
        for s in np.linspace(0.0, 1.0, DENSE_STEPS + 1):
            pin.computeDistances(check.model, data, check.geometry, gdata, check.configuration(qa + s * (qb - qa)))
            d = np.array([r.min_distance for r in gdata.distanceResults])
            touching |= bool(np.any(d <= 0))
            smallest = min(smallest, float(np.min(np.where(check.partial, np.inf, d))))
    return smallest, touching


def test_move_across_the_table_gets_a_via_point_and_every_move_is_safe(abb):
    qa, qb = _mirrored(ABB_BESIDE_TABLE_DEG)
    rules, c = move_rules(abb), abb.cell.spec.clearance_m
    assert rules.free(np.vstack([qa, qb])).all()  # both poses keep the clearance ...
    straight = check_move(abb, qa, qb)
    assert straight.blocked and "machine table" in straight.closest  # ... the straight move crosses the table
    smallest, _ = _dense_check(abb, [qa, qb])
    assert smallest < c  # the dense check agrees
    program = make_program(abb, np.vstack([qa, qb]), np.zeros((2, 3)), np.array(abb.spec.test_poses.seed_q_rad), 1.0)
    assert program.time_s <= program.file_time_s + 1e-9
    crossing = [p for p in program.paths if {tuple(p.points[0]), tuple(p.points[-1])} == {tuple(qa), tuple(qb)}]
    assert crossing and crossing[0].vias >= 1
    smallest, touching = _dense_check(abb, [p.q for p in program.points])
    assert not touching and smallest >= c / 2  # the guarantee of the sampling (moves docstring)
    assert all(mv.clearance_m >= c - 1e-6 for path in program.paths for mv in path.moves)


def test_a_detour_to_several_goals_ends_at_one_and_rrt_connect_grows_from_them_all(abb, monkeypatch):
    """path_to: a detour to one of the goals (each a configuration the caller accepts): through
    the via candidates to the first, else RRT-Connect (no via candidate tried here) growing its
    second tree from every goal, so that a first goal in a closed pocket (every move to it
    declared blocked) does not stop it from reaching another."""
    qa, qb = _mirrored(ABB_BESIDE_TABLE_DEG)
    home = np.array(abb.spec.test_poses.seed_q_rad)
    search = detours.MoveSearch(abb, time_model(abb), np.vstack([home, qa, qb]))
    route = search.path_to(qa, [qb])
    assert np.array_equal(route.points[-1], qb) and route.vias >= 1 and not any(mv.blocked for mv in route.moves)
    monkeypatch.setattr(detours, "MAX_CHECKS", 0)
    monkeypatch.setattr(detours, "RRT_ITERATIONS", 200)
    pocket = qb + 0.01  # a goal none of whose moves is clear
    blocked = search.blocked
    monkeypatch.setattr(search, "blocked", lambda a, b: True if pocket.tobytes() in (a.tobytes(), b.tobytes())
                        else blocked(a, b))
    route = search.path_to(qa, [pocket, qb])
    assert np.array_equal(route.points[0], qa) and np.array_equal(route.points[-1], qb)
    assert not any(search.blocked(a, b) for a, b in itertools.pairwise(route.points))
    with pytest.raises(detours.NoSafePath, match="RRT-Connect"):
        search.path_to(qa, [pocket])


def test_random_plan_program_is_safe_ordered_and_minimises_load_changes(abb):
    Q, F = random_plan(abb, 6, np.random.default_rng(1))
    F[3] = F[0]  # two experiments with the same weight: hung once
    home = np.array(abb.spec.test_poses.seed_q_rad)
    program = make_program(abb, Q, F, home, 2.0)
    assert sorted(program.order) == list(range(1, 7))
    assert program.load_changes == 6 and abs(program.order.index(1) - program.order.index(4)) == 1
    assert program.time_s <= program.file_time_s + 1e-9  # both with their safe moves
    smallest, touching = _dense_check(abb, [p.q for p in program.points])
    assert not touching and smallest >= abb.cell.spec.clearance_m / 2
    # the time of every point: the moves' times plus the measurements
    t = [p.time_s for p in program.points]
    moves_s = sum(program.times.move_time(a.q, b.q) for a, b in zip(program.points[:-1], program.points[1:]))
    assert t[-1] == pytest.approx(moves_s + 6 * 2.0, rel=1e-12)
    stops = [p.stop_before for p in program.points if p.kind == "experiment"]
    assert stops[0].startswith("hang the load") and sum(s is not None for s in stops) == 5
    assert next(p for p in program.points if p.stop_after).stop_after.startswith("remove the load")


# --------------------------------------------------------------------------- formats read back

def _read_urscript(text):
    return [(int(m[2]), [float(v) for v in m[1].split(",")])
            for m in re.finditer(r"movej\(\[([^\]]*)\].*# experiment (\d+)", text)], "rad"


def _read_rapid(text):
    targets = {m[1]: [float(v) for v in m[2].split(",")]
               for m in re.finditer(r"CONST jointtarget (\w+) := \[\[([^\]]*)\]", text)}
    return [(int(m[1][1:]), targets[m[1]]) for m in re.finditer(r"MoveAbsJ (e\d+)\\", text)], "deg"


def _read_krl(text):
    return [(int(m[2]), [float(v.split()[1]) for v in m[1].split(",")])
            for m in re.finditer(r"PTP \{AXIS: ([^}]*)\}\s*; experiment (\d+)", text)], "deg"


def _read_yaml(text):
    numbers = [int(m) for m in re.findall(r"^# experiment (\d+)", text, flags=re.MULTILINE)]
    return list(zip(numbers, [e["positions"] for e in yaml.safe_load(text)])), "model rad"


def _read_json(text):
    record = json.loads(text)
    return [(p["experiment"], p["positions"]) for p in record["points"] if p["experiment"] is not None], "model rad"


READERS = {"urscript": _read_urscript, "rapid": _read_rapid, "krl": _read_krl, "yaml": _read_yaml, "json": _read_json}


def _read_back(problem, program, fmt, Q):
    read, unit = READERS[fmt](program_text(problem, program, fmt, "plan.csv"))
    assert [k for k, _ in read] == list(program.order)  # every experiment, in program order
    ctrl, periodic = controller(problem), problem.rules.limits.periodic
    for k, values in read:
        want = Q[k - 1] if unit == "model rad" else ctrl(Q[k - 1])
        got = np.radians(values[:problem.robot.n]) if unit == "deg" else np.array(values)
        turns = np.where(periodic, np.round((got - want) / (2 * np.pi)), 0)  # the same pose a turn away
        assert np.degrees(np.max(np.abs(got - want - 2 * np.pi * turns))) < READ_BACK_TOL_DEG


def test_a_krl_program_is_named_after_its_file(abb):
    """A KUKA controller loads ``X.src`` only when it defines ``DEF X()``: the command's file
    ``program.src`` and solve's ``programs/test-pose_m6.src``."""
    Q, F = random_plan(abb, 2, np.random.default_rng(5))
    program = make_program(abb, Q, F, np.array(abb.spec.test_poses.seed_q_rad), 1.0)
    assert program_text(abb, program, "krl", "plan.csv").startswith("DEF program()\n")
    assert program_text(abb, program, "krl", "plans/test-pose_m6.csv",
                        "programs/test-pose_m6.src").startswith("DEF test_pose_m6()\n")


def test_every_format_reads_back_the_plan_in_program_order(abb):
    Q, F = random_plan(abb, 4, np.random.default_rng(2))
    program = make_program(abb, Q, F, np.array(abb.spec.test_poses.seed_q_rad), 1.0)
    for fmt in FILES:
        _read_back(abb, program, fmt, Q)
    text = program_text(abb, program, "rapid", "plan.csv")
    assert text.count("Stop;") == program.load_changes and "kg" in text  # the weights to hang


def test_controller_mapping_reads_back_through_signs_and_offsets():
    raw = paper_raw()
    raw["robot"]["controller"] = {"signs": [-1, 1], "offsets_deg": [90.0, -10.0]}
    problem = build(raw)
    Q = np.radians([[10.0, 20.0], [-30.0, 45.0], [60.0, -15.0]])
    F = np.tile([100.0, 0.0], (3, 1))
    program = make_program(problem, Q, F, np.zeros(2), 1.0)
    np.testing.assert_allclose(controller(problem)(Q[0]), np.radians([80.0, 10.0]), atol=1e-15)
    for fmt in ("rapid", "krl", "yaml", "json"):
        _read_back(problem, program, fmt, Q)


# --------------------------------------------------------------------------- bad input

def _plan_csv(path, problem, Q, F=None):
    from casadi_design.cell.cell import clearances
    from casadi_design.records.export import csv_text, plan_table

    near = tuple(clearances(problem.cell, Q)) if problem.cell else None
    F = np.zeros((len(Q), problem.model.nF)) if F is None else F
    path.write_text(csv_text(*plan_table(problem, Q, F, near)))
    return str(path)


@pytest.mark.parametrize("extra, match", [
    (["--format", "gcode"], r"--format: unknown format 'gcode'; allowed: urscript, rapid, krl, yaml, json"),
    (["--format", "json", "--home", "0,0,0"], r"--home: '0,0,0' is not 6 joint values"),
    (["--format", "json", "--home", "0,0,0,0,200,0"], r"--home: joint_5 = 200 deg is outside \[-117.1"),
    (["--format", "json", "--home", "0,50,0,0,60,0"], r"--home: link .* closer than 20 mm to machine table \(by .* mm\); give a home"),
])
def test_bad_program_input_is_one_line_and_writes_nothing(abb, tmp_path, capsys, extra, match):
    plan = _plan_csv(tmp_path / "plan.csv", abb, *random_plan(abb, 2, np.random.default_rng(5)))
    out = tmp_path / "out"
    assert main(["program", str(ABB), "--plan", plan, *extra, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert re.search(match, err) and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_a_home_that_cannot_start_the_moves_is_refused_first_and_named(abb, tmp_path, capsys):
    """The default home (the seed of the test poses) in the table is named as the default, with
    the option that changes it; evaluate --moves refuses a home before it prints the plan's
    scores (it printed the whole table, then the error)."""
    from dataclasses import replace

    from casadi_design.cli.program import home_pose

    table = np.deg2rad([0, 50, 0, 0, 60, 0])
    seeded = replace(abb, spec=replace(abb.spec, test_poses=replace(abb.spec.test_poses, seed_q_rad=tuple(table))))
    with pytest.raises(ProblemError, match=r"^the default home \(\[test_poses\].seed_q_deg, else the middle of the "
                                           r"limits\): link .* closer than 20 mm to machine table .*; give a home pose "
                                           r"inside the limits and clear of the cell with --home$"):
        home_pose(seeded, None)
    plan = _plan_csv(tmp_path / "plan.csv", abb, *random_plan(abb, 2, np.random.default_rng(5)))
    assert main(["evaluate", str(ABB), "--plan", plan, "--moves", "--home", "0,50,0,0,60,0"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("error: --home: link ")


def test_a_plan_that_breaks_its_rules_is_not_programmed(abb, tmp_path, capsys):
    """A robot program runs a plan's poses and loads as they are: a pose in the table's
    clearance (it was refused as unreachable from home) or a load beyond the rig's is one
    line naming the experiment and the rule, and nothing is written."""
    Q, F = random_plan(abb, 2, np.random.default_rng(5))
    u = np.array(abb.force.direction)
    for q, f, match in ((np.deg2rad([0, 50, 0, 0, 60, 0]), F[0], r"experiment 1: link .* closer than 20 mm to "
                         r"machine table \(by .* mm\); a program runs the plan as it is: correct it"),
                        (Q[0], 2 * abb.force.magnitude_N * u, r"experiment 1: \|F\| = 3924 N above 1962 N; a program")):
        plan = _plan_csv(tmp_path / "plan.csv", abb, np.vstack([q, Q[1]]), np.vstack([f, F[1]]))
        out = tmp_path / "out"
        assert main(["program", str(ABB), "--plan", plan, "--format", "json", "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert re.search(match, err) and err.count("\n") == 1, err
        assert not out.exists()


def test_a_reading_just_past_a_limit_is_programmed_at_the_limit(tmp_path, capsys):
    """A measured posture read within --limit-tolerance past a joint limit (FIGAROH's TIAGo
    torso at 0.350181 m of 0.35) is programmed at the limit, which a controller accepts, and
    said; it was written as it was read."""
    paper = load_problem(PAPER)
    plan = tmp_path / "postures.csv"  # bare joint names in rad, as a controller's log or FIGAROH's files
    plan.write_text(f"joint1,joint2,fx_N,fy_N\n0.3,{float(paper.robot.q_max[1]) + 5e-4!r},100,0\n0.1,-1.0,100,0\n")
    assert main(["program", str(PAPER), "--plan", str(plan), "--format", "json", "--out", str(tmp_path / "out")]) == 0
    assert "note: 1 joint value of the plan past its limit (within the reading's tolerance) programmed at the " \
           "limit" in capsys.readouterr().out
    points = json.loads((tmp_path / "out" / "program.json").read_text())["points"]
    q2 = max(p["positions"][1] for p in points if p["experiment"])
    assert q2 == pytest.approx(paper.robot.q_max[1], abs=1e-12)


def test_plan_of_another_robot_and_bad_controller_are_refused(abb, tmp_path, capsys):
    paper = load_problem(PAPER)
    plan = _plan_csv(tmp_path / "plan.csv", paper, np.zeros((2, 2)), np.tile([100.0, 0.0], (2, 1)))
    assert main(["program", str(ABB), "--plan", plan, "--format", "json", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{plan}: column 'joint1_deg' names joint 'joint1', which the robot of" in err
    assert "the plan is for another problem" in err
    raw = paper_raw()
    case, plan = tmp_path / "paper.toml", _plan_csv(tmp_path / "paper.csv", paper, np.zeros((2, 2)),
                                                    np.tile([100.0, 0.0], (2, 1)))
    for controller_table, match in (({"signs": [1, 1, 1]}, (r"\[robot.controller\].signs: has 3 values, the chain "
                                                             r"has 2 joints \(joint1, joint2\); give one per joint")),
                                    ({"signs": [1, 2]}, r"\[robot.controller\].signs: must be \+1 or -1, got \[1.0, 2.0\]")):
        raw["robot"]["controller"] = controller_table
        case.write_text(tomli_w.dumps(raw))
        assert main(["program", str(case), "--plan", plan, "--format", "rapid", "--quiet"]) == 2
        assert re.search(match, capsys.readouterr().err)
    assert main(["program", str(PAPER), "--plan", plan, "--format", "urscript", "--quiet"]) == 2
    assert "--format urscript: the controller drives 6 joints, the robot has 2" in capsys.readouterr().err


def test_a_move_without_a_detour_goes_through_home_and_an_experiment_home_cannot_reach_is_named(abb, tmp_path,
                                                                                               capsys, monkeypatch):
    """No detour may be tried: the move between the two experiments beside the table (the
    straight one crosses it) goes through home, whose straight moves to both are clear; with
    the first as home, the second cannot be reached (any turn of its wrist): one line naming
    it, nothing written."""
    qa, qb = _mirrored(ABB_BESIDE_TABLE_DEG)
    monkeypatch.setattr(detours, "MAX_CHECKS", 0)
    monkeypatch.setattr(detours, "RRT_ITERATIONS", 0)
    home = np.array(abb.spec.test_poses.seed_q_rad)
    program = make_program(abb, np.vstack([qa, qb]), np.zeros((2, 3)), home, 1.0)
    (between,) = [path for path in program.paths if path.vias]
    assert len(between.points) == 3 and np.array_equal(between.points[1], home)
    assert all(not mv.blocked for path in program.paths for mv in path.moves)
    plan = _plan_csv(tmp_path / "plan.csv", abb, qb[None])
    out = tmp_path / "out"
    at = ",".join(f"{v:g}" for v in ABB_BESIDE_TABLE_DEG)
    assert main(["program", str(ABB), "--plan", plan, f"--home={at}", "--format", "krl", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(r"error: experiment 1 cannot be reached from home: no collision-free way to its pose \(no "
                        r"collision-free detour among \d+ via candidates nor by 0 RRT-Connect steps\); move that "
                        r"experiment or give another --home\n", err)  # (the ABB has no periodic joint: one pose)
    assert not out.exists()


def test_evaluate_checks_the_moves_of_your_sequence_with_the_same_code(abb, tmp_path, capsys):
    qa, qb = _mirrored(ABB_BESIDE_TABLE_DEG)
    plan = _plan_csv(tmp_path / "plan.csv", abb, np.vstack([qa, qb]))
    assert main(["evaluate", str(ABB), "--plan", plan, "--moves", "--out", str(tmp_path / "ev"), "--quiet"]) == 0
    assert "experiment 1 -> experiment 2" in capsys.readouterr().out
    record = json.loads((tmp_path / "ev" / "evaluation.json").read_text())["moves"]
    assert [(m["from"], m["to"]) for m in record] == [("home", "experiment 1"), ("experiment 1", "experiment 2"),
                                                      ("experiment 2", "home")]
    crossing = check_move(abb, qa, qb)
    assert record[1]["blocked"] and record[1]["clearance_m"] == crossing.clearance_m


def test_solve_writes_a_program_per_plan(tmp_path):
    out = tmp_path / "solve"
    assert main(["solve", str(PAPER), "--m", "2", "--criteria", "D", "--starts", "1", "--jobs", "1",
                 "--bound-steps", "0", "--quiet", "--program", "krl", "--out", str(out)]) == 0
    problem = load_problem(PAPER)
    from casadi_design.records.export import read_plan_csv

    Q, _ = read_plan_csv(problem, out / "plans" / "D_m2.csv")
    read, _ = _read_krl((out / "programs" / "D_m2.src").read_text())
    assert sorted(k for k, _ in read) == [1, 2]
    for k, values in read:
        assert np.max(np.abs(np.radians(values) - Q[k - 1])) < np.radians(READ_BACK_TOL_DEG)


# --------------------------------------------------------------------------- the UR10 on its meshes

@pytest.mark.slow
def test_ur10_program_is_safe_on_the_meshes_and_crosses_the_table_with_a_via():
    ur10 = load_problem(UR10)
    home = np.array(ur10.spec.test_poses.seed_q_rad)
    Q, F = random_plan(ur10, 12, np.random.default_rng(0))
    program = make_program(ur10, Q, F, home, 3.0)
    smallest, touching = _dense_check(ur10, [p.q for p in program.points])
    assert not touching and smallest >= ur10.cell.spec.clearance_m / 2
    for fmt in FILES:
        _read_back(ur10, program, fmt, Q)
    qa, qb = _mirrored(UR10_BESIDE_TABLE_DEG)
    assert move_rules(ur10).free(np.vstack([qa, qb])).all() and check_move(ur10, qa, qb).blocked
    crossing = make_program(ur10, np.vstack([qa, qb]), np.zeros((2, 0)), home, 1.0)
    assert max(p.vias for p in crossing.paths) >= 1
    smallest, touching = _dense_check(ur10, [p.q for p in crossing.points])
    assert not touching and smallest >= ur10.cell.spec.clearance_m / 2


@pytest.mark.slow
@pytest.mark.parametrize("path, m", [(UR10, 12), (ABB, 6)], ids=["ur10", "abb"])
def test_programs_of_the_case_studies_test_pose_plans_are_safe_on_the_meshes(path, m, tmp_path):
    out = tmp_path / "solve"
    # two seeded starts: the ABB's first at m = 6 ends at max_iter (3000), the second converges
    assert main(["solve", str(path), "--m", str(m), "--criteria", "test-pose", "--starts", "2", "--jobs", "1",
                 "--bound-steps", "0", "--quiet", "--program", "json", "--out", str(out)]) == 0
    problem = load_problem(path)
    from casadi_design.records.export import read_plan_csv

    Q, _ = read_plan_csv(problem, out / "plans" / f"test-pose_m{m}.csv")
    record = json.loads((out / "programs" / f"test-pose_m{m}.json").read_text())
    points = [np.array(p["positions"]) for p in record["points"]]
    smallest, touching = _dense_check(problem, points)
    assert not touching and smallest >= problem.cell.spec.clearance_m / 2
    periodic = problem.rules.limits.periodic
    for p in record["points"]:
        if p["experiment"] is not None:
            d = np.array(p["positions"]) - Q[p["experiment"] - 1]
            d -= 2 * np.pi * np.where(periodic, np.round(d / (2 * np.pi)), 0)
            assert np.degrees(np.max(np.abs(d))) < READ_BACK_TOL_DEG


@pytest.mark.parametrize("fmt, match", [
    ("gcode", r"--program: unknown format 'gcode'; allowed: urscript, rapid, krl, yaml, json"),
    ("urscript", r"--program urscript: the controller drives 6 joints, the robot has 2"),
])
def test_solve_refuses_a_program_format_before_it_solves(tmp_path, capsys, fmt, match):
    out = tmp_path / "out"
    assert main(["solve", str(PAPER), "--m", "1", "--starts", "1", "--bound-steps", "0", "--jobs", "1", "--quiet",
                 "--program", fmt, "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert re.search(match, captured.err) and captured.err.count("\n") == 1
    assert "max over test poses" not in captured.out and not (out / "results.json").exists()


def test_a_plan_that_cannot_be_programmed_leaves_the_results_written_and_says_so(tmp_path, capsys, monkeypatch):
    """solve --program: the results, figures and plans are written (no partial file left)
    before the programs; a plan that cannot be programmed (here every move refused) is one line
    naming it, the folder, and the command that tries another home."""
    from casadi_design.program import sequence

    for error in (DesignError("experiment 1 cannot be reached from home: refused here"),
                  ProblemError("--home: joint2 = 0 deg is in the table here")):  # the default home refused

        def refused(problem, Q, F, home, measure_s):
            raise error

        monkeypatch.setattr(sequence, "make_program", refused)
        out = tmp_path / type(error).__name__
        assert main(["solve", str(PAPER), "--m", "1", "--starts", "1", "--bound-steps", "0", "--jobs", "1", "--criteria",
                     "D", "--quiet", "--program", "json", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err == (f"error: {error} (the D plan of m = 1); the results and plans are written in {out}: "
                       "casadi-design program takes plans/D_m1.csv with another --home\n")
        assert json.loads((out / "results.json").read_text())["designs"][0]["m"] == 1
        assert (out / "plans" / "D_m1.csv").exists() and not (out / "solve.partial.json").exists()


def test_a_turn_is_taken_only_when_it_is_faster(monkeypatch):
    """Of the turns of a pose with periodic joints (the UR10's +/-360 deg), home first reaches
    the fastest; of equal times (a fast wrist beside a slow arm: every move takes the arm's
    time) the one of least joint travel, not a wrist wound a whole turn."""
    from casadi_design.cli.identify import load_without_cell
    from casadi_design.program import sequence

    ur10 = load_without_cell(str(ROOT / "problems" / "ur10_drilling.toml"))
    home, q = np.zeros(6), np.deg2rad([90.0, -60.0, 30.0, -20.0, 40.0, -31.0])
    assert [round(np.rad2deg(c[5])) for c in sequence.turns(ur10, q, home)[:1]] == [-31]

    class Slow:  # every move the same time: only the travel tells the turns apart
        def move_time(self, a, b):
            return 1.0

    monkeypatch.setattr(sequence, "time_model", lambda problem: Slow())
    options = sequence.turns(ur10, q, home)
    assert len(options) > 1 and np.array_equal(options[0], q)  # (every UR10 joint: +/-360 deg)
    travel = [np.abs(c - home).sum() for c in options]
    assert travel == sorted(travel)
