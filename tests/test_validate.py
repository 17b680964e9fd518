"""Virtual calibration: the predicted sqrt(rho) against simulated calibrations on the nonlinear model."""

import json
import time

import numpy as np
import pytest

from casadi_design.problem import load_problem
from casadi_design.results import write_results
from casadi_design.robots import frame_jacobian, frame_placement
from casadi_design.solve import solve_design
from casadi_design.validate import (
    ErrorSpreads,
    chi2_quantile,
    compensate,
    draw_true_parameters,
    evaluate,
    identify_linear,
    identify_nonlinear,
    linearisation_study,
    nonlinear_model,
    plan_matrices,
    plans_from_designs,
    rankings,
    rms_interval,
    validate,
)
from casadi_design.validate import main
from tests.conftest import ROOT, build, paper_raw

GEOMETRIC = ROOT / "problems" / "planar_2r_geometric.toml"


def solve_all(problem):
    return [solve_design(problem, c, m) for m in problem.m_values for c in problem.criteria]


@pytest.fixture(scope="module")
def paper_designs(paper):
    return solve_all(paper)


@pytest.fixture(scope="module")
def geometric():
    return load_problem(GEOMETRIC)


@pytest.fixture(scope="module")
def geometric_plans(geometric):
    return plans_from_designs(solve_all(geometric))


def both_problem():
    """The paper's arm with joint offsets, link 1 length and compliances identified together."""
    raw = paper_raw()
    raw["calibration"]["case"] = "both"
    raw["calibration"]["parameters"] = ["joint1.offset", "joint2.offset", "joint2.tx"]
    raw["experiments"]["m"] = [3]
    return build(raw)


@pytest.mark.parametrize("which", ["paper", "geometric", "both"])
def test_nonlinear_model_linearises_to_B(which, request):
    """d y / d X at X = 0 (central differences of the nonlinear model) equals B(q, F)."""
    problem = {"paper": lambda: request.getfixturevalue("paper"),
               "geometric": lambda: request.getfixturevalue("geometric"), "both": both_problem}[which]()
    model, nl = problem.model, nonlinear_model(problem.model)
    rng = np.random.default_rng(3)
    q = rng.uniform(-2.5, 2.5, (4, model.n))
    F = rng.normal(0.0, 100.0, (4, model.nF))
    ref = evaluate(nl.pose, q, F, np.zeros((4, model.L)))[0][:, :, 0]
    scale = np.array([1e-6 if n.startswith("k.") else 1e-3 for n in model.parameter_names])
    for i in range(model.L):
        h = np.zeros((4, model.L))
        h[:, i] = 1e-3 * scale[i]
        up, down = (evaluate(nl.measurement, q, F, d, ref)[0] for d in (h, -h))
        dy = (up - down) / (2 * h[0, i])
        # B is written for the scaled parameters c * X: its physical columns are B * c
        B = np.array([model.B_numeric(qi, Fi)[:, i] * model.column_scale[i] for qi, Fi in zip(q, F)])
        np.testing.assert_allclose(dy[:, :, 0], B, rtol=1e-6, atol=1e-9 * np.max(np.abs(B)))


def test_deflection_is_the_static_equilibrium_of_pinocchio(paper):
    """The deflected pose solves dq = diag(k) J(q + dq)^T W (Pinocchio's Jacobian), and with a
    soft arm it differs visibly from the linear A k."""
    model, nl, robot = paper.model, nonlinear_model(paper.model), paper.robot
    q, F, k = np.array([0.7, -1.9]), np.array([60.0, -80.0]), np.array([1e-4, 2e-4])
    dq = np.zeros(2)
    for _ in range(50):
        dq = k * (frame_jacobian(robot, q + dq)[:2, :].T @ F)
    expected = frame_placement(robot, q + dq).translation
    p = evaluate(nl.pose, q[None], F[None], k[None])[0][0, 9:12, 0]
    np.testing.assert_allclose(p, expected, atol=1e-12)
    linear = frame_placement(robot, q).translation[:2] + model.B_numeric(q, F) @ k
    assert np.linalg.norm(p[:2] - linear) > 1e-6


