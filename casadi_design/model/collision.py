"""Collision rules of one configuration: links as capsules, obstacles, lines of sight.

Each link is approximated by capsules: a segment ``[a, b]`` fixed in the link's frame and a
radius ``r`` (m), the set of points within ``r`` of the segment. Two capsules are apart by at
least ``c`` (the clearance, m) when

    dist([a1, b1], [a2, b2]) - r1 - r2 - c >= 0,

with ``dist`` the segment-segment distance (:func:`segment_distance`). The rows of
:func:`capsule_rows` are of that form, ``g(q) >= 0`` (m), for

* self-collision: every pair of capsules that can meet (:func:`self_collision_pairs`);
* obstacles fixed in the world, each kind giving its rows (:mod:`casadi_design.model.obstacles`:
  half-spaces such as the floor, boxes, capsules);
* lines of sight: the beam from a tracker to a reflector carried by the robot against every
  capsule, except those of the link carrying the reflector (the beam ends on that link).

The capsules of a URDF robot are fitted around its collision meshes so that every vertex is
inside (:func:`capsules_from_geometry`); a capsule distance is then a lower bound of the mesh
distance, which :func:`casadi_design.model.cell.clearances` computes with Pinocchio and coal to check
a plan.
Robots without collision geometry (DH tables) take capsules given as numbers
(``[cell].capsules``). :func:`capsule_clearances` is the numpy twin of the rows.
"""

from __future__ import annotations

import itertools
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import coal
import numpy as np
import pinocchio as pin
import scipy

from ..runtime.cache import digest, stored
from ..errors import ProblemError
from .obstacles import Capsule, Obstacle, vector3
from .robots import Robot
from .symbolic import compose, joint_axis, rotation_about
from ..runtime.threads import blas_kernels

#: ``delta`` of the smoothed distance ``sqrt(D^2 + delta^2) - delta`` (m): differentiable where
#: the segments touch, below the exact distance by at most ``delta``.
SMOOTHING_M = 1e-6
#: Segments are treated as parallel when ``sin^2`` of their angle is below this.
PARALLEL_TOL = 1e-10
#: Configurations sampled by :func:`self_collision_pairs` to find the pairs that can separate.
PAIR_SAMPLES = 200


@dataclass(frozen=True)
class LineOfSight:
    """Beam from a tracker at ``tracker_m`` (world, m) to a reflector at ``point_m`` in
    ``frame`` (m).

    ``excluded`` names the capsule frames the beam may touch; by default the capsules carried
    by the same joint as ``frame`` (the reflector sits on, or inside, that link's capsule).
    ``spread_m``: the beam stands for every beam from the tracker to a point within this
    distance of ``point_m`` (several reflectors around their centroid): each such beam is
    within ``spread_m`` of this one, point for point, so the rows keep this beam
    ``spread_m`` further from the capsules.
    """

    tracker_m: tuple[float, float, float]
    frame: str
    point_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    excluded: tuple[str, ...] | None = None
    spread_m: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "tracker_m", vector3(self.tracker_m, "line of sight: tracker_m"))
        object.__setattr__(self, "point_m", vector3(self.point_m, f"line of sight to '{self.frame}': point_m"))


# ---------------------------------------------------------------------------------------------
# segment-segment distance


def _clamp01(x, fmin, fmax):
    return fmin(fmax(x, 0.0), 1.0)


def _segment_distance_sq(p0, p1, q0, q1, ops) -> object:
    """``D^2 = min_{s, t in [0, 1]} |p0 + s d1 - q0 - t d2|^2`` (m^2), ``d1 = p1 - p0``,
    ``d2 = q1 - q0``.

    The minimum of a convex quadratic over the square: the stationary point when it lies
    inside and the segments are not parallel, otherwise the smallest of the four
    endpoint-to-segment distances (the minima on the square's sides). Written once for
    CasADi and numpy (``ops``: dot, fmin, fmax, if_else).
    """
    dot, fmin, fmax, if_else = ops.dot, ops.fmin, ops.fmax, ops.if_else
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, b = dot(d1, d1), dot(d2, d2), dot(d1, d2)
    c, f = dot(d1, r), dot(d2, r)

    def to_segment(p, s0, d, dd):
        t = _clamp01(dot(p - s0, d) / fmax(dd, 1e-300), fmin, fmax)
        w = s0 + t * d - p
        return dot(w, w)

    sides = fmin(fmin(to_segment(p0, q0, d2, e), to_segment(p1, q0, d2, e)),
                 fmin(to_segment(q0, p0, d1, a), to_segment(q1, p0, d1, a)))
    denom = a * e - b * b
    crossing = denom > PARALLEL_TOL * a * e
    safe = if_else(crossing, denom, 1.0)
    s, t = (b * f - c * e) / safe, (a * f - b * c) / safe
    w = r + s * d1 - t * d2
    inside = ops.logical_and(crossing, ops.logical_and(ops.logical_and(s > 0, s < 1),
                                                       ops.logical_and(t > 0, t < 1)))
    return if_else(inside, dot(w, w), sides)


