"""Virtual calibration (casadi_design.virtual): the predicted sqrt(rho) against simulated
calibrations on the problem's own nonlinear measurement model."""

import argparse
import json
import math
import time

import numpy as np
import pytest

import casadi_design.cli
from casadi_design.cli.validate import add_arguments, run
from casadi_design.errors import DesignError, OutputError, ProblemError
from casadi_design.identification.residuals import chi2_quantile
from casadi_design.measures.measures import score_plan
from casadi_design.optimisation.solve import solve_design
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import load_problem
from casadi_design.records.files import write_results
from casadi_design.robot.robots import frame_jacobian, frame_placement
from casadi_design.virtual import (
    ErrorSpreads,
    Plan,
    evaluate,
    linearisation_study,
    plans_from_designs,
    plans_from_results,
    rankings,
    validate,
)
from casadi_design.virtual.compensate import compensate
from casadi_design.virtual.identify import identify_nonlinear
from casadi_design.virtual.simulate import (
    draw_true_parameters,
    nominal_poses,
    simulate_measurements,
)
from casadi_design.virtual.statistics import rms_interval
from tests.conftest import ROOT, build, paper_raw, read_raw

GEOMETRIC = ROOT / "problems" / "planar_2r_geometric.toml"
ABB = ROOT / "problems" / "abb_irb6640_machining.toml"
PAPER_FILE = str(ROOT / "problems" / "paper_planar_2r.toml")


def solve_all(problem):
    return [solve_design(problem, c, m) for m in problem.m_values for c in problem.criteria]


def cli(argv):
    """``casadi-design validate ARGV`` as the command line runs it: parse with :func:`add_arguments`, then
    :func:`run` (which raises ProblemError / DesignError / OutputError for the CLI to print)."""
    parser = argparse.ArgumentParser(prog="casadi-design validate")
    add_arguments(parser)
    return run(parser.parse_args(argv))


@pytest.fixture(scope="module")
def paper_designs(paper_solved):
    return list(paper_solved.values())


@pytest.fixture(scope="module")
def geometric():
    return load_problem(GEOMETRIC)


@pytest.fixture(scope="module")
def geometric_plans(geometric):
    return plans_from_designs(geometric, solve_all(geometric))


@pytest.fixture(scope="module")
def geometric_plan_m4(geometric):
    """The test-pose plan of m = 4 alone (of :func:`geometric_plans`, the same plan, solved alone)."""
    return plans_from_designs(geometric, [solve_design(geometric, "test-pose", 4)])[0]


@pytest.fixture(scope="module")
def abb():
    return load_problem(ABB)


@pytest.fixture(scope="module")
def abb_plan(abb):
    """A feasible random plan of the ABB case with the fewest experiments (no IPOPT)."""
    Q, F = random_plan(abb, abb.m_min, np.random.default_rng(0))
    return Plan("test-pose", abb.m_min, Q, F)


def both_problem():
    """The paper's arm with joint offsets, link 1 length and compliances identified together."""
    raw = paper_raw()
    raw["calibration"]["case"] = "both"
    raw["calibration"]["parameters"] = ["joint1.offset", "joint2.offset", "joint2.tx"]
    raw["experiments"]["m"] = [3]
    return build(raw)


def random_configurations(problem, count, rng):
    """``count`` configurations within the joint limits and loads of the calibration's size."""
    robot, model = problem.robot, problem.model
    Q = rng.uniform(robot.q_min, robot.q_max, (count, model.n))
    F = rng.normal(0.0, 1.0, (count, model.nF))
    if problem.force is not None:
        F *= problem.force.magnitude_N / np.linalg.norm(F, axis=1, keepdims=True)
    return Q, F


