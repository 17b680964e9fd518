"""identify on a real industrial robot measured by a laser tracker: Fraunhofer IPA's UR10, Series C
(tests/data/ipa_ur10/README.md). The tracker reads to about 0.01 mm; the robot's error that no
geometric parameter explains is some 0.25 mm per axis: the identification must judge rows,
parameters and predictions by the robot's error, not the tracker's."""

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.cli.identify import load_without_cell
from casadi_design.identification.calibrate import MAX_OUTLIER_SHARE, calibrate
from casadi_design.identification.choice import Candidate, choose
from casadi_design.identification.measurements import FileFormat, read_measurements

DATA = Path(__file__).parents[1] / "data" / "ipa_ur10"
PROBLEM = DATA / "ipa_ur10.toml"
SERIES_C = DATA / "measurements_random_poses_xyz.csv"
COLUMNS = "measurement_x=meas_x,measurement_y=meas_y,measurement_z=meas_z"
FORMAT = FileFormat(units="mm", columns=tuple(tuple(c.split("=")) for c in COLUMNS.split(",")))
#: The identification's training rows: N random rows of the series, per seed. The default run
#: checks the first two seeds' splits, the slow tests the third too (the same checks on another
#: random split; a calibration of 40 rows judged on the other 2733 takes 2 s).
N, SEEDS = 40, (0, 1, 2)
DEFAULT_SEEDS = SEEDS[:2]
#: The predicted held-out RMS is within this factor of the measured one (issue 58).
PREDICTION_FACTOR = 1.5


@pytest.fixture(scope="module")
def ipa():
    problem = load_without_cell(str(PROBLEM))
    return problem, read_measurements(problem, str(SERIES_C), FORMAT)


def split(meas, seed: int):
    """``N`` random rows of ``meas`` and the others."""
    rows = np.random.default_rng(seed).permutation(meas.m)
    return meas.subset(np.sort(rows[:N])), meas.subset(np.sort(rows[N:]))


class _Calibrations(dict):
    """The calibration of each seed's split, computed when first asked for."""

    def __init__(self, problem, meas):
        super().__init__()
        self.problem, self.meas = problem, meas

    def __missing__(self, seed: int):
        training, held_out = split(self.meas, seed)
        self[seed] = calibrate(self.problem, training, validation=held_out)
        return self[seed]


@pytest.fixture(scope="module")
def calibrations(ipa):
    return _Calibrations(*ipa)


def test_the_shipped_file_is_ipa_s_series_c_as_published(ipa):
    expected = {line.split()[1]: line.split()[0] for line in (DATA / "SHA256SUMS").read_text().splitlines()}
    assert set(expected) == {"measurements_random_poses_xyz.csv", "LICENSE.md"}
    for name, digest in expected.items():
        assert hashlib.sha256((DATA / name).read_bytes()).hexdigest() == digest
    # ';' separators and decimal commas, read as the first row of the published file gives them
    _, meas = ipa
    assert meas.m == 2773 and any("',' as the decimal point" in n for n in meas.notes)
    np.testing.assert_array_equal(meas.Q[0], [-3.14159, -1.5708, 0.0, -1.5708, 0.0, 0.0])
    np.testing.assert_allclose(meas.P_m[0, 0], [0.38397123, -3.2407562, 0.20172621], rtol=0, atol=1e-15)


@pytest.mark.parametrize("seed", [pytest.param(s, marks=() if s in DEFAULT_SEEDS else pytest.mark.slow)
                                  for s in SEEDS])
