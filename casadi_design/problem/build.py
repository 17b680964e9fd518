"""Build a read problem: robot, kinematics, calibration model, test poses, base set, smallest m.

:func:`build_problem` turns the plain data of :class:`casadi_design.problem_file.read.ProblemSpec` into
a :class:`Problem`: the Pinocchio robot, its CasADi kinematics, the calibration model
``y(q, F, X)`` with ``B = dy/dX``, the test poses (closed-form or damped-least-squares IK), the
identifiable base set when asked, the parameter scaling, and the identifiability check that
gives the smallest number of experiments. Errors name the problem file and field.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import pickle
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import pinocchio as pin

from ..calibration.artefact import Artefact, artefact
from ..calibration.held import prior_information
from ..calibration.identifiability import BaseSet, base_set, unit_columns
from ..calibration.models import CalibrationModel, calibration_model
from ..cell.cell import Cell, build_cell
from ..cell.spec import Workspace
from ..errors import ProblemError
from ..measures.field import Field, Sites, axes_of, model_sites
from ..measures.measures import information_matrix
from ..problem_file.calibration import ModelErrorSpec
from ..problem_file.experiments import ForceSpec
from ..problem_file.fields import (
    BYTES_PER_EXPERIMENT_L2,
    BYTES_PER_TEST_POSE_L2,
    MAX_EXPERIMENTS,
    MAX_TEST_POSES,
    check_size,
)
from ..problem_file.poses import TestPoseSpec
from ..problem_file.read import ProblemSpec, read_problem, spec_digest_blob
from ..problem_file.robot import RobotSpec
from ..problem_file.solver import SolverSettings
from ..robot.ik import path_ik, sample_path
from ..robot.robots import (
    DHJoint,
    Robot,
    add_tool_frame,
    dh_arm,
    load_urdf,
    make_robot,
    placement_from_xyz_rpy,
    planar_2r_ik,
    planar_arm,
)
from ..robot.symbolic import symbolic_kinematics
from ..runtime.cache import Memo, code_digest, digest, memoised
from ..runtime.threads import blas_setup
from .rules import PlanRules

T = TypeVar("T")

#: Rank test of identifiability: relative singular-value threshold of the column-scaled S.
IDENTIFIABILITY_RTOL = 1e-9
#: Random configurations stacked for the identifiability test.
IDENTIFIABILITY_SAMPLES = 60


@dataclass(frozen=True, eq=False)
class TestPoses:
    """The s test poses: where accuracy is required (a machining trajectory's nodes).

    Attributes
    ----------
    q : ndarray, shape (s, n), rad
    F : ndarray, shape (s, nF), N (and N m): machining wrench at each node.
    position_m : ndarray, shape (s, 3), m: nominal position of the measured frame.
    """

    q: np.ndarray
    F: np.ndarray
    position_m: np.ndarray

    @property
    def s(self) -> int:
        return self.q.shape[0]


@dataclass(frozen=True, eq=False)
class Problem:
    """A built design case: its plain data ``spec`` and what was built from it.

    ``base_set`` is set when the parameters were selected automatically
    (``parameters = "identifiable"``); ``m_min`` is the fewest experiments that can identify X,
    ``ceil(L / d)`` with d (``d_independent``) the independent values per experiment, or
    with information held ``ceil((L - rank M_held) / d)`` new ones (at least one). ``cell``:
    the robot's capsules, obstacles and tracker of ``[cell]`` (None without one).
    ``M_held`` (L x L, scaled parameters, read-only): the information of the experiments
    already measured and of the prior (:mod:`casadi_design.calibration.held`), added to every plan's;
    None without either. ``rules``: the rules of one experiment (joint limits, workspace and
    cell rows, load variables; :class:`~casadi_design.problem.rules.PlanRules`), each built on first
    use and shared by the copies that differ in solver settings or held information.
    """

    spec: ProblemSpec
    robot: Robot
    model: CalibrationModel
    test_poses: TestPoses
    base_set: BaseSet | None
    m_min: int
    rules: PlanRules
    cell: Cell | None = None
    d_independent: int = 1
    M_held: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def path(self) -> str:
        return self.spec.path

    @property
    def sigma_m(self) -> float:
        return self.spec.measurement.sigma_m

    @functools.cached_property
    def artefact(self) -> Artefact | None:
        """The artefact whose points the measured point is seated at (``[measurement.artefact]``,
        :mod:`casadi_design.calibration.artefact`); None: a tracker measures."""
        spec = self.spec.measurement.artefact
        return None if spec is None else artefact(np.array(spec.points_m))

    @property
    def m_values(self) -> tuple[int, ...]:
        return self.spec.m_values

    @property
    def force(self) -> ForceSpec | None:
        return self.spec.force

    @property
    def workspace(self) -> Workspace:
        return self.spec.workspace

    @property
    def criteria(self) -> tuple[str, ...]:
        return self.spec.criteria

    @property
    def solver(self) -> SolverSettings:
        return self.spec.solver

    @property
    def m_held(self) -> int:
        """Number of experiments already measured (``--measured``)."""
        return 0 if self.spec.held is None else self.spec.held.k

    @property
    def measured(self) -> tuple[np.ndarray, np.ndarray]:
        """The experiments already measured (``--measured``): Q (k, n), rad, F (k, nF), N."""
        held, k = self.spec.held, self.m_held
        return (np.array(held.q if k else (), dtype=float).reshape(k, self.robot.n),
                np.array(held.F if k else (), dtype=float).reshape(k, self.model.nF))

    def campaign(self, Q: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The whole campaign of a plan ``Q`` (m, n), ``F`` (m, nF): the measured experiments
        (:attr:`measured`) first, then the plan's, and which rows are measured (bool)."""
        Qh, Fh = self.measured
        Q = np.asarray(Q, dtype=float).reshape(-1, self.robot.n)
        F = np.asarray(F, dtype=float).reshape(len(Q), self.model.nF)
        return np.vstack([Qh, Q]), np.vstack([Fh, F]), np.arange(len(Qh) + len(Q)) < len(Qh)

    @functools.cached_property
    def field(self) -> Field | None:
        """The robot's unmodelled error as a field (:mod:`casadi_design.measures.field`) that the
        test-pose measure holds: ``[calibration.model_error]``, else the one of the ``--prior``
        identification; None: the paper's measure (the tracker's noise alone)."""
        spec = self.spec.calibration.model_error
        if spec is None and self.spec.held is not None:
            spec = self.spec.held.prior_model_error
        return None if spec is None else field_of(spec, self)

    @property
    def field_held(self) -> tuple[np.ndarray, np.ndarray]:
        """The poses measured before the plan that the field correlates it with: ``--measured``
        ones, then those of the ``--prior`` identification. Q (k, n), rad, F (k, nF), N."""
        Q, F = self.measured
        held = self.spec.held
        if held is not None and len(held.prior_q):
            k = len(held.prior_q)
            Q = np.vstack([Q, np.asarray(held.prior_q, dtype=float).reshape(k, self.robot.n)])
            F = np.vstack([F, np.asarray(held.prior_F, dtype=float).reshape(k, self.model.nF)])
        return Q, F

    def field_sites(self, Q: np.ndarray, F: np.ndarray) -> Sites:
        """The :class:`~casadi_design.measures.field.Sites` of the experiments ``Q`` (m, n), rad,
        ``F`` (m, nF), N, for the problem's field: how their measured values see it."""
        return model_sites(self.field, self.model, self.whitening, Q, F)

    @functools.cached_property
    def field_test_sites(self) -> Sites:
        """The test poses' :class:`~casadi_design.measures.field.Sites`: how their required
        components see the field."""
        return model_sites(self.field, self.model, self.whitening, self.test_poses.q, self.test_poses.F, "accuracy")

    @functools.cached_property
    def field_held_rows(self) -> tuple[np.ndarray, Sites]:
        """The held poses' (:attr:`field_held`) rows B (k, d, L) and sites, once."""
        Qh, Fh = self.field_held
        return (self.model.B_stack(Qh, Fh) if len(Qh) else np.zeros((0, self.model.d, self.model.L)),
                self.field_sites(Qh, Fh))

    def field_campaign(self, B: np.ndarray, S: Sites) -> tuple[np.ndarray, Sites]:
        """The rows (k + m, d, L) and sites the field's kriging holds for a plan of rows ``B`` (m,
        d, L) and sites ``S``: the held poses (:attr:`field_held`) first."""
        Bh, Sh = self.field_held_rows
        return np.concatenate([Bh, B]), Sh + S

    @functools.cached_property
    def field_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The base axis (0, 1, 2; -1: an orientation) of each measured value (d,) and of each
        required component at a test pose (r,): how the field couples them
        (:func:`~casadi_design.measures.field.axes_of`)."""
        model = self.model
        return axes_of(model.measured_rows, len(model.markers_m)), axes_of(model.accuracy_rows)

    @functools.cached_property
    def whitening(self) -> np.ndarray:
        """``Wh = sigma Sigma^-1/2`` (d x d) of one experiment's values (identity by default)."""
        wh = self.spec.measurement.whitening
        return np.eye(self.model.d) if wh is None else np.asarray(wh, dtype=float)

    @functools.cached_property
    def field_prior(self) -> np.ndarray | None:
        """The information on X (L x L, scaled parameters, 1/m^2 units of B) of
        ``[calibration.prior]`` alone: with a field the earlier rounds enter as poses
        (:attr:`field_held`), not as a covariance; None without a prior."""
        spec = self.spec
        P = prior_information(self.model.parameter_names, spec.calibration.prior, None, self.robot, 1.0, spec.path)
        return None if P is None else P / np.outer(self.model.column_scale, self.model.column_scale)

    @functools.cached_property
    def B0(self) -> np.ndarray:
        """``B0_j = de_j/dX`` at every test pose j, shape (s, r, L): how the required
        components ``e`` (``[test_poses].components``, under the test pose's wrench) move with
        the parameters X; ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``."""
        tp = self.test_poses
        B0 = self.model.B_stack(tp.q, tp.F, accuracy=True)
        B0.setflags(write=False)  # shared by every design of the problem
        return B0

    @functools.cached_property
    def digest(self) -> str:
        """SHA-256 (hex) of the problem's checked data: what a resumed sweep and a worker's
        cache recognise a problem by."""
        return hashlib.sha256(spec_digest_blob(self.spec)).hexdigest()

    @functools.cached_property
    def fingerprint(self) -> str:
        """A name for all a result of the problem is computed from, for what is kept on disk
        between runs (:mod:`casadi_design.runtime.cache`): its checked data, the robot's Pinocchio
        model, the cell's capsules and real geometry (the meshes' vertices: an edited URDF or
        mesh file is another problem, though its path is the same), the package's code, the
        libraries' versions, the BLAS kernels and thread count. Not the file's path: a copy of
        a problem file is the same problem."""
        cell = self.cell
        robot = pickle.dumps(self.robot.model)
        geometry = b"" if cell is None else pickle.dumps((cell.check.model, cell.check.geometry))
        capsules = b"" if cell is None else repr(cell.capsules).encode()
        data = spec_digest_blob(dataclasses.replace(self.spec, path=""))
        return digest(data, robot, geometry, capsules, code_digest().encode(),
                      *(str(v).encode() for v in blas_setup()))


def load_problem(path: str | Path) -> Problem:
    """Read a problem file and build it."""
    return build_problem(read_problem(path))


#: Problems built in this process, by their checked data (a problem is a pure function of it):
#: commands run one after the other in one process (and worker processes) reuse the robot,
#: model and the CasADi functions cached on it.
KEEP_BUILT = 8
_BUILT: Memo[Problem] = Memo(KEEP_BUILT)


def build_problem(spec: ProblemSpec) -> Problem:
    """Build the robot, model and test poses of ``spec`` and check identifiability.

    A spec that differs from a built one only in its solver settings (``--ipopt``) shares its
    robot, model, test poses and cell, and so the functions cached on them (:func:`per_model`).
    """
    bare = dataclasses.replace(spec, solver=SolverSettings(), held=None)
    problem = _BUILT.get(spec_digest_blob(bare), lambda: _build_named(dataclasses.replace(spec, held=None)))
    if problem.spec != spec:
        problem = dataclasses.replace(problem, spec=spec)
        problem = with_held(problem) if spec.held is not None else problem
    problem.field  # its lengths and the measured positions checked here, not at the first design
    return problem


def field_of(spec: ModelErrorSpec, problem: Problem) -> Field:
    """The :class:`~casadi_design.measures.field.Field` of ``spec`` for the robot of ``problem``:
    one correlation length (and, of the joints' angle errors, one angle) for every joint, or one
    per joint.

    Raises
    ------
    ProblemError
        Lengths, angles or shares of another number than the joints, or a field of the base axes
        for a measurement without positions.
    """
    n, given = problem.robot.n, spec.length_rad
    held = problem.spec.calibration.model_error is None
    where = (f"--prior {problem.spec.held.prior_file}: model_error" if held else
             f"{problem.path}: [calibration.model_error]")
    if len(given) not in (1, n):
        raise ProblemError(f"{where}.length_rad: has {len(given)} lengths for the {n} joints "
                           f"({', '.join(problem.robot.joints)}); give one for every joint or one per joint")
    if spec.angle_rad and len(spec.angle_rad) not in (1, n):
        raise ProblemError(f"{where}.angle_rad: has {len(spec.angle_rad)} angles for the {n} joints "
                           f"({', '.join(problem.robot.joints)}); give one for every joint or one per joint")
    if not spec.angle_rad and not np.any(problem.field_axes[0] >= 0):
        raise ProblemError(f"{where}: the field is an error of positions, and {problem.path} measures none; "
                           "measure x, y, z ([measurement].components) or remove it")
    if spec.shares and len(spec.shares) != n:
        raise ProblemError(f"{where}.shares: has {len(spec.shares)} shares for the {n} joints "
                           f"({', '.join(problem.robot.joints)}); give one per joint")
    angles = tuple(spec.angle_rad) * n if len(spec.angle_rad) == 1 else tuple(spec.angle_rad)
    return Field(spec.scale_m, tuple(given) * n if len(given) == 1 else tuple(given), spec.nugget_m, spec.shares,
                 angles)


def with_held(problem: Problem) -> Problem:
    """``problem`` with the information it holds before any plan (:mod:`casadi_design.calibration.held`):
    ``M_held`` and the fewest new experiments that identify X with it.

    Raises
    ------
    ProblemError
        For a prior of another problem (:func:`~casadi_design.calibration.held.prior_information`).
    """
    spec, model = problem.spec, problem.model
    P = prior_information(model.parameter_names, spec.calibration.prior, spec.held, problem.robot,
                          spec.measurement.sigma_m, spec.path)
    if not problem.m_held and P is None:
        return dataclasses.replace(problem, M_held=None)
    c = model.column_scale
    M = information_matrix(model.B_stack(*problem.measured)) if problem.m_held else np.zeros((model.L, model.L))
    if P is not None:
        M = M + P / np.outer(c, c)
    M = (M + M.T) / 2
    M.setflags(write=False)
    lam = np.linalg.eigvalsh(M)
    rank = int(np.sum(lam > IDENTIFIABILITY_RTOL * max(lam[-1], np.finfo(float).tiny)))
    m_min = max(1, -(-(model.L - rank) // problem.d_independent))
    return dataclasses.replace(problem, M_held=M, m_min=m_min)


def _build_named(spec: ProblemSpec) -> Problem:
    """:func:`_build`, its errors naming the file."""
    try:
        return _build(spec)
    except ProblemError as exc:
        if str(exc).startswith(f"{spec.path}: "):
            raise
        raise ProblemError(f"{spec.path}: {exc}") from None


def per_model(f: Callable[[Problem], T]) -> Callable[[Problem], T]:
    """Cache ``f(problem)`` by the built parts it depends on (model, cell, workspace, load):
    problems that differ only in their solver settings share them."""
    return memoised(KEEP_BUILT, key=lambda problem: (problem.model, problem.cell, problem.workspace,
                                                     problem.force))(f)


def _build(spec: ProblemSpec) -> Problem:
    robot = build_robot(spec.robot)
    margin = spec.workspace.joint_limit_margin_rad
    narrow = np.flatnonzero(robot.q_max - robot.q_min < 2 * margin)
    if narrow.size:
        k = int(narrow[0])
        raise ProblemError(f"[experiments.workspace].joint_limit_margin_rad: {margin:g} leaves no room in the "
                           f"range [{robot.q_min[k]:.6g}, {robot.q_max[k]:.6g}] of {robot.joints[k]}; use a "
                           "smaller margin")
    kin = symbolic_kinematics(robot)
    cal, meas = spec.calibration, spec.measurement
    markers = None if meas.markers_m is None else np.array(meas.markers_m)
    chosen = None
    parameters = cal.parameters
    if parameters == "identifiable":
        full = calibration_model(kin, "geometric", meas.components, geometric=kin.parameter_names,
                                 markers_m=markers)
        chosen = base_set(full)
        parameters = chosen.kept
    model_args = model_arguments(spec, tuple(parameters))
    model = calibration_model(kin, cal.case, **model_args)
    check_size(spec.path, "[experiments].m", max(spec.m_values), MAX_EXPERIMENTS, BYTES_PER_EXPERIMENT_L2,
               "experiments", "use fewer experiments", model.L)
    test_poses = _test_poses(spec.path, spec.test_poses, robot, model)
    check_size(spec.path, "[test_poses]", test_poses.s, MAX_TEST_POSES, BYTES_PER_TEST_POSE_L2,
               "test poses", "give fewer test poses", model.L)
    S, d = check_identifiable(spec, model)
    if spec.parameter_scaling == "column":
        # parameters in units that give every column of B unit RMS over random poses (Khalil)
        c = np.sqrt(np.mean(S.reshape(-1, model.d, model.L) ** 2, axis=0).sum(axis=0))
        model = calibration_model(kin, cal.case, column_scale=c, **model_args)
    cell = _cell(spec, robot, markers)
    rules = PlanRules(robot, model, spec.workspace, spec.force, cell, meas.markers_m)
    problem = Problem(spec, robot, model, test_poses, chosen, -(-model.L // d), rules, cell, d)
    return with_held(problem) if spec.calibration.prior is not None else problem


def model_arguments(spec: ProblemSpec, geometric: tuple[str, ...]) -> dict:
    """The keyword arguments of :func:`~casadi_design.calibration.models.calibration_model` for the
    problem ``spec`` with the geometric errors ``geometric`` (what is measured, required,
    loaded and how the noise is whitened)."""
    cal, meas = spec.calibration, spec.measurement
    return dict(
        measured=meas.components,
        accuracy=spec.test_poses.components,
        geometric=geometric,
        compliant=cal.compliant_joints,
        force=cal.wrench_components,
        markers_m=None if meas.markers_m is None else np.array(meas.markers_m),
        load_point_m=None if spec.force is None else np.array(spec.force.load_point_m),
        whitening=None if meas.whitening is None else np.array(meas.whitening),
    )


#: Cells built in this process, by the data they depend on (a cell samples configurations to
#: select its pairs, which takes seconds; problem variants that keep the cell reuse it).
_CELLS: Memo[Cell] = Memo(KEEP_BUILT)


def _cell(spec: ProblemSpec, robot: Robot, markers: np.ndarray | None) -> Cell | None:
    key = repr((spec.cell, spec.robot, spec.workspace.floor_z_m, None if markers is None else markers.tolist()))
    return _CELLS.get(key, lambda: build_cell(spec.cell, robot, spec.workspace, spec.robot.urdf,
                                              np.zeros((1, 3)) if markers is None else markers))


def build_robot(r: RobotSpec) -> Robot:
    """The Pinocchio robot of a robot description (planar arm, URDF or DH table)."""
    if r.source == "planar":
        model = planar_arm(r.planar_links_m)
    elif r.source == "urdf":
        model = load_urdf(r.urdf, {j: (lo, hi) for j, lo, hi in r.joint_limits_rad})
        if r.inertias_urdf:
            with_inertias(model, load_urdf(r.inertias_urdf), r.inertias_urdf)
    else:
        rows = [DHJoint(j.name, j.kind, j.theta_offset_rad, j.d_m, j.a_m, j.alpha_rad, j.lower, j.upper, j.beta_rad)
                for j in r.dh_rows]
        model = dh_arm(rows, r.dh_convention, placement_from_xyz_rpy(r.flange_xyz_m, r.flange_rpy_rad),
                       base=placement_from_xyz_rpy(r.base_xyz_m, r.base_rpy_rad))
    frame = r.frame
    if r.tool_xyz_m is not None:
        frame = add_tool_frame(model, frame, placement_from_xyz_rpy(r.tool_xyz_m, r.tool_rpy_rad))
    return make_robot(model, frame, {j: (lo, hi) for j, lo, hi in r.joint_limits_rad})


def with_inertias(model: pin.Model, source: pin.Model, name: str) -> None:
    """Give ``model``'s joints the inertias (mass, centre of mass, rotational inertia: the bodies
    each carries) of ``source``'s joints of the same names, in place.

    Raises
    ------
    ProblemError
        When no joint of ``model`` is in ``source``.
    """
    shared = [j for j in model.names[1:] if source.existJointName(j)]
    if not shared:
        raise ProblemError(f"[robot].inertias_urdf: {name} has none of the joints of [robot].urdf "
                           f"({', '.join(model.names[1:])}); give a URDF of the same robot")
    for j in shared:
        model.inertias[model.getJointId(j)] = source.inertias[source.getJointId(j)]


def _test_poses(path: str, tp: TestPoseSpec, robot: Robot, model: CalibrationModel) -> TestPoses:
    where = f"{path}: [test_poses]"
    segment = None
    if tp.kind == "path":
        positions, segment = sample_path(tp.path_kind, np.array(tp.path_points_m), tp.path_nodes)
        rotation = np.eye(3) if tp.tool_rpy_rad is None else pin.rpy.rpyToMatrix(*tp.tool_rpy_rad)
        seed = (robot.q_min + robot.q_max) / 2 if tp.seed_q_rad is None else np.array(tp.seed_q_rad)
        if seed.shape != (robot.n,):
            raise ProblemError(f"{where}.seed_q_deg: has {seed.size} values, the chain has {robot.n} joints "
                               f"({', '.join(robot.joints)}); give {robot.n} joint values in deg")
        q = path_ik(robot, positions, rotation, seed, tp.tool_rpy_rad is None)
    elif tp.kind == "joints":
        q = np.array(tp.joints_rad)
        if q.shape[1] != robot.n:
            raise ProblemError(f"{where}.joints_rad: rows have {q.shape[1]} values, the chain has {robot.n} "
                               f"joints ({', '.join(robot.joints)}); give one row of {robot.n} joint values (rad) per pose")
    else:
        q = np.array([planar_2r_ik(robot, p, tp.elbow) for p in tp.points_m])
    outside = np.flatnonzero(np.any((q < robot.q_min - 1e-12) | (q > robot.q_max + 1e-12), axis=1))
    if outside.size:
        raise ProblemError(f"{where}: test pose {int(outside[0])} (q = {q[outside[0]].round(4).tolist()} rad) is "
                           "outside the joint limits; move the pose or widen [robot.joint_limits_rad]")
    s, nF = q.shape[0], model.nF
    if tp.segment_forces_N is not None:
        F = np.array(tp.segment_forces_N)[segment]
    elif tp.forces_N is not None:
        F = np.array(tp.forces_N)
    elif tp.force_N is not None:
        F = np.tile(np.array(tp.force_N), (s, 1))
    else:
        F = np.zeros((s, nF))
    position = np.asarray(model.position.map(s)(q.T), dtype=float).T
    return TestPoses(q=q, F=F.reshape(s, nF), position_m=position)


def check_identifiable(spec: ProblemSpec, model: CalibrationModel) -> tuple[np.ndarray, int]:
    """Fail early when X cannot be identified: a rank-deficient model, then too few experiments.

    Stacks B over ``IDENTIFIABILITY_SAMPLES`` random configurations with the calibration
    loads (random directions where free), scales its columns by their norms under random
    loads and requires every singular value above ``IDENTIFIABILITY_RTOL`` times the largest
    (and the largest above zero). Returns the stacked (unscaled) B and the number d of
    independent values per experiment (the smallest m is ``ceil(L / d)``).
    """
    L, robot, force = model.L, model.kinematics.robot, spec.force
    rng = np.random.default_rng(12345)
    Q, F, F_any = [], [], []
    for _ in range(IDENTIFIABILITY_SAMPLES):
        Q.append(rng.uniform(robot.q_min, robot.q_max))
        f_any = rng.normal(size=model.nF)
        if force is not None:  # loads of the rig's size, so that column scales reflect them
            f_any *= force.magnitude_N / np.linalg.norm(f_any)
        F_any.append(f_any)
        F.append(np.array(force.vector_N) if force and force.mode == "fixed"
                 else force.magnitude_N * np.array(force.direction) if force and force.mode == "direction"
                 else f_any)
    rows = model.B_stack(np.array(Q), np.array(F))
    generic = model.B_stack(np.array(Q), np.array(F_any))
    S = rows.reshape(-1, L)
    # columns scaled by their norm under generic loads, so that a parameter the actual
    # loads cannot excite stays a (near) zero column; a column of round-off under any load
    # (a compliance whose joint axis runs through the measured point) stays unscaled, near zero
    Sn, _ = unit_columns(S, IDENTIFIABILITY_RTOL, np.linalg.norm(generic.reshape(-1, L), axis=0))
    _, sv, Vt = np.linalg.svd(Sn, full_matrices=False)
    null = ~(sv > IDENTIFIABILITY_RTOL * sv[0]) if sv[0] > 0 else np.ones(L, dtype=bool)
    where = f"{spec.path}: [calibration]"
    measured = ", ".join(spec.measurement.components)
    if sv[0] == 0 or not np.all(np.isfinite(sv)):
        field = "compliant_joints" if model.case == "elastostatic" else "parameters"
        why = (" under the calibration load of [experiments.force]"
               if force is not None and force.mode in ("fixed", "direction") else "")
        raise ProblemError(f"{where}.{field}: no parameter has any effect on the {measured} measurements{why} "
                           "(the identification matrix is zero); measure other components or change the load")
    if np.any(null):
        v = Vt[np.flatnonzero(null)[0]]
        involved = [model.parameter_names[i] for i in np.flatnonzero(np.abs(v) > 1e-6)]
        field = "compliant_joints" if all(p.startswith("k.") for p in involved) else "parameters"
        what = (f"{involved[0]} has no effect on them" if len(involved) == 1
                else f"{' and '.join(involved)} act as one combination")
        if field == "compliant_joints" and force and force.mode in ("fixed", "direction"):
            what += " under the calibration load of [experiments.force]"
        raise ProblemError(
            f"{where}.{field}: the parameters are not identifiable from {measured} measurements: {what} "
            f"(rank {int(np.sum(~null))} of {L}); remove {'it' if len(involved) == 1 else 'one of them'}"
        )
    # an experiment gives at most d independent values (three markers on a rigid tool: 6, not 9)
    d = max(np.linalg.matrix_rank(B, tol=1e-10 * np.abs(B).max()) if np.abs(B).max() > 0 else 0 for B in rows)
    m_min = int(-(-L // d))
    small = [m for m in spec.m_values if m < m_min]
    if small:
        raise ProblemError(
            f"{spec.path}: [experiments].m: m = {small[0]} is too small: {L} parameters "
            f"({', '.join(model.parameter_names)}) with {d} independent measured values per experiment "
            f"need m >= {m_min}; use m >= {m_min}"
        )
    return S, d
