"""The cell as a problem file describes it: capsules, obstacles, disabled pairs and the laser
tracker (:class:`CellSpec`), and the workspace every experiment stays in (:class:`Workspace`)."""

from __future__ import annotations

from dataclasses import dataclass

from .obstacles import Capsule, HalfSpace, Obstacle


@dataclass(frozen=True)
class TrackerSpec:
    """The laser tracker: at ``position_m`` (world, m); each reflector (SMR) opens along the
    unit ``reflector_axis`` (measured frame) and returns the beam within ``acceptance_rad`` of
    that axis."""

    position_m: tuple[float, float, float]
    reflector_axis: tuple[float, float, float]
    acceptance_rad: float


@dataclass(frozen=True)
class CellSpec:
    """The calibration cell: robot capsules, obstacles and tracker, with a clearance (m).

    ``capsules_per_link``: capsules fitted around each link's URDF collision meshes (0: none);
    ``capsules``: capsules given as numbers (added to the fitted ones; the only ones of a DH
    robot); ``disabled_pairs``: pairs of link frames never checked against each other;
    ``srdf``: a MoveIt SRDF of the robot whose ``disable_collisions`` pairs are disabled too
    (those of two links with capsules); ``collision_urdf``: for a DH robot, a URDF of the same
    robot (same joint names) whose collision geometry checks the plans.
    """

    clearance_m: float = 0.0
    capsules_per_link: int = 0
    capsules: tuple[Capsule, ...] = ()
    disabled_pairs: tuple[tuple[str, str], ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    tracker: TrackerSpec | None = None
    collision_urdf: str = ""
    srdf: str = ""


@dataclass(frozen=True)
class Workspace:
    """Where the robot may be during calibration (m, rad).

    Every measured point inside the box, the half-spaces and the sphere (the tracker's range);
    every moving joint origin, moving frame (flange, tool) and measured point at
    ``z >= floor_z_m``; the configurations of any two experiments at least
    ``min_joint_distance_rad`` apart (:func:`casadi_design.plan.rules.joint_distance`); every
    joint at least ``joint_limit_margin_rad`` (rad, m for prismatic joints) inside its limits.
    """

    box_min_m: tuple[float, float, float] | None = None
    box_max_m: tuple[float, float, float] | None = None
    half_spaces: tuple[HalfSpace, ...] = ()
    sphere_center_m: tuple[float, float, float] | None = None
    sphere_radius_m: float | None = None
    floor_z_m: float | None = None
    min_joint_distance_rad: float = 0.0
    joint_limit_margin_rad: float = 0.0
