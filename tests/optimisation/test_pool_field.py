"""Plans chosen from a pool with the robot's unmodelled error as a field (issue 60): the pool's
exchange weighs the kriging variance, and on a simulated UR10 whose error field dominates the
test-pose plan with the field beats the D plan held out at the test poses."""

import dataclasses

import numpy as np
import pytest

from casadi_design.cli.identify import load_without_cell
from casadi_design.measures.field import Field, kriging_mean, kriging_rho, model_sites
from casadi_design.optimisation.pool import choose_design
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem
from casadi_design.problem_file.calibration import ModelErrorSpec
from tests.conftest import ROOT

UR10 = ROOT / "problems" / "ur10_drilling.toml"
SCALE_M, LENGTH_RAD = 2.5e-4, 0.4
JOINTS = Field(0.0, (0.2,) * 6, 2e-5, (), (3e-4, 4e-4, 3e-4, 2e-4, 2e-4, 1e-4))


def with_field(error: ModelErrorSpec):
    """The UR10 of the drilling cell (no cell: the pool is given) with the field ``error``, and a
    pool of 60 random feasible postures and 27 near the holes (within 0.1 rad of a hole's)."""
    plain = load_without_cell(str(UR10))
    spec = plain.spec
    problem = build_problem(dataclasses.replace(spec, calibration=dataclasses.replace(spec.calibration,
                                                                                      model_error=error)))
    rng = np.random.default_rng(11)
    Q, _ = random_plan(problem, 60, rng)
    near = np.repeat(problem.test_poses.q, 3, axis=0) + rng.uniform(-0.1, 0.1, size=(27, problem.robot.n))
    return problem, np.vstack([Q, near]), np.zeros((87, 0))


@pytest.fixture(scope="module")
def case():
    """A field of the base axes 10x sigma."""
    return with_field(ModelErrorSpec(SCALE_M, (LENGTH_RAD,), 0.0))


def test_all_candidates_at_once_are_each_campaign_s_kriging_variance(case):
    """FieldPool prices a plan plus each candidate as kriging_rho of that campaign: where the
    plan identifies X (Woodbury over G) and where only the candidate makes it do so."""
    from casadi_design.optimisation.field_pool import FieldPool

    problem, Q, F = case
    model = problem.model
    B = model.B_stack(Q, F)
    tp = problem.test_poses
    none = np.zeros((0,) + B.shape[1:])
    # 10 postures identify X; 8 do not (24 rows, L = 27), one candidate more may
    for rest, cands in ((list(range(10)), list(range(10, 30))), (list(range(8)), list(range(40, 87)))):
        for field in (problem.field, JOINTS):  # of the base axes, of the joint angles
            S, S0 = model_sites(field, model, np.eye(3), Q, F), model_sites(field, model, np.eye(3), tp.q, tp.F, "accuracy")
            added = FieldPool(field, problem.sigma_m, none, S[[]], B, S, problem.B0, S0).rho_added(rest, cands)
            one_by_one = np.array([kriging_rho(field, problem.sigma_m, B[rest + [c]], S[rest + [c]], problem.B0, S0)
                                   for c in cands])
            finite = np.isfinite(one_by_one)
            assert model.L == 27 and 0 < finite.sum() and np.array_equal(np.isfinite(added), finite)
            np.testing.assert_allclose(added[finite], one_by_one[finite], rtol=1e-8)


def test_the_pool_s_kriging_is_each_campaign_s_with_the_held_poses_and_prior(case):
    """FieldPool (its covariance rows kept across pricings) prices the held poses plus a plan
    plus each candidate as kriging_rho of that campaign, with a prior information, twice (the
    second time from the rows it kept) and with a row cache too small to keep them."""
    from casadi_design.optimisation import field_pool

    problem, Q, F = case
    model, tp = problem.model, problem.test_poses
    B = model.B_stack(Q, F)
    P = np.diag(np.random.default_rng(2).uniform(0.5, 2.0, model.L)) * 1e6
    held, plan, cands = list(range(4)), [4, 9, 17, 30, 55], np.arange(60, 87) - 4
    for field in (problem.field, JOINTS):
        S, S0 = model_sites(field, model, np.eye(3), Q, F), model_sites(field, model, np.eye(3), tp.q, tp.F, "accuracy")
        kriging = field_pool.FieldPool(field, problem.sigma_m, B[held], S[held], B[4:], S[4:], problem.B0, S0, P)
        rows = [held + [4 + i for i in plan] + [4 + c] for c in cands]
        one_by_one = np.array([kriging_rho(field, problem.sigma_m, B[r], S[r], problem.B0, S0, P) for r in rows])
        for _ in range(2):
            np.testing.assert_allclose(kriging.rho_added(plan, cands), one_by_one, rtol=1e-9)
        state = kriging.state(plan)
        for a in (0, 3):  # the plan less its position a (a rank-d downdate of the state's inverse)
            rest = held + [4 + i for j, i in enumerate(plan) if j != a]
            np.testing.assert_allclose(kriging.priced(state, a, cands), [
                kriging_rho(field, problem.sigma_m, B[rest + [4 + c]], S[rest + [4 + c]], problem.B0, S0, P)
                for c in cands], rtol=1e-8)
            np.testing.assert_allclose(kriging.priced(state, a)[cands], kriging.priced(state, a, cands), rtol=1e-12)
        kriging.keep = 1
        np.testing.assert_allclose(kriging.rho_added(plan[1:], cands), [
            kriging_rho(field, problem.sigma_m, B[r[:4] + r[5:]], S[r[:4] + r[5:]], problem.B0, S0, P) for r in rows],
            rtol=1e-9)
        assert len(kriging.rows) == 1

