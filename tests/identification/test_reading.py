"""Reading measurement and plan files as real data comes: Excel's ';'-separated CSVs with decimal
commas (Fraunhofer IPA's UR10 measured by a Leica laser tracker), and the --columns that reads a
file's own coordinate columns."""

from pathlib import Path

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.errors import ProblemError
from casadi_design.identification.measurements import FileFormat, parse_columns, read_experiments, read_measurements
from casadi_design.records.export import read_plan_csv
from tests.conftest import PAPER, ROOT, build, read_raw

#: The published file's joint and position columns (tests/data/ipa_ur10/README.md: series C).
IPA_FILE = ROOT / "tests" / "data" / "ipa_ur10" / "measurements_random_poses_xyz.csv"
#: Its header and first two rows, unchanged (CRLF line ends; MIT license, ipa-robot-accuracy).
IPA_HEAD = (
    "Timestamp;Goal x;Goal y;Goal z;Goal roll;Goal pitch;Goal yaw;shoulder_pan_joint;shoulder_lift_joint;"
    "elbow_joint;wrist_1_joint;wrist_2_joint;wrist_3_joint;measurement_temperature;measurement_x;"
    "measurement_std_x;measurement_y;measurement_std_y;measurement_z;measurement_std_z;measurement_rx;"
    "measurement_std_rx;measurement_ry;measurement_std_ry;measurement_rz;measurement_std_rz\r\n"
    "2,02011E+13;-0,000181978;-0,365141;1,4273;1,57005;1,56969;-0,000186977;-3,14159;-1,5708;0;-1,5708;0;0;"
    "21,68000031;383,97123;0,041565;-3240,7562;0,022023;201,72621;0,0055848;-90,179563;0,0024569;-20,112975;"
    "0,0065397;-90,157388;0,008348\r\n"
    "2,02011E+13;0,0103459;-0,480444;1,00632;3,10253;1,66683;1,57927;-4,08444;-2,6946;1,69873;-2,031;0,99275;"
    "-0,0673035;21,68000031;335,14778;0,0054521;-3134,3677;0,0062093;-221,16088;0,0076535;-84,20352;0,00099888;"
    "-22,726835;0,0026542;-88,245609;0,0014716\r\n")
#: Its joints (rad) and measured point (mm) in those rows, as printed there.
IPA_Q = [[-3.14159, -1.5708, 0.0, -1.5708, 0.0, 0.0], [-4.08444, -2.6946, 1.69873, -2.031, 0.99275, -0.0673035]]
IPA_P_MM = [[383.97123, -3240.7562, 201.72621], [335.14778, -3134.3677, -221.16088]]
IPA_COLUMNS = "measurement_x=meas_x,measurement_y=meas_y,measurement_z=meas_z"
SEMICOLON_NOTE = ("read with ';' between columns and ',' as the decimal point (a CSV of Excel in a "
                  "comma-decimal locale)")
#: The paper's plan by hand (deg, N), with ',' and with ';' as Excel in a comma-decimal locale writes it.
PLAN = "q1_deg,q2_deg,fx_N,fy_N\n0,90.5,0,100\n90,-90,100,0\n45.25,-120,-60,80\n"
EXCEL_PLAN = "q1_deg;q2_deg;fx_N;fy_N\n0;90,5;0;100\n90;-90;100;0\n45,25;-120;-60;80\n"


@pytest.fixture(scope="module")
def ur10():
    raw = read_raw(ROOT / "problems" / "ur10_drilling.toml")
    raw.pop("cell", None)
    return build(raw, "ur10.toml")


def _write(path: Path, text: str) -> Path:
    path.write_bytes(text.encode())
    return path


def _one_line(err: pytest.ExceptionInfo) -> str:
    message = str(err.value)
    assert "\n" not in message and "; " in message, message
    return message


def test_ipa_excel_file_is_read_with_decimal_commas(ur10, tmp_path):
    meas = read_measurements(ur10, str(_write(tmp_path / "ipa.csv", IPA_HEAD)),
                             FileFormat(units="mm", columns=parse_columns(IPA_COLUMNS)))
    assert meas.lines == (2, 3)
    np.testing.assert_array_equal(meas.Q, IPA_Q)
    np.testing.assert_array_equal(meas.P_m[:, 0], np.array(IPA_P_MM) * 1e-3)
    assert meas.notes.count(SEMICOLON_NOTE) == 1
    assert any(n.startswith("ignored columns Timestamp, Goal x, Goal y") for n in meas.notes)


def test_the_whole_ipa_file_is_read(ur10):
    meas = read_measurements(ur10, str(IPA_FILE), FileFormat(units="mm", columns=parse_columns(IPA_COLUMNS)))
    assert meas.m == 2773 and meas.lines[0] == 2 and meas.lines[-1] == 2774
    np.testing.assert_array_equal(meas.Q[:2], IPA_Q)
    np.testing.assert_array_equal(meas.P_m[:2, 0], np.array(IPA_P_MM) * 1e-3)
    np.testing.assert_array_equal(meas.P_m[-1, 0], np.array([263.06373, -2831.6744, -327.93786]) * 1e-3)


def test_ipa_file_as_a_plan_is_its_postures(ur10, tmp_path):
    """evaluate --plan and program read it as postures (bare joints in rad): its measurement_x
    is not one of our meas_ columns, which only identify reads (with --columns)."""
    Q, F, _ = read_experiments(ur10, str(_write(tmp_path / "ipa.csv", IPA_HEAD)))
    np.testing.assert_array_equal(Q, IPA_Q)
    assert F.shape == (2, 0)