def test_defaults_on_40_random_rows_predict_the_others(calibrations, seed):
    """The defaults on 40 random rows, judged on the other 2733: few rows excluded, the
    calibrated robot better held out than registration only, and the prediction within 1.5x
    of the measured error; the unmodelled error carries nearly all of it."""
    cal = calibrations[seed]
    v = cal.validation
    assert len(cal.outliers) < 0.1 * N
    assert not v.moved and v.rms("calibrated") < v.rms("registration")
    ratio = v.rms("predicted") / v.rms("calibrated")
    assert 1 / PREDICTION_FACTOR < ratio < PREDICTION_FACTOR, ratio
    # the residuals are not the tracker's noise: the unmodelled error is 10x it and more, and the
    # parameters' std hold it
    assert not cal.noise_consistent and cal.scale.tau_m > 10 * cal.problem.sigma_m
    assert cal.scale.tracker_share < 0.01
    M = cal.fit.information
    np.testing.assert_allclose(cal.std, cal.scale.s_m * np.sqrt(np.diag(np.linalg.inv(M))), rtol=1e-12)
    assert not any("do not use" in n or "x its prediction" in n for n in cal.notes), cal.notes


def test_the_unmodelled_error_is_what_cross_validation_shows(calibrations):
    """``s^2 = sigma^2 + tau^2`` is the variance per value that explains the leave-one-out error:
    ``sum |e_i|^2 = s^2 sum tr (I - P_i)^-1`` (an independent numpy computation of the PRESS
    residuals of the fit's rows)."""
    cal = calibrations[0]
    f = cal.fit
    J, r = f.J[f.used], f.r[f.used]
    Hinv = np.linalg.inv(J.reshape(-1, J.shape[2]).T @ J.reshape(-1, J.shape[2]))
    total, traces = 0.0, 0.0
    for Ji, ri in zip(J, r):
        A = np.eye(len(ri)) - Ji @ Hinv @ Ji.T
        total += float(np.sum(np.linalg.solve(A, ri) ** 2))
        traces += float(np.trace(np.linalg.inv(A)))
    assert cal.scale.s_m == pytest.approx(math.sqrt(total / traces), rel=1e-9)
    assert cal.scale.tau_m == pytest.approx(math.sqrt(total / traces - cal.problem.sigma_m**2), rel=1e-9)


def test_gravity_models_with_negative_compliances_are_not_chosen(calibrations):
    cals = [calibrations[seed] for seed in DEFAULT_SEEDS]
    refused = [c for cal in cals for c in cal.candidates if c.refused]
    for cal in cals:
        assert cal.model not in {c.name for c in cal.candidates if c.refused}
    for c in refused:
        assert c.fit_model.model.gravity and c.refused.startswith("negative compliance beyond 2 std (k.")


def test_auto_does_not_choose_a_refused_candidate_of_the_best_cross_validated_error():
    """(sizes given as effective numbers of parameters: no fit model is needed to choose)"""
    def candidate(name, cv, size, refused=""):
        return Candidate(name, None, cv, cv, 0.01e-3, dof=size, refused=refused)

    found = [candidate("registration", 1.0e-3, 9), candidate("offsets", 0.6e-3, 13)]
    assert choose([*found, candidate("offsets + gravity", 0.5e-3, 16)], "auto")[0].name == "offsets + gravity"
    assert choose([*found, candidate("offsets + gravity", 0.5e-3, 16, "negative compliance")], "auto")[0].name \
        == "offsets"


def test_a_moved_tracker_is_said_and_the_re_registered_errors_count(ipa, calibrations):
    """The held-out rows in another tracker frame (3.67 m away, turned): one note says the tracker
    moved; the errors that count are the re-registered ones, equal to those in the training
    frame's file (a rigid motion does not change a rigid fit's residuals); no ratio to the
    prediction in the wrong frame, no false 'do not use'."""
    problem, meas = ipa
    training, held_out = split(meas, 0)
    c, s = math.cos(2.0), math.sin(2.0)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1, 0, 0], [0, 0.96, -0.28], [0, 0.28, 0.96]])
    moved = type(held_out)(held_out.path, held_out.lines, held_out.Q, held_out.F,
                           held_out.P_m @ R.T + [3.67, -0.5, 0.2])
    cal = calibrate(problem, training, validation=moved)
    v, same = cal.validation, calibrations[0].validation
    assert v.moved and v.counted[2] == "calibrated_reregistered"
    np.testing.assert_allclose(v.calibrated_reregistered_m, same.calibrated_reregistered_m, atol=1e-9)
    np.testing.assert_allclose(v.registration_reregistered_m, same.registration_reregistered_m, atol=1e-9)
    assert v.rms("nominal") > 3.0  # m: in the training rows' frame
    notes = " ".join(cal.notes)
    assert notes.count("in another tracker frame than the training rows (the tracker moved)") == 1
    assert "x its prediction" not in notes and "do not use" not in notes
    assert v.rms("calibrated_reregistered") < v.rms("registration_reregistered")


