"""The reduced-space NLP: values, gradient, Jacobian and Hessian of the Lagrangian against finite
differences and against the symbolic formulation (one CasADi graph of M with CasADi's exact
derivatives, tests/symbolic_oracle.py), on the paper's case, its load and constraint variants
and the UR10 drilling case; the same IPOPT iterates as the symbolic NLP; E and condition: the
surrogates' bounds and the exact optimum of the lifted semidefinite formulation."""

import dataclasses
import gc

import casadi as ca
import numpy as np
import pytest

from casadi_design.measures.criteria import CRITERIA as REGISTRY
from casadi_design.measures.measures import score_plan
from casadi_design.measures.objectives import log_power_mean
from casadi_design.optimisation.ipopt import QUIET, ipopt_call
from casadi_design.optimisation.nlp import build_nlp
from casadi_design.optimisation.solve import make_solver, solve_design
from casadi_design.plan.design import CONVERGED
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem, load_problem
from casadi_design.problem_file.read import read_problem
from tests.conftest import ROOT, build, paper_raw
from tests.symbolic_oracle import symbolic_nlp

CRITERIA = ("test-pose", "D", "A", "T", "I")
#: E and condition at the highest power of their surrogates (the steepest), and at the lowest
#: (slow: the same formulas).
SPECTRAL = [(c, REGISTRY[c].powers[-1]) for c in ("E", "condition")] + [
    pytest.param((c, REGISTRY[c].powers[0]), marks=pytest.mark.slow) for c in ("E", "condition")]
#: Agreement with the symbolic formulation (relative to the largest entry): rounding only.
SYMBOLIC_RTOL = 1e-9
#: Agreement with central finite differences (relative to the largest entry).
FD_RTOL = 2e-6


def _variant(**edits):
    raw = paper_raw()
    for key, value in edits.items():
        table, field = key.split("__")
        raw["experiments"].setdefault(table, {})[field] = value
    return build(raw)


def _cases():
    """name -> (problem factory, m)"""
    return {
        "paper": (lambda: load_problem(ROOT / "problems" / "paper_planar_2r.toml"), 3),
        # |F| <= F_max, pairwise joint distance and a half-space: every kind of rule row
        "paper-bound-distance": (lambda: _variant(force__mode="bound", workspace__min_joint_distance_rad=0.3,
                                                  workspace__half_spaces=[{"normal": [0.0, 1.0, 0.0],
                                                                           "offset_m": -0.5}]), 3),
        "paper-direction": (lambda: _variant(force__direction=[0.6, 0.8], force__mode="direction"), 3),
        "paper-fixed": (lambda: _fixed_load_paper(), 3),
        "geometric": (lambda: load_problem(ROOT / "problems" / "planar_2r_geometric.toml"), 3),
        # without its cell: the collision rows are only C1 where their closest points change
        # branch, so finite differences of their Hessian are checked in tests/cell/test_cell.py
        "ur10": (lambda: build_problem(dataclasses.replace(read_problem(ROOT / "problems" / "ur10_drilling.toml"),
                                                           cell=None)), 9),
    }


def _fixed_load_paper():
    raw = paper_raw()
    raw["experiments"]["force"] = {"mode": "fixed", "vector_N": [30.0, -80.0]}
    return build(raw)


_PROBLEMS: dict = {}


def _problem(name):
    if name not in _PROBLEMS:
        _PROBLEMS[name] = _cases()[name][0]()
    return _PROBLEMS[name]


def _point(problem, nlp, seed):
    """A random feasible plan, t above its max rho_j, and random multipliers."""
    rng = np.random.default_rng(seed)
    Q, F = random_plan(problem, nlp.m, rng)
    x = np.asarray(nlp.start(Q, F), dtype=float).ravel()
    lam_f = rng.uniform(0.5, 2.0)
    lam_g = rng.normal(size=nlp.lbg.size)
    return x, lam_f, lam_g


