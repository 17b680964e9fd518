"""Points fixed in an artefact (calibration/artefact.py): the turns a placement's points tell,
the placement's columns against finite differences, the first placement, the projection of
the placements (the Schur complement, an independent numpy computation), the rows with the
placements' poses beside X (the test-pose measure of the Schur complement), the registered
test poses and the base set of a Panda's recordings (the tracker's base set less a rigid motion)."""

import numpy as np
import pytest
from pinocchio import exp3 as rotation

from casadi_design.calibration.artefact import (
    artefact,
    artefact_rows,
    identifiable,
    placement_columns,
    placement_projected,
    registered,
    rigid_columns,
)
from casadi_design.problem.build import load_problem
from tests.conftest import ROOT

PANDA = ROOT / "problems" / "panda_ball_socket.toml"


@pytest.mark.parametrize("points, r", [([[0, 0, 0]], 0), ([[0, 0, 0], [0.05, 0, 0]], 2),
                                       ([[0, 0, 0], [0.05, 0, 0], [0.1, 0, 0]], 2),
                                       ([[0, 0, 0], [0.05, 0, 0], [0, 0.04, 0.01]], 3)])
def test_a_placement_tells_the_turns_its_points_tell(points, r):
    A = artefact(np.array(points, float))
    assert A.turns.shape == (3, r) and A.nP == 3 + r
    if r == 2:  # across the line: the turn about it moves no point
        u = np.array(points[1], float) / np.linalg.norm(points[1])
        assert np.allclose(u @ A.turns, 0.0, atol=1e-12)


def test_the_placement_columns_are_the_derivative_of_the_points():
    rng = np.random.default_rng(1)
    A = artefact(np.array([[0, 0, 0], [0.05, 0, 0], [0.01, 0.03, 0.02]]))
    R, t = rotation(rng.normal(size=3)), rng.normal(size=3)
    k = np.array([0, 1, 2, 1])
    G = A.columns(R, k)
    h = 1e-7
    for c in range(A.nP):
        dP = np.zeros(A.nP)
        dP[c] = h
        (Rp, tp), (Rm, tm) = A.moved(R, t, dP), A.moved(R, t, -dP)
        fd = ((tp + A.points_m[k] @ Rp.T) - (tm + A.points_m[k] @ Rm.T)) / (2 * h)
        assert np.allclose(G[:, :, c], fd, atol=1e-8)


@pytest.mark.parametrize("points", [[[0, 0, 0], [0.05, 0, 0]], [[0, 0, 0], [0.05, 0, 0], [0.01, 0.04, 0]]])
def test_the_first_placement_puts_the_points_at_their_means(points):
    A = artefact(np.array(points, float))
    R, t = rotation(np.array([0.3, -1.1, 0.7])), np.array([0.4, -0.2, 0.1])
    centres = {k: t + R @ a for k, a in enumerate(A.points_m)}
    R0, t0 = A.place(centres)
    assert np.allclose(t0 + A.points_m @ R0.T, np.array(list(centres.values())), atol=1e-12)


