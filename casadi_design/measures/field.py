"""The robot's unmodelled error as a random field: the test-pose measure with model discrepancy.

The paper's measure holds one error, the tracker's noise. A real robot also differs from its
model in ways no parameter holds (compliance, gears, temperature): some 0.25 mm per axis on a
UR10, 40 times its tracker's noise. Model it as Kennedy and O'Hagan's discrepancy (2001):

    y_i = B_i X + delta(q_i) + eps_i

with ``delta`` a Gaussian process over the joint configurations on each position axis (x, y, z
of the robot's base), ``cov(delta_a(q), delta_b(q')) = [a == b] k(q, q')``,

    k(q, q') = scale^2 exp(-1/2 sum_l ((q_l - q'_l) / length_l)^2) + nugget^2 [q == q'],

(squared exponential over the joints, one length per joint, rad or m; the nugget is the part
of the error no neighbouring pose tells: repeatability, backlash) and ``eps`` the tracker's
noise, ``sigma^2`` per value. All in the whitened values of the model (``Wh = sigma
Sigma^-1/2``): ``V = cov(y) = (K + nugget^2 I) (x) Wh A Wh^T + sigma^2 I`` with ``A_vw =
[axis(v) == axis(w)]`` over position values (the markers of a pose move together).

After calibration and compensation with the field, the error at test pose ``q0`` is the
error of the universal kriging predictor of ``z0 = B0 X + delta(q0)``: with the cross
covariance ``k0 = cov(y, delta(q0))`` (N x r), ``H = P + B^T V^-1 B`` (P: the prior's
information on X, 1/m^2 units of B) and ``R = B0 - k0^T V^-1 B``,

    rho(q0) = tr(T00) - tr(k0^T V^-1 k0) + tr(R H^-1 R^T) + nugget^2 r_p

(``T00 = scale^2 A00`` the field's own covariance at the test pose, ``r_p`` its position
components; the nugget at the test pose is not compensated). With ``scale = nugget = 0`` it is
``sigma^2 tr(B0 M^-1 B0^T)``: the paper's measure is its limit. Measuring near the test poses
pays when the field dominates (``k0`` grows), informative poses when the noise does.

The kriging mean ``k0^T V^-1 r`` of the calibrated model's residuals ``r`` is the correction of
the compensated robot at ``q0`` (regression kriging: the parameters are the least squares'
ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .criteria import CRITERIA


@dataclass(frozen=True)
class Field:
    """The unmodelled error's field (module docstring): ``scale_m`` (m, per axis), the
    correlation ``lengths`` (n,) per joint (rad, m for prismatic joints) and ``nugget_m`` (m).

    With ``shares`` (n,; sum 1) the smooth part is additive over the joints, each joint's
    share of the variance correlated along its own angle only:

        k(q, q') = scale^2 sum_l shares_l exp(-1/2 ((q_l - q'_l) / length_l)^2),

    an error of the joint angles, such as IPA's UR10 shows (waves of 12 to 29 cycles per
    revolution in its pan and lift joints, ``scripts/joint_error_scan.py``): it correlates every
    pose that shares one angle, whatever the others. Without (empty), the squared exponential
    over all joints at once, which correlates only poses near in every joint."""

    scale_m: float
    lengths: tuple[float, ...]
    nugget_m: float = 0.0
    shares: tuple[float, ...] = ()

    def kernel(self, Qa: np.ndarray, Qb: np.ndarray) -> np.ndarray:
        """The smooth part of k (ka, kb), m^2: ``scale^2 exp(-1/2 |(qa - qb) / length|^2)``, or
        the sum over the joints with ``shares``."""
        ell = np.asarray(self.lengths, dtype=float)
        Za, Zb = np.atleast_2d(Qa) / ell, np.atleast_2d(Qb) / ell
        if self.shares:
            d2 = (Za[:, None, :] - Zb[None, :, :]) ** 2
            return self.scale_m**2 * np.exp(-0.5 * d2) @ np.asarray(self.shares, dtype=float)
        d2 = np.sum(Za**2, 1)[:, None] + np.sum(Zb**2, 1)[None, :] - 2 * Za @ Zb.T
        return self.scale_m**2 * np.exp(-0.5 * np.maximum(d2, 0.0))

    def describe(self) -> str:
        """The field for people: scale, nugget (mm), lengths (rad per joint) and, additive, the
        joints' shares."""
        return (f"scale {self.scale_m * 1e3:.4g} mm, nugget {self.nugget_m * 1e3:.4g} mm, lengths "
                + ", ".join(f"{v:.3g}" for v in self.lengths) + " rad per joint"
                + (", additive over the joints (an error of the joint angles), shares "
                   + ", ".join(f"{v:.2f}" for v in self.shares) if self.shares else ""))

    def as_dict(self) -> dict:
        kernel = ("scale^2 sum_l shares_l exp(-1/2 ((q_l - q'_l) / length_l)^2) + nugget^2 [q == q'] per base axis"
                  if self.shares else
                  "scale^2 exp(-1/2 sum_l ((q_l - q'_l) / length_l)^2) + nugget^2 [q == q'] per base axis")
        return {"scale_m": self.scale_m, "lengths": list(self.lengths), "nugget_m": self.nugget_m,
                **({"shares": list(self.shares)} if self.shares else {}), "kernel": kernel}


