"""The scale of a fit's residuals: the tracker's noise and the robot's unmodelled error.

A real robot differs from its model by more than the tracker's noise: a laser tracker reads to
about 0.01 mm, and the error of an industrial arm that no geometric parameter explains
(compliance, gear and thermal errors) is some 0.1 to 1 mm. Judging rows, parameters and
predictions with the tracker's ``sigma`` alone takes every row for an outlier and predicts an
accuracy the robot does not have. For a fit with whitened residuals ``r`` (m, d) (m of every
value), Jacobian ``J`` (m, d, L) and ``H = J^T J`` (plus a MAP fit's prior):

* **Leverage.** ``P_i = J_i H^-1 J_i^T`` (d x d) per row. A row whose ``I - P_i`` is singular
  (smallest singular value below ``LEVERAGE_RTOL``) is needed to identify the model: it
  cannot be judged by the others.
* **Outliers: externally studentized residuals.** Leaving row ``i`` out, its error is the PRESS
  residual ``e_i = (I - P_i)^-1 r_i``, of covariance ``s^2 (I - P_i)^-1`` with i.i.d. errors of
  variance ``s^2``; the other rows' sum of squares is ``|r|^2 - r_i^T (I - P_i)^-1 r_i`` on
  ``N - L - d_i`` degrees of freedom (the fit without row i, in closed form). The row's score
  is ``max_a |e_ia| / (s_(i) sqrt([(I - P_i)^-1]_aa))`` with ``s_(i)`` the larger of ``sigma``
  and the other rows' scale: a bad shot is judged against the error of the rows without it,
  the robot's unmodelled error included, and cannot inflate its own yardstick (Cook and
  Weisberg, Residuals and Influence in Regression, 1982, 2.2).
* **The cross-validated scale.** Leaving row ``i`` out, its error is the PRESS residual
  ``e_i = (I - P_i)^-1 r_i``; with i.i.d. errors ``E e_i e_i^T = s^2 (I - P_i)^-1``, so
  ``s_cv^2 = sum_i |e_i|^2 / sum_i tr (I - P_i)^-1`` is the variance per value that explains
  the cross-validated error: the error at a new pose, in the model's units.
* **The unmodelled error** ``tau^2 = max(0, s_cv^2 - sigma^2)`` when the chi-square test of
  the residuals rejects the tracker's sigma alone (``|r|^2 / sigma^2`` above a high quantile
  of its law, :data:`~.calibrate.UNMODELLED_CONFIDENCE`), else 0 (the residuals are the tracker's noise: the paper's model, unchanged). The errors of
  the fit are then ``s^2 = sigma^2 + tau^2`` per value: the parameters' covariance is
  ``s^2 H^-1`` and a new pose is off by ``s^2 (tr(B H^-1 B^T) + d)``: the parameters' error
  and the pose's own unmodelled error and noise (Kennedy and O'Hagan's model discrepancy,
  2001, taken uncorrelated between poses). Whitened values (per-axis sigmas) scale tau alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from ..errors import DesignError, ProblemError

F = TypeVar("F")

#: A value whose ``1 - h`` (or a row whose ``I - P_i`` has a smallest singular value) below
#: this is needed to identify the model: its left-out error is not defined.
LEVERAGE_RTOL = 1e-8


def chi2_quantile(p: float, dof):
    """Quantile ``p`` of the chi-square law with ``dof`` degrees of freedom (``dof`` need not
    be an integer; a number or an array): ``2 P^-1(dof / 2, p)`` with ``P`` the regularised
    lower incomplete gamma function, as ``scipy.stats.chi2.ppf`` computes it (from
    scipy.special, a third of scipy.stats's second of import)."""
    from scipy.special import gammaincinv

    return 2.0 * gammaincinv(np.asarray(dof, dtype=float) / 2.0, p)


def leverages(J: np.ndarray, H: np.ndarray) -> np.ndarray:
    """``P_i = J_i H^-1 J_i^T`` (m, d, d) of the rows of ``J`` (m, d, L); ``H`` (L, L)."""
    return np.einsum("kai,ij,kbj->kab", J, np.linalg.inv(H), J)


def press(r: np.ndarray, P: np.ndarray) -> tuple[np.ndarray | None, np.ndarray, int]:
    """The PRESS residuals ``e_i = (I - P_i)^-1 r_i`` (m, d), whitened m, of the rows, and
    ``(I - P_i)^-1`` (m, d, d); None (and the index of the row) when a row is needed to
    identify the model, else -1."""
    A = np.eye(P.shape[1]) - P
    smallest = np.linalg.svd(A, compute_uv=False)[:, -1]
    if np.any(smallest < LEVERAGE_RTOL):
        return None, np.full_like(A, np.nan), int(np.argmin(smallest))
    Ainv = np.linalg.inv(A)
    return np.einsum("kab,kb->ka", Ainv, r), Ainv, -1


def deleted_scores(r: np.ndarray, mask: np.ndarray, P: np.ndarray, sigma: float,
                   dof: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's outlier score and the scale ``s_(i)`` (m) it was judged against (module
    docstring): residuals ``r`` (m, d), values measured ``mask`` (m, d), leverages ``P``
    (m, d, d), ``dof = N - L`` of the fit. A row needed to identify the model, or the last
    degrees of freedom, scores 0."""
    A = np.eye(P.shape[1]) - P
    judged = np.linalg.svd(A, compute_uv=False)[:, -1] >= LEVERAGE_RTOL
    Ainv = np.linalg.inv(np.where(judged[:, None, None], A, np.eye(P.shape[1])))
    e = np.einsum("kab,kb->ka", Ainv, r)
    rest = np.sum(r**2) - np.einsum("ka,ka->k", r, e)
    left = dof - mask.sum(axis=1)
    s = np.where(left > 0, np.sqrt(np.maximum(rest, 0.0) / np.maximum(left, 1)), sigma)
    s = np.maximum(s, sigma)
    z = np.abs(e) / (s[:, None] * np.sqrt(np.maximum(np.diagonal(Ainv, axis1=1, axis2=2), 1.0)))
    return np.where(judged & (left > 0), np.max(np.where(mask, z, 0.0), axis=1), 0.0), s


@dataclass(frozen=True)
class ErrorScale:
    """The errors of a fit per measured value (m): the tracker's ``sigma`` (the problem's),
    the unmodelled error ``tau`` and their sum ``s = sqrt(sigma^2 + tau^2)`` (module
    docstring); ``cross_validated_m`` the ``s_cv`` it came from (NaN: not cross-validated,
    ``sigma_hat`` of the chi-square test used)."""

    sigma_m: float
    tau_m: float
    cross_validated_m: float = math.nan

    @property
    def s_m(self) -> float:
        return math.hypot(self.sigma_m, self.tau_m)

    @property
    def tracker_share(self) -> float:
        """The tracker's share of the variance per value, ``sigma^2 / s^2``."""
        return self.sigma_m**2 / self.s_m**2

    def as_dict(self) -> dict:
        return {"sigma_m": self.sigma_m, "unmodelled_m": self.tau_m, "total_m": self.s_m,
                "tracker_share_of_variance": self.tracker_share,
                "unmodelled_share_of_variance": 1.0 - self.tracker_share,
                "cross_validated_scale_m": None if math.isnan(self.cross_validated_m) else self.cross_validated_m}


