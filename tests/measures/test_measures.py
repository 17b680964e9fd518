"""Measures: numpy twins against the NLP objectives, identities and invariances."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from casadi_design.measures.criteria import CRITERIA
from casadi_design.measures.measures import information_matrix, score_plan, rho_at_test_poses
from casadi_design.optimisation.nlp import build_nlp
from casadi_design.plan.sampling import random_plan
from casadi_design.optimisation.solve import solve_design
from tests.conftest import build, paper_raw

REL = 1e-9


def _random_plan_B(paper, m, seed):
    Q, F = random_plan(paper, m, np.random.default_rng(seed))
    return Q, F, np.array([paper.model.B_numeric(q, f) for q, f in zip(Q, F)])


def test_one_criterion_registry():
    """Seed ids are distinct and fixed (adding a criterion never moves another's starts); the
    scores, columns and row labels of the criteria are distinct."""
    assert [c.seed_id for c in CRITERIA.values()] == list(range(len(CRITERIA)))
    for field in ("score", "column", "row", "legend"):
        assert len({getattr(c, field) for c in CRITERIA.values()}) == len(CRITERIA), field


def test_same_optimum_is_relative():
    """Two UR10 test-pose optima 0.01965 and 0.02015 mm are different optima (2.5 %)."""
    tp, D = CRITERIA["test-pose"], CRITERIA["D"]
    assert not tp.same_optimum(0.02015e-3, 0.01965e-3)
    assert tp.same_optimum(0.01965e-3 * (1 + 1e-7), 0.01965e-3)
    assert D.same_optimum(-40.0 + 1e-7, -40.0) and not D.same_optimum(-40.0 + 1e-3, -40.0)


def test_M_symmetric_psd_and_rho_formula(paper):
    B0 = paper.B0
    _, _, B = _random_plan_B(paper, 3, 0)
    M = information_matrix(B)
    np.testing.assert_allclose(M, M.T)
    assert np.all(np.linalg.eigvalsh(M) > 0)
    direct = [paper.sigma_m**2 * np.trace(b @ np.linalg.inv(M) @ b.T) for b in B0]
    np.testing.assert_allclose(rho_at_test_poses(M, B0, paper.sigma_m), direct, rtol=REL)


@pytest.mark.parametrize("criterion", list(CRITERIA))
def test_nlp_objective_equals_numpy_twin(paper, criterion):
    B0 = paper.B0
    r = 8.0
    nlp = build_nlp(paper, criterion, 3, power=r)
    Q, F, B = _random_plan_B(paper, 3, 1)
    x0 = nlp.start(Q, F)
    f, g = (np.asarray(v, dtype=float).ravel() for v in nlp.oracle(x0, []))
    sc = score_plan(B, B0, paper.sigma_m)
    c, L = nlp.scale, paper.model.L
    if criterion == "test-pose":
        np.testing.assert_allclose(np.sqrt((g[: B0.shape[0]] + f)) * paper.sigma_m, sc.rms_error_m, rtol=REL)
    else:
        lam = c * np.linalg.eigvalsh(information_matrix(B))
        log_mean = {p: np.log(np.mean(lam**p)) / p for p in (r, -r)}  # the surrogates
        expected = {"D": -(sc.value("D") + L * np.log(c)), "A": sc.value("A") / c, "T": -c * sc.value("T"),
                    "E": -log_mean[-r], "condition": log_mean[r] - log_mean[-r],
                    "I": np.mean((sc.rms_error_m / paper.sigma_m) ** 2)}
        assert f[0] == pytest.approx(expected[criterion], rel=REL)


def test_epigraph_reaches_its_value_at_the_optimum(paper):
    """At the optimum t = max_j rho_j / sigma^2; the scores' s_L and s_1/s_L are those of M."""
    d = solve_design(paper, "test-pose", 2, starts=4)
    nlp = build_nlp(paper, "test-pose", 2)
    B = np.array([paper.model.B_numeric(q, f) for q, f in zip(d.Q, d.F)])
    lam = np.linalg.eigvalsh(information_matrix(B))
    assert d.scores.value("E") ** 2 == pytest.approx(lam[0], rel=REL)
    assert d.scores.value("condition") == pytest.approx(np.sqrt(lam[-1] / lam[0]), rel=REL)
    # re-solve from the optimum: the epigraph variable takes the criterion's value
    from casadi_design.optimisation.solve import make_solver

    sol = make_solver(paper, nlp)(x0=nlp.start(d.Q, d.F), lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg)
    Q, F = (np.asarray(v) for v in nlp.plan(sol["x"]))
    sc = score_plan(np.array([paper.model.B_numeric(q, g) for q, g in zip(Q, F)]),
                    paper.B0, paper.sigma_m)
    assert float(sol["f"]) == pytest.approx((sc.max_rms_error_m / paper.sigma_m) ** 2, rel=1e-6)


def test_observability_indices_from_svd(paper):
    _, _, B = _random_plan_B(paper, 4, 2)
    s = np.linalg.svd(B.reshape(-1, B.shape[-1]), compute_uv=False)
    o = score_plan(B, paper.B0, paper.sigma_m).observability
    L, m = len(s), 4
    assert o["O1"] == pytest.approx(np.prod(s) ** (1 / L) / np.sqrt(m), rel=REL)
    assert o["O2"] == pytest.approx(s[-1] / s[0], rel=REL)
    assert o["O3"] == pytest.approx(s[-1], rel=REL)
    assert o["O4"] == pytest.approx(s[-1] ** 2 / s[0], rel=REL)
    assert o["O5"] == pytest.approx(1 / np.sum(1 / s), rel=REL)


def test_log_det_scales_with_L_log_c(paper):
    _, _, B = _random_plan_B(paper, 2, 3)
    B0 = paper.B0
    c = 7.3
    a, b = score_plan(B, B0, 1.0), score_plan(np.sqrt(c) * B, B0, 1.0)
    assert b.value("D") - a.value("D") == pytest.approx(2 * np.log(c), rel=REL)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.lists(st.floats(-3, 3), min_size=4, max_size=4), st.integers(0, 1000))
