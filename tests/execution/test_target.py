"""The smallest m of a tolerance (--target-mm): the search, its bound and its statement."""

import json

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.execution.campaign import Settings
from casadi_design.execution.target import TargetAnswer, run_target
from tests.conftest import PAPER

SETTINGS = Settings(2, bound_steps=10, bound_pool=50)


@pytest.mark.slow  # 3 s: the command test below runs the same search (test-pose alone) and checks the same figures
def test_the_search_finds_the_smallest_m_and_excludes_fewer_by_the_bound(paper):
    """On the paper's arm the test-pose optimum falls as about 1 / sqrt(m) (0.121 mm at m = 1):
    the target 0.05 mm is first reached at m = 6, and m = 5 is excluded by its bound; every m
    designed on the way is above the target, the answer's plan below it."""
    campaign, answer = run_target(paper, ("test-pose", "D"), 1, 15, SETTINGS, 0.05e-3)
    assert answer.m == 6 and answer.fewer_excluded
    assert answer.bounds_m[5] > 0.05e-3 >= answer.errors_m[6]
    assert all(e > 0.05e-3 for m, e in answer.errors_m.items() if m < 6)
    assert answer.bounds_m[6] <= answer.errors_m[6]
    assert ("D", 6) in campaign.designs and campaign.target is answer
    assert "target 0.05 mm: m = 6" in answer.line() and "5 cannot reach 0.05 mm" in answer.line()


def test_an_unreachable_target_says_so_and_designs_the_limit(paper):
    campaign, answer = run_target(paper, ("test-pose",), 1, 4, SETTINGS, 0.01e-3)
    assert answer.m is None and set(campaign.designs) == {("test-pose", 4)}
    assert answer.bounds_m[4] > 0.01e-3
    assert "no plan of up to 4 experiments reaches it" in answer.line()


@pytest.mark.parametrize("bounds, errors, said", [
    ({5: 0.021e-3}, {5: 0.022e-3, 6: 0.019e-3}, "5 cannot reach 0.02 mm (bound 0.021 mm)"),
    ({5: 0.0196e-3}, {5: 0.0204e-3, 6: 0.019e-3}, "5 might (bound 0.0196 mm, its plan 0.0204 mm)"),
])
def test_the_statement_on_one_fewer(bounds, errors, said):
    answer = TargetAnswer(0.02e-3, 6, 20, errors, bounds, 3)
    assert said in answer.line()
    assert answer.as_dict()["fewer_excluded_by_bound"] == ("cannot" in said)
    assert TargetAnswer(0.02e-3, 3, 20, {3: 0.01e-3}, {}, 3).fewer_excluded is None


def test_solve_and_sweep_write_the_answer(tmp_path, capsys):
    tiny = ["--starts", "2", "--bound-steps", "10", "--bound-pool", "50", "--jobs", "1", "--quiet"]
    assert main(["solve", str(PAPER), "--target-mm", "0.05", "--out", str(tmp_path / "s"), *tiny]) == 0
    assert "target 0.05 mm: m = 6" in capsys.readouterr().out
    target = json.loads((tmp_path / "s" / "results.json").read_text())["target"]
    assert target["m"] == 6 and target["fewer_excluded_by_bound"] is True
    errors, bounds = ({int(m): v for m, v in target[k].items()} for k in ("max_rms_error_m", "bound_m"))
    assert bounds[5] > 0.05e-3 >= errors[6] >= bounds[6]  # m = 5 excluded by its bound, m = 6 reaches it
    assert all(e > 0.05e-3 for m, e in errors.items() if m < 6)  # every m designed on the way falls short
    assert target["answer"] in (tmp_path / "s" / "report.md").read_text()
    # --m gives the last m to search; the search starts at the smallest identifiable m
    assert main(["solve", str(PAPER), "--m", "7:8", "--target-mm", "0.05", *tiny]) == 0
    assert "target 0.05 mm: m = 6" in capsys.readouterr().out
    assert main(["sweep", str(PAPER), "--m", "5:6", "--criteria", "test-pose", "--target-mm", "0.05",
                 "--out", str(tmp_path / "w"), *tiny]) == 0
    assert "target 0.05 mm: m = 6" in capsys.readouterr().out
    swept = json.loads((tmp_path / "w" / "sweep.json").read_text())["target"]
    assert swept["m"] == 6 and np.isclose(swept["max_rms_error_m"]["6"], target["max_rms_error_m"]["6"])
    assert main(["solve", str(PAPER), "--target-mm", "0.05", "--criteria", "D", *tiny]) == 2
    assert "add test-pose to --criteria" in capsys.readouterr().err