#: The criteria that weigh the test poses' rho, and so hold a field when the problem has one.
FIELD_CRITERIA = tuple(name for name, c in CRITERIA.items() if c.reads == "rho")


def field_measure(problem, criterion: str) -> bool:
    """Whether ``criterion`` weighs the test poses with the problem's field of unmodelled error
    (test-pose and I with :attr:`~casadi_design.model.build.Problem.field`): its experiments are
    not independent, so the approximate design's bound does not hold for it."""
    return problem.field is not None and criterion in FIELD_CRITERIA


def axes_of(rows: tuple[int, ...], markers: int = 1) -> np.ndarray:
    """The base axis (0, 1, 2 for x, y, z; -1 for an orientation) of each value of a model's
    ``rows`` (indices into the twist, positions first) for ``markers`` points: the order of the
    model's measured values (each marker's positions, then the orientations)."""
    pos = [r for r in rows if r < 3]
    return np.array([r for _ in range(markers) for r in pos] + [-1 for r in rows if r >= 3], dtype=int)


def coupling(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``[axis(a_v) == axis(b_w)]`` over position values (len(a), len(b))."""
    return ((a[:, None] == b[None, :]) & (a[:, None] >= 0)).astype(float)


def value_covariance(field: Field, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray, sigma: float) -> np.ndarray:
    """``V`` (N x N), N = m d, m^2: the covariance of the whitened values of the poses ``Q``
    (m, n), their values' ``axes`` (d,) (module docstring)."""
    A = Wh @ coupling(axes, axes) @ Wh.T
    m = len(Q)
    return np.kron(field.kernel(Q, Q) + field.nugget_m**2 * np.eye(m), A) + sigma**2 * np.eye(m * len(axes))


def cross_covariance(field: Field, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray, Q0: np.ndarray,
                     axes0: np.ndarray) -> np.ndarray:
    """``k0 = cov(y, delta(q0))`` for every test pose: (s, N, r), m^2."""
    C = Wh @ coupling(axes, axes0)  # (d, r)
    k = field.kernel(Q0, Q)  # (s, m)
    return np.einsum("si,vc->sivc", k, C).reshape(len(Q0), len(Q) * len(axes), len(axes0))


def kriging_rho(field: Field, sigma: float, B: np.ndarray, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray,
                B0: np.ndarray, Q0: np.ndarray, axes0: np.ndarray, P: np.ndarray | None = None) -> np.ndarray:
    """``rho(q0)`` (s,), m^2, at the test poses ``Q0`` (s, n) of rows ``B0`` (s, r, L) after a
    campaign of poses ``Q`` (m, n) with rows ``B`` (m, d, L) (whitened), a prior information
    ``P`` (L x L, 1/m^2 units of B; None: none) (module docstring). Infinite where the
    campaign does not identify X."""
    m, d, L = B.shape
    if not m:
        return np.full(len(Q0), np.inf)
    V = value_covariance(field, Q, axes, Wh, sigma)
    Cv = np.linalg.cholesky(V)
    S = B.reshape(m * d, L)
    k0 = cross_covariance(field, Q, axes, Wh, Q0, axes0)  # (s, N, r)
    W = np.linalg.solve(Cv, np.concatenate([S, k0.transpose(1, 0, 2).reshape(m * d, -1)], axis=1))
    WS, Wk = W[:, :L], W[:, L:].reshape(m * d, len(Q0), -1).transpose(1, 0, 2)  # Cv^-1 S, Cv^-1 k0
    H = WS.T @ WS + (0.0 if P is None else P)
    lam = np.linalg.eigvalsh(H)
    if not lam[0] > 1e-12 * max(lam[-1], np.finfo(float).tiny):
        return np.full(len(Q0), np.inf)
    R = B0 - np.einsum("snc,nl->scl", Wk, WS)  # B0 - k0^T V^-1 B
    Y = np.linalg.solve(np.linalg.cholesky(H), R.transpose(0, 2, 1))
    pos0 = float(np.sum(axes0 >= 0))
    return ((field.scale_m**2 + field.nugget_m**2) * pos0 - np.einsum("snc,snc->s", Wk, Wk)
            + np.einsum("slc,slc->s", Y, Y))


def kriging_mean(field: Field, sigma: float, r: np.ndarray, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray,
                 Q0: np.ndarray, axes0: np.ndarray) -> np.ndarray:
    """The field's kriging mean at the poses ``Q0`` (s, r), m: ``k0^T V^-1 r`` of the whitened
    residuals ``r`` (m, d) of the poses ``Q`` (regression kriging, module docstring)."""
    V = value_covariance(field, Q, axes, Wh, sigma)
    alpha = np.linalg.solve(V, np.asarray(r, dtype=float).reshape(-1))
    return np.einsum("snc,n->sc", cross_covariance(field, Q, axes, Wh, Q0, axes0), alpha)


def kriging_rho_added(field: Field, sigma: float, B: np.ndarray, Q: np.ndarray, Bc: np.ndarray, Qc: np.ndarray,
                      axes: np.ndarray, Wh: np.ndarray, B0: np.ndarray, Q0: np.ndarray, axes0: np.ndarray,
                      P: np.ndarray | None = None) -> np.ndarray:
    """``rho`` (k, s), m^2, of the campaigns ``Q`` (m, n) plus one candidate pose each, ``Qc``
    (k, n) with rows ``Bc`` (k, d, L): :func:`kriging_rho` of every campaign at once, by bordering.
    With ``Cv Cv^T = V`` of ``Q`` and a candidate's covariance with them ``v`` (N x d), its own
    ``v_cc``: the Schur complement ``s_c = v_cc - v^T V^-1 v`` brings in the rank-d updates
    ``H + u^T s_c^-1 u`` (``u = B_c - v^T V^-1 S``), ``k0^T V^-1 k0 + w^T s_c^-1 w`` and ``k0^T V^-1 S +
    w^T s_c^-1 u`` (``w = k0_c - v^T V^-1 k0``): O(N^2 (k d + L + s r)) for all k, instead of k
    Cholesky factorisations of (N + d)^2."""
    m, d, L = B.shape
    k, s, r = len(Qc), len(Q0), len(axes0)
    A = Wh @ coupling(axes, axes) @ Wh.T  # a pose's values with one another
    C0 = Wh @ coupling(axes, axes0)  # a pose's values with a test pose's components
    Cv = np.linalg.cholesky(value_covariance(field, Q, axes, Wh, sigma))
    k0 = cross_covariance(field, Q, axes, Wh, Q0, axes0)  # (s, N, r)
    v = np.einsum("ic,vw->civw", field.kernel(Q, Qc), A).reshape(k, m * d, d)
    Y = np.linalg.solve(Cv, np.concatenate([B.reshape(m * d, L), k0.transpose(1, 0, 2).reshape(m * d, s * r),
                                            v.transpose(1, 0, 2).reshape(m * d, k * d)], axis=1))
    YS, Yk = Y[:, :L], Y[:, L:L + s * r].reshape(m * d, s, r)
    Yv = Y[:, L + s * r:].reshape(m * d, k, d)
    G = YS.T @ YS + (0.0 if P is None else P)
    T = np.einsum("nsr,nl->srl", Yk, YS)  # k0^T V^-1 S
    KK = np.einsum("nsr,nsr->s", Yk, Yk)  # tr(k0^T V^-1 k0)
    vcc = (field.scale_m**2 + field.nugget_m**2) * A + sigma**2 * np.eye(d)
    Sc = vcc - np.einsum("nca,ncb->cab", Yv, Yv)
    u = Bc - (Yv.reshape(m * d, k * d).T @ YS).reshape(k, d, L)
    k0c = np.einsum("cs,ar->csar", field.kernel(Qc, Q0), C0)
    w = k0c - (Yv.reshape(m * d, k * d).T @ Yk.reshape(m * d, s * r)).reshape(k, d, s, r).transpose(0, 2, 1, 3)
    Lc = np.linalg.cholesky(Sc)
    ut = np.linalg.solve(Lc, u)  # (k, d, L)
    wt = np.linalg.solve(Lc[:, None], w)  # (k, s, d, r)
    H = G + np.einsum("cal,cak->clk", ut, ut)
    R = B0[None] - (T[None] + np.matmul(wt.transpose(0, 1, 3, 2), ut[:, None]))  # (k, s, r, L)
    out = np.full((k, s), np.inf)
    lam = np.linalg.eigvalsh(H)
    ok = lam[:, 0] > 1e-12 * np.maximum(lam[:, -1], np.finfo(float).tiny)
    if ok.any():
        Ch = np.linalg.cholesky(H[ok])
        Z = np.linalg.solve(Ch, R[ok].transpose(0, 3, 1, 2).reshape(int(ok.sum()), L, s * r))
        pos0 = float(np.sum(axes0 >= 0))
        out[ok] = ((field.scale_m**2 + field.nugget_m**2) * pos0 - KK[None] - np.einsum("csar,csar->cs", wt[ok], wt[ok])
                   + np.sum(Z.reshape(-1, L, s, r) ** 2, axis=(1, 3)))
    return out
