"""Results: the JSON record of a solved case and the Table-4-shaped summary.

``results.json`` is in SI units (m, rad, N) and holds enough to recompute every figure without
this package: sigma, the test poses (q, F), every plan (q, F) and its errors.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from .build import Problem
from .cell import clearances
from .collision import capsule_names
from .criteria import CRITERIA
from .measures import Scores
from .bound import ApproximateDesign, Bound
from .solve import SEEDED, Design, StartRecord

def optimum_spread(design: Design) -> dict:
    """Test-pose errors (m) of every converged start that reached the design's optimum.

    Optimal plans need not be unique; when the criterion is not the test-pose measure,
    equally optimal plans may give different accuracy. ``min``/``max`` over those starts.
    """
    crit = CRITERIA[design.criterion]
    best = design.scores.value(design.criterion)
    tied = [st.max_rms_error_m for st in design.starts if st.converged and crit.same_optimum(st.value, best)]
    return {"starts_at_optimum": len(tied), "min_max_rms_error_m": min(tied), "max_max_rms_error_m": max(tied)}


#: What the ``bound.value`` of a design record bounds (units of the score).
BOUND_MEANING = {"test-pose": "lower bound of max_rms_error_m (m) of any plan of m experiments",
                 "D": "upper bound of log_det_M of any plan of m experiments",
                 "A": "lower bound of trace_M_inv of any plan of m experiments"}


def design_record(design: Design) -> dict:
    """One design as plain data (SI units)."""
    values = [st.value for st in design.starts if st.converged]
    return {
        "criterion": design.criterion,
        "m": design.m,
        "experiments": [
            {"q_rad": q.tolist(), "force": f.tolist()} for q, f in zip(design.Q, design.F)
        ],
        "rms_error_m": design.scores.rms_error_m.tolist(),
        "max_rms_error_m": design.scores.max_rms_error_m,
        "scores": {k: v for k, v in design.scores.as_dict().items() if k != "rms_error_m"},
        "optimum": optimum_spread(design),
        "bound": None if design.bound is None else {
            "value": design.bound.value, "relaxation": design.bound.relaxation,
            "gap_percent": design.gap_percent, "L": design.bound.L,
            "meaning": BOUND_MEANING[design.criterion]},
        "solver": {
            "status": design.status,
            "starts": len(design.starts),
            "converged": design.converged_starts,
            "iterations": design.iterations,
            "wall_s": design.wall_s,
            "seed": design.seed,
            "objective_spread": {"best": design.scores.value(design.criterion),
                                 "worst": max(values) if CRITERIA[design.criterion].sense == "min" else min(values),
                                 "median": float(np.median(values))},
            "per_start": [
                {"status": st.status, "iterations": st.iterations, "value": st.value,
                 "max_rms_error_m": st.max_rms_error_m, "feasible": st.feasible, "origin": st.origin}
                for st in design.starts
            ],
        },
    }


def approximate_record(approx: ApproximateDesign) -> dict:
    """An approximate design as plain data (SI units)."""
    return {"criterion": approx.criterion,
            "support": [{"q_rad": q.tolist(), "force": f.tolist(), "weight": float(w)}
                        for q, f, w in zip(approx.Q, approx.F, approx.weights)],
            "relaxation": approx.value, "certified": approx.certified, "d_max": approx.d_max,
            "exchange_steps": len(approx.history), "pool_size": approx.pool_size,
            "wall_s": approx.wall_s}


def results_dict(problem: Problem, designs: list[Design],
                 approx: dict[str, ApproximateDesign] | None = None) -> dict:
    """The whole results record of a solved problem (with the approximate designs of the
    bounds, when computed)."""
    tp = problem.test_poses
    return {
        "problem": problem.name,
        "problem_file": problem.path,
        "seed": problem.solver.seed,
        "sigma_m": problem.sigma_m,
        "robot": dataclasses.asdict(problem.spec.robot),
        "calibration": {
            "case": problem.model.case,
            "parameters": list(problem.model.parameter_names),
            "column_scale": problem.model.column_scale.tolist(),
            "base_set": None if problem.base_set is None else {
                "rank": problem.base_set.rank,
                "rank_rtol": problem.base_set.rank_rtol,
                "kept": list(problem.base_set.kept),
                "dropped": [{"parameter": n, "reason": r} for n, r in problem.base_set.dropped],
            },
        },
        "measured_components": list(problem.spec.measurement.components),
        "units": {"q": "rad", "force": "N (N m for moments)", "errors": "m"},
        "test_poses": [
            {"q_rad": q.tolist(), "force": f.tolist(), "position_m": p.tolist()}
            for q, f, p in zip(tp.q, tp.F, tp.position_m)
        ],
        "designs": [with_clearances(problem, design_record(d)) for d in designs],
        "approximate_designs": [approximate_record(a) for a in (approx or {}).values()],
        "cell": cell_record(problem),
    }


def with_clearances(problem: Problem, record: dict) -> dict:
    """A design record whose experiments carry their clearance on the real geometry
    (``clearance_m``, m) and the two bodies at that distance (``closest_bodies``), when the
    problem has a ``[cell]`` (:func:`casadi_design.cell.clearances`)."""
    if problem.cell is None:
        return record
    Q = np.array([e["q_rad"] for e in record["experiments"]], dtype=float).T
    for e, c in zip(record["experiments"], clearances(problem.cell, Q)):
        e["clearance_m"], e["closest_bodies"] = c.distance_m, list(c.between)
    return record


def cell_record(problem: Problem) -> dict | None:
    """The cell as built (None without ``[cell]``): clearance (m), the geometry plans are
    checked on, the capsules, and every pair of bodies the rows leave out, with the reason."""
    cell = problem.cell
    if cell is None:
        return None
    names = capsule_names(cell.capsules)
    return {
        "clearance_m": cell.spec.clearance_m,
        "checked_on": cell.check.source,
        "capsules": [{"name": n, "frame": c.frame, "a_m": list(c.a_m), "b_m": list(c.b_m), "radius_m": c.radius_m}
                     for n, c in zip(names, cell.capsules)],
        "self_collision_pairs": [[names[i], names[j]] for i, j in cell.pairs.kept],
        "obstacle_pairs": [[names[k], cell.obstacles[o].name or "capsule obstacle"] for k, o in cell.near],
        "pairs_left_out": [{"bodies": list(k), "reason": r}
                           for k, r in {**cell.pairs.skipped, **cell.near_skipped}.items()],
        "tracker": None if cell.spec.tracker is None else dataclasses.asdict(cell.spec.tracker),
    }


def design_from_record(record: dict) -> Design:
    """The :class:`Design` written by :func:`design_record` (exact: JSON floats round-trip)."""
    m, exps = record["m"], record["experiments"]
    names = {f.name for f in dataclasses.fields(Scores)}
    scores = Scores(rms_error_m=np.array(record["rms_error_m"], dtype=float),
                    **{k: v for k, v in record["scores"].items() if k in names})
    solver = record["solver"]
    return Design(
        criterion=record["criterion"],
        m=m,
        Q=np.array([e["q_rad"] for e in exps], dtype=float).reshape(m, len(exps[0]["q_rad"])),
        F=np.array([e["force"] for e in exps], dtype=float).reshape(m, len(exps[0]["force"])),
        scores=scores,
        status=solver["status"],
        starts=tuple(StartRecord(**{k: math.nan if v is None else v for k, v in st.items()})
                     for st in solver["per_start"]),
        wall_s=solver["wall_s"],
        seed=solver["seed"],
        bound=None if record.get("bound") is None else Bound(
            record["criterion"], m, record["bound"]["value"], record["bound"]["relaxation"],
            record["bound"]["L"]),
    )


#: What to do with a results file that cannot be read back.
_RESULTS_HINT = "give a results file written by casadi-design solve or sweep"


#: Numeric fields of a design's ``scores`` (finite: a design's plan is identifiable).
_SCORE_NUMBERS = ("max_rms_error_m", "log_det_M", "trace_M_inv", "s_min", "trace_M", "condition")
#: The keys of one start in ``solver.per_start``: the fields of :class:`StartRecord`; those
#: with a default (``origin``) may be missing (files of earlier versions).
_START_KEYS = tuple(f.name for f in dataclasses.fields(StartRecord))
_START_REQUIRED = tuple(f.name for f in dataclasses.fields(StartRecord)
                        if f.default is dataclasses.MISSING)


class _Malformed(Exception):
    """What is wrong at one place of a results record, e.g. ``designs[3].m: expected ...``."""


def _shown(value: object) -> str:
    """A JSON value as a message shows it: scalars as written, containers by their kind."""
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _need(ok: bool, where: str, expected: str, value: object) -> None:
    if not ok:
        raise _Malformed(f"{where}: expected {expected}, got {_shown(value)}")


def _is_number(value: object, finite: bool = True) -> bool:
    """A JSON number (not a boolean, not a string); ``finite``: not NaN or +-Infinity either."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return not finite or bool(np.isfinite(float(value)))
    except OverflowError:  # an integer beyond the float range
        return False


