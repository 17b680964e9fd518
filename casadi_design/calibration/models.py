"""Calibration models: the measurement y(q, F, X) and its Jacobian B(q, F) (paper eq. 7, Table 1).

One nonlinear measurement model, written once: the robot with parameters ``X`` (geometric
errors ``Pi`` in m and rad, joint compliances ``k``) under the wrench of load ``F`` deflects
by the fixed point ``dq = diag(k) J(q + dq, Pi)^T W``; the measured values are the positions
of the markers and the orientation of the measured frame, as deviations from a reference pose,
whitened by the noise model. Everything else derives from it:

=================  ==============================  ========================
case               B = dy/dX at X = 0              X
=================  ==============================  ========================
geometric (i)      J_Pi(q)                         Pi (selected errors)
elastostatic (ii)  A(q, F) = [J_n J_n^T W]         k (joint compliances)
both (iii)         [J_Pi(q), A(q, F)]              (Pi, k)
=================  ==============================  ========================

``W`` is the 6-D wrench (N, N m) at the frame origin, world-aligned; a calibration load acting
at ``load_point_m`` adds the moment ``(R r) x f``. The design (``B``), the test poses (``B0``,
machining wrench at the frame origin), the virtual calibration (simulate, identify,
compensate) and the checks of a plan all call these functions.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ProblemError
from ..problem_file.calibration import CASES
from ..problem_file.fields import TWIST_ROWS, WRENCH_ROWS
from ..robot.symbolic import SymbolicKinematics, twist_jacobian
from ..runtime.cache import memoised

#: Fixed-point iterations of the joint deflection ``dq = diag(k) J(q + dq)^T W``: the update
#: shrinks by ~``k |W| reach`` per iteration, so 5 reach 1e-9 rad up to ``k |W| reach`` ~ 0.01
#: (k = 1e-4 rad/(N m) under 100 N at 1 m: 100 times a stiff industrial joint). At X = 0 the
#: derivative of the fixed point is exact after one iteration, which B uses.
DEFLECTION_ITERATIONS = 5


def row_indices(names: tuple[str, ...] | list[str], allowed: tuple[str, ...], field: str) -> tuple[int, ...]:
    """Indices of component ``names`` in ``allowed``, with a clear error on unknown or repeated ones."""
    unknown = [c for c in names if c not in allowed]
    if unknown or not names or len(set(names)) != len(names):
        raise ProblemError(
            f"{field}: has {list(names)}; allowed: distinct entries of {', '.join(allowed)}"
        )
    return tuple(allowed.index(c) for c in names)


#: The axes of a joint's placement a tilt compliance may turn about (``k.<joint>.rx``, ``.ry``,
#: ``.rz``): those across the joint's own axis (rx and ry for a joint about z).
TILT_AXES = ("rx", "ry", "rz")


@dataclass(frozen=True, eq=False)
class CalibrationModel:
    """The measurement model of a calibration case and its linearisation.

    Inputs of the functions: ``q`` (n, rad or m), ``F`` (nF, N or N m), ``X`` (L, the physical
    parameters: m, rad, rad/(N m) or m/N) and ``ref`` (12: column-major rotation and position,
    m, of a reference pose, as given by ``pose``). ``step`` is the last update of the
    deflection fixed point (rad or m).

    Attributes
    ----------
    case : {"geometric", "elastostatic", "both"}
    parameter_names : tuple of str
        Names of X: the selected geometric errors, then ``k.<joint>`` for each compliant joint.
    force_rows : tuple of int
        Wrench components that ``F`` holds (indices into ``WRENCH_ROWS``); empty when no force
        enters the model (geometric case).
    markers_m : ndarray, shape (k, 3)
        Measured points in the measured frame (m); the frame origin by default.
    column_scale : ndarray, shape (L,)
        ``c``: B is written for the scaled parameters ``c * X`` (column l of dy/dX divided by
        ``c_l``); ones unless the problem asks for column scaling. The test-pose measure does
        not depend on it; D-optimal plans neither; A, E, T and condition do.
    pose : casadi.Function
        ``(q, F, X) -> ref``: the pose of the measured frame of robot X deflected by the
        calibration load F.
    measurement : casadi.Function
        ``(q, F, X, ref) -> (y, step)``: the d measured values of robot X under calibration
        load F, as whitened deviations from ``ref`` (``sigma * Sigma^-1/2`` times marker
        positions, then orientation rows), so that the noise of y is ``sigma`` per value.
    accuracy : casadi.Function
        ``(q, F, X, ref) -> (e, step)``: the r required deviation rows of the frame origin of
        robot X under machining wrench F (at the origin) from ``ref``.
    B : casadi.Function
        ``(q, F) -> B``: ``dy/dX`` at ``X = 0``, ``ref = pose(q, F, 0)``, columns scaled
        (d x L): ``M = sum B^T B`` is ``sigma^2`` times the weighted-least-squares information.
    B0 : casadi.Function
        ``(q, F) -> B0``: ``de/dX`` at ``X = 0`` likewise (r x L).
    position : casadi.Function
        ``q -> p``, nominal position (m) of the measured frame's origin.
    points : casadi.Function
        ``q -> P``, 3 x k nominal positions (m) of the measured points.
    gravity : bool
        The compliant joints deflect under the robot's own weight too (``g(q)`` of the URDF's
        inertias, :attr:`SymbolicKinematics.gravity_torque`), beside the wrench ``W``.
    seating_N : tuple of 3 floats, N, or None
        A force at the measured point in every measured experiment (base frame), beside ``W``:
        the push that seats a ball in an artefact's point; the test poses carry none.
    """

    kinematics: SymbolicKinematics
    case: str
    parameter_names: tuple[str, ...]
    measured_rows: tuple[int, ...]
    accuracy_rows: tuple[int, ...]
    force_rows: tuple[int, ...]
    markers_m: np.ndarray
    column_scale: np.ndarray
    pose: ca.Function
    measurement: ca.Function
    accuracy: ca.Function
    B: ca.Function
    B0: ca.Function
    position: ca.Function
    points: ca.Function
    gravity: bool = False
    seating_N: tuple[float, float, float] | None = None

    @property
    def loaded(self) -> bool:
        """The compliant joints deflect under a load known beforehand: the robot's own weight
        (``gravity``) or the seating push (``seating_N``)."""
        return self.gravity or self.seating_N is not None

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
        """``B(q, F)`` (d x L), or ``B0(q, F)`` (r x L) when ``accuracy``, as an array."""
        fn = self.B0 if accuracy else self.B
        return np.asarray(fn(np.asarray(q, float), np.asarray(F, float)), dtype=float).reshape(
            fn.size1_out(0), self.L
        )

    def B_stack(self, Q: np.ndarray, F: np.ndarray, accuracy: bool = False) -> np.ndarray:
        """``B`` (or ``B0``) of N configurations at once: ``Q`` (N, n), ``F`` (N, nF) ->
        (N, d, L)."""
        fn = self.B0 if accuracy else self.B
        Q, F = np.atleast_2d(np.asarray(Q, float)), np.asarray(F, float).reshape(len(Q), self.nF)
        out = np.asarray(fn.map(len(Q))(Q.T, F.T), dtype=float)
        # contiguous: sums over it (e.g. the NLP's scale) then add in the same order in every
        # process, whether the array was computed here or unpickled
        return np.ascontiguousarray(out.reshape(fn.size1_out(0), len(Q), self.L).transpose(1, 0, 2))

    def dq_stack(self, Q: np.ndarray, F: np.ndarray | None = None, rows: str = "measured") -> np.ndarray:
        """How the values move with the joint angles at X = 0 about the nominal pose, (N, ., n):
        ``dy/dq`` of the measured values (whitened, d), ``de/dq`` of the required components
        (r; ``rows="accuracy"``) or ``dp/dq`` of the frame's origin (3; ``"position"``), m per rad
        (rad per rad for orientation rows) (:func:`joint_jacobians`): the loads of a field of
        joint-angle errors."""
        Q = np.atleast_2d(np.asarray(Q, float))
        F = np.zeros((len(Q), self.nF)) if F is None else np.asarray(F, float).reshape(len(Q), self.nF)
        fn = joint_jacobians(self)[("measured", "accuracy", "position").index(rows)]
        if not len(Q):
            return np.zeros((0, fn.size1_out(0), self.n))
        out = np.asarray(fn.map(len(Q))(Q.T, F.T), dtype=float)
        return np.ascontiguousarray(out.reshape(fn.size1_out(0), len(Q), self.n).transpose(1, 0, 2))


@memoised(8)
def joint_jacobians(model: CalibrationModel) -> tuple[ca.Function, ca.Function, ca.Function]:
    """``(q, F) -> dy/dq`` (d x n), ``de/dq`` (r x n) and ``dp/dq`` (3 x n) of ``model`` at X = 0,
    ``ref = pose(q, F, 0)``: the measured values', the required components' and the frame
    origin's derivatives by the joint angles, derived once per model."""
    q, F, ref = ca.SX.sym("q", model.n), ca.SX.sym("F", model.nF), ca.SX.sym("ref", 12)
    X0 = ca.DM.zeros(model.L)
    ref0 = model.pose(q, F, X0)
    y, _ = model.measurement(q, F, X0, ref)
    e, _ = model.accuracy(q, F, X0, ref)
    return tuple(ca.Function(name, [q, F], [ca.substitute(ca.jacobian(v, q), ref, ref0)], ["q", "F"], [name])
                 for name, v in (("dy_dq", y), ("de_dq", e), ("dp_dq", ref0[9:12])))


