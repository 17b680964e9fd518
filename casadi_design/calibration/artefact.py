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

#: Points closer than this (m) to the line through the first two are on that line; a turn is
#: told when its points leave the line by more.
COLLINEAR_M = 1e-6


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` (3 x 3): ``[v]_x w = v x w``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation(w: np.ndarray) -> np.ndarray:
    """``exp([w]_x)`` (Rodrigues), rad."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3) + skew(w)
    K = skew(np.asarray(w) / angle)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


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
            G[:, :, 3:] = np.stack([-R @ skew(self.points_m[j]) @ self.turns for j in k])
        return G

    def moved(self, R: np.ndarray, t: np.ndarray, dP: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The placement ``(R, t)`` corrected by ``dP`` (nP,): ``(R exp([E theta]), t + dt)``."""
        return R @ rotation(self.turns @ dP[3:]), t + dP[:3]

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
        return rotation(np.pi * axis / np.linalg.norm(axis))
    return rotation(w / s * np.arctan2(s, c))


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
    a rigid motion of the whole robot moves them."""
    return np.concatenate([np.tile(np.eye(3), (len(p), 1, 1)), -np.stack([skew(v) for v in p])], axis=2)


def identifiable(J: np.ndarray, p: np.ndarray, G: np.ndarray, placement: np.ndarray,
                 rtol: float) -> tuple[np.ndarray, np.ndarray]:
    """Which columns of ``J`` (N, 3, L) recordings at the points ``p`` (N, 3) of the placements
    ``placement`` (N,; columns ``G`` (N, 3, nP)) tell, with every placement and the robot's base
    unknown: each placement's columns and a rigid motion of the whole robot
    (:func:`rigid_columns`) projected out, the columns of unit norm, QR with column pivoting
    (``|R_ii| > rtol |R_00|``). Returns (kept, live): kept the base set (bool, L), live the
    columns with any effect left (bool, L)."""
    import scipy.linalg

    places = np.unique(placement)
    fixed = np.zeros((len(J), 3, 6 + G.shape[2] * len(places)))
    fixed[:, :, :6] = rigid_columns(p)
    for i, g in enumerate(places):
        fixed[placement == g, :, 6 + i * G.shape[2]:6 + (i + 1) * G.shape[2]] = G[placement == g]
    S, T = J.reshape(-1, J.shape[2]), fixed.reshape(-1, fixed.shape[2])
    Jp = S - T @ np.linalg.lstsq(T, S, rcond=None)[0]
    scale = np.linalg.norm(J.reshape(-1, J.shape[2]), axis=0)
    norms = np.linalg.norm(Jp, axis=0)
    live = norms > rtol * np.maximum(scale, np.finfo(float).tiny)
    kept = np.zeros(J.shape[2], dtype=bool)
    if live.any():
        _, R, piv = scipy.linalg.qr(Jp[:, live] / norms[live], mode="economic", pivoting=True)
        d = np.abs(np.diag(R))
        kept[np.flatnonzero(live)[piv[:int(np.sum(d > rtol * d[0]))]]] = True
    return kept, live


def placement_projected(J: np.ndarray, G: np.ndarray, placement: np.ndarray) -> np.ndarray:
    """The rows ``J`` (N, 3, L) of X with each placement's columns ``G`` (N, 3, nP) projected
    out, ``(I - P_g) J_g`` per placement g (``placement`` (N,)): their ``J^T J`` is the Schur
    complement of the placements, the information of X with every placement unknown
    (module docstring). (N, 3, L)."""
    out = np.empty_like(J)
    for g in np.unique(placement):
        rows = placement == g
        A = J[rows].reshape(-1, J.shape[2])
        Gg = G[rows].reshape(-1, G.shape[2])
        coef = np.linalg.lstsq(Gg, A, rcond=None)[0]
        out[rows] = (A - Gg @ coef).reshape(-1, 3, J.shape[2])
    return out


def artefact_rows(A: Artefact, B: np.ndarray, R: np.ndarray, point: np.ndarray, placement: np.ndarray) -> np.ndarray:
    """The rows of experiments seated at ``point`` (N,) of ``placement`` (N,; 0..P-1, of rotations
    ``R`` (P, 3, 3)) with the placements' poses beside X: ``[B_i, 0 .. -G_i .. 0]`` (N, 3, L + P
    nP), ``G_i`` in its placement's columns (:meth:`Artefact.columns`). Their ``sum B^T B`` is
    additive over the experiments, and the Schur complement of its placements' block is X's
    information with every placement unknown: with the test poses' rows zero on the placements'
    columns, ``tr(B0 M^-1 B0^T)`` is the test-pose measure of the Schur complement."""
    N, _, L = B.shape
    P = len(R)
    out = np.zeros((N, 3, L + P * A.nP))
    out[:, :, :L] = B
    for g in range(P):
        rows = placement == g
        out[rows, :, L + g * A.nP:L + (g + 1) * A.nP] = -A.columns(R[g], point[rows])
    return out


def registered(B0: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """The test poses' rows ``B0`` (s, 3, L) of their positions ``p0`` (s, 3), m, with the rigid
    motions of those points projected out: the error a user sees after registering the work in
    the robot's frame by the robot itself (nothing here measures the base): ``(I - P_T) B0``
    stacked, ``P_T`` the projector on ``[I, -[p_j]_x]`` (3s x 6)."""
    s, r, L = B0.shape
    T = np.concatenate([np.tile(np.eye(3), (s, 1, 1)), -np.stack([skew(p) for p in p0])], axis=2).reshape(3 * s, 6)
    S = B0.reshape(3 * s, L)
    return (S - T @ np.linalg.lstsq(T, S, rcond=None)[0]).reshape(s, r, L)
