"""``viewer.html``: the plans in their cell, one pose at a time, in one self-contained page.

The page opens offline in any browser: no server, no network, nothing downloaded when it is
viewed. It embeds plotly.js (the ``plotly`` package's own copy, :func:`plotly.offline.get_plotlyjs`;
why plotly: docs/dependencies.md), the viewer's script (``viewer.js`` beside this module) and
the data below, as JSON in ``<script type="application/json" id="viewer-data">``. It shows

* the robot on its URDF visual meshes (a DH robot: the capsules of its cell; a robot with
  neither: a line through its joint origins), the tool capsules given as numbers (the
  reflector's bracket), the fitted capsules of the cell (hidden until asked for in the legend),
  the obstacles, the floor, the tracker (its stand is an obstacle of the cell);
* one pose at a time (buttons, a slider or the arrow keys), numbered as in the plan CSV, with
  its load arrow, the beam from the tracker to each reflector, the pose's smallest clearance
  on the real geometry and its joint values (deg; mm for prismatic joints);
* the test poses as points (and a line when they follow a path) coloured by the plan's
  ``sqrt(rho)`` (mm);
* a choice of the plan (criterion and m); a program's route (its moves in the program's order,
  animated through their via points, :func:`route_view`); an identification's measured points
  and the calibrated model's, with the residuals as arrows scaled for the eye
  (:func:`identification_view`).

Nothing here recomputes what the package computes: the rows are the plan CSV's
(:func:`casadi_design.records.export.design_table`, :func:`~casadi_design.records.export.plan_table`),
the clearances the cell check's (:attr:`casadi_design.plan.design.Design.clearances`,
:func:`casadi_design.cell.cell.clearances`), the reflectors the calibration model's
(``problem.model.points``), ``sqrt(rho)`` the design's scores, a program's points and an
identification's points and residuals their own. What moves is placed by Pinocchio
(``updateGeometryPlacements``) once per pose; the page only applies those placements.

Data layout (``geometry``: what is drawn; ``views``: what can be chosen): every moving piece is
a triangle mesh in the frame of a Pinocchio geometry object (``objects``); a view's ``frames``
hold each object's placement (3 x 4, row-major) per frame as little-endian float32 in base64,
a frame per pose (a route: per sample of its moves). Poses, rows and clearances are plain
JSON numbers (what a test reads back).
"""

from __future__ import annotations

import base64
import dataclasses
import itertools
import json
import math
import pickle
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from ..cell.capsules import carrier
from ..cell.cell import clearances
from ..cell.obstacles import Capsule
from ..measures.criteria import CRITERIA
from ..plan.design import Design
from ..problem.build import Problem
from ..problem_file.fields import WRENCH_ROWS
from ..records.export import design_table, joint_units, plan_table
from ..records.files import write_atomic
from ..robot.robots import frame_placement, urdf_file
from ..runtime.cache import memoised

if TYPE_CHECKING:
    import coal

#: The page's file name in an output folder.
VIEWER_NAME = "viewer.html"
#: Version of the page's data (``format`` of the JSON).
VIEWER_FORMAT = "casadi-design viewer 1"
#: Most triangles of a robot's visual meshes in the page: finer meshes are decimated by vertex
#: clustering (:func:`decimated`) on the coarsest grid of ``CLUSTER_CELLS_M`` that keeps under it.
MESH_TRIANGLES = 40_000
#: Grid sizes (m) tried for the vertex clustering, finest first.
CLUSTER_CELLS_M = (0.002, 0.003, 0.004, 0.006, 0.008, 0.012, 0.016)
#: Segments around a capsule, sphere or cylinder, and rings over each of its half-spheres.
ROUND_SEGMENTS, CAP_RINGS = 20, 5
#: Frames of a route per second of the robot's time (the page plays it in real time).
ROUTE_FPS = 12
#: The largest residual arrow of an identification is drawn this long (m), its scale rounded
#: down to 1, 2 or 5 times a power of 10.
ARROW_M = 0.15
#: Colours (CSS) of the robot's meshes (when the URDF gives none), the tool capsules, the
#: cell's fitted capsules and the obstacles.
ROBOT_COLOUR, TOOL_COLOUR, CAPSULE_COLOUR, OBSTACLE_COLOUR = "#b8c4ce", "#e08a2c", "#4a90d9", "#8a8a8a"


# --------------------------------------------------------------------------- meshes


def shape_mesh(shape: coal.CollisionGeometry) -> tuple[np.ndarray, np.ndarray] | None:
    """Triangles of a coal shape in its own frame: vertices (k, 3), m, and faces (t, 3) of
    vertex indices; None for a shape not drawn as a mesh (a half-space: the floor is drawn
    apart, other planes would hide the robot)."""
    import coal

    if isinstance(shape, coal.BVHModelBase):
        V = np.asarray(shape.vertices(), dtype=float)
        T = np.array([[t[0], t[1], t[2]] for t in map(shape.tri_indices, range(shape.num_tris))],
                     dtype=np.int64).reshape(-1, 3)
        return V, T
    if isinstance(shape, coal.Box):
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        T = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        return signs * np.asarray(shape.halfSide, dtype=float), T
    if isinstance(shape, coal.Sphere):
        return round_mesh(shape.radius, 0.0, caps=True)
    if isinstance(shape, coal.Capsule):
        return round_mesh(shape.radius, shape.halfLength, caps=True)
    if isinstance(shape, coal.Cylinder):
        return round_mesh(shape.radius, shape.halfLength, caps=False)
    if isinstance(shape, coal.ConvexBase):
        from scipy.spatial import ConvexHull

        P = np.asarray(shape.points(), dtype=float)
        return P, ConvexHull(P).simplices
    return None


