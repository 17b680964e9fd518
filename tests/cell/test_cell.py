"""The calibration cell of a problem: problem-file keys, the rows every experiment gets, the
check on the real geometry, periodic joints and the joint-limit margin."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest
import scipy.optimize

from casadi_design.cell.capsules import capsule_names
from casadi_design.cell.cell import clearances, touching
from casadi_design.errors import ProblemError
from casadi_design.optimisation.nlp import build_nlp
from casadi_design.optimisation.reduced import reduced_nlp
from casadi_design.optimisation.solve import make_design_solver, solve_start, start_rng
from casadi_design.plan.rules import joint_distance_sq, plan_violations
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem, load_problem
from casadi_design.problem_file.read import parse_problem, read_problem
from casadi_design.records.export import plan_table
from tests.conftest import ROOT

UR10 = ROOT / "problems" / "ur10_drilling.toml"
#: Relative agreement of the rows' Hessian with central differences of their Jacobian. The
#: rows are C1 only (their closest points switch branch): a step that crosses a switch is
#: off, so the agreement is looser than for the criteria.
HESSIAN_FD_RTOL = 1e-4


@pytest.fixture(scope="module")
def ur10():
    return load_problem(UR10)


def _raw(path=UR10):
    import tomllib

    return tomllib.loads(path.read_text())


@pytest.mark.parametrize("case", ["ur10_drilling", "abb_irb6640_machining"])
def test_the_collision_query_finds_the_pairs_the_distances_find(case):
    """``touching`` (coal's collision query, stopping at the first pair in contact) names the
    same first touching pair as the distance of every pair (``clearances``), on random
    configurations anywhere in the joint limits (most of them cross something)."""
    problem = load_problem(ROOT / "problems" / f"{case}.toml")
    limits = problem.rules.limits
    Q = limits.lower + (limits.upper - limits.lower) * np.random.default_rng(3).uniform(size=(60, problem.robot.n))
    by_distance = [c.touching for c in clearances(problem.cell, Q)]
    assert touching(problem.cell, Q) == by_distance
    assert 5 < sum(t is not None for t in by_distance) < len(Q)  # both answers occur


def test_only_rows_linear_in_the_points_are_left_out_of_the_curvature(ur10):
    """The capsule rows without a structural second derivative (``curved`` False, skipped in
    the Hessian) are the floor's (a plane: linear in the points), and their Hessian is zero at
    random points; every row whose Hessian is not zero somewhere is kept. (The table's rows,
    a box's, are piecewise linear too, but CasADi's derivative of fmin / fmax keeps their
    structure: kept, and zero.)"""
    rows = ur10.rules.pose.collision
    labels = ur10.rules.pose.labels[rows.first:]
    flat = np.flatnonzero(~rows.curved)
    assert flat.size == 22 and all(labels[r].endswith("to the floor") for r in flat)
    W = np.random.default_rng(2).normal(size=(20, rows.inputs.shape[1]))
    for r in range(len(rows.curved)):
        curved = max(np.abs(np.asarray(rows.curvature(r, w))).max() for w in W) > 0
        assert rows.curved[r] or not curved, labels[r]
    assert sum(rows.curved) > 50  # the capsule pairs and the line of sight


def test_incidence_row_is_the_cosine_of_the_beam_angle(ur10):
    """Against Pinocchio: the angle between the reflector's axis (x of tool0, turned by the
    tool frame) and the beam from the reflector to the tracker."""
    rules, robot = ur10.rules.pose, ur10.robot
    row = rules.labels.index("reflector: tracker beam beyond the 30 deg acceptance angle")
    assert rules.units[row] == "cos" and rules.lb[row] == pytest.approx(np.cos(np.deg2rad(30)))
    data = robot.model.createData()
    rng = np.random.default_rng(5)
    tracker, axis = np.array(ur10.cell.spec.tracker.position_m), np.array(ur10.cell.spec.tracker.reflector_axis)
    for q in rng.uniform(robot.q_min, robot.q_max, size=(20, robot.n)):
        pin.framesForwardKinematics(robot.model, data, robot.full_q(q))
        M = data.oMf[robot.frame_id]
        beam = tracker - M.translation
        want = (M.rotation @ axis) @ beam / np.linalg.norm(beam)
        got = float(np.asarray(rules.g(q)).ravel()[row])
        assert got == pytest.approx(want, abs=1e-12)


def test_cell_rows_hessian_equals_finite_differences(ur10):
    """The rule rows' part of the Hessian of the Lagrangian, the capsule rows entering row by
    row through their world points, against central differences of their Jacobian."""
    m = 9  # M is regular from 9 experiments on
    nlp = build_nlp(ur10, "T", m)
    rng = np.random.default_rng(6)
    x = nlp.start(*random_plan(ur10, m, rng))
    lam = rng.normal(size=nlp.lbg.size)

    def jac(x):
        return np.asarray(ca.densify(nlp.options["jac_g"](x, [])[1])).reshape(lam.size, x.size)

    H = np.asarray(ca.densify(nlp.options["hess_lag"](x, [], 0.0, lam)))
    H = np.triu(H) + np.triu(H, 1).T
    h = 1e-6
    fd = np.column_stack([(jac(x + h * e) - jac(x - h * e)).T @ lam / (2 * h) for e in np.eye(x.size)])
    assert len(nlp.active) == m * len(ur10.rules.pose.collision.inputs)  # every capsule row
    np.testing.assert_allclose(H, fd, atol=HESSIAN_FD_RTOL * np.abs(H).max())


def test_periodic_joints_are_free_and_wrapped(ur10):
    limits, robot = ur10.rules.limits, ur10.robot
    # the UR10's +/-2 pi joints are periodic; the elbow's +/-pi (exactly a turn) is not
    assert limits.periodic.tolist() == [True, True, False, True, True, True]
    lb, ub = limits.bounds()
    assert np.all(np.isinf(lb[limits.periodic])) and np.all(np.isinf(ub[limits.periodic]))
    np.testing.assert_allclose(limits.lower[2], -np.pi + 0.05)  # the margin
    rng = np.random.default_rng(7)
    Q = rng.uniform(-15, 15, size=(20, robot.n))
    W = limits.wrap(Q)
    assert np.all(W >= limits.lower - 1e-12) and np.all(W <= limits.upper + 1e-12)
    turns = (W - Q)[:, limits.periodic] / (2 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-12)  # whole turns only
    # the same pose: same measured point
    for q, w in zip(Q, W):
        q = np.where(limits.periodic, q, w)
        np.testing.assert_allclose(np.asarray(ur10.model.position(q)).ravel(),
                                   np.asarray(ur10.model.position(w)).ravel(), atol=1e-12)
    # the chord distance: a whole turn apart is the same configuration; small moves as |d|
    qa = limits.sample(rng)
    assert joint_distance_sq(limits, qa, qa + 2 * np.pi * limits.periodic) == pytest.approx(0.0, abs=1e-24)
    d = 1e-4 * rng.normal(size=robot.n)
    assert np.sqrt(joint_distance_sq(limits, qa, qa + d)) == pytest.approx(np.linalg.norm(d), rel=1e-8)
    qs = ca.SX.sym("q", robot.n)
    f = ca.Function("d", [qs], [joint_distance_sq(limits, qs, ca.DM(qa))])
    assert float(f(qa + d)) == pytest.approx(joint_distance_sq(limits, qa + d, qa), rel=1e-12)


@pytest.mark.parametrize("edit, message", [
    (lambda c: c.update(obstacles=[{"name": "t", "kind": "cone"}]), r"\[cell.obstacles\[1\]\].kind: 'cone'; allowed: half_space, box, capsule"),
    (lambda c: c.update(obstacles=[{"name": "t", "kind": "box", "center_m": [0, 0, 0], "half_extents_m": [1, 0, 1]}]),
     r"half_extents_m: \[1.0, 0.0, 1.0\]; give positive half sizes"),
    (lambda c: c.update(obstacles=[{"name": "t", "kind": "box", "center_m": [0, 0, 0], "half_extents_m": [1, 1, 1], "radius_m": 1}]),
     r"'radius_m' is not a key of a box"),
    (lambda c: c.update(obstacles=[{"name": "a", "kind": "half_space", "normal": [0, 0, 1], "offset_m": 0},
                                   {"name": "a", "kind": "half_space", "normal": [0, 0, 1], "offset_m": 1}]),
     r"\[cell.obstacles\[2\]\].name: 'a' is empty, repeated or reserved"),
    (lambda c: c.update(capsules_per_link=9), r"\[cell\].capsules_per_link: must be between 0 and 8"),
    (lambda c: c.update(disabled_pairs=[["forearm_link", "nowhere"]]), r"\[cell\].disabled_pairs: 'nowhere' carries no capsule"),
    (lambda c: c.update(capsules=[{"frame": "nowhere", "a_m": [0, 0, 0], "b_m": [0, 0, 0], "radius_m": 0.1}]),
     r"\[cell\].capsules: no frame or joint 'nowhere'"),
    (lambda c: c["tracker"].update(acceptance_deg=180), r"\[cell.tracker\].acceptance_deg: is 180"),
    (lambda c: c["tracker"].update(reflector_axis=[0, 0, 0]), r"\[cell.tracker\].reflector_axis: is zero"),
    (lambda c: c.update(collision_urdf="robots/x.urdf"), r"\[cell\].collision_urdf: is only used with a DH robot"),
])
def test_bad_cell_keys_name_the_field(edit, message):
    raw = _raw()
    edit(raw["cell"])
    with pytest.raises(ProblemError, match=message):
        build_problem(parse_problem(raw, str(UR10)))


def test_margin_larger_than_a_range_is_refused():
    raw = _raw()
    raw["experiments"]["workspace"]["joint_limit_margin_rad"] = 3.2
    with pytest.raises(ProblemError, match=r"joint_limit_margin_rad: 3.2 leaves no room .* elbow_joint"):
        build_problem(parse_problem(raw, str(UR10)))


def test_dh_robot_needs_capsules_as_numbers():
    raw = _raw(ROOT / "problems" / "abb_irb6640_machining.toml")
    raw["cell"] = {"capsules_per_link": 2}
    with pytest.raises(ProblemError, match=r"\[cell\].capsules_per_link: is 2 but the robot has no URDF collision meshes"):
        parse_problem(raw, "abb.toml")
    raw["cell"] = {"obstacles": [{"name": "wall", "kind": "half_space", "normal": [1, 0, 0], "offset_m": -1}]}
    with pytest.raises(ProblemError, match=r"obstacles and lines of sight need the robot's capsules"):
        build_problem(parse_problem(raw, "abb.toml"))


def test_problem_without_cell_is_unchanged():
    spec = read_problem(ROOT / "problems" / "paper_planar_2r.toml")
    assert spec.cell is None and build_problem(spec).cell is None


def test_one_incidence_and_sight_row_stand_for_every_reflector():
    """The ABB's three reflectors: the centroid rows are conservative for each reflector (its
    exact beam angle, its own line of sight)."""
    from casadi_design.cell.collision import LineOfSight, capsule_clearances

    abb = load_problem(ROOT / "problems" / "abb_irb6640_machining.toml")
    rules, robot, cell = abb.rules.pose, abb.robot, abb.cell
    markers = np.array(abb.spec.measurement.markers_m)
    incidence = rules.labels.index("reflectors: tracker beam beyond the 30 deg acceptance angle")
    sight = [k for k, label in enumerate(rules.labels) if label.startswith("line of sight")]
    tracker, axis = np.array(cell.spec.tracker.position_m), np.array(cell.spec.tracker.reflector_axis)
    data = robot.model.createData()
    each = [LineOfSight(tuple(tracker), cell.sights[0].frame, tuple(p)) for p in markers]
    rng = np.random.default_rng(10)
    seen, clear = 0, 0
    for q in rng.uniform(robot.q_min, robot.q_max, size=(400, robot.n)):
        g = np.asarray(rules.g(q)).ravel()
        pin.framesForwardKinematics(robot.model, data, robot.full_q(q))
        M = data.oMf[robot.frame_id]
        beams = tracker - (M.rotation @ markers.T).T - M.translation
        cos = beams @ (M.rotation @ axis) / np.linalg.norm(beams, axis=1)
        if g[incidence] >= rules.lb[incidence]:
            seen += 1
            assert np.all(cos >= np.cos(cell.spec.tracker.acceptance_rad) - 1e-12)
        if np.all(g[sight] >= 0):
            clear += 1
            own, _ = capsule_clearances(robot, cell.capsules, q, cell.spec.clearance_m, (), each, ())
            assert np.all(own >= -1e-12)
    assert seen > 0 and clear > 0


def test_dh_robot_is_checked_on_its_capsules_with_coal():
    """The ABB (a DH table, no meshes) is checked on its capsules as coal shapes; coal's exact
    capsule distances bound the smooth self-collision rows from above, within their smoothing."""
    from casadi_design.cell.cell import world_capsules

    abb = load_problem(ROOT / "problems" / "abb_irb6640_machining.toml")
    cell, robot, rules = abb.cell, abb.robot, abb.rules.pose
    assert cell.check.source == "capsules"
    names = capsule_names(cell.capsules)
    rows = [(k, names.index(label.split()[1]), names.index(label.split()[3]))
            for k, label in enumerate(rules.labels) if label.startswith("links ")]
    assert len(rows) == len(cell.pairs.kept)
    for q in np.random.default_rng(11).uniform(robot.q_min, robot.q_max, size=(10, robot.n)):
        g, world = np.asarray(rules.g(q)).ravel(), world_capsules(cell, robot, q)
        for k, i, j in rows:
            exact = _coal_distance(world[i], world[j])
            assert exact - 2e-6 <= g[k] + cell.spec.clearance_m <= exact + 1e-9 or exact <= 0


def _coal_distance(first, second) -> float:
    """coal's distance (m) between two capsules given as (a, b, radius, frame), world frame."""
    import coal

    shapes = []
    for a, b, r, _ in (first, second):
        axis = b - a
        length = float(np.linalg.norm(axis))
        R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0, 1]), axis / length).matrix() if length > 0 else np.eye(3)
        shapes.append((coal.Capsule(r, length), coal.Transform3s(R, (a + b) / 2)))
    result = coal.DistanceResult()
    coal.distance(*shapes[0], *shapes[1], coal.DistanceRequest(), result)
    return result.min_distance


