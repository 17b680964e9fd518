"""Multi-start IPOPT solution of the design NLP: the only module that runs a solver.

Each design (criterion, m) is solved from ``starts`` random feasible plans drawn from a
generator seeded by ``(seed, m, criterion)``, so a design is reproducible on its own (a sweep
runs the same seeded starts as a single solve; its extra warm start can only improve on them).
Every start is recorded; the best converged,
feasible start wins, judged by the criterion's own numeric score. A start that IPOPT does not
solve is a status, not an exception.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np
from threadpoolctl import ThreadpoolController

from . import interrupt
from .build import Problem
from .criteria import CRITERIA
from .errors import DesignError, ProblemError
from .measures import Scores, score_plan
from .nlp import B0_at_test_poses, DesignNLP, build_nlp
from .rules import joint_limits, plan_violations, pose_constraints

if TYPE_CHECKING:
    from .bound import Bound
    from .parallel import StartExecutor

#: IPOPT return statuses accepted as converged.
CONVERGED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: For criteria marked ``polished``: the threshold on lambda_min / lambda_max of M below which
#: a start first gets a few D-optimal iterations, and their number.
POLISH_RCOND = 1e-6
POLISH_ITERATIONS = 30
#: Random configurations tried per experiment to satisfy the workspace constraints, drawn one
#: first, then in batches of ``SAMPLING_BATCH`` doubling up to ``SAMPLING_BATCH_MAX``.
SAMPLING_TRIES = 20000
SAMPLING_BATCH = 16
SAMPLING_BATCH_MAX = 1024


#: ``StartRecord.origin`` of the seeded random starts.
SEEDED = "seeded"


@dataclass(frozen=True)
class StartRecord:
    """One IPOPT start: its status, iterations, criterion score and test-pose error (m), and
    where its start plan came from (``origin``: "seeded", or the label of an initial plan, e.g.
    "warm start" or "rounded approximate design")."""

    status: str
    iterations: int
    value: float
    max_rms_error_m: float
    feasible: bool
    origin: str = SEEDED

    @property
    def converged(self) -> bool:
        return self.status in CONVERGED and self.feasible


@dataclass(frozen=True, eq=False)
class Design:
    """The best plan found for one criterion and number of experiments.

    Attributes
    ----------
    Q : ndarray, shape (m, n), rad
    F : ndarray, shape (m, nF), N (N m)
    scores : every measure of the plan.
    status : IPOPT status of the winning start.
    starts : every start, in the order run.
    wall_s : wall time of the multi-start solve, s.
    bound : the certified bound of the criterion for m experiments
        (:func:`casadi_design.bound.bound`), when it was computed.
    """

    criterion: str
    m: int
    Q: np.ndarray
    F: np.ndarray
    scores: Scores
    status: str
    starts: tuple[StartRecord, ...]
    wall_s: float
    seed: int
    bound: Bound | None = None

    @property
    def gap_percent(self) -> float | None:
        """How far the plan is from its bound, % (:func:`casadi_design.bound.gap_percent`)."""
        from .bound import gap_percent

        return None if self.bound is None else gap_percent(self.bound, self.scores.value(self.criterion))

    @property
    def converged_starts(self) -> int:
        return sum(st.converged for st in self.starts)

    @property
    def iterations(self) -> int:
        return sum(st.iterations for st in self.starts)

    @property
    def winner(self) -> StartRecord | None:
        """The start whose plan this is: the first to reach the best value (a later start wins
        only when strictly better); None for a design read without its starts' values."""
        best = self.scores.value(self.criterion)
        return next((st for st in self.starts if st.converged and st.value == best), None)


def start_rng(seed: int, criterion: str, m: int) -> np.random.Generator:
    """The generator of a design's starts: depends on ``seed``, ``criterion`` and ``m`` only."""
    return np.random.default_rng([seed, m, CRITERIA[criterion].seed_id])


