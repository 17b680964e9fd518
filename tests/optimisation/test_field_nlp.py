"""The NLP of test-pose and I with the robot's unmodelled error as a field
(casadi_design/optimisation/field_nlp.py): its rows are the kriging variance of
measures/field.py, its first derivatives central finite differences, on the paper's
arm (loads as variables) with a field of the base axes and one of the joint angles."""

import dataclasses

import numpy as np
import pytest

from casadi_design.optimisation.nlp import build_nlp
from casadi_design.optimisation.solve import field_rho
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem, load_problem
from casadi_design.problem_file.read import HeldSpec
from tests.conftest import ROOT

FIELDS = {"base axes": "scale_m = 5e-4\nlength_rad = 0.5", "joint angles": "angle_rad = [8e-4, 5e-4]\nlength_rad = [0.4, 0.6]"}


@pytest.fixture(scope="module", params=[(name, held) for name in FIELDS for held in (0, 4)])
def paper(request, tmp_path_factory):
    """The paper's arm with a field, and with ``held`` experiments measured before the plan (the
    graph eliminates their part numerically)."""
    name, held = request.param
    text = (ROOT / "problems" / "paper_planar_2r.toml").read_text().replace(
        "[measurement]", f"[calibration.model_error]\n{FIELDS[name]}\n\n[measurement]")
    path = tmp_path_factory.mktemp("field") / "paper_field.toml"
    path.write_text(text)
    problem = load_problem(path)
    rng = np.random.default_rng(1)
    if held:
        Qh, Fh = random_plan(problem, held, rng)
        problem = build_problem(dataclasses.replace(problem.spec, held=HeldSpec(q=Qh.tolist(), F=Fh.tolist())))
        assert len(problem.field_held_rows[1]) == held
    Q, F = random_plan(problem, 3, rng)
    return problem, Q, F


def dense(value) -> np.ndarray:
    """A CasADi output (sparse) as a dense array."""
    import casadi as ca

    return np.asarray(ca.DM(value).full())


@pytest.mark.parametrize("criterion", ["test-pose", "I"])
def test_the_rows_are_the_kriging_variance_and_their_derivatives_finite_differences(paper, criterion):
    problem, Q, F = paper
    nlp = build_nlp(problem, criterion, 3, fixed=problem.M_held, field=True)
    x0 = nlp.start(Q, F)
    f, g = (np.asarray(v, dtype=float).ravel() for v in nlp.oracle(x0, []))
    rho = field_rho(problem, Q, F, problem.model.B_stack(Q, F))
    s = problem.test_poses.s
    if criterion == "test-pose":  # rho_j / sigma^2 - t <= 0
        np.testing.assert_allclose((g[:s] + x0[-1]) * problem.sigma_m**2, rho, rtol=1e-10)
    else:  # the mean of rho_j / sigma^2
        assert f[0] * problem.sigma_m**2 == pytest.approx(np.mean(rho), rel=1e-10)
    h, E = 1e-6, np.eye(len(x0))
    J = dense(nlp.options["jac_g"](x0, [])[1])
    fd = np.array([(np.asarray(nlp.oracle(x0 + h * e, [])[1]) - np.asarray(nlp.oracle(x0 - h * e, [])[1])).ravel()
                   for e in E]).T / (2 * h)
    np.testing.assert_allclose(J, fd, atol=1e-7 * np.max(np.abs(fd)))
    grad = np.asarray(nlp.options["grad_f"](x0, [])[1]).ravel()
    fd = np.array([(float(nlp.oracle(x0 + h * e, [])[0]) - float(nlp.oracle(x0 - h * e, [])[0])) / (2 * h) for e in E])
    np.testing.assert_allclose(grad, fd, atol=1e-7 * np.max(np.abs(fd)))
    assert nlp.options["ipopt.hessian_approximation"] == "limited-memory"
