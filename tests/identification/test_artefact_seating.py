"""The push seating the ball, on a robot whose links carry no masses (MUKCa's iiwa 14): recordings
made independently of the package's model (Pinocchio's Jacobian on the true robot, its joints
deflected by ``k J^T f``), the measurement model's deflection against them, identify's choice of
the seating model where the recordings hold the push and not where they do not."""

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.errors import ProblemError
from casadi_design.identification.artefact_fit import ball_points, calibrate_artefact
from casadi_design.identification.fit import SEATING_N, fit_model
from casadi_design.identification.lsq import nominal_poses
from casadi_design.identification.recordings import Recordings
from casadi_design.problem.build import load_problem
from casadi_design.robot.mapped import evaluate
from tests.artefact_data import recordings
from tests.conftest import ROOT

IIWA = ROOT / "examples" / "iiwa14_ball_socket.toml"
#: The true robot's compliance per newton of push (rad/(N m)): about 1 mrad at joints 2, 4 and 6
#: under a push at 0.5 m, 0.5 mm at the ball.
K_TRUE = {"joint_a2": 2e-3, "joint_a4": 2e-3, "joint_a6": 3e-3}
SIGMA = 5e-5


def _pushed(problem, true, Q: np.ndarray) -> np.ndarray:
    """The encoders' readings of the true robot whose links stand at ``Q``, seated by the push
    :data:`SEATING_N`: ``Q - diag(k) J(Q)^T f`` (the deflection's fixed point is at the links'
    angles), J Pinocchio's at the measured point."""
    robot, data = problem.robot, true.model.createData()
    k = np.array([K_TRUE.get(j, 0.0) for j in robot.joints])
    cols = [true.model.joints[j].idx_v for j in robot.joint_ids]
    out = []
    for q in Q:
        J = pin.computeFrameJacobian(true.model, data, robot.full_q(q), true.frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
        out.append(q - k * (J[:, cols].T @ np.asarray(SEATING_N)))
    return np.array(out)


@pytest.fixture(scope="module")
def iiwa():
    problem = load_problem(IIWA)
    true, Q, k, g = recordings(problem, 3, 12, SIGMA)
    return problem, true, Q, k, g


def _split(Q, k, g, train: int) -> tuple[Recordings, Recordings]:
    def part(sel, name):
        return Recordings(Q[sel], k[sel], np.zeros(int(sel.sum()), int), (name,), tuple(f"{name} {i}" for i in range(int(sel.sum()))))
    return part(g == train, "train"), part(g != train, "held")


def test_the_model_deflects_the_measured_point_by_the_push_and_not_the_test_poses(iiwa):
    """The seating model's measured point at the readings ``q - k J^T f`` is where Pinocchio puts
    the nominal robot's ball at ``q`` (to the fixed point's tolerance); the test poses' error
    carries no push."""
    problem = iiwa[0]
    names = ("joint_a2.offset",) + tuple(f"k.{j}" for j in problem.robot.joints)
    fm = fit_model(problem, "base", names, seating=True)
    model = fm.model
    assert model.seating_N == SEATING_N and model.loaded and not model.gravity
    X = np.array([K_TRUE.get(n[2:], 0.0) for n in model.parameter_names])
    assert set(f"k.{j}" for j in K_TRUE) <= set(model.parameter_names)
    nominal = type(iiwa[1])(problem.robot.model, problem.robot.frame_id, np.zeros(problem.robot.n), pin.SE3.Identity())
    Q = iiwa[2][:8]
    readings = _pushed(problem, nominal, Q)
    p, _ = ball_points(model, readings, X)
    data = problem.robot.model.createData()
    expected = []
    for q in Q:
        pin.framesForwardKinematics(problem.robot.model, data, problem.robot.full_q(q))
        expected.append(data.oMf[problem.robot.frame_id].translation.copy())
    moved = np.linalg.norm(np.array(expected) - ball_points(model, readings, 0 * X)[0], axis=1)
    assert moved.min() > 1e-4  # the push moves the ball 0.1 mm or more: the check below has teeth
    assert np.max(np.linalg.norm(p - np.array(expected), axis=1)) < 1e-8
    F = np.zeros((len(Q), model.nF))
    e = np.asarray(evaluate(model.accuracy, readings, F, np.tile(X, (len(Q), 1)),
                            nominal_poses(model, readings, F))[0])
    assert np.max(np.abs(e)) < 1e-12


def test_identify_chooses_the_seating_model_where_the_recordings_hold_the_push(iiwa):
    """Recordings of the pushed robot: auto chooses the base set with the seating compliances,
    recovers them within 3 std and comes back to the seating's noise at the held-out placement;
    the same robot without the push: auto does not choose it."""
    problem, true, Q, k, g = iiwa
    train, held = _split(_pushed(problem, true, Q), k, g, 0)
    cal = calibrate_artefact(problem, train, held, with_field=False)
    assert cal.model == "identifiable + seating"
    for name, value in K_TRUE.items():  # within 3 std; joints 2 and 4, far from the ball, told well
        i = cal.names.index(f"k.{name}")
        assert abs(cal.fit.X[i] - value) < 3 * cal.std[i] and (name == "joint_a6" or cal.std[i] < value / 3)
    plain = calibrate_artefact(problem, train, held, model="identifiable", with_field=False)
    assert cal.validation[0].consistency_m < 0.5 * plain.validation[0].consistency_m
    assert cal.validation[0].consistency_m < 1.5 * cal.validation[0].predicted_consistency_m
    unpushed = calibrate_artefact(problem, *_split(Q, k, g, 0), with_field=False)
    assert unpushed.model != "identifiable + seating"


def test_the_weight_s_models_are_named_with_their_fix(iiwa):
    """Without masses, the weight's models name inertias_urdf; the seating model is fitted when named."""
    problem, _, Q, k, g = iiwa
    train, _ = _split(Q, k, g, 0)
    with pytest.raises(ProblemError, match="carry no masses.*inertias_urdf"):
        calibrate_artefact(problem, train, model="identifiable + gravity", with_field=False)
    assert calibrate_artefact(problem, train, model="identifiable + seating", with_field=False).model == \
        "identifiable + seating"


def test_the_push_bends_the_bearings_too(iiwa):
    """A bearing's tilt compliance moves the ball under the push as an axial one does."""
    problem, _, Q, _, _ = iiwa
    pushed = fit_model(problem, "base", ("k.joint_a2", "k.joint_a2.rx", "k.joint_a2.ry"), seating=True).model
    assert any(n.startswith("k.joint_a2.r") for n in pushed.parameter_names)
    _, J = ball_points(pushed, Q[:6], np.zeros(pushed.L))
    moves = np.linalg.norm(J, axis=(0, 1))  # each compliance's effect on the ball, m per rad/(N m)
    assert np.all(moves > 1e-3 * moves.max()) and moves.min() > 0


def test_the_seating_model_named_on_a_robot_with_masses():
    """Named on a Panda, whose links' masses are known (auto takes their weight's model), the
    seating model is fitted: the push's compliances, not the weight's; the two models of the same
    names are two (the cache keeps them apart)."""
    problem = load_problem(ROOT / "problems" / "panda_ball_socket.toml")
    names = ("panda_joint2.offset", "k.panda_joint2", "k.panda_joint4")
    pushed, weighed = (fit_model(problem, "base", names, seating=True).model,
                       fit_model(problem, "base", names, gravity=True).model)
    assert pushed is not weighed and weighed.seating_N is None and pushed.seating_N == SEATING_N and weighed.gravity
    _, Q, k, g = recordings(problem, 1, 10, SIGMA)
    train, _ = _split(Q, k, g, 0)
    cal = calibrate_artefact(problem, train, model="identifiable + seating", with_field=False)
    model = cal.fit.fit.model
    assert cal.model == "identifiable + seating" and model.seating_N == SEATING_N and not model.gravity
    assert any(n.startswith("k.") for n in cal.names)
