"""Identifiable base set of geometric parameters: QR with column pivoting.

The full error model (per joint an offset and six placement errors, plus base and tool
errors) is redundant. Stack the identification Jacobian of the measured values over random
configurations, ``S = [B(q_1); ...; B(q_N)]``, scale each column to unit norm (so the choice
does not depend on units), and factor ``S P = Q R`` with column pivoting (ties to the
parameter listed first, :func:`pivoted_columns`). The rank r is the
number of ``|R_ii| > RANK_RTOL |R_00|``; the first r pivoted columns are a base set. Every
other parameter is reported with the reason it was dropped: no effect on the measured values
(zero column), or the kept parameters it is a combination of (least-squares coefficients).

Theory (serial chain, R revolute and P prismatic joints): 4R + 2P + 6 parameters with
full-pose measurement, 4R + 2P + 3 with the position of one point. Three non-collinear
markers on the tool determine its full pose: 4R + 2P + 6.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .models import CalibrationModel

#: Relative threshold on |R_ii| (column-normalised S) below which a direction is not identifiable.
RANK_RTOL = 1e-8
#: Column norms within this (relative) of the largest tie in the pivoting: the first column wins.
TIE_RTOL = 1e-9
#: Random configurations stacked.
SAMPLES = 80
#: A dropped parameter's partners are the kept ones with |coefficient| above this.
PARTNER_TOL = 1e-6


@dataclass(frozen=True)
class BaseSet:
    """Result of the selection: kept names, dropped names with reasons, rank and tolerance."""

    kept: tuple[str, ...]
    dropped: tuple[tuple[str, str], ...]
    rank: int
    rank_rtol: float

    def report(self) -> str:
        lines = [f"identifiable base set: {self.rank} parameters (QR with column pivoting, "
                 f"rank tolerance {self.rank_rtol:g} relative, unit-norm columns)",
                 "kept: " + ", ".join(self.kept)]
        lines += [f"dropped {name}: {why}" for name, why in self.dropped]
        return "\n".join(lines)


def unit_columns(S: np.ndarray, rtol: float, norms: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``S`` with each column divided by its norm (``norms``: those to divide by, default
    ``S``'s own), and which columns are live: a norm above ``rtol`` times the largest. A dead
    column (no effect, or round-off under any load) stays as it is, near zero."""
    norms = np.linalg.norm(S, axis=0) if norms is None else norms
    live = norms > rtol * norms.max()
    return S / np.where(live, norms, 1.0), live


def stacked_jacobian(model: CalibrationModel, rng: np.random.Generator, samples: int = SAMPLES) -> np.ndarray:
    """``S``: B stacked over random configurations within the joint limits (random loads)."""
    robot = model.kinematics.robot
    return np.vstack([
        model.B_numeric(rng.uniform(robot.q_min, robot.q_max), rng.normal(size=model.nF))
        for _ in range(samples)
    ])


def pivoted_columns(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The column order and ``|R_ii|`` of ``S P = Q R`` with column pivoting (Businger-Golub):
    at each step the column of largest norm orthogonal to those taken, by Gram-Schmidt with
    a second pass. Columns whose norms agree to ``TIE_RTOL`` are a tie, taken in their order
    in S: unit-norm columns tie at the first steps (a translation of the base, of joint 1 and
    of the tool move the point alike), and LAPACK's pivoted QR breaks such ties by rounding,
    so the base set would depend on the BLAS a machine has. Returns the order (k,) and the
    norms (k,), k = number of columns."""
    Rm = np.array(S, dtype=float)
    left = list(range(Rm.shape[1]))
    order, diag = [], []
    while left:
        norms = np.linalg.norm(Rm[:, left], axis=0)
        j = left[int(np.flatnonzero(norms >= (1.0 - TIE_RTOL) * norms.max())[0])]
        order.append(j)
        diag.append(float(np.linalg.norm(Rm[:, j])))
        left.remove(j)
        if diag[-1] > 0.0 and left:
            u = Rm[:, j] / diag[-1]
            for _ in range(2):
                Rm[:, left] -= np.outer(u, u @ Rm[:, left])
    return np.array(order, dtype=int), np.array(diag)


def base_set(model: CalibrationModel, seed: int = 0, samples: int = SAMPLES) -> BaseSet:
    """Select an identifiable base set among ``model.parameter_names`` (see module docstring)."""
    S = stacked_jacobian(model, np.random.default_rng(seed), samples)
    norms = np.linalg.norm(S, axis=0)
    Sn, live = unit_columns(S, RANK_RTOL, norms)
    piv, diag = pivoted_columns(Sn[:, live])
    cols = np.flatnonzero(live)[piv]
    rank = int(np.sum(diag > RANK_RTOL * diag[0]))
    kept_idx = sorted(cols[:rank])
    names = model.parameter_names
    dropped = [(names[i], "no effect on the measured values") for i in np.flatnonzero(~live)]
    K = Sn[:, kept_idx]
    for i in sorted(cols[rank:]):
        coef, *_ = np.linalg.lstsq(K, Sn[:, i], rcond=None)
        coef = coef * norms[i] / norms[kept_idx]
        partners = [f"{c:+.4g} {names[kept_idx[k]]}" for k, c in enumerate(coef) if abs(c) > PARTNER_TOL]
        dropped.append((names[i], "acts as " + " ".join(partners)))
    order = {n: k for k, n in enumerate(names)}
    return BaseSet(tuple(names[i] for i in kept_idx), tuple(sorted(dropped, key=lambda d: order[d[0]])),
                   rank, RANK_RTOL)
