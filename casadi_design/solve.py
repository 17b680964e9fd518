"""Multi-start IPOPT solution of the design NLP.

Each design (criterion, m) is solved from ``starts`` random feasible plans drawn from a
generator seeded by ``(seed, m, criterion)``, so a design is reproducible on its own (a sweep
runs the same seeded starts as a single solve; its extra warm start can only improve on them).
Every start is recorded; the best converged,
feasible start wins, judged by the criterion's own numeric score. A start that IPOPT does not
solve is a status, not an exception.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

import casadi as ca
import numpy as np

from .build import Problem
from .cell import clearances
from .criteria import CRITERIA
from .design import CONVERGED, SEEDED, Design, StartRecord
from .errors import DesignError, ProblemError
from .ipopt import QUIET, WARM_START, ipopt_call
from .measures import Scores, score_plan
from .nlp import B0_at_test_poses, DesignNLP, build_nlp
from .rules import joint_limits, plan_violations
from .sampling import random_plan

#: IPOPT statuses of a run stopped by one of its limits: the options were taken.
LIMITS = ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded", "Maximum_WallTime_Exceeded")
#: For criteria marked ``polished``: the threshold on lambda_min / lambda_max of M below which
#: a start first gets a few D-optimal iterations, and their number.
POLISH_RCOND = 1e-6
POLISH_ITERATIONS = 30

#: A start plan ``(Q0 (m, n), F0 (m, nF))`` and what a start gives back.
StartPlan = tuple[np.ndarray, np.ndarray]
StartResult = tuple[StartRecord, np.ndarray, np.ndarray, Scores]


class StartExecutor(Protocol):
    """Runs the starts of one design and yields their results in the order of ``plans``
    (:mod:`casadi_design.parallel`)."""

    def map_starts(self, problem: Problem, criterion: str, m: int, B0: np.ndarray,
                   plans: Sequence[StartPlan], verbose: bool) -> Iterator[StartResult]: ...

    def map_approximate(self, problem: Problem, criteria: Sequence[str], steps: int,
                        pool: int) -> Iterator: ...


def start_rng(seed: int, criterion: str, m: int) -> np.random.Generator:
    """The generator of a design's starts: depends on ``seed``, ``criterion`` and ``m`` only."""
    return np.random.default_rng([seed, m, CRITERIA[criterion].seed_id])


def plan_scores(problem: Problem, Q: np.ndarray, F: np.ndarray, B0: np.ndarray) -> Scores:
    """Scores of a plan given as ``Q`` (m, n), rad, and ``F`` (m, nF), N."""
    return score_plan(problem.model.B_stack(Q, F), B0, problem.sigma_m)


def make_solver(problem: Problem, nlp: DesignNLP, verbose: bool = False,
                warm: bool = False) -> ca.Function:
    """IPOPT on the NLP, with the problem's solver settings (raw options passed through);
    ``warm``: it starts from the multipliers it is given (:data:`WARM_START`)."""
    settings = problem.solver
    opts = {**QUIET, "ipopt.max_iter": settings.max_iter, "ipopt.tol": settings.tol,
            **(WARM_START if warm else {})}
    if verbose:
        opts.update({"ipopt.print_level": 5, "print_time": True, "show_eval_warnings": True})
    opts.update({f"ipopt.{k}": v for k, v in settings.ipopt})
    return nlp.solver(f"design_m{nlp.m}", opts)


def check_ipopt_options(problem: Problem) -> None:
    """Try the [solver.ipopt] options on a one-variable NLP, so a bad option fails before solving."""
    options = problem.solver.ipopt
    if not options:
        return
    x = ca.SX.sym("x")
    opts = {**QUIET, **{f"ipopt.{k}": v for k, v in options}}
    try:
        solver = ca.nlpsol("check", "ipopt", {"x": x, "f": x**2}, opts)
        solver(x0=1.0)
        status = solver.stats()["return_status"]
    except RuntimeError as exc:
        status = str(exc).strip().splitlines()[-1].split(": ", 1)[-1]
    if status not in (*CONVERGED, *LIMITS):
        raise ProblemError(f"{problem.path}: [solver].ipopt: IPOPT rejected the options {dict(options)} "
                           f"({status}); check the names and values against the IPOPT options reference")


