"""``calibrated.toml`` and ``calibrated_dh.toml``: problem files of the calibrated robot, which
every command accepts.

Both are the measured problem's file with the test poses given by their joint values (those of
the problem: the next design is computed at the new estimate for the same robot motions),
machining wrenches per pose. In ``calibrated.toml`` the robot is ``calibrated.urdf`` (measured
frame ``measured_point``, which holds the identified tool point); capsules on the old measured
frame move to ``measured_point``, and a DH robot's kinematic URDF has no meshes, so its
capsules stay those of the file (``capsules_per_link = 0``). In ``calibrated_dh.toml`` (DH
robots) the robot keeps its fields and frames and gets the calibrated table
(:mod:`.dh_table`), so the cell stays as it is (``collision_urdf`` relative to the folder
written). The measured points are those fitted (identify locates points far off).
"""

from __future__ import annotations

import json
import math
import os
import re
import tomllib
from pathlib import Path

from ..problem.build import Problem
from ..problem_file.robot import RobotSpec
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


def _entry(k: str, v: object) -> str:
    """``k = v``; an array of inline tables one table per line."""
    if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
        return f"{_key(k)} = [\n" + "".join(f"  {_value(x)},\n" for x in v) + "]"
    return f"{_key(k)} = {_value(v)}"


def toml_text(record: dict, header: str = "") -> str:
    """TOML of nested dicts (tables), lists (arrays, lists of dicts as inline tables) and
    scalars (strings, numbers, booleans)."""
    lines: list[str] = [f"# {ln}" for ln in header.splitlines()]

    def table(d: dict, name: str) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        if name and (scalars or not d):
            lines.extend(["", f"[{name}]"])
        lines.extend(_entry(k, v) for k, v in scalars.items())
        for k, v in d.items():
            if isinstance(v, dict):
                table(v, f"{name}.{_key(k)}" if name else _key(k))

    table(record, "")
    return "\n".join(lines) + "\n"


def _calibrated_record(problem: Problem, suffix: str) -> dict:
    """The problem's file as a table, named ``<name><suffix>``, test poses by their joints."""
    record = tomllib.loads(Path(problem.path).read_text(encoding="utf-8"))
    record["name"] = f"{problem.name}{suffix}"
    tp = problem.test_poses
    poses = {k: v for k, v in record["test_poses"].items() if k not in POSE_FIELDS}
    poses["joints_rad"] = tp.q.tolist()
    if problem.model.nF:
        poses["forces_N"] = tp.F.tolist()
    record["test_poses"] = poses
    spec = problem.spec  # the measured points as fitted (identify may have located them)
    if spec.measurement.markers_m is not None:
        record["measurement"]["markers_m"] = [list(m) for m in spec.measurement.markers_m]
    if spec.robot.tool_xyz_m is not None:
        record["robot"]["tool_xyz_m"] = list(spec.robot.tool_xyz_m)
    return record


def _relative(path: str, problem: Problem, out: Path) -> str:
    """``path`` of ``problem``'s file (relative to its folder, or absolute) relative to ``out``."""
    if path.startswith("example-robot-data:"):
        return path
    return os.path.relpath((Path(problem.path).parent / path).resolve(), Path(out).resolve())


#: The ``[robot]`` keys calibrated.toml keeps as the problem file gives them: what the calibration
#: does not change (the tool's placement and the chain's source are in calibrated.urdf).
CARRIED = ("joint_limits_rad", "joint_speeds_deg_s", "controller")


def calibrated_problem(problem: Problem, urdf: Path) -> dict:
    """The table of ``calibrated.toml`` (module docstring); ``urdf``: the calibrated URDF."""
    record = _calibrated_record(problem, "_calibrated")
    source = problem.spec.robot.source
    robot = {"urdf": Path(urdf).name, "frame": MEASURED_POINT}  # calibrated.toml is beside it
    kept = record.get("robot", {})
    robot |= {key: kept[key] for key in CARRIED if key in kept}  # the same robot's limits, speeds and controller
    if kept.get("inertias_urdf"):  # the links' masses (a URDF robot's own stay in calibrated.urdf)
        robot["inertias_urdf"] = _relative(kept["inertias_urdf"], problem, Path(urdf).parent)
    record["robot"] = robot
    cell = record.get("cell")
    if cell is not None:
        old = problem.robot.frame
        cell["capsules"] = [{**c, "frame": MEASURED_POINT if c.get("frame") == old else c["frame"]}
                            for c in cell.get("capsules", [])]
        if source != "urdf":
            cell.pop("collision_urdf", None)
            cell["capsules_per_link"] = 0
        _files_from(cell, problem, Path(urdf).parent)
    return record


def _files_from(cell: dict, problem: Problem, out: Path) -> None:
    """The files the ``[cell]`` table names (``collision_urdf``, ``srdf``) relative to ``out``,
    where the calibrated problem file is written."""
    for key in ("collision_urdf", "srdf"):
        if cell.get(key):
            cell[key] = _relative(cell[key], problem, out)


def _degrees(values) -> list[float]:
    return [math.degrees(v) + 0.0 for v in values]  # + 0.0: no -0.0 in the file


def calibrated_dh_problem(problem: Problem, robot: RobotSpec, out: Path) -> dict:
    """The table of ``calibrated_dh.toml`` (module docstring), written in ``out``; ``robot``:
    the calibrated DH robot of :func:`.dh_table.calibrated_dh`."""
    record = _calibrated_record(problem, "_calibrated_dh")
    raw_rows = record["robot"]["dh"]["joints"]
    record["robot"]["dh"] = {
        "convention": robot.dh_convention,
        "base_xyz_m": list(robot.base_xyz_m), "base_rpy_deg": _degrees(robot.base_rpy_rad),
        "flange_xyz_m": list(robot.flange_xyz_m), "flange_rpy_deg": _degrees(robot.flange_rpy_rad),
        "joints": [{"name": r.name, "type": r.kind, "theta_offset_deg": math.degrees(r.theta_offset_rad),
                    "d_m": r.d_m, "a_m": r.a_m, "alpha_deg": math.degrees(r.alpha_rad),
                    "beta_deg": math.degrees(r.beta_rad), "limits_deg": raw["limits_deg"]}
                   for raw, r in zip(raw_rows, robot.dh_rows)]}
    _files_from(record.get("cell", {}), problem, out)
    return record
