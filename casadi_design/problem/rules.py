"""The rules of one experiment of a plan, built with the problem: its joint limits, the
workspace and cell rows of a configuration, and the calibration loads as NLP variables.

:class:`PlanRules` is a built problem's ``rules``
(:attr:`casadi_design.problem.build.Problem.rules`), each part made on first use and shared by
the copies of the problem that differ only in solver settings or held information:

* ``limits`` (:class:`JointLimits`): ``q_min + margin <= q_i <= q_max - margin`` (rad, m); a
  revolute joint whose range spans a full turn is periodic instead: free in the NLP and wrapped
  into its range afterwards;
* ``pose`` (:class:`PoseConstraints`): every measured point in the box, the half-spaces and
  the tracker's sphere; every moving frame origin (joints, links, flange, tool) and measured
  point above the floor; with a ``[cell]``, the rows of :func:`casadi_design.cell.cell.cell_rows`
  (self-collision, obstacles, lines of sight, reflector incidence), as one CasADi function of a
  configuration;
* ``loads`` (:class:`LoadVariables`): the calibration load (:class:`casadi_design.problem_file.experiments.ForceSpec`)
  as NLP variables: ``|F_i| = F_max`` ("equal"), ``|F_i| <= F_max`` ("bound"), ``F_i = F_fixed``
  ("fixed"), ``F_i = a F_max u`` with ``0 <= a <= 1`` ("direction").

The checks of a whole plan (distinct experiments, the real geometry, every rule at once) are
:mod:`casadi_design.plan.rules`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ..calibration.models import CalibrationModel
from ..cell.cell import Cell, cell_rows
from ..cell.collision import PointRows
from ..cell.spec import Workspace
from ..problem_file.experiments import ForceSpec
from ..robot.compiled import MAPPED_MIN_INSTRUCTIONS, compiled_group, compiled_switch
from ..robot.mapped import evaluate
from ..robot.robots import Robot
from ..robot.symbolic import joint_axis


@dataclass(frozen=True, eq=False)
class JointLimits:
    """The joint limits of a plan (rad, m for prismatic joints).

    ``lower``/``upper``: the robot's limits moved inward by ``joint_limit_margin_rad``.
    ``periodic``: revolute joints whose range is more than a full turn. Their angle is free in
    the NLP (a bound there would stop the local search at an angle equivalent to one inside),
    every angle has an equivalent in the range, and :meth:`wrap` maps it to the one within pi
    of the range's middle.
    """

    lower: np.ndarray
    upper: np.ndarray
    periodic: np.ndarray

    @property
    def middle(self) -> np.ndarray:
        return (self.lower + self.upper) / 2

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of q in the NLP: the limits, -inf / inf for periodic joints."""
        return (np.where(self.periodic, -np.inf, self.lower), np.where(self.periodic, np.inf, self.upper))

    def wrap(self, Q: np.ndarray) -> np.ndarray:
        """``Q`` (m, n) with each periodic angle moved by whole turns to
        ``[middle - pi, middle + pi)``, the others clipped to the limits."""
        Q = np.asarray(Q, dtype=float)
        c = self.middle
        wrapped = c + np.mod(Q - c + np.pi, 2 * np.pi) - np.pi
        return np.where(self.periodic, wrapped, np.clip(Q, self.lower, self.upper))

    def sample(self, rng: np.random.Generator, size: int | None = None) -> np.ndarray:
        """A configuration (n), or ``size`` of them (size x n), drawn uniformly within the
        limits (within one turn for periodic joints)."""
        lo = np.where(self.periodic, self.middle - np.pi, self.lower)
        hi = np.where(self.periodic, self.middle + np.pi, self.upper)
        return rng.uniform(lo, hi, size=None if size is None else (size, lo.size))


