"""Capsules, segment distances and collision rows, checked against brute force, coal and
finite differences."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import casadi as ca
import coal
import numpy as np
import pinocchio as pin
import pytest

from casadi_design.cell import capsules as K
from casadi_design.cell import collision as C
from casadi_design.cell import pairs as P
from casadi_design.cell import segments as S
from casadi_design.cell.cell import _fitted
from casadi_design.cell.obstacles import Box, HalfSpace
from casadi_design.errors import ProblemError
from casadi_design.robot.robots import example_robot_data_dir, make_robot

#: grid of the brute-force segment distance (points per side)
GRID = 401
#: agreement of the CasADi rows with their numpy twin (m)
TWIN_TOL = 1e-10
#: relative agreement of the rows' gradients with central differences
GRAD_RTOL = 1e-5
#: coal's mesh distance is computed to ~1e-6 m
MESH_TOL = 1e-6
UR10_URDF = "example-robot-data:ur_description/urdf/ur10_robot.urdf"
#: elbow folded onto the upper arm (rad)
FOLDED = np.array([0.0, -1.57, 3.1, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def ur10():
    root = example_robot_data_dir()
    urdf = root / "ur_description/urdf/ur10_robot.urdf"
    model = pin.buildModelFromUrdf(str(urdf))
    geom = K.load_collision_geometry(model, urdf, [root.parent.parent])
    capsules = _fitted(UR10_URDF, 3)  # those of problems/ur10_drilling.toml (fitted once per process)
    robot = make_robot(model, "tool0")
    return model, geom, capsules, robot, P.self_collision_pairs(robot, capsules)


def _brute_distance(p0, p1, q0, q1):
    s = np.linspace(0, 1, GRID)
    P = p0 + np.outer(s, p1 - p0)
    Q = q0 + np.outer(s, q1 - q0)
    return np.sqrt(((P[:, None, :] - Q[None, :, :]) ** 2).sum(-1).min())


def _segments(rng):
    """Random segments, then parallel, collinear, crossing and degenerate ones."""
    out = [tuple(rng.normal(size=(4, 3))) for _ in range(40)]
    for _ in range(10):
        p0, d, off = rng.normal(size=(3, 3))
        s0, s1 = rng.uniform(-2, 2, 2)
        out.append((p0, p0 + d, p0 + off + s0 * d, p0 + off + s1 * d))  # parallel
        out.append((p0, p0 + d, p0 + s0 * d, p0 + s1 * d))  # collinear
        out.append((p0, p0 + d, p0 + 0.5 * d - off, p0 + 0.5 * d + off))  # crossing
        out.append((p0, p0, p0 + off, p0 + off + d))  # a point
        out.append((p0, p0, p0 + off, p0 + off))  # two points
    return out


def _geometry_balls(geometry) -> tuple[np.ndarray, np.ndarray]:
    """Balls (centres, radii; m) whose convex hull contains a coal geometry, in its frame."""
    pieces = K._geometry_pieces(geometry)
    return np.vstack([c for c, _ in pieces]), np.concatenate([r for _, r in pieces])


@dataclass(frozen=True)
class MeshDistance:
    """Distances (m) between the collision meshes at one configuration: ``pairs`` maps each
    pair of link frames to its distance (0 when the meshes intersect); ``min_m`` is the
    smallest, between ``closest``."""

    min_m: float
    closest: tuple[str, str]
    pairs: dict[tuple[str, str], float]


def mesh_min_distance(model: pin.Model, geom_model: pin.GeometryModel, q: np.ndarray,
                      pairs: Iterable[tuple[str, str]] | None = None) -> MeshDistance:
    """Smallest distance between the meshes of ``pairs`` of link frames at the Pinocchio
    configuration ``q`` (``model.nq``), by ``pinocchio.computeDistances`` (coal).

    ``pairs`` defaults to every pair of links carried by non-adjacent joints. The tests'
    oracle of the mesh distances, independent of :func:`casadi_design.cell.cell.clearances`. Between triangle meshes, coal reports 0 for meshes that
    cross; a mesh entirely inside another without crossing triangles is not detected.
    """
    names = [model.frames[go.parentFrame].name for go in geom_model.geometryObjects]
    wanted = None if pairs is None else {frozenset(p) for p in pairs}
    checked = pin.GeometryModel(geom_model)
    checked.removeAllCollisionPairs()
    for i, gi in enumerate(geom_model.geometryObjects):
        for j in range(i + 1, geom_model.ngeoms):
            gj = geom_model.geometryObjects[j]
            if wanted is None:
                if not K.adjacent_links(model, gi.parentJoint, gj.parentJoint):
                    checked.addCollisionPair(pin.CollisionPair(i, j))
            elif frozenset((names[i], names[j])) in wanted:
                checked.addCollisionPair(pin.CollisionPair(i, j))
    if not checked.collisionPairs:
        raise ValueError("mesh_min_distance: no pair of meshes to check; give pairs of link frames "
                           f"among: {', '.join(sorted(set(names)))}")
    data = checked.createData()
    pin.computeDistances(model, model.createData(), checked, data, np.asarray(q, dtype=float))
    out: dict[tuple[str, str], float] = {}
    for k, cp in enumerate(checked.collisionPairs):
        key = (names[cp.first], names[cp.second])
        out[key] = min(out.get(key, np.inf), max(float(data.distanceResults[k].min_distance), 0.0))
    closest = min(out, key=out.get)
    return MeshDistance(out[closest], closest, out)


def test_segment_distance_matches_brute_force_and_twin():
    rng = np.random.default_rng(0)
    x = ca.SX.sym("x", 12)
    f = ca.Function("d", [x], [S.segment_distance(x[0:3], x[3:6], x[6:9], x[9:12])])
    for p0, p1, q0, q1 in _segments(rng):
        d = S.segment_distance_np(p0, p1, q0, q1)
        brute = _brute_distance(p0, p1, q0, q1)
        grid_error = (np.linalg.norm(p1 - p0) + np.linalg.norm(q1 - q0)) / (GRID - 1)
        assert d <= brute + 1e-12
        assert brute - d <= grid_error + S.SMOOTHING_M
        value = float(f(np.concatenate([p0, p1, q0, q1])))
        assert np.isfinite(value) and abs(value - d) < TWIN_TOL
        grad = np.asarray(ca.Function("g", [x], [ca.jacobian(f(x), x)])(np.concatenate([p0, p1, q0, q1])))
        assert np.all(np.isfinite(grad))


def test_capsules_are_conservative_against_meshes(ur10):
    """Where the meshes collide, some capsule row of the two links is negative."""
    model, geom, capsules, robot, pairs = ur10
    rng = np.random.default_rng(1)
    checked = pin.GeometryModel(geom)
    checked.addAllCollisionPairs()
    seen = 0
    for q in rng.uniform(robot.q_min, robot.q_max, size=(30, robot.n)):
        data = checked.createData()
        pin.computeCollisions(model, model.createData(), checked, data, q, False)
        g, labels = C.capsule_clearances(robot, capsules, q, pairs=pairs.kept)
        for k, cp in enumerate(checked.collisionPairs):
            names = {model.frames[geom.geometryObjects[i].parentFrame].name for i in (cp.first, cp.second)}
            hit = [v for v, label in zip(g, labels)
                   if {w.split("#")[0] for w in label.split()[1:4:2]} == names]
            if data.collisionResults[k].isCollision() and hit:
                seen += 1
                assert min(hit) < 0, (names, q)
    assert seen > 0  # some configurations do collide


def test_folded_elbow_is_flagged(ur10):
    model, geom, capsules, robot, pairs = ur10
    mesh = mesh_min_distance(model, geom, FOLDED, pairs=pairs.links)
    assert mesh.min_m == 0.0
    g, labels = C.capsule_clearances(robot, capsules, FOLDED, pairs=pairs.kept)
    flagged = {tuple(w.split("#")[0] for w in label.split()[1:4:2]) for v, label in zip(g, labels) if v < 0}
    assert mesh.closest in flagged
    off = P.self_collision_pairs(robot, capsules, disabled=[mesh.closest])
    assert mesh.closest not in off.links
    assert {r for k, r in off.skipped.items() if tuple(n.split("#")[0] for n in k) == mesh.closest} == {"disabled"}


def test_line_of_sight_blocked_by_a_link(ur10):
    _, _, capsules, robot, pairs = ur10
    q = np.array([0.3, -1.2, 1.5, -0.8, -1.57, 0.0])
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    tool = data.oMf[robot.model.getFrameId("tool0")]
    clear = C.LineOfSight(tool.translation + 2.0 * tool.rotation[:, 2], "tool0")
    g, labels = C.capsule_clearances(robot, capsules, q, sights=[clear], pairs=())
    assert len(g) == sum(c.frame not in ("wrist_3_link", "ee_link") for c in capsules)  # they carry tool0
    assert np.all(g > 0)
    k = next(k for k, c in enumerate(capsules) if c.frame == "upper_arm_link")
    a, b = K.capsule_ends(robot, q)(capsules[k])
    behind = C.LineOfSight(tool.translation + 2.0 * ((a + b) / 2 - tool.translation), "tool0")
    g, labels = C.capsule_clearances(robot, capsules, q, sights=[behind], pairs=())
    name = K.capsule_names(capsules)[k]
    assert g[labels.index(f"line of sight to tool0: within 0 mm of link {name}")] < 0


def test_box_row_is_below_the_exact_distance():
    rng = np.random.default_rng(2)
    model = pin.Model()
    model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "j")
    model.lowerPositionLimit[:], model.upperPositionLimit[:] = -np.pi, np.pi
    model.addFrame(pin.Frame("tip", 1, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    robot = make_robot(model, "tip")
    for _ in range(50):
        a, b = rng.normal(size=(2, 3))
        capsule = K.Capsule("j", a, b, rng.uniform(0.0, 0.3))
        box = Box(rng.normal(size=3) * 2, rng.uniform(0.1, 1.0, 3), rng.uniform(-np.pi, np.pi, 3))
        q = rng.uniform(-np.pi, np.pi, 1)
        (g,), _ = C.capsule_clearances(robot, [capsule], q, obstacles=[box], pairs=())
        wa, wb = K.capsule_ends(robot, q)(capsule)
        axis = wb - wa
        R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0, 1]), axis / np.linalg.norm(axis)).matrix()
        result = coal.DistanceResult()
        coal.distance(coal.Capsule(capsule.radius_m, np.linalg.norm(axis)), coal.Transform3s(R, (wa + wb) / 2),
                      coal.Box(*(2 * np.array(box.half_extents_m))),
                      coal.Transform3s(pin.rpy.rpyToMatrix(*box.rpy_rad), np.array(box.center_m)),
                      coal.DistanceRequest(), result)
        assert g <= result.min_distance + MESH_TOL


def test_rows_match_twin_and_finite_differences(ur10):
    _, _, capsules, robot, pairs = ur10
    obstacles = [HalfSpace((0, 0, 1), -0.2, "floor"), Box((0.8, 0.0, 0.3), (0.2, 0.3, 0.3)),
                 K.Capsule("universe", (-0.8, -0.5, 0.0), (-0.8, 0.5, 1.0), 0.1)]
    sights = [C.LineOfSight((2.0, 1.0, 1.5), "tool0")]
    q = ca.SX.sym("q", robot.n)
    rows = C.capsule_rows(robot, capsules, q, 0.01, obstacles, sights, pairs.kept)
    g = ca.vertcat(*[r[0] for r in rows])
    f = ca.Function("g", [q], [g, ca.jacobian(g, q)])
    assert all(r[1] == 0.0 and r[2] == np.inf for r in rows)
    rng = np.random.default_rng(3)
    h = 1e-6
    for qv in rng.uniform(robot.q_min, robot.q_max, size=(5, robot.n)):
        twin, labels = C.capsule_clearances(robot, capsules, qv, 0.01, obstacles, sights, pairs.kept)
        assert labels == tuple(r[3] for r in rows)
        value, jac = (np.asarray(v) for v in f(qv))
        assert np.max(np.abs(value.ravel() - twin)) < TWIN_TOL
        fd = np.column_stack([(np.asarray(f(qv + h * e)[0]) - np.asarray(f(qv - h * e)[0])).ravel() / (2 * h)
                              for e in np.eye(robot.n)])
        assert np.max(np.abs(jac - fd)) <= GRAD_RTOL * max(1.0, np.max(np.abs(jac)))


def test_capsule_refuses_a_negative_radius():
    with pytest.raises(ProblemError, match="radius_m must be finite and >= 0"):
        K.Capsule("joint_2", (0, 0, 0), (0, 0, 0), -1.0)


@pytest.fixture(scope="module")
def ur10_three(ur10):
    _, _, capsules, robot, _ = ur10
    return capsules, P.self_collision_pairs(robot, capsules, disabled=[("base_link", "upper_arm_link")])


def test_several_capsules_hold_every_triangle(ur10, ur10_three):
    """Each mesh triangle lies in one capsule of its link: the union covers the surface."""
    model, geom, _, _, _ = ur10
    capsules, _ = ur10_three
    assert len(capsules) > len({c.frame for c in capsules})  # some links got several
    for go in geom.geometryObjects:
        frame = model.frames[go.parentFrame]
        fMg = frame.placement.inverse() * go.placement
        mine = [c for c in capsules if c.frame == frame.name]
        for tri, _ in K._geometry_pieces(go.geometry):
            x = tri @ fMg.rotation.T + fMg.translation
            inside = [max(S.segment_distance_np(p, p, c.a_m, c.b_m, smoothing_m=0.0) for p in x) <= c.radius_m + 1e-12
                      for c in mine]
            assert any(inside)


@pytest.mark.slow  # 3 s: a second fit (one capsule per link); conservativeness stays in the default run
def test_several_capsules_are_conservative_and_pass_more_configurations(ur10, ur10_three):
    model, geom, _, robot, _ = ur10
    three, pairs3 = ur10_three
    one = K.capsules_from_geometry(model, geom, 1)
    pairs1 = P.self_collision_pairs(robot, one, disabled=[("base_link", "upper_arm_link")])
    rng = np.random.default_rng(9)
    passed = {1: 0, 3: 0}
    for q in rng.uniform(robot.q_min, robot.q_max, size=(60, robot.n)):
        mesh = mesh_min_distance(model, geom, q, pairs=pairs3.links)
        ends = K.capsule_ends(robot, q)
        for (fa, fb), d_mesh in mesh.pairs.items():
            d_caps = min(S.segment_distance_np(*ends(a), *ends(b)) - a.radius_m - b.radius_m
                         for a in three if a.frame == fa for b in three if b.frame == fb)
            assert d_caps <= d_mesh + MESH_TOL, (fa, fb, q)
        for k, caps, pairs in ((1, one, pairs1), (3, three, pairs3)):
            passed[k] += bool(np.all(C.capsule_clearances(robot, caps, q, pairs=pairs.kept)[0] > 0))
    assert passed[3] > passed[1]


def test_a_capsule_on_a_finger_off_the_chain_moves_with_the_hand():
    """The Panda's fingers hang on prismatic joints off the chain to its flange: their
    capsules stand at the fingers' neutral opening (as the mesh check's full configuration
    does), symbolic and numeric ends alike; they were refused, so the stock Panda URDF could
    not be put in a cell."""
    from casadi_design.cell.obstacles import Capsule
    from casadi_design.robot.robots import load_urdf

    robot = make_robot(load_urdf("example-robot-data:panda_description/urdf/panda.urdf"), "panda_link8")
    finger = Capsule("panda_leftfinger", (0.0, 0.0, 0.0), (0.0, 0.02, 0.05), 0.01)
    q = ca.SX.sym("q", robot.n)
    ends = ca.Function("ends", [q], list(K.capsule_ends_symbolic(robot, [finger], q)(finger)))
    data = robot.model.createData()
    for qk in np.random.default_rng(0).uniform(robot.q_min, robot.q_max, (5, robot.n)):
        a, b = K.capsule_ends(robot, qk)(finger)
        np.testing.assert_allclose(np.asarray(ends(qk)[0]).ravel(), a, atol=1e-12)
        np.testing.assert_allclose(np.asarray(ends(qk)[1]).ravel(), b, atol=1e-12)
        pin.framesForwardKinematics(robot.model, data, robot.full_q(qk))  # the finger on the hand
        hand = data.oMf[robot.model.getFrameId("panda_hand")]
        assert np.linalg.norm(hand.actInv(a)) < 0.1
