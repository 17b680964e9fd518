"""Certified bounds on what any plan can achieve, from the approximate (continuous) design.

For any plan of m experiments, ``M = sum_i B_i^T B_i = m Wbar`` with ``Wbar`` in the convex
hull of ``{A(x) = B(x)^T B(x)}`` over single experiments ``x = (q, F)`` that satisfy the
per-experiment rules (joint limits, load, workspace; :mod:`casadi_design.rules`). Relaxing
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

and A (``tr M^-1``) is the test-pose form with ``B0 = I``. The maximum over x is a global
search over ONE experiment: a dense random sample of feasible experiments, then IPOPT from the
best of them. The bound is certified only as well as that maximum is found: a missed higher
maximum of d makes the reported bound too optimistic by the same ratio.

Units: M, W and A in the units of B (:meth:`casadi_design.models.CalibrationModel.B_stack`);
errors in m; the test-pose values ``t`` in (m / unit of X)^2 per (unit of B)^2, i.e. ``rho =
sigma^2 t / m`` in m^2.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .build import Problem, per_model
from .errors import DesignError
from .nlp import B0_at_test_poses, plan_bounds, rule_bounds
from .problem import spec_digest_blob
from .reduced import experiment_functions
from .rules import joint_limits, load_variables, plan_violations
from .solve import QUIET, Design, ipopt_call, random_plan

#: Criteria with an approximate design and a bound.
BOUND_CRITERIA = ("test-pose", "D", "A")
#: Candidate experiments of the first pool, and of the dense sample searched for max_x d.
POOL_SIZE = 1000
SAMPLE_SIZE = 5000
#: IPOPT starts of the search for max_x d: the best points of the sample.
POLISH_STARTS = 8
#: The exchange stops when the certified value moves by less than this (relative).
EXCHANGE_RTOL = 1e-4
EXCHANGE_ITERATIONS = 40
#: Multiplicative updates of the weights per convex solve, at most.
MW_ITERATIONS = 5000
#: Weights below this fraction of the largest are left out of the reported support.
WEIGHT_RTOL = 1e-4
#: Plans of :func:`rounded_plans`, and the step of the jittered ones (fraction of the joint range).
ROUNDED_PLANS = 4
ROUNDING_JITTER = 0.02
#: Seed id of the bound's random numbers (beside the criteria's ids 0..5).
SEED_ID = 100
#: Exchange steps of the commands (``--bound-steps``; 0: no bound, no rounded starts).
BOUND_STEPS = 12
#: ``StartRecord.origin`` of the starts rounded from the approximate design.
ROUNDED = "rounded approximate design"


@dataclass(frozen=True, eq=False)
class ApproximateDesign:
    """The approximate design of one criterion and its certificate.

    Attributes
    ----------
    criterion : "test-pose", "D" or "A".
    Q : ndarray, shape (k, n), rad: the support experiments; ``F`` shape (k, nF), N (N m).
    weights : ndarray, shape (k,): their weights (sum 1).
    W : ndarray, shape (L, L): ``sum_k w_k B_k^T B_k``, the mean information per experiment.
    mu : ndarray, shape (s,): weights of the test poses (test-pose; ``[1]`` for D and A).
    value : the relaxation on the final pool: ``max_j tr(B0_j W^-1 B0_j^T)`` (test-pose),
        ``tr W^-1`` (A), ``log det W`` (D). An upper estimate of t* (lower for D).
    certified : ``phi^2 / d_max``, a lower bound of t* (test-pose, A), or
        ``log det W + d_max - L``, an upper bound of ``log det Wbar`` of any plan (D).
    d_max : the largest ``d(x, W)`` found over single experiments.
    history : the certified value after each exchange step.
    pool_size : candidates in the final pool; ``wall_s`` : time, s.
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
    pool_size: int
    wall_s: float


@dataclass(frozen=True)
class Bound:
    """The bound of one criterion for m experiments, in the units of its score
    (:class:`casadi_design.measures.Scores`).

    ``value``: lower bound of ``max_rms_error_m`` (test-pose, m) or of ``trace_M_inv`` (A);
    upper bound of ``log_det_M`` (D). ``relaxation``: the same quantity from the relaxation's
    value on the pool (not certified). ``L``: number of parameters.
    """

    criterion: str
    m: int
    value: float
    relaxation: float
    L: int


def _scores(criterion: str, constant: float, m: int, sigma: float, L: int) -> float:
    """The score of the m-experiment bound from the per-experiment constant."""
    if criterion == "test-pose":
        return float(np.sqrt(sigma**2 * constant / m))
    if criterion == "A":
        return constant / m
    return L * np.log(m) + constant


