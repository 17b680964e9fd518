"""The unmodelled error's field estimated by identify (identification/field_fit.py): its restricted
likelihood against scikit-learn's Gaussian process regression and finite differences, a known
field recovered, and the field of IPA's UR10 (tests/data/ipa_ur10) carried through
identification.json into the design of a second round."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.cli.identify import load_without_cell
from casadi_design.identification.calibrate import calibrate
from casadi_design.identification.field_fit import (
    estimate_field,
    joints_log_likelihood,
    restricted_log_likelihood,
)
from casadi_design.identification.fit import model_points
from casadi_design.identification.held import read_held
from casadi_design.identification.lsq import nominal_poses
from casadi_design.identification.measurements import FileFormat, read_measurements
from casadi_design.measures.field import Field, own_variance
from casadi_design.optimisation.solve import plan_scores
from casadi_design.problem.build import build_problem

DATA = Path(__file__).parents[1] / "data" / "ipa_ur10"
PROBLEM = DATA / "ipa_ur10.toml"
SERIES_C = DATA / "measurements_random_poses_xyz.csv"
FORMAT = FileFormat(units="mm", columns=(("measurement_x", "meas_x"), ("measurement_y", "meas_y"),
                                         ("measurement_z", "meas_z")))
THETA = np.log([2e-4, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 3e-5])
SIGMA = 2e-5


def test_without_parameters_it_is_scikit_learn_s_marginal_likelihood():
    gp = pytest.importorskip("sklearn.gaussian_process")
    kernels = pytest.importorskip("sklearn.gaussian_process.kernels")
    rng = np.random.default_rng(0)
    Q, r = rng.normal(size=(30, 6)), rng.normal(size=(30, 3)) * 1e-4
    mine, _ = restricted_log_likelihood(THETA, r, np.zeros((30, 3, 0)), Q, np.eye(3), SIGMA)
    kernel = (kernels.ConstantKernel(np.exp(THETA[0]) ** 2) * kernels.RBF(np.exp(THETA[1:7]))
              + kernels.WhiteKernel(np.exp(THETA[7]) ** 2))
    reference = gp.GaussianProcessRegressor(kernel, alpha=SIGMA**2, optimizer=None).fit(Q, r)
    assert mine == pytest.approx(reference.log_marginal_likelihood_value_, rel=1e-12)


def test_the_additive_field_is_scikit_learn_s_sum_of_one_joint_kernels():
    """The field additive over the joints (an error of the joint angles): scikit-learn's sum of
    RBF kernels each on one joint (the others' lengths 1e6: constant to 1e-12 over the poses)."""
    gp = pytest.importorskip("sklearn.gaussian_process")
    kernels = pytest.importorskip("sklearn.gaussian_process.kernels")
    rng = np.random.default_rng(3)
    Q, r = rng.normal(size=(30, 6)), rng.normal(size=(30, 3)) * 1e-4
    theta = np.log([1e-4, 2e-4, 5e-5, 3e-5, 1e-5, 8e-5, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 3e-5])
    mine, _ = restricted_log_likelihood(theta, r, np.zeros((30, 3, 0)), Q, np.eye(3), SIGMA, additive=True)
    kernel = kernels.WhiteKernel(np.exp(theta[-1]) ** 2)
    for j in range(6):
        ell = np.full(6, 1e6)
        ell[j] = np.exp(theta[6 + j])
        kernel = kernel + kernels.ConstantKernel(np.exp(theta[j]) ** 2) * kernels.RBF(ell)
    reference = gp.GaussianProcessRegressor(kernel, alpha=SIGMA**2, optimizer=None).fit(Q, r)
    assert mine == pytest.approx(reference.log_marginal_likelihood_value_, rel=1e-9)
    # the field's own kernel is the same sum: scale^2 = sum s_l^2, shares s_l^2 / scale^2
    s2 = np.exp(2 * theta[:6])
    field = Field(float(np.sqrt(s2.sum())), tuple(np.exp(theta[6:12])), 0.0, tuple(s2 / s2.sum()))
    np.testing.assert_allclose(field.kernel(Q, Q[:5]), reference.kernel_(Q, Q[:5]),  # (its white part: 0 here)
                               rtol=1e-9, atol=1e-22)


def test_the_gradient_is_the_finite_differences_of_the_likelihood():
    """With parameters, markers coupled by a whitening (``A`` not diagonal)."""
    rng = np.random.default_rng(1)
    Q, r, J = rng.normal(size=(25, 6)), rng.normal(size=(25, 3)) * 1e-4, rng.normal(size=(25, 3, 4)) * 1e-2
    A = np.array([[1.0, 0.2, 0.0], [0.2, 1.0, 0.0], [0.0, 0.0, 0.5]])
    h = 1e-6
    additive = np.log([1e-4, 2e-4, 5e-5, 3e-5, 1e-5, 8e-5, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 3e-5])
    for theta, kind in ((THETA, False), (additive, True)):
        _, grad = restricted_log_likelihood(theta, r, J, Q, A, SIGMA, kind)
        fd = [(restricted_log_likelihood(theta + h * e, r, J, Q, A, SIGMA, kind)[0]
               - restricted_log_likelihood(theta - h * e, r, J, Q, A, SIGMA, kind)[0]) / (2 * h)
              for e in np.eye(len(theta))]
        np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-3)


