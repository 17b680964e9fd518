"""Configurations with the ball seated in an artefact's socket, planned from nothing.

A placement g of the artefact (``[measurement.artefact] placements``: its frame ``(R_g, t_g)``
in the robot's base frame) puts point k at ``c_gk = t_g + R_g a_k``. A configuration q is seated
there when the nominal measured point is at it, ``p(q) = c_gk`` (the equality a hand-guided
recording meets), and the hand comes into the socket from above: the measured frame's z axis
``z(q)`` within ``tilt_max`` of the artefact's -z, ``acos(-z(q) . R_g e_z) <= tilt_max``. A
7-joint arm keeps 4 degrees of freedom there (one rotation and the null space), a 6-joint arm 3.

Each seated configuration is the inverse kinematics (:func:`~casadi_design.robot.ik.solve_ik`,
position and orientation to 1e-7, :data:`SEATED_IK_STEPS` steps at most) of a hand orientation drawn uniformly over the cone of
``tilt_max`` (its turn about z uniform), from a configuration drawn uniformly within the joint
limits (an arm of fewer than 6 joints, which reaches few orientations, to the position alone,
kept when its hand is within the tilt); it is kept when it keeps every rule of one experiment
(:func:`~casadi_design.plan.rules.plan_violations`: limits less the margin, workspace, cell). The
pool engine then chooses the plan among them (:mod:`casadi_design.optimisation.artefact_pool`).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..calibration.artefact import least_turn
from ..errors import ProblemError
from ..problem.build import Problem
from ..problem_file.read import spec_digest_blob
from ..problem_file.solver import SolverSettings
from ..robot.ik import IK_ACCEPT, solve_ik
from ..robot.robots import frame_placement
from ..runtime.cache import memoised
from .rules import plan_violations

#: Seated configurations drawn per point of each placement, by default.
SEATED_PER_POINT = 30
#: Inverse kinematics tried per seated configuration wanted before a point is called
#: unreachable, each of at most :data:`SEATED_IK_STEPS` steps: from a start uniform within the
#: limits, a Panda's IK converges within 30 steps in a third of the tries (it is 1 s for 40
#: configurations of one socket; 100 steps find as many in twice the time).
SEATED_TRIES = 10
SEATED_IK_STEPS = 30
#: How far back along the hand's z axis from the seated configuration a robot program stops
#: (m): the ball clear of the socket's rim, the operator seats it by hand.
APPROACH_M = 0.02
#: Starts about a seated configuration (normal, this spread in rad) its approach is sought from
#: when a joint's limit stops the inverse kinematics from the configuration itself.
APPROACH_TRIES = 20
APPROACH_SPREAD_RAD = 0.3
#: The seed's stream of the seated configurations (beside the designs' starts').
SEATED_STREAM = 67


@dataclass(frozen=True, eq=False)
class Seated:
    """Seated configurations: ``Q`` (N, n), rad, the artefact's ``point`` and ``placement``
    (N,; index into ``names``, the placements of the problem file) of each."""

    Q: np.ndarray
    point: np.ndarray
    placement: np.ndarray
    names: tuple[str, ...]


def socket_positions(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """The placements' rotations ``R`` (P, 3, 3) and each point's position ``c`` (P, K, 3), m,
    in the robot's base frame (``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    spec = problem.spec.measurement.artefact
    R = np.array([pin.rpy.rpyToMatrix(*p.rpy_rad) for p in spec.placements])
    t = np.array([p.xyz_m for p in spec.placements])
    return R, t[:, None, :] + np.einsum("gij,kj->gki", R, problem.artefact.points_m)


def tilted(axis: np.ndarray, tilt_max: float, rng: np.random.Generator) -> np.ndarray:
    """A rotation whose z axis is uniform over the cone of half-angle ``tilt_max`` (rad) about
    the unit ``axis`` (uniform in solid angle), its turn about z uniform."""
    c = rng.uniform(np.cos(tilt_max), 1.0)
    phi, spin = rng.uniform(0.0, 2 * np.pi, 2)
    s = np.sqrt(max(1.0 - c * c, 0.0))
    z = np.array([0.0, 0.0, 1.0])
    return least_turn(z, axis) @ least_turn(z, np.array([s * np.cos(phi), s * np.sin(phi), c])) @ pin.exp3(spin * z)


def _seated_key(problem: Problem, per_point: int = SEATED_PER_POINT) -> tuple:
    """What the seated configurations of ``problem`` are computed from: its checked data (the
    problem is a pure function of it, :func:`casadi_design.problem.build.build_problem`) less
    the solver settings and the held data but for the seed, and ``per_point``."""
    bare = dataclasses.replace(problem.spec, solver=SolverSettings(), held=None)
    return spec_digest_blob(bare), problem.solver.seed, per_point