def draws(field: Field, model, Q: np.ndarray, Q0: np.ndarray, rng, k: int) -> np.ndarray:
    """``k`` draws of the field (k, poses, 3) at the measured frame of the poses ``Q`` and the
    test poses ``Q0`` (rows x, y, z of both), independent of the package's covariance: of the
    base axes one process per axis; of the joint angles one per joint, its angle error moving the
    frame by ``dp/dq`` (central differences of the model's nominal position)."""
    Qall = np.vstack([Q, Q0])
    if not field.through_joints:
        chol = np.linalg.cholesky(field.kernel(Qall, Qall) + 1e-14 * field.scale_m**2 * np.eye(len(Qall)))
        return np.einsum("ij,tjc->tic", chol, rng.normal(size=(k, len(Qall), 3)))
    h = 1e-6
    position = lambda q: np.asarray(model.position(q)).ravel()
    G = np.array([[(position(q + h * e) - position(q - h * e)) / (2 * h) for e in np.eye(len(q))] for q in Qall])
    g = np.stack([np.linalg.cholesky(s**2 * np.exp(-0.5 * ((Qall[:, None, c] - Qall[None, :, c]) / ell) ** 2)
                                     + 1e-12 * s**2 * np.eye(len(Qall))) @ rng.normal(size=(len(Qall), k))
                  for c, (s, ell) in enumerate(zip(field.angles_rad, field.lengths))], axis=2)  # (poses, k, n)
    return np.einsum("itc,ica->tia", g, G)


@pytest.mark.parametrize("error", ["base axes", "joint angles"])
def test_the_plan_with_the_field_beats_d_at_the_test_poses(case, error):
    """200 simulated robots (parameters and a draw of the field at every posture and hole, the
    tracker's noise): both plans identified alike (least squares, compensation with the field's
    kriging mean); the test-pose plan's error at the holes is below the D plan's, as its
    kriging variance says, and it measures near the holes. For a field of the base axes 10x
    sigma and an error of the joint angles (60 to 80 arcsec in the first three joints)."""
    problem, Q, F = case if error == "base axes" else with_field(ModelErrorSpec(0.0, (0.2,), 0.0, (), JOINTS.angles_rad))
    m = 12
    tp, model = problem.test_poses, problem.model
    plans = {c: choose_design(problem, c, m, Q, F, starts=1, with_bound=False) for c in ("test-pose", "D")}
    assert plans["test-pose"].bound is None  # experiments correlated by the field: no bound
    near = [int(np.sum(np.min(np.linalg.norm(d.Q[:, None] - tp.q[None], axis=2), axis=1) < 0.2)) for d in plans.values()]
    assert near[0] > near[1]
    field: Field = problem.field
    rng = np.random.default_rng(5)
    held_out = {}
    for name, d in plans.items():
        B = model.B_stack(d.Q, d.F)
        S = B.reshape(-1, model.L)
        delta = draws(field, model, d.Q, tp.q, rng, 200)
        err = []
        for t in range(200):
            X = rng.normal(size=model.L) * 1e-3
            y = S @ X + delta[t, :m].reshape(-1) + problem.sigma_m * rng.normal(size=len(S))
            Xhat = np.linalg.lstsq(S, y, rcond=None)[0]
            r = (y - S @ Xhat).reshape(m, -1)
            mean = kriging_mean(field, problem.sigma_m, r, problem.field_sites(d.Q, d.F), problem.field_test_sites)
            e = np.einsum("srl,l->sr", problem.B0, X - Xhat) + delta[t, m:] - mean
            err.append(np.sum(e**2, axis=1))
        held_out[name] = float(np.sqrt(np.mean(err)))
    assert held_out["test-pose"] < 0.8 * held_out["D"], held_out
    assert plans["test-pose"].scores.max_rms_error_m < plans["D"].scores.max_rms_error_m


