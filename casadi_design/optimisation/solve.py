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
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import casadi as ca
import numpy as np

from ..cell.cell import clearances
from ..errors import DesignError, ProblemError
from ..measures.criteria import CRITERIA
from ..measures.field import kriging_rho
from ..measures.measures import Scores, score_plan
from ..plan.design import CONVERGED, SEEDED, Design, StartRecord
from ..plan.rules import ADD_MARGIN_M, FEASIBILITY_TOL, START_MARGIN_M, plan_violations
from ..plan.sampling import random_plan
from ..problem.build import Problem
from ..problem.rules import PoseConstraints
from ..runtime.cache import Memo, digest, keeping_designs
from .ipopt import QUIET, WARM_START, ipopt_call
from .nlp import DesignNLP, build_nlp

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
    (:mod:`casadi_design.execution.parallel`)."""

    def map_starts(self, problem: Problem, criterion: str, m: int,
                   plans: Sequence[StartPlan], verbose: bool) -> Iterator[StartResult]: ...

    def map_approximate(self, problem: Problem, wanted: Sequence[tuple[str, int]], steps: int,
                        pool: int) -> Iterator: ...


def start_rng(seed: int, criterion: str, m: int) -> np.random.Generator:
    """The generator of a design's starts: depends on ``seed``, ``criterion`` and ``m`` only."""
    return np.random.default_rng([seed, m, CRITERIA[criterion].seed_id])


def plan_scores(problem: Problem, Q: np.ndarray, F: np.ndarray, B: np.ndarray | None = None,
                field: bool = True, B0: np.ndarray | None = None) -> Scores:
    """Scores of a plan given as ``Q`` (m, n), rad, and ``F`` (m, nF), N (``B`` its rows when
    they are at hand; ``B0`` the test poses' rows when not the problem's: an artefact's rows with
    the placements' poses beside X, :func:`~casadi_design.calibration.artefact.artefact_rows`).
    With the problem's field of unmodelled error (:attr:`Problem.field`) ``rho`` at the test
    poses is the kriging variance of the whole campaign (the poses held before it, then the
    plan's; :func:`~casadi_design.measures.field.kriging_rho`); not ``field``: the paper's, for a
    search by a criterion that does not weigh rho."""
    B = problem.model.B_stack(Q, F) if B is None else B
    return score_plan(B, problem.B0 if B0 is None else B0, problem.sigma_m, problem.M_held, problem.m_held,
                      rho=None if problem.field is None or not field else field_rho(problem, Q, F, B))