def _skew_vee(A: ca.SX) -> ca.SX:
    """``vee((A - A^T) / 2)``: the small rotation (rad) of ``A = R R_ref^T`` near the identity."""
    return ca.vertcat(A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]) / 2


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
    gravity: bool = False,
    seating_N: tuple[float, float, float] | None = None,
) -> CalibrationModel:
    """Build the measurement model of a calibration case (see :class:`CalibrationModel`).

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
        Where the calibration force acts, in the measured frame (default: its origin).
    whitening : ndarray, shape (d, d)
        ``sigma * Sigma^-1/2`` for a measurement covariance ``Sigma`` and reference ``sigma``
        (default identity).
    column_scale : ndarray, shape (L,)
        Scales of the parameters (see :class:`CalibrationModel`); ones by default.
    gravity : the compliant joints deflect under the robot's own weight too:
        ``dq = diag(k) (J(q + dq)^T W - g(q + dq))`` (an elasto-static case without loads then
        needs no ``force``). A compliance ``<joint>.rx`` (``.ry``, ``.rz``) of ``compliant`` tilts
        the joint's placement about its x (y, z) axis under the moment its bearing carries,
        ``dPi = kt (J_Pi^T W - dV/dPi)`` (:attr:`SymbolicKinematics.gravity_moments`), rad/(N m).
    seating_N : a force (N, base frame) at the measured frame's origin added to ``W`` in the
        measured values only: ``dq = diag(k) J^T (W + [f; 0])`` (the push seating a ball in an
        artefact's point, :attr:`CalibrationModel.seating_N`).
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
                f"[calibration].parameters: case '{case}' needs the geometric errors to identify; "
                f"list them, e.g. {list(kinematics.parameter_names[6:9])}, or give \"identifiable\""
            )
        for g in geometric:
            if g not in kinematics.parameter_names:
                raise ProblemError(
                    f"[calibration].parameters: unknown parameter '{g}'; allowed: base.<e>, "
                    f"<joint>.offset, <joint>.<e>, tool.<e> with <e> in tx, ty, tz, rx, ry, rz "
                    f"and <joint> in {', '.join(robot.joints)}"
                )
        if len(set(geometric)) != len(geometric):
            raise ProblemError(f"[calibration].parameters: repeated names in {list(geometric)}; list each once")
        geo_idx = [kinematics.parameter_names.index(g) for g in geometric]
        names += list(geometric)
    comp_idx: list[int] = []  # per compliance of X: the joint (axial) or the geometric error (tilt) it loads
    tilted: list[bool] = []
    f_rows: tuple[int, ...] = ()
    if case in ("elastostatic", "both"):
        compliant = tuple(robot.joints if compliant is None else compliant)
        for j in compliant:
            joint, _, axis = j.partition(".")
            if joint not in robot.joints or axis not in ("", *TILT_AXES):
                raise ProblemError(
                    f"[calibration].compliant_joints: unknown joint '{j}'; the chain has: "
                    + ", ".join(robot.joints) + f" (a tilt compliance: <joint>.{'/'.join(TILT_AXES)})"
                )
            tilted.append(bool(axis))
            comp_idx.append(kinematics.parameter_names.index(j) if axis else robot.joints.index(joint))
        if not compliant or len(set(compliant)) != len(compliant):
            raise ProblemError(
                f"[calibration].compliant_joints: has {list(compliant)}; list distinct joints among "
                + ", ".join(robot.joints)
            )
        names += [f"k.{j}" for j in compliant]
        f_rows = row_indices(tuple(force), WRENCH_ROWS, "[calibration].wrench_components") \
            if force or not (gravity or seating_N is not None) else ()
    d = len([r for r in m_rows if r < 3]) * len(markers) + len([r for r in m_rows if r >= 3])
    if whitening is not None and np.shape(whitening) != (d, d):
        raise ProblemError(
            f"[measurement]: the noise model is {np.shape(whitening)} but each experiment "
            f"measures {d} values; give one sigma or covariance row per value"
        )
    Wh = ca.DM.eye(d) if whitening is None else ca.DM(np.asarray(whitening, dtype=float))
    lever = np.zeros(3) if load_point_m is None else np.asarray(load_point_m, dtype=float)

    q = ca.SX.sym("q", robot.n)
    F = ca.SX.sym("F", len(f_rows))
    X = ca.SX.sym("X", len(names))
    ref = ca.SX.sym("ref", 12)
    Pi = ca.SX.zeros(len(kinematics.parameter_names))
    for i, g in enumerate(geo_idx):
        Pi[g] = X[i]
    k, kt = ca.SX.zeros(robot.n), ca.SX.zeros(Pi.numel())
    for i, (j, tilt) in enumerate(zip(comp_idx, tilted)):
        (kt if tilt else k)[j] = X[len(geo_idx) + i]
    wrench = ca.SX.zeros(6)
    for i, r in enumerate(f_rows):
        wrench[r] = F[i]
    qs, Pis = ca.SX.sym("qs", robot.n), ca.SX.sym("Pis", Pi.numel())
    jacobian = ca.Function("J", [qs, Pis], [twist_jacobian(*kinematics.placement(qs, Pis), qs)])
    tilts = any(tilted)
    bending = ca.Function("J_Pi", [qs, Pis], [twist_jacobian(*kinematics.placement(qs, Pis), Pis)]) \
        if tilts and (f_rows or seating_N is not None) else None

    def deflected(W: ca.SX, iterations: int) -> tuple[ca.SX, ca.SX, ca.SX]:
        """Pose (R, p) of robot X deflected by W and the last fixed-point update: the joints by
        ``dq = k (J^T W - g)``, the tilts by ``dPi = kt (J_Pi^T W - dV/dPi)`` (``g``, ``dV/dPi``
        with ``gravity`` only)."""
        dq, dPi, step = ca.SX.zeros(robot.n), ca.SX.zeros(Pi.numel()), ca.SX(0)
        if comp_idx:
            for _ in range(iterations):
                tau = jacobian(q + dq, Pi).T @ W
                new = k * (tau - kinematics.gravity_torque(q + dq) if gravity else tau)
                step = ca.mmax(ca.fabs(new - dq))
                if tilts:
                    moment = bending(q + dq, Pi).T @ W if bending is not None else ca.SX.zeros(Pi.numel())
                    bent = kt * (moment - kinematics.gravity_moments(q + dq) if gravity else moment)
                    step = ca.fmax(step, ca.mmax(ca.fabs(bent - dPi)))
                    dPi = bent
                dq = new
        R, p = kinematics.placement(q + dq, Pi + dPi)
        return R, p, step

    def deviation(R: ca.SX, p: ca.SX, rows: tuple[int, ...], points: np.ndarray) -> ca.SX:
        """Position rows of each point (frame coordinates), then orientation rows, from ref."""
        R_ref, p_ref = ca.reshape(ref[0:9], 3, 3), ref[9:12]
        pos = [r for r in rows if r < 3]
        out = [((p + R @ ca.DM(c)) - (p_ref + R_ref @ ca.DM(c)))[pos] for c in points] if pos else []
        rot = [r - 3 for r in rows if r >= 3]
        if rot:
            out.append(_skew_vee(R @ R_ref.T)[rot])
        return ca.vertcat(*out)

    R0, p0 = kinematics.placement(q, Pi)
    W_cal = ca.vertcat(wrench[:3], wrench[3:] + ca.cross(R0 @ ca.DM(lever), wrench[:3]))
    if seating_N is not None:
        W_cal = W_cal + ca.vertcat(ca.DM(np.asarray(seating_N, dtype=float)), ca.DM.zeros(3))

    def measured_values(iterations: int) -> tuple[ca.SX, ca.SX, ca.SX]:
        R, p, step = deflected(W_cal, iterations)
        return Wh @ deviation(R, p, m_rows, markers), step, ca.vertcat(ca.vec(R), p)

    def required_values(iterations: int) -> tuple[ca.SX, ca.SX]:
        R, p, step = deflected(wrench, iterations)
        return deviation(R, p, a_rows, np.zeros((1, 3))), step

    y, y_step, y_pose = measured_values(DEFLECTION_ITERATIONS)
    e, e_step = required_values(DEFLECTION_ITERATIONS)
    c = np.ones(len(names)) if column_scale is None else np.asarray(column_scale, dtype=float)
    Cinv = ca.DM(np.diag(1.0 / c))
    # linearisation at X = 0 about the nominal pose: one deflection iteration is exact there
    X0 = ca.DM.zeros(X.numel())
    ref0 = ca.substitute(ca.vertcat(ca.vec(R0), p0), X, X0)

    def linearised(expr: ca.SX) -> ca.SX:
        J = ca.substitute(ca.substitute(ca.jacobian(expr, X), ref, ref0), X, X0)
        return J @ Cinv

    args, arg_names = [q, F, X, ref], ["q", "F", "X", "ref"]
    return CalibrationModel(
        kinematics=kinematics,
        case=case,
        parameter_names=tuple(names),
        measured_rows=m_rows,
        accuracy_rows=a_rows,
        force_rows=f_rows,
        markers_m=markers,
        column_scale=c,
        pose=ca.Function("pose", [q, F, X], [y_pose], arg_names[:3], ["ref"]),
        measurement=ca.Function("y", args, [y, y_step], arg_names, ["y", "step"]),
        accuracy=ca.Function("e", args, [e, e_step], arg_names, ["e", "step"]),
        B=ca.Function("B", [q, F], [linearised(measured_values(1)[0])], ["q", "F"], ["B"]),
        B0=ca.Function("B0", [q, F], [linearised(required_values(1)[0])], ["q", "F"], ["B0"]),
        position=ca.Function("p", [q], [ref0[9:12]], ["q"], ["p"]),
        points=ca.Function("points", [q], [ref0[9:12] + ca.reshape(ref0[0:9], 3, 3) @ ca.DM(markers.T)],
                           ["q"], ["P"]),
        gravity=gravity,
        seating_N=None if seating_N is None else tuple(float(v) for v in seating_N),
    )
