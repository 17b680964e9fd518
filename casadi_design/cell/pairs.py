"""Which pairs of a robot's own capsules need a row: those that can meet (sampled over the joint
ranges: pairs that stay apart in every sample and adjacent links are left out), and which
capsules an obstacle can reach.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..robot.robots import Robot
from .capsules import adjacent_links, capsule_ends, capsule_names, carrier, moved_by_chain
from .obstacles import Capsule, Obstacle
from .segments import segment_distance_np

#: Configurations sampled by :func:`self_collision_pairs` to find the pairs that can separate.
PAIR_SAMPLES = 200


@dataclass(frozen=True)
class PairSelection:
    """Self-collision pairs: ``kept`` (indices into the capsules) become rows; ``skipped``
    maps each other pair of capsule names to the reason; ``links`` are the pairs of link
    frames of ``kept``."""

    kept: tuple[tuple[int, int], ...]
    skipped: dict[tuple[str, str], str]
    links: tuple[tuple[str, str], ...]


def self_collision_pairs(robot: Robot, capsules: Sequence[Capsule], clearance_m: float = 0.0,
                         disabled: Iterable[tuple[str, str]] = (), samples: int = PAIR_SAMPLES,
                         seed: int = 0) -> PairSelection:
    """The capsule pairs that can meet and that the capsules can keep apart.

    A pair (capsules on joints i and j) is a candidate unless the links are adjacent (same
    joint, or one joint the parent of the other: they touch at the joint) or no joint of the
    chain moves one relative to the other. A candidate is kept when its row
    ``dist - r1 - r2 - clearance`` is positive in at least one of ``samples`` configurations
    drawn uniformly within the joint limits (seeded); otherwise the capsules overlap wherever
    the robot goes (links whose meshes stay close but whose capsules cannot separate), so
    the row would make every plan infeasible: the pair is skipped, with the reason. Pairs whose sampled distance is constant (within 1e-9 m) and positive are skipped
    as never meeting. Pairs of link frames in ``disabled`` (as an SRDF's
    ``disable_collisions``: links that the user knows never meet) are skipped.
    """
    model = robot.model
    jids = [carrier(model, c.frame)[0] for c in capsules]
    rng = np.random.default_rng(seed)
    Q = rng.uniform(robot.q_min, robot.q_max, size=(samples, robot.n))
    ends = [capsule_ends(robot, q) for q in Q]
    kept, skipped, names = [], {}, capsule_names(capsules)
    off = [set(p) for p in disabled]
    for i, ci in enumerate(capsules):
        for j in range(i + 1, len(capsules)):
            cj, key = capsules[j], (names[i], names[j])
            path = set(model.supports[jids[i]]) ^ set(model.supports[jids[j]])
            if {ci.frame, cj.frame} in off:
                skipped[key] = "disabled"
                continue
            if adjacent_links(model, jids[i], jids[j]):
                skipped[key] = "adjacent links"
                continue
            if not path & set(robot.joint_ids):
                skipped[key] = "no joint of the chain moves one relative to the other"
                continue
            g = np.array([segment_distance_np(*e(ci), *e(cj)) for e in ends]) - ci.radius_m - cj.radius_m - clearance_m
            if np.all(g <= 0):
                skipped[key] = (f"capsules overlap in all {samples} sampled configurations "
                                f"(largest clearance {g.max() * 1e3:.1f} mm)")
            elif np.ptp(g) < 1e-9:
                skipped[key] = "constant distance, positive"
            else:
                kept.append((i, j))
    links = tuple(dict.fromkeys((capsules[i].frame, capsules[j].frame) for i, j in kept))
    return PairSelection(tuple(kept), skipped, links)


def near_pairs(robot: Robot, capsules: Sequence[Capsule], obstacles: Sequence[Obstacle]) -> list[tuple[int, int]]:
    """Every (moving capsule, obstacle) pair, obstacle by obstacle."""
    moving = [k for k, c in enumerate(capsules) if moved_by_chain(robot, carrier(robot.model, c.frame)[0])]
    return [(k, o) for o in range(len(obstacles)) for k in moving]
