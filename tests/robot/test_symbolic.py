"""The CasADi translator against Pinocchio's own numeric kinematics."""

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.problem.build import load_problem
from casadi_design.robot.robots import (
    frame_jacobian,
    frame_placement,
    load_urdf,
    make_robot,
    planar_arm,
)
from casadi_design.robot.symbolic import PLACEMENT_ERRORS, parameter_names, symbolic_kinematics
from tests.conftest import ROOT

TOL = 1e-10
FD_STEP = 1e-6
FD_TOL = 1e-8

ROBOTS = {
    "planar": (lambda: planar_arm([0.6, 0.4]), "tool"),
    "planar3": (lambda: planar_arm([0.5, 0.3, 0.2]), "tool"),
    "ur5": (lambda: load_urdf("example-robot-data:ur_description/urdf/ur5_robot.urdf"), "tool0"),
    "ur10": (lambda: load_urdf("example-robot-data:ur_description/urdf/ur10_robot.urdf"), "tool0"),
    "panda": (lambda: load_urdf("example-robot-data:panda_description/urdf/panda.urdf"), "panda_hand"),
    # a link named as a joint (Pinocchio's getFrameId refuses the name): the link's frame
    "z1": (lambda: load_urdf("example-robot-data:z1_description/urdf/z1.urdf"), "gripperStator"),
    "so100": (lambda: load_urdf("example-robot-data:so_arm_description/urdf/so100.urdf"), "gripper"),
    "abb_irb6640": (lambda: load_urdf(str(ROOT / "problems/robots/abb_irb6640_180_255.urdf")), "tool0"),
    "abb_irb6640_dh": (lambda: load_problem(ROOT / "problems/abb_irb6640_machining.toml").robot.model, "tcp"),
}


@pytest.fixture(params=list(ROBOTS), scope="module")
def robot_kin(request):
    build, frame = ROBOTS[request.param]
    robot = make_robot(build(), frame)
    return robot, symbolic_kinematics(robot)


def test_placement_and_jacobian_match_pinocchio(robot_kin):
    robot, kin = robot_kin
    rng = np.random.default_rng(0)
    zero = np.zeros(len(kin.parameter_names))
    for _ in range(25):
        q = rng.uniform(robot.q_min, robot.q_max)
        R, p = (np.asarray(v) for v in kin.placement(q, zero))
        ref = frame_placement(robot, q)
        np.testing.assert_allclose(R, ref.rotation, atol=TOL)
        np.testing.assert_allclose(p.ravel(), ref.translation, atol=TOL)
        np.testing.assert_allclose(np.asarray(kin.jacobian(q)), frame_jacobian(robot, q), atol=TOL)


def _perturbed_pinocchio(robot, name: str, eps: float) -> pin.Model:
    """A copy of the Pinocchio model with one geometric error applied (independent of CasADi)."""
    model = pin.Model(robot.model)
    part, err = name.split(".")
    d = np.zeros(6)
    if err != "offset":
        d[PLACEMENT_ERRORS.index(err)] = eps
    E = pin.SE3(pin.rpy.rpyToMatrix(0, 0, 0), d[:3])
    E.rotation = (
        pin.AngleAxis(d[3], np.array([1.0, 0, 0])).matrix()
        @ pin.AngleAxis(d[4], np.array([0, 1.0, 0])).matrix()
        @ pin.AngleAxis(d[5], np.array([0, 0, 1.0])).matrix()
    )
    if part == "tool":
        fid = robot.frame_id
        f = model.frames[fid]
        f.placement = f.placement * E
        model.frames[fid] = f
    elif part == "base":
        jid = robot.joint_ids[0]
        model.jointPlacements[jid] = E * model.jointPlacements[jid]
    elif err != "offset":
        jid = model.getJointId(part)
        model.jointPlacements[jid] = model.jointPlacements[jid] * E
    return model


def _pose(model, robot, q):
    data = model.createData()
    pin.framesForwardKinematics(model, data, robot.full_q(q))
    return data.oMf[robot.frame_id]


