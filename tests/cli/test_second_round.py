"""The second round from the command line: --measured, --prior, and their bad files."""

import json
import re
from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.cli import main
from casadi_design.errors import ProblemError
from casadi_design.identification.held import read_held
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem
from casadi_design.problem_file.read import read_problem
from casadi_design.records.export import csv_text, plan_table
from tests.cli.test_cli import _A
from tests.conftest import PAPER, ROOT
from tests.identify_data import TrueRobot, measured, measurement_csv

TINY = ["--starts", "2", "--bound-steps", "2", "--bound-pool", "50", "--jobs", "1", "--quiet"]
GEOMETRIC = ROOT / "problems" / "planar_2r_geometric.toml"


def plan_file(path, problem, Q, F):
    path.write_text(csv_text(*plan_table(problem, Q, F)))
    return path


def test_a_campaign_is_its_measured_experiments_then_the_new_ones(paper, tmp_path, capsys):
    """results.json lists the measured experiment first, marked, and its errors are the whole
    campaign's (recomputed by hand); the plan CSV marks the row, evaluate of that CSV alone
    gives the same error, and program orders the new experiments only."""
    Q, F = random_plan(paper, 1, np.random.default_rng(5))
    first = plan_file(tmp_path / "first.csv", paper, Q, F)
    out = tmp_path / "second"
    assert main(["solve", str(PAPER), "--m", "2", "--criteria", "test-pose", "--measured", str(first),
                 "--out", str(out), *TINY]) == 0
    printed = capsys.readouterr().out
    assert "held before the plan: 1 experiment measured" in printed
    res = json.loads((out / "results.json").read_text())
    d = res["designs"][0]
    assert d["m"] == 2 and d["m_measured"] == 1 and res["held"]["m_measured"] == 1
    assert [e.get("measured", False) for e in d["experiments"]] == [True, False, False]
    np.testing.assert_array_equal(d["experiments"][0]["q_rad"], Q[0])
    M = sum(a.T @ a for e in d["experiments"] for a in [_A(np.array(e["q_rad"]), np.array(e["force"]))])
    A0 = [_A(np.array(t["q_rad"]), np.array(t["force"])) for t in res["test_poses"]]
    rms = [res["sigma_m"] * np.sqrt(np.trace(a @ np.linalg.inv(M) @ a.T)) for a in A0]
    assert d["max_rms_error_m"] == pytest.approx(max(rms), rel=1e-9)
    assert d["bound"]["value"] <= d["max_rms_error_m"]
    csv = out / "plans" / "test-pose_m2.csv"
    assert [row.split(",")[-1] for row in csv.read_text().splitlines()] == ["measured", "yes", "no", "no"]
    assert main(["evaluate", str(PAPER), "--plan", str(csv), "--out", str(tmp_path / "e")]) == 0
    evaluated = json.loads((tmp_path / "e" / "evaluation.json").read_text())
    assert max(evaluated["rms_error_m"]) == pytest.approx(d["max_rms_error_m"], rel=1e-9)
    capsys.readouterr()
    assert main(["program", str(PAPER), "--plan", str(csv), "--format", "yaml"]) == 0
    assert ": 2 experiments;" in capsys.readouterr().out


def test_a_prior_from_an_identification_of_rows_is_the_information_of_those_rows(tmp_path, capsys, monkeypatch):
    """identify of rows R (noise-free, in the base frame, the problem's own parameters) writes
    a covariance whose prior holds the same M as --measured R, to 1e-9: the design from an
    identification and the design around its rows are the same design."""
    problem = build_problem(read_problem(GEOMETRIC))
    Q, F = random_plan(problem, 5, np.random.default_rng(2))
    rows = plan_file(tmp_path / "rows.csv", problem, Q, F)
    nominal = TrueRobot(problem.robot.model, problem.robot.frame_id, np.zeros(problem.robot.n), pin.SE3.Identity())
    P = measured(problem, nominal, Q, F, np.random.default_rng(0), sigma=0.0)
    (tmp_path / "meas.csv").write_text(measurement_csv(problem, Q, F, P))
    monkeypatch.chdir(tmp_path)  # the identification names its file as given: relative to here
    assert main(["identify", str(GEOMETRIC), "--measurements", "meas.csv", "--frame", "base",
                 "--model", "identifiable", "--out", str(tmp_path / "id")]) == 0
    monkeypatch.chdir(ROOT)
    capsys.readouterr()
    by_rows = build_problem(replace(problem.spec, held=read_held(problem, [str(rows)], None))).M_held
    prior = read_held(problem, None, str(tmp_path / "id" / "identification.json"))
    assert prior.prior_names == problem.model.parameter_names
    by_prior = build_problem(replace(problem.spec, held=prior)).M_held
    np.testing.assert_allclose(by_prior, by_rows, rtol=0, atol=1e-9 * np.abs(by_rows).max())
    # so both at once count the rows twice: refused, whether by the same path or a copy, from any folder
    identification = str(tmp_path / "id" / "identification.json")
    (tmp_path / "copy.csv").write_bytes((tmp_path / "meas.csv").read_bytes())
    for given in (tmp_path / "meas.csv", tmp_path / "copy.csv"):
        with pytest.raises(ProblemError, match=rf"--measured {re.escape(str(given))}: --prior .* was identified from "
                                               r"it \(.*meas.csv\), so its information is in the prior already"):
            read_held(problem, [str(given)], identification)


