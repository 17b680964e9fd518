"""Text tables for people: Table 4, the solve lines, the sweep table, the measures of a plan.

Errors in mm (the paper's unit), every other measure in the SI units of B; rows and columns
of the measures come from the criteria registry (:data:`casadi_design.measures.criteria.CRITERIA`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from ..measures.criteria import CRITERIA
from ..plan.design import SEEDED, Bound, Design
from ..measures.measures import Scores
from ..execution.sweep import Sweep

#: The bound row's note under a table.
BOUND_NOTE = "bound: no plan of m experiments has a smaller max error (certified lower bound)"


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
        lines.append(BOUND_NOTE)
    return "\n".join(lines)


def format_solver_lines(designs: list[Design]) -> str:
    """One line per design: wall time, IPOPT iterations (or a pool's exchange passes and swaps),
    converged starts, optimum spread."""
    out = []
    for d in designs:
        spread = d.optimum_spread()
        exchanged, passes, swaps = d.exchange
        work = ([f"{d.iterations:6d} IPOPT iterations"] if exchanged < len(d.starts) else []) + (
            [f"{exchanged} exchange{'s' if exchanged > 1 else ''} over the pool: {passes} passes, {swaps} swaps"]
            if exchanged else [])
        out.append(
            f"{d.criterion:<10} m = {d.m:<3} {d.wall_s:7.3f} s  {'; '.join(work)}  "
            f"{d.converged_starts}/{len(d.starts)} starts converged  "
            f"{spread['starts_at_optimum']} at the optimum, their error "
            f"{spread['min_max_rms_error_m'] * 1e3:.4f}..{spread['max_max_rms_error_m'] * 1e3:.4f} mm"
            + ("" if d.bound is None else f"  {d.gap_percent:.1f} % from the bound")
            + ("" if d.winner is None or d.winner.origin == SEEDED else f"  (won by the {d.winner.origin})")
            + (f"  ({d.kept_starts} of {len(d.starts)} starts read back from the cache)" if d.kept_starts else "")
        )
    return "\n".join(out)


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
        lines.append(BOUND_NOTE)
    if any(sweep.warm_start_won(c, m) for c, m in sweep.designs):
        lines.append("* the warm start (previous m's plan plus new poses) beat the seeded starts: "
                     "better than `solve` with the same seed")
    return "\n".join(lines)


def _observability(k: str) -> Callable[[Scores], float]:
    return lambda sc: sc.observability.get(k, math.nan)


#: Rows of the measure table of a plan: label, Scores -> value (table units), format. One row
#: per criterion (registry order), then the mean error and the observability indices.
MEASURE_ROWS: tuple[tuple[str, Callable[[Scores], float], str], ...] = (
    *((c.row, lambda sc, c=c: sc.value(c.name) * c.per_mm, c.fmt) for c in CRITERIA.values()),
    ("mean over test poses of sqrt(rho), mm", lambda sc: float(sc.rms_error_m.mean()) * 1e3, ".4f"),
    *((k, _observability(k), ".6g") for k in ("O1", "O2", "O3", "O4", "O5")),
)


def format_measures(names: list[str], scores: list[Scores]) -> str:
    """Every measure (:data:`MEASURE_ROWS`) of each plan: one column per plan of ``names``."""
    width = max(len(r[0]) for r in MEASURE_ROWS) + 2
    lines = [f"{'measure (SI units of B unless stated)':<{width}}" + "".join(f"{n:>16}" for n in names),
             "-" * (width + 16 * len(names))]
    for label, get, fmt in MEASURE_ROWS:
        lines.append(f"{label:<{width}}" + "".join(f"{get(sc):>16{fmt}}" for sc in scores))
    return "\n".join(lines)


def format_bounds(test_pose: list[Bound], D: list[Bound]) -> str:
    """The ``bound`` command's table: per m the certified lower bound of the test-pose error
    (mm), its relaxation's value (mm) and the upper bound of log det M."""
    lines = [f"{'m':>4}{'test-pose error >= (mm)':>26}{'relaxation (mm)':>18}{'log det M <=':>15}"]
    for tp, d in zip(test_pose, D):
        lines.append(f"{tp.m:>4}{tp.value * 1e3:>26.5f}{tp.relaxation * 1e3:>18.5f}{d.value:>15.4f}")
    return "\n".join(lines)
