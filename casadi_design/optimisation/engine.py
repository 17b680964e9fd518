"""The pool engine: every candidate of a finite pool priced at once by low-rank updates.

A plan of experiments from a pool of k (experiment i: rows ``B_i``, d x L, information ``A_i =
B_i^T B_i``) has ``M = M_held + sum_{i in S} A_i``. Adding a candidate c changes M by ``B_c^T
B_c`` (rank d); swapping a chosen experiment a for c by ``U D U^T`` with ``U = [B_a^T, B_c^T]``
(L x 2d) and ``D = diag(-I_d, I_d)`` (rank 2d). With ``N = M^-1`` and the capacitance ``K = D
+ U^T N U`` (Sherman-Morrison-Woodbury; ``D`` drops for an addition, ``U = B_c^T``):

    M'^-1 = N - (N U) K^-1 (N U)^T,
    log det M' = log det M + log |det K|            (det K has the sign (-1)^d of det D),
    tr M'^-1 = tr N - tr(K^-1 (N U)^T (N U)),
    rho_j' = rho_j - sigma^2 tr(Y_j^T K^-1 Y_j),    Y_j = U^T N B0_j^T   (m^2),
    tr M' = tr M + tr A_c - tr A_a,

and the spectrum (E, condition) from ``eigvalsh(M')``. Per plan, ``G = B N`` (k, d, L), ``V_c
= B_c N B_c^T`` and, for rho, ``Y_c = B_c N B0^T`` are computed once for the whole pool (k d L
(L + s r) flops); then one position of the plan prices all k candidates with 2d x 2d systems
(k (2d)^2 (d + s r)). This is the fast exchange of Cook and Nachtsheim (1980); Atkinson, Donev
and Tobias, Optimum Experimental Designs (2007), ch. 12.

Each criterion reads one quantity of the plan (:attr:`~casadi_design.measures.criteria.Criterion.reads`)
and its own score function turns it into its score, for every candidate at once: the formula of
a criterion exists once. :func:`~casadi_design.measures.measures.score_plan` stays the judge of a
chosen plan (tests check the engine against it on random swaps).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..measures.criteria import CRITERIA, PlanSpectrum
from ..measures.measures import SINGULAR_RTOL, information_matrices


@dataclass(frozen=True, eq=False)
class PlanState:
    """What the engine keeps of one plan ``S`` (pool indices) to price its changes (module
    docstring): ``M`` (L, L), ``N = (M + eps I)^-1``, ``log_det`` of ``M + eps I``, whether M is
    regular (its eigenvalues above :data:`~casadi_design.measures.measures.SINGULAR_RTOL` of the
    largest), and over the pool ``G = B N`` (k, d, L), ``V`` (k, d, d) and, when rho is read,
    ``rho`` (s,), m^2 and ``Y`` (k, d, s r)."""

    S: tuple[int, ...]
    M: np.ndarray
    N: np.ndarray
    log_det: float
    regular: bool
    G: np.ndarray
    V: np.ndarray
    rho: np.ndarray | None
    Y: np.ndarray | None


@dataclass(frozen=True, eq=False)
class PoolEngine:
    """The pool's rows ``B`` (k, d, L) (computed in batch, :meth:`~casadi_design.model.models.CalibrationModel.B_stack`),
    the test poses' ``B0`` (s, r, L), the noise ``sigma`` (m) and the information held before
    the plan ``M_held`` (L, L; None: none)."""

    B: np.ndarray
    B0: np.ndarray
    sigma: float
    M_held: np.ndarray | None = None

    @cached_property
    def A(self) -> np.ndarray:
        """``A_i = B_i^T B_i`` of every candidate, (k, L, L)."""
        return information_matrices(self.B)

    @cached_property
    def trace_A(self) -> np.ndarray:
        return np.trace(self.A, axis1=1, axis2=2)

    @cached_property
    def _B0_rows(self) -> np.ndarray:
        """``B0`` as (s r, L)."""
        return np.asarray(self.B0, dtype=float).reshape(-1, self.B.shape[2])

    def state(self, S: list[int] | tuple[int, ...], reads: str, eps: float = 0.0) -> PlanState | None:
        """The :class:`PlanState` of the plan ``S`` for a criterion that reads ``reads``; with
        ``eps`` > 0 of ``M + eps I`` (a singular plan's regularised log det); None when ``M +
        eps I`` is not positive definite."""
        L = self.B.shape[2]
        M = (np.zeros((L, L)) if self.M_held is None else self.M_held.copy()) + self.A[list(S)].sum(axis=0)
        lam = np.linalg.eigvalsh(M)
        regular = bool(lam[0] > SINGULAR_RTOL * max(lam[-1], np.finfo(float).tiny))
        try:
            C = np.linalg.cholesky(M + eps * np.eye(L))
        except np.linalg.LinAlgError:
            return None
        Ci = np.linalg.solve(C, np.eye(L))
        N = Ci.T @ Ci
        k, d = self.B.shape[:2]
        G = (self.B.reshape(k * d, L) @ N).reshape(k, d, L)
        rho = Y = None
        if reads == "rho":
            Y = (G.reshape(k * d, L) @ self._B0_rows.T).reshape(k, d, -1)
            s = self.B0.shape[0]
            rho = self.sigma**2 * np.sum((self._B0_rows @ Ci.T) ** 2, axis=1).reshape(s, -1).sum(axis=1)
        return PlanState(tuple(S), M, N, float(2.0 * np.sum(np.log(np.diag(C)))), regular, G,
                         np.einsum("kil,kjl->kij", G, self.B), rho, Y)

    def priced(self, state: PlanState, cands: np.ndarray, reads: str, removed: int | None = None) -> PlanSpectrum:
        """The plans ``state.S`` plus each candidate of ``cands`` (pool indices), less the
        experiment ``removed`` (a pool index of ``state.S``; None: an addition): a
        :class:`~casadi_design.measures.criteria.PlanSpectrum` whose fields have a leading
        axis of candidates, with ``identifiable`` and the field ``reads`` filled (module
        docstring). On the state of a regularised plan (``eps`` > 0) the values are those of
        the regularised M (the log det the greedy plan climbs while M is singular)."""
        c = np.asarray(cands, dtype=int)
        rhs = {"rho": state.Y, "trace_inv": state.G}.get(reads)
        logabs, ok, q = _capacitance(state, self.B, c, removed, rhs)
        trace_M = np.trace(state.M) + self.trace_A[c] - (0.0 if removed is None else self.trace_A[removed])
        fields: dict = {}
        if reads == "log_det":
            fields["log_det"] = np.where(ok, state.log_det + logabs, -np.inf)
        elif reads == "trace_inv":
            fields["trace_inv"] = np.where(ok, np.trace(state.N) - q.sum(axis=1), np.inf)
        elif reads == "rho":
            drop = q.reshape(len(c), self.B0.shape[0], -1).sum(axis=2)
            fields["rho"] = np.where(ok[:, None], state.rho - self.sigma**2 * drop, np.inf)
        elif reads == "lam":
            M = state.M + self.A[c] - (0.0 if removed is None else self.A[removed])
            lam = np.clip(np.linalg.eigvalsh(M)[:, ::-1], 0.0, None)
            ok = ok & (lam[:, -1] > SINGULAR_RTOL * np.maximum(lam[:, 0], np.finfo(float).tiny))
            fields.update(lam=lam, sv=np.sqrt(lam))
        return PlanSpectrum(fields.get("lam"), fields.get("sv"), fields.get("rho"), trace_M, ok,
                            fields.get("log_det"), fields.get("trace_inv"))

    def keys(self, criterion: str, state: PlanState, cands: np.ndarray, removed: int | None = None) -> np.ndarray:
        """The score of each changed plan (:meth:`priced`) as a quantity to minimise (:func:`key`)."""
        c = CRITERIA[criterion]
        return key(criterion, c.score_of(self.priced(state, cands, c.reads, removed)))


def key(criterion: str, value: np.ndarray | float) -> np.ndarray:
    """A criterion's score as a quantity to minimise: negated for a maximised criterion, NaN
    and a singular plan (infinite) last."""
    value = np.asarray(value, dtype=float)
    value = value if CRITERIA[criterion].sense == "min" else -value
    return np.where(np.isfinite(value), value, np.inf)


#: The removed experiment's block ``B_a N B_a^T - I`` of the capacitance is inverted on its own
#: when its condition number is below this (the rest of the plan regular); else the whole 2d x
#: 2d capacitance is solved per candidate.
BLOCK_RCOND = 1e-8


def _capacitance(state: PlanState, B: np.ndarray, c: np.ndarray, removed: int | None,
                 rhs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """For each candidate of ``c``: ``log |det K|``, whether the changed M is positive definite,
    and with right-hand sides ``rhs`` (k, d, p) over the pool (``U^T N`` times p columns: ``Y``
    for rho, ``G`` for the trace) the quadratic forms ``diag(Y^T K^-1 Y)``, (n, p).

    An addition: ``K = I + V_c``, symmetric positive definite. A swap: ``K = [[P, X^T], [X, R]]``
    with ``P = V_a - I`` (negative definite while the rest of the plan is regular), ``X = B_c N
    B_a^T`` and ``R = I + V_c``; by block elimination ``det K = det P det S`` and ``Y^T K^-1 Y =
    Y_a^T P^-1 Y_a + Z^T S^-1 Z`` with the Schur complement ``S = R - X P^-1 X^T`` (positive
    definite exactly when the changed M is) and ``Z = Y_c - X P^-1 Y_a``. S is d x d: its
    Cholesky factor and the triangular solves run as array operations over the candidates
    (:func:`_cholesky_small`), not one LAPACK call per candidate."""
    d = B.shape[1]
    I = np.eye(d)
    S, Z, const, logabs0 = I + state.V[c], None if rhs is None else rhs[c], 0.0, 0.0
    if removed is not None:
        P = state.V[removed] - I
        sign, logabs0 = np.linalg.slogdet(P)
        if sign != (-1.0) ** d or 1.0 / np.linalg.cond(P) < BLOCK_RCOND:
            return _capacitance_whole(state, B, c, removed, rhs)
        Pi, n = np.linalg.inv(P), len(c)
        X = (state.G[c].reshape(n * d, -1) @ B[removed].T).reshape(n, d, d)  # B_c N B_a^T
        S = S - np.einsum("nik,njk->nij", (X.reshape(n * d, d) @ Pi).reshape(n, d, d), X)
        if rhs is not None:
            Ya = rhs[removed]
            PiYa = Pi @ Ya
            Z = Z - (X.reshape(n * d, d) @ PiYa).reshape(n, d, -1)
            const = np.sum(Ya * PiYa, axis=0)
    C, ok = _cholesky_small(S)
    logabs = logabs0 + 2.0 * np.sum(np.log(np.where(ok[:, None], np.diagonal(C, axis1=1, axis2=2), 1.0)), axis=1)
    if rhs is None:
        return logabs, ok, None
    W = _forward_small(C, Z)
    return logabs, ok, const + np.sum(W * W, axis=1)


def _capacitance_whole(state: PlanState, B: np.ndarray, c: np.ndarray, removed: int,
                       rhs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`_capacitance` of a swap whose rest of the plan is singular: the whole 2d x 2d K
    per candidate (sign ``(-1)^d`` where the changed M is positive definite)."""
    d, n = B.shape[1], len(c)
    I = np.eye(d)
    X = state.G[c] @ B[removed].T
    K = np.empty((n, 2 * d, 2 * d))
    K[:, :d, :d] = state.V[removed] - I
    K[:, :d, d:] = X.transpose(0, 2, 1)
    K[:, d:, :d] = X
    K[:, d:, d:] = I + state.V[c]
    sign, logabs = np.linalg.slogdet(K)
    ok = (sign == (-1.0) ** d) & np.isfinite(logabs)
    if rhs is None:
        return logabs, ok, None
    K = np.where(ok[:, None, None], K, np.eye(2 * d))  # the others: a placeholder, marked by ok
    Y = np.concatenate([np.broadcast_to(rhs[removed], (n, *rhs.shape[1:])), rhs[c]], axis=1)
    return logabs, ok, np.sum(Y * np.linalg.solve(K, Y), axis=1)


def _cholesky_small(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of many small symmetric matrices ``S`` (n, d, d) by array
    operations over n (d^3 / 6 of them), and whether each is positive definite (the factor of
    one that is not: finite, unused)."""
    n, d = S.shape[:2]
    C = np.zeros_like(S)
    ok = np.ones(n, dtype=bool)
    for j in range(d):
        pivot = S[:, j, j] - np.sum(C[:, j, :j] ** 2, axis=1)
        ok &= pivot > 0.0
        C[:, j, j] = np.sqrt(np.where(pivot > 0.0, pivot, 1.0))
        for i in range(j + 1, d):
            C[:, i, j] = (S[:, i, j] - np.sum(C[:, i, :j] * C[:, j, :j], axis=1)) / C[:, j, j]
    return C, ok


def _forward_small(C: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """``C^-1 Z`` for lower triangular ``C`` (n, d, d) and ``Z`` (n, d, p), by rows."""
    W = np.empty_like(Z)
    for i in range(C.shape[1]):
        W[:, i] = Z[:, i]
        for j in range(i):
            W[:, i] -= C[:, i, j, None] * W[:, j]
        W[:, i] /= C[:, i, i, None]
    return W