def test_test_pose_measure_invariant_under_reparametrisation(paper, t, seed):
    """X -> T X (B -> B T^-1) leaves rho unchanged; E changes; log det shifts by -2 log|det T|."""
    T = np.array(t).reshape(2, 2) + 4 * np.eye(2)
    assume(np.linalg.cond(T) < 100)  # a nearly singular T loses the digits the tolerances ask for
    _, _, B = _random_plan_B(paper, 2, seed)
    B0 = paper.B0
    Ti = np.linalg.inv(T)
    a, b = score_plan(B, B0, 1e-4), score_plan(B @ Ti, B0 @ Ti, 1e-4)
    np.testing.assert_allclose(b.rms_error_m, a.rms_error_m, rtol=1e-7)
    assert b.value("D") == pytest.approx(a.value("D") - 2 * np.log(abs(np.linalg.det(T))), rel=1e-7, abs=1e-7)


def test_E_is_not_invariant_under_reparametrisation(paper):
    """Under X -> T X the ranking of plans by E changes (k2 in other units), not by test-pose."""
    B0 = paper.B0
    Ti = np.linalg.inv(np.diag([1.0, 10.0]))
    plans = [_random_plan_B(paper, 2, seed)[2] for seed in range(20)]
    E = np.array([score_plan(B, B0, 1.0).value("E") for B in plans])
    E_T = np.array([score_plan(B @ Ti, B0 @ Ti, 1.0).value("E") for B in plans])
    rms = np.array([score_plan(B, B0, 1.0).max_rms_error_m for B in plans])
    rms_T = np.array([score_plan(B @ Ti, B0 @ Ti, 1.0).max_rms_error_m for B in plans])
    assert np.argsort(E).tolist() != np.argsort(E_T).tolist()
    assert np.argsort(rms).tolist() == np.argsort(rms_T).tolist()


def test_closed_form_two_offsets_one_pose():
    """Planar 2R, joint offsets only, one pose: det M = (l1 l2 sin q2)^2, largest at q2 = +/- pi/2."""
    raw = paper_raw()
    raw["calibration"] = {"case": "geometric", "parameters": ["joint1.offset", "joint2.offset"]}
    del raw["experiments"]["force"]
    raw["test_poses"].pop("force_N")
    raw["experiments"]["m"] = 1
    problem = build(raw)
    d = solve_design(problem, "D", 1, starts=5)
    assert abs(np.sin(d.Q[0, 1])) == pytest.approx(1.0, abs=1e-6)
    assert d.scores.value("D") == pytest.approx(2 * np.log(0.6 * 0.4), rel=1e-8)
