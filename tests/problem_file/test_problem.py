"""Problem files: every shipped file loads; every bad input gets one clear message."""

from pathlib import Path

import numpy as np
import pytest

from casadi_design.errors import DesignError, ProblemError
from casadi_design.optimisation.solve import solve_design
from casadi_design.problem.build import load_problem
from casadi_design.problem_file.read import parse_problem
from tests.conftest import ROOT, build, paper_raw, read_raw


@pytest.mark.parametrize("path", sorted((ROOT / "problems").glob("*.toml")), ids=lambda p: p.name)
def test_every_problem_file_loads_and_builds(path):
    from casadi_design.optimisation.nlp import build_nlp

    problem = load_problem(path)
    assert problem.test_poses.s >= 1
    for c in problem.criteria:
        build_nlp(problem, c, max(problem.m_values))


def test_paper_problem_is_the_papers_example(paper):
    assert paper.sigma_m == 1e-4
    np.testing.assert_allclose(paper.test_poses.position_m[[0, -1], :2], [[-0.6, 0.4], [0.6, 0.4]], atol=1e-12)
    np.testing.assert_allclose(paper.test_poses.F, np.tile([0.0, 100.0], (paper.test_poses.s, 1)))
    assert paper.model.parameter_names == ("k.joint1", "k.joint2")
    assert paper.m_values == (1, 5) and paper.force.magnitude_N == 100.0


def _edit(path: str, value):
    raw = paper_raw()
    *parents, key = path.split(".")
    table = raw
    for p in parents:
        table = table.setdefault(p, {})
    if value is None:
        del table[key]
    else:
        table[key] = value
    return raw


@pytest.mark.parametrize(
    "path, value, match",
    [
        ("design.criteria", ["test-pose", "d-opt"], r"\[design\].criteria: has 'd-opt'; allowed: test-pose, D, A, E, T, condition"),
        ("design.critera", ["D"], r"\[design\]: unknown key 'critera'; allowed: criteria"),
        ("speed", 3, r"top level: unknown key 'speed'"),
        ("measurement", None, r"\[measurement\]: missing section"),
        ("measurement.sigma_m", None, r"\[measurement\].sigma_m: missing"),
        ("measurement.sigma_m", -1.0, r"sigma_m: must be positive"),
        ("measurement.sigma_m", "0.1 mm", r"sigma_m: expected float"),
        ("test_poses.line_m", {"start": [-0.6, 0.4], "end": [1.2, 0.4], "nodes": 5}, r"out of reach: distance 1264.9 mm, reachable 200.0 to 1000.0 mm"),
        ("test_poses.line_m", {"start": [-0.6, 0.4], "end": [0.6, 0.4]}, r"\[test_poses.line_m\].nodes: missing"),
        ("test_poses.elbow", "left", r"\[test_poses\].elbow: 'left'; allowed: up, down"),
        ("test_poses.force_N", [0.0, 1.0, 2.0], r"force_N: expected finite numbers of shape 2"),
        ("experiments.m", [1, 0], r"\[experiments\].m: expected positive integers"),
        ("experiments.force.mode", "free", r"mode: 'free'; allowed: equal, bound, fixed"),
        ("robot.frame", "flange", r"unknown frame 'flange'; the model has: .*tool"),
        ("robot.joint_limits_rad", {"elbow": [-1, 1]}, r"unknown joint 'elbow'; the chain to 'tool' has: joint1, joint2"),
        ("robot.joint_limits_rad", {"joint1": [1, -1]}, r"lower 1.0 must be below upper -1.0"),
        ("calibration.compliant_joints", ["joint3"], r"unknown joint 'joint3'"),
        ("robot.urdf", "nowhere.urdf", r"\[robot\]: has .* of planar_links_m, urdf, dh; give exactly one"),
        ("robot.joint_limits_rad", {"joint1": ["a", 0]}, r"joint_limits_rad\].joint1: expected numbers"),
        ("robot.joint_limits_rad", {"joint1": [True, 1.0]}, r"joint_limits_rad\].joint1: expected numbers"),
        ("calibration.compliant_joints", [], r"compliant_joints: has \[\]; list distinct joints"),
        ("calibration.compliant_joints", ["joint1", "joint1"], r"compliant_joints: has .*list distinct joints"),
        ("calibration.parameters", ["nonsense"], r"\[calibration\].parameters: is not used by case 'elastostatic'"),
        ("experiments.m", [5, 5], r"\[experiments\].m: has repeated values"),
        ("experiments.force", {"mode": "fixed", "vector_N": [0.0, 0.0]}, r"vector_N: is zero"),
        ("experiments.workspace", {"half_spaces": [{"normal": [0, 1, 0], "offset_m": "x"}]}, r"half_spaces\].offset_m: expected float"),
        ("experiments.workspace", {"half_spaces": [{"normal": [0, 1], "offset_m": 0.0}]}, r"half_spaces\].normal: expected finite numbers of shape 3"),
        ("solver.tol", -1.0, r"\[solver\].tol: must be positive"),
        ("solver.criterion_starts", {"d-opt": 2}, r"\[solver.criterion_starts\]: unknown key 'd-opt'; allowed: .*test-pose"),
        ("solver.criterion_starts", {"D": 0}, r"\[solver.criterion_starts\].D: must be between 1 and"),
        ("solver.criterion_starts", 4, r"\[solver\].criterion_starts: expected a table"),
        ("test_poses.joints_rad", [[0.1, 0.2]], r"give exactly one"),
    ],
)
def test_bad_input_messages(path, value, match):
    with pytest.raises(ProblemError, match=match):
        build(_edit(path, value))