def _int(value: object, where: str, minimum: int) -> None:
    _need(isinstance(value, int) and not isinstance(value, bool) and value >= minimum, where,
          f"an integer >= {minimum}", value)


def _object(value: object, where: str, keys: tuple[str, ...]) -> dict:
    """``value`` as an object that has ``keys``."""
    _need(isinstance(value, dict), where, "an object", value)
    missing = [k for k in keys if k not in value]
    if missing:
        raise _Malformed(f"{where}: missing key '{missing[0]}'")
    return value


def _numbers(value: object, where: str, sizes: dict[str, tuple[int, str]], kind: str) -> None:
    """A list of finite numbers, as long as the first list of its ``kind`` (``sizes``: kind ->
    length and where it was set). Only force lists may be empty (a geometric case has no load).
    """
    _need(isinstance(value, list) and (value or kind == "force"), where,
          "a non-empty list of numbers", value)
    for i, v in enumerate(value):
        _need(_is_number(v), f"{where}[{i}]", "a finite number", v)
    n, like = sizes.setdefault(kind, (len(value), f"as {where}"))
    _need(len(value) == n, where, f"{n} numbers ({like})", value)


def _check_design(d: object, where: str, sizes: dict[str, tuple[int, str]]) -> None:
    """Raise :class:`_Malformed` unless ``d`` is a record :func:`design_from_record` reads."""
    d = _object(d, where, ("criterion", "m", "experiments", "rms_error_m", "scores", "solver"))
    _need(isinstance(d["criterion"], str) and d["criterion"] in CRITERIA, f"{where}.criterion",
          f"one of {', '.join(CRITERIA)}", d["criterion"])
    _int(d["m"], f"{where}.m", 1)
    b = d.get("bound")
    if b is not None:
        b = _object(b, f"{where}.bound", ("value", "relaxation", "L"))
        for k in ("value", "relaxation"):
            _need(_is_number(b[k]), f"{where}.bound.{k}", "a finite number", b[k])
        _int(b["L"], f"{where}.bound.L", 1)
    exps = d["experiments"]
    _need(isinstance(exps, list) and len(exps) == d["m"], f"{where}.experiments",
          f"a list of m = {d['m']} experiments", exps)
    for i, e in enumerate(exps):
        e = _object(e, f"{where}.experiments[{i}]", ("q_rad", "force"))
        _numbers(e["q_rad"], f"{where}.experiments[{i}].q_rad", sizes, "q_rad")
        _numbers(e["force"], f"{where}.experiments[{i}].force", sizes, "force")
    _numbers(d["rms_error_m"], f"{where}.rms_error_m", sizes, "test poses")
    scores = _object(d["scores"], f"{where}.scores",
                     _SCORE_NUMBERS + ("observability", "identifiable"))
    for k in _SCORE_NUMBERS:
        _need(_is_number(scores[k]), f"{where}.scores.{k}", "a finite number", scores[k])
    obs = scores["observability"]
    _need(isinstance(obs, dict), f"{where}.scores.observability", "an object", obs)
    for k, v in obs.items():
        _need(_is_number(v), f"{where}.scores.observability.{k}", "a finite number", v)
    _need(isinstance(scores["identifiable"], bool), f"{where}.scores.identifiable", "true or false",
          scores["identifiable"])
    solver = _object(d["solver"], f"{where}.solver", ("status", "per_start", "wall_s", "seed"))
    _need(isinstance(solver["status"], str), f"{where}.solver.status", "a string", solver["status"])
    _need(_is_number(solver["wall_s"]) and solver["wall_s"] >= 0, f"{where}.solver.wall_s",
          "a number of seconds >= 0", solver["wall_s"])
    _int(solver["seed"], f"{where}.solver.seed", 0)
    starts = solver["per_start"]
    _need(isinstance(starts, list) and starts, f"{where}.solver.per_start", "a non-empty list",
          starts)
    for i, s in enumerate(starts):
        at = f"{where}.solver.per_start[{i}]"
        s = _object(s, at, _START_REQUIRED)
        extra = [k for k in s if k not in _START_KEYS]
        if extra:
            raise _Malformed(f"{at}: unexpected key '{extra[0]}'")
        _need(isinstance(s["status"], str), f"{at}.status", "a string", s["status"])
        _int(s["iterations"], f"{at}.iterations", 0)
        for k in ("value", "max_rms_error_m"):  # null (or +-Infinity, NaN) for a start that failed
            _need(s[k] is None or _is_number(s[k], finite=False), f"{at}.{k}", "a number or null", s[k])
        _need(isinstance(s["feasible"], bool), f"{at}.feasible", "true or false", s["feasible"])
        _need(isinstance(s.get("origin", ""), str), f"{at}.origin", "a string", s.get("origin"))