def test_the_joints_gradient_is_the_finite_differences_of_the_likelihood():
    """The field of the joint angles (dense V): with parameters, loads that couple the values."""
    rng = np.random.default_rng(4)
    Q, r, J = rng.normal(size=(20, 6)), rng.normal(size=(20, 3)) * 1e-4, rng.normal(size=(20, 3, 4)) * 1e-2
    A = np.array([[1.0, 0.2, 0.0], [0.2, 1.0, 0.0], [0.0, 0.0, 0.5]])
    field = Field(0.0, (1.0,) * 6, 0.0, (), (1.0,) * 6)
    S = field.sites(Q, np.arange(3), np.eye(3), rng.normal(size=(20, 3, 6)) * 0.5)
    S = type(S)(S.Q, S.G, A)
    theta = np.log([3e-4, 2e-4, 4e-4, 1e-4, 2e-4, 5e-4, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 3e-5])
    h = 1e-6
    _, grad = joints_log_likelihood(theta, r, J, S, SIGMA)
    fd = [(joints_log_likelihood(theta + h * e, r, J, S, SIGMA)[0]
           - joints_log_likelihood(theta - h * e, r, J, S, SIGMA)[0]) / (2 * h) for e in np.eye(len(theta))]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-3)
    # its value is the restricted likelihood of the same covariance built densely
    from casadi_design.measures.field import value_covariance

    V = value_covariance(Field(0.0, tuple(np.exp(theta[6:12])), float(np.exp(theta[-1])), (),
                               tuple(np.exp(theta[:6]))), S, SIGMA)
    Sx, rr = J.reshape(60, 4), r.reshape(60)
    Vi = np.linalg.inv(V)
    Pi = Vi - Vi @ Sx @ np.linalg.solve(Sx.T @ Vi @ Sx, Sx.T @ Vi)
    expected = -0.5 * (rr @ Pi @ rr + np.linalg.slogdet(V)[1] + np.linalg.slogdet(Sx.T @ Vi @ Sx)[1]
                       + 56 * math.log(2 * math.pi))
    assert joints_log_likelihood(theta, r, J, S, SIGMA)[0] == pytest.approx(expected, rel=1e-10)


