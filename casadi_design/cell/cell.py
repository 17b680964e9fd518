"""The calibration cell of a problem: the robot's capsules, the obstacles and the tracker.

Built once per problem from ``[cell]`` (:func:`build_cell`), it gives

* the cell's rows of one configuration (:func:`cell_rows`), added to the workspace rows of
  :attr:`casadi_design.problem.rules.PlanRules.pose`, hence imposed on every experiment by the NLP
  and checked by :func:`casadi_design.plan.rules.plan_violations`:
  - self-collision, obstacles (the floor of ``[experiments.workspace]`` included: every moving
    capsule stays above it) and the line of sight to the reflectors, from :func:`casadi_design.cell.collision.capsule_rows`
    (m, each ``>= 0``: capsules apart by at least ``clearance_m``);
  - reflector incidence: the beam from reflector ``k`` at ``p_k`` to the tracker at ``t``
    makes the angle ``acos(a . u_k)`` with the reflectors' axis ``a = R(q) a_tool``,
    ``u_k = (t - p_k) / |t - p_k|``; it must stay within the acceptance angle. One smooth row
    per experiment (unit "cos"): with ``c`` the reflectors' centroid, ``u = (t - c) / D``,
    ``D = |t - c|`` and ``s`` the largest distance of a reflector from ``c``, every ``u_k`` is
    within ``asin(s / D)`` of ``u``, so ``a . u >= cos(acceptance - asin(s / D))`` keeps every
    reflector within the acceptance angle (exact for one reflector; a few degrees
    conservative for a spread of markers). Three nearly parallel rows, one per marker, made
    IPOPT crawl (degenerate constraints).
  A reflector that the tracker cannot see rejects the pose, rather than dropping that
  measurement: the information matrix assumes every marker is measured in every experiment,
  and an operator would re-teach such a pose anyway.
* the check of a plan on the real geometry (:func:`clearances`): exact distances (coal,
  through Pinocchio) between the URDF collision meshes (or, for robots without meshes, the
  capsules themselves), the capsules given as numbers (a tool) and the obstacles, for the
  pairs the rows constrain. A plan in which two of them touch or cross breaks a rule of the
  problem. The rows keep ``clearance_m`` between the capsules, hence at least as much between
  the meshes, on every capsule pair they constrain: the reported clearance is the smallest
  distance between bodies all of whose capsule pairs are constrained. Bodies some of whose
  capsules overlap in every configuration (left out of the rows) may sit closer by
  construction, as the UR10's forearm and second wrist link, 18 to 20 mm apart in every pose:
  they are only checked for touching.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin

from ..errors import ProblemError
from ..robot.robots import Robot, example_robot_data_dir, frame_id, load_urdf, urdf_file
from ..runtime.cache import code_digest, digest, memoised, stored
from ..runtime.threads import blas_kernels
from .capsules import capsule_names, capsules_from_geometry, carrier, load_collision_geometry
from .collision import LineOfSight, PointRows, capsule_point_rows, obstacle_pairs
from .obstacles import Capsule, HalfSpace, Obstacle
from .pairs import PairSelection, self_collision_pairs
from .spec import CellSpec, Workspace

#: Largest change (m, rad) of the offset between a DH joint frame and the same joint of
#: ``collision_urdf`` over test configurations: both must carry the same link.
SAME_KINEMATICS_TOL = 1e-6


@dataclass(frozen=True, eq=False)
class CheckGeometry:
    """The real geometry a plan is checked on.

    ``model`` moves ``geometry`` (whose collision pairs are the checked ones); ``q_index[k]``
    is where chain joint k sits in ``model``'s configuration; ``labels`` names each geometry
    object's body (link, tool capsule or obstacle); ``source`` says what the robot's bodies
    are ("URDF collision meshes" or "capsules"); ``partial`` marks the collision pairs of
    bodies some of whose capsule pairs the rows leave out (they always overlap).
    """

    model: pin.Model
    geometry: pin.GeometryModel
    q_index: np.ndarray
    labels: tuple[str, ...]
    source: str
    partial: np.ndarray

    def configuration(self, q: np.ndarray) -> np.ndarray:
        full = pin.neutral(self.model)
        full[self.q_index] = q
        return full


@dataclass(frozen=True, eq=False)
class Cell:
    """A problem's cell: ``capsules`` of the robot, the constrained self-collision ``pairs``,
    the ``obstacles`` (the floor included) with the (capsule, obstacle) pairs ``near`` that
    can meet (``near_skipped``: the others, with the reason), the line of ``sights`` to the
    reflectors, and the geometry plans are ``check``-ed on. ``spec`` keeps the clearance and
    the tracker."""

    spec: CellSpec
    capsules: tuple[Capsule, ...]
    pairs: PairSelection
    obstacles: tuple[Obstacle, ...]
    near: tuple[tuple[int, int], ...]
    near_skipped: dict[tuple[str, str], str]
    sights: tuple[LineOfSight, ...]
    check: CheckGeometry


@dataclass(frozen=True)
class Clearance:
    """One configuration on the real geometry: the smallest distance (m) between bodies whose
    every capsule pair the rows constrain (at least the clearance when the rows hold), the two
    bodies at that distance, and two checked bodies that touch or cross, if any (``touching``;
    bodies some of whose capsules always overlap are only checked for this)."""

    distance_m: float
    between: tuple[str, str]
    touching: tuple[str, str] | None = None


def build_cell(spec: CellSpec | None, robot: Robot, workspace: Workspace, urdf: str,
               markers_m: np.ndarray) -> Cell | None:
    """The cell of ``[cell]`` for ``robot`` (built from ``urdf`` when not empty).

    ``markers_m`` (k x 3, measured frame, m): the reflectors; one line of sight stands for
    all of them: the beam to their centroid, kept further from the capsules by their spread
    (:class:`casadi_design.cell.collision.LineOfSight`). One beam per reflector gave nearly
    parallel rows that made IPOPT crawl.
    """
    if spec is None:
        return None
    model, where = robot.model, "[cell]"
    geometry, bodies, fitted = None, [], ()
    if urdf:
        geometry = load_collision_geometry(model, urdf_file(urdf), _package_dirs(urdf))
        bodies = [model.frames[go.parentFrame].name for go in geometry.geometryObjects]
        if spec.capsules_per_link and geometry.ngeoms:
            fitted = _fitted(urdf, spec.capsules_per_link)
    elif spec.collision_urdf:
        geometry, bodies, fitted = _onto_chain(robot, spec.collision_urdf, spec.capsules_per_link,
                                               f"{where}.collision_urdf")
    if spec.capsules_per_link and (geometry is None or not geometry.ngeoms):
        raise ProblemError(f"{where}.capsules_per_link: the robot has no collision geometry to fit "
                           "capsules around; give them as numbers (capsules = [...]) and capsules_per_link = 0")
    for c in spec.capsules:
        carrier(model, c.frame, f"{where}.capsules")
    capsules = tuple(fitted) + spec.capsules
    if not capsules and (spec.tracker is not None or spec.obstacles):
        raise ProblemError(f"{where}: obstacles and lines of sight need the robot's capsules; give "
                           "capsules = [...] (or capsules_per_link for a URDF robot)")
    links = {c.frame for c in capsules}
    for a, b in spec.disabled_pairs:
        unknown = [x for x in (a, b) if x not in links]
        if unknown:
            raise ProblemError(f"{where}.disabled_pairs: '{unknown[0]}' carries no capsule; the capsules "
                               f"are on: {', '.join(sorted(links))}")
    disabled = spec.disabled_pairs + tuple((a, b) for a, b in srdf_pairs(spec.srdf) if a in links and b in links)
    obstacles = spec.obstacles + ((HalfSpace((0.0, 0.0, 1.0), workspace.floor_z_m, "the floor"),)
                                  if workspace.floor_z_m is not None and capsules else ())
    pairs, (near, near_skipped) = _pairs(robot, capsules, obstacles, spec.clearance_m, disabled)
    markers = np.asarray(markers_m, dtype=float)
    centroid = markers.mean(axis=0)
    sights = ((LineOfSight(spec.tracker.position_m, robot.model.frames[robot.frame_id].name, tuple(centroid),
                           spread_m=float(np.max(np.linalg.norm(markers - centroid, axis=1)))),)
              if spec.tracker is not None and capsules else ())
    check = _check_geometry(robot, capsules, fitted, geometry, bodies, pairs, obstacles, near)
    return Cell(spec, capsules, pairs, obstacles, near, near_skipped, sights, check)


def srdf_pairs(path: str) -> tuple[tuple[str, str], ...]:
    """The ``<disable_collisions link1="..." link2="..."/>`` pairs of a MoveIt SRDF (``path``:
    a file or ``example-robot-data:<relative path>``; "" none), in file order."""
    if not path:
        return ()
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(urdf_file(path)).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ProblemError(f"[cell].srdf: cannot read {path} ({exc}); give the robot's SRDF (MoveIt), e.g. "
                           "example-robot-data:panda_description/srdf/panda.srdf") from None
    return tuple((e.get("link1", ""), e.get("link2", "")) for e in root.iter("disable_collisions"))


def _pairs(robot: Robot, capsules: tuple[Capsule, ...], obstacles: tuple[Obstacle, ...], clearance_m: float,
           disabled: tuple[tuple[str, str], ...]) -> tuple[PairSelection, tuple]:
    """The self-collision pairs (:func:`~casadi_design.cell.collision.self_collision_pairs`) and the
    (capsule, obstacle) pairs (:func:`~casadi_design.cell.collision.obstacle_pairs`) that can meet.

    Both sample configurations (about a second for the UR10's cell, paid by every command and
    worker process); the result is kept on disk (:func:`casadi_design.runtime.cache.stored`), named by
    the robot's Pinocchio model and limits, the capsules, obstacles, clearance and disabled
    pairs, the package's code, the libraries' versions and the BLAS kernels: a later run reads
    the pairs it would have computed."""
    def select() -> tuple[PairSelection, tuple]:
        self_pairs = self_collision_pairs(robot, capsules, clearance_m, disabled) if capsules else \
            PairSelection((), {}, ())
        return self_pairs, obstacle_pairs(robot, capsules, obstacles, clearance_m) if obstacles else ((), {})

    key = digest(pickle.dumps(robot.model), repr((robot.joints, robot.q_min.tolist(), robot.q_max.tolist(), capsules,
                                                   obstacles, clearance_m, disabled)).encode(),
                 code_digest().encode(), blas_kernels().encode())
    return stored("cell-pairs", key, select)


@memoised(8)
def _fitted(urdf: str, per_link: int) -> tuple[Capsule, ...]:
    """The capsules fitted around the collision meshes of ``urdf`` (by frame name: they do
    not depend on frames added later), once per process: a fit takes a few seconds."""
    model = load_urdf(urdf)
    return capsules_from_geometry(model, load_collision_geometry(model, urdf_file(urdf), _package_dirs(urdf)),
                                  per_link)


def _package_dirs(urdf: str) -> list[Path]:
    """Folders where ``package://`` mesh paths of ``urdf`` are looked up."""
    file = urdf_file(urdf)
    dirs = [file.parent, file.parent.parent, file.parent.parent.parent]
    if urdf.startswith("example-robot-data:"):
        dirs.append(example_robot_data_dir().parent.parent)
    return dirs


