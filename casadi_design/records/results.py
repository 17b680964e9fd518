"""Results records: designs, approximate designs and cells to and from plain dicts.

``results.json`` is in SI units (m, rad, N) and holds enough to recompute every figure without
this package: sigma, the test poses (q, F), every plan (q, F) and its errors.
:func:`check_results` says what is wrong with a record read back, naming the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
from importlib.metadata import version

import numpy as np

from ..cell.capsules import capsule_names
from ..cell.cell import Clearance
from ..measures.criteria import CRITERIA
from ..measures.measures import Scores
from ..optimisation.bound import ApproximateDesign
from ..plan.design import Bound, Design, Seating, StartRecord
from ..problem.build import Problem
from ..runtime.threads import blas_kernels


def experiment_records(Q: np.ndarray, F: np.ndarray, near: tuple[Clearance, ...] | None) -> list[dict]:
    """The experiments of a plan (``Q`` (m, n), rad; ``F`` (m, nF), N) as plain data, each with
    its clearance on the real geometry (``clearance_m``, m) and the two bodies at that distance
    (``closest_bodies``) when ``near`` is given."""
    return [{"q_rad": q.tolist(), "force": f.tolist()}
            | ({"clearance_m": c.distance_m, "closest_bodies": list(c.between)} if c else {})
            for q, f, c in zip(Q, F, near or [None] * len(Q))]


def campaign_records(problem: Problem | None, design: Design) -> list[dict]:
    """The experiments of a design's campaign (:meth:`~casadi_design.problem.build.Problem.campaign`):
    the measured ones first, marked ``"measured": true``, then the plan's."""
    held = [] if problem is None else experiment_records(*problem.measured, None)
    new = experiment_records(design.Q, design.F, design.clearances)
    if design.seated is not None:
        new = [e | s for e, s in zip(new, design.seated.as_records())]
    return [e | {"measured": True} for e in held] + new


