"""The program of a plan: home, the experiments in their best order, the via points of blocked
moves, the stops for load changes, and the time of every point.

:func:`make_program` orders the experiments (:mod:`.order`) on the times of their safe paths
(:mod:`.moves`), found lazily: the order is first solved on the straight moves' times (a lower
bound of any path's time, T being a metric), the moves of the tour found are checked and a
blocked move's time replaced by its detour's, until the tour uses only checked moves. An
exact order on these times is then exact on the true ones: any other tour costs at least its
lower bound.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..errors import DesignError, ProblemError
from ..plan.rules import LOAD_RTOL, load_violations
from ..problem.build import Problem
from .detours import MoveSearch, NoSafePath, Route
from .moves import on_meshes, pose_problems
from .order import TimeModel, best_order, load_changes, order_cost, time_model, tour_cost

#: Standard gravity (m/s^2): the mass of a hung weight, for people.
G0 = 9.80665


@dataclass(frozen=True, eq=False)
class Point:
    """A point of the program: ``q`` (n,), rad (model angles); ``kind`` "home", "via" or
    "experiment"; ``experiment`` the plan's row (1-based) or None; ``time_s`` the arrival
    time from the start; ``stop_before`` / ``stop_after``: a manual step (hang, change or
    remove a load) before the measurement, or after it, None when there is none."""

    q: np.ndarray
    kind: str
    experiment: int | None
    time_s: float
    stop_before: str | None = None
    stop_after: str | None = None


@dataclass(frozen=True, eq=False)
class Program:
    """A plan as a robot program (module docstring).

    ``points`` in program order (from home, back home); ``paths[i]`` leads to the i-th
    experiment of ``order`` (the last one back home); ``measure_s`` the measuring time per
    experiment; ``time_s`` / ``file_time_s``: the time of the program and of the plan's
    file order with its own safe moves, s; ``file_straight_s``: the file order as straight
    moves, ``file_blocked`` of which break the clearance; ``load_changes`` /
    ``file_load_changes`` likewise.
    """

    joints: tuple[str, ...]
    points: tuple[Point, ...]
    paths: tuple[Route, ...]
    order: tuple[int, ...]
    times: TimeModel
    measure_s: float
    time_s: float
    file_time_s: float
    file_straight_s: float
    load_changes: int
    file_load_changes: int
    file_blocked: int


def load_text(problem: Problem, f: np.ndarray) -> str:
    """The load ``f`` (nF,), N, for the operator: a hung weight's mass, else the vector."""
    force = problem.force
    if force is not None and force.mode == "direction":
        return f"{np.linalg.norm(f) / G0:.1f} kg ({np.linalg.norm(f):.0f} N)"
    return "F = (" + ", ".join(f"{v:.1f}" for v in f) + ") N"


def turns(problem: Problem, q: np.ndarray, home: np.ndarray) -> list[np.ndarray]:
    """The configurations of the pose ``q`` (n,), rad: each periodic joint (a range of more than
    a turn, as the UR10's +/-360 deg: :class:`casadi_design.problem.rules.JointLimits`) at its angle
    plus any whole turns within the limits; the fastest from ``home`` first, and of equal times
    (a fast wrist beside a slow arm) the one of least joint travel: no whole turn for nothing."""
    limits = problem.rules.limits
    options = [[q[k] + 2 * np.pi * t for t in range(-2, 3) if limits.lower[k] <= q[k] + 2 * np.pi * t <= limits.upper[k]]
               if limits.periodic[k] else [q[k]] for k in range(len(q))]
    out = [np.array(c) for c in itertools.product(*options)]
    times = time_model(problem)
    return sorted(out, key=lambda c: (times.move_time(home, c), float(np.abs(c - home).sum())))


