"""Obstacle kinds: what a kind implements, a new kind as one class (read from a problem file,
its rows, its coal shape, its drawing) and half-space normals made unit once, when read."""

from __future__ import annotations

import dataclasses
import inspect
import tomllib
import types
from dataclasses import dataclass
from typing import ClassVar

import coal
import numpy as np
import pinocchio as pin
import pytest
from matplotlib.figure import Figure

from casadi_design.cell.collision import capsule_clearances
from casadi_design.cell.obstacles import OBSTACLE_COLOUR, OBSTACLE_KINDS, HalfSpace, Obstacle
from casadi_design.problem.build import build_problem
from casadi_design.problem_file.read import SECTIONS, parse_problem
from tests.conftest import ROOT

ABB = ROOT / "problems" / "abb_irb6640_machining.toml"
#: What an obstacle kind implements, besides its ``KEYS``.
INTERFACE = ("parse", "rows", "coal_geometry", "draw")
#: One entry of ``[cell].obstacles`` per kind, within reach of the ABB's links.
ENTRIES = {
    "half_space": {"normal": [-2.0, 0.0, 0.0], "offset_m": -5.0},
    "box": {"center_m": [0.0, 1.6, 1.0], "half_extents_m": [0.3, 0.2, 0.4], "rpy_deg": [0.0, 0.0, 30.0]},
    "capsule": {"a_m": [0.0, -1.8, 0.0], "b_m": [0.0, -1.8, 1.5], "radius_m": 0.1},
    "sphere": {"center_m": [1.2, 1.2, 1.5], "radius_m": 0.2},
}
#: A smoothed segment distance is within this below the exact one (m).
SMOOTHING_TOL = 1e-6


def _sphere_kind() -> type[Obstacle]:
    """A kind written as a new one would be: one class, nothing else touched (its keys are
    already in the schema, as a kind's keys are when it is defined in ``obstacles.py``)."""

    @dataclass(frozen=True)
    class Sphere(Obstacle, kind="sphere"):
        center_m: tuple[float, float, float]
        radius_m: float
        name: str = "sphere"

        KEYS: ClassVar[frozenset[str]] = frozenset({"center_m", "radius_m"})

        @classmethod
        def parse(cls, r, name):
            return cls(tuple(r.array("center_m", (3,), hint="the centre, m")),
                       r.number("radius_m", hint="the radius, m", positive=True), name)

        def rows(self, a, b, radius_m, ops, dist, place):
            c = np.array(self.center_m)
            return [dist(a, b, c, c) - radius_m - self.radius_m]

        def coal_geometry(self):
            return coal.Sphere(self.radius_m), np.eye(3), np.array(self.center_m)

        def draw(self, ax, lo_mm, hi_mm):
            ax.scatter(*np.array(self.center_m) * 1e3, s=40, color=OBSTACLE_COLOUR)
            return lo_mm, hi_mm

    return Sphere


@pytest.fixture(autouse=True)
def kinds():
    """The registry as it was, after each test (a test defines kinds)."""
    saved = dict(OBSTACLE_KINDS)
    yield
    OBSTACLE_KINDS.clear()
    OBSTACLE_KINDS.update(saved)


def _abb_with(*obstacles: dict) -> dict:
    raw = tomllib.loads(ABB.read_text())
    raw["cell"]["obstacles"] = list(obstacles)
    return raw


def test_every_kind_implements_the_interface():
    assert set(INTERFACE) == Obstacle.__abstractmethods__
    assert list(OBSTACLE_KINDS) == ["half_space", "box", "capsule"]
    for kind, cls in OBSTACLE_KINDS.items():
        assert cls.kind == kind and not inspect.isabstract(cls)
        assert all(name in vars(cls) for name in (*INTERFACE, "KEYS")), kind
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
        assert cls.KEYS <= SECTIONS["cell.obstacles"]


@pytest.mark.parametrize("left_out", [*INTERFACE, "KEYS"])
def test_a_kind_that_leaves_something_out_is_refused(left_out):
    Sphere = _sphere_kind()
    body = {name: vars(Sphere)[name] for name in (*INTERFACE, "KEYS") if name != left_out}
    with pytest.raises(TypeError, match=rf"obstacle kind 'cone' \(Cone\) does not implement {left_out}$"):
        types.new_class("Cone", (Obstacle,), {"kind": "cone"}, lambda ns: ns.update(body))
    assert "cone" not in OBSTACLE_KINDS