def design_record(design: Design, problem: Problem | None = None) -> dict:
    """One design as plain data (SI units); with a ``[cell]``, each experiment carries its
    clearance on the real geometry (``clearance_m``, m) and the two bodies at that distance
    (``closest_bodies``). With experiments already measured (``problem.m_held``), they come
    first (:func:`campaign_records`); ``m`` counts the new ones, ``m_measured`` the others, and
    the errors and scores are the campaign's."""
    values = [st.value for st in design.starts if st.converged]
    crit = CRITERIA[design.criterion]
    k = 0 if problem is None else problem.m_held
    return {
        "criterion": design.criterion,
        "m": design.m,
        **({"m_measured": k} if k else {}),
        "experiments": campaign_records(problem, design),
        "rms_error_m": design.scores.rms_error_m.tolist(),
        "max_rms_error_m": design.scores.max_rms_error_m,
        "scores": {k: v for k, v in design.scores.as_dict().items() if k != "rms_error_m"},
        "optimum": design.optimum_spread(),
        "bound": None if design.bound is None else {
            "value": design.bound.value, "relaxation": design.bound.relaxation,
            "gap_percent": design.gap_percent, "L": design.bound.L,
            "meaning": crit.bound.meaning},
        "solver": {
            "status": design.status,
            "starts": len(design.starts),
            "converged": design.converged_starts,
            "iterations": design.iterations,
            "exchange": dict(zip(("starts", "passes", "swaps"), design.exchange)),
            "wall_s": design.wall_s,
            "seed": design.seed,
            "objective_spread": {"best": design.scores.value(design.criterion),
                                 "worst": crit.worst(values),
                                 "median": float(np.median(values))},
            "per_start": [
                {"status": st.status, "iterations": st.iterations, "value": st.value,
                 "max_rms_error_m": st.max_rms_error_m, "feasible": st.feasible, "origin": st.origin,
                 "runs": st.runs, "rows_held": st.rows_held, "swaps": st.swaps}
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
            "exchange_steps": len(approx.history), "independent_checks": len(approx.checked),
            "pool_size": approx.pool_size,
            "wall_s": approx.wall_s, **({"m_new": approx.m} if approx.m else {})}


#: The libraries whose versions a results record names (their rounding decides which start wins).
NUMERIC_LIBRARIES = ("casadi", "numpy", "scipy", "pin")


def results_dict(problem: Problem, designs: list[Design],
                 approx: dict[tuple[str, int], ApproximateDesign] | None = None) -> dict:
    """The whole results record of a solved problem (with the approximate designs of the
    bounds, when computed)."""
    tp = problem.test_poses
    return {
        "problem": problem.name,
        "problem_file": problem.path,
        "seed": problem.solver.seed,
        # what the numbers were computed with (README, Same numbers on any machine)
        "blas_kernels": blas_kernels(),
        "versions": {name: version(name) for name in NUMERIC_LIBRARIES},
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
        **({"held": held} if (held := held_record(problem)) else {}),
        "designs": [design_record(d, problem) for d in designs],
        "approximate_designs": [approximate_record(a) for a in (approx or {}).values()],
        "cell": cell_record(problem),
    }


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


def held_record(problem: Problem) -> dict | None:
    """What the designs of ``problem`` hold before their plans (None: nothing): the files, the
    number of measured experiments and the prior's parameters."""
    held = problem.spec.held
    if held is None and problem.M_held is None:
        return None
    return {"files": [] if held is None else list(held.sources), "m_measured": problem.m_held,
            "prior_parameters": [] if held is None else list(held.prior_names),
            "calibration_prior": problem.spec.calibration.prior is not None,
            "smallest_m_new": problem.m_min}


def design_from_record(record: dict) -> Design:
    """The :class:`Design` written by :func:`design_record` (exact: JSON floats round-trip);
    the measured experiments of its campaign left out."""
    m, exps = record["m"], [e for e in record["experiments"] if not e.get("measured")]
    saved = record["scores"]
    scores = Scores(np.array(record["rms_error_m"], dtype=float),
                    {c.score: saved[c.score] for c in CRITERIA.values()}, saved["observability"],
                    saved["identifiable"])
    solver = record["solver"]
    near = [Clearance(e["clearance_m"], tuple(e["closest_bodies"])) for e in exps if "clearance_m" in e]
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
        clearances=tuple(near) if len(near) == m else None,
        seated=_seating(exps),
    )


def _seating(exps: list[dict]) -> Seating | None:
    """The :class:`~casadi_design.plan.design.Seating` of a design's experiments (records with
    ``point`` and ``placement``), None when they have none."""
    if not exps or "point" not in exps[0]:
        return None
    names = tuple(dict.fromkeys(e["placement"] for e in exps))
    return Seating(np.array([e["point"] for e in exps], dtype=int),
                   np.array([names.index(e["placement"]) for e in exps], dtype=int), names)


#: Numeric fields of a design's ``scores`` (finite: a design's plan is identifiable).
_SCORE_NUMBERS = tuple(c.score for c in CRITERIA.values())
#: The keys of one start in ``solver.per_start``: the fields of :class:`StartRecord`; those
#: with a default (``origin``, ``runs``, ``rows_held``, ``swaps``) may be missing (files of earlier
#: versions).
_START_KEYS = tuple(f.name for f in dataclasses.fields(StartRecord))
_START_REQUIRED = tuple(f.name for f in dataclasses.fields(StartRecord)
                        if f.default is dataclasses.MISSING)


class MalformedRecord(Exception):
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
        raise MalformedRecord(f"{where}: expected {expected}, got {_shown(value)}")


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
        raise MalformedRecord(f"{where}: missing key '{missing[0]}'")
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
    """Raise ``MalformedRecord`` unless ``d`` is a record :func:`design_from_record` reads."""
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
    k = d.get("m_measured", 0)
    _int(k, f"{where}.m_measured", 0)
    _need(isinstance(exps, list) and len(exps) == d["m"] + k, f"{where}.experiments",
          f"a list of m + m_measured = {d['m'] + k} experiments", exps)
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
            raise MalformedRecord(f"{at}: unexpected key '{extra[0]}'")
        _need(isinstance(s["status"], str), f"{at}.status", "a string", s["status"])
        _int(s["iterations"], f"{at}.iterations", 0)
        for k in ("value", "max_rms_error_m"):  # null (or +-Infinity, NaN) for a start that failed
            _need(s[k] is None or _is_number(s[k], finite=False), f"{at}.{k}", "a number or null", s[k])
        _need(isinstance(s["feasible"], bool), f"{at}.feasible", "true or false", s["feasible"])
        _need(isinstance(s.get("origin", ""), str), f"{at}.origin", "a string", s.get("origin"))
        _int(s.get("runs", 1), f"{at}.runs", 1)
        _int(s.get("rows_held", 0), f"{at}.rows_held", 0)
        _int(s.get("swaps", 0), f"{at}.swaps", 0)


def check_results(record: object) -> None:
    """Raise ``MalformedRecord`` unless ``record`` is a results or sweep record that
    :func:`design_from_record`, ``plot`` and ``evaluate --compare`` can use."""
    if not isinstance(record, dict):
        raise MalformedRecord(f"holds {_shown(record)}, not a results record (a JSON object)")
    missing = [k for k in ("problem", "test_poses", "designs") if k not in record]
    if missing:
        raise MalformedRecord(f"has no '{missing[0]}'")
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
    per = sweep.get("criterion_starts", {})
    _need(isinstance(per, dict), "sweep.criterion_starts", "a table of criterion: starts", per)
    for c, k in per.items():
        _need(c in CRITERIA, "sweep.criterion_starts", f"criteria among {', '.join(CRITERIA)}", c)
        _int(k, f"sweep.criterion_starts.{c}", 1)
    _need(isinstance(sweep["warm_start"], bool), "sweep.warm_start", "true or false",
          sweep["warm_start"])
    if sweep["reference"] is not None:
        _check_design(sweep["reference"], "sweep.reference", sizes)
    solved = {(d["criterion"], d["m"]) for d in designs}
    grid = ((c, m) for m in sweep["m"] for c in sweep["criteria"])
    lost = next((cm for cm in grid if cm not in solved), None)
    if lost:
        raise MalformedRecord(f"designs: no design for criterion {lost[0]}, m = {lost[1]} of the sweep")
