"""``[cell]``: the robot's capsules, the obstacles, the pairs never checked and the laser tracker,
read into the cell's description (:class:`casadi_design.cell.spec.CellSpec`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..cell.obstacles import OBSTACLE_KINDS, Capsule
from ..cell.spec import CellSpec, TrackerSpec
from .fields import TableReader, short, to_vec
from .robot import RobotSpec

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "cell": {"clearance_m", "capsules_per_link", "capsules", "disabled_pairs", "srdf", "obstacles", "tracker",
             "collision_urdf"},
    "cell.capsules": {"frame", "a_m", "b_m", "radius_m"},
    "cell.obstacles": {"name", "kind"}.union(*(kind.KEYS for kind in OBSTACLE_KINDS.values())),
    "cell.tracker": {"position_m", "reflector_axis", "acceptance_deg"},
}


def _entries(c: TableReader, key: str, example: str) -> list[TableReader]:
    """The inline tables of the list ``key`` of ``c``, each as a reader named ``key[k]``."""
    out = []
    for k, row in enumerate(c.get(key, list, [])):
        if not isinstance(row, dict):
            raise c.error(f"entry {k + 1} is {short(row)}", f"write each entry as {example}", key)
        out.append(c.row(row, f"{c.section}.{key}", f"{c.section}.{key}[{k + 1}]"))
    return out


def read_cell(c: TableReader | None, robot: RobotSpec) -> CellSpec | None:
    if c is None:
        return None
    capsules = tuple(Capsule.parse(r, "", r.get("frame", str, hint="a link frame or joint name of the robot"))
                     for r in _entries(c, "capsules", "{ frame = \"link\", a_m = [...], b_m = [...], radius_m = r }"))
    per_link = c.integer("capsules_per_link", 3 if robot.source == "urdf" else 0,
                         "capsules fitted around each link's collision meshes, 1 to 8 (0: none)", low=0, high=8)
    if per_link and robot.source != "urdf":
        raise c.error(f"is {per_link} but the robot has no URDF collision meshes",
                      "give the capsules as numbers (capsules = [...]) and capsules_per_link = 0", "capsules_per_link")
    pairs = []
    for k, pair in enumerate(c.get("disabled_pairs", list, [])):
        if not (isinstance(pair, list) and len(pair) == 2 and all(isinstance(v, str) for v in pair)):
            raise c.error(f"entry {k + 1} is {short(pair)}", "write each as [\"link_a\", \"link_b\"]", "disabled_pairs")
        pairs.append((pair[0], pair[1]))
    obstacles = []
    for r in _entries(c, "obstacles", "{ name = \"table\", kind = \"box\", center_m = [...], half_extents_m = [...] }"):
        name = r.get("name", str, hint="a name for messages, e.g. name = \"table\"")
        if not name.strip() or name in [o.name for o in obstacles] or name == "the floor":
            raise r.error(f"'{name}' is empty, repeated or reserved", "give each obstacle its own name", "name")
        kinds = list(OBSTACLE_KINDS)
        kind = r.get("kind", str, hint=f"{', '.join(kinds[:-1])} or {kinds[-1]}")
        if kind not in OBSTACLE_KINDS:
            raise r.error(f"'{kind}'", f"allowed: {', '.join(kinds)}", "kind")
        shape = OBSTACLE_KINDS[kind]
        extra = sorted(set(r.table) - shape.KEYS - {"name", "kind"})
        if extra:
            raise r.error(f"'{extra[0]}' is not a key of a {kind}", f"a {kind} takes {', '.join(sorted(shape.KEYS))}",
                          extra[0])
        obstacles.append(shape.parse(r, name))
    t = c.sub("tracker")
    tracker = None
    if t is not None:
        axis = t.array("reflector_axis", (3,), hint="the direction the reflector opens towards, in the measured frame")
        if not np.linalg.norm(axis) > 0:
            raise t.error("is zero", "give a non-zero 3-vector", "reflector_axis")
        acceptance = t.number("acceptance_deg", hint="the reflector's acceptance half-angle, e.g. 30 for an SMR",
                              positive=True)
        if acceptance >= 180:
            raise t.error(f"is {acceptance}", "give an angle below 180 deg", "acceptance_deg")
        tracker = TrackerSpec(to_vec(t.array("position_m", (3,), hint="the tracker's head, world, m")),
                              to_vec(axis / np.linalg.norm(axis)), math.radians(acceptance))
    urdf = c.get("collision_urdf", str, "")
    if urdf and robot.source != "dh":
        raise c.error("is only used with a DH robot", "remove it: the robot's own URDF meshes are used", "collision_urdf")
    urdf, srdf = (_file_of(c, name) for name in (urdf, c.get("srdf", str, "")))
    return CellSpec(c.number("clearance_m", 0.0, hint="the smallest distance kept between bodies, m", nonnegative=True),
                    per_link, capsules, tuple(pairs), tuple(obstacles), tracker, urdf, srdf)


def _file_of(c: TableReader, path: str) -> str:
    """A file named in the problem file: ``example-robot-data:...``, absolute, or relative to
    the problem file's folder ("" stays "")."""
    if path and not path.startswith("example-robot-data:") and not Path(path).is_absolute():
        return str(Path(c.path).parent / path)
    return path
