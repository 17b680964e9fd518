"""The reduced-space NLP of the smooth criteria (test-pose, D, A, T): numeric derivatives.

IPOPT's variables are the plan and the test-pose bound only, ``x = (vec Q, vec V, t)`` in the
layout of :mod:`casadi_design.nlp`. Experiment i enters through its ``p = n + nv`` variables
``z_i = (q_i, v_i)`` and ``B_i = B(q_i, F(v_i))``; the criterion through the scaled information
matrix ``M = c sum_i B_i^T B_i`` (c: the NLP's ``scale``) and ``N = M^-1``. Small CasADi
functions of ONE experiment, mapped over the m experiments, give ``B``, ``dB/dz`` and the
weighted second derivative ``sum_kl W_kl d2B_kl/dz2`` (and the rows of the rules with their
derivatives); the rest is matrix calculus in numpy. For a variable a of experiment i,

    dM_a = c (dB_a^T B_i + B_i^T dB_a),
    d2M_ab = c (d2B_ab^T B_i + B_i^T d2B_ab + dB_a^T dB_b + dB_b^T dB_a)

for a, b of experiment i (0 for variables of two experiments).

The criterion's part ``phi(M)`` of the Lagrangian and its derivatives:

=========  ================================================  ================  =====
criterion  phi(M)                                            Gbar = dphi/dM    kappa
=========  ================================================  ================  =====
test-pose  sum_j mu_j rho_j = tr(P N),  P = sum_j mu_j H_j   -N P N            2
A          sigma_f tr(N)                                     -sigma_f N N      2
D          -sigma_f log det M                                -sigma_f N        1
T          -sigma_f tr(M)                                    -sigma_f I        0
=========  ================================================  ================  =====

with ``rho_j = tr(H_j N)``, ``H_j = c B0_j^T B0_j`` the test-pose rows ``rho_j - t <= 0`` (mu_j
their multipliers, sigma_f the objective's), and

    d phi = tr(Gbar dM_a),   d2 phi[a, b] = kappa tr(-Gbar dM_a N dM_b) + tr(Gbar d2M_ab).

(For ``tr(P N)``: ``d2 = 2 tr(G dM_a N dM_b) - tr(G d2M_ab)``, ``G = N P N``; for
``-log det M``: ``d2 = tr(N dM_a N dM_b) - tr(N d2M_ab)``.) The Jacobian of the test-pose rows
is ``J[j, a] = -tr(N H_j N dM_a)`` and ``-1`` for t. Since ``N = M^-1`` couples all
experiments, the Hessian is dense over the plan variables (block-diagonal for T, kappa = 0);
the rules add per-experiment and pairwise blocks. Units: q in rad (m for prismatic joints), v
and the scaled M without units.

IPOPT gets f, g, the gradient, the Jacobian and the upper triangle of the Hessian of the
Lagrangian through :class:`NumericFunction` callbacks; the quantities of the last point are
kept, so f, g and their derivatives at one x cost one evaluation each.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np
from scipy.linalg import solve_triangular

from .build import Problem
from .rules import load_variables, pose_constraints

#: kappa of each criterion of the reduced space (see the module docstring).
CURVATURE = {"test-pose": 2.0, "D": 1.0, "A": 2.0, "T": 0.0}


class NumericFunction(ca.Callback):
    """A CasADi function evaluated in Python on the nonzeros of its inputs and outputs.

    ``evaluate(*inputs) -> outputs``: 1-D arrays of the structural nonzeros (column-major), as
    declared by ``inputs`` and ``outputs`` (lists of ``(name, sparsity)``). The caller keeps the
    object alive as long as any CasADi function calls it.
    """

    def __init__(self, name: str, inputs: list[tuple[str, ca.Sparsity]],
                 outputs: list[tuple[str, ca.Sparsity]], evaluate: Callable):
        ca.Callback.__init__(self)
        self._inputs, self._outputs, self._evaluate = inputs, outputs, evaluate
        self.construct(name, {})

    def get_n_in(self) -> int:
        return len(self._inputs)

    def get_n_out(self) -> int:
        return len(self._outputs)

    def get_name_in(self, i: int) -> str:
        return self._inputs[i][0]

    def get_name_out(self, i: int) -> str:
        return self._outputs[i][0]

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return self._inputs[i][1]

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return self._outputs[i][1]

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg, res) -> int:
        # CasADi owns the buffers (and passes None for absent ones): copy the inputs
        args = [np.zeros(sp.nnz()) if a is None else np.array(np.frombuffer(a, dtype=float))
                for a, (_, sp) in zip(arg, self._inputs)]
        for r, value in zip(res, self._evaluate(*args)):
            if r is not None:
                np.frombuffer(r, dtype=float)[:] = value
        return 0


@dataclass(frozen=True, eq=False)
class BufferedFunction:
    """A CasADi function called through its buffers (``Function.buffer``): dense numpy inputs
    in, dense numpy outputs out, without the conversions of ``DM``. Not reentrant."""

    fn: ca.Function
    buffer: object
    call: Callable[[], None]
    args: tuple[np.ndarray, ...]
    res: tuple[np.ndarray, ...]
    #: column-major positions of each output's nonzeros in its dense matrix
    positions: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, fn: ca.Function) -> BufferedFunction:
        buffer, call = fn.buffer()
        args = tuple(np.zeros(fn.nnz_in(i)) for i in range(fn.n_in()))
        res = tuple(np.zeros(fn.nnz_out(i)) for i in range(fn.n_out()))
        for i, a in enumerate(args):
            assert fn.sparsity_in(i).is_dense()
            buffer.set_arg(i, memoryview(a))
        for i, r in enumerate(res):
            buffer.set_res(i, memoryview(r))
        positions = []
        for i in range(fn.n_out()):
            sp = fn.sparsity_out(i)
            positions.append(np.array(sp.row(), dtype=int) + sp.size1() * np.repeat(
                np.arange(sp.size2()), np.diff(sp.colind())))
        return cls(fn, buffer, call, args, res, tuple(positions))

    def __call__(self, *inputs: np.ndarray) -> list[np.ndarray]:
        """The outputs (copies) as dense arrays of their shape."""
        for a, x in zip(self.args, inputs):
            a[:] = np.ravel(x, order="F")
        self.call()
        out = []
        for i, (r, pos) in enumerate(zip(self.res, self.positions)):
            shape = self.fn.size_out(i)
            dense = np.zeros(shape[0] * shape[1])
            dense[pos] = r
            out.append(dense.reshape(shape, order="F"))
        return out


@dataclass(frozen=True, eq=False)
class ExperimentFunctions:
    """CasADi functions of one experiment's variables ``z = (q, v)`` (p = n + nv).

    ``c(z)`` are the experiment's rule rows: ``|v|^2`` when the load direction is free, then the
    workspace rows :func:`~casadi_design.rules.pose_constraints` of q (m).

    Attributes
    ----------
    values : ``z -> (B, c)``, B (d x L) unscaled.
    first : ``z -> (d vec(B) / dz (d L x p), dc/dz (nc x p))``.
    second : ``(z, W, lam) -> d2/dz2 (sum_kl W_kl B_kl + lam . c)`` (p x p), W (d x L), lam (nc).
    pair : ``u -> |q_a - q_b|^2`` (rad^2) for ``u = (q_a, q_b)``; ``pair_first``: its gradient
        (1 x 2n); ``pair_second``: ``(u, lam) -> lam`` times its Hessian (2n x 2n).
    """

    n: int
    nv: int
    nc: int
    values: ca.Function
    first: ca.Function
    second: ca.Function
    pair: ca.Function
    pair_first: ca.Function
    pair_second: ca.Function

    @property
    def p(self) -> int:
        return self.n + self.nv


@functools.cache
def experiment_functions(problem: Problem) -> ExperimentFunctions:
    """The functions of one experiment of ``problem`` (built once per problem)."""
    model, loads, rules = problem.model, load_variables(problem), pose_constraints(problem)
    n = model.n
    q, v = ca.SX.sym("q", n), ca.SX.sym("v", loads.nv)
    z = ca.vertcat(q, v)
    B = model.B(q, loads.loads(v))
    c = ca.vertcat(*([ca.sumsqr(v)] if loads.norm_lb is not None else []), rules.g(q))
    W, lam = ca.SX.sym("W", *B.shape), ca.SX.sym("lam", c.numel())
    second = ca.hessian(ca.dot(W, B) + ca.dot(lam, c), z)[0]
    qa, qb, mu = ca.SX.sym("qa", n), ca.SX.sym("qb", n), ca.SX.sym("mu")
    u = ca.vertcat(qa, qb)
    d = ca.sumsqr(qa - qb)
    cse = {"cse": True}  # common subexpressions of the kinematics: 10-35 % fewer operations
    return ExperimentFunctions(
        n, loads.nv, c.numel(),
        ca.Function("B", [z], [B, c], ["z"], ["B", "c"], cse),
        ca.Function("dB", [z], [ca.jacobian(ca.vec(B), z), ca.jacobian(c, z)], ["z"], ["dB", "dc"], cse),
        ca.Function("d2B", [z, W, lam], [second], ["z", "W", "lam"], ["d2"], cse),
        ca.Function("pair", [u], [d], ["u"], ["d"]),
        ca.Function("dpair", [u], [ca.jacobian(d, u)], ["u"], ["dd"]),
        ca.Function("d2pair", [u, mu], [ca.hessian(mu * d, u)[0]], ["u", "mu"], ["d2"]),
    )


@dataclass(frozen=True, eq=False)
class ReducedNLP:
    """The numeric NLP of one (criterion, m): f, g and their exact derivatives at any x.

    Attributes
    ----------
    B0s : ndarray, shape (s, r, L): ``sqrt(scale) B0``.
    cols : ndarray, shape (m, p): index in x of each experiment's variables z_i.
    rule_rows : ndarray, shape (m, nc): index in g of each experiment's rule rows.
    pairs : ndarray, shape (P, 2): the experiments (a < b) of each joint-distance row.
    pair_rows : ndarray, shape (P,): their index in g.
    n_rows : number of criterion rows (s for test-pose, 0 otherwise), first in g.
    nx, ng : sizes of x and g.
    """

    criterion: str
    m: int
    scale: float
    fns: ExperimentFunctions
    B0s: np.ndarray
    cols: np.ndarray
    rule_rows: np.ndarray
    pairs: np.ndarray
    pair_rows: np.ndarray
    n_rows: int
    nx: int
    ng: int
    last: list = field(default_factory=list)

    @cached_property
    def mapped(self) -> dict[str, BufferedFunction]:
        """The functions of :class:`ExperimentFunctions` mapped over the experiments (pairs)."""
        f, P = self.fns, len(self.pairs)
        out = {"values": f.values.map(self.m), "first": f.first.map(self.m),
               "second": f.second.map(self.m)}
        if P:
            out.update(pair=f.pair.map(P), pair_first=f.pair_first.map(P),
                       pair_second=f.pair_second.map(P))
        return {k: BufferedFunction.of(fn) for k, fn in out.items()}

    @cached_property
    def jacobian_pattern(self) -> np.ndarray:
        """Structural nonzeros of dg/dx (ng x nx, bool)."""
        J = np.zeros((self.ng, self.nx), dtype=bool)
        J[: self.n_rows, : self.cols.size] = True
        J[: self.n_rows, self.nx - 1] = self.n_rows > 0
        dc = np.array(ca.DM(self.fns.first.sparsity_out(1), 1.0), dtype=bool)
        J[self.rule_rows[:, :, None], self.cols[:, None, :]] = dc
        J[self.pair_rows[:, None], self.pair_cols] = True
        return J

    @cached_property
    def hessian_pattern(self) -> np.ndarray:
        """Structural nonzeros of the upper triangle of the Hessian of the Lagrangian (nx x nx,
        bool): dense over the plan variables where M^-1 couples every experiment (kappa > 0);
        for T, the blocks of each experiment and of each pair."""
        H = np.zeros((self.nx, self.nx), dtype=bool)
        if CURVATURE[self.criterion]:
            H[np.ix_(self.cols.ravel(), self.cols.ravel())] = True
        else:
            H[self.cols[:, :, None], self.cols[:, None, :]] = True
            H[self.pair_cols[:, :, None], self.pair_cols[:, None, :]] = True
        return np.triu(H)

    @cached_property
    def pair_cols(self) -> np.ndarray:
        """Index in x of ``(q_a, q_b)`` of each pair, shape (P, 2n)."""
        n = self.fns.n
        return np.concatenate([self.cols[self.pairs[:, 0], :n], self.cols[self.pairs[:, 1], :n]],
                              axis=1)

    def at(self, x: np.ndarray) -> _Point:
        """The quantities at x (those of the last call when x is the same)."""
        if self.last and np.array_equal(self.last[0].x, x):
            return self.last[0]
        point = _Point(self, np.array(x, dtype=float))
        self.last[:] = [point]
        return point

    def f_g(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pt = self.at(x)
        return np.array([pt.f]), pt.g

    def grad_f(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pt = self.at(x)
        return np.array([pt.f]), pt.grad_f

    def jac_g(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pt = self.at(x)
        return pt.g, pt.jac_g.T[self.jacobian_pattern.T]

    def hess_lag(self, x: np.ndarray, lam_f: float, lam_g: np.ndarray) -> np.ndarray:
        """The upper triangle (column-major nonzeros) of the Hessian of the Lagrangian
        ``lam_f d2f/dx2 + sum_k lam_g[k] d2g_k/dx2``."""
        return self.at(x).hess_lag(float(lam_f), lam_g).T[self.hessian_pattern.T]

    def functions(self) -> tuple[ca.Function, dict]:
        """The NLP ``(x, p) -> (f, g)`` and the nlpsol options with its derivative functions."""
        dense = ca.Sparsity.dense

        def pattern(mask: np.ndarray) -> ca.Sparsity:
            rows, cols = np.nonzero(mask)
            return ca.Sparsity.triplet(*mask.shape, rows.tolist(), cols.tolist())

        x_p = [("x", dense(self.nx, 1)), ("p", dense(0, 1))]
        f, g = ("f", dense(1, 1)), ("g", dense(self.ng, 1))
        oracle = NumericFunction("nlp", x_p, [f, g], lambda x, p: self.f_g(x))
        options = {
            "grad_f": NumericFunction("grad_f", x_p, [f, ("grad_f_x", dense(self.nx, 1))],
                                      lambda x, p: self.grad_f(x)),
            "jac_g": NumericFunction("jac_g", x_p, [g, ("jac_g_x", pattern(self.jacobian_pattern))],
                                     lambda x, p: self.jac_g(x)),
            "hess_lag": NumericFunction(
                "hess_lag", x_p + [("lam_f", dense(1, 1)), ("lam_g", dense(self.ng, 1))],
                [("triu_hess_gamma_x_x", pattern(self.hessian_pattern))],
                lambda x, p, lam_f, lam_g: [self.hess_lag(x, lam_f[0], lam_g)]),
            "no_nlp_grad": True,  # the multipliers' gradient would differentiate the callbacks
        }
        return oracle, options


@dataclass(frozen=True, eq=False)
class _Point:
    """Every quantity of a :class:`ReducedNLP` at one x, computed when first needed."""

    nlp: ReducedNLP
    x: np.ndarray

    @cached_property
    def Z(self) -> np.ndarray:
        """The experiments' variables, shape (p, m)."""
        return self.x[self.nlp.cols.T]

    @cached_property
    def _values(self) -> tuple[np.ndarray, np.ndarray]:
        B, c = self.nlp.mapped["values"](self.Z)
        return B.reshape(len(B), self.nlp.m, -1).transpose(1, 0, 2), c.T

    @property
    def B(self) -> np.ndarray:
        """Unscaled B_i, shape (m, d, L)."""
        return self._values[0]

    @cached_property
    def M(self) -> np.ndarray:
        return self.nlp.scale * np.einsum("ikl,ikn->ln", self.B, self.B)

    @cached_property
    def C(self) -> np.ndarray | None:
        """``C`` of ``M = C C^T`` (lower triangular); None when M is not positive definite."""
        try:
            return np.linalg.cholesky(self.M)
        except np.linalg.LinAlgError:
            return None

    @cached_property
    def Cinv(self) -> np.ndarray:
        return solve_triangular(self.C, np.eye(len(self.C)), lower=True)

    @cached_property
    def N(self) -> np.ndarray:
        return self.Cinv.T @ self.Cinv

    @cached_property
    def f(self) -> float:
        if self.C is None:
            return np.nan
        crit = self.nlp.criterion
        if crit == "test-pose":
            return float(self.x[-1])
        if crit == "D":
            return float(-2 * np.sum(np.log(np.diag(self.C))))
        if crit == "A":
            return float(np.sum(self.Cinv**2))
        return float(-np.trace(self.M))

    @cached_property
    def g(self) -> np.ndarray:
        nlp = self.nlp
        g = np.empty(nlp.ng)
        if nlp.n_rows:
            if self.C is None:
                g[: nlp.n_rows] = np.nan
            else:
                K = nlp.B0s @ self.Cinv.T
                g[: nlp.n_rows] = np.einsum("jrl,jrl->j", K, K) - self.x[-1]
        g[nlp.rule_rows] = self._values[1]
        if len(nlp.pairs):
            g[nlp.pair_rows] = nlp.mapped["pair"](self.x[nlp.pair_cols.T])[0].ravel()
        return g

    @cached_property
    def _first(self) -> tuple[np.ndarray, np.ndarray]:
        dB, dc = self.nlp.mapped["first"](self.Z)
        m, (d, L), p = self.nlp.m, self.B.shape[1:], self.nlp.fns.p
        return dB.reshape(L, d, m, p).transpose(2, 3, 1, 0), dc.reshape(-1, m, p).transpose(1, 0, 2)

    @property
    def dB(self) -> np.ndarray:
        """``dB_i / dz_i[a]``, unscaled, shape (m, p, d, L)."""
        return self._first[0]

    @cached_property
    def dM(self) -> np.ndarray:
        """``dM / dz_i[a]`` of every variable of the plan in the order of ``cols``: (m p, L, L)."""
        T = self.nlp.scale * np.einsum("iakl,ikn->ialn", self.dB, self.B)
        L = T.shape[-1]
        return (T + T.transpose(0, 1, 3, 2)).reshape(-1, L, L)

    @cached_property
    def Y(self) -> np.ndarray:
        """``N H_j N`` of every test pose, shape (s, L, L)."""
        E = self.nlp.B0s @ self.N
        return np.einsum("jrk,jrl->jkl", E, E)

    @cached_property
    def G_f(self) -> np.ndarray:
        """``df/dM`` (L x L) of D, A and T."""
        crit, L = self.nlp.criterion, len(self.M)
        if crit == "D":
            return -self.N
        return -self.N @ self.N if crit == "A" else -np.eye(L)

    @cached_property
    def grad_f(self) -> np.ndarray:
        nlp = self.nlp
        grad = np.zeros(nlp.nx)
        if nlp.criterion == "test-pose":
            grad[-1] = 1.0
        elif self.C is None:
            grad[:] = np.nan
        else:
            grad[nlp.cols.ravel()] = self.dM.reshape(len(self.dM), -1) @ self.G_f.ravel()
        return grad

    @cached_property
    def jac_g(self) -> np.ndarray:
        """dg/dx, dense (ng x nx)."""
        nlp = self.nlp
        J = np.zeros((nlp.ng, nlp.nx))
        if nlp.n_rows:
            if self.C is None:
                J[: nlp.n_rows] = np.nan
            else:
                L = len(self.M)
                dM = self.dM.reshape(-1, L * L)
                J[: nlp.n_rows, nlp.cols.ravel()] = -self.Y.reshape(-1, L * L) @ dM.T
            J[: nlp.n_rows, -1] = -1.0
        J[nlp.rule_rows[:, :, None], nlp.cols[:, None, :]] = self._first[1]
        if len(nlp.pairs):
            P, n2 = nlp.pair_cols.shape
            dd = nlp.mapped["pair_first"](self.x[nlp.pair_cols.T])[0].reshape(P, n2)
            J[nlp.pair_rows[:, None], nlp.pair_cols] = dd
        return J

    def hess_lag(self, lam_f: float, lam_g: np.ndarray) -> np.ndarray:
        """``lam_f d2f/dx2 + sum_k lam_g[k] d2g_k/dx2``, dense (nx x nx)."""
        nlp = self.nlp
        H = np.zeros((nlp.nx, nlp.nx))
        lam_c = lam_g[nlp.rule_rows]
        if self.C is None:
            H[:] = np.nan
            return H
        if nlp.criterion == "test-pose":
            Gbar = -np.einsum("j,jkl->kl", lam_g[: nlp.n_rows], self.Y)
        else:
            Gbar = lam_f * self.G_f
        kappa, c, dM, L = CURVATURE[nlp.criterion], nlp.scale, self.dM, len(self.M)
        cols = nlp.cols.ravel()
        if kappa:
            T = (-Gbar) @ dM @ self.N
            H[np.ix_(cols, cols)] = kappa * (T.reshape(-1, L * L) @ dM.reshape(-1, L * L).T)
        # tr(Gbar d2M_ab) = c (2 <B Gbar, d2B_ab> + 2 <dB_a Gbar, dB_b>), with the rules' rows
        W = 2 * c * (self.B @ Gbar)
        W = W.transpose(1, 0, 2).reshape(W.shape[1], -1)
        d2 = nlp.mapped["second"](self.Z, W, lam_c.T)[0]
        p = nlp.fns.p
        blocks = d2.reshape(p, nlp.m, p).transpose(1, 0, 2)
        blocks += 2 * c * np.einsum("iakl,ibkl->iab", self.dB @ Gbar, self.dB)
        H[nlp.cols[:, :, None], nlp.cols[:, None, :]] += blocks
        if len(nlp.pairs):
            P, n2 = nlp.pair_cols.shape
            mu = lam_g[nlp.pair_rows][None, :]
            d2p = nlp.mapped["pair_second"](self.x[nlp.pair_cols.T], mu)[0]
            np.add.at(H, (nlp.pair_cols[:, :, None], nlp.pair_cols[:, None, :]),
                      d2p.reshape(n2, P, n2).transpose(1, 0, 2))
        return H


