"""Random feasible plans (casadi_design.plan.sampling): every rule kept and the real meshes
clear, drawn as the one-then-growing-batches rule draws them."""

from __future__ import annotations

import numpy as np
import pytest

from casadi_design.cell.cell import clearances
from casadi_design.plan.rules import plan_violations
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import load_problem
from tests.conftest import ROOT

UR10 = ROOT / "problems" / "ur10_drilling.toml"


@pytest.fixture(scope="module")
def ur10():
    return load_problem(UR10)


def test_random_plans_satisfy_every_row_and_the_mesh_check(ur10):
    Q, F = random_plan(ur10, 3, np.random.default_rng(4))
    rules = ur10.rules.pose
    assert all(np.all(rules.violation(q) == 0) for q in Q)
    # capsules are conservative: rows satisfied means the meshes keep the clearance on every
    # pair the rows constrain; the forearm and the second wrist link, some of whose capsules
    # always overlap, are 18 to 20 mm apart by construction: only checked for touching
    assert ur10.cell.check.partial.any()
    for c in clearances(ur10.cell, Q):
        assert c.distance_m >= ur10.cell.spec.clearance_m - 1e-9 and c.touching is None
    assert plan_violations(ur10, Q, F) == []


@pytest.mark.parametrize("case", ["ur10_drilling", "abb_irb6640_machining", "paper_planar_2r"])
def test_random_plans_follow_the_one_then_growing_batches_rule(case):
    """``random_plan``'s configurations are judged in blocks ahead of the rule, but they are
    what the rule gives drawn batch by batch (one configuration, then 16, 32, ... up to 1024;
    the first feasible one of the first batch that has one), and the generator is left there
    (the loads, drawn after, come from the same stream)."""
    from casadi_design.plan import sampling

    problem = load_problem(ROOT / "problems" / f"{case}.toml")
    rules, limits = problem.rules.pose, problem.rules.limits
    mine, rule = np.random.default_rng(8), np.random.default_rng(8)
    Q = sampling._configurations(problem, 12, mine)
    for q in Q:
        batch = 1
        while True:
            candidates = limits.sample(rule, batch)
            ok = np.flatnonzero(rules.feasible(candidates))
            if ok.size:
                np.testing.assert_array_equal(q, candidates[ok[0]])
                break
            batch = sampling.SAMPLING_BATCH if batch == 1 else min(2 * batch, sampling.SAMPLING_BATCH_MAX)
    assert mine.uniform() == rule.uniform()  # the same place in the stream
