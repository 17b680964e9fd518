"""Results: the JSON record of a solved case and the Table-4-shaped summary.

``results.json`` is in SI units (m, rad, N) and holds enough to recompute every figure without
this package: sigma, the test poses (q, F), every plan (q, F) and its errors.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .measures import CRITERIA, Scores
from .problem import Problem
from .solve import Design, StartRecord

#: Relative tolerance within which two starts count as reaching the same optimum.
SAME_OPTIMUM_RTOL = 1e-6


def optimum_spread(design: Design) -> dict:
    """Test-pose errors (m) of every converged start that reached the design's optimum.

    Optimal plans need not be unique; when the criterion is not the test-pose measure,
    equally optimal plans may give different accuracy. ``min``/``max`` over those starts.
    """
    best = design.scores.value(design.criterion)
    tied = [
        s.max_rms_error_m
        for s in design.starts
        if s.converged and abs(s.value - best) <= SAME_OPTIMUM_RTOL * max(abs(best), 1.0)
    ]
    return {"starts_at_optimum": len(tied), "min_max_rms_error_m": min(tied), "max_max_rms_error_m": max(tied)}


def design_record(design: Design) -> dict:
    """One design as plain data (SI units)."""
    values = [s.value for s in design.starts if s.converged]
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
                {"status": s.status, "iterations": s.iterations, "value": s.value,
                 "max_rms_error_m": s.max_rms_error_m, "feasible": s.feasible}
                for s in design.starts
            ],
        },
    }


def results_dict(problem: Problem, designs: list[Design]) -> dict:
    """The whole results record of a solved problem."""
    tp = problem.test_poses
    return {
        "problem": problem.name,
        "problem_file": problem.path,
        "seed": problem.solver.seed,
        "sigma_m": problem.sigma_m,
        "robot": problem.raw["robot"],
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
        "measured_components": problem.raw["measurement"]["components"],
        "units": {"q": "rad", "force": "N (N m for moments)", "errors": "m"},
        "test_poses": [
            {"q_rad": q.tolist(), "force": f.tolist(), "position_m": p.tolist()}
            for q, f, p in zip(tp.q, tp.F, tp.position_m)
        ],
        "designs": [design_record(d) for d in designs],
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
        starts=tuple(StartRecord(**s) for s in solver["per_start"]),
        wall_s=solver["wall_s"],
        seed=solver["seed"],
    )


def read_json(path: Path) -> dict:
    """A results.json / sweep.json file, or the one inside a folder (sweep.json first)."""
    path = Path(path)
    if path.is_dir():
        found = [path / n for n in ("sweep.json", "results.json") if (path / n).is_file()]
        if not found:
            raise OutputError(f"{path}: no sweep.json or results.json in this folder; "
                              "give the file written by `casadi-design solve` or `sweep`")
        path = found[0]
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise OutputError(f"{path}: no such results file") from None
    except json.JSONDecodeError as exc:
        raise OutputError(f"{path}: not valid JSON ({exc}); give a results.json or sweep.json") from None
    if not isinstance(record, dict) or "designs" not in record:
        raise OutputError(f"{path}: has no 'designs'; give a results.json or sweep.json")
    record["_path"] = str(path)
    return record


class OutputError(ValueError):
    """An output folder or file cannot be written (or read back) as asked."""


def prepare_out(out: Path, force: bool = False, resume: bool = False) -> Path:
    """Check that ``out`` may be written: missing, empty, or ``force``/``resume`` given.

    Nothing is created here, so an error later leaves no folder behind.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()) and not (force or resume):
        raise OutputError(f"{out}: folder exists and is not empty; add --force to overwrite "
                          "its files (or choose another --out)")
    return out


def write_json(path: Path, record: dict) -> None:
    """``record`` as indented JSON, atomically."""
    write_atomic(path, (json.dumps(record, indent=2) + "\n").encode())


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (never half-written)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_results(path: Path, problem: Problem, designs: list[Design]) -> dict:
    record = results_dict(problem, designs)
    write_atomic(path, (json.dumps(record, indent=2) + "\n").encode())
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
        )
    return "\n".join(out)
