"""6-D pose measurements (a camera's position and orientation of the measured frame) read as the
problem's markers placed by each pose, checked against the markers computed with Pinocchio."""


import numpy as np
import pinocchio as pin
import pytest

from casadi_design.errors import ProblemError
from casadi_design.records.export import csv_text, plan_table
from casadi_design.identification.calibrate import calibrate
from casadi_design.identification.measurements import read_measurements
from casadi_design.plan.sampling import random_plan
from tests.conftest import ROOT, build, read_raw
from tests.identify_data import perturbed

UR10 = ROOT / "problems" / "ur10_drilling.toml"
MARKERS_M = [[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.0, 0.09, 0.02]]


@pytest.fixture(scope="module")
def ur10_markers():
    raw = read_raw(UR10)
    raw.pop("cell", None)
    raw["measurement"]["markers_m"] = MARKERS_M
    return build(raw, str(UR10))


def _true_poses(problem, true, Q):
    """Poses (R, p) of the measured frame of ``true`` in the tracker frame, by Pinocchio."""
    data = true.model.createData()
    out = []
    for q in Q:
        pin.framesForwardKinematics(true.model, data, problem.robot.full_q(q))
        out.append(true.tracker * data.oMf[true.frame_id])
    return out


def _csv(problem, Q, F, poses, convention):
    header, rows = plan_table(problem, Q, F)
    header = header[:len(rows[0])]
    if convention == "quaternion":
        header += ["meas_x_m", "meas_y_m", "meas_z_m", "meas_qw", "meas_qx", "meas_qy", "meas_qz"]
        for row, M in zip(rows, poses):
            q = pin.Quaternion(M.rotation)
            row += [*M.translation, q.w, q.x, q.y, q.z]
    else:
        header += ["meas_x_mm", "meas_y_mm", "meas_z_mm", "meas_roll_deg", "meas_pitch_deg", "meas_yaw_deg"]
        for row, M in zip(rows, poses):
            row += [*(M.translation * 1e3), *np.degrees(pin.rpy.matrixToRpy(M.rotation))]
    return csv_text(header, rows)


@pytest.mark.parametrize("convention", ["quaternion", "rpy"])
def test_poses_are_read_as_the_markers_they_place(tmp_path, ur10_markers, convention):
    problem = ur10_markers
    true = perturbed(problem, np.random.default_rng(3))
    Q, F = random_plan(problem, 8, np.random.default_rng(4))
    poses = _true_poses(problem, true, Q)
    (tmp_path / "poses.csv").write_text(_csv(problem, Q, F, poses, convention))
    meas = read_measurements(problem, str(tmp_path / "poses.csv"))
    expected = np.array([[M.act(np.array(c)) for c in MARKERS_M] for M in poses])
    assert np.max(np.abs(meas.P_m - expected)) < 1e-9
    assert any("6-D poses" in n for n in meas.notes)
    # noise-free poses of a perturbed robot: the problem's own model fits them to the
    # linearisation's remainder, far below a millimetre
    cal = calibrate(problem, meas, model="identifiable")
    assert np.nanmax(cal.residual_rms_m) < 1e-5, np.nanmax(cal.residual_rms_m)


def test_poses_need_markers_and_unit_quaternions(tmp_path, ur10_markers):
    problem = ur10_markers
    true = perturbed(problem, np.random.default_rng(3))
    Q, F = random_plan(problem, 4, np.random.default_rng(5))
    text = _csv(problem, Q, F, _true_poses(problem, true, Q), "quaternion")
    lines = text.splitlines()
    cells = lines[2].split(",")
    cells[-4] = str(2 * float(cells[-4]) + 0.5)
    (tmp_path / "bad.csv").write_text("\n".join([lines[0], lines[1], ",".join(cells), *lines[3:]]) + "\n")
    with pytest.raises(ProblemError, match=r"bad.csv: row 3: the quaternion \(meas_qw, meas_qx, meas_qy, meas_qz\) has norm"):
        read_measurements(problem, str(tmp_path / "bad.csv"))
    (tmp_path / "half.csv").write_text(text.replace("meas_qz", "qz"))
    with pytest.raises(ProblemError, match="orientation columns are incomplete"):
        read_measurements(problem, str(tmp_path / "half.csv"))
    raw = read_raw(UR10)
    raw.pop("cell", None)
    one_point = build(raw, str(UR10))
    (tmp_path / "poses.csv").write_text(text)
    with pytest.raises(ProblemError, match=r"at least three markers not on a line.*markers_m = "):
        read_measurements(one_point, str(tmp_path / "poses.csv"))