def test_error_jacobian_matches_finite_differences_of_pinocchio(robot_kin):
    """Each column of J_Pi against central differences of Pinocchio's FK with the error applied."""
    robot, kin = robot_kin
    rng = np.random.default_rng(1)
    for _ in range(3):
        q = rng.uniform(robot.q_min, robot.q_max)
        J_Pi = np.asarray(kin.error_jacobian(q))
        for k, name in enumerate(kin.parameter_names):
            joint = name.split(".")[0]
            if name.endswith(".offset"):
                dq = np.zeros(robot.n)
                dq[robot.joints.index(joint)] = FD_STEP
                plus, minus = _pose(robot.model, robot, q + dq), _pose(robot.model, robot, q - dq)
            else:
                plus = _pose(_perturbed_pinocchio(robot, name, FD_STEP), robot, q)
                minus = _pose(_perturbed_pinocchio(robot, name, -FD_STEP), robot, q)
            dp = (plus.translation - minus.translation) / (2 * FD_STEP)
            dth = pin.log3(plus.rotation @ minus.rotation.T) / (2 * FD_STEP)
            np.testing.assert_allclose(J_Pi[:, k], np.r_[dp, dth], atol=FD_TOL, err_msg=name)


def test_parameter_names_count():
    robot = make_robot(planar_arm([0.6, 0.4]), "tool")
    names = parameter_names(robot)
    assert len(names) == 6 + 7 * robot.n + 6
    assert names[6] == "joint1.offset" and names[-1] == "tool.rz"


def test_a_link_named_as_its_joint_is_measured_at_the_link():
    """Unitree Z1's URDF names a link as the fixed joint that carries it (``gripperStator``):
    Pinocchio's ``getFrameId`` refuses the name; the robot is measured at the link's frame, where
    the joint's is too."""
    model = load_urdf("example-robot-data:z1_description/urdf/z1.urdf")
    ids = [i for i, f in enumerate(model.frames) if f.name == "gripperStator"]
    assert len(ids) == 2
    with pytest.raises(ValueError):
        model.getFrameId("gripperStator")
    robot = make_robot(model, "gripperStator")
    assert model.frames[robot.frame_id].type == pin.FrameType.BODY
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.randomConfiguration(model))
    assert np.allclose(data.oMf[ids[0]].homogeneous, data.oMf[ids[1]].homogeneous, atol=1e-12)


KINOVA = "example-robot-data:kinova_description/robots/kinova.urdf"


def test_a_continuous_joint_with_limits_given_is_read_as_revolute():
    """Kinova's URDF declares joints 1, 4 and 6 continuous (Pinocchio: cos and sin, two
    coordinates): refused in one line naming [robot.joint_limits_rad]; with limits given there,
    read as revolute joints with those limits, whose kinematics is Pinocchio's continuous joint's
    at the same angle (the effort and velocity of the URDF's <limit> kept)."""
    from casadi_design.errors import ProblemError

    original = load_urdf(KINOVA)
    with pytest.raises(ProblemError, match=r"joint 'j2s6s200_joint_1' is a continuous joint .* give its limits in "
                                           r"\[robot.joint_limits_rad\], e.g. j2s6s200_joint_1 = "):
        make_robot(original, "j2s6s200_link_6")
    limits = {f"j2s6s200_joint_{i}": (-6.0 - i / 10, 6.0 + i / 10) for i in (1, 4, 6)}
    model = load_urdf(KINOVA, limits)
    robot = make_robot(model, "j2s6s200_link_6")
    assert robot.n == 6 and original.nq == robot.n + 3
    for i in (1, 4, 6):
        j = robot.joints.index(f"j2s6s200_joint_{i}")
        assert (robot.q_min[j], robot.q_max[j]) == limits[f"j2s6s200_joint_{i}"]
        assert model.velocityLimit[j] == original.velocityLimit[original.joints[original.getJointId(robot.joints[j])].idx_v]
    data, odata = model.createData(), original.createData()
    fid, ofid = robot.frame_id, original.getFrameId("j2s6s200_link_6", pin.BODY)
    for q in np.random.default_rng(0).uniform(robot.q_min, robot.q_max, (5, robot.n)):
        oq = np.concatenate([[np.cos(v), np.sin(v)] if original.joints[original.getJointId(n)].nq == 2 else [v]
                             for n, v in zip(robot.joints, q)])
        pin.framesForwardKinematics(model, data, q)
        pin.framesForwardKinematics(original, odata, oq)
        assert np.allclose(data.oMf[fid].homogeneous, odata.oMf[ofid].homogeneous, atol=1e-12)
