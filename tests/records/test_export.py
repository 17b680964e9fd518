"""Plans as CSV (to the robot and back), `evaluate` on a plan written by hand, the report."""

import json

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.errors import ProblemError
from casadi_design.measures.criteria import CRITERIA
from casadi_design.optimisation.solve import plan_scores, solve_design
from casadi_design.plan.rules import plan_violations
from casadi_design.problem.build import load_problem
from casadi_design.records.export import plan_table, read_plan_csv, report_markdown, write_plan_csv
from tests.conftest import PAPER, ROOT, build, paper_raw, read_raw

L1, L2 = 0.6, 0.4  # the paper's arm, m
#: A plan written by hand: three poses (deg) and loads (N) of 100 N.
HAND_DEG = np.array([[0.0, 90.0], [90.0, -90.0], [45.0, -120.0]])
HAND_F = np.array([[0.0, 100.0], [100.0, 0.0], [-60.0, 80.0]])


def _A(q, F):
    """Planar 2R elasto-static matrix [J_n J_n^T F], written out by hand."""
    s1, c1, s12, c12 = np.sin(q[0]), np.cos(q[0]), np.sin(q[0] + q[1]), np.cos(q[0] + q[1])
    J = np.array([[-L1 * s1 - L2 * s12, -L2 * s12], [L1 * c1 + L2 * c12, L2 * c12]])
    return J * (J.T @ F)[None, :]


def _write(path, text):
    path.write_text(text)
    return path


@pytest.fixture
def hand_csv(tmp_path):
    rows = "\n".join(f"{a:g},{b:g},{fx:g},{fy:g}" for (a, b), (fx, fy) in zip(HAND_DEG, HAND_F))
    return _write(tmp_path / "plan.csv", "# three poses by hand\nq1_deg,q2_deg,fx_N,fy_N\n" + rows + "\n")


