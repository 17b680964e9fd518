"""The robot's unmodelled error as a random field: the test-pose measure with model discrepancy.

The paper's measure holds one error, the tracker's noise. A real robot also differs from its
model in ways no parameter holds (compliance, gears, temperature): some 0.25 mm per axis on a
UR10, 40 times its tracker's noise. Model it as Kennedy and O'Hagan's discrepancy (2001):

    y_i = B_i X + delta(q_i) + eps_i

with ``delta`` a Gaussian process over the joint configurations of p components, each of its
own covariance ``k_c(q, q')``, that move a pose's values by its loads ``G(q)`` (d x p):

    cov(y_i, y_k) = G_i diag(k_c(q_i, q_k)) G_k^T + nugget^2 [i == k] A + sigma^2 [i == k] I,

- **an error of the joint angles** (:attr:`Field.angles_rad`): component c is joint c's angle
  error, ``k_c = angle_c^2 exp(-1/2 ((q_c - q'_c) / length_c)^2)`` (rad^2), seen through the
  joint's own column of the values' Jacobian, ``G = dy/dq`` (at X = 0): an angle error of the
  gears moves the tool along ``J_c(q)``, whose lever changes with the other joints. IPA's UR10
  has such waves, 12 to 29 cycles per revolution in its pan and lift joints
  (``scripts/joint_error_scan.py``);
- **an error of each base axis** (x, y, z): ``G = Wh C`` (``C_va = [axis(v) == a]`` over the
  position values; the markers of a pose move together) and one kernel for the three, the
  squared exponential over all joints, ``k = scale^2 exp(-1/2 sum_l ((q_l - q'_l) /
  length_l)^2)`` (m^2), or additive over the joints (:attr:`Field.shares`);

the nugget ``A = Wh C C^T Wh^T`` the part no neighbouring pose tells (repeatability, backlash) and
``eps`` the tracker's noise, ``sigma^2`` per value, all in the whitened values of the model
(``Wh = sigma Sigma^-1/2``).

After calibration and compensation with the field, the error at test pose ``q0`` (loads ``G0``,
r x p, of its required components) is the error of the universal kriging predictor of ``z0 = B0
X + delta(q0)``: with the cross covariance ``k0 = cov(y, delta(q0))`` (N x r), ``H = P + B^T V^-1
B`` (P: the prior's information on X, 1/m^2 units of B) and ``R = B0 - k0^T V^-1 B``,

    rho(q0) = tr(T00) - tr(k0^T V^-1 k0) + tr(R H^-1 R^T) + nugget^2 r_p

(``T00 = G0 diag(k_c(q0, q0)) G0^T`` the field's own covariance at the test pose, ``r_p`` its
position components; the nugget at the test pose is not compensated). With no field it is
``sigma^2 tr(B0 M^-1 B0^T)``: the paper's measure is its limit. Measuring near the test poses
pays when the field dominates (``k0`` grows), informative poses when the noise does.

The kriging mean ``k0^T V^-1 r`` of the calibrated model's residuals ``r`` is the correction of
the compensated robot at ``q0`` (regression kriging: the parameters are the least squares'
ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from .criteria import CRITERIA
from .measures import SINGULAR_RTOL


@dataclass(frozen=True)
class Field:
    """The unmodelled error's field (module docstring): the correlation ``lengths`` (n,) per joint
    (rad, m for prismatic joints), the ``nugget_m`` (m) and either

    - ``angles_rad`` (n,): the std of each joint's angle error (rad; m for a prismatic joint),
      seen through the joint's own column of the Jacobian: an error of the joint angles, which
      correlates every pose that shares one angle, whatever the others (``scale_m`` 0); or
    - ``scale_m`` (m, per base axis), the squared exponential over all joints at once, which
      correlates only poses near in every joint; with ``shares`` (n,; sum 1) additive over the
      joints, ``k = scale^2 sum_l shares_l exp(-1/2 ((q_l - q'_l) / length_l)^2)`` on each base
      axis."""

    scale_m: float
    lengths: tuple[float, ...]
    nugget_m: float = 0.0
    shares: tuple[float, ...] = ()
    angles_rad: tuple[float, ...] = ()

    @property
    def through_joints(self) -> bool:
        """An error of the joint angles (:attr:`angles_rad`), not of the base axes."""
        return bool(self.angles_rad)

    def kernel(self, Qa: np.ndarray, Qb: np.ndarray) -> np.ndarray:
        """The base axes' smooth kernel (ka, kb), m^2: ``scale^2 exp(-1/2 |(qa - qb) / length|^2)``,
        or the sum over the joints with ``shares``."""
        ell = np.asarray(self.lengths, dtype=float)
        Za, Zb = np.atleast_2d(Qa) / ell, np.atleast_2d(Qb) / ell
        if self.shares:
            d2 = (Za[:, None, :] - Zb[None, :, :]) ** 2
            return self.scale_m**2 * np.exp(-0.5 * d2) @ np.asarray(self.shares, dtype=float)
        d2 = np.sum(Za**2, 1)[:, None] + np.sum(Zb**2, 1)[None, :] - 2 * Za @ Zb.T
        return self.scale_m**2 * np.exp(-0.5 * np.maximum(d2, 0.0))

    def components(self, Qa: np.ndarray, Qb: np.ndarray) -> np.ndarray:
        """``k_c(qa, qb)`` of each component (ka, kb, p): the joints' angle errors (rad^2), or
        the base axes' one kernel three times (m^2)."""
        if self.through_joints:
            ell, s = np.asarray(self.lengths, dtype=float), np.asarray(self.angles_rad, dtype=float)
            Za, Zb = np.atleast_2d(Qa) / ell, np.atleast_2d(Qb) / ell
            return s**2 * np.exp(-0.5 * (Za[:, None, :] - Zb[None, :, :]) ** 2)
        return np.repeat(self.kernel(Qa, Qb)[:, :, None], 3, axis=2)

    @property
    def variances(self) -> np.ndarray:
        """``k_c(q, q)`` of each component (p,)."""
        return (np.asarray(self.angles_rad, dtype=float) ** 2 if self.through_joints
                else np.full(3, self.scale_m**2))

    def sites(self, Q: np.ndarray, axes: np.ndarray, Wh: np.ndarray, dq: np.ndarray | None = None) -> Sites:
        """The :class:`Sites` of the poses ``Q`` (m, n) whose values lie on the base ``axes``
        (d,; -1 an orientation), whitened by ``Wh`` (d x d; the identity for a test pose's
        components); ``dq`` (m, d, n): the values' ``dy/dq`` as the values are (the measured
        ones whitened, a test pose's not), for the joints' field."""
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        C = coupling(axes, np.arange(3))
        if self.through_joints:
            G = np.asarray(dq, dtype=float).reshape(len(Q), len(axes), len(self.lengths))
        else:
            G = np.broadcast_to(Wh @ C, (len(Q), len(axes), 3))
        return Sites(Q, G, Wh @ C @ C.T @ Wh.T)

    def describe(self) -> str:
        """The field for people: its kind, the joints' angle errors (arcsec) or scale (mm),
        nugget (mm), lengths (rad per joint) and, additive, the joints' shares."""
        lengths = _per_joint(self.lengths, 1.0, "rad")
        if self.through_joints:
            return ("an error of the joint angles (through each joint's Jacobian column), angles "
                    + _per_joint(self.angles_rad, ARCSEC, "arcsec") + f", lengths {lengths}, nugget "
                    f"{self.nugget_m * 1e3:.4g} mm")
        return (f"scale {self.scale_m * 1e3:.4g} mm, nugget {self.nugget_m * 1e3:.4g} mm, lengths {lengths}"
                + (", additive over the joints, shares " + ", ".join(f"{v:.2f}" for v in self.shares)
                   if self.shares else ""))

    def as_dict(self) -> dict:
        if self.through_joints:
            kernel = ("cov(y, y') = sum_c angle_c^2 exp(-1/2 ((q_c - q'_c) / length_c)^2) (dy/dq_c)(dy'/dq_c)^T "
                      "+ nugget^2 [q == q'] per base axis")
        elif self.shares:
            kernel = "scale^2 sum_l shares_l exp(-1/2 ((q_l - q'_l) / length_l)^2) + nugget^2 [q == q'] per base axis"
        else:
            kernel = "scale^2 exp(-1/2 sum_l ((q_l - q'_l) / length_l)^2) + nugget^2 [q == q'] per base axis"
        return {"scale_m": self.scale_m, "lengths": list(self.lengths), "nugget_m": self.nugget_m,
                **({"shares": list(self.shares)} if self.shares else {}),
                **({"angles_rad": list(self.angles_rad)} if self.through_joints else {}), "kernel": kernel}


ARCSEC = 180.0 / np.pi * 3600.0


def _per_joint(values: tuple[float, ...], factor: float, unit: str) -> str:
    """Values per joint for people: one for every joint when they are all the same."""
    if len(set(values)) == 1:
        return f"{values[0] * factor:.3g} {unit} for every joint"
    return ", ".join(f"{v * factor:.3g}" for v in values) + f" {unit} per joint"


@dataclass(frozen=True, eq=False)
class Sites:
    """Poses where the field is seen and how their values see it: ``Q`` (m, n), rad; ``G`` (m,
    d, p) how each value moves with each component of the field (module docstring); ``A`` (d, d)
    the nugget's coupling of one pose's values."""

    Q: np.ndarray
    G: np.ndarray
    A: np.ndarray

    def __len__(self) -> int:
        return len(self.Q)

    def __getitem__(self, rows) -> Sites:
        return Sites(self.Q[rows], self.G[rows], self.A)

    def __add__(self, other: Sites) -> Sites:
        """The sites of both, these first."""
        return Sites(np.vstack([self.Q, other.Q]), np.concatenate([self.G, other.G]), self.A)


def model_sites(field: Field, model, Wh: np.ndarray, Q: np.ndarray, F: np.ndarray | None = None,
                rows: str = "measured") -> Sites:
    """The :class:`Sites` of the poses ``Q`` (m, n), rad, under the wrenches ``F`` (m, nF), N, of a
    calibration ``model`` (:class:`~casadi_design.calibration.models.CalibrationModel`) for their
    ``rows``: the measured values (``"measured"``, whitened by ``Wh``), the required components
    (``"accuracy"``) or the frame's origin (``"position"``, base frame)."""
    axes = {"measured": axes_of(model.measured_rows, len(model.markers_m)), "accuracy": axes_of(model.accuracy_rows),
            "position": np.arange(3)}[rows]
    return field.sites(Q, axes, Wh if rows == "measured" else np.eye(len(axes)),
                       model.dq_stack(Q, F, rows) if field.through_joints else None)


#: The criteria that weigh the test poses' rho, and so hold a field when the problem has one.
FIELD_CRITERIA = tuple(name for name, c in CRITERIA.items() if c.reads == "rho")


def field_measure(problem, criterion: str) -> bool:
    """Whether ``criterion`` weighs the test poses with the problem's field of unmodelled error
    (test-pose and I with :attr:`~casadi_design.problem.build.Problem.field`): its experiments are
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


def covariance(field: Field, Sa: Sites, Sb: Sites) -> np.ndarray:
    """``cov(delta(a), delta(b))`` of the smooth part between every value of the sites ``Sa``
    and ``Sb``: (ma, da, mb, db), m^2: :func:`loaded`."""
    return loaded(Sa.G, field.components(Sa.Q, Sb.Q), Sb.G)


def loaded(Ga: np.ndarray, K: np.ndarray, Gb: np.ndarray) -> np.ndarray:
    """``G_a diag(K_ab) G_b^T`` for every pair (ma, da, mb, db) of loads ``Ga`` (ma, da, p), ``Gb``
    (mb, db, p) and components' covariances ``K`` (ma, mb, p)."""
    T = Ga[:, None, :, :] * K[:, :, None, :]  # (ma, mb, da, p): G_a diag(K_ab)
    return np.matmul(T, Gb.transpose(0, 2, 1)[None]).transpose(0, 2, 1, 3)  # one small product per pair


def value_covariance(field: Field, S: Sites, sigma: float) -> np.ndarray:
    """``V`` (N x N), N = m d, m^2: the covariance of the whitened values of the sites ``S``
    (module docstring)."""
    m, d = S.G.shape[:2]
    return covariance(field, S, S).reshape(m * d, m * d) + np.kron(np.eye(m), noise(field, S, sigma))


def noise(field: Field, S: Sites, sigma: float) -> np.ndarray:
    """The part of a site's own covariance (d x d), m^2, that no other site shares: the nugget's
    ``nugget^2 A`` and the tracker's ``sigma^2 I``."""
    return field.nugget_m**2 * S.A + sigma**2 * np.eye(len(S.A))


def cross_covariance(field: Field, S: Sites, S0: Sites) -> np.ndarray:
    """``k0 = cov(y, delta(q0))`` for every test pose of ``S0``: (s, N, r), m^2 (:func:`covariance`)."""
    return covariance(field, S, S0).transpose(2, 0, 1, 3).reshape(len(S0), -1, S0.G.shape[1])


def own_variance(field: Field, S0: Sites) -> np.ndarray:
    """``tr(T00) + nugget^2 r_p`` (s,), m^2: the field's variance summed over each test pose's
    components, before any measurement."""
    return np.einsum("c,svc->s", field.variances, S0.G**2) + field.nugget_m**2 * np.trace(S0.A)


def _regular(lam: np.ndarray) -> np.ndarray:
    """Whether each matrix of ascending eigenvalues ``lam`` (..., L) identifies X: its smallest
    above :data:`~casadi_design.measures.measures.SINGULAR_RTOL` of its largest."""
    return lam[..., 0] > SINGULAR_RTOL * np.maximum(lam[..., -1], np.finfo(float).tiny)


def kriging_rho(field: Field, sigma: float, B: np.ndarray, S: Sites, B0: np.ndarray, S0: Sites,
                P: np.ndarray | None = None) -> np.ndarray:
    """``rho(q0)`` (s,), m^2, at the test poses ``S0`` (s sites) of rows ``B0`` (s, r, L) after a
    campaign of sites ``S`` (m) with rows ``B`` (m, d, L) (whitened), a prior information ``P``
    (L x L, 1/m^2 units of B; None: none) (module docstring). Infinite where the campaign does
    not identify X."""
    m, d, L = B.shape
    if not m:
        return np.full(len(S0), np.inf)
    Cv = np.linalg.cholesky(value_covariance(field, S, sigma))
    k0 = cross_covariance(field, S, S0)  # (s, N, r)
    W = np.linalg.solve(Cv, np.concatenate([B.reshape(m * d, L), k0.transpose(1, 0, 2).reshape(m * d, -1)], axis=1))
    WS, Wk = W[:, :L], W[:, L:].reshape(m * d, len(S0), -1).transpose(1, 0, 2)  # Cv^-1 S, Cv^-1 k0
    H = WS.T @ WS + (0.0 if P is None else P)
    lam = np.linalg.eigvalsh(H)
    if not _regular(lam):
        return np.full(len(S0), np.inf)
    R = B0 - np.einsum("snc,nl->scl", Wk, WS)  # B0 - k0^T V^-1 B
    Y = np.linalg.solve(np.linalg.cholesky(H), R.transpose(0, 2, 1))
    return own_variance(field, S0) - np.einsum("snc,snc->s", Wk, Wk) + np.einsum("slc,slc->s", Y, Y)


def kriging_mean(field: Field, sigma: float, r: np.ndarray, S: Sites, S0: Sites) -> np.ndarray:
    """The field's kriging mean at the sites ``S0`` (s, r), m: ``k0^T V^-1 r`` of the whitened
    residuals ``r`` (m, d) of the sites ``S`` (regression kriging, module docstring)."""
    alpha = np.linalg.solve(value_covariance(field, S, sigma), np.asarray(r, dtype=float).reshape(-1))
    return np.einsum("snc,n->sc", cross_covariance(field, S, S0), alpha)


@dataclass(frozen=True, eq=False)
class Held:
    """The held poses' part of every campaign's kriging, eliminated once (they never leave a
    campaign): ``Ch`` (h d x h d, ``V_hh = Ch Ch^T``), their whitened rows ``UB = Ch^-1 B_h``
    (h d x L) and cross covariance with the test poses ``Uk = Ch^-1 k0_h`` (h d x s r), and what
    G, R and ``tr(k0^T V^-1 k0)`` of every campaign start from: ``G = P + UB^T UB`` (L x L), ``R =
    B0 - Uk^T UB`` (s, r, L), ``KK = |Uk|^2`` per test pose (s,). A campaign's other values y_p
    then enter through ``x^T V^-1 y = (Ch^-1 x_h)^T (Ch^-1 y_h) + e_x^T D^-1 e_y`` with ``T = V_ph
    Ch^-T``, ``e_x = x_p - T Ch^-1 x_h`` and ``D = V_pp - T T^T``."""

    Ch: np.ndarray
    UB: np.ndarray
    Uk: np.ndarray
    G: np.ndarray
    R: np.ndarray
    KK: np.ndarray


def held_part(field: Field, sigma: float, Bh: np.ndarray, Sh: Sites, B0: np.ndarray, S0: Sites,
              P: np.ndarray | None = None) -> Held:
    """The :class:`Held` part of the held poses ``Sh`` (h sites, rows ``Bh`` (h, d, L), none
    allowed) for the test poses ``S0`` of rows ``B0`` (s, r, L), with the prior information ``P``
    (L x L; None: none)."""
    s, r, L = B0.shape
    Ch, UB, Uk = np.zeros((0, 0)), np.zeros((0, L)), np.zeros((0, s * r))
    if len(Sh):
        Ch = np.linalg.cholesky(value_covariance(field, Sh, sigma))
        UB, Uk = np.split(solve_triangular(Ch, np.concatenate([Bh.reshape(-1, L), covariance(field, Sh, S0).reshape(
            -1, s * r)], axis=1), lower=True, check_finite=False), [L], axis=1)
    return Held(Ch, UB, Uk, (np.zeros((L, L)) if P is None else P) + UB.T @ UB, B0 - (Uk.T @ UB).reshape(s, r, L),
                np.sum(Uk**2, axis=0).reshape(s, r).sum(axis=1))


def own_blocks(field: Field, S: Sites, sigma: float) -> np.ndarray:
    """The covariance of each site's own whitened values (m, d, d), m^2: the diagonal blocks of
    :func:`value_covariance`."""
    return np.einsum("cvp,p,cwp->cvw", S.G, field.variances, S.G) + noise(field, S, sigma)


def added_rho(G: np.ndarray, R: np.ndarray, KK: np.ndarray, Sch: np.ndarray, u: np.ndarray, w: np.ndarray,
              own: np.ndarray) -> np.ndarray:
    """``rho`` (k, s), m^2, of a campaign plus one candidate each, by bordering its kriging
    system: from the campaign's ``G = S^T V^-1 S + P`` (L x L), ``R = B0 - k0^T V^-1 S`` (s, r,
    L) and ``KK = tr(k0^T V^-1 k0)`` per test pose (s,), and per candidate the Schur complement
    ``Sch = v_cc - v^T V^-1 v`` (k, d, d), ``u = B_c - v^T V^-1 S`` (k, d, L) and ``w =
    k0_c - v^T V^-1 k0`` (k, d, s r); ``own`` the test poses' own variance (s,).

    The candidate brings in rank-d updates: ``H_c = G + u^T Sch^-1 u``, ``KK + tr(w^T Sch^-1 w)``
    and ``R - y^T u`` (``y = Sch^-1 w``), and ``rho = own - KK - tr(w^T y) + tr(R_c H_c^-1
    R_c^T)``. Where G is regular, Woodbury's ``H_c^-1 = G^-1 - G^-1 u^T M^-1 u G^-1`` (``M = Sch
    + u G^-1 u^T``, the candidate's variance after the campaign's kriging) collapses it to the
    campaign's own rho less the candidate's share,

        rho_c = own - KK + tr(R G^-1 R^T) - tr(E^T M^-1 E),  E = w + u G^-1 R^T (d x r per test pose),

    a d x d inverse and products of d x s r blocks per candidate; else each H_c is factored.
    Infinite where a campaign does not identify X."""
    k, d, L = u.shape
    s, r = R.shape[0], R.shape[1]

    def per_pose(X: np.ndarray) -> np.ndarray:  # (k, d, s r) summed over d and r: (k, s)
        return X.sum(axis=1).reshape(len(X), s, r).sum(axis=2)

    lam = np.linalg.eigvalsh(G)
    if _regular(lam):  # Woodbury over G
        Gi = cho_solve((np.linalg.cholesky(G), True), np.eye(L), check_finite=False)
        R2 = R.reshape(s * r, L)
        GiR = Gi @ R2.T  # (L, s r)
        u2 = u.reshape(k * d, L)
        E = w + (u2 @ GiR).reshape(k, d, s * r)
        M = Sch + (u2 @ Gi).reshape(k, d, L) @ u.transpose(0, 2, 1)  # (k, d, d)
        RGR = np.sum(R2 * GiR.T, axis=1).reshape(s, r).sum(axis=1)
        return (own - KK + RGR)[None] - per_pose(E * (np.linalg.inv(M) @ E))
    Schi = np.linalg.inv(Sch)
    y = Schi @ w  # (k, d, s r)
    H = G + u.transpose(0, 2, 1) @ (Schi @ u)
    Rc = R[None] - np.einsum("casr,cal->csrl", y.reshape(k, d, s, r), u)  # (k, s, r, L)
    out = np.full((k, s), np.inf)
    lam = np.linalg.eigvalsh(H)
    ok = _regular(lam)
    if ok.any():
        Ch = np.linalg.cholesky(H[ok])
        Zc = np.linalg.solve(Ch, Rc[ok].transpose(0, 3, 1, 2).reshape(int(ok.sum()), L, s * r))
        out[ok] = (own - KK)[None] - per_pose((w * y)[ok]) + np.sum(Zc.reshape(-1, L, s, r) ** 2, axis=(1, 3))
    return out
