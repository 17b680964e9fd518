"""Points fixed in an artefact: the measured point (a ball on the hand) seated at known points
(sockets) of a tool clamped on the table, with no external measurement.

The artefact's points ``a_k`` (k = 0..K-1, its own frame, m) are known (a caliper-checked
tool); each placement g of the artefact (the tool clamped somewhere: a "tool position") has an
unknown pose ``T_g = (R_g, t_g)`` in the robot's base frame, a nuisance like a tracker's frame.
A recording i is a configuration ``q_i`` with the ball in point ``k_i`` of placement ``g_i``:

    p(q_i, X) = t_g + R_g a_k + e_i,    e_i ~ N(0, sigma^2 I_3)

with ``p`` the problem's one measurement model (the measured frame's origin, or
``tool_xyz_m`` on it, :mod:`.models`) and ``sigma`` the seating repeatability (m). Each
placement's pose is corrected as ``t_g + dt``, ``R_g exp([E theta])`` with ``E`` (3 x r) the
turns its points tell (:attr:`Artefact.turns`): all three for three points or more not on a
line, the two across the line for points on a line (the turn about it moves none of them:
absorbed), none for one point. Linearised, a recording's residual is

    r_i = B_i dX - G_i dP_g,    G_i = [I_3, -R_g [a_k]_x E]   (3 x (3 + r)),

and the information of X is the Schur complement of the placements, one per placement:

    M = sum_g (B_g^T B_g - B_g^T G_g (G_g^T G_g)^-1 G_g^T B_g)

(:func:`placement_projected`): what the placements absorb is exactly what no recording of the
artefact tells. The robot's placement in the world (``base.*``) moves every placement alike and
is absorbed too; the known spacing of the points gives the scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .identifiability import pivoted_columns

#: A parameter is told by an artefact's recordings when more than this share of its own effect is
#: left once the placements, a rigid motion of the robot and the parameters kept take theirs
#: (:func:`identifiable`): its information is then above ``TOLD_RTOL**2`` of its own, the
#: plans' threshold of a singular ``M`` (:data:`~casadi_design.measures.measures.SINGULAR_RTOL`,
#: 1e-12). Below it the rows are regular only by the nominal robot's rounding: a UR5's
#: ``shoulder_lift_joint.rx`` at one placement keeps 4e-8 of its effect, configurations seated by
#: the inverse kinematics to 1e-7 m, and no plan of them was regular. On MUKCa's recordings the
#: weakest parameter kept keeps 8e-5 (panda_4 ``right``) and the next is 1e-15.
TOLD_RTOL = 1e-6
#: Directions of the motions projected out (:func:`projected_out`) below this share of the
#: largest are not motions: a rigid motion of the whole robot and a placement's differ at two
#: sockets only by the points' spread about them, 1e-12 m for configurations seated by the
#: plans' NLP; taken as motions, they removed what no motion makes from a parameter's effect (a
#: UR5's ``shoulder_lift_joint.rx`` then kept 3e-6 of its own and the plan's rows were singular).
#: Recordings spread by the nominal robot's error (mm) are far above it.
MOTION_RCOND = 1e-9

#: Points closer than this (m) to the line through the first two are on that line; a turn is
#: told when its points leave the line by more.
COLLINEAR_M = 1e-6


@dataclass(frozen=True, eq=False)
class Artefact:
    """An artefact's points and the turns of a placement they tell.

    Attributes
    ----------
    points_m : ndarray, shape (K, 3), m: the points in the artefact's frame.
    turns : ndarray, shape (3, r): the turns (unit axes, artefact frame) a placement's
        recordings tell: 3 (points not on a line), 2 (on a line: across it), 0 (one point).
    """

    points_m: np.ndarray
    turns: np.ndarray

    @property
    def K(self) -> int:
        """Number of points."""
        return len(self.points_m)

    @property
    def nP(self) -> int:
        """Parameters of one placement: 3 translations and the turns told."""
        return 3 + self.turns.shape[1]

    @property
    def spacings_m(self) -> np.ndarray:
        """Distances between the points (K, K), m."""
        return np.linalg.norm(self.points_m[:, None] - self.points_m[None], axis=2)

    def columns(self, R: np.ndarray, k: np.ndarray) -> np.ndarray:
        """``G = d(t + R exp([E theta]) a_k) / d(dt, theta)`` at theta = 0 for points ``k``
        (N,) of a placement of rotation ``R``: (N, 3, nP)."""
        k = np.asarray(k, dtype=int)
        G = np.zeros((len(k), 3, self.nP))
        G[:, :, :3] = np.eye(3)
        if self.turns.shape[1]:
            G[:, :, 3:] = np.stack([-R @ pin.skew(self.points_m[j]) @ self.turns for j in k])
        return G

    def moved(self, R: np.ndarray, t: np.ndarray, dP: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The placement ``(R, t)`` corrected by ``dP`` (nP,): ``(R exp([E theta]), t + dt)``."""
        return R @ pin.exp3(self.turns @ dP[3:]), t + dP[:3]

    def place(self, centres: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """A first placement ``(R, t)`` from the mean measured point of each artefact point
        recorded (``{k: (3,)}``, base frame, m): the least-squares rigid fit of the points to
        those means (Kabsch; points on a line: the turn that lays the line on the means' line,
        the least one; one point: no turn)."""
        k = np.array(sorted(centres))
        A, C = self.points_m[k], np.array([centres[j] for j in k])
        a0, c0 = A.mean(axis=0), C.mean(axis=0)
        if len(k) == 1:
            R = np.eye(3)
        elif self.turns.shape[1] == 3 and np.linalg.matrix_rank(A - a0, tol=COLLINEAR_M) >= 2:
            U, _, Vt = np.linalg.svd((C - c0).T @ (A - a0))
            R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        else:
            u = line_direction(A - a0)
            v = line_direction(C - c0, along=(C - c0).T @ ((A - a0) @ u))
            R = least_turn(u, v)
        return R, c0 - R @ a0

    def placed(self, p: np.ndarray, point: np.ndarray, placement: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first poses ``R`` (P, 3, 3), ``t`` (P, 3) of the placements 0..P-1 of points ``p``
        (N, 3) recorded at ``point`` of ``placement`` (N,): :meth:`place` of each placement's
        mean point per artefact point."""
        poses = [self.place({k: p[(placement == g) & (point == k)].mean(axis=0)
                             for k in np.unique(point[placement == g])}) for g in range(int(placement.max()) + 1)]
        return np.array([R for R, _ in poses]), np.array([t for _, t in poses])


def line_direction(D: np.ndarray, along: np.ndarray | None = None) -> np.ndarray:
    """The unit direction of the points ``D`` (N, 3) about their mean, signed towards
    ``along`` (3,) when given."""
    u = np.linalg.svd(D, full_matrices=False)[2][0]
    if along is not None and u @ along < 0:
        u = -u
    return u


def least_turn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The rotation of least angle taking the unit ``u`` to the unit ``v``."""
    w, c = np.cross(u, v), float(u @ v)
    s = float(np.linalg.norm(w))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
        return pin.exp3(np.pi * axis / np.linalg.norm(axis))
    return pin.exp3(w / s * np.arctan2(s, c))


def artefact(points_m: np.ndarray) -> Artefact:
    """The :class:`Artefact` of ``points_m`` (K, 3), m, with the turns its points tell."""
    P = np.asarray(points_m, dtype=float).reshape(-1, 3)
    if len(P) == 1:
        return Artefact(P, np.zeros((3, 0)))
    D = P - P.mean(axis=0)
    s = np.linalg.svd(D, compute_uv=False)
    if len(P) > 2 and s[1] > COLLINEAR_M:
        return Artefact(P, np.eye(3))
    u = line_direction(D)
    across = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]
    return Artefact(P, across)


def rigid_columns(p: np.ndarray) -> np.ndarray:
    """``d(p + dt + dw x p) / d(dt, dw) = [I, -[p]_x]`` of points ``p`` (N, 3): (N, 3, 6), how
    a rigid motion moves them."""
    return np.concatenate([np.tile(np.eye(3), (len(p), 1, 1)), -np.stack([pin.skew(v) for v in p])], axis=2)


def projected_out(J: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The rows ``J`` (N, 3, L) less their least-squares part in the columns ``T`` (N, 3, c):
    ``(I - T T^+) J`` stacked, (N, 3, L), ``T^+`` without the directions of ``T`` below
    :data:`MOTION_RCOND` of its largest."""
    S, C = J.reshape(-1, J.shape[2]), T.reshape(-1, T.shape[2])
    return (S - C @ np.linalg.lstsq(C, S, rcond=MOTION_RCOND)[0]).reshape(J.shape)


def placement_columns(A: Artefact, R: np.ndarray, point: np.ndarray, placement: np.ndarray) -> np.ndarray:
    """Each recording's placement columns ``G_i`` (:meth:`Artefact.columns`) in its placement's
    block: (N, 3, P nP) for points ``point`` (N,) of ``placement`` (N,; 0..P-1, of rotations ``R``
    (P, 3, 3))."""
    out = np.zeros((len(point), 3, len(R) * A.nP))
    for g in range(len(R)):
        rows = placement == g
        out[rows, :, g * A.nP:(g + 1) * A.nP] = A.columns(R[g], point[rows])
    return out


def identifiable(J: np.ndarray, p: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which columns of ``J`` (N, 3, L) recordings at the points ``p`` (N, 3) of placements of
    columns ``G`` (N, 3, P nP, :func:`placement_columns`) tell, with every placement and the
    robot's base unknown: the placements' columns and a rigid motion of the whole robot
    (:func:`rigid_columns`) projected out, each column divided by its norm before the projection,
    QR with column pivoting (``|R_ii| > TOLD_RTOL |R_00|``; ties to the parameter listed first,
    :func:`~.identifiability.pivoted_columns`, so that the set does not depend on the BLAS): a
    parameter is told when a share of its own effect beyond :data:`TOLD_RTOL` is left once the others'
    is taken (a calibrated Panda's ``panda_joint2.ry``, nearly a turn of the base about its
    vertical: 2e-3 of its effect is left by the projection and 1e-6 of that by the others',
    told by no recording). Returns (kept, live): kept the base set (bool, L), live the columns
    with any effect left (bool, L)."""
    Jp = projected_out(J, np.concatenate([rigid_columns(p), G], axis=2)).reshape(-1, J.shape[2])
    scale = np.linalg.norm(J.reshape(-1, J.shape[2]), axis=0)
    norms = np.linalg.norm(Jp, axis=0)
    live = norms > TOLD_RTOL * np.maximum(scale, np.finfo(float).tiny)
    kept = np.zeros(J.shape[2], dtype=bool)
    if live.any():
        piv, d = pivoted_columns(Jp[:, live] / scale[live])
        kept[np.flatnonzero(live)[piv[:int(np.sum(d > TOLD_RTOL * d[0]))]]] = True
    return kept, live


def placement_projected(J: np.ndarray, G: np.ndarray) -> np.ndarray:
    """The rows ``J`` (N, 3, L) of X with the placements' columns ``G`` (N, 3, P nP,
    :func:`placement_columns`) projected out: their ``J^T J`` is the Schur complement of the
    placements, the information of X with every placement unknown (module docstring)."""
    return projected_out(J, G)


def artefact_rows(A: Artefact, B: np.ndarray, R: np.ndarray, point: np.ndarray, placement: np.ndarray) -> np.ndarray:
    """The rows of experiments seated at ``point`` (N,) of ``placement`` (N,; 0..P-1, of rotations
    ``R`` (P, 3, 3)) with the placements' poses beside X: ``[B_i, 0 .. -G_i .. 0]`` (N, 3, L + P
    nP) (:func:`placement_columns`): the residuals' Jacobian in X and the poses. Their ``sum
    B^T B`` is additive over the experiments, and the Schur complement of its placements' block
    is X's information with every placement unknown: with the test poses' rows zero on the
    placements' columns, ``tr(B0 M^-1 B0^T)`` is the test-pose measure of the Schur complement."""
    return np.concatenate([B, -placement_columns(A, R, point, placement)], axis=2)


def registered(B0: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """The test poses' rows ``B0`` (s, 3, L) of their positions ``p0`` (s, 3), m, with the rigid
    motions of those points projected out (:func:`rigid_columns`): the error a user sees after
    registering the work in the robot's frame by the robot itself (nothing here measures the
    base)."""
    return projected_out(B0, rigid_columns(p0))
