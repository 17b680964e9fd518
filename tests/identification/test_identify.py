"""casadi-design identify: the robot identified from measured points made independently of the
package's error model (tests/identify_data.py: a perturbed Pinocchio model, a tracker rotated
133 deg and metres away, noise sigma)."""

import json
import re

import numpy as np
import pinocchio as pin
import pytest
from scipy.stats import chi2

from casadi_design.cli import main
from casadi_design.cli.identify import load_without_cell
from casadi_design.errors import ProblemError
from casadi_design.identification import lsq
from casadi_design.identification.calibrate import calibrate
from casadi_design.identification.fit import model_points
from casadi_design.identification.measurements import read_measurements
from casadi_design.calibrated.report import identification_record, tracker_std
from casadi_design.plan.sampling import random_plan
from casadi_design.robot.robots import frame_placement, make_robot
from casadi_design.virtual import identify as virtual_identify
from tests.conftest import ROOT
from tests.identify_data import angle_between, measured, measurement_csv, perturbed, true_points

UR10 = ROOT / "problems" / "ur10_drilling.toml"
PAPER = ROOT / "problems" / "paper_planar_2r.toml"
ABB = ROOT / "problems" / "abb_irb6640_machining.toml"
#: Held-out positions: the calibrated model's RMS error below this quantile of its law.
HELD_OUT_QUANTILE = 0.999
#: Estimates within this many standard deviations of the truth.
SIGMAS = 3.0
#: The exported URDF and the fit's model agree to this (m).
EXPORT_TOL_M = 1e-10


def rms(v):
    return float(np.sqrt(np.mean(np.square(v))))


@pytest.fixture(scope="module")
def ur10():
    return load_without_cell(str(UR10))


def held_out_bound(cal, valid) -> float:
    """``HELD_OUT_QUANTILE`` of the RMS error (m) of the calibrated model at the validation
    points: the errors (model error and the validation's noise) are ``N(0, C)``,
    ``C = sigma^2 (B_v M^-1 B_v^T + I)``, and ``|e|^2 ~ trace(C) / nu chi2(nu)``,
    ``nu = trace(C)^2 / trace(C^2)`` (Satterthwaite)."""
    model, sigma = cal.fit.fit.model, cal.problem.sigma_m
    B = model.B_stack(valid.Q, valid.F).reshape(-1, model.L)
    C = sigma**2 * (B @ np.linalg.solve(cal.fit.information, B.T) + np.eye(len(B)))
    nu = np.trace(C) ** 2 / np.sum(C * C)
    return float(np.sqrt(np.trace(C) / valid.seen.sum() * chi2.ppf(HELD_OUT_QUANTILE, nu) / nu))


def write_measurements(path, problem, true, m, seed, hidden=()):
    """A measurement CSV of ``m`` random feasible poses of ``problem`` measured on ``true``."""
    Q, F = random_plan(problem, m, np.random.default_rng(seed))
    P = measured(problem, true, Q, F, np.random.default_rng(seed + 100))
    path.write_text(measurement_csv(problem, Q, F, P, hidden))
    return Q, F, P


@pytest.fixture(scope="module")
def ur10_files(ur10, tmp_path_factory):
    """The UR10 perturbed everywhere (joint 1 too), 12 measured rows and 30 validation rows."""
    folder = tmp_path_factory.mktemp("ur10")
    true = perturbed(ur10, np.random.default_rng(1))
    write_measurements(folder / "meas.csv", ur10, true, 12, 2)
    write_measurements(folder / "valid.csv", ur10, true, 30, 3)
    return folder, true


def test_validate_and_identify_share_one_identification():
    assert virtual_identify.identify_nonlinear is lsq.identify_nonlinear