_CA = SimpleNamespace(dot=ca.dot, fmin=ca.fmin, fmax=ca.fmax, sqrt=ca.sqrt, if_else=ca.if_else,
                      logical_and=ca.logic_and)
_NP = SimpleNamespace(dot=np.dot, fmin=np.minimum, fmax=np.maximum, sqrt=np.sqrt,
                      if_else=lambda c, x, y: x if c else y, logical_and=lambda x, y: bool(x and y))


def segment_distance(p0, p1, q0, q1, smoothing_m: float = SMOOTHING_M) -> ca.SX:
    """Distance (m) between the segments ``[p0, p1]`` and ``[q0, q1]`` (CasADi, 3-vectors).

    Returns ``sqrt(D^2 + delta^2) - delta`` with ``D`` the exact distance and
    ``delta = smoothing_m``: within ``delta`` below ``D``, defined everywhere.

    Smoothness: ``D^2`` is the minimum over ``(s, t)`` of a convex quadratic; where the
    minimiser is unique its gradient is that of the quadratic at the minimiser (Danskin), and
    the branches (interior point, clamped sides) meet with equal values and gradients. ``D^2``
    is therefore continuously differentiable except for parallel segments whose projections
    overlap (a whole set of closest pairs), where it is continuous but has a kink; near that
    set (``sin^2`` of the angle ~ ``PARALLEL_TOL``) the gradient is computed through an
    ill-conditioned stationary point and loses digits. Degenerate segments (points) are
    exact. No branch divides by zero, so no NaN is produced.
    """
    p0, p1, q0, q1 = (ca.SX(v) if not isinstance(v, ca.SX) else v for v in (p0, p1, q0, q1))
    D2 = _segment_distance_sq(p0, p1, q0, q1, _CA)
    return ca.sqrt(D2 + smoothing_m**2) - smoothing_m


def segment_distance_np(p0, p1, q0, q1, smoothing_m: float = SMOOTHING_M) -> float:
    """Numpy twin of :func:`segment_distance` (same formula, m)."""
    p0, p1, q0, q1 = (np.asarray(v, dtype=float) for v in (p0, p1, q0, q1))
    D2 = max(float(_segment_distance_sq(p0, p1, q0, q1, _NP)), 0.0)
    return float(np.sqrt(D2 + smoothing_m**2) - smoothing_m)


# ---------------------------------------------------------------------------------------------
# capsules from geometry


