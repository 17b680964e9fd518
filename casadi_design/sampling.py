"""Random feasible plans: the seeded starts of the multi-start and the candidates of the bound.

A plan is drawn one experiment at a time: configurations uniform within the joint limits
(:meth:`~casadi_design.rules.JointLimits.sample`), kept when every workspace and cell row holds
(:meth:`~casadi_design.rules.PoseConstraints.feasible`), and a load that satisfies the
problem's load rule.
"""

from __future__ import annotations

import numpy as np

from .build import Problem
from .errors import DesignError
from .rules import joint_limits, pose_constraints

#: Random configurations tried per experiment to satisfy the workspace constraints, drawn one
#: first, then in batches of ``SAMPLING_BATCH`` doubling up to ``SAMPLING_BATCH_MAX``.
SAMPLING_TRIES = 20000
SAMPLING_BATCH = 16
SAMPLING_BATCH_MAX = 1024


def random_plan(problem: Problem, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random feasible plan: ``Q`` (m, n), rad, within the limits and workspace; ``F``
    (m, nF), N, satisfying the load rule.

    Raises
    ------
    DesignError
        When no configuration of ``SAMPLING_TRIES`` satisfies the workspace and cell rows (the
        message names the rows most often broken).
    """
    model, force = problem.model, problem.force
    rules, limits = pose_constraints(problem), joint_limits(problem)
    Q = np.empty((m, problem.robot.n))
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
        Q[i] = q
    if model.nF == 0:
        return Q, np.zeros((m, 0))
    if force.mode == "fixed":
        return Q, np.tile(np.array(force.vector_N), (m, 1))
    if force.mode == "direction":
        return Q, force.magnitude_N * np.outer(rng.uniform(0.5, 1.0, m), force.direction)
    d = rng.normal(size=(model.nF, m)).T  # drawn as (nF, m): the seeded streams of earlier versions
    return Q, force.magnitude_N * d / np.linalg.norm(d, axis=1)[:, None]
