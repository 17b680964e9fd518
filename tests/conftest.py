"""Shared problems and robots for the tests."""

from __future__ import annotations

import copy
import os
import sys
import tempfile
import tomllib
from pathlib import Path

import pytest

# Bytecode is written even where PYTHONDONTWRITEBYTECODE is set (as on the CI machines): the
# suite starts dozens of Python processes (its two workers, process pools, commands run as
# scripts) that each compile the package again without it, about 0.2 s of CPU each.
sys.dont_write_bytecode = False

from casadi_design.runtime.threads import fixed_blas  # noqa: E402

# The suite runs CasADi's virtual machine: compiling a robot's functions the first time costs
# seconds per cell. tests/robot/test_compiled.py checks the compiled code gives the same bits.
os.environ.setdefault("CASADI_DESIGN_COMPILE", "0")
# What the package keeps between runs (casadi_design.runtime.cache: the capsules fitted around the
# meshes) goes to a folder of the test runs, not the user's cache.
os.environ.setdefault("CASADI_DESIGN_CACHE", os.path.join(tempfile.gettempdir(), f"casadi-design-tests-{os.getuid()}"))
# The approximate designs are computed in each test, not read back from an earlier run's
# (tests/runtime/test_cache.py checks reading them back).
os.environ.setdefault("CASADI_DESIGN_KEEP_DESIGNS", "0")
fixed_blas()  # as the command does, before numpy and CasADi load (casadi_design.launch)

from casadi_design.problem.build import build_problem, load_problem  # noqa: E402
from casadi_design.problem_file.read import parse_problem  # noqa: E402


def _keep_more_built() -> None:
    """Each test worker keeps more of what it built than a command does (the memos of
    casadi_design.runtime.cache, by the problem's checked data or its model): the suite's
    modules build the same problem files (and so the same fit models and CasADi functions)
    again and again, and a memo of 8 forgets them between one module and the next. A kept value
    is the value that would be computed, to the bit (tests/runtime/test_cache.py)."""
    from casadi_design.calibration import models
    from casadi_design.identification import compensate, fit, lsq
    from casadi_design.optimisation import approximate, reduced
    from casadi_design.problem import build
    from casadi_design.program import moves

    for memo in (build._BUILT, build._CELLS, fit._FITS, reduced.experiment_functions.memo,
                 approximate._search.memo, moves.move_rules.memo, models.joint_jacobians.memo,
                 lsq.measurement_jacobian.memo, lsq.measurement_slopes.memo, compensate.accuracy_jacobian.memo):
        memo.size = max(memo.size, KEEP)


#: Problems (and what is derived from them) each test worker keeps (:func:`_keep_more_built`).
KEEP = 48
_keep_more_built()

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "problems" / "paper_planar_2r.toml"
PROBLEM_FILES = sorted((ROOT / "problems").glob("*.toml"))


def read_raw(path: Path) -> dict:
    """A problem file as a fresh, editable dict."""
    with open(path, "rb") as fh:
        return copy.deepcopy(tomllib.load(fh))


def paper_raw() -> dict:
    """The paper's problem file as a fresh, editable dict."""
    return read_raw(PAPER)


def build(raw: dict, path: str = "test.toml"):
    """Read (check) and build a problem from a dict, as if it were the file ``path``."""
    return build_problem(parse_problem(raw, path))


@pytest.fixture(scope="session")
def paper():
    return load_problem(PAPER)


@pytest.fixture(scope="session")
def paper_solved(paper):
    """The paper's six designs (Table 4: test-pose, D, E at m = 1, 5), solved once for the suite
    with :data:`STARTS` seeded starts: ``{(criterion, m): Design}``."""
    from casadi_design.optimisation.solve import solve_design

    return {(c, m): solve_design(paper, c, m, starts=STARTS) for m in paper.m_values for c in paper.criteria}


#: Seeded starts of the runs of the paper's example shared by the tests (the problem file's 20
#: find the same optima, to Table 4's digits: tests/optimisation/test_design.py). Three: each of
#: Table 4's six designs has its optimum among its first two (E at m = 1 in the second); six
#: cost the suite's solve and sweep a third more IPOPT runs for the same designs.
STARTS = 3


@pytest.fixture(scope="session")
def paper_solve_out(tmp_path_factory):
    """``casadi-design solve`` of the paper's example (Table 4's designs, STARTS starts, one
    process, a 300-candidate bound pool), run once for the suite: its output folder."""
    from casadi_design.cli import main

    out = tmp_path_factory.mktemp("paper_solve")
    assert main(["solve", str(PAPER), "--out", str(out), "--starts", str(STARTS), "--jobs", "1",
                 "--bound-pool", "300", "--quiet"]) == 0
    return out


#: Session fixtures that take seconds: the tests that use one run on the same xdist worker
#: (``--dist loadgroup``, pyproject.toml), so that it is computed once, not once per worker.
SHARED = ("paper_solve_out", "paper_solved")


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    """Group the tests for xdist: those of a shared session fixture (:data:`SHARED`) by the
    fixture, those of a module-scoped fixture by their module; the others run anywhere. A
    module whose module-scoped fixture is used by tests of a shared fixture too (the browser of
    tests/reports/test_viewer.py) has its module's group join the shared one: the fixture is
    set up on one worker, not on both (a Chromium started and plotly.js compiled once, ~2 s)."""
    groups = {}
    for item in items:
        shared = [f for f in SHARED if f in item.fixturenames]
        # pytest keeps an item's fixture definitions in _fixtureinfo (no public accessor)
        module = any(d and d[-1].scope == "module" for d in item._fixtureinfo.name2fixturedefs.values())
        if shared or module:
            groups[item] = ("+".join(shared) or item.module.__name__, module)
    joined = {}
    for item, (group, module) in groups.items():
        if module and group != item.module.__name__:
            joined.setdefault(item.module.__name__, group)
    for item, (group, _) in groups.items():
        item.add_marker(pytest.mark.xdist_group(joined.get(group, group)))