def _onto_chain(robot: Robot, urdf: str, per_link: int, where: str) -> tuple[pin.GeometryModel, list[str], tuple[Capsule, ...]]:
    """The collision geometry of ``urdf`` carried by the joints of ``robot`` (a DH robot) with
    the same names, a body name per object (the joint's name) and up to ``per_link`` capsules
    fitted around it, on those joints.

    An object or capsule point on URDF joint ``j`` goes onto the robot's joint of the same
    name through the offset ``oMi_robot^-1 oMi_urdf``; that offset must be the same in every
    configuration (checked at q = 0 and three random configurations), else the URDF is not
    the same robot. Bodies on joints off the chain are left out.
    """
    urdf_model = load_urdf(urdf)
    geometry = load_collision_geometry(urdf_model, urdf_file(urdf), _package_dirs(urdf))
    missing = [j for j in robot.joints if not urdf_model.existJointName(j)]
    if missing:
        raise ProblemError(f"{where}: the URDF has no joint '{missing[0]}'; its joints must carry the "
                           f"names of the chain ({', '.join(robot.joints)})")
    index = np.array([urdf_model.joints[urdf_model.getJointId(j)].idx_q for j in robot.joints])
    data, udata = robot.model.createData(), urdf_model.createData()
    to_robot = {urdf_model.getJointId(robot.model.names[j]): j for j in robot.joint_ids}
    offsets = None
    rng = np.random.default_rng(0)
    for q in [np.zeros(robot.n)] + [rng.uniform(robot.q_min, robot.q_max) for _ in range(3)]:
        full = pin.neutral(urdf_model)
        full[index] = q
        pin.forwardKinematics(robot.model, data, robot.full_q(q))
        pin.forwardKinematics(urdf_model, udata, full)
        now = {u: data.oMi[j].inverse() * udata.oMi[u] for u, j in to_robot.items()}
        if offsets is None:
            offsets = now
        for u, M in now.items():
            if not offsets[u].isApprox(M, SAME_KINEMATICS_TOL):
                raise ProblemError(f"{where}: its kinematics differ from the robot's at joint "
                                   f"'{urdf_model.names[u]}'; give a URDF of the same robot")
    out, bodies = pin.GeometryModel(), []
    for go in geometry.geometryObjects:
        if go.parentJoint in to_robot:
            j = to_robot[go.parentJoint]
            out.addGeometryObject(pin.GeometryObject(go.name, j, 0, offsets[go.parentJoint] * go.placement,
                                                     go.geometry))
            bodies.append(robot.model.names[j])
    fitted = []
    for c in capsules_from_geometry(urdf_model, geometry, per_link) if per_link else ():
        frame = urdf_model.frames[frame_id(urdf_model, c.frame)]
        if frame.parentJoint in to_robot:
            jMc = offsets[frame.parentJoint] * frame.placement
            fitted.append(Capsule(robot.model.names[to_robot[frame.parentJoint]], jMc.act(np.array(c.a_m)),
                                  jMc.act(np.array(c.b_m)), c.radius_m))
    return out, bodies, tuple(fitted)


