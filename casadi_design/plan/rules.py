"""The rules a plan must satisfy, checked once: the NLP's constraints and the plan check use them.

A plan is m experiments ``(q_i, F_i)``. Each experiment keeps the rules of the problem
(``problem.rules``, :class:`casadi_design.problem.rules.PlanRules`): its joint limits, the
workspace and cell rows of its configuration, its calibration load. The plan adds:

* distinct experiments: ``joint_distance(q_i, q_j) >= min_joint_distance_rad``
  (:func:`joint_distance_sq`);
* with a ``[cell]``, no two bodies touching on the real geometry
  (:func:`casadi_design.cell.cell.touching`, :func:`mesh_contacts`), checked after solving.

The NLP imposes the pose rows on every experiment, and its bounds and load variables encode the
other rules. After solving, :func:`plan_violations` checks every rule on the returned plan: the
solver accepts a start only when it finds none, and ``casadi-design evaluate`` prints them for a
user's plan.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..cell.cell import touching
from ..problem.build import Problem
from ..problem.rules import JointLimits

#: Largest violation of a joint limit or workspace rule accepted (rad, m).
FEASIBILITY_TOL = 1e-6
#: The capsule rows an IPOPT run holds (the starts, :mod:`casadi_design.optimisation.solve`, and the
#: bound's searches, :mod:`casadi_design.optimisation.bound`): those closer than ``START_MARGIN_M`` (m) to
#: their bound where it starts; after a run, those closer than ``ADD_MARGIN_M`` (m) join, until
#: every row left out is farther. Chosen by measurement on the UR10 and ABB cells (README, Speed).
START_MARGIN_M = 0.05
ADD_MARGIN_M = 0.01
#: Relative tolerance on the calibration load (its norm, direction or fixed value).
LOAD_RTOL = 1e-4


def joint_distance_sq(limits: JointLimits, qa, qb):
    """Squared distance (rad^2) of two configurations (numpy or CasADi): ``sum_k d_k^2`` with
    ``d_k = q_a,k - q_b,k``, or ``2 sin(d_k / 2)`` for periodic joints (the chord: equal to
    ``d_k`` to third order, zero for a whole turn)."""
    d = qa - qb
    numeric = isinstance(d, np.ndarray)
    if np.any(limits.periodic):
        w = limits.periodic.astype(float)
        w = w if numeric else ca.DM(w)
        d = w * 2 * (np.sin if numeric else ca.sin)(d / 2) + (1 - w) * d
    return float(d @ d) if numeric else ca.sumsqr(d)


def _amount(v: float, unit: str, lb: float) -> str:
    """A row's violation ``v`` for people: mm for "m" rows; for "cos" rows (``cos(angle) >=
    lb``) the angle beyond its limit, deg."""
    if unit == "m":
        return f"{v * 1e3:.3g} mm"
    return f"{np.rad2deg(np.arccos(np.clip(lb - v, -1, 1)) - np.arccos(lb)):.3g} deg"


def mesh_contacts(problem: Problem, Q: np.ndarray) -> list[str]:
    """The experiments of ``Q`` (m, n), rad, whose links or obstacles touch or cross on the
    cell's real geometry (:func:`casadi_design.cell.cell.touching`), one line each; none without
    a cell."""
    if problem.cell is None:
        return []
    return [f"experiment {i + 1}: {pair[0]} and {pair[1]} touch or cross on the {problem.cell.check.source}"
            for i, pair in enumerate(touching(problem.cell, Q)) if pair is not None]


def load_violations(problem: Problem, F: np.ndarray) -> list[str]:
    """The loads ``F`` (m, nF), N (N m), that break ``[experiments.force]`` (its magnitude,
    fixed vector or direction, to :data:`LOAD_RTOL`), one line each."""
    force, out = problem.force, []
    for i, f in enumerate(np.asarray(F, dtype=float).reshape(-1, problem.model.nF) if force is not None else ()):
        norm = float(np.linalg.norm(f))
        ratio = norm / force.magnitude_N
        if force.mode == "fixed" and not np.allclose(f, force.vector_N, rtol=LOAD_RTOL, atol=0):
            out.append(f"experiment {i + 1}: load {f.tolist()} is not the fixed {list(force.vector_N)}")
        elif force.mode != "fixed" and ratio > 1 + LOAD_RTOL:
            out.append(f"experiment {i + 1}: |F| = {norm:.6g} N above {force.magnitude_N:g} N")
        elif force.mode == "equal" and ratio < 1 - LOAD_RTOL:
            out.append(f"experiment {i + 1}: |F| = {norm:.6g} N, the problem applies {force.magnitude_N:g} N")
        elif force.mode == "direction":
            u = np.array(force.direction)
            if np.linalg.norm(f - u * (u @ f)) > LOAD_RTOL * force.magnitude_N or u @ f < -LOAD_RTOL * force.magnitude_N:
                out.append(f"experiment {i + 1}: load {f.tolist()} is not along the direction {list(u)}")
    return out


def plan_violations(problem: Problem, Q: np.ndarray, F: np.ndarray, meshes: bool = True) -> list[str]:
    """Every rule the plan breaks, one line each (empty: the plan is feasible).

    Parameters
    ----------
    Q : ndarray, shape (m, n), rad (m for prismatic joints)
    F : ndarray, shape (m, nF), N (N m)
    meshes : False leaves out the check on the cell's real geometry (:func:`mesh_contacts`,
        about 0.6 ms per configuration on the UR10's meshes), for a caller that runs it later on the plans it keeps.
    """
    robot, ws = problem.robot, problem.workspace
    Q = np.asarray(Q, dtype=float)
    F = np.asarray(F, dtype=float).reshape(len(Q), problem.model.nF)
    out, rules, limits = [], problem.rules.pose, problem.rules.limits
    for i, q in enumerate(Q):
        for k, j in enumerate(robot.joints):
            if not limits.lower[k] - FEASIBILITY_TOL <= q[k] <= limits.upper[k] + FEASIBILITY_TOL:
                margin = f" (limits less the {ws.joint_limit_margin_rad:g} margin)" if ws.joint_limit_margin_rad else ""
                out.append(f"experiment {i + 1}: {j} = {q[k]:.6g} outside [{limits.lower[k]:.6g}, "
                           f"{limits.upper[k]:.6g}]{margin}")
        worst: dict[str, int] = {}  # rows sharing a label (a capsule's two ends): the worst one
        violation = rules.violation(q)
        for k in np.flatnonzero(violation > FEASIBILITY_TOL):
            label = rules.labels[k]
            if label not in worst or violation[k] > violation[worst[label]]:
                worst[label] = k
        out += [f"experiment {i + 1}: {label} by {_amount(violation[k], rules.units[k], rules.lb[k])}"
                for label, k in worst.items()]
    if meshes:
        out += mesh_contacts(problem, Q)
    out += load_violations(problem, F)
    dmin = ws.min_joint_distance_rad
    m = len(Q)
    for i in range(m):
        for j in range(i + 1, m):
            dist = float(np.sqrt(joint_distance_sq(limits, Q[i], Q[j])))
            if dist < dmin - FEASIBILITY_TOL:
                out.append(f"experiments {i + 1} and {j + 1}: joint distance {dist:.4g} rad below "
                           f"min_joint_distance_rad = {dmin:g}")
    return out
