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
    largest), and over the pool, row i of every candidate's block together (the engine's
    arithmetic runs on contiguous vectors over the candidates): ``G = B N`` (d, k, L), ``V``
    (d, d, k) with ``V[i, j, c] = (B_c N B_c^T)_ij`` and, when rho is read, ``rho`` (s,), m^2
    and ``Y = B N B0^T`` (d, k, s r)."""

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
    """The pool's rows ``B`` (k, d, L) (computed in batch, :meth:`~casadi_design.calibration.models.CalibrationModel.B_stack`),
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
    def _per_pose(self) -> np.ndarray:
        """The sum of a test pose's r rows: (s r, s) of ones and zeros."""
        s, r = self.B0.shape[:2]
        return np.kron(np.eye(s), np.ones((r, 1)))

    @cached_property
    def _B_rows(self) -> np.ndarray:
        """``B`` by rows of the blocks: (d, k, L)."""
        return np.ascontiguousarray(self.B.transpose(1, 0, 2))

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
        G = self._B_rows @ N
        rho = Y = None
        if reads == "rho":
            Y = G @ self._B0_rows.T
            s = self.B0.shape[0]
            rho = self.sigma**2 * np.sum((self._B0_rows @ Ci.T) ** 2, axis=1).reshape(s, -1).sum(axis=1)
        return PlanState(tuple(S), M, N, float(2.0 * np.sum(np.log(np.diag(C)))), regular, G,
                         np.einsum("ikl,jkl->ijk", G, self._B_rows), rho, Y)

    def priced(self, state: PlanState, cands: np.ndarray | None, reads: str, removed: int | None = None) -> PlanSpectrum:
        """The plans ``state.S`` plus each candidate of ``cands`` (pool indices; None: every
        posture of the pool, the plan's own among them, in the pool's order), less the
        experiment ``removed`` (a pool index of ``state.S``; None: an addition): a
        :class:`~casadi_design.measures.criteria.PlanSpectrum` whose fields have a leading
        axis of candidates, with ``identifiable`` and the field ``reads`` filled (module
        docstring). On the state of a regularised plan (``eps`` > 0) the values are those of
        the regularised M (the log det the greedy plan climbs while M is singular)."""
        c = slice(None) if cands is None else np.asarray(cands, dtype=int)
        rhs = {"rho": state.Y, "trace_inv": state.G}.get(reads)
        logabs, ok, q = _capacitance(state, self.B, c, removed, rhs)
        trace_M = np.trace(state.M) + self.trace_A[c] - (0.0 if removed is None else self.trace_A[removed])
        fields: dict = {}
        if reads == "log_det":
            fields["log_det"] = np.where(ok, state.log_det + logabs, -np.inf)
        elif reads == "trace_inv":
            fields["trace_inv"] = np.where(ok, np.trace(state.N) - q.sum(axis=1), np.inf)
        elif reads == "rho":
            rho = state.rho - self.sigma**2 * (q @ self._per_pose)
            ok = ok & np.all(rho > 0.0, axis=1)  # not: a change that leaves M all but singular (cancellation)
            fields["rho"] = np.where(ok[:, None], rho, np.inf)
        elif reads == "lam":
            M = state.M + self.A[c] - (0.0 if removed is None else self.A[removed])
            lam = np.clip(np.linalg.eigvalsh(M)[:, ::-1], 0.0, None)
            ok = ok & (lam[:, -1] > SINGULAR_RTOL * np.maximum(lam[:, 0], np.finfo(float).tiny))
            fields.update(lam=lam, sv=np.sqrt(lam))
        return PlanSpectrum(fields.get("lam"), fields.get("sv"), fields.get("rho"), trace_M, ok,
                            fields.get("log_det"), fields.get("trace_inv"))

    def keys(self, criterion: str, state: PlanState, cands: np.ndarray | None, removed: int | None = None,
             power: float | None = None) -> np.ndarray:
        """The score of each changed plan (:meth:`priced`) as a quantity to minimise (:func:`key`);
        with ``power``, the criterion's smooth surrogate of that power
        (:attr:`~casadi_design.measures.criteria.Criterion.smoothed`)."""
        return key(criterion, score(criterion, self.priced(state, cands, CRITERIA[criterion].reads, removed), power))


def score(criterion: str, spectrum: PlanSpectrum, power: float | None = None) -> np.ndarray:
    """The criterion's score of the plans of ``spectrum`` or, with ``power``, its smooth
    surrogate of that power."""
    c = CRITERIA[criterion]
    return c.score_of(spectrum) if power is None else c.smoothed(spectrum, power)


def key(criterion: str, value: np.ndarray | float) -> np.ndarray:
    """A criterion's score as a quantity to minimise: negated for a maximised criterion, NaN
    and a singular plan (infinite) last."""
    value = np.asarray(value, dtype=float)
    value = value if CRITERIA[criterion].sense == "min" else -value
    return np.where(np.isfinite(value), value, np.inf)


#: The removed experiment's block ``B_a N B_a^T - I`` of the capacitance is inverted on its own
#: when its reciprocal condition number is above this (the rest of the plan regular); else the
#: candidate's block is eliminated first (:func:`_capacitance_added_first`).
BLOCK_RCOND = 1e-8