def make_program(problem: Problem, Q: np.ndarray, F: np.ndarray, home: np.ndarray,
                 measure_s: float, steps: Sequence[str] | None = None) -> Program:
    """The program of the plan ``Q`` (m, n), rad, ``F`` (m, nF), N, from and back to ``home``
    (n,), rad, measuring ``measure_s`` seconds per experiment; each experiment in the
    configuration of its pose (:func:`turns`) that home reaches first by a clear move, else by
    a detour; a move between two experiments that no detour of its own makes safe goes
    through home. ``steps``: an operator's step at each experiment (m,), the program stopped
    for it (``stop_before``) and back at the experiment's configuration after it (a via point):
    a ball hand-guided into its socket from the approach ``Q`` and recorded there.

    Raises
    ------
    ProblemError
        ``home`` outside the joint limits or in collision; an experiment whose pose breaks the
        clearance or touches (its joints are checked when the plan is read), a load beyond
        ``[experiments.force]``.
    DesignError
        An experiment that no collision-free way from home reaches (the message names it), or a
        move whose meshes touch.
    """
    Q, home = np.array(Q, dtype=float), np.asarray(home, dtype=float)  # (Q a copy: its turns are set below)
    m = len(Q)
    why = pose_problems(problem, home)
    if why:
        raise ProblemError(f"--home: {why}; give a home pose inside the limits and clear of the cell")
    # the plan's poses and loads as they are: what the robot is asked to do keeps the cell and the rig
    broken = [f"experiment {k}: {why}" for k, q in enumerate(Q, start=1)
              for why in [pose_problems(problem, q, limits=False)] if why] + load_violations(problem, F)
    if broken:
        raise ProblemError(f"{broken[0]}{f' (and {len(broken) - 1} more)' if len(broken) > 1 else ''}; a program "
                           "runs the plan as it is: correct it (casadi-design evaluate --plan lists what it breaks)")
    times = time_model(problem)
    search = MoveSearch(problem, times, np.vstack([home, Q]))
    # each experiment as the configuration of its pose that home reaches by the fastest clear move
    # (a wrist turned the long way round may sweep past the forearm), else the first that a
    # detour from home reaches: home is then a way between any two
    paths: dict[tuple[int, int], Route] = {}
    for k, q in enumerate(Q, start=1):
        options = turns(problem, q, home)
        clear = next((c for c in options if not search.blocked(home, c)), None)
        if clear is None:  # (the plan's own configuration first)
            paths[0, k] = _reached(search, home, [q.copy(), *(c for c in options if not np.array_equal(c, q))], k)
            paths[k, 0] = paths[0, k].reversed()
        Q[k - 1] = paths[0, k].points[-1] if clear is None else clear
    nodes = np.vstack([home, Q])
    search.anchors = nodes
    straight = times.time_matrix(nodes)
    T = straight.copy()
    for (i, j), path in paths.items():
        T[i, j] = path.time_s
    tol = LOAD_RTOL * (problem.force.magnitude_N if problem.force is not None else 1.0)
    changes = load_changes(np.asarray(F, dtype=float).reshape(m, -1), tol)

    def safe(i: int, j: int) -> Route:
        if (i, j) not in paths:
            try:
                path = search.path(nodes[i], nodes[j])
            except NoSafePath:  # (between two experiments: the way through home is safe)
                path = _joined(safe(i, 0), safe(0, j))
            paths[i, j] = path
            paths[j, i] = path.reversed()
            T[i, j] = T[j, i] = path.time_s
        return paths[i, j]

    def edges(order) -> list[tuple[int, int]]:
        tour = [0, *order, 0]
        return list(itertools.pairwise(tour))

    while True:
        order = best_order(order_cost(T, changes))
        todo = [e for e in edges(order) if e not in paths]
        if not todo:
            break
        for i, j in todo:
            safe(i, j)
    # the capsules keep the clearance on every move: the meshes confirm it where they come closest
    final = [replace(paths[e], moves=tuple(on_meshes(problem, mv) for mv in paths[e].moves)) for e in edges(order)]
    touching = next((e for e, path in zip(edges(order), final) if any(mv.touching for mv in path.moves)), None)
    if touching is not None:
        name = ["home", *(f"experiment {k}" for k in range(1, m + 1))]
        raise DesignError(f"the move from {name[touching[0]]} to {name[touching[1]]} keeps the capsules "
                          "apart but its meshes touch; move that experiment or give another --home")
    # the file order with its own safe moves (detours only raise T off the tour: the order stays optimal)
    file_order = tuple(range(1, m + 1))
    file_blocked = sum(search.blocked(nodes[i], nodes[j]) for i, j in edges(file_order))
    for i, j in edges(file_order):
        safe(i, j)
    file_time = (tour_cost(T, file_order) + m * measure_s, tour_cost(straight, file_order) + m * measure_s)
    return _assemble(problem, Q, np.asarray(F, dtype=float).reshape(m, -1), nodes, order,
                     final, changes, times, measure_s, file_time,
                     int(sum(changes[i, j] for i, j in edges(file_order))), file_blocked, steps)


