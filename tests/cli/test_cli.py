"""The command line: results.json recomputed without the package, figures, error paths."""

import json
import subprocess
import sys

import numpy as np
import pytest

from casadi_design.cli import main
from tests.conftest import STARTS, PAPER, ROOT

L1, L2 = 0.6, 0.4  # the paper's arm, m


def _A(q, F):
    """Planar 2R elasto-static matrix [J_n J_n^T F], written out by hand."""
    s1, c1, s12, c12 = np.sin(q[0]), np.cos(q[0]), np.sin(q[0] + q[1]), np.cos(q[0] + q[1])
    J = np.array([[-L1 * s1 - L2 * s12, -L2 * s12], [L1 * c1 + L2 * c12, L2 * c12]])
    return J * (J.T @ F)[None, :]


@pytest.fixture(scope="module")
def solved(paper_solve_out):
    return paper_solve_out, json.loads((paper_solve_out / "results.json").read_text())


def test_results_json_recomputes_without_the_package(solved):
    _, res = solved
    assert res["problem"] == "paper_planar_2r" and res["seed"] == 2024 and res["sigma_m"] == 1e-4
    assert res["robot"]["planar_links_m"] == [L1, L2]
    assert {(d["criterion"], d["m"]) for d in res["designs"]} == {
        (c, m) for c in ("test-pose", "D", "E") for m in (1, 5)}
    A0 = [_A(np.array(t["q_rad"]), np.array(t["force"])) for t in res["test_poses"]]
    for d in res["designs"]:
        assert len(d["experiments"]) == d["m"]
        assert d["solver"]["status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
        rounded = {"test-pose": 4, "D": 8, "E": 4}[d["criterion"]]  # starts from an approximate design (E: A's)
        assert d["solver"]["starts"] == STARTS + rounded and d["solver"]["wall_s"] > 0
        assert (d["bound"] is not None) == (d["criterion"] != "E")
        if d["criterion"] == "test-pose":
            assert d["bound"]["value"] <= d["max_rms_error_m"]
        if d["criterion"] == "D":
            assert d["bound"]["value"] >= d["scores"]["log_det_M"]
        M = sum(_A(np.array(e["q_rad"]), np.array(e["force"])).T @ _A(np.array(e["q_rad"]), np.array(e["force"]))
                for e in d["experiments"])
        rms = [res["sigma_m"] * np.sqrt(np.trace(a @ np.linalg.inv(M) @ a.T)) for a in A0]
        np.testing.assert_allclose(d["rms_error_m"], rms, rtol=1e-8)
        assert d["max_rms_error_m"] == pytest.approx(max(rms), rel=1e-12)


def test_figures_are_real_images(solved):
    import matplotlib.image

    out, _ = solved
    img = matplotlib.image.imread(out / "fig1.png")
    assert img.shape[0] > 400 and img.shape[1] > 800
    assert img[..., :3].std() > 0.05  # not blank
    assert (out / "fig1.pdf").read_bytes().startswith(b"%PDF")


def test_bad_problem_exits_2_with_one_line_and_writes_nothing(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(PAPER.read_text().replace("sigma_m = 1.0e-4", "sigma_m = -1.0"))
    out = tmp_path / "out"
    assert main(["solve", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "[measurement].sigma_m: must be positive" in err[0]
    assert not out.exists()


def test_script_is_a_thin_wrapper(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(PAPER.read_text().replace('"E"]', '"Z"]'))
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "solve_case.py"), str(bad)],
                         capture_output=True, text=True, check=False)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert "[design].criteria: has 'Z'" in run.stderr


# --------------------------------------------------------------------------- the command itself

@pytest.mark.parametrize("command, words", [
    ("solve", ["--m", "--starts", "--jobs", "--dask-scheduler", "--quiet", "--verbose", "--force", "mm"]),
    ("sweep", ["--m", "1:10", "--log", "--resume", "--no-warm-start", "--jobs", "mm"]),
    ("evaluate", ["--plan", "q1_deg", "fx_N", "--compare", "mm"]),
    ("plot", ["--log", "--format", "--m", "mm"]),
])
def test_every_subcommand_explains_its_options(command, words, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for w in words:
        assert w in text, w


@pytest.mark.parametrize("command", ["solve", "sweep", "evaluate", "plot", "bound", "validate", "identify", "program"])
def test_every_subcommand_takes_quiet(command, capsys):
    """A script can pass -q to any command."""
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert "--quiet, -q" in capsys.readouterr().out


def test_console_script_is_declared_and_scripts_stay_thin():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"] == {"casadi-design": "casadi_design.launch:main"}
    assert any(d.startswith("tqdm") for d in project["dependencies"])
    assert project["optional-dependencies"]["dask"] == ["dask[distributed]>=2023.1"]
    src = (ROOT / "scripts" / "solve_case.py").read_text()
    assert "from casadi_design.launch import main" in src and len(src.splitlines()) < 12


def test_python_dash_m_runs_the_command():
    run = subprocess.run([sys.executable, "-m", "casadi_design", "sweep", "--help"],
                         capture_output=True, text=True, cwd=ROOT, check=False)
    assert run.returncode == 0 and "usage: casadi-design sweep" in run.stdout


def test_solve_refuses_a_non_empty_output_folder(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("x")
    assert main(["solve", str(PAPER), "--out", str(tmp_path), "--starts", "1"]) == 2
    assert capsys.readouterr().err.startswith(f"error: {tmp_path}: folder exists and is not empty; add --force")
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_validate_subcommand_runs_the_virtual_calibration(tmp_path, paper_solve_out, capsys):
    """(validate without --results simulates solve's plans: tests/virtual/test_validate.py)"""
    bad = tmp_path / "bad.toml"
    bad.write_text(PAPER.read_text().replace("sigma_m = 1.0e-4", "sigma_m = 0.0"))
    assert main(["validate", str(bad)]) == 2
    assert "[measurement].sigma_m: must be positive" in capsys.readouterr().err
    assert main(["validate", str(PAPER), "--results", str(paper_solve_out / "results.json"), "--trials", "50",
                 "--out", str(tmp_path / "v")]) == 0
    out = capsys.readouterr().out
    assert "ranking by the measure ['test-pose', 'D', 'E'], by simulation" in out
    assert (tmp_path / "v" / "validation.json").exists()


def test_quiet_keeps_the_base_set_to_its_count():
    """-q prints the case and the base set's count, not what each parameter left out acts as
    (28 lines on a DH arm of 33 parameters)."""
    from casadi_design.cli.common import case_line
    from casadi_design.cli.identify import load_without_cell

    problem = load_without_cell(str(ROOT / "problems" / "ur10_drilling.toml"))
    full, quiet = case_line(problem).splitlines(), case_line(problem, quiet=True).splitlines()
    assert quiet == full[:2] and full[1].startswith("identifiable base set: ")
    assert any(line.startswith("dropped ") for line in full[2:])


@pytest.mark.parametrize("unbuffered", ["1", ""])
def test_a_reader_that_stops_reading_loses_nothing(tmp_path, unbuffered):
    """``casadi-design ... | head``: the output's reader gone before the command prints, the
    command still writes its files and ends as it would, with no error (buffered or not)."""
    import os

    read, write = os.pipe()
    os.close(read)  # the reader is gone: every write to the pipe fails (EPIPE)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"} | (
        {"PYTHONUNBUFFERED": unbuffered} if unbuffered else {})
    try:
        run = subprocess.run([sys.executable, "-m", "casadi_design", "solve", str(PAPER), "--m", "3", "--criteria", "D",
                              "--starts", "1", "--bound-steps", "0", "--out", str(tmp_path / "out")],
                             stdout=write, stderr=subprocess.PIPE, text=True, env=env, check=False)
    finally:
        os.close(write)
    assert run.returncode == 0 and run.stderr.strip() == "", run.stderr
    assert (tmp_path / "out" / "results.json").exists() and (tmp_path / "out" / "report.md").exists()