def joint_angle_residuals(angles, lengths, m: int, seed: int):
    """Residuals of angle errors of len(angles) joints through random loads, the tracker's noise,
    four parameters profiled out: (r, J, Q, G)."""
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-2, 2, size=(m, len(angles)))
    G = rng.normal(size=(m, 3, len(angles))) * 0.7  # m per rad
    g = np.stack([np.linalg.cholesky(s**2 * np.exp(-0.5 * ((Q[:, None, c] - Q[None, :, c]) / ell) ** 2)
                                     + 1e-12 * s**2 * np.eye(m)) @ rng.normal(size=m)
                  for c, (s, ell) in enumerate(zip(angles, lengths))], axis=1)
    J = rng.normal(size=(m, 3, 4)) * 1e-2
    y = np.einsum("mdl,l->md", J, rng.normal(size=4) * 1e-3) + np.einsum("mvc,mc->mv", G, g)
    y += SIGMA * rng.normal(size=y.shape)
    S = J.reshape(-1, 4)
    return (y.reshape(-1) - S @ np.linalg.lstsq(S, y.reshape(-1), rcond=None)[0]).reshape(m, 3), J, Q, G


def test_joints_alike_are_told_by_the_aic():
    """Three joints with the same angle error (80 arcsec) and length (0.15 rad), 120 poses: the AIC
    keeps one angle and one length for every joint, within 25 % (a seeded draw: between nested
    models the AIC keeps the larger with a probability of about P(chi2_4 > 8) = 9 %)."""
    r, J, Q, G = joint_angle_residuals([4e-4] * 3, [0.15] * 3, 120, 8)
    found = estimate_field(r, J, Q, np.arange(3), np.eye(3), SIGMA, G).field
    assert found.through_joints and len(set(found.angles_rad)) == 1 and len(set(found.lengths)) == 1
    assert found.angles_rad[0] == pytest.approx(4e-4, rel=0.25) and found.lengths[0] == pytest.approx(0.15, rel=0.25)


def test_a_known_error_of_the_joint_angles_is_recovered():
    """Residuals drawn from angle errors of three joints (60, 100 and 40 arcsec, lengths 0.1 to
    0.3 rad) through random loads, the tracker's noise, four parameters profiled out, 150 poses:
    the AIC chooses the field of the joint angles, one angle per joint, within 30 %."""
    angles = np.array([3e-4, 5e-4, 2e-4])
    r, J, Q, G = joint_angle_residuals(angles, [0.1, 0.2, 0.3], 150, 6)
    found = estimate_field(r, J, Q, np.arange(3), np.eye(3), SIGMA, G).field
    assert found.through_joints
    np.testing.assert_allclose(found.angles_rad, angles, rtol=0.3)


def test_a_known_field_is_recovered():
    """Residuals drawn from a field (scale 0.25 mm, lengths 0.8 rad, nugget 0.03 mm) and the
    tracker's noise at 200 random configurations, three axes, with four parameters profiled
    out: the scale within 25 %, the lengths of the joints within a factor 2."""
    rng = np.random.default_rng(2)
    truth = Field(2.5e-4, (0.8,) * 4, 3e-5)
    Q = rng.uniform(-2, 2, size=(200, 4))
    K = truth.kernel(Q, Q) + truth.nugget_m**2 * np.eye(200) + SIGMA**2 * np.eye(200)
    delta = np.linalg.cholesky(K) @ rng.normal(size=(200, 3))
    J = rng.normal(size=(200, 3, 4)) * 1e-2
    X = rng.normal(size=4) * 1e-3
    y = np.einsum("mdl,l->md", J, X) + delta
    S = J.reshape(600, 4)
    r = (y.reshape(-1) - S @ np.linalg.lstsq(S, y.reshape(-1), rcond=None)[0]).reshape(200, 3)
    found = estimate_field(r, J, Q, np.arange(3), np.eye(3), SIGMA).field
    assert found.scale_m == pytest.approx(truth.scale_m, rel=0.25)
    assert np.all((np.array(found.lengths) > 0.4) & (np.array(found.lengths) < 1.6)), found.lengths