def field_rho(problem: Problem, Q: np.ndarray, F: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``rho`` (s,), m^2, at the test poses of the campaign of the held poses and the plan
    ``Q``, ``F`` (rows ``B``) with the problem's field (:attr:`Problem.field`)."""
    B, S = problem.field_campaign(B, problem.field_sites(Q, F))
    return kriging_rho(problem.field, problem.sigma_m, B, S, problem.B0, problem.field_test_sites, problem.field_prior)


def make_solver(problem: Problem, nlp: DesignNLP, verbose: bool = False, how: str = "cold",
                max_iter: int | None = None, watch: bool = False) -> ca.Function:
    """IPOPT on the NLP, with the problem's solver settings (raw options passed through).

    ``how``: "cold" (IPOPT's own start), "warm" (from the primal and dual point it is given,
    :data:`WARM_START`) or "resumed" (the same with the barrier parameter ``RESUME_MU``: a
    run stopped on its way); ``max_iter``: instead of the problem's; ``watch``: it stops at an
    iterate that breaks a capsule row the NLP does not hold (:class:`_Watch`); in a cell every
    run stops when it stalls (:data:`STALL_ITERATIONS`)."""
    settings = problem.solver
    opts = {**QUIET, "ipopt.max_iter": settings.max_iter if max_iter is None else max_iter,
            "ipopt.tol": settings.tol}
    if how != "cold":
        opts.update(WARM_START)
    if how == "resumed":
        opts["ipopt.mu_init"] = RESUME_MU
    if verbose:
        opts.update({"ipopt.print_level": 5, "print_time": True, "show_eval_warnings": True})
    opts.update({f"ipopt.{k}": v for k, v in settings.ipopt})
    if watch or problem.rules.pose.collision is not None:
        opts["iteration_callback"] = _Watch(problem, nlp, rows=watch)
    solver = nlp.solver(f"design_m{nlp.m}", opts)
    solver.watch = opts.get("iteration_callback")  # alive as long as the solver
    return solver


#: IPOPT's status of a run that :class:`_Watch` stopped at a row it does not hold, and the
#: status a start records for a run it stopped as stalled.
STOPPED = "User_Requested_Stop"
STALLED = "Stalled"
#: A run in a cell stalls when for ``STALL_ITERATIONS`` iterations no iterate makes progress:
#: a plan that keeps every row the NLP holds with an objective lower by ``STALL_RTOL``
#: (relative) than every such plan before it, or, while none has kept them, a largest row
#: violation lower by ``STALL_RTOL`` than every earlier one. A stalled run ends its start
#: (status :data:`STALLED`, not converged). IPOPT can cycle at a fixed barrier parameter (the
#: UR10 test-pose design at m = 12: four iterates repeating for 2700 iterations) or stay in
#: its restoration phase (at m = 9: 1900 and 2400 iterations), up to the start's max_iter.
#: Chosen by measurement on both studies (README, Speed): the winning starts of their 20
#: designs run at most 269 iterations without progress (the ABB's test-pose design at m = 6),
#: the starts left at max_iter 2130 to 2933; some converged starts that lose 1043 to 1259.
STALL_ITERATIONS = 500
STALL_RTOL = 1e-6


class _Watch(ca.Callback):
    """IPOPT's iteration callback of a run in a cell. It stops the run at an iterate that
    makes no progress in :data:`STALL_ITERATIONS` (``stalled`` is then True), and, with
    ``rows``, at the first iterate whose plan breaks a capsule row the NLP does not hold
    (status :data:`STOPPED`), so that the rows that can bind there join before the iterates
    go farther."""

    def __init__(self, problem: Problem, nlp: DesignNLP, rows: bool = True):
        ca.Callback.__init__(self)
        self._rules, self._plan, self._active = problem.rules.pose, nlp.plan, nlp.active
        self._rows, self._lbg, self._ubg = rows, nlp.lbg, nlp.ubg
        self._sizes = {"x": nlp.lbx.size, "g": nlp.lbg.size, "f": 1, "lam_x": nlp.lbx.size,
                       "lam_g": nlp.lbg.size}
        self.iteration, self.last_progress, self.stalled = 0, 0, False
        self.best_f, self.best_h = np.inf, np.inf
        self.construct("watch", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self._sizes.get(ca.nlpsol_out(i), 0), 1)

    def _progress(self, f: float, g: np.ndarray) -> bool:
        """Whether the iterate of objective ``f`` and rows ``g`` makes progress (see
        :data:`STALL_ITERATIONS`)."""
        h = float(np.max(np.maximum(self._lbg - g, g - self._ubg), initial=0.0))
        if h <= FEASIBILITY_TOL:
            better = f < self.best_f - STALL_RTOL * abs(self.best_f)
            self.best_f, self.best_h = min(self.best_f, f), 0.0
            return better
        better = h < self.best_h * (1 - STALL_RTOL)
        self.best_h = min(self.best_h, h)
        return better

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg, res) -> int:
        # CasADi's buffers of x, f and g as views, valid during the call, instead of ``eval``'s
        # DM arguments: no conversion per iteration (about a tenth of IPOPT's CheckConvergence
        # time on the UR10 test-pose design at m = 12; the callback's call itself costs about
        # 0.45 ms an iteration inside CasADi either way)
        x, f, g = (np.frombuffer(a, dtype=float) if a is not None else np.zeros(0) for a in arg[:3])
        np.frombuffer(res[0], dtype=float)[0] = self._stop(x, float(f[0]), g)
        return 0

    def _stop(self, x: np.ndarray, f: float, g: np.ndarray) -> int:
        """1 to stop the run at the iterate x (objective f, rows g): stalled, or (``rows``) a
        capsule row it does not hold broken."""
        self.iteration += 1
        if self._progress(f, g):
            self.last_progress = self.iteration
        if self.iteration - self.last_progress >= STALL_ITERATIONS:
            self.stalled = True
            return 1
        if not self._rows:
            return 0
        slack = self._rules.capsule_slack(self._plan(x)[0])
        return int(_left_out_broken(slack, self._active, WATCH_DEPTH_M))


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
    """The NLPs of one (criterion, m) and their IPOPT solvers: one stage, or for E and
    condition one per power r of their surrogate (each run starts where the last stopped),
    after a short D-optimality run (``polish``) that first moves nearly singular starts away
    from M = 0. With a cell, each NLP holds the capsule rows that can bind (:func:`solve_start`),
    so they are built per run; without one, one per stage is made and kept (``made``) for
    every start."""

    problem: Problem
    criterion: str
    m: int
    verbose: bool = False
    made: dict = field(default_factory=dict, repr=False)

    def _kept(self, key: tuple, make: Callable[[], tuple]) -> tuple:
        """Without capsule rows a stage's NLP and solver are the same for every start: made
        once. With them each run holds its own rows and iteration budget: made for it."""
        if self.problem.rules.pose.collision is not None:
            return make()
        if key not in self.made:
            self.made[key] = make()
        return self.made[key]

    @property
    def powers(self) -> tuple[float, ...]:
        return CRITERIA[self.criterion].powers or (0.0,)

    def stage(self, k: int, active: np.ndarray, how: str, max_iter: int,
              watch: bool) -> tuple[DesignNLP, ca.Function]:
        """The NLP of stage k holding the capsule rows ``active`` (K x 2) and its solver
        (options of :func:`make_solver`)."""
        def make():
            nlp = build_nlp(self.problem, self.criterion, self.m, self.powers[k], active,
                            fixed=self.problem.M_held)
            return nlp, make_solver(self.problem, nlp, self.verbose, how, max_iter, watch)

        return self._kept(("stage", k, active.tobytes(), how, max_iter, watch), make)

    def polish(self, active: np.ndarray) -> tuple[DesignNLP, ca.Function]:
        """The D-optimal NLP of the polish run (criteria marked ``polished``) holding the
        capsule rows ``active``, and its solver."""
        def make():
            nlp = build_nlp(self.problem, "D", self.m, active=active, fixed=self.problem.M_held)
            return nlp, nlp.solver("polish", {**QUIET, "ipopt.max_iter": POLISH_ITERATIONS})

        return self._kept(("polish", active.tobytes()), make)