def test_a_start_holding_the_rows_that_can_bind_ends_at_an_optimum_of_every_row(ur10):
    """A start holds only the capsule rows that can bind (a few of the 9 x 100); its plan keeps
    every row and is a KKT point of the NLP holding every row: the objective's gradient is a
    nonnegative combination of the gradients of the rows and bounds active there (least
    squares with nonnegative multipliers, outside IPOPT), to rounding; a plan moved by 0.1
    mrad is not."""
    m, criterion = 9, "test-pose"
    B0 = ur10.B0
    Q0, F0 = random_plan(ur10, m, start_rng(ur10.solver.seed, criterion, m))
    rec, Q, F, _ = solve_start(ur10, make_design_solver(ur10, criterion, m), Q0, F0)
    rows = m * len(ur10.rules.pose.collision.inputs)
    assert rec.converged and rec.runs > 1 and 0 < rec.rows_held < rows / 4
    assert plan_violations(ur10, Q, F) == []
    full = build_nlp(ur10, criterion, m)
    assert len(full.active) == rows
    everything = reduced_nlp(ur10, criterion, m, full.scale)

    def stationarity(Q: np.ndarray, active_tol: float = 1e-6) -> float:  # IPOPT stops within ~1e-7
        x = np.array(full.start(Q, F), dtype=float)
        x[-1] += everything.at(x).g[: len(B0)].max()  # t = the largest rho: its rows active
        g, grad, J = everything.at(x).g, everything.slopes(x).grad_f, everything.slopes(x).jac_g
        lower, upper = g - full.lbg < active_tol, full.ubg - g < active_tol
        I = np.eye(len(x))
        C = np.column_stack([J[lower].T, -J[upper].T, I[:, x - full.lbx < active_tol],
                             -I[:, full.ubx - x < active_tol]])
        return scipy.optimize.nnls(C, grad)[1] / np.linalg.norm(grad)

    assert stationarity(Q) < 1e-6
    assert stationarity(Q + 1e-4) > 1e-2


