"""What a second round starts from, read from files: experiments already measured (a plan or
measurement CSV, ``--measured``) and an earlier identification (``identification.json``,
``--prior``: its covariance, and its field of unmodelled error with the poses it was estimated
on), as the :class:`~casadi_design.problem_file.read.HeldSpec` of a problem
(:mod:`casadi_design.calibration.held` turns it into information)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import ProblemError
from ..problem.build import Problem
from ..problem_file.calibration import ModelErrorSpec
from ..problem_file.read import HeldSpec
from .measurements import file_sha256, read_experiments


def read_prior(problem: Problem, path: str) -> tuple[tuple[str, ...], np.ndarray, tuple[tuple[str, str | None], ...]]:
    """The robot parameters of an ``identification.json``, their covariance (SI units) and
    the measurement files it was identified from (path, SHA-256 or None).

    Raises
    ------
    ProblemError
        A missing or unreadable file, or one without ``parameters`` and ``covariance`` (written
        by an older ``identify``, or not an identification).
    """
    where = f"--prior {path}"
    try:
        record = json.loads(Path(path).read_bytes().decode("utf-8-sig"))
    except FileNotFoundError:
        raise ProblemError(f"{where}: no such file; give the identification.json written by "
                           "casadi-design identify") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ProblemError(f"{where}: cannot be read as JSON ({exc}); give the identification.json "
                           "written by casadi-design identify") from None
    parameters = record.get("parameters") if isinstance(record, dict) else None
    C = record.get("covariance") if isinstance(record, dict) else None
    try:
        names = [p["name"] for p in parameters]
        robot = [p.get("of") != "tracker frame" for p in parameters]
        C = np.array(C, dtype=float)
    except (TypeError, KeyError, ValueError):
        raise ProblemError(f"{where}: has no 'parameters' and 'covariance' of an identification; give the "
                           "identification.json written by casadi-design identify") from None
    L = len(names)
    if C.shape != (L, L) or not np.all(np.isfinite(C)):
        raise ProblemError(f"{where}: 'covariance' is not a finite {L} x {L} matrix of its {L} parameters; "
                           "give the identification.json written by casadi-design identify")
    keep = np.flatnonzero(robot)  # the tracker frame of that round is not this one's
    files = [r.get("file") for r in record.get("rounds") or [] if isinstance(r, dict)] or [record.get("measurements")]
    digests = record.get("measurements_sha256") or []
    return (tuple(names[i] for i in keep), C[np.ix_(keep, keep)],
            tuple((str(f), d if isinstance(d, str) else None) for f, d in zip(files, [*digests, *[None] * len(files)])))


def read_prior_field(problem: Problem, path: str) -> tuple[ModelErrorSpec | None, np.ndarray, np.ndarray]:
    """The unmodelled error's field of an ``identification.json`` (its ``model_error``) and the
    poses it was estimated on, Q (k, n), rad (m), F (k, nF), N; None and no poses when the
    identification found the residuals to be the tracker's noise.

    Raises
    ------
    ProblemError
        A ``model_error`` that is not one of this robot (its joints, lengths or poses)."""
    where = f"--prior {path}: model_error"
    record = json.loads(Path(path).read_bytes().decode("utf-8-sig"))
    error = record.get("model_error")
    none = (None, np.zeros((0, problem.robot.n)), np.zeros((0, problem.model.nF)))
    if error is None:
        return none
    try:
        spec = ModelErrorSpec(float(error["scale_m"]), tuple(float(v) for v in error["lengths"]),
                              float(error["nugget_m"]), tuple(float(v) for v in error.get("shares") or ()),
                              tuple(float(v) for v in error.get("angles_rad") or ()))
        Q = np.array(error["poses"]["q"], dtype=float).reshape(-1, problem.robot.n)
        F = np.array(error["poses"]["F"], dtype=float)
    except (TypeError, KeyError, ValueError):
        raise ProblemError(f"{where}: is not a field of this robot's {problem.robot.n} joints (scale_m, lengths, "
                           "nugget_m, poses); give the identification.json written by casadi-design identify for "
                           "this robot") from None
    if list(error.get("joints") or problem.robot.joints) != list(problem.robot.joints):
        raise ProblemError(f"{where}: is of the joints {', '.join(error['joints'])}, not those of {problem.path} "
                           f"({', '.join(problem.robot.joints)}); give the identification of this robot")
    if F.size != len(Q) * problem.model.nF:
        F = np.zeros((len(Q), problem.model.nF))  # the loads of another case: its poses unloaded
    return spec, Q, F.reshape(len(Q), problem.model.nF)


def _same_file(path: str, source: tuple[str, str | None]) -> bool:
    """Whether the file ``path`` is the ``source`` an identification was made from: the same
    bytes (its SHA-256), or the same path where the identification names none."""
    if source[1] is not None:
        return file_sha256(path) == source[1]
    try:
        return Path(path).resolve() == Path(source[0]).resolve()
    except OSError:
        return False


def read_held(problem: Problem, measured: list[str] | None, prior: str | None) -> HeldSpec | None:
    """The :class:`~casadi_design.problem_file.read.HeldSpec` of ``--measured`` files (their rows
    in order) and a ``--prior`` identification; None without either."""
    if not measured and prior is None:
        return None
    Q, F = np.zeros((0, problem.robot.n)), np.zeros((0, problem.model.nF))
    for path in measured or []:
        q, f, _ = read_experiments(problem, path, ignore_unknown=True)
        Q, F = np.vstack([Q, q]), np.vstack([F, f])
    names, C, sources = ((), None, ()) if prior is None else read_prior(problem, prior)
    field, Qp, Fp = (None, (), ()) if prior is None else read_prior_field(problem, prior)
    twice = [(m, f) for m in measured or [] for f, _ in [s for s in sources if _same_file(m, s)]]
    if twice:  # its information is in the prior already
        raise ProblemError(f"--measured {twice[0][0]}: --prior {prior} was identified from it ({twice[0][1]}), so "
                           "its information is in the prior already; give it as --measured or as the --prior, not both")
    return HeldSpec(tuple(map(tuple, Q.tolist())), tuple(map(tuple, F.tolist())), names,
                    None if C is None else tuple(map(tuple, C.tolist())), tuple(measured or []), prior,
                    tuple(map(tuple, np.asarray(Qp).tolist())), tuple(map(tuple, np.asarray(Fp).tolist())), field)