@memoised(8, key=_seated_key)
def seated_configurations(problem: Problem, per_point: int = SEATED_PER_POINT) -> Seated:
    """``per_point`` seated configurations of each point of each placement of the problem file
    (module docstring), drawn by the problem's seed (``[solver] seed``). Kept per process
    (:func:`~casadi_design.runtime.cache.memoised`: ``solve``, ``sweep`` and ``bound`` of one
    problem in one process draw them once; a Panda's take about a second), read-only.

    Raises
    ------
    ProblemError
        No placement given; a point of a placement no configuration seats within
        ``SEATED_TRIES * per_point`` tries (the message names the placement and the point).
    """
    spec, robot = problem.spec.measurement.artefact, problem.robot
    if not spec.placements:
        raise ProblemError(f"{problem.path}: [measurement.artefact].placements: configurations are planned with the "
                           "ball seated at the placements the problem file gives; add placements = [{ name = \"front\", "
                           "xyz_m = [x, y, z], rpy_deg = [0, 0, 0] }] or give recordings as --candidates DIR")
    R, c = socket_positions(problem)
    rng = np.random.default_rng([problem.solver.seed, SEATED_STREAM])
    limits, F0 = problem.rules.limits, np.zeros((1, problem.model.nF))
    few, cos_max = robot.n < 6, np.cos(spec.tilt_max_rad)  # fewer than 6 joints: the ball's position alone
    Q, point, placement = [], [], []
    for g, name in enumerate(p.name for p in spec.placements):
        into = -R[g][:, 2]  # the artefact's -z: the hand's z axis points into the socket
        for k in range(problem.artefact.K):
            found = 0
            for _ in range(SEATED_TRIES * per_point):
                target = pin.SE3(tilted(into, spec.tilt_max_rad, rng), c[g, k])
                q, err = solve_ik(robot, target, limits.sample(rng), position_only=few, max_iter=SEATED_IK_STEPS)
                if (err <= IK_ACCEPT and (not few or frame_placement(robot, q).rotation[:, 2] @ into >= cos_max)
                        and not plan_violations(problem, q[None], F0, meshes=False)):
                    Q.append(q)
                    point.append(k)
                    placement.append(g)
                    found += 1
                    if found == per_point:
                        break
            if found == 0:
                raise ProblemError(
                    f"{problem.path}: [measurement.artefact].placements: no configuration of "
                    f"{SEATED_TRIES * per_point} tried seats the ball in point {k} of '{name}' at "
                    f"({', '.join(f'{v * 1e3:.1f}' for v in c[g, k])}) mm within the joint limits, the workspace "
                    f"and a tilt of {np.degrees(spec.tilt_max_rad):g} deg; move the placement within the robot's "
                    "reach or raise tilt_max_deg")
    arrays = np.array(Q), np.array(point), np.array(placement)
    for a in arrays:
        a.setflags(write=False)  # kept and shared by the callers (the memo)
    return Seated(*arrays, tuple(p.name for p in spec.placements))


def approaches(problem: Problem, Q: np.ndarray) -> np.ndarray:
    """The configurations (m, n), rad, that hold the hand of each seated configuration ``Q``
    (m, n) with its z axis as seated and the measured point :data:`APPROACH_M` back along it (out
    of the socket), its turn about the axis free (the ball is a sphere: a wrist at its limit turns
    the other way), by inverse kinematics from it, then, where a joint's limit stops it (a plan at
    its limits), from :data:`APPROACH_TRIES` starts about it (seeded); where none holds the axis
    (an arm of 5 joints, a wrist at its limit), the point alone, the hand turned as little as the
    steps of least norm turn it: where a robot program stops before the operator seats the
    ball.

    Raises
    ------
    ProblemError
        A configuration whose approach the robot cannot reach within its limits.
    """
    robot, out = problem.robot, []
    rng = np.random.default_rng([problem.solver.seed, SEATED_STREAM, 1])
    for i, q in enumerate(np.asarray(Q, dtype=float)):
        M = frame_placement(robot, q)
        target = pin.SE3(M.rotation, M.translation - APPROACH_M * M.rotation[:, 2])
        starts = [q] + [np.clip(q + rng.normal(0.0, APPROACH_SPREAD_RAD, q.size), robot.q_min, robot.q_max)
                        for _ in range(APPROACH_TRIES)]
        for position_only, q0 in itertools.product(dict.fromkeys((robot.n < 5, True)), starts):  # the axis, then the point
            qa, err = solve_ik(robot, target, q0, position_only=position_only, free_spin=True)
            if err <= IK_ACCEPT:
                break
        else:
            raise ProblemError(f"experiment {i + 1}: the hand cannot be held {APPROACH_M * 1e3:g} mm back from its "
                               "socket within the joint limits; leave the experiment out or seat it by hand from "
                               "another configuration")
        out.append(qa)
    return np.array(out)
