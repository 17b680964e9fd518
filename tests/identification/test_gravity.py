"""Joint compliance under the robot's own weight: the symbolic gravity torques and the moments
each joint's bearing carries against Pinocchio's, a tilt compliance bending the joint's placement
by them, and a UR10 that sags under its weight (simulated with Pinocchio) identified by the
gravity candidate of identify, its compliances within 3 standard deviations."""

import math
import re

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.cli.identify import load_without_cell
from casadi_design.identification.calibrate import calibrate
from casadi_design.identification.fit import fit, fit_model, register
from casadi_design.identification.measurements import read_measurements
from casadi_design.plan.sampling import random_plan
from tests.conftest import ROOT
from tests.identify_data import TrueRobot, measured, measurement_csv, perturbed

UR10 = ROOT / "problems" / "ur10_drilling.toml"
TIAGO = ROOT / "tests" / "data" / "tiago_mocap" / "tiago_mocap.toml"
#: Compliances of the true UR10 (rad/(N m)): the shoulder and elbow carry 60 to 150 N m.
K_TRUE = np.array([0.0, 2e-5, 3e-5, 4e-5, 0.0, 0.0])


@pytest.mark.parametrize("path", [UR10, TIAGO])
def test_gravity_torques_are_pinocchios(path):
    problem = load_without_cell(str(path))
    robot, g_fn = problem.robot, problem.model.kinematics.gravity_torque
    data = robot.model.createData()
    cols = [robot.model.joints[j].idx_v for j in robot.joint_ids]
    rng = np.random.default_rng(2)
    for _ in range(5):
        q = rng.uniform(np.maximum(robot.q_min, -math.pi), np.minimum(robot.q_max, math.pi))
        expected = pin.computeGeneralizedGravity(robot.model, data, robot.full_q(q))[cols]
        assert np.abs(expected).max() > 1.0  # N m: the arm has weight
        np.testing.assert_allclose(np.asarray(g_fn(q)).ravel(), expected, atol=1e-9)


@pytest.mark.parametrize("path", [UR10, ROOT / "problems" / "panda_ball_socket.toml"])
def test_the_moments_on_each_joint_are_pinocchios(path):
    """``dV/dPi`` at a joint's placement errors (rx, ry, rz, offset) is the moment its bearing
    carries: Pinocchio's recursive Newton-Euler force across the joint, in the joint's placement
    frame (its own rotation undone)."""
    problem = load_without_cell(str(path))
    robot, kin = problem.robot, problem.model.kinematics
    data = robot.model.createData()
    rng = np.random.default_rng(3)
    for _ in range(3):
        q = rng.uniform(np.maximum(robot.q_min, -math.pi), np.minimum(robot.q_max, math.pi))
        G = np.asarray(kin.gravity_moments(q)).ravel()
        pin.rnea(robot.model, data, robot.full_q(q), np.zeros(robot.model.nv), np.zeros(robot.model.nv))
        for k, (joint, jid) in enumerate(zip(robot.joints, robot.joint_ids)):
            axis = np.asarray(robot.model.joints[jid].extract().axis if "Unaligned" in
                              robot.model.joints[jid].shortname() else np.eye(3)["XYZ".index(
                                  robot.model.joints[jid].shortname()[-1])])
            moment = pin.exp3(axis * q[k]) @ data.f[jid].angular
            i = kin.parameter_names.index(f"{joint}.rx")
            np.testing.assert_allclose(G[i:i + 3], moment, atol=1e-9)
            assert G[kin.parameter_names.index(f"{joint}.offset")] == pytest.approx(moment @ axis, abs=1e-9)


def test_a_tilt_compliance_bends_the_joint_s_placement_by_its_moment():
    """X = k on ``k.<joint>.rx`` puts the measured frame where the kinematics put it with the
    joint's placement turned by ``-k dV/drx`` (no joint deflects, so the fixed point is exact)."""
    from casadi_design.calibration.models import calibration_model

    problem = load_without_cell(str(ROOT / "problems" / "panda_ball_socket.toml"))
    kin = problem.model.kinematics
    model = calibration_model(kin, "elastostatic", measured=("x", "y", "z"), compliant=("panda_joint3.rx",),
                              gravity=True)
    assert model.parameter_names == ("k.panda_joint3.rx",)
    q, k = np.array([0.3, 0.5, -0.2, -2.0, 0.4, 1.8, 0.7]), 2e-5
    i = kin.parameter_names.index("panda_joint3.rx")
    Pi = np.zeros(len(kin.parameter_names))
    Pi[i] = -k * float(np.asarray(kin.gravity_moments(q)).ravel()[i])
    assert abs(Pi[i]) > 1e-5  # rad: a real bend
    R, p = (np.asarray(v) for v in kin.placement(q, Pi))
    pose = np.asarray(model.pose(q, np.zeros(0), np.array([k]))).ravel()
    np.testing.assert_allclose(pose[9:12], p.ravel(), atol=1e-12)
    np.testing.assert_allclose(pose[:9].reshape(3, 3).T, R, atol=1e-12)


