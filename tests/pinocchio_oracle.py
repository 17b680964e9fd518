"""Test oracle: the test-pose errors of a geometric plan from Pinocchio alone.

The measured point's position is differentiated by central finite differences in every joint
placement error (six per joint, in the joint's frame) and the measured frame's placement error
(six): a parameterisation of all geometric errors, redundant, unlike the package's base set.
The predicted error of an estimable quantity does not depend on the parameterisation: with
``S`` the stacked position Jacobians of the plan and ``B0_j`` that of test pose j,
``rho_j = sigma^2 tr(B0_j (S^T S)^+ B0_j^T)`` (any generalised inverse), which is what the
package computes in its base set.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

#: Finite-difference step of the placement errors (m, rad).
STEP = 1e-6


def position_jacobians(problem, Q: np.ndarray) -> np.ndarray:
    """d(point)/d(errors) at each configuration of ``Q`` (k, n): shape (k, 3, 6 n + 6)."""
    robot = problem.robot
    markers = np.asarray(problem.model.markers_m, float)[0]
    fid = robot.frame_id

    def points(model: pin.Model) -> np.ndarray:
        data = model.createData()
        out = []
        for q in Q:
            pin.framesForwardKinematics(model, data, robot.full_q(q))
            M = data.oMf[fid]
            out.append(M.translation + M.rotation @ markers)
        return np.array(out)

    columns = []
    for jid in robot.joint_ids:
        for a in range(6):
            pair = []
            for sign in (1.0, -1.0):
                model = pin.Model(robot.model)
                model.jointPlacements[jid] = model.jointPlacements[jid] * pin.exp6(sign * STEP * np.eye(6)[a])
                pair.append(points(model))
            columns.append((pair[0] - pair[1]) / (2 * STEP))
    for a in range(6):
        pair = []
        for sign in (1.0, -1.0):
            model = pin.Model(robot.model)
            frame = model.frames[fid]
            frame.placement = frame.placement * pin.exp6(sign * STEP * np.eye(6)[a])
            model.frames[fid] = frame
            pair.append(points(model))
        columns.append((pair[0] - pair[1]) / (2 * STEP))
    return np.stack(columns, axis=-1)


def rms_errors(problem, Q: np.ndarray, rcond: float = 1e-9) -> np.ndarray:
    """``sqrt(rho_j)`` (m) at the problem's test poses of the plan ``Q`` (positions measured
    with noise sigma per coordinate, positions required)."""
    S = position_jacobians(problem, Q).reshape(-1, 6 * problem.robot.n + 6)
    B0 = position_jacobians(problem, problem.test_poses.q)
    N = np.linalg.pinv(S.T @ S, rcond=rcond, hermitian=True)
    return problem.sigma_m * np.sqrt(np.einsum("jri,il,jrl->j", B0, N, B0))