def fit_capsule(frame: str, points_m: np.ndarray, inflation_m: np.ndarray | None = None) -> Capsule:
    """Smallest-volume capsule found that contains balls ``(points_m[i], inflation_m[i])``.

    Every ball is inside, by construction: for an axis ``u`` through a centre ``c`` (the 3
    principal axes of the points, then refined by Nelder-Mead on the volume
    ``pi r^2 L + 4/3 pi r^3``), with axial ``t_i`` and radial ``d_i`` coordinates of the
    points, ``r = max_i (d_i + rho_i)`` and the ends ``t_a = min_i (t_i + sqrt((r - rho_i)^2 -
    d_i^2))``, ``t_b = max_i (t_i - sqrt((r - rho_i)^2 - d_i^2))``. When ``t_a > t_b`` the
    capsule is a sphere around the middle. A capsule holding the vertices of a mesh holds
    the mesh (it is convex).

    Parameters
    ----------
    points_m : ndarray, shape (k, 3), m
    inflation_m : ndarray, shape (k,), m
        Radius of a ball around each point (0 for mesh vertices).
    """
    X = np.asarray(points_m, dtype=float).reshape(-1, 3)
    rho = np.zeros(len(X)) if inflation_m is None else np.asarray(inflation_m, dtype=float)
    mean = X.mean(axis=0)
    _, _, Vt = np.linalg.svd(X - mean, full_matrices=False)

    def shape(x: np.ndarray, basis: np.ndarray):
        # x: tilt of the axis basis[0] about basis[1], basis[2] (rad), centre offset (m)
        Rb = pin.exp3(x[0] * basis[1] + x[1] * basis[2])
        u, v, w = Rb @ basis[0], Rb @ basis[1], Rb @ basis[2]
        c = mean + x[2] * v + x[3] * w
        Y = X - c
        t = Y @ u
        d = np.linalg.norm(Y - np.outer(t, u), axis=1)
        r = float(np.max(d + rho))
        reach = np.sqrt(np.maximum((r - rho) ** 2 - d**2, 0.0))
        ta, tb = float(np.min(t + reach)), float(np.max(t - reach))
        if ta > tb:
            centre = c + u * (ta + tb) / 2
            r = float(np.max(np.linalg.norm(X - centre, axis=1) + rho))
            return np.pi * 4 / 3 * r**3, centre, centre, r
        return np.pi * r**2 * (tb - ta + 4 * r / 3), c + ta * u, c + tb * u, r

    # imported here: a fit runs only when the capsules are not on disk, and at the top it cost
    # every process 0.15 to 0.27 s of start-up
    from scipy.optimize import minimize
    best = None
    for k in range(3):
        basis = np.roll(Vt, -k, axis=0)
        x = minimize(lambda x: shape(x, basis)[0], np.zeros(4), method="Nelder-Mead",
                     options={"xatol": 1e-6, "fatol": 1e-12, "maxiter": 2000}).x
        fit = shape(x, basis)
        if best is None or fit[0] < best[0]:
            best = fit
    _, a, b, r = best
    return Capsule(frame, a, b, r)


def _geometry_pieces(geometry) -> list[tuple[np.ndarray, np.ndarray]]:
    """Convex pieces covering a coal geometry, in its frame: each as balls (centres k x 3,
    radii k; m) whose convex hull contains the piece. A mesh gives one piece per triangle;
    a primitive, or a convex mesh, one piece."""
    if isinstance(geometry, coal.BVHModelBase):
        V = np.asarray(geometry.vertices(), dtype=float)
        T = np.array([[t[0], t[1], t[2]] for t in map(geometry.tri_indices, range(geometry.num_tris))])
        return [(V[t], np.zeros(3)) for t in T]
    if isinstance(geometry, coal.ConvexBase):
        P = np.asarray(geometry.points(), dtype=float)
        return [(P, np.zeros(len(P)))]
    if isinstance(geometry, coal.Box):
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        return [(corners * np.asarray(geometry.halfSide), np.zeros(8))]
    if isinstance(geometry, coal.Sphere):
        return [(np.zeros((1, 3)), np.array([geometry.radius]))]
    if isinstance(geometry, (coal.Capsule, coal.Cylinder)):
        h = geometry.halfLength
        return [(np.array([[0, 0, -h], [0, 0, h]], dtype=float), np.full(2, geometry.radius))]
    raise ProblemError(f"collision geometry of type {type(geometry).__name__} is not supported; "
                       "use meshes, convex meshes, boxes, spheres, capsules or cylinders")


def _rough_volume(X: np.ndarray, rho: np.ndarray) -> float:
    """Volume (m^3) of the capsule of :func:`fit_capsule` on the principal axis alone (no
    refinement): a quick score of a partition."""
    c = X.mean(axis=0)
    u = np.linalg.svd(X - c, full_matrices=False)[2][0]
    t = (X - c) @ u
    d = np.linalg.norm((X - c) - np.outer(t, u), axis=1)
    r = float(np.max(d + rho))
    reach = np.sqrt(np.maximum((r - rho) ** 2 - d**2, 0.0))
    length = max(float(np.max(t - reach) - np.min(t + reach)), 0.0)
    return np.pi * r**2 * (length + 4 * r / 3)


#: A link gets one more capsule only when it cuts the total volume by this fraction.
SPLIT_GAIN = 0.10
#: Cut positions tried along a link's principal axis: these quantiles of its pieces.
CUT_QUANTILES = np.linspace(0.1, 0.9, 9)