PANDA = ROOT / "problems" / "panda_ball_socket.toml"


def _artefact(edit):
    raw = read_raw(PANDA)
    edit(raw, raw["measurement"]["artefact"])
    return raw


@pytest.mark.parametrize("edit, match", [
    (lambda r, a: a.update(points_m=[[0, 0, 0], [50, 0, 0]]), r"\[measurement.artefact\].points_m: has points 50 m apart; "
     r"give them in m"),
    (lambda r, a: a.update(points_m=[[0, 0, 0], [0, 0, 0]]), r"points_m: has a point twice"),
    (lambda r, a: a.update(points_m=[[0, 0, 0]]), r"points_m: has one point, which tells no length"),
    (lambda r, a: a.update(points_m=[]), r"points_m: expected finite numbers of shape any x 3, got \[\]; one row"),
    (lambda r, a: r["measurement"].update(components=["x", "y"]), r"\[measurement\].components: an artefact's points "
     r"are met by one point in x, y and z"),
    (lambda r, a: r["measurement"].update(sigma_rad=1e-4), r"\[measurement\].sigma_rad: is not used with an artefact"),
    (lambda r, a: a["placements"].append(dict(a["placements"][0])), r"placements\[5\]\].name: 'front_center' is empty "
     r"or repeated"),
    (lambda r, a: a.update(tilt_max_deg=200), r"tilt_max_deg: is 200 deg; give an angle in deg up to 180"),
    (lambda r, a: a.update(clamps=9), r"\[measurement.artefact\].clamps"),
    # the design's test-pose measure with a field is that of tracker rows (no placements' poses)
    (lambda r, a: r["calibration"].update(model_error={"angle_rad": [2e-4] * 7, "length_rad": [0.3] * 7}),
     r"\[calibration\].model_error: is not held by a design of an artefact's configurations yet; remove it"),
])
def test_bad_artefact_input_messages(edit, match):
    with pytest.raises(ProblemError, match=match):
        parse_problem(_artefact(edit), "test.toml")


def test_bad_ipopt_option_is_refused_before_solving():
    from casadi_design.optimisation.solve import check_ipopt_options

    problem = build(_edit("solver.ipopt", {"no_such_option": 3}))
    with pytest.raises(ProblemError, match=r"test.toml: \[solver\].ipopt: IPOPT rejected the options"):
        check_ipopt_options(problem)


