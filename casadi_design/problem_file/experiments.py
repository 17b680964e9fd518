"""``[experiments]``: the numbers of experiments, the calibration load of each and the
workspace the robot stays in while it is measured."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cell.obstacles import HalfSpace
from ..cell.spec import Workspace
from .fields import MAX_LOAD_N, TableReader, Vec, check_load, short, to_vec

FORCE_MODES = ("equal", "bound", "fixed", "direction")

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "experiments": {"m", "force", "workspace"},
    "experiments.force": {"mode", "magnitude_N", "vector_N", "direction", "load_point_m"},
    "experiments.workspace": {"box_min_m", "box_max_m", "half_spaces", "sphere_center_m",
                              "sphere_radius_m", "floor_z_m", "min_joint_distance_rad",
                              "joint_limit_margin_rad"},
    "experiments.workspace.half_spaces": {"normal", "offset_m"},
}


@dataclass(frozen=True)
class ForceSpec:
    """Calibration load of every experiment.

    ``mode``: "equal" (``|F| = magnitude_N``, direction free), "bound" (``|F| <= magnitude_N``),
    "fixed" (``F = vector_N`` in every experiment) or "direction" (``F = a magnitude_N u`` with
    the unit ``direction`` u fixed and ``0 <= a <= 1``: a hung weight of choosable mass).
    Norms are over the wrench components. ``load_point_m`` (measured frame, m) is where the
    force acts.
    """

    mode: str
    magnitude_N: float
    vector_N: Vec = ()
    direction: Vec = ()
    load_point_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


def read_force(f: TableReader, nF: int) -> ForceSpec:
    mode = f.get("mode", str, hint=f"allowed: {', '.join(FORCE_MODES)}")
    if mode not in FORCE_MODES:
        raise f.error(f"'{mode}'", f"allowed: {', '.join(FORCE_MODES)}", "mode")
    load_point = to_vec(f.array("load_point_m", (3,), np.zeros(3), hint="(x, y, z) in the measured frame, m"))
    if mode == "fixed":
        vec = f.array("vector_N", (nF,), hint=f"{nF} wrench components, N (N m)")
        if not np.any(vec):
            raise f.error("is zero: a zero load identifies no compliance", "give the applied load", "vector_N")
        check_load(f, "vector_N", vec, "give the applied load in N and N m")
        if "magnitude_N" in f.table:
            raise f.error("is not used with mode = \"fixed\"", "remove it", "magnitude_N")
        return ForceSpec(mode, float(np.linalg.norm(vec)), to_vec(vec), (), load_point)
    magnitude = f.number("magnitude_N", hint="the largest load the rig applies, N", positive=True)
    if magnitude > MAX_LOAD_N:
        raise f.error(f"is {magnitude:g} N, above {MAX_LOAD_N:g} N (100 t)", "give the largest load "
                      "the rig applies in N, e.g. 100.0", "magnitude_N")
    if "vector_N" in f.table:
        raise f.error(f"is only used with mode = \"fixed\", not \"{mode}\"", "remove it", "vector_N")
    direction: Vec = ()
    if mode == "direction":
        u = f.array("direction", (nF,), hint=f"{nF} wrench components of the load's direction")
        if not np.linalg.norm(u) > 0:
            raise f.error("is zero", "give the direction of the load", "direction")
        direction = to_vec(u / np.linalg.norm(u))
    elif "direction" in f.table:
        raise f.error(f"is only used with mode = \"direction\", not \"{mode}\"", "remove it", "direction")
    return ForceSpec(mode, magnitude, (), direction, load_point)


def read_workspace(w: TableReader | None) -> Workspace:
    if w is None:
        return Workspace()
    lo = w.array("box_min_m", (3,), None, hint="(x, y, z) in m")
    hi = w.array("box_max_m", (3,), None, hint="(x, y, z) in m")
    if (lo is None) != (hi is None):
        raise w.error("give both box_min_m and box_max_m", "or neither")
    if lo is not None and not np.all(lo < hi):
        raise w.error(f"box_min_m {lo.tolist()} must be below box_max_m {hi.tolist()}", "fix the box")
    spaces = []
    for k, hs in enumerate(w.get("half_spaces", list, [])):
        if not isinstance(hs, dict):
            raise w.error(f"entry {k} is {short(hs)}", "write { normal = [nx, ny, nz], offset_m = b } for normal . p >= b", "half_spaces")
        h = w.row(hs, "experiments.workspace.half_spaces")
        normal = h.array("normal", (3,), hint="a non-zero 3-vector")
        if not np.linalg.norm(normal) > 0:
            raise h.error("is zero", "give a non-zero 3-vector", "normal")
        spaces.append(HalfSpace(to_vec(normal), h.number("offset_m", hint="b in normal . p >= b, m"), f"half-space {k + 1}"))
    center = w.array("sphere_center_m", (3,), None, hint="(x, y, z) of the tracker, m")
    radius = w.number("sphere_radius_m", None, hint="the tracker's range, m", positive=True)
    if (center is None) != (radius is None):
        raise w.error("give both sphere_center_m and a positive sphere_radius_m", "or neither")
    return Workspace(
        to_vec(lo), to_vec(hi), tuple(spaces), to_vec(center), radius,
        w.number("floor_z_m", None, hint="height of the floor, m"),
        w.number("min_joint_distance_rad", 0.0, hint="a distance in rad", nonnegative=True),
        w.number("joint_limit_margin_rad", 0.0, hint="a margin inside the joint limits in rad, e.g. 0.05",
                 nonnegative=True),
    )
