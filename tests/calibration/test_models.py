"""Calibration models B(q, F) against independent computations."""

import numpy as np
import pytest

from casadi_design.calibration.models import calibration_model
from casadi_design.errors import ProblemError
from casadi_design.problem.build import load_problem
from casadi_design.robot.robots import (
    frame_jacobian,
    frame_placement,
    load_urdf,
    make_robot,
    planar_arm,
)
from casadi_design.robot.symbolic import symbolic_kinematics
from tests.conftest import PROBLEM_FILES

FD_STEP = 1e-6
FD_TOL = 1e-8


@pytest.fixture(scope="module")
def planar():
    robot = make_robot(planar_arm([0.6, 0.4]), "tool")
    return robot, symbolic_kinematics(robot)


@pytest.fixture(scope="module")
def ur10():
    robot = make_robot(load_urdf("example-robot-data:ur_description/urdf/ur10_robot.urdf"), "tool0")
    return robot, symbolic_kinematics(robot)


@pytest.mark.parametrize("which", ["planar", "ur10"])
def test_A_is_the_derivative_of_the_compliant_deflection(which, request):
    """A k = d/d(eps) FK(q + eps diag(k) J^T W) at eps = 0, by central differences of Pinocchio."""
    robot, kin = request.getfixturevalue(which)
    force = ("fx", "fy") if which == "planar" else ("fx", "fy", "fz", "mx", "my", "mz")
    rows = ("x", "y") if which == "planar" else ("x", "y", "z")
    model = calibration_model(kin, "elastostatic", measured=rows, force=force)
    rng = np.random.default_rng(2)
    for _ in range(10):
        q = rng.uniform(robot.q_min, robot.q_max)
        F = rng.normal(scale=100.0, size=len(force))
        k = rng.uniform(0.5, 2.0, size=robot.n)
        W = np.zeros(6)
        W[[("fx", "fy", "fz", "mx", "my", "mz").index(c) for c in force]] = F
        dq = k * (frame_jacobian(robot, q).T @ W)
        plus = frame_placement(robot, q + FD_STEP * dq).translation
        minus = frame_placement(robot, q - FD_STEP * dq).translation
        fd = ((plus - minus) / (2 * FD_STEP))[: len(rows)]
        np.testing.assert_allclose(model.B_numeric(q, F) @ k, fd, rtol=1e-7, atol=FD_TOL * np.abs(F).max())


def test_planar_link_lengths_and_offsets_against_perturbed_arms(planar):
    """J_Pi columns of joint offsets and link lengths equal FK differences of re-built arms."""
    robot, kin = planar
    names = ("joint1.offset", "joint2.offset", "joint2.tx", "tool.tx")
    model = calibration_model(kin, "geometric", measured=("x", "y"), geometric=names)
    rng = np.random.default_rng(3)

    def fk(l1, l2, q):
        return frame_placement(make_robot(planar_arm([l1, l2]), "tool"), q).translation[:2]

    for _ in range(10):
        q = rng.uniform(-np.pi, np.pi, 2)
        e = FD_STEP
        cols = [
            (fk(0.6, 0.4, q + [e, 0]) - fk(0.6, 0.4, q - [e, 0])) / (2 * e),
            (fk(0.6, 0.4, q + [0, e]) - fk(0.6, 0.4, q - [0, e])) / (2 * e),
            (fk(0.6 + e, 0.4, q) - fk(0.6 - e, 0.4, q)) / (2 * e),
            (fk(0.6, 0.4 + e, q) - fk(0.6, 0.4 - e, q)) / (2 * e),
        ]
        np.testing.assert_allclose(model.B_numeric(q, np.zeros(0)), np.array(cols).T, atol=FD_TOL)


def test_combined_case_stacks_geometric_and_elastostatic(planar):
    robot, kin = planar
    geo = ("joint2.tx", "tool.tx")
    both = calibration_model(kin, "both", measured=("x", "y"), geometric=geo, force=("fx", "fy"))
    g = calibration_model(kin, "geometric", measured=("x", "y"), geometric=geo)
    e = calibration_model(kin, "elastostatic", measured=("x", "y"), force=("fx", "fy"))
    q, F = np.array([0.3, 1.1]), np.array([30.0, -80.0])
    assert both.parameter_names == geo + ("k.joint1", "k.joint2")
    np.testing.assert_allclose(both.B_numeric(q, F), np.hstack([g.B_numeric(q, F[:0]), e.B_numeric(q, F)]))


