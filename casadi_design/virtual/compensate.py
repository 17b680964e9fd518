"""Compensation at the test poses: :mod:`casadi_design.identification.compensate`, the one
compensation, shared by measured data and the simulated calibrations."""

from ..identification.compensate import (
    CHORD_RATE,
    COMPENSATION_MAX_ITERATIONS,
    COMPENSATION_STEP_TOL,
    COMPENSATION_TOL,
    accuracy_jacobian,
    compensate,
)

__all__ = ["CHORD_RATE", "COMPENSATION_MAX_ITERATIONS", "COMPENSATION_STEP_TOL", "COMPENSATION_TOL",
           "accuracy_jacobian", "compensate"]