def round_mesh(radius: float, half_length: float, caps: bool) -> tuple[np.ndarray, np.ndarray]:
    """A capsule (``caps``: half-spheres at both ends; a sphere when ``half_length`` is 0) or a
    closed cylinder of ``radius`` along z from ``-half_length`` to ``half_length`` (m), as coal
    places them: rings of ``ROUND_SEGMENTS`` vertices, and a vertex at each end."""
    if caps:
        lat = np.linspace(0.0, np.pi / 2, CAP_RINGS + 1)[1:]  # from the equator up, the pole left out
        rings = [(radius * np.cos(a), -half_length - radius * np.sin(a)) for a in lat[::-1]]
        rings += [(radius, -half_length), (radius, half_length)]
        rings += [(radius * np.cos(a), half_length + radius * np.sin(a)) for a in lat]
        rings = [(r, z) for r, z in rings if r > 1e-9 * max(radius, 1.0)]
        ends = (-half_length - radius, half_length + radius)
    else:
        rings, ends = [(radius, -half_length), (radius, half_length)], (-half_length, half_length)
    phi = np.linspace(0.0, 2 * np.pi, ROUND_SEGMENTS, endpoint=False)
    V = [np.array([0.0, 0.0, ends[0]])]
    for r, z in rings:
        V += [np.array([r * np.cos(p), r * np.sin(p), z]) for p in phi]
    V.append(np.array([0.0, 0.0, ends[1]]))
    n, k, T = len(rings), ROUND_SEGMENTS, []
    for s in range(k):  # the bottom fan, the bands, the top fan
        T.append([0, 1 + (s + 1) % k, 1 + s])
    for ring in range(n - 1):
        a, b = 1 + ring * k, 1 + (ring + 1) * k
        for s in range(k):
            t = (s + 1) % k
            T += [[a + s, a + t, b + t], [a + s, b + t, b + s]]
    top, last = 1 + n * k, 1 + (n - 1) * k
    for s in range(k):
        T.append([top, last + s, last + (s + 1) % k])
    return np.array(V), np.array(T)


