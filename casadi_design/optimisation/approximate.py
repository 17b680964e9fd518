"""The continuous approximate design of a criterion: the exchange over a pool of candidate
experiments whose convex problem and certificate are :mod:`.bound`'s, with the searches for
``max_x d(x, W)`` over ONE experiment that certify it, and the plans rounded from it.

The maximum over x is a global search: a dense random sample of feasible experiments, then
IPOPT from the best of them and from the support points. The bound is certified only as well as
that maximum is found: a missed higher maximum of d makes the reported bound too optimistic by
the same ratio; a last search over a fresh sample checks the certificate that is reported.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import DesignError
from ..measures.criteria import BOUND_CRITERIA, CRITERIA
from ..plan.rules import ADD_MARGIN_M, START_MARGIN_M, mesh_contacts, plan_violations
from ..plan.sampling import random_plan
from ..problem.build import Problem, per_model
from ..problem.rules import CollisionRows
from ..robot.compiled import compiled_group
from .bound import (
    EXCHANGE_RTOL,
    WEIGHT_RTOL,
    ApproximateDesign,
    certificate,
    check_m,
    experiment_information,
    linearised,
    pool_optimum,
    scaled_pool,
    unscaled,
)
from .ipopt import QUIET, WARM_START, ipopt_call
from .nlp import build_nlp, plan_bounds, rule_bounds
from .reduced import experiment_functions

#: Candidate experiments of the first pool, and of the dense sample searched for max_x d.
POOL_SIZE = 300
SAMPLE_SIZE = 3000
#: IPOPT starts of the search for max_x d besides the support points: the best candidates.
#: With 8, an independent search of 64 starts from another sample finds maxima of d up to
#: 2.5 % (UR10 test-pose), 4 % (ABB test-pose) higher than the exchange's, so its certificates
#: are optimistic; with 16 the exchange finds those maxima itself.
POLISH_STARTS = 16
#: Support points polished per step, the heaviest first.
POLISH_SUPPORT = 24
#: Candidates (d > phi) added to the pool per exchange step, and their first weight (times the
#: support's mean weight).
ADDED_CANDIDATES = 40
NEW_WEIGHT = 0.1
#: Maxima closer than this (relative, in their information matrices) are one candidate.
DISTINCT_RTOL = 1e-6
#: IPOPT starts of the final, independent search for max_x d from a sample of SAMPLE_SIZE (16
#: find too few maxima, above); a smaller sample (``--bound-pool``) polishes as large a part of
#: it, POLISH_STARTS at least (:func:`verify_starts`).
VERIFY_STARTS = 64
#: Smallest eigenvalue of the first pool's mean information, relative to the largest.
POOL_RCOND = 1e-12
EXCHANGE_ITERATIONS = 40
#: The step of the jittered plans of :func:`rounded_plans` (fraction of the joint range); how
#: many plans: the design criterion's :attr:`~casadi_design.measures.criteria.Criterion.rounded`.
ROUNDING_JITTER = 0.02
#: Seed id of the bound's random numbers (beside the criteria's ids 0..6).
SEED_ID = 100
#: Exchange steps of the commands (``--bound-steps``; 0: no bound, no rounded starts).
BOUND_STEPS = 40
#: ``StartRecord.origin`` of the starts rounded from the approximate design.
ROUNDED = "rounded approximate design"


def _sample(problem: Problem, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``size`` random feasible single experiments: Q (size, n), F (size, nF)."""
    return random_plan(problem, size, rng)


#: IPOPT on the search for max_x d from a maximum of an earlier exchange step, with its
#: multipliers: the barrier parameter and bound pushes of a continuation, so the search
#: follows the maximum as W moves (about 6 iterations instead of a cold start's 30).
WARM_SEARCH = {**WARM_START, "ipopt.warm_start_bound_push": 1e-9, "ipopt.warm_start_mult_bound_push": 1e-9,
               "ipopt.warm_start_slack_bound_push": 1e-9}
#: Runs of a search at most (see :class:`Search`; the rows it holds: those within
#: :data:`~casadi_design.plan.rules.START_MARGIN_M` of their bound at its start, then those within
#: :data:`~casadi_design.plan.rules.ADD_MARGIN_M` at each run's maximum); the last holds every row.
SEARCH_RUNS = 6
#: The numbers of capsule rows a search NLP has room for (the rows it holds are parameters,
#: the places left over hold a row without bounds); the last one: every row.
SEARCH_SIZES = (8, 16, 32, 64)


