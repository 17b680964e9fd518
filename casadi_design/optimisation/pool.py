"""Plans chosen from postures the user already has (``--candidates``): exchange over a pool.

Given a pool of k feasible experiments (taught by hand, known safe, or measured) with
information ``A_i = B_i^T B_i``, a plan of m of them (each at most once) has ``M = M_held +
sum_{i in S} A_i``. Every candidate is priced at once by the pool engine
(:class:`~casadi_design.optimisation.engine.PoolEngine`: low-rank updates of the plan's
``M^-1``; with the problem's field, the bordered kriging of
:class:`~casadi_design.optimisation.field_pool.FieldPool`). The choice:

1. starts: the greedy plan (one experiment at a time, the one that improves the criterion most;
   while M is singular, the one that raises ``log det(M + eps I)`` most), the m heaviest
   postures of the pool's approximate design, :data:`POOL_ROUNDED` plans drawn from its
   weights, and ``starts`` random subsets (seeded by the problem's seed, the criterion and m);
2. exchange (Cook and Nachtsheim's modified Fedorov exchange): each position of the plan in turn
   takes the swap that improves the criterion most, until a pass swaps nothing; a criterion with
   a smooth surrogate (test-pose: the p-mean of rho) climbs it first;
3. :data:`POOL_PERTURBED` perturbations of the best plan so far (at most
   :data:`PERTURBED_PER_START` per seeded start), each exchanged (iterated local search);
4. the best plan over the starts, scored as any plan (:func:`~casadi_design.optimisation.solve.plan_scores`).

The bound is the pool's relaxation with its certificate
(:func:`casadi_design.optimisation.bound.pool_design`), each posture at most once (weights at
most 1/m): priced over the whole pool, it is exact and bounds every choice of m distinct
postures from the pool, not every plan of the robot.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..cell.cell import clearances
from ..errors import ProblemError
from ..measures.criteria import BOUND_CRITERIA, CRITERIA, PlanSpectrum
from ..measures.field import field_measure
from ..measures.measures import Scores
from ..plan.design import EXCHANGE_ENDED, Design, StartRecord
from ..plan.rules import START_MARGIN_M, plan_violations
from ..plan.sampling import random_plan
from ..problem.build import Problem
from .bound import bound, pool_design
from .field_pool import KrigingState, field_pool
from .engine import PlanState, PoolEngine, key, score
from .ipopt import QUIET, ipopt_call
from .nlp import build_nlp
from .solve import plan_scores, start_rng

#: Starts drawn from the pool's approximate design: m distinct postures, each drawn with
#: probability by its weight (plus :data:`POOL_FLOOR` of the mean weight, so that any posture
#: may be drawn), then exchanged. On IPA's pool of 500 (m = 20, test-pose) the best of 20 such
#: starts ends 3.5 % from the pool's bound, of 6 greedy and seeded ones 4.7 %.
POOL_ROUNDED = 8
POOL_FLOOR = 0.01
ROUNDED_POOL = "plan drawn from the pool's approximate design"
#: Perturbations of the best plan so far (iterated local search): :data:`PERTURBED_SHARE` of
#: its postures replaced at random, then exchanged; the better plan is kept. The exchange ends
#: in a plan no single swap improves; these escape it (on the pool of 500 above, 40 of them
#: take the best plan from 3.5 % to 2.9 % of the bound; m = 30: 1.6 % to 1.5 %).
POOL_PERTURBED = 24
#: ... and at most this many per seeded start asked for (``--starts``: a search of one start
#: perturbs 6 times).
PERTURBED_PER_START = 6
PERTURBED_SHARE = 0.2
PERTURBED = "best plan so far, perturbed"
#: The power of the smooth surrogate the exchange climbs first (test-pose: the 8-mean of rho,
#: :attr:`~casadi_design.measures.criteria.Criterion.smoothed`). From 10 random starts on IPA's
#: pool of 500 (m = 20) the exchange ends at best 4.8 % from the pool's bound on the max alone,
#: 2.9 % after the 8-mean (32: 3.8 %); m = 30: 2.9 % and 1.7 %.
POOL_POWER = 8.0
#: Regularisation of the greedy steps while M is singular, relative to the pool's mean trace.
GREEDY_EPS = 1e-9
#: Exchange passes of one start at most.
MAX_PASSES = 200
#: A swap is taken when it improves the criterion's score by more than this fraction of it: the
#: exchange does not creep through swaps that move a max error by a nanometre.
EXCHANGE_RTOL = 1e-6


def _scores(problem: Problem, pool: tuple, S: list[int],
            criterion: str | None = None) -> Scores:
    """The scores of the postures ``S`` of the pool ``(Q, F, B, kriging, B0)`` (their B
    precomputed, (k, d, L), their :class:`~casadi_design.optimisation.field_pool.FieldPool` where
    the search weighs the field, else None, and the test poses' rows):
    :func:`~casadi_design.optimisation.solve.plan_scores`; for the search by ``criterion`` (None:
    every score as reported) the field only where it weighs it."""
    Q, F, B, _, B0 = pool
    return plan_scores(problem, Q[S], F[S], B[S], criterion is None or field_measure(problem, criterion), B0)


def _field_keys(problem: Problem, criterion: str, pool: tuple, plan: list[int], a: int | None,
                cands: np.ndarray | None, power: float | None = None, state: KrigingState | None = None) -> np.ndarray:
    """The score key of the plan less its position ``a`` (None: the whole plan) plus each
    posture of ``cands`` (pool indices; None: every posture) for a criterion that weighs the
    problem's field: every plan at once by bordering the kriging system of ``state`` (that of
    ``plan``; None: made here) (:class:`~casadi_design.optimisation.field_pool.FieldPool`),
    scored by the criterion's own score of rho (with ``power``: its smooth surrogate)."""
    kriging = pool[3]
    if not kriging.h and len(plan) == (a is not None):  # a plan's first posture, no held poses: each on its own
        return np.array([_plan_key(problem, criterion, pool, [c], power)
                         for c in (range(len(pool[0])) if cands is None else cands)])
    rho = kriging.priced(kriging.state(plan) if state is None else state, a, cands)
    finite = np.all(np.isfinite(rho), axis=1)
    spectrum = PlanSpectrum(None, None, np.where(finite[:, None], rho, 1.0), None, finite)
    return np.where(finite, key(criterion, score(criterion, spectrum, power)), np.inf)