def test_m_too_small_for_the_parameters():
    raw = paper_raw()
    raw["calibration"] = {"case": "both", "parameters": ["joint2.tx", "tool.tx"],
                          "wrench_components": ["fx", "fy"]}
    raw["experiments"]["m"] = [1, 5]
    with pytest.raises(ProblemError, match=r"m = 1 is too small: 4 parameters .* with 2 independent measured values per experiment need m >= 2; use m >= 2"):
        build(raw)


def test_non_identifiable_parameter_set():
    """A base rotation about z and joint 1's offset move the tool identically."""
    raw = paper_raw()
    raw["calibration"] = {"case": "geometric", "parameters": ["joint1.offset", "base.rz", "tool.tx"]}
    del raw["experiments"]["force"]
    del raw["test_poses"]["force_N"]
    raw["experiments"]["m"] = [2, 5]
    with pytest.raises(ProblemError, match=r"parameters: the parameters are not identifiable .*joint1.offset and base.rz act as one combination"):
        build(raw)
    raw["calibration"]["parameters"] = ["joint1.offset", "tool.rx"]
    with pytest.raises(ProblemError, match=r"not identifiable .*tool.rx has no effect on them .*remove it"):
        build(raw)


def test_geometric_case_rejects_loads_and_elbow_with_joints():
    raw = paper_raw()
    raw["calibration"] = {"case": "geometric", "parameters": ["joint1.offset", "joint2.offset"]}
    del raw["experiments"]["force"]
    with pytest.raises(ProblemError, match=r"\[test_poses\]: a geometric case has no machining load"):
        build(raw)
    del raw["test_poses"]["force_N"]
    del raw["test_poses"]["line_m"]
    raw["test_poses"]["joints_rad"] = [[0.1, 1.0]]
    with pytest.raises(ProblemError, match=r"\[test_poses\].elbow: only applies with points_m or line_m, not joints_rad"):
        build(raw)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ProblemError, match="no such problem file"):
        load_problem(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[robot\nframe = 1\n")
    with pytest.raises(ProblemError, match=r"bad.toml: not valid TOML"):
        load_problem(bad)


def test_test_pose_outside_joint_limits():
    raw = paper_raw()
    raw["robot"]["joint_limits_rad"] = {"joint2": [0.0, 3.0]}
    with pytest.raises(ProblemError, match=r"test pose 0 .* is outside the joint limits"):
        build(raw)


def test_infeasible_workspace_is_a_clear_error():
    raw = paper_raw()
    raw["experiments"]["workspace"] = {"half_spaces": [{"normal": [1.0, 0.0, 0.0], "offset_m": 2.0}]}
    problem = build(raw)
    with pytest.raises(DesignError, match=r"\[experiments.workspace\] leaves no feasible pose"):
        solve_design(problem, "D", 1, starts=1)


def test_solver_failure_is_a_status_then_a_clear_error():
    raw = paper_raw()
    raw["solver"]["max_iter"] = 1
    problem = build(raw)
    with pytest.raises(DesignError, match=r"none of 2 starts converged .*Maximum_Iterations_Exceeded.* x 2"):
        solve_design(problem, "test-pose", 5, starts=2)


def test_problem_files_have_documented_keys():
    doc = (ROOT / "docs" / "problem-format.md").read_text()
    from casadi_design.problem_file.read import SECTIONS

    for section, keys in SECTIONS.items():
        for key in set(keys or ()) - {k.split(".")[-1] for k in SECTIONS}:
            assert f"`{key}`" in doc, f"{section}.{key} is not documented"


def test_path_is_named_in_messages(tmp_path):
    f = tmp_path / "case.toml"
    f.write_text(Path(ROOT / "problems" / "paper_planar_2r.toml").read_text().replace('"E"]', '"F"]'))
    with pytest.raises(ProblemError, match=r"case.toml: \[design\].criteria: has 'F'"):
        load_problem(f)
