"""``artefact_design.json``: the designs ``solve`` makes for a problem measured at an artefact's
points, and its plan CSVs (joints in rad, the artefact's point, the placement), read back by
``validate``, ``evaluate --compare``, ``program`` and ``identify``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ProblemError
from ..problem.build import Problem

ARTEFACT_DESIGN = "artefact_design.json"
#: What ``measurement`` says in the file.
KIND = "points fixed in an artefact"


@dataclass(frozen=True, eq=False)
class ArtefactPlan:
    """A plan of configurations seated at an artefact's points: its ``criterion``, ``Q`` (m, n),
    rad, and each configuration's ``point`` and ``placement`` (m,)."""

    criterion: str
    Q: np.ndarray
    point: np.ndarray
    placement: np.ndarray


def artefact_plans(problem: Problem, path: str | Path, option: str = "--results") -> list[ArtefactPlan]:
    """The plans of an ``artefact_design.json`` (or its folder) of ``casadi-design solve`` for
    ``problem``: its plan CSVs beside it, read as recordings are
    (:func:`~casadi_design.identification.recordings.read_recordings`).

    Raises
    ------
    ProblemError
        A missing or unreadable file, or one not of an artefact's design.
    """
    from ..identification.recordings import read_recordings

    path = Path(path)
    if path.is_dir():
        path = path / ARTEFACT_DESIGN
    try:
        record = json.loads(path.read_text())
        designs = [(d["criterion"], d["plan"]) for d in record["designs"]]
        if record.get("measurement") != KIND:
            raise ValueError
    except (OSError, ValueError, KeyError, TypeError):
        raise ProblemError(f"{option}: {path} is not the {ARTEFACT_DESIGN} of casadi-design solve {problem.path}; "
                           f"solve first: casadi-design solve {problem.path} --out DIR") from None
    out = []
    for criterion, plan in designs:
        rec = read_recordings(problem, [str(path.parent / plan)], option)
        out.append(ArtefactPlan(criterion, rec.Q, rec.point, rec.placement))
    return out