def _plan_key(problem: Problem, criterion: str, pool: tuple, S: list[int], power: float | None = None) -> float:
    """The score key of the plan ``S`` as the search sees it (:func:`_scores`); with ``power``
    the criterion's smooth surrogate of its rho."""
    scores = _scores(problem, pool, S, criterion)
    if power is None or not scores.identifiable:
        return float(key(criterion, scores.value(criterion)))
    return float(key(criterion, score(criterion, PlanSpectrum(None, None, scores.rms_error_m**2, None, True),
                                      power)))


def _eps(engine: PoolEngine) -> float:
    """The regularisation of a singular plan's log det: :data:`GREEDY_EPS` of the pool's mean
    trace per parameter."""
    return GREEDY_EPS * float(np.mean(engine.trace_A)) / engine.B.shape[2]


def _greedy(problem: Problem, criterion: str, m: int, pool: tuple, engine: PoolEngine) -> list[int]:
    """m postures one at a time, each the one that improves the criterion most (while M is
    singular: ``log det(M + eps I)``), priced by the engine."""
    reads, field = CRITERIA[criterion].reads, field_measure(problem, criterion)
    free = np.ones(len(engine.B), dtype=bool)
    chosen: list[int] = []
    for _ in range(m):
        cands = np.flatnonzero(free)
        state = engine.state(chosen, reads)
        if state is not None and state.regular:
            keys = (_field_keys(problem, criterion, pool, chosen, None, cands) if field
                    else engine.keys(criterion, state, cands))
        else:
            keys = -engine.priced(engine.state(chosen, "log_det", _eps(engine)), cands, "log_det").log_det
        best = int(cands[int(np.argmin(keys))])
        chosen.append(best)
        free[best] = False
    return chosen


