"""Bad-input classes that used to give a traceback, a hang or a silent wrong answer: one line each."""

import math
import socket
import time

import pytest

from casadi_design.cli import main
from casadi_design.errors import DesignError, ProblemError
from casadi_design.execution import parallel
from casadi_design.problem.build import load_problem
from casadi_design.problem_file.read import read_problem
from tests.conftest import PAPER, ROOT, build, paper_raw, read_raw

GEOMETRIC = ROOT / "problems" / "planar_2r_geometric.toml"
ABB = ROOT / "problems" / "abb_irb6640_machining.toml"


def _edited(path, *edits):
    raw = read_raw(path)
    for keys, value in edits:
        table = raw
        for k in keys[:-1]:
            table = table[k]
        table[keys[-1]] = value
    return raw


@pytest.mark.parametrize("edits, match", [
    ([(("measurement", "sigma_m"), math.nan)], r"\[measurement\].sigma_m: expected a finite number, got nan"),
    ([(("measurement", "sigma_m"), math.inf)], r"sigma_m: expected a finite number, got inf"),
    ([(("robot", "planar_links_m"), [0.6, math.inf])], r"planar_links_m: expected finite numbers"),
    ([(("experiments", "force", "magnitude_N"), math.nan)], r"magnitude_N: expected a finite number"),
    ([(("solver", "tol"), math.nan)], r"\[solver\].tol: expected a finite number"),
    ([(("experiments", "workspace"), {"floor_z_m": -math.inf})], r"floor_z_m: expected a finite number"),
    ([(("test_poses", "force_N"), ["0", "100"])], r"force_N: expected numbers of shape 2, got \['0', '100'\]; "),
    ([(("robot", "joint_limits_rad"), {"joint1": [1.0, -1.0]})], r"joint_limits_rad\].joint1: lower 1.0 must be below upper -1.0"),
    ([(("experiments", "m"), [100000])], r"\[experiments\].m: 100000 experiments would need at least 1.6e\+03 GB .*; use fewer experiments \(at most 500\)"),
    ([(("test_poses", "line_m"), {"start": [-0.6, 0.4], "end": [0.6, 0.4], "nodes": 10**9})],
     r"\[test_poses.line_m\].nodes: 1000000000 test poses would need at least .* GB .*give fewer nodes"),
    ([(("solver", "seed"), -3)], r"\[solver\].seed: must be between 0 and"),
])
def test_read_refuses_bad_values_with_one_message(edits, match):
    with pytest.raises(ProblemError, match=match):
        build(_edited(PAPER, *edits))


def test_dh_rows_with_nan_or_reversed_limits():
    joints = read_raw(ABB)["robot"]["dh"]["joints"]
    bad = [dict(joints[0], a_m=math.nan)] + joints[1:]
    with pytest.raises(ProblemError, match=r"\[robot.dh.joints\[1\]\].a_m: expected a finite number"):
        build(_edited(ABB, (("robot", "dh", "joints"), bad)))
    bad = [dict(joints[0], limits_deg=[170.0, -170.0])] + joints[1:]
    with pytest.raises(ProblemError, match=r"limits_deg: lower 170 must be below upper -170"):
        build(_edited(ABB, (("robot", "dh", "joints"), bad)))


@pytest.mark.parametrize("keys, value, match", [
    (("joints", 1, "beta_deg"), 90.0,
     r"^test.toml: \[robot.dh.joints\[2\]\].beta_deg: is 90; give an angle strictly between -90 and 90 deg$"),
    (("joints", 0, "beta_deg"), "0.1", r"\[robot.dh.joints\[1\]\].beta_deg: expected float, got '0.1'"),
    (("joints", 0, "beta"), 0.1, r"\[robot.dh.joints\[1\]\]: unknown key 'beta'; allowed: .*beta_deg"),
    (("base_xyz_m",), [0.0, 0.1], r"^test.toml: \[robot.dh\].base_xyz_m: expected finite numbers of shape 3, got \[0.0, 0.1\]"),
    (("base_rpy_deg",), [0.0, math.inf, 0.0], r"\[robot.dh\].base_rpy_deg: expected finite numbers of shape 3"),
])
def test_dh_hayati_and_base_fields_refused_with_one_line(keys, value, match):
    with pytest.raises(ProblemError, match=match) as info:
        build(_edited(ABB, (("robot", "dh", *keys), value)))
    assert "\n" not in str(info.value)


