"""Configurations planned with the ball seated (plan/seated.py) and where to clamp the tool
(optimisation/artefact_pool.choose_clamps), on MUKCa's Panda of problems/panda_ball_socket.toml:
the nominal ball at its socket (Pinocchio's own kinematics against the placement's pose
composed here with scipy's rotations), the hand within the tilt, the seed's plans the same, the
hand's orientations uniform over the cone, an unreachable placement named in one line, the
approach of a robot program, and the choice of the placement by the measure (the best set's plan,
scored again by the one scorer, and the certified bound below each set's plan)."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from casadi_design.errors import ProblemError
from casadi_design.measures.measures import information_matrices
from casadi_design.optimisation.artefact_pool import artefact_pool, artefact_scores, choose_clamps
from casadi_design.optimisation.bound import bound, pool_design
from casadi_design.plan.seated import APPROACH_M, seated_configurations, tilted
from casadi_design.problem.build import load_problem
from casadi_design.problem_file.measurement import PlacementSpec
from casadi_design.robot.robots import frame_placement
from tests.artefact_data import ball_socket_file
from tests.conftest import ROOT

PANDA = ROOT / "problems" / "panda_ball_socket.toml"
#: Seated configurations per point in these tests (the command draws 30).
PER_POINT = 8


@pytest.fixture(scope="module")
def panda():
    problem = load_problem(PANDA)
    return problem, seated_configurations(problem, PER_POINT)


def test_every_seated_configuration_puts_the_nominal_ball_in_its_socket(panda):
    problem, s = panda
    spec = problem.spec.measurement.artefact
    assert s.Q.shape == (len(spec.placements) * problem.artefact.K * PER_POINT, problem.robot.n)
    for q, k, g in zip(s.Q, s.point, s.placement):
        place = spec.placements[g]
        R = Rotation.from_euler("xyz", place.rpy_rad).as_matrix()  # roll, pitch, yaw: R = Rz Ry Rx
        socket = np.array(place.xyz_m) + R @ problem.artefact.points_m[k]
        M = frame_placement(problem.robot, q)
        assert np.linalg.norm(M.translation - socket) < 1e-7
        tilt = np.arccos(np.clip(-M.rotation[:, 2] @ R[:, 2], -1, 1))
        assert tilt <= spec.tilt_max_rad + 1e-9
        assert np.all(q >= problem.robot.q_min) and np.all(q <= problem.robot.q_max)
    # many postures per socket (a 7-joint arm keeps 4 degrees of freedom there), the same from the same seed
    one = s.Q[(s.point == 0) & (s.placement == 0)]
    assert np.min(np.std(one, axis=0)) > 0.05
    # drawn again (not the process's kept value, seated_configurations.memo): the same from the same seed
    assert np.array_equal(seated_configurations.__wrapped__(problem, PER_POINT).Q, s.Q)
    assert seated_configurations(problem, PER_POINT) is s and not s.Q.flags.writeable  # kept, read-only


def test_the_hand_s_orientations_are_uniform_over_the_cone():
    rng = np.random.default_rng(3)
    axis = np.array([0.2, -0.3, -0.9]) / np.linalg.norm([0.2, -0.3, -0.9])
    c = np.array([tilted(axis, np.radians(55), rng)[:, 2] @ axis for _ in range(4000)])
    assert c.min() >= np.cos(np.radians(55)) - 1e-12
    # uniform in solid angle: cos(tilt) uniform on [cos 55 deg, 1]
    assert np.mean(c) == pytest.approx((1 + np.cos(np.radians(55))) / 2, abs=0.01)
    assert np.std(c) == pytest.approx((1 - np.cos(np.radians(55))) / np.sqrt(12), abs=0.01)


def test_an_unreachable_placement_is_named_in_one_line():
    problem = load_problem(PANDA)
    far = replace(problem.spec.measurement.artefact, placements=(PlacementSpec("far", (3.0, 0.0, 0.0)),))
    problem = replace(problem, spec=replace(problem.spec, measurement=replace(problem.spec.measurement, artefact=far)))
    with pytest.raises(ProblemError) as info:
        seated_configurations(problem, 2)
    assert "'far'" in str(info.value) and "point 0" in str(info.value) and "\n" not in str(info.value)


def test_a_program_stops_back_along_the_hand_s_axis(panda):
    from casadi_design.plan.seated import approaches

    problem, s = panda
    Q = s.Q[:4]
    for q, qa in zip(Q, approaches(problem, Q)):
        M, Ma = frame_placement(problem.robot, q), frame_placement(problem.robot, qa)
        assert np.allclose(Ma.rotation[:, 2], M.rotation[:, 2], atol=1e-7)  # its turn about the axis free
        assert np.allclose(Ma.translation, M.translation - APPROACH_M * M.rotation[:, 2], atol=1e-7)


def test_the_placement_is_chosen_by_the_measure(panda):
    problem, s = panda
    m = 12
    ch = choose_clamps(problem, s.Q, s.point, s.placement, s.names, "test-pose", m, 1, 1)
    values = {S: d.scores.max_rms_error_m for S, d in ch.by_set if d is not None}
    assert len(values) == len(s.names) and values[ch.placements] == min(values.values())
    d = ch.design
    assert set(d.seated.placement) == set(ch.placements) and np.array_equal(d.Q, s.Q[ch.rows])
    # the one scorer: the plan scored alone gives the design's error at every test pose
    again = artefact_scores(problem, d.Q, d.seated.point, d.seated.placement)
    assert np.allclose(again.rms_error_m, d.scores.rms_error_m, rtol=1e-9)
    # no plan of m configurations of a set beats the set's certified bound
    for S, plan in ch.by_set:
        rows = np.isin(s.placement, S)
        pool = artefact_pool(problem, s.Q[rows], s.point[rows], s.placement[rows])
        A = information_matrices(pool.B[pool.kept])
        approx = pool_design(problem, "test-pose", s.Q[rows][pool.kept], np.zeros((int(pool.kept.sum()), 0)), A, m,
                             pool.B0)
        assert bound(problem, m, approx, pool.B.shape[2]).value <= plan.scores.max_rms_error_m * (1 + 1e-9)


def test_a_six_joint_ur5_s_plans_from_nothing_identify_its_base_set():
    """A UR5 with a ball on its flange (examples/ur5_ball_socket.toml): a placement's seated
    configurations tell its tracker base set less the 6 parameters a rigid motion of the robot
    makes (``shoulder_lift_joint.rx`` with them: the configurations leave 4e-8 of its own effect,
    the inverse kinematics' rounding); the plan the NLP moves along the sockets (seated to 1e-12
    m) scores regular, alone, as the design said. Before, rx was kept, every plan was singular and
    ``solve`` refused the file; a plan of the NLP lost a parameter to the rounding."""
    problem = load_problem(ROOT / "examples" / "ur5_ball_socket.toml")
    s = seated_configurations(problem, PER_POINT)
    left = s.placement == 2  # its plan of the NLP lost a parameter to the rounding (front's did not)
    pool = artefact_pool(problem, s.Q[left], s.point[left], s.placement[left])
    assert len(pool.names) == problem.model.L - 6 and "shoulder_lift_joint.rx" not in pool.names
    ch = choose_clamps(problem, s.Q[left], s.point[left], s.placement[left], s.names, "test-pose", 9, 1, 1,
                       seated=True)
    d = ch.design
    again = artefact_scores(problem, d.Q, d.seated.point, d.seated.placement)
    assert again.identifiable and np.allclose(again.rms_error_m, d.scores.rms_error_m, rtol=1e-6)


#: An arm of 5 joints (SO-100) with a ball 50 mm out of its gripper, the tool at one spot.
SO100_ROBOT = {"urdf": "example-robot-data:so_arm_description/urdf/so100.urdf", "frame": "gripper",
               "tool_xyz_m": [0.0, 0.0, 0.05]}
SO100_PLACEMENTS = [{"name": "side", "xyz_m": [0.1266, -0.1608, 0.2493], "rpy_deg": [0, 0, 60]}]
SO100_TEST_Q = [[1.0736, 1.9781, -0.3238, -2.1176, 1.1533], [-0.7348, 1.0842, -0.0013, -1.8130, 1.5137],
                [1.1836, 1.5531, -0.5737, -1.1632, 1.2909], [-1.0664, 0.3951, -0.3674, -0.7764, 1.5087]]


def test_a_five_joint_arm_is_seated_by_the_ball_s_position_within_the_tilt(tmp_path):
    """An arm of 5 joints (SO-100) reaches few hand orientations: its configurations are seated
    by the ball's position alone and kept within the tilt. Drawn with the orientation too, as a
    6-joint arm's, no configuration of 300 tried was seated and solve refused the placement."""
    problem = load_problem(ball_socket_file(tmp_path / "so100.toml", "so100_ball_socket", SO100_ROBOT, SO100_TEST_Q,
                                            SO100_PLACEMENTS))
    assert problem.robot.n == 5
    s = seated_configurations(problem, PER_POINT)
    spec = problem.spec.measurement.artefact
    R = Rotation.from_euler("xyz", spec.placements[0].rpy_rad).as_matrix()
    assert len(s.Q) == problem.artefact.K * PER_POINT
    for q, k in zip(s.Q, s.point):
        M = frame_placement(problem.robot, q)
        assert np.linalg.norm(M.translation - (np.array(spec.placements[0].xyz_m) + R @ problem.artefact.points_m[k])) < 1e-7
        assert -M.rotation[:, 2] @ R[:, 2] >= np.cos(spec.tilt_max_rad) - 1e-12
    d = choose_clamps(problem, s.Q, s.point, s.placement, s.names, "test-pose", 12, 1, 1, seated=True).design
    assert artefact_scores(problem, d.Q, d.seated.point, d.seated.placement).identifiable
    # the robot program's stops: the ball 20 mm back along the hand's axis (the plan's joints at
    # their limits: the hand held at its orientation, as a 6-joint arm's, reached none of them)
    from casadi_design.plan.seated import approaches

    assert np.any(np.isclose(d.Q, problem.robot.q_min) | np.isclose(d.Q, problem.robot.q_max))
    for q, qa in zip(d.Q, approaches(problem, d.Q)):
        M, Ma = frame_placement(problem.robot, q), frame_placement(problem.robot, qa)
        assert np.allclose(Ma.translation, M.translation - APPROACH_M * M.rotation[:, 2], atol=1e-7)
        assert np.all(qa >= problem.robot.q_min) and np.all(qa <= problem.robot.q_max)


def test_too_few_configurations_are_refused_naming_the_fewest(panda):
    """m configurations give 3 m values: fewer than the base set and the placement's pose
    (25 + 5 on the Panda) is refused in one line naming the fewest m, not as configurations that
    do not vary enough."""
    problem, s = panda
    with pytest.raises(ProblemError, match=r"--m 9: 9 configurations give 27 values, fewer than the 30 unknowns \(25 "
                                           r"parameters .* and 5 of the placements' poses\); give m >= 10$"):
        choose_clamps(problem, s.Q, s.point, s.placement, s.names, "D", 9, 1, 1)
    assert choose_clamps(problem, s.Q, s.point, s.placement, s.names, "D", 10, 1, 1).design.scores.identifiable
