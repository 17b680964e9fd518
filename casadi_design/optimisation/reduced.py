"""The reduced-space NLP of every criterion: numeric derivatives.

IPOPT's variables are the plan and the test-pose bound only, ``x = (Q, V, t)`` in the
layout of :mod:`casadi_design.optimisation.nlp`. Experiment i enters through its ``p = n + nv`` variables
``z_i = (q_i, v_i)`` and ``B_i = B(q_i, F(v_i))``; the criterion through the scaled information
matrix ``M = c sum_i B_i^T B_i`` (c: the NLP's ``scale``) and ``N = M^-1``. Small CasADi
functions of ONE experiment, mapped over the m experiments, give ``B``, ``dB/dz`` and the
weighted second derivative ``sum_kl W_kl d2B_kl/dz2`` (and the rows of the rules with their
derivatives); the rest is matrix calculus in numpy. For a variable a of experiment i,

    dM_a = c (dB_a^T B_i + B_i^T dB_a),
    d2M_ab = c (d2B_ab^T B_i + B_i^T d2B_ab + dB_a^T dB_b + dB_b^T dB_a)

for a, b of experiment i (0 for variables of two experiments).

The criterion's part ``phi(M)`` of the Lagrangian, its gradient ``G = dphi/dM`` and its
curvature come from the criterion's registry entry (:mod:`casadi_design.measures.objectives`; this
module never asks which criterion it solves). For an epigraph criterion (test-pose) the rows
are ``rho_j - t <= 0``, ``rho_j = tr(H_j N)``, ``H_j = c B0_j^T B0_j`` (mu_j their
multipliers, sigma_f the objective's multiplier), and with ``Gbar = sigma_f G`` (or
``-sum_j mu_j N H_j N`` for the epigraph)

    d phi = tr(Gbar dM_a),   d2 phi[a, b] = curvature[a, b] + tr(Gbar d2M_ab),

the curvature being ``kappa tr(-Gbar dM_a N dM_b)`` for the smooth criteria.

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

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import casadi as ca
import numpy as np
from scipy.linalg.lapack import dpotrf, dtrtri

from ..measures.criteria import CRITERIA
from ..measures.objectives import EpigraphRows, Local, Objective
from ..plan.rules import joint_distance_sq
from ..problem.build import Problem, per_model
from ..problem.rules import CollisionRows
from ..robot.compiled import compiled_group


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
        # views of CasADi's buffers, valid during the call (None: an absent input or output)
        args = [np.zeros(sp.nnz()) if a is None else np.frombuffer(a, dtype=float)
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
    #: column-major positions of each output's nonzeros in its dense matrix, and its shape
    positions: tuple[np.ndarray, ...]
    shapes: tuple[tuple[int, int], ...]

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
        return cls(fn, buffer, call, args, res, tuple(positions),
                   tuple(tuple(fn.size_out(i)) for i in range(fn.n_out())))

    def __call__(self, *inputs: np.ndarray) -> list[np.ndarray]:
        """The outputs (copies) as dense arrays of their shape."""
        for a, x in zip(self.args, inputs):
            a[:] = np.ravel(x, order="F")
        self.call()
        out = []
        for r, pos, shape in zip(self.res, self.positions, self.shapes):
            if len(pos) == shape[0] * shape[1]:
                out.append(r.reshape(shape, order="F").copy())
            else:
                dense = np.zeros(shape[0] * shape[1])
                dense[pos] = r
                out.append(dense.reshape(shape, order="F"))
        return out


@dataclass(frozen=True, eq=False)
class ExperimentFunctions:
    """CasADi functions of one experiment's variables ``z = (q, v)`` (p = n + nv).

    ``c(z)`` are the experiment's rule rows held in every experiment: ``|v|^2`` when the load
    direction is free, then the workspace rows :attr:`~casadi_design.problem.rules.PlanRules.pose` of
    q (m), but for a cell's capsule rows: those enter row by row (``collision``, from the world
    points ``w(q)``, 3K, m), only where they can bind.

    Attributes
    ----------
    values : ``z -> (B, c, w)``, B (d x L) unscaled.
    first : ``z -> (d vec(B) / dz (d L x p), dc/dz (nc x p), dw/dz (3K x p))``.
    second : ``(z, W, lam, u) -> d2/dz2 (sum_kl W_kl B_kl + lam . c + u . w)`` (p x p), W (d x L),
        lam (nc), u (3K).
    pair : ``u -> joint_distance_sq(q_a, q_b)`` (rad^2) for ``u = (q_a, q_b)``; ``pair_first``: its gradient
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
    collision: CollisionRows | None

    @property
    def p(self) -> int:
        return self.n + self.nv


