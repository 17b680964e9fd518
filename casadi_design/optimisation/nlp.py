"""The design NLP: choose the plan ``{(q_i, F_i)}, i = 1..m`` that optimises a criterion.

Decision variables: ``Q`` (m, n), rad, the load variables ``V`` (m, nv; see
:class:`~casadi_design.problem.rules.LoadVariables`: ``Fbar = F / |F|_max``, a magnitude ``a`` for a
load of fixed direction, none for fixed loads and geometric cases), and the criterion's own
bound ``t`` of the test-pose criterion: ``x = (Q, V, t)`` row by row, so that the variables of
one experiment are contiguous. The test-pose criterion is the min-max of
the paper (eq. 15) in epigraph form:

    minimise t  subject to  trace(B0_j M^-1 B0_j^T) <= t,  j = 1..s

(``rho_j = sigma^2`` times the left side, so sigma does not change the plan).

Constraint rows, in this order: the criterion's rows, the loads (``|Fbar_i|^2 = 1`` or
``<= 1``), the workspace rows of every experiment
(:attr:`~casadi_design.problem.rules.PlanRules.pose`) but a cell's capsule rows, the capsule rows
the NLP holds (``active``: all of them, or those that can bind at the plans of a start,
:mod:`casadi_design.optimisation.solve`), and the joint distance of every pair of experiments; joint limits
and load magnitudes are bounds of x.

The NLP is posed in the reduced space (:mod:`casadi_design.optimisation.reduced`): IPOPT's variables are x
only, values and exact derivatives come from numeric linear algebra; E and condition through
their smooth surrogates of power r. IPOPT sees the information matrix scaled to O(1) per
experiment, ``scale M``, and ``B0`` scaled by ``sqrt(scale)``: a constant factor leaves every
criterion's optimal plans and ``trace(B0 M^-1 B0^T)`` unchanged and keeps IPOPT's steps well
scaled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..measures.field import FIELD_CRITERIA
from ..problem.build import Problem
from ..problem.rules import LoadVariables
from .field_nlp import FieldNLP, kriging_graph
from .reduced import all_rows, reduced_nlp


@dataclass(frozen=True, eq=False)
class DesignNLP:
    """The NLP of one (criterion, m), ready for IPOPT.

    Attributes
    ----------
    scale : the constant factor of M inside the NLP (``information(x)`` returns ``scale M``).
    oracle : ``(x, p) -> (f, g)`` with ``p`` empty, the NLP as ``casadi.nlpsol`` takes it.
    plan : ``x -> (Q, F)``, joint values (m, n), rad, and loads (m, nF), N.
    information : ``x -> scale M`` (L x L).
    start : ``(Q, F) -> x0``, a plan completed with the auxiliary variables.
    active : the capsule rows held, (experiment, row) pairs (K x 2); ``active_rows``: their
        index in g.
    options : ``nlpsol`` options of the formulation: its own derivative functions.
    """

    criterion: str
    m: int
    scale: float
    oracle: ca.Function
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    plan: Callable
    information: Callable
    start: Callable[[np.ndarray, np.ndarray], np.ndarray]
    active: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=int))
    active_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    options: dict = field(default_factory=dict)

    def solver(self, name: str, opts: dict) -> ca.Function:
        """IPOPT on this NLP with the options ``opts``."""
        solver = ca.nlpsol(name, "ipopt", self.oracle, {**opts, **self.options})
        solver.design_nlp = self  # keeps the Python callbacks alive as long as the solver
        return solver


def information_scale(L: int, B0: np.ndarray) -> float:
    """The factor of M (and of ``B0^T B0``) inside the NLP: ``L / mean_j |B0_j|_F^2``."""
    return L / max(np.einsum("sij,sij->", B0, B0) / B0.shape[0], np.finfo(float).tiny)


#: Bound of each load variable where the rows ``|v_i|^2 <= 1`` hold them (:func:`plan_bounds`
#: with ``box=False``): twice the sphere's radius, out of reach of a feasible point; a finite
#: bound keeps the iterates near the sphere (none: the searches' steps leave it by a factor 10
#: and take longer to come back).
LOAD_BOX = 2.0


def build_nlp(problem: Problem, criterion: str, m: int, power: float = 0.0, active: np.ndarray | None = None,
              weights: np.ndarray | None = None, fixed: np.ndarray | None = None, field: bool = False) -> DesignNLP:
    """Build the NLP of ``criterion`` for ``m`` experiments (a pure function of the problem);
    ``power``: r of the surrogate of E and condition (one of ``Criterion.powers``);
    ``active``: the capsule rows it holds, (experiment, row) pairs (K x 2; None: all);
    ``weights`` (m,): ``M = sum_i w_i B_i^T B_i + fixed``, the support of an approximate design
    (:func:`casadi_design.optimisation.reduced.reduced_nlp`; no joint-distance rows);
    ``fixed`` (L x L, unscaled): information held before the plan (``problem.M_held`` for a
    design, the light support points' for a move of the approximate design); ``field``: the
    criterion (test-pose or I) weighs the problem's field, its part the kriging variance
    (:class:`~casadi_design.optimisation.field_nlp.FieldNLP`)."""
    n, loads = problem.robot.n, problem.rules.loads
    scale = information_scale(problem.model.L, problem.B0)
    nlp = reduced_nlp(problem, criterion, m, scale, power, active, weights, fixed)
    if field:
        if criterion not in FIELD_CRITERIA or problem.field is None:
            raise ValueError(f"build_nlp: the NLP with the field is one of {', '.join(FIELD_CRITERIA)} for a problem "
                             f"with a field, not {criterion}{'' if problem.field is not None else ' without one'}")
        nlp = FieldNLP(nlp, kriging_graph(problem, m))
    oracle, options = nlp.functions()
    lbx, ubx = plan_bounds(problem, m, loads)
    lbg, ubg = rule_bounds(problem, m, loads, nlp.active, pairs=len(nlp.pairs) > 0)
    if nlp.n_rows:  # the epigraph: t >= 0; rho_j - t <= 0
        lbx, ubx = np.append(lbx, 0.0), np.append(ubx, np.inf)
        s = nlp.n_rows
        lbg, ubg = np.concatenate([np.full(s, -np.inf), lbg]), np.concatenate([np.zeros(s), ubg])
    n_plan = (n + loads.nv) * m

    def plan(x) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=float).ravel()
        return x[: n * m].reshape(m, n), loads.loads(x[n * m: n_plan].reshape(m, loads.nv))

    def information(x) -> np.ndarray:
        return nlp.at(np.asarray(x, dtype=float).ravel()).M

    def start(Q0: np.ndarray, F0: np.ndarray) -> np.ndarray:
        x0 = np.concatenate([np.asarray(Q0).ravel(), loads.variables(F0).ravel(),
                             np.zeros(nlp.nx - n_plan)])
        if nlp.n_rows:  # t0 = 1.01 max_j rho_j, strictly feasible
            x0[-1] = 1.01 * np.max(nlp.at(x0).g[: nlp.n_rows])
        return x0

    return DesignNLP(criterion, m, scale, oracle, lbx, ubx, lbg, ubg, plan, information, start,
                     nlp.active, nlp.active_rows, options)


def plan_bounds(problem: Problem, m: int, loads: LoadVariables,
                box: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of ``(Q, V)``: joint limits (rad, m; :meth:`JointLimits.bounds`) and the
    load variables, ``lower <= v <= 1``.

    Not ``box``: where the rows ``|v_i|^2 <= 1`` hold the load variables
    (:class:`~casadi_design.problem.rules.LoadVariables`), ``|v_k| <= LOAD_BOX`` instead, which
    no feasible point reaches. The box at 1 adds nothing there but bounds tangent to that
    sphere at its poles (a load along an axis), where IPOPT cannot tell the bound's multiplier
    from the row's and cycles through restorations: the bound's searches, whose maxima lie
    there on the paper's example, take 117 iterations instead of 44. The design NLPs keep
    the box: started at an optimal plan whose loads lie at the poles, IPOPT without it can
    leave that optimum for a worse one."""
    lower, upper = problem.rules.limits.bounds()
    wide = not box and loads.norm_lb is not None
    return (np.concatenate([np.tile(lower, m), np.full(loads.nv * m, -LOAD_BOX if wide else loads.lower)]),
            np.concatenate([np.tile(upper, m), np.full(loads.nv * m, LOAD_BOX if wide else 1.0)]))


def rule_bounds(problem: Problem, m: int, loads: LoadVariables,
                active: np.ndarray | None = None, pairs: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the rule rows: loads ``|v_i|^2``, workspace of each experiment (its capsule
    rows apart), the capsule rows ``active`` ((experiment, row) pairs; None: all), joint
    distance of each pair ``i < j`` (squared, rad^2;
    :func:`~casadi_design.plan.rules.joint_distance_sq`; none when not ``pairs``)."""
    rules, dmin = problem.rules.pose, problem.workspace.min_joint_distance_rad
    held = rules.lb.size if rules.collision is None else rules.collision.first
    rows = held + (all_rows(problem, m) if active is None else active)[:, 1]
    n_norm = m if loads.norm_lb is not None else 0
    n_pairs = m * (m - 1) // 2 if dmin > 0 and pairs else 0
    lb = np.concatenate([np.full(n_norm, loads.norm_lb or 0.0), np.tile(rules.lb[:held], m),
                         rules.lb[rows], np.full(n_pairs, dmin**2)])
    ub = np.concatenate([np.ones(n_norm), np.tile(rules.ub[:held], m), rules.ub[rows],
                         np.full(n_pairs, np.inf)])
    return lb, ub