def make_design_solver(problem: Problem, criterion: str, m: int, verbose: bool = False) -> DesignSolver:
    return DesignSolver(problem, criterion, m, verbose)


#: The rows where they can bind. A start holds the capsule rows closer than
#: ``START_MARGIN_M`` (m) to their bound at its start plan. An IPOPT run stops at an iterate
#: that breaks a row it does not hold by more than ``WATCH_DEPTH_M`` (:class:`_Watch`); the
#: rows closer than ``START_MARGIN_M`` there join, and IPOPT goes on from that iterate with
#: the barrier parameter ``RESUME_MU``. At the end of a run every row of the rulebook is
#: checked at its plan: those closer than ``ADD_MARGIN_M`` join and IPOPT runs again from the
#: last primal and dual point (warm start), until every row left out is farther than
#: ``ADD_MARGIN_M`` from its bound; then the plan is a local optimum of the whole rulebook (the
#: rows left out are inactive there). A run that fails runs once more from the start plan with
#: the rows held so far. The runs of a start share the problem's ``max_iter``; the last of
#: ``MAX_ROUNDS`` runs is not stopped, and its plan is checked as any other (a plan breaking a
#: row is not feasible). The margins were chosen by measurement on the UR10 and ABB cells
#: (see the README's speed section; the margins are :data:`casadi_design.plan.rules.START_MARGIN_M`
#: and :data:`~casadi_design.plan.rules.ADD_MARGIN_M`). ``MAX_ROUNDS`` leaves room for many rounds:
#: on the UR10 from m = 12 on, the plan meets new rows round after round; the first three
#: seeded starts at m = 20 end feasible after 15, 15 and 25 runs, and with at most 12 runs
#: most starts of a sweep to m = 20 that use them all end on plans breaking capsule rows by up
#: to 80 mm (at m = 20 every seeded start, so that the design there rests on the warm start
#: alone). The shared ``max_iter`` bounds a start's cost whatever the rounds.
WATCH_DEPTH_M = 0.05
RESUME_MU = 1e-3
MAX_ROUNDS = 40