def test_covariance_symmetry_is_relative():
    """Entries of 1e-10 m^2: an absolute tolerance of 1e-8 would call any such matrix symmetric."""
    raw = paper_raw()
    raw["measurement"]["covariance"] = [[1e-8, 3e-9], [1e-9, 1e-8]]
    with pytest.raises(ProblemError, match=r"covariance: is not symmetric"):
        build(raw)
    raw["measurement"]["covariance"] = [[1e-8, 2e-9], [2e-9, 1e-8]]
    assert build(raw).model.L == 2


def test_nothing_identifiable_is_refused():
    """Only the orientation of a planar arm is measured: link lengths have no effect at all."""
    raw = read_raw(GEOMETRIC)
    raw["calibration"]["parameters"] = ["joint2.tx", "tool.tx"]
    raw["measurement"] = {"components": ["rz"], "sigma_m": 1e-4, "sigma_rad": 1e-4}
    raw["test_poses"]["components"] = ["x", "y"]
    with pytest.raises(ProblemError, match=r"\[calibration\].parameters: no parameter has any effect on the rz "
                                           r"measurements .*; measure other components"):
        build(raw)


def test_redundant_parameter_is_named_before_m_is_checked():
    raw = read_raw(GEOMETRIC)
    raw["calibration"]["parameters"] = ["joint1.offset", "base.rz", "tool.tx"]
    raw["experiments"]["m"] = [1]
    with pytest.raises(ProblemError, match=r"joint1.offset and base.rz act as one combination"):
        build(raw)


def test_file_encodings_and_kinds(tmp_path):
    with pytest.raises(ProblemError, match=r"is a folder, not a problem file"):
        read_problem(tmp_path)
    f = tmp_path / "case.toml"
    f.write_bytes(PAPER.read_text().encode("utf-16"))
    with pytest.raises(ProblemError, match=r"case.toml: is (not UTF-8 text|a binary file)"):
        read_problem(f)
    f.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00")
    with pytest.raises(ProblemError, match=r"is a binary file"):
        read_problem(f)
    f.write_bytes("\ufeff".encode() + PAPER.read_bytes())  # a byte-order mark is fine
    assert read_problem(f).m_values == (1, 5)


def test_urdf_problems_are_one_line(tmp_path, capsys):
    urdf = tmp_path / "arm.urdf"
    link = '<link name="{0}"/>'
    joint = ('<joint name="{n}" type="{t}"><parent link="{p}"/><child link="{c}"/><origin xyz="{x} 0 0"/>'
             '<axis xyz="{a}"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')
    body = "".join(link.format(n) for n in ("base", "l1", "l2"))
    raw = read_raw(GEOMETRIC)
    raw["robot"] = {"urdf": str(urdf), "frame": "l2"}
    raw["calibration"]["parameters"] = ["j1.offset", "j2.offset"]
    cases = [
        (joint.format(n="j1", t="continuous", p="base", c="l1", x=0, a="0 0 1"), r"joint 'j1' is a continuous joint \(revolute without limits, about z\)"),
        (joint.format(n="j1", t="revolute", p="base", c="l1", x=0, a="0 0 0"), r"joint 'j1' has the axis \[0.0, 0.0, 0.0\] of zero length"),
        ('<joint name="j1" type="revolute"><parent link="base"/><child link="l1"/></joint>', r"Pinocchio cannot read .*does not specify limits"),
    ]
    for first, match in cases:
        second = joint.format(n="j2", t="revolute", p="l1", c="l2", x=0.5, a="0 0 1")
        urdf.write_text(f'<robot name="arm">{body}{first}{second}</robot>')
        with pytest.raises(ProblemError, match=match):
            build(raw)
    capsys.readouterr()
    f = tmp_path / "case.toml"
    import tomli_w
    f.write_text(tomli_w.dumps(raw))
    assert main(["solve", str(f), "--jobs", "1", "--quiet"]) == 2
    _, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("error: ")  # no C++ parser lines before ours