@pytest.fixture(scope="module")
def abb_with_every_kind():
    """The ABB case with one obstacle of every kind, the toy sphere included, each named by its
    kind (built once: a cell costs a second); the registry is left as it was."""
    saved = dict(OBSTACLE_KINDS)
    _sphere_kind()
    spec = parse_problem(_abb_with(*({"name": kind, "kind": kind, **entry} for kind, entry in ENTRIES.items())),
                         str(ABB))
    OBSTACLE_KINDS.clear()
    OBSTACLE_KINDS.update(saved)
    return spec, build_problem(spec)


@pytest.mark.parametrize("kind", list(ENTRIES))
def test_a_kind_is_read_gives_rows_its_coal_shape_and_draws(kind, abb_with_every_kind):
    spec, problem = abb_with_every_kind
    _sphere_kind()
    assert set(ENTRIES) == set(OBSTACLE_KINDS)  # a new kind comes with its entry here
    (thing,) = [o for o in spec.cell.obstacles if o.name == kind]
    assert type(thing).kind == kind
    cell, robot = problem.cell, problem.robot
    k = cell.obstacles.index(thing)
    assert any(o == k for _, o in cell.near), "no capsule can meet the obstacle: move it"
    # its rows: every kept (capsule, obstacle) pair, "- clearance" on the kind's lower bounds
    label = f"closer than {cell.spec.clearance_m * 1e3:g} mm to {kind}"
    rng = np.random.default_rng(4)
    check, gdata = cell.check, cell.check.geometry.createData()
    (index,) = [i for i, go in enumerate(check.geometry.geometryObjects) if go.name == kind]
    assert isinstance(check.geometry.geometryObjects[index].geometry, type(thing.coal_geometry()[0]))
    pairs = [p for p, cp in enumerate(check.geometry.collisionPairs) if index in (cp.first, cp.second)]
    assert pairs
    apart = 0
    for q in rng.uniform(robot.q_min, robot.q_max, size=(10, robot.n)):
        g, labels = capsule_clearances(robot, cell.capsules, q, cell.spec.clearance_m, cell.obstacles, cell.sights,
                                       cell.pairs.kept, cell.near)
        mine = [v for v, lb in zip(g, labels) if lb.endswith(label)]
        assert mine
        # on its coal shape, no checked body is closer than the rows say (the bodies are the
        # ABB's capsules: a box row is conservative, the others within the smoothing)
        pin.computeDistances(check.model, check.model.createData(), check.geometry, gdata, check.configuration(q))
        exact = min(gdata.distanceResults[p].min_distance for p in pairs)
        if exact > 0:  # coal's depth of crossing bodies is not a distance
            apart += 1
            assert min(mine) <= exact - cell.spec.clearance_m + SMOOTHING_TOL
    assert apart
    # its drawing
    ax = Figure().add_subplot(projection="3d")
    lo, hi = np.array([-1e3, -1e3, 500.0]), np.array([1e3, 1e3, 2e3])
    before = len(ax.lines) + len(ax.collections)
    view = thing.draw(ax, lo.copy(), hi.copy())
    assert all(v.shape == (3,) for v in view)
    assert len(ax.lines) + len(ax.collections) > before or kind == "half_space"  # a wall is not drawn


def test_half_space_normals_are_unit_once_read():
    raw = _abb_with({"name": "wall", "kind": "half_space", "normal": [0.0, 3.0, 4.0], "offset_m": 1.0})
    raw["experiments"]["workspace"]["half_spaces"] = [{"normal": [2.0, 0.0, 0.0], "offset_m": -8.0}]
    spec = parse_problem(raw, str(ABB))
    (wall,), (bound,) = spec.cell.obstacles, spec.workspace.half_spaces
    assert wall.normal == pytest.approx((0.0, 0.6, 0.8), abs=1e-15) and wall.offset_m == pytest.approx(0.2, abs=1e-15)
    assert bound.normal == (1.0, 0.0, 0.0) and bound.offset_m == -4.0
    for h in (wall, bound, HalfSpace((1.0, -2.0, 2.0), 3.0)):
        assert abs(np.linalg.norm(h.normal) - 1.0) <= 4 * np.finfo(float).eps
    # the same set: n . x >= b  <=>  (n / |n|) . x >= b / |n|
    x = np.array([0.3, 0.1, 0.2])
    assert (np.array(h.normal) @ x - h.offset_m) * 3.0 == pytest.approx(np.array([1.0, -2.0, 2.0]) @ x - 3.0)