def _codes(rows: np.ndarray, R: int) -> np.ndarray:
    """(experiment, row) pairs (K x 2) as the integers ``i R + r``."""
    return rows[:, 0] * R + rows[:, 1]


def _left_out_broken(slack: np.ndarray, active: np.ndarray, depth_m: float) -> bool:
    """Whether a capsule row that ``active`` (K x 2, (experiment, row)) does not hold is broken
    by more than ``depth_m`` (m), from the slack (m x R, m) of every row of the plan."""
    R = slack.shape[1]
    return np.setdiff1d(_codes(np.argwhere(slack < -depth_m), R), _codes(active, R)).size > 0


def _carried(old: DesignNLP, new: DesignNLP, lam_g: np.ndarray) -> np.ndarray:
    """The multipliers ``lam_g`` of ``old``'s rows on the rows of ``new``, which holds the
    same rows and more capsule rows (those start at 0)."""
    R = 1 + int(max(old.active[:, 1].max(initial=0), new.active[:, 1].max(initial=0)))
    out = np.zeros(new.lbg.size)
    other_old = np.setdiff1d(np.arange(old.lbg.size), old.active_rows)
    other_new = np.setdiff1d(np.arange(new.lbg.size), new.active_rows)
    out[other_new] = lam_g[other_old]
    where = np.searchsorted(_codes(new.active, R), _codes(old.active, R))
    out[new.active_rows[where]] = lam_g[old.active_rows]
    return out


