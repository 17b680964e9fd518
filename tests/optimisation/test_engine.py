"""The pool engine (casadi_design.optimisation.engine) against score_plan, the judge of a plan:
every criterion, additions and swaps, with information held and with a rest of the plan that is
singular; and the pool's choice and bound against enumeration on a real robot's pool."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from conftest import ROOT

from casadi_design.measures.criteria import CRITERIA
from casadi_design.measures.measures import information_matrices, information_matrix, score_plan
from casadi_design.optimisation.bound import bound, pool_design, top_mean
from casadi_design.optimisation.engine import PoolEngine, key
from casadi_design.optimisation.pool import choose_design
from casadi_design.optimisation.solve import plan_scores
from casadi_design.plan.design import EXCHANGE_ENDED
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem, load_problem
from casadi_design.problem_file.read import HeldSpec

#: Agreement of the engine's low-rank updates with score_plan's own factorisation.
RTOL = 1e-9


@pytest.fixture(scope="module")
def ur10():
    """The UR10 drilling cell (27 parameters, x y z measured, 9 test poses) and 40 random
    feasible experiments in it with their B."""
    problem = load_problem(ROOT / "problems" / "ur10_drilling.toml")
    Q, F = random_plan(problem, 40, np.random.default_rng(3))
    return problem, Q, F, problem.model.B_stack(Q, F)


def relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b) / np.abs(b)))


@pytest.mark.parametrize("held", [False, True])
def test_every_addition_and_swap_is_priced_as_score_plan_scores_it(ur10, held):
    problem, _, _, B = ur10
    M_held = information_matrix(B[30:33]) if held else None
    engine = PoolEngine(B[:30], problem.B0, problem.sigma_m, M_held)
    S = [0, 3, 5, 8, 11, 14, 17, 20, 22, 25]  # 30 rows for 27 parameters
    out = np.setdiff1d(np.arange(30), S)
    for removed in (None, S[0], S[6]):
        rest = [i for i in S if i != removed]
        judged = [score_plan(B[rest + [c]], problem.B0, problem.sigma_m, M_held) for c in out]
        for name, crit in CRITERIA.items():
            state = engine.state(S, crit.reads)
            priced = crit.score_of(engine.priced(state, out, crit.reads, removed))
            assert relative(priced, np.array([j.value(name) for j in judged])) < RTOL, (name, removed)
            keys = engine.keys(name, state, out, removed)  # the key to minimise: the score, or its negative
            assert np.array_equal(keys, key(name, priced))
            assert np.argmin(keys) == np.argmin([key(name, j.value(name)) for j in judged])


def test_a_swap_whose_rest_is_singular_is_priced_with_the_candidate_first(ur10):
    """Nine experiments give 27 rows for 27 parameters: less one, M is singular and the removed
    block of the capacitance cannot be inverted on its own; the candidate's block is eliminated
    first, and a swap that leaves M singular is not identifiable."""
    problem, Q, F, B = ur10
    engine = PoolEngine(B, problem.B0, problem.sigma_m)
    S = list(range(9))
    assert engine.state(S, "rho").regular and engine.state(S[1:], "rho") is None  # M of the rest: singular
    out = np.arange(9, 40)
    judged = [score_plan(B[S[1:] + [c]], problem.B0, problem.sigma_m) for c in out]
    for name in ("test-pose", "D", "A"):
        crit = CRITERIA[name]
        priced = engine.priced(engine.state(S, crit.reads), out, crit.reads, S[0])
        # 27 rows for 27 parameters: ill-conditioned plans (0.3 to 2.8 mm for 0.025 mm of noise)
        assert relative(crit.score_of(priced), np.array([j.value(name) for j in judged])) < 10 * RTOL, name
    # the same experiment out and in again: M is the plan's own; a copy of a chosen one: singular
    B2 = np.concatenate([B[:9], B[1:2]])
    engine2 = PoolEngine(B2, problem.B0, problem.sigma_m)
    priced = engine2.priced(engine2.state(S, "log_det"), np.array([0, 9]), "log_det", S[0])
    assert priced.identifiable[0] and not priced.identifiable[1]
    assert priced.log_det[0] == pytest.approx(plan_scores(problem, Q[:9], F[:9]).value("D"), rel=1e-12)


def test_the_top_mean_is_the_box_constrained_maximum():
    d = np.random.default_rng(0).normal(size=50)
    assert top_mean(d, 7) == pytest.approx(np.sort(d)[-7:].mean(), rel=1e-15)
    assert top_mean(d, 0) == d.max()


def test_the_choice_and_the_pool_bound_against_every_subset(ur10):
    """All 3003 plans of 10 of 14 UR10 experiments enumerated: the chosen plan is the best by
    test-pose and by D, and the pool's bound (each posture at most once) holds against it and
    is tighter than the bound that allows repeats."""
    problem, Q, F, B = ur10
    Qp, Fp = Q[:14], F[:14]
    values = {c: [] for c in ("test-pose", "D")}
    for S in itertools.combinations(range(14), 10):
        sc = plan_scores(problem, Qp[list(S)], Fp[list(S)])
        for c in values:
            values[c].append(sc.value(c))
    best = {"test-pose": min(values["test-pose"]), "D": max(values["D"])}
    A = information_matrices(B[:14])
    for c, b in best.items():
        d = choose_design(problem, c, 10, Qp, Fp, starts=2)
        assert d.scores.value(c) == pytest.approx(b, rel=1e-12)
        once, repeats = bound(problem, 10, pool_design(problem, c, Qp, Fp, A, 10)), bound(
            problem, 10, pool_design(problem, c, Qp, Fp, A))
        if c == "D":
            assert b <= once.value <= repeats.value + 1e-9
        else:
            assert repeats.value - 1e-12 <= once.value <= b
        assert d.status == EXCHANGE_ENDED and d.exchange[0] == len(d.starts)


def test_with_held_information_the_engine_s_choice_is_scored_with_it(ur10):
    problem, Q, F, _ = ur10
    held = build_problem(replace(problem.spec, held=HeldSpec(tuple(map(tuple, Q[30:33].tolist())),
                                                             tuple(map(tuple, F[30:33].tolist())))))
    d = choose_design(held, "test-pose", 8, Q[:30], F[:30], starts=1)
    whole = plan_scores(problem, np.vstack([Q[30:33], d.Q]), np.vstack([F[30:33], d.F])).max_rms_error_m
    assert d.scores.max_rms_error_m == pytest.approx(whole, rel=1e-10)
    assert d.bound.value <= d.scores.max_rms_error_m
    starts, passes, swaps = d.exchange
    assert starts == len(d.starts) and passes >= starts and swaps >= 0
