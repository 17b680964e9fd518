"""Detours around blocked moves: :meth:`MoveSearch.path` searches the fastest way through via points
(:class:`casadi_design.program.order.TimeModel`) through collision-free configurations, whose own
moves are checked as they are used (:mod:`.moves`; a lazy shortest-path search): the blocked
samples and the ends lifted clear along the gradient of their closest rows, the configurations
with some joints at one end and the others at the other (a move joint group by joint group),
the way to home, the plan's experiments, and seeded random configurations of the whole
workspace and near the move; RRT-Connect when none of them gives a path.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from ..plan.rules import FEASIBILITY_TOL
from ..problem.build import Problem

#: Largest displacement of any capsule between two samples of a move where it touches the
#: clearance, as a fraction of the clearance (module docstring).
from .moves import Move, check_move, move_rules, scan, scanned_move
from .order import TimeModel

#: Collision-free random configurations of the whole workspace offered as via points, and
#: per blocked move near its middle (at spreads ``LOCAL_SPREADS_RAD`` of each joint).
GLOBAL_VIAS = 16
LOCAL_VIAS = 4
LOCAL_SPREADS_RAD = (0.2, 0.5, 1.0)
#: Blocked samples of a move lifted clear as via candidates, by these steps (rad) along the
#: gradient of the row broken most (central differences of step ``FD_STEP_RAD``).
LIFTED_SAMPLES = 4
LIFT_STEPS_RAD = (0.05, 0.1, 0.2, 0.4, 0.8)
FD_STEP_RAD = 1e-5
ACTIVE_M = 0.001
#: Most joints whose every split between a move's two ends is a via candidate (2^n - 2 of them).
MIXED_UP_TO = 7
#: Via candidates on the way from a move's ends (and its middle) to home, at these fractions.
HOME_FRACTIONS = (0.25, 0.5, 0.75)
#: Blocked moves met in the search through the via candidates before RRT-Connect takes over.
MAX_CHECKS = 400
#: RRT-Connect, the search of last resort: steps (each a checked move) and their largest size.
RRT_ITERATIONS = 3000
RRT_STEP_RAD = 0.3
RRT_BOX_RAD = 0.5
#: Seed of the via points' random configurations (a program is reproducible).
VIA_SEED = 0


@dataclass(frozen=True)
class Route:
    """A collision-free way from ``points[0]`` to ``points[-1]`` (each (n,), rad): the straight
    moves between consecutive points (``moves``, checked on the capsule rows), the via points
    in between and its ``time_s``."""

    points: tuple[np.ndarray, ...]
    moves: tuple[Move, ...]
    time_s: float

    def reversed(self) -> Route:
        return Route(self.points[::-1], self.moves[::-1], self.time_s)

    @property
    def vias(self) -> int:
        return len(self.points) - 2

    @property
    def clearance_m(self) -> float:
        """The smallest capsule clearance along the path (m)."""
        return min(mv.clearance_m for mv in self.moves)

    @property
    def mesh_m(self) -> float:
        """The smallest mesh distance at the moves' closest samples (m)."""
        return min(mv.mesh_m for mv in self.moves)

    @property
    def beam(self) -> str | None:
        """The first tracker beam the path breaks on its way (None: kept)."""
        return next((mv.beam for mv in self.moves if mv.beam), None)


class NoSafePath(Exception):
    """No detour was found; the caller names the move."""