def _partition(points: np.ndarray, radii: np.ndarray, piece: np.ndarray, most: int) -> list[np.ndarray]:
    """Groups of pieces (masks over the points) whose capsules have the least rough volume.

    The pieces are cut into slabs along the points' principal axis by their centroids, at
    ``CUT_QUANTILES``; from one slab up to ``most``, a further cut is kept only when it
    reduces the total volume by ``SPLIT_GAIN``.
    """
    n = int(piece.max()) + 1
    count = np.bincount(piece, minlength=n)
    centroid = np.array([np.bincount(piece, points[:, a], n) for a in range(3)]).T / count[:, None]
    c = points.mean(axis=0)
    u = np.linalg.svd(points - c, full_matrices=False)[2][0]
    t = (centroid - c) @ u
    cuts = np.unique(np.quantile(t, CUT_QUANTILES))

    def groups(chosen) -> list[np.ndarray]:
        slab = np.searchsorted(np.asarray(chosen), t)[piece]
        return [m for m in (slab == k for k in range(len(chosen) + 1)) if m.any()]

    def volume(chosen) -> float:
        return sum(_rough_volume(points[m], radii[m]) for m in groups(chosen))

    best, best_volume = (), volume(())
    for k in range(1, most):
        options = list(itertools.combinations(cuts, k))
        if not options:
            break
        chosen = min(options, key=volume)
        v = volume(chosen)
        if v > (1 - SPLIT_GAIN) * best_volume:
            break
        best, best_volume = chosen, v
    return groups(best)


def capsules_from_geometry(model: pin.Model, geom_model: pin.GeometryModel, per_link: int = 1) -> tuple[Capsule, ...]:
    """Up to ``per_link`` capsules per link (frame) carrying geometry objects, in the link's
    frame; links in the model's frame order.

    The link's convex pieces (mesh triangles, primitives: :func:`_geometry_pieces`) are
    grouped into slabs along the link's principal axis (:func:`_partition`), and a capsule is
    fitted around each group (:func:`fit_capsule`). Every piece lies inside one capsule
    (convexity), so the link's surface lies inside the union of its capsules and the smallest
    capsule distance between two links is never larger than the mesh distance.

    The fit takes seconds (Nelder-Mead on each capsule); its result is kept on disk
    (:func:`casadi_design.runtime.cache.stored`), named by the pieces' bytes, ``per_link``, the code of
    this module and of :class:`Capsule`'s, the numpy and scipy versions and the BLAS kernels
    (the fit rounds differently with other kernels: capsules fitted by a library caller on its
    machine's own kernels differ in the last bits from the command's, and so could the plans
    made with them): a later run reads the same capsules.
    """
    parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for go in geom_model.geometryObjects:
        # geometry placement is relative to the joint; express it in the link frame
        fMg = model.frames[go.parentFrame].placement.inverse() * go.placement
        parts.setdefault(go.parentFrame, []).extend(
            (c @ fMg.rotation.T + fMg.translation, r) for c, r in _geometry_pieces(go.geometry))
    links = [(model.frames[fid].name, pieces) for fid, pieces in sorted(parts.items())]

    def fit() -> tuple[Capsule, ...]:
        out = []
        for name, pieces in links:
            points = np.vstack([c for c, _ in pieces])
            radii = np.concatenate([r for _, r in pieces])
            piece = np.repeat(np.arange(len(pieces)), [len(r) for _, r in pieces])
            for mask in _partition(points, radii, piece, per_link):
                out.append(fit_capsule(name, points[mask], radii[mask]))
        return tuple(out)

    code = (Path(__file__).read_bytes(), Path(sys.modules[Capsule.__module__].__file__).read_bytes())
    key = digest(*code, np.__version__.encode(), scipy.__version__.encode(), blas_kernels().encode(),
                 str(per_link).encode(), *(part for name, pieces in links for c, r in pieces
                                          for part in (name.encode(), np.ascontiguousarray(c).tobytes(),
                                                       np.ascontiguousarray(r).tobytes())))
    return stored("capsules", key, fit)