def test_a_plan_table_without_clearances_has_no_clearance_columns(ur10):
    """A plan of a cell problem written without its clearances (compensated poses, a user's
    plan): every row as long as the header; with them, the two columns are there."""
    Q, F = random_plan(ur10, 3, np.random.default_rng(2))
    for near in (None, tuple(clearances(ur10.cell, Q))):
        header, rows = plan_table(ur10, Q, F, near)
        assert all(len(row) == len(header) for row in rows)
        assert ("clearance_mm" in " ".join(header)) == (near is not None)


def test_a_run_stops_as_stalled_only_after_its_iterates_stop_making_progress(ur10):
    """The stall rule of a run in a cell (:data:`casadi_design.optimisation.solve.STALL_ITERATIONS`): a
    cycle of plans that keep every row stops the run that many iterations after its last new
    best objective; a slowly falling objective, or a violation that keeps shrinking while the
    objective rises (a run on its way to a feasible plan), never does."""
    from casadi_design.optimisation.solve import STALL_ITERATIONS, _Watch

    nlp = build_nlp(ur10, "test-pose", 1)
    lb, ub = np.asarray(nlp.lbg, dtype=float), np.asarray(nlp.ubg, dtype=float)
    inside = np.select([np.isfinite(lb) & np.isfinite(ub), np.isfinite(lb), np.isfinite(ub)],
                       [(lb + ub) / 2, lb + 1.0, ub - 1.0], 0.0)  # a value that keeps every row
    assert np.all(inside >= lb) and np.all(inside <= ub)
    broken = np.flatnonzero(np.isfinite(lb))[0]

    def run(iterates):
        watch, stops = _Watch(ur10, nlp, rows=False), []
        x = ca.DM.zeros(nlp.lbx.size)
        for k, (f, h) in enumerate(iterates, start=1):
            g = inside.copy()
            g[broken] = lb[broken] - h
            if float(watch(x, ca.DM(f), ca.DM(g), x, ca.DM(g), ca.DM())) == 1.0:  # as IPOPT calls it
                stops.append(k)
                break
        return stops, watch.stalled

    n = 3 * STALL_ITERATIONS
    cycle = [(v, 0.0) for v in (1.0, 1.1, 0.99, 1.05)] * n  # the last new best: iteration 3
    assert run(cycle) == ([3 + STALL_ITERATIONS], True)
    assert run([(1.0 - 1e-4 * k, 0.0) for k in range(n)]) == ([], False)
    climb = [(k, 1.0 / (k + 1)) for k in range(n)]  # infeasible, the violation falling
    assert run(climb) == ([], False)
    assert run(climb[:10] + [(20.0, 0.5)] * n)[0] == [10 + STALL_ITERATIONS]