def _geometry_object(name: str, joint: int, placement: pin.SE3, body: Obstacle) -> pin.GeometryObject:
    """The coal shape of ``body`` (:meth:`casadi_design.cell.obstacles.Obstacle.coal_geometry`),
    its frame placed by ``placement`` in ``joint``."""
    shape, R, p = body.coal_geometry()
    return pin.GeometryObject(name, joint, 0, placement * pin.SE3(R, p), shape)


def _check_geometry(robot: Robot, capsules, fitted, geometry, bodies, pairs: PairSelection,
                    obstacles, near) -> CheckGeometry:
    """The geometry model of :func:`clearances` with the pairs it checks (see the module
    docstring): the meshes the capsules were fitted around (else the capsules themselves),
    the capsules given as numbers and the obstacles. Each object belongs to the body (capsule
    frame) it stands for; the pairs checked are those of the rows: bodies of a kept capsule
    pair, a body and an obstacle of ``near``."""
    model = robot.model
    out, labels = pin.GeometryModel(), []
    meshes = geometry is not None and geometry.ngeoms and fitted
    if meshes:
        for go, body in zip(geometry.geometryObjects, bodies):
            out.addGeometryObject(pin.GeometryObject(go.name, go.parentJoint, 0, go.placement, go.geometry))
            labels.append(body)
    for c in capsules[len(fitted):] if meshes else capsules:
        jid, jMc = carrier(model, c.frame)
        out.addGeometryObject(_geometry_object(f"capsule:{c.frame}", jid, jMc, c))
        labels.append(c.frame)
    robot_objects = len(labels)
    self_pairs = {frozenset((capsules[i].frame, capsules[j].frame)) for i, j in pairs.kept}
    for i in range(robot_objects):
        for j in range(i + 1, robot_objects):
            if frozenset((labels[i], labels[j])) in self_pairs:
                out.addCollisionPair(pin.CollisionPair(i, j))
    for k, o in enumerate(obstacles):
        index = out.addGeometryObject(_geometry_object(o.name, 0, pin.SE3.Identity(), o))
        labels.append(o.label)
        frames = {capsules[c].frame for c, ob in near if ob == k}
        for i in range(robot_objects):
            if labels[i] in frames:
                out.addCollisionPair(pin.CollisionPair(i, index))
    q_index = np.array([model.joints[j].idx_q for j in robot.joint_ids])
    names = capsule_names(capsules)
    frame_of = dict(zip(names, (c.frame for c in capsules)))
    overlapping = {frozenset((frame_of[a], frame_of[b])) for (a, b), why in pairs.skipped.items()
                   if why.startswith("capsules overlap")}
    partial = np.array([frozenset((labels[cp.first], labels[cp.second])) in overlapping
                        for cp in out.collisionPairs], dtype=bool)
    return CheckGeometry(model, out, q_index, tuple(labels),
                         "URDF collision meshes" if meshes else "capsules", partial)


