"""The NLP along the seated configurations (optimisation/seated_nlp.py) on MUKCa's Panda: its
graph of rho is the pool engine's (to 1e-7: M's condition number is 1e4), and IPOPT's plan keeps every ball in its socket
(Pinocchio's kinematics), every hand within the tilt and the limits, and lowers the exchange's
max error, recorded among the design's starts."""

import casadi as ca
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from casadi_design.optimisation.artefact_pool import artefact_scores, choose_clamps
from casadi_design.measures.criteria import CRITERIA
from casadi_design.optimisation.seated_nlp import SEATED_NLP, CriterionOfM, seated_graph, seated_nlp
from casadi_design.plan.seated import seated_configurations
from casadi_design.problem.build import load_problem
from casadi_design.robot.robots import frame_placement
from tests.conftest import ROOT

PANDA = ROOT / "problems" / "panda_ball_socket.toml"


@pytest.fixture(scope="module")
def exchanged():
    problem = load_problem(PANDA)
    s = seated_configurations(problem, 8)
    return problem, choose_clamps(problem, s.Q, s.point, s.placement, s.names, "test-pose", 12, 1, 1).design


def test_the_graph_is_the_engine_s_measure(exchanged):
    problem, d = exchanged
    rho, information, seat, sockets, _, _ = seated_graph(problem, d)
    r = np.asarray(rho(d.Q.T), dtype=float).ravel()
    np.testing.assert_allclose(problem.sigma_m * np.sqrt(r), d.scores.rms_error_m, rtol=1e-7)
    assert np.max(np.abs(np.asarray(seat(d.Q.T), dtype=float).ravel()[:3 * d.m])) < 1e-7
    M = np.asarray(information(d.Q.T), dtype=float)
    assert np.linalg.slogdet(M)[1] == pytest.approx(d.scores.value("D"), abs=1e-6)
    assert np.trace(np.linalg.inv(M)) == pytest.approx(d.scores.value("A"), rel=1e-7)
    assert np.sqrt(np.linalg.eigvalsh(M)[0]) == pytest.approx(d.scores.value("E"), rel=1e-7)


@pytest.mark.parametrize("criterion, power", [("D", 0.0), ("A", 0.0), ("I", 0.0), ("E", 16.0), ("condition", 4.0)])
def test_a_criterion_of_m_is_its_objective_and_its_jacobian_the_gradient(exchanged, criterion, power):
    """phi(M) / L (log phi for A and I) and its Jacobian through CasADi against central differences along random
    symmetric directions congruent to M (M +- h E stays positive definite), at the exchange's M
    made better conditioned (central differences lose the digits of a condition number of 1e9)."""
    problem, d = exchanged
    _, information, _, _, _, B0 = seated_graph(problem, d)
    M0 = np.asarray(information(d.Q.T), dtype=float)
    M0 = M0 / np.trace(M0) * len(M0) + 0.01 * np.eye(len(M0))  # O(1) entries as the NLP's; condition 1e9 -> 1e3
    crit = CRITERIA[criterion]
    L = len(M0)
    phi = CriterionOfM(crit.objective, crit.objective.weights(B0), power, L, L)
    X = ca.MX.sym("M", L, L)
    grad = ca.Function("g", [X], [ca.jacobian(phi(X), X)])
    G = np.asarray(grad(M0), dtype=float).reshape(L, L, order="F")
    rng, C = np.random.default_rng(1), np.linalg.cholesky(M0)
    for _ in range(3):
        S = rng.standard_normal((L, L))
        E = C @ (S + S.T) @ C.T  # M0 +- h E = C (I +- h (S + S^T)) C^T stays positive definite
        h = 1e-5
        fd = (float(phi(M0 + h * E)) - float(phi(M0 - h * E))) / (2 * h)
        assert np.sum(G * E) == pytest.approx(fd, rel=1e-5, abs=1e-10)


@pytest.mark.slow  # 11 s: four powers of E's surrogate
@pytest.mark.parametrize("criterion", ["E"])
def test_the_nlp_improves_every_criterion_s_exchange_plan_and_keeps_it_seated(criterion):
    problem = load_problem(PANDA)
    s = seated_configurations(problem, 8)
    d = choose_clamps(problem, s.Q, s.point, s.placement, s.names, criterion, 12, 1, 1).design
    refined = seated_nlp(problem, d)
    crit = CRITERIA[criterion]
    assert all(r.origin.startswith(SEATED_NLP) for r in refined.starts[-max(1, len(crit.powers)):])
    assert crit.better(refined.scores.value(criterion), d.scores.value(criterion))
    again = artefact_scores(problem, refined.Q, refined.seated.point, refined.seated.placement)
    assert again.value(criterion) == pytest.approx(refined.scores.value(criterion), rel=1e-12)
    _, _, seat, _, _, _ = seated_graph(problem, refined)
    assert np.max(np.abs(np.asarray(seat(refined.Q.T), dtype=float).ravel()[:3 * d.m])) < 1e-7


def test_the_nlp_keeps_the_balls_seated_and_lowers_the_max_error(exchanged):
    problem, d = exchanged
    refined = seated_nlp(problem, d)
    assert [r.origin for r in refined.starts[-2:]] == [f"{SEATED_NLP} (8-mean)", f"{SEATED_NLP} (32-mean)"]
    assert refined.scores.max_rms_error_m < 0.95 * d.scores.max_rms_error_m
    again = artefact_scores(problem, refined.Q, refined.seated.point, refined.seated.placement)
    assert again.max_rms_error_m == pytest.approx(refined.scores.max_rms_error_m, rel=1e-12)
    spec = problem.spec.measurement.artefact
    robot = problem.robot
    for q, k, g in zip(refined.Q, refined.seated.point, refined.seated.placement):
        place = next(p for p in spec.placements if p.name == refined.seated.names[g])
        R = Rotation.from_euler("xyz", place.rpy_rad).as_matrix()
        M = frame_placement(robot, q)
        assert np.linalg.norm(M.translation - (np.array(place.xyz_m) + R @ problem.artefact.points_m[k])) < 1e-7
        assert -M.rotation[:, 2] @ R[:, 2] >= np.cos(spec.tilt_max_rad) - 1e-6
        assert np.all(q >= robot.q_min) and np.all(q <= robot.q_max)
