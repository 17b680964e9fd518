"""Files: the output folder, atomic writes, and JSON in and out.

Everything the commands write goes through :func:`write_atomic` (a temporary file and a rename:
never a half-written file); the output folder is checked by :func:`prepare_out` before any
work starts. The package's computing layers never write files; the commands do, through this
module.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import OutputError
from ..optimisation.bound import ApproximateDesign
from ..plan.design import Design
from ..problem.build import Problem
from .results import MalformedRecord, check_results, design_from_record, design_record, results_dict

#: The files written by :func:`write_atomic` since the command started (:func:`start_log`):
#: what an error names as already written.
_WRITTEN: list[Path] = []


def start_log() -> None:
    """Forget the files written so far (a command starts)."""
    _WRITTEN.clear()


def _already_written() -> str:
    names = list(dict.fromkeys(str(p) for p in _WRITTEN))
    return f"already written: {', '.join(names)}" if names else "nothing was written"


def prepare_out(out: Path | str, force: bool = False, resume: bool = False,
                resume_files: tuple[str, ...] = ()) -> Path:
    """Check, before anything is solved, that the output folder ``out`` may be written.

    ``out`` may be missing (with missing parents: they are created when the files are
    written), empty, or hold files when ``force`` (overwrite them) or ``resume`` is given;
    ``resume`` needs one of ``resume_files`` (e.g. the ``sweep.partial.json`` of an interrupted
    sweep) in it. A missing folder is created and removed again, its missing parents too (a
    place that takes no folder, as ``/proc``, fails here, not after the work), so an error
    later leaves no folder behind.

    Raises
    ------
    OutputError
        Empty name, missing or not writable parent, not a folder, not empty, nothing to resume
        (one line each).
    """
    if not str(out).strip():  # checked on the string: Path("") is "."
        raise OutputError("--out is empty; give a folder name")
    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise OutputError(f"{out}: exists and is not a folder; choose another --out")
        folder = next(p for p in (out, *out.parents) if p.exists())  # out, or its nearest existing parent
        if not folder.is_dir():
            raise OutputError(f"{out}: {folder} is not a folder; choose another --out")
        if not os.access(folder, os.W_OK | os.X_OK | (os.R_OK if folder == out else 0)):
            raise OutputError(f"{out}: no permission to write in {folder}; choose another --out "
                              "or change the folder's permissions")
        if out.is_dir() and any(out.iterdir()) and not (force or resume):
            raise OutputError(f"{out}: folder exists and is not empty; add --force to overwrite "
                              "its files (or choose another --out)")
        if resume and not any((out / n).is_file() for n in resume_files):
            raise OutputError(f"{out}: nothing to resume (no {' or '.join(resume_files)}); run "
                              "without --resume")
    except OSError as exc:
        raise OutputError(f"{out}: cannot be checked ({exc.strerror}); choose another "
                          "--out") from None
    if not out.exists():
        missing = [p for p in (out, *out.parents) if not p.exists()]  # the deepest first
        try:
            out.mkdir(parents=True)
            for p in missing:
                p.rmdir()
        except OSError as exc:
            raise OutputError(f"{out}: the folder cannot be created ({exc.strerror}); choose "
                              "another --out") from None
    return out


def make_folder(folder: Path) -> Path:
    """Create ``folder`` (and its parents) if missing, with a one-line error.

    Raises
    ------
    OutputError
        The folder cannot be created (removed parent, permissions, full disk).
    """
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: the folder cannot be created ({exc.strerror}); "
                          f"{_already_written()}; fix the folder or its permissions, then run the "
                          "command again") from None
    return folder


def json_ready(value: object) -> object:
    """``value`` with every non-finite float (a singular plan's error, a failed start) as None,
    so that the file is standard JSON (``null``), readable by any tool."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def write_json(path: Path, record: dict) -> None:
    """``record`` as indented standard JSON (non-finite numbers as ``null``), atomically."""
    write_atomic(path, (json.dumps(json_ready(record), indent=2, allow_nan=False) + "\n").encode())


def _umask() -> int:
    """The process's umask (read by setting it and setting it back: process-global)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (never half-written),
    creating its folder when missing (:func:`make_folder`).

    The file gets the mode a plain ``open(path, "wb")`` gives a new file, ``0o666`` less the
    umask (the temporary file of :func:`tempfile.mkstemp` is ``0o600``).

    Raises
    ------
    OutputError
        The file cannot be written (full disk, permissions changed, folder removed): one line
        naming it, the files already written by the command, and what to do; no temporary
        file is left.
    """
    path = Path(path)
    make_folder(path.parent)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException as exc:  # Ctrl-C included: never a temporary file left
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if not isinstance(exc, OSError):
            raise
        raise OutputError(f"{path}: could not be written ({exc.strerror}); {_already_written()}; "
                          "free some disk space or fix the folder's permissions, then run the "
                          "command again") from None
    _WRITTEN.append(path)


#: What to do with a results file that cannot be read back.
_RESULTS_HINT = "give a results file written by casadi-design solve or sweep"


def read_results(path: Path | str) -> dict:
    """A results.json / sweep.json file, or the one inside a folder (sweep.json first).

    The record is checked (:func:`casadi_design.records.results.check_results`) before it is returned,
    so its designs can be given to :func:`~casadi_design.records.results.design_from_record`;
    ``record["_path"]`` is the file read.

    Raises
    ------
    OutputError
        No such file, not UTF-8 JSON, or a record of another shape (one line, naming the field).
    """
    path = Path(path)
    try:
        if path.is_dir():
            found = [path / n for n in ("sweep.json", "results.json") if (path / n).is_file()]
            if not found:
                raise OutputError(f"{path}: no sweep.json or results.json in this folder; "
                                  "give the file written by `casadi-design solve` or `sweep`")
            path = found[0]
        if path.exists() and not path.is_file():
            raise OutputError(f"{path}: is not a regular file (a device or a pipe); "
                              f"{_RESULTS_HINT}")
        record = json.loads(path.read_bytes().decode("utf-8-sig"))
    except FileNotFoundError:
        raise OutputError(f"{path}: no such results file; check the path") from None
    except OSError as exc:
        raise OutputError(f"{path}: cannot be read ({exc.strerror}); check the path and its "
                          "permissions") from None
    except UnicodeDecodeError as exc:
        raise OutputError(f"{path}: is not UTF-8 text (byte at offset {exc.start}), so not a "
                          f"results file; {_RESULTS_HINT}") from None
    except json.JSONDecodeError as exc:
        raise OutputError(f"{path}: not valid JSON ({exc}); give a results.json or sweep.json") from None
    except RecursionError:
        raise OutputError(f"{path}: JSON nested too deeply; {_RESULTS_HINT}") from None
    try:
        check_results(record)
    except MalformedRecord as exc:
        raise OutputError(f"{path}: {exc}; {_RESULTS_HINT}") from None
    record["_path"] = str(path)
    return record


def partial_record(path: Path, problem: Problem, key: dict, designs: list[Design]) -> None:
    """Save the finished designs of an unfinished campaign (``key``: what they depend on,
    :func:`casadi_design.execution.campaign.campaign_key`), atomically; called after each design."""
    write_json(Path(path), {"format": "casadi-design partial", "problem": problem.name,
                            "key": key, "designs": [design_record(d) for d in designs]})


def load_partial(out: Path, key: dict, sources: tuple[tuple[str, tuple[str, ...]], ...]
                 ) -> dict[tuple[str, int], Design]:
    """Finished designs saved in ``out``: from the first file of ``sources`` that exists
    (``(name, path of its key in the record)``), {} when none does.

    Raises OutputError when the saved designs were made with another problem or options, or
    the file is damaged.
    """
    for name, where in sources:
        path = Path(out) / name
        if not path.is_file():
            continue
        damaged = OutputError(f"{path}: not a file saved by casadi-design, or damaged; use --force "
                              "to start over")
        try:
            record = json.loads(path.read_bytes().decode("utf-8"))
            saved = record
            for k in where:
                saved = saved[k]
            diff = [k for k in key if saved.get(k) != key[k]]
        except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, AttributeError):
            raise damaged from None
        if diff:
            k = diff[0]
            what = "the problem file changed" if k == "problem_sha256" else (
                f"{k} was {saved.get(k)}, now {key[k]}")
            raise OutputError(f"{path}: saved with other settings ({what}); resume with the same "
                              "problem and options, or use --force to start over")
        try:
            return {(d["criterion"], d["m"]): design_from_record(d) for d in record["designs"]}
        except (KeyError, TypeError, ValueError, AttributeError):
            raise damaged from None
    return {}


def write_results(path: Path, problem: Problem, designs: list[Design],
                  approx: dict[tuple[str, int], ApproximateDesign] | None = None,
                  target: dict | None = None) -> dict:
    """``results.json`` of ``designs`` (:func:`casadi_design.records.results.results_dict`) and
    the answer of a ``--target-mm`` search, atomically; returns the record."""
    record = results_dict(problem, designs, approx) | ({"target": target} if target is not None else {})
    write_json(path, record)
    return record