def test_ur10_held_out_positions_within_the_predicted_accuracy_and_urdf_export(ur10, ur10_files, tmp_path, capsys):
    folder, _ = ur10_files
    out = tmp_path / "out"
    assert main(["identify", str(UR10), "--measurements", str(folder / "meas.csv"),
                 "--validation", str(folder / "valid.csv"), "--out", str(out), "--model", "identifiable"]) == 0
    printed = capsys.readouterr().out
    record = json.loads((out / "identification.json").read_text())
    v = record["validation"]
    # the nominal model after its best registration is millimetres off; the calibrated model
    # meets the predicted accuracy on poses it never saw
    assert v["nominal_rms_m"] > 1e-3
    assert record["noise"]["consistent"] and record["least_squares"]["converged"]
    # errors of the base and of joint 1's placement (before it turns) move the whole robot
    # rigidly, and so does a turn about joint 1's axis anywhere before joint 2 moves (joint 2's
    # x axis is joint 1's z: its origin turns pi/2 about y): the tracker frame takes all of
    # them and nothing else
    rigid = {p for p in ur10.model.parameter_names if p.startswith(("base.", "shoulder_pan_joint."))}
    turn = {"shoulder_lift_joint.rx"} & set(ur10.model.parameter_names)
    assert rigid and {a["name"] for a in record["absorbed"]} == rigid | turn
    assert "validation, 30 rows" in printed and "warning" not in printed

    problem = ur10
    meas = read_measurements(problem, str(folder / "valid.csv"))
    cal = calibrate(problem, read_measurements(problem, str(folder / "meas.csv")), validation=meas, model="identifiable")
    assert v["calibrated_rms_m"] == pytest.approx(rms(cal.validation.calibrated_m))
    assert v["calibrated_rms_m"] <= held_out_bound(cal, meas) < 0.1 * v["nominal_rms_m"]
    # calibrated.urdf loaded by Pinocchio puts the measured point where the calibrated model does
    robot = make_robot(pin.buildModelFromUrdf(str(out / "calibrated.urdf")), "measured_point", {})
    urdf_points = np.array([frame_placement(robot, q).translation for q in meas.Q])
    model = model_points(cal.fit.fit.model, meas.Q, meas.F, cal.fit.robot_X)[:, 0]
    assert np.max(np.abs(urdf_points - model)) < EXPORT_TOL_M
    # ... and calibrated.toml is a problem file of that robot
    again = load_without_cell(str(out / "calibrated.toml"))
    assert np.allclose(again.test_poses.q, problem.test_poses.q)
    assert np.max(np.abs(np.array([frame_placement(again.robot, q).translation for q in meas.Q]) - model)) < EXPORT_TOL_M
    # the compensated commands put the calibrated robot's point on the nominal targets
    rows = np.genfromtxt(out / "compensated_test_poses.csv", delimiter=",", names=True, dtype=None, encoding=None)
    qc = np.column_stack([rows[f"{j}_rad"] for j in problem.robot.joints])
    reached = np.array([frame_placement(again.robot, q).translation for q in qc])
    assert np.max(np.abs(reached - problem.test_poses.position_m)) < 1e-8
    assert rows["converged"].all()


def test_tracker_frame_recovered(ur10, tmp_path):
    """Without errors that act as a motion of the whole robot (the frame absorbs them), the
    identified tracker frame is the true one within 3 of its standard deviations."""
    true = perturbed(ur10, np.random.default_rng(5), base_like=False)
    write_measurements(tmp_path / "meas.csv", ur10, true, 12, 6)
    cal = calibrate(ur10, read_measurements(ur10, str(tmp_path / "meas.csv")), model="identifiable")
    T, std = cal.fit.tracker_from_base, tracker_std(cal)
    assert np.all(np.abs(T[:3, 3] - true.tracker.translation) <= SIGMAS * std[:3, 3])
    assert np.all(np.abs(T[:3, :3] - true.tracker.rotation) <= SIGMAS * std[:3, :3] + 1e-12)
    assert angle_between(T[:3, :3], true.tracker.rotation) < 1e-4


def test_outlier_found_and_excluded(ur10, tmp_path):
    true = perturbed(ur10, np.random.default_rng(1))
    Q, F = random_plan(ur10, 14, np.random.default_rng(2))
    P = measured(ur10, true, Q, F, np.random.default_rng(4))
    P[6, 0, 1] += 0.5e-3  # a bad shot: 20 sigma
    (tmp_path / "meas.csv").write_text(measurement_csv(ur10, Q, F, P))
    cal = calibrate(ur10, read_measurements(ur10, str(tmp_path / "meas.csv")))
    assert [line for line, _, _ in cal.outliers] == [8]  # header is line 1: row 6 is line 8
    # judged against the other rows' error, which is the tracker's noise here
    assert cal.outliers[0][1] > 4 and cal.outliers[0][2] == ur10.sigma_m
    assert not cal.fit.used[6] and cal.noise_consistent and cal.scale.tau_m == 0


