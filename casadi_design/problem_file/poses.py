"""``[test_poses]``: where accuracy is required (joint values, planar points or a line, or a
Cartesian path solved by IK) and the machining wrench there."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .fields import (
    BYTES_PER_TEST_POSE_L2,
    MAX_TEST_POSES,
    TWIST_ROWS,
    Mat,
    TableReader,
    Vec,
    check_load,
    check_size,
    to_mat,
    to_vec,
)
from .measurement import MeasurementSpec

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "test_poses": {"components", "joints_rad", "points_m", "line_m", "path", "tool_rpy_deg", "seed_q_deg",
                   "elbow", "force_N", "forces_N", "segment_forces_N"},
    "test_poses.path": {"kind", "points_m", "nodes"},
    "test_poses.line_m": {"start", "end", "nodes"},
}


@dataclass(frozen=True)
class TestPoseSpec:
    """Where accuracy is required.

    ``kind`` is "joints" (``joints_rad``), "planar" (``points_m``: (x, y) points of a planar
    arm, from ``points_m`` or ``line_m``, solved in closed form on ``elbow``) or "path"
    (``path_points_m`` sampled by ``path_kind`` into ``path_nodes`` and solved by IK with
    ``tool_rpy_rad``, None for position only). The machining wrench: ``force_N`` (one for all),
    ``forces_N`` (one per pose) or ``segment_forces_N`` (one per path segment).
    """

    components: tuple[str, ...]
    kind: str
    joints_rad: Mat = ()
    points_m: Mat = ()
    elbow: str = "up"
    path_kind: str = ""
    path_points_m: Mat = ()
    path_nodes: int = 0
    tool_rpy_rad: Vec | None = None
    seed_q_rad: Vec | None = None
    force_N: Vec | None = None
    forces_N: Mat | None = None
    segment_forces_N: Mat | None = None


def read_test_poses(tp: TableReader, meas: MeasurementSpec, nF: int) -> TestPoseSpec:
    components = tp.names("components", TWIST_ROWS, meas.components)
    given = [k for k in ("joints_rad", "points_m", "line_m", "path") if k in tp.table]
    if len(given) != 1:
        raise tp.error(f"has {given or 'none'} of joints_rad, points_m, line_m, path", "give exactly one")
    only = {"elbow": ("points_m", "line_m"), "tool_rpy_deg": ("path",), "seed_q_deg": ("path",)}
    for key, kinds in only.items():
        if key in tp.table and given[0] not in kinds:
            raise tp.error(f"only applies with {' or '.join(kinds)}, not {given[0]}", "remove it", key)
    spec: dict[str, Any] = {}
    if given[0] == "path":
        spec.update(_path(tp))
        s, segments = spec.pop("_s"), spec.pop("_segments")
    elif given[0] == "joints_rad":
        q = tp.array("joints_rad", (None, None), hint="one row of joint values (rad) per pose")
        check_size(tp.path, "[test_poses].joints_rad", len(q), MAX_TEST_POSES, BYTES_PER_TEST_POSE_L2,
                   "test poses", "give fewer test poses")
        if len(q) == 0:
            raise tp.error("is empty", "give one row of joint values (rad) per pose", "joints_rad")
        spec.update(kind="joints", joints_rad=to_mat(q))
        s, segments = len(q), None
    else:
        if given[0] == "points_m":
            pts = tp.array("points_m", (None, 2), hint="one row (x, y) in m per point")
            if len(pts) == 0:
                raise tp.error("is empty", "give one row (x, y) in m per point", "points_m")
        else:
            line = tp.sub("line_m")
            start = line.array("start", (2,), hint="(x, y) of the first node, m")
            end = line.array("end", (2,), hint="(x, y) of the last node, m")
            nodes = line.integer("nodes", hint="number of nodes, >= 2", low=2)
            check_size(tp.path, "[test_poses.line_m].nodes", nodes, MAX_TEST_POSES, BYTES_PER_TEST_POSE_L2,
                       "test poses", "give fewer nodes")
            pts = start + np.linspace(0.0, 1.0, nodes)[:, None] * (end - start)
        check_size(tp.path, "[test_poses].points_m", len(pts), MAX_TEST_POSES, BYTES_PER_TEST_POSE_L2,
                   "test poses", "give fewer points")
        elbow = tp.get("elbow", str, "up")
        if elbow not in ("up", "down"):
            raise tp.error(f"'{elbow}'", "allowed: up, down", "elbow")
        spec.update(kind="planar", points_m=to_mat(pts), elbow=elbow)
        s, segments = len(pts), None
    if nF == 0 and any(k in tp.table for k in ("force_N", "forces_N", "segment_forces_N")):
        raise tp.error("a geometric case has no machining load in its model", "remove force_N / forces_N")
    loads = [k for k in ("force_N", "forces_N", "segment_forces_N") if k in tp.table]
    if len(loads) > 1:
        raise tp.error(f"has {', '.join(loads)}", "give one of them")
    if "segment_forces_N" in tp.table:
        if segments is None:
            raise tp.error("needs a path", "use force_N or forces_N", "segment_forces_N")
        spec["segment_forces_N"] = to_mat(tp.array("segment_forces_N", (segments, nF),
                                                 hint=f"one row of {nF} wrench components per path segment"))
    elif "forces_N" in tp.table:
        spec["forces_N"] = to_mat(tp.array("forces_N", (s, nF), hint=f"one row of {nF} wrench components per test pose"))
    elif "force_N" in tp.table:
        spec["force_N"] = to_vec(tp.array("force_N", (nF,), hint=f"{nF} wrench components"))
    elif nF:
        raise tp.error("missing force_N", f"give the machining wrench, {nF} components in N (N m)", "force_N")
    for key in loads:
        check_load(tp, key, spec[key], "give the machining wrench in N and N m")
    return TestPoseSpec(components=components, **spec)


def _path(tp: TableReader) -> dict:
    """A Cartesian path: its kind, points and nodes, the tool orientation and the IK seed."""
    path = tp.sub("path")
    kind = path.get("kind", str, hint="line, polyline, arc or points")
    need = {"line": 2, "arc": 3, "polyline": None, "points": None}
    if kind not in need:
        raise path.error(f"'{kind}'", "allowed: line, polyline, arc, points", "kind")
    pts = path.array("points_m", (need[kind], 3), hint="rows (x, y, z) in m: line 2, arc 3 (start, via, end), polyline/points any")
    if len(pts) < (1 if kind == "points" else 2):
        raise path.error(f"has {len(pts)} points", "add points", "points_m")
    if kind == "points" and "nodes" in path.table:
        raise path.error("is not used with kind = \"points\"", "remove it", "nodes")
    nodes = len(pts) if kind == "points" else path.integer("nodes", hint="number of nodes, >= 2", low=2)
    check_size(tp.path, "[test_poses.path].nodes", nodes, MAX_TEST_POSES, BYTES_PER_TEST_POSE_L2,
               "test poses", "give fewer nodes")
    if kind in ("line", "polyline") and np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) == 0):
        raise path.error("has two equal consecutive points", "remove the repeated point", "points_m")
    rpy = tp.array("tool_rpy_deg", (3,), None, hint="roll, pitch, yaw of the tool in deg")
    seed = tp.array("seed_q_deg", (None,), None, hint="joint values in deg")
    return {"kind": "path", "path_kind": kind, "path_points_m": to_mat(pts), "path_nodes": nodes,
            "tool_rpy_rad": None if rpy is None else to_vec(np.radians(rpy)),
            "seed_q_rad": None if seed is None else to_vec(np.radians(seed)),
            "_s": nodes, "_segments": 1 if kind == "arc" else len(pts) - 1 if kind != "points" else len(pts)}