@pytest.mark.parametrize("which", ["paper", "geometric", "both", "abb"])
def test_simulated_measurement_linearises_to_B(which, request):
    """One model: the values the virtual calibration simulates, ``model.measurement`` of a
    true robot ``X = eps v`` about the nominal pose, are ``B (c v) eps`` to first order (central
    differences, every parameter). The ABB case checks it with three markers, a load hung off
    the spindle (its moment) and the deflection fixed point."""
    problem = {"paper": lambda: request.getfixturevalue("paper"),
               "geometric": lambda: request.getfixturevalue("geometric"), "both": both_problem,
               "abb": lambda: request.getfixturevalue("abb")}[which]()
    model = problem.model
    N = 4
    Q, F = random_configurations(problem, N, np.random.default_rng(3))
    ref = nominal_poses(model, Q, F)
    eps = np.array([1e-9 if n.startswith("k.") else 1e-6 for n in model.parameter_names])
    V = np.diag(eps)  # one direction v per parameter, eps |v| physical units
    up, down = (evaluate(model.measurement, np.repeat(Q, model.L, axis=0), np.repeat(F, model.L, axis=0),
                         np.tile(sign * V, (N, 1)), np.repeat(ref, model.L, axis=0))[0]
                for sign in (1.0, -1.0))
    dy = ((up - down)[:, :, 0] / 2).reshape(N, model.L, model.d)  # y(eps v) to first order
    B = model.B_stack(Q, F)
    # B is written for the scaled parameters c X: the change is B (c v)
    expected = np.einsum("ndl,kl->nkd", B, V * model.column_scale)
    np.testing.assert_allclose(dy, expected, rtol=1e-6, atol=1e-7 * np.max(np.abs(expected)))
    # and along a random direction, as the simulation draws it: (y(eps v) - y(-eps v)) / 2 ~
    # B (c v) eps, the second-order terms cancelled (they are ~1e-4 of y at eps v on the ABB)
    v = eps * np.random.default_rng(4).standard_normal(model.L)
    y = (evaluate(model.measurement, Q, F, np.tile(v, (N, 1)), ref)[0][:, :, 0]
         - evaluate(model.measurement, Q, F, np.tile(-v, (N, 1)), ref)[0][:, :, 0]) / 2
    np.testing.assert_allclose(y, B @ (model.column_scale * v), rtol=1e-5, atol=1e-7 * np.max(np.abs(y)))
    assert model.d == (9 if which == "abb" else 2)


def test_deflection_is_the_static_equilibrium_of_pinocchio(paper):
    """The deflected pose solves dq = diag(k) J(q + dq)^T W (Pinocchio's Jacobian), and with a
    soft arm it differs visibly from the linear A k."""
    model, robot = paper.model, paper.robot
    q, F, k = np.array([0.7, -1.9]), np.array([60.0, -80.0]), np.array([1e-4, 2e-4])
    dq = np.zeros(2)
    for _ in range(50):
        dq = k * (frame_jacobian(robot, q + dq)[:2, :].T @ F)
    expected = frame_placement(robot, q + dq).translation
    p = evaluate(model.pose, q[None], F[None], k[None])[0][0, 9:12, 0]
    np.testing.assert_allclose(p, expected, atol=1e-12)
    linear = frame_placement(robot, q).translation[:2] + model.B_numeric(q, F) @ k
    assert np.linalg.norm(p[:2] - linear) > 1e-6


def test_gauss_newton_recovers_large_errors_where_one_linear_step_does_not(geometric, geometric_plan_m4):
    plan = geometric_plan_m4
    model = geometric.model
    X_true = draw_true_parameters(model, ErrorSpreads(length_m=0.02, angle_rad=np.radians(2.0)), 50,
                                  np.random.default_rng(0))
    # noise-free measurements (sigma = 0): the minimiser is X_true itself
    ref, y = simulate_measurements(model, plan, X_true, 0.0, ErrorSpreads(), np.random.default_rng(1))
    X_hat, report = identify_nonlinear(model, plan.Q, plan.F, ref, y, geometric.sigma_m)
    assert report.non_converged == 0 and report.iterations > 2
    np.testing.assert_allclose(X_hat, X_true, atol=1e-6)
    S = model.B_stack(plan.Q, plan.F).reshape(-1, model.L)  # one linear least-squares step
    X_lin = (y @ np.linalg.pinv(S).T) / model.column_scale
    assert np.max(np.abs(X_lin - X_true)) > 1e-4
    _, stopped = identify_nonlinear(model, plan.Q, plan.F, ref, y, geometric.sigma_m, max_iterations=1)
    assert stopped.non_converged == 50