def compliances_within_sigmas(cal, problem, true):
    names = [n for n in cal.names if n.startswith("k.")]
    assert names
    for n in names:
        i = cal.names.index(n)
        k = true.k[problem.robot.joints.index(n[2:])]
        assert abs(cal.fit.X[i] - k) <= SIGMAS * cal.std[i], (n, cal.fit.X[i], k, cal.std[i])


def test_paper_elastostatic_compliances_within_3_sigma(tmp_path):
    problem = load_without_cell(str(PAPER))
    rng = np.random.default_rng(7)
    true = perturbed(problem, rng, k=np.array([4e-5, 7e-5]))
    true = type(true)(pin.Model(problem.robot.model), true.frame_id, true.k, true.tracker)  # geometry known
    write_measurements(tmp_path / "meas.csv", problem, true, 8, 8)
    cal = calibrate(problem, read_measurements(problem, str(tmp_path / "meas.csv")), model="identifiable")
    assert cal.fit.fit.frame_names == ("base.tx", "base.ty", "base.rz")  # a planar tracker frame
    compliances_within_sigmas(cal, problem, true)
    assert any(n.startswith("an elasto-static plan is designed for points measured in the robot's base frame")
               for n in cal.notes)


def test_compliances_that_absorb_geometric_errors_are_flagged(tmp_path):
    """The paper's arm with geometric errors the elasto-static model does not hold, five rows:
    the residuals are 7x the tracker's noise, so the compliances' std holds the unmodelled
    error (joint 2 comes out negative, within its noise, the truth within 1 std), and the
    calibrated robot misses the validation rows by more than registration only; said, with
    what to do."""
    problem = load_without_cell(str(PAPER))
    true = perturbed(problem, np.random.default_rng(4), k=np.array([4e-5, 7e-5]))
    write_measurements(tmp_path / "meas.csv", problem, true, 5, 14)
    write_measurements(tmp_path / "valid.csv", problem, true, 20, 54)
    cal = calibrate(problem, read_measurements(problem, str(tmp_path / "meas.csv")), model="identifiable",
                    validation=read_measurements(problem, str(tmp_path / "valid.csv")))
    i = cal.fit.fit.model.parameter_names.index("k.joint2")
    assert cal.scale.tau_m > 5 * problem.sigma_m and not cal.noise_consistent
    assert -2 * cal.std[i] < cal.fit.X[i] < 0 and abs(cal.fit.X[i] - true.k[1]) < cal.std[i]
    assert not any("negative compliance" in n for n in cal.notes)
    v = cal.validation
    worse = f"({v.rms('calibrated') * 1e3:.3f} against {v.rms('registration') * 1e3:.3f} mm RMS)"
    assert v.rms("calibrated") > 1.05 * v.rms("registration")
    assert f"the calibrated robot is farther from the validation rows than registration only {worse}: do not use " \
           "its files" in " ".join(cal.notes)


@pytest.mark.slow  # 4 s: building the ABB's model and its Taylor Jacobian (41 parameters); the
# default run identifies the ABB with a hidden marker in tests/cli/test_every_command.py
def test_abb_markers_loads_and_a_hidden_marker(tmp_path):
    problem = load_without_cell(str(ABB))
    true = perturbed(problem, np.random.default_rng(9), k=np.r_[0.0, np.full(5, 1e-6)])
    write_measurements(tmp_path / "meas.csv", problem, true, 10, 10, hidden=((3, 1),))
    meas = read_measurements(problem, str(tmp_path / "meas.csv"))
    assert meas.seen.sum() == 29
    cal = calibrate(problem, meas, model="identifiable")
    compliances_within_sigmas(cal, problem, true)
    assert cal.noise_consistent and not cal.outliers
    # the DH robot's kinematic calibrated.urdf: its marker frames where the calibrated model
    # puts the markers (unloaded)
    from casadi_design.calibrated.urdf import calibrated_chain, urdf_text

    (tmp_path / "calibrated.urdf").write_text(urdf_text(problem, calibrated_chain(
        problem, cal.names, cal.fit.robot_X)))
    model = pin.buildModelFromUrdf(str(tmp_path / "calibrated.urdf"))
    expected = model_points(cal.fit.fit.model, meas.Q, np.zeros_like(meas.F), cal.fit.robot_X)
    for c in range(3):
        robot = make_robot(model, f"marker_{c + 1}", {})
        got = np.array([frame_placement(robot, q).translation for q in meas.Q])
        assert np.max(np.abs(got - expected[:, c])) < EXPORT_TOL_M