def _check_results(record: object) -> None:
    """Raise :class:`_Malformed` unless ``record`` is a results or sweep record that
    :func:`design_from_record`, ``plot`` and ``evaluate --compare`` can use."""
    if not isinstance(record, dict):
        raise _Malformed(f"holds {_shown(record)}, not a results record (a JSON object)")
    missing = [k for k in ("problem", "test_poses", "designs") if k not in record]
    if missing:
        raise _Malformed(f"has no '{missing[0]}'")
    _need(isinstance(record["problem"], str), "problem", "a string", record["problem"])
    sizes: dict[str, tuple[int, str]] = {}
    poses = record["test_poses"]
    _need(isinstance(poses, list) and poses, "test_poses", "a non-empty list", poses)
    for i, t in enumerate(poses):
        _numbers(_object(t, f"test_poses[{i}]", ("position_m",))["position_m"],
                 f"test_poses[{i}].position_m", sizes, "position_m")
    sizes["test poses"] = (len(poses), "one per test pose")
    designs = record["designs"]
    _need(isinstance(designs, list) and designs, "designs", "a non-empty list", designs)
    for i, d in enumerate(designs):
        _check_design(d, f"designs[{i}]", sizes)
    if "sweep" not in record:
        return
    sweep = _object(record["sweep"], "sweep",
                    ("m", "criteria", "seeded_starts", "warm_start", "reference"))
    _need(isinstance(sweep["m"], list) and sweep["m"], "sweep.m", "a non-empty list", sweep["m"])
    for i, m in enumerate(sweep["m"]):
        _int(m, f"sweep.m[{i}]", 1)
    _need(isinstance(sweep["criteria"], list) and sweep["criteria"], "sweep.criteria",
          "a non-empty list", sweep["criteria"])
    for i, c in enumerate(sweep["criteria"]):
        _need(isinstance(c, str) and c in CRITERIA, f"sweep.criteria[{i}]",
              f"one of {', '.join(CRITERIA)}", c)
    _int(sweep["seeded_starts"], "sweep.seeded_starts", 1)
    _need(isinstance(sweep["warm_start"], bool), "sweep.warm_start", "true or false",
          sweep["warm_start"])
    if sweep["reference"] is not None:
        _check_design(sweep["reference"], "sweep.reference", sizes)
    solved = {(d["criterion"], d["m"]) for d in designs}
    grid = ((c, m) for m in sweep["m"] for c in sweep["criteria"])
    lost = next((cm for cm in grid if cm not in solved), None)
    if lost:
        raise _Malformed(f"designs: no design for criterion {lost[0]}, m = {lost[1]} of the sweep")


