"""Sweeps over the number of experiments ``m`` and the criteria: how accuracy grows with m.

For each (criterion, m) the sweep runs :func:`casadi_design.solve.solve_design` with the same
seeded starts as a single solve, plus, for every m after the first, one *warm start*: the
sweep's plan for the previous m (``m_prev``) completed with ``m - m_prev`` random
experiments drawn from their own generator (:func:`warm_start_rng`). The warm start runs
after the seeded starts and wins only when strictly better, so a sweep's design equals the
solve's design when the warm start does not win, and is better when it does; each row says
which happened (``warm_start_won``) and keeps the best seeded result.

Reference line "repeat the best single pose": repeating a plan k times multiplies M by k, so
``sqrt(rho)`` is divided by ``sqrt(k)``. From the best test-pose plan of ``m_ref`` experiments
(``m_ref`` = the smallest identifiable m, 1 for the paper) the line is
``e(m_ref) sqrt(m_ref / m)``; a plan that beats it gains from *different* poses, not from
repetition (the paper: factor 2.5 from 1 to 5 experiments against sqrt(5) = 2.24).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .bound import ROUNDED_PLANS, ApproximateDesign, rounded_starts, with_bound
from .errors import ProblemError
from .criteria import CRITERIA
from .nlp import B0_at_test_poses
from .build import Problem
from .problem import spec_digest_blob
from .solve import SEEDED, Design, StartRecord, random_plan, solve_design

if TYPE_CHECKING:
    from .parallel import StartExecutor

#: The 4th entry of the warm-start generator's seed (start_rng uses 3 entries).
WARM_STREAM = 1


def parse_m_values(text: str) -> list[int]:
    """``"1:10"`` (inclusive range), ``"1:10:3"`` (with a step) or ``"1,2,5"``; sorted, unique.

    Raises ``ValueError`` with a message for people.
    """
    text = text.strip()
    try:
        if ":" in text:
            parts = [int(p) for p in text.split(":")]
            if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] < 1):
                raise ValueError
            values = list(range(parts[0], parts[1] + 1, parts[2] if len(parts) == 3 else 1))
        else:
            values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(
            f"--m takes a range first:last[:step] (e.g. 1:10) or integers separated by commas "
            f"(e.g. 1,2,5), got '{text}'") from None
    if not values or any(v < 1 for v in values):
        raise ValueError(f"--m takes positive numbers of experiments, got '{text}'")
    return sorted(set(values))


def check_m_values(problem: Problem, m_values: Iterable[int]) -> None:
    small = [m for m in m_values if m < problem.m_min]
    if small:
        raise ProblemError(
            f"{problem.path}: --m {small[0]} is too small: {problem.model.L} parameters need "
            f"m >= {problem.m_min} experiments; start the range at {problem.m_min}")


def check_criteria(problem: Problem, criteria: Iterable[str]) -> None:
    for c in criteria:
        if c not in CRITERIA:
            raise ProblemError(f"{problem.path}: --criteria has '{c}'; allowed: {', '.join(CRITERIA)}")


def warm_start_rng(seed: int, criterion: str, m: int) -> np.random.Generator:
    """Generator of the experiments added to the previous plan; not the seeded starts' one."""
    return np.random.default_rng([seed, m, CRITERIA[criterion].seed_id, WARM_STREAM])