@pytest.fixture(scope="module")
def good_csv(ur10, ur10_files):
    folder, _ = ur10_files
    return (folder / "meas.csv").read_text().splitlines()


def _mutate(lines, what):
    header, rows = lines[0].split(","), [r.split(",") for r in lines[1:]]
    if what == "missing column":
        k = header.index("meas_z_mm")
        header.pop(k)
        for r in rows:
            r.pop(k)
    elif what == "unit":
        header[header.index("meas_x_mm")] = "meas_x"
    elif what == "nan":
        rows[2][header.index("shoulder_pan_joint_deg")] = "nan"
    elif what == "empty coordinate":
        rows[4][header.index("meas_y_mm")] = ""
    elif what == "repeated header":
        rows.insert(3, list(header))
    elif what == "too few rows":
        rows = rows[:5]
    elif what == "joint limit":
        for r in rows[3:4]:
            r[header.index("elbow_joint_deg")] = "400"
            r[header.index("elbow_joint_rad")] = repr(float(np.radians(400.0)))
    elif what == "not registrable":  # the joint columns of another robot order
        a, b = header.index("shoulder_lift_joint_deg"), header.index("elbow_joint_deg")
        c, d = header.index("shoulder_lift_joint_rad"), header.index("elbow_joint_rad")
        header[a], header[b], header[c], header[d] = header[b], header[a], header[d], header[c]
    return "\n".join(",".join(r) for r in [header, *rows]) + "\n"


