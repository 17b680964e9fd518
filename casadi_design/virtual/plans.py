"""The plans a virtual calibration simulates: solved designs, or a results file's."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import OutputError, ProblemError
from ..plan.design import Design
from ..problem.build import Problem
from ..records.files import read_results
from .simulate import Plan


def plans_from_designs(problem: Problem, designs: list[Design]) -> list[Plan]:
    """The plans of solved designs, each with its campaign's measured experiments first
    (:meth:`~casadi_design.problem.build.Problem.campaign`): the whole campaign is identified."""
    return [Plan(d.criterion, len(Q), Q, F) for d in designs for Q, F, _ in [problem.campaign(d.Q, d.F)]]


def plans_from_results(problem: Problem, path: str | Path) -> list[Plan]:
    """The plans of a ``results.json`` (or ``sweep.json``) written by ``casadi-design solve``
    (``sweep``) for ``problem``.

    Raises
    ------
    ProblemError
        When the file is missing, unreadable or malformed, or was written for another model.
    """
    path = Path(path)
    if not path.exists():
        raise ProblemError(f"--results: no such file {path}; solve first: "
                           f"casadi-design solve {problem.path} --out DIR")
    try:
        record = read_results(path)
    except OutputError as exc:
        raise ProblemError(f"--results: {exc}") from None
    model = problem.model
    wanted = {"calibration.parameters": list(model.parameter_names), "sigma_m": problem.sigma_m}
    calibration = record.get("calibration")
    parameters = calibration.get("parameters") if isinstance(calibration, dict) else None
    found = {"calibration.parameters": parameters, "sigma_m": record.get("sigma_m")}
    for key, value in wanted.items():
        if found[key] != value:
            raise ProblemError(
                f"--results: {path} has {key} = {found[key]!r} but {problem.path} has {value!r}; "
                f"give the results of this problem (casadi-design solve {problem.path} --out DIR)"
            )
    plans = []
    for i, d in enumerate(record["designs"]):
        k = len(d["experiments"])  # the campaign's: its measured experiments too
        Q = np.array([e["q_rad"] for e in d["experiments"]], dtype=float).reshape(k, -1)
        F = np.array([e["force"] for e in d["experiments"]], dtype=float).reshape(k, -1)
        if Q.shape[1] != model.n or F.shape[1] != model.nF:
            raise ProblemError(
                f"--results: {path} designs[{i}] has {Q.shape[1]} joints and {F.shape[1]} force "
                f"components per experiment, {problem.path} has {model.n} and {model.nF}; give the "
                "results of this problem"
            )
        plans.append(Plan(d["criterion"], k, Q, F))
    return plans