def load_collision_geometry(model: pin.Model, urdf_path, package_dirs: Sequence[str] = ()) -> pin.GeometryModel:
    """The collision geometry of a URDF (meshes read by Pinocchio and coal, scales applied)."""
    try:
        return pin.buildGeomFromUrdf(model, str(urdf_path), pin.GeometryType.COLLISION,
                                     package_dirs=[str(d) for d in package_dirs])
    except (RuntimeError, ValueError) as exc:
        raise ProblemError(f"{urdf_path}: cannot read the collision geometry ({exc}); check the "
                           "mesh paths and package_dirs") from None


# ---------------------------------------------------------------------------------------------
# kinematics of the capsules


def carrier(model: pin.Model, name: str, where: str = "[cell].capsules") -> tuple[int, pin.SE3]:
    """The joint carrying frame or joint ``name`` and the placement of ``name`` in it; an
    unknown name is refused naming the field ``where``."""
    if model.existFrame(name):
        frame = model.frames[model.getFrameId(name)]
        return frame.parentJoint, frame.placement
    if model.existJointName(name):
        return model.getJointId(name), pin.SE3.Identity()
    names = sorted({f.name for f in model.frames if f.name != "universe"} | set(model.names[1:]))
    raise ProblemError(f"{where}: no frame or joint '{name}'; the robot has: {', '.join(names)}")


def _symbolic_joint_placement(robot: Robot, q: ca.SX, jid: int, memo: dict) -> tuple[ca.SX, ca.SX]:
    """World placement ``(R, p)`` of joint ``jid`` at chain configuration ``q`` (joints off the
    chain at their neutral value, 0), nominal kinematics as in :mod:`casadi_design.model.symbolic`."""
    if jid == 0:
        return ca.SX.eye(3), ca.SX.zeros(3)
    if jid not in memo:
        model = robot.model
        R, p = _symbolic_joint_placement(robot, q, model.parents[jid], memo)
        pMj = model.jointPlacements[jid]
        R, p = compose(R, p, ca.SX(pMj.rotation), ca.SX(pMj.translation))
        if jid in robot.joint_ids:
            axis, kind = joint_axis(model.joints[jid])
            qk = q[robot.joint_ids.index(jid)]
            R, p = (R @ rotation_about(axis, qk), p) if kind == "R" else (R, p + R @ (ca.SX(axis) * qk))
        elif model.joints[jid].nq:
            raise ProblemError(f"capsules on joint '{model.names[jid]}' off the chain to '{robot.frame}' "
                               "are not supported; attach them to links of the chain")
        memo[jid] = (R, p)
    return memo[jid]


def _moves(robot: Robot, jid: int) -> bool:
    return any(j in robot.joint_ids for j in robot.model.supports[jid])


def _adjacent(model: pin.Model, i: int, j: int) -> bool:
    return i == j or model.parents[i] == j or model.parents[j] == i


def _ends_symbolic(robot: Robot, capsules: Sequence[Capsule], q: ca.SX) -> Callable:
    memo: dict = {}

    def ends(capsule: Capsule):
        jid, jMc = carrier(robot.model, capsule.frame)
        R, p = _symbolic_joint_placement(robot, q, jid, memo)
        return tuple(p + R @ ca.DM(jMc.act(np.array(x))) for x in (capsule.a_m, capsule.b_m))

    return ends


def _ends_numeric(robot: Robot, q: np.ndarray) -> Callable:
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, robot.full_q(q))

    def ends(capsule: Capsule):
        jid, jMc = carrier(robot.model, capsule.frame)
        oMc = data.oMi[jid] * jMc
        return tuple(oMc.act(np.array(x)) for x in (capsule.a_m, capsule.b_m))

    return ends


# ---------------------------------------------------------------------------------------------
# pairs and rows


def capsule_names(capsules: Sequence[Capsule]) -> tuple[str, ...]:
    """A name per capsule: its frame, with ``#k`` (k = 1, 2, ...) when a frame has several."""
    count = {c.frame: 0 for c in capsules}
    for c in capsules:
        count[c.frame] += 1
    seen = dict.fromkeys(count, 0)
    out = []
    for c in capsules:
        seen[c.frame] += 1
        out.append(c.frame if count[c.frame] == 1 else f"{c.frame}#{seen[c.frame]}")
    return tuple(out)