@pytest.mark.parametrize("what, says", [
    ("missing column", "missing column 'meas_z_mm'; append the measured coordinates in mm"),
    ("unit", "column 'meas_x' has no unit; name it meas_x_mm or meas_x_m"),
    ("nan", "row 4, column 'shoulder_pan_joint_deg': not a finite number"),
    ("empty coordinate", "row 6, column 'meas_y_mm': empty while the other coordinates of the point are given; "
                         "give all of meas_x_mm, meas_y_mm, meas_z_mm or delete the row"),
    ("repeated header", "row 5 repeats the header; delete it"),
    ("too few rows", "5 rows give 15 measured values, fewer than the 27 parameters"),
    ("joint limit", "row 5, column 'elbow_joint_deg': 400 deg is outside the joint limits"),
    ("not registrable", "cannot be registered to the nominal robot"),
])
def test_bad_input_gives_one_line_and_writes_nothing(good_csv, tmp_path, capsys, what, says):
    bad = tmp_path / "bad.csv"
    bad.write_text(_mutate(good_csv, what))
    out = tmp_path / "out"
    # the problem's own model: with --model auto five rows identify a smaller model
    assert main(["identify", str(UR10), "--measurements", str(bad), "--out", str(out), "--model", "identifiable"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {bad}: ") and says in err and err.count("\n") == 1, err
    assert "Traceback" not in err and not out.exists()


def test_a_validation_file_in_other_units_is_refused(ur10_files, tmp_path, capsys):
    """--units reads every file alike: a validation file in m read as mm is 1000x small, so the
    nominal robot is far off its points even after the best rigid fit; refused in one line
    naming the file and the units (it was scored as a calibration 'missing what the robot does')."""
    folder, _ = ur10_files
    lines = (folder / "valid.csv").read_text().splitlines()
    header = lines[0].split(",")
    cols = [k for k, h in enumerate(header) if h.startswith("meas_")]
    rows = [[str(float(v) / 1e3) if k in cols else v for k, v in enumerate(r.split(","))] for r in lines[1:]]
    small = tmp_path / "valid_m.csv"
    small.write_text("\n".join(",".join(r) for r in [header, *rows]) + "\n")
    out = tmp_path / "out"
    assert main(["identify", str(UR10), "--measurements", str(folder / "meas.csv"), "--validation", str(small),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(rf"error: --validation {re.escape(str(small))}: after the best rigid fit the nominal robot is "
                        r"[\d.]+ mm RMS off its points, more than 20 mm: not this robot's rows, or not in the "
                        r"measurements' units \(--units, --joint-units and --columns read every file alike\)\n", err), err
    assert not out.exists()


def test_no_validation_set_warns(ur10_files, tmp_path, capsys):
    folder, _ = ur10_files
    assert main(["identify", str(UR10), "--measurements", str(folder / "meas.csv"), "--out", str(tmp_path / "o")]) == 0
    assert "warning: no validation set" in capsys.readouterr().out


#: The issue's target: over 20 simulated campaigns, the calibrated UR10's RMS error at the 9
#: test poses within this factor of the predicted sqrt(rho).
CAMPAIGNS, TARGET_FACTOR = 20, 1.3


@pytest.mark.slow
def test_ur10_campaigns_meet_the_predicted_accuracy(tmp_path):
    """UR10 in its cell, the test-pose plan at m = 12 (4 seeded starts), sigma = 25 um, 20
    campaigns on independently perturbed robots: the error of the compensated robot at the
    test poses (in the tracker frame, where the holes are registered) against sqrt(rho)."""
    from casadi_design.optimisation.solve import solve_design
    from casadi_design.problem.build import load_problem

    problem = load_without_cell(str(UR10))
    design = solve_design(load_problem(UR10), "test-pose", 12, starts=4)
    Q, F = design.Q, design.F
    tp = problem.test_poses
    square, predicted, nominal = [], [], []
    for c in range(CAMPAIGNS):
        true = perturbed(problem, np.random.default_rng(1000 + c))
        P = measured(problem, true, Q, F, np.random.default_rng(2000 + c))
        (tmp_path / "meas.csv").write_text(measurement_csv(problem, Q, F, P))
        cal = calibrate(problem, read_measurements(problem, str(tmp_path / "meas.csv")), model="identifiable")
        T = cal.fit.tracker_from_base
        reached = true_points(problem, true, cal.q_compensated, tp.F)[:, 0] @ true.tracker.rotation.T + true.tracker.translation
        target = tp.position_m @ T[:3, :3].T + T[:3, 3]
        square.append(np.sum((reached - target) ** 2, axis=1))
        predicted.append(cal.predicted_rms_m**2)
        at_q0 = true_points(problem, true, tp.q, tp.F)[:, 0] @ true.tracker.rotation.T + true.tracker.translation
        nominal.append(np.sum((at_q0 - (tp.position_m @ cal.fit.T0[:3, :3].T + cal.fit.T0[:3, 3])) ** 2, axis=1))
    rms_cal, rms_pred, rms_nom = (float(np.sqrt(np.mean(v))) for v in (square, predicted, nominal))
    print(f"UR10, {CAMPAIGNS} campaigns: calibrated {rms_cal * 1e3:.4f} mm RMS at the test poses, "
          f"predicted {rms_pred * 1e3:.4f} mm, nominal (registered) {rms_nom * 1e3:.4f} mm")
    assert rms_cal <= TARGET_FACTOR * rms_pred and rms_nom > 0.1e-3


def test_a_fit_that_does_not_converge_gives_one_line(ur10_files, tmp_path, capsys, monkeypatch):
    from functools import partial

    from casadi_design.identification import fit

    monkeypatch.setattr(fit, "identify_nonlinear", partial(lsq.identify_nonlinear, max_iterations=1))
    folder, _ = ur10_files
    out = tmp_path / "out"
    assert main(["identify", str(UR10), "--measurements", str(folder / "meas.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    # (MINPACK counts the evaluation that stops it: 1 or 2)
    assert re.search(r"the fit did not meet its tolerances in [12] evaluations of the model", err)
    assert err.count("\n") == 1
    assert not out.exists()


def test_base_frame_prediction_is_the_designs_measure(ur10, tmp_path):
    """With base-frame coordinates the fit's parameters are the problem's own X, and the
    predicted sqrt(rho) at the test poses is the design's measure of the measured plan."""
    from casadi_design.measures.measures import score_plan

    true = perturbed(ur10, np.random.default_rng(11))
    true = type(true)(true.model, true.frame_id, true.k, pin.SE3.Identity())  # base frame
    Q, F, _ = write_measurements(tmp_path / "meas.csv", ur10, true, 12, 12)
    cal = calibrate(ur10, read_measurements(ur10, str(tmp_path / "meas.csv")), frame="base", model="identifiable")
    design = score_plan(ur10.model.B_stack(Q, F), ur10.B0, ur10.sigma_m)
    np.testing.assert_allclose(cal.predicted_rms_m, design.rms_error_m, rtol=1e-6)
    assert cal.names == ur10.model.parameter_names and cal.noise_consistent


def test_a_point_far_off_is_located_with_a_tracker_frame_per_round(ur10, tmp_path):
    """Two rounds, the tracker moved in between, the measured point 70 mm off the file's
    tool_xyz_m: it is located with one frame per round (it was located only for one round or
    --same-frame, and FIGAROH's two TIAGo days were refused as 88.5 mm off)."""
    from casadi_design.identification.fit import register
    from casadi_design.identification.measurements import rounds_of

    true = perturbed(ur10, np.random.default_rng(5), base_like=False)
    offset = np.array([0.06, 0.02, -0.03])
    frame = true.model.frames[true.frame_id]
    frame.placement = frame.placement * pin.SE3(np.eye(3), offset)
    true.model.frames[true.frame_id] = frame
    moved = type(true)(true.model, true.frame_id, true.k,
                       pin.SE3(pin.exp3(np.array([0.1, 0.2, -0.4])), np.array([0.3, 1.1, -0.2])) * true.tracker)
    write_measurements(tmp_path / "first.csv", ur10, true, 8, 21)
    write_measurements(tmp_path / "second.csv", ur10, moved, 8, 22)
    meas = rounds_of([read_measurements(ur10, str(tmp_path / n)) for n in ("first.csv", "second.csv")])
    problem, _, T0s, notes = register(ur10, "tracker", meas)
    assert len(T0s) == 2 and re.match(rf"the measured points of {re.escape(str(ur10.path))} lie 69.\d mm off", notes[0])
    located = np.array(problem.spec.robot.tool_xyz_m) - np.array(ur10.spec.robot.tool_xyz_m)
    assert np.abs(located - offset).max() < 3e-3  # (the robot's own errors: millimetres)


def test_rounds_in_two_tracker_frames_identify_one_robot(ur10, tmp_path, capsys):
    """Two rounds of 8 rows, the tracker moved in between: fitted with a frame per round, the
    residuals are the noise (chi-square consistent) and each frame is its round's true one;
    taken as one frame (--same-frame) they are millimetres off. The robot's covariance with a
    frame per round is that of the Schur complement: at least the one-frame fit's of the same
    rows (a frame known adds information)."""
    from casadi_design.identification.measurements import rounds_of

    true = perturbed(ur10, np.random.default_rng(5), base_like=False)
    moved = type(true)(true.model, true.frame_id, true.k,
                       pin.SE3(pin.exp3(np.array([0.1, 0.2, -0.4])), np.array([0.3, 1.1, -0.2])) * true.tracker)
    write_measurements(tmp_path / "first.csv", ur10, true, 8, 21)
    write_measurements(tmp_path / "second.csv", ur10, moved, 8, 22)
    files = [read_measurements(ur10, str(tmp_path / n)) for n in ("first.csv", "second.csv")]
    two = calibrate(ur10, rounds_of(files), model="identifiable")
    assert two.noise_consistent and not two.outliers
    assert two.fit.frames.shape == (1, len(two.fit.fit.frame_names))
    T1 = two.fit.tracker_from_base
    assert angle_between(T1[:3, :3], true.tracker.rotation) < 1e-4
    record = identification_record(two, {})
    T2 = np.array(record["tracker_from_base_per_round"][1])
    assert angle_between(T2[:3, :3], moved.tracker.rotation) < 1e-4
    assert np.abs(T2[:3, 3] - moved.tracker.translation).max() < 1e-3
    assert [r["rows"] for r in record["rounds"]] == [8, 8]
    assert rms(two.residual_rms_m) < 2 * ur10.sigma_m
    with pytest.raises(ProblemError, match="cannot be registered"):  # one frame: the tracker's move is metres
        calibrate(ur10, rounds_of(files, same_frame=True), model="identifiable")
    # the same rows in one frame: the information of the robot parameters is at least as large
    same = [read_measurements(ur10, str(tmp_path / "first.csv"))]
    write_measurements(tmp_path / "second_same.csv", ur10, true, 8, 22)
    same.append(read_measurements(ur10, str(tmp_path / "second_same.csv")))
    joint = calibrate(ur10, rounds_of(same, same_frame=True), model="identifiable")
    robot = slice(len(two.fit.fit.frame_names), None)
    assert np.all(joint.std[robot] <= two.std[robot] * (1 + 1e-9))
    assert main(["identify", str(UR10), "--measurements", str(tmp_path / "first.csv"), "--measurements",
                 str(tmp_path / "second.csv"), "--model", "identifiable", "--out", str(tmp_path / "out")]) == 0
    assert "first.csv + " in json.loads((tmp_path / "out" / "identification.json").read_text())["measurements"]


@pytest.mark.parametrize("case", ["abb_irb6640_machining", "panda_ball_socket"])
def test_calibrated_toml_keeps_the_robot_s_speeds_controller_and_masses(case, tmp_path):
    """calibrated.toml is the same robot calibrated: its joint speeds and controller (the
    programs' time and joint convention) and the URDF of its links' masses (the weight's models)
    as the problem file gives them, that file's relative path rewritten from the folder written."""
    import tomllib

    from casadi_design.calibrated.calibrated_toml import calibrated_problem, toml_text
    from casadi_design.calibrated.urdf import calibrated_chain, urdf_text

    path = ROOT / "problems" / f"{case}.toml"
    problem = load_without_cell(str(path))
    raw = tomllib.loads(path.read_text())["robot"]
    (tmp_path / "calibrated.urdf").write_text(urdf_text(problem, calibrated_chain(problem, (), np.zeros(0))))
    (tmp_path / "calibrated.toml").write_text(toml_text(calibrated_problem(problem, tmp_path / "calibrated.urdf"), "#"))
    robot = tomllib.loads((tmp_path / "calibrated.toml").read_text())["robot"]
    for key in ("joint_speeds_deg_s", "controller", "inertias_urdf"):
        assert robot.get(key) == raw.get(key), key
    again = load_without_cell(str(tmp_path / "calibrated.toml"))
    assert again.spec.robot.inertias_urdf == problem.spec.robot.inertias_urdf
    if case == "panda_ball_socket":  # the weight loads the calibrated Panda's joints as the nominal one's
        q = problem.test_poses.q[0]
        np.testing.assert_allclose(np.asarray(again.model.kinematics.gravity_torque(q)).ravel(),
                                   np.asarray(problem.model.kinematics.gravity_torque(q)).ravel(), atol=1e-9)


def test_calibrated_toml_names_a_relative_inertias_urdf_from_where_it_is_written(tmp_path):
    """A problem file's ``inertias_urdf`` given relative to it is rewritten relative to the
    folder calibrated.toml is written in, and that file reads it."""
    import tomllib

    from casadi_design.calibrated.calibrated_toml import calibrated_problem, toml_text
    from casadi_design.calibrated.urdf import calibrated_chain, urdf_text
    from casadi_design.robot.robots import urdf_file

    source = ROOT / "problems" / "panda_ball_socket.toml"
    (tmp_path / "masses.urdf").write_bytes(urdf_file("example-robot-data:panda_description/urdf/panda.urdf").read_bytes())
    text = source.read_text().replace('"robots/mukca/panda.urdf"', f'"{source.parent / "robots/mukca/panda.urdf"}"')
    path = tmp_path / "panda.toml"
    path.write_text(text.replace('"example-robot-data:panda_description/urdf/panda.urdf"', '"masses.urdf"'))
    problem = load_without_cell(str(path))
    out = tmp_path / "out" / "identify"
    out.mkdir(parents=True)
    (out / "calibrated.urdf").write_text(urdf_text(problem, calibrated_chain(problem, (), np.zeros(0))))
    (out / "calibrated.toml").write_text(toml_text(calibrated_problem(problem, out / "calibrated.urdf"), "#"))
    assert tomllib.loads((out / "calibrated.toml").read_text())["robot"]["inertias_urdf"] == "../../masses.urdf"
    again = load_without_cell(str(out / "calibrated.toml"))
    q = problem.test_poses.q[0]
    np.testing.assert_allclose(np.asarray(again.model.kinematics.gravity_torque(q)).ravel(),
                               np.asarray(problem.model.kinematics.gravity_torque(q)).ravel(), atol=1e-9)
