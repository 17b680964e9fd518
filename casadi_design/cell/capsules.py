"""Capsules around a robot's links: fitted around a URDF's collision meshes so that every vertex is
inside (a capsule distance is then a lower bound of the mesh distance), or given as numbers for a
DH robot; where each capsule is at a configuration q (its carrying joint and the segment ends,
in CasADi and numpy).
"""

from __future__ import annotations

import itertools
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import casadi as ca
import coal
import numpy as np
import pinocchio as pin
import scipy

from ..errors import ProblemError
from ..robot.robots import Robot, frame_id
from ..robot.symbolic import compose, joint_axis, rotation_about
from ..runtime.cache import digest, stored
from ..runtime.threads import blas_kernels
from .obstacles import Capsule


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
    # the volume sees only maxima and minima over the balls: each distinct ball once (a mesh
    # vertex is in about six triangles), the first axes from all of them
    X, rho = np.hsplit(np.unique(np.column_stack([X, rho]), axis=0), [3])
    X, rho = np.ascontiguousarray(X), rho.ravel()

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
        frame = model.frames[frame_id(model, name)]
        return frame.parentJoint, frame.placement
    if model.existJointName(name):
        return model.getJointId(name), pin.SE3.Identity()
    names = sorted({f.name for f in model.frames if f.name != "universe"} | set(model.names[1:]))
    raise ProblemError(f"{where}: no frame or joint '{name}'; the robot has: {', '.join(names)}")


def _symbolic_joint_placement(robot: Robot, q: ca.SX, jid: int, memo: dict) -> tuple[ca.SX, ca.SX]:
    """World placement ``(R, p)`` of joint ``jid`` at chain configuration ``q`` (joints off the
    chain at their neutral value, 0), nominal kinematics as in :mod:`casadi_design.robot.symbolic`."""
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
        # a joint off the chain (a gripper's finger) stands at its neutral value: no motion
        memo[jid] = (R, p)
    return memo[jid]


def moved_by_chain(robot: Robot, jid: int) -> bool:
    return any(j in robot.joint_ids for j in robot.model.supports[jid])


def adjacent_links(model: pin.Model, i: int, j: int) -> bool:
    return i == j or model.parents[i] == j or model.parents[j] == i


def capsule_ends_symbolic(robot: Robot, capsules: Sequence[Capsule], q: ca.SX) -> Callable:
    memo: dict = {}

    def ends(capsule: Capsule):
        jid, jMc = carrier(robot.model, capsule.frame)
        R, p = _symbolic_joint_placement(robot, q, jid, memo)
        return tuple(p + R @ ca.DM(jMc.act(np.array(x))) for x in (capsule.a_m, capsule.b_m))

    return ends


def capsule_ends(robot: Robot, q: np.ndarray) -> Callable:
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