@dataclass(frozen=True)
class PairSelection:
    """Self-collision pairs: ``kept`` (indices into the capsules) become rows; ``skipped``
    maps each other pair of capsule names to the reason; ``links`` are the pairs of link
    frames of ``kept``."""

    kept: tuple[tuple[int, int], ...]
    skipped: dict[tuple[str, str], str]
    links: tuple[tuple[str, str], ...]


def self_collision_pairs(robot: Robot, capsules: Sequence[Capsule], clearance_m: float = 0.0,
                         disabled: Iterable[tuple[str, str]] = (), samples: int = PAIR_SAMPLES,
                         seed: int = 0) -> PairSelection:
    """The capsule pairs that can meet and that the capsules can keep apart.

    A pair (capsules on joints i and j) is a candidate unless the links are adjacent (same
    joint, or one joint the parent of the other: they touch at the joint) or no joint of the
    chain moves one relative to the other. A candidate is kept when its row
    ``dist - r1 - r2 - clearance`` is positive in at least one of ``samples`` configurations
    drawn uniformly within the joint limits (seeded); otherwise the capsules overlap wherever
    the robot goes (links whose meshes stay close but whose capsules cannot separate), so
    the row would make every plan infeasible: the pair is skipped, with the reason. Pairs whose sampled distance is constant (within 1e-9 m) and positive are skipped
    as never meeting. Pairs of link frames in ``disabled`` (as an SRDF's
    ``disable_collisions``: links that the user knows never meet) are skipped.
    """
    model = robot.model
    jids = [carrier(model, c.frame)[0] for c in capsules]
    rng = np.random.default_rng(seed)
    Q = rng.uniform(robot.q_min, robot.q_max, size=(samples, robot.n))
    ends = [_ends_numeric(robot, q) for q in Q]
    kept, skipped, names = [], {}, capsule_names(capsules)
    off = [set(p) for p in disabled]
    for i, ci in enumerate(capsules):
        for j in range(i + 1, len(capsules)):
            cj, key = capsules[j], (names[i], names[j])
            path = set(model.supports[jids[i]]) ^ set(model.supports[jids[j]])
            if {ci.frame, cj.frame} in off:
                skipped[key] = "disabled"
                continue
            if _adjacent(model, jids[i], jids[j]):
                skipped[key] = "adjacent links"
                continue
            if not path & set(robot.joint_ids):
                skipped[key] = "no joint of the chain moves one relative to the other"
                continue
            g = np.array([segment_distance_np(*e(ci), *e(cj)) for e in ends]) - ci.radius_m - cj.radius_m - clearance_m
            if np.all(g <= 0):
                skipped[key] = (f"capsules overlap in all {samples} sampled configurations "
                                f"(largest clearance {g.max() * 1e3:.1f} mm)")
            elif np.ptp(g) < 1e-9:
                skipped[key] = "constant distance, positive"
            else:
                kept.append((i, j))
    links = tuple(dict.fromkeys((capsules[i].frame, capsules[j].frame) for i, j in kept))
    return PairSelection(tuple(kept), skipped, links)


def _near_all(robot: Robot, capsules: Sequence[Capsule], obstacles: Sequence[Obstacle]) -> list[tuple[int, int]]:
    """Every (moving capsule, obstacle) pair, obstacle by obstacle."""
    moving = [k for k, c in enumerate(capsules) if _moves(robot, carrier(robot.model, c.frame)[0])]
    return [(k, o) for o in range(len(obstacles)) for k in moving]


