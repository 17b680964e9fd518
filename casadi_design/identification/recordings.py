"""Recordings of points fixed in an artefact: configurations with the ball seated in a point of
the artefact, in one of its placements (:mod:`casadi_design.calibration.artefact`).

Two layouts, as they come:

* **A folder per placement** (MUKCa's, as published): ``hole_0.csv``, ``hole_1.csv``, ... with
  no header, one row a configuration, the chain's joints in rad in the chain's order; the
  number in the name is the artefact's point. The folder's name names the placement.
* **A CSV of the project's**: a plan CSV's joint columns (``<joint>_rad`` / ``_deg``, or
  ``q1_rad``...) with a ``point`` column (the artefact's point, 0..K-1) and a ``placement``
  column (an integer naming the placement within the file).

Several files or folders are several placements (each its own unknown pose). Every error is
one line naming the file and the fix.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibration.artefact import artefact
from ..errors import ProblemError
from ..problem.build import Problem
from ..records.export import (LIMIT_TOL, SEATED_COLUMNS, check_joint_limits, csv_cells, limits_past,
                              past_limit_text, read_plan_file, read_plan_table)

#: The column of a plan CSV that names each placement number.
PLACEMENT_NAME = SEATED_COLUMNS[2]
#: The file name of a point's recordings in a placement's folder.
POINT_FILE = re.compile(r"hole_(\d+)\.csv")
#: The largest point or placement number a CSV may give (beyond: not a label, and an int64 overflows).
MAX_LABEL = 10**6
#: Joint values all within this many rad of 0 with some beyond 2 pi look like degrees.
DEGREES_RAD = 2 * math.pi


@dataclass(frozen=True, eq=False)
class Recordings:
    """Configurations with the ball seated in a point of the artefact.

    Attributes
    ----------
    Q : ndarray, shape (N, n), rad (m): the configurations.
    point : ndarray of int, shape (N,): the artefact's point of each.
    placement : ndarray of int, shape (N,): the placement of each (0..P-1).
    names : tuple of str, (P,): each placement's name (its folder, or file and number).
    sources : tuple of str, (N,): the file and line of each configuration, for messages.
    notes : what the reader did that a person should know.
    """

    Q: np.ndarray
    point: np.ndarray
    placement: np.ndarray
    names: tuple[str, ...]
    sources: tuple[str, ...]
    notes: tuple[str, ...] = ()

    @property
    def N(self) -> int:
        return len(self.Q)

    @property
    def P(self) -> int:
        """Number of placements."""
        return len(self.names)

    def subset(self, rows: np.ndarray) -> Recordings:
        """The configurations ``rows`` (indices or a bool mask), placements kept as numbered."""
        i = np.arange(self.N)[rows]
        return Recordings(self.Q[i], self.point[i], self.placement[i], self.names,
                          tuple(self.sources[k] for k in i), self.notes)

    def of(self, g: int) -> Recordings:
        """Placement ``g`` alone, numbered 0."""
        rows = self.placement == g
        return Recordings(self.Q[rows], self.point[rows], np.zeros(int(rows.sum()), dtype=int), (self.names[g],),
                          tuple(s for s, r in zip(self.sources, rows) if r), self.notes)


def read_recordings(problem: Problem, paths: list[str], option: str = "--measurements",
                    limit_tolerance: float = LIMIT_TOL) -> Recordings:
    """The recordings of ``paths`` (each a placement's folder or a CSV of the project's; module
    docstring), one placement per folder and per ``placement`` of a CSV, numbered in order; joint
    values past a limit by at most ``limit_tolerance`` (rad or m) are accepted with a note.

    Raises
    ------
    ProblemError
        A path that does not exist, a folder with no recordings, a wrong number of joints, an
        unknown point, a placement of one configuration, angles that look like degrees, joint
        values past the limits (one line naming the file and the fix).
    """
    if problem.artefact is None:
        raise ProblemError(f"{problem.path}: [measurement.artefact] is missing, so {option} cannot be "
                           "recordings of an artefact's points; add it (points_m) or give tracker measurements")
    parts = [_folder(problem, Path(p), option, limit_tolerance) if Path(p).is_dir() else
             _csv(problem, p, option, limit_tolerance) for p in paths]
    Q, point, placement, names, sources, notes, where = [], [], [], [], [], [], []
    for path, part in zip(paths, parts):
        for name, (Qg, kg, src) in part[0].items():
            Q.append(Qg)
            point.append(kg)
            placement.append(np.full(len(Qg), len(names)))
            names.append(name)
            sources += src
            where.append(path if Path(path).is_dir() else f"{path}: placement {name}")
        notes += part[1]
    if len(set(names)) != len(names):
        raise ProblemError(f"{option}: placement '{next(n for n in names if names.count(n) > 1)}' is given twice (a "
                           "folder's placement is named by the folder); give each placement once, under its own name")
    if option == "--measurements":  # a placement's pose is fitted: its points must tell its turns
        A = problem.artefact
        for at, kg in zip(where, point):
            seen = np.unique(kg)
            told = artefact(A.points_m[seen]).turns.shape[1]
            if told < A.turns.shape[1]:
                raise ProblemError(f"{option} {at}: its configurations are at point{'s' * (len(seen) > 1)} "
                                   f"{', '.join(str(j) for j in seen)} only, which tell {told} of the "
                                   f"{A.turns.shape[1]} turns of the placement (a turn about a line through them "
                                   "moves none): record the ball in another point there too, or give it as "
                                   "--validation")
    if option == "--validation":  # a point's consistency is its configurations' spread about their mean
        for name, kg in zip(names, point):
            one = [j for j in np.unique(kg) if np.sum(kg == j) == 1]
            if one:
                raise ProblemError(f"{option} {name}: point {one[0]} has one configuration, which tells no "
                                   "consistency; record more at that point or leave its file out")
    return Recordings(np.vstack(Q), np.concatenate(point), np.concatenate(placement), tuple(names),
                      tuple(sources), tuple(notes))


def _checked(problem: Problem, where: str, Q: np.ndarray, k: np.ndarray, sources: list[str]) -> None:
    """The checks every layout shares, for one placement ``where``."""
    K = problem.artefact.K
    if len(np.unique(Q, axis=0)) < 2:
        raise ProblemError(f"{where}: one configuration{' repeated' * (len(Q) > 1)}; a placement needs several (the "
                           "ball seated in its points in many configurations) to tell the robot anything; record more "
                           "or leave it out")
    bad = np.flatnonzero((k < 0) | (k >= K))
    if bad.size:
        raise ProblemError(f"{sources[bad[0]]}: point {k[bad[0]]} is not a point of the artefact (it has {K}: "
                           f"0..{K - 1}, [measurement.artefact].points_m); fix the number or add the point")
    if np.all(np.abs(Q) < DEGREES_RAD * 60) and np.any(np.abs(Q) > DEGREES_RAD):
        i, j = np.unravel_index(int(np.argmax(np.abs(Q))), Q.shape)
        raise ProblemError(f"{sources[i]}: joint {j + 1} is {Q[i, j]:.6g}, beyond 2 pi: the angles look like "
                           "degrees; give them in rad")


def _folder(problem: Problem, folder: Path, option: str, tolerance: float) -> tuple[dict, list[str]]:
    """A placement's folder of ``hole_<k>.csv`` files (MUKCa's layout)."""
    files = sorted((int(m.group(1)), f) for f in folder.iterdir() if (m := POINT_FILE.fullmatch(f.name)))
    same = [(i, a, b) for (i, a), (j, b) in zip(files, files[1:]) if i == j]
    if same:
        i, a, b = same[0]
        raise ProblemError(f"{option} {folder}: {a.name} and {b.name} are both point {i}; keep one file per point")
    if not files:
        inner = sorted(d.name for d in folder.iterdir() if d.is_dir() and any(
            POINT_FILE.fullmatch(f.name) for f in d.iterdir()))
        if inner:  # a robot's folder of placements (MUKCa's data/<robot>)
            raise ProblemError(f"{option} {folder}: a folder of {len(inner)} placement{'s' * (len(inner) > 1)} "
                               f"({', '.join(inner)}), not one "
                               f"placement; give each placement's folder, e.g. {option} {folder / inner[0]} (the "
                               "ones fitted as --measurements, the held-out ones as --validation)")
        raise ProblemError(f"{option} {folder}: a folder with no recordings (hole_0.csv, hole_1.csv, ...: one "
                           "row of joint values in rad per configuration); give a placement's folder")
    n = problem.robot.n
    Q, k, sources = [], [], []
    for point, f in files:
        try:
            with warnings.catch_warnings():  # an empty file: skipped below, without numpy's warning
                warnings.simplefilter("ignore", UserWarning)
                rows = np.loadtxt(f, delimiter=",", ndmin=2)
        except ValueError as exc:
            raise ProblemError(f"{f}: not a table of numbers ({exc}); give one row of {n} joint values in rad "
                               "per configuration, no header") from None
        if rows.size == 0:
            continue
        if rows.shape[1] != n:
            raise ProblemError(f"{f}: {rows.shape[1]} joint values a row, the chain to "
                               f"'{problem.spec.robot.frame}' has {n} ({', '.join(problem.robot.joints)}); "
                               "give them in the chain's order")
        if not np.all(np.isfinite(rows)):
            raise ProblemError(f"{f}: a value that is not a finite number; fix or delete its row")
        Q.append(rows)
        k.append(np.full(len(rows), point))
        sources += [f"{f}: row {i + 1}" for i in range(len(rows))]
    if not Q:
        raise ProblemError(f"{option} {folder}: its hole_*.csv files are empty; record configurations or leave "
                           "the folder out")
    Q, k = np.vstack(Q), np.concatenate(k)
    _checked(problem, f"{option} {folder}", Q, k, sources)
    return {folder.name: (Q, k, sources)}, _limits(problem, Q, sources, tolerance)


def _limits(problem: Problem, Q: np.ndarray, sources: list[str], tolerance: float) -> list[str]:
    """Notes on the joint values ``Q`` past a limit by at most ``tolerance`` (rad or m: a real
    encoder reads past the URDF's limit; rounding below :data:`LIMIT_TOL` silently), one line
    naming the row of a value past it by more (:func:`~casadi_design.records.export.limits_past`,
    as :func:`~casadi_design.records.export.check_joint_limits` says it of a CSV)."""
    robot = problem.robot
    rows, worst, over = limits_past(robot, Q)
    j = int(np.argmax(worst))
    i = int(rows[j])
    unit = ["m" if robot.is_prismatic(k) else "rad" for k in range(robot.n)]
    if worst[j] > tolerance:
        allowed = past_limit_text(tolerance, unit[j])
        raise ProblemError(f"{sources[i]}: {robot.joints[j]} = {Q[i, j]:.6g} is outside its limits "
                           f"[{robot.q_min[j]:.6g}, {robot.q_max[j]:.6g}] {unit[j]} {allowed}; check the joint order "
                           "and units (identify accepts readings past a limit with --limit-tolerance)")
    return [f"{sources[int(rows[k])]}, {joint}: {over[k]} reading{'s' if over[k] > 1 else ''} past the joint limits "
            f"by at most {worst[k]:.3g} {unit[k]}, within --limit-tolerance {tolerance:g}: accepted"
            for k, joint in enumerate(robot.joints) if over[k]]


def _csv(problem: Problem, path: str, option: str, tolerance: float) -> tuple[dict, list[str]]:
    """A CSV of the project's: joint columns, ``point`` and ``placement``."""
    if not Path(path).exists():
        raise ProblemError(f"{option} {path}: no such file or folder; give a placement's folder (hole_0.csv, ...) "
                           "or a CSV with joint, point and placement columns")
    if POINT_FILE.fullmatch(Path(path).name):  # one point's file of a placement's folder
        raise ProblemError(f"{option} {path}: one point's recordings of a placement; give its folder, "
                           f"{option} {Path(path).parent}, so that all its points are read (hole_0.csv, hole_1.csv, ...)")
    plan = read_plan_file(path)
    Q, _, values, lines = read_plan_table(problem, plan, ("point", "placement"),
                                          "point and placement (integers)", ignore_unknown=True)
    for c in ("point", "placement"):
        if c not in values:
            raise ProblemError(f"{path}: no '{c}' column; add it (an integer per row: the artefact's point and "
                               "the placement it was clamped at)")
        v = values[c]
        bad = np.flatnonzero(~np.isfinite(v) | (v != np.round(v)) | (np.abs(v) > MAX_LABEL))
        if bad.size:
            raise ProblemError(f"{path}: row {lines[bad[0]]}, column '{c}': {float(v[bad[0]]):g} is not an integer; "
                               "give the number")
    notes = [f"{path}: {n}" for n in check_joint_limits(problem, plan, Q, lines, tolerance)]
    named = _placement_names(plan, values["placement"])
    out = {}
    for g in np.unique(values["placement"]).astype(int):
        rows = values["placement"] == g
        sources = [f"{path}: row {line}" for line, r in zip(lines, rows) if r]
        k = values["point"][rows].astype(int)
        _checked(problem, f"{path}: placement {g}", Q[rows], k, sources)
        name = named.get(g, f"{Path(path).stem}:{g}")
        if name in out:
            raise ProblemError(f"{path}: column '{PLACEMENT_NAME}': '{name}' names two placement numbers; give each "
                               "placement its own name (or leave the column out)")
        out[name] = (Q[rows], k, sources)
    return out, notes


def _placement_names(plan, placement: np.ndarray) -> dict[int, str]:
    """The name of each placement number of a plan CSV with a ``placement_name`` column (as
    ``solve`` writes it), where every row of a number gives it one name; else none."""
    if PLACEMENT_NAME not in plan.header:
        return {}
    c = plan.header.index(PLACEMENT_NAME)
    names: dict[int, set[str]] = {}
    for (_, line), g in zip(plan.lines[1:], placement.astype(int)):
        cells = csv_cells(line, plan.separator)
        names.setdefault(int(g), set()).add(cells[c].strip() if c < len(cells) else "")
    return {g: n.pop() for g, n in names.items() if len(n) == 1 and "" not in n}
