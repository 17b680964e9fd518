"""Translate a ``pinocchio.Model`` into CasADi expressions of the measured frame.

The PyPI ``pin`` wheels do not ship ``pinocchio.casadi``, so the forward kinematics is rebuilt
here from the model's joint placements, joint axes and frame placement, with the geometric
errors of the calibration model built in:

    oMf(q, Pi) = E(Pi_base) * prod_j [ jointPlacement_j * E(Pi_j) * X_j(q_j + dq_j) ] * fMt * E(Pi_tool)

where ``E(d) = (Rx(rx) Ry(ry) Rz(rz), (tx, ty, tz))`` is a small placement error (m, rad),
``dq_j`` is joint j's offset and ``X_j`` its motion (rotation about, or translation along, its
axis). At ``Pi = 0`` this is Pinocchio's kinematics; tests check it to 1e-10.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import pinocchio as pin

from .robots import Robot

#: The six components of a small placement error.
PLACEMENT_ERRORS = ("tx", "ty", "tz", "rx", "ry", "rz")


@dataclass(frozen=True, eq=False)
class SymbolicKinematics:
    """CasADi functions of the measured frame of a :class:`Robot`.

    Attributes
    ----------
    parameter_names : tuple of str
        Names of the full geometric error vector ``Pi``: ``base.<e>``, then per joint
        ``<joint>.offset`` and ``<joint>.<e>``, then ``tool.<e>``, with ``<e>`` in
        tx, ty, tz (m), rx, ry, rz (rad).
    placement : casadi.Function
        ``(q, Pi) -> (R, p)``: rotation (3 x 3) and position (3, m) of the frame in the world.
    jacobian : casadi.Function
        ``q -> J``: 6 x n Jacobian at ``Pi = 0``, rows (vx, vy, vz, wx, wy, wz), world-aligned
        axes at the frame origin (Pinocchio's LOCAL_WORLD_ALIGNED).
    error_jacobian : casadi.Function
        ``q -> J_Pi``: 6 x len(Pi) derivative of the frame's small displacement
        (dp, dtheta), same rows as ``jacobian``, with respect to ``Pi`` at ``Pi = 0``.
    joint_origins : casadi.Function
        ``q -> P``: 3 x n nominal positions (m) of the chain's joint origins.
    frame_origins : casadi.Function
        ``q -> P``: 3 x K nominal positions (m) of the distinct origins of every frame carried
        by a joint of the chain (link, joint, flange and tool frames), the measured frame last.
    frame_names : tuple of str
        A name for each column of ``frame_origins`` (a frame at that origin).
    gravity_torque : casadi.Function
        ``q -> g``: n joint torques (N m; N for prismatic joints) that hold the robot's own
        weight at ``Pi = 0``, ``g = dV/dq`` with ``V = -sum_b m_b g0 . c_b(q)`` over the bodies the
        chain moves (the URDF's inertias; the other joints at their neutral values) and ``g0``
        the model's gravity: Pinocchio's ``computeGeneralizedGravity`` for the chain's joints.
    gravity_moments : casadi.Function
        ``q -> G``: ``dV/dPi`` at ``Pi = 0`` (len(Pi)): the load the robot's own weight puts on
        each geometric error, e.g. at ``<joint>.rx`` and ``.ry`` the moment (N m) the joint's
        bearing carries about the x and y axes of its placement (the virtual work of a small
        tilt there), at ``<joint>.offset`` the joint's torque ``g``.
    """

    robot: Robot
    parameter_names: tuple[str, ...]
    placement: ca.Function
    jacobian: ca.Function
    error_jacobian: ca.Function
    joint_origins: ca.Function
    frame_origins: ca.Function
    frame_names: tuple[str, ...]
    gravity_torque: ca.Function
    gravity_moments: ca.Function


def rotation_about(axis: np.ndarray, angle: ca.SX) -> ca.SX:
    """Rotation matrix about a unit ``axis`` by ``angle`` (Rodrigues), exact zeros kept."""
    K = ca.SX(np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]))
    return ca.SX.eye(3) + ca.sin(angle) * K + (1 - ca.cos(angle)) * (K @ K)


def joint_axis(joint: pin.JointModel) -> tuple[np.ndarray, str]:
    kind = joint.shortname()
    unit = {"X": np.array([1.0, 0, 0]), "Y": np.array([0, 1.0, 0]), "Z": np.array([0, 0, 1.0])}
    if kind in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
        axis = np.asarray(joint.extract().axis, dtype=float)
        return axis / np.linalg.norm(axis), "R" if "Revolute" in kind else "P"
    return unit[kind[-1]], kind[len("JointModel")]


def _error_placement(d: ca.SX) -> tuple[ca.SX, ca.SX]:
    """``E(d)`` for ``d = (tx, ty, tz, rx, ry, rz)``: (Rx Ry Rz, t)."""
    R = rotation_about(np.array([1.0, 0, 0]), d[3]) @ rotation_about(np.array([0, 1.0, 0]), d[4])
    return R @ rotation_about(np.array([0, 0, 1.0]), d[5]), d[0:3]


def compose(Ra, pa, Rb, pb):
    return Ra @ Rb, pa + Ra @ pb


def twist_jacobian(R: ca.SX, p: ca.SX, v: ca.SX) -> ca.SX:
    """6 x len(v) derivative of the frame displacement (dp, dtheta) with respect to ``v``.

    Linear rows: ``dp/dv``. Angular rows: ``vee(dR/dv_k R^T)``, the world-aligned small
    rotation (rad) produced by a unit change of ``v_k``.
    """
    dR = ca.jacobian(ca.vec(R), v)
    cols = []
    for k in range(v.numel()):
        S = ca.reshape(dR[:, k], 3, 3) @ R.T
        cols.append(ca.vertcat(S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]) / 2)
    return ca.vertcat(ca.jacobian(p, v), ca.horzcat(*cols))


def parameter_names(robot: Robot) -> tuple[str, ...]:
    """Names of the full geometric error vector ``Pi`` (see :class:`SymbolicKinematics`)."""
    names = [f"base.{e}" for e in PLACEMENT_ERRORS]
    for joint in robot.joints:
        names += [f"{joint}.offset"] + [f"{joint}.{e}" for e in PLACEMENT_ERRORS]
    return tuple(names + [f"tool.{e}" for e in PLACEMENT_ERRORS])


def symbolic_kinematics(robot: Robot) -> SymbolicKinematics:
    """Build the CasADi kinematics of ``robot.frame`` with the geometric errors ``Pi``."""
    model = robot.model
    names = parameter_names(robot)
    q = ca.SX.sym("q", robot.n)
    Pi = ca.SX.sym("Pi", len(names))
    R, p = _error_placement(Pi[0:6])
    origins, carried, carried_names = [], [], []
    weights = carried_weights(robot)
    V = ca.SX(0)
    for k, jid in enumerate(robot.joint_ids):
        base = 6 + 7 * k
        M = model.jointPlacements[jid]
        R, p = compose(R, p, ca.SX(M.rotation), ca.SX(M.translation))
        R, p = compose(R, p, *_error_placement(Pi[base + 1 : base + 7]))
        origins.append(p)
        axis, kind = joint_axis(model.joints[jid])
        qk = q[k] + Pi[base]
        if kind == "R":
            R = R @ rotation_about(axis, qk)
        else:
            p = p + R @ (ca.SX(axis) * qk)
        for mass, lever in weights[k]:
            V -= mass * ca.dot(ca.DM(model.gravity.linear), p + R @ ca.DM(lever))
        points, point_names = _carried_frames(model, jid, R, p, exclude=robot.frame_id)
        carried += points
        carried_names += point_names
    fMt = model.frames[robot.frame_id].placement
    R, p = compose(R, p, ca.SX(fMt.rotation), ca.SX(fMt.translation))
    R, p = compose(R, p, *_error_placement(Pi[-6:]))

    zero = ca.DM.zeros(len(names))
    frames = ca.substitute(ca.horzcat(*carried, p), Pi, zero)
    J = ca.substitute(twist_jacobian(R, p, q), Pi, zero)
    J_Pi = ca.substitute(twist_jacobian(R, p, Pi), Pi, zero)
    return SymbolicKinematics(
        robot=robot,
        parameter_names=names,
        placement=ca.Function("placement", [q, Pi], [R, p], ["q", "Pi"], ["R", "p"]),
        jacobian=ca.Function("J", [q], [J], ["q"], ["J"]),
        error_jacobian=ca.Function("J_Pi", [q], [J_Pi], ["q"], ["J_Pi"]),
        joint_origins=ca.Function("origins", [q], [ca.substitute(ca.horzcat(*origins), Pi, zero)], ["q"], ["P"]),
        frame_origins=ca.Function("frame_origins", [q], [frames], ["q"], ["P"]),
        frame_names=tuple(carried_names) + (robot.frame,),
        gravity_torque=ca.Function("gravity_torque", [q], [ca.substitute(ca.gradient(V, q), Pi, zero)],
                                   ["q"], ["g"]),
        gravity_moments=ca.Function("gravity_moments", [q], [ca.substitute(ca.gradient(V, Pi), Pi, zero)],
                                    ["q"], ["G"]),
    )


def carried_weights(robot: Robot) -> list[list[tuple[float, np.ndarray]]]:
    """Per chain joint, the (mass kg, centre of mass m in the joint's frame) of each body whose
    nearest chain joint on its way to the root it is (its own body, and those of joints off
    the chain beyond it, at their neutral values; bodies before the chain do not move)."""
    model = robot.model
    chain = {jid: k for k, jid in enumerate(robot.joint_ids)}
    data = model.createData()
    pin.forwardKinematics(model, data, robot.full_q(np.zeros(robot.n)))
    out: list[list[tuple[float, np.ndarray]]] = [[] for _ in robot.joint_ids]
    for b in range(1, model.njoints):
        a = b
        while a and a not in chain:
            a = model.parents[a]
        mass = float(model.inertias[b].mass)
        if a and mass > 0:
            lever = (data.oMi[a].inverse() * data.oMi[b]).act(np.asarray(model.inertias[b].lever, float))
            out[chain[a]].append((mass, lever))
    return out


def _carried_frames(model: pin.Model, jid: int, R: ca.SX, p: ca.SX,
                    exclude: int) -> tuple[list[ca.SX], list[str]]:
    """Origins (world, m) of the frames whose parent is joint ``jid`` at placement ``(R, p)``,
    one per distinct position in the joint frame (the joint's own origin included), and a
    name for each."""
    # name a position after its most telling frame: an operational frame (tool0), then a link
    rank = {pin.FrameType.OP_FRAME: 0, pin.FrameType.BODY: 1}
    offsets: dict[tuple, tuple[np.ndarray, str, int]] = {(0.0, 0.0, 0.0): (np.zeros(3), model.names[jid], 2)}
    for fid, frame in enumerate(model.frames):
        if frame.parentJoint == jid and fid != exclude:
            t = np.asarray(frame.placement.translation, dtype=float)
            key, r = tuple(np.round(t, 9)), rank.get(frame.type, 3)
            if key not in offsets or r < offsets[key][2]:
                offsets[key] = (t, frame.name, r)
    return [p + R @ ca.DM(t) for t, _, _ in offsets.values()], [name for _, name, _ in offsets.values()]
