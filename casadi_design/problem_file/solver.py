"""``[solver]``: the seeded IPOPT starts of each design, the seed and IPOPT's options."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..measures.criteria import CRITERIA
from .fields import TableReader, short

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "solver": {"starts", "seed", "max_iter", "tol", "ipopt", "criterion_starts"},
    "solver.ipopt": None,
    "solver.criterion_starts": set(CRITERIA),
}


@dataclass(frozen=True)
class SolverSettings:
    """Multi-start IPOPT settings; ``ipopt`` options pass through unchanged.

    ``starts``: seeded starts per design; ``criterion_starts``: (criterion, starts) pairs that
    replace it for the designs of those criteria (:func:`seeded_starts`).
    """

    starts: int = 20
    seed: int = 0
    max_iter: int = 3000
    tol: float = 1e-10
    ipopt: tuple[tuple[str, Any], ...] = ()
    criterion_starts: tuple[tuple[str, int], ...] = ()

    def starts_for(self, criterion: str) -> int:
        """The seeded starts of a design of ``criterion``."""
        return seeded_starts(self.starts, self.criterion_starts, criterion)


def seeded_starts(starts: int, criterion_starts: tuple[tuple[str, int], ...], criterion: str) -> int:
    """The seeded starts of a design of ``criterion``: its entry of ``criterion_starts``, or
    ``starts``."""
    return dict(criterion_starts).get(criterion, starts)


def starts_text(starts: int, criterion_starts: tuple[tuple[str, int], ...]) -> str:
    """The seeded starts per design, for people: ``16`` or ``16 (test-pose: 4)``."""
    per = ", ".join(f"{c}: {k}" for c, k in criterion_starts)
    return f"{starts} ({per})" if per else str(starts)


def read_solver(table: TableReader | None) -> SolverSettings:
    if table is None:
        return SolverSettings()
    d = SolverSettings()
    ipopt = table.sub("ipopt")
    options = tuple(sorted(ipopt.table.items())) if ipopt else ()
    for key, value in options:
        if not isinstance(value, (int, float, str)) or isinstance(value, float) and not math.isfinite(value):
            raise ipopt.error(f"expected a number or a string, got {short(value)}",
                              "see the IPOPT options reference", key)
    per = table.sub("criterion_starts")
    criterion_starts = tuple((c, per.integer(c, ..., "give its designs' seeded starts, e.g. test-pose = 4",
                                             low=1, high=100_000)) for c in per.table) if per else ()
    return SolverSettings(
        starts=table.integer("starts", d.starts, "the number of IPOPT starts", low=1, high=100_000),
        criterion_starts=criterion_starts,
        seed=table.integer("seed", d.seed, "a non-negative integer", low=0, high=2**63 - 1),
        max_iter=table.integer("max_iter", d.max_iter, "IPOPT iterations per start", low=0, high=10**9),
        tol=table.number("tol", d.tol, "IPOPT's tolerance, e.g. 1e-10", positive=True),
        ipopt=options,
    )