def _exact_least_squares(model, plan, ref, y, sigma):
    """Gauss-Newton with the exact Jacobian of the model at every iterate (the reference)."""
    import casadi as ca

    q, F = ca.SX.sym("q", model.n), ca.SX.sym("F", model.nF)
    X, r = ca.SX.sym("X", model.L), ca.SX.sym("ref", 12)
    h = model.measurement(q, F, X, r)[0]
    fn = ca.Function("h", [q, F, X, r], [h, ca.jacobian(h, X)])
    out = []
    for yt in y:
        Xt = np.zeros(model.L)
        for _ in range(20):
            hs, Js = zip(*[(np.asarray(a).ravel(), np.asarray(b)) for a, b in
                           (fn(qi, Fi, Xt, ri) for qi, Fi, ri in zip(plan.Q, plan.F, ref))])
            step = np.linalg.lstsq(np.vstack(Js), yt - np.concatenate(hs), rcond=None)[0]
            Xt = Xt + step
            if np.linalg.norm(np.vstack(Js) @ step) < 1e-9 * sigma:
                break
        out.append(Xt)
    return np.array(out)


#: How far (in standard deviations of the estimate) the least squares may stop from the exact
#: least-squares estimate: with the exact Jacobian, and with the Taylor Jacobian of the Monte
#: Carlo (its O(|X|^2) error moves the stationary point).
EXACT_STOP = 1e-3
TAYLOR_STOP = 0.1


@pytest.mark.parametrize("factor", [1.0, 10.0])
@pytest.mark.parametrize("jacobian, stop", [("exact", EXACT_STOP), ("taylor", TAYLOR_STOP)])
def test_least_squares_reaches_the_least_squares_estimate(geometric, geometric_plan_m4, factor, jacobian, stop):
    """The least squares of the virtual calibration and of measured data (exact residuals)
    reaches the estimate of Gauss-Newton with the exact Jacobian at every iterate, also at 10x
    the default spreads (5 mm, 0.5 deg), where the Taylor Jacobian's O(|X|^2) error is 100x larger."""
    plan = geometric_plan_m4
    model = geometric.model
    rng = np.random.default_rng(3)
    X_true = draw_true_parameters(model, ErrorSpreads().scaled(factor), 8, rng)
    ref, y = simulate_measurements(model, plan, X_true, geometric.sigma_m, ErrorSpreads(), rng)
    X_hat, report = identify_nonlinear(model, plan.Q, plan.F, ref, y, geometric.sigma_m, jacobian=jacobian)
    assert report.non_converged == 0
    X_ls = _exact_least_squares(model, plan, ref, y, geometric.sigma_m)
    B = model.B_stack(plan.Q, plan.F).reshape(-1, model.L) / model.column_scale
    noise = geometric.sigma_m * np.sqrt(np.diag(np.linalg.inv(B.T @ B)))  # std of X_hat
    assert np.max(np.abs(X_hat - X_ls) / noise) < stop


def test_compensation_with_the_true_model_leaves_no_error(geometric):
    """Exact parameters: the compensated true robot hits every target; X = 0 leaves the raw error."""
    model, tp = geometric.model, geometric.test_poses
    X_true = np.tile(draw_true_parameters(model, ErrorSpreads(), 1, np.random.default_rng(1)), (tp.s, 1))
    target = nominal_poses(model, tp.q, tp.F)
    qc, done, miss = compensate(model, tp.q, tp.F, target, X_true, geometric.sigma_m)
    assert done.all() and miss <= 1e-6 * geometric.sigma_m
    e = evaluate(model.accuracy, qc, tp.F, X_true, target)[0][:, :, 0]
    assert np.max(np.linalg.norm(e, axis=1)) == pytest.approx(miss, rel=1e-6)
    raw = np.linalg.norm(evaluate(model.accuracy, tp.q, tp.F, X_true, target)[0][:, :, 0], axis=1)
    B0 = model.B_stack(tp.q, tp.F, accuracy=True)
    linear = np.linalg.norm(B0 @ (model.column_scale * X_true[0]), axis=1)
    np.testing.assert_allclose(raw, linear, rtol=0.02)
    assert np.min(raw) > 1e-4


