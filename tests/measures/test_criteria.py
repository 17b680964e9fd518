"""The criteria registry: one entry per criterion, and I-optimality added as one entry.

I minimises the mean over the test poses of ``rho_j = sigma^2 tr(B0_j M^-1 B0_j^T)``; its
score is ``sqrt(mean_j rho_j)`` (m). Its derivatives are checked with the other criteria's in
tests/optimisation/test_reduced.py (finite differences and an independent symbolic formulation); here: its
optimum against a brute-force grid of the paper's hand-written B, its bound against the
test-pose certificate with equal weights and an SDP, Table-4-style rows on the paper's case,
and that every table, column and option is generated from the registry.
"""

import numpy as np
import pytest

from casadi_design.cli import build_parser
from casadi_design.execution.sweep import COLUMNS
from casadi_design.measures.criteria import BOUND_CRITERIA, CRITERIA
from casadi_design.measures.measures import score_plan
from casadi_design.optimisation.approximate import approximate_design
from casadi_design.optimisation.bound import bound
from casadi_design.optimisation.solve import solve_design
from casadi_design.reports.tables import MEASURE_ROWS
from tests.optimisation.test_bound import SMALL_POOL, planar_A

#: Relative slack of "a plan optimal for I is at least as good for I as any other plan".
OPTIMAL_RTOL = 1e-6
#: The solver's single-experiment I optimum against a 0.5 deg grid of (q2, load angle).
GRID_RTOL = 2e-4


@pytest.fixture(scope="module")
def paper_I(paper):
    return approximate_design(paper, "I", **SMALL_POOL)