def _first_order(nlp, x):
    """f, g, grad f and dense dg/dx of the reduced NLP, through its CasADi functions."""
    f, g = (np.asarray(v, dtype=float).ravel() for v in nlp.oracle(x, []))
    grad = np.asarray(nlp.options["grad_f"](x, [])[1], dtype=float).ravel()
    J = np.asarray(ca.densify(nlp.options["jac_g"](x, [])[1]), dtype=float).reshape(g.size, x.size)
    return f[0], g, grad, J


def _reduced(nlp, x, lam_f, lam_g):
    """:func:`_first_order` and the full Hessian of the Lagrangian."""
    H = np.asarray(ca.densify(nlp.options["hess_lag"](x, [], lam_f, lam_g)), dtype=float)
    assert np.all(np.tril(H, -1) == 0), "IPOPT takes the upper triangle"
    return (*_first_order(nlp, x), np.triu(H) + np.triu(H, 1).T)


def _close(a, b, rtol):
    scale = max(np.max(np.abs(b), initial=0.0), 1e-300)
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("case", ["paper", "paper-bound-distance", "paper-direction", "paper-fixed", "geometric"])
def test_derivatives_equal_the_symbolic_formulation(case, criterion):
    problem, m = _problem(case), _cases()[case][1]
    nlp, sym = build_nlp(problem, criterion, m), symbolic_nlp(problem, criterion, m)
    for bound in ("lbx", "ubx", "lbg", "ubg"):
        np.testing.assert_array_equal(getattr(nlp, bound), getattr(sym, bound))
    assert nlp.scale == sym.scale
    x, lam_f, lam_g = _point(problem, nlp, seed=1)
    np.testing.assert_allclose(np.asarray(sym.start(*nlp.plan(x))).ravel(), x, rtol=1e-12)
    xs = ca.SX.sym("x", x.size)
    fs, gs = sym.oracle(xs, [])
    lagrangian = lam_f * fs + ca.dot(ca.DM(lam_g), gs)
    oracle = ca.Function("oracle", [xs], [fs, gs, ca.gradient(fs, xs), ca.densify(ca.jacobian(gs, xs)),
                                          ca.densify(ca.hessian(lagrangian, xs)[0])])
    expected = [np.asarray(v, dtype=float) for v in oracle(x)]
    for got, want in zip(_reduced(nlp, x, lam_f, lam_g), expected):
        _close(np.reshape(got, want.shape), want, SYMBOLIC_RTOL)


@pytest.mark.parametrize("criterion", [(c, 0.0) for c in CRITERIA] + SPECTRAL)
@pytest.mark.parametrize("case", ["paper-bound-distance", "paper-direction", "ur10"])
def test_derivatives_equal_finite_differences(case, criterion):
    problem, m = _problem(case), _cases()[case][1]
    _check_finite_differences(build_nlp(problem, *criterion[:1], m, power=criterion[1]), problem, seed=2)


def _check_finite_differences(nlp, problem, seed):
    """The gradient, Jacobian and Hessian of the Lagrangian of ``nlp`` at a random plan
    against central differences of its values and first derivatives."""
    x, lam_f, lam_g = _point(problem, nlp, seed=seed)
    f, g, grad, J, H = _reduced(nlp, x, lam_f, lam_g)
    step = 1e-6 * np.maximum(1.0, np.abs(x))
    fd_grad, fd_J, fd_H = np.empty_like(grad), np.empty_like(J), np.empty_like(H)
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = step[k]
        plus, minus = _first_order(nlp, x + e), _first_order(nlp, x - e)
        fd_grad[k] = (plus[0] - minus[0]) / (2 * step[k])
        fd_J[:, k] = (plus[1] - minus[1]) / (2 * step[k])
        grad_lag = [lam_f * r[2] + r[3].T @ lam_g for r in (plus, minus)]
        fd_H[:, k] = (grad_lag[0] - grad_lag[1]) / (2 * step[k])
    _close(grad, fd_grad, FD_RTOL)
    _close(J, fd_J, FD_RTOL)
    _close(H, fd_H, FD_RTOL)


