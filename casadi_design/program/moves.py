"""Moves that cannot collide: each move checked along its whole path, via points where blocked.

A move is the straight joint-space line ``q(s) = q_a + s (q_b - q_a)``, ``0 <= s <= 1``. It is
checked with the rows of the plan's rules, written once (:func:`casadi_design.plan.rules.pose_constraints`):

* the cell's **capsule rows** (self-collision, obstacles and the floor: ``g >= 0`` keeps the
  clearance c) at samples close enough that no capsule can come more than ``c / 2`` inside
  the clearance between two of them. A point of the robot at distance at most ``R_k`` from
  the axis of joint k moves by at most ``delta = sum_k R_k |q_b,k - q_a,k|`` (m) over the
  whole move (``R_k = 1`` for a prismatic joint), so a row ``g_r`` (a distance between
  bodies that move at most ``delta_r = sum of their delta``, :func:`row_reach`) changes by
  at most ``delta_r ds`` over a step ``ds``. From a sample where every row is ``g_r >= 0``,
  the next sample is ``ds = min_r (g_r + c / 2) / delta_r`` further: where two capsules touch
  the clearance (``g_r = 0``) neither moves more than ``STEP_FRACTION = 1/4`` of the
  clearance between samples (two moving capsules; one against a fixed obstacle: half of it),
  and the steps grow with the distance.
  Where every sample keeps the clearance, the whole move keeps at least ``c / 2`` between
  the capsules, hence between the meshes inside them (``STEP_WITHOUT_CLEARANCE_M`` stands
  for ``c / 4`` in a cell without clearance);
* the **real meshes** (:func:`casadi_design.model.cell.clearances`, coal) at the ``MESH_SAMPLES``
  samples where the capsule rows come closest (their local minima);
* the **beam** to the reflectors, at the same samples: the line-of-sight rows (broken where
  the beam meets a capsule, ``g < -c``) and the incidence row. A move where the beam breaks
  is flagged, not blocked: the tracker must re-acquire the reflector before the next
  measurement.

A move that breaks the clearance (a capsule row below ``-FEASIBILITY_TOL``) or whose meshes
touch is blocked; :meth:`MoveSearch.path` then searches a detour through via points: the
fastest path (:class:`casadi_design.program.order.TimeModel`) through collision-free
configurations, whose own moves are checked as they are used (a lazy shortest-path search):
the blocked samples and the ends lifted clear along the gradient of their closest rows, the
configurations with some joints at one end and the others at the other (a move joint group by
joint group), the way to home, the plan's experiments, and seeded random configurations of the
whole workspace and near the move; RRT-Connect when none of them gives a path.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from ..model.build import Problem, per_model
from ..model.cell import clearances
from ..model.capsules import capsule_names, carrier
from ..model.compiled import compiled
from ..records.export import is_prismatic
from ..model.mapped import OneByOne, evaluate
from ..plan.rules import FEASIBILITY_TOL, joint_limits, pose_constraints
from .order import TimeModel

#: Largest displacement of any capsule between two samples of a move where it touches the
#: clearance, as a fraction of the clearance (module docstring).
STEP_FRACTION = 0.25
#: That displacement (m) in a cell without clearance.
STEP_WITHOUT_CLEARANCE_M = 0.005
#: Samples of a move (the capsule rows' closest local minima) checked on the real meshes.
MESH_SAMPLES = 3
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


@dataclass(frozen=True, eq=False)
class MoveRules:
    """The rows a move is checked with (indices into :func:`casadi_design.plan.rules.pose_constraints`):
    ``collision`` (capsule rows: self-collision, obstacles, floor), ``sight`` (lines of sight)
    and ``incidence`` (the reflector's acceptance angle, ``g >= lb``), the rows ``g`` of one
    configuration (compiled, :mod:`casadi_design.model.compiled`), ``reach_m`` (rows, n): per row,
    the sum of the bounds R_k of the module docstring of the bodies it keeps apart (0 for rows
    that are not capsule rows), and ``step_m``, the capsules' largest displacement between
    two samples where they touch the clearance."""

    g: ca.Function
    lb: np.ndarray
    labels: tuple[str, ...]
    collision: np.ndarray
    sight: np.ndarray
    incidence: np.ndarray
    reach_m: np.ndarray
    step_m: float
    clearance_m: float

    @functools.cached_property
    def at(self) -> OneByOne:
        """``g`` called one configuration at a time, as a move's scan does, through one kept
        buffer (:class:`~casadi_design.model.mapped.OneByOne`)."""
        return OneByOne(self.g)

    def rows(self, Q: np.ndarray) -> np.ndarray:
        """Every row (k, rows) at the configurations ``Q`` (k, n)."""
        return evaluate(self.g, np.asarray(Q, dtype=float))[0][:, :, 0]

    def free(self, Q: np.ndarray) -> np.ndarray:
        """Whether each configuration of ``Q`` (k, n) keeps every capsule row (clearance)."""
        G = self.rows(Q)[:, self.collision]
        return np.all(G >= -FEASIBILITY_TOL, axis=1) if G.size else np.ones(len(Q), dtype=bool)


@per_model
def move_rules(problem: Problem) -> MoveRules | None:
    """The :class:`MoveRules` of ``problem`` (None without a cell: nothing to collide with)."""
    cell = problem.cell
    if cell is None:
        return None
    rules = pose_constraints(problem)
    screen = rules.screen.numel_out(0)
    index = np.arange(len(rules.labels))
    sight = np.array([k >= screen and label.startswith("line of sight") for k, label in enumerate(rules.labels)])
    capsule = index >= screen
    clearance = cell.spec.clearance_m
    return MoveRules(compiled(rules.g), rules.lb, rules.labels,
                     index[capsule & ~sight], index[sight], index[(index < screen) & (np.array(rules.units) == "cos")],
                     row_reach(problem, rules.labels),
                     STEP_FRACTION * clearance if clearance > 0 else STEP_WITHOUT_CLEARANCE_M, clearance)


def row_reach(problem: Problem, labels: tuple[str, ...]) -> np.ndarray:
    """Per row of ``labels`` (rows, n), m per rad: the sum of :func:`reach` over the capsules
    the row names (:func:`casadi_design.model.collision.capsule_names`, as the capsule rows' labels
    name them; 0 for the other rows). A capsule row changes by at most ``reach @ |dq|`` over
    a move ``dq``: it is a distance between bodies that move at most that much."""
    cell = problem.cell
    bodies = {name: reach(problem, [(c.frame, np.array(c.a_m)), (c.frame, np.array(c.b_m))])
              for name, c in zip(capsule_names(cell.capsules), cell.capsules)}
    out = np.zeros((len(labels), problem.robot.n))
    for r, label in enumerate(labels):
        out[r] = sum((bodies[w] for w in (w.rstrip(":") for w in label.split()) if w in bodies),
                     np.zeros(problem.robot.n))
    return out


def reach(problem: Problem, points: list[tuple[str, np.ndarray]]) -> np.ndarray:
    """``R_k`` (m per rad, 1 for a prismatic joint): an upper bound, in every configuration, of
    the distance from joint k's origin to every point moved by joint k, of ``points`` (frame,
    position in that frame, m).

    The distance from joint k to a point carried by joint j is at most the sum of the (fixed)
    distances between the origins of the joints from k to j, plus the travel of the
    prismatic joints among them, plus the point's distance from joint j's origin.
    """
    robot = problem.robot
    model, limits = robot.model, joint_limits(problem)
    chain = {jid: k for k, jid in enumerate(robot.joint_ids)}
    travel = {jid: max(abs(limits.lower[k]), abs(limits.upper[k])) if is_prismatic(problem, k) else 0.0
              for jid, k in chain.items()}
    out = np.zeros(robot.n)
    for frame, p in points:
        jid, jMp = carrier(model, frame)
        lever, at = float(np.linalg.norm(jMp.act(p))), jid
        while at > 0:
            if at in chain:
                k = chain[at]
                out[k] = 1.0 if is_prismatic(problem, k) else max(out[k], lever)
            lever += float(np.linalg.norm(model.jointPlacements[at].translation)) + travel.get(at, 0.0)
            at = model.parents[at]
    return out


@dataclass(frozen=True)
class Move:
    """One straight joint-space move, checked (module docstring).

    ``clearance_m``: the smallest capsule clearance along it (the capsule rows' minimum plus
    the cell's clearance: the capsules' distance over the pairs the rows constrain), between
    ``closest`` (the row's label); ``mesh_m``: the smallest distance on the real geometry at
    the worst samples; ``touching``: two bodies touching there; ``beam``: the first
    line-of-sight or incidence row broken along the move (None: the tracker keeps the beam);
    ``samples``: how many configurations were checked; ``worst_q`` (k, n), rad: the samples
    checked on the meshes.
    """

    clearance_m: float
    closest: str
    mesh_m: float
    touching: tuple[str, str] | None
    beam: str | None
    samples: int
    cell_clearance_m: float
    worst_q: np.ndarray | None = None

    @property
    def blocked(self) -> bool:
        return self.clearance_m < self.cell_clearance_m - FEASIBILITY_TOL or self.touching is not None


#: The move without a cell: nothing to collide with or to hide the beam.
FREE = Move(np.inf, "", np.inf, None, None, 0, 0.0)


def scan(rules: MoveRules, qa: np.ndarray, qb: np.ndarray, stop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The samples ``s`` (k,) of the move from ``qa`` to ``qb`` and every row at them (k, rows),
    stepping ``ds = min_r (max(g_r, 0) + c / 2) / delta_r`` over the capsule rows g_r (module
    docstring); with ``stop``, up to the first sample that breaks the clearance."""
    qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
    delta = rules.reach_m[rules.collision] @ np.abs(qb - qa)  # each row's largest change over the move
    moving = delta > 0
    slack = 2 * rules.step_m  # c / 2
    s, S, G = 0.0, [], []
    while True:
        g = rules.at(qa + s * (qb - qa))
        S.append(s)
        G.append(g)
        col = g[rules.collision]
        if s >= 1.0 or not moving.any() or stop and col.min() < -FEASIBILITY_TOL:
            return np.array(S), np.array(G)
        s = min(1.0, s + float(np.min((np.maximum(col[moving], 0.0) + slack) / delta[moving])))


def check_move(problem: Problem, qa: np.ndarray, qb: np.ndarray, meshes: bool = True) -> Move:
    """The :class:`Move` from ``qa`` to ``qb`` (n,), rad: capsule rows along the whole move
    (:func:`scan`), the meshes at the worst samples (unless not ``meshes``: ``mesh_m`` is then
    NaN), the beam (module docstring)."""
    rules = move_rules(problem)
    if rules is None:
        return FREE
    qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
    move = _scanned(rules, qa, qb, *scan(rules, qa, qb))
    return on_meshes(problem, move) if meshes else move


def _scanned(rules: MoveRules, qa: np.ndarray, qb: np.ndarray, S: np.ndarray, G: np.ndarray) -> Move:
    """The :class:`Move` from the whole scan ``S``, ``G`` of :func:`scan`, its meshes not checked."""
    col = G[:, rules.collision]
    worst = col.min(axis=1) if col.size else np.full(len(S), np.inf)
    closest = rules.labels[rules.collision[np.argmin(col[np.argmin(worst)])]] if col.size else ""
    beam = None
    broken_sight = G[:, rules.sight] < -rules.clearance_m
    broken_angle = G[:, rules.incidence] < rules.lb[rules.incidence] - FEASIBILITY_TOL
    for rows, broken in ((rules.sight, broken_sight), (rules.incidence, broken_angle)):
        if beam is None and broken.any():
            beam = rules.labels[rows[np.argwhere(broken)[0][1]]]
    # the meshes where the capsules come closest: the smallest local minima of the rows
    minima = [i for i in range(len(worst)) if (i == 0 or worst[i] <= worst[i - 1])
              and (i == len(worst) - 1 or worst[i] <= worst[i + 1])]
    at = sorted(minima, key=lambda i: worst[i])[:MESH_SAMPLES]
    return Move(float(worst.min()) + rules.clearance_m, closest, np.nan, None, beam, len(S), rules.clearance_m,
                qa + S[at, None] * (qb - qa))


def on_meshes(problem: Problem, move: Move) -> Move:
    """``move`` with its real-geometry distance and touching bodies at its worst samples."""
    if move.worst_q is None or not len(move.worst_q):
        return move
    near = clearances(problem.cell, move.worst_q)
    touching = next((c.touching for c in near if c.touching is not None), None)
    return replace(move, mesh_m=min(c.distance_m for c in near), touching=touching)


@dataclass(frozen=True)
class Path:
    """A collision-free way from ``points[0]`` to ``points[-1]`` (each (n,), rad): the straight
    moves between consecutive points (``moves``, checked on the capsule rows), the via points
    in between and its ``time_s``."""

    points: tuple[np.ndarray, ...]
    moves: tuple[Move, ...]
    time_s: float

    def reversed(self) -> Path:
        return Path(self.points[::-1], self.moves[::-1], self.time_s)

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
                    self.scanned[key] = _scanned(self.rules, qa, qb, S, G)
            self.broken[key] = self.broken[np.concatenate([qb, qa]).tobytes()] = broken
        return self.broken[key]

    @functools.cached_property
    def global_vias(self) -> np.ndarray:
        """``GLOBAL_VIAS`` seeded collision-free configurations of the whole workspace."""
        return self._free(lambda size: joint_limits(self.problem).sample(self.rng, size), GLOBAL_VIAS)

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
        rules, limits = self.rules, joint_limits(self.problem)
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
        limits, middle = joint_limits(self.problem), (qa + qb) / 2
        return np.vstack([self._free(lambda size, s=s: limits.wrap(middle + s * self.rng.standard_normal((size, middle.size))),
                                     LOCAL_VIAS) for s in LOCAL_SPREADS_RAD])

    def path(self, qa: np.ndarray, qb: np.ndarray) -> Path:
        """The straight move when it keeps the clearance, else the fastest detour found
        (lazy shortest path: the fastest path through the candidates is checked move by move,
        a blocked move removed, until a path is clear). Raises :class:`NoSafePath`."""
        qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
        if not self.blocked(qa, qb):
            return Path((qa, qb), (self.move(qa, qb),), self.times.move_time(qa, qb))
        nodes = np.vstack([qa, qb, self.lifted(qa, qb), self.mixed(qa, qb), self.toward_home(qa, qb), self.anchors,
                           self.global_vias, self.local_vias(qa, qb)])
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
                return Path(tuple(nodes[route]), tuple(self.move(nodes[i], nodes[j]) for i, j in legs),
                            float(sum(T[i, j] for i, j in legs)))
            blocked[bad] = blocked[bad[::-1]] = True
        route = self.rrt_connect(qa, qb)
        if route is None:
            raise NoSafePath(f"no collision-free detour among {len(nodes) - 2} via candidates nor by "
                             f"{RRT_ITERATIONS} RRT-Connect steps")
        route = self.shortcut(route)
        legs = list(itertools.pairwise(route))
        return Path(tuple(route), tuple(self.move(a, b) for a, b in legs),
                    float(sum(self.times.move_time(a, b) for a, b in legs)))

    def rrt_connect(self, qa: np.ndarray, qb: np.ndarray) -> list[np.ndarray] | None:
        """A collision-free path by RRT-Connect (Kuffner and LaValle 2000): two trees grown from
        ``qa`` and ``qb`` towards seeded random configurations (half of them in the box of both
        ends widened by ``RRT_BOX_RAD``, half within the joint limits) by steps
        of at most ``RRT_STEP_RAD``, each step a checked move, until they meet."""
        limits, rng = joint_limits(self.problem), np.random.default_rng(VIA_SEED)
        trees = [([qa], [-1]), ([qb], [-1])]

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


def home_problems(problem: Problem, home: np.ndarray) -> str | None:
    """Why ``home`` (n,), rad, cannot start a program (outside the joint limits, breaking the
    clearance or touching on the meshes), None when it can."""
    limits = joint_limits(problem)
    for k, j in enumerate(problem.robot.joints):
        if not limits.lower[k] - FEASIBILITY_TOL <= home[k] <= limits.upper[k] + FEASIBILITY_TOL:
            return (f"{j} = {np.rad2deg(home[k]):.6g} deg is outside [{np.rad2deg(limits.lower[k]):.6g}, "
                    f"{np.rad2deg(limits.upper[k]):.6g}] deg")
    rules = move_rules(problem)
    if rules is None:
        return None
    g = rules.rows(home[None])[0]
    bad = [k for k in rules.collision if g[k] < -FEASIBILITY_TOL]
    if bad:
        k = min(bad, key=lambda k: g[k])
        return f"{rules.labels[k]} (by {-g[k] * 1e3:.3g} mm)"
    near = clearances(problem.cell, home[None])[0]
    if near.touching is not None:
        return f"{near.touching[0]} and {near.touching[1]} touch on the {problem.cell.check.source}"
    return None