def _regular_state(engine: PoolEngine, S: list[int], reads: str) -> PlanState | None:
    """The engine's state of the plan ``S``, None when its M is singular."""
    state = engine.state(S, reads)
    return state if state is not None and state.regular else None


def _passes(S: list[int], chosen: np.ndarray, state: PlanState | None, restate: Callable, keys_at: Callable,
            current: float, stop: Callable, budget: int) -> tuple[int, int]:
    """Passes of the modified exchange over the plan ``S`` (in place; ``chosen`` its mask over
    the pool): each position a in turn takes the posture of the least ``keys_at(state, a)`` (a
    key per posture of the pool) when it is below ``current`` by more than
    :data:`EXCHANGE_RTOL`, and ``restate(S)`` is the state after a swap (None: M is singular once
    factored, and the next best posture is tried instead); until a pass swaps
    nothing, ``stop(state)`` holds when a pass would start, or ``budget`` passes. A pass without
    a swap ends at the position of the last swap: that position and those after it were priced
    with this plan and kept it, so the rest of the pass would swap nothing. The passes and the
    swaps."""
    passes = swaps = 0
    last = None  # the position of the last swap
    while passes < budget and not stop(state):
        passes += 1
        swapped = False
        for a in range(len(S)):
            if a == last and not swapped:  # no swap since a's: a and the positions after it were priced
                return passes, swaps      # with this plan and kept it (a keeps the best of its rest)
            keys = np.where(chosen, np.inf, keys_at(state, a))
            i = int(np.argmin(keys))
            while keys[i] < current - EXCHANGE_RTOL * abs(current):
                old, S[a] = S[a], i
                new = restate(S)
                if new is not None:
                    chosen[old], chosen[i] = False, True
                    current, swapped, swaps, last, state = float(keys[i]), True, swaps + 1, a, new
                    break
                # priced by a low-rank update, singular once factored (a condition number near 1 / eps:
                # the sweep of problems/panda_ball_socket.toml): not taken, the next best is tried
                S[a], keys[i] = old, np.inf
                i = int(np.argmin(keys))
        if not swapped:
            break
    return passes, swaps


def _exchange(problem: Problem, criterion: str, S: list[int], pool: tuple,
              engine: PoolEngine) -> tuple[list[int], float, int, int]:
    """The modified exchange (Cook and Nachtsheim 1980) from the subset ``S`` (:func:`_passes`),
    every candidate of a position priced at once (:class:`~casadi_design.optimisation.engine.PoolEngine`,
    or for the field the bordered kriging). A singular start first climbs the regularised
    ``log det(M + eps I)`` until M is regular; a criterion with a smooth surrogate climbs it
    (power :data:`POOL_POWER`) before its own score. The subset, its score key, the passes and
    the swaps."""
    S, chosen = [int(i) for i in S], np.zeros(len(engine.B), dtype=bool)
    chosen[S] = True
    reads, field = CRITERIA[criterion].reads, field_measure(problem, criterion)

    def regularised(S: list[int]) -> PlanState:  # its ``regular`` is M's own, without eps
        return engine.state(S, "log_det", _eps(engine))

    state = regularised(S)
    passes, swaps = _passes(S, chosen, state, regularised,
                            lambda state, a: -engine.priced(state, None, "log_det", S[a]).log_det,
                            -state.log_det, lambda state: state.regular, MAX_PASSES)

    def field_keys(state: KrigingState, a: int, power: float | None) -> np.ndarray:
        return _field_keys(problem, criterion, pool, S, a, None, power, state)  # the plan's own: _passes masks them

    for power in ((POOL_POWER,) if CRITERIA[criterion].smoothed else ()) + (None,):
        state = _regular_state(engine, S, reads)
        if field and state is not None:
            state = pool[3].state(S)
        done = _passes(S, chosen, state, pool[3].state if field else (lambda S: engine.state(S, reads)),
                       (lambda state, a, power=power: field_keys(state, a, power)) if field else
                       (lambda state, a, power=power: engine.keys(criterion, state, None, S[a], power)),
                       _plan_key(problem, criterion, pool, S, power), lambda state: state is None,
                       MAX_PASSES - passes)
        passes, swaps = passes + done[0], swaps + done[1]
    return S, _plan_key(problem, criterion, pool, S), passes, swaps


