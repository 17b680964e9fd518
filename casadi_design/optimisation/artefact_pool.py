"""Which recorded configurations to use, for points fixed in an artefact: the pool engine on rows
with the placements' poses beside X.

A pool of recordings (configurations with the ball seated at a point of a placement,
:mod:`casadi_design.identification.recordings`) is priced by the engine of
:mod:`.pool` with each experiment's rows ``[B_i, -G_i]`` (:func:`~casadi_design.calibration.artefact.artefact_rows`):
``M`` is then additive over the experiments, and with the test poses' rows zero on the
placements' columns ``tr(B0 M^-1 B0^T)`` is the test-pose measure of X with every placement
unknown (the Schur complement). The test poses' error is the one a user sees after registering
the work in the robot's frame by the robot itself: the rigid motion of the test points
projected out (:func:`~casadi_design.calibration.artefact.registered`). X is the base set the
pool tells (:func:`~casadi_design.calibration.artefact.identifiable`: no fixed point tells the
robot's base). D, A, E and the others judge ``M`` of X and the placements' poses together.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..calibration.artefact import artefact_rows, identifiable, placement_columns, registered
from ..errors import ProblemError
from ..plan.design import Design, Seating
from ..problem.build import Problem
from .pool import choose_design, kept_postures


@dataclass(frozen=True, eq=False)
class ArtefactPool:
    """A pool of recordings as the engine sees it: the configurations ``Q`` (k, n), rad, their
    artefact's ``point`` and ``placement`` (k,), the names of X (``names``, the base set the pool
    tells), the rows ``B`` (k, 3, L + P nP), the test poses' ``B0`` (s, 3, L + P nP), which
    configurations a plan may use (``kept`` (k,): those that keep the problem's rules,
    :func:`~.pool.kept_postures`) and the placements' nominal poses ``R`` (P, 3, 3), ``t``
    (P, 3), m, in the order of their numbers."""

    Q: np.ndarray
    point: np.ndarray
    placement: np.ndarray
    names: tuple[str, ...]
    B: np.ndarray
    B0: np.ndarray
    kept: np.ndarray
    R: np.ndarray
    t: np.ndarray


def artefact_pool(problem: Problem, Q: np.ndarray, point: np.ndarray, placement: np.ndarray) -> ArtefactPool:
    """The :class:`ArtefactPool` of configurations ``Q`` seated at ``point`` of ``placement``
    (module docstring); each placement's pose from the nominal robot's mean point of each of its
    points (:meth:`~casadi_design.calibration.artefact.Artefact.place`).

    Raises
    ------
    ProblemError
        Test poses that do not require x, y and z; information held before the plan (a prior,
        measured experiments), which the rows with the placements' poses do not hold yet.
    """
    A, model = problem.artefact, problem.model
    check_designable(problem)
    F = np.zeros((len(Q), model.nF))
    B = model.B_stack(Q, F)
    p = np.stack([np.asarray(model.points(q), dtype=float).reshape(3) for q in Q])
    at = np.searchsorted(np.unique(placement), placement)
    R, t = A.placed(p, point, at)
    kept, _ = identifiable(B, p, placement_columns(A, R, point, at))
    rows = artefact_rows(A, B[:, :, kept], R, point, at)
    B0 = registered(problem.B0[:, :, kept], problem.test_poses.position_m)
    B0 = np.concatenate([B0, np.zeros((len(B0), 3, rows.shape[2] - B0.shape[2]))], axis=2)
    names = tuple(n for n, k in zip(model.parameter_names, kept) if k)
    return ArtefactPool(Q, point, placement, names, rows, B0, kept_postures(problem, Q, F)[0], R, t)


def check_designable(problem: Problem) -> None:
    """Refuse what a design of an artefact's configurations does not hold.

    Raises
    ------
    ProblemError
        Information held before the plan (a prior, measured experiments: a second round);
        test poses that do not require x, y and z.
    """
    if problem.M_held is not None:
        raise ProblemError(f"{problem.path}: [calibration.prior] (or --measured, --prior): a design of an artefact's "
                           "configurations does not hold information before the plan (a second round) yet; remove "
                           "them, and identify the recordings of every round together")
    if tuple(sorted(problem.spec.test_poses.components)) != ("x", "y", "z"):
        raise ProblemError(f"{problem.path}: [test_poses].components: an artefact's calibration is judged at the "
                           "test poses' positions after registering the work; give components = [\"x\", \"y\", \"z\"]")


def choose_recordings(problem: Problem, pool: ArtefactPool, criterion: str, m: int, starts: int) -> Design:
    """The m recordings of the pool best by ``criterion`` (:func:`~.pool.choose_design` on the
    pool's rows kept). The design's ``Q``; which recordings: :func:`chosen_rows`."""
    idx = np.flatnonzero(pool.kept)
    Q = pool.Q[idx]
    return choose_design(problem, criterion, m, Q, np.zeros((len(Q), problem.model.nF)), starts,
                         with_bound=False, rows=(pool.B[idx], pool.B0))


def chosen_rows(pool: ArtefactPool, design: Design) -> np.ndarray:
    """The pool's rows of the design's configurations (m,), in the design's order."""
    return np.array([int(np.flatnonzero(np.all(pool.Q == q, axis=1))[0]) for q in design.Q])


@dataclass(frozen=True, eq=False)
class ClampChoice:
    """Where to clamp the artefact: the best plan of one criterion and m over every set of
    ``clamps`` placements of the pool (``design``; ``rows``, its configurations' indices in the
    pool, in the design's order; ``placements``, its set), and each set's best plan (``by_set``:
    (set, design), None where no plan of the set identifies X)."""

    design: Design
    rows: np.ndarray
    placements: tuple[int, ...]
    by_set: tuple[tuple[tuple[int, ...], Design | None], ...]


def choose_clamps(problem: Problem, Q: np.ndarray, point: np.ndarray, placement: np.ndarray, names: tuple[str, ...],
                  criterion: str, m: int, starts: int, clamps: int, seated: bool = False) -> ClampChoice:
    """The m configurations ``Q`` (k, n), rad, seated at ``point`` of ``placement`` (k,; indices
    into the placements' ``names``) best by ``criterion``, recorded at ``clamps`` of the
    placements: for every set of ``clamps`` placements, the pool of its configurations
    (:func:`artefact_pool`) and its best plan (:func:`choose_recordings`); the best set's plan,
    its :attr:`~casadi_design.plan.design.Design.seated` set. The measure judges the sets as it
    judges plans: each placement recorded is a pose more to absorb. ``seated``: the configurations
    are seated by the nominal robot at the problem file's placements
    (:mod:`casadi_design.plan.seated`), and each set's plan is then moved along them by IPOPT
    (:func:`~.seated_nlp.seated_nlp`) before the sets are compared.

    Raises
    ------
    ProblemError
        No set of ``clamps`` placements whose configurations identify X with m of them.
    """
    from itertools import combinations

    from ..measures.criteria import CRITERIA

    check_designable(problem)
    better, by_set, best, most, fewest = CRITERIA[criterion].better, [], None, 0, None
    for S in combinations(np.unique(placement).tolist(), clamps):
        idx = np.flatnonzero(np.isin(placement, S))
        try:
            pool = artefact_pool(problem, Q[idx], point[idx], placement[idx])
            most = max(most, int(pool.kept.sum()))
            unknowns = (len(pool.names), pool.B.shape[2] - len(pool.names))  # X's and the placements' poses'
            if fewest is None or sum(unknowns) < sum(fewest):
                fewest = unknowns
            d = choose_recordings(problem, pool, criterion, m, starts)
        except ProblemError:  # too few configurations, or none of m identifies X there
            by_set.append((tuple(S), None))
            continue
        rows = idx[chosen_rows(pool, d)]
        d = replace(d, seated=Seating(point[rows], placement[rows], names))
        if seated:
            from .seated_nlp import seated_nlp

            d = seated_nlp(problem, d)
        by_set.append((tuple(S), d))
        if best is None or better(d.scores.value(criterion), best[0].scores.value(criterion)):
            best = (d, rows, tuple(S))
    if best is None:
        where = f"{problem.path}: [measurement.artefact]" if seated else "--candidates"
        if m > most:
            raise ProblemError(f"{where}: --m {m}: only {most} configurations keep the problem's rules "
                               f"([experiments.workspace]) at any {clamps} of the placements; give m <= {most}"
                               + (" or more placements" if seated else " or more recordings"))
        if fewest is not None and 3 * m < sum(fewest):
            need = -(-sum(fewest) // 3)
            raise ProblemError(f"{where}: --m {m}: {m} configurations give {3 * m} values, fewer than the {sum(fewest)} "
                               f"unknowns ({fewest[0]} parameters the configurations tell and {fewest[1]} of the "
                               f"placements' poses); give m >= {need}")
        raise ProblemError(f"{where}: no {clamps} of the placements give m = {m} configurations that identify the "
                           "parameters and the placements' poses; give a larger m or more varied configurations"
                           + (", more placements or raise clamps" if seated else ""))
    return ClampChoice(*best, tuple(by_set))


def artefact_scores(problem: Problem, Q: np.ndarray, point: np.ndarray, placement: np.ndarray):
    """The scores of a plan of configurations ``Q`` (m, n), rad, seated at ``point`` of
    ``placement`` (m,): :func:`~.solve.plan_scores` of its rows with the placements' poses beside
    X (:func:`artefact_pool` of the plan alone: X the base set it tells)."""
    from .solve import plan_scores

    pool = artefact_pool(problem, Q, point, placement)
    return plan_scores(problem, Q, np.zeros((len(Q), problem.model.nF)), pool.B, False, pool.B0)
