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
    B : casadi.Function
        ``(q, F) -> B``, the measured rows (calibration experiments).
    B0 : casadi.Function
        ``(q, F) -> B0``, the rows whose accuracy is required at test poses.
    position : casadi.Function
        ``q -> p``, nominal position (m) of the measured frame, for workspace constraints.
    """

    kinematics: SymbolicKinematics
    case: str
    parameter_names: tuple[str, ...]
    measured_rows: tuple[int, ...]
    accuracy_rows: tuple[int, ...]
    force_rows: tuple[int, ...]
    B: ca.Function
    B0: ca.Function
    position: ca.Function

    @property
    def L(self) -> int:
        """Number of parameters to identify, dim X."""
        return len(self.parameter_names)

    @property
    def n(self) -> int:
        return self.kinematics.robot.n

    @property
    def nF(self) -> int:
        return len(self.force_rows)

    def B_numeric(self, q: np.ndarray, F: np.ndarray, accuracy: bool = False) -> np.ndarray:
        fn = self.B0 if accuracy else self.B
        return np.asarray(fn(np.asarray(q, float), np.asarray(F, float)), dtype=float).reshape(
            len(self.accuracy_rows if accuracy else self.measured_rows), self.L
        )


def elastostatic_matrix(J: ca.SX, W: ca.SX, rows: tuple[int, ...], joints: tuple[int, ...]) -> ca.SX:
    """``A = [J_n J_n^T W]`` for the compliant ``joints`` (column indices of J), ``rows`` of J."""
    return ca.horzcat(*[J[list(rows), n] * ca.dot(J[:, n], W) for n in joints])


def calibration_model(
    kinematics: SymbolicKinematics,
    case: str,
    measured: tuple[str, ...],
    accuracy: tuple[str, ...] | None = None,
    geometric: tuple[str, ...] = (),
    compliant: tuple[str, ...] | None = None,
    force: tuple[str, ...] = (),
) -> CalibrationModel:
    """Build B(q, F) for a calibration case.

    Parameters
    ----------
    measured : component names among x, y, z, rx, ry, rz measured in each experiment.
    accuracy : components required at the test poses (default: ``measured``).
    geometric : names of the geometric errors to identify (see ``kinematics.parameter_names``);
        required for the geometric and combined cases.
    compliant : joints whose compliance is identified (default: every joint of the chain).
    force : wrench components among fx, fy, fz, mx, my, mz held by F (elasto-static cases).
    """
    if case not in CASES:
        raise ProblemError(f"[calibration].case: '{case}'; allowed: {', '.join(CASES)}")
    robot = kinematics.robot
    m_rows = row_indices(tuple(measured), TWIST_ROWS, "[measurement].components")
    a_rows = row_indices(tuple(accuracy or measured), TWIST_ROWS, "[test_poses].components")
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
    W = ca.SX.zeros(6)
    for i, r in enumerate(f_rows):
        W[r] = F[i]
    J = kinematics.jacobian(q)
    J_Pi = kinematics.error_jacobian(q)

    def B_of(rows: tuple[int, ...]) -> ca.SX:
        blocks = []
        if geo_idx:
            blocks.append(J_Pi[list(rows), geo_idx])
        if comp_idx:
            blocks.append(elastostatic_matrix(J, W, rows, tuple(comp_idx)))
        return ca.horzcat(*blocks)

    _, p = kinematics.placement(q, ca.DM.zeros(len(kinematics.parameter_names)))
    return CalibrationModel(
        kinematics=kinematics,
        case=case,
        parameter_names=tuple(names),
        measured_rows=m_rows,
        accuracy_rows=a_rows,
        force_rows=f_rows,
        B=ca.Function("B", [q, F], [B_of(m_rows)], ["q", "F"], ["B"]),
        B0=ca.Function("B0", [q, F], [B_of(a_rows)], ["q", "F"], ["B0"]),
        position=ca.Function("p", [q], [p], ["q"], ["p"]),
    )