#: Largest function (instructions) whose common subexpressions are eliminated: on the
#: kinematics of B that saves 10-35 % of the operations; on a cell's collision rows (300k
#: instructions) it saves only 7 % and takes seconds to find.
CSE_LIMIT = 100_000


def _function(name: str, ins: list, outs: list, in_names: list[str], out_names: list[str]) -> ca.Function:
    """A CasADi function, with common subexpressions eliminated below ``CSE_LIMIT``."""
    f = ca.Function(name, ins, outs, in_names, out_names)
    return ca.Function(name, ins, outs, in_names, out_names, {"cse": True}) if f.n_instructions() < CSE_LIMIT else f


@per_model
def experiment_functions(problem: Problem) -> ExperimentFunctions:
    """The functions of one experiment of ``problem`` (built once per problem)."""
    model, loads, rules = problem.model, problem.rules.loads, problem.rules.pose
    n = model.n
    q, v = ca.SX.sym("q", n), ca.SX.sym("v", loads.nv)
    z = ca.vertcat(q, v)
    B = model.B(q, loads.load(v))
    collision = rules.collision
    held = rules.g if collision is None else rules.screen
    c = ca.vertcat(*([ca.sumsqr(v)] if loads.norm_lb is not None else []), held(q))
    w = collision.points(q) if collision is not None else ca.SX(0, 1)
    W, lam, u = ca.SX.sym("W", *B.shape), ca.SX.sym("lam", c.numel()), ca.SX.sym("u", w.numel())
    second = ca.hessian(ca.dot(W, B) + ca.dot(lam, c) + ca.dot(u, w), z)[0]
    qa, qb, mu = ca.SX.sym("qa", n), ca.SX.sym("qb", n), ca.SX.sym("mu")
    ab = ca.vertcat(qa, qb)
    d = joint_distance_sq(problem.rules.limits, qa, qb)
    return ExperimentFunctions(
        n, loads.nv, c.numel(),
        _function("B", [z], [B, c, w], ["z"], ["B", "c", "w"]),
        _function("dB", [z], [ca.jacobian(ca.vec(B), z), ca.jacobian(c, z), ca.jacobian(w, z)], ["z"],
                  ["dB", "dc", "dw"]),
        _function("d2B", [z, W, lam, u], [second], ["z", "W", "lam", "u"], ["d2"]),
        ca.Function("pair", [ab], [d], ["u"], ["d"]),
        ca.Function("dpair", [ab], [ca.jacobian(d, ab)], ["u"], ["dd"]),
        ca.Function("d2pair", [ab, mu], [ca.hessian(mu * d, ab)[0]], ["u", "mu"], ["d2"]),
        collision,
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
    active : ndarray, shape (K, 2): the capsule rows held, as (experiment i, row r of
        :class:`~casadi_design.problem.rules.CollisionRows`); ``active_rows`` (K,): their index in g.
    n_rows : number of criterion rows (s for an epigraph criterion, 0 otherwise), first in g.
    nx, ng : sizes of x and g.
    objective : the criterion's part (:mod:`casadi_design.measures.objectives`).
    P : its weight matrix (:meth:`~casadi_design.measures.objectives.Objective.weights`), or None.
    power : r of the spectral surrogates of E and condition; 0 otherwise.
    weights : ndarray, shape (m,), or None: each experiment's weight in M (:meth:`c`).
    fixed : ndarray, shape (L, L), or None: ``scale M0``, information added to M.
    last : the quantities of the last x: ``[x bytes, _Values, _Slopes or None]``.
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
    active: np.ndarray
    active_rows: np.ndarray
    n_rows: int
    nx: int
    ng: int
    objective: Objective
    P: np.ndarray | None
    power: float = 0.0
    weights: np.ndarray | None = None
    fixed: np.ndarray | None = None
    last: list = field(default_factory=list)

    def c(self, ndim: int) -> float | np.ndarray:
        """The factor of each experiment's information: ``scale``, or with ``weights``
        ``scale w_i`` shaped (m, 1, ..., 1) with ``ndim`` dimensions in all."""
        if self.weights is None:
            return self.scale
        return (self.scale * self.weights).reshape((-1,) + (1,) * (ndim - 1))

    @cached_property
    def mapped(self) -> dict[str, BufferedFunction]:
        """The functions of :class:`ExperimentFunctions`, compiled (:mod:`casadi_design.robot.compiled`),
        mapped over the experiments (pairs)."""
        f, P = self.fns, len(self.pairs)
        values, first, second = compiled_group([f.values, f.first, f.second])  # built side by side
        out = {"values": values.map(self.m), "first": first.map(self.m), "second": second.map(self.m)}
        if P:
            out.update(pair=f.pair.map(P), pair_first=f.pair_first.map(P),
                       pair_second=f.pair_second.map(P))
        if len(self.active):
            K, rows = len(self.active), f.collision
            out.update(row_value=rows.value.map(K), row_slope=rows.slope.map(K))
            if len(self.curved):
                out.update(row_curvature=rows.curvature.map(len(self.curved)))
        return {k: BufferedFunction.of(fn) for k, fn in out.items()}

    @cached_property
    def curved(self) -> np.ndarray:
        """Which held capsule rows have a second derivative (index in ``active``): the others
        add nothing to the Hessian but through their slope."""
        return np.flatnonzero(self.fns.collision.curved[self.active[:, 1]])

    @cached_property
    def row_inputs(self) -> np.ndarray:
        """Index in the experiment's points ``w`` (3K, then a zero) of the inputs ``w_r`` of
        each held capsule row, shape (K, width)."""
        return self.fns.collision.inputs[self.active[:, 1]]

    @cached_property
    def pair_cols(self) -> np.ndarray:
        """Index in x of ``(q_a, q_b)`` of each pair, shape (P, 2n)."""
        n = self.fns.n
        return np.concatenate([self.cols[self.pairs[:, 0], :n], self.cols[self.pairs[:, 1], :n]],
                              axis=1)

    @cached_property
    def jacobian_pattern(self) -> np.ndarray:
        """Structural nonzeros of dg/dx (ng x nx, bool)."""
        J = np.zeros((self.ng, self.nx), dtype=bool)
        J[: self.n_rows, : self.cols.size] = True
        J[: self.n_rows, self.nx - 1] = self.n_rows > 0
        dc = np.array(ca.DM(self.fns.first.sparsity_out(1), 1.0), dtype=bool)
        J[self.rule_rows[:, :, None], self.cols[:, None, :]] = dc
        J[self.pair_rows[:, None], self.pair_cols] = True
        J[self.active_rows[:, None], self.cols[self.active[:, 0], : self.fns.n]] = True
        return J

    @cached_property
    def hessian_pattern(self) -> np.ndarray:
        """Structural nonzeros of the upper triangle of the Hessian of the Lagrangian (nx x nx,
        bool): dense over the plan variables where M^-1 couples every experiment (a curvature
        term); for T, the blocks of each experiment and of each pair."""
        H = np.zeros((self.nx, self.nx), dtype=bool)
        if self.objective.couples:
            H[np.ix_(self.cols.ravel(), self.cols.ravel())] = True
        else:
            H[self.cols[:, :, None], self.cols[:, None, :]] = True
            H[self.pair_cols[:, :, None], self.pair_cols[:, None, :]] = True
        return np.triu(H)

    @cached_property
    def jacobian_nonzeros(self) -> np.ndarray:
        """Positions in the row-major dense dg/dx (ng x nx) of its nonzeros, in CasADi's
        (column-major) order."""
        k = np.flatnonzero(self.jacobian_pattern.T.ravel())
        return k % self.ng * self.nx + k // self.ng

    @cached_property
    def plan_order(self) -> np.ndarray:
        """Position of each x in the plan order ``(experiment i, variable a of z_i)``, -1 for t."""
        order = np.full(self.nx, -1)
        order[self.cols.ravel()] = np.arange(self.cols.size)
        return order

    @cached_property
    def hessian_nonzeros(self) -> np.ndarray:
        """Positions in the row-major Hessian in plan order (V x V, V = m p) of the nonzeros of
        the Hessian of x, in CasADi's (column-major) order."""
        cols, rows = np.nonzero(self.hessian_pattern.T)
        return self.plan_order[rows] * self.cols.size + self.plan_order[cols]

    @cached_property
    def block_positions(self) -> np.ndarray:
        """Positions of the experiments' (p x p) blocks in the row-major (V x V) Hessian in plan
        order, shape (m, p, p)."""
        V, p = self.cols.size, self.fns.p
        k = np.arange(self.m)[:, None, None] * p
        return (k + np.arange(p)[:, None]) * V + k + np.arange(p)

    @cached_property
    def pair_positions(self) -> np.ndarray:
        """Positions of each pair's ``(q_a, q_b)`` (2n x 2n) block in the row-major (V x V)
        Hessian in plan order, shape (P, 2n, 2n)."""
        order = self.plan_order[self.pair_cols]
        return order[:, :, None] * self.cols.size + order[:, None, :]

    def _at(self, x: np.ndarray) -> list:
        x = np.asarray(x, dtype=float)
        key = x.tobytes()
        if not self.last or self.last[0] != key:
            self.last[:] = [key, _values(self, x.copy()), None]
        return self.last

    def at(self, x: np.ndarray) -> _Values:
        """The values at x (those of the last call when x is the same)."""
        return self._at(x)[1]

    def slopes(self, x: np.ndarray) -> _Slopes:
        """The first derivatives at x (those of the last call when x is the same)."""
        last = self._at(x)
        if last[2] is None:
            last[2] = _slopes(self, last[1])
        return last[2]

    def f_g(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = self.at(x)
        return np.array([v.f]), v.g

    def grad_f(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.array([self.at(x).f]), self.slopes(x).grad_f

    def jac_g(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.at(x).g, self.slopes(x).jac_g.ravel()[self.jacobian_nonzeros]

    def hess_lag(self, x: np.ndarray, lam_f: float, lam_g: np.ndarray) -> np.ndarray:
        """The upper triangle (column-major nonzeros) of the Hessian of the Lagrangian
        ``lam_f d2f/dx2 + sum_k lam_g[k] d2g_k/dx2``."""
        H = _plan_hessian(self, self.at(x), self.slopes(x), float(lam_f), lam_g)
        return H.ravel()[self.hessian_nonzeros]

    def functions(self) -> tuple[ca.Function, dict]:
        """The NLP ``(x, p) -> (f, g)`` and the nlpsol options with its derivative functions."""
        return callbacks(self, self.nx, self.ng, self.jacobian_pattern, self.hessian_pattern)


def callbacks(nlp, nx: int, ng: int, jacobian: np.ndarray,
              hessian: np.ndarray | None = None) -> tuple[ca.Function, dict]:
    """The NLP ``(x, p) -> (f, g)`` of ``nlp`` (its ``f_g``, ``grad_f``, ``jac_g`` and, with the
    structural nonzeros ``hessian`` of the upper triangle, ``hess_lag``) as
    :class:`NumericFunction` callbacks and the nlpsol options that hold its derivatives;
    ``jacobian``: the structural nonzeros of dg/dx (ng x nx, bool)."""
    dense = ca.Sparsity.dense

    def pattern(mask: np.ndarray) -> ca.Sparsity:
        rows, cols = np.nonzero(mask)
        return ca.Sparsity.triplet(*mask.shape, rows.tolist(), cols.tolist())

    x_p = [("x", dense(nx, 1)), ("p", dense(0, 1))]
    f, g = ("f", dense(1, 1)), ("g", dense(ng, 1))
    oracle = NumericFunction("nlp", x_p, [f, g], lambda x, p: nlp.f_g(x))
    options = {
        "grad_f": NumericFunction("grad_f", x_p, [f, ("grad_f_x", dense(nx, 1))], lambda x, p: nlp.grad_f(x)),
        "jac_g": NumericFunction("jac_g", x_p, [g, ("jac_g_x", pattern(jacobian))], lambda x, p: nlp.jac_g(x)),
        "no_nlp_grad": True,  # the multipliers' gradient would differentiate the callbacks
    }
    if hessian is not None:
        options["hess_lag"] = NumericFunction(
            "hess_lag", x_p + [("lam_f", dense(1, 1)), ("lam_g", dense(ng, 1))],
            [("triu_hess_gamma_x_x", pattern(hessian))],
            lambda x, p, lam_f, lam_g: [nlp.hess_lag(x, lam_f[0], lam_g)])
    return oracle, options


class _Values(NamedTuple):
    """f, g and what they are made of at one x.

    Z : (p, m) the experiments' variables; B : (m, d, L) unscaled; w_rows : (K, width) the
    inputs of the held capsule rows (m); M : (L, L) scaled;
    Cinv : ``C^-1`` for ``M = C C^T`` (C lower triangular), None when M is not positive definite;
    local : the objective at M (None for an epigraph criterion or a singular M).
    """

    x: np.ndarray
    Z: np.ndarray
    B: np.ndarray
    w_rows: np.ndarray
    M: np.ndarray
    Cinv: np.ndarray | None
    local: Local | None
    f: float
    g: np.ndarray


class _Slopes(NamedTuple):
    """First derivatives at one x: dB (m, p, d, L) unscaled, dM (m p, L, L) in the order of
    ``cols``, ``N = M^-1``, ``Y_j = N H_j N`` (s, L, L; epigraph) or ``G_f = df/dM`` (the
    other criteria), and the gradient of f and the dense Jacobian of g; for the held capsule
    rows, ``dg_r/dw_r`` (K, width) and ``dw_r/dz`` (K, width, p)."""

    dB: np.ndarray
    row_slope: np.ndarray
    dw_rows: np.ndarray
    dM: np.ndarray
    N: np.ndarray
    Y: np.ndarray | None
    G_f: np.ndarray | None
    grad_f: np.ndarray
    jac_g: np.ndarray


def _values(nlp: ReducedNLP, x: np.ndarray) -> _Values:
    m = nlp.m
    Z = x[nlp.cols.T]
    B, rules, w = nlp.mapped["values"](Z)
    d, L = B.shape[0], B.shape[1] // m
    B = B.reshape(d, m, L).transpose(1, 0, 2)
    S = B.reshape(m * d, L)
    M = nlp.scale * (S.T @ S) if nlp.weights is None else (nlp.c(3) * B).reshape(m * d, L).T @ S
    if nlp.fixed is not None:
        M = M + nlp.fixed
    C, info = dpotrf(M, lower=1, clean=1)
    Cinv = dtrtri(C, lower=1)[0] if info == 0 else None
    g = np.empty(nlp.ng)
    local = None
    if Cinv is None:
        f = np.nan
        g[: nlp.n_rows] = np.nan
    elif nlp.n_rows:
        f = float(x[-1])
        g[: nlp.n_rows] = EpigraphRows.rows(nlp.B0s, Cinv) - x[-1]
    else:
        local = nlp.objective.at(M, C, Cinv, nlp.P, nlp.power)
        f = local.value
    g[nlp.rule_rows] = rules.T
    w_rows = np.zeros((0, 0))
    if len(nlp.active):
        w = np.vstack([w, np.zeros((1, m))])  # index 3K: the zero that fills w_r
        w_rows = w[nlp.row_inputs, nlp.active[:, :1]]
        g[nlp.active_rows] = nlp.mapped["row_value"](nlp.active[None, :, 1], w_rows.T)[0].ravel()
    if len(nlp.pairs):
        g[nlp.pair_rows] = nlp.mapped["pair"](x[nlp.pair_cols.T])[0].ravel()
    return _Values(x, Z, B, w_rows, M, Cinv, local, f, g)


def _slopes(nlp: ReducedNLP, v: _Values) -> _Slopes:
    m, p, c = nlp.m, nlp.fns.p, nlp.c(4)
    d, L = v.B.shape[1:]
    dB, dc, dw = nlp.mapped["first"](v.Z)
    dB = dB.reshape(L, d, m, p).transpose(2, 3, 1, 0)
    grad, J = np.zeros(nlp.nx), np.zeros((nlp.ng, nlp.nx))
    J[nlp.rule_rows[:, :, None], nlp.cols[:, None, :]] = dc.reshape(-1, m, p).transpose(1, 0, 2)
    slope = dw_rows = np.zeros((0, 0))
    if len(nlp.active):
        K = len(nlp.active)
        slope = nlp.mapped["row_slope"](nlp.active[None, :, 1], v.w_rows.T)[0].reshape(K, -1)
        dw = np.concatenate([dw.reshape(-1, m, p), np.zeros((1, m, p))])
        dw_rows = dw[nlp.row_inputs, nlp.active[:, :1]]
        J[nlp.active_rows[:, None], nlp.cols[nlp.active[:, 0]]] = np.einsum("kw,kwp->kp", slope, dw_rows)
    if len(nlp.pairs):
        P, n2 = nlp.pair_cols.shape
        J[nlp.pair_rows[:, None], nlp.pair_cols] = nlp.mapped["pair_first"](
            v.x[nlp.pair_cols.T])[0].reshape(P, n2)
    if nlp.n_rows:
        grad[-1] = 1.0
        J[: nlp.n_rows, -1] = -1.0
    if v.Cinv is None:
        grad[: nlp.cols.size] = np.nan
        J[: nlp.n_rows] = np.nan
        nan = np.full((m * p, L, L), np.nan)
        return _Slopes(dB, slope, dw_rows, nan, nan[0], None, None, grad, J)
    N = v.Cinv.T @ v.Cinv
    T = c * (dB.transpose(0, 1, 3, 2) @ v.B[:, None])  # dB_a^T B_i, (m, p, L, L)
    dM = (T + T.transpose(0, 1, 3, 2)).reshape(m * p, L * L)
    cols = nlp.cols.ravel()
    Y = G_f = None
    if nlp.n_rows:
        Y = EpigraphRows.row_gradients(nlp.B0s, N)
        J[: nlp.n_rows, cols] = -Y.reshape(-1, L * L) @ dM.T
    else:
        G_f = nlp.objective.gradient(v.local, N, nlp.P)
        grad[cols] = dM @ G_f.ravel()
    return _Slopes(dB, slope, dw_rows, dM.reshape(m * p, L, L), N, Y, G_f, grad, J)


def _plan_hessian(nlp: ReducedNLP, v: _Values, sl: _Slopes, lam_f: float,
                  lam_g: np.ndarray) -> np.ndarray:
    """``lam_f d2f/dx2 + sum_k lam_g[k] d2g_k/dx2`` over the plan variables in plan order
    (V x V); t enters f and g linearly."""
    m, p, c = nlp.m, nlp.fns.p, nlp.c(3)
    V, L = m * p, len(v.M)
    if v.Cinv is None:
        return np.full((V, V), np.nan)
    Gbar = (-(lam_g[: nlp.n_rows] @ sl.Y.reshape(-1, L * L)).reshape(L, L) if nlp.n_rows
            else lam_f * sl.G_f)
    H = nlp.objective.curvature(v.local, Gbar, sl.dM, sl.N, lam_f)
    # tr(Gbar d2M_ab) = c (2 <B Gbar, d2B_ab> + 2 <dB_a Gbar, dB_b>), and the rules' rows
    W = (2 * c) * (v.B @ Gbar)
    d = W.shape[1]
    # the held capsule rows g_r(w_r(z)): u = sum_r lam_r dg_r/dw enters the kinematics' second
    # derivative, and each row adds lam_r (dw_r/dz)^T d2g_r/dw_r2 (dw_r/dz) to its block
    K3 = nlp.fns.values.size_out(2)[0]
    u = np.zeros((K3 + 1, m))  # index 3K: the zero that fills w_r
    if len(nlp.active):
        lam = lam_g[nlp.active_rows]
        np.add.at(u, (nlp.row_inputs, nlp.active[:, :1]), lam[:, None] * sl.row_slope)
        c_rows = nlp.curved
        if c_rows.size:
            width = sl.row_slope.shape[1]
            curvature = nlp.mapped["row_curvature"](nlp.active[None, c_rows, 1], v.w_rows[c_rows].T)[0]
            curvature = lam[c_rows, None, None] * curvature.reshape(width, c_rows.size, width).transpose(1, 0, 2)
    d2 = nlp.mapped["second"](v.Z, W.transpose(1, 0, 2).reshape(d, -1), lam_g[nlp.rule_rows].T,
                              u[:K3])[0]
    blocks = d2.reshape(p, m, p).transpose(1, 0, 2)
    if len(nlp.active) and c_rows.size:
        dw = sl.dw_rows[c_rows]
        np.add.at(blocks, nlp.active[c_rows, 0], dw.transpose(0, 2, 1) @ (curvature @ dw))
    dBG = (sl.dB @ Gbar).reshape(m, p, d * L)
    blocks += (2 * c) * (dBG @ sl.dB.reshape(m, p, d * L).transpose(0, 2, 1))
    flat = H.ravel()
    flat[nlp.block_positions] += blocks
    if len(nlp.pairs):
        P, n2 = nlp.pair_cols.shape
        d2p = nlp.mapped["pair_second"](v.x[nlp.pair_cols.T], lam_g[nlp.pair_rows][None, :])[0]
        np.add.at(flat, nlp.pair_positions, d2p.reshape(n2, P, n2).transpose(1, 0, 2))
    return H


def all_rows(problem: Problem, m: int) -> np.ndarray:
    """Every capsule row of every experiment, as (experiment, row) pairs (K, 2): the whole
    rulebook."""
    rows = problem.rules.pose.collision
    R = 0 if rows is None else len(rows.inputs)
    return np.array([(i, r) for i in range(m) for r in range(R)], dtype=int).reshape(-1, 2)


def reduced_nlp(problem: Problem, criterion: str, m: int,
                scale: float, power: float = 0.0, active: np.ndarray | None = None,
                weights: np.ndarray | None = None, fixed: np.ndarray | None = None) -> ReducedNLP:
    """The reduced-space NLP of ``criterion`` for m experiments (``power``: r of E and
    condition) holding the capsule rows ``active`` ((experiment, row) pairs, K x 2; None:
    every row, :func:`all_rows`). With ``weights`` (m,) and ``fixed`` (L x L),
    ``M = scale (sum_i w_i B_i^T B_i + fixed)``: the support points of an approximate design
    (:mod:`casadi_design.optimisation.bound`), each a single experiment of its own, so there is no
    joint-distance row.

    x = (Q, V, t for an epigraph criterion); g = (epigraph rows, load rows, workspace rows of
    each experiment but the capsule rows, the capsule rows held, joint-distance rows of each
    pair a < b), as in :mod:`casadi_design.optimisation.nlp`.
    """
    fns, objective = experiment_functions(problem), CRITERIA[criterion].objective
    active = all_rows(problem, m) if active is None else np.asarray(active, dtype=int).reshape(-1, 2)
    n, nv = fns.n, fns.nv
    B0 = problem.B0
    n_rows = B0.shape[0] if objective.epigraph else 0
    idx = np.arange(m)[:, None]
    cols = np.concatenate([idx * n + np.arange(n), n * m + idx * nv + np.arange(nv)], axis=1)
    has_norm = int(problem.rules.loads.norm_lb is not None)
    n_ws = fns.nc - has_norm
    rule_rows = np.concatenate([n_rows + idx + np.zeros((1, has_norm), dtype=int),
                                n_rows + has_norm * m + idx * n_ws + np.arange(n_ws)], axis=1)
    distance = problem.workspace.min_joint_distance_rad > 0 and weights is None
    pairs = np.array([(a, b) for a in range(m) for b in range(a + 1, m) if distance], dtype=int)
    first_active = n_rows + fns.nc * m
    first_pair = first_active + len(active)
    nx = (n + nv) * m + objective.epigraph
    B0s = np.sqrt(scale) * B0
    return ReducedNLP(criterion, m, scale, fns, B0s, cols, rule_rows, pairs.reshape(-1, 2),
                      first_pair + np.arange(len(pairs)), active, first_active + np.arange(len(active)),
                      n_rows, nx, first_pair + len(pairs), objective, objective.weights(B0s), power,
                      None if weights is None else np.asarray(weights, dtype=float),
                      None if fixed is None else scale * np.asarray(fixed, dtype=float))