def random_plan(problem: Problem, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random feasible plan: ``Q`` (n x m, rad) within the limits and workspace, ``F`` (nF x m, N)."""
    robot, model, force = problem.robot, problem.model, problem.force
    rules, limits = pose_constraints(problem), joint_limits(problem)
    Q = np.empty((robot.n, m))
    for i in range(m):
        # one configuration, then growing batches (one CasADi call each) until one is feasible
        tried, batch, q = 0, 1, None
        while q is None and tried < SAMPLING_TRIES:
            size = min(batch, SAMPLING_TRIES - tried)
            candidates = limits.sample(rng, size)
            ok = np.flatnonzero(rules.feasible(candidates))
            q = candidates[ok[0]] if ok.size else None
            tried, batch = tried + size, SAMPLING_BATCH if batch == 1 else min(2 * batch, SAMPLING_BATCH_MAX)
        if q is None:
            broken = np.sum([rules.violation(c) > 0 for c in candidates], axis=0)
            worst = [rules.labels[k] for k in np.argsort(-broken)[:3] if broken[k]]
            where = "[experiments.workspace] and [cell] leave" if problem.cell else "[experiments.workspace] leaves"
            raise DesignError(
                f"{problem.path}: {where} no feasible pose: none of {SAMPLING_TRIES} random "
                f"configurations within the joint limits satisfies them (most often broken: "
                f"{'; '.join(worst)}); enlarge the workspace, move the obstacles or the tracker, or "
                "widen the joint limits"
            )
        Q[:, i] = q
    if model.nF == 0:
        return Q, np.zeros((0, m))
    if force.mode == "fixed":
        return Q, np.tile(np.array(force.vector_N)[:, None], (1, m))
    if force.mode == "direction":
        return Q, force.magnitude_N * np.outer(force.direction, rng.uniform(0.5, 1.0, m))
    d = rng.normal(size=(model.nF, m))
    return Q, force.magnitude_N * d / np.linalg.norm(d, axis=0)


def plan_scores(problem: Problem, Q: np.ndarray, F: np.ndarray, B0: np.ndarray) -> Scores:
    """Scores of a plan given as ``Q`` (n x m, rad) and ``F`` (nF x m, N)."""
    return score_plan(problem.model.B_stack(Q.T, F.T), B0, problem.sigma_m)


#: nlpsol options of a silent IPOPT whose failures are statuses, not exceptions.
QUIET = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "error_on_fail": False,
         "show_eval_warnings": False}


#: nlpsol options of a run that continues from the primal and dual point of the previous one.
WARM_START = {"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-6}


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
    if status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level", "Maximum_Iterations_Exceeded"):
        raise ProblemError(f"{problem.path}: [solver].ipopt: IPOPT rejected the options {dict(options)} "
                           f"({status}); check the names and values against the IPOPT options reference")


@functools.cache
def _blas() -> ThreadpoolController:
    """The BLAS libraries loaded in this process (found once: a search costs ~2 ms)."""
    return ThreadpoolController()


@contextlib.contextmanager
def ipopt_call() -> Iterator[None]:
    """Run an IPOPT solve: Ctrl-C stops it (:func:`casadi_design.interrupt.solver_call`), and BLAS
    runs on one thread. The reduced-space derivatives multiply small matrices (L x L): BLAS
    threads cost more than they give there (10x slower on a busy 2-core machine), and the
    rounding, hence a start's outcome, would depend on the thread count (and so on ``--jobs``)."""
    with interrupt.solver_call(), _blas().limit(limits=1, user_api="blas"):
        yield


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
    """One IPOPT start of the design solver from ``Q0`` (n x m, rad), ``F0`` (nF x m, N).

    The unit of work of the multi-start, run here or in worker processes
    (:mod:`casadi_design.parallel`). Returns the start's record, its plan ``Q`` (n x m, rad),
    ``F`` (nF x m, N) and the plan's scores.
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
    initial_plans : extra starts ``(Q0, F0)`` or ``(Q0, F0, origin)``: ``Q0`` shape (n, m), rad;
        ``F0`` shape (nF, m), N; ``origin`` labels the start's record ("initial plan" if not
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
        F0 = F0.reshape(0, m) if F0.size == 0 and problem.model.nF == 0 else F0
        if Q0.shape != (problem.robot.n, m) or F0.shape != (problem.model.nF, m):
            raise ValueError(
                f"solve_design: initial plan {k} has Q of shape {Q0.shape} and F of shape "
                f"{F0.shape}; expected ({problem.robot.n}, {m}) and ({problem.model.nF}, {m})"
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
        raise DesignError(
            f"{problem.path}: criterion {criterion}, m = {m}: none of {len(records)} starts converged "
            f"to a feasible plan (IPOPT: {', '.join(f'{k} x {v}' for k, v in counts.items())}); "
            "raise [solver].starts or max_iter, or relax the constraints"
        )
    rec, Q, F, scores = best
    return Design(criterion, m, Q.T.copy(), F.T.copy(), scores, rec.status, tuple(records),
                  time.perf_counter() - t0, problem.solver.seed)