def warm_start_plan(problem: Problem, previous: Design, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The plan of ``previous`` (m_prev experiments) plus ``m - m_prev`` random experiments.

    Returns ``Q0`` (n x m, rad) and ``F0`` (nF x m, N), a start for :func:`solve_design`.
    """
    k = m - previous.m
    if k < 1:
        raise ValueError(f"warm start for m = {m} from a plan of {previous.m} experiments")
    Q_new, F_new = random_plan(problem, k, warm_start_rng(problem.solver.seed, previous.criterion, m))
    return np.hstack([previous.Q.T, Q_new]), np.hstack([previous.F.T, F_new])


#: ``StartRecord.origin`` of the warm start of a sweep.
WARM_ORIGIN = "warm start"


def best_seeded(design: Design) -> StartRecord | None:
    """The record that wins among the seeded starts (the rule of solve_design)."""
    crit = CRITERIA[design.criterion]
    best = None
    for rec in design.starts:
        if rec.origin == SEEDED and rec.converged and (best is None or crit.better(rec.value, best.value)):
            best = rec
    return best


@dataclass(frozen=True, eq=False)
class Sweep:
    """The designs of a sweep and how they were obtained.

    Attributes
    ----------
    designs : {(criterion, m): Design}
    seeded_starts : seeded starts per design.
    reference : the best test-pose design at ``problem.m_min``, for the "repeat" line (None when
        the sweep has no test-pose criterion).
    """

    m_values: tuple[int, ...]
    criteria: tuple[str, ...]
    designs: dict[tuple[str, int], Design]
    seeded_starts: int
    warm_start: bool
    reference: Design | None = None

    def warm_start_won(self, criterion: str, m: int) -> bool:
        """True when the warm start is strictly better than every seeded start."""
        winner = self.designs[criterion, m].winner
        return winner is not None and winner.origin == WARM_ORIGIN

    def repeat_reference_m(self, m: int) -> float:
        """``e(m_ref) sqrt(m_ref / m)`` (m): the best m_ref-experiment plan repeated."""
        if self.reference is None:
            return math.nan
        return self.reference.scores.max_rms_error_m * math.sqrt(self.reference.m / m)


def run_sweep(
    problem: Problem,
    criteria: Iterable[str],
    m_values: Iterable[int],
    starts: int | None = None,
    *,
    warm_start: bool = True,
    done: dict[tuple[str, int], Design] | None = None,
    executor: StartExecutor | None = None,
    progress: Callable[[int], object] | None = None,
    on_design: Callable[[Design], object] | None = None,
    verbose: bool = False,
    approx: dict[str, ApproximateDesign] | None = None,
) -> Sweep:
    """Solve every (criterion, m), m ascending; ``done`` designs (a resumed sweep) are kept.

    ``on_design`` is called with each design as soon as it is solved (to save it); the order
    is m ascending, then criteria in the given order. ``approx``: the approximate designs
    (:func:`casadi_design.bound.approximate_designs`) whose rounded plans are extra starts and
    whose bounds the designs carry.
    """
    approx = approx or {}
    criteria, ms = tuple(criteria), tuple(sorted(set(m_values)))
    check_criteria(problem, criteria)
    check_m_values(problem, ms)
    n_seeded = starts or problem.solver.starts
    designs: dict[tuple[str, int], Design] = dict(done or {})
    B0 = B0_at_test_poses(problem)
    for i, m in enumerate(ms):
        for c in criteria:
            if (c, m) in designs:
                if progress is not None:
                    progress(len(designs[c, m].starts))
                continue
            extra = [(*warm_start_plan(problem, designs[c, ms[i - 1]], m), WARM_ORIGIN)] if warm_start and i else []
            d = solve_design(problem, c, m, B0, starts=n_seeded, verbose=verbose,
                             initial_plans=extra + rounded_starts(problem, approx, c, m),
                             executor=executor, progress=progress)
            d = designs[c, m] = with_bound(problem, d, approx)
            if on_design is not None:
                on_design(d)
    m_ref = problem.m_min
    reference = designs.get(("test-pose", m_ref))
    if reference is None and "test-pose" in criteria:
        reference = solve_design(problem, "test-pose", m_ref, B0, starts=n_seeded, verbose=verbose,
                                 executor=executor, progress=progress)
    return Sweep(ms, criteria, {k: designs[k] for k in ((c, m) for m in ms for c in criteria)},
                 n_seeded, warm_start, reference)


def sweep_total_starts(problem: Problem, criteria: Iterable[str], m_values: Iterable[int],
                       starts: int | None = None, warm_start: bool = True,
                       bounded: Iterable[str] = ()) -> int:
    """Number of IPOPT starts a sweep runs (for progress bars), reference design included;
    ``bounded``: the criteria with rounded starts."""
    criteria, ms = tuple(criteria), sorted(set(m_values))
    n = (starts or problem.solver.starts)
    total = len(criteria) * (len(ms) * n + (len(ms) - 1 if warm_start else 0))
    total += len(ms) * ROUNDED_PLANS * len(set(bounded) & set(criteria))
    if "test-pose" in criteria and problem.m_min not in ms:
        total += n
    return total


#: Columns of the sweep table (CSV and JSON), in order, with units.
COLUMNS = (
    "criterion", "m", "max_error_mm", "repeat_best_single_pose_mm", "log_det_M", "trace_M_inv",
    "s_min", "trace_M", "condition", "O1", "O2", "O3", "O4", "O5", "identifiable", "status",
    "starts", "converged", "iterations", "wall_s", "warm_start_won", "seeded_best_max_error_mm",
    "starts_at_optimum", "bound", "gap_percent", "won_by",
)


def sweep_rows(sweep: Sweep) -> list[dict]:
    """One row per (criterion, m): the plan's measures and its solve statistics.

    Errors in mm; the other measures in the SI units of B (see :mod:`casadi_design.measures`).
    """
    from .results import optimum_spread

    rows = []
    for (c, m), d in sweep.designs.items():
        scores = d.scores
        seeded = best_seeded(d)
        rows.append({
            "criterion": c,
            "m": m,
            "max_error_mm": scores.max_rms_error_m * 1e3,
            "repeat_best_single_pose_mm": sweep.repeat_reference_m(m) * 1e3,
            "log_det_M": scores.log_det_M,
            "trace_M_inv": scores.trace_M_inv,
            "s_min": scores.s_min,
            "trace_M": scores.trace_M,
            "condition": scores.condition,
            **{k: scores.observability.get(k, math.nan) for k in ("O1", "O2", "O3", "O4", "O5")},
            "identifiable": scores.identifiable,
            "status": d.status,
            "starts": len(d.starts),
            "converged": d.converged_starts,
            "iterations": d.iterations,
            "wall_s": d.wall_s,
            "warm_start_won": sweep.warm_start_won(c, m),
            "seeded_best_max_error_mm": seeded.max_rms_error_m * 1e3 if seeded else math.nan,
            "starts_at_optimum": optimum_spread(d)["starts_at_optimum"],
            # the bound in the units of the criterion's score (max error in mm for test-pose)
            "bound": None if d.bound is None else d.bound.value * (1e3 if c == "test-pose" else 1.0),
            "gap_percent": None if d.bound is None else d.gap_percent,
            "won_by": "" if d.winner is None else d.winner.origin,
        })
    return rows


def format_sweep_table(sweep: Sweep) -> str:
    """Max error (mm) along the test poses: rows m, columns criteria and the repeat line.

    ``*`` marks a design whose warm start beat every seeded start.
    """
    repeat = sweep.reference is not None  # solved when test-pose is among the criteria
    bounded = ("test-pose" in sweep.criteria
               and all(sweep.designs["test-pose", m].bound for m in sweep.m_values))
    head = (f"{'m':>4}" + "".join(f"{c:>12}" for c in sweep.criteria)
            + (f"{'repeat best':>14}" if repeat else "") + (f"{'bound':>10}" if bounded else ""))
    ref = "" if not repeat else (
        f" (repeat best: the best test-pose plan of {sweep.reference.m} experiment"
        f"{'s' if sweep.reference.m > 1 else ''} repeated, e / sqrt(m / {sweep.reference.m}))")
    lines = ["max over test poses of sqrt(rho), mm" + ref, head, "-" * len(head)]
    for m in sweep.m_values:
        cells = []
        for c in sweep.criteria:
            d = sweep.designs[c, m]
            mark = "*" if sweep.warm_start_won(c, m) else " "
            cells.append(f"{d.scores.max_rms_error_m * 1e3:>11.4f}{mark}")
        lines.append(f"{m:>4}" + "".join(cells)
                     + (f"{sweep.repeat_reference_m(m) * 1e3:>14.4f}" if repeat else "")
                     + (f"{sweep.designs['test-pose', m].bound.value * 1e3:>10.4f}" if bounded else ""))
    if bounded:
        lines.append("bound: no plan of m experiments has a smaller max error (certified lower bound)")
    if any(sweep.warm_start_won(c, m) for c, m in sweep.designs):
        lines.append("* the warm start (previous m's plan plus new poses) beat the seeded starts: "
                     "better than `solve` with the same seed")
    return "\n".join(lines)


# --------------------------------------------------------------------------- files

#: Name of the file that keeps the finished designs of an unfinished sweep.
PARTIAL_NAME = "sweep.partial.json"


def problem_digest(problem: Problem) -> str:
    """SHA-256 of the problem's checked data: a resumed sweep must be of the same problem."""
    return hashlib.sha256(spec_digest_blob(problem.spec)).hexdigest()


def sweep_key(problem: Problem, criteria: Iterable[str], m_values: Iterable[int], starts: int,
              warm_start: bool, bound: tuple[int, int] = (0, 0)) -> dict:
    """What a sweep's designs depend on (``bound``: exchange steps and pool of the approximate
    designs); a resume must match it."""
    return {"problem_sha256": problem_digest(problem), "seed": problem.solver.seed,
            "starts": starts, "warm_start": warm_start, "m": sorted(set(m_values)),
            "criteria": list(criteria), "bound_steps_pool": list(bound)}


def partial_record(path: Path, problem: Problem, key: dict, designs: list[Design]) -> None:
    """Save the finished designs of a sweep, atomically (called after each design)."""
    from .results import design_record, write_json

    write_json(Path(path), {"format": "casadi-design sweep partial", "problem": problem.name,
                            "key": key, "designs": [design_record(d) for d in designs]})


def load_partial(out: Path, key: dict) -> dict[tuple[str, int], Design]:
    """Finished designs of a sweep in ``out``: from ``sweep.partial.json``, else ``sweep.json``.

    Raises OutputError when the saved sweep was made with another problem or options.
    """
    from .results import OutputError, design_from_record

    for name, where in ((PARTIAL_NAME, "key"), ("sweep.json", "sweep")):
        path = Path(out) / name
        if not path.is_file():
            continue
        damaged = OutputError(f"{path}: not a sweep saved by casadi-design, or damaged; use --force "
                              "to start over")
        try:
            record = json.loads(path.read_bytes().decode("utf-8"))
            saved = record[where] if where == "key" else record["sweep"]["key"]
            diff = [k for k in key if saved.get(k) != key[k]]
        except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, AttributeError):
            raise damaged from None
        if diff:
            k = diff[0]
            what = "the problem file changed" if k == "problem_sha256" else (
                f"{k} was {saved.get(k)}, now {key[k]}")
            raise OutputError(f"{path}: saved with other settings ({what}); resume with the same "
                              "problem and options, or use --force to start over")
        try:
            return {(d["criterion"], d["m"]): design_from_record(d) for d in record["designs"]}
        except (KeyError, TypeError, ValueError, AttributeError):
            raise damaged from None
    return {}


