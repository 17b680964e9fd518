"""The calibrated robot for any URDF reader, and as a problem file every command accepts.

The identified errors ``Pi`` enter the kinematics as (:mod:`casadi_design.robot.symbolic`)

    oMf = E(Pi_base) prod_k [ M_k E(Pi_k) X_k(q_k + offset_k) ] fMt E(Pi_tool)

so the calibrated joint placement of chain joint k is ``M_k' = M_k E(Pi_k) Z_k(offset_k)``
(``Z_k``: the joint's own motion by its offset, so a joint-zero offset becomes a rotation of the
origin about the joint axis), with ``E(Pi_base)`` in front of the first one, and the measured
frame sits at ``fMt' = fMt E(Pi_tool)`` on the last joint. In a URDF, Pinocchio's ``M_k`` is
``A_k O_k`` (``A_k``: the fixed joints from the previous joint's link, ``O_k``: the joint's
``<origin>``), so the corrected ``<origin>`` is ``A_k^-1 M_k'`` (FIGAROH's approach: errors in
the origins, never in the ``<calibration>`` tag that drivers ignore). A URDF robot keeps its
file (links, meshes, inertias, limits) with corrected origins; a DH or planar robot gets a
kinematic URDF of its chain. Either has fixed frames ``measured_point`` (and ``marker_1``...).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..problem.build import Problem
from ..robot.robots import Robot, urdf_file
from ..robot.symbolic import joint_axis
from ..identification.fit import error_placement

#: Name of the fixed frame at the identified measured point; markers are ``marker_<i>``.
MEASURED_POINT = "measured_point"


@dataclass(frozen=True, eq=False)
class CalibratedChain:
    """Calibrated placements: ``joints[k]`` = ``M_k'`` (SE3, relative to joint k-1's frame),
    ``tool`` = ``fMt'`` (relative to the last joint's frame)."""

    joints: tuple[pin.SE3, ...]
    tool: pin.SE3


def _se3(T: np.ndarray) -> pin.SE3:
    return pin.SE3(T[:3, :3].copy(), T[:3, 3].copy())


def calibrated_chain(problem: Problem, names: tuple[str, ...], X: np.ndarray) -> CalibratedChain:
    """The calibrated placements for the geometric errors ``names`` = ``X`` (m, rad; others 0)."""
    robot = problem.robot
    Pi = dict(zip(names, np.asarray(X, dtype=float)))

    def E(owner: str) -> pin.SE3:
        return _se3(error_placement([Pi.get(f"{owner}.{e}", 0.0) for e in ("tx", "ty", "tz", "rx", "ry", "rz")]))

    joints = []
    for k, (name, jid) in enumerate(zip(robot.joints, robot.joint_ids)):
        axis, kind = joint_axis(robot.model.joints[jid])
        offset = Pi.get(f"{name}.offset", 0.0)
        Z = (pin.SE3(pin.exp3(axis * offset), np.zeros(3)) if kind == "R"
             else pin.SE3(np.eye(3), axis * offset))
        M = robot.model.jointPlacements[jid] * E(name) * Z
        joints.append(E("base") * M if k == 0 else M)
    return CalibratedChain(tuple(joints), robot.model.frames[robot.frame_id].placement * E("tool"))


def calibrated_model(robot: Robot, chain: CalibratedChain) -> pin.Model:
    """The robot's Pinocchio model with the calibrated placements (for checks)."""
    model = pin.Model(robot.model)
    for jid, M in zip(robot.joint_ids, chain.joints):
        model.jointPlacements[jid] = M
    frame = model.frames[robot.frame_id]
    frame.placement = chain.tool
    model.frames[robot.frame_id] = frame
    return model


def _origin(element: ET.Element, M: pin.SE3) -> None:
    """Set the ``<origin>`` of a URDF joint element to ``M`` (xyz m, rpy rad, full precision)."""
    origin = element.find("origin")
    if origin is None:
        origin = ET.SubElement(element, "origin")
    origin.set("xyz", " ".join(repr(float(v)) for v in M.translation))
    origin.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(M.rotation)))


def _read_origin(element: ET.Element) -> pin.SE3:
    origin = element.find("origin")
    xyz = np.zeros(3) if origin is None else np.array([float(v) for v in origin.get("xyz", "0 0 0").split()])
    rpy = np.zeros(3) if origin is None else np.array([float(v) for v in origin.get("rpy", "0 0 0").split()])
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def _fixed_frames(problem: Problem, chain: CalibratedChain, parent: str, root: ET.Element) -> None:
    """Fixed frames ``measured_point`` (and ``marker_<i>``) on the link ``parent``."""
    frames = [(MEASURED_POINT, chain.tool)]
    if problem.spec.measurement.markers_m is not None:
        frames += [(f"marker_{i + 1}", chain.tool * pin.SE3(np.eye(3), c))
                   for i, c in enumerate(problem.model.markers_m)]
    for name, M in frames:
        ET.SubElement(root, "link", name=name)
        joint = ET.SubElement(root, "joint", name=f"{name}_joint", type="fixed")
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=name)
        _origin(joint, M)


def _absolute_meshes(root: ET.Element, source: Path, dirs: list[Path]) -> None:
    """Mesh file names resolved to absolute paths, so that the file works from any folder."""
    for mesh in root.iter("mesh"):
        name = mesh.get("filename", "")
        if name.startswith("package://"):
            found = next((d / name[len("package://"):] for d in dirs if (d / name[len("package://"):]).is_file()), None)
            if found is not None:
                mesh.set("filename", str(found.resolve()))
        elif name and not name.startswith(("/", "file://")):
            mesh.set("filename", str((source.parent / name).resolve()))


def urdf_text(problem: Problem, chain: CalibratedChain) -> str:
    """The calibrated URDF (module docstring)."""
    robot = problem.robot
    if problem.spec.robot.source == "urdf":
        from ..cell.cell import _package_dirs  # where package:// meshes of this URDF are found

        source = urdf_file(problem.spec.robot.urdf)
        tree = ET.parse(source)
        root = tree.getroot()
        elements = {j.get("name"): j for j in root.findall("joint")}
        for name, jid, M_new in zip(robot.joints, robot.joint_ids, chain.joints):
            element = elements[name]
            A = robot.model.jointPlacements[jid] * _read_origin(element).inverse()
            _origin(element, A.inverse() * M_new)
        parent = elements[robot.joints[-1]].find("child").get("link")
        _absolute_meshes(root, source, _package_dirs(problem.spec.robot.urdf))
    else:
        root = ET.Element("robot", name=f"{robot.name}_calibrated")
        parent = "base_link"
        ET.SubElement(root, "link", name=parent)
        for k, (name, jid, M_new) in enumerate(zip(robot.joints, robot.joint_ids, chain.joints)):
            axis, kind = joint_axis(robot.model.joints[jid])
            joint = ET.SubElement(root, "joint", name=name, type="revolute" if kind == "R" else "prismatic")
            child = f"{name}_link"
            ET.SubElement(root, "link", name=child)
            ET.SubElement(joint, "parent", link=parent)
            ET.SubElement(joint, "child", link=child)
            _origin(joint, M_new)
            ET.SubElement(joint, "axis", xyz=" ".join(repr(float(v)) for v in axis))
            ET.SubElement(joint, "limit", lower=repr(float(robot.q_min[k])), upper=repr(float(robot.q_max[k])),
                          effort="0", velocity="0")
            parent = child
    _fixed_frames(problem, chain, parent, root)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"