@pytest.mark.parametrize("p, dof, value", [(0.975, 100, 129.5612), (0.025, 100, 74.2219),
                                           (0.975, 1000, 1089.531), (0.025, 1000, 914.257),
                                           (0.975, 1, 5.023886), (0.025, 2, 0.0506356)])
def test_chi2_quantile_against_tables(p, dof, value):
    assert chi2_quantile(p, dof) == pytest.approx(value, rel=1e-5)


def _chi2_cdf(x: float, k: int) -> float:
    """P(chi2(k) <= x) in closed form, without scipy: erf for k = 1; for even k = 2n,
    P(Poisson(x / 2) >= n) (terms summed in logs: k up to thousands)."""
    if k == 1:
        return math.erf(math.sqrt(x / 2))
    assert k % 2 == 0
    lam = x / 2
    return 1 - math.fsum(math.exp(j * math.log(lam) - lam - math.lgamma(j + 1))
                         for j in range(k // 2))


@pytest.mark.parametrize("dof, trials", [(1.0, 1), (2.0, 1), (2.0, 7), (1.5, 4), (2.0, 2000)])
def test_rms_interval_bounds_sit_at_the_exact_chi_square_tails(dof, trials):
    """Each bound of the interval, turned back into the chi-square value it stands for
    (T ms / bound^2 with T = trials nu), has the tail probability (1 -+ c) / 2 under the
    closed-form chi-square CDF (T = 1, or even T, also from a fractional nu), not under
    scipy's quantile function that the interval is computed with."""
    ms, c = 2.5e-9, 0.9
    T = round(trials * dof)
    low, high = rms_interval(np.array([ms]), np.array([dof]), trials, confidence=c)
    assert 0 < low[0] < np.sqrt(ms) < high[0]
    assert _chi2_cdf(T * ms / low[0] ** 2, T) == pytest.approx((1 + c) / 2, abs=1e-9)
    assert _chi2_cdf(T * ms / high[0] ** 2, T) == pytest.approx((1 - c) / 2, abs=1e-9)
    # an RMS interval: four times the mean square, twice the bounds
    low4, high4 = rms_interval(np.array([4 * ms]), np.array([dof]), trials, confidence=c)
    np.testing.assert_allclose([low4[0], high4[0]], [2 * low[0], 2 * high[0]], rtol=1e-12)


def test_rms_interval_misses_on_each_side_at_the_nominal_rate_for_fractional_dof():
    """T ms / rho ~ chi2(T) exactly (numpy's chi-square draws, T = 7 x 1.37 = 9.59): the 90 %
    interval lies above sqrt(rho) 5 % of the time and below it 5 % (100000 draws: one standard
    error 0.07 %)."""
    rng = np.random.default_rng(11)
    rho, dof, trials, n = 4e-8, 1.37, 7, 100_000
    T = trials * dof
    ms = rho * rng.chisquare(T, size=n) / T
    low, high = rms_interval(ms, dof, trials, confidence=0.9)
    assert np.mean(low > np.sqrt(rho)) == pytest.approx(0.05, abs=0.0035)
    assert np.mean(high < np.sqrt(rho)) == pytest.approx(0.05, abs=0.0035)


def test_rms_interval_covers_the_true_rms_95_percent_of_the_time():
    """Gaussian errors of a rank-2 covariance (nu between 1 and 2), 500 draws per interval;
    1000 intervals resolve the coverage to +-0.7 % (one standard error)."""
    rng = np.random.default_rng(7)
    C = np.array([[1.0, 0.6], [0.6, 0.5]])
    nu = np.trace(C) ** 2 / np.trace(C @ C)
    e = rng.multivariate_normal(np.zeros(2), C, size=(1000, 500))
    low, high = rms_interval(np.mean(np.sum(e**2, axis=2), axis=1), np.full(1000, nu), 500)
    covered = np.mean((low <= np.sqrt(np.trace(C))) & (np.sqrt(np.trace(C)) <= high))
    assert 0.93 <= covered <= 0.97


@pytest.mark.slow  # 10 s: 2000 trials of six plans; the default suite keeps the ABB, correlated noise and two rounds
def test_paper_example_agrees_within_5_percent_at_every_node(paper, paper_designs):
    """Table 4's six plans, 2000 virtual calibrations each on the nonlinear compliant arm.

    2000 trials are needed here: the relative standard error of a simulated RMS is
    ~1 / sqrt(2 N nu) = 1.6 % for N = 2000, nu >= 1, so 5 % at every one of 6 x 61 nodes is
    a 3-sigma bound; 1000 trials would make it 2.2 sigma."""
    t0 = time.perf_counter()
    v = validate(paper, plans_from_designs(paper, paper_designs), trials=2000, seed=0)
    print(f"\npaper example, 6 plans x 2000 trials: {time.perf_counter() - t0:.2f} s")
    assert len(v.plans) == 6
    for p, d in zip(v.plans, paper_designs):
        np.testing.assert_allclose(p.predicted_rms_m, d.scores.rms_error_m, rtol=1e-9)
        assert p.worst_relative_error < 0.05, (p.plan.criterion, p.plan.m, p.worst_relative_error)
        assert np.all(p.ci_low_m < p.empirical_rms_m) and np.all(p.empirical_rms_m < p.ci_high_m)
        # the interval's half-width is the sampling error of 2000 trials: ~1.96 sqrt(2 / (N nu)) / 2
        half = (p.ci_high_m - p.ci_low_m) / (2 * p.empirical_rms_m)
        np.testing.assert_allclose(half, 1.96 * np.sqrt(2 / (2000 * p.dof)) / 2, rtol=0.05)
        assert p.identification.method.startswith("trust-region least squares") and p.identification.non_converged == 0
        assert p.compensation_failed == 0
    for m, r in rankings(v.plans).items():
        assert r["by_simulation"] == r["by_measure"] == ["test-pose", "D", "E"], m


@pytest.mark.slow  # 4.5 s: 1000 trials of six plans; the default suite keeps the ABB, correlated noise and two rounds
def test_geometric_case_agrees_within_10_percent_at_every_node(geometric, geometric_plans):
    """1000 trials: relative standard error of a simulated RMS ~1 / sqrt(2 N nu) <= 2.2 % (nu
    >= 1), so 10 % is a 4.5-sigma bound (the linearisation bias is ~1.6 % at these spreads)."""
    v = validate(geometric, geometric_plans, trials=1000, seed=0)
    assert [(p.plan.criterion, p.plan.m) for p in v.plans] == [
        (c, m) for m in (2, 4) for c in ("test-pose", "D", "E")]
    for p in v.plans:
        assert p.worst_relative_error < 0.10, (p.plan.criterion, p.plan.m, p.worst_relative_error)
        assert p.identification.method.startswith("trust-region least squares")
        assert p.identification.non_converged == 0 and p.compensation_failed == 0


@pytest.mark.slow  # a study (spreads x1 and x400, 300 trials each): the README's breakdown figures
def test_linearisation_breaks_down_for_large_errors(geometric, geometric_plans):
    """Spreads x 400 (20 cm, 20 deg): the identified arms cannot reach part of the line and the
    simulated error departs from sqrt(rho) by more than 10 %; at x 1 neither happens."""
    (_, small), (_, large) = linearisation_study(geometric, geometric_plans, [1.0, 400.0], trials=300)
    assert large.spreads.length_m == pytest.approx(0.2)
    assert all(p.compensation_failed == 0 and p.worst_relative_error < 0.1 for p in small.plans)
    assert all(p.compensation_failed > 0 for p in large.plans)
    assert max(p.worst_relative_error for p in large.plans) > 0.1


def test_abb_with_markers_and_hung_load(abb, abb_plan):
    """The 6-axis case with three markers (9 values per experiment), a load hung off the
    spindle and 35 parameters: 20 virtual calibrations of a random plan with the fewest
    experiments. 20 trials of ~2 effective dof give a standard error of ~11 % on the RMS, so
    0.5..2 at every node is a loose (> 4 sigma) check of the prediction."""
    v = validate(abb, [abb_plan], trials=20, seed=0)
    (p,) = v.plans
    tp = abb.test_poses
    predicted = score_plan(abb.model.B_stack(abb_plan.Q, abb_plan.F),
                           abb.model.B_stack(tp.q, tp.F, accuracy=True), abb.sigma_m).rms_error_m
    np.testing.assert_array_equal(p.predicted_rms_m, predicted)
    assert p.identification.method.startswith("trust-region least squares") and p.identification.non_converged == 0
    assert p.compensation_failed == 0 and p.compensation_residual_m <= 1e-6 * abb.sigma_m
    assert np.all((0.5 < p.ratio) & (p.ratio < 2.0)), p.ratio


def test_correlated_noise_enters_through_the_whitening():
    """A full measurement covariance (UR10, correlated x, y, z noise up to 2.5 sigma): the
    simulation adds sigma per whitened value, i.e. the covariance in metres, and agrees with
    sqrt(rho) of the whitened B. 300 trials: standard error <= 4.1 % (nu >= 1), so 15 % at
    every node is a 3.7-sigma bound; ignoring the covariance would be off by a factor ~2."""
    raw = read_raw(ROOT / "problems" / "ur10_drilling.toml")
    raw["measurement"]["covariance"] = (np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.5], [0.0, 0.5, 1.0]])
                                        * 1e-9).tolist()
    problem = build(raw)
    Q, F = random_plan(problem, problem.m_min, np.random.default_rng(0))
    (p,) = validate(problem, [Plan("D", problem.m_min, Q, F)], trials=300).plans
    assert p.worst_relative_error < 0.15 and p.compensation_failed == 0