def read_json(path: Path | str) -> dict:
    """A results.json / sweep.json file, or the one inside a folder (sweep.json first).

    The record is checked (:func:`_check_results`) before it is returned, so its designs can
    be given to :func:`design_from_record`; ``record["_path"]`` is the file read.

    Raises
    ------
    OutputError
        No such file, not UTF-8 JSON, or a record of another shape (one line, naming the field).
    """
    path = Path(path)
    try:
        if path.is_dir():
            found = [path / n for n in ("sweep.json", "results.json") if (path / n).is_file()]
            if not found:
                raise OutputError(f"{path}: no sweep.json or results.json in this folder; "
                                  "give the file written by `casadi-design solve` or `sweep`")
            path = found[0]
        if path.exists() and not path.is_file():
            raise OutputError(f"{path}: is not a regular file (a device or a pipe); "
                              f"{_RESULTS_HINT}")
        record = json.loads(path.read_bytes().decode("utf-8-sig"))
    except FileNotFoundError:
        raise OutputError(f"{path}: no such results file; check the path") from None
    except OSError as exc:
        raise OutputError(f"{path}: cannot be read ({exc.strerror}); check the path and its "
                          "permissions") from None
    except UnicodeDecodeError as exc:
        raise OutputError(f"{path}: is not UTF-8 text (byte at offset {exc.start}), so not a "
                          f"results file; {_RESULTS_HINT}") from None
    except json.JSONDecodeError as exc:
        raise OutputError(f"{path}: not valid JSON ({exc}); give a results.json or sweep.json") from None
    except RecursionError:
        raise OutputError(f"{path}: JSON nested too deeply; {_RESULTS_HINT}") from None
    try:
        _check_results(record)
    except _Malformed as exc:
        raise OutputError(f"{path}: {exc}; {_RESULTS_HINT}") from None
    record["_path"] = str(path)
    return record