def obstacle_pairs(robot: Robot, capsules: Sequence[Capsule], obstacles: Sequence[Obstacle],
                   clearance_m: float = 0.0, samples: int = PAIR_SAMPLES,
                   seed: int = 0) -> tuple[tuple[tuple[int, int], ...], dict[tuple[str, str], str]]:
    """The (moving capsule, obstacle) pairs that can meet and that the capsules can keep apart.

    As :func:`self_collision_pairs`, over ``samples`` seeded configurations within the joint
    limits: a pair whose row is the same in every sample (a link that only turns about a
    vertical axis over the floor) is skipped as "constant distance" when positive; a pair
    whose row is negative in every sample (the housing at the shoulder of a link always
    within the clearance of the floor the robot stands on) is skipped with that reason.
    Returns the kept pairs and the reasons for the others, keyed by (capsule, obstacle) names.
    """
    near = _near_all(robot, capsules, obstacles)
    rng = np.random.default_rng(seed)
    rows = [capsule_clearances(robot, capsules, q, clearance_m, obstacles, (), (), near)
            for q in rng.uniform(robot.q_min, robot.q_max, size=(samples, robot.n))]
    labels = rows[0][1]
    G = np.array([g for g, _ in rows])
    # a pair's rows share its label (a half-space gives two); its clearance is their minimum
    groups = list(dict.fromkeys(labels))
    G = np.column_stack([G[:, [i for i, lb in enumerate(labels) if lb == label]].min(axis=1) for label in groups])
    names, kept, skipped = capsule_names(capsules), [], {}
    for (k, o), g in zip(near, G.T):
        key = (names[k], obstacles[o].label)
        if np.ptp(g) < 1e-9 and g[0] > 0:
            skipped[key] = "constant distance, positive"
        elif np.all(g <= 0):
            skipped[key] = (f"closer than the clearance in all {samples} sampled configurations "
                            f"(largest clearance {g.max() * 1e3:.1f} mm)")
        else:
            kept.append((k, o))
    return tuple(kept), skipped


def _rows(robot: Robot, capsules: Sequence[Capsule], ends: Callable, ops, dist: Callable,
          clearance_m: float, obstacles: Sequence[Obstacle], sights: Sequence[LineOfSight],
          pairs: Sequence[tuple[int, int]], near: Sequence[tuple[int, int]] | None = None) -> list[tuple[object, str]]:
    """Rows ``(g, label)`` with ``g >= 0`` required (m), for CasADi or numpy (``ops``);
    ``near``: the (capsule, obstacle) index pairs constrained (None: :func:`_near_all`)."""
    model, names = robot.model, capsule_names(capsules)
    world = [ends(c) for c in capsules]
    jids = [carrier(model, c.frame)[0] for c in capsules]
    mm = f"{clearance_m * 1e3:g} mm"
    out = []
    for i, j in pairs:
        g = dist(*world[i], *world[j]) - capsules[i].radius_m - capsules[j].radius_m - clearance_m
        out.append((g, f"links {names[i]} and {names[j]} closer than {mm}"))

    def place(segment: Capsule):
        """World ends of a segment of an obstacle (m); it must not move with the robot."""
        if _moves(robot, carrier(model, segment.frame)[0]):
            raise ProblemError(f"obstacle capsule on '{segment.frame}': it moves with the robot; "
                               "give obstacles in a fixed frame such as 'universe'")
        return ends(segment)

    for k, o in (_near_all(robot, capsules, obstacles) if near is None else near):
        (a, b), obstacle = world[k], obstacles[o]
        out += [(g - clearance_m, f"link {names[k]} closer than {mm} to {obstacle.label}")
                for g in obstacle.rows(a, b, capsules[k].radius_m, ops, dist, place)]
    for sight in sights:
        jid, _ = carrier(model, sight.frame, "line of sight")
        excluded = (set(sight.excluded) if sight.excluded is not None
                    else {c.frame for c, j in zip(capsules, jids) if j == jid})
        reflector = ends(Capsule(sight.frame, sight.point_m, sight.point_m, 0.0))[0]
        tracker = np.array(sight.tracker_m)
        for k, c in enumerate(capsules):
            if c.frame not in excluded:
                g = dist(tracker, reflector, *world[k]) - c.radius_m - sight.spread_m - clearance_m
                out.append((g, f"line of sight to {sight.frame}: within {mm} of link {names[k]}"))
    return out


@dataclass(frozen=True, eq=False)
class PointRows:
    """Collision rows as functions of world points: the form in which the NLP holds only the
    rows that can bind (:mod:`casadi_design.optimisation.reduced`).

    ``W`` (CasADi SX, 3K) stands for K world points (m): both ends of every capsule moving with
    q, and each line of sight's reflector; ``points`` (SX of q, 3K) gives them at q. Row r is
    ``G_r(W) >= 0`` (m) with label ``labels[r]``; it depends on at most 4 of the points (two
    segments), the rest of its data (obstacles, tracker, radii, clearance) being constants.
    """

    W: ca.SX
    points: ca.SX
    G: tuple[ca.SX, ...]
    labels: tuple[str, ...]

    def of_q(self) -> list[ca.SX]:
        """The rows as SX of q: ``G_r(points(q))``."""
        return ca.substitute(list(self.G), [self.W], [self.points]) if self.G else []