@pytest.mark.slow
def test_abb_agrees_within_10_percent_with_400_trials(abb, abb_plan):
    """400 trials (standard error ~2.5 % at nu ~ 2): every node within 10 % (about 25 s)."""
    (p,) = validate(abb, [abb_plan], trials=400, seed=0).plans
    assert p.worst_relative_error < 0.10 and p.coverage > 0.5


def test_cli_writes_validation_json_and_figure(tmp_path, paper, paper_designs, capsys):
    results = tmp_path / "results.json"
    write_results(results, paper, paper_designs)
    out = tmp_path / "val"
    args = [PAPER_FILE, "--results", str(results), "--trials", "100", "--seed", "5", "--out", str(out)]
    assert cli(args) == 0
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
    assert (out / "validation.pdf").stat().st_size > 1_000
    # the plans read back exactly; same seed, same numbers
    plans = plans_from_results(paper, results)
    for p, d in zip(plans, paper_designs):
        assert np.array_equal(p.Q, d.Q) and np.array_equal(p.F, d.F)
    again = validate(paper, plans[:1], trials=100, seed=5).plans[0]
    assert again.empirical_rms_m.tolist() == first["empirical_rms_m"]


def test_cli_rejects_bad_input_before_writing(tmp_path, paper, paper_designs, capsys):
    results = tmp_path / "results.json"
    write_results(results, paper, paper_designs)
    with pytest.raises(ProblemError, match="--results.*calibration.parameters"):
        cli([str(GEOMETRIC), "--results", str(results), "--trials", "10"])
    with pytest.raises(ProblemError, match="no such file"):
        cli([str(GEOMETRIC), "--results", str(tmp_path / "missing.json")])
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ProblemError, match="--results: .*not valid JSON"):
        cli([str(GEOMETRIC), "--results", str(tmp_path / "broken.json")])
    with pytest.raises(ProblemError, match="trials = 1"):  # before solving anything
        cli([str(GEOMETRIC), "--trials", "1"])
    with pytest.raises(SystemExit):  # the option named, by the argument parser
        cli([str(GEOMETRIC), "--length-mm", "-1000"])
    assert "argument --length-mm: --length-mm takes a length in mm >= 0, got '-1000'" in capsys.readouterr().err
    with pytest.raises(ProblemError, match=r"error spread length_m = -1.0; give a finite value >= 0"):  # in Python
        ErrorSpreads(length_m=-1.0)
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputError, match="not a folder"):
        cli([PAPER_FILE, "--results", str(results), "--out", str(tmp_path / "file")])
    # a simulation that fails (the true robots' deflection diverges) creates no folder
    out = tmp_path / "never"
    with pytest.raises(DesignError, match="deflection"):
        cli([PAPER_FILE, "--results", str(results), "--trials", "5", "--k", "1", "--out", str(out)])
    assert not out.exists()