def test_gauss_newton_recovers_large_errors_where_one_linear_step_does_not(geometric, geometric_plans):
    plan = next(p for p in geometric_plans if p.m == 4)
    model, nl = geometric.model, nonlinear_model(geometric.model)
    X_true = draw_true_parameters(model, ErrorSpreads(length_m=0.02, angle_rad=np.radians(2.0)), 50,
                                  np.random.default_rng(0))
    ref = evaluate(nl.pose, plan.Q, plan.F, np.zeros((4, model.L)))[0][:, :, 0]
    y = evaluate(nl.measurement, np.tile(plan.Q, (50, 1)), np.tile(plan.F, (50, 1)),
                 np.repeat(X_true, 4, axis=0), np.tile(ref, (50, 1)))[0].reshape(50, -1)
    X_hat, report = identify_nonlinear(nl, plan.Q, plan.F, ref, y, geometric.sigma_m)
    assert report.non_converged == 0 and report.iterations > 2
    np.testing.assert_allclose(X_hat, X_true, atol=1e-6)  # LM_TOL sigma = 1e-7 m in y
    B, _ = plan_matrices(geometric, plan)
    X_lin, _ = identify_linear(B.reshape(-1, model.L), y)
    X_lin = X_lin / model.column_scale
    assert np.max(np.abs(X_lin - X_true)) > 1e-4
    _, stopped = identify_nonlinear(nl, plan.Q, plan.F, ref, y, geometric.sigma_m, max_iterations=1)
    assert stopped.non_converged == 50


def test_compensation_with_the_true_model_leaves_no_error(geometric):
    """Exact parameters: the compensated true robot hits every target; X = 0 leaves the raw error."""
    model, nl, tp = geometric.model, nonlinear_model(geometric.model), geometric.test_poses
    X_true = np.tile(draw_true_parameters(model, ErrorSpreads(), 1, np.random.default_rng(1)), (tp.s, 1))
    target = evaluate(nl.pose, tp.q, tp.F, np.zeros((tp.s, model.L)))[0][:, :, 0]
    qc, done, miss = compensate(nl, tp.q, tp.F, target, X_true, geometric.sigma_m)
    assert done.all() and miss <= 1e-6 * geometric.sigma_m
    e = evaluate(nl.accuracy, qc, tp.F, X_true, target)[0][:, :, 0]
    assert np.max(np.linalg.norm(e, axis=1)) == pytest.approx(miss, rel=1e-6)
    raw = np.linalg.norm(evaluate(nl.accuracy, tp.q, tp.F, X_true, target)[0][:, :, 0], axis=1)
    B0 = np.array([model.B_numeric(q, F, accuracy=True) for q, F in zip(tp.q, tp.F)])
    np.testing.assert_allclose(raw, np.linalg.norm(B0 @ (model.column_scale * X_true[0]), axis=1), rtol=0.02)
    assert np.min(raw) > 1e-4


@pytest.mark.parametrize("p, dof, value", [(0.975, 100, 129.5612), (0.025, 100, 74.2219),
                                           (0.975, 1000, 1089.531), (0.025, 1000, 914.257)])
def test_chi2_quantile_against_tables(p, dof, value):
    assert chi2_quantile(p, dof) == pytest.approx(value, rel=1e-4)


def test_rms_interval_covers_the_true_rms_95_percent_of_the_time():
    """Gaussian errors of a rank-2 covariance (nu between 1 and 2), 2000 draws per interval."""
    rng = np.random.default_rng(7)
    C = np.array([[1.0, 0.6], [0.6, 0.5]])
    nu = np.trace(C) ** 2 / np.trace(C @ C)
    e = rng.multivariate_normal(np.zeros(2), C, size=(1000, 2000))
    low, high = rms_interval(np.mean(np.sum(e**2, axis=2), axis=1), np.full(1000, nu), 2000)
    covered = np.mean((low <= np.sqrt(np.trace(C))) & (np.sqrt(np.trace(C)) <= high))
    assert 0.93 <= covered <= 0.97