def _information(problem, Q, F):
    """sum_k B_k^T B_k of the experiments Q (k, n), F (k, nF), with numpy."""
    B = problem.model.B_stack(Q, F)
    return np.einsum("kri,krj->ij", B, B)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("case", ["paper-bound-distance", "ur10"])
def test_weighted_derivatives_equal_finite_differences(case, criterion):
    """The support of an approximate design (the bound's moves): M = scale (sum_i w_i B_i^T B_i
    + M0) with random weights w and the information M0 of two other experiments."""
    problem, m = _problem(case), _cases()[case][1]
    rng = np.random.default_rng(6)
    M0 = _information(problem, *random_plan(problem, 2, rng))
    nlp = build_nlp(problem, criterion, m, weights=rng.uniform(0.2, 3.0, m), fixed=M0)
    assert nlp.lbg.size == build_nlp(problem, criterion, m).lbg.size - (
        m * (m - 1) // 2 if problem.workspace.min_joint_distance_rad > 0 else 0), "no joint-distance rows"
    _check_finite_differences(nlp, problem, seed=7)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_integer_weights_and_fixed_information_are_experiments(criterion):
    """Weights (2, 1) on (z1, z2) with the information of z3 fixed are the plain NLP of the
    plan (z1, z1, z2, z3): the same objective and rho_j, and the gradient of z1 is the sum of
    its two copies' gradients."""
    problem = _problem("paper-direction")
    Q, F = random_plan(problem, 3, np.random.default_rng(8))
    weighted = build_nlp(problem, criterion, 2, weights=np.array([2.0, 1.0]),
                         fixed=_information(problem, Q[2:], F[2:]))
    plain = build_nlp(problem, criterion, 4)
    xw, xp = weighted.start(Q[:2], F[:2]), plain.start(Q[[0, 0, 1, 2]], F[[0, 0, 1, 2]])
    np.testing.assert_allclose(weighted.information(xw), plain.information(xp), rtol=1e-12)
    n, p = problem.robot.n, (xp.size - xw.size) // 2
    t = xw.size - 2 * p
    np.testing.assert_allclose(xw[2 * p:], xp[4 * p:], rtol=1e-12)  # t: the same max_j rho_j

    def columns(m, i):  # x = (Q, V, t): experiment i's joints and load variables
        return np.r_[i * n:(i + 1) * n, m * n + i * (p - n):m * n + (i + 1) * (p - n)]

    fw, gw, gradw, Jw = _first_order(weighted, xw)
    fp, gp, gradp, Jp = _first_order(plain, xp)
    pairs = 6 if problem.workspace.min_joint_distance_rad > 0 else 0
    rows = gw.size - (gp.size - gw.size - pairs)  # the epigraph rows rho_j - t (before the rules)
    np.testing.assert_allclose(fw, fp, rtol=1e-12)
    np.testing.assert_allclose(gw[:rows], gp[:rows], rtol=1e-12, atol=1e-12 * np.abs(gp[:rows]).max(initial=0.0))
    for got, want in ((gradw[None], gradp[None]), (Jw[:rows], Jp[:rows])):
        for iw, ip in ((0, (0, 1)), (1, (2,))):
            expected = sum(want[:, columns(4, k)] for k in ip)
            _close(got[:, columns(2, iw)], expected, 1e-10)
        np.testing.assert_allclose(got[:, 2 * p:], want[:, 4 * p:], rtol=1e-10, atol=1e-12)
    assert t in (0, 1)
@pytest.mark.parametrize("criterion", CRITERIA)
def test_ur10_derivatives_equal_the_symbolic_formulation(criterion):
    """The UR10 (L = 27, m = 9): f, g, gradient and Jacobian from CasADi's graph, the Hessian
    through CasADi's Hessian-vector products in random directions (the full symbolic Hessian takes
    ~15 s and 1.3 GB to build; see the slow test below)."""
    problem = _problem("ur10")
    nlp, sym = build_nlp(problem, criterion, 9), symbolic_nlp(problem, criterion, 9)
    x, lam_f, lam_g = _point(problem, nlp, seed=3)
    f, g, grad, J, H = _reduced(nlp, x, lam_f, lam_g)
    xs, v = ca.SX.sym("x", x.size), ca.SX.sym("v", x.size)
    fs, gs = sym.oracle(xs, [])
    grad_lag = ca.gradient(lam_f * fs + ca.dot(ca.DM(lam_g), gs), xs)
    oracle = ca.Function("oracle", [xs, v], [fs, gs, ca.gradient(fs, xs), ca.densify(ca.jacobian(gs, xs)),
                                             ca.jtimes(grad_lag, xs, v)])
    V = np.random.default_rng(4).normal(size=(x.size, 3))
    for k in range(V.shape[1]):
        want = [np.asarray(w, dtype=float) for w in oracle(x, V[:, k])]
        for got, expected in zip((f, g, grad, J, H @ V[:, k]), want):
            _close(np.reshape(got, expected.shape), expected, SYMBOLIC_RTOL)


@pytest.mark.slow
@pytest.mark.parametrize("criterion", CRITERIA)
def test_ur10_full_hessian_equals_the_symbolic_one(criterion):
    problem = _problem("ur10")
    nlp, sym = build_nlp(problem, criterion, 9), symbolic_nlp(problem, criterion, 9)
    x, lam_f, lam_g = _point(problem, nlp, seed=5)
    xs = ca.SX.sym("x", x.size)
    fs, gs = sym.oracle(xs, [])
    H = ca.Function("H", [xs], [ca.densify(ca.hessian(lam_f * fs + ca.dot(ca.DM(lam_g), gs), xs)[0])])
    _close(_reduced(nlp, x, lam_f, lam_g)[4], np.asarray(H(x), dtype=float), SYMBOLIC_RTOL)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_ipopt_iterates_equal_the_symbolic_formulations(paper, criterion):
    """Same x0, bounds and rows: IPOPT takes the same steps on both formulations, until
    rounding decides. D, A and T agree to rounding for at least 10 iterations (D for 33 of 40).
    The test-pose KKT systems (61 rows, many nearly active) amplify rounding: moving x0 by one
    ulp changes the symbolic formulation's own iterates by 1e-12 after one step and its
    iteration count (44 instead of 38); the two formulations agree to 1e-8 for 3 iterations.
    Then the same optimum value for test-pose, D and A (the optimal test-pose plans are a
    continuum); T, from a near-stationary point, goes to different stationary points after a
    near-tie in the line search (iteration 14)."""
    nlp, sym = build_nlp(paper, criterion, 5), symbolic_nlp(paper, criterion, 5)
    rng = np.random.default_rng(6)
    for _ in range(3):
        x0 = nlp.start(*random_plan(paper, 5, rng))
        runs = []
        for formulation in (nlp, sym):
            solver = formulation.solver("s", {"ipopt.print_level": 0, "print_time": False, "error_on_fail": False,
                                              "ipopt.tol": paper.solver.tol,
                                              "ipopt.max_iter": 10 if criterion == "T" else 3000})
            with ipopt_call():
                sol = solver(x0=x0, lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg)
            runs.append((solver.stats()["return_status"], np.array(solver.stats()["iterations"]["obj"]),
                         float(sol["f"])))
        (status, obj, f), (status_s, obj_s, f_s) = runs
        agree, rtol = (3, 1e-8) if criterion == "test-pose" else (10, 1e-12)
        np.testing.assert_allclose(obj[:agree], obj_s[:agree], rtol=rtol)
        if criterion != "T":
            assert status == status_s == "Solve_Succeeded"
            assert f == pytest.approx(f_s, rel=1e-9)


def test_log_power_means_bound_the_extreme_eigenvalues():
    """``log lambda_min <= l_{-r} <= log lambda_min + log(L)/r`` and ``log lambda_max - log(L)/r <=
    l_r <= log lambda_max``, with equality of the upper (lower) bound when all eigenvalues are
    equal; and its value equals the direct formula where that does not overflow."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        lam = np.exp(rng.uniform(-5, 5, size=rng.integers(2, 36)))
        for r in (1.0, 16.0, 256.0, 4096.0):
            lo, hi = log_power_mean(lam, -r)[0], log_power_mean(lam, r)[0]
            L = len(lam)
            assert np.log(lam.min()) - 1e-12 <= lo <= np.log(lam.min()) + np.log(L) / r + 1e-12
            assert np.log(lam.max()) - np.log(L) / r - 1e-12 <= hi <= np.log(lam.max()) + 1e-12
            if r <= 16:
                assert lo == pytest.approx(np.log(np.mean(lam ** -r)) / -r, rel=1e-12, abs=1e-12)
    assert log_power_mean(np.full(5, 2.0), -64.0)[0] == pytest.approx(np.log(2.0), rel=1e-14)


@pytest.mark.parametrize("criterion, case, m", [
    ("E", "paper", 5), ("condition", "paper-direction", 3),
    *[pytest.param(c, case, m, marks=pytest.mark.slow) for c, case, m in
      (("E", "paper-direction", 3), ("E", "geometric", 3), ("condition", "paper", 5),
       ("condition", "geometric", 3))]])
def test_surrogates_reach_the_exact_optimum(criterion, case, m):
    """The continuation in r reaches the optimum of the exact semidefinite formulation (the
    lifted Cholesky-factor NLP of the oracle) from the same 6 starts, within what the last
    power r guarantees: a surrogate optimum has ``lambda_min >= L^(-1/r)`` times the optimal
    one (``s_L`` within ``L^(-1/2r)``), and ``s_1/s_L`` within ``L^(1/r)``."""
    problem = _problem(case)
    B0 = problem.B0
    design = solve_design(problem, criterion, m, starts=6)
    sym = symbolic_nlp(problem, criterion, m, B0)
    solver = sym.solver("exact", {**QUIET, "ipopt.tol": 1e-10, "ipopt.max_iter": 3000})
    best = None
    rng = np.random.default_rng([problem.solver.seed, m, REGISTRY[criterion].seed_id])
    for _ in range(6):
        Q0, F0 = random_plan(problem, m, rng)
        with ipopt_call():
            sol = solver(x0=sym.start(Q0, F0), lbx=sym.lbx, ubx=sym.ubx, lbg=sym.lbg, ubg=sym.ubg)
        if solver.stats()["return_status"] not in CONVERGED:
            continue
        Q, F = (np.asarray(v, dtype=float) for v in sym.plan(sol["x"]))
        value = score_plan(problem.model.B_stack(Q, F), B0, problem.sigma_m).value(criterion)
        if best is None or REGISTRY[criterion].better(value, best):
            best = value
    assert best is not None
    L, r = problem.model.L, REGISTRY[criterion].powers[-1]
    if criterion == "E":
        assert design.scores.value("E") >= best * L ** (-0.5 / r) * (1 - 1e-9)
    else:
        assert design.scores.value("condition") <= best * L ** (1 / r) * (1 + 1e-9)


def test_solver_keeps_its_callbacks_alive(paper):
    """The Python callbacks live as long as the solver, not only as long as the NLP object."""
    nlp = build_nlp(paper, "test-pose", 2)
    args = dict(x0=nlp.start(*random_plan(paper, 2, np.random.default_rng(0))),
                lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg)
    solver = make_solver(paper, nlp)
    del nlp
    gc.collect()
    solver(**args)
    assert solver.stats()["return_status"] in CONVERGED


def test_singular_information_is_an_invalid_number_not_an_exception(paper):
    """At a plan that does not identify X (M singular) the values are NaN: IPOPT shortens its
    step there, and a start from such a plan ends with IPOPT's status, not a Python error."""
    nlp = build_nlp(paper, "test-pose", 1)
    x = nlp.start(np.zeros((1, 2)), np.array([[100.0, 0.0]]))
    f, g = (np.asarray(v).ravel() for v in nlp.oracle(x, []))
    assert np.isnan(g[0]) and np.isnan(x[-1])