def test_validate_subcommand_and_script(tmp_path, paper, paper_designs, capsys):
    """``casadi-design validate`` (and scripts/validate_case.py, its thin wrapper) run the same
    command; errors print one line and exit with code 2."""
    import runpy
    import sys

    results = tmp_path / "results.json"
    write_results(results, paper, paper_designs)
    command = ["validate", PAPER_FILE, "--results", str(results), "--trials", "10"]
    assert casadi_design.cli.main(command) == 0
    assert "ranking by the measure" in capsys.readouterr().out
    argv = sys.argv
    try:
        sys.argv = ["validate_case.py", str(GEOMETRIC), "--results", str(results)]
        with pytest.raises(SystemExit) as exit_:
            runpy.run_path(str(ROOT / "scripts" / "validate_case.py"), run_name="__main__")
    finally:
        sys.argv = argv
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --results") and err.count("\n") == 1


@pytest.mark.slow  # two paths compared (3.5 s); validate of solve's results.json runs by default (test_cli, test_every_command)
def test_validate_without_results_validates_the_plans_of_solve(tmp_path):
    """``validate CASE OPTIONS`` simulates exactly the plans ``solve CASE OPTIONS`` writes (one
    campaign for both, rounded starts and bounds included): its validation.json equals the one
    of ``validate --results`` on solve's results.json, number for number."""
    import casadi_design.cli as command

    opts = ["--m", "2", "--criteria", "test-pose,D", "--starts", "2", "--bound-steps", "1",
            "--bound-pool", "60", "--jobs", "1", "--quiet"]
    assert command.main(["solve", PAPER_FILE, *opts, "--out", str(tmp_path / "solved")]) == 0
    trials = ["--trials", "20", "--seed", "3"]
    assert command.main(["validate", PAPER_FILE, *opts, *trials, "--out", str(tmp_path / "direct")]) == 0
    assert command.main(["validate", PAPER_FILE, "--results", str(tmp_path / "solved" / "results.json"),
                         *trials, "--out", str(tmp_path / "read")]) == 0
    direct, read = (json.loads((tmp_path / d / "validation.json").read_text()) for d in ("direct", "read"))
    solved = json.loads((tmp_path / "solved" / "results.json").read_text())["designs"]
    assert [(p["criterion"], p["m"]) for p in direct["plans"]] == [(d["criterion"], d["m"]) for d in solved]
    for a, b, d in zip(direct["plans"], read["plans"], solved):
        assert a["predicted_rms_m"] == b["predicted_rms_m"] == d["rms_error_m"]
        assert a["empirical_rms_m"] == b["empirical_rms_m"]
    assert any(st["origin"] == "rounded approximate design" for d in solved for st in d["solver"]["per_start"])


def test_a_two_round_campaign_is_simulated_whole(paper, tmp_path, capsys):
    """validate --measured: round 2 designed around the measured round 1, then each trial
    measures and identifies both rounds together; the simulated max error agrees with the
    campaign's predicted sqrt(rho) within 5 % (2000 trials: about 2 % standard error)."""
    from casadi_design.cli import main
    from casadi_design.plan.sampling import random_plan
    from casadi_design.records.export import csv_text, plan_table
    from tests.conftest import PAPER

    Q, F = random_plan(paper, 1, np.random.default_rng(3))
    first = tmp_path / "first.csv"
    first.write_text(csv_text(*plan_table(paper, Q, F)))
    assert main(["validate", str(PAPER), "--m", "2", "--criteria", "test-pose", "--measured", str(first),
                 "--starts", "2", "--bound-steps", "0", "--jobs", "1", "--trials", "2000",
                 "--out", str(tmp_path / "v"), "--quiet"]) == 0
    capsys.readouterr()
    plan = json.loads((tmp_path / "v" / "validation.json").read_text())["plans"][0]
    assert plan["m"] == 3  # the campaign: 1 measured + 2 new
    assert plan["max"]["empirical_m"] == pytest.approx(plan["max"]["predicted_m"], rel=0.05)