def _perturbed(S: list[int], k: int, rng: np.random.Generator) -> list[int]:
    """The plan ``S`` with :data:`PERTURBED_SHARE` of its postures (at least 2, at most all
    of those left out of it) replaced by random ones of the pool of k."""
    out = np.setdiff1d(np.arange(k), S)
    n = min(max(2, round(PERTURBED_SHARE * len(S))), len(out), len(S))
    S = list(S)
    for a, c in zip(rng.choice(len(S), size=n, replace=False), rng.choice(out, size=n, replace=False)):
        S[a] = int(c)
    return S


def kept_postures(problem: Problem, Q: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, int, list[str]]:
    """Which postures of a pool ``Q`` (k, n), rad, ``F`` (k, nF), N a plan may use, shape (k,)
    bool: each posture once (the first of its repeats: a plan measures it at most once) and
    only those that keep every rule of one experiment
    (:func:`casadi_design.plan.rules.plan_violations`: limits less the margin, workspace, cell
    and meshes, load). Also the number of repeats left out, and why each posture that breaks
    a rule does (its first broken rule, "posture i: ...")."""
    first = np.zeros(len(Q), dtype=bool)
    first[np.unique(np.hstack([Q, F]), axis=0, return_index=True)[1]] = True
    why = [plan_violations(problem, q[None], f[None]) if once else [] for q, f, once in zip(Q, F, first)]
    return (first & np.array([not w for w in why], dtype=bool).reshape(len(Q)), int(np.sum(~first)),
            [w[0].replace("experiment 1", f"posture {i + 1}", 1) for i, w in enumerate(why) if w])


def choose_design(problem: Problem, criterion: str, m: int, Q: np.ndarray, F: np.ndarray,
                  starts: int, with_bound: bool = True, initial: tuple[tuple[str, list[int]], ...] = (),
                  rows: tuple[np.ndarray, np.ndarray] | None = None) -> Design:
    """The plan of m postures of the pool ``Q`` (k, n), rad, ``F`` (k, nF), N that is best by
    ``criterion`` (module docstring), with the pool's bound when the criterion has one. The
    pool's postures keep the problem's rules (:func:`kept_postures`). ``initial``: (origin,
    indices of m postures) exchanged first, beside the greedy plan and the others. ``rows``:
    the pool's rows and the test poses' (B (k, d, L'), B0 (s, r, L')) when they are not the
    problem's model's (an artefact's, with its placements' poses beside X; no bound then).

    Raises
    ------
    ProblemError
        A pool of fewer than m postures.
    """
    t0 = time.perf_counter()
    k = len(Q)
    if m > k:
        raise ProblemError(f"--candidates: the pool has {k} postures that keep the problem's rules, fewer than "
                           f"m = {m}; give m <= {k} or more postures")
    B, B0 = (problem.model.B_stack(Q, F), problem.B0) if rows is None else rows
    engine = PoolEngine(B, B0, problem.sigma_m, problem.M_held)
    pool = (Q, F, B, field_pool(problem, Q, F, B) if field_measure(problem, criterion) else None, B0)
    approx = (pool_design(problem, criterion, Q, F, engine.A, m) if with_bound and rows is None and
              criterion in BOUND_CRITERIA and not field_measure(problem, criterion) else None)
    rng = start_rng(problem.solver.seed, criterion, m)
    first = [*initial, ("greedy", _greedy(problem, criterion, m, pool, engine))]
    if approx is not None:
        first.append(("heaviest of the pool's approximate design", list(np.argsort(approx.weights)[::-1][:m])))
        p = approx.weights + POOL_FLOOR / k
        first += [(ROUNDED_POOL, list(rng.choice(k, size=m, replace=False, p=p / p.sum())))
                  for _ in range(POOL_ROUNDED)]
    first += [("seeded", list(rng.choice(k, size=m, replace=False))) for _ in range(starts)]
    records, best = [], None

    def run(origin: str, S: list[int]) -> None:
        nonlocal best
        S, score_key, passes, swaps = _exchange(problem, criterion, S, pool, engine)
        scores = _scores(problem, pool, S)
        records.append(StartRecord(EXCHANGE_ENDED, passes, scores.value(criterion), scores.max_rms_error_m,
                                   scores.identifiable, origin, swaps=swaps))
        if scores.identifiable and (best is None or score_key < best[0]):
            best = (score_key, sorted(S), scores, records[-1])

    for origin, S in first:
        run(origin, S)
    for _ in range(min(POOL_PERTURBED, PERTURBED_PER_START * starts) if best is not None and k > m else 0):
        run(PERTURBED, _perturbed(best[1], k, rng))
    if best is None:
        raise ProblemError(f"--candidates: no choice of {m} postures of the pool identifies the parameters; "
                           "give more varied postures or a larger m")
    _, S, scores, rec = best
    return Design(criterion, m, Q[S], F[S], scores, rec.status, tuple(records), time.perf_counter() - t0,
                  problem.solver.seed, bound=None if approx is None else bound(problem, m, approx),
                  clearances=tuple(clearances(problem.cell, Q[S])) if problem.cell else None)


