"""Joint compliance under the robot's own weight: the symbolic gravity torques against
Pinocchio's, and a UR10 that sags under its weight (simulated with Pinocchio) identified by the
gravity candidate of identify, its compliances within 3 standard deviations."""

import math

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.cli.identify import load_without_cell
from casadi_design.identification.calibrate import calibrate
from casadi_design.identification.fit import fit, fit_model, register
from casadi_design.identification.measurements import read_measurements
from casadi_design.plan.sampling import random_plan
from tests.conftest import ROOT
from tests.identify_data import measured, measurement_csv, perturbed

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