@pytest.mark.parametrize("what, shift", [("a 5 mm bad shot", (5e-3, 0.0)), ("a joint read 1 deg off", (0.0, 1.0))])
def test_a_bad_shot_or_a_wrong_joint_reading_is_still_found(ipa, what, shift):
    """Judged against the other rows' error (0.25 mm per value), a bad shot of the tracker and a
    wrong joint reading stand out: the only row excluded."""
    problem, meas = ipa
    training, _ = split(meas, 1)
    P, Q = training.P_m.copy(), training.Q.copy()
    P[7, 0, 0] += shift[0]
    Q[7, 2] += math.radians(shift[1])
    bad = type(training)(training.path, training.lines, Q, training.F, P)
    cal = calibrate(problem, bad)
    assert [line for line, _, _ in cal.outliers] == [training.lines[7]], what
    assert not cal.fit.used[7] and cal.outliers[0][2] > 5 * problem.sigma_m


@pytest.mark.slow  # 16 s: the field's estimate and kriging on 2773 rows; the default run identifies 40 and 100
def test_every_row_of_the_series(ipa):
    """All 2773 rows with the defaults: a handful excluded (the published series has no gross
    error), none of the cap's note."""
    problem, meas = ipa
    cal = calibrate(problem, meas)
    assert len(cal.outliers) < 0.01 * meas.m < MAX_OUTLIER_SHARE * meas.m
    assert not any("excluded as bad shots" in n for n in cal.notes)
    assert cal.scale.tau_m > 10 * problem.sigma_m


def test_identify_reads_the_published_format_and_records_both_scales(tmp_path, capsys):
    """The command on the file as published (';', decimal commas, IPA's column names), 40 rows
    for the fit and 60 to validate: identification.json keeps the tracker's sigma and the
    unmodelled error with their shares, and splits the test poses' prediction."""
    lines = SERIES_C.read_text().splitlines()
    (tmp_path / "fit.csv").write_text("\n".join(lines[:41]) + "\n")
    (tmp_path / "valid.csv").write_text("\n".join([lines[0], *lines[41:101]]) + "\n")
    out = tmp_path / "out"
    assert main(["identify", str(PROBLEM), "--measurements", str(tmp_path / "fit.csv"), "--validation",
                 str(tmp_path / "valid.csv"), "--units", "mm", "--columns", COLUMNS, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    record = json.loads((out / "identification.json").read_text())
    e = record["error_per_value"]
    assert e["sigma_m"] == 2e-5 and e["unmodelled_m"] > 10 * e["sigma_m"]
    assert e["total_m"] == pytest.approx(math.hypot(e["sigma_m"], e["unmodelled_m"]))
    assert e["tracker_share_of_variance"] + e["unmodelled_share_of_variance"] == pytest.approx(1.0)
    tp = record["test_poses"]
    np.testing.assert_allclose(np.square(tp["predicted_rms_m"]),
                               np.square(tp["predicted_parameters_rms_m"]) + tp["predicted_unmodelled_rms_m"] ** 2,
                               rtol=1e-9)
    assert tp["predicted_unmodelled_rms_m"] == pytest.approx(math.sqrt(3) * e["unmodelled_m"], rel=1e-9)
    assert "the robot's unmodelled error" in printed and len(record["outliers"]) < 4
    v = record["validation"]
    assert not v["tracker_moved"] and v["calibrated_rms_m"] < v["registration_rms_m"]