def test_paper_example_agrees_within_5_percent_at_every_node(paper, paper_designs):
    """Table 4's six plans, 2000 virtual calibrations each on the nonlinear compliant arm."""
    t0 = time.perf_counter()
    v = validate(paper, plans_from_designs(paper_designs), trials=2000, seed=0)
    print(f"\npaper example, 6 plans x 2000 trials: {time.perf_counter() - t0:.2f} s")
    assert len(v.plans) == 6
    for p, d in zip(v.plans, paper_designs):
        np.testing.assert_allclose(p.predicted_rms_m, d.scores.rms_error_m, rtol=1e-9)
        assert p.worst_relative_error < 0.05, (p.plan.criterion, p.plan.m, p.worst_relative_error)
        assert np.all(p.ci_low_m < p.empirical_rms_m) and np.all(p.empirical_rms_m < p.ci_high_m)
        # the interval's half-width is the sampling error of 2000 trials: ~1.96 sqrt(2 / (N nu)) / 2
        half = (p.ci_high_m - p.ci_low_m) / (2 * p.empirical_rms_m)
        np.testing.assert_allclose(half, 1.96 * np.sqrt(2 / (2000 * p.dof)) / 2, rtol=0.05)
        assert p.identification.method == "linear least squares"
        assert p.compensation_failed == 0
    for m, r in rankings(v).items():
        assert r["by_simulation"] == r["by_measure"] == ["test-pose", "D", "E"], m


def test_geometric_case_agrees_within_10_percent_at_every_node(geometric, geometric_plans):
    v = validate(geometric, geometric_plans, trials=2000, seed=0)
    assert [(p.plan.criterion, p.plan.m) for p in v.plans] == [
        (c, m) for m in (2, 4) for c in ("test-pose", "D", "E")]
    for p in v.plans:
        assert p.worst_relative_error < 0.10, (p.plan.criterion, p.plan.m, p.worst_relative_error)
        assert p.identification.method == "Levenberg-Marquardt"
        assert p.identification.non_converged == 0 and p.compensation_failed == 0


def test_linearisation_breaks_down_for_large_errors(geometric, geometric_plans):
    """Spreads x 400 (20 cm, 20 deg): the identified arms cannot reach part of the line and the
    simulated error departs from sqrt(rho) by more than 10 %; at x 1 neither happens."""
    (_, small), (_, large) = linearisation_study(geometric, geometric_plans, [1.0, 400.0], trials=300)
    assert all(p.compensation_failed == 0 and p.worst_relative_error < 0.1 for p in small.plans)
    assert all(p.compensation_failed > 0 for p in large.plans)
    assert max(p.worst_relative_error for p in large.plans) > 0.1


def test_script_writes_validation_json_and_figure(tmp_path, paper, paper_designs, capsys):
    results = tmp_path / "results.json"
    write_results(results, paper, paper_designs)
    out = tmp_path / "val"
    args = [str(ROOT / "problems" / "paper_planar_2r.toml"), "--results", str(results),
            "--trials", "100", "--seed", "5", "--out", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "wall time" in text and "ranking by the measure" in text
    record = json.loads((out / "validation.json").read_text())
    assert (record["seed"], record["trials"], record["case"]) == (5, 100, "elastostatic")
    assert [(p["criterion"], p["m"]) for p in record["plans"]] == [
        (d.criterion, d.m) for d in paper_designs]
    first = record["plans"][0]
    assert len(first["empirical_rms_m"]) == len(first["ci_low_m"]) == paper.test_poses.s
    assert first["max"]["predicted_m"] == pytest.approx(paper_designs[0].scores.max_rms_error_m)
    assert (out / "validation.png").stat().st_size > 10_000
    # same seed, same numbers
    assert main(args) == 0
    again = json.loads((out / "validation.json").read_text())["plans"][0]
    assert again["empirical_rms_m"] == first["empirical_rms_m"]


def test_script_rejects_results_of_another_problem(tmp_path, paper, paper_designs, capsys):
    results = tmp_path / "results.json"
    write_results(results, paper, paper_designs)
    assert main([str(GEOMETRIC), "--results", str(results), "--trials", "10"]) == 2
    err = capsys.readouterr().err
    assert "--results" in err and "calibration.parameters" in err
    assert main([str(GEOMETRIC), "--results", str(tmp_path / "missing.json")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main([str(GEOMETRIC), "--trials", "1"]) == 2
    assert "trials = 1" in capsys.readouterr().err