def test_bad_second_round_files_get_one_line(paper, tmp_path, capsys):
    ur10 = build_problem(replace(read_problem(ROOT / "problems/ur10_drilling.toml"), cell=None))
    other = plan_file(tmp_path / "ur10.csv", ur10, *random_plan(ur10, 2, np.random.default_rng(0)))
    Q, F = random_plan(paper, 1, np.random.default_rng(0))
    Q[0, 1] = 9.0  # rad: beyond the joint's limits
    outside = plan_file(tmp_path / "outside.csv", paper, Q, F)
    (tmp_path / "identification.json").write_text(json.dumps(
        {"parameters": [{"name": "shoulder_pan_joint.offset", "of": "robot"}], "covariance": [[1e-6]]}))
    cases = [(["--measured", str(other)], "joint 'shoulder_pan_joint', which the robot of"),
             (["--measured", str(outside)], "row 2, column 'joint2_deg'"),
             (["--prior", str(tmp_path / "identification.json")], "names none of this problem's parameters"),
             (["--prior", str(tmp_path / "missing.json")], "no such file")]
    for extra, message in cases:
        assert main(["solve", str(PAPER), "--m", "1", *TINY, *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err


def test_a_solve_reads_each_measured_file_once_and_builds_its_problem_once(paper, tmp_path, capsys, monkeypatch):
    """``solve --measured A --measured B --program json``: each file's text is read once (its
    header, rows and joint limits from that one reading; B in FIGAROH's measurement layout,
    whose header decides how it is read) and the problem is built twice, without and then with
    what is held, not once more for the program's format."""
    import casadi_design.problem.build as build
    import casadi_design.records.export as export

    geometric = build_problem(read_problem(GEOMETRIC))
    Q, F = random_plan(geometric, 2, np.random.default_rng(1))
    first = plan_file(tmp_path / "first.csv", geometric, Q, F)
    nominal = TrueRobot(geometric.robot.model, geometric.robot.frame_id, np.zeros(geometric.robot.n), pin.SE3.Identity())
    P = measured(geometric, nominal, Q, F, np.random.default_rng(0), sigma=0.0)[:, 0]  # m
    figaroh = [[*q, *p] for q, p in zip(Q, P)]  # bare joint names (rad), x1, y1, z1 (m)
    (tmp_path / "meas.csv").write_text(csv_text([*geometric.robot.joints, "x1", "y1", "z1"], figaroh))
    read, built = [], []
    text, problem_of = export._plan_text, build.build_problem
    monkeypatch.setattr(export, "_plan_text", lambda path: read.append(path) or text(path))
    monkeypatch.setattr(build, "build_problem", lambda spec: built.append(spec.held) or problem_of(spec))
    out = tmp_path / "second"
    assert main(["solve", str(GEOMETRIC), "--m", "1", "--criteria", "D", "--measured", str(first),
                 "--measured", str(tmp_path / "meas.csv"), "--program", "json", "--out", str(out), *TINY,
                 "--starts", "1", "--bound-steps", "0"]) == 0
    capsys.readouterr()
    assert read == [str(first), str(tmp_path / "meas.csv")]
    assert [held is None for held in built] == [True, False] and len(built[1].q) == 4
    assert (out / "programs" / "D_m1.json").exists()
