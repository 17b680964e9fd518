"""The unmodelled error's field estimated from a fit's residuals: restricted maximum likelihood.

The residuals ``r`` (N = m d whitened values, m) of a least-squares fit with Jacobian ``J``
(N x L) are those of ``y = J X + delta + eps`` (:mod:`casadi_design.measures.field`) with the
parameters profiled out. Their restricted (REML) log-likelihood (Patterson and Thompson 1971;
Rasmussen and Williams, Gaussian Processes for Machine Learning, 2006, 2.7) is

    l(theta) = -1/2 (r^T Pi r + log|V| + log|J^T V^-1 J| + (N - L) log 2 pi),
    Pi = V^-1 - V^-1 J (J^T V^-1 J)^-1 J^T V^-1,

with gradient ``dl/dtheta_k = 1/2 (r^T Pi V_k Pi r - tr(Pi V_k))``, ``V_k = dV/dtheta_k``,
``theta = log(scale, length_1 .. length_n, nugget)``; the tracker's sigma is the problem's. It
is maximised by L-BFGS-B (scipy) from two starts (the joint angles' per joint: from the optimum of
one angle and length for every joint), for the fields of
:class:`~casadi_design.measures.field.Field`: of the base axes, the squared exponential over the
joints and the one additive over them; of the joint angles, seen through each joint's Jacobian
column (``theta = log(angle_1 .. angle_n, length_1 .. length_n, nugget)``, V dense), with an
angle and a length per joint or one angle and one length for every joint (a robot whose joints
have gears alike); the one of the lower AIC (``2 k - 2 l``, k hyperparameters: n + 2, 2 n + 1,
2 n + 1 and 3) is kept. Without parameters (L = 0) it is the
marginal likelihood of a Gaussian process regression of the residuals on the joint
configurations, one output per base axis sharing the kernel: scikit-learn's
``GaussianProcessRegressor`` with ``ConstantKernel * RBF + WhiteKernel`` and ``alpha = sigma^2``
gives the same value (tests/identification/test_field_fit.py). A fit of more than ``FIELD_ROWS``
rows is estimated on that many of them (seeded): the hyperparameters of a few hundred poses
are as good as of thousands, at a cubic cost. Each kind's starts are searched on ``PRE_ROWS``
of those and the best refined on all of them (IPA, 300 rows: the same field, 4.9 s instead of
8 s), the base axes' kinds and the joint angles' on two threads.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from dataclasses import field as dataclass_field

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotri

from ..measures.field import (
    Field,
    Sites,
    coupling,
    kriging_mean,
    kriging_rho,
    loaded,
    model_sites,
    value_covariance,
)

#: Rows the field is estimated from, at most.
FIELD_ROWS = 300
#: Seed of the rows kept when there are more.
FIELD_SEED = 0
#: Rows (of those) the starts are searched on first; the best is then refined on all of them.
PRE_ROWS = 100
#: The lengths are searched within these (rad or m), the scale and nugget from SCALE_LOW sigma.
LENGTH_BOUNDS = (0.02, 50.0)
#: ... those of the additive field and of the joint angles' within these: a joint's share longer
#: than about a radian is all but a constant or a slope over its range, which the geometric
#: parameters take, and its variance is then not told by the restricted likelihood (it runs to
#: its bound).
ADDITIVE_LENGTH_BOUNDS = (0.02, 1.0)
SCALE_LOW = 1e-3
#: L-BFGS-B's relative change of the log-likelihood at which it stops.
FTOL = 1e-7


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


def squared_differences(Q: np.ndarray) -> np.ndarray:
    """``(q_il - q_kl)^2`` (m, m, n) of the poses ``Q`` (m, n): the kernels' distances before
    their lengths, once per estimate."""
    return (Q[:, None, :] - Q[None, :, :]) ** 2


def restricted_log_likelihood(theta: np.ndarray, r: np.ndarray, J: np.ndarray, Q: np.ndarray, A: np.ndarray,
                              sigma: float, additive: bool = False,
                              D0: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """``l(theta)`` and its gradient (module docstring) for residuals ``r`` (m, d), ``J`` (m, d,
    L), poses ``Q`` (m, n), the coupling ``A`` (d, d) of a pose's values; ``additive``: the
    field additive over the joints, ``theta = log(s_1 .. s_n, length_1 .. length_n, nugget)``
    with ``K = sum_l s_l^2 exp(-1/2 ((q_l - q'_l) / length_l)^2)``; ``D0``: the poses'
    :func:`squared_differences` (None: computed here).

    With ``A = U diag(a) U^T`` the values rotated by ``U`` have ``V = blockdiag_c(a_c Kt +
    sigma^2 I)`` (``Kt = K + nugget^2 I``, m x m): d blocks of m x m instead of one of m d."""
    m, n = Q.shape
    nugget, scales = np.exp(theta[-1]), np.exp(theta[:n] if additive else theta[:1])
    ell = np.exp(theta[len(scales):len(scales) + n])
    D = (squared_differences(Q) if D0 is None else D0) / ell**2  # (m, m, n)
    if additive:
        s2 = scales**2
        E = np.exp(-0.5 * D)
        K = E @ s2
    else:
        K = scales[0] ** 2 * np.exp(-0.5 * D.sum(axis=2))
    a, U = np.linalg.eigh(A)
    rc = r @ U  # (m, d): the rotated values, column c of weight a_c
    Jc = np.einsum("mdl,dc->cml", J, U)  # (d, m, L)
    Kt = K + nugget**2 * np.eye(m)
    Vi, logdet, blocks = np.empty((len(a), m, m)), 0.0, {}
    for c, ac in enumerate(a):
        if ac not in blocks:  # blocks of equal weight (an isotropic tracker: all d) inverted once
            blocks[ac] = _inverse(ac * Kt + sigma**2 * np.eye(m))
        Vi[c], logdet_c = blocks[ac]
        logdet += logdet_c
    L = J.shape[2]
    Vr = np.einsum("cij,jc->ci", Vi, rc)  # V^-1 r per block
    if L:
        VJ = Vi @ Jc
        G = np.einsum("cil,cik->lk", Jc, VJ)
        T = VJ @ np.linalg.inv(G)  # (d, m, L)
        alpha = Vr - T @ np.einsum("cil,ci->l", Jc, Vr)  # Pi r per block
        Pi_diag = Vi - T @ VJ.transpose(0, 2, 1)  # the diagonal blocks of Pi
        logdet_G = np.linalg.slogdet(G)[1]
    else:
        alpha, Pi_diag, logdet_G = Vr, Vi, 0.0
    N = m * len(a)
    value = -0.5 * (np.sum(alpha * rc.T) + logdet + logdet_G + (N - L) * math.log(2 * math.pi))
    # dl/dtheta_k = 1/2 sum_c a_c (alpha_c^T dKt_k alpha_c - <Pi_c, dKt_k>) = 1/2 <dKt_k, Psi>
    Psi = np.einsum("c,ci,cj->ij", a, alpha, alpha) - np.einsum("c,cij->ij", a, Pi_diag)
    if additive:  # dKt: 2 s_l^2 E_l, s_l^2 E_l D_l, 2 nugget^2 I
        EP = E * Psi[:, :, None]
        grad = np.concatenate([s2 * EP.sum(axis=(0, 1)), 0.5 * s2 * np.einsum("ijl,ijl->l", EP, D)])
    else:  # dKt: 2 K, K D_l, 2 nugget^2 I
        KP = K * Psi
        grad = np.concatenate([[np.sum(KP)], 0.5 * np.einsum("ij,ijl->l", KP, D)])
    return float(value), np.append(grad, nugget**2 * np.trace(Psi))


def _inverse(V: np.ndarray) -> tuple[np.ndarray, float]:
    """``V^-1`` and ``log|V|`` of a covariance by its Cholesky factor (LAPACK's potrf, potri).

    Raises
    ------
    numpy.linalg.LinAlgError
        V not positive definite."""
    C, info = dpotrf(V, lower=1)  # the upper triangle zero (clean)
    if info:
        raise np.linalg.LinAlgError("the field's covariance is not positive definite")
    logdet = 2 * float(np.sum(np.log(np.diag(C))))
    Vi = dpotri(C, lower=1, overwrite_c=1)[0]  # the lower triangle; the upper still zero
    own = Vi.diagonal().copy()
    Vi = Vi + Vi.T  # both triangles (a copy of the lower in the upper: no tril copies)
    np.fill_diagonal(Vi, own)
    return Vi, logdet


def joints_log_likelihood(theta: np.ndarray, r: np.ndarray, J: np.ndarray, S: Sites,
                          sigma: float, D0: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """``l(theta)`` and its gradient (module docstring) of the field of the joints' angle errors
    for residuals ``r`` (m, d), ``J`` (m, d, L) at the sites ``S`` (their loads ``dy/dq``),
    ``theta = log(angle_1 .. angle_n, length_1 .. length_n, nugget)``. ``V`` is dense (m d x m
    d); ``dV/dtheta_k`` is never formed: with ``a_ic = G_ic^T alpha_i`` and ``P_c[i, k] = G_ic^T
    Pi_ik G_kc``, ``alpha^T dV alpha`` and ``tr(Pi dV)`` of joint c's angle are ``2 a_c^T K_c a_c``
    and ``2 sum(K_c * P_c)``, of its length ``K_c * D_c`` in their place."""
    m, d = r.shape
    n, N, L = S.Q.shape[1], m * d, J.shape[2]
    s2, ell, nug2 = np.exp(2 * theta[:n]), np.exp(theta[n:2 * n]), np.exp(2 * theta[-1])
    D = (squared_differences(S.Q) if D0 is None else D0) / ell**2  # (m, m, n)
    K = s2 * np.exp(-0.5 * D)  # k_c(q_i, q_k)
    V = loaded(S.G, K, S.G).reshape(N, N)  # a new array: the nugget and the noise added in place
    V.reshape(m, d, m, d)[np.arange(m), :, np.arange(m), :] += nug2 * S.A
    V.flat[::N + 1] += sigma**2
    Vi, logdet = _inverse(V)
    if L:
        Sx = J.reshape(N, L)
        VS = Vi @ Sx
        Gm = Sx.T @ VS
        Pi = Vi  # V^-1 no longer needed: Pi in its place
        Pi -= VS @ np.linalg.solve(Gm, VS.T)
        logdet_G = np.linalg.slogdet(Gm)[1]
    else:
        Pi, logdet_G = Vi, 0.0
    rr = r.reshape(N)
    alpha = Pi @ rr
    value = -0.5 * (rr @ alpha + logdet + logdet_G + (N - L) * math.log(2 * math.pi))
    a = np.einsum("ivc,iv->ic", S.G, alpha.reshape(m, d))  # (m, n)
    P4 = Pi.reshape(m, d, m, d)
    P = np.stack([np.einsum("iv,ivkw,kw->ik", S.G[:, :, c], P4, S.G[:, :, c], optimize=True) for c in range(n)])
    quad = np.einsum("ic,ikc,kc->c", a, K, a)
    trace = np.einsum("ikc,cik->c", K, P)
    KD = K * D
    quad_l = np.einsum("ic,ikc,kc->c", a, KD, a)
    trace_l = np.einsum("ikc,cik->c", KD, P)
    Pd = P4[np.arange(m), :, np.arange(m), :]  # (m, d, d)
    Ar = alpha.reshape(m, d)
    nug = 2 * nug2 * (np.einsum("iv,vw,iw->", Ar, S.A, Ar) - np.einsum("ivw,wv->", Pd, S.A))
    grad = 0.5 * np.concatenate([2 * (quad - trace), quad_l - trace_l, [nug]])
    return float(value), grad


def estimate_field(r: np.ndarray, J: np.ndarray, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray,
                   sigma: float, dq: np.ndarray | None = None) -> FieldFit:
    """The field of the residuals ``r`` (m, d) of a fit with Jacobian ``J`` (m, d, L) at the
    poses ``Q`` (m, n), their values' base ``axes`` (d,) and whitening ``Wh`` (module
    docstring); with ``dq`` (m, d, n), the values' ``dy/dq`` (whitened), the field of the joint
    angles is among those compared."""
    from scipy.optimize import minimize  # imported here: scipy.optimize takes ~0.3 s

    m = len(r)
    if m > FIELD_ROWS:
        keep = np.sort(np.random.default_rng(FIELD_SEED).choice(m, FIELD_ROWS, replace=False))
        r, J, Q = r[keep], J[keep], Q[keep]
        dq = None if dq is None else dq[keep]
        m = FIELD_ROWS
    A = Wh @ coupling(axes, axes) @ Wh.T
    n, D0 = Q.shape[1], squared_differences(Q)
    seen = r[:, axes >= 0] if np.any(axes >= 0) else r  # positions; an orientation's only without them
    spread = max(float(np.sqrt(max(np.mean(seen**2) - sigma**2, sigma**2))), sigma)
    low, high = math.log(SCALE_LOW * sigma), math.log(100 * spread)
    width = np.maximum(np.std(Q, axis=0), 0.1)
    nugget0 = [math.log(max(0.3 * spread, SCALE_LOW * sigma))]
    if dq is not None:  # an angle (rad) moves a value by |dy/dq| (m per rad)
        sites = Sites(Q, dq, A)
        lever = max(float(np.sqrt(np.mean(np.sum(dq**2, axis=1)))), 1e-9)
    pre = np.sort(np.random.default_rng(FIELD_SEED).permutation(m)[:PRE_ROWS]) if m > PRE_ROWS else None

    def fit(kind: str, alike_theta: np.ndarray | None = None) -> tuple[float, FieldFit, np.ndarray]:
        """The kind's field of the highest restricted likelihood, its AIC and hyperparameters."""
        if kind.startswith("joints"):
            k = 1 if kind == "joints alike" else n  # one angle and one length for every joint, or each its own
            scales, scale_bounds = [math.log(spread / lever / math.sqrt(n))] * k, (low - math.log(lever),
                                                                                   high - math.log(lever))
            E = np.zeros((2 * n + 1, 2 * k + 1))  # theta = E t
            E[np.arange(n), np.arange(n) % k] = E[n + np.arange(n), k + np.arange(n) % k] = E[-1, -1] = 1.0

            def minus_l(t: np.ndarray, rows: slice | np.ndarray) -> tuple[float, np.ndarray]:
                if stop.is_set():  # the other thread was interrupted (Ctrl-C) or failed
                    raise InterruptedError
                value, grad = joints_log_likelihood(E @ t, r[rows], J[rows], sites[rows], sigma, D0[rows][:, rows])
                return -value, -E.T @ grad
        else:
            additive = kind == "additive"
            scales = [math.log(spread / math.sqrt(n))] * n if additive else [math.log(spread)]
            scale_bounds = (low, high)

            def minus_l(t: np.ndarray, rows: slice | np.ndarray) -> tuple[float, np.ndarray]:
                value, grad = restricted_log_likelihood(t, r[rows], J[rows], Q[rows], A, sigma, additive,
                                                        D0[rows][:, rows])
                return -value, -grad

        ell = LENGTH_BOUNDS if kind == "axes" else ADDITIVE_LENGTH_BOUNDS
        w0 = width if len(scales) > 1 or kind == "axes" else np.full(1, np.median(width))
        bounds = [scale_bounds] * len(scales) + [tuple(map(math.log, ell))] * len(w0) + [(low, high)]
        # an angle and a length per joint: from the optimum of one for every joint (nested, so its
        # likelihood is at least that one's); the others from two starts
        starts = ([alike_theta] if kind == "joints" else
                  [np.concatenate([scales, np.log(np.clip(w0 / shrink, *ell)), nugget0]) for shrink in (1.0, 3.0)])

        def search(rows: slice | np.ndarray, starts: list[np.ndarray]):
            return min((minimize(minus_l, t0, args=(rows,), jac=True, method="L-BFGS-B", bounds=bounds,
                                 options={"ftol": FTOL}) for t0 in starts), key=lambda f: f.fun)

        if pre is not None:  # the starts searched on PRE_ROWS of the rows, the best refined on all
            starts = [search(pre, starts).x]
        found = search(slice(None), starts)
        theta = E @ found.x if kind.startswith("joints") else found.x  # the joints': one entry per joint
        first = n if kind.startswith("joints") else len(scales)
        lengths, nugget = tuple(float(v) for v in np.exp(theta[first:first + n])), float(np.exp(theta[-1]))
        if kind.startswith("joints"):
            field = Field(0.0, lengths, nugget, (), tuple(float(v) for v in np.exp(theta[:n])))
        elif kind == "additive":
            s2 = np.exp(2 * theta[:n])
            field = Field(float(np.sqrt(s2.sum())), lengths, nugget, tuple(float(v) for v in s2 / s2.sum()))
        else:
            field = Field(float(np.exp(theta[0])), lengths, nugget)
        return 2 * len(found.x) + 2 * found.fun, FieldFit(field, float(-found.fun), m), theta

    def joints() -> list[tuple[float, FieldFit, np.ndarray]]:
        alike = fit("joints alike")
        return [alike, fit("joints", alike[2])]

    # the base axes' kinds here and the joint angles' on a thread (LAPACK and numpy release the
    # GIL; each optimisation runs as it would alone, so the estimate does not depend on it)
    stop, pool = threading.Event(), ThreadPoolExecutor(max_workers=1)
    try:
        angles = pool.submit(joints) if dq is not None else None
        fits = [fit("axes"), fit("additive")] + ([] if angles is None else angles.result())
    except BaseException:  # Ctrl-C stops the thread at its next evaluation
        stop.set()
        raise
    finally:
        pool.shutdown(wait=True)
    return min(fits, key=lambda f: f[0])[1]  # the lower AIC: 2 hyperparameters - 2 l


@dataclass(frozen=True, eq=False)
class TrainedField:
    """A field estimated with the rows it was estimated on: what predicts and corrects the
    robot's unmodelled error at other poses (:mod:`casadi_design.measures.field`). ``sites`` the
    rows' :class:`~casadi_design.measures.field.Sites`, ``r`` (m, d) their whitened residuals
    (m), ``B`` (m, d, L) their rows at X = 0 (the design's), ``Wh`` the whitening, ``sigma`` the
    tracker's noise (m) and ``model`` the calibration model (how other poses see the field)."""

    estimate: FieldFit
    sites: Sites
    r: np.ndarray
    B: np.ndarray
    Wh: np.ndarray
    sigma: float
    model: object
    _loo: dict = dataclass_field(default_factory=dict, init=False, repr=False)  # loo_rms's, once each

    @property
    def field(self) -> Field:
        return self.estimate.field

    @property
    def Q(self) -> np.ndarray:
        """The rows' poses (m, n), rad."""
        return self.sites.Q

    def at(self, Q0: np.ndarray, F0: np.ndarray | None = None, rows: str = "accuracy") -> Sites:
        """The sites of the poses ``Q0`` (s, n) under the wrenches ``F0`` for their ``rows``: the
        required components (``"accuracy"``), the measured values (``"measured"``, whitened) or
        the frame's origin (``"position"``, base frame)."""
        return model_sites(self.field, self.model, self.Wh, Q0, F0, rows)

    def mean(self, S0: Sites) -> np.ndarray:
        """The kriging mean of the error (s, r), m, at the sites ``S0``."""
        return kriging_mean(self.field, self.sigma, self.r, self.sites, S0)

    def shift(self, Q0: np.ndarray) -> np.ndarray:
        """The correction of the frame's position (s, 3), m, base frame: the kriging mean on x, y, z."""
        return self.mean(self.at(Q0, rows="position"))

    def turn(self, Q0: np.ndarray, F0: np.ndarray | None = None) -> np.ndarray:
        """The tool's turn (s, 3), rad, base frame, on the orientation components the test poses
        require (0 on the others): the kriging mean of their rows. Only an error of the joint
        angles turns the tool; the base axes' field moves positions."""
        model = self.model
        turn = np.zeros((len(np.atleast_2d(Q0)), 3))
        rot = [k for k, a in enumerate(model.accuracy_rows) if a >= 3]
        if self.field.through_joints and rot:
            turn[:, [model.accuracy_rows[k] - 3 for k in rot]] = self.mean(self.at(Q0, F0, "accuracy"))[:, rot]
        return turn

    def marker_shift(self, Q0: np.ndarray, F0: np.ndarray | None = None) -> np.ndarray:
        """The correction of each measured point (s, markers, 3), m, base frame (0 on an axis not
        measured): the kriging mean of the measured values, un-whitened. The base axes' field
        moves the markers of a pose together (:meth:`shift`); an angle error of a joint turns
        them about it, each by its own lever."""
        model = self.model
        markers = len(model.markers_m)
        if not self.field.through_joints:
            return np.repeat(self.shift(Q0)[:, None, :], markers, axis=1)
        pos = [a for a in model.measured_rows if a < 3]
        dev = self.mean(self.at(Q0, F0, "measured")) @ np.linalg.inv(self.Wh).T  # (s, d)
        out = np.zeros((len(dev), markers, 3))
        out[:, :, pos] = dev[:, :markers * len(pos)].reshape(len(dev), markers, len(pos))
        return out

    def rho(self, B0: np.ndarray, S0: Sites) -> np.ndarray:
        """The error variance (s,), m^2, after compensation with the field at the sites ``S0``
        of rows ``B0`` (s, r, L): :func:`~casadi_design.measures.field.kriging_rho`."""
        return kriging_rho(self.field, self.sigma, self.B, self.sites, B0, S0)

    def loo_rms(self, with_field: bool = True) -> float:
        """The RMS per value (m) of the rows' leave-one-out errors: each row predicted from the
        others by least squares and, ``with_field``, the field's kriging. For the
        predictor with projector ``Pi = V^-1 - V^-1 S (S^T V^-1 S)^-1 S^T V^-1`` the row left out
        is off by ``Pi_ii^-1 (Pi r)_i`` (Dubrule, Cross validation of kriging in a unique
        neighborhood, 1983); ``V = I`` gives least squares' PRESS residuals. Each is computed
        once (the notes and identification.json read both)."""
        if with_field not in self._loo:
            self._loo[with_field] = self._loo_rms(with_field)
        return self._loo[with_field]

    def _loo_rms(self, with_field: bool) -> float:
        m, d, L = self.B.shape
        S = self.B.reshape(m * d, L)
        if with_field:
            Vi = np.linalg.inv(value_covariance(self.field, self.sites, self.sigma))
            ViS = Vi @ S
        else:  # V = I: V^-1 S is S (a copy: numpy would take S^T S for syrk's, which rounds otherwise)
            Vi, ViS = np.eye(m * d), S.copy()
        Pi = Vi - ViS @ np.linalg.solve(S.T @ ViS, ViS.T)
        a = (Pi @ self.r.reshape(-1)).reshape(m, d)
        blocks = Pi.reshape(m, d, m, d)[np.arange(m), :, np.arange(m), :]  # (m, d, d)
        e = np.linalg.solve(blocks, a[:, :, None])[:, :, 0]
        return float(np.sqrt(np.mean(e**2)))