def sweep_record(problem: Problem, sweep: Sweep, key: dict,
                 approx: dict[str, ApproximateDesign] | None = None) -> dict:
    """``sweep.json``: the results record of every design (and the approximate designs of
    the bounds) plus the sweep's table and settings (``key``: :func:`sweep_key`)."""
    from .results import design_record, results_dict

    record = results_dict(problem, list(sweep.designs.values()), approx)
    record["sweep"] = {
        "key": key,
        "m": list(sweep.m_values),
        "criteria": list(sweep.criteria),
        "seeded_starts": sweep.seeded_starts,
        "warm_start": sweep.warm_start,
        "units": {"max_error_mm": "mm", "repeat_best_single_pose_mm": "mm",
                  "bound": "mm for test-pose (lower bound of max_error_mm); log det M for D, "
                           "trace M^-1 for A (upper and lower bounds)",
                  "seeded_best_max_error_mm": "mm", "wall_s": "s",
                  "other measures": "SI units of B (lengths in m)"},
        "columns": list(COLUMNS),
        "rows": sweep_rows(sweep),
        "reference": None if sweep.reference is None else design_record(sweep.reference),
    }
    return record


def sweep_from_record(record: dict) -> Sweep:
    """The :class:`Sweep` of a ``sweep.json`` record (for redrawing its figures)."""
    from .results import design_from_record

    saved = record["sweep"]
    designs = {(d["criterion"], d["m"]): design_from_record(d) for d in record["designs"]}
    reference = None if saved["reference"] is None else design_from_record(saved["reference"])
    return Sweep(tuple(saved["m"]), tuple(saved["criteria"]), designs, saved["seeded_starts"], saved["warm_start"],
                 reference)
