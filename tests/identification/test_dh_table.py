"""The calibrated DH table (identification/dh_table.py, ``calibrated_dh.toml``): it reproduces
the calibrated chain exactly, gives the nominal table back, and ``identify`` writes it as a
problem file with the kinematics of ``calibrated.urdf``.

The calibrated chains are made here, independently of the package's error model: every joint
placement of the Pinocchio model perturbed by 0.5 mm / 1 mrad, a joint-zero offset per joint
(a rotation about its axis), and the measured frame moved by 0.5 mm / 1 mrad. The robots are
built from their ``[robot]`` alone (no calibration model, no cell): each check takes
milliseconds."""

import json
import tomllib

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.cli import main
from casadi_design.calibrated.dh_table import calibrated_dh, is_hayati
from casadi_design.calibrated.urdf import MEASURED_POINT, CalibratedChain, calibrated_model
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_robot, load_problem
from casadi_design.problem_file.read import parse_problem, read_problem
from casadi_design.problem_file.robot import DHRow, RobotSpec
from casadi_design.robot.robots import frame_placement, make_robot
from tests.conftest import ROOT
from tests.identify_data import measured, measurement_csv, perturbed

ABB = ROOT / "problems" / "abb_irb6640_machining.toml"
#: The derived table and the calibrated chain agree to this (m, and rad for the rotations).
EXACT = 1e-9
#: The nominal table re-derived from the nominal chain: to rounding (m, rad).
ROUNDING = 1e-12
LENGTH_M, ANGLE_RAD = 0.5e-3, 1e-3
#: A small modified-DH (Craig) arm with the hard cases: axes 2, 3 and 4 parallel (two Hayati
#: links, a nonzero d between them), axes 4 and 5 intersecting, a flange and a tool; geometric,
#: one measured point off the last axis.
CRAIG_TOML = """
name = "craig_5r"
[robot]
frame = "flange"
tool_xyz_m = [0.05, 0.0, 0.10]
[robot.dh]
convention = "modified"
flange_xyz_m = [0.01, 0.02, 0.10]
flange_rpy_deg = [5.0, 10.0, 15.0]
joints = [
  { name = "j1", type = "R", theta_offset_deg = 0.0, d_m = 0.40, a_m = 0.0, alpha_deg = 0.0, limits_deg = [-170.0, 170.0] },
  { name = "j2", type = "R", theta_offset_deg = 30.0, d_m = 0.0, a_m = 0.10, alpha_deg = 90.0, limits_deg = [-170.0, 170.0] },
  { name = "j3", type = "R", theta_offset_deg = 0.0, d_m = 0.05, a_m = 0.50, alpha_deg = 0.0, limits_deg = [-170.0, 170.0] },
  { name = "j4", type = "R", theta_offset_deg = -90.0, d_m = 0.30, a_m = 0.40, alpha_deg = 0.0, limits_deg = [-170.0, 170.0] },
  { name = "j5", type = "R", theta_offset_deg = 0.0, d_m = 0.10, a_m = 0.0, alpha_deg = -90.0, limits_deg = [-170.0, 170.0] },
]
[calibration]
case = "geometric"
parameters = "identifiable"
[measurement]
components = ["x", "y", "z"]
sigma_m = 1.0e-5
[test_poses]
components = ["x", "y", "z"]
joints_rad = [[0.1, 0.2, 0.3, 0.4, 0.5], [-0.5, 0.4, -0.3, 0.2, -0.1]]
[experiments]
m = [30]
[design]
criteria = ["D"]
"""
CRAIG = parse_problem(tomllib.loads(CRAIG_TOML), "craig.toml").robot


def axis_links(spec: RobotSpec) -> tuple[DHRow, ...]:
    """The rows holding the links between consecutive axes (n - 1 of them)."""
    return spec.dh_rows[:-1] if spec.dh_convention == "standard" else spec.dh_rows[1:]


def perturbed_chain(robot, rng) -> CalibratedChain:
    """The chain of ``robot`` (a Robot) calibrated by random errors (module docstring)."""
    joints = []
    for jid in robot.joint_ids:
        error = pin.SE3(pin.exp3(rng.normal(0, ANGLE_RAD, 3)), rng.normal(0, LENGTH_M, 3))
        zero = pin.SE3(pin.exp3(np.array([0.0, 0.0, rng.normal(0, ANGLE_RAD)])), np.zeros(3))  # DH joints turn about z
        joints.append(robot.model.jointPlacements[jid] * error * zero)
    tool = pin.SE3(pin.exp3(rng.normal(0, ANGLE_RAD, 3)), rng.normal(0, LENGTH_M, 3))
    return CalibratedChain(tuple(joints), robot.model.frames[robot.frame_id].placement * tool)


def kinematics_gap(a, b, Q, markers) -> tuple[float, float]:
    """Largest gap (m) between the measured points (``markers`` in the measured frame) of robots
    ``a`` and ``b`` over the rows of ``Q``, and between their joint axes: the angle (rad)
    between the z axes and the distance (m) of a's joint origin from b's axis line."""
    da, db = a.model.createData(), b.model.createData()
    points = axes = 0.0
    for q in Q:
        Ma, Mb = frame_placement(a, q), frame_placement(b, q)
        gap = (markers @ Ma.rotation.T + Ma.translation) - (markers @ Mb.rotation.T + Mb.translation)
        points = max(points, np.abs(gap).max())
        pin.forwardKinematics(a.model, da, a.full_q(q))
        pin.forwardKinematics(b.model, db, b.full_q(q))
        for ja, jb in zip(a.joint_ids, b.joint_ids):
            za, zb = da.oMi[ja].rotation[:, 2], db.oMi[jb].rotation[:, 2]
            offset = da.oMi[ja].translation - db.oMi[jb].translation
            axes = max(axes, np.linalg.norm(np.cross(za, zb)), np.linalg.norm(np.cross(offset, zb)))
    return float(points), float(axes)