def bound(problem: Problem, m: int, approx: ApproximateDesign) -> Bound:
    """The bound for ``m`` experiments: ``sqrt(sigma^2 t / m)`` (m) for test-pose, ``t / m``
    for A, ``L log m + log det W + d_max - L`` for D (see the module docstring)."""
    L = problem.model.L
    return Bound(approx.criterion, m, _scores(approx.criterion, approx.certified, m, problem.sigma_m, L),
                 _scores(approx.criterion, approx.value, m, problem.sigma_m, L), L)


def gap_percent(b: Bound, achieved: float) -> float:
    """How far a plan's score ``achieved`` is from the bound, in percent: the excess of the
    error (test-pose) or of ``tr M^-1`` (A) over the bound; for D, of ``det M^(-1/L)``."""
    if b.criterion == "D":
        return float(100.0 * np.expm1((b.value - achieved) / b.L))
    return float(100.0 * (achieved / b.value - 1.0))


def _information(problem: Problem, Q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``B_k^T B_k`` of experiments ``Q`` (k, n), ``F`` (k, nF): shape (k, L, L)."""
    B = problem.model.B_stack(Q, F)
    return np.einsum("kri,krj->kij", B, B)


def _sample(problem: Problem, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``size`` random feasible single experiments: Q (size, n), F (size, nF)."""
    Q, F = random_plan(problem, size, rng)
    return Q.T.copy(), F.T.copy()


def _weights(A: np.ndarray, B0: np.ndarray | None, w: np.ndarray, mu: np.ndarray,
             rtol: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The convex problem on a pool ``A`` (k, L, L), ``W = sum_k w_k A_k``, w in the simplex:
    ``min_w max_j tr(B0_j W^-1 B0_j^T)`` (``B0`` (s, r, L)) or ``max_w log det W`` (``B0``
    None), by multiplicative updates from ``w`` (k,) and ``mu`` (s,).

    test-pose and A: ``mu_j <- mu_j f_j / sum_i mu_i f_i`` (``f_j = tr(H_j W^-1)``, the weights
    move to the worst test poses) and ``w_k <- w_k sqrt(d_k / phi)`` (the multiplicative
    algorithm of the linear criterion ``phi = tr(H W^-1)``, ``H = sum_j mu_j H_j``,
    ``d_k = tr(H W^-1 A_k W^-1)``). D: ``w_k <- w_k d_k / L``, ``d_k = tr(W^-1 A_k)``
    (Titterington). Each step brackets the pool's optimum: ``phi^2 / max_k d_k <= opt <=
    max_j f_j`` (D: ``log det W <= opt <= log det W + max_k d_k - L``); the updates stop when
    the bracket is within ``rtol`` (relative; D: ``rtol L``) or after ``MW_ITERATIONS``.
    Returns w, mu and the bracket (lower, upper) of the pool's optimum.
    """
    k, L = A.shape[:2]
    Av = A.reshape(k, L * L)
    Hj = None if B0 is None else np.einsum("jri,jrl->jil", B0, B0)
    for _ in range(MW_ITERATIONS):
        N = np.linalg.inv((w @ Av).reshape(L, L))
        if Hj is None:
            d = Av @ N.ravel()
            logdet = -np.linalg.slogdet(N)[1]
            lower, upper = logdet, logdet + d.max() - L
            w = w * d / L
            if upper - lower <= rtol * L:
                break
        else:
            f = np.einsum("jil,li->j", Hj, N)
            mu = mu * f / (mu @ f)
            H = np.einsum("j,jil->il", mu, Hj)
            d = Av @ (N @ H @ N).ravel()
            phi = float(w @ d)
            lower, upper = phi**2 / d.max(), float(f.max())
            w = w * np.sqrt(d / phi)
            if upper - lower <= rtol * upper:
                break
        w /= w.sum()
    return w, mu, float(lower), float(upper)


@per_model
def _search(problem: Problem) -> tuple[ca.Function, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IPOPT on one experiment ``z = (q, v)``: ``max tr(G B(z)^T B(z))`` within its rules, with
    parameter ``vec G`` (L x L); and the bounds of z and of the rule rows."""
    fns, loads = experiment_functions(problem), load_variables(problem)
    L = problem.model.L
    z, G = ca.SX.sym("z", fns.p), ca.SX.sym("G", L, L)
    B, c = fns.values(z)
    solver = ca.nlpsol("max_d", "ipopt", {"x": z, "p": ca.vec(G), "f": -ca.dot(B @ G, B), "g": c},
                       {**QUIET, "ipopt.tol": 1e-10, "ipopt.max_iter": 200})
    # the plan of one experiment: its variables and rule rows are those of z and c
    return (solver, *plan_bounds(problem, 1, loads), *rule_bounds(problem, 1, loads))


def _maximise_d(problem: Problem, G: np.ndarray, Q: np.ndarray, F: np.ndarray,
                d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of ``d(x) = tr(G B(x)^T B(x))`` from the ``POLISH_STARTS`` best of the sampled
    experiments ``Q`` (k, n), ``F`` (k, nF) with values ``d`` (k,). Returns the feasible
    maxima: Q (p, n), F (p, nF)."""
    solver, lbx, ubx, lbg, ubg = _search(problem)
    loads, n = load_variables(problem), problem.robot.n
    scale = 1.0 / np.max(d)  # IPOPT sees d of order 1
    found = []
    for i in np.argsort(d)[::-1][:POLISH_STARTS]:
        z0 = np.concatenate([Q[i], loads.variables(F[i][:, None]).ravel()])
        with ipopt_call():  # Ctrl-C stops the command, not just this search
            sol = solver(x0=z0, p=(scale * G).ravel(order="F"), lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        z = np.clip(np.asarray(sol["x"]).ravel(), lbx, ubx)
        q, f = z[:n], loads.loads(z[n:, None]).ravel()
        if not plan_violations(problem, q[:, None], f[:, None]):
            found.append((q, f))
    return (np.array([q for q, _ in found]).reshape(len(found), n),
            np.array([f for _, f in found]).reshape(len(found), F.shape[1]))


def approximate_design(
    problem: Problem,
    criterion: str = "test-pose",
    *,
    pool_size: int = POOL_SIZE,
    sample_size: int = SAMPLE_SIZE,
    rtol: float = EXCHANGE_RTOL,
    iterations: int = EXCHANGE_ITERATIONS,
    progress: Callable[[float], object] | None = None,
) -> ApproximateDesign:
    """The approximate design of ``criterion`` and its certified bound constant.

    A pool of ``pool_size`` random feasible experiments (seeded by ``problem.solver.seed``)
    gives the convex problem over the weights (:func:`_weights`). Then exchange steps: the
    local maxima of ``d(x, W)`` (searched by IPOPT from the best of ``sample_size`` random
    feasible experiments) that exceed ``phi`` join the pool, until the certified value is
    within ``rtol`` (relative; for D: ``rtol L`` on log det) of the relaxation's value on the
    pool (then both are within rtol of the hull's optimum), or no local maximum of d exceeds
    ``phi`` (the equivalence theorem: the pool holds the hull's optimum, up to the search for
    the maximum). ``progress`` is called with the certified value after each step.

    Raises
    ------
    DesignError
        For a criterion without a bound.
    """
    if criterion not in BOUND_CRITERIA:
        raise DesignError(f"approximate design: criterion '{criterion}' has no bound; "
                          f"allowed: {', '.join(BOUND_CRITERIA)}")
    t0 = time.perf_counter()
    L = problem.model.L
    B0 = None if criterion == "D" else B0_at_test_poses(problem) if criterion == "test-pose" else np.eye(L)[None]
    rng = np.random.default_rng([problem.solver.seed, SEED_ID, BOUND_CRITERIA.index(criterion)])
    Q, F = _sample(problem, pool_size, rng)
    Qs, Fs = _sample(problem, sample_size, rng)
    A = _information(problem, Q, F)
    c = L / np.mean(np.trace(A, axis1=1, axis2=2))  # the weights see c A: W of order 1
    A, As = c * A, c * _information(problem, Qs, Fs)
    B0c = None if B0 is None else np.sqrt(c) * B0
    s = 1 if B0 is None else len(B0)
    w, mu = np.full(len(A), 1.0 / len(A)), np.full(s, 1.0 / s)
    history: list[float] = []
    for _ in range(iterations):
        w, mu, _, value = _weights(A, B0c, w, mu, rtol / 10)
        W = np.einsum("k,kij->ij", w, A)
        Wi = np.linalg.inv(W)
        if B0c is None:
            G, phi, value = Wi, float(L), float(np.linalg.slogdet(W)[1])
        else:
            H = np.einsum("j,jri,jrl->il", mu, B0c, B0c)
            G, phi = Wi @ H @ Wi, float(np.trace(H @ Wi))
        ds = np.einsum("kij,ij->k", As, G)
        Qp, Fp = _maximise_d(problem, G, Qs, Fs, ds)
        Ap = c * _information(problem, Qp, Fp)
        dp = np.einsum("kij,ij->k", Ap, G)
        d_max = float(max(ds.max(), dp.max(initial=0.0), np.einsum("kij,ij->k", A, G).max()))
        certified = float(value + d_max - L if B0c is None else phi**2 / d_max)
        history.append(certified)
        if progress is not None:
            progress(certified)
        new = dp > phi
        gap = (certified - value) / L if B0c is None else (value - certified) / value
        if gap <= rtol or not new.any():
            break
        Q, F, A = np.concatenate([Q, Qp[new]]), np.concatenate([F, Fp[new]]), np.concatenate([A, Ap[new]])
        w = np.concatenate([w, np.full(new.sum(), 1.0 / len(A))])
        w /= w.sum()
    support = w > WEIGHT_RTOL * w.max()
    if B0c is None:  # log det of the unscaled W
        value, certified = value - L * np.log(c), certified - L * np.log(c)
        history = [h - L * np.log(c) for h in history]
    return ApproximateDesign(criterion, Q[support], F[support], w[support] / w[support].sum(), W / c, mu,
                             value, certified, d_max, tuple(history), len(A), time.perf_counter() - t0)


def apportion(weights: np.ndarray, m: int) -> np.ndarray:
    """Pukelsheim's efficient apportionment of m experiments to the support points of
    ``weights`` (k,): ``n_i = ceil((m - k/2) w_i)``, then one at a time to the smallest
    ``n_i / w_i`` (or from the largest ``(n_i - 1) / w_i``) until ``sum n_i = m``."""
    w = np.asarray(weights, dtype=float)
    n = np.maximum(np.ceil((m - len(w) / 2) * w), 0).astype(int)
    while n.sum() < m:
        n[np.argmin(n / w)] += 1
    while n.sum() > m:
        n[np.argmax((n - 1) / w)] -= 1
    return n


def rounded_plans(problem: Problem, approx: ApproximateDesign, m: int,
                  count: int = ROUNDED_PLANS) -> list[tuple[np.ndarray, np.ndarray]]:
    """Plans of m experiments from the approximate design, as extra starts of
    :func:`casadi_design.solve.solve_design` (``initial_plans``).

    The first repeats support point i ``n_i`` times (:func:`apportion`); the other ``count - 1``
    move each of its joint values by a normal step of ``ROUNDING_JITTER`` times the joint's
    range (seeded by ``problem.solver.seed`` and m), so repeated experiments can separate.
    Returns ``(Q0, F0)`` pairs: Q0 shape (n, m), rad; F0 shape (nF, m), N.
    """
    idx = np.repeat(np.arange(len(approx.weights)), apportion(approx.weights, m))
    Q0, F0 = approx.Q[idx].T, approx.F[idx].T
    limits = joint_limits(problem)
    rng = np.random.default_rng([problem.solver.seed, SEED_ID, m])
    span = (limits.upper - limits.lower)[:, None]
    plans = [(Q0, F0)]
    for _ in range(count - 1):
        Q = Q0 + ROUNDING_JITTER * span * rng.normal(size=Q0.shape)
        plans.append((limits.wrap(Q), F0.copy()))
    return plans


#: Approximate designs computed in this process, by (the problem's checked data, criterion,
#: steps, pool): a pure function of them, reused by the commands that run one after the other
#: in one process (keyed like :func:`casadi_design.build.build_problem`'s problems).
_COMPUTED: dict[tuple[bytes, str, int, int], ApproximateDesign] = {}
KEEP_COMPUTED = 32


def approximate_designs(problem: Problem, criteria, steps: int = BOUND_STEPS,
                        pool: int = POOL_SIZE) -> dict[str, ApproximateDesign]:
    """The approximate design of each of ``criteria`` that has a bound, with ``steps`` exchange
    steps at most, a first pool of ``pool`` candidates and a sample of ``SAMPLE_SIZE / POOL_SIZE``
    times as many for the search of max d; none when ``steps`` is 0."""
    blob = spec_digest_blob(problem.spec)
    out = {}
    for c in criteria:
        if c in BOUND_CRITERIA and steps > 0:
            key = (blob, c, steps, pool)
            if key not in _COMPUTED:
                _COMPUTED[key] = approximate_design(problem, c, iterations=steps, pool_size=pool,
                                                    sample_size=pool * SAMPLE_SIZE // POOL_SIZE)
                while len(_COMPUTED) > KEEP_COMPUTED:
                    _COMPUTED.pop(next(iter(_COMPUTED)))
            out[c] = _COMPUTED[key]
    return out


def rounded_starts(problem: Problem, approx: dict[str, ApproximateDesign], criterion: str,
                   m: int) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """The :func:`rounded_plans` of ``criterion`` as labelled extra starts of
    :func:`casadi_design.solve.solve_design` (none without its approximate design)."""
    a = approx.get(criterion)
    return [] if a is None else [(Q, F, ROUNDED) for Q, F in rounded_plans(problem, a, m)]


def with_bound(problem: Problem, design: Design, approx: dict[str, ApproximateDesign]) -> Design:
    """``design`` with the bound of its criterion and m (unchanged without its approximate
    design)."""
    a = approx.get(design.criterion)
    return design if a is None else dataclasses.replace(design, bound=bound(problem, design.m, a))

