"""Measurements of a robot made independently of the package's error model, for the tests of
``casadi-design identify``.

The true robot is the problem's Pinocchio model with its joint placements perturbed (0.5 mm,
1 mrad per joint, joint-zero offsets folded into the placements) and the measured frame moved
(0.5 mm); under a load it deflects by the static equilibrium ``dq = k J(q + dq)^T W`` solved
with Pinocchio's own Jacobian; the tracker sits at a frame rotated 100+ deg and metres away;
noise ``sigma`` per coordinate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from casadi_design.records.export import csv_text, plan_table
from casadi_design.identification.measurements import measured_axes, measurement_columns

LENGTH_M, ANGLE_RAD = 0.5e-3, 1e-3


@dataclass(frozen=True, eq=False)
class TrueRobot:
    model: pin.Model
    frame_id: int
    k: np.ndarray          # (n,) compliance per chain joint, rad/(N m)
    tracker: pin.SE3       # base -> tracker


def perturbed(problem, rng, base_like: bool = True, k: np.ndarray | None = None) -> TrueRobot:
    """The true robot (module docstring). Without ``base_like`` the placements of joints 1 and
    2 and the zero of joint 1 stay nominal: on a chain whose first two axes are orthogonal,
    their errors that act as a motion of the whole robot (the tracker frame absorbs them) are
    among these."""
    robot = problem.robot
    model = pin.Model(robot.model)
    for idx, jid in enumerate(robot.joint_ids):
        joint = model.joints[jid]
        kind = joint.shortname()
        axis = {"X": np.eye(3)[0], "Y": np.eye(3)[1], "Z": np.eye(3)[2]}.get(kind[-1])
        if axis is None:
            axis = np.asarray(joint.extract().axis, float)
        error = pin.SE3(pin.exp3(rng.normal(0, ANGLE_RAD, 3)), rng.normal(0, LENGTH_M, 3))
        offset = rng.normal(0, ANGLE_RAD)
        if not base_like and idx < 2:
            error, offset = pin.SE3.Identity(), offset if idx else 0.0
        zero = (pin.SE3(pin.exp3(axis * offset), np.zeros(3)) if "R" in kind[len("JointModel"):][:1]
                else pin.SE3(np.eye(3), axis * offset * LENGTH_M / ANGLE_RAD))
        model.jointPlacements[jid] = model.jointPlacements[jid] * error * zero
    fid = robot.frame_id
    frame = model.frames[fid]
    frame.placement = frame.placement * pin.SE3(np.eye(3), rng.normal(0, LENGTH_M, 3))
    model.frames[fid] = frame
    if len(measured_axes(problem)) == 3:  # about 2.3 rad = 133 deg, metres away
        tracker = pin.SE3(pin.exp3(np.array([0.3, -0.5, 2.2])), np.array([2.7, -1.4, 0.8]))
    else:  # a planar arm: the tracker's plane is the arm's
        tracker = pin.SE3(pin.exp3(np.array([0.0, 0.0, 2.2])), np.array([2.7, -1.4, 0.0]))
    return TrueRobot(model, fid, np.zeros(robot.n) if k is None else np.asarray(k, float), tracker)


def true_points(problem, true: TrueRobot, Q: np.ndarray, F: np.ndarray, gravity: bool = False) -> np.ndarray:
    """Points (m, k, 3), m, of the true robot in the base frame, deflected by the loads (and
    with ``gravity`` by its own weight: Pinocchio's generalized gravity of the true model)."""
    robot, spec = problem.robot, problem.spec
    markers = problem.model.markers_m
    lever = np.zeros(3) if spec.force is None else np.asarray(spec.force.load_point_m, float)
    rows = problem.model.force_rows
    data = true.model.createData()
    out = []
    for q, f in zip(Q, F):
        wrench = np.zeros(6)
        wrench[list(rows)] = f
        dq = np.zeros(robot.n)
        for _ in range(30 if true.k.any() else 1):  # the fixed point
            qf = robot.full_q(q + dq)
            pin.computeJointJacobians(true.model, data, qf)
            pin.framesForwardKinematics(true.model, data, qf)
            M = data.oMf[true.frame_id]
            W = np.concatenate([wrench[:3], wrench[3:] + np.cross(M.rotation @ lever, wrench[:3])])
            J = pin.getFrameJacobian(true.model, data, true.frame_id, pin.LOCAL_WORLD_ALIGNED)
            cols = [true.model.joints[j].idx_v for j in robot.joint_ids]
            tau = J[:, cols].T @ W
            if gravity:
                tau = tau - pin.computeGeneralizedGravity(true.model, data, qf)[cols]
            dq = true.k * tau
        pin.framesForwardKinematics(true.model, data, robot.full_q(q + dq))
        M = data.oMf[true.frame_id]
        out.append(M.translation + markers @ M.rotation.T)
    return np.array(out)


def measured(problem, true: TrueRobot, Q, F, rng, sigma: float | None = None,
             gravity: bool = False) -> np.ndarray:
    """Tracker-frame coordinates (m, k, 3), m, with noise sigma per coordinate."""
    sigma = problem.sigma_m if sigma is None else sigma
    p = true_points(problem, true, Q, F, gravity)
    P = p @ true.tracker.rotation.T + true.tracker.translation
    return P + sigma * rng.standard_normal(P.shape)


def measurement_csv(problem, Q, F, P_m, hidden: tuple[tuple[int, int], ...] = ()) -> str:
    """A measurement CSV: the plan's columns and the coordinates in mm (``hidden``: (row,
    marker) pairs left empty)."""
    header, rows = plan_table(problem, Q, F)
    columns = measurement_columns(problem)
    axes = measured_axes(problem)
    header = header[:len(rows[0])] + [f"{c}_mm" for point in columns for c in point]  # no clearance columns
    for i, row in enumerate(rows):
        for c in range(len(columns)):
            row += ["" if (i, c) in hidden else float(P_m[i, c, a] * 1e3) for a in axes]
    return csv_text(header, rows)


def angle_between(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.linalg.norm(pin.log3(Ra.T @ Rb)))


def degrees(R: np.ndarray) -> float:
    return math.degrees(np.linalg.norm(pin.log3(R)))