def clearances(cell: Cell, Q: np.ndarray) -> list[Clearance]:
    """The :class:`Clearance` of each configuration of ``Q`` (m, n), rad, on the real geometry
    (coal reports crossing meshes as 0 apart). A plan's are computed once: the plan check,
    results, CSV and report ask for the same ones."""
    Q = np.ascontiguousarray(Q, dtype=float)
    return list(_clearances(cell, Q.tobytes(), Q.shape[-1]))


@memoised(256)
def _clearances(cell: Cell, Q_bytes: bytes, n: int) -> tuple[Clearance, ...]:
    Q = np.frombuffer(Q_bytes).reshape(-1, n)
    check = cell.check
    if not check.geometry.collisionPairs:
        return tuple(Clearance(np.inf, ("", "")) for _ in Q)
    data, gdata = check.model.createData(), check.geometry.createData()
    names = [(check.labels[cp.first], check.labels[cp.second]) for cp in check.geometry.collisionPairs]
    out = []
    for q in Q:
        pin.computeDistances(check.model, data, check.geometry, gdata, check.configuration(q))
        d = np.array([max(float(r.min_distance), 0.0) for r in gdata.distanceResults])
        full = np.where(check.partial, np.inf, d)
        k, touch = int(np.argmin(full)), np.flatnonzero(d <= 0.0)
        out.append(Clearance(float(full[k]), names[k] if np.isfinite(full[k]) else ("", ""),
                             names[touch[0]] if touch.size else None))
    return tuple(out)