@dataclass(frozen=True, eq=False)
class Search:
    """IPOPT on one experiment ``z = (q, v)``: ``max tr(G B(z)^T B(z))`` within its rules,
    with parameter ``vec G`` (L x L), started cold or from a point and its multipliers (warm,
    :data:`WARM_SEARCH`); the bounds of z and of every rule row (``lbg``, ``ubg``; the capsule
    rows are rows ``capsules`` of them, in the order of
    :class:`~casadi_design.problem.rules.CollisionRows`).

    A search holds the rule rows that are not capsule rows and only the capsule rows that can
    bind: the NLP of :meth:`solvers` has room for K capsule rows, and which rows is a parameter
    (a place left over takes index R: a row 0 without bounds), so one NLP per size serves every
    set of rows. ``fixed`` are the functions of z (and G) of the objective and the other rows:
    values, first and second derivatives, compiled (:mod:`casadi_design.robot.compiled`). The
    capsule rows go through the world points of the capsules' ends, as in the design NLP
    (:class:`~casadi_design.problem.rules.CollisionRows`): ``row["points"]`` gives ``w(q)`` (3K) and
    ``dw/dq`` once per evaluation, ``row["value"]``, ``row["slope"]`` and ``row["curvature"]``
    the held rows place by place through the rows' compiled switches of ``w_r`` (mapped over
    the K places), by the chain rule

        dg_r/dz = dg_r/dw_r dw_r/dz,
        lam_r d2g_r/dz2 = lam_r (dw_r/dz)^T d2g_r/dw_r2 (dw_r/dz) + d2(c^T w)/dz2,

    with ``c = sum_r lam_r dg_r/dw`` summed over the places first, so the kinematics' second
    derivatives (``row["points_curvature"]``) are evaluated once, not once per row. Of 100 UR10
    capsule rows a search holds about ten; a held row costs about 5 us an evaluation of the
    Hessian of the Lagrangian instead of 35 us for its own Hessian in z in the virtual
    machine."""

    fixed: dict
    row: dict
    capsules: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    kept: dict = field(default_factory=dict)

    def size(self, held: int) -> int:
        """The room of the NLP that holds ``held`` capsule rows: a size of :data:`SEARCH_SIZES`
        or every row."""
        return next((k for k in SEARCH_SIZES if held <= k < self.capsules.size), self.capsules.size)

    def solvers(self, K: int) -> tuple[ca.Function, ca.Function]:
        """The cold and warm IPOPT of the search with room for ``K`` capsule rows: parameters
        ``(vec G, rows)``, rule rows the others, then the K places."""
        if K not in self.kept:
            fx, row = self.fixed, self.row
            z, G = ca.MX.sym("z", self.lbx.size), ca.MX.sym("G", *fx["f"].size_in(1))
            rows = ca.MX.sym("rows", 1, K)
            p, lam_f = ca.vertcat(ca.vec(G), rows.T), ca.MX.sym("lam_f")
            c0, n0 = fx["c"](z), fx["c"].numel_out(0)
            lam_g = ca.MX.sym("lam_g", n0 + K)
            g, J = c0, fx["dc"](z)
            H = lam_f * fx["d2f"](z, G) + fx["d2c"](z, lam_g[:n0])
            if K:
                n, p_z = row["points"].size1_in(0), z.numel()
                w, dw = row["points"](z[:n])
                w = ca.vertcat(w, 0.0)  # the filler coordinate of CollisionRows.inputs
                dw = ca.vertcat(ca.horzcat(dw, ca.MX(dw.size1(), p_z - n)), ca.MX(1, p_z))
                g = ca.vertcat(g, row["value"].map(K, [False, True], [False])(rows, w).T)
                J = ca.vertcat(J, ca.reshape(row["slope"].map(K, [False, True, True], [False])(rows, w, dw),
                                             p_z, K).T)
                Hr, c = row["curvature"].map(K, [False, True, True, False], [True, True])(rows, w, dw,
                                                                                        lam_g[n0:].T)
                Hw = row["points_curvature"](z[:n], c[:-1])
                H += Hr + (Hw if p_z == n else ca.diagcat(Hw, ca.MX(p_z - n, p_z - n)))
            f = fx["f"](z, G)
            opts = {**QUIET, "ipopt.tol": 1e-10, "ipopt.max_iter": 200, "no_nlp_grad": True, "calc_lam_p": False,
                    "grad_f": ca.Function("grad_f", [z, p], [f, fx["df"](z, G)], ["x", "p"], ["f", "grad_f_x"]),
                    "jac_g": ca.Function("jac_g", [z, p], [g, J], ["x", "p"], ["g", "jac_g_x"]),
                    "hess_lag": ca.Function("hess_lag", [z, p, lam_f, lam_g], [ca.triu(H)],
                                            ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])}
            nlp = {"x": z, "p": p, "f": f, "g": g}
            self.kept[K] = (ca.nlpsol("max_d", "ipopt", nlp, opts),
                            ca.nlpsol("max_d_warm", "ipopt", nlp, {**opts, **WARM_SEARCH}))
        return self.kept[K]

    def rows(self, held: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For the NLP of size ``K`` holding the capsule rows ``held``: its row parameter (K,),
        the rows of ``lbg`` at its places (-1 where a place is left over) and its lbg, ubg."""
        R, first = self.capsules.size, self.lbg.size - self.capsules.size
        index = np.concatenate([held, np.full(K - held.size, R)]).astype(float)
        where = np.concatenate([np.arange(first), self.capsules[held], np.full(K - held.size, -1)])
        free = where < 0
        lbg, ubg = self.lbg[where], self.ubg[where]
        lbg[free], ubg[free] = -np.inf, np.inf
        return index, where, lbg, ubg


@per_model
def _search(problem: Problem) -> Search:
    """The :class:`Search` of the problem (built once per problem)."""
    fns, loads = experiment_functions(problem), problem.rules.loads
    L = problem.model.L
    z, G = ca.SX.sym("z", fns.p), ca.SX.sym("G", L, L)
    B, c, _ = fns.values(z)
    f, lam_c = -ca.dot(B @ G, B), ca.SX.sym("lam_c", c.numel())
    fixed = {"f": ca.Function("d", [z, G], [f]), "df": ca.Function("dd", [z, G], [ca.gradient(f, z)]),
             "d2f": ca.Function("d2d", [z, G], [ca.densify(ca.hessian(f, z)[0])]),
             "c": ca.Function("rules", [z], [c]),
             "dc": ca.Function("drules", [z], [ca.densify(ca.jacobian(c, z))]),
             "d2c": ca.Function("d2rules", [z, lam_c], [ca.densify(ca.hessian(ca.dot(lam_c, c), z)[0])])}
    fixed = dict(zip(fixed, compiled_group(list(fixed.values()))))
    rules = problem.rules.pose
    R = 0 if rules.collision is None else len(rules.collision.cases)
    row = {} if rules.collision is None else _search_rows(rules.collision, fns.n, fns.p)  # none without a cell
    lbx, ubx = plan_bounds(problem, 1, loads, box=False)
    lbg, ubg = rule_bounds(problem, 1, loads)
    return Search(fixed, row, np.arange(c.numel(), c.numel() + R), lbx, ubx, lbg, ubg)


def _search_rows(rows: CollisionRows, n: int, p: int) -> dict:
    """The capsule rows of :class:`Search` through the world points ``w(q)`` (3K) of
    ``rows``: ``points`` ``q -> (w, dw/dq)`` and ``points_curvature`` ``(q, c) -> d2(c^T
    w)/dq2`` (n x n), compiled; and per place, with ``r`` the row (R: a place left over, whose
    outputs are 0), ``wx = (w, 0)`` (3K + 1) and ``Jx`` its derivative in z (3K + 1, p):
    ``value`` ``(r, wx) -> g_r``, ``slope`` ``(r, wx, Jx) -> dg_r/dz`` (1 x p) and
    ``curvature`` ``(r, wx, Jx, lam) -> (lam Jx_r^T d2g_r/dw_r2 Jx_r, lam dg_r/dwx)`` (p x p,
    3K + 1). The rows' own functions are the compiled switches of ``rows``; choosing row r's
    coordinates ``w_r = wx[inputs[r]]`` (and putting its slope back in place) are switches of
    copies."""
    K3, R = rows.points.numel_out(0), len(rows.cases)
    q, c = ca.SX.sym("q", n), ca.SX.sym("c", K3)
    w = rows.points(q)
    points = compiled_group([ca.Function("search_points", [q], [w, ca.densify(ca.jacobian(w, q))]),
                             ca.Function("search_points_curvature", [q, c],
                                         [ca.densify(ca.hessian(ca.dot(c, w), q)[0])])])
    wx, Jx, v = ca.SX.sym("wx", K3 + 1), ca.SX.sym("Jx", K3 + 1, p), ca.SX.sym("v", rows.inputs.shape[1])
    take, take_J, put = [], [], []
    for r, idx in enumerate(rows.inputs):
        back = ca.SX.zeros(K3 + 1)
        for i, k in enumerate(idx):
            back[k] += v[i]
        take.append(ca.Function(f"take_{r}", [wx], [wx[idx]]))
        take_J.append(ca.Function(f"take_J_{r}", [Jx], [Jx[idx, :]]))
        put.append(ca.Function(f"put_{r}", [v], [back]))
    take, take_J, put = (ca.Function.conditional(name, f, f[0])
                         for name, f in (("take", take), ("take_J", take_J), ("put", put)))
    r, lam = ca.MX.sym("r"), ca.MX.sym("lam")
    wm, Jm = ca.MX.sym("wx", K3 + 1), ca.MX.sym("Jx", K3 + 1, p)
    wr, Jr = take(r, wm), take_J(r, Jm)
    held = r < R

    def only(e: ca.MX) -> ca.MX:
        return ca.if_else(held, e, ca.MX.zeros(e.sparsity()))

    slope_w = rows.slope(r, wr)
    return {"points": points[0], "points_curvature": points[1],
            "value": ca.Function("capsule_value", [r, wm], [only(rows.value(r, wr))]),
            "slope": ca.Function("capsule_slope", [r, wm, Jm], [only(slope_w @ Jr)]),
            "curvature": ca.Function("capsule_curvature", [r, wm, Jm, lam],
                                     [only(lam * (Jr.T @ rows.curvature(r, wr) @ Jr)),
                                      only(put(r, lam * slope_w.T))])}


#: The multipliers of a maximum of d (of z's bounds, of the rule rows) per unit of d: a warm
#: start's.
Duals = tuple[np.ndarray, np.ndarray]
#: What runs a batch of searches: :func:`maximise_d`'s signature.
Maximise = Callable[[Problem, float, np.ndarray, np.ndarray, np.ndarray, list], tuple]


def _held(problem: Problem, q: np.ndarray, margin_m: float, held: np.ndarray | None = None) -> np.ndarray:
    """The capsule rows within ``margin_m`` (m) of their bound at ``q`` (n,), rad, joined to
    ``held`` (sorted row numbers of :class:`~casadi_design.problem.rules.CollisionRows`)."""
    near = problem.rules.pose.near(q[None], margin_m)[:, 1]
    return near if held is None else np.union1d(held, near)


def _search_one(problem: Problem, search: Search, G: np.ndarray, z0: np.ndarray,
                start: Duals | None, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One search from ``z0`` (cold, or warm from the multipliers ``start``, per unit of d)
    with IPOPT's objective ``scale d``: runs holding the capsule rows that can bind
    (:class:`Search`), each from the last one's primal and dual point, until every row left
    out is farther than :data:`~casadi_design.plan.rules.ADD_MARGIN_M` from its bound at the maximum, or the last run
    holds every row. Returns z and the multipliers of z's bounds and of every rule row (0 for
    the rows not held)."""
    n, R = problem.robot.n, search.capsules.size
    held = _held(problem, z0[:n], START_MARGIN_M,
                 None if start is None else np.flatnonzero(start[1][search.capsules]))
    lam_x, lam_g = (None, None) if start is None else (scale * start[0], scale * start[1])
    z, p = z0, (scale * G).ravel(order="F")
    for run in range(SEARCH_RUNS):
        if run == SEARCH_RUNS - 1:
            held = np.arange(R)
        K = search.size(held.size)
        index, where, lbg, ubg = search.rows(held, K)
        cold, warm = search.solvers(K)
        args = dict(x0=z, p=np.concatenate([p, index]), lbx=search.lbx, ubx=search.ubx, lbg=lbg, ubg=ubg)
        with ipopt_call():  # Ctrl-C stops the command, not just this search
            if lam_g is None:
                sol = cold(**args)
            else:
                sol = warm(**args, lam_x0=lam_x, lam_g0=np.where(where < 0, 0.0, lam_g[where]))
        z = np.clip(np.asarray(sol["x"]).ravel(), search.lbx, search.ubx)
        lam_x, lam_g = np.asarray(sol["lam_x"]).ravel(), np.zeros(search.lbg.size)
        lam_g[where[where >= 0]] = np.asarray(sol["lam_g"]).ravel()[where >= 0]
        grown = _held(problem, z[:n], ADD_MARGIN_M, held)
        if grown.size == held.size:
            break
        held = grown
    return z, lam_x, lam_g


def maximise_d(problem: Problem, scale: float, G: np.ndarray, Q: np.ndarray, F: np.ndarray,
                duals: list[Duals | None]) -> tuple[np.ndarray, np.ndarray, list[Duals]]:
    """Local maxima of ``d(x) = tr(G B(x)^T B(x))`` (IPOPT sees ``scale d``) from the
    experiments ``Q`` (k, n), ``F`` (k, nF); one with ``duals`` (a maximum of an earlier step)
    starts warm from them, the others cold (:func:`_search_one`). Each search is a pure
    function of its inputs, so a batch may be split over workers (:data:`Maximise`). Returns
    the maxima that keep every rule but the check on the real geometry
    (:func:`casadi_design.plan.rules.plan_violations` with ``meshes=False``; the caller checks
    those it uses, :func:`_untouched`): Q (p, n), F (p, nF), their duals."""
    search = _search(problem)
    loads, n = problem.rules.loads, problem.robot.n
    found = []
    for q0, f0, start in zip(Q, F, duals):
        z0 = np.concatenate([q0, loads.variables(f0[None]).ravel()])
        z, lam_x, lam_g = _search_one(problem, search, G, z0, start, scale)
        q, f = z[:n], loads.load(z[n:])
        if not plan_violations(problem, q[None], f[None], meshes=False):
            found.append((q, f, (lam_x / scale, lam_g / scale)))
    return (np.array([q for q, _, _ in found]).reshape(len(found), n),
            np.array([f for _, f, _ in found]).reshape(len(found), F.shape[1]), [u for _, _, u in found])


def _untouched(problem: Problem, Q: np.ndarray) -> np.ndarray:
    """Which experiments of ``Q`` (k, n), rad, keep clear on the cell's real geometry
    (:func:`casadi_design.plan.rules.mesh_contacts`), shape (k,) bool."""
    return np.array([not mesh_contacts(problem, q[None]) for q in Q], dtype=bool).reshape(len(Q))


def approximate_design(
    problem: Problem,
    criterion: str = "test-pose",
    *,
    m: int = 0,
    pool_size: int = POOL_SIZE,
    sample_size: int = SAMPLE_SIZE,
    rtol: float = EXCHANGE_RTOL,
    iterations: int = EXCHANGE_ITERATIONS,
    progress: Callable[[float], object] | None = None,
    maximise: Maximise | None = None,
) -> ApproximateDesign:
    """The approximate design of ``criterion`` and its certified bound constant.

    Column generation over single experiments. The candidates are ``pool_size`` random feasible
    experiments (seeded by ``problem.solver.seed``), the first pool, and ``sample_size`` more.
    Each step solves the convex problem on the pool (:func:`pool_optimum`), prices every
    candidate by ``d(x, W)``, and polishes by IPOPT (:func:`maximise_d`) the support points and
    the ``POLISH_STARTS`` best candidates: at the optimum every support point is a local
    maximum of d, so the support moves to where the continuum wants it. A support point that
    is a maximum of an earlier step starts warm from its multipliers (it follows its maximum
    as W moves); the others start cold. The certificate of the step is ``phi^2 / d_max`` (D:
    ``log det W + d_max - L``) with d_max the largest d of the candidates and maxima. The next
    pool is the support, the ``ADDED_CANDIDATES`` best candidates and the maxima whose d
    exceeds ``phi``; every ``form.moves`` steps (the criterion's
    :attr:`~casadi_design.measures.criteria.BoundForm.moves`) also the heavy support points moved
    together with W (:func:`_moved`). When the best certified value is within ``rtol``
    (relative; D: ``rtol L`` on log det) of the best value on a pool (then both are within
    rtol of the hull's optimum), when no candidate or maximum exceeds ``phi`` (the
    equivalence theorem: the pool holds the hull's optimum, up to the search for the
    maximum), or at the last of ``iterations`` steps, an independent search from a fresh
    sample checks the best certificate (:func:`_verified`). The steps stop when it finds no d
    larger by more than ``rtol``; otherwise what it found joins the candidates (and the pool)
    and the steps go on, so a maximum the exchange missed moves the design instead of only
    loosening the bound. ``progress`` is called with the best certified value after each
    step; ``maximise`` runs the IPOPT searches of a step (None: :func:`maximise_d`, here, one
    after the other; the same maxima either way).

    The best certificate is kept with its W, mu, d_max and support, the best checked one once
    checked: the reported certificate is always one an independent search confirmed; ``value``
    is the best value on a pool over the steps.

    Raises
    ------
    DesignError
        For a criterion without a bound, or a first pool whose information is singular.
    """
    if criterion not in BOUND_CRITERIA:
        raise DesignError(f"approximate design: criterion '{criterion}' has no bound; "
                          f"allowed: {', '.join(BOUND_CRITERIA)}")
    check_m(problem, m)  # before the sample
    t0 = time.perf_counter()
    maximise = maximise_d if maximise is None else maximise
    L, form = problem.model.L, CRITERIA[criterion].bound
    rng = np.random.default_rng([problem.solver.seed, SEED_ID, CRITERIA[criterion].seed_id])
    Q, F = _sample(problem, pool_size + sample_size, rng)
    c, A, F0, Hj = scaled_pool(problem, criterion, experiment_information(problem, Q, F), m)
    lam = np.linalg.eigvalsh(A[:pool_size].mean(axis=0) + (0.0 if F0 is None else F0))
    if not lam[0] > POOL_RCOND * lam[-1]:
        rank = int(np.sum(lam > POOL_RCOND * lam[-1]))
        raise DesignError(f"approximate design: the first pool of {pool_size} random experiments "
                          f"(--bound-pool) identifies {rank} of the {L} parameters; use a larger pool "
                          f"(default {POOL_SIZE})")
    sense = 1.0 if Hj is None else -1.0  # D's certificate is an upper bound, the others' lower
    pool, w = np.arange(pool_size), np.full(pool_size, 1.0 / pool_size)
    best, value, history = None, -np.inf * sense, []
    duals: dict[int, Duals] = {}  # the candidates that are maxima of an earlier step: theirs
    checked, proven = [], None  # the checked steps, the best checked certificate
    for step in range(iterations):
        w, mu = pool_optimum(A[pool], Hj, w, F0)
        W = np.einsum("k,kij->ij", w, A[pool])
        lin = linearised(W, mu, Hj, F0)
        G, phi, step_value = lin.G, lin.phi, lin.value
        value = max(value, step_value) if Hj is None else min(value, step_value)
        d = np.einsum("kij,ij->k", A, G)
        support = w > WEIGHT_RTOL * w.max()
        heavy = pool[np.argsort(w)[::-1][:min(support.sum(), POLISH_SUPPORT)]]
        starts = np.union1d(heavy, np.argsort(d)[::-1][:POLISH_STARTS])
        Qp, Fp, Ap, dp, up = _maxima(problem, G, c, Q[starts], F[starts], d[starts],
                                     [duals.get(int(i)) for i in starts], phi, maximise)
        d_max = float(max(d.max(), dp.max(initial=0.0)))
        certified = certificate(Hj, lin, d_max)
        if best is None or sense * (certified - best[0]) < 0:
            best = (certified, pool[support], w[support] / w[support].sum(), W, mu, d_max)
        priced = np.setdiff1d(np.flatnonzero(d > phi), pool[support])
        added = priced[np.argsort(d[priced])[::-1][:ADDED_CANDIDATES]]
        if form.moves and step and step % form.moves == 0:  # the heavy support moved: new candidates
            Qm, Fm = _moved(problem, criterion, Q[pool[support]], F[pool[support]], w[support],
                            A[pool[support]] / c, None if F0 is None else F0 / c)
            Am = c * experiment_information(problem, Qm, Fm)
            Qp, Fp, Ap = (np.concatenate(pair) for pair in ((Qp, Qm), (Fp, Fm), (Ap, Am)))
            up = [*up, *[None] * len(Qm)]  # no duals: their searches start cold
        new = _distinct(Ap, A[pool[support]])
        gap = (best[0] - value) / L if Hj is None else (value - best[0]) / value
        last = step == iterations - 1
        Qv, Fv, Av, stop = Q[:0], F[:0], A[:0], False
        if gap <= rtol or not (added.size or new.any()) or last:
            # the best step's certificate from a fresh sample: it stands when that search finds
            # no larger d; otherwise what it found joins the candidates and the steps go on
            certified, d_max, Qv, Fv, Av = _verified(problem, c, *best[3:], Hj, F0, rng, sample_size, maximise)
            agreed = sense * (certified - best[0]) <= rtol * (L if Hj is None else best[0])
            best = (certified, *best[1:5], d_max)
            if proven is not None and sense * (proven[0] - certified) < 0:
                best = proven  # an earlier check's certificate is better: it stands
            proven = best
            checked.append(step)
            stop = agreed or last
        history.append(best[0])
        if progress is not None:
            progress(best[0])
        if stop:
            break
        duals.update(zip(range(len(A), len(A) + int(new.sum())), (u for u, k in zip(up, new) if k)))
        Q, F, A = (np.concatenate([Q, Qp[new], Qv]), np.concatenate([F, Fp[new], Fv]),
                   np.concatenate([A, Ap[new], Av]))
        pool = np.concatenate([pool[support], added, np.arange(len(A) - new.sum() - len(Qv), len(A))])
        w = np.concatenate([w[support], np.full(len(pool) - support.sum(), NEW_WEIGHT * w[support].mean())])
        w /= w.sum()
    certified, idx, weights, W, mu, d_max = best
    value, certified, *history = unscaled(Hj, c, L, value, certified, *history)  # log det of the unscaled W
    return ApproximateDesign(criterion, Q[idx], F[idx], weights, W / c, mu, value, certified, d_max,
                             tuple(history), tuple(checked), len(A), time.perf_counter() - t0,
                             m=0 if F0 is None else m)


#: A move of the support (:func:`_moved`, every ``BoundForm.moves`` exchange steps): the
#: heavy points, those carrying all the weight but ``MOVE_TAIL``, by one IPOPT run of at most
#: ``MOVE_ITERATIONS`` from the support (barrier parameter ``MOVE_MU``: the support is nearly
#: optimal already). On the UR10 test-pose design, moves every 6 steps bring the
#: certificate's gap to 0.05 % in 37 steps, 37.7 s (0.58 % in 40 steps, 31.1 s without); every
#: 4 steps 0.07 % in 42 s, every 2 0.07 % in 64 s, every step 0.04 % in 99 s. Moving every
#: support point (62 at step 12) runs to 3000 iterations and 59 s: the points of tiny weight
#: barely steer their rows. A's 77 to 105 heavy points take 8 to 13 s a move (30 of them 0.2
#: to 1.6 s, no better bound), so A has no moves; D's moves capped at 30 points end 0.002
#: above the uncapped bound of log det.
MOVE_TAIL = 0.05
MOVE_MU = 1e-4
MOVE_ITERATIONS = 200
MOVE_TOL = 1e-8


def _moved(problem: Problem, criterion: str, Q: np.ndarray, F: np.ndarray, w: np.ndarray,
           A: np.ndarray, held: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The support points ``Q`` (k, n), rad, ``F`` (k, nF), N of weights ``w`` (k,) and
    information ``A`` (k, L, L) moved to better places: with the weights fixed, the heavy
    points (the fewest carrying ``1 - MOVE_TAIL`` of the weight) minimise the criterion of

        W = sum_heavy w_i B(z_i)^T B(z_i) + sum_light w_l A_l (+ held, the fixed part)

    over their experiments z_i, from where they are (the criterion's design NLP,
    :func:`casadi_design.optimisation.nlp.build_nlp` with ``weights`` and the light points' information
    ``fixed``, holding the capsule rows near the support). The exchange moves the support only
    through the maxima of d at the current W, one step behind the W they change (the value falls
    a few 1e-4 per step at the end, and the certificate lags): this moves the points and W
    together. Returns the moved points that keep every rule and the cell's real geometry; they
    join the pool as candidates, whose optimum decides their weights, so a move that fails or
    goes astray costs time only. One run, without adding the rows a point ends past: on the
    UR10 it keeps about 60 % of the heavy points; growing the rows as a design's start does
    (:func:`casadi_design.optimisation.solve.solve_start`) keeps nearly all, but the moves take twice as long
    and the test-pose certificate ends 0.6 % from its relaxation instead of 0.05 %."""
    w = w / w.sum()
    order = np.argsort(w)[::-1]
    K = int(np.searchsorted(np.cumsum(w[order]), 1.0 - MOVE_TAIL)) + 1
    heavy, light = order[:K], order[K:]
    Q, F = Q[heavy], F[heavy]
    nlp = build_nlp(problem, criterion, K,
                    active=problem.rules.pose.near(Q, START_MARGIN_M), weights=K * w[heavy],
                    fixed=K * (np.einsum("k,kij->ij", w[light], A[light]) + (0.0 if held is None else held)))
    solver = nlp.solver("move", {**QUIET, "ipopt.mu_init": MOVE_MU,
                                 "ipopt.max_iter": MOVE_ITERATIONS, "ipopt.tol": MOVE_TOL})
    with ipopt_call():
        sol = solver(x0=nlp.start(Q, F), lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg)
    Qm, Fm = (np.asarray(v, dtype=float) for v in nlp.plan(sol["x"]))
    Qm = problem.rules.limits.wrap(Qm)
    ok = np.array([not plan_violations(problem, q[None], f[None], meshes=False)
                   for q, f in zip(Qm, Fm)], dtype=bool)
    ok[ok] = _untouched(problem, Qm[ok])
    return Qm[ok], Fm[ok]


def _distinct(Ap: np.ndarray, Aref: np.ndarray, rtol: float = DISTINCT_RTOL) -> np.ndarray:
    """Which of the experiments of information ``Ap`` (p, L, L) differ from those of ``Aref``
    (r, L, L) and from the ones before them by more than ``rtol`` (relative, Frobenius): local
    searches from nearby starts end at the same maximum, and a pool of duplicates (equal for
    the design, whatever their joint values) only slows the convex solves."""
    keep = np.zeros(len(Ap), dtype=bool)
    ref = [a.ravel() for a in Aref]
    for i, a in enumerate(a.ravel() for a in Ap):
        tol = rtol * np.linalg.norm(a)
        if not ref or np.min(np.linalg.norm(np.asarray(ref) - a, axis=1)) > tol:
            keep[i] = True
            ref.append(a)
    return keep


def _maxima(problem: Problem, G: np.ndarray, c: float, Q: np.ndarray, F: np.ndarray, d: np.ndarray,
            duals: list[Duals | None], above: float, maximise: Maximise
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[Duals]]:
    """The feasible local maxima of d above ``above`` from the experiments ``Q``, ``F`` (values
    ``d``, warm starts ``duals``; ``maximise``: :func:`maximise_d` here, or split over
    workers) with their scaled information ``c A``
    (p, L, L), their d (p,) and duals. Maxima at or below ``above`` (phi, or the largest d
    found) can neither join the pool nor raise d_max (phi is the support's mean d, so d_max
    >= phi): they are left out before the check on the real geometry, the costly part of the
    plan check."""
    Qp, Fp, up = maximise(problem, 1.0 / np.max(d), G, Q, F, duals)  # IPOPT sees d of order 1
    Ap = c * experiment_information(problem, Qp, Fp)
    dp = np.einsum("kij,ij->k", Ap, G)
    keep = dp > above
    keep[keep] = _untouched(problem, Qp[keep])
    return Qp[keep], Fp[keep], Ap[keep], dp[keep], [u for u, k in zip(up, keep) if k]


def verify_starts(size: int) -> int:
    """IPOPT starts of the independent search over a fresh sample of ``size`` experiments:
    ``VERIFY_STARTS`` per ``SAMPLE_SIZE``, ``POLISH_STARTS`` at least (64 of 3000, 16 of 300)."""
    return max(POLISH_STARTS, VERIFY_STARTS * size // SAMPLE_SIZE)


def _verified(problem: Problem, c: float, W: np.ndarray, mu: np.ndarray, d_max: float,
              Hj: np.ndarray | None, F0: np.ndarray | None, rng: np.random.Generator, size: int,
              maximise: Maximise) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """The certificate of ``W`` (scaled by c) and ``mu`` once more, with max_x d searched over a
    fresh sample of ``size`` experiments and IPOPT from its :func:`verify_starts` best: a search
    independent of the exchange, whose own maxima went into the pool. Returns the certified
    value, d_max (the larger of ``d_max`` and the new search's) and the experiments of the new
    search with d above ``d_max`` (the sample's and the maxima's: Q (k, n), F (k, nF), their
    scaled information (k, L, L))."""
    lin = linearised(W, mu, Hj, F0)
    G = lin.G
    Q, F = _sample(problem, size, rng)
    A = c * experiment_information(problem, Q, F)
    d = np.einsum("kij,ij->k", A, G)
    best = np.argsort(d)[::-1][:verify_starts(size)]
    Qp, Fp, Ap, dp, _ = _maxima(problem, G, c, Q[best], F[best], d[best], [None] * len(best), d_max, maximise)
    above = best[d[best] > d_max]
    d_max = float(max(d_max, d.max(), dp.max(initial=0.0)))
    return (certificate(Hj, lin, d_max), d_max, np.concatenate([Q[above], Qp]),
            np.concatenate([F[above], Fp]), np.concatenate([A[above], Ap]))


def apportion(weights: np.ndarray, m: int) -> np.ndarray:
    """Pukelsheim's efficient apportionment of m experiments to the support points of
    ``weights`` (k,): ``n_i = ceil((m - k/2) w_i)``, then one at a time to the smallest
    ``n_i / w_i`` (or from the largest ``(n_i - 1) / w_i``) until ``sum n_i = m``; of equal
    ratios, the heaviest point gains first and the lightest loses first. With fewer
    experiments than half the support (m < k/2: every ``n_i`` starts at 0, all ratios equal),
    the m heaviest points get one each."""
    w = np.asarray(weights, dtype=float)
    n = np.maximum(np.ceil((m - len(w) / 2) * w), 0).astype(int)
    while n.sum() < m:
        n[np.lexsort((-w, n / w))[0]] += 1
    while n.sum() > m:
        n[np.lexsort((w, -(n - 1) / w))[0]] -= 1
    return n


def rounded_plans(problem: Problem, approx: ApproximateDesign, m: int,
                  count: int | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Plans of m experiments from the approximate design, as extra starts of
    :func:`casadi_design.optimisation.solve.solve_design` (``initial_plans``).

    ``count`` plans (None: the :attr:`~casadi_design.measures.criteria.Criterion.rounded` of the approximate
    design's criterion).
    The first repeats support point i ``n_i`` times (:func:`apportion`); the other ``count - 1``
    move each of its joint values by a normal step of ``ROUNDING_JITTER`` times the joint's
    range (seeded by ``problem.solver.seed`` and m), so repeated experiments can separate.
    Returns ``(Q0, F0)`` pairs: Q0 shape (m, n), rad; F0 shape (m, nF), N.
    """
    count = CRITERIA[approx.criterion].rounded if count is None else count
    idx = np.repeat(np.arange(len(approx.weights)), apportion(approx.weights, m))
    Q0, F0 = approx.Q[idx], approx.F[idx]
    limits = problem.rules.limits
    rng = np.random.default_rng([problem.solver.seed, SEED_ID, m])
    span = limits.upper - limits.lower
    plans = [(Q0, F0)]
    for _ in range(count - 1):
        step = rng.normal(size=Q0.shape[::-1]).T  # drawn as (n, m): fixes each seed's starts
        plans.append((limits.wrap(Q0 + ROUNDING_JITTER * span * step), F0.copy()))
    return plans


def approximate_one(problem: Problem, criterion: str, steps: int, pool: int,
                    maximise: Maximise | None = None, m: int = 0) -> ApproximateDesign:
    """The approximate design of ``criterion`` (for ``m`` new experiments when the problem
    holds information, module docstring) with ``steps`` exchange steps at most, a first pool
    of ``pool`` candidates and a sample of ``SAMPLE_SIZE / POOL_SIZE`` times as many for the
    search of max d (``maximise``: :func:`approximate_design`'s)."""
    return approximate_design(problem, criterion, m=m, iterations=steps, pool_size=pool,
                              sample_size=pool * SAMPLE_SIZE // POOL_SIZE, maximise=maximise)