class OutputError(ValueError):
    """An output folder or file cannot be written (or read back) as asked."""


def prepare_out(out: Path | str, force: bool = False, resume: bool = False) -> Path:
    """Check, before anything is solved, that the output folder ``out`` may be written.

    ``out`` may be missing (its parent folder must exist: it is not created), empty, or hold
    files when ``force`` (overwrite them) or ``resume`` is given; ``resume`` needs the
    ``sweep.partial.json`` or ``sweep.json`` of an earlier sweep in it. Nothing is created
    here, so an error later leaves no folder behind.

    Raises
    ------
    OutputError
        Empty name, missing or not writable parent, not a folder, not empty, nothing to resume
        (one line each).
    """
    from .sweep import PARTIAL_NAME

    if not str(out).strip():  # checked on the string: Path("") is "."
        raise OutputError("--out is empty; give a folder name")
    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise OutputError(f"{out}: exists and is not a folder; choose another --out")
        if not out.exists() and not out.parent.is_dir():
            what = "is not a folder" if out.parent.exists() else "does not exist"
            raise OutputError(f"{out}: its parent folder {out.parent} {what}; create it first or "
                              "choose another --out")
        folder = out if out.exists() else out.parent
        if not os.access(folder, os.W_OK | os.X_OK | (os.R_OK if folder == out else 0)):
            raise OutputError(f"{out}: no permission to write in {folder}; choose another --out "
                              "or change the folder's permissions")
        if out.is_dir() and any(out.iterdir()) and not (force or resume):
            raise OutputError(f"{out}: folder exists and is not empty; add --force to overwrite "
                              "its files (or choose another --out)")
        if resume and not any((out / n).is_file() for n in (PARTIAL_NAME, "sweep.json")):
            raise OutputError(f"{out}: nothing to resume (no {PARTIAL_NAME} or sweep.json); run "
                              "without --resume")
    except OSError as exc:
        raise OutputError(f"{out}: cannot be checked ({exc.strerror}); choose another "
                          "--out") from None
    return out


