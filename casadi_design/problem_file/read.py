"""Problem files: TOML descriptions of a calibration design case, read into plain frozen data.

Reading only checks and stores: types, finite numbers, shapes, ranges, names of sections and
keys, sizes. It builds no robot, no CasADi expression and runs no solver, so a
:class:`ProblemSpec` is cheap to pickle and send to worker processes. Building the robot,
kinematics, calibration model, test poses, base set and smallest m is the next step
(:func:`casadi_design.problem.build.build_problem`), whose errors name the same fields.

Each section has a module of its own with its plain data, its keys and its reader (``robot``,
``calibration``, ``measurement``, ``poses`` (test poses), ``experiments``, ``cell``, ``solver``); this
one reads the file and the top level and puts the sections together. The format is documented
in ``docs/problem-format.md``. Every error names the file, the field, what is wrong and what
to do.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..cell.spec import CellSpec, Workspace
from ..errors import ProblemError
from ..measures.criteria import CRITERIA
from . import calibration, cell, experiments, measurement, poses, robot, solver
from .calibration import CalibrationSpec, ModelErrorSpec, read_calibration
from .cell import read_cell
from .experiments import ForceSpec, read_force, read_workspace
from .fields import BYTES_PER_EXPERIMENT_L2, MAX_EXPERIMENTS, Mat, TableReader, check_size, short
from .measurement import MeasurementSpec, read_measurement
from .poses import TestPoseSpec, read_test_poses
from .robot import RobotSpec, read_robot
from .solver import SolverSettings, read_solver

#: Largest problem file read (bytes): a bigger one is not a hand-written case.
MAX_FILE_BYTES = 10_000_000
#: The keys allowed in each table of a problem file (None: any key): the top level's and the
#: design's here, every other section's in its module (``KEYS``).
SECTIONS: dict[str, set[str] | None] = {
    "": {"name", "description", "robot", "calibration", "measurement", "test_poses",
         "experiments", "design", "solver", "cell"},
    "design": {"criteria", "parameter_scaling"},
    **robot.KEYS, **calibration.KEYS, **measurement.KEYS, **poses.KEYS, **experiments.KEYS, **cell.KEYS,
    **solver.KEYS,
}


@dataclass(frozen=True)
class HeldSpec:
    """What is known before this design (``--measured``, ``--prior``): experiments already
    measured and a prior on the parameters, whose information every design adds to its own.

    ``q`` (k, n), rad (m for prismatic joints), and ``F`` (k, nF), N (N m): the measured
    experiments; ``prior_names`` and ``prior_covariance`` (SI units per parameter pair): an
    identification's covariance of the parameters it names (those of this problem's
    parameters it does not name have no prior); ``measured_files`` and ``prior_file``: the files
    they were read from; ``prior_q``, ``prior_F`` and ``prior_model_error``: the poses that
    identification used and the unmodelled error's field it estimated (the field correlates
    new poses with those: :mod:`casadi_design.measures.field`)."""

    q: Mat = ()
    F: Mat = ()
    prior_names: tuple[str, ...] = ()
    prior_covariance: Mat | None = None
    measured_files: tuple[str, ...] = ()
    prior_file: str | None = None
    prior_q: Mat = ()
    prior_F: Mat = ()
    prior_model_error: ModelErrorSpec | None = None

    @property
    def k(self) -> int:
        """Number of measured experiments."""
        return len(self.q)

    @property
    def sources(self) -> tuple[str, ...]:
        """Every file it was read from: the measured experiments', then the prior's."""
        return self.measured_files + (() if self.prior_file is None else (self.prior_file,))


@dataclass(frozen=True)
class ProblemSpec:
    """A read and checked problem file: plain data only (see the module docstring)."""

    name: str
    path: str
    description: str
    robot: RobotSpec
    calibration: CalibrationSpec
    measurement: MeasurementSpec
    test_poses: TestPoseSpec
    m_values: tuple[int, ...]
    force: ForceSpec | None
    workspace: Workspace
    criteria: tuple[str, ...]
    parameter_scaling: str = "column"
    solver: SolverSettings = field(default_factory=SolverSettings)
    cell: CellSpec | None = None
    held: HeldSpec | None = None


def read_problem(path: str | Path) -> ProblemSpec:
    """Read and check a problem file (UTF-8 TOML; a byte-order mark is accepted)."""
    path = str(path)
    p = Path(path)
    if p.is_dir():
        raise ProblemError(f"{path}: is a folder, not a problem file; give a .toml file, e.g. "
                           "problems/paper_planar_2r.toml")
    try:
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ProblemError(f"{path}: is {size / 1e6:.0f} MB, not a problem file; give a TOML "
                               f"file under {MAX_FILE_BYTES // 1_000_000} MB")
        data = p.read_bytes()
    except FileNotFoundError:
        raise ProblemError(f"{path}: no such problem file; check the path") from None
    except OSError as exc:
        raise ProblemError(f"{path}: cannot be read ({exc.strerror}); check the file") from None
    if b"\0" in data:
        raise ProblemError(f"{path}: is a binary file, not a TOML problem file; give a text file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ProblemError(f"{path}: is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProblemError(f"{path}: not valid TOML ({exc}); check the syntax at that line") from None
    return parse_problem(raw, path)


def parse_problem(raw: dict, path: str = "<problem>") -> ProblemSpec:
    """Check a parsed TOML table ``raw`` and return its plain data."""
    try:
        return _parse(raw, path)
    except ProblemError as exc:
        if str(exc).startswith(f"{path}: "):
            raise
        raise ProblemError(f"{path}: {exc}") from None


def _parse(raw: dict, path: str) -> ProblemSpec:
    top = TableReader(path, raw, "", SECTIONS)
    name = top.get("name", str, Path(path).stem)
    description = top.get("description", str, "")
    robot = read_robot(top.sub("robot", required=True))
    cal = top.sub("calibration", required=True)
    calibration = read_calibration(cal)
    elastic = calibration.case in ("elastostatic", "both")
    measurement = read_measurement(top.sub("measurement", required=True))
    if measurement.artefact is not None and calibration.model_error is not None:
        raise cal.error("is not held by a design of an artefact's configurations yet", "remove it: identify "
                        "estimates the robot's unmodelled error from the recordings", "model_error")
    test_poses = read_test_poses(top.sub("test_poses", required=True), measurement, len(calibration.wrench_components))
    exp = top.sub("experiments", required=True)
    m_raw = exp.get("m", (int, list), hint="the number of experiments, e.g. m = [1, 5]")
    m_values = tuple(m_raw) if isinstance(m_raw, list) else (m_raw,)
    if not m_values or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in m_values):
        raise exp.error(f"expected positive integers, got {short(m_raw)}", "e.g. m = [1, 5]", "m")
    if len(set(m_values)) != len(m_values):
        raise exp.error(f"has repeated values {list(m_values)}", "list each m once", "m")
    check_size(path, "[experiments].m", max(m_values), MAX_EXPERIMENTS, BYTES_PER_EXPERIMENT_L2,
               "experiments", "use fewer experiments")
    if elastic:
        force = read_force(exp.sub("force", required=True), len(calibration.wrench_components))
    else:
        if "force" in exp.table:
            raise exp.error("a geometric case applies no load", "remove [experiments.force]", "force")
        force = None
    workspace = read_workspace(exp.sub("workspace"))
    design = top.sub("design", required=True)
    criteria = design.names("criteria", tuple(CRITERIA), hint="e.g. criteria = [\"test-pose\", \"D\", \"E\"]")
    scaling = design.get("parameter_scaling", str, "column")
    if scaling not in ("column", "none"):
        raise design.error(f"'{scaling}'", "allowed: column, none", "parameter_scaling")
    solver = read_solver(top.sub("solver"))
    cell = read_cell(top.sub("cell"), robot)
    return ProblemSpec(name, path, description, robot, calibration, measurement, test_poses, m_values,
                       force, workspace, criteria, scaling, solver, cell)


def spec_digest_blob(spec: ProblemSpec) -> bytes:
    """A stable byte string of ``spec`` (for keys of resumed sweeps and worker caches)."""
    return repr(spec).encode()