@pytest.fixture(scope="module")
def ipa():
    problem = load_without_cell(str(PROBLEM))
    meas = read_measurements(problem, str(SERIES_C), FORMAT)
    rows = np.random.default_rng(0).permutation(meas.m)
    return problem, meas.subset(np.sort(rows[:40])), meas.subset(np.sort(rows[40:]))


def test_identify_estimates_the_field_and_compensates_with_it(ipa):
    """40 rows of IPA's UR10: the field is estimated (its scale about the unmodelled error), the
    held-out error with its kriging mean is below the calibrated model's alone, and the
    compensated test poses put the calibrated robot plus the field's mean on the targets."""
    problem, training, held_out = ipa
    cal = calibrate(problem, training, validation=held_out)
    field = cal.field
    # an error of the joint angles (scripts/joint_error_scan.py), its std per axis about the unmodelled error's
    assert field is not None and field.field.through_joints
    per_axis = np.sqrt(np.mean(own_variance(field.field, field.at(training.Q, rows="position"))) / 3)
    assert 0.5 < per_axis / cal.scale.tau_m < 2
    v = cal.validation
    assert v.rms("field") < v.rms("calibrated")
    assert np.all(cal.predicted_field_m <= cal.predicted_rms_m + 1e-12)
    # the measured point is the frame's origin (one point, tool_xyz_m): the calibrated robot at the
    # compensated commands, moved by the field's mean, is on the nominal targets
    model, tp = cal.fit.fit.model, cal.problem.test_poses
    reached = model_points(model, cal.q_compensated, tp.F, cal.fit.robot_X)[:, 0] + field.shift(tp.q)
    assert cal.compensation_converged.all()
    np.testing.assert_allclose(reached, nominal_poses(model, tp.q, tp.F)[:, 9:], rtol=0, atol=2e-6)
    assert np.max(np.linalg.norm(field.shift(tp.q), axis=1)) > 1e-5  # a correction, not nothing
    # the measured point is the frame's origin: the kriging mean of the measured values (through
    # dy/dq) is the frame's (through dp/dq)
    np.testing.assert_allclose(field.marker_shift(tp.q, tp.F)[:, 0], field.shift(tp.q), rtol=1e-9, atol=1e-12)


