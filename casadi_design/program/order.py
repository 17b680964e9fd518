"""The time of a move and the order of the experiments that minimises the time of a plan.

A move is a synchronous joint-space move from ``q_a`` to ``q_b``: every joint starts and stops
together, each on a trapezoidal speed profile (speed ``v_k``, acceleration ``a_k = v_k / t_acc``
with ``t_acc`` the acceleration time of ``[robot.controller]``), and the slowest joint sets the
time. Joint k alone needs, for ``d = |q_b,k - q_a,k|``,

    t_k(d) = 2 sqrt(d / a_k)          if d < v_k^2 / a_k   (a triangle: full speed never reached)
    t_k(d) = d / v_k + v_k / a_k      otherwise            (accelerate, cruise, brake),

and the move takes ``T(q_a, q_b) = max_k t_k(d_k)`` (s). Each ``t_k`` is increasing and
subadditive, so T is a metric: a detour is never faster than the straight move.

The program starts and ends at home (node 0) and measures every experiment once; its time is
the sum of its moves' times plus a fixed measuring time per experiment. Changing the
calibration load (hanging another weight) is a manual step: the order minimises the number
of load changes first (home carries no load), then the time, with the edge cost
``C_ij = W [F_i != F_j] + T_ij`` where ``W`` exceeds the time of any tour. The order is exact
(Held-Karp dynamic programming) up to ``EXACT_UP_TO`` experiments, and found by a local search
(2-opt and or-opt moves from the file order and the nearest-neighbour tour) beyond.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..errors import ProblemError
from ..problem.build import Problem
from ..problem_file.robot import ControllerSpec
from ..records.export import joint_scales

#: Speed (rad/s, m/s) of a joint without a velocity limit in its model or problem file.
DEFAULT_SPEED = 1.0
#: Most experiments ordered exactly (Held-Karp: 2^N N^2 operations, 0.1 s at N = 13).
EXACT_UP_TO = 13
#: Improvements of a tour's cost below this (s) end the local search.
IMPROVEMENT_TOL = 1e-9


@dataclass(frozen=True, eq=False)
class TimeModel:
    """Synchronous joint-space moves (module docstring).

    Attributes
    ----------
    speed : ndarray, shape (n,), rad/s (m/s for prismatic joints)
    acceleration : ndarray, shape (n,), rad/s^2 (m/s^2)
    source : str
        Where the speeds come from, for people.
    """

    speed: np.ndarray
    acceleration: np.ndarray
    source: str

    def joint_times(self, dq: np.ndarray) -> np.ndarray:
        """``t_k(|dq_k|)`` (s) of joint displacements ``dq`` (..., n), rad (m)."""
        d = np.abs(np.asarray(dq, dtype=float))
        v, a = self.speed, self.acceleration
        return np.where(d < v**2 / a, 2 * np.sqrt(d / a), d / v + v / a)

    def move_time(self, qa: np.ndarray, qb: np.ndarray) -> float:
        """``T(q_a, q_b) = max_k t_k`` (s)."""
        return float(np.max(self.joint_times(np.asarray(qb, float) - np.asarray(qa, float))))

    def lead_joint(self, qa: np.ndarray, qb: np.ndarray) -> int:
        """The joint that sets the time of the move (the first of equals)."""
        return int(np.argmax(self.joint_times(np.asarray(qb, float) - np.asarray(qa, float))))

    def time_matrix(self, Q: np.ndarray) -> np.ndarray:
        """``T(Q_i, Q_j)`` (s) of every pair of configurations ``Q`` (N, n)."""
        Q = np.asarray(Q, dtype=float)
        return np.max(self.joint_times(Q[:, None, :] - Q[None, :, :]), axis=2)


def time_model(problem: Problem) -> TimeModel:
    """The moves of ``problem``'s robot: speeds from ``[robot].joint_speeds_deg_s``, else the
    URDF's velocity limits, else ``DEFAULT_SPEED``; accelerations from the acceleration time
    of ``[robot.controller]``."""
    robot, spec = problem.robot, problem.spec.robot
    n = robot.n
    controller = spec.controller or ControllerSpec()
    if spec.joint_speeds_deg_s is not None:
        given = np.array(spec.joint_speeds_deg_s)
        if given.size != n:
            raise ProblemError(f"{problem.path}: [robot].joint_speeds_deg_s: has {given.size} values, the "
                               f"chain has {n} joints ({', '.join(robot.joints)}); give one speed per joint in deg/s")
        speed = given * joint_scales(problem)
        source = "[robot].joint_speeds_deg_s"
    else:
        limit = np.array([robot.model.velocityLimit[robot.model.joints[j].idx_v] for j in robot.joint_ids])
        known = (limit > 0) & (limit < 1e10)
        speed = np.where(known, limit, DEFAULT_SPEED)
        source = ("the URDF's velocity limits" if known.all() else
                  f"{DEFAULT_SPEED:g} rad/s per joint (no speeds in the model; give [robot].joint_speeds_deg_s)"
                  if not known.any() else f"the URDF's velocity limits, {DEFAULT_SPEED:g} rad/s where it has none")
    return TimeModel(speed, speed / controller.acceleration_time_s, source)


def load_changes(F: np.ndarray, tol_N: float) -> np.ndarray:
    """Whether the load changes between nodes i and j (home, then the experiments): ``|F_i -
    F_j| > tol_N``, home carrying none. ``F`` (m, nF), N; returns (m + 1, m + 1) bool."""
    F = np.asarray(F, dtype=float)
    L = np.vstack([np.zeros((1, F.shape[1])), F])
    return np.linalg.norm(L[:, None, :] - L[None, :, :], axis=2) > tol_N


def order_cost(T: np.ndarray, changes: np.ndarray) -> np.ndarray:
    """``C = W changes + T`` with ``W`` above the time of any tour (module docstring)."""
    W = 1.0 + len(T) * float(np.max(T, initial=0.0))
    return W * changes + T


def tour_cost(C: np.ndarray, order: tuple[int, ...] | list[int]) -> float:
    """Cost of home -> order[0] -> ... -> order[-1] -> home (nodes 1..N are experiments)."""
    nodes = [0, *order, 0]
    return float(sum(C[i, j] for i, j in itertools.pairwise(nodes)))


def held_karp(C: np.ndarray) -> tuple[int, ...]:
    """The tour of least cost from home (node 0) through nodes 1..N and back, exactly.

    ``D[S, j]``: least cost from home through the set S of experiments ending at j in S;
    ``D[S, j] = min_{i in S - j} D[S - j, i] + C[i, j]``, the tour ``min_j D[all, j] + C[j, 0]``.
    """
    N = len(C) - 1
    if N == 0:
        return ()
    inner, bit = C[1:, 1:], 1 << np.arange(N)
    D = np.full((1 << N, N), np.inf)
    parent = np.full((1 << N, N), -1, dtype=int)
    D[bit, np.arange(N)] = C[0, 1:]
    for S in range(1, 1 << N):
        js = np.flatnonzero(S & bit)
        if js.size < 2:
            continue
        prev = D[S ^ bit[js]] + inner[:, js].T  # (k, N): come from i into j
        parent[S, js] = np.argmin(prev, axis=1)
        D[S, js] = prev[np.arange(js.size), parent[S, js]]
    S, j = (1 << N) - 1, int(np.argmin(D[-1] + C[1:, 0]))
    order = []
    while j >= 0:
        order.append(j + 1)
        S, j = S ^ (1 << j), int(parent[S, j])
    return tuple(reversed(order))


def local_search(C: np.ndarray, order: tuple[int, ...]) -> tuple[int, ...]:
    """``order`` improved by 2-opt (reverse a stretch) and or-opt (move a stretch of 1 to 3
    experiments elsewhere, either way round) until no move lowers the cost (symmetric C)."""
    tour = [0, *order, 0]
    best = tour_cost(C, order)
    improved = True
    while improved:
        improved = False
        candidates = [tour[:i] + tour[i:j + 1][::-1] + tour[j + 1:]
                      for i in range(1, len(tour) - 2) for j in range(i + 1, len(tour) - 1)]
        for k in (1, 2, 3):
            for i in range(1, len(tour) - k):
                piece, rest = tour[i:i + k], tour[:i] + tour[i + k:]
                candidates += [rest[:p] + s + rest[p:] for p in range(1, len(rest)) if p != i
                               for s in (piece, piece[::-1])]
        for t in candidates:
            cost = tour_cost(C, t[1:-1])
            if cost < best - IMPROVEMENT_TOL:
                tour, best, improved = t, cost, True
                break
    return tuple(tour[1:-1])


def nearest_neighbour(C: np.ndarray) -> tuple[int, ...]:
    """From home, always to the cheapest experiment not yet visited."""
    left, at, order = set(range(1, len(C))), 0, []
    while left:
        at = min(left, key=lambda j: (C[at, j], j))
        order.append(at)
        left.remove(at)
    return tuple(order)


def best_order(C: np.ndarray) -> tuple[int, ...]:
    """The least-cost tour: :func:`held_karp` up to ``EXACT_UP_TO`` experiments, else the
    better of :func:`local_search` from the file order and from :func:`nearest_neighbour`."""
    N = len(C) - 1
    if N <= EXACT_UP_TO:
        return held_karp(C)
    tours = [local_search(C, start) for start in (tuple(range(1, N + 1)), nearest_neighbour(C))]
    return min(tours, key=lambda t: tour_cost(C, t))