def error_scale(r: np.ndarray, P: np.ndarray, sigma: float, sigma_hat: float,
                noise_rejected: bool) -> ErrorScale:
    """The :class:`ErrorScale` of a fit's rows (module docstring): whitened residuals ``r``
    (m, d), leverages ``P`` (m, d, d); ``sigma_hat`` the in-sample estimate ``sqrt(|r|^2 /
    dof)`` used when a row is needed to identify the model; ``noise_rejected`` whether the
    chi-square test rejects ``sigma`` (residuals too large)."""
    e, Ainv, _ = press(r, P)
    weight = math.nan if e is None else float(np.trace(Ainv, axis1=1, axis2=2).sum())
    # a row all but needed to identify the model (a leverage at 1 up to rounding): no cross-validation
    s_cv = float(np.sqrt(np.sum(e**2) / weight)) if weight > 0 and np.isfinite(weight) else math.nan
    if not noise_rejected:
        return ErrorScale(sigma, 0.0, s_cv)
    s = sigma_hat if math.isnan(s_cv) else s_cv
    return ErrorScale(sigma, math.sqrt(max(0.0, s**2 - sigma**2)), s_cv)


@dataclass(frozen=True)
class Stopped:
    """Why :func:`without_outliers` stopped with rows still beyond the threshold: ``beyond``
    rows left at the cap (``scale_m`` the median scale they were judged against), or the refit
    without row ``row`` (score ``score``) failed with ``error``."""

    beyond: int = 0
    scale_m: float = math.nan
    row: int = -1
    score: float = math.nan
    error: Exception | None = None


def without_outliers(fit_rows: Callable[[np.ndarray], F], scores: Callable[[F], tuple[np.ndarray, np.ndarray]],
                     m: int, threshold: float, max_share: float
                     ) -> tuple[F, list[tuple[int, float, float]], Stopped | None]:
    """Fit the ``m`` rows (``fit_rows(used)``, a bool mask), then exclude the rows whose score
    (``scores(fit)``: each row's score and the scale, m, it was judged against) exceeds
    ``threshold`` and half the worst row's, the worst first, and refit, while rows exceed it; at
    most ``max_share`` of the rows (at least one). A bad shot stands out against the residual
    scale; what many rows share is the model's error. A refit that fails (the rest do not
    identify X, or it does not converge) keeps the last good fit. Returns the fit, the rows
    excluded (index, score, scale m) and why it stopped early (None: no row left beyond)."""
    used = np.ones(m, dtype=bool)
    f = fit_rows(used)
    cap = max(1, math.floor(max_share * m))
    excluded: list[tuple[int, float, float]] = []
    while True:
        score, scale = scores(f)
        beyond = np.flatnonzero(score > threshold)
        if not beyond.size:
            return f, excluded, None
        room = cap - len(excluded)
        if room <= 0:
            return f, excluded, Stopped(beyond.size, float(np.nanmedian(scale)))
        worst = beyond[np.argsort(-score[beyond], kind="stable")]
        batch = worst[score[worst] > score[worst[0]] / 2][:room]
        trial = used.copy()
        trial[batch] = False
        try:
            refit = fit_rows(trial)
        except (ProblemError, DesignError) as e:  # keep the rows and the last good fit
            return f, excluded, Stopped(row=int(batch[0]), score=float(score[batch[0]]), error=e)
        excluded += [(int(i), float(score[i]), float(scale[i])) for i in batch]
        used, f = trial, refit
