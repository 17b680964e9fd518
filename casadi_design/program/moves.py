"""Moves that cannot collide: each move checked along its whole path.

A move is the straight joint-space line ``q(s) = q_a + s (q_b - q_a)``, ``0 <= s <= 1``. It is
checked with the rows of the plan's rules, written once (:attr:`casadi_design.problem.rules.PlanRules.pose`):

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
* the **real meshes** (:func:`casadi_design.cell.cell.clearances`, coal) at the ``MESH_SAMPLES``
  samples where the capsule rows come closest (their local minima);
* the **beam** to the reflectors, at the same samples: the line-of-sight rows (broken where
  the beam meets a capsule, ``g < -c``) and the incidence row. A move where the beam breaks
  is flagged, not blocked: the tracker must re-acquire the reflector before the next
  measurement.

A move that breaks the clearance (a capsule row below ``-FEASIBILITY_TOL``) or whose meshes
touch is blocked: :mod:`.detours` then finds a way around it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from ..cell.capsules import capsule_names, carrier
from ..cell.cell import clearances, touching
from ..plan.rules import FEASIBILITY_TOL
from ..problem.build import Problem, per_model
from ..records.export import is_prismatic
from ..robot.compiled import compiled
from ..robot.mapped import OneByOne, evaluate

#: Largest displacement of any capsule between two samples of a move where it touches the
#: clearance, as a fraction of the clearance (module docstring).


#: Largest displacement of any capsule between two samples of a move where it touches the
#: clearance, as a fraction of the clearance (module docstring).
STEP_FRACTION = 0.25
#: That displacement (m) in a cell without clearance.
STEP_WITHOUT_CLEARANCE_M = 0.005
#: Samples of a move (the capsule rows' closest local minima) checked on the real meshes.
MESH_SAMPLES = 3
@dataclass(frozen=True, eq=False)
class MoveRules:
    """The rows a move is checked with (indices into :attr:`casadi_design.problem.rules.PlanRules.pose`):
    ``collision`` (capsule rows: self-collision, obstacles, floor), ``sight`` (lines of sight)
    and ``incidence`` (the reflector's acceptance angle, ``g >= lb``), the rows ``g`` of one
    configuration (compiled, :mod:`casadi_design.robot.compiled`), ``reach_m`` (rows, n): per row,
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
        buffer (:class:`~casadi_design.robot.mapped.OneByOne`)."""
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
    rules = problem.rules.pose
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
    the row names (:func:`casadi_design.cell.collision.capsule_names`, as the capsule rows' labels
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
    model, limits = robot.model, problem.rules.limits
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
    rows, delta = rules.collision[moving], delta[moving]  # the rows that move, and by how much
    slack = 2 * rules.step_m  # c / 2
    s, S, G = 0.0, [], []
    while True:
        g = rules.at(qa + s * (qb - qa))
        S.append(s)
        G.append(g)
        if s >= 1.0 or not rows.size or stop and g[rules.collision].min() < -FEASIBILITY_TOL:
            return np.array(S), np.array(G)
        s = min(1.0, s + float(np.min((np.maximum(g[rows], 0.0) + slack) / delta)))


def check_move(problem: Problem, qa: np.ndarray, qb: np.ndarray, meshes: bool = True) -> Move:
    """The :class:`Move` from ``qa`` to ``qb`` (n,), rad: capsule rows along the whole move
    (:func:`scan`), the meshes at the worst samples (unless not ``meshes``: ``mesh_m`` is then
    NaN), the beam (module docstring)."""
    rules = move_rules(problem)
    if rules is None:
        return FREE
    qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
    move = scanned_move(rules, qa, qb, *scan(rules, qa, qb))
    return on_meshes(problem, move) if meshes else move


def scanned_move(rules: MoveRules, qa: np.ndarray, qb: np.ndarray, S: np.ndarray, G: np.ndarray) -> Move:
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


def pose_problems(problem: Problem, q: np.ndarray, limits: bool = True) -> str | None:
    """Why the configuration ``q`` (n,), rad, cannot stand in a program (outside the joint
    limits, with ``limits``; breaking the clearance, the floor included; touching on the
    meshes), None when it can: a home, or an experiment of a plan (whose joints were checked
    against the robot's limits when it was read)."""
    bounds = problem.rules.limits
    for k, j in enumerate(problem.robot.joints if limits else ()):
        if not bounds.lower[k] - FEASIBILITY_TOL <= q[k] <= bounds.upper[k] + FEASIBILITY_TOL:
            return (f"{j} = {np.rad2deg(q[k]):.6g} deg is outside [{np.rad2deg(bounds.lower[k]):.6g}, "
                    f"{np.rad2deg(bounds.upper[k]):.6g}] deg")
    rules = move_rules(problem)
    if rules is None:
        return None
    g = rules.rows(q[None])[0]
    bad = [k for k in rules.collision if g[k] < -FEASIBILITY_TOL]
    if bad:
        k = min(bad, key=lambda k: g[k])
        return f"{rules.labels[k]} (by {-g[k] * 1e3:.3g} mm)"
    pair = touching(problem.cell, q[None])[0]  # (the plan check's query: plan.rules.mesh_contacts)
    if pair is not None:
        return f"{pair[0]} and {pair[1]} touch on the {problem.cell.check.source}"
    return None
