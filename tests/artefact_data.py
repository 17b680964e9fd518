"""Recordings of a ball seated at points of an artefact, made independently of the package's
model: the true robot of :func:`tests.identify_data.perturbed` (joint placements 0.5 mm, 1 mrad;
the measured point moved 0.5 mm), each configuration found by damped least squares on the true
robot's Pinocchio model from a random start so that its ball sits at a point of a placement, plus
the seating's noise ``sigma`` per axis.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from tests.identify_data import TrueRobot, perturbed

#: Two placements of a two-socket tool (50 mm) in front of a Panda: (R, t) in the base frame.
PLACEMENTS = ((pin.rpy.rpyToMatrix(0.0, 0.0, 0.3), np.array([0.50, -0.05, 0.10])),
              (pin.rpy.rpyToMatrix(0.0, 0.1, -0.8), np.array([0.35, 0.35, 0.05])))


def seated(problem, true: TrueRobot, target: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` configurations (count, n), rad, of the true robot with its measured point at
    ``target`` (3,), m, within the joint limits, from random starts."""
    robot, data = problem.robot, true.model.createData()
    out = []
    while len(out) < count:
        q = robot.q_min + (robot.q_max - robot.q_min) * rng.uniform(0.15, 0.85, robot.n)
        for _ in range(200):
            qf = robot.full_q(q)
            pin.framesForwardKinematics(true.model, data, qf)
            e = target - data.oMf[true.frame_id].translation
            if np.linalg.norm(e) < 1e-10:
                break
            J = pin.computeFrameJacobian(true.model, data, qf, true.frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
            J = J[:, [true.model.joints[j].idx_v for j in robot.joint_ids]]
            q = q + J.T @ np.linalg.solve(J @ J.T + 1e-8 * np.eye(3), e)
        if np.linalg.norm(e) < 1e-10 and np.all((q > robot.q_min + 0.05) & (q < robot.q_max - 0.05)):
            out.append(q)
    return np.array(out)


def recordings(problem, seed: int, per_point: int, sigma: float, placements=PLACEMENTS):
    """The true robot and its recordings: per placement and artefact point ``per_point``
    configurations with the ball at the point moved by N(0, sigma^2 I) (the seating). Returns
    (true, Q, point, placement)."""
    rng = np.random.default_rng(seed)
    true = perturbed(problem, rng)
    A = problem.artefact
    Q, point, placement = [], [], []
    for g, (R, t) in enumerate(placements):
        for k, a in enumerate(A.points_m):
            for _ in range(per_point):
                Q.append(seated(problem, true, t + R @ a + rng.normal(0, sigma, 3), rng, 1)[0])
                point.append(k)
                placement.append(g)
    return true, np.array(Q), np.array(point), np.array(placement)


def true_ball(problem, true: TrueRobot, Q: np.ndarray) -> np.ndarray:
    """The true robot's measured point (N, 3), m, at configurations ``Q``."""
    data = true.model.createData()
    out = []
    for q in Q:
        pin.framesForwardKinematics(true.model, data, problem.robot.full_q(q))
        out.append(data.oMf[true.frame_id].translation.copy())
    return np.array(out)


def ball_socket_file(path, name: str, robot: dict, test_q: list, placements: list | None = None):
    """A problem file at ``path`` of a ball on ``robot`` (the ``[robot]`` table) seated in the two
    sockets (50 mm apart, 0.05 mm) of a tool, at ``placements`` (``[measurement.artefact]
    placements``, none: recordings only), test poses ``test_q`` (rad); geometric, the
    identifiable base set, the test-pose criterion, m = 16. Returns ``path``."""
    import tomli_w

    artefact = {"points_m": [[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]], **({"placements": placements} if placements else {})}
    path.write_text(tomli_w.dumps({
        "name": name, "robot": robot, "calibration": {"case": "geometric", "parameters": "identifiable"},
        "measurement": {"components": ["x", "y", "z"], "sigma_m": 5e-5, "artefact": artefact},
        "test_poses": {"components": ["x", "y", "z"], "joints_rad": test_q},
        "experiments": {"m": [16]}, "design": {"criteria": ["test-pose"]}}))
    return path