@dataclass(frozen=True, eq=False)
class PoseConstraints:
    """Workspace rows of one configuration: ``lb <= g(q) <= ub``, one label and unit per row
    ("m", or "cos" for the cosine of an angle); ``screen`` gives the first rows alone (all but
    the cell's capsule rows, which cost most); ``collision``: those capsule rows, the last
    ones, in the form that evaluates them one by one (None without a ``[cell]``)."""

    g: ca.Function
    lb: np.ndarray
    ub: np.ndarray
    labels: tuple[str, ...]
    units: tuple[str, ...]
    screen: ca.Function
    collision: CollisionRows | None = None

    def feasible(self, Q: np.ndarray) -> np.ndarray:
        """Whether each configuration (row of ``Q``, k x n) satisfies every row: the first
        rows (``screen``: all but the costly capsule rows) on all of them, every row on those
        that pass."""
        Q = np.asarray(Q, dtype=float)
        ok = np.ones(len(Q), dtype=bool)
        for f in (self.screen, self.g):
            rows = f.numel_out(0)
            if not rows or not ok.any():
                continue
            idx = np.flatnonzero(ok)
            G = _rows_at(f, Q[idx])
            ok[idx] = np.all((G >= self.lb[:rows]) & (G <= self.ub[:rows]), axis=1)
        return ok

    def capsule_slack(self, Q: np.ndarray) -> np.ndarray:
        """``g - lb`` (m) of every capsule row (of :class:`CollisionRows`) in each
        configuration of ``Q`` (k x n): shape (k, R), R = 0 without a cell."""
        Q = np.asarray(Q, dtype=float)
        if self.collision is None:
            return np.zeros((len(Q), 0))
        first = self.collision.first
        return _rows_at(self.g, Q)[:, first:] - self.lb[first:]

    def near(self, Q: np.ndarray, margin_m: float) -> np.ndarray:
        """The capsule rows closer than ``margin_m`` (m) to their bound ``g >= 0`` in the plan
        ``Q`` (m, n): (experiment, row of :class:`CollisionRows`) pairs (K x 2), in that order."""
        return np.argwhere(self.capsule_slack(Q) < margin_m)

    def violation(self, q: np.ndarray) -> np.ndarray:
        """Violation (in the row's unit, >= 0) of each row at configuration ``q``."""
        if not self.lb.size:
            return np.zeros(0)
        g = np.asarray(self.g(np.asarray(q, dtype=float))).ravel()
        return np.maximum(np.maximum(self.lb - g, g - self.ub), 0.0)


@dataclass(frozen=True, eq=False)
class CollisionRows:
    """The capsule rows of one configuration, row by row: the NLP evaluates only the rows it
    holds (those that can bind; :mod:`casadi_design.optimisation.reduced`).

    Row r is row ``first + r`` of :class:`PoseConstraints` (``g >= 0``, m). It depends on the
    world points ``w = points(q)`` (3K, m; :class:`casadi_design.cell.collision.PointRows`) through
    ``w_r = w[inputs[r]]`` (the same number of coordinates for every row, ``width =
    inputs.shape[1]``: those of the few points it uses, then the index 3K, a zero, to fill):
    ``g_r = G_r(w_r)``. ``cases[r]`` are row r's functions ``w_r -> g_r``, ``dg_r/dw_r (1 x
    width)`` and ``d2g_r/dw_r2 (width x width)``; ``value``, ``slope`` and ``curvature`` are
    CasADi switches ``(r, w_r) ->`` those, over their compiled code
    (:mod:`casadi_design.robot.compiled`, built when first asked for): they evaluate row r alone, so
    a switch mapped over k rows costs those k rows. ``curved`` (bool, one per row): whether
    ``d2g_r/dw_r2`` has a structural nonzero (a plane's rows and a box's, piecewise linear in
    the points, have none).
    """

    first: int
    points: ca.Function
    inputs: np.ndarray
    cases: tuple[tuple[ca.Function, ca.Function, ca.Function], ...]
    curved: np.ndarray

    @cached_property
    def value(self) -> ca.Function:
        return compiled_switch("row", [c[0] for c in self.cases])

    @cached_property
    def slope(self) -> ca.Function:
        return compiled_switch("drow", [c[1] for c in self.cases])

    @cached_property
    def curvature(self) -> ca.Function:
        return compiled_switch("d2row", [c[2] for c in self.cases])


