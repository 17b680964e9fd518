"""Measurement CSVs: a plan CSV of ``solve`` with the measured coordinates appended.

The joint columns (``<joint>_deg`` / ``_rad``, or ``q1_deg``...) and load columns are those of a
plan (:func:`casadi_design.export.read_plan_table`); the measured coordinates (mm) follow:
``meas_x_mm, meas_y_mm, meas_z_mm`` for one measured point, ``meas1_x_mm, ..., measK_z_mm`` for
the K markers of ``markers_m`` in their order, one column per measured position component
(``[measurement].components``). An empty cell is a marker the tracker did not see; a marker's
coordinates are all given or all empty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..build import Problem
from ..errors import ProblemError
from ..export import joint_units, read_plan_table

#: The position components a tracker measures, in the order of the columns.
AXES = ("x", "y", "z")
#: Joint values this far outside their limits (rad or m) are still accepted (rounding in a CSV).
LIMIT_TOL = 1e-6


@dataclass(frozen=True, eq=False)
class Measurements:
    """The rows of a measurement CSV.

    Attributes
    ----------
    path : str, the file.
    lines : tuple of int, the line of the file of each row (1-based).
    Q : ndarray, shape (m, n), rad (m): joint values;  F : ndarray, shape (m, nF), N (N m).
    P_m : ndarray, shape (m, k, 3), m: measured coordinates of the k measured points, in the
        frame of the measurements; NaN for a marker not seen and for a component not measured.
    """

    path: str
    lines: tuple[int, ...]
    Q: np.ndarray
    F: np.ndarray
    P_m: np.ndarray

    @property
    def m(self) -> int:
        return len(self.Q)

    @property
    def seen(self) -> np.ndarray:
        """Bool (m, k): the markers measured in each row."""
        return np.any(np.isfinite(self.P_m), axis=2)

    def row(self, i: int) -> str:
        return f"{self.path}: row {self.lines[i]}"


def measured_axes(problem: Problem) -> tuple[int, ...]:
    """Indices (into x, y, z) of the measured position components."""
    return tuple(AXES.index(c) for c in problem.spec.measurement.components if c in AXES)


def measurement_columns(problem: Problem) -> list[list[str]]:
    """Per measured point, its column names (mm), e.g. ``[["meas_x_mm", "meas_y_mm"]]``."""
    axes = [AXES[a] for a in measured_axes(problem)]
    if problem.spec.measurement.markers_m is None:
        return [[f"meas_{a}_mm" for a in axes]]
    return [[f"meas{c + 1}_{a}_mm" for a in axes] for c in range(len(problem.model.markers_m))]


def read_measurements(problem: Problem, path: str) -> Measurements:
    """Read a measurement CSV of ``problem`` (module docstring).

    Raises
    ------
    ProblemError
        The errors of a plan CSV, and: orientation components measured, a missing coordinate
        column, a marker with some coordinates empty, a row without any measured point, joint
        values outside the joint limits (one line each, naming the file, row and column).
    """
    path = str(path)
    components = problem.spec.measurement.components
    if any(c not in AXES for c in components):
        raise ProblemError(
            f"{problem.path}: [measurement].components has {list(components)}; identify reads "
            "measured positions (x, y, z) only; measure positions, e.g. three markers for the pose")
    columns = measurement_columns(problem)
    names = tuple(c for point in columns for c in point)
    hint = ", ".join(names) + " (measured coordinates, mm)"
    Q, F, values, lines = read_plan_table(problem, path, names, hint)
    missing = [c for c in names if c not in values]
    if missing:
        raise ProblemError(f"{path}: missing column '{missing[0]}'; append the measured coordinates "
                           f"in mm: {', '.join(names)}")
    m, axes = len(Q), measured_axes(problem)
    P = np.full((m, len(columns), 3), np.nan)
    for c, point in enumerate(columns):
        block = np.column_stack([values[name] for name in point]) * 1e-3
        given = np.isfinite(block)
        partial = np.flatnonzero(given.any(axis=1) & ~given.all(axis=1))
        if partial.size:
            i = int(partial[0])
            empty = point[int(np.flatnonzero(~given[i])[0])]
            raise ProblemError(f"{path}: row {lines[i]}, column '{empty}': empty while the other "
                               f"coordinates of the point are given; give all of {', '.join(point)} "
                               "or leave all empty (a marker the tracker did not see)")
        P[:, c, list(axes)] = block
    blind = np.flatnonzero(~np.any(np.isfinite(P), axis=(1, 2)))
    if blind.size:
        raise ProblemError(f"{path}: row {lines[int(blind[0])]}: no measured coordinate in "
                           f"{', '.join(names)}; fill them in or delete the row")
    robot = problem.robot
    outside = (Q < robot.q_min - LIMIT_TOL) | (Q > robot.q_max + LIMIT_TOL)
    if outside.any():
        i, k = (int(v[0]) for v in np.nonzero(outside))
        _, people, scale = joint_units(problem, k)
        j = robot.joints[k]
        raise ProblemError(
            f"{path}: row {lines[i]}, column of joint {k + 1} ({j}_{people} or q{k + 1}_{people}): "
            f"{Q[i, k] / scale:.6g} {people} is outside the joint limits [{robot.q_min[k] / scale:.6g}, "
            f"{robot.q_max[k] / scale:.6g}] {people} of {problem.path}; check the units, the order "
            "of the joint columns and that the file belongs to this case")
    return Measurements(path, tuple(lines), Q, F, P)
