"""The test-pose measure with the robot's unmodelled error as a random field
(casadi_design/measures/field.py): its limit (the paper's measure), an independent numpy
computation of the universal kriging variance, and a Monte Carlo of a simulated robot whose error
is a known Gaussian process."""

import dataclasses

import numpy as np
import pytest

from casadi_design.cli.identify import load_without_cell
from casadi_design.measures.field import Field, axes_of, kriging_mean, kriging_rho
from casadi_design.measures.measures import information_matrix, rho_at_test_poses
from casadi_design.model.build import build_problem
from casadi_design.model.problem import ModelErrorSpec
from casadi_design.optimisation.solve import plan_scores
from casadi_design.plan.sampling import random_plan
from tests.conftest import ROOT

UR10 = ROOT / "problems" / "ur10_drilling.toml"
FIELD = Field(2.5e-4, (0.6, 0.5, 0.7, 0.9, 1.0, 1.2), 3e-5)


@pytest.fixture(scope="module")
def ur10():
    problem = load_without_cell(str(UR10))
    Q, F = random_plan(problem, 14, np.random.default_rng(3))
    return problem, Q, F, problem.model.B_stack(Q, F)


def axes(problem):
    return axes_of(problem.model.measured_rows), axes_of(problem.model.accuracy_rows)


def test_without_a_field_it_is_the_paper_s_measure(ur10):
    problem, Q, F, B = ur10
    a, a0 = axes(problem)
    zero = Field(0.0, FIELD.lengths, 0.0)
    rho = kriging_rho(zero, problem.sigma_m, B, Q, a, np.eye(3), problem.B0, problem.test_poses.q, a0)
    np.testing.assert_allclose(rho, rho_at_test_poses(information_matrix(B), problem.B0, problem.sigma_m), rtol=1e-9)


def test_a_vanishing_field_in_the_problem_file_gives_every_figure_of_today(ur10):
    """[calibration.model_error] of 1e-12 m: every score of the plan is today's to 1e-9."""
    problem, Q, F, B = ur10
    spec = problem.spec
    tiny = dataclasses.replace(spec, calibration=dataclasses.replace(
        spec.calibration, model_error=ModelErrorSpec(1e-12, (0.5,), 0.0)))
    with_field = build_problem(tiny)
    assert with_field.field is not None and with_field.field.lengths == (0.5,) * 6
    today, field = plan_scores(problem, Q, F), plan_scores(with_field, Q, F)
    np.testing.assert_allclose(field.rms_error_m, today.rms_error_m, rtol=1e-9)
    for k, v in today.values.items():
        assert field.values[k] == pytest.approx(v, rel=1e-9), k


def universal_kriging_variance(Sigma_y, S, k0, C00, B0):
    """The error variance of the best linear unbiased predictor of ``z0 = B0 X + delta0`` from
    ``y = S X + delta + eps`` by its own equations: ``min E|z0 - Lambda^T y|^2`` subject to
    ``S^T Lambda = B0^T``, the Lagrange system ``[[V, S], [S^T, 0]] [Lambda; mu] = [k0; B0^T]``."""
    N, L = S.shape
    Kkt = np.block([[Sigma_y, S], [S.T, np.zeros((L, L))]])
    sol = np.linalg.solve(Kkt, np.vstack([k0, B0.T]))
    Lam = sol[:N]
    return float(np.trace(C00 - 2 * Lam.T @ k0 + Lam.T @ Sigma_y @ Lam))


def test_the_kriging_variance_is_the_blup_s_error(ur10):
    """An independent numpy computation: the covariance of every value built entry by entry
    from the kernel, the predictor from its Lagrange system."""
    problem, Q, F, B = ur10
    a, a0 = axes(problem)
    sigma, tp = problem.sigma_m, problem.test_poses
    m, d, L = B.shape
    ell = np.array(FIELD.lengths)

    def k(q, p):
        return FIELD.scale_m**2 * np.exp(-0.5 * np.sum(((q - p) / ell) ** 2)) + FIELD.nugget_m**2 * float(np.all(q == p))

    Sigma_y = np.array([[k(Q[i], Q[j]) * (a[u] == a[v]) + sigma**2 * (i == j and u == v)
                         for j in range(m) for v in range(d)] for i in range(m) for u in range(d)])
    rho = kriging_rho(FIELD, sigma, B, Q, a, np.eye(3), problem.B0, tp.q, a0)
    for j in range(tp.s):
        k0 = np.array([[k(Q[i], tp.q[j]) * (a[u] == a0[c]) for c in range(len(a0))] for i in range(m) for u in range(d)])
        k0 = k0 - np.array([[FIELD.nugget_m**2 * float(np.all(Q[i] == tp.q[j])) * (a[u] == a0[c])
                             for c in range(len(a0))] for i in range(m) for u in range(d)])  # no test pose measured
        C00 = (FIELD.scale_m**2 + FIELD.nugget_m**2) * np.eye(len(a0))
        assert rho[j] == pytest.approx(universal_kriging_variance(Sigma_y, B.reshape(m * d, L), k0, C00, problem.B0[j]),
                                       rel=1e-8)


