"""``calibrated.toml``: the problem file of the calibrated robot, which every command accepts.

It is the measured problem's file with the robot replaced by ``calibrated.urdf`` (measured
frame ``measured_point``, which holds the identified tool point) and the test poses given by
their joint values (those of the problem: the next design is computed at the new estimate for
the same robot motions), machining wrenches per pose. Capsules on the old measured frame move
to ``measured_point``; a DH robot's kinematic URDF has no meshes, so its capsules stay those
of the file (``capsules_per_link = 0``).
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

from ..build import Problem
from .urdf import MEASURED_POINT

#: The [test_poses] fields that describe the poses or their wrenches, replaced by joints_rad
#: and forces_N.
POSE_FIELDS = ("joints_rad", "points_m", "line_m", "path", "tool_rpy_deg", "seed_q_deg", "elbow",
               "force_N", "forces_N", "segment_forces_N")


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def _value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    return "[" + ", ".join(_value(x) for x in v) + "]"


def toml_text(record: dict, header: str = "") -> str:
    """TOML of nested dicts (tables), lists (arrays, lists of dicts as inline tables) and
    scalars (strings, numbers, booleans)."""
    lines: list[str] = [f"# {ln}" for ln in header.splitlines()]

    def table(d: dict, name: str) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        if name and (scalars or not d):
            lines.extend(["", f"[{name}]"])
        lines.extend(f"{_key(k)} = {_value(v)}" for k, v in scalars.items())
        for k, v in d.items():
            if isinstance(v, dict):
                table(v, f"{name}.{_key(k)}" if name else _key(k))

    table(record, "")
    return "\n".join(lines) + "\n"


def calibrated_problem(problem: Problem, urdf: Path) -> dict:
    """The table of ``calibrated.toml`` (module docstring); ``urdf``: the calibrated URDF."""
    record = tomllib.loads(Path(problem.path).read_text(encoding="utf-8"))
    source = problem.spec.robot.source
    robot = {"urdf": str(Path(urdf).resolve()), "frame": MEASURED_POINT}
    if "joint_limits_rad" in record.get("robot", {}):
        robot["joint_limits_rad"] = record["robot"]["joint_limits_rad"]
    record["robot"] = robot
    record["name"] = f"{problem.name}_calibrated"
    tp = problem.test_poses
    poses = {k: v for k, v in record["test_poses"].items() if k not in POSE_FIELDS}
    poses["joints_rad"] = tp.q.tolist()
    if problem.model.nF:
        poses["forces_N"] = tp.F.tolist()
    record["test_poses"] = poses
    cell = record.get("cell")
    if cell is not None:
        old = problem.robot.frame
        cell["capsules"] = [{**c, "frame": MEASURED_POINT if c.get("frame") == old else c["frame"]}
                            for c in cell.get("capsules", [])]
        if source != "urdf":
            cell.pop("collision_urdf", None)
            cell["capsules_per_link"] = 0
    return record
