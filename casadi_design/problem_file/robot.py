"""``[robot]``: a planar arm, a URDF or a DH table, its measured frame and tool, joint limits and
speeds, and the controller's joint conventions."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .fields import TableReader, Vec, short, to_vec

#: Hayati's angle beta of a DH row lies strictly within +/- this (deg): only there does a
#: direction of the next axis have one (alpha, beta) pair.
MAX_BETA_DEG = 90.0

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "robot": {"planar_links_m", "urdf", "dh", "frame", "tool_xyz_m", "tool_rpy_deg", "joint_limits_rad",
              "joint_speeds_deg_s", "controller", "inertias_urdf"},
    "robot.controller": {"signs", "offsets_deg", "acceleration_time_s"},
    "robot.dh": {"convention", "joints", "base_xyz_m", "base_rpy_deg", "flange_xyz_m", "flange_rpy_deg"},
    "robot.dh.joints": {"name", "type", "theta_offset_deg", "d_m", "a_m", "alpha_deg", "beta_deg", "limits_deg"},
    "robot.joint_limits_rad": None,
}


@dataclass(frozen=True)
class DHRow:
    """One row of a Denavit-Hartenberg table (lengths m, angles rad), ``beta_rad`` Hayati's
    rotation about y (0 in a plain DH row); see ``robots.DHJoint``."""

    name: str
    kind: str
    theta_offset_rad: float
    d_m: float
    a_m: float
    alpha_rad: float
    lower: float
    upper: float
    beta_rad: float = 0.0


@dataclass(frozen=True)
class ControllerSpec:
    """The robot controller's joint conventions, as in the file: controller angle ``= sign_k
    q_k + offset_k`` (``q`` the model's joint angle) per joint of the chain, ``offsets_deg`` in
    deg (mm for prismatic joints; None: +1 and 0 for every joint); each joint reaches its full
    speed in ``acceleration_time_s``. Converted to SI, and checked against the chain, by
    :func:`casadi_design.program.order.time_model` and :func:`casadi_design.program.formats.controller`."""

    signs: Vec | None = None
    offsets_deg: Vec | None = None
    acceleration_time_s: float = 0.5


@dataclass(frozen=True)
class RobotSpec:
    """The robot of a case: one of a planar arm, a URDF or a DH table, and its measured frame.

    ``urdf`` is an absolute path or ``example-robot-data:<relative path>``. ``tool_xyz_m`` /
    ``tool_rpy_rad`` (None when not given) add a tool frame after ``frame``. A DH table's DH
    frame 0 sits at (``base_xyz_m``, ``base_rpy_rad``) in the world, its frame ``flange`` at
    (``flange_xyz_m``, ``flange_rpy_rad``) after the last row.
    ``joint_limits_rad`` overrides limits as (joint, lower, upper), rad or m.
    ``inertias_urdf``: a URDF of the same robot (same joint names) whose links' masses and
    inertias replace those of ``urdf`` (a kinematic URDF without them), for the joints' load
    under the robot's own weight; "" for none.
    ``joint_speeds_deg_s`` (one per joint, deg/s or mm/s as in the file; None: the URDF's
    velocity limits) and
    ``controller`` (None: identity, acceleration time ``ControllerSpec.acceleration_time_s``)
    are what the robot programs of :mod:`casadi_design.program` need.
    """

    frame: str
    planar_links_m: Vec = ()
    urdf: str = ""
    dh_convention: str = ""
    dh_rows: tuple[DHRow, ...] = ()
    base_xyz_m: Vec = (0.0, 0.0, 0.0)
    base_rpy_rad: Vec = (0.0, 0.0, 0.0)
    flange_xyz_m: Vec = (0.0, 0.0, 0.0)
    flange_rpy_rad: Vec = (0.0, 0.0, 0.0)
    tool_xyz_m: Vec | None = None
    tool_rpy_rad: Vec | None = None
    inertias_urdf: str = ""
    joint_limits_rad: tuple[tuple[str, float, float], ...] = ()
    joint_speeds_deg_s: Vec | None = None
    controller: ControllerSpec | None = None

    @property
    def source(self) -> str:
        return "planar" if self.planar_links_m else "urdf" if self.urdf else "dh"


def read_robot(r: TableReader) -> RobotSpec:
    frame = r.get("frame", str, hint="the measured frame, e.g. frame = \"tool\"")
    given = [k for k in ("planar_links_m", "urdf", "dh") if k in r.table]
    if len(given) != 1:
        raise r.error(f"has {given or 'none'} of planar_links_m, urdf, dh", "give exactly one, e.g. "
                      "planar_links_m = [0.6, 0.4] or urdf = \"example-robot-data:ur_description/urdf/ur10_robot.urdf\"")
    spec: dict[str, Any] = {}
    if given[0] == "planar_links_m":
        links = r.array("planar_links_m", (None,), hint="link lengths in m")
        if len(links) == 0 or np.any(links <= 0):
            raise r.error(f"expected positive link lengths, got {links.tolist()}", "lengths in m", "planar_links_m")
        spec["planar_links_m"] = to_vec(links)
    elif given[0] == "urdf":
        urdf = r.get("urdf", str)
        if not urdf.strip():
            raise r.error("is empty", "give the URDF path", "urdf")
        if not urdf.startswith("example-robot-data:") and not Path(urdf).is_absolute():
            urdf = str(Path(r.path).parent / urdf)
        spec["urdf"] = urdf
        inertias = r.get("inertias_urdf", str, "", hint="a URDF of the same robot whose links carry masses")
        if inertias and not inertias.startswith("example-robot-data:") and not Path(inertias).is_absolute():
            inertias = str(Path(r.path).parent / inertias)
        spec["inertias_urdf"] = inertias
    else:
        spec.update(_dh(r.sub("dh")))
    if "tool_xyz_m" in r.table or "tool_rpy_deg" in r.table:
        spec["tool_xyz_m"] = to_vec(r.array("tool_xyz_m", (3,), np.zeros(3), hint="(x, y, z) in m"))
        spec["tool_rpy_rad"] = to_vec(np.radians(r.array("tool_rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw in deg")))
    lt = r.sub("joint_limits_rad")
    limits = []
    for j in (lt.table if lt else {}):
        lo, hi = lt.array(j, (2,), hint="[lower, upper] in rad (m for prismatic joints)")
        if not lo < hi:
            raise lt.error(f"lower {lo} must be below upper {hi}", "give [lower, upper]", j)
        limits.append((j, float(lo), float(hi)))
    speeds = r.array("joint_speeds_deg_s", (None,), None, hint="one speed per joint in deg/s (mm/s for prismatic joints)")
    if speeds is not None and not np.all(speeds > 0):
        raise r.error(f"must be positive, got {speeds.tolist()}", "give each joint's largest speed in deg/s",
                      "joint_speeds_deg_s")
    return RobotSpec(frame=frame, joint_limits_rad=tuple(limits), **spec,
                     joint_speeds_deg_s=to_vec(speeds),
                     controller=_controller(r.sub("controller")))


def _controller(c: TableReader | None) -> ControllerSpec | None:
    """``[robot.controller]``: joint signs (+1 / -1), offsets (deg), acceleration time (s);
    their lengths are checked against the chain when a program is made."""
    if c is None:
        return None
    signs = c.array("signs", (None,), None, hint="+1 or -1 per joint, e.g. [1, 1, -1, 1, -1, 1]")
    if signs is not None and not np.all(np.abs(signs) == 1):
        raise c.error(f"must be +1 or -1, got {signs.tolist()}", "give +1 or -1 per joint", "signs")
    offsets = c.array("offsets_deg", (None,), None, hint="one offset per joint in deg (mm for prismatic joints)")
    return ControllerSpec(to_vec(signs), to_vec(offsets),
                          c.number("acceleration_time_s", ControllerSpec.acceleration_time_s,
                                   hint="the time a joint takes to reach its full speed, s", positive=True))


def _dh(d: TableReader) -> dict:
    convention = d.get("convention", str, hint="standard or modified")
    if convention not in ("standard", "modified"):
        raise d.error(f"'{convention}'", "allowed: standard, modified", "convention")
    rows_raw = d.get("joints", list, hint="one table per joint: { name, type, theta_offset_deg, d_m, a_m, alpha_deg, limits_deg }")
    optional = {"beta_deg"}
    if not rows_raw:
        raise d.error("is empty", "give one row per joint", "joints")
    rows = []
    for k, row in enumerate(rows_raw):
        if not isinstance(row, dict):
            raise d.error(f"row {k + 1} is {short(row)}", "write each row as an inline table { name = ..., ... }", "joints")
        j = d.row(row, "robot.dh.joints", f"robot.dh.joints[{k + 1}]")
        missing = sorted(KEYS["robot.dh.joints"] - optional - set(row))
        if missing:
            raise j.error(f"misses {', '.join(missing)}", "every row needs name, type (R), theta_offset_deg, d_m, a_m, alpha_deg, limits_deg "
                          "(beta_deg is optional)")
        given = j.array("limits_deg", (2,), hint="[lower, upper] in deg")
        lo, hi = np.radians(given)
        if not lo < hi:
            raise j.error(f"lower {np.degrees(lo):g} must be below upper {np.degrees(hi):g}", "give [lower, upper] in deg", "limits_deg")
        if given[1] - given[0] <= 2 * math.pi:  # a joint's range of a few degrees: radians typed as degrees
            raise j.error(f"{given.tolist()} spans {given[1] - given[0]:.3g} deg", "give degrees, e.g. "
                          f"[{math.degrees(given[0]):.4g}, {math.degrees(given[1]):.4g}] for {given.tolist()} rad",
                          "limits_deg")
        kind = j.get("type", str)
        if kind != "R":
            raise j.error(f"'{kind}'", "allowed: R (describe prismatic axes in a URDF)", "type")
        beta = j.number("beta_deg", 0.0, hint="Hayati's rotation about y in deg, for nearly parallel axes")
        if not abs(beta) < MAX_BETA_DEG:
            raise j.error(f"is {beta:g}", f"give an angle strictly between -{MAX_BETA_DEG:g} and {MAX_BETA_DEG:g} deg",
                          "beta_deg")
        rows.append(DHRow(j.get("name", str), kind, math.radians(j.get("theta_offset_deg", float)), j.get("d_m", float),
                          j.get("a_m", float), math.radians(j.get("alpha_deg", float)), float(lo), float(hi),
                          math.radians(beta)))
    names = [row.name for row in rows]
    if len(set(names)) != len(names):
        raise d.error(f"has repeated joint names {names}", "name each joint once", "joints")
    return {"dh_convention": convention, "dh_rows": tuple(rows),
            "base_xyz_m": to_vec(d.array("base_xyz_m", (3,), np.zeros(3), hint="(x, y, z) in m")),
            "base_rpy_rad": to_vec(np.radians(d.array("base_rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw in deg"))),
            "flange_xyz_m": to_vec(d.array("flange_xyz_m", (3,), np.zeros(3), hint="(x, y, z) in m")),
            "flange_rpy_rad": to_vec(np.radians(d.array("flange_rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw in deg")))}