def test_projected_rows_give_the_schur_complement_and_the_rows_beside_x_its_test_pose_measure():
    rng = np.random.default_rng(2)
    A = artefact(np.array([[0, 0, 0], [0.05, 0, 0]]))
    N, L, P = 24, 5, 2
    J = rng.normal(size=(N, 3, L))
    k, g = rng.integers(0, 2, N), np.repeat([0, 1], N // 2)
    R = np.stack([rotation(rng.normal(size=3)) for _ in range(P)])
    # the Schur complement of the placements' block of the normal matrix, by numpy
    full = artefact_rows(A, J, R, k, g).reshape(-1, L + P * A.nP)
    Mf = full.T @ full
    S = Mf[:L, :L] - Mf[:L, L:] @ np.linalg.solve(Mf[L:, L:], Mf[L:, :L])
    Jp = placement_projected(J, placement_columns(A, R, k, g)).reshape(-1, L)
    assert np.allclose(Jp.T @ Jp, S, rtol=1e-10, atol=1e-10)
    B0 = rng.normal(size=(4, 3, L))
    B0f = np.concatenate([B0, np.zeros((4, 3, P * A.nP))], axis=2)
    rho_aug = [np.trace(b @ np.linalg.solve(Mf, b.T)) for b in B0f]
    rho = [np.trace(b @ np.linalg.solve(S, b.T)) for b in B0]
    assert np.allclose(rho_aug, rho, rtol=1e-9)


def test_registered_test_poses_see_no_rigid_motion_and_keep_the_rest():
    rng = np.random.default_rng(3)
    p0 = rng.normal(size=(6, 3))
    T = rigid_columns(p0)  # a rigid motion of the test points as 6 parameters
    B0 = np.concatenate([T, rng.normal(size=(6, 3, 2))], axis=2)
    Br = registered(B0, p0)
    assert np.allclose(Br[:, :, :6], 0.0, atol=1e-12)
    assert np.linalg.matrix_rank(Br[:, :, 6:].reshape(-1, 2)) == 2
    assert np.allclose(registered(Br, p0), Br, atol=1e-12)  # a projection


@pytest.fixture(scope="module")
def recorded():
    """The Panda problem's model and 8 configurations per socket of two placements: the rows
    ``B`` (N, 3, L), the ball's points ``p``, the artefact, each placement's first turn ``R``,
    the placements' columns ``G``, the points ``k`` and placements ``g``."""
    from tests.artefact_data import recordings

    problem = load_problem(PANDA)
    _, Q, k, g = recordings(problem, 0, 8, 5e-5)
    model = problem.model
    B = model.B_stack(Q, np.zeros((len(Q), 0)))
    p = np.stack([np.asarray(model.points(q)).reshape(3) for q in Q])
    A = problem.artefact
    R = np.array([A.place({j: p[(g == h) & (k == j)].mean(axis=0) for j in (0, 1)})[0] for h in (0, 1)])
    return model, B, p, A, R, placement_columns(A, R, k, g), k, g


def test_a_pandas_recordings_tell_its_tracker_base_set_less_a_rigid_motion(recorded):
    """The tracker's identifiable base set of the Panda (31: 4 of them base.*, and joint 1's two
    tilts) holds 6 that a rigid motion of the whole robot makes: the artefact's recordings tell
    the other 25, whatever the placements."""
    model, B, p, _, _, G, _, _ = recorded
    assert model.L == 31
    kept, live = identifiable(B, p, G)
    left = {n for n, keep in zip(model.parameter_names, kept) if not keep}
    assert kept.sum() == 25
    assert left == {"base.tx", "base.ty", "base.tz", "base.rz", "panda_joint1.rx", "panda_joint1.ry"}


def test_tied_parameters_are_kept_in_their_order_whatever_the_rounding(recorded):
    """Two parameters that move the recordings alike (a copy of a column, as a joint's ty and rz
    can be for one placement of an iiwa) are a tie: the one listed first is kept, whichever of
    the two carries a rounding difference (LAPACK's pivoting left it to the BLAS's kernel, and
    the other choice stalled the fit)."""
    model, B, p, _, _, G, _, _ = recorded
    j = model.parameter_names.index("panda_joint3.tx")
    for noisy in (0, 1):
        twin = np.concatenate([B[:, :, :j + 1], B[:, :, j:j + 1], B[:, :, j + 1:]], axis=2)
        twin[:, :, j + noisy] *= 1 + 1e-13  # a rounding difference on one of the two
        kept, _ = identifiable(twin, p, G)
        assert kept[j] and not kept[j + 1] and kept.sum() == 25


def test_a_parameter_whose_own_effect_is_all_but_absorbed_is_not_told(recorded):
    """A parameter that moves the ball as a turn of the whole robot about the vertical plus
    2e-3 of another's effect (and 2e-9 more: a calibrated Panda's ``panda_joint2.ry``) is told
    by no recording: it is not kept, and the rows of the kept ones with the placements' are
    regular (kept, the design's information was singular and no plan identified X)."""
    model, B, p, A, R, G, k, g = recorded
    told = B[:, :, model.parameter_names.index("panda_joint3.tx")]
    noise = np.random.default_rng(1).standard_normal(told.shape) * np.linalg.norm(told) / np.sqrt(told.size)
    almost = rigid_columns(p)[:, :, 5] + 2e-3 * (told + 1e-6 * noise)
    kept, live = identifiable(np.concatenate([B, almost[:, :, None]], axis=2), p, G)
    assert live[-1] and not kept[-1] and kept.sum() == 25
    rows = artefact_rows(A, B[:, :, kept[:-1]], R, k, g).reshape(-1, 25 + G.shape[2])
    s = np.linalg.svd(rows, compute_uv=False)
    assert s[-1] > 1e-6 * s[0]
