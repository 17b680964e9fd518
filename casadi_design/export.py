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
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from .errors import ProblemError
from .models import WRENCH_ROWS
from .problem import Problem
from .results import write_atomic
from .solve import Design

#: Largest disagreement (rad or m) between the two unit columns of one joint in a plan CSV.
UNIT_AGREEMENT_TOL = 1e-6
POSITION_COLUMNS = ("x_mm", "y_mm", "z_mm")


def is_prismatic(problem: Problem, k: int) -> bool:
    """Whether joint ``k`` of the chain is prismatic (its value in m, not rad)."""
    robot = problem.robot
    return robot.model.joints[robot.joint_ids[k]].shortname().startswith("JointModelP")


def joint_units(problem: Problem, k: int) -> tuple[str, str, float]:
    """(SI unit suffix, people's unit suffix, SI per people's unit) of joint ``k``."""
    return ("m", "mm", 1e-3) if is_prismatic(problem, k) else ("rad", "deg", math.pi / 180)


def force_columns(problem: Problem) -> list[str]:
    """Column names of the load components: ``fx_N``..., ``mx_Nm``..."""
    return [f"{WRENCH_ROWS[r]}_{'N' if WRENCH_ROWS[r][0] == 'f' else 'Nm'}"
            for r in problem.model.force_rows]


def plan_table(problem: Problem, Q: np.ndarray, F: np.ndarray) -> tuple[list[str], list[list]]:
    """Header and rows of a plan: ``Q`` shape (m, n), rad (m); ``F`` shape (m, nF), N (N m)."""
    joints = problem.robot.joints
    units = [joint_units(problem, k) for k in range(len(joints))]
    header = (["experiment"] + [f"{j}_{u[1]}" for j, u in zip(joints, units)]
              + [f"{j}_{u[0]}" for j, u in zip(joints, units)] + force_columns(problem)
              + list(POSITION_COLUMNS))
    rows = []
    for i, (q, f) in enumerate(zip(np.asarray(Q, float), np.asarray(F, float).reshape(len(Q), -1))):
        p = np.asarray(problem.model.position(q), dtype=float).ravel() * 1e3
        rows.append([i + 1] + [qk / u[2] for qk, u in zip(q, units)] + list(q) + list(f) + list(p))
    return header, rows


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
    write_atomic(Path(path), csv_text(*plan_table(problem, design.Q, design.F)).encode())


def write_table_csv(path: Path, columns: tuple[str, ...] | list[str], rows: list[dict]) -> None:
    """Rows (dicts) as CSV with the given columns, atomically."""
    write_atomic(Path(path), csv_text(list(columns), [[r[c] for c in columns] for r in rows]).encode())


