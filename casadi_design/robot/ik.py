"""Inverse kinematics of test paths: damped least squares on Pinocchio's kinematics.

A Cartesian path (line, polyline, circular arc or list of points, m) with a constant tool
orientation is sampled into nodes; each node is solved from the previous node's solution, so
the whole path stays on one branch. The step is

    dq = J^T (J J^T + lambda^2 I)^-1 e,   e = (p* - p, log3(R* R^T)),   lambda^2 = LAMBDA0^2 + |e|^2

(world-aligned Jacobian of the tool frame), clipped to the joint limits.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from ..errors import ProblemError
from .robots import Robot

#: Convergence threshold on |e| (m and rad).
IK_TOL = 1e-10
#: Largest residual (m, rad) accepted when iterations run out.
IK_ACCEPT = 1e-7
IK_MAX_ITER = 500
LAMBDA0 = 1e-3


def sample_path(kind: str, points: np.ndarray, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (nodes x 3, m) along a path and the index of the segment each lies on.

    ``line``: from points[0] to points[1]; ``polyline``: through all points, equally spaced in
    arc length; ``arc``: the circular arc from points[0] through points[1] to points[2];
    ``points``: the points themselves (``nodes`` ignored).
    """
    P = np.asarray(points, dtype=float)
    if kind == "points":
        return P, np.arange(len(P))
    if kind in ("line", "polyline"):
        seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
        arc = np.linspace(0.0, seg.sum(), nodes)
        edges = np.r_[0.0, np.cumsum(seg)]
        k = np.clip(np.searchsorted(edges, arc, side="right") - 1, 0, len(seg) - 1)
        t = (arc - edges[k]) / seg[k]
        return P[k] + t[:, None] * (P[k + 1] - P[k]), k
    a, b, c = P
    u, v = b - a, c - a
    w = np.cross(u, v)
    if not np.linalg.norm(w) > 1e-9 * max(u @ u, v @ v):
        raise ProblemError("[test_poses].path: the three arc points are collinear; give start, a point on "
                           "the arc and end that span a circle")
    center = a + (np.cross(w, u) * (v @ v) + np.cross(v, w) * (u @ u)) / (2 * (w @ w))
    e1 = (a - center) / np.linalg.norm(a - center)
    e2 = np.cross(w / np.linalg.norm(w), e1)
    r = np.linalg.norm(a - center)

    def angle(p):
        return np.mod(np.arctan2((p - center) @ e2, (p - center) @ e1), 2 * np.pi)

    phi = np.linspace(0.0, angle(c), nodes)
    return center + r * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2), np.zeros(nodes, int)


def solve_ik(robot: Robot, target: pin.SE3, q0: np.ndarray, position_only: bool = False,
             limits: bool = True, max_iter: int = IK_MAX_ITER, free_spin: bool = False) -> tuple[np.ndarray, float]:
    """Configuration reaching ``target`` with the tool frame, from ``q0``, within the joint
    limits (``limits``; else anywhere), in at most ``max_iter`` steps; and the residual |e|.
    ``position_only``: the position alone; ``free_spin``: the position and the tool's z axis,
    its turn about it free (a ball's): the orientation's error ``log3(R* R^T)`` and the
    Jacobian's rows of it taken along the target's x and y axes only (zero where ``R^T R*``
    is a turn about z)."""
    model, data, fid = robot.model, robot.model.createData(), robot.frame_id
    low, high = (robot.q_min, robot.q_max) if limits else (-np.inf, np.inf)
    q = np.clip(np.asarray(q0, dtype=float), low, high)
    # what every step uses, made once (a step is mostly Python's overhead: a 7-joint arm's is
    # about 50 us): the configuration of the whole model, the error and the identity
    t, R, e = target.translation, target.rotation, np.empty(6)
    # the rows asked for: the first k of (position, orientation), or with the spin free the
    # orientation's along the target's x and y axes (S)
    S = None
    if free_spin and not position_only:
        S = np.zeros((5, 6))
        S[:3, :3], S[3:, 3:] = np.eye(3), R[:, :2].T
    k = 3 if position_only else 6 if S is None else 5
    q_full, q_index, v_index, eye = robot.full_q(q), robot.q_index, robot.v_index, np.eye(k)
    world = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    err = np.inf
    for _ in range(max_iter):
        q_full[q_index] = q
        pin.computeJointJacobians(model, data, q_full)  # the joints' placements and Jacobians at once
        pin.updateFramePlacements(model, data)
        M = data.oMf[fid]
        e[:3] = t - M.translation
        if k > 3:  # the orientation's error only where it is asked for
            e[3:] = pin.log3(R @ M.rotation.T)
        ek = e[:k] if S is None else S @ e
        err = math.sqrt(ek.dot(ek))  # np.linalg.norm's sum of squares and square root
        if err < IK_TOL:
            break
        J = pin.getFrameJacobian(model, data, fid, world)[:, v_index]
        J = J[:k] if S is None else S @ J
        lam2 = LAMBDA0**2 + err**2
        q = np.clip(q + J.T @ np.linalg.solve(J @ J.T + lam2 * eye, ek), low, high)
    return q, err


def path_ik(robot: Robot, positions_m: np.ndarray, rotation: np.ndarray, q_seed: np.ndarray,
            position_only: bool = False) -> np.ndarray:
    """Joint values (s x n, rad) of the nodes, each seeded by the previous one.

    Raises
    ------
    ProblemError
        For the first node the IK cannot reach within ``IK_ACCEPT``.
    """
    q, out, s = np.asarray(q_seed, dtype=float), [], len(positions_m)
    for j, p in enumerate(positions_m):
        q_from = q
        q, err = solve_ik(robot, pin.SE3(rotation, p), q_from, position_only)
        if not err <= IK_ACCEPT:  # also catches NaN
            where = f"[test_poses].path: node {j + 1} of {s} at ({', '.join(f'{v * 1e3:.1f}' for v in p)}) mm"
            start = "from seed_q_deg" if j == 0 else "from the previous node"
            tool = "" if position_only else " with the given tool orientation"
            q_free, err_free = solve_ik(robot, pin.SE3(rotation, p), q_from, position_only, limits=False)
            out_of = [k for k in range(robot.n) if not any(  # (a revolute joint in any whole turn)
                robot.q_min[k] <= q_free[k] + 2 * np.pi * t <= robot.q_max[k] for t in
                ((0,) if robot.is_prismatic(k) else (0, -1, 1, -2, 2)))]
            if err_free <= IK_ACCEPT and out_of:  # reached, past a joint limit
                k = out_of[0]
                raise ProblemError(
                    f"{where} is reached {start}{tool} with "
                    f"{robot.joints[k]} at {np.rad2deg(q_free[k]):.1f} deg, outside its limits "
                    f"[{np.rad2deg(robot.q_min[k]):.1f}, {np.rad2deg(robot.q_max[k]):.1f}] deg, and not within "
                    "them; move the path, give seed_q_deg for another branch, or widen [robot.joint_limits_rad] "
                    "if the robot allows it")
            raise ProblemError(
                f"{where} is unreachable{tool} (residual {err * 1e3:.3g} {'mm' if position_only else 'mm/mrad'} "
                f"after {IK_MAX_ITER} iterations {start}); move the path"
                + ("" if position_only else ", change tool_rpy_deg") + " or give seed_q_deg closer to it"
            )
        out.append(q)
    return np.array(out)
