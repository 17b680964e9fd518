"""Problem files: TOML descriptions of a calibration design case, read into plain frozen data.

Reading only checks and stores: types, finite numbers, shapes, ranges, names of sections and
keys, sizes. It builds no robot, no CasADi expression and runs no solver, so a
:class:`ProblemSpec` is cheap to pickle and send to worker processes. Building the robot,
kinematics, calibration model, test poses, base set and smallest m is the next step
(:func:`casadi_design.model.build.build_problem`), whose errors name the same fields.

The format is documented in ``docs/problem-format.md``. Every error names the file, the field,
what is wrong and what to do.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..measures.criteria import CRITERIA
from ..errors import ProblemError
from .obstacles import OBSTACLE_KINDS, Capsule, HalfSpace, Obstacle

CASES = ("geometric", "elastostatic", "both")
FORCE_MODES = ("equal", "bound", "fixed", "direction")
#: Components of a twist (measured / required rows) and of a wrench, in the order used everywhere.
TWIST_ROWS = ("x", "y", "z", "rx", "ry", "rz")
WRENCH_ROWS = ("fx", "fy", "fz", "mx", "my", "mz")
#: Largest problem file read (bytes): a bigger one is not a hand-written case.
MAX_FILE_BYTES = 10_000_000
#: Largest number of test poses and of experiments accepted. Each experiment adds a copy of the
#: symbolic B(q, F) to the NLP graph (about ``BYTES_PER_EXPERIMENT_L2`` L^2 bytes) and each test
#: pose an epigraph constraint (about ``BYTES_PER_TEST_POSE_L2`` L^2 bytes).
MAX_TEST_POSES = 5_000
MAX_EXPERIMENTS = 500
BYTES_PER_EXPERIMENT_L2 = 160_000
BYTES_PER_TEST_POSE_L2 = 4_000
#: Relative asymmetry accepted in a covariance matrix.
SYMMETRY_RTOL = 1e-9
#: Largest measurement noise std (m) and calibration load (N, N m) accepted: beyond them the
#: value is a typing error (no tracker is that noisy, no rig that strong), and its square
#: overflows the arithmetic.
MAX_SIGMA_M = 1.0
MAX_LOAD_N = 1e6
#: Hayati's angle beta of a DH row lies strictly within +/- this (deg): only there does a
#: direction of the next axis have one (alpha, beta) pair.
MAX_BETA_DEG = 90.0

SECTIONS: dict[str, set[str] | None] = {
    "": {"name", "description", "robot", "calibration", "measurement", "test_poses",
         "experiments", "design", "solver", "cell"},
    "robot": {"planar_links_m", "urdf", "dh", "frame", "tool_xyz_m", "tool_rpy_deg", "joint_limits_rad",
              "joint_speeds_deg_s", "controller"},
    "robot.controller": {"signs", "offsets_deg", "acceleration_time_s"},
    "robot.dh": {"convention", "joints", "base_xyz_m", "base_rpy_deg", "flange_xyz_m", "flange_rpy_deg"},
    "robot.dh.joints": {"name", "type", "theta_offset_deg", "d_m", "a_m", "alpha_deg", "beta_deg", "limits_deg"},
    "robot.joint_limits_rad": None,  # joint names: checked against the model when built
    "calibration": {"case", "parameters", "compliant_joints", "wrench_components", "prior", "model_error"},
    "calibration.prior": {"length_m", "angle_rad", "offset_rad", "compliance_rad_per_Nm"},
    "calibration.model_error": {"scale_m", "angle_rad", "length_rad", "nugget_m", "shares"},
    "measurement": {"components", "sigma_m", "sigma_rad", "sigma_axes_m", "covariance", "markers_m"},
    "test_poses": {"components", "joints_rad", "points_m", "line_m", "path", "tool_rpy_deg", "seed_q_deg",
                   "elbow", "force_N", "forces_N", "segment_forces_N"},
    "test_poses.path": {"kind", "points_m", "nodes"},
    "test_poses.line_m": {"start", "end", "nodes"},
    "experiments": {"m", "force", "workspace"},
    "experiments.force": {"mode", "magnitude_N", "vector_N", "direction", "load_point_m"},
    "experiments.workspace": {"box_min_m", "box_max_m", "half_spaces", "sphere_center_m",
                              "sphere_radius_m", "floor_z_m", "min_joint_distance_rad",
                              "joint_limit_margin_rad"},
    "experiments.workspace.half_spaces": {"normal", "offset_m"},
    "design": {"criteria", "parameter_scaling"},
    "cell": {"clearance_m", "capsules_per_link", "capsules", "disabled_pairs", "srdf", "obstacles", "tracker",
             "collision_urdf"},
    "cell.capsules": {"frame", "a_m", "b_m", "radius_m"},
    "cell.obstacles": {"name", "kind"}.union(*(kind.KEYS for kind in OBSTACLE_KINDS.values())),
    "cell.tracker": {"position_m", "reflector_axis", "acceptance_deg"},
    "solver": {"starts", "seed", "max_iter", "tol", "ipopt", "criterion_starts"},
    "solver.ipopt": None,  # passed through to IPOPT unchanged
    "solver.criterion_starts": set(CRITERIA),
}

Vec = tuple[float, ...]
Mat = tuple[tuple[float, ...], ...]


# --------------------------------------------------------------------------- plain data

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
    joint_limits_rad: tuple[tuple[str, float, float], ...] = ()
    joint_speeds_deg_s: Vec | None = None
    controller: ControllerSpec | None = None

    @property
    def source(self) -> str:
        return "planar" if self.planar_links_m else "urdf" if self.urdf else "dh"


@dataclass(frozen=True)
class PriorSpec:
    """What is known of the robot's parameters before measuring (``[calibration.prior]``): the
    standard deviation of a zero-mean normal prior per group (None: no prior on the group),
    e.g. a factory calibration's accuracy. Groups: the joint placement errors' translations
    (``length_m``, m; also the zero offsets of prismatic joints) and rotations (``angle_rad``,
    rad), the zero offsets of revolute joints (``offset_rad``, rad), the joint compliances
    (``compliance_rad_per_Nm``, rad/(N m)). The tracker frame and the measured points (``tool.*``)
    have none: registration places them."""

    length_m: float | None = None
    angle_rad: float | None = None
    offset_rad: float | None = None
    compliance_rad_per_Nm: float | None = None


@dataclass(frozen=True)
class ModelErrorSpec:
    """The robot's unmodelled error as a random field over its configurations
    (``[calibration.model_error]``, :mod:`casadi_design.measures.field`): either ``angle_rad``
    the std of each joint's angle error (rad; an error of the joint angles, seen through each
    joint's Jacobian column) or ``scale_m`` its std per base axis (m, 0 with ``angle_rad``);
    ``length_rad`` its correlation length per joint (rad; m for a prismatic joint), ``nugget_m``
    the part no neighbouring pose tells (m), ``shares`` each joint's share of the variance of a
    field of the base axes additive over the joints (sum 1; empty: the squared exponential over
    all joints at once)."""

    scale_m: float
    length_rad: tuple[float, ...]
    nugget_m: float = 0.0
    shares: tuple[float, ...] = ()
    angle_rad: tuple[float, ...] = ()


@dataclass(frozen=True)
class CalibrationSpec:
    """What is identified. ``parameters`` is a tuple of names or ``"identifiable"``;
    ``compliant_joints`` None means every joint of the chain; ``prior``: ``[calibration.prior]``
    (None without one)."""

    case: str
    parameters: tuple[str, ...] | str = ()
    compliant_joints: tuple[str, ...] | None = None
    wrench_components: tuple[str, ...] = ()
    prior: PriorSpec | None = None
    model_error: ModelErrorSpec | None = None


@dataclass(frozen=True)
class MeasurementSpec:
    """What each experiment measures and with which noise.

    ``whitening`` is ``sigma * Sigma^-1/2`` (d x d) for the per-value noise of one experiment,
    None when every value has std ``sigma_m``. Values are ordered as measured: the position
    components of each marker, then the orientation components.
    """

    components: tuple[str, ...]
    sigma_m: float
    markers_m: Mat | None = None
    whitening: Mat | None = None


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


@dataclass(frozen=True)
class TrackerSpec:
    """The laser tracker: at ``position_m`` (world, m); each reflector (SMR) opens along the
    unit ``reflector_axis`` (measured frame) and returns the beam within ``acceptance_rad`` of
    that axis."""

    position_m: tuple[float, float, float]
    reflector_axis: tuple[float, float, float]
    acceptance_rad: float


@dataclass(frozen=True)
class CellSpec:
    """The calibration cell: robot capsules, obstacles and tracker, with a clearance (m).

    ``capsules_per_link``: capsules fitted around each link's URDF collision meshes (0: none);
    ``capsules``: capsules given as numbers (added to the fitted ones; the only ones of a DH
    robot); ``disabled_pairs``: pairs of link frames never checked against each other;
    ``srdf``: a MoveIt SRDF of the robot whose ``disable_collisions`` pairs are disabled too
    (those of two links with capsules); ``collision_urdf``: for a DH robot, a URDF of the same
    robot (same joint names) whose collision geometry checks the plans.
    """

    clearance_m: float = 0.0
    capsules_per_link: int = 0
    capsules: tuple[Capsule, ...] = ()
    disabled_pairs: tuple[tuple[str, str], ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    tracker: TrackerSpec | None = None
    collision_urdf: str = ""
    srdf: str = ""


@dataclass(frozen=True)
class Workspace:
    """Where the robot may be during calibration (m, rad).

    Every measured point inside the box, the half-spaces and the sphere (the tracker's range);
    every moving joint origin, moving frame (flange, tool) and measured point at
    ``z >= floor_z_m``; the configurations of any two experiments at least
    ``min_joint_distance_rad`` apart (:func:`casadi_design.plan.rules.joint_distance`); every
    joint at least ``joint_limit_margin_rad`` (rad, m for prismatic joints) inside its limits.
    """

    box_min_m: tuple[float, float, float] | None = None
    box_max_m: tuple[float, float, float] | None = None
    half_spaces: tuple[HalfSpace, ...] = ()
    sphere_center_m: tuple[float, float, float] | None = None
    sphere_radius_m: float | None = None
    floor_z_m: float | None = None
    min_joint_distance_rad: float = 0.0
    joint_limit_margin_rad: float = 0.0


@dataclass(frozen=True)
class SolverSettings:
    """Multi-start IPOPT settings; ``ipopt`` options pass through unchanged.

    ``starts``: seeded starts per design; ``criterion_starts``: (criterion, starts) pairs that
    replace it for the designs of those criteria (:func:`seeded_starts`).
    """

    starts: int = 20
    seed: int = 0
    max_iter: int = 3000
    tol: float = 1e-10
    ipopt: tuple[tuple[str, Any], ...] = ()
    criterion_starts: tuple[tuple[str, int], ...] = ()

    def starts_for(self, criterion: str) -> int:
        """The seeded starts of a design of ``criterion``."""
        return seeded_starts(self.starts, self.criterion_starts, criterion)


def seeded_starts(starts: int, criterion_starts: tuple[tuple[str, int], ...], criterion: str) -> int:
    """The seeded starts of a design of ``criterion``: its entry of ``criterion_starts``, or
    ``starts``."""
    return dict(criterion_starts).get(criterion, starts)


def starts_text(starts: int, criterion_starts: tuple[tuple[str, int], ...]) -> str:
    """The seeded starts per design, for people: ``16`` or ``16 (test-pose: 4)``."""
    per = ", ".join(f"{c}: {k}" for c, k in criterion_starts)
    return f"{starts} ({per})" if per else str(starts)


@dataclass(frozen=True)
class HeldSpec:
    """What is known before this design (``--measured``, ``--prior``): experiments already
    measured and a prior on the parameters, whose information every design adds to its own.

    ``q`` (k, n), rad (m for prismatic joints), and ``F`` (k, nF), N (N m): the measured
    experiments; ``prior_names`` and ``prior_covariance`` (SI units per parameter pair): an
    identification's covariance of the parameters it names (those of this problem's
    parameters it does not name have no prior); ``measured_files`` and ``prior_file``: the files
    they were read from; ``prior_q``, ``prior_F`` and ``prior_model_error``: the poses that
    identification used and the unmodelled error's field it estimated (the field correlates
    new poses with those: :mod:`casadi_design.measures.field`)."""

    q: Mat = ()
    F: Mat = ()
    prior_names: tuple[str, ...] = ()
    prior_covariance: Mat | None = None
    measured_files: tuple[str, ...] = ()
    prior_file: str | None = None
    prior_q: Mat = ()
    prior_F: Mat = ()
    prior_model_error: ModelErrorSpec | None = None

    @property
    def k(self) -> int:
        """Number of measured experiments."""
        return len(self.q)

    @property
    def sources(self) -> tuple[str, ...]:
        """Every file it was read from: the measured experiments', then the prior's."""
        return self.measured_files + (() if self.prior_file is None else (self.prior_file,))


@dataclass(frozen=True)
class ProblemSpec:
    """A read and checked problem file: plain data only (see the module docstring)."""

    name: str
    path: str
    description: str
    robot: RobotSpec
    calibration: CalibrationSpec
    measurement: MeasurementSpec
    test_poses: TestPoseSpec
    m_values: tuple[int, ...]
    force: ForceSpec | None
    workspace: Workspace
    criteria: tuple[str, ...]
    parameter_scaling: str = "column"
    solver: SolverSettings = field(default_factory=SolverSettings)
    cell: CellSpec | None = None
    held: HeldSpec | None = None


# --------------------------------------------------------------------------- field reader

def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class _Reader:
    """Typed access to one TOML table with file/field-qualified errors."""

    def __init__(self, path: str, table: dict, section: str, label: str | None = None):
        """``section`` names the keys allowed (:data:`SECTIONS`); ``label`` names the table in
        messages (default ``section``: e.g. ``robot.dh.joints[3]`` for a row)."""
        self.path, self.table, self.section = path, table, label or section
        allowed = SECTIONS[section]
        unknown = sorted(set(table) - allowed) if allowed is not None else []
        if unknown:
            raise self.error(f"unknown key '{unknown[0]}'", f"allowed: {', '.join(sorted(allowed))}")

    def where(self, key: str | None = None) -> str:
        if not self.section:
            return f"{self.path}: {key or 'top level'}"
        return f"{self.path}: [{self.section}]" + (f".{key}" if key else "")

    def error(self, what: str, hint: str, key: str | None = None) -> ProblemError:
        return ProblemError(f"{self.where(key)}: {what}; {hint or 'fix it'}")

    def get(self, key: str, kind: type | tuple, default: Any = ..., hint: str = "") -> Any:
        """The value of ``key``, of type ``kind`` (an int is accepted for float); floats must
        be finite."""
        if key not in self.table:
            if default is ...:
                raise self.error("missing", hint or f"add {key} = ...", key)
            return default
        value = self.table[key]
        if kind is float and _is_number(value):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            name = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
            raise self.error(f"expected {name}, got {value!r}", hint or "fix its type", key)
        if isinstance(value, float) and not math.isfinite(value):
            raise self.error(f"expected a finite number, got {value!r}", hint or "give a finite value", key)
        return value

    def number(self, key: str, default: Any = ..., hint: str = "", positive: bool = False,
               nonnegative: bool = False) -> float:
        value = self.get(key, float, default, hint)
        if value is None or value is default and default is not ...:
            return value
        if positive and not value > 0 or nonnegative and not value >= 0:
            raise self.error(f"must be {'positive' if positive else '>= 0'}, got {value}", hint, key)
        return value

    def integer(self, key: str, default: Any = ..., hint: str = "", low: int = 0,
                high: int | None = None) -> int:
        value = self.get(key, int, default, hint)
        if value is default and default is not ...:
            return value
        if value < low or high is not None and value > high:
            bounds = f">= {low}" if high is None else f"between {low} and {high}"
            raise self.error(f"must be {bounds}, got {value}", hint, key)
        return value

    def names(self, key: str, allowed: tuple[str, ...] | None = None, default: Any = ...,
              hint: str = "", noun: str = "names") -> tuple[str, ...]:
        """A list of distinct strings (among ``allowed`` when given)."""
        value = self.get(key, list, default, hint)
        if value is default and default is not ...:
            return value
        if not all(isinstance(v, str) for v in value):
            raise self.error(f"expected a list of names, got {value!r}", hint or "write names in quotes", key)
        unknown = [v for v in value if allowed and v not in allowed]
        if unknown:
            raise self.error(f"has '{unknown[0]}'", f"allowed: {', '.join(allowed)}", key)
        if not value or len(set(value)) != len(value):
            what = f"distinct entries of {', '.join(allowed)}" if allowed else f"distinct {noun}"
            raise self.error(f"has {value}", f"list {what}", key)
        return tuple(value)

    def array(self, key: str, shape: tuple, default: Any = ..., hint: str = "") -> np.ndarray | Any:
        """A nested list of numbers (int or float, never strings or booleans) of ``shape``
        (None: any length), all finite."""
        value = self.get(key, list, default, hint)
        if value is default and default is not ...:
            return default
        want = " x ".join("any" if w is None else str(w) for w in shape)

        def flat(v: Any, depth: int) -> bool:
            if depth == 0:
                return _is_number(v)
            return isinstance(v, list) and all(flat(x, depth - 1) for x in v)

        if not flat(value, len(shape)):
            raise self.error(f"expected numbers of shape {want}, got {_short(value)}",
                             hint or "give a list of numbers (not strings)", key)
        try:
            arr = np.array(value, dtype=float)
        except ValueError:  # ragged
            arr = np.zeros(0)
        ok = arr.ndim == len(shape) and all(w in (None, d) for w, d in zip(shape, arr.shape))
        if not ok or not np.all(np.isfinite(arr)):
            raise self.error(f"expected finite numbers of shape {want}, got {_short(value)}",
                             hint or f"give {want} numbers", key)
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
            raise self.error(f"expected a table, got {_short(value)}", f"write it as [{self._name(key)}]", key)
        return _Reader(self.path, value, self._name(key))

    def _name(self, key: str) -> str:
        return f"{self.section}.{key}" if self.section else key


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _vec(a: np.ndarray | None) -> Vec | None:
    return None if a is None else tuple(float(v) for v in np.ravel(a))


def _mat(a: np.ndarray | None) -> Mat | None:
    return None if a is None else tuple(tuple(float(v) for v in row) for row in np.asarray(a))


# --------------------------------------------------------------------------- reading

def read_problem(path: str | Path) -> ProblemSpec:
    """Read and check a problem file (UTF-8 TOML; a byte-order mark is accepted)."""
    path = str(path)
    p = Path(path)
    if p.is_dir():
        raise ProblemError(f"{path}: is a folder, not a problem file; give a .toml file, e.g. "
                           "problems/paper_planar_2r.toml")
    try:
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ProblemError(f"{path}: is {size / 1e6:.0f} MB, not a problem file; give a TOML "
                               f"file under {MAX_FILE_BYTES // 1_000_000} MB")
        data = p.read_bytes()
    except FileNotFoundError:
        raise ProblemError(f"{path}: no such problem file; check the path") from None
    except OSError as exc:
        raise ProblemError(f"{path}: cannot be read ({exc.strerror}); check the file") from None
    if b"\0" in data:
        raise ProblemError(f"{path}: is a binary file, not a TOML problem file; give a text file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ProblemError(f"{path}: is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProblemError(f"{path}: not valid TOML ({exc}); check the syntax at that line") from None
    return parse_problem(raw, path)


def parse_problem(raw: dict, path: str = "<problem>") -> ProblemSpec:
    """Check a parsed TOML table ``raw`` and return its plain data."""
    try:
        return _parse(raw, path)
    except ProblemError as exc:
        if str(exc).startswith(f"{path}: "):
            raise
        raise ProblemError(f"{path}: {exc}") from None


def _parse(raw: dict, path: str) -> ProblemSpec:
    top = _Reader(path, raw, "")
    name = top.get("name", str, Path(path).stem)
    description = top.get("description", str, "")
    robot = _robot(top.sub("robot", required=True))
    calibration = _calibration(top.sub("calibration", required=True))
    elastic = calibration.case in ("elastostatic", "both")
    measurement = _measurement(top.sub("measurement", required=True))
    test_poses = _test_poses(top.sub("test_poses", required=True), measurement, len(calibration.wrench_components))
    exp = top.sub("experiments", required=True)
    m_raw = exp.get("m", (int, list), hint="the number of experiments, e.g. m = [1, 5]")
    m_values = tuple(m_raw) if isinstance(m_raw, list) else (m_raw,)
    if not m_values or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in m_values):
        raise exp.error(f"expected positive integers, got {_short(m_raw)}", "e.g. m = [1, 5]", "m")
    if len(set(m_values)) != len(m_values):
        raise exp.error(f"has repeated values {list(m_values)}", "list each m once", "m")
    check_size(path, "[experiments].m", max(m_values), MAX_EXPERIMENTS, BYTES_PER_EXPERIMENT_L2,
               "experiments", "use fewer experiments")
    if elastic:
        force = _force(exp.sub("force", required=True), len(calibration.wrench_components))
    else:
        if "force" in exp.table:
            raise exp.error("a geometric case applies no load", "remove [experiments.force]", "force")
        force = None
    workspace = _workspace(exp.sub("workspace"))
    design = top.sub("design", required=True)
    criteria = design.names("criteria", tuple(CRITERIA), hint="e.g. criteria = [\"test-pose\", \"D\", \"E\"]")
    scaling = design.get("parameter_scaling", str, "column")
    if scaling not in ("column", "none"):
        raise design.error(f"'{scaling}'", "allowed: column, none", "parameter_scaling")
    solver = _solver(top.sub("solver"))
    cell = _cell(top.sub("cell"), robot)
    return ProblemSpec(name, path, description, robot, calibration, measurement, test_poses, m_values,
                       force, workspace, criteria, scaling, solver, cell)


def check_size(path: str, where: str, count: int, limit: int, bytes_per_l2: int, what: str,
               fix: str, L: int | None = None) -> None:
    """Refuse ``count`` above ``limit`` with the memory it would need (for ``L`` parameters,
    or at least 10 when not yet known)."""
    if count <= limit:
        return
    need = count * bytes_per_l2 * (L or 10) ** 2
    raise ProblemError(f"{path}: {where}: {count} {what} would need {'about' if L else 'at least'} "
                       f"{need / 1e9:.3g} GB for the design NLP; {fix} (at most {limit})")


def _robot(r: _Reader) -> RobotSpec:
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
        spec["planar_links_m"] = _vec(links)
    elif given[0] == "urdf":
        urdf = r.get("urdf", str)
        if not urdf.strip():
            raise r.error("is empty", "give the URDF path", "urdf")
        if not urdf.startswith("example-robot-data:") and not Path(urdf).is_absolute():
            urdf = str(Path(r.path).parent / urdf)
        spec["urdf"] = urdf
    else:
        spec.update(_dh(r.sub("dh")))
    if "tool_xyz_m" in r.table or "tool_rpy_deg" in r.table:
        spec["tool_xyz_m"] = _vec(r.array("tool_xyz_m", (3,), np.zeros(3), hint="(x, y, z) in m"))
        spec["tool_rpy_rad"] = _vec(np.radians(r.array("tool_rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw in deg")))
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
                     joint_speeds_deg_s=_vec(speeds),
                     controller=_controller(r.sub("controller")))


def _controller(c: _Reader | None) -> ControllerSpec | None:
    """``[robot.controller]``: joint signs (+1 / -1), offsets (deg), acceleration time (s);
    their lengths are checked against the chain when a program is made."""
    if c is None:
        return None
    signs = c.array("signs", (None,), None, hint="+1 or -1 per joint, e.g. [1, 1, -1, 1, -1, 1]")
    if signs is not None and not np.all(np.abs(signs) == 1):
        raise c.error(f"must be +1 or -1, got {signs.tolist()}", "give +1 or -1 per joint", "signs")
    offsets = c.array("offsets_deg", (None,), None, hint="one offset per joint in deg (mm for prismatic joints)")
    return ControllerSpec(_vec(signs), _vec(offsets),
                          c.number("acceleration_time_s", ControllerSpec.acceleration_time_s,
                                   hint="the time a joint takes to reach its full speed, s", positive=True))


def _dh(d: _Reader) -> dict:
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
            raise d.error(f"row {k + 1} is {_short(row)}", "write each row as an inline table { name = ..., ... }", "joints")
        j = _Reader(d.path, row, "robot.dh.joints", f"robot.dh.joints[{k + 1}]")
        missing = sorted(SECTIONS["robot.dh.joints"] - optional - set(row))
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
            "base_xyz_m": _vec(d.array("base_xyz_m", (3,), np.zeros(3), hint="(x, y, z) in m")),
            "base_rpy_rad": _vec(np.radians(d.array("base_rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw in deg"))),
            "flange_xyz_m": _vec(d.array("flange_xyz_m", (3,), np.zeros(3), hint="(x, y, z) in m")),
            "flange_rpy_rad": _vec(np.radians(d.array("flange_rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw in deg")))}


def _calibration(cal: _Reader) -> CalibrationSpec:
    case = cal.get("case", str, hint=f"allowed: {', '.join(CASES)}")
    if case not in CASES:
        raise cal.error(f"'{case}' is not a calibration case", f"allowed: {', '.join(CASES)}", "case")
    elastic = case in ("elastostatic", "both")
    for key, used in (("parameters", case != "elastostatic"), ("compliant_joints", elastic),
                      ("wrench_components", elastic)):
        if key in cal.table and not used:
            raise cal.error(f"is not used by case '{case}'", "remove it or change the case", key)
    parameters: tuple[str, ...] | str = ()
    if case != "elastostatic":
        value = cal.get("parameters", (list, str), hint="a list of names, e.g. [\"joint1.offset\"], or \"identifiable\"")
        if isinstance(value, str):
            if value != "identifiable":
                raise cal.error(f"'{value}'", "give a list of names or \"identifiable\"", "parameters")
            parameters = value
        else:
            parameters = cal.names("parameters", hint="e.g. [\"joint1.offset\", \"tool.tx\"]")
    return CalibrationSpec(
        case, parameters,
        cal.names("compliant_joints", default=None, hint="joint names, e.g. [\"joint1\", \"joint2\"]",
                  noun="joints") if elastic else None,
        cal.names("wrench_components", WRENCH_ROWS, hint="the wrench components of F, e.g. [\"fx\", \"fy\"]") if elastic else (),
        _prior(cal.sub("prior")),
        _model_error(cal.sub("model_error")),
    )


def _model_error(table: _Reader | None) -> ModelErrorSpec | None:
    """``[calibration.model_error]``: the joints' angle errors (rad) or the field's scale per base
    axis (m), its correlation length (rad, one for every joint or one per joint; checked against
    the robot's joints when it is built), its nugget (m) and, of the base axes' field, the joints'
    shares."""
    if table is None:
        return None
    joints = table.get("angle_rad", (int, float, list), None,
                       hint="each joint's angle error std in rad, e.g. 3e-4, or one per joint")
    angles = () if joints is None else _positive_list(table, "angle_rad", joints,
                                                       "give a positive angle in rad, e.g. 3e-4, or one per joint")
    if angles and table.get("scale_m", (int, float), None) is not None:
        raise table.error("and angle_rad are both given", "give angle_rad (an error of the joint angles) or scale_m "
                          "(an error of each base axis), not both", "scale_m")
    scale = 0.0 if angles else table.number("scale_m", hint="the unmodelled error's std per axis in m, e.g. 2.5e-4",
                                            positive=True)
    value = table.get("length_rad", (int, float, list), hint="a correlation length in rad, e.g. 0.5, or one per joint")
    lengths = _positive_list(table, "length_rad", value, "give a positive length in rad, e.g. 0.5, or a list of one "
                             "per joint")
    nugget = table.number("nugget_m", 0.0, hint="the uncorrelated unmodelled error's std in m, e.g. 2e-5")
    if not nugget >= 0:
        raise table.error(f"is {nugget:g}", "give a std >= 0 in m", "nugget_m")
    value = table.get("shares", (list,), [], hint="each joint's share of the variance, e.g. [0.5, 0.5, 0, 0, 0, 0]")
    try:
        shares = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        shares = np.array([np.nan])
    if shares.size and angles:
        raise table.error("is given with angle_rad", "shares split the base axes' scale_m over the joints; with "
                          "angle_rad each joint has its own angle, leave shares out", "shares")
    if shares.size and not (np.all(np.isfinite(shares) & (shares >= 0)) and abs(shares.sum() - 1.0) < 1e-6):
        raise table.error(f"is {value!r}", "give one share >= 0 per joint, summing to 1 (an additive field), "
                          "or leave it out", "shares")
    return ModelErrorSpec(scale, lengths, nugget, tuple(float(v) for v in shares), angles)


def _positive_list(table: _Reader, key: str, value, fix: str) -> tuple[float, ...]:
    """``value``, one positive number or a list of them, as a tuple; else the error naming ``key``."""
    try:
        v = np.atleast_1d(np.asarray(value, dtype=float)) if not isinstance(value, bool) else np.array([np.nan])
    except (TypeError, ValueError):
        v = np.array([np.nan])
    if v.ndim != 1 or not v.size or not np.all(np.isfinite(v) & (v > 0)):
        raise table.error(f"is {value!r}", fix, key)
    return tuple(float(x) for x in v)


def _prior(prior: _Reader | None) -> PriorSpec | None:
    """``[calibration.prior]``: one positive standard deviation per group given."""
    if prior is None:
        return None
    hints = {"length_m": "a std in m, e.g. 1e-3", "angle_rad": "a std in rad, e.g. 1e-3",
             "offset_rad": "a std in rad, e.g. 0.01", "compliance_rad_per_Nm": "a std in rad/(N m), e.g. 1e-6"}
    values = {k: prior.number(k, None, hint=h, positive=True) for k, h in hints.items()}
    if all(v is None for v in values.values()):
        raise prior.error("gives no standard deviation", f"give one or more of {', '.join(hints)}, "
                          "or remove the table")
    return PriorSpec(**values)


def _measurement(meas: _Reader) -> MeasurementSpec:
    measured = meas.names("components", TWIST_ROWS, hint="e.g. components = [\"x\", \"y\", \"z\"]")
    sigma = meas.number("sigma_m", hint="the measurement noise std in m, e.g. 1e-4", positive=True)
    if sigma > MAX_SIGMA_M:
        raise meas.error(f"is {sigma:g} m, above {MAX_SIGMA_M:g} m (no tracker is that noisy)",
                         "give the noise std in m, e.g. 1e-4 for 0.1 mm", "sigma_m")
    markers = meas.array("markers_m", (None, 3), None, hint="one row (x, y, z) in m per marker, in the measured frame")
    if markers is not None and len(markers) == 0:
        raise meas.error("is empty", "give one row (x, y, z) in m per marker, or remove it", "markers_m")
    if markers is not None and not any(c in ("x", "y", "z") for c in measured):
        raise meas.error("markers need position components", "measure x, y or z, or remove markers_m", "markers_m")
    return MeasurementSpec(measured, sigma, _mat(markers), _mat(_whitening(meas, measured, markers, sigma)))


def _whitening(meas: _Reader, measured: tuple[str, ...], markers, sigma: float) -> np.ndarray | None:
    """``sigma * Sigma^-1/2`` for the per-value noise of one experiment (None: all values sigma).

    ``sigma_axes_m`` gives a std per x, y, z axis, ``sigma_rad`` the orientation std,
    ``covariance`` the full d x d covariance (m^2, rad^2).
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
        asym = float(np.max(np.abs(C - C.T)))
        if asym > SYMMETRY_RTOL * float(np.max(np.abs(C))):
            raise meas.error(f"is not symmetric (largest |C - C^T| = {asym:.3g})",
                             "give a symmetric covariance (m^2, rad^2)", "covariance")
        try:
            Lc = np.linalg.cholesky((C + C.T) / 2)
        except np.linalg.LinAlgError:
            raise meas.error("is not positive definite", "give a valid covariance (m^2, rad^2)", "covariance") from None
        return sigma * np.linalg.inv(Lc)
    axes = meas.array("sigma_axes_m", (3,), None, hint="std of x, y, z in m")
    srad = meas.number("sigma_rad", None, hint="the orientation noise std in rad", positive=True)
    if axes is None and srad is None:
        return None
    if axes is not None and not np.all((axes > 0) & (axes <= MAX_SIGMA_M)):
        raise meas.error(f"must be positive and at most {MAX_SIGMA_M:g} m, got {axes.tolist()}",
                         "give standard deviations in m", "sigma_axes_m")
    std = [axes["xyz".index(c)] if axes is not None else sigma for _ in range(k) for c in pos] + [srad] * len(rot)
    return np.diag(sigma / np.array(std, dtype=float))


def _test_poses(tp: _Reader, meas: MeasurementSpec, nF: int) -> TestPoseSpec:
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
        spec.update(kind="joints", joints_rad=_mat(q))
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
        spec.update(kind="planar", points_m=_mat(pts), elbow=elbow)
        s, segments = len(pts), None
    if nF == 0 and any(k in tp.table for k in ("force_N", "forces_N", "segment_forces_N")):
        raise tp.error("a geometric case has no machining load in its model", "remove force_N / forces_N")
    loads = [k for k in ("force_N", "forces_N", "segment_forces_N") if k in tp.table]
    if len(loads) > 1:
        raise tp.error(f"has {', '.join(loads)}", "give one of them")
    if "segment_forces_N" in tp.table:
        if segments is None:
            raise tp.error("needs a path", "use force_N or forces_N", "segment_forces_N")
        spec["segment_forces_N"] = _mat(tp.array("segment_forces_N", (segments, nF),
                                                 hint=f"one row of {nF} wrench components per path segment"))
    elif "forces_N" in tp.table:
        spec["forces_N"] = _mat(tp.array("forces_N", (s, nF), hint=f"one row of {nF} wrench components per test pose"))
    elif "force_N" in tp.table:
        spec["force_N"] = _vec(tp.array("force_N", (nF,), hint=f"{nF} wrench components"))
    elif nF:
        raise tp.error("missing force_N", f"give the machining wrench, {nF} components in N (N m)", "force_N")
    for key in loads:
        _check_load(tp, key, spec[key], "give the machining wrench in N and N m")
    return TestPoseSpec(components=components, **spec)


def _check_load(r: _Reader, key: str, values, fix: str) -> None:
    """A wrench's components (N, N m) of the field ``key`` at most :data:`MAX_LOAD_N` in size."""
    largest = float(np.max(np.abs(np.asarray(values, dtype=float))))
    if largest > MAX_LOAD_N:
        raise r.error(f"has {largest:g}, above {MAX_LOAD_N:g} N (N m)", fix, key)


def _path(tp: _Reader) -> dict:
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
    return {"kind": "path", "path_kind": kind, "path_points_m": _mat(pts), "path_nodes": nodes,
            "tool_rpy_rad": None if rpy is None else _vec(np.radians(rpy)),
            "seed_q_rad": None if seed is None else _vec(np.radians(seed)),
            "_s": nodes, "_segments": 1 if kind == "arc" else len(pts) - 1 if kind != "points" else len(pts)}


def _force(f: _Reader, nF: int) -> ForceSpec:
    mode = f.get("mode", str, hint=f"allowed: {', '.join(FORCE_MODES)}")
    if mode not in FORCE_MODES:
        raise f.error(f"'{mode}'", f"allowed: {', '.join(FORCE_MODES)}", "mode")
    load_point = _vec(f.array("load_point_m", (3,), np.zeros(3), hint="(x, y, z) in the measured frame, m"))
    if mode == "fixed":
        vec = f.array("vector_N", (nF,), hint=f"{nF} wrench components, N (N m)")
        if not np.any(vec):
            raise f.error("is zero: a zero load identifies no compliance", "give the applied load", "vector_N")
        _check_load(f, "vector_N", vec, "give the applied load in N and N m")
        if "magnitude_N" in f.table:
            raise f.error("is not used with mode = \"fixed\"", "remove it", "magnitude_N")
        return ForceSpec(mode, float(np.linalg.norm(vec)), _vec(vec), (), load_point)
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
        direction = _vec(u / np.linalg.norm(u))
    elif "direction" in f.table:
        raise f.error(f"is only used with mode = \"direction\", not \"{mode}\"", "remove it", "direction")
    return ForceSpec(mode, magnitude, (), direction, load_point)


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
            raise w.error(f"entry {k} is {_short(hs)}", "write { normal = [nx, ny, nz], offset_m = b } for normal . p >= b", "half_spaces")
        h = _Reader(w.path, hs, "experiments.workspace.half_spaces")
        normal = h.array("normal", (3,), hint="a non-zero 3-vector")
        if not np.linalg.norm(normal) > 0:
            raise h.error("is zero", "give a non-zero 3-vector", "normal")
        spaces.append(HalfSpace(_vec(normal), h.number("offset_m", hint="b in normal . p >= b, m"), f"half-space {k + 1}"))
    center = w.array("sphere_center_m", (3,), None, hint="(x, y, z) of the tracker, m")
    radius = w.number("sphere_radius_m", None, hint="the tracker's range, m", positive=True)
    if (center is None) != (radius is None):
        raise w.error("give both sphere_center_m and a positive sphere_radius_m", "or neither")
    return Workspace(
        _vec(lo), _vec(hi), tuple(spaces), _vec(center), radius,
        w.number("floor_z_m", None, hint="height of the floor, m"),
        w.number("min_joint_distance_rad", 0.0, hint="a distance in rad", nonnegative=True),
        w.number("joint_limit_margin_rad", 0.0, hint="a margin inside the joint limits in rad, e.g. 0.05",
                 nonnegative=True),
    )


def _entries(c: _Reader, key: str, example: str) -> list[_Reader]:
    """The inline tables of the list ``key`` of ``c``, each as a reader named ``key[k]``."""
    out = []
    for k, row in enumerate(c.get(key, list, [])):
        if not isinstance(row, dict):
            raise c.error(f"entry {k + 1} is {_short(row)}", f"write each entry as {example}", key)
        out.append(_Reader(c.path, row, f"{c.section}.{key}", f"{c.section}.{key}[{k + 1}]"))
    return out


def _cell(c: _Reader | None, robot: RobotSpec) -> CellSpec | None:
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
            raise c.error(f"entry {k + 1} is {_short(pair)}", "write each as [\"link_a\", \"link_b\"]", "disabled_pairs")
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
        tracker = TrackerSpec(_vec(t.array("position_m", (3,), hint="the tracker's head, world, m")),
                              _vec(axis / np.linalg.norm(axis)), math.radians(acceptance))
    urdf = c.get("collision_urdf", str, "")
    if urdf and robot.source != "dh":
        raise c.error("is only used with a DH robot", "remove it: the robot's own URDF meshes are used", "collision_urdf")
    urdf, srdf = (_file_of(c, name) for name in (urdf, c.get("srdf", str, "")))
    return CellSpec(c.number("clearance_m", 0.0, hint="the smallest distance kept between bodies, m", nonnegative=True),
                    per_link, capsules, tuple(pairs), tuple(obstacles), tracker, urdf, srdf)


def _file_of(c: _Reader, path: str) -> str:
    """A file named in the problem file: ``example-robot-data:...``, absolute, or relative to
    the problem file's folder ("" stays "")."""
    if path and not path.startswith("example-robot-data:") and not Path(path).is_absolute():
        return str(Path(c.path).parent / path)
    return path


def _solver(table: _Reader | None) -> SolverSettings:
    if table is None:
        return SolverSettings()
    d = SolverSettings()
    ipopt = table.sub("ipopt")
    options = tuple(sorted(ipopt.table.items())) if ipopt else ()
    for key, value in options:
        if not isinstance(value, (int, float, str)) or isinstance(value, float) and not math.isfinite(value):
            raise ipopt.error(f"expected a number or a string, got {_short(value)}",
                              "see the IPOPT options reference", key)
    per = table.sub("criterion_starts")
    criterion_starts = tuple((c, per.integer(c, ..., "give its designs' seeded starts, e.g. test-pose = 4",
                                             low=1, high=100_000)) for c in per.table) if per else ()
    return SolverSettings(
        starts=table.integer("starts", d.starts, "the number of IPOPT starts", low=1, high=100_000),
        criterion_starts=criterion_starts,
        seed=table.integer("seed", d.seed, "a non-negative integer", low=0, high=2**63 - 1),
        max_iter=table.integer("max_iter", d.max_iter, "IPOPT iterations per start", low=0, high=10**9),
        tol=table.number("tol", d.tol, "IPOPT's tolerance, e.g. 1e-10", positive=True),
        ipopt=options,
    )


def spec_digest_blob(spec: ProblemSpec) -> bytes:
    """A stable byte string of ``spec`` (for keys of resumed sweeps and worker caches)."""
    return repr(spec).encode()