def collision_rows(rows: PointRows, q: ca.SX, first: int) -> CollisionRows:
    """:class:`CollisionRows` of the capsule rows ``rows`` (rows ``first...`` of the pose)."""
    K3 = rows.W.numel()
    G = ca.vertcat(*rows.G)
    uses = ca.jacobian(G, rows.W).sparsity()
    dependence = np.array(ca.DM(uses, 1.0), dtype=bool).reshape(len(rows.G), K3 // 3, 3).any(axis=2)
    width = 3 * max(1, int(dependence.sum(axis=1).max()))
    w = ca.SX.sym("w", width)
    inputs, cases = [], []
    for r, g in enumerate(rows.G):
        idx = [3 * k + a for k in np.flatnonzero(dependence[r]) for a in range(3)]
        if idx:
            g = ca.substitute(g, rows.W[idx], w[: len(idx)])
        inputs.append(idx + [K3] * (width - len(idx)))
        cases.append((ca.Function("row", [w], [g]), ca.Function("drow", [w], [ca.jacobian(g, w)]),
                      ca.Function("d2row", [w], [ca.hessian(g, w)[0]])))
    return CollisionRows(first, ca.Function("points", [q], [rows.points], ["q"], ["w"]),
                         np.array(inputs, dtype=int).reshape(len(rows.G), width), tuple(cases),
                         np.array([d2.nnz_out(0) > 0 for _, _, d2 in cases], dtype=bool))


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

    def load(self, v):
        """The load ``F`` (nF, N) of one experiment's variables ``v`` (nv; numpy or CasADi)."""
        if isinstance(v, np.ndarray):
            return self.magnitude_N * (self.U @ v) + self.fixed_N
        return self.magnitude_N * (ca.DM(self.U) @ v) + ca.DM(self.fixed_N)

    def loads(self, V: np.ndarray) -> np.ndarray:
        """``F`` (m, nF), N, of the variables ``V`` (m, nv)."""
        return self.magnitude_N * (np.asarray(V, dtype=float) @ self.U.T) + self.fixed_N

    def variables(self, F: np.ndarray) -> np.ndarray:
        """``V`` (m, nv) of loads ``F`` (m, nF), N, that satisfy the rule."""
        F = np.asarray(F, dtype=float)
        return F.reshape(F.shape[0], self.U.shape[0]) @ self.U / self.magnitude_N


def _rows_at(f: ca.Function, Q: np.ndarray) -> np.ndarray:
    """The rows of ``f`` (a function of one configuration) at each configuration of ``Q``
    (k x n): shape (k, rows); one mapped call per chunk, in this thread (a worker's starts
    and approximate designs run one per core), compiled from
    :data:`~casadi_design.robot.compiled.MAPPED_MIN_INSTRUCTIONS` on (the screen rows too)."""
    fn = compiled_group([f], MAPPED_MIN_INSTRUCTIONS)[0]
    return evaluate(fn, np.asarray(Q, dtype=float), threads=1)[0].reshape(len(Q), f.numel_out(0))


@dataclass(frozen=True, eq=False)
class PlanRules:
    """The rules of one experiment of a problem (module docstring), each built on first use.

    ``markers_m``: the measured points on the tool (None: the tool point alone), for the
    reflector's incidence rows of a cell."""

    robot: Robot
    model: CalibrationModel
    workspace: Workspace
    force: ForceSpec | None
    cell: Cell | None
    markers_m: tuple | None

    @cached_property
    def limits(self) -> JointLimits:
        """The plan's joint limits (:class:`JointLimits`)."""
        robot, margin = self.robot, self.workspace.joint_limit_margin_rad
        lower, upper = robot.q_min + margin, robot.q_max - margin  # lower <= upper: checked when built
        revolute = np.array([joint_axis(robot.model.joints[j])[1] == "R" for j in robot.joint_ids])
        return JointLimits(lower, upper, revolute & (upper - lower > 2 * np.pi + 1e-9))

    @cached_property
    def pose(self) -> PoseConstraints:
        """The workspace and cell rows of one configuration (module docstring)."""
        ws, model, robot = self.workspace, self.model, self.robot
        q = ca.SX.sym("q", robot.n)
        P = model.points(q)
        rows: list[tuple[ca.SX, float, float, str, str]] = []
        for j in range(P.shape[1]):
            p, name = P[:, j], f"measured point {j + 1}" if P.shape[1] > 1 else "measured point"
            if ws.box_min_m is not None:
                rows += [(p[a], ws.box_min_m[a], ws.box_max_m[a], f"{name}: {'xyz'[a]} outside the box", "m")
                         for a in range(3)]
            for k, hs in enumerate(ws.half_spaces):  # unit normals (casadi_design.cell.obstacles.HalfSpace)
                rows.append((ca.dot(ca.DM(hs.normal), p), hs.offset_m, np.inf, f"{name}: outside half-space {k + 1}",
                             "m"))
            if ws.sphere_center_m is not None:
                rows.append((ca.sqrt(ca.sumsqr(p - ca.DM(ws.sphere_center_m)) + 1e-12), -np.inf, ws.sphere_radius_m,
                             f"{name}: out of the tracker's range", "m"))
        if ws.floor_z_m is not None:
            # frames fixed to the base (not moving with q) are where the robot stands: not constrained
            frames, names = model.kinematics.frame_origins(q), model.kinematics.frame_names
            named = ([(frames[:, k], f"frame '{names[k]}'") for k in range(frames.shape[1] - 1)]
                     + [(frames[:, -1], f"measured frame '{robot.frame}'")]
                     + [(P[:, j], f"measured point {j + 1}") for j in range(P.shape[1])])
            rows += [(p[2], ws.floor_z_m, np.inf, f"{name}: below the floor", "m")
                     for p, name in named if ca.depends_on(p[2], q)]
        capsule = None
        if self.cell is not None:
            R = model.kinematics.placement(q, ca.DM.zeros(len(model.kinematics.parameter_names)))[0]
            capsule, incidence = cell_rows(self.cell, robot, q, R, P,
                                           np.zeros((1, 3)) if self.markers_m is None else np.array(self.markers_m))
            rows += incidence
        screen = len(rows)  # the rows before the capsule rows are cheap: they screen candidates
        if capsule is not None:
            rows += [(g, 0.0, np.inf, label, "m") for g, label in zip(capsule.of_q(), capsule.labels)]
        g = ca.vertcat(*[r[0] for r in rows]) if rows else ca.SX(0, 1)
        return PoseConstraints(ca.Function("workspace", [q], [g], ["q"], ["g"]),
                               np.array([r[1] for r in rows], dtype=float),
                               np.array([r[2] for r in rows], dtype=float), tuple(r[3] for r in rows),
                               tuple(r[4] for r in rows),
                               ca.Function("screen", [q], [g[:screen]], ["q"], ["g"]),
                               collision_rows(capsule, q, screen) if capsule is not None and capsule.G else None)

    @cached_property
    def loads(self) -> LoadVariables:
        """The load variables of the problem's calibration load (:class:`LoadVariables`)."""
        nF, force = self.model.nF, self.force
        if nF == 0 or force is None or force.mode == "fixed":
            fixed = np.array(force.vector_N if nF and force is not None else np.zeros(nF), dtype=float)
            return LoadVariables(np.zeros((nF, 0)), 1.0, fixed, -1.0, None)
        if force.mode == "direction":
            return LoadVariables(np.array(force.direction, dtype=float)[:, None], force.magnitude_N,
                                 np.zeros(nF), 0.0, None)
        return LoadVariables(np.eye(nF), force.magnitude_N, np.zeros(nF), -1.0,
                             1.0 if force.mode == "equal" else 0.0)