def test_a_simulated_robot_with_a_known_field_meets_the_kriging_variance(ur10):
    """Monte Carlo: 4000 robots whose error is a draw of the field at the measured and the test
    poses and whose tracker adds sigma; least squares (generalised) and the kriging mean
    compensate; the mean square error at each test pose is within 5 % of rho."""
    problem, Q, F, B = ur10
    a, a0 = axes(problem)
    sigma, tp = problem.sigma_m, problem.test_poses
    m, d, L = B.shape
    rho = kriging_rho(FIELD, sigma, B, Q, a, np.eye(3), problem.B0, tp.q, a0)
    Qall = np.vstack([Q, tp.q])
    Kall = FIELD.kernel(Qall, Qall) + FIELD.nugget_m**2 * np.eye(len(Qall))
    chol = np.linalg.cholesky(Kall + 1e-30 * np.eye(len(Qall)))
    rng = np.random.default_rng(7)
    trials = 4000
    X = rng.normal(size=(trials, L)) * 1e-3
    delta = np.einsum("ij,tjc->tic", chol, rng.normal(size=(trials, len(Qall), 3)))  # per base axis
    S = B.reshape(m * d, L)
    y = X @ S.T + delta[:, :m, :].reshape(trials, m * d) + sigma * rng.normal(size=(trials, m * d))
    V = np.kron(Kall[:m, :m], np.eye(3)) + sigma**2 * np.eye(m * d)
    Vi = np.linalg.inv(V)
    Xhat = np.linalg.solve(S.T @ Vi @ S, (y @ Vi @ S).T).T  # generalised least squares
    r = y - Xhat @ S.T
    mean = np.array([kriging_mean(FIELD, sigma, ri.reshape(m, d), Q, a, np.eye(3), tp.q, a0) for ri in r[:trials]])
    z0 = np.einsum("tl,srl->tsr", X, problem.B0) + delta[:, m:, :]
    err = z0 - (np.einsum("tl,srl->tsr", Xhat, problem.B0) + mean)
    np.testing.assert_allclose(np.mean(np.sum(err**2, axis=2), axis=0), rho, rtol=0.05)


def test_an_additive_field_from_the_problem_file(tmp_path):
    """``shares`` in [calibration.model_error]: the field is additive over the joints, its kernel
    the sum of one-joint squared exponentials; shares that are not one per joint summing to 1
    are refused by name."""
    from casadi_design.errors import ProblemError
    from casadi_design.model.build import load_problem

    base = (ROOT / "problems" / "paper_planar_2r.toml").read_text()

    def problem(lines: str):
        path = tmp_path / "paper_field.toml"
        path.write_text(base.replace("[measurement]", f"[calibration.model_error]\n{lines}\n\n[measurement]"))
        return load_problem(path)

    field = problem("scale_m = 5e-4\nlength_rad = [0.3, 0.6]\nshares = [0.7, 0.3]").field
    Q = np.random.default_rng(0).uniform(-2, 2, size=(6, 2))
    expected = 5e-4**2 * sum(w * np.exp(-0.5 * ((Q[:, None, l] - Q[None, :, l]) / ell) ** 2)
                             for l, (w, ell) in enumerate([(0.7, 0.3), (0.3, 0.6)]))
    np.testing.assert_allclose(field.kernel(Q, Q), expected, rtol=1e-12)
    assert "additive over the joints" in field.describe() and field.as_dict()["shares"] == [0.7, 0.3]
    with pytest.raises(ProblemError, match=r"shares: is \[0.7, 0.4\].*summing to 1"):
        problem("scale_m = 5e-4\nlength_rad = 0.5\nshares = [0.7, 0.4]")
    with pytest.raises(ProblemError, match="shares: has 3 shares for the 2 joints"):
        problem("scale_m = 5e-4\nlength_rad = 0.5\nshares = [0.5, 0.25, 0.25]")