@pytest.mark.parametrize("spec, markers, parallel", [
    (read_problem(ABB).robot, np.array(read_problem(ABB).measurement.markers_m), 1),  # axes 2-3
    (CRAIG, np.array([[0.0, 0.0, 0.0], [0.1, -0.05, 0.02]]), 2),  # axes 2-3 and 3-4
], ids=["abb-standard", "craig-modified"])
def test_derived_table_reproduces_the_calibrated_chain(spec, markers, parallel):
    robot = build_robot(spec)
    rng = np.random.default_rng(3)
    Q = rng.uniform(robot.q_min, robot.q_max, (50, robot.n))
    for _ in range(5):
        chain = perturbed_chain(robot, rng)
        table = calibrated_dh(spec, chain)
        points, axes = kinematics_gap(build_robot(table), make_robot(calibrated_model(robot, chain), robot.frame), Q, markers)
        assert points < EXACT and axes < EXACT
        # Hayati exactly where the nominal axes are parallel, small values everywhere
        for nominal, row in zip(spec.dh_rows, table.dh_rows):
            assert abs(row.theta_offset_rad - nominal.theta_offset_rad) < 20 * ANGLE_RAD
            assert abs(row.alpha_rad - nominal.alpha_rad) < 10 * ANGLE_RAD
            assert abs(row.a_m - nominal.a_m) < 10 * LENGTH_M and abs(row.d_m - nominal.d_m) < 10 * LENGTH_M
        hayati = [is_hayati(link) for link in axis_links(spec)]
        assert [link.beta_rad != 0 for link in axis_links(table)] == hayati and sum(hayati) == parallel
        assert max(np.abs(table.base_xyz_m)) < 10 * LENGTH_M and max(np.abs(table.base_rpy_rad)) < 10 * ANGLE_RAD


def test_nominal_chain_gives_the_nominal_table():
    spec = read_problem(ABB).robot
    robot = build_robot(spec)
    nominal = CalibratedChain(tuple(robot.model.jointPlacements[j] for j in robot.joint_ids),
                              robot.model.frames[robot.frame_id].placement)
    table = calibrated_dh(spec, nominal)
    for row, want in zip(table.dh_rows, spec.dh_rows):
        got = np.array([row.theta_offset_rad, row.d_m, row.a_m, row.alpha_rad, row.beta_rad])
        np.testing.assert_allclose(got, [want.theta_offset_rad, want.d_m, want.a_m, want.alpha_rad, 0.0],
                                   atol=ROUNDING, err_msg=row.name)
        assert (row.name, row.kind, row.lower, row.upper) == (want.name, want.kind, want.lower, want.upper)
    np.testing.assert_allclose(np.r_[table.base_xyz_m, table.base_rpy_rad], 0.0, atol=ROUNDING)
    got = pin.SE3(pin.rpy.rpyToMatrix(*table.flange_rpy_rad), np.array(table.flange_xyz_m))
    want = pin.SE3(pin.rpy.rpyToMatrix(*spec.flange_rpy_rad), np.array(spec.flange_xyz_m))
    assert np.abs((got.inverse() * want).homogeneous - np.eye(4)).max() < ROUNDING


def test_identify_writes_a_calibrated_dh_problem_with_the_urdfs_kinematics(tmp_path, capsys):
    """A modified-DH arm identified from 30 points of a perturbed robot: calibrated_dh.toml
    loads with the package's loader (built, test poses by joints) and its measured point is
    calibrated.urdf's ``measured_point`` at every q."""
    path = tmp_path / "craig.toml"
    path.write_text(CRAIG_TOML)
    problem = load_problem(path)
    true = perturbed(problem, np.random.default_rng(5))
    Q, F = random_plan(problem, 30, np.random.default_rng(6))
    (tmp_path / "meas.csv").write_text(measurement_csv(problem, Q, F, measured(problem, true, Q, F, np.random.default_rng(7))))
    out = tmp_path / "out"
    assert main(["identify", str(path), "--measurements", str(tmp_path / "meas.csv"), "--out", str(out)]) == 0
    assert "calibrated_dh.toml" in capsys.readouterr().out
    record = json.loads((out / "identification.json").read_text())
    assert record["files"]["dh_problem"] == "calibrated_dh.toml"
    assert "calibrated_dh.toml" in (out / "identification.md").read_text()

    again = load_problem(out / "calibrated_dh.toml")
    assert again.name == "craig_5r_calibrated_dh" and again.robot.frame == "tcp"
    np.testing.assert_allclose(again.test_poses.q, problem.test_poses.q)
    urdf = make_robot(pin.buildModelFromUrdf(str(out / "calibrated.urdf")), MEASURED_POINT)
    Qr = np.random.default_rng(8).uniform(problem.robot.q_min, problem.robot.q_max, (50, problem.robot.n))
    points, axes = kinematics_gap(again.robot, urdf, Qr, np.zeros((1, 3)))
    assert points < EXACT and axes < EXACT
    # the table is not the nominal one: the identified errors are in it
    assert max(abs(a.d_m - b.d_m) + abs(a.a_m - b.a_m) for a, b in zip(again.spec.robot.dh_rows, problem.spec.robot.dh_rows)) > 1e-5
