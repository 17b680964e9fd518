"""Compiled CasADi functions (casadi_design.robot.compiled): the same results to the bit as CasADi's
virtual machine, built once and found again on disk, and the virtual machine when no compiler
works. The rest of the suite runs with compiling off (conftest): these tests compile into a
temporary cache of their own."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from casadi_design.optimisation.reduced import experiment_functions
from casadi_design.plan.sampling import random_plan
from casadi_design.robot import compiled as cc
from casadi_design.robot.mapped import OneByOne, Stacked, evaluate
from tests.conftest import ROOT


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """Compiling on, into an empty cache of this test."""
    monkeypatch.setenv("CASADI_DESIGN_COMPILE", "1")
    monkeypatch.setenv("CASADI_DESIGN_CACHE", str(tmp_path))
    monkeypatch.setattr(cc, "_groups", {})
    if not cc.enabled():
        pytest.skip("no C compiler on this machine")
    return tmp_path


@pytest.fixture(scope="module")
def ur10():
    """The UR10 in its cell, built anew (not the process's cached problem, whose functions
    other tests built with compiling off)."""
    from casadi_design.problem.build import _build
    from casadi_design.problem_file.read import read_problem

    return _build(read_problem(ROOT / "problems" / "ur10_drilling.toml"))


@pytest.fixture(scope="module")
def Q_ur10(ur10):
    """40 random feasible UR10 configurations (rad), drawn before a test turns compiling on: the
    tests compile only the functions they check (each a gcc run of a second or more)."""
    rng = np.random.default_rng(3)
    return np.array([random_plan(ur10, 1, rng)[0][0] for _ in range(40)])


def _same(fn: ca.Function, other: ca.Function, *rows: np.ndarray) -> None:
    for a, b in zip(evaluate(fn, *rows, threads=1), evaluate(other, *rows, threads=1)):
        assert np.array_equal(a, b), fn.name()


def test_the_experiment_functions_give_the_same_bits(cache, ur10, Q_ur10):
    fns = experiment_functions(ur10)
    rng = np.random.default_rng(3)
    Z = np.concatenate([Q_ur10, rng.uniform(-1, 1, size=(40, fns.nv))], axis=1)
    for fn in (fns.values, fns.first):
        fast = cc.compiled(fn)
        assert fast.class_name() == "External"
        _same(fn, fast, Z)
    fast = cc.compiled(fns.second)
    W, lam, u = (rng.normal(size=(40, fns.second.numel_in(k))) for k in (1, 2, 3))
    _same(fns.second, fast, Z, W, lam, u)
    assert len(list(cache.glob("*.so"))) == 3


def test_every_rule_row_of_a_configuration_gives_the_same_bits(cache, ur10, Q_ur10):
    """The rows of one configuration (the sampling's judge and the move checks of a robot
    program, :func:`casadi_design.program.moves.move_rules`) at sampled configurations."""
    from casadi_design.program.moves import move_rules

    g, Q = ur10.rules.pose.g, Q_ur10[:20]
    fast = move_rules(ur10).g
    assert fast.class_name() == "External" and fast is cc.compiled(g)
    _same(g, fast, Q)
    at = move_rules(ur10).at  # one configuration at a time through a kept buffer, as a move's scan
    for q in Q[:3]:
        assert np.array_equal(np.asarray(g(q)), np.asarray(fast(q)))
        assert np.array_equal(np.asarray(g(q)).ravel(), at(q))


def test_one_by_one_gives_each_input_its_own_output():
    """:class:`OneByOne` on CasADi's virtual machine: the bits of ``fn(x)`` for each input in
    turn, a copy that the next call does not change; a function it cannot serve is refused."""
    x = ca.SX.sym("x", 3)
    fn = ca.Function("f", [x], [ca.vertcat(ca.sin(x[0]) * x[1], x[2] ** 2, ca.dot(x, x))])
    at, rng = OneByOne(fn), np.random.default_rng(5)
    X = rng.normal(size=(4, 3))
    out = [at(xi) for xi in X]
    for xi, y in zip(X, out):
        assert np.array_equal(np.asarray(fn(xi)).ravel(), y)
    with pytest.raises(ValueError, match="one dense input"):
        OneByOne(ca.Function("two", [x, ca.SX.sym("y")], [x]))


def test_stacked_gives_evaluate_s_bits_call_after_call(paper):
    """:class:`Stacked` keeps one buffer for the same rows with new values: each call the bits of
    :func:`evaluate` (and of the function case by case), earlier results untouched."""
    model, rng = paper.model, np.random.default_rng(6)
    m = 5
    Q, F, ref = rng.uniform(-3, 3, (m, 2)), rng.uniform(-100, 100, (m, 2)), rng.standard_normal((m, 12))
    stacked, kept = Stacked(model.measurement, m), []
    for _ in range(3):
        X = np.tile(rng.uniform(-1e-4, 1e-4, model.L), (m, 1))
        got = stacked(Q, F, X, ref)
        want = evaluate(model.measurement, Q, F, X, ref, threads=1)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
        one = np.asarray(model.measurement(Q[2], F[2], X[2], ref[2])[0]).ravel()
        np.testing.assert_array_equal(got[0][2, :, 0], one)
        kept.append((got[0].copy(), got[0]))
    assert all(np.array_equal(a, b) for a, b in kept)  # a later call did not overwrite an earlier result
    with pytest.raises(ValueError, match="at most 64"):
        Stacked(model.measurement, 100)


def test_some_capsule_rows_give_the_same_bits(cache, ur10, Q_ur10):
    """The value, slope and curvature of a few capsule rows (of the switches' cases), compiled,
    at the points of sampled configurations (the whole switches: the slow test below)."""
    rows, Q = ur10.rules.pose.collision, Q_ur10[:8]
    rng = np.random.default_rng(4)
    w = np.concatenate([evaluate(rows.points, Q, threads=1)[0][:, :, 0], np.zeros((len(Q), 1))], axis=1)
    for r in rng.choice(len(rows.cases), size=6, replace=False):
        fast = cc.compiled_group(rows.cases[r], min_instructions=0)
        assert {f.class_name() for f in fast} == {"External"}
        for plain, compiled in zip(rows.cases[r], fast):
            _same(plain, compiled, w[:, rows.inputs[r]])


@pytest.mark.slow
def test_the_capsule_rows_give_the_same_bits(cache, ur10):
    """Every row's value, slope and curvature through the compiled switches, at the points of
    sampled configurations, against the virtual machine's switch of the same cases."""
    rows = ur10.rules.pose.collision
    rng = np.random.default_rng(5)
    Q = np.array([random_plan(ur10, 1, rng)[0][0] for _ in range(8)])
    w = np.concatenate([evaluate(rows.points, Q, threads=1)[0][:, :, 0], np.zeros((len(Q), 1))], axis=1)
    R = len(rows.inputs)
    index = np.repeat(np.arange(R), len(Q)).astype(float)[:, None]
    args = w[np.tile(np.arange(len(Q)), R)[:, None], rows.inputs[index[:, 0].astype(int)]]
    for k, name in enumerate(("value", "slope", "curvature")):
        plain = ca.Function.conditional(name, [c[k] for c in rows.cases], rows.cases[0][k])
        fast = getattr(rows, name)
        assert fast.class_name() == "Switch"
        built = cc._groups[(cc.MIN_INSTRUCTIONS, *(id(c[k]) for c in rows.cases))][1]  # what the switch was made of
        assert {f.class_name() for f in built} == {"External"}
        _same(plain, fast, index, args)
    assert len(list(cache.glob("*.so"))) >= 3


@pytest.mark.slow
def test_a_start_in_the_cell_is_the_same_compiled_or_not(cache, monkeypatch):
    """One UR10 start in its cell (rows joining as they can bind): the same IPOPT iterations, plan
    and value with the compiled functions as in the virtual machine."""
    from casadi_design.optimisation.solve import make_design_solver, solve_start, start_rng
    from casadi_design.problem.build import _build
    from casadi_design.problem_file.read import read_problem

    spec = read_problem(ROOT / "problems" / "ur10_drilling.toml")

    def run():
        problem = _build(spec)  # built anew: its own CasADi functions
        Q0, F0 = random_plan(problem, 9, start_rng(problem.solver.seed, "test-pose", 9))
        return solve_start(problem, make_design_solver(problem, "test-pose", 9), Q0, F0)

    monkeypatch.setenv("CASADI_DESIGN_COMPILE", "0")
    plain = run()
    monkeypatch.setenv("CASADI_DESIGN_COMPILE", "1")
    fast = run()
    assert list(cache.glob("*.so"))
    assert fast[0] == plain[0] and fast[0].iterations > 10
    assert np.array_equal(fast[1], plain[1]) and np.array_equal(fast[2], plain[2])


def test_a_library_is_built_once_and_found_again(cache, monkeypatch):
    x = ca.SX.sym("x", 4)
    fn = ca.Function("f", [x], [ca.sin(x) * ca.exp(x[0] * x[1]) + ca.sqrt(ca.sumsqr(x) + 1)])
    first = cc.compiled_group([fn], min_instructions=0)[0]
    assert first.class_name() == "External" and len(list(cache.glob("*.so"))) == 1

    def no_compiler(*args, **kwargs):
        raise AssertionError("compiled again")

    monkeypatch.setattr(cc, "_groups", {})  # another process: only the disk remembers
    monkeypatch.setattr(cc, "_build", no_compiler)
    monkeypatch.setattr(cc, "_source", no_compiler)  # found by its serialization, no code written
    again = cc.compiled_group([fn], min_instructions=0)[0]
    X = np.random.default_rng(0).normal(size=(16, 4))
    _same(fn, again, X)
    _same(first, again, X)
    # the same name and shape, one constant changed: another library, not the first one's
    other = ca.Function("f", [x], [ca.sin(x) * ca.exp(x[0] * x[1]) + ca.sqrt(ca.sumsqr(x) + 2)])
    with pytest.raises(AssertionError, match="compiled again"):
        cc.compiled_group([other], min_instructions=0)


def test_small_functions_and_switched_off_compiling_stay_as_they_are(cache, monkeypatch):
    x = ca.SX.sym("x", 2)
    small = ca.Function("small", [x], [x[0] * x[1]])
    assert cc.compiled(small) is small
    big = ca.Function("big", [x], [ca.sin(x) * ca.cos(x[0])])
    monkeypatch.setenv("CASADI_DESIGN_COMPILE", "0")
    assert cc.compiled_group([big], min_instructions=0)[0] is big
    assert not list(cache.glob("*.so"))


def test_a_failing_compiler_leaves_the_function_and_no_library(cache, monkeypatch, capsys):
    monkeypatch.setenv("CC", "false")  # a compiler that fails on everything
    x = ca.SX.sym("x", 2)
    fn = ca.Function("g", [x], [ca.sin(x) * ca.cos(x[0])])
    assert cc.compiled_group([fn], min_instructions=0)[0] is fn
    err = capsys.readouterr().err
    assert "could not compile" in err and "virtual machine" in err and err.count("\n") == 1
    assert not list(cache.glob("*.so")) and not [p for p in cache.iterdir() if p.is_dir()]
