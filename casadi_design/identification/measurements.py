"""Measurement CSVs: a plan CSV of ``solve`` with the measured coordinates appended, or the
files real data comes in.

The joint columns (``<joint>_deg`` / ``_rad``, or ``q1_deg``...) and load columns are those of a
plan (:func:`casadi_design.records.export.read_plan_table`); the measured coordinates follow:
``meas_x_mm, meas_y_mm, meas_z_mm`` for one measured point, ``meas1_x_mm, ..., measK_z_mm`` for
the K markers of ``markers_m`` in their order, one column per measured position component
(``[measurement].components``); ``_m`` instead of ``_mm`` for metres. An empty cell is a marker
the tracker did not see; a marker's coordinates are all given or all empty.

Real files (:class:`FileFormat`): joint columns by their bare names (``torso_lift_joint``) in
``joint_units``; coordinate columns without a unit (``meas1_x``) in ``units``; a column map from
the file's names to these; FIGAROH's layout (``x1, y1, z1, ..., x4, y4, z4`` in m, bare joint
names in rad and m) recognised by its header. Columns of neither kind are ignored with a note;
joint readings up to ``limit_tolerance`` past a joint limit are accepted with a note. A file
separated by ``;`` is read with ``,`` as the decimal point, with a note. Without the measured
coordinates, the message names the file's columns that look like them (``x``, ``X``,
``measurement_x``, ``x1``...) and the ``--columns`` that reads them.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..errors import ProblemError
from ..problem.build import Problem
from ..records.export import (
    LIMIT_TOL,
    PlanFile,
    check_joint_limits,
    is_prismatic,
    joint_units,
    read_plan_file,
    read_plan_table,
)

#: The position components a tracker measures, in the order of the columns.
AXES = ("x", "y", "z")
#: Default of ``--limit-tolerance`` (rad or m): readings this far past a limit are accepted with
#: a note (a real encoder reads past the URDF's limit: TIAGo's torso 0.35018 m of 0.35 m).
LIMIT_TOLERANCE = 1e-3
#: Largest measured coordinate (m): a laser tracker reaches 80 m, motion capture a room.
MAX_COORDINATE_M = 100.0
#: Orientation columns of a 6-D pose of the measured frame (beside its position ``meas_x, meas_y,
#: meas_z``): a unit quaternion, or roll, pitch, yaw (``R = Rz(yaw) Ry(pitch) Rx(roll)``, as in
#: URDF and ROS) with ``_rad`` or ``_deg``.
ORIENTATIONS = {"quaternion": ("meas_qw", "meas_qx", "meas_qy", "meas_qz"),
                "rpy": ("meas_roll", "meas_pitch", "meas_yaw")}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180}
#: A quaternion whose norm is further from 1 is not a rotation (a wrong column).
QUATERNION_NORM_TOL = 1e-3
#: A column name that plausibly holds a measured coordinate (lower case): the axis, maybe after a
#: word such as ``measurement_`` and before a marker number (``x``, ``measurement_x``, ``x1``).
COORDINATE_GUESS = re.compile(r"(?:(?:meas|measured|measurement|tracker|pos|position)[ _-]?)?"
                              r"(?P<axis>[xyz])[ _-]?(?P<marker>\d*)")
#: Units of coordinates (SI per unit) and of bare joint columns.
COORDINATE_UNITS = {"mm": 1e-3, "m": 1.0}
REVOLUTE_UNITS = {"rad": 1.0, "deg": math.pi / 180}
PRISMATIC_UNITS = {"m": 1.0, "mm": 1e-3}


@dataclass(frozen=True)
class FileFormat:
    """How to read a measurement file (module docstring).

    units : "mm" or "m": coordinate columns without a unit suffix (None: FIGAROH's layout in m,
        other files must name the unit).
    joint_units : units of bare joint columns: one of rad / deg (revolute) and one of m / mm
        (prismatic), default rad and m.
    columns : (file's name, name read here) pairs, e.g. ("x1", "meas1_x").
    limit_tolerance : rad or m past a joint limit accepted with a note.
    """

    units: str | None = None
    joint_units: tuple[str, ...] = ("rad", "m")
    columns: tuple[tuple[str, str], ...] = ()
    limit_tolerance: float = LIMIT_TOLERANCE

    def __post_init__(self):
        if self.units is not None and self.units not in COORDINATE_UNITS:
            raise ProblemError(f"--units {self.units}: allowed: {', '.join(COORDINATE_UNITS)}")
        for u in self.joint_units:
            if u not in REVOLUTE_UNITS and u not in PRISMATIC_UNITS:
                raise ProblemError(f"--joint-units {u}: allowed: rad or deg (revolute joints), m or mm "
                                   "(prismatic joints), e.g. --joint-units deg,mm")
        if not (math.isfinite(self.limit_tolerance) and self.limit_tolerance >= 0):
            raise ProblemError(f"--limit-tolerance {self.limit_tolerance:g}: give a number >= 0 (rad or m)")

    @property
    def revolute(self) -> str:
        return next((u for u in self.joint_units if u in REVOLUTE_UNITS), "rad")

    @property
    def prismatic(self) -> str:
        return next((u for u in self.joint_units if u in PRISMATIC_UNITS and u not in REVOLUTE_UNITS), "m")


def parse_columns(text: str) -> tuple[tuple[str, str], ...]:
    """``--columns x1=meas1_x,y1=meas1_y`` -> (("x1", "meas1_x"), ("y1", "meas1_y"))."""
    pairs = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        theirs, _, ours = item.partition("=")
        if not theirs.strip() or not ours.strip():
            raise ProblemError(f"--columns: '{item}' is not FILE_COLUMN=OUR_COLUMN; give e.g. "
                               "--columns x1=meas1_x,y1=meas1_y,z1=meas1_z")
        pairs.append((theirs.strip(), ours.strip()))
    return tuple(pairs)


@dataclass(frozen=True, eq=False)
class Measurements:
    """The rows of a measurement CSV.

    Attributes
    ----------
    path : str, the file.
    lines : tuple of int, the line of the file of each row (1-based).
    Q : ndarray, shape (m, n), rad (m): joint values;  F : ndarray, shape (m, nF), N (N m).
    P_m : ndarray, shape (m, k, 3), m: measured coordinates of the k measured points, in the
        frame of the measurements; NaN for a marker not seen and for a component not measured.
    notes : what the reader did that a person should know (columns ignored, the layout
        recognised, readings past a joint limit).
    rounds : ndarray of int, shape (m,), or None: the file of each row (0, 1, ...: rounds
        measured one after the other; :func:`rounds_of`), None: one file.
    paths : the file of each round (``path`` names them all).
    same_frame : the rounds share one tracker frame (else each has its own: the tracker moved).
    """

    path: str
    lines: tuple[int, ...]
    Q: np.ndarray
    F: np.ndarray
    P_m: np.ndarray
    notes: tuple[str, ...] = ()
    rounds: np.ndarray | None = None
    paths: tuple[str, ...] = ()
    same_frame: bool = False

    def subset(self, rows: np.ndarray) -> "Measurements":
        """The rows ``rows`` (indices or a bool mask) of these measurements."""
        i = np.arange(self.m)[rows]
        return Measurements(self.path, tuple(self.lines[k] for k in i), self.Q[i], self.F[i],
                            self.P_m[i], self.notes, None if self.rounds is None else self.rounds[i], self.paths,
                            self.same_frame)

    @property
    def frames(self) -> int:
        """Number of tracker frames the rows were measured in."""
        return 1 if self.rounds is None or self.same_frame else len(self.paths)

    @property
    def frame_of(self) -> np.ndarray:
        """The tracker frame of each row (0..frames-1), shape (m,)."""
        return np.zeros(self.m, dtype=int) if self.frames == 1 else self.rounds

    @property
    def m(self) -> int:
        return len(self.Q)

    @property
    def seen(self) -> np.ndarray:
        """Bool (m, k): the markers measured in each row."""
        return np.any(np.isfinite(self.P_m), axis=2)

    def row(self, i: int) -> str:
        return f"{self.paths[self.rounds[i]] if self.paths else self.path}: row {self.lines[i]}"


def file_sha256(path: str) -> str | None:
    """The SHA-256 of a measurement file's bytes (None when it cannot be read): what names it
    wherever it is copied (``identification.json``'s sources; a later ``--measured`` of the
    same rows, :mod:`.held`)."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def rounds_of(files: list[Measurements], same_frame: bool = False) -> Measurements:
    """The rows of several measurement files as one set, each file a round measured in a frame
    of its own (the tracker moved between rounds) unless ``same_frame``."""
    if len(files) == 1:
        return files[0]
    rounds = np.concatenate([np.full(f.m, k) for k, f in enumerate(files)])
    notes = tuple(f"{f.path}: {n}" for f in files for n in f.notes)
    return Measurements(" + ".join(f.path for f in files), tuple(line for f in files for line in f.lines),
                        np.vstack([f.Q for f in files]), np.vstack([f.F for f in files]),
                        np.concatenate([f.P_m for f in files]), notes, rounds, tuple(f.path for f in files),
                        same_frame)


def measured_axes(problem: Problem) -> tuple[int, ...]:
    """Indices (into x, y, z) of the measured position components."""
    return tuple(AXES.index(c) for c in problem.spec.measurement.components if c in AXES)


def measurement_columns(problem: Problem) -> list[list[str]]:
    """Per measured point, its column names without unit, e.g. ``[["meas_x", "meas_y"]]``."""
    axes = [AXES[a] for a in measured_axes(problem)]
    if problem.spec.measurement.markers_m is None:
        return [[f"meas_{a}" for a in axes]]
    return [[f"meas{c + 1}_{a}" for a in axes] for c in range(len(problem.model.markers_m))]


def _has_measured(header: list[str]) -> bool:
    """Whether ``header`` has a column of ours for a measured point (``meas_x_mm``, ``meas1_x``,
    ``meas_qw``...; not a file's own ``measurement_x``)."""
    return any(re.match(r"meas\d*_", h) for h in header)


def _figaroh(header: list[str]) -> bool:
    """FIGAROH's layout: x1, y1, z1 (then x2 ...) and no column of ours for the coordinates."""
    return {"x1", "y1", "z1"} <= set(header) and not _has_measured(header)


def _reading(problem: Problem, header: list[str], fmt: FileFormat, path: str,
             points: list[list[str]]) -> tuple[dict[str, str], dict[str, float], list[str]]:
    """How to read ``header``: the renames (file -> ours, with unit), the SI per unit of each of
    our coordinate columns (those of ``points``) and orientation angles, and notes."""
    notes: list[str] = []
    columns = dict(fmt.columns)
    units = fmt.units
    if _figaroh(header) and not columns:
        k = 1 if problem.spec.measurement.markers_m is None else len(problem.model.markers_m)
        base = (lambda c: "meas") if problem.spec.measurement.markers_m is None else (lambda c: f"meas{c}")
        columns = {f"{a}{c}": f"{base(c)}_{a}" for c in range(1, k + 1) for a in AXES}
        units = units or "m"
        notes.append(f"read as FIGAROH's layout: {', '.join(columns)} as the measured point"
                     + ("s" if k > 1 else "") + f" in {units}, bare joint names in "
                     f"{fmt.revolute} / {fmt.prismatic}")
    ours = [c for point in points for c in point]
    robot = problem.robot
    rename: dict[str, str] = {}
    scales: dict[str, float] = {}
    for h in header:
        name = columns.get(h, h)
        unit = None
        for u in COORDINATE_UNITS:
            if name.endswith(f"_{u}") and name[: -len(u) - 1] in ours:
                name, unit = name[: -len(u) - 1], u
                break
        angle = next((a for a in ORIENTATIONS["rpy"] if name in (f"{a}_rad", f"{a}_deg")), None)
        if angle is not None:
            rename[h] = f"{angle}_rad"
            scales[f"{angle}_rad"] = ANGLE_UNITS[name.rpartition("_")[2]]
        elif name in ORIENTATIONS["quaternion"]:
            if name != h:
                rename[h] = name
        elif name in ours:
            if unit is None:
                if units is None:
                    raise ProblemError(f"{path}: column '{h}' has no unit; name it {name}_mm or {name}_m, "
                                       "or give the unit of the coordinates with --units mm or --units m")
                unit = units
            rename[h] = f"{name}_mm"
            scales[f"{name}_mm"] = COORDINATE_UNITS[unit]
        elif name in robot.joints:
            k = robot.joints.index(name)
            unit = fmt.prismatic if is_prismatic(problem, k) else fmt.revolute
            si, people, _ = joint_units(problem, k)
            rename[h] = f"{name}_{si}" if unit in ("rad", "m") else f"{name}_{people}"
        elif name != h:
            rename[h] = name
    return rename, scales, notes


def _guessed_columns(header: list[str], taken: set[str], points: list[list[str]]) -> dict[str, str]:
    """The file's columns (not in ``taken``) that plausibly hold our coordinate columns ``points``
    (:data:`COORDINATE_GUESS`), ours -> theirs; empty unless each has exactly one candidate:
    for one point a column without a marker number (else with number 1), for several the
    point's number."""
    found = {}
    for c, point in enumerate(points):
        for ours in point:
            axis = ours.rpartition("_")[2]
            candidates = {}
            for h in header:
                guess = COORDINATE_GUESS.fullmatch(h.lower())
                if h not in taken and guess and guess["axis"] == axis:
                    candidates.setdefault(guess["marker"], []).append(h)
            numbers = ("", "1") if len(points) == 1 else (str(c + 1),)
            given = next((candidates[k] for k in numbers if k in candidates), [])
            if len(given) != 1:
                return {}
            found[ours] = given[0]
    return found


def _missing_message(path: str, header: list[str], fmt: FileFormat, rename: dict[str, str],
                     known: set[str], points: list[list[str]], missing: str) -> str:
    """The one-line message on a missing coordinate column ``missing``: the ``--columns`` that
    reads the file's columns that look like the coordinates, when it has them."""
    names = ", ".join(f"{c}_mm" for point in points for c in point)
    kept = [(t, o) for t, o in fmt.columns if t in header]  # the user's map of the file's columns
    taken = {h for h in header if rename.get(h, h) in known} | {t for t, _ in kept}
    guessed = _guessed_columns(header, taken, [[c for c in point if c not in {o for _, o in kept}]
                                               for point in points])
    if not guessed:
        return (f"{path}: missing column '{missing}'; append the measured coordinates in mm: {names} "
                "(or name the file's columns with --columns)")
    pairs = [f"{t}={o}" for t, o in kept] + [f"{t}={o}" for o, t in guessed.items()]
    units = f"--units {fmt.units}" if fmt.units else "--units mm (or --units m)"
    return (f"{path}: missing column '{missing}'; its columns {', '.join(guessed.values())} look like the "
            f"measured coordinates: read them with --columns {','.join(pairs)} {units}, or rename them "
            f"{', '.join(f'{o}_mm' for o in guessed)} (_m for metres)")


def _orientation(problem: Problem, header: list[str], fmt: FileFormat, path: str) -> str | None:
    """The orientation convention of ``ORIENTATIONS`` whose columns the file has (after the
    column map), or None for positions only."""
    columns = dict(fmt.columns)
    names = {columns.get(h, h).removesuffix("_rad").removesuffix("_deg") for h in header}
    given = [c for c, cols in ORIENTATIONS.items() if any(n in names for n in cols)]
    if not given:
        return None
    convention = given[0]
    missing = [n for n in ORIENTATIONS[convention] if n not in names]
    if len(given) > 1 or missing:
        raise ProblemError(f"{path}: the orientation columns are incomplete or of two kinds; give "
                           + " or ".join(", ".join(cols) + (" (_rad or _deg)" if c == "rpy" else "")
                                         for c, cols in ORIENTATIONS.items()))
    markers = problem.spec.measurement.markers_m
    spread = 0 if markers is None else np.linalg.matrix_rank(
        np.asarray(markers) - np.mean(markers, axis=0), tol=1e-6)
    if spread < 2 or set(problem.spec.measurement.components) != set(AXES):
        raise ProblemError(
            f"{path}: has 6-D poses ({', '.join(ORIENTATIONS[convention])}); they are read as the "
            f"markers of [measurement].markers_m placed by each pose, so {problem.path} needs "
            "components = [\"x\", \"y\", \"z\"] and at least three markers not on a line, in the "
            "measured frame (m), e.g. markers_m = [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]")
    return convention


def pose_rotations(convention: str, values: np.ndarray) -> np.ndarray:
    """Rotation matrices (m, 3, 3) of ``values`` (m, 4) quaternions ``w, x, y, z`` (normalised)
    or (m, 3) roll, pitch, yaw (rad): ``R = Rz(yaw) Ry(pitch) Rx(roll)``, Pinocchio's."""
    if convention == "quaternion":
        return np.array([pin.Quaternion(*(float(v) for v in row)).normalized().matrix() for row in values])
    return np.array([pin.rpy.rpyToMatrix(*(float(v) for v in row)) for row in values])


def read_measurements(problem: Problem, path: PlanFile | str, fmt: FileFormat = FileFormat()) -> Measurements:
    """Read a measurement CSV of ``problem`` (its path, or the
    :class:`~casadi_design.records.export.PlanFile` already read) in the format ``fmt`` (module
    docstring).

    Raises
    ------
    ProblemError
        The errors of a plan CSV, and: orientation components measured, incomplete orientation
        columns, 6-D poses for a problem without three markers, a quaternion not of norm 1, a
        pose partly empty, a missing coordinate
        column, a marker with some coordinates empty, a row without any measured point, joint
        values beyond ``fmt.limit_tolerance`` outside the joint limits (one line each, naming
        the file, row and column as the file spells it).
    """
    components = problem.spec.measurement.components
    if any(c not in AXES for c in components):
        raise ProblemError(
            f"{problem.path}: [measurement].components has {list(components)}; identify reads "
            "measured positions (x, y, z) only; measure positions, e.g. three markers for the pose")
    plan = path if isinstance(path, PlanFile) else read_plan_file(path)
    path, header = plan.path, plan.header
    convention = _orientation(problem, header, fmt, path)
    columns = measurement_columns(problem) if convention is None else [[f"meas_{a}" for a in AXES]]
    names = tuple(f"{c}_mm" for point in columns for c in point)
    angles = () if convention is None else tuple(
        n + ("_rad" if convention == "rpy" else "") for n in ORIENTATIONS[convention])
    hint = ", ".join(names) + " (measured coordinates, mm; _m for metres)"
    rename, scales, notes = _reading(problem, header, fmt, path, columns)
    notes = [*plan.notes, *notes]
    Q, F, values, lines = read_plan_table(problem, plan, names + angles, hint, rename, ignore_unknown=True)
    spelled = {ours: theirs for theirs, ours in rename.items()}
    known = set(names) | set(angles) | _plan_columns(problem)
    missing = [c for c in names if c not in values]
    if missing:
        raise ProblemError(_missing_message(path, header, fmt, rename, known, columns, missing[0]))
    ignored = [h for h in header if rename.get(h, h) not in known]
    if ignored:
        notes.append(f"ignored column{'s' if len(ignored) > 1 else ''} {', '.join(ignored)} "
                     "(neither a joint, a load nor a measured coordinate of this problem)")
    m, axes = len(Q), measured_axes(problem)
    P = np.full((m, len(columns), 3), np.nan)
    for c, point in enumerate(columns):
        point = [f"{name}_mm" for name in point]
        block = np.column_stack([values[name] * scales.get(name, 1e-3) for name in point])
        given = np.isfinite(block)
        partial = np.flatnonzero(given.any(axis=1) & ~given.all(axis=1))
        if partial.size:
            i = int(partial[0])
            empty = spelled.get(point[int(np.flatnonzero(~given[i])[0])], point[int(np.flatnonzero(~given[i])[0])])
            raise ProblemError(f"{path}: row {lines[i]}, column '{empty}': empty while the other "
                               f"coordinates of the point are given; give all of "
                               f"{', '.join(spelled.get(n, n) for n in point)} "
                               + ("or leave all empty (a marker the tracker did not see)" if len(columns) > 1 else
                                  "or delete the row (its point was not measured)"))
        far = np.flatnonzero(np.nan_to_num(np.abs(block)).max(axis=1) > MAX_COORDINATE_M)
        if far.size:
            i = int(far[0])
            a = int(np.nanargmax(np.abs(block[i])))
            name = spelled.get(point[a], point[a])
            raise ProblemError(f"{path}: row {lines[i]}, column '{name}': {block[i, a]:.6g} m from the "
                               f"tracker's origin, beyond {MAX_COORDINATE_M:g} m; check the value and the "
                               "unit of the coordinates (_mm or _m in the column name, or --units)")
        P[:, c, list(axes)] = block
    if convention is not None:
        P = _posed_markers(problem, path, convention, P[:, 0], values, angles, spelled, scales, lines)
        notes.append(f"read 6-D poses ({', '.join(spelled.get(a, a) for a in angles)}) as the "
                     f"{len(problem.model.markers_m)} markers of [measurement].markers_m placed by each pose")
    blind = np.flatnonzero(~np.any(np.isfinite(P), axis=(1, 2)))
    if blind.size:
        raise ProblemError(f"{path}: row {lines[int(blind[0])]}: no measured coordinate in "
                           f"{', '.join(spelled.get(n, n) for n in names)}; fill them in or delete the row")
    notes += check_joint_limits(problem, plan, Q, lines, fmt.limit_tolerance, rename)
    return Measurements(path, tuple(lines), Q, F, P, tuple(notes))


def read_experiments(problem: Problem, path: PlanFile | str, *, limits: bool = True,
                     ignore_unknown: bool = False) -> tuple[np.ndarray, np.ndarray, PlanFile]:
    """The experiments of a plan or a measurement CSV (its path, or the file already read):
    ``Q`` (k, n), rad (m), ``F`` (k, nF), N (N m), and the file as read (its ``measured``
    column). A file whose joints are named without a unit (real data) is read in rad and m:
    with measured coordinates (FIGAROH's layout, ``meas...`` columns) as ``identify`` reads it
    (:func:`read_measurements`), without them as a list of postures (a controller's log), its
    other columns ignored; there readings up to :data:`LIMIT_TOLERANCE` past a joint limit are
    accepted. A plan's joint values outside the joint limits are refused with ``limits``
    (:func:`~casadi_design.records.export.check_joint_limits`), and its unknown columns unless
    ``ignore_unknown``.

    Raises
    ------
    ProblemError
        The errors of :func:`~casadi_design.records.export.read_plan_table` and
        :func:`read_measurements` (one line naming the file, row and column).
    """
    plan = path if isinstance(path, PlanFile) else read_plan_file(path)
    header, joints = plan.header, problem.robot.joints
    bare = any(j in header for j in joints)
    if bare and (_figaroh(header) or _has_measured(header)):
        meas = read_measurements(problem, plan)
        return meas.Q, meas.F, plan
    rename = {j: f"{j}_{joint_units(problem, k)[0]}" for k, j in enumerate(joints) if bare}
    Q, F, _, lines = read_plan_table(problem, plan, rename=rename, ignore_unknown=ignore_unknown or bare)
    if limits or bare:
        check_joint_limits(problem, plan, Q, lines, LIMIT_TOLERANCE if bare else LIMIT_TOL, rename)
    return Q, F, plan


def _plan_columns(problem: Problem) -> set[str]:
    """The names of a plan's own columns (joints in every unit, loads, bookkeeping)."""
    from ..records.export import CLEARANCE_COLUMNS, POSITION_COLUMNS, force_columns

    names = {"experiment", *POSITION_COLUMNS, *CLEARANCE_COLUMNS, *force_columns(problem)}
    for k, j in enumerate(problem.robot.joints):
        si, people, _ = joint_units(problem, k)
        names |= {f"{base}_{u}" for base in (f"q{k + 1}", j) for u in (si, people)}
    return names


def _posed_markers(problem: Problem, path: str, convention: str, p: np.ndarray, values: dict,
                   angles: tuple[str, ...], spelled: dict[str, str], scales: dict[str, float],
                   lines: list[int]) -> np.ndarray:
    """The markers (m, k, 3), m, of ``markers_m`` at the measured poses: ``p + R c`` with
    ``p`` (m, 3) the measured position and ``R`` the orientation read from the ``angles``
    columns; a row with the pose left empty is a pose not seen (NaN)."""
    A = np.column_stack([values[a] * scales.get(a, 1.0) for a in angles])
    given = np.isfinite(A).all(axis=1)
    bad = np.flatnonzero(np.isfinite(A).any(axis=1) & ~given | (np.isfinite(p).all(axis=1) != given))
    if bad.size:
        raise ProblemError(f"{path}: row {lines[int(bad[0])]}: the pose is partly empty; give its "
                           f"position and {', '.join(spelled.get(a, a) for a in angles)}, or leave "
                           "all empty (a pose not seen)")
    if convention == "quaternion":
        norm = np.linalg.norm(np.where(given[:, None], A, 1.0), axis=1)
        off = np.flatnonzero(given & (np.abs(norm - 1) > QUATERNION_NORM_TOL))
        if off.size:
            i = int(off[0])
            raise ProblemError(f"{path}: row {lines[i]}: the quaternion "
                               f"({', '.join(spelled.get(a, a) for a in angles)}) has norm {norm[i]:.6g}, "
                               "not 1; give w, x, y, z of a unit quaternion in those columns")
    identity = [1.0, 0.0, 0.0, 0.0] if convention == "quaternion" else [0.0, 0.0, 0.0]
    R = pose_rotations(convention, np.where(given[:, None], A, identity))
    markers = np.asarray(problem.model.markers_m, dtype=float)
    P = p[:, None, :] + np.einsum("mij,kj->mki", R, markers)
    P[~given] = np.nan
    return P