def json_ready(value: object) -> object:
    """``value`` with every non-finite float (a singular plan's error, a failed start) as None,
    so that the file is standard JSON (``null``), readable by any tool."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def write_json(path: Path, record: dict) -> None:
    """``record`` as indented standard JSON (non-finite numbers as ``null``), atomically."""
    write_atomic(path, (json.dumps(json_ready(record), indent=2, allow_nan=False) + "\n").encode())


def _umask() -> int:
    """The process's umask (read by setting it and setting it back: process-global)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (never half-written).

    The file gets the mode a plain ``open(path, "wb")`` gives a new file, ``0o666`` less the
    umask (the temporary file of :func:`tempfile.mkstemp` is ``0o600``).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_results(path: Path, problem: Problem, designs: list[Design],
                  approx: dict[str, ApproximateDesign] | None = None) -> dict:
    record = results_dict(problem, designs, approx)
    write_json(path, record)
    return record


def format_table(designs: list[Design]) -> str:
    """Maximum RMS error along the test poses (mm): rows criteria, columns m (Table 4)."""
    ms = sorted({d.m for d in designs})
    crits = list(dict.fromkeys(d.criterion for d in designs))
    cell = {(d.criterion, d.m): d.scores.max_rms_error_m * 1e3 for d in designs}
    head = f"{'criterion':<12}" + "".join(f"{f'm = {m}':>12}" for m in ms)
    lines = ["max over test poses of sqrt(rho), mm", head, "-" * len(head)]
    for c in crits:
        lines.append(f"{c:<12}" + "".join(
            f"{cell[c, m]:>12.4f}" if (c, m) in cell else f"{'':>12}" for m in ms))
    bounds = {d.m: d.bound.value * 1e3 for d in designs if d.criterion == "test-pose" and d.bound}
    if bounds:
        lines.append(f"{'bound':<12}" + "".join(
            f"{bounds[m]:>12.4f}" if m in bounds else f"{'':>12}" for m in ms))
        lines.append("bound: no plan of m experiments has a smaller max error (certified lower bound)")
    return "\n".join(lines)


def format_solver_lines(designs: list[Design]) -> str:
    """One line per design: wall time, IPOPT iterations, converged starts, optimum spread."""
    out = []
    for d in designs:
        spread = optimum_spread(d)
        out.append(
            f"{d.criterion:<10} m = {d.m:<3} {d.wall_s:7.3f} s  {d.iterations:6d} IPOPT iterations  "
            f"{d.converged_starts}/{len(d.starts)} starts converged  "
            f"{spread['starts_at_optimum']} at the optimum, their error "
            f"{spread['min_max_rms_error_m'] * 1e3:.4f}..{spread['max_max_rms_error_m'] * 1e3:.4f} mm"
            + ("" if d.bound is None else f"  {d.gap_percent:.1f} % from the bound")
            + ("" if d.winner is None or d.winner.origin == SEEDED else f"  (won by the {d.winner.origin})")
        )
    return "\n".join(out)
