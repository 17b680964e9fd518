"""The criteria's functions of the information matrix: value, gradient and curvature.

Each criterion of :mod:`casadi_design.measures.criteria` holds one of these objects; the reduced-space
NLP (:mod:`casadi_design.optimisation.reduced`) calls them and never asks which criterion it is solving.
All act on the scaled information matrix ``M`` (L x L) of the NLP, with ``M = C C^T``
(C lower triangular), ``N = M^-1`` and, for the criteria that weigh test poses, ``P``: the
criterion's weight matrix made from the scaled ``B0`` (:meth:`Objective.weights`).

==================  ==========================================  ================  =====
objective           phi(M)                                      G = dphi/dM       kappa
==================  ==========================================  ================  =====
test-pose (rows)    rho_j = tr(H_j N), H_j = B0_j^T B0_j        -N H_j N          2
A                   tr(N)                                       -N N              2
I                   tr(P N), P = mean_j H_j                     -N P N            2
D                   -log det M                                  -N                1
T                   -tr(M)                                      -I                0
E, condition        sum_k c_k l_{s_k r}(M) (spectral surrogate) U diag(b) U^T     --
==================  ==========================================  ================  =====

With ``dM_a`` the derivative of M along plan variable a, the second derivative of phi is
``kappa tr(-G dM_a N dM_b) + tr(G d2M_ab)`` (the first term is :meth:`Objective.curvature`;
the second is the same for every criterion and made by the NLP).

Spectral surrogates (E and condition, not smooth where eigenvalues repeat): the log power
means of the eigenvalues ``lambda_i`` of M,

    l_p(M) = (1/p) log( (1/L) sum_i lambda_i^p ),   l_{-r} -> log lambda_min,  l_r -> log lambda_max

as r -> infinity (``log lambda_min <= l_{-r} <= log lambda_min + log(L)/r``; Kiefer's phi_p).
With ``M = U diag(lambda) U^T``, ``w_i = lambda_i^p / sum_k lambda_k^p``, ``b_i = w_i / lambda_i``:

    dl_p = tr(U diag(b) U^T dM),
    d2l_p[E1, E2] = sum_ij Gamma_ij E1~_ij E2~_ij - p (b . diag E1~)(b . diag E2~),

``E~ = U^T E U``, ``Gamma_ij = (b_i - b_j) / (lambda_i - lambda_j)`` (``(p - 1) b_i / lambda_i``
for equal eigenvalues; Daleckii-Krein). Units: the scaled M has none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


class Spectrum(NamedTuple):
    """A spectral surrogate ``phi(M) = sum_k c_k l_{p_k}(M)`` at one M and its derivatives:
    ``grad = dphi/dM`` (L x L), ``Gamma`` (L x L) and ``R`` (L x L) such that
    ``d2phi[E1, E2] = sum_ij Gamma_ij E1~_ij E2~_ij + diag(E1~) . R diag(E2~)``,
    ``E~ = U^T E U``."""

    value: float
    U: np.ndarray
    grad: np.ndarray
    Gamma: np.ndarray
    R: np.ndarray


def log_power_mean(lam: np.ndarray, p: float) -> tuple[float, np.ndarray, np.ndarray]:
    """``l_p = (1/p) log(mean lambda^p)`` of positive ``lam`` (p != 0), its gradient ``b`` with
    respect to the eigenvalues and the divided differences ``Gamma`` of ``b`` (module
    docstring), computed without overflow for any p."""
    loglam = np.log(lam)
    z = p * loglam
    e = np.exp(z - z.max())
    S = e.sum()
    value = float((z.max() + np.log(S / len(lam))) / p)
    b = e / S / lam
    # Gamma_ij = (b_j / lam_j) expm1((p - 1) delta) / expm1(delta), delta = log(lam_i / lam_j),
    # taken from the side where (p - 1) delta <= 0 (no overflow; Gamma is symmetric)
    delta = loglam[:, None] - loglam[None, :]
    x = (p - 1) * delta
    base = (b / lam)[None, :]
    with np.errstate(all="ignore"):  # the branch np.where does not take may overflow
        A = np.where(delta == 0, (p - 1) * base, base * np.expm1(x) / np.expm1(delta))
    return value, b, np.where(x <= 0, A, A.T)


def spectrum(M: np.ndarray, terms: tuple[tuple[float, float], ...], r: float) -> Spectrum:
    """The surrogate ``sum_k c_k l_{s_k r}(M)`` of ``terms = ((c_k, s_k), ...)`` at positive
    definite M."""
    lam, U = np.linalg.eigh(M)
    value, b_sum = 0.0, np.zeros(len(lam))
    Gamma, R = np.zeros((len(lam),) * 2), np.zeros((len(lam),) * 2)
    for c, sign in terms:
        p = sign * r
        v, b, G = log_power_mean(lam, p)
        value += c * v
        b_sum += c * b
        Gamma += c * G
        R -= (c * p) * np.outer(b, b)
    return Spectrum(value, U, (U * b_sum) @ U.T, Gamma, R)


class Local(NamedTuple):
    """An objective at one M: its value and what its derivatives need (``spectrum`` for the
    spectral surrogates, else None)."""

    value: float
    spectrum: Spectrum | None = None


@dataclass(frozen=True)
class Objective:
    """phi(M) of one criterion in the reduced space (module docstring).

    ``epigraph``: the criterion is ``min t`` subject to one row ``tr(H_j N) <= t`` per test
    pose (test-pose), not an objective; its rows' weights are :meth:`weights`.
    """

    epigraph: bool = False
    kappa: float = 0.0
    #: phi > 0 at every regular M (A, I): ``log phi`` has its minimisers and no scale (the
    #: seated NLP, :mod:`casadi_design.optimisation.seated_nlp`, minimises it)
    positive: bool = False

    @property
    def couples(self) -> bool:
        """Whether phi couples the experiments (a Hessian dense over the plan variables)."""
        return self.kappa > 0

    def weights(self, B0s: np.ndarray) -> np.ndarray | None:
        """The weight matrix P of the objective from the scaled ``B0`` (s, r, L); None when
        phi does not weigh the test poses."""
        return None

    def at(self, M: np.ndarray, C: np.ndarray, Cinv: np.ndarray, P: np.ndarray | None,
           power: float) -> Local:
        """phi at M (``C``: Cholesky factor, ``Cinv = C^-1``; ``power``: r of a surrogate)."""
        raise NotImplementedError

    def gradient(self, local: Local, N: np.ndarray, P: np.ndarray | None) -> np.ndarray:
        """``dphi/dM`` (L x L) at the M of ``local``."""
        raise NotImplementedError

    def curvature(self, local: Local, G: np.ndarray, dM: np.ndarray, N: np.ndarray,
                  lam_f: float) -> np.ndarray:
        """The part of ``d2(lam_f phi)[dM_a, dM_b]`` besides ``tr(G d2M_ab)`` (V x V), with
        ``G = lam_f dphi/dM`` (for the epigraph ``-sum_j mu_j N H_j N``): ``kappa tr(-G dM_a N
        dM_b)`` for every pair of plan variables, ``dM`` (V, L, L)."""
        V, L = dM.shape[0], N.shape[0]
        if not self.kappa:
            return np.zeros((V, V))
        T = (-G) @ dM @ N
        return self.kappa * (T.reshape(V, L * L) @ dM.reshape(V, L * L).T)


@dataclass(frozen=True)
class EpigraphRows(Objective):
    """The test-pose epigraph: rows ``rho_j = tr(H_j N) = |B0_j C^-T|_F^2`` (values in
    :meth:`rows`), their multipliers weighting ``G = -sum_j lam_j N H_j N``."""

    epigraph: bool = True
    kappa: float = 2.0

    @staticmethod
    def rows(B0s: np.ndarray, Cinv: np.ndarray) -> np.ndarray:
        """``tr(H_j N)`` for each test pose j, shape (s,)."""
        s, r, L = B0s.shape
        K = B0s.reshape(s * r, L) @ Cinv.T
        return np.sum((K * K).reshape(s, r * L), axis=1)

    @staticmethod
    def row_gradients(B0s: np.ndarray, N: np.ndarray) -> np.ndarray:
        """``-d tr(H_j N)/dM = N H_j N``, shape (s, L, L)."""
        E = B0s @ N
        return E.transpose(0, 2, 1) @ E


@dataclass(frozen=True)
class TraceInverse(Objective):
    """A: ``tr(N) = |C^-1|_F^2``."""

    kappa: float = 2.0
    positive: bool = True

    def at(self, M, C, Cinv, P, power) -> Local:
        return Local(float(np.sum(Cinv * Cinv)))

    def gradient(self, local, N, P) -> np.ndarray:
        return -N @ N


@dataclass(frozen=True)
class MeanTestPose(Objective):
    """I: ``tr(P N) = mean_j tr(H_j N)``, ``P = mean_j H_j``: the mean of the test-pose
    rows (``rho_j = sigma^2 tr(H_j N)``)."""

    kappa: float = 2.0
    positive: bool = True

    def weights(self, B0s: np.ndarray) -> np.ndarray:
        return np.einsum("jri,jrl->il", B0s, B0s) / B0s.shape[0]

    def at(self, M, C, Cinv, P, power) -> Local:
        return Local(float(np.sum(P * (Cinv.T @ Cinv))))

    def gradient(self, local, N, P) -> np.ndarray:
        return -N @ P @ N


@dataclass(frozen=True)
class LogDet(Objective):
    """D: ``-log det M = -2 sum_i log C_ii``."""

    kappa: float = 1.0

    def at(self, M, C, Cinv, P, power) -> Local:
        return Local(float(-2 * np.sum(np.log(np.diag(C)))))

    def gradient(self, local, N, P) -> np.ndarray:
        return -N


@dataclass(frozen=True)
class Trace(Objective):
    """T: ``-tr(M)`` (linear in M: no curvature)."""

    def at(self, M, C, Cinv, P, power) -> Local:
        return Local(float(-np.trace(M)))

    def gradient(self, local, N, P) -> np.ndarray:
        return -np.eye(len(N))


@dataclass(frozen=True)
class SpectralSurrogate(Objective):
    """E and condition: ``sum_k c_k l_{s_k r}(M)`` for ``terms = ((c_k, s_k), ...)``."""

    terms: tuple[tuple[float, float], ...] = ()

    @property
    def couples(self) -> bool:
        return True

    def at(self, M, C, Cinv, P, power) -> Local:
        spec = spectrum(M, self.terms, power)
        return Local(spec.value, spec)

    def gradient(self, local, N, P) -> np.ndarray:
        return local.spectrum.grad

    def curvature(self, local, G, dM, N, lam_f) -> np.ndarray:
        sp, V, L = local.spectrum, dM.shape[0], N.shape[0]
        E = sp.U.T @ dM @ sp.U
        diag = np.diagonal(E, axis1=1, axis2=2)
        return lam_f * ((E * sp.Gamma).reshape(V, L * L) @ E.reshape(V, L * L).T
                        + diag @ sp.R @ diag.T)
