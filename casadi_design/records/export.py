"""Plans as CSV files for robot programs (and back), and the one-page Markdown report.

A plan CSV has one row per experiment::

    experiment, <joint>_deg..., <joint>_rad..., fx_N, fy_N, ..., x_mm, y_mm, z_mm

joint values in deg and rad (prismatic joints: ``_mm`` and ``_m``), in the order of the chain
(root first); the calibration load (N, moments ``mx_Nm``...) when the case has one; and the
nominal position of the measured point (mm), where the tracker should look. The load-induced
deflection is not included: it is what the experiment measures.

:func:`read_plan_csv` reads such a file, or one written by hand: joints named ``q1``, ``q2``...
(1-based) or by their joint names, each with a unit suffix ``_deg`` / ``_rad`` (``_mm`` /
``_m`` for prismatic joints); force columns as above (optional for fixed loads); the columns
``experiment``, ``x_mm``, ``y_mm``, ``z_mm`` are ignored. Lines starting with ``#`` are comments.
A file whose header is separated by ``;`` (Excel in a comma-decimal locale) is read with ``;``
between cells and ``,`` as the decimal point.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cell.cell import Clearance
from ..errors import ProblemError
from ..plan.design import Design, Seating
from ..problem.build import Problem
from ..problem_file.fields import WRENCH_ROWS
from .files import write_atomic

#: Largest disagreement (rad or m) between the two unit columns of one joint in a plan CSV.
UNIT_AGREEMENT_TOL = 1e-6
#: Joint values this far outside their limits (rad or m) are accepted silently (rounding in a CSV).
LIMIT_TOL = 1e-6
POSITION_COLUMNS = ("x_mm", "y_mm", "z_mm")
#: Column of a campaign's plan CSV that marks the experiments already measured (``yes``/``no``).
MEASURED_COLUMN = "measured"
#: Columns written for people with a [cell] and ignored when read: the experiment's clearance on
#: the real geometry (mm) and the two closest bodies.
CLEARANCE_COLUMNS = ("clearance_mm", "closest_bodies")
#: The columns of a plan of an artefact's points: the point the ball is seated at, the
#: placement (an integer, as :mod:`casadi_design.identification.recordings` reads it) and its name.
SEATED_COLUMNS = ("point", "placement", "placement_name")
#: Columns of ``identify``'s compensated_test_poses.csv beside a plan's, ignored when read (the
#: file is a plan: program and evaluate take it): whether the compensation converged, and each
#: joint's change from the test pose (``<joint>_change_<unit>``, :func:`change_columns`).
CONVERGED_COLUMN = "converged"


def change_columns(problem: Problem) -> list[str]:
    """The compensated test poses' change of each joint from the test pose, in its unit for people."""
    return [f"{j}_change_{joint_units(problem, k)[1]}" for k, j in enumerate(problem.robot.joints)]


def is_prismatic(problem: Problem, k: int) -> bool:
    """Whether joint ``k`` of the chain is prismatic (its value in m, not rad)."""
    return problem.robot.is_prismatic(k)


def joint_units(problem: Problem, k: int) -> tuple[str, str, float]:
    """(SI unit suffix, people's unit suffix, SI per people's unit) of joint ``k``."""
    return ("m", "mm", 1e-3) if is_prismatic(problem, k) else ("rad", "deg", math.pi / 180)


def joint_scales(problem: Problem) -> np.ndarray:
    """SI per people's unit of every joint of the chain (:func:`joint_units`), shape (n,):
    pi / 180 (rad per deg) or 1e-3 (m per mm)."""
    return np.array([joint_units(problem, k)[2] for k in range(problem.robot.n)])


def force_columns(problem: Problem) -> list[str]:
    """Column names of the load components: ``fx_N``..., ``mx_Nm``..."""
    return [f"{WRENCH_ROWS[r]}_{'N' if WRENCH_ROWS[r][0] == 'f' else 'Nm'}"
            for r in problem.model.force_rows]


