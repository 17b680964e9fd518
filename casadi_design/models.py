"""Calibration models: the transformation matrix B(q, F) of dp = B X (paper eq. 7, Table 1).

=================  ==============================  ========================
case               B                               X
=================  ==============================  ========================
geometric (i)      J_Pi(q)                         Pi (selected errors)
elastostatic (ii)  A(q, F)                         k (joint compliances)
both (iii)         [J_Pi(q), A(q, F)]              (Pi, k)
=================  ==============================  ========================

``A(q, F) = [J_1 J_1^T W, ..., J_n J_n^T W]`` with ``J_n`` column n of the 6 x n Jacobian and
``W`` the 6-D wrench (N, N m) at the frame origin, world-aligned: the deflection
``J diag(k) J^T W`` is linear in the compliances ``k`` (rad / (N m) or m / N). Only the rows
of the measured (or, at a test pose, the required) components of the displacement enter B.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from .errors import ProblemError
from .symbolic import TWIST_ROWS, SymbolicKinematics

CASES = ("geometric", "elastostatic", "both")
#: Components of a wrench, in the order of the rows of J.
WRENCH_ROWS = ("fx", "fy", "fz", "mx", "my", "mz")


def row_indices(names: tuple[str, ...] | list[str], allowed: tuple[str, ...], field: str) -> tuple[int, ...]:
    """Indices of component ``names`` in ``allowed``, with a clear error on unknown or repeated ones."""
    unknown = [c for c in names if c not in allowed]
    if unknown or not names or len(set(names)) != len(names):
        raise ProblemError(
            f"{field}: has {list(names)}; allowed: distinct entries of {', '.join(allowed)}"
        )
    return tuple(allowed.index(c) for c in names)


@dataclass(frozen=True, eq=False)
class CalibrationModel:
    """The linear identification model of a calibration case.

    Attributes
    ----------
    case : {"geometric", "elastostatic", "both"}
    parameter_names : tuple of str
        Names of X: the selected geometric errors, then ``k.<joint>`` for each compliant joint.
    force_rows : tuple of int
        Wrench components that ``F`` holds (indices into ``WRENCH_ROWS``); empty when no force
        enters B (geometric case).
    markers_m : ndarray, shape (k, 3)
        Measured points in the measured frame (m); the frame origin by default.
    column_scale : ndarray, shape (L,)
        ``c``: B is written for the scaled parameters ``c * X`` (column k of B divided by
        ``c_k``); ones unless the problem asks for column scaling. The test-pose measure does
        not depend on it; D-optimal plans neither; A, E, T and condition do.
    B : casadi.Function
        ``(q, F) -> B``: measured rows of one experiment (d x L), whitened by the noise model
        so that ``M = sum B^T B`` is ``sigma^2`` times the weighted-least-squares information.
    B0 : casadi.Function
        ``(q, F) -> B0``, the rows whose accuracy is required at test poses (at the frame
        origin, machining wrench applied there).
    position : casadi.Function
        ``q -> p``, nominal position (m) of the measured frame's origin.
    points : casadi.Function
        ``q -> P``, 3 x k nominal positions (m) of the measured points (workspace constraints).
    """

    kinematics: SymbolicKinematics
    case: str
    parameter_names: tuple[str, ...]
    measured_rows: tuple[int, ...]
    accuracy_rows: tuple[int, ...]
    force_rows: tuple[int, ...]
    markers_m: np.ndarray
    column_scale: np.ndarray
    B: ca.Function
    B0: ca.Function
    position: ca.Function
    points: ca.Function

    @property
    def L(self) -> int:
        """Number of parameters to identify, dim X."""
        return len(self.parameter_names)

    @property
    def d(self) -> int:
        """Measured values per experiment."""
        return self.B.size1_out(0)

    @property
    def n(self) -> int:
        return self.kinematics.robot.n

    @property
    def nF(self) -> int:
        return len(self.force_rows)

    def B_numeric(self, q: np.ndarray, F: np.ndarray, accuracy: bool = False) -> np.ndarray:
        fn = self.B0 if accuracy else self.B
        return np.asarray(fn(np.asarray(q, float), np.asarray(F, float)), dtype=float).reshape(
            fn.size1_out(0), self.L
        )


def elastostatic_matrix(J: ca.SX, W: ca.SX, joints: tuple[int, ...]) -> ca.SX:
    """``A = [J_n J_n^T W]``: 6 x len(joints) deflection twist per unit compliance of ``joints``."""
    return ca.horzcat(*[J[:, n] * ca.dot(J[:, n], W) for n in joints])


def _skew(c: ca.SX) -> ca.SX:
    return ca.vertcat(
        ca.horzcat(0, -c[2], c[1]), ca.horzcat(c[2], 0, -c[0]), ca.horzcat(-c[1], c[0], 0)
    )


def measurement_map(R: ca.SX, rows: tuple[int, ...], markers: np.ndarray) -> ca.SX:
    """Map G from the frame's small displacement twist (dp, dtheta) to the measured values.

    Position rows of each marker ``r`` (frame coordinates): ``dp - [R r]x dtheta``; then the
    orientation rows once. ``rows`` index x, y, z, rx, ry, rz.
    """
    pos = [r for r in rows if r < 3]
    blocks = []
    for r in markers:
        c = R @ ca.DM(r)
        blocks.append(ca.horzcat(ca.SX.eye(3), -_skew(c))[pos, :])
    rot = [r - 3 for r in rows if r >= 3]
    if rot:
        blocks.append(ca.horzcat(ca.SX.zeros(3, 3), ca.SX.eye(3))[rot, :])
    return ca.vertcat(*blocks)


def calibration_model(
    kinematics: SymbolicKinematics,
    case: str,
    measured: tuple[str, ...],
    accuracy: tuple[str, ...] | None = None,
    geometric: tuple[str, ...] = (),
    compliant: tuple[str, ...] | None = None,
    force: tuple[str, ...] = (),
    markers_m: np.ndarray | None = None,
    load_point_m: np.ndarray | None = None,
    whitening: np.ndarray | None = None,
    column_scale: np.ndarray | None = None,
) -> CalibrationModel:
    """Build B(q, F) for a calibration case.

    Parameters
    ----------
    measured : component names among x, y, z, rx, ry, rz measured in each experiment; the
        position components are measured at every marker.
    accuracy : components required at the test poses, at the frame origin (default:
        ``measured``).
    geometric : names of the geometric errors to identify (see ``kinematics.parameter_names``);
        required for the geometric and combined cases.
    compliant : joints whose compliance is identified (default: every joint of the chain).
    force : wrench components among fx, fy, fz, mx, my, mz held by F (elasto-static cases).
    markers_m : ndarray, shape (k, 3), m
        Measured points in the measured frame (default: its origin).
    load_point_m : ndarray, shape (3,), m
        Where the calibration force acts, in the measured frame (default: its origin); an
        offset adds the moment ``(R r) x f``.
    whitening : ndarray, shape (d, d)
        ``sigma * Sigma^-1/2`` for a measurement covariance ``Sigma`` and reference ``sigma``
        (default identity): B is pre-multiplied by it (weighted least squares).
    column_scale : ndarray, shape (L,)
        Scales of the parameters (see :class:`CalibrationModel`); ones by default.
    """
    if case not in CASES:
        raise ProblemError(f"[calibration].case: '{case}'; allowed: {', '.join(CASES)}")
    robot = kinematics.robot
    m_rows = row_indices(tuple(measured), TWIST_ROWS, "[measurement].components")
    a_rows = row_indices(tuple(accuracy or measured), TWIST_ROWS, "[test_poses].components")
    markers = np.zeros((1, 3)) if markers_m is None else np.asarray(markers_m, dtype=float).reshape(-1, 3)
    names: list[str] = []
    geo_idx: list[int] = []
    if case in ("geometric", "both"):
        if not geometric:
            raise ProblemError(
                f"[calibration].parameters: case '{case}' needs the geometric errors to identify, "
                f"e.g. {list(kinematics.parameter_names[6:9])}"
            )
        for g in geometric:
            if g not in kinematics.parameter_names:
                raise ProblemError(
                    f"[calibration].parameters: unknown parameter '{g}'; allowed: base.<e>, "
                    f"<joint>.offset, <joint>.<e>, tool.<e> with <e> in tx, ty, tz, rx, ry, rz "
                    f"and <joint> in {', '.join(robot.joints)}"
                )
        if len(set(geometric)) != len(geometric):
            raise ProblemError(f"[calibration].parameters: repeated names in {list(geometric)}")
        geo_idx = [kinematics.parameter_names.index(g) for g in geometric]
        names += list(geometric)
    comp_idx: list[int] = []
    f_rows: tuple[int, ...] = ()
    if case in ("elastostatic", "both"):
        compliant = tuple(robot.joints if compliant is None else compliant)
        for j in compliant:
            if j not in robot.joints:
                raise ProblemError(
                    f"[calibration].compliant_joints: unknown joint '{j}'; the chain has: "
                    + ", ".join(robot.joints)
                )
        if not compliant or len(set(compliant)) != len(compliant):
            raise ProblemError(
                f"[calibration].compliant_joints: has {list(compliant)}; list distinct joints among "
                + ", ".join(robot.joints)
            )
        comp_idx = [robot.joints.index(j) for j in compliant]
        names += [f"k.{j}" for j in compliant]
        f_rows = row_indices(tuple(force), WRENCH_ROWS, "[calibration].wrench_components")

    q = ca.SX.sym("q", robot.n)
    F = ca.SX.sym("F", len(f_rows))
    R, p = kinematics.placement(q, ca.DM.zeros(len(kinematics.parameter_names)))
    W0 = ca.SX.zeros(6)
    for i, r in enumerate(f_rows):
        W0[r] = F[i]
    lever = R @ ca.DM(np.zeros(3) if load_point_m is None else np.asarray(load_point_m, dtype=float))
    W = ca.vertcat(W0[:3], W0[3:] + ca.cross(lever, W0[:3]))
    J = kinematics.jacobian(q)
    J_Pi = kinematics.error_jacobian(q)

    def twist_matrix(W: ca.SX) -> ca.SX:
        blocks = []
        if geo_idx:
            blocks.append(J_Pi[:, geo_idx])
        if comp_idx:
            blocks.append(elastostatic_matrix(J, W, tuple(comp_idx)))
        return ca.horzcat(*blocks)

    G = measurement_map(R, m_rows, markers)
    if whitening is not None:
        if np.shape(whitening) != (G.shape[0], G.shape[0]):
            raise ProblemError(
                f"[measurement]: the noise model is {np.shape(whitening)} but each experiment "
                f"measures {G.shape[0]} values; give one sigma or covariance row per value"
            )
        G = ca.DM(whitening) @ G
    G0 = measurement_map(R, a_rows, np.zeros((1, 3)))
    c = np.ones(len(names)) if column_scale is None else np.asarray(column_scale, dtype=float)
    Cinv = ca.DM(np.diag(1.0 / c))
    return CalibrationModel(
        kinematics=kinematics,
        case=case,
        parameter_names=tuple(names),
        measured_rows=m_rows,
        accuracy_rows=a_rows,
        force_rows=f_rows,
        markers_m=markers,
        column_scale=c,
        B=ca.Function("B", [q, F], [G @ twist_matrix(W) @ Cinv], ["q", "F"], ["B"]),
        B0=ca.Function("B0", [q, F], [G0 @ twist_matrix(W0) @ Cinv], ["q", "F"], ["B0"]),
        position=ca.Function("p", [q], [p], ["q"], ["p"]),
        points=ca.Function("points", [q], [p + R @ ca.DM(markers.T)], ["q"], ["P"]),
    )