def decimated(V: np.ndarray, T: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh ``V`` (k, 3), m, ``T`` (t, 3) simplified by vertex clustering (Rossignac and
    Borrel, 1993): the vertices in each cube of a grid of ``cell_m`` merged into their mean,
    the triangles that collapse dropped; shape within ``cell_m`` of the original."""
    key = np.floor(V / cell_m).astype(np.int64)
    _, cluster, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    cluster = cluster.ravel()
    W = np.zeros((len(counts), 3))
    np.add.at(W, cluster, V)
    W /= counts[:, None]
    S = cluster[T]
    S = S[(S[:, 0] != S[:, 1]) & (S[:, 1] != S[:, 2]) & (S[:, 0] != S[:, 2])]
    used, S = np.unique(S, return_inverse=True)
    return W[used], S.reshape(-1, 3)


@memoised(4, key=lambda urdf, model: (urdf, pickle.dumps(model)))
def visual_geometry(urdf: str, model: pin.Model) -> tuple[pin.GeometryModel, tuple[tuple[np.ndarray, np.ndarray] | None, ...]]:
    """The visual geometry of ``urdf`` on ``model`` (the robot loaded from it) and each object's
    triangles in its frame, the meshes decimated together under ``MESH_TRIANGLES``
    (:func:`decimated`). Read once per process (about 1 s for the UR10's 116 000 triangles) for
    a URDF and its robot: the problems of one URDF built apart (a command's and identify's,
    without the cell) have equal models, kept by their serialization (20 kB, a millisecond)."""
    from ..cell.cell import _package_dirs  # the folders the collision meshes are found in

    try:
        geometry = pin.buildGeomFromUrdf(model, str(urdf_file(urdf)), pin.GeometryType.VISUAL,
                                         package_dirs=[str(d) for d in _package_dirs(urdf)])
    except (RuntimeError, ValueError):  # visual meshes missing: the collision check reads its own
        return pin.GeometryModel(), ()
    meshes = [shape_mesh(go.geometry) for go in geometry.geometryObjects]
    meshes = [None if m is None else (m[0] * np.asarray(go.meshScale, dtype=float), m[1])
              for m, go in zip(meshes, geometry.geometryObjects)]
    total = sum(len(m[1]) for m in meshes if m is not None)
    for cell in CLUSTER_CELLS_M if total > MESH_TRIANGLES else ():
        small = [None if m is None else decimated(*m, cell) for m in meshes]
        if sum(len(m[1]) for m in small if m is not None) <= MESH_TRIANGLES or cell == CLUSTER_CELLS_M[-1]:
            meshes = small
            break
    return geometry, tuple(meshes)


@dataclass(frozen=True)
class Piece:
    """A moving mesh: ``vertices`` (k, 3), m, in the frame of geometry object ``obj``, its
    ``faces`` (t, 3), and the trace it is drawn in (``group``: "robot", "tool" or "capsules")."""

    obj: int
    vertices: np.ndarray
    faces: np.ndarray
    group: str
    colour: str


@dataclass(frozen=True, eq=False)
class Scene:
    """What is drawn of a problem: the moving ``pieces`` placed by the objects of ``geometry``
    on the robot's model (``sticks``: the robot as a line through its joint origins instead),
    the static meshes (world, m: name, vertices, faces), the floor's height, the tracker."""

    geometry: pin.GeometryModel
    pieces: tuple[Piece, ...]
    sticks: bool
    static: tuple[tuple[str, np.ndarray, np.ndarray], ...]
    floor_z_m: float | None
    tracker_m: np.ndarray | None
    robot_source: str


def _capsule_object(model: pin.Model, c: Capsule, name: str) -> tuple[pin.GeometryObject, tuple]:
    """A capsule on the robot as a Pinocchio geometry object (its coal shape placed on its
    carrying joint) and its mesh."""
    jid, jMc = carrier(model, c.frame)
    shape, R, p = c.coal_geometry()
    return pin.GeometryObject(name, jid, 0, jMc * pin.SE3(R, p), shape), shape_mesh(shape)


def problem_scene(problem: Problem) -> Scene:
    """The :class:`Scene` of ``problem``: with a URDF its visual meshes, else the robot's
    bodies on the cell's geometry (a DH robot's capsules, or the meshes of its
    ``collision_urdf``), else sticks; the cell from ``problem.cell`` when built (the fitted
    capsules too), else from the problem file's ``[cell]``."""
    robot, spec = problem.robot, problem.spec
    cell_spec = spec.cell
    geometry, pieces = pin.GeometryModel(), []

    def add(obj: pin.GeometryObject, mesh, group: str, colour: str) -> None:
        if mesh is not None and len(mesh[1]):
            pieces.append(Piece(geometry.addGeometryObject(obj), np.asarray(mesh[0], float),
                                np.asarray(mesh[1], np.int64), group, colour))

    source = "sticks"
    if spec.robot.urdf:
        visual, meshes = visual_geometry(spec.robot.urdf, robot.model)
        for go, mesh in zip(visual.geometryObjects, meshes):
            colour = go.meshColor
            rgb = ROBOT_COLOUR if np.allclose(colour, 0.9) or not go.overrideMaterial else (
                "#" + "".join(f"{int(255 * c):02x}" for c in colour[:3]))
            add(pin.GeometryObject(go.name, go.parentJoint, go.parentFrame, go.placement, go.geometry),
                mesh, "robot", rgb)
        source = "URDF visual meshes" if pieces else source
    given = cell_spec.capsules if cell_spec is not None else ()
    if not pieces and problem.cell is not None and problem.cell.check.source == "URDF collision meshes":
        check = problem.cell.check  # a DH robot's collision_urdf, on its chain (model.cell)
        for go in check.geometry.geometryObjects[: len(check.geometry.geometryObjects) - len(problem.cell.obstacles)]:
            if not go.name.startswith("capsule:"):
                add(pin.GeometryObject(go.name, go.parentJoint, 0, go.placement, go.geometry),
                    shape_mesh(go.geometry), "robot", ROBOT_COLOUR)
        source = "collision meshes"
    if pieces:  # the tool capsules the URDF lacks
        for k, c in enumerate(given):
            add(*_capsule_object(robot.model, c, f"tool capsule {k + 1} on {c.frame}"), "tool", TOOL_COLOUR)
        if problem.cell is not None:
            fitted = problem.cell.capsules[: len(problem.cell.capsules) - len(given)]
            for k, c in enumerate(fitted):
                add(*_capsule_object(robot.model, c, f"capsule {k + 1} on {c.frame}"), "capsules", CAPSULE_COLOUR)
    elif given:  # a DH robot: the capsules of its cell
        for k, c in enumerate(given):
            add(*_capsule_object(robot.model, c, f"capsule {k + 1} on {c.frame}"), "robot", ROBOT_COLOUR)
        source = "capsules of the cell"
    obstacles = problem.cell.obstacles if problem.cell is not None else (cell_spec.obstacles if cell_spec else ())
    static = []
    for o in obstacles:
        shape, R, p = o.coal_geometry()
        mesh = shape_mesh(shape)
        if mesh is not None:
            static.append((o.label, mesh[0] @ np.asarray(R).T + np.asarray(p), mesh[1]))
    tracker = None if cell_spec is None or cell_spec.tracker is None else np.array(cell_spec.tracker.position_m)
    return Scene(geometry, tuple(pieces), not pieces, tuple(static), problem.workspace.floor_z_m, tracker, source)


# --------------------------------------------------------------------------- what a pose shows


def _b64(array: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


@dataclass(frozen=True, eq=False)
class Frames:
    """The robot in each of k configurations: each object's placement (k, objects, 12: 3 x 4
    row-major, m), the line through its joint origins (k, n + 2, 3), its reflectors (k, p, 3)."""

    placements: np.ndarray
    sticks: np.ndarray
    points: np.ndarray

    def record(self) -> dict:
        return {"count": len(self.points), "placements": _b64(self.placements, "<f4"),
                "sticks": _b64(self.sticks, "<f4"), "points": _b64(self.points, "<f4"),
                "sticks_per_frame": self.sticks.shape[1], "points_per_frame": self.points.shape[1]}


def robot_frames(problem: Problem, scene: Scene, Q: np.ndarray) -> Frames:
    """:class:`Frames` of the configurations ``Q`` (k, n), rad: Pinocchio's placements of the
    scene's objects, the joint origins (the world origin, each joint of the chain, the measured
    frame) and the reflectors of the calibration model (``problem.model.points``)."""
    robot = problem.robot
    model, data = robot.model, robot.model.createData()
    gdata = scene.geometry.createData()
    Q = np.asarray(Q, dtype=float).reshape(-1, robot.n)
    objects = len(scene.geometry.geometryObjects)
    placements = np.zeros((len(Q), objects, 12))
    sticks = np.zeros((len(Q), robot.n + 2, 3))
    points = []
    for i, q in enumerate(Q):
        pin.forwardKinematics(model, data, robot.full_q(q))
        pin.updateGeometryPlacements(model, data, scene.geometry, gdata)
        for k in range(objects):
            M = gdata.oMg[k]
            placements[i, k] = np.hstack([M.rotation, M.translation[:, None]]).ravel()
        sticks[i, 1:-1] = [data.oMi[j].translation for j in robot.joint_ids]
        sticks[i, -1] = frame_placement(robot, q).translation
        points.append(np.asarray(problem.model.points(q), dtype=float).T)
    return Frames(placements, sticks, np.array(points).reshape(len(Q), -1, 3))


def load_arrow(problem: Problem, q: np.ndarray, f: np.ndarray) -> list[list[float]] | None:
    """Where the calibration load ``f`` (nF,), N, acts at ``q`` and its force (world, N): the
    load point of ``[experiments.force]`` (measured frame) in the world, and the force's
    components of the wrench; None without a force."""
    f = np.asarray(f, dtype=float).ravel()
    wrench = np.zeros(6)
    wrench[list(problem.model.force_rows)] = f
    if not np.any(wrench[:3]):
        return None
    point = np.zeros(3) if problem.force is None else np.asarray(problem.force.load_point_m, dtype=float)
    return [frame_placement(problem.robot, q).act(point).tolist(), wrench[:3].tolist()]


def load_words(problem: Problem, f: np.ndarray) -> str:
    """The load ``f`` (nF,) for people: each wrench component with its unit."""
    if not len(f):
        return "no load"
    names = [WRENCH_ROWS[r] for r in problem.model.force_rows]
    return ", ".join(f"{n} = {v:.1f} {'N' if n[0] == 'f' else 'N m'}" for n, v in zip(names, f))


def _number(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def poses_of_table(problem: Problem, header: list[str], rows: list[list], Q: np.ndarray, F: np.ndarray,
                   frames: list[int]) -> list[dict]:
    """One record per row of a plan's table (:func:`~casadi_design.records.export.plan_table`):
    its number, joint values (deg, mm) and clearance (mm) as the CSV has them, its load (N) and
    arrow, the frame that shows it."""
    n = problem.robot.n
    at = {c: k for k, c in enumerate(header)}
    out = []
    for row, q, f, frame in zip(rows, Q, F, frames):
        c = at.get("clearance_mm")
        near = row[c] if c is not None and row[c] != "" else None
        out.append({"number": int(row[0]), "frame": int(frame), "q": [float(v) for v in row[1:1 + n]],
                    "measured": at.get("measured") is not None and row[at["measured"]] == "yes",
                    "clearance_mm": None if near is None else float(near),
                    "closest": None if near is None else row[at["closest_bodies"]],
                    "load": [float(v) for v in f], "load_text": load_words(problem, f),
                    "arrow": load_arrow(problem, q, f)})
    return out


def _table(header: list[str], rows: list[list]) -> dict:
    return {"columns": header, "rows": [[float(v) if isinstance(v, (float, np.floating)) else
                                          int(v) if isinstance(v, (int, np.integer)) else v for v in r] for r in rows]}


def design_view(problem: Problem, scene: Scene, design: Design) -> dict:
    """The view of a design's plan: its campaign's rows as in its plan CSV
    (:func:`~casadi_design.records.export.design_table`: measured experiments first), the robot
    at each, ``sqrt(rho)`` at the test poses."""
    header, rows = design_table(problem, design)
    Q, F, _ = problem.campaign(design.Q, design.F)
    legend = CRITERIA[design.criterion].legend
    return {"kind": "plan", "criterion": design.criterion, "m": int(design.m),
            "label": f"{legend}, m = {design.m}: max sqrt(rho) {design.scores.max_rms_error_m * 1e3:.4f} mm",
            "file": f"plans/{design.criterion}_m{design.m}.csv", **_table(header, rows),
            "poses": poses_of_table(problem, header, rows, Q, F, list(range(len(Q)))),
            "frames": robot_frames(problem, scene, Q).record(),
            "rms_mm": [_number(v * 1e3) for v in design.scores.rms_error_m],
            "rms_label": "sqrt(rho) of the plan, mm"}


def route_view(problem: Problem, scene: Scene, Q: np.ndarray, F: np.ndarray, program, label: str,
               rms_error_m: np.ndarray | None = None) -> dict:
    """The view of a robot program (a :class:`casadi_design.program.sequence.Program` of the plan
    ``Q`` (m, n), rad, ``F`` (m, nF), N): the experiments in the program's order, numbered as
    the plan's rows (:func:`~casadi_design.records.export.plan_table`, clearances of the cell
    check), each in the configuration the program reaches it in; and the route, each straight
    joint move ``q_a + s (q_b - q_a)`` between the program's points sampled at ``ROUTE_FPS``
    frames per second of its time."""
    near = tuple(clearances(problem.cell, Q)) if problem.cell is not None else None
    header, rows = plan_table(problem, Q, F, near)
    points = program.points
    configs, times, moves, at_point = [points[0].q], [0.0], [], [0]
    departure = 0.0
    for a, b in itertools.pairwise(points):
        duration = max(b.time_s - departure, 0.0)
        k = max(2, math.ceil(duration * ROUTE_FPS))
        for s in np.arange(1, k + 1) / k:
            configs.append(a.q + s * (b.q - a.q))
            times.append(departure + s * duration)
        at_point.append(len(configs) - 1)
        departure = b.time_s + (program.measure_s if b.kind == "experiment" else 0.0)
    names = ["home" if p.kind == "home" else f"experiment {p.experiment}" for p in points]
    stops = [i for i, p in enumerate(points) if p.kind != "via"]
    paths = list(program.paths)
    for (i, j), path in zip(itertools.pairwise(stops), paths):
        moves.append({"from": names[i], "to": names[j], "start": at_point[i], "end": at_point[j],
                      "vias": path.vias, "time_s": points[j].time_s - (points[i].time_s + (
                          program.measure_s if points[i].kind == "experiment" else 0.0)),
                      "clearance_mm": _number(path.clearance_m * 1e3), "beam": path.beam})
    order = [p for p in points if p.kind == "experiment"]
    frame_of = {p.experiment: at_point[i] for i, p in enumerate(points) if p.kind == "experiment"}
    by_number = {int(r[0]): (r, q, f) for r, q, f in zip(rows, Q, np.asarray(F).reshape(len(Q), -1))}
    poses = poses_of_table(problem, header, [by_number[p.experiment][0] for p in order],
                           [p.q for p in order], [by_number[p.experiment][2] for p in order],
                           [frame_of[p.experiment] for p in order])
    scales = np.array([joint_units(problem, k)[2] for k in range(problem.robot.n)])
    for pose, p in zip(poses, order):
        pose["q"] = [float(v) for v in p.q / scales]  # the program's configuration (a turned wrist)
        pose["stop"] = p.stop_before
    view = {"kind": "program", "label": label, **_table(header, rows), "poses": poses,
            "frames": robot_frames(problem, scene, np.array(configs)).record(),
            "route": {"moves": moves, "times_s": times, "time_s": program.time_s,
                      "order": [int(k) for k in program.order]}}
    if rms_error_m is not None:
        view |= {"rms_mm": [_number(v * 1e3) for v in rms_error_m], "rms_label": "sqrt(rho) of the plan, mm"}
    return view


def arrow_scale(largest_m: float, reach_m: float = ARROW_M) -> float:
    """The factor that draws a residual of ``largest_m`` (m) at most ``reach_m`` long: 1, 2 or 5
    times a power of 10."""
    if not largest_m > 0:
        return 1.0
    raw = reach_m / largest_m
    power = 10.0 ** math.floor(math.log10(raw))
    return max(s * power for s in (1.0, 2.0, 5.0) if s * power <= raw)


def identification_view(calibration, scene: Scene) -> dict:
    """The view of an identification (a :class:`casadi_design.identification.calibrate.Calibration`):
    the robot at each row of the measurements (numbered by its line in the file), its measured points and the calibrated model's
    in the robot's base frame (each row's tracker frame undone: ``tracker_from_base`` of the fit
    with that row's frame), the residuals ``measured - model`` as arrows scaled by
    :func:`arrow_scale` (the calibration's residuals ``measured - model``, an axis not measured
    drawn as 0, a point not seen left out), the predicted ``sqrt(rho)`` at the test poses."""
    c = calibration
    problem, meas, fit = c.problem, c.measurements, c.fit
    frame_of = np.zeros(meas.m, dtype=int) if meas.frame_of is None else np.asarray(meas.frame_of)
    model_P = fit.tracker_points(meas.Q, meas.F, frame_of)
    rows_X = fit.rows_X(frame_of)
    seen = ~np.all(np.isnan(c.residual_axes_m), axis=2)  # (m, k): the points measured
    model, residual = np.zeros_like(model_P), np.zeros_like(model_P)
    for i in range(meas.m):
        T = dataclasses.replace(fit, X=rows_X[i], T0s=fit.T0s[frame_of[i]][None]).tracker_from_base
        back = np.linalg.inv(T)  # tracker frame -> base frame
        model[i] = model_P[i] @ back[:3, :3].T + back[:3, 3]
        residual[i] = np.nan_to_num(c.residual_axes_m[i]) @ back[:3, :3].T  # (an axis not measured: 0)
    measured = np.where(seen[:, :, None], model + residual, np.nan)
    largest = float(np.max(np.linalg.norm(residual, axis=2))) if residual.size else 0.0
    scale = arrow_scale(largest)
    scales = np.array([joint_units(problem, k)[2] for k in range(problem.robot.n)])
    frames = robot_frames(problem, scene, meas.Q)
    poses = []
    for i in range(meas.m):
        f = meas.F[i]
        poses.append({"number": int(meas.lines[i]), "frame": i, "q": [float(v) for v in meas.Q[i] / scales],
                      "measured": False, "clearance_mm": None, "closest": None,
                      "load": [float(v) for v in f], "load_text": load_words(problem, f),
                      "arrow": load_arrow(problem, meas.Q[i], f),
                      "used": bool(fit.used[i]), "residual_rms_mm": _number(c.residual_rms_m[i] * 1e3),
                      "residual_max_mm": _number(c.residual_max_m[i] * 1e3)})
    tracker = None
    if np.any(fit.T0s[0] != np.eye(4)) or len(fit.fit.frame_names):
        tracker = np.linalg.inv(fit.tracker_from_base)[:3, 3].tolist()  # where the tracker was
    return {"kind": "identification", "label": f"identification ({c.model} model): {meas.m} rows of {meas.path}",
            "poses": poses, "frames": frames.record(),
            "rms_mm": [_number(v * 1e3) for v in c.predicted_rms_m],
            "rms_label": "predicted sqrt(rho) after calibration, mm",
            "residuals": {"measured_m": [[p.tolist() if ok else None for p, ok in zip(row, s)]
                                         for row, s in zip(measured, seen)],
                          "model_m": model.tolist(), "arrows_m": (model + scale * residual).tolist(),
                          "scale": scale, "tracker_m": tracker,
                          "text": f"residual arrows x {scale:g} (1 mm drawn as {scale * 1e-3:g} m)"}}


def artefact_identification_view(calibration, scene: Scene) -> dict:
    """The view of an identification from an artefact's recordings (a
    :class:`casadi_design.identification.artefact_fit.ArtefactCalibration`): the robot at each
    recording of the fit, the sockets where the fit puts them (each placement's fitted pose,
    drawn as the measured points), the calibrated robot's ball centres, the residuals ``ball -
    socket`` as arrows scaled by :func:`arrow_scale`, and the predicted error at the test poses
    after registering the work: ``sqrt(tr(J0_j C J0_j^T))`` with ``J0`` the test points' rows of
    X, their rigid motion projected out
    (:func:`~casadi_design.calibration.artefact.registered`)."""
    from ..calibration.artefact import registered
    from ..identification.artefact_fit import ball_points

    c = calibration
    problem, rec, f = c.problem, c.recordings, c.fit
    A = problem.artefact
    sockets = f.t[rec.placement] + np.einsum("kab,kb->ka", f.R[rec.placement], A.points_m[rec.point])
    ball = sockets + f.r
    scale = arrow_scale(float(np.max(np.linalg.norm(f.r, axis=1))) if len(f.r) else 0.0)
    scales = np.array([joint_units(problem, k)[2] for k in range(problem.robot.n)])
    tp = problem.test_poses
    J0 = registered(ball_points(f.fit.model, tp.q, f.X)[1], tp.position_m)
    rms = np.sqrt(np.einsum("sil,lk,sik->s", J0, c.C, J0))
    poses = [{"number": i + 1, "frame": i, "q": [float(v) for v in rec.Q[i] / scales], "measured": False,
              "clearance_mm": None, "closest": None, "load": [], "load_text": load_words(problem, np.zeros(0)),
              "arrow": None,
              "used": bool(f.used[i]), "residual_rms_mm": _number(np.linalg.norm(f.r[i]) / np.sqrt(3) * 1e3),
              "residual_max_mm": _number(np.max(np.abs(f.r[i])) * 1e3)} for i in range(rec.N)]
    return {"kind": "identification",
            "label": f"identification ({c.model} model): {rec.N} recordings at {', '.join(rec.names)}",
            "poses": poses, "frames": robot_frames(problem, scene, rec.Q).record(),
            "rms_mm": [_number(v * 1e3) for v in rms],
            "rms_label": "predicted error after calibration and registering the work, mm",
            "residuals": {"measured_m": [[p.tolist()] for p in sockets], "model_m": [[p.tolist()] for p in ball],
                          "arrows_m": [[p.tolist()] for p in sockets + scale * f.r], "scale": scale,
                          "tracker_m": None,
                          "text": f"sockets (the fitted placements) and the calibrated ball centres; residual arrows x "
                                  f"{scale:g} (1 mm drawn as {scale * 1e-3:g} m)"}}


# --------------------------------------------------------------------------- the page


def scene_record(problem: Problem, scene: Scene, views: list[dict]) -> dict:
    """The page's ``geometry`` and test poses: one mesh trace per group of moving pieces (each
    vertex with its object), the static meshes, the floor, the tracker and the box every
    frame of every view stays in (the axes' ranges)."""
    traces = []
    for group, name, visible in (("robot", f"robot ({scene.robot_source})", True),
                                 ("tool", "tool capsules (cell)", True),
                                 ("capsules", "capsules of the cell (clearance rows)", "legendonly")):
        parts = [p for p in scene.pieces if p.group == group]
        if not parts:
            continue
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
        traces.append({"group": group, "name": name, "visible": visible, "colour": parts[0].colour,
                       "vertices": _b64(np.vstack([p.vertices for p in parts]), "<f4"),
                       "objects": _b64(np.concatenate([np.full(len(p.vertices), p.obj) for p in parts]), "<u2"),
                       "faces": _b64(np.vstack([p.faces + o for p, o in zip(parts, offsets)]), "<u4"),
                       "opacity": 0.35 if group == "capsules" else 1.0})
    points = [problem.test_poses.position_m]
    for _, V, _ in scene.static:
        points.append(V)
    if scene.tracker_m is not None:
        points.append(scene.tracker_m[None])
    radius = np.zeros(len(scene.geometry.geometryObjects))
    for p in scene.pieces:
        radius[p.obj] = max(radius[p.obj], float(np.max(np.linalg.norm(p.vertices, axis=1))))
    for v in views:
        fr = v["frames"]
        P = np.frombuffer(base64.b64decode(fr["placements"]), "<f4").reshape(fr["count"], -1, 12)
        origins = P[:, :, [3, 7, 11]].reshape(-1, 3)
        r = np.tile(radius, fr["count"])[:, None]
        points += [origins - r, origins + r,
                   np.frombuffer(base64.b64decode(fr["sticks"]), "<f4").reshape(-1, 3),
                   np.frombuffer(base64.b64decode(fr["points"]), "<f4").reshape(-1, 3)]
        for arrow in (p["arrow"] for p in v["poses"] if p["arrow"]):
            points.append(np.array(arrow[0])[None])
    allp = np.vstack([np.asarray(p, dtype=float).reshape(-1, 3) for p in points])
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    if scene.floor_z_m is not None:
        lo[2] = scene.floor_z_m
    pad = 0.05 * float(np.max(hi - lo)) + 0.05
    lo, hi = lo - pad, hi + pad
    if scene.floor_z_m is not None:
        lo[2] = scene.floor_z_m
    return {"traces": traces, "objects": [go.name for go in scene.geometry.geometryObjects],
            "sticks": scene.sticks, "robot_source": scene.robot_source,
            "static": [{"name": name, "vertices": np.round(V, 6).tolist(), "faces": T.tolist()}
                       for name, V, T in scene.static],
            "floor_z_m": scene.floor_z_m,
            "tracker_m": None if scene.tracker_m is None else scene.tracker_m.tolist(),
            "bounds_m": [lo.tolist(), hi.tolist()]}


def viewer_html(problem: Problem, scene: Scene, views: list[dict], title: str) -> str:
    """The page (module docstring) of ``views`` of ``problem``."""
    from plotly.offline import get_plotlyjs

    from .plotting import is_path

    cell = problem.cell
    data = {"format": VIEWER_FORMAT, "problem": problem.name, "title": title,
            "joints": [{"name": j, "unit": joint_units(problem, k)[1]} for k, j in enumerate(problem.robot.joints)],
            "clearance_mm": None if cell is None else cell.spec.clearance_m * 1e3,
            "checked_on": None if cell is None else cell.check.source,
            "point": "reflector" if problem.artefact is None else "ball centre",  # what the measured point is
            "geometry": scene_record(problem, scene, views),
            "test_poses": {"position_m": problem.test_poses.position_m.tolist(),
                           "path": is_path(problem.test_poses.position_m)},
            "views": views}
    text = json.dumps(data, allow_nan=False, separators=(",", ":")).replace("</", "<\\/")
    script = files(__package__).joinpath("viewer.js").read_text(encoding="utf-8")
    safe_title = title.replace("&", "&amp;").replace("<", "&lt;")
    head, after_data = _PAGE.split("@DATA@")
    between, after_plotly = after_data.split("@PLOTLY@")
    before_script, tail = after_plotly.split("@SCRIPT@")
    return "".join([head.replace("@TITLE@", safe_title), text, between, get_plotlyjs(), before_script,
                    script, tail])


def write_viewer(out: Path, problem: Problem, designs: list[Design], programs: dict | None = None) -> list[str]:
    """``out/viewer.html`` of the designs' plans (with their programs' routes: ``programs``,
    (criterion, m) -> Program, as ``solve --program`` makes them), atomically; returns the
    file name."""
    scene = problem_scene(problem)
    views = []
    for d in designs:
        views.append(design_view(problem, scene, d))
        program = (programs or {}).get((d.criterion, d.m))
        if program is not None:
            views.append(route_view(problem, scene, d.Q, d.F, program,
                                    f"{CRITERIA[d.criterion].legend}, m = {d.m}: robot program, "
                                    f"{program.time_s:.1f} s", d.scores.rms_error_m))
    write_atomic(Path(out) / VIEWER_NAME, viewer_html(problem, scene, views, f"{problem.name}: plans").encode())
    return [VIEWER_NAME]


def write_program_viewer(out: Path, problem: Problem, Q: np.ndarray, F: np.ndarray, program, plan: str) -> list[str]:
    """``out/viewer.html`` of a robot program of the plan ``Q``, ``F`` (the plan file ``plan``)."""
    scene = problem_scene(problem)
    views = [route_view(problem, scene, Q, F, program, f"program of {plan}: {program.time_s:.1f} s")]
    write_atomic(Path(out) / VIEWER_NAME, viewer_html(problem, scene, views, f"{problem.name}: program").encode())
    return [VIEWER_NAME]


def write_identification_viewer(out: Path, calibration) -> list[str]:
    """``out/viewer.html`` of an identification (:func:`identification_view`; from an artefact's
    recordings :func:`artefact_identification_view`)."""
    problem = calibration.problem
    scene = problem_scene(problem)
    view = artefact_identification_view if hasattr(calibration, "recordings") else identification_view
    views = [view(calibration, scene)]
    write_atomic(Path(out) / VIEWER_NAME,
                 viewer_html(problem, scene, views, f"{problem.name}: identification").encode())
    return [VIEWER_NAME]


def results_problem(record: dict) -> tuple[Problem | None, str]:
    """The problem a results record (``results.json`` or ``sweep.json``) was solved for, built
    again from its problem file, to view its plans; None and why when it cannot be: the file
    is gone or changed (other test poses), or the plans follow experiments measured before
    (``--measured``: their rows come first in the plan CSVs)."""
    from ..errors import DesignError, ProblemError
    from ..problem.build import load_problem

    if (record.get("held") or {}).get("m_measured"):
        return None, "the plans follow experiments measured before (--measured); solve writes their viewer"
    path = record.get("problem_file")
    if not isinstance(path, str) or not Path(path).is_file():
        return None, f"its problem file {path} is not found from here; run plot where solve ran"
    try:
        problem = load_problem(path)
    except (ProblemError, DesignError) as exc:
        return None, str(exc)
    poses = np.array([t["position_m"] for t in record["test_poses"]], dtype=float)
    if problem.name != record["problem"] or poses.shape != problem.test_poses.position_m.shape or \
            not np.allclose(poses, problem.test_poses.position_m, rtol=0, atol=1e-9):
        return None, f"{path} has changed since the plans were solved (other test poses)"
    return problem, ""


def read_viewer_data(path: Path | str) -> dict:
    """The data embedded in a ``viewer.html`` (what its page shows)."""
    text = Path(path).read_text(encoding="utf-8")
    start = text.index('<script type="application/json" id="viewer-data">')
    start = text.index(">", start) + 1
    return json.loads(text[start:text.index("</script>", start)])


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>@TITLE@</title>
<script>
window.viewerErrors = [];
window.addEventListener("error", function (e) {
  window.viewerErrors.push(String(e.message || e.type) + (e.filename ? " (" + e.filename + ":" + e.lineno + ")" : ""));
});
window.addEventListener("unhandledrejection", function (e) { window.viewerErrors.push("unhandled: " + String(e.reason)); });
</script>
<style>
html, body { margin: 0; height: 100%; font: 13px/1.35 system-ui, sans-serif; color: #222; }
body { display: flex; flex-direction: column; height: 100vh; overflow: hidden; }
#bar { display: flex; flex-wrap: wrap; gap: 6px 10px; align-items: center; padding: 6px 10px;
       border-bottom: 1px solid #ccc; background: #f6f7f8; }
#bar h1 { font-size: 14px; margin: 0 8px 0 0; }
#bar select { max-width: 34em; }
#slider { width: 16em; }
#main { flex: 1 1 0; display: flex; min-height: 0; }
#plot { flex: 1 1 0; min-width: 0; height: 100%; overflow: hidden; }
#panel { width: 290px; overflow-y: auto; padding: 8px 10px; border-left: 1px solid #ccc; background: #fbfbfb; }
#panel h2 { font-size: 14px; margin: 0 0 6px; }
#panel table { border-collapse: collapse; margin: 4px 0 8px; }
#panel td { padding: 1px 6px 1px 0; }
#panel td.v { text-align: right; font-variant-numeric: tabular-nums; }
.warn { color: #b00020; }
.note { color: #555; }
#errors { color: #b00020; margin: 0; padding: 4px 10px; }
</style>
</head>
<body>
<div id="bar">
  <h1 id="title"></h1>
  <label>plan <select id="view"></select></label>
  <button id="prev" title="previous pose (left arrow key)">&#9664;</button>
  <input id="slider" type="range" min="1" max="1" step="1" value="1" aria-label="pose">
  <button id="next" title="next pose (right arrow key)">&#9654;</button>
  <span id="which"></span>
  <button id="play" hidden>&#9655; play the route</button>
</div>
<pre id="errors" hidden></pre>
<div id="main"><div id="plot"></div><div id="panel"></div></div>
<pre id="status" hidden></pre>
<script type="application/json" id="viewer-data">@DATA@</script>
<script>@PLOTLY@</script>
<script>@SCRIPT@</script>
</body>
</html>
"""