def read_plan_csv(problem: Problem, path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """A plan from a CSV file: ``Q`` shape (n, m), rad (m); ``F`` shape (nF, m), N (N m).

    Raises
    ------
    ProblemError
        Missing or unknown columns, non-numbers, disagreeing unit columns (one line each).
    """
    path = str(path)
    try:
        with open(path, newline="") as fh:
            lines = [ln for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    except FileNotFoundError:
        raise ProblemError(f"{path}: no such plan file") from None
    reader = csv.reader(lines)
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise ProblemError(f"{path}: empty plan file; give a header row and one row per experiment") from None
    rows = [r for r in reader]
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
    allowed = set(columns) | set(forces) | {"experiment", *POSITION_COLUMNS}
    unknown = [h for h in header if h not in allowed]
    if unknown:
        si, people, _ = joint_units(problem, 0)
        raise ProblemError(
            f"{path}: unknown column '{unknown[0]}'; allowed: q1_{people} or q1_{si} ... "
            f"q{robot.n}_<unit> (or joint names {', '.join(robot.joints)} with the unit suffix)"
            + (f", {', '.join(forces)}" if forces else "") + ", experiment, x_mm, y_mm, z_mm")
    if len(set(header)) != len(header):
        raise ProblemError(f"{path}: repeated column names in {header}")

    def number(r: int, c: int) -> float:
        try:
            v = float(rows[r][c])
        except (ValueError, IndexError):
            got = rows[r][c] if c < len(rows[r]) else "nothing"
            raise ProblemError(f"{path}: row {r + 2}, column '{header[c]}': expected a number, "
                               f"got '{got}'") from None
        if not math.isfinite(v):
            raise ProblemError(f"{path}: row {r + 2}, column '{header[c]}': not finite ({v})")
        return v

    m = len(rows)
    Q = np.full((robot.n, m), np.nan)
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
                f"{path}: the columns {', '.join(header[c] for c, _ in given)} of joint {j} "
                f"disagree by {spread:.3g} (rad or m); give one of them or fix the values")
        # the SI column when given (exact), else the people's unit converted
        Q[k] = values[next((i for i, (_, s) in enumerate(given) if s == 1.0), 0)]
    nF = problem.model.nF
    if nF == 0:
        return Q, np.zeros((0, m))
    present = [h in header for h in forces]
    if not any(present) and problem.force is not None and problem.force.mode == "fixed":
        return Q, np.tile(np.array(problem.force.vector_N)[:, None], (1, m))
    if not all(present):
        missing = [h for h, p in zip(forces, present) if not p]
        raise ProblemError(f"{path}: missing force column '{missing[0]}'; the plan needs the "
                           f"calibration load of each experiment: {', '.join(forces)} (N, N m)")
    F = np.array([[number(r, header.index(h)) for r in range(m)] for h in forces])
    return Q, F


#: Relative tolerance on the load magnitude of a plan written by hand (rounded components).
LOAD_RTOL = 1e-3


def plan_violations(problem: Problem, Q: np.ndarray, F: np.ndarray) -> list[str]:
    """What a plan (``Q`` n x m rad, ``F`` nF x m N) breaks among the problem's constraints.

    Joint limits and workspace to ``solve.FEASIBILITY_TOL`` (rad, m); loads to ``LOAD_RTOL``.
    """
    from .solve import FEASIBILITY_TOL, workspace_violation

    robot, out = problem.robot, []
    for i, q in enumerate(np.asarray(Q).T):
        for k, j in enumerate(robot.joints):
            if not robot.q_min[k] - FEASIBILITY_TOL <= q[k] <= robot.q_max[k] + FEASIBILITY_TOL:
                out.append(f"experiment {i + 1}: {j} = {q[k]:.6g} outside [{robot.q_min[k]:.6g}, "
                           f"{robot.q_max[k]:.6g}]")
        v = workspace_violation(problem, np.asarray(problem.model.position(q), dtype=float).ravel())
        if v > FEASIBILITY_TOL:
            out.append(f"experiment {i + 1}: measured point {v * 1e3:.3g} mm outside the workspace")
    force = problem.force
    if force is not None and np.size(F):
        for i, f in enumerate(np.asarray(F).T):
            norm = float(np.linalg.norm(f))
            if force.mode == "fixed" and not np.allclose(f, force.vector_N, rtol=LOAD_RTOL):
                out.append(f"experiment {i + 1}: load {f.tolist()} is not the fixed {list(force.vector_N)}")
            elif force.mode != "fixed" and norm > force.magnitude_N * (1 + LOAD_RTOL):
                out.append(f"experiment {i + 1}: |F| = {norm:.6g} above {force.magnitude_N:g}")
            elif force.mode == "equal" and norm < force.magnitude_N * (1 - LOAD_RTOL):
                out.append(f"experiment {i + 1}: |F| = {norm:.6g}, the problem applies {force.magnitude_N:g}")
    return out


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

    return "\n".join([line(header), "|" + "---|" * len(header)] + [line(r) for r in rows])


def plan_markdown(problem: Problem, design: Design) -> str:
    """A plan as a Markdown table: joints (deg or mm), load (N), measured point (mm)."""
    header, rows = plan_table(problem, design.Q, design.F)
    n = problem.robot.n
    keep = [0, *range(1, 1 + n), *range(1 + 2 * n, len(header))]
    return _md_table([header[c] for c in keep],
                     [[str(r[0])] + [f"{r[c]:.2f}" for c in keep[1:]] for r in rows])


def report_markdown(problem: Problem, designs: list[Design], *, table: str, figures: list[tuple[str, str]],
                    plans_for: list[int], files: list[str], starts: int, title: str = "Calibration plan",
                    notes: list[str] = ()) -> str:
    """The one-page report: the case, the table, the figures, the plans for ``plans_for`` m.

    ``table`` is a preformatted text table (mm); ``figures`` are (caption, relative file).
    """
    raw, model, tp = problem.raw, problem.model, problem.test_poses
    force = problem.force
    load = ("none (geometric case)" if force is None else
            f"{force.mode}, |F| = {force.magnitude_N:g} N" if force.mode != "fixed" else
            f"fixed F = {list(force.vector_N)} N")
    x = tp.position_m * 1e3
    lines = [
        f"# {title}: {problem.name}",
        "",
        str(raw.get("description", "")),
        "",
        _md_table(["", ""], [
            ["problem file", f"`{problem.path}`"],
            ["robot", (f"{problem.robot.name}, {problem.robot.n} joints "
                       f"({', '.join(problem.robot.joints)}), measured frame `{problem.robot.frame}`")],
            ["identified", f"{model.case}: {', '.join(model.parameter_names)}"],
            ["measured", f"{', '.join(raw['measurement']['components'])}, sigma = {problem.sigma_m * 1e3:g} mm"],
            ["test poses", (f"{tp.s} poses, from ({', '.join(f'{v:.0f}' for v in x[0])}) to "
                            f"({', '.join(f'{v:.0f}' for v in x[-1])}) mm")],
            ["calibration load", load],
            ["solver", f"IPOPT, {starts} seeded starts per design, seed {problem.solver.seed}"],
        ]),
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
    lines += ["## Plans", "", ("Joints in deg (mm for prismatic joints), load in N, measured point "
                               "in mm; full precision in the plans/*.csv files."), ""]
    for m in plans_for:
        for d in (d for d in designs if d.m == m):
            title = f"### {d.criterion} plan, m = {m}: max error {d.scores.max_rms_error_m * 1e3:.4f} mm"
            lines += [title, "", plan_markdown(problem, d), ""]
    lines += ["## Files", "", *[f"- `{f}`" for f in files], ""]
    return "\n".join(lines)
