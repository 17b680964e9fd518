"""Obstacle kinds of a cell: one class per kind, with all the package does with it.

A kind (the ``kind`` of an entry of ``[cell].obstacles``) is a frozen dataclass subclassing
:class:`Obstacle` with that ``kind``; the class

* reads its entry of the problem file (:meth:`Obstacle.parse`, the keys :attr:`Obstacle.KEYS`),
* gives the rows that keep a capsule of the robot off it (:meth:`Obstacle.rows`, m),
* gives its coal shape for the check of a plan on the real geometry
  (:meth:`Obstacle.coal_geometry`),
* draws itself in the figure of the poses (:meth:`Obstacle.draw`, mm).

Defining the class registers the kind (:data:`OBSTACLE_KINDS`); a class that leaves one of
these out is refused when defined. The reading layer (:mod:`casadi_design.problem_file.read`) imports
this module: it imports numpy only, coal where a shape is made, and takes CasADi or numpy
operations as an argument of :meth:`Obstacle.rows`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from ..errors import ProblemError

if TYPE_CHECKING:
    import coal
    from matplotlib.axes import Axes


class FieldReader(Protocol):
    """What a shape's :meth:`Obstacle.parse` reads its table with: the problem file's field
    reader (:mod:`casadi_design.problem_file.read`), whose messages name the file and the field."""

    def array(self, key: str, shape: tuple, default: Any = ..., hint: str = "") -> np.ndarray | Any: ...

    def number(self, key: str, default: Any = ..., hint: str = "", positive: bool = False,
               nonnegative: bool = False) -> float: ...

    def error(self, what: str, hint: str, key: str | None = None) -> ProblemError: ...

#: The obstacle classes by their ``kind`` in a problem file, in the order they were defined.
OBSTACLE_KINDS: dict[str, type[Obstacle]] = {}
#: Colour of the obstacles in figures (grey level).
OBSTACLE_COLOUR = "0.35"


def vector3(value, name: str) -> tuple[float, float, float]:
    """``value`` as 3 finite floats; else a :class:`ProblemError` naming the field ``name``."""
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ProblemError(f"{name}: needs 3 finite numbers; got {value!r}")
    return tuple(float(x) for x in v)


class Obstacle(ABC):
    """A body fixed in the world that every moving capsule of the robot keeps away from.

    Subclass it with the kind's name, ``class Box(Obstacle, kind="box")``, as a frozen
    dataclass with a ``name`` field (used in messages), and implement every abstract method.
    """

    #: Its ``kind`` in a problem file (set by the subclass's ``kind=``).
    kind: ClassVar[str]
    #: The keys of its entry in ``[cell].obstacles`` besides ``name`` and ``kind``.
    KEYS: ClassVar[frozenset[str]]

    def __init_subclass__(cls, kind: str, **kwargs):
        super().__init_subclass__(**kwargs)
        missing = sorted(m for m in Obstacle.__abstractmethods__
                         if getattr(getattr(cls, m), "__isabstractmethod__", False))
        if not isinstance(getattr(cls, "KEYS", None), frozenset):
            missing.append("KEYS")
        if missing:
            raise TypeError(f"obstacle kind '{kind}' ({cls.__name__}) does not implement {', '.join(missing)}")
        cls.kind = kind
        OBSTACLE_KINDS[kind] = cls

    @property
    def label(self) -> str:
        """Its name in messages."""
        return self.name

    @classmethod
    @abstractmethod
    def parse(cls, r: FieldReader, name: str) -> Obstacle:
        """The obstacle ``name`` of the entry read by ``r`` (only :attr:`KEYS` besides name
        and kind, checked by the caller); errors name the file and the field."""

    @abstractmethod
    def rows(self, a, b, radius_m: float, ops: Any, dist: Callable, place: Callable) -> list:
        """Lower bounds (m) of the distance between the capsule ``[a, b]`` (world ends, m,
        CasADi or numpy 3-vectors) of radius ``radius_m`` (m) and the obstacle, each smooth
        where the capsule is off the obstacle; the capsule keeps a clearance c when every
        row is ``>= c``.

        ``ops`` has ``dot``, ``fmin`` and ``fmax`` of CasADi or numpy; ``dist(p0, p1, q0,
        q1)`` is the segment distance (m) of the same; ``place(capsule)`` gives the world
        ends of a segment given in a fixed frame (m).
        """

    @abstractmethod
    def coal_geometry(self) -> tuple[coal.CollisionGeometry, np.ndarray, np.ndarray]:
        """Its coal shape, with the rotation (3 x 3) and translation (3, m) that place the
        shape in the obstacle's frame."""

    @abstractmethod
    def draw(self, ax: Axes, lo_mm: np.ndarray, hi_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Draw on the 3-D axes ``ax`` (mm), whose view is the box ``[lo_mm, hi_mm]``; return
        the view it needs (the same box when it does not change it)."""


@dataclass(frozen=True)
class HalfSpace(Obstacle, kind="half_space"):
    """The free side ``{x : normal . x >= offset_m}`` of a plane (m).

    Stored with a unit normal: a normal ``n`` and offset ``b`` given become ``n / |n|`` and
    ``b / |n|`` (the same set), so ``normal . x - offset_m`` is the signed distance (m) of
    ``x`` from the plane. In ``[experiments.workspace]`` it bounds the measured points; as an
    obstacle of the cell (the floor at height h is ``HalfSpace((0, 0, 1), h)``) it bounds every
    moving capsule.
    """

    normal: tuple[float, float, float]
    offset_m: float
    name: str = "half-space"

    KEYS: ClassVar[frozenset[str]] = frozenset({"normal", "offset_m"})

    def __post_init__(self):
        n = vector3(self.normal, f"{self.name}: normal")
        length = np.linalg.norm(n)
        if not length > 0 or not np.isfinite(self.offset_m):
            raise ProblemError(f"{self.name}: needs a non-zero normal and a finite offset_m; got "
                               f"{self.normal!r}, {self.offset_m!r}")
        object.__setattr__(self, "normal", tuple(float(x) for x in np.array(n) / length))
        object.__setattr__(self, "offset_m", float(self.offset_m / length))

    @classmethod
    def parse(cls, r: FieldReader, name: str) -> HalfSpace:
        normal = r.array("normal", (3,), hint="the plane's normal, towards the free side")
        if not np.linalg.norm(normal) > 0:
            raise r.error("is zero", "give a non-zero 3-vector", "normal")
        return cls(tuple(normal), r.number("offset_m", hint="b in normal . x >= b, m"), name)

    def rows(self, a, b, radius_m, ops, dist, place) -> list:
        """``n . a - o - r`` and ``n . b - o - r``: two smooth rows whose minimum is the exact
        signed distance of the capsule from the plane."""
        n = np.array(self.normal)
        return [ops.dot(n, e) - self.offset_m - radius_m for e in (a, b)]

    def coal_geometry(self):
        import coal

        return coal.Halfspace(np.array(self.normal), self.offset_m), np.eye(3), np.zeros(3)

    def draw(self, ax, lo_mm, hi_mm):
        """A floor (normal +z) as a grid across the view at its height, which becomes the
        view's bottom; other planes are not drawn (they would hide the robot)."""
        if self.normal != (0.0, 0.0, 1.0):
            return lo_mm, hi_mm
        z = self.offset_m * 1e3
        X, Y = np.meshgrid(np.linspace(lo_mm[0], hi_mm[0], 6), np.linspace(lo_mm[1], hi_mm[1], 6))
        ax.plot_wireframe(X, Y, np.full_like(X, z), color="0.8", lw=0.5)
        return np.r_[lo_mm[:2], z], hi_mm


@dataclass(frozen=True)
class Box(Obstacle, kind="box"):
    """Box centred at ``center_m``, half sizes ``half_extents_m`` along its axes (m), turned
    by ``rpy_rad`` (roll, pitch, yaw, URDF convention) from the world axes."""

    center_m: tuple[float, float, float]
    half_extents_m: tuple[float, float, float]
    rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "box"

    KEYS: ClassVar[frozenset[str]] = frozenset({"center_m", "half_extents_m", "rpy_deg"})

    def __post_init__(self):
        object.__setattr__(self, "center_m", vector3(self.center_m, f"{self.name}: center_m"))
        object.__setattr__(self, "rpy_rad", vector3(self.rpy_rad, f"{self.name}: rpy_rad"))
        h = vector3(self.half_extents_m, f"{self.name}: half_extents_m")
        if min(h) < 0:
            raise ProblemError(f"{self.name}: half_extents_m must be >= 0; got {self.half_extents_m!r}")
        object.__setattr__(self, "half_extents_m", h)

    @classmethod
    def parse(cls, r: FieldReader, name: str) -> Box:
        half = r.array("half_extents_m", (3,), hint="half sizes along the box's axes, m")
        if not np.all(half > 0):
            raise r.error(f"{half.tolist()}", "give positive half sizes (m)", "half_extents_m")
        rpy = r.array("rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw of the box, deg")
        return cls(tuple(r.array("center_m", (3,), hint="the box's centre, m")), tuple(half),
                   tuple(np.deg2rad(rpy)), name)

    @property
    def rotation(self) -> np.ndarray:
        """World rotation of the box's axes: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
        (cr, cp, cy), (sr, sp, sy) = np.cos(self.rpy_rad), np.sin(self.rpy_rad)
        return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
                @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))

    def faces(self) -> tuple[np.ndarray, np.ndarray]:
        """Outward unit normals ``N`` (6 x 3) and offsets ``o`` (6, m): the box is
        ``{x : N x <= o}``."""
        R = self.rotation
        N = np.vstack([R.T, -R.T])
        return N, N @ np.array(self.center_m) + np.tile(self.half_extents_m, 2)

    def rows(self, a, b, radius_m, ops, dist, place) -> list:
        """``max_f [min(N_f . a, N_f . b) - o_f] - r`` (:meth:`faces`): the largest gap between
        the capsule and a face plane; when positive, that plane separates the capsule from the
        box. Conservative: a capsule passing diagonally near an edge or corner may be reported
        too close though it is not (the exact distance is larger); kinks where two faces or
        two ends tie."""
        N, off = self.faces()
        gaps = [ops.fmin(ops.dot(N[f], a), ops.dot(N[f], b)) - off[f] for f in range(6)]
        g = gaps[0]
        for gap in gaps[1:]:
            g = ops.fmax(g, gap)
        return [g - radius_m]

    def coal_geometry(self):
        import coal

        return coal.Box(*(2 * np.array(self.half_extents_m))), self.rotation, np.array(self.center_m)

    def draw(self, ax, lo_mm, hi_mm):
        """Its 12 edges."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        corners = np.array(self.center_m) + (signs * np.array(self.half_extents_m)) @ self.rotation.T
        for i in range(8):
            for j in range(i + 1, 8):
                if np.sum(signs[i] != signs[j]) == 1:
                    ax.plot(*(corners[[i, j]] * 1e3).T, color=OBSTACLE_COLOUR, lw=0.8)
        return lo_mm, hi_mm


@dataclass(frozen=True)
class Capsule(Obstacle, kind="capsule"):
    """Points within ``radius_m`` of the segment ``[a_m, b_m]`` (m, in the frame ``frame``).

    ``frame`` names a frame (a link) or a joint of the robot model; the segment moves with it.
    A capsule in the world frame (``"universe"``) is an obstacle; ``name`` names it in messages.
    """

    frame: str
    a_m: tuple[float, float, float]
    b_m: tuple[float, float, float]
    radius_m: float
    name: str = ""

    KEYS: ClassVar[frozenset[str]] = frozenset({"a_m", "b_m", "radius_m"})

    def __post_init__(self):
        object.__setattr__(self, "a_m", vector3(self.a_m, f"capsule on '{self.frame}': a_m"))
        object.__setattr__(self, "b_m", vector3(self.b_m, f"capsule on '{self.frame}': b_m"))
        r = float(self.radius_m)
        if not (np.isfinite(r) and r >= 0):
            raise ProblemError(f"capsule on '{self.frame}': radius_m must be finite and >= 0; got {self.radius_m!r}")
        object.__setattr__(self, "radius_m", r)

    @property
    def label(self) -> str:
        return self.name or "capsule obstacle"

    @classmethod
    def parse(cls, r: FieldReader, name: str, frame: str = "universe") -> Capsule:
        """As :meth:`Obstacle.parse`; ``frame``: where the segment is given (a robot's capsule
        names its link)."""
        return cls(frame, tuple(r.array("a_m", (3,), hint="one end of the segment, m")),
                   tuple(r.array("b_m", (3,), hint="the other end of the segment, m")),
                   r.number("radius_m", hint="the capsule's radius, m", nonnegative=True), name)

    def rows(self, a, b, radius_m, ops, dist, place) -> list:
        """``dist([a, b], [a_o, b_o]) - r - r_o``, its segment placed in the world by ``place``."""
        return [dist(a, b, *place(self)) - radius_m - self.radius_m]

    def coal_geometry(self):
        """A coal capsule along ``[a_m, b_m]`` (coal's capsules lie along z about the origin)."""
        import coal
        import pinocchio as pin

        a, b = np.array(self.a_m), np.array(self.b_m)
        axis = b - a
        length = float(np.linalg.norm(axis))
        R = (pin.Quaternion.FromTwoVectors(np.array([0.0, 0, 1]), axis / length).matrix() if length > 0
             else np.eye(3))
        return coal.Capsule(self.radius_m, length), R, (a + b) / 2

    def draw(self, ax, lo_mm, hi_mm):
        """Its segment as a line as thick as the capsule."""
        ax.plot(*(np.array([self.a_m, self.b_m]) * 1e3).T, color=OBSTACLE_COLOUR,
                lw=max(1.0, 60 * self.radius_m), alpha=0.5)
        return lo_mm, hi_mm
