"""The NLP along the seated configurations (optimisation/seated_nlp.py) on MUKCa's Panda: its
graph of rho is the pool engine's (to 1e-7: M's condition number is 1e4), and IPOPT's plan keeps every ball in its socket
(Pinocchio's kinematics), every hand within the tilt and the limits, and lowers the exchange's
max error, recorded among the design's starts."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from casadi_design.optimisation.artefact_pool import artefact_scores, choose_clamps
from casadi_design.optimisation.seated_nlp import SEATED_NLP, seated_graph, seated_nlp
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
    rho, log_det, seat, sockets, _ = seated_graph(problem, d)
    r = np.asarray(rho(d.Q.T), dtype=float).ravel()
    np.testing.assert_allclose(problem.sigma_m * np.sqrt(r), d.scores.rms_error_m, rtol=1e-7)
    assert np.max(np.abs(np.asarray(seat(d.Q.T), dtype=float).ravel()[:3 * d.m])) < 1e-7
    assert float(log_det(d.Q.T)) == pytest.approx(d.scores.value("D"), abs=1e-6)


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
