"""The checks of a whole plan (casadi_design.plan.rules): an old plan through the floor and
the table, an experiment inside the joint-limit margin."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from casadi_design.cell.cell import clearances
from casadi_design.plan.rules import plan_violations
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem, load_problem
from casadi_design.records.export import read_plan_csv
from tests.conftest import ROOT

UR10 = ROOT / "problems" / "ur10_drilling.toml"


@pytest.fixture(scope="module")
def ur10():
    return load_problem(UR10)


def test_old_plan_through_the_floor_is_rejected(ur10):
    """The D-optimal plan at m = 12 of the UR10 case without its cell (solved before the cell
    existed) drives links through the floor and the table: every rule set says so."""
    Q, F = read_plan_csv(ur10, ROOT / "tests" / "data" / "ur10_D_m12_without_cell.csv")
    bare = build_problem(dataclasses.replace(ur10.spec, cell=None,
                                             workspace=dataclasses.replace(ur10.workspace, joint_limit_margin_rad=0.0)))
    assert plan_violations(bare, Q, F) == []  # the old rules: frame origins above the floor only
    lines = plan_violations(ur10, Q, F)
    assert any("closer than 20 mm to the floor" in ln for ln in lines)
    assert any("closer than 20 mm to table" in ln for ln in lines)
    assert any("acceptance angle" in ln for ln in lines)
    near = clearances(ur10.cell, Q)
    assert sum(c.touching is not None for c in near) >= 6  # meshes cross the floor or the table
    hit = [i for i, c in enumerate(near) if c.touching is not None]
    for i in hit:  # every experiment the meshes reject, the rows reject too (capsules are conservative)
        assert any(ln.startswith(f"experiment {i + 1}: ") and "closer than" in ln for ln in lines)


def test_margin_keeps_plans_off_the_limits(ur10):
    Q, F = random_plan(ur10, 2, np.random.default_rng(8))
    Q[0, 2] = -np.pi + 0.01  # the elbow 10 mrad from its limit, inside the 50 mrad margin
    lines = plan_violations(ur10, Q, F)
    assert any(ln.startswith("experiment 1: elbow_joint") and "margin" in ln for ln in lines)
