"""Identification of the simulated robots: Levenberg-Marquardt on the measurement model.

It works on the whitened measured values of ``model.measurement`` (noise ``sigma`` per value),
so ordinary least squares is the weighted least squares of the noise model. It is
:func:`casadi_design.identification.lsq.identify_nonlinear`, the code that identifies a robot
from measured data, for the geometric and the elasto-static cases alike: the residuals are the
exact model's; the Jacobian of each trial is its Taylor expansion ``J(X) = J0 + sum_l X_l
dJ/dX_l`` at X = 0, exact to ``O(|X|^2)`` (relative ~1e-7 for errors of 0.5 mm and 0.05 deg),
derived once per plan from the model (:func:`measurement_slopes`): evaluating the exact
``dy/dX`` of every trial cost ten times the residuals and 85 % of a virtual calibration. (The
elasto-static cases had one linear least-squares step ``y = B X`` before; the figures of the
paper's case are the same to the printed digits.)
"""

from __future__ import annotations


from ..identification.lsq import (  # the one identification, shared with measured data
    LM_TOL,
    Identification,
    identify_nonlinear,
    measurement_slopes,
    taylor_jacobian,
)

__all__ = ["LM_TOL", "Identification", "identify_nonlinear", "measurement_slopes", "taylor_jacobian"]
