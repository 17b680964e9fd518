"""A study from Python: the request built once, run with callbacks, each finished design kept
in its partial file and read back by a resumed study without solving again."""

import numpy as np
import pytest

from casadi_design.errors import ProblemError
from casadi_design.execution.campaign import Settings
from casadi_design.execution.study import Study, run_study, writing


def test_a_study_keeps_its_designs_and_a_resumed_one_solves_nothing(paper, tmp_path, monkeypatch):
    partial = tmp_path / "solve.partial.json"
    study = Study(paper, ("test-pose", "D"), (1, 2), Settings(2, bound_steps=0), jobs=1, partial=partial)
    finished, starts = [], []
    first = run_study(study, on_design=finished.append, progress=starts.append)
    assert [(d.criterion, d.m) for d in finished] == [("test-pose", 1), ("D", 1), ("test-pose", 2), ("D", 2)]
    assert sum(starts) == study.starts == 8 and partial.is_file()

    from casadi_design.optimisation import solve

    monkeypatch.setattr(solve, "_solved_start", lambda *a: pytest.fail("a resumed study solved a start"))
    resumed = []
    again = run_study(Study(paper, ("test-pose", "D"), (1, 2), Settings(2, bound_steps=0), jobs=1,
                            partial=partial, resume=True), on_resume=resumed.append)
    assert resumed == [4]
    for key, d in first.designs.items():
        np.testing.assert_array_equal(again.designs[key].Q, d.Q)
        assert again.designs[key].scores.max_rms_error_m == d.scores.max_rms_error_m
    with writing(study):
        pass
    assert not partial.exists()  # the files written: the partial file goes


def test_a_study_checks_its_request(paper):
    with pytest.raises(ProblemError, match="--criteria has 'X'"):
        Study(paper, ("X",), (1,), Settings(1))
    with pytest.raises(ProblemError, match="--m 0 is too small"):
        Study(paper, ("D",), (0,), Settings(1))


def test_a_criterion_runs_its_own_seeded_starts_the_first_of_more(paper):
    """``[solver.criterion_starts]``: a design of a listed criterion runs its own number of
    seeded starts, the others the problem's; fewer starts are the first of more (each seeded
    plan depends on the seed, the criterion and m only), and --starts replaces both."""
    from dataclasses import replace

    from casadi_design.problem.build import build_problem

    problem = build_problem(replace(paper.spec, solver=replace(paper.solver, starts=3, criterion_starts=(("D", 1),))))
    settings = Settings.of(problem, bound_steps=0)
    assert (settings.seeded("D"), settings.seeded("test-pose"), settings.starts_text()) == (1, 3, "3 (D: 1)")
    assert Settings.of(problem, 5, bound_steps=0).seeded("D") == 5  # the command line's --starts
    study = Study(problem, ("test-pose", "D"), (1,), settings, jobs=1)
    starts = []
    done = run_study(study, progress=starts.append)
    assert [len(done.designs[c, 1].starts) for c in ("test-pose", "D")] == [3, 1]
    assert sum(starts) == study.starts == 4
    more = run_study(Study(problem, ("D",), (1,), Settings(3, bound_steps=0), jobs=1))
    assert done.designs["D", 1].starts[0] == more.designs["D", 1].starts[0]
