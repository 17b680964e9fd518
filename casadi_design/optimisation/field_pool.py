"""The kriging of plans drawn from a pool, for the exchange with the field: what every pricing
shares, computed once.

The exchange prices, at each position a of a plan, every posture of the pool as the one that
takes it: the kriging variance rho of the held poses, the plan less a and the candidate
(:func:`~casadi_design.measures.field.added_rho`, a candidate's share in closed form). Its
inputs are products ``X^T V_r^-1 Y`` of the campaign less a (X, Y: the rows B, the cross
covariance k0 with the test poses, the covariance v with the pool's postures). Computed per
pricing they cost O(N^2 (k d + L + s r)); here:

- :meth:`FieldPool.state`: once per plan (after each swap), ``V^-1`` of the whole campaign
  (N = (h + m) d values) and its products with B, k0 and v;
- :meth:`FieldPool.priced`: per position, the campaign less a by a rank-d downdate of those
  products (``V_r^-1 = Vi_rr - Vi_rA Vi_AA^-1 Vi_Ar``, A the d values of a): O(k d (L + s r) d);
- the covariance of each site with every other (a row of d x (h + k) d, computed the first time
  a plan holds the site and kept, least recently used out beyond :data:`ROW_BYTES`), each
  site's own block and its cross covariance with the test poses, once.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..measures.field import Field, Sites, added_rho, covariance, noise, own_blocks, own_variance

#: Memory the covariance rows of the sites kept may take (bytes).
ROW_BYTES = 256 * 2**20


class FieldPool:
    """The held poses (h sites, rows ``Bh`` (h, d, L)) and a pool (k sites ``S``, rows ``B``
    (k, d, L)) of a ``field`` with the tracker's ``sigma`` (m), the test poses' rows ``B0`` (s,
    r, L) and sites ``S0``, the prior information ``P`` (L x L or None). Sites are numbered
    held first: pool posture i is site h + i."""

    def __init__(self, field: Field, sigma: float, Bh: np.ndarray, Sh: Sites, B: np.ndarray, S: Sites,
                 B0: np.ndarray, S0: Sites, P: np.ndarray | None = None):
        self.field, self.sigma, self.P = field, sigma, P
        self.h = len(Sh)
        self.sites = Sh + S
        self.B = np.concatenate([Bh, B])
        self.B0, self.own = B0, own_variance(field, S0)
        n, d = len(self.sites), self.B.shape[1]
        self.d = d
        self.k0 = covariance(field, self.sites, S0).reshape(n, d, -1)  # (h + k, d, s r)
        self.vcc = own_blocks(field, self.sites, sigma)  # (h + k, d, d)
        self.noise = noise(field, self.sites, sigma)  # (d, d)
        self.rows: OrderedDict[int, np.ndarray] = OrderedDict()
        self.keep = max(64, ROW_BYTES // (8 * d * n * d))

    def _rows(self, sites: np.ndarray) -> np.ndarray:
        """The covariance of the ``sites`` with every site (len(sites), d, h + k, d)."""
        new = [int(i) for i in sites if int(i) not in self.rows]
        if new:
            block = covariance(self.field, self.sites[new], self.sites)
            for i, row in zip(new, block):
                self.rows[i] = row
        out = np.stack([self.rows[int(i)] for i in sites])
        for i in sites:
            self.rows.move_to_end(int(i))
        while len(self.rows) > self.keep:
            self.rows.popitem(last=False)
        return out

    def state(self, plan: list[int]) -> KrigingState:
        """The kriging system of the held poses plus the pool's postures ``plan``: its inverse
        and its products with the rows, the test poses and every posture of the pool."""
        sites = np.concatenate([np.arange(self.h), self.h + np.asarray(plan, dtype=int)])
        m, d, L = len(sites), self.d, self.B.shape[2]
        R = self._rows(sites)  # (m, d, h + k, d)
        V = R[:, :, sites, :].reshape(m * d, m * d) + np.kron(np.eye(m), self.noise)
        Vi = cho_solve(cho_factor(V, lower=True, check_finite=False), np.eye(m * d), check_finite=False)
        X = {"B": self.B[sites].reshape(m * d, L), "k0": self.k0[sites].reshape(m * d, -1),
             "v": R[:, :, self.h:, :].reshape(m * d, -1)}
        PX = {name: Vi @ x for name, x in X.items()}
        grams = {("B", "B"): X["B"].T @ PX["B"], ("k0", "B"): X["k0"].T @ PX["B"],
                 ("k0", "k0"): _blocks(X["k0"], PX["k0"], 1), ("v", "v"): _blocks(X["v"], PX["v"], d),
                 ("v", "B"): X["v"].T @ PX["B"], ("v", "k0"): X["v"].T @ PX["k0"]}
        return KrigingState(self.h, d, Vi, X, PX, grams)

    def priced(self, state: KrigingState, a: int | None, cands: np.ndarray) -> np.ndarray:
        """``rho`` (len(cands), s), m^2, of ``state``'s campaign less its plan's position ``a``
        (None: none) plus each posture of ``cands`` (pool indices):
        :func:`~casadi_design.measures.field.added_rho` of the products with ``V^-1`` of that
        campaign (:meth:`KrigingState.products`)."""
        cands = np.asarray(cands, dtype=int)
        k, d, L = len(cands), self.d, self.B.shape[2]
        gram, c = state.products(a, cands), self.h + cands
        return added_rho(gram("B", "B") + (0.0 if self.P is None else self.P), self.B0 - gram("k0", "B").reshape(self.B0.shape),
                         gram("k0", "k0").reshape(-1, self.B0.shape[1]).sum(axis=1), self.vcc[c] - gram("v", "v"),
                         self.B[c] - gram("v", "B").reshape(k, d, L), self.k0[c] - gram("v", "k0").reshape(k, d, -1),
                         self.own)

    def rho_added(self, plan: list[int], cands: np.ndarray) -> np.ndarray:
        """``rho`` (len(cands), s), m^2, of the held poses plus the pool's postures ``plan`` plus
        each of ``cands`` (pool indices)."""
        return self.priced(self.state(plan), None, cands)


@dataclass(frozen=True, eq=False)
class KrigingState:
    """The kriging system of a campaign (h held sites, then the plan's, d values each): ``Vi =
    V^-1`` (N x N), its blocks ``X`` (the rows ``"B"`` N x L, the cross covariance with the test
    poses ``"k0"`` N x s r, the covariance with every posture of the pool ``"v"`` N x k d), ``PX =
    V^-1 X`` and the products ``grams[x, y] = X_x^T V^-1 X_y`` (of k0 with itself the diagonal
    (s r,), of v the d x d blocks of each posture (k, d, d))."""

    h: int
    d: int
    Vi: np.ndarray
    X: dict
    PX: dict
    grams: dict

    def products(self, a: int | None, cands: np.ndarray):
        """``gram(x, y)``: :attr:`grams` over the campaign's values r less the plan's position
        ``a`` (A: its d values; None: none), the columns of v those of the postures ``cands``:
        with ``V_rr^-1 = Vi_rr - Vi_rA Vi_AA^-1 Vi_Ar``, ``x^T Vi y - x_A^T z_y - (Vi x)_A^T y_A
        - z_x^T Vi_AA^-1 z_y``, ``z = (Vi x)_A - Vi_AA x_A``."""
        d = self.d
        cols = (d * np.asarray(cands)[:, None] + np.arange(d)).ravel()
        if a is not None:
            A = slice((self.h + a) * d, (self.h + a + 1) * d)
            Vaa = self.Vi[A, A]
            Vaa_inv = np.linalg.inv(Vaa)
            xA = {"B": self.X["B"][A], "k0": self.X["k0"][A], "v": self.X["v"][A][:, cols]}
            pA = {"B": self.PX["B"][A], "k0": self.PX["k0"][A], "v": self.PX["v"][A][:, cols]}
            z = {x: pA[x] - Vaa @ xA[x] for x in xA}
            Viz = {x: Vaa_inv @ z[x] for x in z}

        def gram(x: str, y: str) -> np.ndarray:
            full = self.grams[x, y]
            if x == "v":
                full = full[cands] if y == "v" else full[cols]
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


def per_block(diag: np.ndarray, r: int) -> np.ndarray:
    """Sums of ``r`` consecutive entries (len / r,): a trace per test pose of its r components."""
    return diag.reshape(-1, r).sum(axis=1)

def field_pool(problem, Q: np.ndarray, F: np.ndarray, B: np.ndarray) -> FieldPool:
    """The :class:`FieldPool` of the pool ``Q`` (k, n), rad, ``F`` (k, nF), N, of rows ``B`` (k,
    d, L) for ``problem`` (:class:`~casadi_design.problem.build.Problem`): its field, held poses,
    test poses and prior."""
    Bh, Sh = problem.field_held_rows
    return FieldPool(problem.field, problem.sigma_m, Bh, Sh, B, problem.field_sites(Q, F), problem.B0,
                     problem.field_test_sites, problem.field_prior)