@pytest.fixture(scope="module")
def sagging_ur10(tmp_path_factory):
    problem = load_without_cell(str(UR10))
    true = perturbed(problem, np.random.default_rng(4), k=K_TRUE)
    Q, F = random_plan(problem, 60, np.random.default_rng(5))
    P = measured(problem, true, Q, F, np.random.default_rng(6), gravity=True)
    path = tmp_path_factory.mktemp("sag") / "meas.csv"
    path.write_text(measurement_csv(problem, Q, F, P))
    return problem, read_measurements(problem, str(path))


def test_compliances_under_own_weight_are_identified(sagging_ur10):
    problem, meas = sagging_ur10
    problem, _, T0, _ = register(problem, "tracker", meas)
    names = problem.model.parameter_names + tuple(f"k.{j}" for j in problem.robot.joints)
    fm = fit_model(problem, "tracker", names, gravity=True)
    f = fit(problem, fm, meas, T0, np.ones(meas.m, dtype=bool))
    std = problem.sigma_m * np.sqrt(np.diagonal(np.linalg.inv(f.information)))
    kept = fm.model.parameter_names
    found = {n[2:] for n in kept if n.startswith("k.")}
    assert {"shoulder_lift_joint", "elbow_joint", "wrist_1_joint"} <= found
    for j in found:
        i = kept.index(f"k.{j}")
        k = K_TRUE[problem.robot.joints.index(j)]
        assert abs(f.X[i] - k) <= 3 * std[i], (j, f.X[i], k, std[i])
    # residuals at the noise: the model explains the sag (sigma 25 um per coordinate)
    assert np.sqrt(np.mean(f.r[f.mask] ** 2)) < 1.5 * problem.sigma_m


def test_auto_prefers_the_gravity_model_for_a_sagging_arm(sagging_ur10):
    problem, meas = sagging_ur10
    cal = calibrate(problem, meas)
    names = [c.name for c in cal.candidates]
    assert any(n.endswith("+ gravity") for n in names)
    assert cal.model.endswith("+ gravity"), [(c.name, c.cv_rms_m) for c in cal.candidates]
    # its robot files hold the kinematics only: the note says how far they are without the sag
    (note,) = [n for n in cal.notes if "under the robot's own weight" in n]
    without, with_sag = (float(v) for v in re.findall(r"([\d.]+) mm", note))
    assert with_sag == pytest.approx(np.sqrt(np.mean(cal.residual_rms_m[cal.fit.used] ** 2)) * 1e3, abs=1e-3)
    assert without > 3 * with_sag  # the UR10 sags by millimetres under its weight


#: An elasto-static case of a robot whose URDF gives the links' masses: the UR5's joints 1 to 5
#: under a load of up to 50 N at a point 150 mm out of the flange (no cell).
UR5_ELASTOSTATIC = """
name = "ur5_compliances"
[robot]
urdf = "example-robot-data:ur_description/urdf/ur5_robot.urdf"
frame = "tool0"
tool_xyz_m = [0.0, 0.0, 0.15]
[calibration]
case = "elastostatic"
compliant_joints = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint"]
wrench_components = ["fx", "fy", "fz"]
[measurement]
components = ["x", "y", "z"]
sigma_m = 2.0e-5
[test_poses]
components = ["x", "y", "z"]
tool_rpy_deg = [180.0, 0.0, 0.0]
seed_q_deg = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]
force_N = [0.0, 20.0, -30.0]
path = { kind = "points", points_m = [[0.5, 0.0, 0.15], [0.4, 0.1, 0.15]] }
[experiments]
m = [6]
[experiments.force]
mode = "bound"
magnitude_N = 50.0
[design]
criteria = ["D"]
"""


def test_an_elastostatic_case_is_identified_in_the_base_frame(tmp_path):
    """``identify --frame base`` on an elasto-static case with the robot's weight: its gravity
    candidates are elasto-static models too (they were built as case 'both' without geometric
    errors, and every model was refused); the compliances come within 3 standard deviations
    of the true ones, the robot's own sag simulated by Pinocchio."""
    path = tmp_path / "ur5.toml"
    path.write_text(UR5_ELASTOSTATIC)
    problem = load_without_cell(str(path))
    k_true = np.array([2e-6, 1.5e-6, 2.5e-6, 6e-6, 5e-6, 8e-6])
    true = TrueRobot(pin.Model(problem.robot.model), problem.robot.frame_id, k_true, pin.SE3.Identity())
    Q, F = random_plan(problem, 30, np.random.default_rng(1))
    csv = tmp_path / "meas.csv"
    csv.write_text(measurement_csv(problem, Q, F, measured(problem, true, Q, F, np.random.default_rng(2), gravity=True)))
    cal = calibrate(problem, read_measurements(problem, str(csv)), frame="base")
    assert any(c.name.endswith("+ gravity") and not math.isnan(c.cv_rms_m) for c in cal.candidates)
    names = cal.fit.fit.model.parameter_names
    assert {f"k.{j}" for j in problem.spec.calibration.compliant_joints} <= set(names), (cal.model, names)
    for i, name in enumerate(names):
        if name.startswith("k."):
            k = k_true[problem.robot.joints.index(name[2:])]
            assert abs(cal.fit.X[i] - k) <= 3 * cal.std[i], (name, cal.fit.X[i], k, cal.std[i])