def _reached(search: MoveSearch, home: np.ndarray, options: list[np.ndarray], k: int) -> Route:
    """The detour from ``home`` to one of ``options`` (the configurations of experiment ``k``'s
    pose, :func:`turns`, none reached by a straight move; the via candidates of the first,
    RRT-Connect towards all: :meth:`MoveSearch.path_to`). Raises :class:`DesignError` when no
    detour reaches any of them."""
    try:
        return search.path_to(home, options)
    except NoSafePath as exc:
        where = (f"to its pose ({exc})" if len(options) == 1 else f"to any of the {len(options)} configurations "
                 f"of its pose (its periodic joints' whole turns: {exc})")
        raise DesignError(f"experiment {k} cannot be reached from home: no collision-free way {where}; "
                          "move that experiment or give another --home") from None


def _joined(a: Route, b: Route) -> Route:
    """The route ``a`` then ``b`` (``b`` starts where ``a`` ends)."""
    return Route(a.points + b.points[1:], a.moves + b.moves, a.time_s + b.time_s)


def _assemble(problem, Q, F, nodes, order, paths, changes, times, measure_s, file_time, file_changes,
              file_blocked, steps=None) -> Program:
    """The points of the program: home, each path's via points and its experiment (with the
    operator's step, then back at it: :func:`make_program`), home."""
    tour = [0, *order, 0]
    t, hanging = 0.0, np.zeros(F.shape[1])
    points = [Point(nodes[0], "home", None, 0.0)]
    for i, j, path in zip(tour[:-1], tour[1:], paths):
        if j == 0 and changes[i, 0]:  # the load comes off before the way home
            points[-1] = replace(points[-1], stop_after=f"remove the load {load_text(problem, hanging)}")
        for q in path.points[1:]:
            t += times.move_time(points[-1].q, q)
            points.append(Point(q, "via", None, t))
        points.pop()  # the path's end: home or the experiment
        if j == 0:
            points.append(Point(nodes[0], "home", None, t))
            break
        before = None
        if changes[i, j]:
            f = F[j - 1]
            before = (f"hang the load {load_text(problem, f)}" if not changes[0, i] else
                      f"remove the load {load_text(problem, hanging)}" if not changes[0, j] else
                      f"replace the load {load_text(problem, hanging)} by {load_text(problem, f)}")
            hanging = f
        if steps is not None:
            before = "; ".join(x for x in (before, steps[j - 1]) if x)
        points.append(Point(Q[j - 1], "experiment", j, t, before))
        t += measure_s
        if steps is not None:  # back where the step started: the moves checked start there
            points.append(Point(Q[j - 1], "via", None, t))
    return Program(problem.robot.joints, tuple(points), tuple(paths), tuple(order), times, measure_s, t,
                   *file_time, int(sum(changes[i, j] for i, j in itertools.pairwise(tour))), file_changes,
                   file_blocked)
