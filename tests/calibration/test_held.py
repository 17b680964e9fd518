"""Information held before a plan (experiments already measured, a prior): the campaign's M,
its identifiability and the bound of its completions."""

from dataclasses import replace

import numpy as np
import pytest

from casadi_design.errors import ProblemError
from casadi_design.optimisation.approximate import approximate_design
from casadi_design.optimisation.bound import bound
from casadi_design.optimisation.solve import plan_scores, solve_design
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem
from casadi_design.problem_file.calibration import PriorSpec
from casadi_design.problem_file.read import HeldSpec, read_problem
from tests.conftest import ROOT
from tests.pinocchio_oracle import rms_errors as pinocchio_rms


def held(problem, Q, F, **prior) -> object:
    """``problem`` with the experiments ``Q``, ``F`` measured (and a prior)."""
    spec = HeldSpec(tuple(map(tuple, Q.tolist())), tuple(map(tuple, F.tolist())), **prior)
    return build_problem(replace(problem.spec, held=spec))


def numpy_rho(problem, Q, F) -> np.ndarray:
    """``sigma^2 tr(B0_j M^-1 B0_j^T)`` of the plan Q, F, by numpy alone from the model's B."""
    S = problem.model.B_stack(Q, F).reshape(-1, problem.model.L)
    N = np.linalg.inv(S.T @ S)
    return problem.sigma_m**2 * np.array([np.trace(b @ N @ b.T) for b in problem.B0])


def test_a_campaign_scores_as_its_measured_and_new_experiments_together(paper):
    rng = np.random.default_rng(7)
    Qh, Fh = random_plan(paper, 1, rng)
    Q, F = random_plan(paper, 2, rng)
    campaign = held(paper, Qh, Fh)
    assert campaign.m_held == 1 and paper.M_held is None
    got = plan_scores(campaign, Q, F)
    want = numpy_rho(paper, np.vstack([Qh, Q]), np.vstack([Fh, F]))
    np.testing.assert_allclose(got.rms_error_m, np.sqrt(want), rtol=1e-10)
    whole = plan_scores(paper, np.vstack([Qh, Q]), np.vstack([Fh, F]))  # the same plan, nothing held
    for c, v in whole.values.items():
        assert got.values[c] == pytest.approx(v, rel=1e-10), c
    Qc, Fc, measured = campaign.campaign(Q, F)
    np.testing.assert_array_equal(Qc, np.vstack([Qh, Q]))
    assert measured.tolist() == [True, False, False]


def test_six_measured_ur10_experiments_make_six_new_ones_identifiable():
    """27 parameters, 3 values per experiment: 9 experiments alone; 6 measured hold rank 18, so
    3 new ones complete them, and 6 + 6 identify what 6 alone cannot."""
    ur10 = build_problem(replace(read_problem(ROOT / "problems/ur10_drilling.toml"), cell=None))
    rng = np.random.default_rng(3)
    Qh, Fh = random_plan(ur10, 6, rng)
    Q, F = random_plan(ur10, 6, rng)
    assert ur10.m_min == 9 and not plan_scores(ur10, Qh, Fh).identifiable
    campaign = held(ur10, Qh, Fh)
    assert campaign.m_min == 3 and np.linalg.matrix_rank(campaign.M_held) == 18
    scores = plan_scores(campaign, Q, F)
    assert scores.identifiable
    np.testing.assert_allclose(scores.rms_error_m, np.sqrt(numpy_rho(ur10, np.vstack([Qh, Q]), np.vstack([Fh, F]))),
                               rtol=1e-8)
    # and by Pinocchio alone, in a redundant parameterisation of every geometric error
    np.testing.assert_allclose(scores.rms_error_m, pinocchio_rms(ur10, np.vstack([Qh, Q])), rtol=1e-7)


def test_a_group_prior_adds_sigma_squared_over_the_variance_in_the_scaled_parameters():
    spec = read_problem(ROOT / "problems/planar_2r_geometric.toml")
    prior = replace(spec.calibration, prior=PriorSpec(length_m=1e-3, offset_rad=2e-3))
    problem = build_problem(replace(spec, calibration=prior))
    c, sigma = problem.model.column_scale, problem.sigma_m
    std = np.array([2e-3, 2e-3, 1e-3, np.inf])  # joint1.offset, joint2.offset, joint2.tx; tool.tx: none
    np.testing.assert_allclose(problem.M_held, np.diag(sigma**2 / std**2 / c**2), rtol=1e-14)
    assert problem.m_min == 1  # the prior leaves tool.tx to the plan: one experiment (2 values) does


def test_a_prior_that_names_none_of_the_parameters_is_refused(paper):
    with pytest.raises(ProblemError, match="names none of this problem's parameters") as e:
        held(paper, np.zeros((0, 2)), np.zeros((0, 2)), prior_names=("shoulder_pan_joint.offset",),
             prior_covariance=((1e-6,),), prior_file="ur10/identification.json")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("criterion", ["test-pose", "D"])
def test_the_bound_of_a_completion_holds_for_every_completion_and_is_tight(paper, criterion):
    """The certificate with a fixed part (module docstring of bound.py) is below the max error
    (above the log det) of 200 random completions of one measured experiment by two, and within
    its relaxation (tangent bounds are tight at the optimum), and the designed completion within
    a few percent of it."""
    rng = np.random.default_rng(11)
    campaign = held(paper, *random_plan(paper, 1, rng))
    approx = approximate_design(campaign, criterion, m=2, pool_size=60, sample_size=600)
    b = bound(campaign, 2, approx)
    values = [plan_scores(campaign, *random_plan(campaign, 2, rng)).value(criterion) for _ in range(200)]
    best = solve_design(campaign, criterion, 2, starts=4).scores.value(criterion)
    if criterion == "D":
        assert max(values) <= b.value and best <= b.value and b.value - b.relaxation < 1e-3 * b.L
        assert b.value - best < 0.1  # exp(0.1 / L): 5 % per parameter
    else:
        assert min(values) >= b.value and best >= b.value and b.value / b.relaxation > 0.999
        assert best / b.value < 1.05
    with pytest.raises(Exception, match="made for m = 2"):
        bound(campaign, 3, approx)
