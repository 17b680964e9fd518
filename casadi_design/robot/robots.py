"""Robot models: Pinocchio models of serial arms, their joint limits and numeric kinematics.

A :class:`Robot` is the fixed description used by every later step: a ``pinocchio.Model``,
the frame whose placement is measured, and the chain of joints that move it (the design
variables ``q``, in that order, rad for revolute and m for prismatic joints).
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..errors import ProblemError

#: Joint types the symbolic translator supports (one configuration variable each).
SUPPORTED_JOINTS = (
    "JointModelRX",
    "JointModelRY",
    "JointModelRZ",
    "JointModelRevoluteUnaligned",
    "JointModelPX",
    "JointModelPY",
    "JointModelPZ",
    "JointModelPrismaticUnaligned",
)

#: Largest joint limit taken as given (rad for a revolute joint, m for a prismatic one): a
#: revolute limit past two turns is a value in degrees, a prismatic one past 100 m in mm.
MAX_LIMIT = {"R": 4 * np.pi, "P": 100.0}


def prismatic(joint: pin.JointModel) -> bool:
    """Whether a joint of :data:`SUPPORTED_JOINTS` is prismatic (PX, PY, PZ, PrismaticUnaligned)."""
    return joint.shortname().startswith("JointModelP")


@dataclass(frozen=True, eq=False)
class Robot:
    """A serial chain to calibrate.

    Attributes
    ----------
    name : str
    model : pinocchio.Model
    frame : str
        Frame whose placement is measured (the tool frame).
    joints : tuple of str
        Joints supporting ``frame``, root first: the order of ``q``.
    q_min, q_max : ndarray, shape (n,)
        Joint limits, rad (revolute) or m (prismatic).
    """

    name: str
    model: pin.Model
    frame: str
    joints: tuple[str, ...]
    q_min: np.ndarray
    q_max: np.ndarray

    @property
    def n(self) -> int:
        """Number of joints in the chain."""
        return len(self.joints)

    @cached_property
    def frame_id(self) -> int:
        return frame_id(self.model, self.frame)

    @cached_property
    def joint_ids(self) -> tuple[int, ...]:
        return tuple(self.model.getJointId(j) for j in self.joints)

    @cached_property
    def q_index(self) -> np.ndarray:
        """Where the chain's joints sit in Pinocchio's configuration (n,)."""
        return np.array([self.model.joints[j].idx_q for j in self.joint_ids], dtype=int)

    @cached_property
    def v_index(self) -> np.ndarray:
        """Where the chain's joints sit in Pinocchio's velocity, the Jacobian's columns (n,)."""
        return np.array([self.model.joints[j].idx_v for j in self.joint_ids], dtype=int)

    @cached_property
    def _neutral(self) -> np.ndarray:
        return pin.neutral(self.model)

    def is_prismatic(self, k: int) -> bool:
        """Whether joint ``k`` of the chain is prismatic (its value in m, not rad)."""
        return prismatic(self.model.joints[self.joint_ids[k]])

    def full_q(self, q: np.ndarray) -> np.ndarray:
        """Pinocchio configuration of the whole model with the chain at ``q`` (others neutral)."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n,):
            raise ValueError(f"full_q: {q.shape} joint values for a chain of {self.n}")
        q_full = self._neutral.copy()
        q_full[self.q_index] = q
        return q_full


def planar_arm(link_lengths_m: list[float] | tuple[float, ...], name: str = "planar") -> pin.Model:
    """Planar serial arm in the x-y plane: revolute joints about z, links along local x.

    Joint ``i`` (named ``joint{i}``) sits at the end of link ``i-1``; the frame ``tool`` sits at
    the end of the last link. At ``q = 0`` the arm is stretched along +x.

    Parameters
    ----------
    link_lengths_m : sequence of float, m
    """
    lengths = [float(v) for v in link_lengths_m]
    model = pin.Model()
    model.name = name
    parent = 0
    offset = 0.0
    for i, length in enumerate(lengths, start=1):
        placement = pin.SE3(np.eye(3), np.array([offset, 0.0, 0.0]))
        parent = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i}")
        offset = length
    model.lowerPositionLimit[:] = -np.pi
    model.upperPositionLimit[:] = np.pi
    tool = pin.SE3(np.eye(3), np.array([offset, 0.0, 0.0]))
    model.addFrame(pin.Frame("tool", parent, tool, pin.FrameType.OP_FRAME))
    return model


@dataclass(frozen=True)
class DHJoint:
    """One row of a Denavit-Hartenberg table (lengths m, angles rad), with Hayati's ``beta``.

    Standard DH (``convention="standard"``):
    ``T_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)``.
    Modified DH (Craig, ``"modified"``): ``T_i = Rx(alpha_i) Tx(a_i) Ry(beta_i) Rz(theta_i) Tz(d_i)``,
    where this row's ``alpha``/``a``/``beta`` are Craig's alpha_{i-1}/a_{i-1}/beta_{i-1}.
    ``theta_i = q_i + theta_offset`` for revolute (R) joints; ``d_i = q_i + d`` for prismatic (P).
    ``beta`` (Hayati, 0 in a plain DH table) tilts the next axis about the common normal's
    perpendicular: with it a nearly parallel pair of axes is described without a large ``d``.
    """

    name: str
    kind: str
    theta_offset: float
    d: float
    a: float
    alpha: float
    lower: float
    upper: float
    beta: float = 0.0


def _rz(t: float) -> pin.SE3:
    return pin.SE3(pin.AngleAxis(t, np.array([0.0, 0, 1])).matrix(), np.zeros(3))


def _rx(t: float) -> pin.SE3:
    return pin.SE3(pin.AngleAxis(t, np.array([1.0, 0, 0])).matrix(), np.zeros(3))


def _ry(t: float) -> pin.SE3:
    return pin.SE3(pin.AngleAxis(t, np.array([0.0, 1, 0])).matrix(), np.zeros(3))


def _tz(d: float) -> pin.SE3:
    return pin.SE3(np.eye(3), np.array([0.0, 0, d]))


def _tx(a: float) -> pin.SE3:
    return pin.SE3(np.eye(3), np.array([a, 0.0, 0]))


def dh_joint(theta: float, d: float) -> pin.SE3:
    """``Rz(theta) Tz(d)``: along one joint axis (theta rad, d m)."""
    return _rz(theta) * _tz(d)


def dh_link(a: float, alpha: float, beta: float = 0.0) -> pin.SE3:
    """``Tx(a) Rx(alpha) Ry(beta)``: from one joint axis to the next (a m, angles rad)."""
    return _tx(a) * _rx(alpha) * _ry(beta)


def dh_arm(
    rows: list[DHJoint], convention: str, tool: pin.SE3 | None = None, name: str = "dh",
    base: pin.SE3 | None = None,
) -> pin.Model:
    """Serial arm from a DH table: joints about / along local z, frame ``flange`` after the last row.

    ``base`` is the placement of the DH frame 0 in the world (identity by default), ``tool`` the
    flange-to-tool placement after the last row (identity by default). Joint ``i``'s frame is
    the frame of its ``Rz(theta_i)`` (revolute) or ``Rz(theta_i) Tz(d_i)`` (prismatic): in both
    conventions the chain is ``base [link_0] prod_i [Rz(theta_i) Tz(d_i) link_i] tool`` with
    ``link = dh_link(a, alpha, beta)`` of row i (standard) or row i+1 (modified).
    """
    if convention not in ("standard", "modified"):
        raise ProblemError(f"[robot.dh].convention: '{convention}'; allowed: standard, modified")
    model = pin.Model()
    model.name = name
    parent, pending = 0, base or pin.SE3.Identity()
    for row in rows:
        if row.kind not in ("R", "P"):
            raise ProblemError(f"[robot.dh].joints: joint '{row.name}' has type '{row.kind}'; allowed: R, P")
        # the joint moves at Rz(theta) (R) or at Tz(d) (P): what comes before it is fixed
        head = dh_joint(row.theta_offset, 0.0 if row.kind == "R" else row.d)
        tail = _tz(row.d) if row.kind == "R" else pin.SE3.Identity()
        link = dh_link(row.a, row.alpha, row.beta)
        if convention == "standard":
            placement, after = pending * head, tail * link
        else:
            placement, after = pending * link * head, tail
        joint = pin.JointModelRZ() if row.kind == "R" else pin.JointModelPZ()
        parent = model.addJoint(parent, joint, placement, row.name)
        model.lowerPositionLimit[model.joints[parent].idx_q] = row.lower
        model.upperPositionLimit[model.joints[parent].idx_q] = row.upper
        pending = after
    model.addFrame(pin.Frame("flange", parent, pending * (tool or pin.SE3.Identity()), pin.FrameType.OP_FRAME))
    return model


def placement_from_xyz_rpy(xyz_m, rpy_rad) -> pin.SE3:
    """``SE3`` from a translation (m) and roll-pitch-yaw angles (rad), URDF convention."""
    return pin.SE3(pin.rpy.rpyToMatrix(*(float(v) for v in rpy_rad)), np.asarray(xyz_m, dtype=float))


def frame_id(model: pin.Model, name: str) -> int:
    """The id of the frame ``name``: the URDF link's where a joint bears its name
    too (Pinocchio's ``getFrameId`` refuses the ambiguity): Unitree Z1's ``gripperStator``, the
    fixed joint that carries the link, at its place; SO-100's ``gripper``, the jaw's joint, 3 cm
    from the link's frame; ``[robot] frame`` names a link.

    Raises
    ------
    ProblemError
        A frame the model does not have (the message lists those it has).
    """
    ids = [i for i, f in enumerate(model.frames) if f.name == name]
    if not ids:
        names = [f.name for f in model.frames if f.name != "universe"]
        raise ProblemError(f"[robot].frame: unknown frame '{name}'; the model has: {', '.join(names)}")
    return next((i for i in ids if model.frames[i].type == pin.FrameType.BODY), ids[0])


def add_tool_frame(model: pin.Model, frame: str, placement: pin.SE3, name: str = "tcp") -> str:
    """Add a tool frame ``name`` at ``placement`` relative to ``frame``; returns its name."""
    parent = model.frames[frame_id(model, frame)]
    if model.existFrame(name):
        raise ProblemError(f"[robot].tool_xyz_m: the model already has a frame '{name}'; set [robot].frame to it instead")
    model.addFrame(pin.Frame(name, parent.parentJoint, parent.placement * placement, pin.FrameType.OP_FRAME))
    return name


def example_robot_data_dir() -> Path:
    """Folder of the URDFs shipped by the ``example-robot-data`` wheel (no download)."""
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        raise ProblemError(
            "[robot].urdf: example-robot-data is not installed; pip install example-robot-data"
        ) from None
    root = Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")))
    if not root.is_dir():
        raise ProblemError(
            f"example-robot-data is installed but its robots folder {root} is missing; "
            "reinstall it with: pip install --force-reinstall example-robot-data"
        )
    return root


def urdf_file(path: str | Path) -> Path:
    """The file of a URDF path: ``example-robot-data:<relative path>`` or a file path."""
    text, prefix = str(path), "example-robot-data:"
    return example_robot_data_dir() / text[len(prefix):] if text.startswith(prefix) else Path(text)


def load_urdf(path: str | Path, revolute: Mapping[str, tuple[float, float]] | None = None) -> pin.Model:
    """Load a URDF into a ``pinocchio.Model`` (kinematics only).

    ``path`` is a file path, or ``example-robot-data:<relative path>`` for a URDF shipped by
    the example-robot-data package, e.g. ``example-robot-data:ur_description/urdf/ur10_robot.urdf``.
    A continuous joint named in ``revolute`` (joint -> (lower, upper), rad: the problem file's
    ``[robot.joint_limits_rad]``) is read as a revolute joint with those limits (Kinova's URDFs
    declare their unlimited joints continuous; Pinocchio gives them two coordinates, cos and sin).
    """
    file = urdf_file(path)
    if not file.is_file():
        raise ProblemError(f"[robot].urdf: file {file} does not exist; give a URDF path")
    text = _revolute_text(file, revolute) if revolute else None
    with _captured_stderr() as said:
        try:
            model = pin.buildModelFromUrdf(str(file)) if text is None else pin.buildModelFromXML(text)
        except (RuntimeError, ValueError) as exc:
            model, error = None, str(exc).strip()
    if model is None:
        # the URDF parser prints its reason on the C++ stderr before raising a vaguer error
        said_lines = [re.sub(r"^Error:\s*|\s*at line \d+ in \S+$", "", ln.strip()) for ln in said()]
        reason = "; ".join(ln for ln in said_lines if ln) or error
        raise ProblemError(f"[robot].urdf: Pinocchio cannot read {file} ({reason}); fix the URDF")
    return model


def _revolute_text(file: Path, revolute: Mapping[str, tuple[float, float]]) -> str | None:
    """The URDF ``file`` with its continuous joints named in ``revolute`` made revolute with
    those limits (rad; the ``<limit>``'s effort and velocity kept, 0 where absent: no speed
    known); None when it has none of them, or cannot be parsed (Pinocchio then says why)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(file).getroot()
    except ET.ParseError:
        return None
    changed = False
    for joint in root.iter("joint"):
        if joint.get("type") == "continuous" and joint.get("name") in revolute:
            lower, upper = revolute[joint.get("name")]
            limit = joint.find("limit")
            if limit is None:
                limit = ET.SubElement(joint, "limit")
            limit.set("lower", repr(float(lower)))
            limit.set("upper", repr(float(upper)))
            limit.attrib.setdefault("effort", "0")
            limit.attrib.setdefault("velocity", "0")
            joint.set("type", "revolute")
            changed = True
    return ET.tostring(root, encoding="unicode") if changed else None


@contextlib.contextmanager
def _captured_stderr() -> Iterator[Callable[[], list[str]]]:
    """Capture what C++ code writes to file descriptor 2 (not only Python's ``sys.stderr``)."""
    sys.stderr.flush()
    saved = os.dup(2)
    lines: list[str] = []
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield lambda: lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            lines += tmp.read().decode("utf-8", "replace").splitlines()


def joint_kind_for_people(shortname: str) -> str:
    """``JointModelRUBZ`` -> "a continuous joint (revolute without limits, about z)" and so on."""
    axis = shortname[-1].lower() if shortname[-1] in "XYZ" else ""
    about = f", about {axis}" if axis else ""
    kinds = {"JointModelRUB": "a continuous joint (revolute without limits{})",
             "JointModelFreeFlyer": "a floating joint (6 degrees of freedom){}",
             "JointModelSpherical": "a spherical joint (3 degrees of freedom){}",
             "JointModelPlanar": "a planar joint (3 degrees of freedom){}",
             "JointModelTranslation": "a translation joint (3 degrees of freedom){}",
             "JointModelHelical": "a helical joint{}"}
    for prefix, text in kinds.items():
        if shortname.startswith(prefix):
            return text.format(about)
    return f"a joint of type {shortname.removeprefix('JointModel')}"


def make_robot(
    model: pin.Model,
    frame: str,
    joint_limits: dict[str, tuple[float, float]] | None = None,
    name: str | None = None,
) -> Robot:
    """Wrap a Pinocchio model as a :class:`Robot` measured at ``frame``.

    Parameters
    ----------
    joint_limits : dict joint name -> (lower, upper), rad or m
        Overrides the model's limits for the named joints.
    """
    parent = model.frames[frame_id(model, frame)].parentJoint
    chain = [j for j in model.supports[parent] if j != 0]
    for jid in chain:
        joint = model.joints[jid]
        kind = joint.shortname()
        if kind not in SUPPORTED_JOINTS:
            fix = (f"give its limits in [robot.joint_limits_rad], e.g. {model.names[jid]} = [-6.2832, 6.2832] (read as "
                   "a revolute joint), or declare it revolute" if kind.startswith("JointModelRUB") else "declare it "
                   "revolute (or prismatic)")
            raise ProblemError(
                f"[robot]: joint '{model.names[jid]}' is {joint_kind_for_people(kind)}; the chain to "
                f"'{frame}' may hold revolute and prismatic joints with limits only; {fix} with "
                "<limit lower=... upper=...> in the URDF"
            )
        if kind.endswith("Unaligned"):
            axis = np.asarray(joint.extract().axis, dtype=float)
            if not (np.all(np.isfinite(axis)) and np.linalg.norm(axis) > 0):
                raise ProblemError(f"[robot]: joint '{model.names[jid]}' has the axis {axis.tolist()} of zero "
                                   "length; give its <axis xyz=...> a non-zero direction in the URDF")
    joints = tuple(model.names[j] for j in chain)
    idx = [model.joints[j].idx_q for j in chain]
    q_min = np.array(model.lowerPositionLimit[idx], dtype=float)
    q_max = np.array(model.upperPositionLimit[idx], dtype=float)
    for jname, bounds in (joint_limits or {}).items():
        if jname not in joints:
            raise ProblemError(
                f"[robot.joint_limits_rad]: unknown joint '{jname}'; the chain to '{frame}' has: "
                + ", ".join(joints)
            )
        lo, hi = (float(b) for b in bounds)
        if not lo < hi:
            raise ProblemError(f"[robot.joint_limits_rad].{jname}: lower {lo} must be below upper {hi}; "
                               "give [lower, upper]")
        k = joints.index(jname)
        revolute = not prismatic(model.joints[chain[k]])
        if max(abs(lo), abs(hi)) > MAX_LIMIT["R" if revolute else "P"]:
            raise ProblemError(
                f"[robot.joint_limits_rad].{jname}: [{lo:g}, {hi:g}] is past "
                + (f"two turns: give rad, e.g. [{np.deg2rad(lo):.4g}, {np.deg2rad(hi):.4g}] for [{lo:g}, {hi:g}] deg"
                   if revolute else f"100 m: give m, e.g. [{lo / 1e3:.4g}, {hi / 1e3:.4g}] for [{lo:g}, {hi:g}] mm"))
        q_min[k], q_max[k] = lo, hi
    bad = [j for j, lo, hi in zip(joints, q_min, q_max) if not (np.isfinite(lo) and np.isfinite(hi))]
    if bad:
        raise ProblemError(
            f"[robot.joint_limits_rad]: joints {', '.join(bad)} have no finite limits in the model; "
            "give them in [robot.joint_limits_rad] as name = [lower, upper]"
        )
    return Robot(name or model.name, model, frame, joints, q_min, q_max)


def frame_placement(robot: Robot, q: np.ndarray) -> pin.SE3:
    """Numeric placement of ``robot.frame`` at chain configuration ``q`` (Pinocchio)."""
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.full_q(q))
    return data.oMf[robot.frame_id]


