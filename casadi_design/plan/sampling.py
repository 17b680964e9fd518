"""Random feasible plans: the seeded starts of the multi-start and the candidates of the bound.

A plan is drawn one experiment at a time: configurations uniform within the joint limits
(:meth:`~casadi_design.problem.rules.JointLimits.sample`), kept when every workspace and cell row holds
(:meth:`~casadi_design.problem.rules.PoseConstraints.feasible`), and a load that satisfies the
problem's load rule. Each experiment tries one configuration, then growing batches, and takes
the first feasible one of the first batch that has one. The configurations are judged in large
blocks ahead of that rule (a few CasADi calls for a whole plan instead of several per
experiment), and the generator is left where the rule leaves it: the same plans as drawing
batch by batch.
"""

from __future__ import annotations

import numpy as np

from ..errors import DesignError
from ..problem.build import Problem

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
    Q = _configurations(problem, m, rng)
    if model.nF == 0:
        return Q, np.zeros((m, 0))
    if force.mode == "fixed":
        return Q, np.tile(np.array(force.vector_N), (m, 1))
    if force.mode == "direction":
        return Q, force.magnitude_N * np.outer(rng.uniform(0.5, 1.0, m), force.direction)
    d = rng.normal(size=(model.nF, m)).T  # drawn as (nF, m): the order fixes each seed's plans
    return Q, force.magnitude_N * d / np.linalg.norm(d, axis=1)[:, None]


def _configurations(problem: Problem, m: int, rng: np.random.Generator) -> np.ndarray:
    """The configurations of a random plan, ``Q`` (m, n), rad (:func:`random_plan`)."""
    rules, limits = problem.rules.pose, problem.rules.limits
    start = rng.bit_generator.state
    drawn, ok = np.empty((0, problem.robot.n)), np.empty(0, dtype=bool)

    def judged(k: int, done: int) -> None:
        """At least k configurations of the stream drawn and judged; ``done`` experiments
        chosen so far set the size of the next block (their rate for the rest, with a margin)."""
        nonlocal drawn, ok
        while len(drawn) < k:
            rate = len(drawn) / done if done else SAMPLING_BATCH
            block = limits.sample(rng, max(k - len(drawn), int(1.25 * rate * (m - done)) + 1))
            drawn, ok = np.concatenate([drawn, block]), np.concatenate([ok, rules.feasible(block)])

    Q, used = np.empty((m, problem.robot.n)), 0
    for i in range(m):
        tried, batch, q = 0, 1, None
        while q is None and tried < SAMPLING_TRIES:
            size = min(batch, SAMPLING_TRIES - tried)
            judged(used + size, i)
            hit = np.flatnonzero(ok[used: used + size])
            q = drawn[used + hit[0]] if hit.size else None
            candidates = drawn[used: used + size]
            used, tried = used + size, tried + size
            batch = SAMPLING_BATCH if batch == 1 else min(2 * batch, SAMPLING_BATCH_MAX)
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
    rng.bit_generator.state = start  # as if only the configurations the rule tried were drawn
    limits.sample(rng, used)
    return Q