def capsule_point_rows(robot: Robot, capsules: Sequence[Capsule], q: ca.SX, clearance_m: float = 0.0,
                       obstacles: Sequence[Obstacle] = (), sights: Sequence[LineOfSight] = (),
                       pairs: Sequence[tuple[int, int]] | None = None,
                       near: Sequence[tuple[int, int]] | None = None) -> PointRows:
    """The rows of :func:`capsule_rows` as functions of the world points (:class:`PointRows`)."""
    if pairs is None:
        pairs = self_collision_pairs(robot, capsules, clearance_m).kept
    placed = _ends_symbolic(robot, capsules, q)
    symbols, points = [], []

    def ends(capsule: Capsule):
        if not _moves(robot, carrier(robot.model, capsule.frame)[0]):
            return placed(capsule)  # constants
        out = []
        for p in placed(capsule):
            symbols.append(ca.SX.sym(f"w{len(symbols)}", 3))
            points.append(p)
            out.append(symbols[-1])
        return tuple(out)

    rows = _rows(robot, capsules, ends, _CA, segment_distance, clearance_m, obstacles, sights, pairs, near)
    return PointRows(ca.vertcat(*symbols) if symbols else ca.SX(0, 1),
                     ca.vertcat(*points) if points else ca.SX(0, 1),
                     tuple(g for g, _ in rows), tuple(label for _, label in rows))


def capsule_rows(robot: Robot, capsules: Sequence[Capsule], q: ca.SX, clearance_m: float = 0.0,
                 obstacles: Sequence[Obstacle] = (), sights: Sequence[LineOfSight] = (),
                 pairs: Sequence[tuple[int, int]] | None = None,
                 near: Sequence[tuple[int, int]] | None = None) -> list[tuple[ca.SX, float, float, str]]:
    """Collision rows of configuration ``q`` (CasADi SX, n): ``(g(q), 0, inf, label)``, each
    ``g >= 0`` (m), in the format of :func:`casadi_design.plan.rules.pose_constraints`' rows.

    * self-collision, for ``pairs`` of capsule indices (default :func:`self_collision_pairs`):
      ``dist(s_i, s_j) - r_i - r_j - clearance_m``;
    * for each (capsule, obstacle) index pair of ``near`` (default: every capsule moving with
      ``q`` and every obstacle; :func:`obstacle_pairs` selects those that can meet): each row
      of the obstacle (:meth:`casadi_design.model.obstacles.Obstacle.rows`, a lower bound of the
      distance between the capsule and the obstacle) ``- clearance_m``;
    * for each line of sight, every capsule not excluded (see :class:`LineOfSight`):
      ``dist([tracker, reflector(q)], s_k) - r_k - spread - clearance_m``.

    ``dist`` is :func:`segment_distance` (smoothed, within ``SMOOTHING_M`` below the exact
    distance). The rows are those of :func:`capsule_point_rows` at the points of q.
    """
    rows = capsule_point_rows(robot, capsules, q, clearance_m, obstacles, sights, pairs, near)
    return [(g, 0.0, np.inf, label) for g, label in zip(rows.of_q(), rows.labels)]


def capsule_clearances(robot: Robot, capsules: Sequence[Capsule], q: np.ndarray, clearance_m: float = 0.0,
                       obstacles: Sequence[Obstacle] = (), sights: Sequence[LineOfSight] = (),
                       pairs: Sequence[tuple[int, int]] | None = None,
                       near: Sequence[tuple[int, int]] | None = None) -> tuple[np.ndarray, tuple[str, ...]]:
    """Numpy twin of :func:`capsule_rows` at ``q`` (ndarray, n): the rows' values ``g`` (m,
    negative: too close) and labels, in the same order; placements by Pinocchio."""
    if pairs is None:
        pairs = self_collision_pairs(robot, capsules, clearance_m).kept
    rows = _rows(robot, capsules, _ends_numeric(robot, np.asarray(q, dtype=float)), _NP, segment_distance_np,
                 clearance_m, obstacles, sights, pairs, near)
    return np.array([float(g) for g, _ in rows]), tuple(label for _, label in rows)