def _polished(problem: Problem, ds: DesignSolver, Q0: np.ndarray, F0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Q0, F0)``, or a few D iterations from it when its M is nearly singular: at a singular
    M the PSD-factor form of E / condition has a stationary point with lam = 0."""
    if not CRITERIA[ds.criterion].polished:
        return Q0, F0
    d_nlp, d_solver = ds.polish(problem.rules.pose.near(Q0, START_MARGIN_M))
    x0 = d_nlp.start(Q0, F0)
    lam = np.linalg.eigvalsh(np.asarray(d_nlp.information(x0)))
    if lam[0] > POLISH_RCOND * lam[-1]:
        return Q0, F0
    with ipopt_call():
        sol = d_solver(x0=x0, lbx=d_nlp.lbx, ubx=d_nlp.ubx, lbg=d_nlp.lbg, ubg=d_nlp.ubg)
    Q, F = (np.asarray(v, dtype=float) for v in d_nlp.plan(sol["x"]))
    return problem.rules.limits.wrap(Q), F


def solve_start(
    problem: Problem, ds: DesignSolver, Q0: np.ndarray, F0: np.ndarray
) -> tuple[StartRecord, np.ndarray, np.ndarray, Scores]:
    """One IPOPT start of the design solver from ``Q0`` (m, n), rad, ``F0`` (m, nF), N.

    The unit of work of the multi-start, run here or in worker processes
    (:mod:`casadi_design.execution.parallel`). With a cell, each stage runs in rounds holding the
    capsule rows that can bind (see :data:`START_MARGIN_M`). Returns the start's record, its
    plan ``Q`` (m, n), rad, ``F`` (m, nF), N, and the plan's scores.

    A start is a pure function of the problem, the criterion, m and its start plan, so
    it is kept on disk (:mod:`casadi_design.runtime.cache`, ``start-<key>``, named by the problem's
    :attr:`~casadi_design.problem.build.Problem.fingerprint` and those) and a later command reads it
    back to the bit: a sweep after the study, a one-start solve, a run stopped by Ctrl-C and
    started again. Not with ``verbose`` (IPOPT's output is asked for) nor when
    :data:`casadi_design.runtime.cache.KEEP_DESIGNS` is 0.
    """
    if ds.verbose or not keeping_designs():
        return _solved_start(problem, ds, Q0, F0)
    arrays = (np.ascontiguousarray(a, dtype=float) for a in (problem.B0, Q0, F0))
    key = digest(problem.fingerprint.encode(), ds.criterion.encode(), str(ds.m).encode(),
                 *(a.tobytes() + str(a.shape).encode() for a in arrays))
    return STARTS.get(key, lambda: _solved_start(problem, ds, Q0, F0))


class KeptStart(tuple):
    """A start's result read back from the disk (:func:`solve_start`): the same tuple, marked
    so that its design can say how many of its starts were read back."""


#: The starts' results, on disk only (a process does not meet the same start twice).
STARTS: Memo[tuple] = Memo(0, kind="start", on_read=KeptStart)


def _solved_start(
    problem: Problem, ds: DesignSolver, Q0: np.ndarray, F0: np.ndarray
) -> tuple[StartRecord, np.ndarray, np.ndarray, Scores]:
    """:func:`solve_start` computed."""
    Q0, F0 = _polished(problem, ds, Q0, F0)
    rules = problem.rules.pose
    active = rules.near(Q0, START_MARGIN_M)
    x, duals, last, iterations, runs, status = None, {}, None, 0, 0, None
    for k in range(len(ds.powers)):
        if status == STALLED:  # a stalled run ends its start
            break
        how, restarted = ("warm" if k else "cold"), False
        for run in range(MAX_ROUNDS):
            watch = rules.collision is not None and run < MAX_ROUNDS - 1
            # the runs of a start in a cell share max_iter; without a cell each stage has it
            budget = problem.solver.max_iter - (iterations if rules.collision is not None else 0)
            nlp, solver = ds.stage(k, active, how, max(budget, 1), watch)
            if how == "cold":
                duals = {}
            elif last is not None:
                duals["lam_g0"] = _carried(last, nlp, np.asarray(duals["lam_g0"]).ravel())
            x = nlp.start(Q0, F0) if x is None else x
            with ipopt_call():  # IPOPT reports Ctrl-C as a failed start: stop instead
                sol = solver(x0=x, lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg, **duals)
            x, duals, last = sol["x"], {"lam_x0": sol["lam_x"], "lam_g0": sol["lam_g"]}, nlp
            stats = solver.stats()
            iterations, runs = iterations + int(stats.get("iter_count", 0)), runs + 1
            status = STALLED if solver.watch is not None and solver.watch.stalled else stats["return_status"]
            if rules.collision is None:
                break
            if status == STALLED:
                break
            if status not in (*CONVERGED, STOPPED):
                if restarted or run == MAX_ROUNDS - 1:
                    break
                # once: again from the start plan with the rows held so far (from inside another
                # link or an obstacle, a smooth distance row can lead the wrong way)
                x, last, how, restarted = None, None, "cold", True
                continue
            grown, how = _grown(rules, nlp.plan(x)[0], active, status)
            if len(grown) == len(active):
                break
            active = grown
    Q, F = (np.asarray(v, dtype=float) for v in nlp.plan(x))
    Q = problem.rules.limits.wrap(Q)
    scores = plan_scores(problem, Q, F)
    rec = StartRecord(
        status=str(status),
        iterations=iterations,
        value=scores.value(nlp.criterion),
        max_rms_error_m=scores.max_rms_error_m,
        feasible=not plan_violations(problem, Q, F) and scores.identifiable,
        runs=runs,
        rows_held=len(active),
    )
    return rec, Q, F, scores


def _grown(rules: PoseConstraints, Q: np.ndarray, active: np.ndarray, status: str) -> tuple[np.ndarray, str]:
    """After a run that ended with ``status`` at the plan ``Q`` (m, n), rad, holding the
    capsule rows ``active`` (K x 2): the rows to hold next, and how the next run starts.

    A converged run whose plan keeps every row left out: the rows closer than
    ``ADD_MARGIN_M`` join, and the next run starts "warm" (from the primal and dual point).
    A run that :class:`_Watch` stopped, or whose plan breaks a row left out: the rows closer
    than ``START_MARGIN_M`` join, and the next run goes on from the iterate as a "resumed" run
    (its barrier parameter, ``RESUME_MU``, larger than a warm start's).
    """
    slack = rules.capsule_slack(Q)
    R = slack.shape[1]
    clear = status != STOPPED and not _left_out_broken(slack, active, FEASIBILITY_TOL)
    codes = np.union1d(_codes(active, R), _codes(np.argwhere(slack < (ADD_MARGIN_M if clear else START_MARGIN_M)), R))
    return np.column_stack([codes // R, codes % R]), "warm" if clear else "resumed"


def seeded_plans(problem: Problem, criterion: str, m: int, starts: int | None = None) -> list[StartPlan]:
    """The ``starts`` (default: the problem's, :meth:`~casadi_design.problem_file.solver.SolverSettings.starts_for`)
    seeded random start plans of a design, from :func:`start_rng`: they depend on the seed, the
    criterion and m only, and fewer starts are the first of more."""
    rng = start_rng(problem.solver.seed, criterion, m)
    return [random_plan(problem, m, rng) for _ in range(starts or problem.solver.starts_for(criterion))]


def initial_starts(problem: Problem, m: int, initial_plans: Sequence[tuple]) -> tuple[list[StartPlan], list[str]]:
    """Extra starts ``(Q0, F0)`` or ``(Q0, F0, origin)`` as start plans and their origins
    ("initial plan" when not given); raises ValueError for a plan of the wrong shape."""
    plans, origins = [], []
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
    return plans, origins


def solve_design(
    problem: Problem,
    criterion: str,
    m: int,
    starts: int | None = None,
    verbose: bool = False,
    *,
    initial_plans: Sequence[tuple] = (),
    executor: StartExecutor | None = None,
    progress: Callable[[int], object] | None = None,
) -> Design:
    """Best plan of ``m`` experiments for ``criterion`` over the multi-start.

    The ``starts`` seeded random plans are drawn first (:func:`seeded_plans`, so they do not
    depend on ``initial_plans`` or ``executor``); the ``initial_plans`` run after them as
    additional starts. Starts are judged in that order and a later start wins only when it is
    strictly better (:func:`best_design`), so extra starts can only improve the seeded result.

    Parameters
    ----------
    initial_plans : extra starts ``(Q0, F0)`` or ``(Q0, F0, origin)``: ``Q0`` shape (m, n), rad;
        ``F0`` shape (m, nF), N; ``origin labels the start's record ("initial plan" if not
        given).
    executor : runs the starts elsewhere (:mod:`casadi_design.execution.parallel`); None runs them here,
        one after the other. The result is the same either way.
    progress : called with 1 after each start (e.g. ``tqdm.update``).

    Raises
    ------
    DesignError
        When no start converges to a feasible plan (the message lists the IPOPT statuses).
    """
    t0 = time.perf_counter()
    plans = seeded_plans(problem, criterion, m, starts)
    extra, extra_origins = initial_starts(problem, m, initial_plans)
    plans, origins = plans + extra, [SEEDED] * len(plans) + extra_origins
    if executor is None:
        ds = make_design_solver(problem, criterion, m, verbose)
        results = (solve_start(problem, ds, Q0, F0) for Q0, F0 in plans)
    else:
        results = executor.map_starts(problem, criterion, m, plans, verbose)

    def counted():
        for r in results:
            if progress is not None:
                progress(1)
            yield r

    return best_design(problem, criterion, m, counted(), origins, t0)


def best_design(problem: Problem, criterion: str, m: int, results: Iterable[StartResult],
                origins: Sequence[str], t0: float) -> Design:
    """The design of the starts' ``results`` (in the order of their plans, labelled by
    ``origins``): the first converged feasible start that no later one beats strictly, by the
    criterion's own score; ``t0``: ``time.perf_counter()`` when its first start was sent.

    Raises
    ------
    DesignError
        When no start converged to a feasible plan (the message lists the IPOPT statuses).
    """
    crit = CRITERIA[criterion]
    records, best, why, kept = [], None, [], 0
    for result, origin in zip(results, origins):
        rec, Q, F, scores = result
        kept += isinstance(result, KeptStart)
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
                  clearances=tuple(clearances(problem.cell, Q)) if problem.cell else None, kept_starts=kept)
