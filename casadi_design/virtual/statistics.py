"""Statistics of the simulated errors: chi-square intervals of the RMS error and rankings.

The residual error at test pose j is, to first order, ``e ~ N(0, C_j)`` with
``C_j = sigma^2 B0_j M^-1 B0_j^T`` and ``trace C_j = rho_j``. Its square ``|e|^2`` is
approximated by ``rho_j / nu_j chi2(nu_j)`` with the effective degrees of freedom
``nu_j = trace(C_j)^2 / trace(C_j^2)`` (Satterthwaite), so the mean square of N trials gives
``N nu_j`` degrees of freedom and an exact chi-square interval of the RMS error.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from ..identification.residuals import chi2_quantile

#: Level of the confidence intervals of the empirical RMS errors.
CONFIDENCE = 0.95


def effective_dof(C: np.ndarray) -> np.ndarray:
    """Degrees of freedom ``nu = trace(C)^2 / trace(C^2)`` of ``|e|^2``, ``e ~ N(0, C)``.

    ``|e|^2`` has mean ``trace C = rho`` and is approximated by ``rho / nu chi2(nu)``
    (Satterthwaite); ``C`` of shape (s, r, r). ``nu = 1`` where ``C = 0``.
    """
    square = np.einsum("sij,sji->s", C, C)
    return np.trace(C, axis1=1, axis2=2) ** 2 / np.where(square > 0, square, 1.0) + (square == 0)


def rms_interval(mean_square: np.ndarray, dof: np.ndarray, trials: np.ndarray | int,
                 confidence: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Confidence interval of the RMS error from the mean square of ``trials`` errors (m).

    With ``T = trials nu``, ``T mean_square / rho ~ chi2(T)``, so
    ``sqrt(rho) in [sqrt(T ms / chi2_{(1+c)/2}(T)), sqrt(T ms / chi2_{(1-c)/2}(T))]``.
    """
    T = trials * np.asarray(dof, dtype=float)
    return (np.sqrt(T * mean_square / chi2_quantile((1 + confidence) / 2, T)),
            np.sqrt(T * mean_square / chi2_quantile((1 - confidence) / 2, T)))


class _Validated(Protocol):
    criterion: str
    m: int


class _Result(Protocol):
    plan: _Validated
    predicted_rms_m: np.ndarray
    empirical_rms_m: np.ndarray


def rankings(plans: Sequence[_Result]) -> dict[int, dict[str, list[str]]]:
    """Per m, the criteria from best to worst by max ``sqrt(rho)`` and by max simulated RMS.

    ``plans``: the :class:`~casadi_design.virtual.PlanValidation` of a validation.
    """
    def order(group: list[_Result], field: str) -> list[str]:
        return [p.plan.criterion for p in sorted(group, key=lambda p: np.max(getattr(p, field)))]

    out: dict[int, dict[str, list[str]]] = {}
    for m in sorted({p.plan.m for p in plans}):
        group = [p for p in plans if p.plan.m == m]
        out[m] = {"by_measure": order(group, "predicted_rms_m"),
                  "by_simulation": order(group, "empirical_rms_m")}
    return out