def test_command_line_errors_are_one_line(tmp_path, capsys):
    for argv in (["solve"], ["solve", str(PAPER), "--starts", "x"], ["plot", str(tmp_path), "--format", "jpg"],
                 ["nonsense"], ["solve", str(PAPER), "--out", ""],
                 ["sweep", str(PAPER), "--out", str(tmp_path / "a" / "b")]):  # a: a file, not a folder
        (tmp_path / "a").write_text("")
        assert main(argv) == 2, argv
        _, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and "; " in lines[0], err
    assert (tmp_path / "a").is_file()


def test_unreachable_dask_scheduler_is_one_line_within_seconds(monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setattr(parallel, "DASK_CONNECT_TIMEOUT_S", 0.5)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(DesignError, match=rf"--dask-scheduler tcp://127.0.0.1:{port}: no Dask scheduler answered"):
        parallel.DaskExecutor(f"tcp://127.0.0.1:{port}")
    with socket.socket() as silent:  # a port that takes the connection and never answers (no scheduler)
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        t0 = time.perf_counter()
        with pytest.raises(DesignError, match=rf"--dask-scheduler tcp://127.0.0.1:{port}: no Dask scheduler answered "
                                              r"within 0.5 s \(connected, but no Dask handshake came back"):
            parallel.DaskExecutor(f"tcp://127.0.0.1:{port}")
        assert time.perf_counter() - t0 < 3  # it waited for ever: Dask's timeout leaves the handshake out


def test_plan_check_covers_the_flange_and_tool_frames():
    """The floor rule applies to every moving frame: the flange (tool0) can no longer go under it.
    Checked against Pinocchio's own frame placements at random configurations."""
    import numpy as np
    import pinocchio as pin


    problem = load_problem(ROOT / "problems" / "ur10_drilling.toml")
    robot, rules = problem.robot, problem.rules.pose
    floor = [k for k, label in enumerate(rules.labels) if "below the floor" in label]
    data = robot.model.createData()
    for q in np.random.default_rng(0).uniform(robot.q_min, robot.q_max, (5, robot.n)):
        pin.framesForwardKinematics(robot.model, data, robot.full_q(q))
        g = np.asarray(rules.g(q)).ravel()[floor]
        for name in ("tool0", "ee_link", "wrist_3_link", "forearm_link", robot.frame):
            z = data.oMf[robot.model.getFrameId(name)].translation[2]
            assert np.min(np.abs(g - z)) < 1e-12, name


UR10 = ROOT / "problems" / "ur10_drilling.toml"
UR10_PLAN = ROOT / "tests" / "data" / "ur10_D_m12_without_cell.csv"


def _plan_rows():
    import csv

    with open(UR10_PLAN) as f:
        return list(csv.reader(f))


def _write(path, rows):
    import csv

    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    return path


def _one_error_line(capsys):
    _, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def test_an_absurd_measured_coordinate_is_one_line_naming_row_and_column(tmp_path, capsys):
    rows = _plan_rows()
    rows = [rows[0] + ["meas_x_mm", "meas_y_mm", "meas_z_mm"]] + [r + r[-3:] for r in rows[1:]]
    rows[3][-1] = "1e300"
    meas = _write(tmp_path / "meas.csv", rows)
    assert main(["identify", str(UR10), "--measurements", str(meas), "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert "row 4, column 'meas_z_mm'" in line and "beyond 100 m" in line
    assert not (tmp_path / "o").exists()



def test_coordinates_in_columns_of_another_name_are_named_with_their_columns_option(tmp_path, capsys):
    rows = _plan_rows()
    rows = [rows[0] + ["X", "Y", "Z"]] + [r + r[-3:] for r in rows[1:]]  # the plan's nominal x_mm, y_mm, z_mm
    meas = _write(tmp_path / "meas.csv", rows)
    assert main(["identify", str(UR10), "--measurements", str(meas), "--units", "mm", "--out", str(tmp_path / "o")]) == 2
    assert _one_error_line(capsys) == (
        f"error: {meas}: missing column 'meas_x_mm'; its columns X, Y, Z look like the measured coordinates: read "
        "them with --columns X=meas_x,Y=meas_y,Z=meas_z --units mm, or rename them meas_x_mm, meas_y_mm, meas_z_mm "
        "(_m for metres)")
    assert not (tmp_path / "o").exists()


def test_program_reads_a_plan_saved_by_excel_with_semicolons(tmp_path, capsys):
    rows = [["q1_deg", "q2_deg", "fx_N", "fy_N"], ["0", "90.5", "0", "100"], ["90", "-90", "100", "0"],
            ["45.25", "-120", "-60", "80"]]
    comma, excel = _write(tmp_path / "plan.csv", rows), tmp_path / "excel.csv"
    excel.write_text("\n".join(";".join(cell.replace(".", ",") for cell in r) for r in rows) + "\n")
    printed = []
    for plan in (comma, excel):
        assert main(["program", str(PAPER), "--plan", str(plan), "--format", "yaml", "--quiet"]) == 0
        printed.append(capsys.readouterr().out.replace(str(plan), "PLAN"))
    assert printed[0] == printed[1] and "plan PLAN: 3 experiments" in printed[0]

def test_program_refuses_a_plan_joint_beyond_its_limit(tmp_path, capsys):
    rows = _plan_rows()
    rows[1][1], rows[1][7] = repr(math.degrees(9.0)), "9.0"  # shoulder_pan 9 rad, limits +-2 pi
    plan = _write(tmp_path / "plan.csv", rows)
    assert main(["program", str(UR10), "--plan", str(plan), "--format", "urscript", "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert "row 2, column 'shoulder_pan_joint_deg'" in line and "outside the joint limits [-360, 360] deg" in line
    assert not (tmp_path / "o").exists()


def test_a_plan_of_another_robot_names_the_plan_file(capsys):
    assert main(["program", str(PAPER), "--plan", str(UR10_PLAN), "--format", "urscript"]) == 2
    line = _one_error_line(capsys)
    assert str(UR10_PLAN) in line and "names joint 'shoulder_pan_joint'" in line and "--format" not in line


def test_a_design_no_start_can_make_leaves_no_partial_file(tmp_path, capsys):
    out = tmp_path / "o"
    # IPOPT stopped after 8 iterations: m = 1 converges (saved in solve.partial.json), then
    # m = 5 does not (measured)
    assert main(["solve", str(PAPER), "--m", "1,5", "--criteria", "D", "--ipopt", "max_iter=8",
                 "--starts", "2", "--bound-steps", "0", "--jobs", "1", "--out", str(out), "-q"]) == 2
    _, err = capsys.readouterr()
    assert "criterion D, m = 5: none of" in err
    assert not out.exists()


def test_validate_of_another_problem_s_results_names_that_problem(tmp_path, capsys):
    solved = tmp_path / "paper"
    assert main(["solve", str(PAPER), "--m", "3", "--criteria", "D", "--starts", "1", "--bound-steps", "0",
                 "--quiet", "--out", str(solved)]) == 0
    capsys.readouterr()
    assert main(["validate", str(ROOT / "problems" / "panda_ball_socket.toml"), "--results", str(solved),
                 "--trials", "2"]) == 2
    line = _one_error_line(capsys)
    assert "they are the results of problem paper_planar_2r" in line and "point and placement" not in line


def test_program_prints_nothing_before_its_error(tmp_path, capsys):
    panda = ROOT / "problems" / "panda_ball_socket.toml"
    Q = load_problem(panda).test_poses.q  # recorded at panda_2's mid_left, as MUKCa publishes a placement
    for k in (0, 1):
        (tmp_path / f"hole_{k}.csv").write_text("\n".join(",".join(f"{v:.6f}" for v in q) for q in Q[2 * k:2 * k + 2]) + "\n")
    assert main(["program", str(panda), "--plan", str(tmp_path), "--format", "urscript"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("error: --format urscript: the controller drives 6 joints")
