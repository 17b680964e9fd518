"""Problem files: TOML descriptions of a calibration design case, loaded into frozen data.

The format is documented in ``docs/problem-format.md``. Every field is checked on load;
errors name the file, the field, what is allowed and what was given.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import pinocchio as pin

from .errors import ProblemError
from .identifiability import BaseSet, base_set
from .ik import path_ik, sample_path
from .measures import CRITERIA
from .models import CASES, CalibrationModel, calibration_model
from .robots import (
    DHJoint,
    Robot,
    add_tool_frame,
    dh_arm,
    load_urdf,
    make_robot,
    placement_from_xyz_rpy,
    planar_2r_ik,
    planar_arm,
)
from .symbolic import symbolic_kinematics

FORCE_MODES = ("equal", "bound", "fixed", "direction")
#: Rank test of identifiability: relative singular-value threshold of the column-scaled S.
IDENTIFIABILITY_RTOL = 1e-9
#: Random configurations stacked for the identifiability test.
IDENTIFIABILITY_SAMPLES = 60

SECTIONS: dict[str, set[str] | None] = {
    "": {"name", "description", "robot", "calibration", "measurement", "test_poses",
         "experiments", "design", "solver"},
    "robot": {"planar_links_m", "urdf", "dh", "frame", "tool_xyz_m", "tool_rpy_deg", "joint_limits_rad"},
    "robot.dh": {"convention", "joints", "flange_xyz_m", "flange_rpy_deg"},
    "robot.dh.joints": {"name", "type", "theta_offset_deg", "d_m", "a_m", "alpha_deg", "limits_deg"},
    "robot.joint_limits_rad": None,  # joint names: checked against the model instead
    "calibration": {"case", "parameters", "compliant_joints", "wrench_components"},
    "measurement": {"components", "sigma_m", "sigma_rad", "sigma_axes_m", "covariance", "markers_m"},
    "test_poses": {"components", "joints_rad", "points_m", "line_m", "path", "tool_rpy_deg", "seed_q_deg",
                   "elbow", "force_N", "forces_N", "segment_forces_N"},
    "test_poses.path": {"kind", "points_m", "nodes"},
    "test_poses.line_m": {"start", "end", "nodes"},
    "experiments": {"m", "force", "workspace"},
    "experiments.force": {"mode", "magnitude_N", "vector_N", "direction", "load_point_m"},
    "experiments.workspace": {"box_min_m", "box_max_m", "half_spaces", "sphere_center_m",
                              "sphere_radius_m", "floor_z_m", "min_joint_distance_rad"},
    "experiments.workspace.half_spaces": {"normal", "offset_m"},
    "design": {"criteria", "parameter_scaling"},
    "solver": {"starts", "seed", "max_iter", "tol", "ipopt"},
    "solver.ipopt": None,  # passed through to IPOPT unchanged
}


@dataclass(frozen=True, eq=False)
class TestPoses:
    """The s test poses: where accuracy is required (a machining trajectory's nodes).

    Attributes
    ----------
    q : ndarray, shape (s, n), rad
    F : ndarray, shape (s, nF), N (and N m): machining wrench at each node.
    position_m : ndarray, shape (s, 3), m: nominal position of the measured frame.
    """

    q: np.ndarray
    F: np.ndarray
    position_m: np.ndarray

    @property
    def s(self) -> int:
        return self.q.shape[0]


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
    vector_N: tuple[float, ...] = ()
    direction: tuple[float, ...] = ()
    load_point_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class HalfSpace:
    """``normal . p >= offset_m`` for the measured point ``p`` (m)."""

    normal: tuple[float, float, float]
    offset_m: float


@dataclass(frozen=True)
class Workspace:
    """Where the robot may be during calibration (m, rad).

    Every measured point inside the box, the half-spaces and the sphere (the tracker's range);
    every joint origin and measured point at ``z >= floor_z_m``; the configurations of any two
    experiments at least ``min_joint_distance_rad`` apart (Euclidean norm of q_i - q_j).
    """

    box_min_m: tuple[float, float, float] | None = None
    box_max_m: tuple[float, float, float] | None = None
    half_spaces: tuple[HalfSpace, ...] = ()
    sphere_center_m: tuple[float, float, float] | None = None
    sphere_radius_m: float | None = None
    floor_z_m: float | None = None
    min_joint_distance_rad: float = 0.0


@dataclass(frozen=True)
class SolverSettings:
    """Multi-start IPOPT settings; ``ipopt`` options pass through unchanged."""

    starts: int = 20
    seed: int = 0
    max_iter: int = 3000
    tol: float = 1e-10
    ipopt: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True, eq=False)
class Problem:
    """A loaded, checked design case. ``base_set`` is set when the parameters were selected
    automatically (``parameters = "identifiable"``)."""

    name: str
    path: str
    raw: dict
    robot: Robot
    model: CalibrationModel
    sigma_m: float
    test_poses: TestPoses
    m_values: tuple[int, ...]
    force: ForceSpec | None
    workspace: Workspace
    criteria: tuple[str, ...]
    solver: SolverSettings = field(default_factory=SolverSettings)
    base_set: BaseSet | None = None
    #: fewest experiments that can identify X: ceil(L / d), d the independent values per experiment
    m_min: int = 1


class _Reader:
    """Typed access to one TOML table with file/field-qualified errors."""

    def __init__(self, path: str, table: dict, section: str):
        self.path, self.table, self.section = path, table, section
        allowed = SECTIONS[section]
        unknown = sorted(set(table) - allowed) if allowed is not None else []
        if unknown:
            raise self.error(
                f"unknown key '{unknown[0]}'", f"allowed: {', '.join(sorted(allowed))}"
            )

    def where(self, key: str | None = None) -> str:
        sec = f"[{self.section}]" if self.section else "top level"
        return f"{self.path}: {sec}" + (f".{key}" if key else "")

    def error(self, what: str, hint: str, key: str | None = None) -> ProblemError:
        return ProblemError(f"{self.where(key)}: {what}; {hint}")

    def get(self, key: str, kind: type | tuple, default: Any = ..., hint: str = "") -> Any:
        if key not in self.table:
            if default is ...:
                raise self.error("missing", hint or f"add {key} = ...", key)
            return default
        value = self.table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            name = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
            raise self.error(f"expected {name}, got {value!r}", hint or "fix its type", key)
        return value

    def array(self, key: str, shape: tuple, default: Any = ..., hint: str = "") -> np.ndarray | Any:
        value = self.get(key, list, default, hint)
        if value is default and default is not ...:
            return default
        try:
            if any(isinstance(v, bool) for v in np.ravel(np.array(value, dtype=object))):
                raise TypeError("booleans are not numbers")
            arr = np.array(value, dtype=float)
        except (TypeError, ValueError):
            raise self.error(f"expected numbers, got {value!r}", hint or "give a list of numbers", key)
        ok = arr.ndim == len(shape) and all(w in (None, d) for w, d in zip(shape, arr.shape))
        if not ok or not np.all(np.isfinite(arr)):
            want = " x ".join("any" if w is None else str(w) for w in shape)
            raise self.error(f"expected finite numbers of shape {want}, got {value!r}", hint or "", key)
        return arr

    def sub(self, key: str, required: bool = False) -> _Reader | None:
        if key not in self.table:
            if required:
                raise ProblemError(
                    f"{self.path}: [{self._name(key)}]: missing section; add a [{self._name(key)}] table"
                )
            return None
        value = self.table[key]
        if not isinstance(value, dict):
            raise self.error(f"expected a table, got {value!r}", f"write it as [{self._name(key)}]", key)
        return _Reader(self.path, value, self._name(key))

    def _name(self, key: str) -> str:
        return f"{self.section}.{key}" if self.section else key


def load_problem(path: str | Path) -> Problem:
    """Read, check and build a problem file."""
    path = str(path)
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except FileNotFoundError:
        raise ProblemError(f"{path}: no such problem file")
    except tomllib.TOMLDecodeError as exc:
        raise ProblemError(f"{path}: not valid TOML ({exc}); check the syntax at that line")
    return build_problem(raw, path)


def build_problem(raw: dict, path: str = "<problem>") -> Problem:
    """Check and build a problem from its parsed TOML ``raw``."""
    try:
        return _build(raw, path)
    except ProblemError as exc:
        if str(exc).startswith(f"{path}: "):
            raise
        raise ProblemError(f"{path}: {exc}") from None


def _build(raw: dict, path: str) -> Problem:
    top = _Reader(path, raw, "")
    name = top.get("name", str, Path(path).stem)
    robot = _robot(top.sub("robot", required=True))
    cal = top.sub("calibration", required=True)
    meas = top.sub("measurement", required=True)
    case = cal.get("case", str, hint=f"allowed: {', '.join(CASES)}")
    if case not in CASES:
        raise cal.error(f"'{case}' is not a calibration case", f"allowed: {', '.join(CASES)}", "case")
    elastic = case in ("elastostatic", "both")
    measured = tuple(meas.get("components", list, hint="e.g. components = [\"x\", \"y\", \"z\"]"))
    sigma = meas.get("sigma_m", float, hint="the measurement noise std in m, e.g. 1e-4")
    if not sigma > 0:
        raise meas.error(f"must be positive, got {sigma}", "give the noise std in m", "sigma_m")
    tp = top.sub("test_poses", required=True)
    accuracy = tuple(tp.get("components", list, list(measured)))
    wrench = tuple(cal.get("wrench_components", list, [] if not elastic else ...,
                           hint="the wrench components of F, e.g. [\"fx\", \"fy\"]"))
    if not elastic and wrench:
        raise cal.error("is only used by elasto-static cases", "remove it", "wrench_components")
    for key, used in (("parameters", case != "elastostatic"), ("compliant_joints", elastic)):
        if key in cal.table and not used:
            raise cal.error(f"is not used by case '{case}'", "remove it or change the case", key)
    kin = symbolic_kinematics(robot)
    markers = meas.array("markers_m", (None, 3), None, hint="one row (x, y, z) in m per marker, in the measured frame")
    exp = top.sub("experiments", required=True)
    fsub = exp.sub("force", required=elastic) if elastic else None
    load_point = fsub.array("load_point_m", (3,), np.zeros(3), hint="(x, y, z) in the measured frame, m") if fsub else None
    parameters = cal.get("parameters", (list, str), [])
    chosen = None
    if isinstance(parameters, str):
        if parameters != "identifiable":
            raise cal.error(f"'{parameters}'", "give a list of names or \"identifiable\"", "parameters")
        full = calibration_model(kin, "geometric", measured, geometric=kin.parameter_names, markers_m=markers)
        chosen = base_set(full)
        parameters = list(chosen.kept)
    model_args = dict(
        measured=measured,
        accuracy=accuracy,
        geometric=tuple(parameters),
        compliant=tuple(cal.get("compliant_joints", list)) if "compliant_joints" in cal.table else None,
        force=wrench,
        markers_m=markers,
        load_point_m=load_point,
        whitening=_whitening(meas, measured, markers, sigma),
    )
    model = calibration_model(kin, case, **model_args)
    test_poses = _test_poses(tp, robot, model)
    m_raw = exp.get("m", (int, list), hint="the number of experiments, e.g. m = [1, 5]")
    m_values = tuple(m_raw) if isinstance(m_raw, list) else (m_raw,)
    if not m_values or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in m_values):
        raise exp.error(f"expected positive integers, got {m_raw!r}", "e.g. m = [1, 5]", "m")
    if len(set(m_values)) != len(m_values):
        raise exp.error(f"has repeated values {list(m_values)}", "list each m once", "m")
    force = _force(fsub, model) if elastic else None
    if not elastic and "force" in exp.table:
        raise exp.error("a geometric case applies no load", "remove [experiments.force]", "force")
    workspace = _workspace(exp.sub("workspace"))
    design = top.sub("design", required=True)
    criteria = tuple(design.get("criteria", list, hint="e.g. criteria = [\"test-pose\", \"D\", \"E\"]"))
    for c in criteria:
        if c not in CRITERIA:
            raise design.error(f"has '{c}'", f"allowed: {', '.join(CRITERIA)}", "criteria")
    if not criteria or len(set(criteria)) != len(criteria):
        raise design.error(f"has {list(criteria)}", f"list distinct names among: {', '.join(CRITERIA)}", "criteria")
    scaling = design.get("parameter_scaling", str, "column")
    if scaling not in ("column", "none"):
        raise design.error(f"'{scaling}'", "allowed: column, none", "parameter_scaling")
    solver = _solver(top.sub("solver"))
    problem = Problem(name, path, raw, robot, model, sigma, test_poses, m_values, force,
                      workspace, criteria, solver, chosen)
    S, m_min = check_identifiable(problem, exp)
    problem = replace(problem, m_min=m_min)
    if scaling == "none":
        return problem
    # parameters in units that give every column of B unit RMS over random poses (Khalil)
    c = np.sqrt(np.mean(S.reshape(-1, model.d, model.L) ** 2, axis=0).sum(axis=0))
    return replace(problem, model=calibration_model(kin, case, column_scale=c, **model_args))


def _whitening(meas: _Reader, measured: tuple[str, ...], markers, sigma: float) -> np.ndarray | None:
    """``sigma * Sigma^-1/2`` for the per-value noise of one experiment (None: all values sigma).

    Values are ordered as measured: the position components of each marker, then the
    orientation components. ``sigma_axes_m`` gives a std per x, y, z axis, ``sigma_rad`` the
    orientation std, ``covariance`` the full d x d covariance (m^2, rad^2).
    """
    k = 1 if markers is None else len(markers)
    pos = [c for c in measured if c in ("x", "y", "z")]
    rot = [c for c in measured if c in ("rx", "ry", "rz")]
    d = k * len(pos) + len(rot)
    if rot and "sigma_rad" not in meas.table and "covariance" not in meas.table:
        raise meas.error("orientation is measured but its noise is not given", "add sigma_rad (rad)", "sigma_rad")
    if "covariance" in meas.table:
        if "sigma_axes_m" in meas.table or "sigma_rad" in meas.table:
            raise meas.error("give either covariance or sigma_axes_m / sigma_rad", "not both", "covariance")
        C = meas.array("covariance", (d, d), hint=f"a {d} x {d} symmetric positive definite matrix (m^2, rad^2)")
        try:
            Lc = np.linalg.cholesky(C) if np.allclose(C, C.T) else None
        except np.linalg.LinAlgError:
            Lc = None
        if Lc is None:
            raise meas.error("is not symmetric positive definite", "give a valid covariance (m^2, rad^2)", "covariance")
        return sigma * np.linalg.inv(Lc)
    axes = meas.array("sigma_axes_m", (3,), None, hint="std of x, y, z in m")
    srad = meas.get("sigma_rad", float, None)
    if axes is None and srad is None:
        return None
    for name, v in (("sigma_axes_m", axes), ("sigma_rad", srad)):
        if v is not None and not np.all(np.asarray(v) > 0):
            raise meas.error(f"must be positive, got {v}", "give standard deviations", name)
    std = [axes["xyz".index(c)] if axes is not None else sigma for _ in range(k) for c in pos] + [srad] * len(rot)
    return np.diag(sigma / np.array(std, dtype=float))


def _robot(r: _Reader) -> Robot:
    frame = r.get("frame", str, hint="the measured frame, e.g. frame = \"tool\"")
    given = [k for k in ("planar_links_m", "urdf", "dh") if k in r.table]
    if len(given) != 1:
        raise r.error(f"has {given or 'none'} of planar_links_m, urdf, dh", "give exactly one, e.g. "
                      "planar_links_m = [0.6, 0.4] or urdf = \"example-robot-data:ur_description/urdf/ur10_robot.urdf\"")
    if given[0] == "planar_links_m":
        links = r.array("planar_links_m", (None,))
        if len(links) == 0 or np.any(links <= 0):
            raise r.error(f"expected positive link lengths, got {links.tolist()}", "lengths in m", "planar_links_m")
        model = planar_arm(links)
    elif given[0] == "urdf":
        urdf = r.get("urdf", str)
        if not urdf.startswith("example-robot-data:") and not Path(urdf).is_absolute():
            urdf = str(Path(r.path).parent / urdf)
        model = load_urdf(urdf)
    else:
        model = _dh(r.sub("dh"))
    if "tool_xyz_m" in r.table or "tool_rpy_deg" in r.table:
        tool = placement_from_xyz_rpy(r.array("tool_xyz_m", (3,), np.zeros(3)),
                                      np.radians(r.array("tool_rpy_deg", (3,), np.zeros(3))))
        frame = add_tool_frame(model, frame, tool)
    lt = r.sub("joint_limits_rad")
    limits = {j: tuple(lt.array(j, (2,), hint="[lower, upper] in rad (m for prismatic joints)"))
              for j in (lt.table if lt else {})}
    return make_robot(model, frame, limits)


def _dh(d: _Reader):
    convention = d.get("convention", str, hint="standard or modified")
    rows_raw = d.get("joints", list, hint="one table per joint: { name, type, theta_offset_deg, d_m, a_m, alpha_deg, limits_deg }")
    if not rows_raw:
        raise d.error("is empty", "give one row per joint", "joints")
    rows = []
    for k, row in enumerate(rows_raw):
        if not isinstance(row, dict):
            raise d.error(f"row {k} is {row!r}", "write each row as an inline table { name = ..., ... }", "joints")
        j = _Reader(f"{d.path}: [robot.dh].joints row {k}", row, "robot.dh.joints")
        missing = sorted(SECTIONS["robot.dh.joints"] - set(row))
        if missing:
            raise j.error(f"misses {', '.join(missing)}", "every row needs name, type (R), theta_offset_deg, d_m, a_m, alpha_deg, limits_deg")
        lim = np.radians(j.array("limits_deg", (2,)))
        kind = j.get("type", str)
        if kind != "R":
            raise j.error(f"'{kind}'", "allowed: R (describe prismatic axes in a URDF)", "type")
        rows.append(DHJoint(j.get("name", str), kind, np.radians(j.get("theta_offset_deg", float)), j.get("d_m", float),
                            j.get("a_m", float), np.radians(j.get("alpha_deg", float)), lim[0], lim[1]))
    names = [row.name for row in rows]
    if len(set(names)) != len(names):
        raise d.error(f"has repeated joint names {names}", "name each joint once", "joints")
    flange = placement_from_xyz_rpy(d.array("flange_xyz_m", (3,), np.zeros(3)),
                                    np.radians(d.array("flange_rpy_deg", (3,), np.zeros(3))))
    return dh_arm(rows, convention, flange)


def _test_poses(tp: _Reader, robot: Robot, model: CalibrationModel) -> TestPoses:
    given = [k for k in ("joints_rad", "points_m", "line_m", "path") if k in tp.table]
    if len(given) != 1:
        raise tp.error(f"has {given or 'none'} of joints_rad, points_m, line_m, path", "give exactly one")
    only = {"elbow": ("points_m", "line_m"), "tool_rpy_deg": ("path",), "seed_q_deg": ("path",)}
    for key, kinds in only.items():
        if key in tp.table and given[0] not in kinds:
            raise tp.error(f"only applies with {' or '.join(kinds)}, not {given[0]}", "remove it", key)
    segment = None
    if given[0] == "path":
        q, segment = _path(tp, robot)
    elif given[0] == "joints_rad":
        q = tp.array("joints_rad", (None, robot.n), hint=f"one row of {robot.n} joint angles (rad) per pose")
    else:
        if given[0] == "points_m":
            pts = tp.array("points_m", (None, 2), hint="one row (x, y) in m per point")
        else:
            line = tp.sub("line_m")
            start = line.array("start", (2,), hint="(x, y) of the first node, m")
            end = line.array("end", (2,), hint="(x, y) of the last node, m")
            nodes = line.get("nodes", int, hint="number of nodes, >= 2")
            if nodes < 2:
                raise line.error(f"must be >= 2, got {nodes}", "give the number of nodes", "nodes")
            pts = start + np.linspace(0.0, 1.0, nodes)[:, None] * (end - start)
        elbow = tp.get("elbow", str, "up")
        if elbow not in ("up", "down"):
            raise tp.error(f"'{elbow}'", "allowed: up, down", "elbow")
        q = np.array([planar_2r_ik(robot, p, elbow) for p in pts])
    outside = np.flatnonzero(np.any((q < robot.q_min - 1e-12) | (q > robot.q_max + 1e-12), axis=1))
    if outside.size:
        raise tp.error(f"test pose {int(outside[0])} (q = {q[outside[0]].round(4).tolist()} rad) is outside the joint limits",
                       "move the pose or widen [robot.joint_limits_rad]")
    nF = model.nF
    if nF == 0 and ("force_N" in tp.table or "forces_N" in tp.table):
        raise tp.error("a geometric case has no machining load in its model", "remove force_N / forces_N")
    loads = [k for k in ("force_N", "forces_N", "segment_forces_N") if k in tp.table]
    if len(loads) > 1:
        raise tp.error(f"has {', '.join(loads)}", "give one of them")
    if "segment_forces_N" in tp.table:
        if segment is None:
            raise tp.error("needs a path", "use force_N or forces_N", "segment_forces_N")
        per_segment = tp.array("segment_forces_N", (int(segment.max()) + 1, nF),
                               hint=f"one row of {nF} wrench components per path segment")
        F = per_segment[segment]
    elif "forces_N" in tp.table:
        F = tp.array("forces_N", (q.shape[0], nF), hint=f"one row of {nF} wrench components per test pose")
    elif "force_N" in tp.table:
        F = np.tile(tp.array("force_N", (nF,), hint=f"{nF} wrench components"), (q.shape[0], 1))
    elif nF:
        raise tp.error("missing force_N", f"give the machining wrench, {nF} components in N (N m)", "force_N")
    else:
        F = np.zeros((q.shape[0], 0))
    pos = np.array([np.asarray(model.position(qi)).ravel() for qi in q])
    return TestPoses(q=q, F=F, position_m=pos)


def _path(tp: _Reader, robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Test poses on a Cartesian path, by IK with a constant tool orientation."""
    path = tp.sub("path")
    kind = path.get("kind", str, hint="line, polyline, arc or points")
    need = {"line": 2, "arc": 3, "polyline": None, "points": None}
    if kind not in need:
        raise path.error(f"'{kind}'", "allowed: line, polyline, arc, points", "kind")
    pts = path.array("points_m", (need[kind], 3), hint="rows (x, y, z) in m: line 2, arc 3 (start, via, end), polyline/points any")
    if len(pts) < 2 and kind != "points":
        raise path.error("needs at least 2 points", "add points", "points_m")
    nodes = path.get("nodes", int, 1 if kind == "points" else ..., hint="number of nodes, >= 2")
    if kind == "points" and "nodes" in path.table:
        raise path.error("is not used with kind = \"points\"", "remove it", "nodes")
    if kind != "points" and nodes < 2:
        raise path.error(f"must be >= 2, got {nodes}", "give the number of nodes", "nodes")
    positions, segment = sample_path(kind, pts, nodes)
    position_only = "tool_rpy_deg" not in tp.table
    rotation = pin.rpy.rpyToMatrix(*np.radians(tp.array("tool_rpy_deg", (3,), np.zeros(3))))
    seed = np.radians(tp.array("seed_q_deg", (robot.n,), np.degrees((robot.q_min + robot.q_max) / 2),
                               hint=f"{robot.n} joint values in deg"))
    return path_ik(robot, positions, rotation, seed, position_only), segment


def _force(f: _Reader, model: CalibrationModel) -> ForceSpec:
    mode = f.get("mode", str, hint=f"allowed: {', '.join(FORCE_MODES)}")
    if mode not in FORCE_MODES:
        raise f.error(f"'{mode}'", f"allowed: {', '.join(FORCE_MODES)}", "mode")
    if mode == "fixed":
        vec = f.array("vector_N", (model.nF,), hint=f"{model.nF} wrench components, N (N m)")
        if not np.any(vec):
            raise f.error("is zero: a zero load identifies no compliance", "give the applied load", "vector_N")
        if "magnitude_N" in f.table:
            raise f.error("is not used with mode = \"fixed\"", "remove it", "magnitude_N")
        return ForceSpec(mode, float(np.linalg.norm(vec)), tuple(vec.tolist()), (), _load_point(f))
    magnitude = f.get("magnitude_N", float, hint="the largest load the rig applies, N")
    if not magnitude > 0:
        raise f.error(f"must be positive, got {magnitude}", "give the load in N", "magnitude_N")
    if "vector_N" in f.table:
        raise f.error(f"is only used with mode = \"fixed\", not \"{mode}\"", "remove it", "vector_N")
    direction: tuple[float, ...] = ()
    if mode == "direction":
        u = f.array("direction", (model.nF,), hint=f"{model.nF} wrench components of the load's direction")
        if not np.linalg.norm(u) > 0:
            raise f.error("is zero", "give the direction of the load", "direction")
        direction = tuple((u / np.linalg.norm(u)).tolist())
    elif "direction" in f.table:
        raise f.error(f"is only used with mode = \"direction\", not \"{mode}\"", "remove it", "direction")
    return ForceSpec(mode, magnitude, (), direction, _load_point(f))


def _load_point(f: _Reader) -> tuple[float, float, float]:
    return tuple(f.array("load_point_m", (3,), np.zeros(3)).tolist())


def _workspace(w: _Reader | None) -> Workspace:
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
            raise w.error(f"entry {k} is {hs!r}", "write { normal = [nx, ny, nz], offset_m = b } for normal . p >= b", "half_spaces")
        h = _Reader(w.path, hs, "experiments.workspace.half_spaces")
        normal = h.array("normal", (3,), hint="a non-zero 3-vector")
        if not np.linalg.norm(normal) > 0:
            raise h.error("is zero", "give a non-zero 3-vector", "normal")
        spaces.append(HalfSpace(tuple(normal.tolist()), h.get("offset_m", float, hint="b in normal . p >= b, m")))
    center = w.array("sphere_center_m", (3,), None, hint="(x, y, z) of the tracker, m")
    radius = w.get("sphere_radius_m", float, None, hint="the tracker's range, m")
    if (center is None) != (radius is None) or radius is not None and radius <= 0:
        raise w.error("give both sphere_center_m and a positive sphere_radius_m", "or neither")
    dmin = w.get("min_joint_distance_rad", float, 0.0)
    if dmin < 0:
        raise w.error(f"must be >= 0, got {dmin}", "give a distance in rad", "min_joint_distance_rad")
    return Workspace(
        None if lo is None else tuple(lo.tolist()),
        None if hi is None else tuple(hi.tolist()),
        tuple(spaces),
        None if center is None else tuple(center.tolist()),
        radius,
        w.get("floor_z_m", float, None),
        dmin,
    )


def _solver(s: _Reader | None) -> SolverSettings:
    if s is None:
        return SolverSettings()
    d = SolverSettings()
    starts = s.get("starts", int, d.starts)
    if starts < 1:
        raise s.error(f"must be >= 1, got {starts}", "give the number of IPOPT starts", "starts")
    settings = SolverSettings(
        starts=starts,
        seed=s.get("seed", int, d.seed),
        max_iter=s.get("max_iter", int, d.max_iter),
        tol=s.get("tol", float, d.tol),
        ipopt=tuple(sorted(s.sub("ipopt").table.items())) if "ipopt" in s.table else (),
    )
    for key, value in (("seed", settings.seed), ("max_iter", settings.max_iter), ("tol", settings.tol)):
        if value < 0 or key == "tol" and value == 0:
            raise s.error(f"must be {'positive' if key == 'tol' else '>= 0'}, got {value}", "fix it", key)
    _check_ipopt_options(s, settings)
    return settings


def _check_ipopt_options(s: _Reader, settings: SolverSettings) -> None:
    """Try the [solver.ipopt] options on a one-variable NLP, so a bad option fails at load."""
    if not settings.ipopt:
        return
    x = ca.SX.sym("x")
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "error_on_fail": False,
            **{f"ipopt.{k}": v for k, v in settings.ipopt}}
    try:
        solver = ca.nlpsol("check", "ipopt", {"x": x, "f": x**2}, opts)
        solver(x0=1.0)
        status = solver.stats()["return_status"]
    except RuntimeError as exc:
        status = str(exc).strip().splitlines()[-1].split(": ", 1)[-1]
    if status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level", "Maximum_Iterations_Exceeded"):
        raise s.error(f"IPOPT rejected the options {dict(settings.ipopt)} ({status})",
                      "check the names and values against the IPOPT options reference", "ipopt")



def check_identifiable(problem: Problem, exp: _Reader) -> tuple[np.ndarray, int]:
    """Fail early when X cannot be identified: too few experiments or a rank-deficient model.

    Stacks B over ``IDENTIFIABILITY_SAMPLES`` random configurations with the calibration
    loads (random directions where free), scales its columns by their norms under random
    loads and requires every singular value above
    ``IDENTIFIABILITY_RTOL`` times the largest. Returns the stacked (unscaled) B and the
    smallest m.
    """
    model = problem.model
    L = model.L
    rng = np.random.default_rng(12345)
    robot, force = problem.robot, problem.force
    rows, generic = [], []
    for _ in range(IDENTIFIABILITY_SAMPLES):
        q = rng.uniform(robot.q_min, robot.q_max)
        F_any = rng.normal(size=model.nF)
        if force is not None:  # loads of the rig's size, so that column scales reflect them
            F_any *= force.magnitude_N / np.linalg.norm(F_any)
        F = (np.array(force.vector_N) if force and force.mode == "fixed"
             else force.magnitude_N * np.array(force.direction) if force and force.mode == "direction"
             else F_any)
        rows.append(model.B_numeric(q, F))
        generic.append(model.B_numeric(q, F_any))
    # an experiment gives at most d independent values (three markers on a rigid tool: 6, not 9)
    d = max(np.linalg.matrix_rank(B, tol=1e-10 * np.abs(B).max()) for B in rows)
    m_min = -(-L // d)
    small = [m for m in problem.m_values if m < m_min]
    if small:
        raise exp.error(
            f"m = {small[0]} is too small: {L} parameters ({', '.join(model.parameter_names)}) "
            f"with {d} independent measured values per experiment need m >= {m_min}",
            f"use m >= {m_min}",
            "m",
        )
    S = np.vstack(rows)
    # columns scaled by their norm under generic loads, so that a parameter the actual
    # loads cannot excite stays a (near) zero column
    Sn = S / np.maximum(np.linalg.norm(np.vstack(generic), axis=0), np.finfo(float).tiny)
    _, sv, Vt = np.linalg.svd(Sn, full_matrices=False)
    null = sv < IDENTIFIABILITY_RTOL * sv[0]
    if np.any(null):
        v = Vt[np.flatnonzero(null)[0]]
        involved = [model.parameter_names[i] for i in np.flatnonzero(np.abs(v) > 1e-6)]
        field = "compliant_joints" if all(p.startswith("k.") for p in involved) else "parameters"
        what = (f"{involved[0]} has no effect on them" if len(involved) == 1
                else f"{' and '.join(involved)} act as one combination")
        if field == "compliant_joints" and force and force.mode in ("fixed", "direction"):
            what += " under the calibration load of [experiments.force]"
        raise ProblemError(
            f"{problem.path}: [calibration].{field}: the parameters are not identifiable from "
            f"{', '.join(problem.raw['measurement']['components'])} measurements: {what} "
            f"(rank {int(np.sum(~null))} of {L}); remove {'it' if len(involved) == 1 else 'one of them'}"
        )
    return S, m_min