class MoveSearch:
    """Checked moves of one program, each checked once, and the detours of blocked ones.

    ``anchors`` (k, n): configurations the program visits (home and the experiments), offered
    as via points with ``GLOBAL_VIAS`` seeded collision-free random configurations.
    """

    def __init__(self, problem: Problem, times: TimeModel, anchors: np.ndarray):
        self.problem, self.times, self.rules = problem, times, move_rules(problem)
        self.anchors = np.asarray(anchors, dtype=float)
        self.checked: dict[bytes, Move] = {}
        self.broken: dict[bytes, bool] = {}
        self.scanned: dict[bytes, Move] = {}  # moves found clear by :meth:`blocked`, scanned whole
        self.rng = np.random.default_rng(VIA_SEED)

    def move(self, qa: np.ndarray, qb: np.ndarray) -> Move:
        """The move checked on the capsule rows (each move once; the meshes: :meth:`confirm`)."""
        key = np.concatenate([qa, qb]).tobytes()
        if key not in self.checked:
            self.checked[key] = self.checked[np.concatenate([qb, qa]).tobytes()] = (
                self.scanned.pop(key, None) or check_move(self.problem, qa, qb, meshes=False))
        return self.checked[key]

    def blocked(self, qa: np.ndarray, qb: np.ndarray) -> bool:
        """Whether the move breaks the clearance (:func:`scan` up to the first sample that does,
        once per move). A move found clear was scanned whole: :meth:`move` takes that scan."""
        key = np.concatenate([qa, qb]).tobytes()
        if key in self.checked:
            return self.checked[key].blocked
        if key not in self.broken:
            broken = False
            if self.rules is not None:
                qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
                S, G = scan(self.rules, qa, qb, stop=True)
                col = G[-1, self.rules.collision]
                broken = bool(col.size) and float(col.min()) < -FEASIBILITY_TOL
                if not broken:
                    self.scanned[key] = scanned_move(self.rules, qa, qb, S, G)
            self.broken[key] = self.broken[np.concatenate([qb, qa]).tobytes()] = broken
        return self.broken[key]

    @functools.cached_property
    def global_vias(self) -> np.ndarray:
        """``GLOBAL_VIAS`` seeded collision-free configurations of the whole workspace."""
        return self._free(lambda size: self.problem.rules.limits.sample(self.rng, size), GLOBAL_VIAS)

    def _free(self, draw, count: int) -> np.ndarray:
        """Up to ``count`` collision-free configurations of ``draw(size)``, in draw order."""
        found, tries = [], 0
        while sum(map(len, found)) < count and tries < 50:
            Q = draw(4 * count)
            found.append(Q[self.rules.free(Q)])
            tries += 1
        return np.vstack(found)[:count] if found else np.zeros((0, self.problem.robot.n))

    def lifted(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """Via candidates that lift the move clear ("raised poses"): from both ends and up to
        ``LIFTED_SAMPLES`` samples where the clearance breaks, steps of ``LIFT_STEPS_RAD``
        along the gradient (central differences) of the sum of the capsule rows within
        ``ACTIVE_M`` of their bound there (the row broken most, if none is)."""
        rules, limits = self.rules, self.problem.rules.limits
        S, G = scan(rules, qa, qb)
        Q, G = qa + S[:, None] * (qb - qa), G[:, rules.collision]
        broken = np.flatnonzero(G.min(axis=1) < -FEASIBILITY_TOL)
        picks = broken[np.linspace(0, len(broken) - 1, min(LIFTED_SAMPLES, len(broken))).astype(int)]
        E, out = FD_STEP_RAD * np.eye(len(qa)), []
        for q in [qa, qb, *Q[picks]]:
            g = rules.rows(q[None])[0, rules.collision]
            active = np.flatnonzero(g < ACTIVE_M)
            active = active if active.size else np.array([int(np.argmin(g))])
            D = rules.rows(np.vstack([q + E, q - E]))[:, rules.collision[active]].sum(axis=1)
            grad = (D[:len(q)] - D[len(q):]) / (2 * FD_STEP_RAD)
            if np.linalg.norm(grad) > 0:
                out += [limits.wrap(q + t * grad / np.linalg.norm(grad))[None] for t in LIFT_STEPS_RAD]
        if not out:
            return np.zeros((0, len(qa)))
        V = np.vstack(out)
        return V[rules.free(V)]

    def mixed(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """The collision-free configurations with some joints at ``qa`` and the others at
        ``qb`` (a move joint group by joint group, as the wrist first, then the arm); for more
        than ``MIXED_UP_TO`` joints, the groups of consecutive joints."""
        n = len(qa)
        if n <= MIXED_UP_TO:
            masks = [np.array([(k >> j) & 1 for j in range(n)], dtype=bool) for k in range(1, 2**n - 1)]
        else:
            masks = [np.arange(n) < j for j in range(1, n)] + [np.arange(n) >= j for j in range(1, n)]
        Q = np.array([np.where(mask, qb, qa) for mask in masks])
        return Q[self.rules.free(Q)]

    def toward_home(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """The collision-free configurations on the way from ``qa``, ``qb`` and their middle to
        home (``anchors[0]``, raised clear of the cell) at the fractions ``HOME_FRACTIONS``."""
        home, Q = self.anchors[0], []
        for q in (qa, qb, (qa + qb) / 2):
            Q += [q + f * (home - q) for f in HOME_FRACTIONS]
        Q = np.array(Q)
        return Q[self.rules.free(Q)]

    def local_vias(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """``LOCAL_VIAS`` collision-free configurations near the move's middle per spread of
        ``LOCAL_SPREADS_RAD`` (each joint drawn around the middle with that std)."""
        limits, middle = self.problem.rules.limits, (qa + qb) / 2
        return np.vstack([self._free(lambda size, s=s: limits.wrap(middle + s * self.rng.standard_normal((size, middle.size))),
                                     LOCAL_VIAS) for s in LOCAL_SPREADS_RAD])

    def path(self, qa: np.ndarray, qb: np.ndarray) -> Route:
        """The straight move when it keeps the clearance, else the fastest detour found
        (:meth:`path_to`). Raises :class:`NoSafePath`."""
        qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
        if not self.blocked(qa, qb):
            return Route((qa, qb), (self.move(qa, qb),), self.times.move_time(qa, qb))
        return self.path_to(qa, [qb])

    def path_to(self, qa: np.ndarray, goals: list[np.ndarray]) -> Route:
        """A detour from ``qa`` to one of ``goals`` (the configurations of one pose; their
        straight moves from ``qa`` are not tried): the fastest found through the via candidates
        to the first goal (a lazy shortest path: the fastest path is checked move by move, a
        blocked move removed, until a path is clear), else RRT-Connect towards every goal at
        once. Raises :class:`NoSafePath`."""
        qa, goals = np.asarray(qa, dtype=float), [np.asarray(g, dtype=float) for g in goals]
        qb = goals[0]
        nodes = np.vstack([qa, qb, self.lifted(qa, qb), self.mixed(qa, qb), self.toward_home(qa, qb),
                           self.anchors, self.global_vias, self.local_vias(qa, qb)])
        T = self.times.time_matrix(nodes)
        blocked = np.zeros(T.shape, dtype=bool)
        blocked[0, 1] = blocked[1, 0] = True
        for _ in range(MAX_CHECKS):
            route = _shortest(np.where(blocked, np.inf, T), 0, 1)
            if route is None:
                break
            legs = list(itertools.pairwise(route))
            bad = next(((i, j) for i, j in legs if self.blocked(nodes[i], nodes[j])), None)
            if bad is None:
                return Route(tuple(nodes[route]), tuple(self.move(nodes[i], nodes[j]) for i, j in legs),
                            float(sum(T[i, j] for i, j in legs)))
            blocked[bad] = blocked[bad[::-1]] = True
        route = self.rrt_connect(qa, goals)
        if route is None:
            raise NoSafePath(f"no collision-free detour among {len(nodes) - 2} via candidates nor by "
                             f"{RRT_ITERATIONS} RRT-Connect steps")
        route = self.shortcut(route)
        legs = list(itertools.pairwise(route))
        return Route(tuple(route), tuple(self.move(a, b) for a, b in legs),
                    float(sum(self.times.move_time(a, b) for a, b in legs)))

    def rrt_connect(self, qa: np.ndarray, goals: list[np.ndarray]) -> list[np.ndarray] | None:
        """A collision-free path by RRT-Connect (Kuffner and LaValle 2000) from ``qa`` to one of
        ``goals``: two trees, one grown from ``qa``, one from every goal, towards seeded random
        configurations (half of them in the box of ``qa`` and the first goal widened by
        ``RRT_BOX_RAD``, half within the joint limits) by steps of at most ``RRT_STEP_RAD``,
        each step a checked move, until they meet."""
        limits, rng = self.problem.rules.limits, np.random.default_rng(VIA_SEED)
        qb = goals[0]
        trees = [([qa], [-1]), (list(goals), [-1] * len(goals))]

        def extend(tree, target):
            nodes, parents = tree
            k = int(np.argmin(np.linalg.norm(np.array(nodes) - target, axis=1)))
            d = target - nodes[k]
            new = target if np.linalg.norm(d) <= RRT_STEP_RAD else nodes[k] + RRT_STEP_RAD * d / np.linalg.norm(d)
            if self.rules.free(new[None])[0] and not self.blocked(nodes[k], new):
                nodes.append(new)
                parents.append(k)
                return len(nodes) - 1
            return None

        def branch(tree, k):
            nodes, parents = tree
            out = []
            while k >= 0:
                out.append(nodes[k])
                k = parents[k]
            return out

        for it in range(RRT_ITERATIONS):
            grow, other = trees[it % 2], trees[1 - it % 2]
            # half the samples in the box around both ends (widened by RRT_BOX_RAD), half anywhere
            lo, hi = ((np.maximum(np.minimum(qa, qb) - RRT_BOX_RAD, limits.lower),
                       np.minimum(np.maximum(qa, qb) + RRT_BOX_RAD, limits.upper)) if rng.random() < 0.5
                      else (limits.lower, limits.upper))
            k = extend(grow, rng.uniform(lo, hi))
            if k is None:
                continue
            target = grow[0][k]
            while (j := extend(other, target)) is not None:
                if np.array_equal(other[0][j], target):
                    a, b = branch(grow, k), branch(other, j)
                    path = a[::-1] + b[1:] if it % 2 == 0 else b[::-1] + a[1:]
                    return path
        return None

    def shortcut(self, route: list[np.ndarray]) -> list[np.ndarray]:
        """``route`` with its points skipped where a straight move from an earlier point keeps
        the clearance (from the start, the farthest point reachable first)."""
        out, i = [route[0]], 0
        while i < len(route) - 1:
            j = next(j for j in range(len(route) - 1, i, -1) if j == i + 1 or not self.blocked(route[i], route[j]))
            out.append(route[j])
            i = j
        return out


def _shortest(W: np.ndarray, source: int, target: int) -> list[int] | None:
    """Dijkstra on the complete graph of edge weights ``W`` (inf: no edge); the node list."""
    n = len(W)
    dist, prev, done = np.full(n, np.inf), np.full(n, -1), np.zeros(n, dtype=bool)
    dist[source] = 0.0
    while True:
        u = int(np.argmin(np.where(done, np.inf, dist)))
        if done[u] or not np.isfinite(dist[u]):
            return None
        if u == target:
            break
        done[u] = True
        better = ~done & (dist[u] + W[u] < dist)
        dist[better], prev[better] = dist[u] + W[u][better], u
    route = [target]
    while route[-1] != source:
        route.append(int(prev[route[-1]]))
    return route[::-1]