def test_a_free_design_with_a_field_is_exchanged_with_it_and_has_no_bound(tmp_path, capsys):
    """solve without --candidates on the paper's arm with a field: the output says the measure
    holds it; the test-pose plan is at least as good with the field as the NLP's plan scored
    with it, D is as without the field, and test-pose has no bound."""
    import json

    from casadi_design.cli import main

    text = (ROOT / "problems" / "paper_planar_2r.toml").read_text().replace(
        '[measurement]', '[calibration.model_error]\nscale_m = 5e-4\nlength_rad = 0.5\n\n[measurement]')
    (tmp_path / "paper_field.toml").write_text(text)
    assert main(["solve", str(tmp_path / "paper_field.toml"), "--m", "3", "--criteria", "test-pose,D",
                 "--starts", "2", "--jobs", "1", "--bound-pool", "50", "--bound-steps", "1",
                 "--out", str(tmp_path / "out"), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "model error: test-pose and I weigh the robot's unmodelled error" in printed
    record = json.loads((tmp_path / "out" / "results.json").read_text())
    designs = {d["criterion"]: d for d in record["designs"]}
    tp = designs["test-pose"]
    assert tp["bound"] is None and designs["D"]["bound"] is not None
    starts = tp["solver"]["per_start"]
    nlp = [s for s in starts if not s["origin"].startswith("exchange with the field")]
    assert len(nlp) < len(starts) and any(s["origin"] == "exchange with the field: the NLP's plan" for s in starts)
    assert tp["max_rms_error_m"] <= min(s["max_rms_error_m"] for s in nlp if s["feasible"]) + 1e-15
    # then IPOPT on the NLP with the field (the kriging variance) from the exchange's plan: on this
    # smooth field (0.5 rad) it improves on the exchange, and its plan is the design's
    field_nlp = [s for s in starts if s["origin"] == "NLP with the field, from the exchange's plan"]
    exchanged = min(s["max_rms_error_m"] for s in starts if s["origin"].startswith("exchange with the field"))
    assert len(field_nlp) == 1 and field_nlp[0]["feasible"]
    assert field_nlp[0]["max_rms_error_m"] < exchanged and tp["max_rms_error_m"] == field_nlp[0]["max_rms_error_m"]


def test_the_bound_command_refuses_a_field(tmp_path, capsys):
    from casadi_design.cli import main

    text = (ROOT / "problems" / "paper_planar_2r.toml").read_text().replace(
        '[measurement]', '[calibration.model_error]\nscale_m = 5e-4\nlength_rad = 0.5\n\n[measurement]')
    (tmp_path / "paper_field.toml").write_text(text)
    assert main(["bound", str(tmp_path / "paper_field.toml"), "--m", "3", "--jobs", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not hold; bound the paper's measure without the field" in err


def test_the_nlp_with_the_field_keeps_its_plan_s_turns():
    """The NLP with the field refines a plan within a box of the field's length and returns it
    as it is: a periodic joint's angle past pi is not wrapped by a whole turn, which the kernel
    over the joint angles tells apart (the same pose, another angle of the gears)."""
    from casadi_design.optimisation.pool import FIELD_NLP_BOX, field_nlp
    from casadi_design.optimisation.solve import plan_scores
    from casadi_design.plan.design import Design

    problem, Q, F = with_field(ModelErrorSpec(0.0, (0.2,), 0.0, (), JOINTS.angles_rad))
    limits = problem.rules.limits
    assert limits.periodic[0] and limits.upper[0] - limits.lower[0] > 2 * np.pi
    Q = Q[:10].copy()
    q, lower, upper = Q[:, 0].copy(), limits.lower[0], limits.upper[0]
    Q[:, 0] = np.where(q - 2 * np.pi >= lower, q - 2 * np.pi, np.where(q + 2 * np.pi <= upper, q + 2 * np.pi, q))
    assert np.sum(np.abs(Q[:, 0] - q) > np.pi) >= 8  # most on their other turn, past pi from the middle
    F = F[:10]
    scores = plan_scores(problem, Q, F)
    rec, Qn, Fn, after = field_nlp(problem, Design("test-pose", 10, Q, F, scores, "start", (), 0.0, 1))
    assert np.max(np.abs(Qn - Q)) <= FIELD_NLP_BOX * min(problem.field.lengths) + 1e-6  # IPOPT relaxes bounds by 1e-8
    assert rec.converged and after.max_rms_error_m <= scores.max_rms_error_m