def reduced_nlp(problem: Problem, criterion: str, m: int, B0: np.ndarray,
                scale: float) -> ReducedNLP:
    """The reduced-space NLP of ``criterion`` (a key of :data:`CURVATURE`) for m experiments.

    x = (vec Q, vec V, t for test-pose); g = (test-pose rows, load rows, workspace rows of
    each experiment, joint-distance rows of each pair a < b), as in :mod:`casadi_design.nlp`.
    """
    fns = experiment_functions(problem)
    n, nv = fns.n, fns.nv
    n_rows = B0.shape[0] if criterion == "test-pose" else 0
    idx = np.arange(m)[:, None]
    cols = np.concatenate([idx * n + np.arange(n), n * m + idx * nv + np.arange(nv)], axis=1)
    has_norm = int(load_variables(problem).norm_lb is not None)
    n_ws = fns.nc - has_norm
    rule_rows = np.concatenate([n_rows + idx + np.zeros((1, has_norm), dtype=int),
                                n_rows + has_norm * m + idx * n_ws + np.arange(n_ws)], axis=1)
    distance = problem.workspace.min_joint_distance_rad > 0
    pairs = np.array([(a, b) for a in range(m) for b in range(a + 1, m) if distance], dtype=int)
    first_pair = n_rows + fns.nc * m
    nx = (n + nv) * m + (criterion == "test-pose")
    return ReducedNLP(criterion, m, scale, fns, np.sqrt(scale) * B0, cols, rule_rows,
                      pairs.reshape(-1, 2), first_pair + np.arange(len(pairs)), n_rows, nx,
                      first_pair + len(pairs))