@dataclass(frozen=True, eq=False)
class DesignSolver:
    """The NLP of one (criterion, m) with its IPOPT solver: one stage, or for E and condition
    one per power r of their surrogate (each run starts where the last stopped), after a short
    D-optimality run that first moves nearly singular starts away from M = 0."""

    stages: tuple[tuple[DesignNLP, ca.Function], ...]
    polish: tuple[DesignNLP, ca.Function] | None


def make_design_solver(problem: Problem, criterion: str, m: int, B0: np.ndarray,
                       verbose: bool = False) -> DesignSolver:
    crit = CRITERIA[criterion]
    stages = []
    for k, power in enumerate(crit.powers or (0.0,)):
        nlp = build_nlp(problem, criterion, m, B0, power)
        stages.append((nlp, make_solver(problem, nlp, verbose, warm=k > 0)))
    polish = None
    if crit.polished:
        d_nlp = build_nlp(problem, "D", m, B0)
        d_solver = d_nlp.solver("polish", {**QUIET, "ipopt.max_iter": POLISH_ITERATIONS})
        polish = (d_nlp, d_solver)
    return DesignSolver(tuple(stages), polish)


def _polished(problem: Problem, ds: DesignSolver, Q0: np.ndarray, F0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Q0, F0)``, or a few D iterations from it when its M is nearly singular: at a singular
    M the PSD-factor form of E / condition has a stationary point with lam = 0."""
    if ds.polish is None:
        return Q0, F0
    d_nlp, d_solver = ds.polish
    x0 = d_nlp.start(Q0, F0)
    lam = np.linalg.eigvalsh(np.asarray(d_nlp.information(x0)))
    if lam[0] > POLISH_RCOND * lam[-1]:
        return Q0, F0
    with ipopt_call():
        sol = d_solver(x0=x0, lbx=d_nlp.lbx, ubx=d_nlp.ubx, lbg=d_nlp.lbg, ubg=d_nlp.ubg)
    Q, F = (np.asarray(v, dtype=float) for v in d_nlp.plan(sol["x"]))
    return joint_limits(problem).wrap(Q), F


def solve_start(
    problem: Problem, ds: DesignSolver, B0: np.ndarray, Q0: np.ndarray, F0: np.ndarray
) -> tuple[StartRecord, np.ndarray, np.ndarray, Scores]:
    """One IPOPT start of the design solver from ``Q0`` (m, n), rad, ``F0`` (m, nF), N.

    The unit of work of the multi-start, run here or in worker processes
    (:mod:`casadi_design.parallel`). Returns the start's record, its plan ``Q`` (m, n), rad,
    ``F`` (m, nF), N, and the plan's scores.
    """
    Q0, F0 = _polished(problem, ds, Q0, F0)
    x, iterations, duals = ds.stages[0][0].start(Q0, F0), 0, {}
    for nlp, solver in ds.stages:
        with ipopt_call():  # IPOPT reports Ctrl-C as a failed start: stop instead
            sol = solver(x0=x, lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg, **duals)
        x, duals = sol["x"], {"lam_x0": sol["lam_x"], "lam_g0": sol["lam_g"]}
        stats = solver.stats()
        iterations += int(stats.get("iter_count", 0))
    Q, F = (np.asarray(v, dtype=float) for v in nlp.plan(x))
    Q = joint_limits(problem).wrap(Q)
    scores = plan_scores(problem, Q, F, B0)
    rec = StartRecord(
        status=str(stats["return_status"]),
        iterations=iterations,
        value=scores.value(nlp.criterion),
        max_rms_error_m=scores.max_rms_error_m,
        feasible=not plan_violations(problem, Q, F) and scores.identifiable,
    )
    return rec, Q, F, scores


def solve_design(
    problem: Problem,
    criterion: str,
    m: int,
    B0: np.ndarray | None = None,
    starts: int | None = None,
    verbose: bool = False,
    *,
    initial_plans: Sequence[tuple] = (),
    executor: StartExecutor | None = None,
    progress: Callable[[int], object] | None = None,
) -> Design:
    """Best plan of ``m`` experiments for ``criterion`` over the multi-start.

    The ``starts`` seeded random plans are drawn first (from :func:`start_rng`, so they do not
    depend on ``initial_plans`` or ``executor``); the ``initial_plans`` run after them as
    additional starts. Starts are judged in that order and a later start wins only when it is
    strictly better, so extra starts can only improve the seeded result.

    Parameters
    ----------
    initial_plans : extra starts ``(Q0, F0)`` or ``(Q0, F0, origin)``: ``Q0`` shape (m, n), rad;
        ``F0`` shape (m, nF), N; ``origin labels the start's record ("initial plan" if not
        given).
    executor : runs the starts elsewhere (:mod:`casadi_design.parallel`); None runs them here,
        one after the other. The result is the same either way.
    progress : called with 1 after each start (e.g. ``tqdm.update``).

    Raises
    ------
    DesignError
        When no start converges to a feasible plan (the message lists the IPOPT statuses).
    """
    B0 = B0_at_test_poses(problem) if B0 is None else B0
    t0 = time.perf_counter()
    rng = start_rng(problem.solver.seed, criterion, m)
    plans = [random_plan(problem, m, rng) for _ in range(starts or problem.solver.starts)]
    origins = [SEEDED] * len(plans)
    for k, (Q0, F0, *origin) in enumerate(initial_plans):
        origins.append(origin[0] if origin else "initial plan")
        Q0, F0 = np.asarray(Q0, dtype=float), np.asarray(F0, dtype=float)
        F0 = F0.reshape(m, 0) if F0.size == 0 and problem.model.nF == 0 else F0
        if Q0.shape != (m, problem.robot.n) or F0.shape != (m, problem.model.nF):
            raise ValueError(
                f"solve_design: initial plan {k} has Q of shape {Q0.shape} and F of shape "
                f"{F0.shape}; expected ({m}, {problem.robot.n}) and ({m}, {problem.model.nF})"
            )
        plans.append((Q0, F0))
    if executor is None:
        ds = make_design_solver(problem, criterion, m, B0, verbose)
        results = (solve_start(problem, ds, B0, Q0, F0) for Q0, F0 in plans)
    else:
        results = executor.map_starts(problem, criterion, m, B0, plans, verbose)
    crit = CRITERIA[criterion]
    records, best, why = [], None, []
    for (rec, Q, F, scores), origin in zip(results, origins):
        if progress is not None:
            progress(1)
        rec = dataclasses.replace(rec, origin=origin)
        records.append(rec)
        why.append("" if rec.feasible else " (singular M: the plan does not identify every parameter)"
                   if not scores.identifiable else " (the plan breaks a rule of the problem)")
        if rec.converged and (best is None or crit.better(rec.value, best[0].value)):
            best = (rec, Q, F, scores)
    if best is None:
        counts: dict[str, int] = {}
        for r, reason in zip(records, why):
            counts[r.status + reason] = counts.get(r.status + reason, 0) + 1
        timed_out = any("Time_Exceeded" in r.status for r in records)
        raise DesignError(
            f"{problem.path}: criterion {criterion}, m = {m}: none of {len(records)} starts converged "
            f"to a feasible plan (IPOPT: {', '.join(f'{k} x {v}' for k, v in counts.items())}); "
            + ("raise [solver.ipopt] max_cpu_time / max_wall_time (or --ipopt max_cpu_time=...), "
               "or remove them" if timed_out else
               "raise [solver].starts or max_iter, or relax the constraints")
        )
    rec, Q, F, scores = best
    return Design(criterion, m, Q, F, scores, rec.status, tuple(records),
                  time.perf_counter() - t0, problem.solver.seed,
                  clearances=tuple(clearances(problem.cell, Q)) if problem.cell else None)