def test_evaluate_reproduces_the_library_numbers_for_a_hand_written_plan(paper, hand_csv, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["evaluate", str(PAPER), "--plan", str(hand_csv), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    ev = json.loads((out / "evaluation.json").read_text())
    Q, F = np.radians(HAND_DEG), HAND_F
    lib = plan_scores(paper, Q, F)  # what solve computes for a plan
    assert ev["m"] == 3 and ev["violations"] == []
    np.testing.assert_array_equal(ev["rms_error_m"], lib.rms_error_m)
    for key, value in lib.values.items():
        assert ev[key] == value, key
    assert ev["observability"] == lib.observability
    # and independently of the library, from the formulas of the paper
    M = sum(_A(q, f).T @ _A(q, f) for q, f in zip(Q, F))
    rho = [1e-4**2 * np.trace(_A(q0, f0) @ np.linalg.solve(M, _A(q0, f0).T))
           for q0, f0 in zip(paper.test_poses.q, paper.test_poses.F)]
    assert ev["max_rms_error_m"] == pytest.approx(np.sqrt(max(rho)), rel=1e-9)
    assert ev["log_det_M"] == pytest.approx(np.log(np.linalg.det(M)), rel=1e-9)
    assert f"{np.sqrt(max(rho)) * 1e3:.4f}" in printed
    assert "satisfies the problem's joint limits, load and workspace" in printed


def test_joint_names_and_radians_give_the_same_scores(paper, hand_csv, tmp_path, capsys):
    rad = np.radians(HAND_DEG)
    rows = "\n".join(f"{i + 1},{float(a)!r},{float(b)!r},{fx},{fy}"
                     for i, ((a, b), (fx, fy)) in enumerate(zip(rad, HAND_F)))
    other = _write(tmp_path / "rad.csv", "experiment,joint1_rad,joint2_rad,fx_N,fy_N\n" + rows + "\n")
    Qa, Fa = read_plan_csv(paper, hand_csv)
    Qb, Fb = read_plan_csv(paper, other)
    np.testing.assert_allclose(Qa, Qb, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(Fa, Fb)
    # the scores: evaluate on each file, as a user runs it
    scores = []
    for name, plan in (("deg", hand_csv), ("rad", other)):
        assert main(["evaluate", str(PAPER), "--plan", str(plan), "--out", str(tmp_path / name),
                     "--quiet"]) == 0
        scores.append(json.loads((tmp_path / name / "evaluation.json").read_text()))
    deg, rad = scores
    assert capsys.readouterr().err == ""
    keys = [c.score for c in CRITERIA.values()]  # each criterion's (max_rms_error_m, log_det_M...)
    assert set(keys) <= set(deg) and set(keys) <= set(rad)
    for key in keys:
        assert rad[key] == pytest.approx(deg[key], rel=1e-9), key
    np.testing.assert_allclose(rad["rms_error_m"], deg["rms_error_m"], rtol=1e-9)
    assert rad["observability"] == pytest.approx(deg["observability"], rel=1e-9)
    assert rad["violations"] == deg["violations"] == []
    # and they are the plan's: the paper's formulas on the poses in degrees, outside the package
    M = sum(_A(q, f).T @ _A(q, f) for q, f in zip(np.radians(HAND_DEG), HAND_F))
    rho = [paper.sigma_m**2 * np.trace(_A(q0, f0) @ np.linalg.solve(M, _A(q0, f0).T))
           for q0, f0 in zip(paper.test_poses.q, paper.test_poses.F)]
    assert rad["max_rms_error_m"] == pytest.approx(np.sqrt(max(rho)), rel=1e-9)
    np.testing.assert_allclose(rad["rms_error_m"], np.sqrt(rho), rtol=1e-9)
    assert rad["log_det_M"] == pytest.approx(np.log(np.linalg.det(M)), rel=1e-9)


def test_exported_plan_reads_back_exactly_and_scores_like_the_design(paper, tmp_path):
    d = solve_design(paper, "test-pose", 5, starts=3)
    path = tmp_path / "plan.csv"
    write_plan_csv(path, paper, d)
    header = path.read_text().splitlines()[0].split(",")
    assert header == ["experiment", "joint1_deg", "joint2_deg", "joint1_rad", "joint2_rad", "fx_N", "fy_N",
                      "x_mm", "y_mm", "z_mm"]
    Q, F = read_plan_csv(paper, path)
    np.testing.assert_array_equal(Q, d.Q)
    np.testing.assert_array_equal(F, d.F)
    again = plan_scores(paper, Q, F)
    assert again.max_rms_error_m == d.scores.max_rms_error_m
    _, rows = plan_table(paper, d.Q, d.F)
    for (q1, q2), row in zip(d.Q, rows):  # the point the tracker looks at, mm
        assert row[-3:-1] == pytest.approx([1e3 * (L1 * np.cos(q1) + L2 * np.cos(q1 + q2)),
                                            1e3 * (L1 * np.sin(q1) + L2 * np.sin(q1 + q2))], rel=1e-12)
        assert row[1:3] == pytest.approx(np.degrees([q1, q2]), rel=1e-15)


def test_evaluate_compares_with_the_optimal_plans_of_the_same_m(paper_solve_out, tmp_path, capsys):
    solved = paper_solve_out
    plan = solved / "plans" / "D_m5.csv"
    assert main(["evaluate", str(PAPER), "--plan", str(plan), "--compare", str(solved),
                 "--out", str(tmp_path / "ev")]) == 0
    lines = capsys.readouterr().out.splitlines()
    head = next(ln for ln in lines if ln.startswith("measure"))
    assert head.split()[-7:] == ["your", "plan", "test-pose", "m=5", "D", "m=5", "E", "m=5"][-7:]
    row = next(ln for ln in lines if ln.startswith("max over test poses")).split()
    mine, tp, D = float(row[-4]), float(row[-3]), float(row[-2])
    assert mine == D and tp < D  # the D plan read back scores as the D design
    import matplotlib.image

    img = matplotlib.image.imread(tmp_path / "ev" / "evaluation.png")
    assert img.shape[0] > 300 and img[..., :3].std() > 0.05
    # a copy of the problem file edited under the same name (sigma doubled) is another problem
    edited = tmp_path / "paper_noisy.toml"
    edited.write_text(PAPER.read_text().replace("sigma_m = 1.0e-4", "sigma_m = 2.0e-4"))
    assert edited.read_text() != PAPER.read_text()
    assert main(["evaluate", str(edited), "--plan", str(plan), "--compare", str(solved)]) == 2
    assert f"results of 'paper_planar_2r' with other sigma_m than {edited}; compare with results of this problem " \
           "file" in capsys.readouterr().err


def test_evaluate_reports_broken_constraints(paper, tmp_path, capsys):
    plan = _write(tmp_path / "p.csv", "q1_deg,q2_deg,fx_N,fy_N\n0,90,0,150\n200,10,0,100\n")
    assert main(["evaluate", str(PAPER), "--plan", str(plan)]) == 0
    out = capsys.readouterr().out
    assert "breaks 2 constraint(s)" in out
    assert "experiment 1: |F| = 150 N above 100 N" in out
    assert "experiment 2: joint1 = 3.49066 outside [-3.14159, 3.14159]" in out


@pytest.mark.parametrize("text, match", [
    ("q1_deg,q2_degree,fx_N,fy_N\n0,1,0,100\n", "unknown column 'q2_degree'; allowed: q1_deg or q1_rad"),
    ("q1_deg,fx_N,fy_N\n0,0,100\n", r"no column for joint 2 \(joint2\); add q2_deg or q2_rad"),
    ("q1_deg,q2_deg,fx_N,fy_N\n0,x,0,100\n", "row 2, column 'q2_deg': expected a number, got 'x'"),
    ("q1_deg,q2_deg,q1_rad,fx_N,fy_N\n10,0,0,0,100\n", "columns q1_deg, q1_rad of joint joint1 disagree"),
    ("q1_deg,q2_deg,fx_N\n0,0,100\n", "missing force column 'fy_N'"),
    ("q1_deg,q2_deg,fx_N,fy_N\n", "no experiments below the header"),
    ("# nothing\n", "empty plan file"),
])
def test_bad_plan_files(paper, tmp_path, text, match):
    with pytest.raises(ProblemError, match=match):
        read_plan_csv(paper, _write(tmp_path / "bad.csv", text))


def test_bad_plan_file_is_one_line_through_the_command(tmp_path, capsys):
    assert main(["evaluate", str(PAPER), "--plan", str(tmp_path / "none.csv")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path / 'none.csv'}: no such plan file; check the path"


def test_fixed_load_plans_need_no_force_columns(tmp_path):
    raw = paper_raw()
    raw["experiments"]["force"] = {"mode": "fixed", "vector_N": [0.0, 100.0]}
    p = build(raw)
    Q, F = read_plan_csv(p, _write(tmp_path / "p.csv", "q1_deg,q2_deg\n0,90\n90,-90\n"))
    np.testing.assert_array_equal(F, [[0.0, 100.0], [0.0, 100.0]])
    assert plan_violations(p, Q, F) == []


def test_solve_writes_plans_and_a_report_that_links_its_figures(paper_solve_out):
    out = paper_solve_out  # the paper's criteria test-pose, D, E at m = 1, 5
    report = (out / "report.md").read_text()
    assert report.startswith("# Calibration plan: paper_planar_2r")
    assert "| calibration load | equal, \\|F\\| = 100 N |" in report
    assert "![Fig. 1: +/- sqrt(rho) along the test poses](fig1.png)" in report and (out / "fig1.png").exists()
    assert "### D plan, m = 5" in report
    assert sorted(p.name for p in (out / "plans").iterdir()) == [
        "D_m1.csv", "D_m5.csv", "E_m1.csv", "E_m5.csv", "test-pose_m1.csv", "test-pose_m5.csv"]


def _test_poses_row(problem) -> str:
    report = report_markdown(problem, [], table="", figures=[], plans_for=[], files=[], starts="2")
    return next(line for line in report.splitlines() if line.startswith("| test poses |"))


def test_report_describes_joint_space_test_poses_by_the_box_of_their_points():
    """TIAGo's 12 held-out postures (joints_rad) are no line from the first to the last: the row
    gives their number and the box of their measured points (mm)."""
    tiago = load_problem(ROOT / "tests" / "data" / "tiago_mocap" / "tiago_mocap.toml")
    assert _test_poses_row(tiago) == ("| test poses | 12 joint-space poses (joints_rad), positions within "
                                      "x 222..898, y -80..372, z 304..1078 mm |")


def test_report_describes_separate_points_by_their_box_and_a_path_from_its_first_to_its_last_point():
    raw = read_raw(ROOT / "problems" / "ur10_drilling.toml")
    raw.pop("cell", None)
    assert _test_poses_row(build(raw)) == ("| test poses | 9 points (points_m), positions within x 600..900, "
                                           "y -300..300, z 100..100 mm |")
    raw["test_poses"]["path"] = {"kind": "line", "points_m": [[0.6, -0.3, 0.1], [0.9, 0.3, 0.1]], "nodes": 5}
    assert _test_poses_row(build(raw)) == "| test poses | 5 poses, from (600, -300, 100) to (900, 300, 100) mm |"
