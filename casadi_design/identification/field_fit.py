"""The unmodelled error's field estimated from a fit's residuals: restricted maximum likelihood.

The residuals ``r`` (N = m d whitened values, m) of a least-squares fit with Jacobian ``J``
(N x L) are those of ``y = J X + delta + eps`` (:mod:`casadi_design.measures.field`) with the
parameters profiled out. Their restricted (REML) log-likelihood (Patterson and Thompson 1971;
Rasmussen and Williams, Gaussian Processes for Machine Learning, 2006, 2.7) is

    l(theta) = -1/2 (r^T Pi r + log|V| + log|J^T V^-1 J| + (N - L) log 2 pi),
    Pi = V^-1 - V^-1 J (J^T V^-1 J)^-1 J^T V^-1,

with gradient ``dl/dtheta_k = 1/2 (r^T Pi V_k Pi r - tr(Pi V_k))``, ``V_k = dV/dtheta_k``,
``theta = log(scale, length_1 .. length_n, nugget)``; the tracker's sigma is the problem's. It
is maximised by L-BFGS-B (scipy) from two starts, for the squared exponential over the joints
and for the field additive over them (an error of the joint angles,
:class:`~casadi_design.measures.field.Field`), and the one of the lower AIC (``2 k - 2 l``, k
hyperparameters: n + 2 and 2 n + 1) is kept. Without parameters (L = 0) it is the
marginal likelihood of a Gaussian process regression of the residuals on the joint
configurations, one output per base axis sharing the kernel: scikit-learn's
``GaussianProcessRegressor`` with ``ConstantKernel * RBF + WhiteKernel`` and ``alpha = sigma^2``
gives the same value (tests/identification/test_field.py). A fit of more than ``FIELD_ROWS``
rows is estimated on that many of them (seeded): the hyperparameters of a few hundred poses
are as good as of thousands, at a cubic cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..measures.field import Field, coupling, kriging_mean, kriging_rho, value_covariance

#: Rows the field is estimated from, at most.
FIELD_ROWS = 300
#: Seed of the rows kept when there are more.
FIELD_SEED = 0
#: The lengths are searched within these (rad or m), the scale and nugget from SCALE_LOW sigma.
LENGTH_BOUNDS = (0.02, 50.0)
#: ... those of the additive field within these: a joint's share longer than about a radian is
#: all but a constant or a slope over its range, which the geometric parameters take, and its
#: variance is then not told by the restricted likelihood (it runs to its bound).
ADDITIVE_LENGTH_BOUNDS = (0.02, 1.0)
SCALE_LOW = 1e-3


@dataclass(frozen=True)
class FieldFit:
    """The field estimated (:class:`~casadi_design.measures.field.Field`), its restricted
    log-likelihood and the rows it was estimated from."""

    field: Field
    log_likelihood: float
    rows: int

    def as_dict(self) -> dict:
        return {**self.field.as_dict(), "restricted_log_likelihood": self.log_likelihood,
                "estimated_from_rows": self.rows}


def restricted_log_likelihood(theta: np.ndarray, r: np.ndarray, J: np.ndarray, Q: np.ndarray, A: np.ndarray,
                              sigma: float, additive: bool = False) -> tuple[float, np.ndarray]:
    """``l(theta)`` and its gradient (module docstring) for residuals ``r`` (m, d), ``J`` (m, d,
    L), poses ``Q`` (m, n), the coupling ``A`` (d, d) of a pose's values; ``additive``: the
    field additive over the joints, ``theta = log(s_1 .. s_n, length_1 .. length_n, nugget)``
    with ``K = sum_l s_l^2 exp(-1/2 ((q_l - q'_l) / length_l)^2)``.

    With ``A = U diag(a) U^T`` the values rotated by ``U`` have ``V = blockdiag_c(a_c Kt +
    sigma^2 I)`` (``Kt = K + nugget^2 I``, m x m): d blocks of m x m instead of one of m d."""
    m, n = Q.shape
    nugget, scales = np.exp(theta[-1]), np.exp(theta[:n] if additive else theta[:1])
    ell = np.exp(theta[len(scales):len(scales) + n])
    D = (Q[:, None, :] - Q[None, :, :]) ** 2 / ell**2  # (m, m, n)
    if additive:
        s2 = scales**2
        E = np.exp(-0.5 * D)
        K = E @ s2
        dK = [*(2 * s2[l] * E[:, :, l] for l in range(n)), *(s2[l] * E[:, :, l] * D[:, :, l] for l in range(n)),
              2 * nugget**2 * np.eye(m)]  # dKt / dtheta_k
    else:
        K = scales[0] ** 2 * np.exp(-0.5 * D.sum(axis=2))
        dK = [2 * K, *(K * D[:, :, l] for l in range(n)), 2 * nugget**2 * np.eye(m)]  # dKt / dtheta_k
    a, U = np.linalg.eigh(A)
    rc = r @ U  # (m, d): the rotated values, column c of weight a_c
    Jc = np.einsum("mdl,dc->cml", J, U)  # (d, m, L)
    Kt = K + nugget**2 * np.eye(m)
    Vi, logdet = [], 0.0
    for ac in a:
        C = np.linalg.cholesky(ac * Kt + sigma**2 * np.eye(m))
        Ci = np.linalg.inv(C)
        Vi.append(Ci.T @ Ci)
        logdet += 2 * np.sum(np.log(np.diag(C)))
    Vi = np.array(Vi)  # (d, m, m)
    L = J.shape[2]
    Vr = np.einsum("cij,jc->ci", Vi, rc)  # V^-1 r per block
    if L:
        VJ = np.einsum("cij,cjl->cil", Vi, Jc)
        G = np.einsum("cil,cik->lk", Jc, VJ)
        T = VJ @ np.linalg.inv(G)  # (d, m, L)
        alpha = Vr - T @ np.einsum("cil,ci->l", Jc, Vr)  # Pi r per block
        Pi_diag = Vi - T @ VJ.transpose(0, 2, 1)  # the diagonal blocks of Pi
        logdet_G = np.linalg.slogdet(G)[1]
    else:
        alpha, Pi_diag, logdet_G = Vr, Vi, 0.0
    N = m * len(a)
    value = -0.5 * (np.sum(alpha * rc.T) + logdet + logdet_G + (N - L) * math.log(2 * math.pi))
    grad = np.array([0.5 * sum(ac * (alpha[c] @ Kk @ alpha[c] - np.sum(Pi_diag[c] * Kk)) for c, ac in enumerate(a))
                     for Kk in dK])
    return float(value), grad


def estimate_field(r: np.ndarray, J: np.ndarray, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray,
                   sigma: float) -> FieldFit:
    """The field of the residuals ``r`` (m, d) of a fit with Jacobian ``J`` (m, d, L) at the
    poses ``Q`` (m, n), their values' base ``axes`` (d,) and whitening ``Wh`` (module docstring)."""
    from scipy.optimize import minimize  # imported here: scipy.optimize takes ~0.3 s

    m, d = r.shape
    if m > FIELD_ROWS:
        keep = np.sort(np.random.default_rng(FIELD_SEED).choice(m, FIELD_ROWS, replace=False))
        r, J, Q = r[keep], J[keep], Q[keep]
        m = FIELD_ROWS
    A = Wh @ coupling(axes, axes) @ Wh.T
    n = Q.shape[1]
    spread = max(float(np.sqrt(max(np.mean(r[:, axes >= 0] ** 2) - sigma**2, sigma**2))), sigma)
    low = math.log(SCALE_LOW * sigma)
    bounds = [(low, math.log(100 * spread)), *[tuple(map(math.log, LENGTH_BOUNDS))] * n, (low, math.log(100 * spread))]
    width = np.maximum(np.std(Q, axis=0), 0.1)
    nugget0 = [math.log(max(0.3 * spread, SCALE_LOW * sigma))]
    fits = []
    for additive in (False, True):
        scales = [math.log(spread / math.sqrt(n))] * n if additive else [math.log(spread)]
        ell = ADDITIVE_LENGTH_BOUNDS if additive else LENGTH_BOUNDS

        def minus_l(t: np.ndarray, additive: bool = additive) -> tuple[float, np.ndarray]:
            value, grad = restricted_log_likelihood(t, r, J, Q, A, sigma, additive)
            return -value, -grad

        found = min((minimize(minus_l, np.concatenate([scales, np.log(np.clip(width / shrink, *ell)), nugget0]),
                              jac=True, method="L-BFGS-B",
                              bounds=bounds[:1] * len(scales) + [tuple(map(math.log, ell))] * n + bounds[-1:])
                     for shrink in (1.0, 3.0)),
                    key=lambda f: f.fun)
        theta = found.x
        if additive:
            s2 = np.exp(2 * theta[:n])
            field = Field(float(np.sqrt(s2.sum())), tuple(float(v) for v in np.exp(theta[n:2 * n])),
                          float(np.exp(theta[-1])), tuple(float(v) for v in s2 / s2.sum()))
        else:
            field = Field(float(np.exp(theta[0])), tuple(float(v) for v in np.exp(theta[1:1 + n])),
                          float(np.exp(theta[-1])))
        fits.append((2 * len(theta) + 2 * found.fun, FieldFit(field, float(-found.fun), m)))
    return min(fits, key=lambda f: f[0])[1]  # the lower AIC: 2 hyperparameters - 2 l


@dataclass(frozen=True, eq=False)
class TrainedField:
    """A field estimated with the rows it was estimated on: what predicts and corrects the
    robot's unmodelled error at other poses (:mod:`casadi_design.measures.field`). ``Q`` (m, n)
    the rows' poses, ``r`` (m, d) their whitened residuals (m), ``B`` (m, d, L) their rows at
    X = 0 (the design's), ``axes`` (d,) the base axis of each value, ``Wh`` the whitening and
    ``sigma`` the tracker's noise (m)."""

    estimate: FieldFit
    Q: np.ndarray
    r: np.ndarray
    B: np.ndarray
    axes: np.ndarray
    Wh: np.ndarray
    sigma: float

    @property
    def field(self) -> Field:
        return self.estimate.field

    def mean(self, Q0: np.ndarray, axes0: np.ndarray) -> np.ndarray:
        """The kriging mean of the error (s, r), m, at the poses ``Q0`` on the components of
        ``axes0`` (-1: an orientation, 0)."""
        return kriging_mean(self.field, self.sigma, self.r, self.Q, self.axes, self.Wh, Q0, axes0)

    def shift(self, Q0: np.ndarray) -> np.ndarray:
        """The correction of a point's position (s, 3), m, base frame: the kriging mean on x, y, z."""
        return self.mean(Q0, np.arange(3))

    def rho(self, B0: np.ndarray, Q0: np.ndarray, axes0: np.ndarray) -> np.ndarray:
        """The error variance (s,), m^2, after compensation with the field at the poses ``Q0``
        of rows ``B0`` (s, r, L): :func:`~casadi_design.measures.field.kriging_rho`."""
        return kriging_rho(self.field, self.sigma, self.B, self.Q, self.axes, self.Wh, B0, Q0, axes0)

    def loo_rms(self, with_field: bool = True) -> float:
        """The RMS per value (m) of the rows' leave-one-out errors: each row predicted from the
        others by least squares and, ``with_field``, the field's kriging. For the
        predictor with projector ``Pi = V^-1 - V^-1 S (S^T V^-1 S)^-1 S^T V^-1`` the row left out
        is off by ``Pi_ii^-1 (Pi r)_i`` (Dubrule, Cross validation of kriging in a unique
        neighborhood, 1983); ``V = I`` gives least squares' PRESS residuals."""
        m, d, L = self.B.shape
        S = self.B.reshape(m * d, L)
        V = (value_covariance(self.field, self.Q, self.axes, self.Wh, self.sigma) if with_field
             else np.eye(m * d))
        Vi = np.linalg.inv(V)
        ViS = Vi @ S
        Pi = Vi - ViS @ np.linalg.solve(S.T @ ViS, ViS.T)
        a = (Pi @ self.r.reshape(-1)).reshape(m, d)
        blocks = Pi.reshape(m, d, m, d)[np.arange(m), :, np.arange(m), :]  # (m, d, d)
        e = np.linalg.solve(blocks, a[:, :, None])[:, :, 0]
        return float(np.sqrt(np.mean(e**2)))