def test_a_second_round_designs_with_the_first_round_s_field(ipa, tmp_path, capsys):
    """identification.json carries the field and its poses; --prior reads them: the test-pose
    measure of a plan is the kriging variance of the first round's poses and the plan's."""
    problem, training, _ = ipa
    lines = SERIES_C.read_text().splitlines()
    rows = [lines[0]] + [lines[i + 1] for i in np.flatnonzero(np.isin(np.arange(len(lines) - 1),
                                                                       np.array(training.lines) - 2))]
    (tmp_path / "r1.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "id1"
    assert main(["identify", str(PROBLEM), "--measurements", str(tmp_path / "r1.csv"), "--units", "mm",
                 "--columns", "measurement_x=meas_x,measurement_y=meas_y,measurement_z=meas_z",
                 "--out", str(out), "-q"]) == 0
    record = json.loads((out / "identification.json").read_text())
    # the compensated test poses are a plan: program writes them (its robot targets)
    assert main(["program", str(PROBLEM), "--plan", str(out / "compensated_test_poses.csv"), "--format", "json",
                 "--out", str(tmp_path / "program"), "-q"]) == 0
    targets = json.loads((tmp_path / "program" / "program.json").read_text())
    assert len(targets["order"]) == len(record["test_poses"]["q_compensated"])
    error = record["model_error"]
    assert max(error["angles_rad"]) > 2e-4 and len(error["angles_rad"]) == len(error["lengths"]) == 6
    assert len(error["poses"]["q"]) == 40
    held = read_held(problem, None, str(out / "identification.json"))
    assert held.prior_model_error.angle_rad == tuple(error["angles_rad"]) and len(held.prior_q) == 40
    import dataclasses

    second = build_problem(dataclasses.replace(problem.spec, held=held))
    assert second.field is not None and len(second.field_held[0]) == 40
    Q = training.Q[:8]
    scores = plan_scores(second, Q, training.F[:8])
    assert math.isfinite(scores.max_rms_error_m) and scores.max_rms_error_m > 10 * problem.sigma_m


def test_a_user_s_poses_are_compensated_as_the_test_poses(ipa):
    """compensated(cal, Q) on the test poses gives compensated_test_poses.csv's commands, and on
    other poses puts the calibrated robot plus the field's mean on their nominal targets."""
    from casadi_design.identification.calibrate import compensated

    problem, training, held_out = ipa
    cal = calibrate(problem, training)
    tp = cal.problem.test_poses
    q, ok = compensated(cal, tp.q)
    np.testing.assert_allclose(q, cal.q_compensated, rtol=0, atol=1e-12)
    Q = held_out.Q[:5]
    q, ok = compensated(cal, Q)
    model = cal.fit.fit.model
    shift = cal.field.shift(Q) if cal.field_compensates else 0.0
    reached = model_points(model, q, np.zeros((5, 0)), cal.fit.robot_X)[:, 0] + shift
    assert ok.all()
    np.testing.assert_allclose(reached, nominal_poses(model, Q, np.zeros((5, 0)))[:, 9:], rtol=0, atol=2e-6)


def test_an_error_of_the_joint_angles_turns_the_targets_back():
    """The UR10 of the drilling cell, the test poses' orientation required too, a field of the
    joint angles trained on 15 poses' residuals: the compensated commands put the nominal robot's
    frame at the target moved against the field's mean position and turned back by its mean turn
    (``R = exp(-[w]) R_target``), and the turn is the kriging mean of the orientation rows."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from casadi_design.identification.calibrate import corrected_commands
    from casadi_design.identification.field_fit import FieldFit, TrainedField
    from casadi_design.plan.sampling import random_plan

    plain = load_without_cell(str(Path(__file__).parents[2] / "problems" / "ur10_drilling.toml"))
    spec = plain.spec
    problem = build_problem(dataclasses.replace(spec, test_poses=dataclasses.replace(
        spec.test_poses, components=("x", "y", "z", "rx", "ry", "rz"))))
    model, tp = problem.model, problem.test_poses
    field = Field(0.0, (0.3,) * 6, 1e-5, (), (4e-4,) * 6)
    Q, F = random_plan(problem, 15, np.random.default_rng(2))
    S = field.sites(Q, problem.field_axes[0], problem.whitening, model.dq_stack(Q, F))
    r = np.random.default_rng(3).normal(size=(15, model.d)) * 3e-4
    trained = TrainedField(FieldFit(field, 0.0, 15), S, r, model.B_stack(Q, F), problem.whitening,
                           problem.sigma_m, model)
    q0, F0 = tp.q[:5], tp.F[:5]
    w = trained.turn(q0, F0)
    assert np.max(np.abs(w)) > 1e-5  # a turn of some arcsec
    np.testing.assert_allclose(w, trained.mean(trained.at(q0, F0))[:, 3:], rtol=1e-12)
    qc, ok = corrected_commands(model, np.zeros(model.L), q0, F0, problem.sigma_m, trained)
    assert ok.all()
    reached, target = nominal_poses(model, qc, F0), nominal_poses(model, q0, F0)
    np.testing.assert_allclose(reached[:, 9:], target[:, 9:] - trained.shift(q0), rtol=0, atol=1e-8)
    R = reached[:, :9].reshape(-1, 3, 3).transpose(0, 2, 1)
    R0 = target[:, :9].reshape(-1, 3, 3).transpose(0, 2, 1)
    turned = Rotation.from_matrix(R @ R0.transpose(0, 2, 1)).as_rotvec()
    np.testing.assert_allclose(turned, -w, rtol=0, atol=1e-9)