def plan_table(problem: Problem, Q: np.ndarray, F: np.ndarray,
               near: tuple[Clearance, ...] | None = None, seated: Seating | None = None) -> tuple[list[str], list[list]]:
    """Header and rows of a plan: ``Q`` shape (m, n), rad (m); ``F`` shape (m, nF), N (N m).

    With a ``[cell]`` and ``near`` (:attr:`casadi_design.plan.design.Design.clearances`), each row
    also gives the experiment's clearance on the real geometry (mm) and the two bodies at that
    distance. With ``seated`` (a plan of an artefact's points), each row gives the artefact's
    ``point``, the ``placement`` (an integer, as identify reads it) and its name.
    """
    joints = problem.robot.joints
    units = [joint_units(problem, k) for k in range(len(joints))]
    near = near if problem.cell and near else None
    header = (["experiment"] + [f"{j}_{u[1]}" for j, u in zip(joints, units)]
              + [f"{j}_{u[0]}" for j, u in zip(joints, units)] + force_columns(problem)
              + list(POSITION_COLUMNS) + (list(CLEARANCE_COLUMNS) if near else []))
    Q = np.asarray(Q, float)
    blank = ["", ""] if near else []  # an experiment without a clearance (a measured one)
    near = near or [None] * len(Q)
    rows = []
    for i, (q, f, c) in enumerate(zip(Q, np.asarray(F, float).reshape(len(Q), -1), near)):
        p = np.asarray(problem.model.position(q), dtype=float).ravel() * 1e3
        rows.append([i + 1] + [qk / u[2] for qk, u in zip(q, units)] + list(q) + list(f) + list(p)
                    + ([c.distance_m * 1e3, " / ".join(c.between)] if c else blank))
    if seated is not None:
        header += list(SEATED_COLUMNS)
        rows = [r + [int(k), int(g), seated.names[g]] for r, k, g in zip(rows, seated.point, seated.placement)]
    return header, rows


def design_table(problem: Problem, design: Design) -> tuple[list[str], list[list]]:
    """:func:`plan_table` of a design's campaign (:meth:`~casadi_design.problem.build.Problem.campaign`):
    with experiments already measured, they come first and a last column ``measured`` says
    ``yes`` or ``no``."""
    Q, F, measured = problem.campaign(design.Q, design.F)
    k = int(measured.sum())
    near = None if design.clearances is None else (None,) * k + tuple(design.clearances)
    header, rows = plan_table(problem, Q, F, near, design.seated)
    if not k:
        return header, rows
    return header + [MEASURED_COLUMN], [r + ["yes" if flag else "no"] for r, flag in zip(rows, measured)]


def csv_text(header: list[str], rows: list[list]) -> str:
    """CSV with full-precision floats (``repr``: a value read back is the value written)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow([repr(float(v)) if isinstance(v, (float, np.floating)) else v for v in row])
    return buf.getvalue()


def write_plan_csv(path: Path, problem: Problem, design: Design) -> None:
    """The design's plan, one row per experiment, atomically."""
    write_atomic(Path(path), csv_text(*design_table(problem, design)).encode())


def write_plans(out: Path, problem: Problem, designs: list[Design]) -> list[str]:
    """Each design's plan as ``out/plans/<criterion>_m<m>.csv``; returns the file names."""
    names = [f"plans/{d.criterion}_m{d.m}.csv" for d in designs]
    for name, d in zip(names, designs):
        write_plan_csv(out / name, problem, d)
    return names


def write_table_csv(path: Path, columns: tuple[str, ...] | list[str], rows: list[dict]) -> None:
    """Rows (dicts) as CSV with the given columns, atomically."""
    write_atomic(Path(path), csv_text(list(columns), [[r[c] for c in columns] for r in rows]).encode())


#: Largest plan file read, bytes, and most experiments (rows) in a plan.
_MAX_PLAN_BYTES = 10 * 2**20
_MAX_PLAN_ROWS = 100_000


