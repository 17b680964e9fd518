"""Identification of the simulated robots: linear least squares or Levenberg-Marquardt.

Both work on the whitened measured values of ``model.measurement`` (noise ``sigma`` per
value), so ordinary least squares is the weighted least squares of the noise model.

* Elasto-static case: ``y = B X_s`` to first order in the compliances, with ``B`` the model's
  ``dy/dX`` for the scaled parameters ``X_s = c X`` (``c = model.column_scale``); the least
  squares ``X_s = (S^T S)^-1 S^T y`` of the stacked ``S`` is divided by ``c``.
* Otherwise: Levenberg-Marquardt on ``model.measurement`` itself
  (:func:`casadi_design.identification.lsq.identify_nonlinear`, the code that identifies a
  robot from measured data): the residuals are the exact model's; the Jacobian of each trial
  is its Taylor expansion ``J(X) = J0 + sum_l X_l dJ/dX_l`` at X = 0, exact to ``O(|X|^2)`` (relative ~1e-7 for errors of 0.5 mm and 0.05 deg), derived
  once per plan from the model (:func:`measurement_slopes`): evaluating the exact ``dy/dX`` of
  every trial cost ten times the residuals and 85 % of a virtual calibration.
"""

from __future__ import annotations

import numpy as np

from ..identification.lsq import (  # the one identification, shared with measured data
    LM_TOL,
    Identification,
    identify_nonlinear,
    measurement_slopes,
    taylor_jacobian,
)

__all__ = ["LM_TOL", "Identification", "identify_linear", "identify_nonlinear",
           "measurement_slopes", "taylor_jacobian"]


def identify_linear(B: np.ndarray, y: np.ndarray,
                    column_scale: np.ndarray) -> tuple[np.ndarray, Identification]:
    """Least squares of every trial at once: ``X = ((S^T S)^-1 S^T y) / c``.

    Parameters
    ----------
    B : ndarray, shape (m, d, L) or (m d, L): the plan's ``B_i`` (``model.B_stack``), written
        for the scaled parameters ``c X``.
    y : ndarray, shape (trials, m d): whitened measured values.
    column_scale : ndarray, shape (L,): ``c = model.column_scale``.

    Returns
    -------
    X : ndarray, shape (trials, L), physical parameters.
    """
    S = np.asarray(B, dtype=float).reshape(-1, np.shape(B)[-1])
    return (y @ np.linalg.pinv(S).T) / column_scale, Identification("linear least squares", 1, 0)
