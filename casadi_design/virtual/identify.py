"""Identification of the simulated robots: the least squares that identifies measured data.

It works on the whitened measured values of ``model.measurement`` (noise ``sigma`` per value),
so ordinary least squares is the weighted least squares of the noise model. It is
:func:`casadi_design.identification.lsq.identify_nonlinear`, for the geometric and the
elasto-static cases alike: scipy's trust region with the exact Jacobian of the model.
"""

from __future__ import annotations

from ..identification.lsq import (  # the one identification, shared with measured data
    LSQ_TOL,
    Identification,
    identify_nonlinear,
    measurement_jacobian,
)

__all__ = ["LSQ_TOL", "Identification", "identify_nonlinear", "measurement_jacobian"]