def frame_jacobian(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Numeric 6 x n Jacobian of ``robot.frame``, world-aligned at the frame origin (Pinocchio).

    Rows are (vx, vy, vz, wx, wy, wz); columns follow ``robot.joints``.
    """
    data = robot.model.createData()
    J = pin.computeFrameJacobian(
        robot.model, data, robot.full_q(q), robot.frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )
    return np.asarray(J[:, robot.v_index])


def planar_2r_ik(robot: Robot, point_m: np.ndarray, elbow: str) -> np.ndarray:
    """Closed-form inverse kinematics of a two-link planar arm built by :func:`planar_arm`.

    Parameters
    ----------
    point_m : ndarray, shape (2,), m
        Target (x, y) of the tool frame.
    elbow : {"up", "down"}
        Branch: "up" gives q2 <= 0 (elbow on the left of the base-to-tool line, seen from +z),
        "down" gives q2 >= 0.

    Returns
    -------
    q : ndarray, shape (2,), rad
    """
    if robot.n != 2:
        raise ProblemError(
            f"[test_poses]: Cartesian test points need a two-link planar arm; '{robot.name}' has "
            f"{robot.n} joints; give joint-space test poses instead"
        )
    l1 = float(robot.model.jointPlacements[robot.joint_ids[1]].translation[0])
    l2 = float(robot.model.frames[robot.frame_id].placement.translation[0])
    x, y = (float(v) for v in point_m)
    c2 = (x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    if abs(c2) > 1 + 1e-12:
        r = np.hypot(x, y)
        raise ProblemError(
            f"[test_poses]: point ({x * 1e3:.1f}, {y * 1e3:.1f}) mm is out of reach: distance "
            f"{r * 1e3:.1f} mm, reachable {abs(l1 - l2) * 1e3:.1f} to {(l1 + l2) * 1e3:.1f} mm"
        )
    sign = {"up": -1.0, "down": 1.0}[elbow]
    q2 = sign * np.arccos(np.clip(c2, -1.0, 1.0))
    q1 = np.arctan2(y, x) - np.arctan2(l2 * np.sin(q2), l1 + l2 * np.cos(q2))
    q1 = (q1 + np.pi) % (2 * np.pi) - np.pi
    return np.array([q1, q2])