def _plan_text(path: str) -> str:
    """The text of the plan file ``path``: UTF-8, a leading byte-order mark (Excel) dropped.

    Folders, devices, pipes, binary or non-UTF-8 content and files over ``_MAX_PLAN_BYTES``
    are refused (one-line :class:`ProblemError`) before they are read whole.
    """
    if not path:
        raise ProblemError("the plan file name is empty; give the CSV file")
    file = Path(path)
    try:
        st = file.stat()
        if file.is_dir():
            raise ProblemError(f"{path}: is a folder, not a plan file; give the CSV file")
        if not file.is_file():
            raise ProblemError(f"{path}: is not a regular file (a device or a pipe); give the "
                               "CSV file")
        data = b""
        if st.st_size <= _MAX_PLAN_BYTES:
            with open(file, "rb") as fh:
                data = fh.read(_MAX_PLAN_BYTES + 1)  # + 1: the file may have grown since
    except FileNotFoundError:
        raise ProblemError(f"{path}: no such plan file; check the path") from None
    except OSError as exc:
        raise ProblemError(f"{path}: cannot be read ({exc.strerror}); check the path and its "
                           "permissions") from None
    size = max(st.st_size, len(data))
    if size > _MAX_PLAN_BYTES:
        raise ProblemError(f"{path}: is {size / 2**20:.1f} MB; a plan has at most {_MAX_PLAN_ROWS} "
                           f"experiments ({_MAX_PLAN_BYTES // 2**20} MB); give a smaller plan")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):  # UTF-16 byte-order marks
        raise ProblemError(f"{path}: is UTF-16 text (Excel 'Unicode Text'), not UTF-8; save it as "
                           "'CSV UTF-8 (comma delimited)'")
    if b"\0" in data:
        raise ProblemError(f"{path}: is a binary file (it holds NUL bytes), not UTF-8 CSV text; "
                           "give the plan CSV file")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ProblemError(f"{path}: is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset "
                           f"{exc.start}); save it as 'CSV UTF-8 (comma delimited)'") from None


def csv_cells(line: str, separator: str = ",") -> list[str]:
    """The cells of one CSV line separated by ``separator``, blanks around them stripped."""
    return [c.strip() for c in next(csv.reader([line], delimiter=separator))]


