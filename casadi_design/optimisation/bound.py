"""Certified bounds on what any plan can achieve, from the approximate (continuous) design.

For any plan of m experiments, ``M = sum_i B_i^T B_i = m Wbar`` with ``Wbar`` in the convex
hull of ``{A(x) = B(x)^T B(x)}`` over single experiments ``x = (q, F)`` that satisfy the
per-experiment rules (joint limits, load, workspace; :mod:`casadi_design.plan.rules`). Relaxing
"m equal-weight points" to "any point of the hull" gives, for the test-pose criterion,

    max_j rho_j(plan) >= (sigma^2 / m) t*,   t* = min_{W in hull} max_j tr(B0_j W^-1 B0_j^T).

The hull is reached through a pool of candidate experiments: ``W = sum_k w_k A_k`` with ``w``
in the simplex, a convex problem (:func:`approximate_design`). Its value on a pool is only an
upper estimate of t*; the bound is *certified* by the general equivalence theorem: for any W
in the hull and any weights ``mu`` on the test poses (``sum_j mu_j = 1``; here the dual
variables of the epigraph rows), with ``H = sum_j mu_j B0_j^T B0_j``,

    phi(W) = tr(H W^-1),   d(x, W) = tr(H W^-1 A(x) W^-1),   t* >= phi(W)^2 / max_x d(x, W)

(convexity of ``tr(H W^-1)`` on the positive definite matrices, its tangent at ``c W`` and the
best c; tight at the optimum, where ``max_x d = phi``). For D (``log det``): for any plan,

    log det M <= L log m + log det W + max_x tr(W^-1 A(x)) - L,

and A (``tr M^-1``) is the test-pose form with ``B0 = I``; I (the mean of ``rho_j``) is the
test-pose form with the one matrix ``mean_j B0_j^T B0_j``, i.e. the same certificate with
equal weights ``mu_j = 1/s``. Each criterion's form is its registry entry's
:class:`~casadi_design.measures.criteria.BoundForm`. The maximum over x is a global
search over ONE experiment (:mod:`.approximate`); on a finite pool it is priced exactly
(:func:`pool_design`).

With information held before the plan (``problem.M_held``: experiments already measured, a
prior; :mod:`casadi_design.calibration.held`), ``M = M_held + m Wbar`` is no longer homogeneous in m:
the approximate design is made for one m, over ``F0 + W`` with the fixed part ``F0 = M_held / m``,
and the tangent of the convex ``tr(H (F0 + W)^-1)`` at W gives for any W* of the hull

    tr(H (F0 + W*)^-1) >= tr(H N) + tr(N H N W) - max_x d(x, W),   N = (F0 + W)^-1,

and for D ``log det(F0 + W*) <= log det(F0 + W) + max_x tr(N A(x)) - tr(N W)``: both tight at
the optimum, where ``max_x d`` is ``tr(N H N W)`` (``tr(N W)``), the support's mean d.

Units: M, W and A in the units of B (:meth:`casadi_design.calibration.models.CalibrationModel.B_stack`);
errors in m; the test-pose values ``t`` in (m / unit of X)^2 per (unit of B)^2, i.e. ``rho =
sigma^2 t / m`` in m^2.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import casadi as ca
import numpy as np

from ..errors import DesignError
from ..measures.criteria import CRITERIA
from ..measures.measures import information_matrices
from ..plan.design import Bound
from ..problem.build import Problem
from .ipopt import QUIET, ipopt_call
from .reduced import NumericFunction

#: IPOPT on the convex problem of a pool: tolerance and iterations.
POOL_TOL = 1e-10
POOL_ITERATIONS = 200
#: The exchange stops when the certified value is within this of the relaxation (relative).
EXCHANGE_RTOL = 1e-3
#: Weights below this fraction of the largest are left out of the reported support.
WEIGHT_RTOL = 1e-4


@dataclass(frozen=True, eq=False)
class ApproximateDesign:
    """The approximate design of one criterion and its certificate.

    Attributes
    ----------
    criterion : a criterion with a bound form (:data:`casadi_design.measures.criteria.BOUND_CRITERIA`).
    Q : ndarray, shape (k, n), rad: the support experiments; ``F`` shape (k, nF), N (N m).
    weights : ndarray, shape (k,): their weights (sum 1).
    W : ndarray, shape (L, L): ``sum_k w_k B_k^T B_k``, the mean information per experiment.
    mu : ndarray, shape (s,): weights of the test poses (test-pose; ``[1]`` for D, A and I).
    value : the best relaxation on a pool over the steps: ``max_j tr(B0_j W^-1 B0_j^T)``
        (test-pose), ``tr W^-1`` (A), ``mean_j tr(B0_j W^-1 B0_j^T)`` (I), ``log det W`` (D).
        An upper estimate of t* (lower for D).
    certified : ``phi^2 / d_max``, a lower bound of t* (test-pose, A, I), or
        ``log det W + d_max - L``, an upper bound of ``log det Wbar`` of any plan (D), for the
        W, mu of the step with the best certificate (support, weights, W and mu are that
        step's), with d_max from the exchange and a final independent search.
    d_max : the largest ``d(x, W)`` found over single experiments.
    history : the best certified value after each exchange step; it never falls but at the
        steps of ``checked``.
    checked : the steps after which the best certificate was checked by an independent search
        (:func:`_verified`), which lowers it when it finds a larger d; the last one is the
        reported certificate's.
    pool_size : candidates priced (random ones and local maxima); ``wall_s`` : time, s.
    kept : read back from the disk (:func:`computed`), computed by an earlier run in ``wall_s``.
    m : the number of new experiments it is for, with information held (``F0 = M_held / m``);
        0 without: the design of every m.
    """

    criterion: str
    Q: np.ndarray
    F: np.ndarray
    weights: np.ndarray
    W: np.ndarray
    mu: np.ndarray
    value: float
    certified: float
    d_max: float
    history: tuple[float, ...]
    checked: tuple[int, ...]
    pool_size: int
    wall_s: float
    kept: bool = False
    m: int = 0


def bound(problem: Problem, m: int, approx: ApproximateDesign, L: int | None = None) -> Bound:
    """The bound for ``m`` experiments in the units of the criterion's score
    (:attr:`casadi_design.measures.criteria.BoundForm.score`): ``sqrt(sigma^2 t / m)`` (m) for
    test-pose and I, ``t / m`` for A, ``L log m + log det W + d_max - L`` for D (see the
    module docstring; ``L`` the pool's parameters when they are not the problem's model's: an
    artefact's rows). An approximate design made for one m (``approx.m``) bounds that m only.

    Raises
    ------
    DesignError
        For an ``approx`` made for another m."""
    if approx.m and approx.m != m:
        raise DesignError(f"the approximate design of {approx.criterion} was made for m = {approx.m} new "
                          f"experiments, not {m}")
    L, score = L or problem.model.L, CRITERIA[approx.criterion].bound.score
    return Bound(approx.criterion, m, score(approx.certified, m, problem.sigma_m, L),
                 score(approx.value, m, problem.sigma_m, L), L)


def experiment_information(problem: Problem, Q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``B_k^T B_k`` of experiments ``Q`` (k, n), ``F`` (k, nF): shape (k, L, L)."""
    return information_matrices(problem.model.B_stack(Q, F))


class Scaled(NamedTuple):
    """A pool's information as the convex problem sees it (:func:`scaled_pool`): ``c`` (the weights
    see ``c A``: W of order 1), ``A`` scaled (k, L, L), the fixed part ``F0 = c M_held / m``
    (None: nothing held) and ``Hj = c`` times the criterion's rows (None for D)."""

    c: float
    A: np.ndarray
    F0: np.ndarray | None
    Hj: np.ndarray | None


def scaled_pool(problem: Problem, criterion: str, A: np.ndarray, m: int, B0: np.ndarray | None = None) -> Scaled:
    """:class:`Scaled` of the information ``A`` (k, L, L) of a pool, for ``m`` new experiments
    when the problem holds information (module docstring); ``B0`` the test poses' rows when they
    are not the problem's (an artefact's, :mod:`~casadi_design.optimisation.artefact_pool`).

    Raises
    ------
    DesignError
        With information held and no m (0) (:func:`check_m`).
    """
    check_m(problem, m)
    form = CRITERIA[criterion].bound
    c = problem.model.L / np.mean(np.trace(A, axis1=1, axis2=2))
    return Scaled(c, c * A, None if problem.M_held is None else c * problem.M_held / m,
                  None if form.log_det else c * form.rows(problem.B0 if B0 is None else B0))


def check_m(problem: Problem, m: int) -> None:
    """With information held an approximate design is for one m: refuse none (0)."""
    if problem.M_held is not None and m < 1:
        raise DesignError("approximate design: the problem holds information (measured experiments or a "
                          "prior), so the design is made for one number of new experiments; give m >= 1")


#: Candidates the convex problem of a pool holds at once (:func:`pool_design`): a larger pool
#: is priced whole by d and its best candidates join (column generation); the dense Hessian of
#: :func:`pool_optimum` grows as its square.
POOL_COLUMNS = 400
#: Candidates of a large pool added per column-generation step, and the steps at most.
POOL_ADDED = 100
POOL_STEPS = 30


def top_mean(d: np.ndarray, m: int) -> float:
    """The largest ``sum_k w_k d_k`` over the weights of the simplex with each ``w_k <= 1 / m``
    (a plan of m distinct postures): the mean of the m largest ``d_k``; the largest d for m =
    0 (repeats allowed)."""
    return float(np.max(d)) if m == 0 else float(np.mean(np.partition(d, len(d) - m)[len(d) - m:]))


def pool_design(problem: Problem, criterion: str, Q: np.ndarray, F: np.ndarray, A: np.ndarray,
                m: int = 0, B0: np.ndarray | None = None) -> ApproximateDesign:
    """The approximate design of a finite pool of experiments ``Q`` (k, n), ``F`` (k, nF) of
    information ``A`` (k, L, L) for plans of ``m`` distinct postures (each weight at most 1 / m;
    0: repeats allowed): the convex problem on the pool (:func:`pool_optimum`) and its
    certificate, exact, since d is priced over the whole pool; the certificate's largest d is
    the mean of the m largest (:func:`top_mean`: the tangent's minimum over the box). It bounds
    any choice of m distinct postures of the pool, not every plan of the robot; ``weights``
    holds every point's. A pool of more than :data:`POOL_COLUMNS` is solved by column
    generation: the convex problem on the candidates of the largest d at the pool's mean
    information, then on those and the :data:`POOL_ADDED` of the largest d outside them, until
    no candidate outside has d above the support's or the certificate meets the relaxation
    within :data:`EXCHANGE_RTOL`. ``B0``: the test poses' rows when not the problem's
    (:func:`scaled_pool`)."""
    t0 = time.perf_counter()
    s = scaled_pool(problem, criterion, A, m, B0)
    k, L = A.shape[:2]
    w_max = 1.0 / m if m else 1.0
    first = linearised(np.mean(s.A, axis=0), np.full(1 if s.Hj is None else len(s.Hj), 1.0), s.Hj, s.F0)
    d = np.einsum("kij,ij->k", s.A, first.G)
    active = np.sort(np.argsort(d)[::-1][:max(POOL_COLUMNS, 2 * m)])
    w_all, best = np.zeros(k), None
    for _ in range(POOL_STEPS):
        w0 = np.maximum(w_all[active], 0.1 / len(active))
        w, mu = pool_optimum(s.A[active], s.Hj, np.minimum(w0 / w0.sum(), w_max), s.F0, w_max)
        W = np.einsum("k,kij->ij", w, s.A[active])
        lin = linearised(W, mu, s.Hj, s.F0)
        d = np.einsum("kij,ij->k", s.A, lin.G)
        value, certified = unscaled(s.Hj, s.c, L, lin.value, certificate(s.Hj, lin, top_mean(d, m)))
        w_all = np.zeros(k)
        w_all[active] = w
        if best is None or tighter(s.Hj, certified, best[1]):
            best = (value, certified, w_all, mu, W, float(np.max(d)))
        outside = np.setdiff1d(np.arange(k), active)
        threshold = np.min(d[active][w > WEIGHT_RTOL * w.max()])
        new = outside[d[outside] > threshold]
        if not len(new) or abs(best[0] - best[1]) <= EXCHANGE_RTOL * abs(best[0]):
            break
        new = new[np.argsort(d[new])[::-1][:POOL_ADDED]]
        kept = active[w > WEIGHT_RTOL * w.max()] if len(active) + len(new) > 2 * POOL_COLUMNS else active
        active = np.union1d(kept, new)
    value, certified, w_all, mu, W, d_max = best
    return ApproximateDesign(criterion, Q, F, w_all, W / s.c, mu, value, certified, d_max, (), (), k,
                             time.perf_counter() - t0, m=m)


def tighter(Hj: np.ndarray | None, certified: float, than: float) -> bool:
    """Whether a certificate is tighter: larger for the lower bounds (test-pose, A, I), smaller
    for D's upper bound (``Hj`` None)."""
    return certified < than if Hj is None else certified > than


def unscaled(Hj: np.ndarray | None, c: float, L: int, *values: float) -> list[float]:
    """Values of the problem scaled by ``c`` in the units of B: D's (``Hj`` None) log det
    less ``L log c``; the others as they are."""
    return list(values) if Hj is not None else [v - L * np.log(c) for v in values]


def pool_optimum(A: np.ndarray, Hj: np.ndarray | None, w0: np.ndarray,
                  F0: np.ndarray | None = None, w_max: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The convex problem on a pool ``A`` (k, L, L), ``W = sum_k w_k A_k`` with w in the simplex
    (and each ``w_k <= w_max``: 1 / m for plans of m distinct postures),
    solved by IPOPT with exact derivatives from ``w0`` (k,), ``N = (F0 + W)^-1`` with the
    fixed part ``F0`` (L x L; None: 0):

    - test-pose and A (``Hj`` = ``B0_j^T B0_j``, shape (s, L, L)): ``min t`` subject to
      ``f_j = tr(Hj_j N) <= t``, ``N = W^-1``; the rows' multipliers are the test-pose weights
      mu (they sum to 1, the gradient of t);
    - D (``Hj`` None): ``min -log det W``.

    With ``df_j/dw_k = -<N Hj_j N, A_k>`` and ``d(-log det W)/dw_k = -<N, A_k>``, the Hessian of
    the Lagrangian is ``<G A_k N, A_l>`` with ``G = 2 N (sum_j lam_j Hj_j) N`` (test-pose) or
    ``G = sigma_f N`` (D): dense over the pool, so pools are kept to a few hundred candidates
    (:func:`approximate_design` adds candidates by column generation). Returns w (k,) and mu
    (s,; ``[1]`` for D). Any w and mu give a valid certificate; how exactly IPOPT solves this
    only decides how tight it is.
    """
    k, L = A.shape[:2]
    Av = A.reshape(k, L * L)
    s = 0 if Hj is None else len(Hj)
    nx, ng = k + (s > 0), s + 1
    last: dict = {}

    def inverse(x: np.ndarray) -> np.ndarray:
        if "x" not in last or not np.array_equal(last["x"], x):
            W = (x[:k] @ Av).reshape(L, L)
            N = np.linalg.inv(W if F0 is None else F0 + W)
            last.update(x=x.copy(), N=(N + N.T) / 2)
        return last["N"]

    def f_g(x: np.ndarray) -> list[np.ndarray]:
        N = inverse(x)
        if s == 0:
            return [np.array([np.linalg.slogdet(N)[1]]), np.array([x.sum()])]
        return [x[k:].copy(), np.concatenate([np.einsum("jil,li->j", Hj, N) - x[k], [x[:k].sum()]])]

    def grad_f(x: np.ndarray) -> list[np.ndarray]:
        g = -(Av @ inverse(x).ravel()) if s == 0 else np.eye(nx)[k]
        return [f_g(x)[0], g]

    def jac_g(x: np.ndarray) -> list[np.ndarray]:
        J = np.zeros((ng, nx))
        if s:
            N = inverse(x)
            J[:s, :k] = -((N @ Hj) @ N).reshape(s, L * L) @ Av.T
            J[:s, k] = -1.0
        J[s, :k] = 1.0
        return [f_g(x)[1], J.ravel(order="F")]

    rows, cols = np.triu_indices(nx)
    order = np.lexsort((rows, cols))  # the upper triangle's nonzeros, column by column
    rows, cols = rows[order], cols[order]

    def hess(x: np.ndarray, lam_f: np.ndarray, lam_g: np.ndarray) -> list[np.ndarray]:
        N = inverse(x)
        G = lam_f[0] * N if s == 0 else 2.0 * N @ np.einsum("j,jil->il", lam_g[:s], Hj) @ N
        Hs = np.zeros((nx, nx))
        Hs[:k, :k] = ((G @ A) @ N).reshape(k, L * L) @ Av.T
        return [Hs[rows, cols]]

    dense = ca.Sparsity.dense
    x_p = [("x", dense(nx, 1)), ("p", dense(0, 1))]
    f, g = ("f", dense(1, 1)), ("g", dense(ng, 1))
    opts = {
        "grad_f": NumericFunction("grad_f", x_p, [f, ("grad_f_x", dense(nx, 1))], lambda x, p: grad_f(x)),
        "jac_g": NumericFunction("jac_g", x_p, [g, ("jac_g_x", dense(ng, nx))], lambda x, p: jac_g(x)),
        "hess_lag": NumericFunction("hess_lag", x_p + [("lam_f", dense(1, 1)), ("lam_g", dense(ng, 1))],
                                    [("triu_hess_gamma_x_x", ca.Sparsity.upper(nx))],
                                    lambda x, p, lam_f, lam_g: hess(x, lam_f, lam_g)),
        "no_nlp_grad": True, **QUIET, "ipopt.tol": POOL_TOL, "ipopt.max_iter": POOL_ITERATIONS,
    }
    oracle = NumericFunction("nlp", x_p, [f, g], lambda x, p: f_g(x))  # alive while IPOPT runs
    solver = ca.nlpsol("pool_optimum", "ipopt", oracle, opts)
    x0 = w0 if s == 0 else np.concatenate([w0, [1.01 * f_g(np.concatenate([w0, [0.0]]))[1][:s].max()]])
    with ipopt_call():
        sol = solver(x0=x0, lbx=np.concatenate([np.zeros(k), np.full(nx - k, -np.inf)]),
                     ubx=np.concatenate([np.full(k, w_max if w_max < 1.0 else np.inf), np.full(nx - k, np.inf)]),
                     lbg=np.concatenate([np.full(s, -np.inf), [1.0]]), ubg=np.concatenate([np.zeros(s), [1.0]]))
    w = np.maximum(np.asarray(sol["x"]).ravel()[:k], 0.0)
    mu = np.maximum(np.asarray(sol["lam_g"]).ravel()[:s], 0.0) if s else np.ones(1)
    if not mu.sum() > 0:  # a failed solve: the worst test pose
        mu = np.eye(s)[np.argmax(f_g(np.concatenate([w, [0.0]]))[1][:s])]
    return w / w.sum(), mu / mu.sum()


class Linearised(NamedTuple):
    """What the certificate of a W and mu needs (:func:`linearised`): ``G`` with ``d(x, W) =
    <A(x), G>``, ``phi = <W, G>`` (the support's mean d), W's value and the mu-weighted value
    ``level`` (test-pose, A, I: ``tr(H N)``; D: 0)."""

    G: np.ndarray
    phi: float
    value: float
    level: float
    held: bool


def linearised(W: np.ndarray, mu: np.ndarray, Hj: np.ndarray | None, F0: np.ndarray | None = None) -> Linearised:
    """:class:`Linearised` of ``W`` (scaled, L x L), ``mu`` and the fixed part ``F0`` (None: 0),
    ``N = (F0 + W)^-1``. Test-pose and A: ``G = N H N``, value ``max_j tr(Hj_j N)``, ``H =
    sum_j mu_j Hj_j``, ``phi = tr(H N) - tr(G F0)``; D: ``G = N``, value ``log det(F0 + W)``,
    ``phi = L - tr(N F0)``."""
    T = W if F0 is None else F0 + W
    N = np.linalg.inv(T)
    if Hj is None:
        phi = float(len(W)) - (0.0 if F0 is None else float(np.einsum("ij,ji->", N, F0)))
        return Linearised(N, phi, float(np.linalg.slogdet(T)[1]), 0.0, F0 is not None)
    H = np.einsum("j,jil->il", mu, Hj)
    G = N @ H @ N
    level = float(np.trace(H @ N))
    phi = level - (0.0 if F0 is None else float(np.einsum("ij,ji->", G, F0)))
    return Linearised(G, phi, float(np.einsum("jil,li->j", Hj, N).max()), level, F0 is not None)


def certificate(Hj: np.ndarray | None, lin: Linearised, d_max: float) -> float:
    """The certificate of :func:`linearised`'s W and mu (module docstring). D: ``value + d_max
    - phi``, an upper bound of ``log det`` of any hull point (``log det W + d_max - L`` without a
    fixed part). Test-pose, A, I: a lower bound of t*, ``phi^2 / d_max`` without a fixed part
    (tangent at the best multiple of W), ``level + phi - d_max`` (at least 0) with one."""
    if Hj is None:
        return float(lin.value + d_max - lin.phi)
    if lin.held:
        return float(max(lin.level + lin.phi - d_max, 0.0))
    return float(lin.phi**2 / d_max)