def touching(cell: Cell, Q: np.ndarray) -> list[tuple[str, str] | None]:
    """For each configuration of ``Q`` (m, n), rad: the first two checked bodies that touch or
    cross on the real geometry (the :attr:`Clearance.touching` of :func:`clearances`), None
    when none does. A collision query that stops at the first pair in contact, not the
    distance of every pair: on the UR10's meshes 0.6 ms a configuration instead of 11 ms."""
    check = cell.check
    if not check.geometry.collisionPairs:
        return [None] * len(Q)
    data, gdata = check.model.createData(), check.geometry.createData()
    out = []
    for q in np.asarray(Q, dtype=float):
        hit = pin.computeCollisions(check.model, data, check.geometry, gdata, check.configuration(q), True)
        k = next((k for k, r in enumerate(gdata.collisionResults) if r.isCollision()), None) if hit else None
        cp = None if k is None else check.geometry.collisionPairs[k]
        out.append(None if cp is None else (check.labels[cp.first], check.labels[cp.second]))
    return out


Row = tuple[ca.SX, float, float, str, str]


def cell_rows(cell: Cell, robot: Robot, q: ca.SX, R: ca.SX, P: ca.SX,
              markers_m: np.ndarray) -> tuple[PointRows, list[Row]]:
    """The cell's rows of configuration ``q``: ``(g, lb, ub, label, unit)`` with ``lb <= g <= ub``.

    ``R`` (3 x 3): the measured frame's rotation; ``P`` (3 x k, m): the reflectors, both at
    ``q``; ``markers_m`` (k x 3, m): the reflectors in the measured frame. Returns the capsule
    rows (m, each ``>= 0``) as functions of the world points
    (:func:`casadi_design.cell.collision.capsule_point_rows`) and,
    apart because they cost far less to evaluate, the incidence rows as cosines (unit "cos",
    module docstring).
    """
    capsule = capsule_point_rows(robot, cell.capsules, q, cell.spec.clearance_m, cell.obstacles, cell.sights,
                                 cell.pairs.kept, cell.near)
    rows: list[Row] = []
    tracker = cell.spec.tracker
    if tracker is not None:
        a = R @ ca.DM(tracker.reflector_axis)
        c = ca.sum2(P) / P.shape[1]
        spread = float(np.max(np.linalg.norm(markers_m - markers_m.mean(axis=0), axis=1)))
        u = ca.DM(tracker.position_m) - c
        D = ca.norm_2(u)
        margin = ca.asin(ca.fmin(spread / D, 0.99)) if spread > 0 else 0.0
        acceptance = tracker.acceptance_rad
        # cos(angle at the centroid) >= cos(acceptance - margin), shifted so that the row reads
        # as cos(angle) >= cos(acceptance) (exact for one reflector)
        rows.append((ca.dot(a, u) / D - ca.cos(acceptance - margin) + np.cos(acceptance), np.cos(acceptance),
                     np.inf, f"{'reflectors' if spread > 0 else 'reflector'}: tracker beam beyond the "
                             f"{np.rad2deg(acceptance):g} deg acceptance angle", "cos"))
    return capsule, rows


def world_capsules(cell: Cell, robot: Robot, q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float, str]]:
    """The robot's capsules at configuration ``q`` (n, rad): world ends ``a``, ``b`` (m),
    radius (m) and frame, for drawing."""
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, robot.full_q(np.asarray(q, dtype=float)))
    out = []
    for c in cell.capsules:
        jid, jMc = carrier(robot.model, c.frame)
        oMc = data.oMi[jid] * jMc
        out.append((oMc.act(np.array(c.a_m)), oMc.act(np.array(c.b_m)), c.radius_m, c.frame))
    return out