def read_plan_csv(problem: Problem, path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """A plan from a CSV file: ``Q`` shape (m, n), rad (m); ``F`` shape (m, nF), N (N m)
    (:func:`read_plan_table` without extra columns)."""
    Q, F, _, _ = read_plan_table(problem, path)
    return Q, F


@dataclass(frozen=True)
class PlanFile:
    """A plan or measurement CSV read once (:func:`read_plan_file`): its path, the (line
    number, text) of its header and rows, empty lines and ``#`` comments dropped, and the
    ``separator`` of its cells: ``,`` (numbers with a ``.`` decimal point) or ``;`` (a ``,``
    decimal point). Every reader of its columns takes it, so a file is read and checked once
    however many parts of it are asked for."""

    path: str
    lines: tuple[tuple[int, str], ...]
    separator: str = ","

    @property
    def decimal(self) -> str:
        """The decimal point of its numbers: ``,`` in a ``;``-separated file, else ``.``."""
        return "," if self.separator == ";" else "."

    @property
    def notes(self) -> tuple[str, ...]:
        """How the file was read, for people: its separators when they are not ``,``."""
        if self.separator == ",":
            return ()
        return ("read with ';' between columns and ',' as the decimal point (a CSV of Excel in a "
                "comma-decimal locale)",)

    @property
    def header(self) -> list[str]:
        """The column names as the file spells them (trailing empty names dropped)."""
        header = csv_cells(self.lines[0][1], self.separator)
        while header and not header[-1]:
            header.pop()
        return header

    @property
    def measured(self) -> np.ndarray:
        """Which rows are marked measured (the ``measured`` column says ``yes``: the
        experiments of a campaign measured before its plan); none without the column."""
        header, body = self.header, self.lines[1:]
        if MEASURED_COLUMN not in header:
            return np.zeros(len(body), dtype=bool)
        c = header.index(MEASURED_COLUMN)
        return np.array([len(cells) > c and cells[c].lower() in ("yes", "true", "1")
                         for cells in (csv_cells(ln, self.separator) for _, ln in body)], dtype=bool)


def read_plan_file(path: Path | str) -> PlanFile:
    """The :class:`PlanFile` of ``path``: UTF-8 text checked as :func:`read_plan_table` says,
    with at least a header; its separator is ``;`` when its header has one, else ``,``.

    Raises
    ------
    ProblemError
        A file that cannot be read as a plan's text, an empty one, or a header with both ``;``
        and ``,`` between its names.
    """
    path = str(path)
    lines = tuple((i, ln) for i, ln in enumerate(_plan_text(path).splitlines(), start=1)
                  if ln.strip(" \t,;") and not ln.lstrip().startswith("#"))
    if not lines:
        raise ProblemError(f"{path}: empty plan file; give a header row and one row per experiment")
    head = lines[0][1]
    if ";" in head and "," in head:
        raise ProblemError(f"{path}: its header (line {lines[0][0]}) has both ';' and ',' between names, so "
                           "its columns cannot be told apart; save it with ',' separators and '.' decimal "
                           "points (or ';' separators and ',' decimal points)")
    return PlanFile(path, lines, ";" if ";" in head else ",")


def read_plan_table(problem: Problem, plan: PlanFile | Path | str, extra: tuple[str, ...] = (),
                    extra_hint: str = "", rename: dict[str, str] | None = None,
                    ignore_unknown: bool = False,
                    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], list[int]]:
    """A plan from a CSV file (its path, or the :class:`PlanFile` already read): ``Q`` shape
    (m, n), rad (m); ``F`` shape (m, nF), N (N m); the ``extra`` columns that are present (e.g.
    measured coordinates), as floats with NaN for empty cells; and the line of the file of each
    row (1-based). ``extra_hint`` names the extra
    columns in the message on an unknown column. ``rename`` maps a column as the file spells it
    to the name read here (messages keep the file's spelling); with ``ignore_unknown`` other
    columns are skipped instead of refused (:attr:`PlanFile.header` tells which).

    UTF-8 text, with or without a byte-order mark; cells separated by ``,`` with ``.`` as the
    decimal point, or by ``;`` (the header says which) with ``,`` as the decimal point
    (:attr:`PlanFile.decimal`). Trailing empty cells (as Excel writes them) are dropped, and
    so are lines of empty cells and lines starting with ``#``. Row numbers in messages are
    lines of the file (1-based).

    Raises
    ------
    ProblemError
        Not a UTF-8 text file, more than 100000 rows (10 MB), a header with both ';' and ',',
        rows of another length than the header, missing or unknown columns, non-numbers or
        non-finite numbers, a '.' in a number of a ';'-separated file, disagreeing unit
        columns (one line each).
    """
    plan = plan if isinstance(plan, PlanFile) else read_plan_file(plan)
    path, body, sep, decimal = plan.path, plan.lines[1:], plan.separator, plan.decimal
    if len(body) > _MAX_PLAN_ROWS:
        raise ProblemError(f"{path}: has {len(body)} rows; a plan has at most {_MAX_PLAN_ROWS} "
                           "experiments; give a smaller plan")
    spelled = plan.header
    rename = rename or {}
    header = [rename.get(h, h) for h in spelled]
    rows = [(i, csv_cells(ln, sep)) for i, ln in body]
    if not rows:
        raise ProblemError(f"{path}: no experiments below the header; give one row per experiment")
    robot = problem.robot
    columns: dict[str, tuple[int, float]] = {}  # column -> (joint index, SI per unit)
    for k, j in enumerate(robot.joints):
        si, people, scale = joint_units(problem, k)
        for name in (f"q{k + 1}", j):
            columns[f"{name}_{si}"] = (k, 1.0)
            columns[f"{name}_{people}"] = (k, scale)
    forces = force_columns(problem)
    allowed = set(columns) | set(forces) | {"experiment", MEASURED_COLUMN, *POSITION_COLUMNS, *CLEARANCE_COLUMNS,
                                            CONVERGED_COLUMN, *change_columns(problem), *extra}
    if "" in header:
        raise ProblemError(f"{path}: column {header.index('') + 1} of the header has no name; "
                           "name it or delete the column")
    unknown = [h for h in header if h not in allowed]
    alien = sorted((h for h in unknown if h.rpartition("_")[0] and h.rpartition("_")[2] in ("deg", "rad", "mm", "m")),
                   key=lambda h: h.rpartition("_")[2] not in ("deg", "rad"))  # angles first: coordinates are in mm too
    if alien and not any(h in columns for h in header):
        joint = alien[0].rpartition("_")[0]
        raise ProblemError(
            f"{path}: column '{alien[0]}' names joint '{joint}', which the robot of "
            f"{problem.path} does not have ({', '.join(robot.joints)}): the plan is for another "
            "problem; give the plan made for this one")
    if unknown and not ignore_unknown:
        si, people, _ = joint_units(problem, 0)
        raise ProblemError(
            f"{path}: unknown column '{unknown[0]}'; allowed: q1_{people} or q1_{si} ... "
            f"q{robot.n}_<unit> (or joint names {', '.join(robot.joints)} with the unit suffix)"
            + (f", {', '.join(forces)}" if forces else "") + ", experiment, x_mm, y_mm, z_mm"
            + (f", {extra_hint}" if extra_hint else ""))
    repeated = next((c for c, h in enumerate(header) if header.count(h) > 1 and h in allowed), None)
    if repeated is not None:
        twins = [spelled[c] for c, h in enumerate(header) if h == header[repeated]]
        raise ProblemError(f"{path}: column '{spelled[repeated]}' is given {len(twins)} times"
                           + (f" (as {', '.join(twins)})" if len(set(twins)) > 1 else "")
                           + "; give each column once")
    for i, cells in rows:
        if len(cells) > len(header) and not any(cells[len(header):]):
            del cells[len(header):]  # trailing empty cells
        if [c.strip().lower() for c in cells] == [s.strip().lower() for s in spelled]:
            raise ProblemError(f"{path}: row {i} repeats the header; delete it (one header line, at the top)")
        if len(cells) != len(header):
            raise ProblemError(f"{path}: row {i} has {len(cells)} cells, the header has "
                               f"{len(header)}; give one value per column in every row "
                               + ("(a decimal comma splits a number in two: use '.')" if sep == "," else
                                  "(separated by ';' as in the header)"))

    def number(r: int, c: int, empty_allowed: bool = False) -> float:
        line, cell = rows[r][0], rows[r][1][c]
        where = f"{path}: row {line}, column '{spelled[c]}'"
        if decimal == "," and "." in cell:  # a thousands separator or a '.' decimal point: unclear
            raise ProblemError(f"{where}: '{cell}' has a '.' in a file separated by ';', where ',' is the "
                               "decimal point; write it with a decimal comma (or save the file with ',' "
                               "separators and '.' decimal points)")
        try:
            v = float(cell.replace(decimal, ".")) if cell else math.nan
        except ValueError:
            raise ProblemError(f"{where}: expected a number, got '{cell}'; give a number with a "
                               f"'{decimal}' decimal point in every cell") from None
        if not math.isfinite(v) and not (empty_allowed and not cell):
            got = f"'{cell}'" if cell else "an empty cell"
            raise ProblemError(f"{where}: not a finite number, got {got}; give a finite number in "
                               "every cell")
        return v

    m = len(rows)
    Q = np.full((m, robot.n), np.nan)
    for k, j in enumerate(robot.joints):
        given = [(c, columns[h][1]) for c, h in enumerate(header) if h in columns and columns[h][0] == k]
        if not given:
            si, people, _ = joint_units(problem, k)
            raise ProblemError(f"{path}: no column for joint {k + 1} ({j}); add q{k + 1}_{people} "
                               f"or q{k + 1}_{si} (or {j}_{people} / {j}_{si})")
        values = np.array([[number(r, c) * s for r in range(m)] for c, s in given])
        spread = np.max(np.ptp(values, axis=0))
        if spread > UNIT_AGREEMENT_TOL:
            raise ProblemError(
                f"{path}: the columns {', '.join(spelled[c] for c, _ in given)} of joint {j} "
                f"disagree by {spread:.3g} (rad or m); give one of them or fix the values")
        # the SI column when given (exact), else the people's unit converted
        Q[:, k] = values[next((i for i, (_, scale) in enumerate(given) if scale == 1.0), 0)]
    values = {h: np.array([number(r, header.index(h), True) for r in range(m)]) for h in extra if h in header}
    lines_of_rows = [i for i, _ in rows]
    nF = problem.model.nF
    if nF == 0:
        return Q, np.zeros((m, 0)), values, lines_of_rows
    present = [h in header for h in forces]
    if not any(present) and problem.force is not None and problem.force.mode == "fixed":
        return Q, np.tile(np.array(problem.force.vector_N), (m, 1)), values, lines_of_rows
    if not all(present):
        missing = [h for h, p in zip(forces, present) if not p]
        raise ProblemError(f"{path}: missing force column '{missing[0]}'; the plan needs the "
                           f"calibration load of each experiment: {', '.join(forces)} (N, N m)")
    F = np.array([[number(r, header.index(h)) for r in range(m)] for h in forces]).T  # checked column by column
    return Q, F, values, lines_of_rows