#: Random feasible experiments of the pool a free design of a criterion that weighs the field is
#: exchanged over (:func:`field_design`), beside the campaign's plans' experiments.
FIELD_POOL = 300
#: The NLP with the field (:mod:`~casadi_design.optimisation.field_nlp`) from the exchange's plan:
#: each joint within :data:`FIELD_NLP_BOX` of the field's shortest correlation length of that
#: plan, for at most :data:`FIELD_NLP_ITERATIONS` IPOPT iterations. The kriging variance is rugged
#: on the scale of the lengths: on the paper's arm with a field of 0.5 rad (m = 3) IPOPT from the
#: exchange's plan without the box leaves the load rows' bounds and ends worse; within a quarter
#: of the length it lowers the max error by 1.5 %. IPA's UR10 with 100 poses held and m = 10
#: (``scripts/field_benchmark.py``): 53 iterations, 10 s, the exchange's 0.1596 mm to 0.1571 mm.
FIELD_NLP_BOX = 0.25
FIELD_NLP_ITERATIONS = 300
#: ... and it ends, beside IPOPT's own convergence, when for 5 iterations its error is below 1e-3
#: and the criterion moves by less than 1e-6 (relative): the limited-memory Hessian reaches the
#: optimum's value long before its multipliers (paper's arm: 191 iterations, 400 not enough for
#: the default tolerance).
FIELD_NLP_OPTIONS = {"ipopt.acceptable_tol": 1e-3, "ipopt.acceptable_obj_change_tol": 1e-6, "ipopt.acceptable_iter": 5}
FIELD_NLP = "NLP with the field, from the exchange's plan"


