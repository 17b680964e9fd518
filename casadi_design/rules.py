"""The rules a plan must satisfy, written once: the NLP's constraints and the plan check use them.

A plan is m experiments ``(q_i, F_i)``. Its rules:

* joint limits: ``q_min <= q_i <= q_max`` (rad, m);
* calibration load (:class:`casadi_design.problem.ForceSpec`): ``|F_i| = F_max`` ("equal"),
  ``|F_i| <= F_max`` ("bound"), ``F_i = F_fixed`` ("fixed"), ``F_i = a F_max u`` with
  ``0 <= a <= 1`` ("direction");
* workspace of every configuration (:func:`pose_constraints`): each measured point in the box,
  the half-spaces and the tracker's sphere; every moving frame origin (joints, links, flange,
  tool) and measured point above the floor;
* distinct experiments: ``|q_i - q_j| >= min_joint_distance_rad``.

:func:`pose_constraints` gives the workspace rows as one CasADi function (the NLP imposes it on
every experiment); the NLP's bounds and load variables encode the other rules. After solving,
:func:`plan_violations` checks every rule on the returned plan: the solver accepts a start only
when it finds none, and ``casadi-design evaluate`` prints them for a user's plan.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .build import Problem

#: Largest violation of a joint limit or workspace rule accepted (rad, m).
FEASIBILITY_TOL = 1e-6
#: Relative tolerance on the calibration load (its norm, direction or fixed value).
LOAD_RTOL = 1e-4


@dataclass(frozen=True, eq=False)
class PoseConstraints:
    """Workspace rows of one configuration: ``lb <= g(q) <= ub`` (m), one label per row."""

    g: ca.Function
    lb: np.ndarray
    ub: np.ndarray
    labels: tuple[str, ...]

    def violation(self, q: np.ndarray) -> np.ndarray:
        """Violation (m, >= 0) of each row at configuration ``q``."""
        if not self.lb.size:
            return np.zeros(0)
        g = np.asarray(self.g(np.asarray(q, dtype=float))).ravel()
        return np.maximum(np.maximum(self.lb - g, g - self.ub), 0.0)


@functools.cache
def pose_constraints(problem: Problem) -> PoseConstraints:
    """The workspace rules of one configuration (see the module docstring)."""
    ws, model, robot = problem.workspace, problem.model, problem.robot
    q = ca.SX.sym("q", robot.n)
    P = model.points(q)
    rows: list[tuple[ca.SX, float, float, str]] = []
    for j in range(P.shape[1]):
        p, name = P[:, j], f"measured point {j + 1}" if P.shape[1] > 1 else "measured point"
        if ws.box_min_m is not None:
            rows += [(p[a], ws.box_min_m[a], ws.box_max_m[a], f"{name}: {'xyz'[a]} outside the box") for a in range(3)]
        for k, hs in enumerate(ws.half_spaces):
            n = np.array(hs.normal) / np.linalg.norm(hs.normal)
            rows.append((ca.dot(ca.DM(n), p), hs.offset_m / np.linalg.norm(hs.normal), np.inf,
                         f"{name}: outside half-space {k + 1}"))
        if ws.sphere_center_m is not None:
            rows.append((ca.sqrt(ca.sumsqr(p - ca.DM(ws.sphere_center_m)) + 1e-12), -np.inf, ws.sphere_radius_m,
                         f"{name}: out of the tracker's range"))
    if ws.floor_z_m is not None:
        # frames fixed to the base (not moving with q) are where the robot stands: not constrained
        frames, names = model.kinematics.frame_origins(q), model.kinematics.frame_names
        named = ([(frames[:, k], f"frame '{names[k]}'") for k in range(frames.shape[1] - 1)]
                 + [(frames[:, -1], f"measured frame '{robot.frame}'")]
                 + [(P[:, j], f"measured point {j + 1}") for j in range(P.shape[1])])
        rows += [(p[2], ws.floor_z_m, np.inf, f"{name}: below the floor")
                 for p, name in named if ca.depends_on(p[2], q)]
    g = ca.vertcat(*[r[0] for r in rows]) if rows else ca.SX(0, 1)
    return PoseConstraints(ca.Function("workspace", [q], [g], ["q"], ["g"]),
                           np.array([r[1] for r in rows], dtype=float),
                           np.array([r[2] for r in rows], dtype=float), tuple(r[3] for r in rows))


@dataclass(frozen=True, eq=False)
class LoadVariables:
    """The calibration loads as NLP variables: ``nv`` values ``v_i`` per experiment.

    ``F_i = magnitude_N U v_i + fixed_N`` (N, N m) with ``U`` (nF x nv) the identity for a free
    direction ("equal", "bound": ``v = F / F_max``, with the rows ``norm_lb <= |v_i|^2 <= 1``),
    the unit direction u for "direction" (``v = a``), and no variables (nv = 0) for a fixed load
    or a case without loads. Bounds of each ``v`` entry: ``lower <= v <= 1``.
    """

    U: np.ndarray
    magnitude_N: float
    fixed_N: np.ndarray
    lower: float
    norm_lb: float | None

    @property
    def nv(self) -> int:
        return self.U.shape[1]

    def loads(self, V):
        """``F`` (nF x m, N) of the variables ``V`` (nv x m; numpy or CasADi)."""
        m = V.shape[1]
        if isinstance(V, np.ndarray):
            return self.magnitude_N * (self.U @ V) + self.fixed_N[:, None]
        return self.magnitude_N * (ca.DM(self.U) @ V) + ca.repmat(ca.DM(self.fixed_N), 1, m)

    def variables(self, F: np.ndarray) -> np.ndarray:
        """``V`` (nv x m) of loads ``F`` (nF x m, N) that satisfy the rule."""
        F = np.asarray(F, dtype=float)
        return self.U.T @ F.reshape(self.U.shape[0], F.shape[-1]) / self.magnitude_N


def load_variables(problem: Problem) -> LoadVariables:
    """The load variables of the problem's calibration load (see :class:`LoadVariables`)."""
    nF, force = problem.model.nF, problem.force
    if nF == 0 or force is None or force.mode == "fixed":
        fixed = np.array(force.vector_N if nF and force is not None else np.zeros(nF), dtype=float)
        return LoadVariables(np.zeros((nF, 0)), 1.0, fixed, -1.0, None)
    if force.mode == "direction":
        return LoadVariables(np.array(force.direction, dtype=float)[:, None], force.magnitude_N,
                             np.zeros(nF), 0.0, None)
    return LoadVariables(np.eye(nF), force.magnitude_N, np.zeros(nF), -1.0,
                         1.0 if force.mode == "equal" else 0.0)