def test_accuracy_rows_can_differ_from_measured_rows(ur10):
    robot, kin = ur10
    model = calibration_model(kin, "elastostatic", measured=("x", "y", "z"), accuracy=("z",),
                              force=("fz",), compliant=("shoulder_lift_joint", "elbow_joint"))
    q, F = np.linspace(-1, 1, 6), np.array([-200.0])
    assert model.B_numeric(q, F).shape == (3, 2)
    np.testing.assert_allclose(model.B_numeric(q, F, accuracy=True), model.B_numeric(q, F)[2:3])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(case="geometric", measured=("x", "y")), "needs the geometric errors"),
        (dict(case="geometric", measured=("x", "y"), geometric=("joint3.offset",)), "unknown parameter 'joint3.offset'"),
        (dict(case="elastostatic", measured=("x", "w"), force=("fx",)), r"\[measurement\].components"),
        (dict(case="elastostatic", measured=("x",), force=("fx",), compliant=("elbow",)), "unknown joint 'elbow'"),
        (dict(case="elastostatic", measured=("x",), force=("f",)), r"\[calibration\].wrench_components"),
        (dict(case="thermal", measured=("x",)), "allowed: geometric, elastostatic, both"),
    ],
)
def test_model_errors(planar, kwargs, match):
    with pytest.raises(ProblemError, match=match):
        calibration_model(planar[1], **kwargs)


def _skew(c):
    return np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])


def _B_by_the_analytic_formula(problem, q, F, accuracy):
    """The linear model as it was written before the measurement model existed (the oracle):
    ``Wh G [J_Pi, A(q, W)] C^-1`` with G the marker map and ``A = [J_n J_n^T W]``."""
    model = problem.model
    kin, robot = model.kinematics, problem.robot
    R, _ = (np.asarray(v, dtype=float) for v in kin.placement(q, np.zeros(len(kin.parameter_names))))
    J = np.asarray(kin.jacobian(q), dtype=float)
    J_Pi = np.asarray(kin.error_jacobian(q), dtype=float)
    wrench = np.zeros(6)
    wrench[list(model.force_rows)] = F
    if not accuracy and problem.force is not None:
        wrench[3:] += np.cross(R @ np.array(problem.force.load_point_m), wrench[:3])
    cols = []
    for name in model.parameter_names:
        if name.startswith("k."):
            j = robot.joints.index(name[2:])
            cols.append(J[:, j] * (J[:, j] @ wrench))
        else:
            cols.append(J_Pi[:, kin.parameter_names.index(name)])
    T = np.array(cols).T
    rows = model.accuracy_rows if accuracy else model.measured_rows
    markers = np.zeros((1, 3)) if accuracy else model.markers_m
    pos, rot = [r for r in rows if r < 3], [r - 3 for r in rows if r >= 3]
    G = [np.hstack([np.eye(3), -_skew(R @ r)])[pos] for r in markers] if pos else []
    G += [np.hstack([np.zeros((3, 3)), np.eye(3)])[rot]] if rot else []
    G = np.vstack(G)
    spec = problem.spec.measurement
    if not accuracy and spec.whitening is not None:
        G = np.array(spec.whitening) @ G
    return G @ T / model.column_scale


@pytest.mark.parametrize("path", PROBLEM_FILES, ids=lambda p: p.stem)
def test_B_is_the_jacobian_of_the_measurement_model_on_every_problem(path):
    """B = dy/dX at X = 0 equals the analytic linear model (markers, load-point moment, whitening,
    column scaling), at random configurations and loads, for the measured and required rows."""
    problem = load_problem(path)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = rng.uniform(problem.robot.q_min, problem.robot.q_max)
        F = 100.0 * rng.normal(size=problem.model.nF)
        for accuracy in (False, True):
            expected = _B_by_the_analytic_formula(problem, q, F, accuracy)
            got = problem.model.B_numeric(q, F, accuracy)
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