PANDA_CELL = """
name = "panda_srdf"
[robot]
urdf = "example-robot-data:panda_description/urdf/panda.urdf"
frame = "panda_link8"
tool_xyz_m = [0.07, 0.0, 0.03]
[calibration]
case = "geometric"
parameters = "identifiable"
[measurement]
components = ["x", "y", "z"]
sigma_m = 2.5e-5
[test_poses]
components = ["x", "y", "z"]
tool_rpy_deg = [180.0, 0.0, 0.0]
seed_q_deg = [0.0, -45.0, 0.0, -135.0, 0.0, 90.0, 45.0]
path = { kind = "points", points_m = [[0.45, 0.0, 0.25]] }
[experiments]
m = [11]
[design]
criteria = ["D"]
[cell]
clearance_m = 0.02
capsules_per_link = 0
capsules = [
  { frame = "panda_link3", a_m = [0.0, 0.0, -0.1], b_m = [0.0, 0.0, 0.0], radius_m = 0.06 },
  { frame = "panda_link5", a_m = [0.0, 0.0, -0.2], b_m = [0.0, 0.0, 0.0], radius_m = 0.06 },
  { frame = "panda_hand", a_m = [0.0, -0.1, 0.05], b_m = [0.0, 0.1, 0.05], radius_m = 0.04 },
]
"""