def _mean_rho_m2(paper, B):
    """``mean_j rho_j = sigma^2 tr(Hbar M^-1)`` (m^2) of one-experiment plans B (..., 2, 2) by
    plain numpy, M^-1 by its adjugate (inf where M is singular)."""
    B0 = paper.B0
    H = np.einsum("jri,jrl->il", B0, B0) / len(B0)
    M = np.einsum("...ri,...rl->...il", B, B)
    det = M[..., 0, 0] * M[..., 1, 1] - M[..., 0, 1] * M[..., 1, 0]
    adj = H[0, 0] * M[..., 1, 1] - H[0, 1] * M[..., 1, 0] - H[1, 0] * M[..., 0, 1] + H[1, 1] * M[..., 0, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(det > 1e-12 * np.max(det), paper.sigma_m**2 * adj / det, np.inf)


def test_every_table_column_and_option_comes_from_the_registry():
    """A new entry appears in the scores, the evaluate table, the sweep columns, the command
    line's choices and (with a bound form) the bound criteria, without another edit."""
    rows = {r[0] for r in MEASURE_ROWS}
    for c in CRITERIA.values():
        assert c.row in rows and c.column in COLUMNS, c.name
    assert BOUND_CRITERIA == ("test-pose", "D", "A", "I")
    help_text = build_parser()._subparsers._group_actions[0].choices["solve"].format_help()
    assert "condition, I" in " ".join(help_text.split())
    sc = score_plan(np.eye(2)[None], np.eye(2)[None], 1.0)
    assert list(sc.values) == [c.score for c in CRITERIA.values()]


def test_I_optimum_of_one_experiment_equals_a_brute_force_grid(paper):
    """m = 1 on the paper's arm: the multi-start's I plan against every (q2, load angle) of a
    0.5 deg grid (q1 = 0: turning the arm and the load together leaves M unchanged) scored
    with the hand-written B. The grid's best is no better than the solver's, and close."""
    g = np.radians(np.arange(-180.0, 180.0, 0.5))
    q2, a = np.meshgrid(g, g, indexing="ij")
    B = planar_A(np.zeros_like(q2), q2, 100.0 * np.stack([np.cos(a), np.sin(a)], -1))
    grid_best = np.sqrt(np.min(_mean_rho_m2(paper, B)))
    d = solve_design(paper, "I", 1, starts=8)
    assert d.scores.value("I") <= grid_best * (1 + OPTIMAL_RTOL)
    assert d.scores.value("I") >= grid_best * (1 - GRID_RTOL)
    # the package's score is the numpy formula's
    assert d.scores.value("I") == pytest.approx(
        np.sqrt(_mean_rho_m2(paper, paper.model.B_stack(d.Q, d.F))[0]), rel=1e-12)


def test_I_bound_is_the_test_pose_certificate_with_equal_weights(paper, paper_I):
    """The I certificate is ``phi^2 / max_x d`` with ``H = sum_j mu_j B0_j^T B0_j`` at
    ``mu_j = 1/s``: recomputed here from the approximate design's W with max_x d over a grid of
    the hand-written B; and no plan of m experiments beats it."""
    B0 = paper.B0
    H = np.einsum("j,jri,jrl->il", np.full(len(B0), 1 / len(B0)), B0, B0)
    Wi = np.linalg.inv(paper_I.W)
    G, phi = Wi @ H @ Wi, np.trace(H @ Wi)
    g = np.linspace(-np.pi, np.pi, 121)
    q1, q2 = np.meshgrid(g, g, indexing="ij")
    grid_max = max(np.einsum("...ri,ij,...rj->...", A, G, A).max()
                   for A in (planar_A(q1, q2, 100.0 * np.array([np.cos(a), np.sin(a)])) for a in g))
    assert grid_max <= paper_I.d_max * (1 + 1e-9)
    assert phi**2 / paper_I.d_max == pytest.approx(paper_I.certified, rel=1e-9)
    assert paper_I.certified == pytest.approx(phi**2 / grid_max, rel=0.01)  # the grid comes close
    for m in (1, 5):
        b = bound(paper, m, paper_I)
        assert b.value == pytest.approx(np.sqrt(paper.sigma_m**2 * paper_I.certified / m), rel=1e-12)
        assert solve_design(paper, "I", m, starts=4).scores.value("I") >= b.value * (1 - 1e-9)


def test_I_relaxation_against_a_semidefinite_program(paper, paper_I):
    """On a grid pool, min tr(Hbar W^-1) by an SDP (cvxpy + Clarabel) is >= the hull's value
    >= the certified one, and the package's relaxation is as good as the SDP's."""
    cp = pytest.importorskip("cvxpy")
    g = np.linspace(-np.pi, np.pi, 25)[:-1]
    q1, q2, a = (v.ravel() for v in np.meshgrid(g, g, g, indexing="ij"))
    B = planar_A(q1, q2, 100.0 * np.stack([np.cos(a), np.sin(a)], -1))
    A = np.einsum("kri,krj->kij", B, B)
    B0 = paper.B0
    R = np.linalg.cholesky(np.einsum("jri,jrl->il", B0, B0) / len(B0)).T  # Hbar = R^T R
    w, W = cp.Variable(len(A), nonneg=True), cp.Variable((2, 2), symmetric=True)
    t = cp.matrix_frac(R.T, W)
    cp.Problem(cp.Minimize(t), [cp.sum(w) == 1, cp.vec(W, order="F") == A.reshape(len(A), 4).T @ w]
               ).solve(solver="CLARABEL")
    assert paper_I.certified <= t.value * (1 + 1e-9)
    assert paper_I.value <= t.value * (1 + 1e-6)


def test_table4_rows_with_I(paper, capsys):
    """Table-4-style rows on the paper's case (m = 1 and 5): the I plan has the smallest mean
    error of all plans, the test-pose plan the smallest max error; every mean is below its max;
    the I plan is printed with the others."""
    designs = {(c, m): solve_design(paper, c, m, starts=6) for m in (1, 5) for c in ("test-pose", "D", "I")}
    for m in (1, 5):
        I_best = designs["I", m].scores.value("I")
        tp_best = designs["test-pose", m].scores.max_rms_error_m
        for c in ("test-pose", "D", "I"):
            sc = designs[c, m].scores
            assert I_best <= sc.value("I") * (1 + OPTIMAL_RTOL), c
            assert tp_best <= sc.max_rms_error_m * (1 + OPTIMAL_RTOL), c
            assert sc.value("I") <= sc.max_rms_error_m
        # the I plan trades the worst pose for the average: strictly, on this path
        assert designs["I", m].scores.max_rms_error_m > tp_best * (1 + 1e-3)
    from casadi_design.reports.tables import format_table

    text = format_table(list(designs.values()))
    assert [ln.split()[0] for ln in text.splitlines()[3:]] == ["test-pose", "D", "I"]
    print(text)
