"""Numeric measures of a calibration plan: the test-pose measure and the classical criteria.

For a plan of m experiments with transformation matrices ``B_i`` (stacked: ``S``), the
information matrix is ``M = sum_i B_i^T B_i = S^T S`` and ``cov(X) = sigma^2 M^-1``.

* test-pose measure (paper eq. 12 and 15): ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``, the
  expected mean square error (m^2) at test pose j after compensation; reported as the RMS error
  ``sqrt(rho_j)`` (m) and its maximum over the test poses.
* the score of every criterion of :data:`casadi_design.measures.criteria.CRITERIA` (D: ``log det M``,
  A: ``trace M^-1``, E: ``s_L``, T: ``trace M``, condition: ``s_1 / s_L``, I: ``sqrt(mean_j
  rho_j)``), each computed by its registry entry from the plan's spectrum and rho.
* observability indices: O1 = (s_1...s_L)^(1/L) / sqrt(m), O2 = s_L / s_1, O3 = s_L,
  O4 = s_L^2 / s_1, O5 = 1 / sum(1 / s_l).

These numpy functions are the twins of the NLP objectives of :mod:`casadi_design.measures.objectives`;
tests check that both agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .criteria import CRITERIA, PlanSpectrum

#: Relative eigenvalue threshold below which M counts as singular.
SINGULAR_RTOL = 1e-12


@dataclass(frozen=True)
class Scores:
    """Every measure of one plan, in SI units of B (lengths in m).

    ``rms_error_m`` (s,): ``sqrt(rho_j)`` at each test pose; ``values``: the score of every
    criterion, by its :attr:`~casadi_design.measures.criteria.Criterion.score` key (the registry's
    order); ``observability``: O1..O5.
    """

    rms_error_m: np.ndarray
    values: dict[str, float]
    observability: dict[str, float]
    identifiable: bool

    def value(self, criterion: str) -> float:
        """The score of ``criterion``."""
        return float(self.values[CRITERIA[criterion].score])

    @property
    def max_rms_error_m(self) -> float:
        """``max_j sqrt(rho_j)`` (m), the test-pose score."""
        return self.value("test-pose")

    def as_dict(self) -> dict:
        return {"rms_error_m": [float(v) for v in self.rms_error_m], **self.values,
                "observability": self.observability, "identifiable": self.identifiable}


def information_matrix(B: np.ndarray) -> np.ndarray:
    """``M = sum_i B_i^T B_i`` for ``B`` of shape (m, d, L) (or the stacked S, shape (m d, L))."""
    S = np.asarray(B, dtype=float).reshape(-1, np.shape(B)[-1])
    return S.T @ S


def information_matrices(B: np.ndarray) -> np.ndarray:
    """``B_i^T B_i`` of each experiment of ``B`` (m, d, L): shape (m, L, L), whose sum is
    :func:`information_matrix`."""
    B = np.asarray(B, dtype=float)
    return np.einsum("kri,krj->kij", B, B)


def rho_at_test_poses(M: np.ndarray, B0: np.ndarray, sigma: float) -> np.ndarray:
    """``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)`` (m^2) for ``B0`` of shape (s, r, L).

    Infinite where ``M`` is singular.
    """
    return rho_of_plans(np.asarray(M, dtype=float)[None], B0, sigma)[0]


def rho_of_plans(M: np.ndarray, B0: np.ndarray, sigma: float) -> np.ndarray:
    """``rho_j`` (k, s), m^2, of k plans' information matrices ``M`` (k, L, L) at once:
    ``sigma^2 |C^-1 B0_j^T|^2`` with ``M = C C^T``; infinite for a plan whose ``M`` is not
    positive definite."""
    B0 = np.asarray(B0, dtype=float)
    rho = np.full((len(M), B0.shape[0]), np.inf)
    try:
        C = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:  # some singular: each on its own
        for i, Mi in enumerate(M):
            try:
                rho[i] = rho_of_plans(Mi[None], B0, sigma)[0]
            except np.linalg.LinAlgError:
                pass
        return rho
    s, r, L = B0.shape
    rhs = np.broadcast_to(B0.transpose(2, 0, 1).reshape(L, s * r), (len(M), L, s * r))
    Y = np.linalg.solve(C, rhs).reshape(len(M), L, s, r)  # one solve per plan, every test pose its right-hand side
    return sigma**2 * np.einsum("kisj,kisj->ks", Y, Y)


def plan_spectra(M: np.ndarray, B0: np.ndarray, sigma: float) -> list[PlanSpectrum]:
    """What the scores of k plans are computed from (:class:`~casadi_design.measures.criteria.PlanSpectrum`),
    their information matrices ``M`` (k, L, L) at once: the eigenvalues, ``rho`` at the test
    poses (infinite for a plan that does not identify X), the trace, ``log det M = sum log
    lam`` and ``tr M^-1 = sum 1 / lam``."""
    lam = np.clip(np.linalg.eigvalsh(M)[:, ::-1], 0.0, None)
    regular = lam[:, -1] > SINGULAR_RTOL * np.maximum(lam[:, 0], np.finfo(float).tiny)
    rho = np.full((len(M), np.shape(B0)[0]), np.inf)
    if regular.any():
        rho[regular] = rho_of_plans(M[regular], B0, sigma)
    trace = np.trace(M, axis1=1, axis2=2)
    with np.errstate(divide="ignore"):
        log_det, trace_inv = np.sum(np.log(lam), axis=1), np.sum(1.0 / lam, axis=1)
    return [PlanSpectrum(l, np.sqrt(l), r, float(t), bool(ok), float(ld), float(ti))
            for l, r, t, ok, ld, ti in zip(lam, rho, trace, regular, log_det, trace_inv)]


def observability_indices(sv: np.ndarray, m: int) -> dict[str, float]:
    """O1..O5 from the singular values ``sv`` (descending) of the stacked S of m experiments."""
    L = len(sv)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {
            "O1": float(np.exp(np.mean(np.log(sv))) / np.sqrt(m)),
            "O2": float(sv[-1] / sv[0]),
            "O3": float(sv[-1]),
            "O4": float(sv[-1] ** 2 / sv[0]),
            "O5": float(1.0 / np.sum(1.0 / sv)) if sv[-1] > 0 else 0.0,
        } if L else {}


def score_plan(B: np.ndarray, B0: np.ndarray, sigma: float, M_held: np.ndarray | None = None,
               m_held: int = 0, rho: np.ndarray | None = None) -> Scores:
    """All measures of a plan, of the campaign ``M = M_held + sum_i B_i^T B_i`` when
    information is held before it (:mod:`casadi_design.calibration.held`).

    Parameters
    ----------
    B : ndarray, shape (m, d, L)
        Transformation matrices of the m experiments (measured rows).
    B0 : ndarray, shape (s, r, L)
        Transformation matrices at the s test poses (required rows).
    sigma : float, m
        Standard deviation of the measurement noise.
    M_held : ndarray, shape (L, L), or None
        Information of the experiments already measured and of the prior.
    m_held : int
        Number of experiments already measured (the observability indices count them).
    rho : ndarray, shape (s,), m^2, or None
        ``rho_j`` of a measure other than the paper's (the unmodelled error's field,
        :mod:`casadi_design.measures.field`); None: ``sigma^2 trace(B0_j M^-1 B0_j^T)``.
    """
    B = np.asarray(B, dtype=float)
    M = information_matrix(B)
    if M_held is not None:
        M = M + M_held
    spectrum = plan_spectra(M[None], B0, sigma)[0]
    if rho is not None and spectrum.identifiable:
        spectrum = spectrum._replace(rho=np.asarray(rho, dtype=float))
    return Scores(
        rms_error_m=np.sqrt(spectrum.rho),
        values={c.score: float(c.score_of(spectrum)) for c in CRITERIA.values()},
        observability=observability_indices(spectrum.sv, B.shape[0] + m_held),
        identifiable=spectrum.identifiable,
    )