def test_excel_plan_reads_like_the_comma_plan(paper, tmp_path):
    Q, F = read_plan_csv(paper, _write(tmp_path / "plan.csv", PLAN))
    Qe, Fe = read_plan_csv(paper, _write(tmp_path / "excel.csv", EXCEL_PLAN))
    np.testing.assert_array_equal(Qe, Q)
    np.testing.assert_array_equal(Fe, F)
    np.testing.assert_allclose(np.degrees(Qe[:, 1]), [90.5, -90.0, -120.0], rtol=0, atol=1e-12)


def test_excel_plan_is_evaluated_like_the_comma_plan(tmp_path, capsys):
    scores = []
    for name, text in (("plan.csv", PLAN), ("excel.csv", EXCEL_PLAN)):
        path = _write(tmp_path / name, text)
        assert main(["evaluate", str(PAPER), "--plan", str(path), "--quiet"]) == 0
        scores.append(capsys.readouterr().out.replace(str(path), "PLAN"))
    assert scores[0] == scores[1] and "plan PLAN: 3 experiments" in scores[0]


@pytest.mark.parametrize("text, match", [
    ("q1_deg;q2_deg,fx_N;fy_N\n0;90;0;100\n",
     r"excel.csv: its header \(line 1\) has both ';' and ',' between names, so its columns cannot be told "
     r"apart; save it with ',' separators and '.' decimal points \(or ';' separators and ',' decimal points\)$"),
    ("q1_deg;q2_deg;fx_N;fy_N\n0;90,5;0;100\n0;90.5;0;100\n",
     r"excel.csv: row 3, column 'q2_deg': '90.5' has a '.' in a file separated by ';', where ',' is the decimal "
     r"point; write it with a decimal comma \(or save the file with ',' separators and '.' decimal points\)$"),
    ("q1_deg;q2_deg;fx_N;fy_N\n0;1.234,5;0;100\n", r"row 2, column 'q2_deg': '1.234,5' has a '.' in a file"),
    ("q1_deg;q2_deg;fx_N;fy_N\n0;9,0,5;0;100\n",
     r"row 2, column 'q2_deg': expected a number, got '9,0,5'; give a number with a ',' decimal point"),
    ("q1_deg;q2_deg;fx_N;fy_N\n0,90,0,100\n",
     r"row 2 has 1 cells, the header has 4; give one value per column in every row \(separated by ';' as in "
     r"the header\)$"),
])
def test_excel_files_that_cannot_be_read_unambiguously(paper, tmp_path, text, match):
    with pytest.raises(ProblemError, match=match) as err:
        read_plan_csv(paper, _write(tmp_path / "excel.csv", text))
    _one_line(err)


# --------------------------------------------------------------------------- coordinate columns

def _points_csv(path: Path, names: str) -> Path:
    """Two UR10 rows (joints in rad, bare names) with the measured point (mm) in ``names``."""
    joints = "shoulder_pan_joint,shoulder_lift_joint,elbow_joint,wrist_1_joint,wrist_2_joint,wrist_3_joint"
    rows = [",".join(map(repr, q + p)) for q, p in zip(IPA_Q, IPA_P_MM)]
    return _write(path, f"{joints},{names}\n" + "\n".join(rows) + "\n")


@pytest.mark.parametrize("names, units, columns", [
    ("x,y,z", "mm", "x=meas_x,y=meas_y,z=meas_z --units mm"),
    ("X,Y,Z", "mm", "X=meas_x,Y=meas_y,Z=meas_z --units mm"),
    ("X1,Y1,Z1", "mm", "X1=meas_x,Y1=meas_y,Z1=meas_z --units mm"),
    ("measurement_x,measurement_y,measurement_z", None,
     "measurement_x=meas_x,measurement_y=meas_y,measurement_z=meas_z --units mm (or --units m)"),
])
def test_missing_coordinates_name_the_columns_that_hold_them(ur10, tmp_path, names, units, columns):
    path = _points_csv(tmp_path / "points.csv", names)
    with pytest.raises(ProblemError) as err:
        read_measurements(ur10, str(path), FileFormat(units=units))
    found = names.replace(",", ", ")
    assert _one_line(err) == (
        f"{path}: missing column 'meas_x_mm'; its columns {found} look like the measured coordinates: read them "
        f"with --columns {columns}, or rename them meas_x_mm, meas_y_mm, meas_z_mm (_m for metres)")
    # what it suggests reads the file
    pairs = columns.split(" ")[0]
    meas = read_measurements(ur10, str(path), FileFormat(units=units or "mm", columns=parse_columns(pairs)))
    np.testing.assert_array_equal(meas.P_m[:, 0], np.array(IPA_P_MM) * 1e-3)


@pytest.mark.parametrize("names", ["a,b,c", "Goal x,Goal y,Goal z", "x,y,x_std", "measurement_std_x,y,z"])
def test_missing_coordinates_without_a_likely_column(ur10, tmp_path, names):
    path = _points_csv(tmp_path / "points.csv", names)
    with pytest.raises(ProblemError) as err:
        read_measurements(ur10, str(path), FileFormat(units="mm"))
    assert _one_line(err).startswith(f"{path}: missing column 'meas_") and (
        "append the measured coordinates in mm: meas_x_mm, meas_y_mm, meas_z_mm (or name the file's columns "
        "with --columns)") in str(err.value)


def test_missing_coordinates_keep_the_columns_given(ur10, tmp_path):
    path = _points_csv(tmp_path / "points.csv", "x,y,Z")
    with pytest.raises(ProblemError) as err:
        read_measurements(ur10, str(path), FileFormat(units="mm", columns=(("x", "meas_x"), ("y", "meas_y"))))
    assert "missing column 'meas_z_mm'; its columns Z look like the measured coordinates: read them with " \
           "--columns x=meas_x,y=meas_y,Z=meas_z --units mm, or rename them meas_z_mm" in _one_line(err)
