"""The kriging of plans drawn from a pool, for the exchange with the field: what every pricing
shares, computed once.

The exchange prices, at each position a of a plan, every posture of the pool as the one that
takes it: the kriging variance rho of the held poses, the plan less a and the candidate
(:func:`~casadi_design.measures.field.added_rho`, a candidate's share in closed form). Its
inputs are products ``X^T V_r^-1 Y`` of the campaign less a (X, Y: the rows B, the cross
covariance k0 with the test poses, the covariance v with the pool's postures). Computed per
pricing they cost O(N^2 (k d + L + s r)); here:

- the held poses, conditioned on once (:class:`FieldPool`);
- :meth:`FieldPool.state`: once per plan (after each swap), ``V^-1`` of the plan's m d values
  and its products with B, k0 and v;
- :meth:`FieldPool.priced`: per position, the campaign less a by a rank-d downdate of those
  products (``V_r^-1 = Vi_rr - Vi_rA Vi_AA^-1 Vi_Ar``, A the d values of a): O(k d (L + s r) d);
- the covariance of each posture with every other (a row of d x k d, computed the first time
  a plan holds the posture and kept, least recently used out beyond :data:`ROW_BYTES`), each
  posture's own block and its cross covariance with the test poses, once.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from ..measures.field import Field, Sites, added_rho, covariance, held_part, noise, own_blocks, own_variance

#: Memory the covariance rows of the sites kept may take (bytes).
ROW_BYTES = 256 * 2**20


class FieldPool:
    """The held poses (h sites ``Sh``, rows ``Bh`` (h, d, L)) and a pool (k sites ``S``, rows
    ``B`` (k, d, L)) of a ``field`` with the tracker's ``sigma`` (m), the test poses' rows ``B0``
    (s, r, L) and sites ``S0``, the prior information ``P`` (L x L or None).

    The held poses never leave a plan: they are conditioned on once
    (:func:`~casadi_design.measures.field.held_part`). With their whitened covariance with the
    pool ``W = C_h^-1 V_h.``, a pool's kriging is that of the covariance ``V - W^T W`` given them,
    its rows ``B - W^T C_h^-1 B_h`` and cross covariance ``k0 - W^T C_h^-1 k0_h``, and G, R and
    tr(k0^T V^-1 k0) start from the held poses' own: a plan's system holds its own m d values
    alone."""

    def __init__(self, field: Field, sigma: float, Bh: np.ndarray, Sh: Sites, B: np.ndarray, S: Sites,
                 B0: np.ndarray, S0: Sites, P: np.ndarray | None = None):
        self.field, self.sites, self.h = field, S, len(Sh)
        k, d, L = B.shape
        s, r = B0.shape[:2]
        self.d, self.own, self.noise = d, own_variance(field, S0), noise(field, S, sigma)  # noise (d, d)
        self.k0 = covariance(field, S, S0).reshape(k, d, s * r)
        self.B, self.vcc = B, own_blocks(field, S, sigma)  # (k, d, L), (k, d, d)
        held = held_part(field, sigma, Bh, Sh, B0, S0, P)
        self.G0, self.R0, self.KK0 = held.G, held.R, held.KK
        self.W = None
        if len(Sh):
            self.W = W = solve_triangular(held.Ch, covariance(field, Sh, S).reshape(-1, k * d), lower=True,
                                          check_finite=False)  # (h d, k d)
            self.B = B - (W.T @ held.UB).reshape(k, d, L)
            self.k0 = self.k0 - (W.T @ held.Uk).reshape(k, d, s * r)
            self.vcc = self.vcc - _blocks(W, W, d)
        self.rows: OrderedDict[int, np.ndarray] = OrderedDict()
        self.keep = max(64, ROW_BYTES // (8 * d * k * d))

    def _rows(self, plan: np.ndarray) -> np.ndarray:
        """The covariance of the postures ``plan`` with every posture of the pool given the held
        poses (len(plan), d, k, d)."""
        new = [int(i) for i in plan if int(i) not in self.rows]
        if new:
            block = covariance(self.field, self.sites[new], self.sites)
            if self.W is not None:
                cols = (self.d * np.asarray(new)[:, None] + np.arange(self.d)).ravel()
                block = block - (self.W[:, cols].T @ self.W).reshape(block.shape)
            for i, row in zip(new, block):
                self.rows[i] = row
        out = np.stack([self.rows[int(i)] for i in plan]) if len(plan) else np.zeros((0, self.d, len(self.B), self.d))
        for i in plan:
            self.rows.move_to_end(int(i))
        while len(self.rows) > self.keep:
            self.rows.popitem(last=False)
        return out

    def state(self, plan: list[int]) -> KrigingState:
        """The kriging system of the pool's postures ``plan`` given the held poses: its inverse
        and its products with the rows, the test poses and every posture of the pool."""
        plan = np.asarray(plan, dtype=int)
        m, d, L = len(plan), self.d, self.B.shape[2]
        R = self._rows(plan)  # (m, d, k, d)
        V = R[:, :, plan, :].reshape(m * d, m * d) + np.kron(np.eye(m), self.noise)
        Vi = cho_solve(cho_factor(V, lower=True, check_finite=False), np.eye(m * d), check_finite=False) if m \
            else V
        X = {"B": self.B[plan].reshape(m * d, L), "k0": self.k0[plan].reshape(m * d, -1), "v": R.reshape(m * d, -1)}
        PX = {name: Vi @ x for name, x in X.items()}
        grams = {("B", "B"): X["B"].T @ PX["B"], ("k0", "B"): X["k0"].T @ PX["B"],
                 ("k0", "k0"): _blocks(X["k0"], PX["k0"], 1), ("v", "v"): _blocks(X["v"], PX["v"], d),
                 ("v", "B"): X["v"].T @ PX["B"], ("v", "k0"): X["v"].T @ PX["k0"]}
        return KrigingState(d, Vi, X, PX, grams)

    def priced(self, state: KrigingState, a: int | None, cands: np.ndarray | None = None) -> np.ndarray:
        """``rho`` (len(cands), s), m^2, of the held poses, ``state``'s plan less its position
        ``a`` (None: none) and each posture of ``cands`` (pool indices; None: every posture, a
        plan's own too, in the pool's order):
        :func:`~casadi_design.measures.field.added_rho` of the products with ``V^-1`` of that
        campaign (:meth:`KrigingState.products`)."""
        c = slice(None) if cands is None else np.asarray(cands, dtype=int)
        k, d, L = len(self.B[c]), self.d, self.B.shape[2]
        gram = state.products(a, None if cands is None else c)
        return added_rho(self.G0 + gram("B", "B"), self.R0 - gram("k0", "B").reshape(self.R0.shape),
                         self.KK0 + gram("k0", "k0").reshape(-1, self.R0.shape[1]).sum(axis=1),
                         self.vcc[c] - gram("v", "v"), self.B[c] - gram("v", "B").reshape(k, d, L),
                         self.k0[c] - gram("v", "k0").reshape(k, d, -1), self.own)

    def rho_added(self, plan: list[int], cands: np.ndarray) -> np.ndarray:
        """``rho`` (len(cands), s), m^2, of the held poses plus the pool's postures ``plan`` plus
        each of ``cands`` (pool indices)."""
        return self.priced(self.state(plan), None, cands)


@dataclass(frozen=True, eq=False)
class KrigingState:
    """The kriging system of a plan given the held poses (d values a posture): ``Vi =
    V^-1`` (N x N), its blocks ``X`` (the rows ``"B"`` N x L, the cross covariance with the test
    poses ``"k0"`` N x s r, the covariance with every posture of the pool ``"v"`` N x k d), ``PX =
    V^-1 X`` and the products ``grams[x, y] = X_x^T V^-1 X_y`` (of k0 with itself the diagonal
    (s r,), of v the d x d blocks of each posture (k, d, d))."""

    d: int
    Vi: np.ndarray
    X: dict
    PX: dict
    grams: dict

    def products(self, a: int | None, cands: np.ndarray | None):
        """``gram(x, y)``: :attr:`grams` over the campaign's values r less the plan's position
        ``a`` (A: its d values; None: none), the columns of v those of the postures ``cands``
        (None: all):
        with ``V_rr^-1 = Vi_rr - Vi_rA Vi_AA^-1 Vi_Ar``, ``x^T Vi y - x_A^T z_y - (Vi x)_A^T y_A
        - z_x^T Vi_AA^-1 z_y``, ``z = (Vi x)_A - Vi_AA x_A``."""
        d = self.d
        cols = slice(None) if cands is None else (d * np.asarray(cands)[:, None] + np.arange(d)).ravel()
        cands = slice(None) if cands is None else cands
        if a is not None:
            A = slice(a * d, (a + 1) * d)
            Vaa = self.Vi[A, A]
            Vaa_inv = np.linalg.inv(Vaa)
            xA = {"B": self.X["B"][A], "k0": self.X["k0"][A], "v": self.X["v"][A][:, cols]}
            pA = {"B": self.PX["B"][A], "k0": self.PX["k0"][A], "v": self.PX["v"][A][:, cols]}
            z = {x: pA[x] - Vaa @ xA[x] for x in xA}
            Viz = {x: Vaa_inv @ z[x] for x in z}

        def gram(x: str, y: str) -> np.ndarray:
            full = self.grams[x, y]
            if x == "v":
                full = full[cands] if y == "v" else full[cols]  # (a view where cands is every posture)
            if a is None:
                return full
            if (x, y) == ("v", "v") or (x, y) == ("k0", "k0"):
                b = d if x == "v" else 1
                return full - _blocks(xA[x], z[y], b) - _blocks(pA[x], xA[y], b) - _blocks(z[x], Viz[y], b)
            return full - xA[x].T @ z[y] - pA[x].T @ xA[y] - z[x].T @ Viz[y]

        return gram


def _blocks(X: np.ndarray, Y: np.ndarray, b: int) -> np.ndarray:
    """The diagonal b x b blocks of ``X^T Y`` (N x c each, c = j b): (j, b, b), or (c,) for b = 1."""
    if b == 1:
        return np.einsum("nc,nc->c", X, Y)
    N, c = X.shape
    return np.einsum("nja,njb->jab", X.reshape(N, c // b, b), Y.reshape(N, c // b, b), optimize=True)


def field_pool(problem, Q: np.ndarray, F: np.ndarray, B: np.ndarray) -> FieldPool:
    """The :class:`FieldPool` of the pool ``Q`` (k, n), rad, ``F`` (k, nF), N, of rows ``B`` (k,
    d, L) for ``problem`` (:class:`~casadi_design.problem.build.Problem`): its field, held poses,
    test poses and prior."""
    Bh, Sh = problem.field_held_rows
    return FieldPool(problem.field, problem.sigma_m, Bh, Sh, B, problem.field_sites(Q, F), problem.B0,
                     problem.field_test_sites, problem.field_prior)