def field_design(problem: Problem, design: Design, others: list[Design], starts: int) -> Design:
    """A free (continuous) design of a criterion that weighs the problem's field
    (:func:`~casadi_design.measures.field.field_measure`): the NLP optimised the criterion
    without the field (the reduced NLP is a function of M); the plan is then exchanged, with
    the field, over a pool of its own experiments, those of the campaign's ``others`` plans,
    ``FIELD_POOL`` random feasible experiments (seeded) and, without loads, the test poses that
    keep the rules (where the field rewards measuring), from the NLP's plan first; the better of
    the two goes to the NLP with the field (:func:`field_nlp`), whose plan is kept where IPOPT
    converged to a plan that keeps the rules and is better. The best by the criterion with the
    field; its starts record all three."""
    rng = start_rng(problem.solver.seed, design.criterion, design.m)
    Qr, Fr = random_plan(problem, FIELD_POOL, rng)
    Qs = [design.Q, *(d.Q for d in others), Qr]
    Fs = [design.F, *(d.F for d in others), Fr]
    if problem.model.nF == 0:
        Qs.append(problem.test_poses.q)
        Fs.append(np.zeros((problem.test_poses.s, 0)))
    Q, F = np.vstack(Qs), np.vstack(Fs)
    ok, _, _ = kept_postures(problem, Q, F)
    ok[:design.m] = True  # the NLP's plan keeps the rules (it was checked)
    keep = np.flatnonzero(ok)
    chosen = choose_design(problem, design.criterion, design.m, Q[keep], F[keep], starts, with_bound=False,
                           initial=(("the NLP's plan", list(range(design.m))),))
    crit = CRITERIA[design.criterion]
    starts_of = design.starts + tuple(replace(r, origin=f"exchange with the field: {r.origin}") for r in chosen.starts)
    best = (chosen if crit.better(chosen.scores.value(design.criterion), design.scores.value(design.criterion))
            else design)
    best = replace(best, wall_s=design.wall_s + chosen.wall_s)  # the NLP's and the exchange's
    t0 = time.perf_counter()
    rec, Qn, Fn, scores = field_nlp(problem, best)
    starts_of += (rec,)
    if rec.converged and crit.better(rec.value, best.scores.value(design.criterion)):
        best = replace(best, Q=Qn, F=Fn, scores=scores, status=rec.status,
                       clearances=tuple(clearances(problem.cell, Qn)) if problem.cell else None)
    return replace(best, starts=starts_of, wall_s=best.wall_s + time.perf_counter() - t0)


def field_nlp(problem: Problem, design: Design) -> tuple[StartRecord, np.ndarray, np.ndarray, Scores]:
    """IPOPT on the NLP of ``design``'s criterion with the problem's field (the kriging
    variance, :class:`~casadi_design.optimisation.field_nlp.FieldNLP`) from its plan, within the
    box :data:`FIELD_NLP_BOX` around it and holding the capsule rows near it: its start's record
    (feasible: its plan keeps every rule and identifies X), plan and scores."""
    Q0, F0 = design.Q, design.F
    nlp = build_nlp(problem, design.criterion, design.m, active=problem.rules.pose.near(Q0, START_MARGIN_M),
                    fixed=problem.M_held, field=True)
    x0 = nlp.start(Q0, F0)
    box, k = FIELD_NLP_BOX * min(problem.field.lengths), Q0.size
    lbx, ubx = nlp.lbx.copy(), nlp.ubx.copy()
    lbx[:k], ubx[:k] = np.maximum(lbx[:k], x0[:k] - box), np.minimum(ubx[:k], x0[:k] + box)
    solver = nlp.solver("field", {**QUIET, **FIELD_NLP_OPTIONS, "ipopt.max_iter": FIELD_NLP_ITERATIONS,
                                  "ipopt.tol": problem.solver.tol})
    with ipopt_call():
        sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=nlp.lbg, ubg=nlp.ubg)
    Q, F = (np.asarray(v, dtype=float) for v in nlp.plan(sol["x"]))
    # within the box of a plan that keeps the limits: not wrapped by whole turns, which the field's
    # kernel over the joint angles tells apart (IPA: -4.87 rad wrapped to 1.41 rad left the held poses)
    limits = problem.rules.limits
    Q = np.clip(Q, limits.lower, limits.upper)
    scores = plan_scores(problem, Q, F)
    stats = solver.stats()
    rec = StartRecord(str(stats["return_status"]), int(stats.get("iter_count", 0)), scores.value(design.criterion),
                      scores.max_rms_error_m, not plan_violations(problem, Q, F) and scores.identifiable, FIELD_NLP,
                      rows_held=len(nlp.active))
    return rec, Q, F, scores