@pytest.mark.parametrize("srdf, kept", [("", 3), ("example-robot-data:panda_description/srdf/panda.srdf", 0)])
def test_the_pairs_an_srdf_disables_are_not_checked(tmp_path, srdf, kept):
    """MoveIt's SRDF of the Panda disables hand / link 5 ("Default"), hand / link 3 and link 3 /
    link 5 ("Never"): with ``[cell].srdf`` none of the three capsule pairs is a row (the fitted
    capsules of hand and link 5 met for a band of joint 7 where the meshes are 33 mm apart, and
    split the reachable space); without it all three are."""
    path = tmp_path / "panda.toml"
    path.write_text(PANDA_CELL + (f'srdf = "{srdf}"\n' if srdf else ""))
    cell = load_problem(path).cell
    assert len(cell.pairs.kept) == kept, cell.pairs.skipped
    path.write_text(PANDA_CELL + 'srdf = "missing.srdf"\n')
    with pytest.raises(ProblemError, match=r"panda.toml: \[cell\].srdf: cannot read .*missing.srdf .*give the robot's "
                                           r"SRDF \(MoveIt\)"):
        load_problem(path)


def test_a_calibrated_problem_file_names_the_srdf_from_where_it_is_written(tmp_path):
    """identify's calibrated.toml is written in its output folder: a relative ``srdf`` of the
    problem file is rewritten relative to that folder (it was copied as written, and the
    calibrated file could not be read)."""
    from casadi_design.calibrated.calibrated_toml import calibrated_problem
    from casadi_design.robot.robots import urdf_file

    (tmp_path / "robot").mkdir()
    (tmp_path / "robot" / "panda.srdf").write_bytes(urdf_file("example-robot-data:panda_description/srdf/panda.srdf")
                                                   .read_bytes())
    path = tmp_path / "panda.toml"
    path.write_text(PANDA_CELL + 'srdf = "robot/panda.srdf"\n')
    out = tmp_path / "out" / "identify"
    record = calibrated_problem(load_problem(path), out / "calibrated.urdf")
    assert record["cell"]["srdf"] == "../../robot/panda.srdf"
    assert (out / record["cell"]["srdf"]).resolve() == (tmp_path / "robot" / "panda.srdf").resolve()