def plan_violations(problem: Problem, Q: np.ndarray, F: np.ndarray) -> list[str]:
    """Every rule the plan breaks, one line each (empty: the plan is feasible).

    Parameters
    ----------
    Q : ndarray, shape (n, m), rad (m for prismatic joints)
    F : ndarray, shape (nF, m), N (N m)
    """
    robot, force, ws = problem.robot, problem.force, problem.workspace
    Q = np.asarray(Q, dtype=float)
    F = np.asarray(F, dtype=float).reshape(problem.model.nF, Q.shape[1])
    out, rules = [], pose_constraints(problem)
    for i, q in enumerate(Q.T):
        for k, j in enumerate(robot.joints):
            if not robot.q_min[k] - FEASIBILITY_TOL <= q[k] <= robot.q_max[k] + FEASIBILITY_TOL:
                out.append(f"experiment {i + 1}: {j} = {q[k]:.6g} outside [{robot.q_min[k]:.6g}, "
                           f"{robot.q_max[k]:.6g}]")
        for v, label in zip(rules.violation(q), rules.labels):
            if v > FEASIBILITY_TOL:
                out.append(f"experiment {i + 1}: {label} by {v * 1e3:.3g} mm")
    if force is not None and F.size:
        for i, f in enumerate(F.T):
            norm = float(np.linalg.norm(f))
            ratio = norm / force.magnitude_N
            if force.mode == "fixed" and not np.allclose(f, force.vector_N, rtol=LOAD_RTOL, atol=0):
                out.append(f"experiment {i + 1}: load {f.tolist()} is not the fixed {list(force.vector_N)}")
            elif force.mode != "fixed" and ratio > 1 + LOAD_RTOL:
                out.append(f"experiment {i + 1}: |F| = {norm:.6g} above {force.magnitude_N:g}")
            elif force.mode == "equal" and ratio < 1 - LOAD_RTOL:
                out.append(f"experiment {i + 1}: |F| = {norm:.6g}, the problem applies {force.magnitude_N:g}")
            elif force.mode == "direction":
                u = np.array(force.direction)
                if np.linalg.norm(f - u * (u @ f)) > LOAD_RTOL * force.magnitude_N or u @ f < -LOAD_RTOL * force.magnitude_N:
                    out.append(f"experiment {i + 1}: load {f.tolist()} is not along the direction {list(u)}")
    dmin = ws.min_joint_distance_rad
    m = Q.shape[1]
    for i in range(m):
        for j in range(i + 1, m):
            dist = float(np.linalg.norm(Q[:, i] - Q[:, j]))
            if dist < dmin - FEASIBILITY_TOL:
                out.append(f"experiments {i + 1} and {j + 1}: joint distance {dist:.4g} rad below "
                           f"min_joint_distance_rad = {dmin:g}")
    return out