def limits_past(robot, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint of ``robot`` (n,): the row of ``Q`` (N, n) farthest past a limit, how far past
    it (rad or m; <= 0 within the limits) and how many rows are past it by more than
    :data:`LIMIT_TOL` (a CSV's rounding)."""
    past = np.maximum(robot.q_min - Q, Q - robot.q_max)
    rows = np.argmax(past, axis=0)
    return rows, past[rows, np.arange(past.shape[1])], np.sum(past > LIMIT_TOL, axis=0)


def past_limit_text(tolerance: float, unit: str) -> str:
    """How far a reading refused is past its joint's limit, for people: beyond ``tolerance``
    (``unit``) when identify was given one, else out of reach."""
    return (f"by more than --limit-tolerance {tolerance:g} ({unit})" if tolerance > LIMIT_TOL
            else "(the robot cannot reach it)")


def check_joint_limits(problem: Problem, plan: PlanFile, Q: np.ndarray, lines: list[int],
                       tolerance: float = LIMIT_TOL, rename: dict[str, str] | None = None) -> list[str]:
    """Notes on the joint values ``Q`` of a plan file past a limit by at most ``tolerance``
    (rad or m; a real encoder reads past the URDF's limit), and one error beyond: the row as
    ``lines`` numbers it and the column as the file spells it (``rename`` as for
    :func:`read_plan_table`).

    Raises
    ------
    ProblemError
        A joint value outside its limits by more than ``tolerance``.
    """
    robot, path, header = problem.robot, plan.path, plan.header
    rename = rename or {}
    rows, worst, over = limits_past(robot, Q)
    allowed = past_limit_text(tolerance, "rad or m")
    notes = []
    for k, j in enumerate(robot.joints):
        si, people, scale = joint_units(problem, k)
        ours = {f"{base}_{u}" for base in (f"q{k + 1}", j) for u in (si, people)}
        column = next((h for h in header if rename.get(h, h) in ours), f"{j}_{people}")
        unit = next((u for u in (si, people) if rename.get(column, column).endswith(f"_{u}")), people)
        per = 1.0 if unit == si else scale
        i = int(rows[k])
        if worst[k] > tolerance:
            raise ProblemError(
                f"{path}: row {lines[i]}, column '{column}': {Q[i, k] / per:.6g} {unit} is outside the "
                f"joint limits [{robot.q_min[k] / per:.6g}, {robot.q_max[k] / per:.6g}] {unit} of "
                f"{problem.path} {allowed}; check the units, the order of the joint columns and "
                "that the file belongs to this case")
        if over[k]:
            notes.append(f"column '{column}': {over[k]} reading{'s' if over[k] > 1 else ''} past the "
                         f"joint limits by at most {worst[k] / per:.3g} {unit} (row {lines[i]}), within "
                         f"--limit-tolerance {tolerance:g}: accepted")
    return notes


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

    return "\n".join([line(header), "|" + "---|" * len(header)] + [line(r) for r in rows])


def plan_markdown(problem: Problem, design: Design) -> str:
    """A plan as a Markdown table: joints (deg or mm), load (N), measured point (mm), with a
    ``[cell]`` the clearance (mm) and the closest bodies."""
    header, rows = design_table(problem, design)
    n = problem.robot.n
    keep = [0, *range(1, 1 + n), *range(1 + 2 * n, len(header))]
    return _md_table([header[c] for c in keep],
                     [[str(r[0])] + [f"{r[c]:.2f}" if isinstance(r[c], float) else str(r[c]) for c in keep[1:]]
                      for r in rows])


def bound_notes(designs: list[Design]) -> list[str]:
    """One sentence per test-pose design with a bound: how much a better plan could still gain."""
    out = []
    for d in designs:
        if d.criterion == "test-pose" and d.bound is not None:
            e, b = d.scores.max_rms_error_m, d.bound.value
            out.append(
                f"m = {d.m}: no plan of {d.m} experiment{'s' if d.m > 1 else ''} can bring the "
                f"worst test pose below {b * 1e3:.4f} mm (a certified lower bound from the "
                f"approximate design); this plan reaches {e * 1e3:.4f} mm, {d.gap_percent:.1f} % "
                f"above it: no other plan can reduce its error by more than {100 * (1 - b / e):.1f} %.")
    return out


def describe_test_poses(problem: Problem) -> str:
    """The test poses in a few words: for poses given in joint space (``joints_rad``) or as
    separate points (a path of kind ``points``) how many and the box their measured points
    span (mm); for a line, an arc or a polyline where it goes, from the first to the last
    point (mm)."""
    spec, tp = problem.spec.test_poses, problem.test_poses
    x = tp.position_m * 1e3

    def mm(v: float) -> str:
        return str(round(float(v)))  # an int: no -0

    what = {"joints": "joint-space pose", "path": "point" if spec.path_kind == "points" else ""}.get(spec.kind, "")
    if what:
        low, high = x.min(axis=0), x.max(axis=0)
        return (f"{tp.s} {what}{'s' if tp.s > 1 else ''} ({'joints_rad' if spec.kind == 'joints' else 'points_m'}), "
                "positions within " + ", ".join(f"{a} {mm(lo)}..{mm(hi)}" for a, lo, hi in zip("xyz", low, high))
                + " mm")
    return (f"{tp.s} poses, from ({', '.join(mm(v) for v in x[0])}) to "
            f"({', '.join(mm(v) for v in x[-1])}) mm")


def report_markdown(problem: Problem, designs: list[Design], *, table: str, figures: list[tuple[str, str]],
                    plans_for: list[int], files: list[str], starts: str, title: str = "Calibration plan",
                    notes: list[str] = (), rows: dict[str, str] | None = None) -> str:
    """The one-page report: the case, the table, the figures, the plans for ``plans_for`` m.

    ``table`` is a preformatted text table (mm); ``figures`` are (caption, relative file);
    ``rows``: rows of the case's table said otherwise (e.g. ``solver``: how the plans were found,
    by default IPOPT from ``starts`` seeded starts).
    """
    model = problem.model
    force = problem.force
    load = ("none (geometric case)" if force is None else
            f"{force.mode}, |F| {'=' if force.mode == 'equal' else '<='} {force.magnitude_N:g} N" if force.mode != "fixed" else
            f"fixed F = {list(force.vector_N)} N")
    notes = [*notes, *bound_notes(designs)]
    lines = [
        f"# {title}: {problem.name}",
        "",
        problem.spec.description,
        "",
        _md_table(["", ""], [[name, (rows or {}).get(name, text)] for name, text in [
            ["problem file", f"`{problem.path}`"],
            ["robot", (f"{problem.robot.name}, {problem.robot.n} joints "
                       f"({', '.join(problem.robot.joints)}), measured frame `{problem.robot.frame}`")],
            ["identified", f"{model.case}: {', '.join(model.parameter_names)}"],
            ["measured", f"{', '.join(problem.spec.measurement.components)}, sigma = {problem.sigma_m * 1e3:g} mm"],
            ["test poses", describe_test_poses(problem)],
            ["calibration load", load],
            ["solver", f"IPOPT, {starts} seeded starts per design, seed {problem.solver.seed}"],
        ]]),
        "",
        "## Accuracy along the test poses",
        "",
        "```",
        table,
        "```",
        "",
        *[f"- {n}" for n in notes],
        *([""] if notes else []),
    ]
    for caption, fname in figures:
        lines += [f"![{caption}]({fname})", "", f"*{caption}*", ""]
    lines += ["## Plans", "", (f"Joints in deg (mm for prismatic joints), {'' if force is None else 'load in N, '}"
                               "measured point in mm; full precision in the plans/*.csv files."), ""]
    for m in plans_for:
        for d in (d for d in designs if d.m == m):
            title = f"### {d.criterion} plan, m = {m}: max error {d.scores.max_rms_error_m * 1e3:.4f} mm"
            lines += [title, "", plan_markdown(problem, d), ""]
    lines += ["## Files", "", *[f"- `{f}`" for f in files], ""]
    return "\n".join(lines)