def _capacitance(state: PlanState, B: np.ndarray, c: np.ndarray | slice, removed: int | None,
                 rhs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """For each candidate of ``c``: ``log |det K|``, whether the changed M is positive definite,
    and with right-hand sides ``rhs`` (d, k, p) over the pool (``U^T N`` times p columns: ``Y``
    for rho, ``G`` for the trace) the quadratic forms ``diag(Y^T K^-1 Y)``, (n, p).

    An addition: ``K = R = I + V_c``, symmetric positive definite. A swap: ``K = [[P, X^T], [X,
    R]]`` with ``P = V_a - I`` (negative definite while the rest of the plan is regular) and ``X
    = B_c N B_a^T``; by block elimination ``det K = det P det S`` and ``Y^T K^-1 Y = Y_a^T P^-1
    Y_a + Z^T S^-1 Z`` with the Schur complement ``S = R - X P^-1 X^T`` (positive definite
    exactly when the changed M is) and ``Z = Y_c - X P^-1 Y_a``. Where the rest of the plan is
    singular (P cannot be inverted) R is eliminated first (:func:`_capacitance_added_first`).
    The d x d Cholesky factors and triangular solves run entry by entry as vectors over the
    candidates (:func:`_cholesky_small`), not one LAPACK call per candidate."""
    d = B.shape[1]
    S = np.array([[state.V[i, j][c] + (i == j) for j in range(d)] for i in range(d)])  # (d, d, n)
    Z = None if rhs is None else [rhs[i][c] for i in range(d)]
    const, logabs0 = 0.0, 0.0
    if removed is not None:
        P = state.V[:, :, removed] - np.eye(d)
        sign, logabs0 = np.linalg.slogdet(P)
        if sign != (-1.0) ** d or 1.0 / np.linalg.cond(P) < BLOCK_RCOND:
            return _capacitance_added_first(state, B, c, S, Z, removed, rhs)
        Pi = np.linalg.inv(P)
        X = [state.G[i][c] @ B[removed].T for i in range(d)]  # row i of B_c N B_a^T, (n, d) each
        XPi = [x @ Pi for x in X]
        for i in range(d):
            for j in range(d):
                S[i, j] -= np.einsum("nl,nl->n", XPi[i], X[j])
        if rhs is not None:
            Ya = rhs[:, removed]
            Z = [Z[i] - XPi[i] @ Ya for i in range(d)]
            const = np.sum(Ya * (Pi @ Ya), axis=0)
    C, ok = _cholesky_small(S)
    logabs = logabs0 + _log_det_small(C, ok)
    if rhs is None:
        return logabs, ok, None
    return logabs, ok, const + sum(w * w for w in _forward_small(C, Z))


def _capacitance_added_first(state: PlanState, B: np.ndarray, c: np.ndarray | slice, R: np.ndarray,
                             Yc: list[np.ndarray] | None, removed: int, rhs: np.ndarray | None
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`_capacitance` of a swap whose rest of the plan is singular: ``R = I + V_c`` (d, d,
    n) is eliminated first. With ``R = C_R C_R^T``, ``E = C_R^-1 X`` and ``W = C_R^-1 Y_c``, the
    block ``-T = I - V_a + E^T E`` (minus the Schur complement of R: the removed block of the
    plan with c added) is positive definite exactly when the changed M is; then ``|det K| = det
    R det(-T)`` and ``Y^T K^-1 Y = |W|^2 - |C_T^-1 (Y_a - E^T W)|^2`` with ``-T = C_T C_T^T``."""
    d = B.shape[1]
    C_R, ok = _cholesky_small(R)
    E = _forward_small(C_R, [state.G[i][c] @ B[removed].T for i in range(d)])  # rows of C_R^-1 X, (n, d)
    V_a = state.V[:, :, removed]
    T = np.array([[(i == j) - V_a[i, j] + sum(E[l][:, i] * E[l][:, j] for l in range(d)) for j in range(d)]
                  for i in range(d)])
    C_T, ok_T = _cholesky_small(T)
    ok = ok & ok_T
    logabs = _log_det_small(C_R, ok) + _log_det_small(C_T, ok)
    if rhs is None:
        return logabs, ok, None
    W = _forward_small(C_R, Yc)
    Ya = rhs[:, removed]
    U = _forward_small(C_T, [Ya[j] - sum(E[l][:, j, None] * W[l] for l in range(d)) for j in range(d)])
    return logabs, ok, sum(w * w for w in W) - sum(u * u for u in U)


def _log_det_small(C: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``log det`` of the matrices whose Cholesky factors are ``C`` (d, d, n) (0 where not ok)."""
    return 2.0 * np.sum(np.log(np.where(ok, np.diagonal(C).T, 1.0)), axis=0)


def _forward_small(C: np.ndarray, Z: list[np.ndarray]) -> list[np.ndarray]:
    """``C^-1 Z`` by rows for lower triangular ``C`` (d, d, n) and the d rows of Z, (n, p) each."""
    W: list[np.ndarray] = []
    for i in range(C.shape[0]):
        w = Z[i].copy()
        for j in range(i):
            w -= C[i, j][:, None] * W[j]
        w /= C[i, i][:, None]
        W.append(w)
    return W


def _cholesky_small(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of many small symmetric matrices ``S`` (d, d, n) entry by entry
    as vectors over n, and whether each is positive definite (the factor of one that is not:
    finite, unused)."""
    d, n = S.shape[0], S.shape[2]
    C = np.zeros_like(S)
    ok = np.ones(n, dtype=bool)
    for j in range(d):
        pivot = S[j, j] - sum(C[j, l] ** 2 for l in range(j))
        ok &= pivot > 0.0
        C[j, j] = np.sqrt(np.where(pivot > 0.0, pivot, 1.0))
        for i in range(j + 1, d):
            C[i, j] = (S[i, j] - sum(C[i, l] * C[j, l] for l in range(j))) / C[j, j]
    return C, ok
