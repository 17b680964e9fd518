"""Collision rules of one configuration: links as capsules (:mod:`.capsules`), obstacles, lines of sight.

Two capsules are apart by at least ``c`` (the clearance, m) when

    dist([a1, b1], [a2, b2]) - r1 - r2 - c >= 0,

with ``dist`` the segment-segment distance (:mod:`.segments`). The rows of :func:`capsule_rows`
are of that form, ``g(q) >= 0`` (m), for

* self-collision: every pair of capsules that can meet (:func:`.pairs.self_collision_pairs`);
* obstacles fixed in the world, each kind giving its rows (:mod:`casadi_design.cell.obstacles`:
  half-spaces such as the floor, boxes, capsules);
* lines of sight: the beam from a tracker to a reflector carried by the robot against every
  capsule, except those of the link carrying the reflector (the beam ends on that link).

:func:`casadi_design.cell.cell.clearances` checks a plan on the real meshes with Pinocchio and
coal. :func:`capsule_clearances` is the numpy twin of the rows.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ProblemError
from ..robot.robots import Robot
from .capsules import capsule_ends, capsule_ends_symbolic, capsule_names, carrier, moved_by_chain
from .obstacles import Capsule, Obstacle, vector3
from .pairs import PAIR_SAMPLES, near_pairs, self_collision_pairs
from .segments import CASADI_OPS, NUMPY_OPS, segment_distance, segment_distance_np


@dataclass(frozen=True)
class LineOfSight:
    """Beam from a tracker at ``tracker_m`` (world, m) to a reflector at ``point_m`` in
    ``frame`` (m).

    ``excluded`` names the capsule frames the beam may touch; by default the capsules carried
    by the same joint as ``frame`` (the reflector sits on, or inside, that link's capsule).
    ``spread_m``: the beam stands for every beam from the tracker to a point within this
    distance of ``point_m`` (several reflectors around their centroid): each such beam is
    within ``spread_m`` of this one, point for point, so the rows keep this beam
    ``spread_m`` further from the capsules.
    """

    tracker_m: tuple[float, float, float]
    frame: str
    point_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    excluded: tuple[str, ...] | None = None
    spread_m: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "tracker_m", vector3(self.tracker_m, "line of sight: tracker_m"))
        object.__setattr__(self, "point_m", vector3(self.point_m, f"line of sight to '{self.frame}': point_m"))


# ---------------------------------------------------------------------------------------------
# segment-segment distance


def obstacle_pairs(robot: Robot, capsules: Sequence[Capsule], obstacles: Sequence[Obstacle],
                   clearance_m: float = 0.0, samples: int = PAIR_SAMPLES,
                   seed: int = 0) -> tuple[tuple[tuple[int, int], ...], dict[tuple[str, str], str]]:
    """The (moving capsule, obstacle) pairs that can meet and that the capsules can keep apart.

    As :func:`self_collision_pairs`, over ``samples`` seeded configurations within the joint
    limits: a pair whose row is the same in every sample (a link that only turns about a
    vertical axis over the floor) is skipped as "constant distance" when positive; a pair
    whose row is negative in every sample (the housing at the shoulder of a link always
    within the clearance of the floor the robot stands on) is skipped with that reason.
    Returns the kept pairs and the reasons for the others, keyed by (capsule, obstacle) names.
    """
    near = near_pairs(robot, capsules, obstacles)
    rng = np.random.default_rng(seed)
    rows = [capsule_clearances(robot, capsules, q, clearance_m, obstacles, (), (), near)
            for q in rng.uniform(robot.q_min, robot.q_max, size=(samples, robot.n))]
    labels = rows[0][1]
    G = np.array([g for g, _ in rows])
    # a pair's rows share its label (a half-space gives two); its clearance is their minimum
    groups = list(dict.fromkeys(labels))
    G = np.column_stack([G[:, [i for i, lb in enumerate(labels) if lb == label]].min(axis=1) for label in groups])
    names, kept, skipped = capsule_names(capsules), [], {}
    for (k, o), g in zip(near, G.T):
        key = (names[k], obstacles[o].label)
        if np.ptp(g) < 1e-9 and g[0] > 0:
            skipped[key] = "constant distance, positive"
        elif np.all(g <= 0):
            skipped[key] = (f"closer than the clearance in all {samples} sampled configurations "
                            f"(largest clearance {g.max() * 1e3:.1f} mm)")
        else:
            kept.append((k, o))
    return tuple(kept), skipped


def _rows(robot: Robot, capsules: Sequence[Capsule], ends: Callable, ops, dist: Callable,
          clearance_m: float, obstacles: Sequence[Obstacle], sights: Sequence[LineOfSight],
          pairs: Sequence[tuple[int, int]], near: Sequence[tuple[int, int]] | None = None) -> list[tuple[object, str]]:
    """Rows ``(g, label)`` with ``g >= 0`` required (m), for CasADi or numpy (``ops``);
    ``near``: the (capsule, obstacle) index pairs constrained (None: :func:`near_pairs`)."""
    model, names = robot.model, capsule_names(capsules)
    world = [ends(c) for c in capsules]
    jids = [carrier(model, c.frame)[0] for c in capsules]
    mm = f"{clearance_m * 1e3:g} mm"
    out = []
    for i, j in pairs:
        g = dist(*world[i], *world[j]) - capsules[i].radius_m - capsules[j].radius_m - clearance_m
        out.append((g, f"links {names[i]} and {names[j]} closer than {mm}"))

    def place(segment: Capsule):
        """World ends of a segment of an obstacle (m); it must not move with the robot."""
        if moved_by_chain(robot, carrier(model, segment.frame)[0]):
            raise ProblemError(f"obstacle capsule on '{segment.frame}': it moves with the robot; "
                               "give obstacles in a fixed frame such as 'universe'")
        return ends(segment)

    for k, o in (near_pairs(robot, capsules, obstacles) if near is None else near):
        (a, b), obstacle = world[k], obstacles[o]
        out += [(g - clearance_m, f"link {names[k]} closer than {mm} to {obstacle.label}")
                for g in obstacle.rows(a, b, capsules[k].radius_m, ops, dist, place)]
    for sight in sights:
        jid, _ = carrier(model, sight.frame, "line of sight")
        excluded = (set(sight.excluded) if sight.excluded is not None
                    else {c.frame for c, j in zip(capsules, jids) if j == jid})
        reflector = ends(Capsule(sight.frame, sight.point_m, sight.point_m, 0.0))[0]
        tracker = np.array(sight.tracker_m)
        for k, c in enumerate(capsules):
            if c.frame not in excluded:
                g = dist(tracker, reflector, *world[k]) - c.radius_m - sight.spread_m - clearance_m
                out.append((g, f"line of sight to {sight.frame}: within {mm} of link {names[k]}"))
    return out


@dataclass(frozen=True, eq=False)
class PointRows:
    """Collision rows as functions of world points: the form in which the NLP holds only the
    rows that can bind (:mod:`casadi_design.optimisation.reduced`).

    ``W`` (CasADi SX, 3K) stands for K world points (m): both ends of every capsule moving with
    q, and each line of sight's reflector; ``points`` (SX of q, 3K) gives them at q. Row r is
    ``G_r(W) >= 0`` (m) with label ``labels[r]``; it depends on at most 4 of the points (two
    segments), the rest of its data (obstacles, tracker, radii, clearance) being constants.
    """

    W: ca.SX
    points: ca.SX
    G: tuple[ca.SX, ...]
    labels: tuple[str, ...]

    def of_q(self) -> list[ca.SX]:
        """The rows as SX of q: ``G_r(points(q))``."""
        return ca.substitute(list(self.G), [self.W], [self.points]) if self.G else []


def capsule_point_rows(robot: Robot, capsules: Sequence[Capsule], q: ca.SX, clearance_m: float = 0.0,
                       obstacles: Sequence[Obstacle] = (), sights: Sequence[LineOfSight] = (),
                       pairs: Sequence[tuple[int, int]] | None = None,
                       near: Sequence[tuple[int, int]] | None = None) -> PointRows:
    """The rows of :func:`capsule_rows` as functions of the world points (:class:`PointRows`)."""
    if pairs is None:
        pairs = self_collision_pairs(robot, capsules, clearance_m).kept
    placed = capsule_ends_symbolic(robot, capsules, q)
    symbols, points = [], []

    def ends(capsule: Capsule):
        if not moved_by_chain(robot, carrier(robot.model, capsule.frame)[0]):
            return placed(capsule)  # constants
        out = []
        for p in placed(capsule):
            symbols.append(ca.SX.sym(f"w{len(symbols)}", 3))
            points.append(p)
            out.append(symbols[-1])
        return tuple(out)

    rows = _rows(robot, capsules, ends, CASADI_OPS, segment_distance, clearance_m, obstacles, sights, pairs, near)
    return PointRows(ca.vertcat(*symbols) if symbols else ca.SX(0, 1),
                     ca.vertcat(*points) if points else ca.SX(0, 1),
                     tuple(g for g, _ in rows), tuple(label for _, label in rows))


def capsule_rows(robot: Robot, capsules: Sequence[Capsule], q: ca.SX, clearance_m: float = 0.0,
                 obstacles: Sequence[Obstacle] = (), sights: Sequence[LineOfSight] = (),
                 pairs: Sequence[tuple[int, int]] | None = None,
                 near: Sequence[tuple[int, int]] | None = None) -> list[tuple[ca.SX, float, float, str]]:
    """Collision rows of configuration ``q`` (CasADi SX, n): ``(g(q), 0, inf, label)``, each
    ``g >= 0`` (m), in the format of :attr:`casadi_design.problem.rules.PlanRules.pose`' rows.

    * self-collision, for ``pairs`` of capsule indices (default :func:`self_collision_pairs`):
      ``dist(s_i, s_j) - r_i - r_j - clearance_m``;
    * for each (capsule, obstacle) index pair of ``near`` (default: every capsule moving with
      ``q`` and every obstacle; :func:`obstacle_pairs` selects those that can meet): each row
      of the obstacle (:meth:`casadi_design.cell.obstacles.Obstacle.rows`, a lower bound of the
      distance between the capsule and the obstacle) ``- clearance_m``;
    * for each line of sight, every capsule not excluded (see :class:`LineOfSight`):
      ``dist([tracker, reflector(q)], s_k) - r_k - spread - clearance_m``.

    ``dist`` is :func:`segment_distance` (smoothed, within ``SMOOTHING_M`` below the exact
    distance). The rows are those of :func:`capsule_point_rows` at the points of q.
    """
    rows = capsule_point_rows(robot, capsules, q, clearance_m, obstacles, sights, pairs, near)
    return [(g, 0.0, np.inf, label) for g, label in zip(rows.of_q(), rows.labels)]


def capsule_clearances(robot: Robot, capsules: Sequence[Capsule], q: np.ndarray, clearance_m: float = 0.0,
                       obstacles: Sequence[Obstacle] = (), sights: Sequence[LineOfSight] = (),
                       pairs: Sequence[tuple[int, int]] | None = None,
                       near: Sequence[tuple[int, int]] | None = None) -> tuple[np.ndarray, tuple[str, ...]]:
    """Numpy twin of :func:`capsule_rows` at ``q`` (ndarray, n): the rows' values ``g`` (m,
    negative: too close) and labels, in the same order; placements by Pinocchio."""
    if pairs is None:
        pairs = self_collision_pairs(robot, capsules, clearance_m).kept
    rows = _rows(robot, capsules, capsule_ends(robot, np.asarray(q, dtype=float)), NUMPY_OPS, segment_distance_np,
                 clearance_m, obstacles, sights, pairs, near)
    return np.array([float(g) for g, _ in rows]), tuple(label for _, label in rows)
