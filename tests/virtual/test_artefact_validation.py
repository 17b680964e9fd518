"""The virtual calibration of a plan of configurations seated at an artefact's points
(virtual/artefact.py) on MUKCa's Panda: each trial's robot hand-guided into the sockets within
the seating repeatability (checked with Pinocchio's kinematics of the true robot's model),
identified by identify's own fit, judged at the test poses after registering the work; the
simulated error agrees with the predicted sqrt(rho) (the whole calibration against the linear
theory: 5 % over 800 trials in the slow test)."""

import numpy as np
import pytest

from casadi_design.identification.fit import model_points
from casadi_design.optimisation.artefact_pool import choose_clamps
from casadi_design.plan.seated import seated_configurations
from casadi_design.problem.build import load_problem
from casadi_design.virtual.artefact import seated_recordings, simulate_artefact_plan
from casadi_design.virtual.simulate import ErrorSpreads, Plan, draw_true_parameters
from tests.conftest import ROOT

PANDA = ROOT / "problems" / "panda_ball_socket.toml"


@pytest.fixture(scope="module")
def plan():
    problem = load_problem(PANDA)
    s = seated_configurations(problem, 8)
    d = choose_clamps(problem, s.Q, s.point, s.placement, s.names, "test-pose", 14, 1, 1).design
    return problem, d


def test_a_simulated_recording_seats_the_true_robot_s_ball(plan):
    problem, d = plan
    rng = np.random.default_rng(0)
    X = draw_true_parameters(problem.model, ErrorSpreads(), 3, rng)
    target = model_points(problem.model, d.Q, d.F, np.zeros(problem.model.L))[:, 0]
    X_rows = np.repeat(X, d.m, axis=0)
    Qr = seated_recordings(problem, np.tile(d.Q, (3, 1)), X_rows, np.tile(target, (3, 1)))
    reached = model_points(problem.model, Qr, np.zeros((len(Qr), 0)), X_rows)[:, 0]
    assert np.max(np.linalg.norm(reached - np.tile(target, (3, 1)), axis=1)) < 1e-9
    moved = np.linalg.norm(Qr - np.tile(d.Q, (3, 1)), axis=1)
    assert 1e-5 < np.median(moved) < 0.05  # the true robot is a little off: the hand moves it a little


def _ratio(problem, d, trials: int) -> float:
    v = simulate_artefact_plan(problem, Plan(d.criterion, d.m, d.Q, d.F), d.seated.point, d.seated.placement,
                               ErrorSpreads(), trials, np.random.default_rng(7))
    assert v.identification.non_converged <= trials // 50
    return float(np.sqrt(np.mean(v.empirical_rms_m**2) / np.mean(v.predicted_rms_m**2)))


def test_the_simulated_calibration_agrees_with_the_prediction(plan):
    problem, d = plan
    assert _ratio(problem, d, 60) == pytest.approx(1.0, abs=0.15)


@pytest.mark.slow
def test_the_simulated_calibration_agrees_with_the_prediction_within_5_percent(plan):
    problem, d = plan
    assert _ratio(problem, d, 800) == pytest.approx(1.0, abs=0.05)
