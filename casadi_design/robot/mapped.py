"""Evaluate a CasADi function on many stacked inputs at once (a mapped call, chunked), or on
one input after another through a kept buffer.

The batched numerics of the identification (every Gauss-Newton step) and of the virtual
calibration (every simulated trial) go through :func:`evaluate`; the sequential scan of a
robot move (each sample's step depends on the rows at the last) through :class:`OneByOne`.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..runtime.cache import memoised
from ..runtime.threads import cpu_count

#: Largest number of cases one mapped CasADi call evaluates: longer stacks run in chunks of
#: this size, shorter ones in the next power of two, so that a few mapped functions serve
#: every size (building one takes ~30 ms, as long as evaluating ~20000 cases); up to
#: ``EXACT`` cases (a plan's experiments, checked at every IPOPT iteration) in a function of
#: their own size, not padded.
CHUNK = 8192
EXACT = 64


#: Threads of the mapped evaluations: every core (the cases are independent, so the results do
#: not depend on it).
THREADS = cpu_count()


class OneByOne:
    """``fn`` (one dense input, one dense output) called on one input at a time through one
    buffer kept for every call (``Function.buffer``): the input is copied in, the output
    copied out, no CasADi matrices on the way. On the UR10's 109 cell rows in CasADi's
    virtual machine 21 us a call instead of 43 us through ``fn(q)`` (the same bits). Not
    for two threads at once: the buffer is shared."""

    def __init__(self, fn: ca.Function):
        if fn.n_in() != 1 or fn.n_out() != 1 or not (fn.sparsity_in(0).is_dense() and fn.sparsity_out(0).is_dense()):
            raise ValueError(f"OneByOne: {fn.name()} must have one dense input and one dense output")
        self.x, self.y = np.zeros(fn.numel_in(0)), np.zeros(fn.numel_out(0))
        self.buffer, self.call = fn.buffer()
        self.buffer.set_arg(0, memoryview(self.x))
        self.buffer.set_res(0, memoryview(self.y))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``fn(x)`` as a flat array (column-major), a fresh copy."""
        self.x[:] = np.ravel(x, order="F")
        self.call()
        return self.y.copy()


class Stacked:
    """``fn`` evaluated on the same N stacked cases again and again with new values (the rows of
    a fit at each iteration), through one mapped function and one buffer kept for every call:
    :func:`evaluate` without its per-call set-up (the same function of the same size, so the
    same bits). Dense inputs and outputs; not for two threads at once: the buffer is shared."""

    def __init__(self, fn: ca.Function, N: int):
        if not all(fn.sparsity_in(i).is_dense() for i in range(fn.n_in())) or \
                not all(fn.sparsity_out(b).is_dense() for b in range(fn.n_out())):
            raise ValueError(f"Stacked: {fn.name()} must have dense inputs and outputs")
        K = N if 0 < N <= EXACT else min(CHUNK, 1 << max(N - 1, 0).bit_length())
        if K != N:
            raise ValueError(f"Stacked: {N} cases; give at most {EXACT}, or use evaluate")
        self.shapes = [(fn.size1_out(b), fn.size2_out(b)) for b in range(fn.n_out())]
        self.args = [np.zeros((N, fn.numel_in(i))) for i in range(fn.n_in())]
        self.res = [np.zeros((N, fn.numel_out(b))) for b in range(fn.n_out())]
        self.buffer, self.call_buffer = _mapped(fn, N, 1).buffer()
        for i, a in enumerate(self.args):
            self.buffer.set_arg(i, memoryview(a))
        for b, r in enumerate(self.res):
            self.buffer.set_res(b, memoryview(r))

    def __call__(self, *rows: np.ndarray) -> list[np.ndarray]:
        """As :func:`evaluate`: each output (N, rows, columns), fresh arrays."""
        for a, r in zip(self.args, rows):
            a[...] = np.reshape(r, a.shape)
        self.call_buffer()
        return [r.reshape(len(r), c, n).transpose(0, 2, 1).copy() for r, (n, c) in zip(self.res, self.shapes)]


@memoised(128)
def _mapped(fn: ca.Function, N: int, threads: int) -> ca.Function:
    return fn.map(N, "thread", threads) if threads > 1 else fn.map(N)


def evaluate(fn: ca.Function, *rows: np.ndarray, threads: int = THREADS) -> list[np.ndarray]:
    """Evaluate ``fn`` on N stacked inputs at once (CasADi map, on ``threads`` threads).

    The arrays are handed to CasADi without conversion (``Function.buffer``): row t of a
    C-ordered (N, size) array is the t-th column of the mapped input, as CasADi stores it.

    Parameters
    ----------
    rows : ndarray, shape (N, size of input a), one per (dense, column-vector) input of ``fn``

    Returns
    -------
    list of ndarray, shape (N, rows of output b, columns of output b), one per output
    """
    N = rows[0].shape[0]
    inputs = [np.ascontiguousarray(a, dtype=float).reshape(N, fn.numel_in(i)) for i, a in enumerate(rows)]
    if any(not fn.sparsity_in(i).is_dense() for i in range(fn.n_in())):
        raise ValueError(f"evaluate: {fn.name()} has sparse inputs; give a function of dense inputs")
    nonzeros = [np.empty((N, fn.nnz_out(b))) for b in range(fn.n_out())]
    K = N if 0 < N <= EXACT else min(CHUNK, 1 << max(N - 1, 0).bit_length())
    mapped = _mapped(fn, K, threads)
    for start in range(0, N, K):
        stop = min(start + K, N)
        buffer, call = mapped.buffer()
        if stop - start == K:
            args, res = [a[start:stop] for a in inputs], [o[start:stop] for o in nonzeros]
        else:  # the last, short chunk: pad with copies of its last case
            pad = K - (stop - start)
            args = [np.concatenate([a[start:stop], np.repeat(a[stop - 1:stop], pad, axis=0)])
                    for a in inputs]
            res = [np.empty((K, o.shape[1])) for o in nonzeros]
        for i, a in enumerate(args):
            buffer.set_arg(i, memoryview(a))
        for b, o in enumerate(res):
            buffer.set_res(b, memoryview(o))
        call()
        if stop - start < K:
            for o, r in zip(nonzeros, res):
                o[start:stop] = r[:stop - start]
    out = []
    for b, nz in enumerate(nonzeros):
        sp = fn.sparsity_out(b)
        if sp.is_dense():
            full = nz
        else:  # e.g. a Jacobian with structural zeros: scatter its nonzeros (column-major)
            full = np.zeros((N, sp.numel()))
            full[:, sp.find()] = nz
        out.append(full.reshape(N, sp.size2(), sp.size1()).transpose(0, 2, 1))
    return out
